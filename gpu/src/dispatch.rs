//! Dispatches of the kernels: points, grids and tiles in 2D, points and boxes in 3D, cut into
//! chunks, recorded, submitted and pipelined.

use fractile_codec::decode::PointValue;
use fractile_codec::extract::{Answer, Sites};
use wgpu::util::DeviceExt;

use crate::*;

/// One dispatch: the kernel, the operator, `count` points (`points`: their list or a grid's
/// axes), the uniform bytes given the points a row of the dispatch grid, and what it reads back.
#[derive(Clone, Copy)]
pub(crate) struct Dispatch<'a> {
    pub(crate) pipeline: &'a wgpu::ComputePipeline,
    pub(crate) op: &'a GpuOperator,
    pub(crate) count: usize,
    pub(crate) uniform: &'a dyn Fn(u32) -> Vec<u8>,
    pub(crate) points: &'a [u8],
    pub(crate) read: Read,
}

/// The uniforms of a grid's dispatch of `count` points from point `first`, `width` a row.
pub(crate) fn grid_params(
    op: &GpuOperator,
    (count, first, width): (usize, usize, u32),
    iterations: u32,
    tolerance: f32,
    values_only: bool,
) -> Params {
    Params {
        count: count as u32,
        first: first as u32,
        iterations,
        mode: 2,
        tolerance,
        width,
        values_only: u32::from(values_only),
        ..op.params
    }
}

/// Appends `src` to `dst` (whose capacity already holds it) on every core, each thread copying
/// a block into its place. Hand-written because a parallel copy into a vector's spare capacity
/// is what rayon's collect does only for its own iterators, and `extend_from_slice` is one
/// thread.
pub(crate) fn append_parallel(dst: &mut Vec<f32>, src: &[f32]) {
    use rayon::prelude::*;
    pub(crate) const BLOCK: usize = 1 << 16;
    if src.len() <= BLOCK {
        // A tile's values: one block, copied here rather than handed to a busy pool.
        dst.extend_from_slice(src);
        return;
    }
    dst.reserve(src.len());
    let start = dst.len();
    let spare = &mut dst.spare_capacity_mut()[..src.len()];
    spare
        .par_chunks_mut(BLOCK)
        .zip(src.par_chunks(BLOCK))
        .for_each(|(to, from)| {
            for (t, f) in to.iter_mut().zip(from) {
                t.write(*f);
            }
        });
    // SAFETY: the `src.len()` elements after `start` were all written just above.
    unsafe { dst.set_len(start + src.len()) };
}

impl Gpu {
    /// Seconds the device takes to decode a `width x height` window of the whole unit square
    /// (pixel centres, `iterations` steps), results left on the device: the kernel's time plus
    /// one submission's overhead, without the readback that [`Gpu::grid`] adds. For the bench.
    pub fn kernel_seconds(
        &self,
        op: &GpuOperator,
        width: u32,
        height: u32,
        iterations: u32,
    ) -> Result<f64, GpuError> {
        let total = width as usize * height as usize;
        let start = std::time::Instant::now();
        let mut first = 0usize;
        while first < total {
            let count = (total - first).min(self.chunk);
            let params = Params {
                count: count as u32,
                first: first as u32,
                iterations,
                mode: 1,
                width,
                a: [0.0; 2],
                b: [1.0 / width as f32, 1.0 / height as f32],
                ..op.params
            };
            self.run(Dispatch {
                pipeline: self.kernel2d(op),
                op,
                count,
                uniform: &|row| bytemuck::bytes_of(&Params { row, ..params }).to_vec(),
                points: &[0u8; 16],
                read: Read::Nothing,
            })?;
            first += count;
        }
        Ok(start.elapsed().as_secs_f64())
    }

    /// Continuous decoding of 3D points in unit coordinates (normalised values), like
    /// `decode::points` on the octree operator.
    pub fn volume_points(
        &self,
        op: &GpuOperator,
        points: &[[f32; 3]],
        iterations: u32,
        tolerance: f32,
    ) -> Result<Vec<PointValue>, GpuError> {
        let base = op
            .volume
            .ok_or_else(|| GpuError::Device("not a volume operator".into()))?;
        let mut out = Vec::with_capacity(points.len());
        for chunk in points.chunks(self.chunk) {
            let params = Params3 {
                count: chunk.len() as u32,
                iterations,
                tolerance,
                mode: 0,
                ..base
            };
            out.extend(self.dispatch_with(
                &self.pipeline3,
                op,
                chunk.len(),
                &|row| bytemuck::bytes_of(&Params3 { row, ..params }).to_vec(),
                bytemuck::cast_slice(chunk),
            )?);
        }
        Ok(out)
    }

    /// Continuous decoding of a box `[lo, hi]` of the unit cube at `dims` samples per axis,
    /// corners included (x fastest), like `decode::volume_window`: the device makes the points
    /// from the CPU's axes (`decode::volume_axes`), so both decode the same points. Each
    /// point with its bound and steps (16 bytes a point read back).
    pub fn volume_grid(
        &self,
        op: &GpuOperator,
        lo: [f32; 3],
        hi: [f32; 3],
        dims: [u32; 3],
        iterations: u32,
        tolerance: f32,
    ) -> Result<Vec<PointValue>, GpuError> {
        let mut out = Vec::new();
        self.volume_box(
            op,
            (lo, hi, dims),
            (iterations, tolerance),
            Read::Points,
            &mut |r| {
                if let Readback::Points(v) = r {
                    out.extend(v);
                }
            },
        )?;
        Ok(out)
    }

    /// [`Gpu::volume_grid`]'s values alone, the bounds and steps reduced on the device to their
    /// largest (4 bytes a point read back): what a mesh needs.
    pub fn volume_grid_values(
        &self,
        op: &GpuOperator,
        lo: [f32; 3],
        hi: [f32; 3],
        dims: [u32; 3],
        iterations: u32,
        tolerance: f32,
    ) -> Result<GridValues, GpuError> {
        let mut out = GridValues::default();
        self.volume_box(
            op,
            (lo, hi, dims),
            (iterations, tolerance),
            Read::Values,
            &mut |r| out.absorb(r),
        )?;
        Ok(out)
    }

    /// The chunked dispatches of a box, each read back (as `read` says) into `sink`.
    pub(crate) fn volume_box(
        &self,
        op: &GpuOperator,
        (lo, hi, dims): ([f32; 3], [f32; 3], [u32; 3]),
        (iterations, tolerance): (u32, f32),
        read: Read,
        sink: &mut dyn FnMut(Readback<'_>),
    ) -> Result<(), GpuError> {
        let base = op
            .volume
            .ok_or_else(|| GpuError::Device("not a volume operator".into()))?;
        let axes = fractile_codec::decode::volume_axes(lo, hi, dims.map(|d| d as usize));
        // x, then y, then z: the kernel reads sample (i, j, k) at `axes[i]`, `axes[nx + j]`,
        // `axes[nx + ny + k]`.
        let axes: Vec<f32> = axes.concat();
        let total = dims.iter().map(|&d| d as usize).product::<usize>();
        let mut submit = |count: usize, first: usize| {
            let params = Params3 {
                count: count as u32,
                first: first as u32,
                iterations,
                tolerance,
                mode: 1,
                dims,
                values_only: u32::from(read == Read::Values),
                ..base
            };
            self.submit(Dispatch {
                pipeline: &self.pipeline3,
                op,
                count,
                uniform: &|row| bytemuck::bytes_of(&Params3 { row, ..params }).to_vec(),
                points: bytemuck::cast_slice(&axes),
                read,
            })
        };
        self.pipelined(total, &mut submit, sink)
    }

    /// Continuous decoding of points in unit coordinates (normalised values), like
    /// `decode::points`; points outside the unit square come back NaN with bound 0.
    pub fn points(
        &self,
        op: &GpuOperator,
        points: &[[f32; 2]],
        iterations: u32,
        tolerance: f32,
    ) -> Result<Vec<PointValue>, GpuError> {
        let mut out = Vec::with_capacity(points.len());
        for chunk in points.chunks(self.chunk) {
            let params = Params {
                count: chunk.len() as u32,
                first: 0,
                iterations,
                mode: 0,
                tolerance,
                ..op.params
            };
            out.extend(self.dispatch(op, params, bytemuck::cast_slice(chunk))?);
        }
        Ok(out)
    }

    /// Continuous decoding of a grid of points generated on the device (a window, or a
    /// separable grid such as a tile's reprojected pixels); row-major, normalised values, each
    /// with its own bound and step count (16 bytes a point read back).
    pub fn grid(
        &self,
        op: &GpuOperator,
        grid: Grid,
        iterations: u32,
        tolerance: f32,
    ) -> Result<Vec<PointValue>, GpuError> {
        let mut out = Vec::new();
        self.grid_dispatches(op, &grid, iterations, tolerance, false, &mut |r| {
            if let Readback::Points(v) = r {
                if out.is_empty() {
                    out = v;
                } else {
                    out.extend(v);
                }
            }
        })?;
        Ok(out)
    }

    /// [`Gpu::grid`] reading back the values alone (4 bytes a point), with the bounds and step
    /// counts reduced on the device to their largest: what a tile or a window needs (one
    /// bound for all its pixels), at a quarter of the transfer. A grid of a tile's size joins
    /// the grids other threads are asking for in one submission (see [`Gpu::rounds`]).
    pub fn grid_values(
        &self,
        op: &GpuOperator,
        grid: Grid,
        iterations: u32,
        tolerance: f32,
    ) -> Result<GridValues, GpuError> {
        let (width, height) = grid.size();
        let total = width as usize * height as usize;
        // A tile's grid joins the other requests' in one submission (see `batch`).
        if total > 0 && total <= batch::GRID_POINTS.min(self.chunk) {
            let (width, _, axes) = grid_axes(&grid);
            let params = grid_params(op, (total, 0, width), iterations, tolerance, true);
            return self.grid_values_in_round(op, params, axes);
        }
        let mut out = GridValues::default();
        out.values.reserve_exact(total);
        self.grid_dispatches(op, &grid, iterations, tolerance, true, &mut |r| {
            out.absorb(r)
        })?;
        Ok(out)
    }

    /// The answer to a codec's continuous hook (`fractile_codec::extract::ChainDevice`):
    /// a list of points with a value, bound and step count each, a separable grid (a tile, a
    /// region) with its values alone and their largest bound and step count.
    pub fn answer(
        &self,
        op: &GpuOperator,
        sites: Sites<'_>,
        iterations: u32,
        tolerance: f32,
    ) -> Result<Answer, GpuError> {
        Ok(match sites {
            Sites::List(points) => Answer::Points(self.points(op, points, iterations, tolerance)?),
            Sites::Grid { xs, ys } => {
                let grid = Grid::Separable {
                    xs: xs.to_vec(),
                    ys: ys.to_vec(),
                };
                let g = self.grid_values(op, grid, iterations, tolerance)?;
                Answer::Values {
                    values: g.values,
                    error_bound: g.error_bound,
                    iterations: g.iterations,
                }
            }
        })
    }

    /// The dispatches of a grid, in chunks, each read back into `sink`.
    pub(crate) fn grid_dispatches(
        &self,
        op: &GpuOperator,
        grid: &Grid,
        iterations: u32,
        tolerance: f32,
        values_only: bool,
        sink: &mut dyn FnMut(Readback<'_>),
    ) -> Result<(), GpuError> {
        let (width, height, axes) = grid_axes(grid);
        let total = width as usize * height as usize;
        let read = if values_only {
            Read::Values
        } else {
            Read::Points
        };
        let mut submit = |count: usize, first: usize| {
            let params = grid_params(
                op,
                (count, first, width),
                iterations,
                tolerance,
                values_only,
            );
            self.submit(Dispatch {
                pipeline: self.kernel2d(op),
                op,
                count,
                uniform: &|row| bytemuck::bytes_of(&Params { row, ..params }).to_vec(),
                points: bytemuck::cast_slice(&axes),
                read,
            })
        };
        self.pipelined(total, &mut submit, sink)
    }

    /// `total` points in chunks, each submitted (`submit(count, first)`) before the last one is
    /// read into `sink`: the device computes a chunk while the host copies the last one out.
    pub(crate) fn pipelined(
        &self,
        total: usize,
        submit: &mut dyn FnMut(usize, usize) -> Result<Option<Pending>, GpuError>,
        sink: &mut dyn FnMut(Readback<'_>),
    ) -> Result<(), GpuError> {
        let mut first = 0usize;
        let mut pending = None;
        while first < total {
            let count = (total - first).min(self.chunk);
            let next = submit(count, first)?;
            if let Some(done) = std::mem::replace(&mut pending, next) {
                self.finish(done, sink)?;
            }
            first += count;
        }
        if let Some(done) = pending {
            self.finish(done, sink)?;
        }
        Ok(())
    }

    pub(crate) fn dispatch(
        &self,
        op: &GpuOperator,
        params: Params,
        points: &[u8],
    ) -> Result<Vec<PointValue>, GpuError> {
        self.dispatch_with(
            self.kernel2d(op),
            op,
            params.count as usize,
            &|row| bytemuck::bytes_of(&Params { row, ..params }).to_vec(),
            points,
        )
    }

    /// One dispatch of `count` points through `pipeline`; `uniform(row)` makes the uniform
    /// bytes given the points per row of the dispatch grid.
    pub(crate) fn dispatch_with(
        &self,
        pipeline: &wgpu::ComputePipeline,
        op: &GpuOperator,
        count: usize,
        uniform: &dyn Fn(u32) -> Vec<u8>,
        points: &[u8],
    ) -> Result<Vec<PointValue>, GpuError> {
        self.run(Dispatch {
            pipeline,
            op,
            count,
            uniform,
            points,
            read: Read::Points,
        })
    }

    /// Records, submits and reads back one dispatch as `read` says. [`Read::Nothing`] waits for
    /// the device to finish and reads nothing: what [`Gpu::kernel_seconds`] times.
    pub(crate) fn run(&self, d: Dispatch<'_>) -> Result<Vec<PointValue>, GpuError> {
        let mut out = Vec::new();
        if let Some(pending) = self.submit(d)? {
            self.finish(pending, &mut |r| {
                if let Readback::Points(v) = r {
                    out = v;
                }
            })?;
        }
        Ok(out)
    }

    /// Records and submits one dispatch with the copy of its results into a mapped buffer;
    /// [`Gpu::finish`] waits for it and reads it. `None`: nothing to read (no points, or
    /// [`Read::Nothing`], which has waited for the device).
    pub(crate) fn submit(&self, d: Dispatch<'_>) -> Result<Option<Pending>, GpuError> {
        let read = d.read;
        if d.count == 0 {
            return Ok(None);
        }
        let dev = &self.device;
        let mut encoder = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("decode2d"),
        });
        let out = self.record(&mut encoder, d);
        if read == Read::Nothing {
            self.queue.submit([encoder.finish()]);
            dev.poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            return Ok(None);
        }
        let values_only = read == Read::Values;
        let size = out.readback_bytes();
        let readback = self.readback(size);
        out.copy_to(&mut encoder, &readback, 0);
        self.queue.submit([encoder.finish()]);
        Ok(Some(Pending {
            mapped: map_read(&readback),
            readback,
            values_bytes: values_only.then_some(out.values_bytes),
        }))
    }

    /// Records one dispatch of `count` points into `encoder`: its buffers, bind group and
    /// workgroups (what [`Gpu::submit`] submits alone and `batch` many to a submission).
    pub(crate) fn record(&self, encoder: &mut wgpu::CommandEncoder, d: Dispatch<'_>) -> Recorded {
        let Dispatch {
            pipeline,
            op,
            count,
            uniform,
            points,
            read,
        } = d;
        let groups = (count as u32).div_ceil(WORKGROUP);
        let gx = groups.min(65_535);
        let gy = groups.div_ceil(gx);
        let dev = &self.device;
        let uniform = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("params"),
            contents: &uniform(gx * WORKGROUP),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let input = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("points"),
            contents: points,
            usage: wgpu::BufferUsages::STORAGE,
        });
        // The outputs a dispatch does not write are bound as a few bytes (every binding of the
        // layout must be).
        let output = |label, bytes: u64| {
            dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes.max(16),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        };
        let (results_bytes, values_bytes) = if read == Read::Values {
            (0, count as u64 * 4)
        } else {
            (count as u64 * 16, 0)
        };
        let results = output("results", results_bytes);
        let values = output("values", values_bytes);
        // Zeroed: the kernel takes maxima into it.
        let summary = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("summary"),
            contents: &[0u8; 16],
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        });
        let bind = dev.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("decode2d"),
            layout: &self.layout,
            entries: &[
                (0, &uniform),
                (1, &op.lut),
                (2, &op.pieces),
                (3, &input),
                (4, &results),
                (5, &values),
                (6, &summary),
            ]
            .map(|(binding, b)| wgpu::BindGroupEntry {
                binding,
                resource: b.as_entire_binding(),
            }),
        });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("decode2d"),
                timestamp_writes: None,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        Recorded {
            results,
            values,
            summary,
            results_bytes,
            values_bytes,
        }
    }
}
