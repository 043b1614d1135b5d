//! What a dispatch reads back: buffers mapped for reading, points or a grid's values with
//! their bound, and the wait for them.

use fractile_codec::decode::PointValue;

use crate::*;

/// What a dispatch reads back.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Read {
    /// Nothing: wait for the device (kernel timing).
    Nothing,
    /// Value, bound and step count of every point.
    Points,
    /// Values, and the largest bound and step count.
    Values,
}

/// What a dispatch read back (see [`Read`]).
pub(crate) enum Readback<'a> {
    Points(Vec<PointValue>),
    /// The values as mapped (read in place: copied once, into the caller's output), the
    /// largest bound and the most steps.
    Values(&'a [f32], f32, u32),
}

/// A dispatch submitted, its results on their way into a mapped buffer.
pub(crate) struct Pending {
    pub(crate) readback: wgpu::Buffer,
    pub(crate) mapped: Mapped,
    /// The bytes of values before the summary, for a values-only dispatch.
    pub(crate) values_bytes: Option<u64>,
}

/// Where a buffer's mapping callback reports.
pub(crate) type Mapped = std::sync::mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>;

/// Maps `buffer` for reading once the work submitted before is done.
pub(crate) fn map_read(buffer: &wgpu::Buffer) -> Mapped {
    let (tx, mapped) = std::sync::mpsc::channel();
    buffer.slice(..).map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    mapped
}

/// The output buffers of a recorded dispatch.
pub(crate) struct Recorded {
    pub(crate) results: wgpu::Buffer,
    pub(crate) values: wgpu::Buffer,
    pub(crate) summary: wgpu::Buffer,
    pub(crate) results_bytes: u64,
    pub(crate) values_bytes: u64,
}

impl Recorded {
    /// Bytes it reads back: four floats a point, or the values then the summary's two words.
    pub(crate) fn readback_bytes(&self) -> u64 {
        if self.values_bytes > 0 {
            self.values_bytes + 8
        } else {
            self.results_bytes
        }
    }

    /// Records the copy of what it reads back into `readback` at `offset`.
    pub(crate) fn copy_to(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        readback: &wgpu::Buffer,
        offset: u64,
    ) {
        if self.values_bytes > 0 {
            encoder.copy_buffer_to_buffer(&self.values, 0, readback, offset, self.values_bytes);
            encoder.copy_buffer_to_buffer(
                &self.summary,
                0,
                readback,
                offset + self.values_bytes,
                8,
            );
        } else {
            encoder.copy_buffer_to_buffer(&self.results, 0, readback, offset, self.results_bytes);
        }
    }
}

/// A grid's values with one bound for them all ([`Gpu::grid_values`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GridValues {
    /// Normalised values, row-major (NaN outside the unit square).
    pub values: Vec<f32>,
    /// The largest of the points' bounds (normalised; 0 for none).
    pub error_bound: f32,
    /// The most steps a point took.
    pub iterations: u32,
}

impl GridValues {
    /// Adds a values-only chunk: its values after the others, its bound and steps into the
    /// largest. A NaN bound (a chain whose contrast product is NaN) wins, as it would per
    /// point.
    pub(crate) fn absorb(&mut self, r: Readback<'_>) {
        if let Readback::Values(v, bound, taken) = r {
            // One copy of each chunk, from the mapped buffer into its place in the output, on
            // every core: a single-threaded copy into fresh memory (its page faults included)
            // was most of a 4096 x 4096 window's time on an H100 (56 ms against 1 ms of kernel).
            append_parallel(&mut self.values, v);
            self.error_bound = if bound.is_nan() {
                bound
            } else {
                self.error_bound.max(bound)
            };
            self.iterations = self.iterations.max(taken);
        }
    }
}

impl Gpu {
    /// A buffer of `size` bytes the host maps to read.
    pub(crate) fn readback(&self, size: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// Waits until `mapped` says its buffer is mapped, by polling without blocking: a blocking
    /// poll holds the device's resource lock for the whole wait, and the submissions and buffer
    /// drops of other requests queue behind it (measured on an H100: a tile sampled in 0.65 ms
    /// alone took 1.85 ms with 16 in flight).
    pub(crate) fn wait_mapped(&self, mapped: &Mapped) -> Result<(), GpuError> {
        let done = loop {
            self.device
                .poll(wgpu::PollType::Poll)
                .map_err(|e| GpuError::Readback(e.to_string()))?;
            match mapped.try_recv() {
                Ok(r) => break r,
                Err(std::sync::mpsc::TryRecvError::Empty) => {
                    std::thread::sleep(std::time::Duration::from_micros(20))
                }
                Err(e) => return Err(GpuError::Readback(e.to_string())),
            }
        };
        done.map_err(|e| GpuError::Readback(e.to_string()))
    }

    /// Waits for a submitted dispatch (and no later one) and gives its results to `sink`
    /// while they are mapped.
    pub(crate) fn finish(
        &self,
        pending: Pending,
        sink: &mut dyn FnMut(Readback<'_>),
    ) -> Result<(), GpuError> {
        let Pending {
            readback,
            mapped,
            values_bytes,
        } = pending;
        self.wait_mapped(&mapped)?;
        let slice = readback.slice(..);
        let view = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        if let Some(values_bytes) = values_bytes {
            let (v, tail) = view.split_at(values_bytes as usize);
            let word = |k: usize| u32::from_le_bytes(tail[4 * k..4 * k + 4].try_into().expect("4"));
            sink(Readback::Values(
                bytemuck::cast_slice(v),
                f32::from_bits(word(0)),
                word(1),
            ));
        } else {
            let raw: &[[f32; 4]] = bytemuck::cast_slice(&view);
            let point = |r: &[f32; 4]| PointValue {
                value: r[0],
                error_bound: r[1],
                iterations: r[2] as u32,
            };
            // As values (`append_parallel`): large read-backs are converted on every core.
            let points = if raw.len() > 1 << 16 {
                use rayon::prelude::*;
                raw.par_iter().map(point).collect()
            } else {
                raw.iter().map(point).collect()
            };
            sink(Readback::Points(points));
        }
        drop(view);
        readback.unmap();
        Ok(())
    }
}
