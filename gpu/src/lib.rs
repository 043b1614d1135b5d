//! GPU decoding of fractile's operators with wgpu compute, on any adapter (a discrete GPU,
//! an integrated one, or Mesa's lavapipe on machines without one).
//!
//! A 2D operator is flattened once ([`fractile_codec::core::pieces`]) and uploaded as two storage
//! buffers ([`GpuOperator`], resident until dropped); each request then dispatches the kernel of
//! `shaders/decode2d.wgsl` over a list of points, a window's grid, or a Web Mercator tile's
//! pixels (reprojected on the GPU). A 3D octree operator (IFS3D) is uploaded the same way, its
//! cell-index map and one affine cell per range, for `shaders/decode3d.wgsl` over a list of 3D
//! points or a box grid (what a mesh region samples). The kernel mirrors the CPU's continuous decoder, in
//! f32, so answers agree with it to rounding (Mesa and GPUs reorder float additions: compare
//! with a tolerance, never for equality).
//!
//! Work is cut into dispatches of at most [`CHUNK`] points: a storage binding may hold 128 MiB
//! and a dispatch dimension 65,535 workgroups (a 2D grid of groups covers more).

use bytemuck::{Pod, Zeroable};
use fractile_codec::codecs::ifs3d::octree::OctreeOperator;
use fractile_codec::core::decode::PointValue;
use fractile_codec::core::operator::Operator;
use fractile_codec::core::pieces::{Ends, Flat, Lattice, Offsets, PieceTable};
use fractile_codec::extract::{Answer, Sites};
use wgpu::util::DeviceExt;

mod batch;

/// The 2D kernel's source, with the entry point both kernels share (`shaders/entry.wgsl`:
/// the outputs, the values-only reduction).
pub const SHADER: &str = concat!(
    include_str!("../../shaders/decode2d.wgsl"),
    include_str!("../../shaders/entry.wgsl")
);

/// The 3D kernel's source, with the shared entry point.
pub const SHADER_3D: &str = concat!(
    include_str!("../../shaders/decode3d.wgsl"),
    include_str!("../../shaders/entry.wgsl")
);

/// Most points in one dispatch (16 bytes of result each: 64 MiB).
pub const CHUNK: usize = 1 << 22;

const WORKGROUP: u32 = 256;

/// Why the GPU could not answer.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter (the message names each backend's reason); callers fall back to the CPU.
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    /// The adapter refused a device.
    #[error("GPU device: {0}")]
    Device(String),
    /// Reading results back failed (device lost, out of memory).
    #[error("GPU readback: {0}")]
    Readback(String),
    /// A table is over what one binding may hold.
    #[error("GPU: {0}")]
    TooLarge(String),
    /// Tables whose parts do not fit together (a bug in the codec that flattened them).
    #[error("GPU tables: {0}")]
    Tables(String),
}

/// Uniforms of one dispatch; the layout of `Params` in the kernel (144 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct Params {
    count: u32,
    first: u32,
    iterations: u32,
    mode: u32,
    tolerance: f32,
    seed: f32,
    half: f32,
    width: u32,
    lut_origin: [f32; 2],
    lut_cell: [f32; 2],
    lut_size: [u32; 2],
    valid: [f32; 2],
    a: [f32; 2],
    b: [f32; 2],
    row: u32,
    /// The fixed-point step of chain positions and its inverse (powers of two; see
    /// `fractile_codec::core::decode::position_quantum`).
    quantum: f32,
    inv_quantum: f32,
    /// 1: values and a reduced bound ([`Gpu::grid_values`]) instead of four floats a point.
    values_only: u32,
    /// `1 / lut_cell`: the kernel multiplies (exact for the power-of-two cells of the lattice
    /// codecs), where a WGSL division may be off by 2.5 ulp and floor onto the cell before.
    inv_lut_cell: [f32; 2],
    pad: [u32; 2],
    /// A lattice's one contrast.
    contrast: [f32; 4],
    /// Samples along x and y of a lattice whose chains end on them ([`Ends`]), else 0.
    ends_size: [u32; 2],
    /// Their chains' f32 rounding a step.
    ulps: f32,
    pad_ends: u32,
}

/// Uniforms of a 3D dispatch; the layout of `Params` in `decode3d.wgsl` (80 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
struct Params3 {
    count: u32,
    first: u32,
    iterations: u32,
    mode: u32,
    tolerance: f32,
    seed: f32,
    half: f32,
    side: u32,
    inv_cell: f32,
    valid: f32,
    dims: [u32; 3],
    row: u32,
    /// The fixed-point step of positions and its inverse, as in 2D.
    quantum: f32,
    inv_quantum: f32,
    /// 1: values and a reduced bound ([`Gpu::volume_grid_values`]).
    values_only: u32,
    pad: [u32; 3],
}

/// What a 2D operator's uniforms take from its tables, whichever form they have.
struct Shape {
    frame: [f32; 2],
    valid: [f32; 2],
    lut_origin: [f32; 2],
    lut_cell: [f32; 2],
    lut_size: [u32; 2],
    interval: (f32, f32),
}

impl Shape {
    /// The operator on the device: its two tables, their bytes, and the lattice they are, if
    /// they are one (its contrast, the form of its offsets and its ends).
    fn operator(
        self,
        (lut, pieces): (wgpu::Buffer, wgpu::Buffer),
        bytes: usize,
        lattice: Option<&Lattice>,
    ) -> GpuOperator {
        let ends: Option<&Ends> = lattice.and_then(|l| l.ends.as_ref());
        let quantum = fractile_codec::core::decode::position_quantum(&self.frame);
        let (lo, hi) = self.interval;
        GpuOperator {
            lut,
            pieces,
            params: Params {
                seed: (lo + hi) * 0.5,
                half: (hi - lo) * 0.5,
                lut_origin: self.lut_origin,
                lut_cell: self.lut_cell,
                lut_size: self.lut_size,
                valid: self.valid,
                quantum,
                inv_quantum: 1.0 / quantum,
                inv_lut_cell: self.lut_cell.map(|c| 1.0 / c),
                contrast: lattice.map(|l| l.contrast).unwrap_or_default(),
                ends_size: ends.map_or([0; 2], |e| e.size),
                ulps: ends.map_or(0.0, |e| e.ulps),
                ..Params::default()
            },
            kernel: Kernel2d::of(
                lattice.is_some(),
                lattice.is_some_and(|l| matches!(l.offsets, Offsets::Blocks(_))),
                ends.is_some(),
            ),
            volume: None,
            bytes,
        }
    }
}

/// Where a dispatch's points come from.
#[derive(Clone, Debug, PartialEq)]
pub enum Grid {
    /// A `width x height` grid over the unit-square window `[u0, v0, u1, v1]` (pixel centres).
    Window {
        /// `[u0, v0, u1, v1]`.
        rect: [f32; 4],
        /// Points a row.
        width: u32,
        /// Rows.
        height: u32,
    },
    /// A separable grid: point (i, j) is `(xs[i], ys[j])` in unit coordinates. The pixels of a
    /// Web Mercator tile over an asset placed in lon/lat are one.
    Separable {
        /// Unit x of each column.
        xs: Vec<f32>,
        /// Unit y of each row.
        ys: Vec<f32>,
    },
}

impl Grid {
    /// Points a row and rows.
    pub fn size(&self) -> (u32, u32) {
        match self {
            Grid::Window { width, height, .. } => (*width, *height),
            Grid::Separable { xs, ys } => (xs.len() as u32, ys.len() as u32),
        }
    }
}

/// What a dispatch reads back.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Read {
    /// Nothing: wait for the device (kernel timing).
    Nothing,
    /// Value, bound and step count of every point.
    Points,
    /// Values, and the largest bound and step count.
    Values,
}

/// What a dispatch read back (see [`Read`]).
enum Readback<'a> {
    Points(Vec<PointValue>),
    /// The values as mapped (read in place: copied once, into the caller's output), the
    /// largest bound and the most steps.
    Values(&'a [f32], f32, u32),
}

/// A dispatch submitted, its results on their way into a mapped buffer.
struct Pending {
    readback: wgpu::Buffer,
    mapped: Mapped,
    /// The bytes of values before the summary, for a values-only dispatch.
    values_bytes: Option<u64>,
}

/// One dispatch: the kernel, the operator, `count` points (`points`: their list or a grid's
/// axes), the uniform bytes given the points a row of the dispatch grid, and what it reads back.
#[derive(Clone, Copy)]
struct Dispatch<'a> {
    pipeline: &'a wgpu::ComputePipeline,
    op: &'a GpuOperator,
    count: usize,
    uniform: &'a dyn Fn(u32) -> Vec<u8>,
    points: &'a [u8],
    read: Read,
}

/// Where a buffer's mapping callback reports.
type Mapped = std::sync::mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>;

/// Maps `buffer` for reading once the work submitted before is done.
fn map_read(buffer: &wgpu::Buffer) -> Mapped {
    let (tx, mapped) = std::sync::mpsc::channel();
    buffer.slice(..).map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    mapped
}

/// The output buffers of a recorded dispatch.
struct Recorded {
    results: wgpu::Buffer,
    values: wgpu::Buffer,
    summary: wgpu::Buffer,
    results_bytes: u64,
    values_bytes: u64,
}

impl Recorded {
    /// Bytes it reads back: four floats a point, or the values then the summary's two words.
    fn readback_bytes(&self) -> u64 {
        if self.values_bytes > 0 {
            self.values_bytes + 8
        } else {
            self.results_bytes
        }
    }

    /// Records the copy of what it reads back into `readback` at `offset`.
    fn copy_to(&self, encoder: &mut wgpu::CommandEncoder, readback: &wgpu::Buffer, offset: u64) {
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
    fn absorb(&mut self, r: Readback<'_>) {
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

/// The specialisations of the 2D kernel (its pipeline constants), one a form of tables.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Kernel2d {
    /// The tables are a [`Lattice`]'s (`LATTICE`).
    lattice: bool,
    /// Its offsets are in blocks of cells sharing corners ([`Offsets::Blocks`], `BLOCKS`).
    blocks: bool,
    /// Its chains end on its samples ([`Ends`], `ENDS`).
    ends: bool,
}

impl Kernel2d {
    /// Every form a table can take (`blocks` and `ends` only with `lattice`).
    const ALL: [Kernel2d; 5] = [
        Kernel2d::of(false, false, false),
        Kernel2d::of(true, false, false),
        Kernel2d::of(true, false, true),
        Kernel2d::of(true, true, false),
        Kernel2d::of(true, true, true),
    ];

    const fn of(lattice: bool, blocks: bool, ends: bool) -> Kernel2d {
        Kernel2d {
            lattice,
            blocks,
            ends,
        }
    }

    /// Its place in [`Kernel2d::ALL`].
    fn index(self) -> usize {
        match (self.lattice, self.blocks, self.ends) {
            (false, ..) => 0,
            (true, false, false) => 1,
            (true, false, true) => 2,
            (true, true, false) => 3,
            (true, true, true) => 4,
        }
    }
}

/// An operator resident on the device (2D pieces, or a 3D octree when `volume` is set). A
/// clone names the same device buffers.
#[derive(Clone)]
pub struct GpuOperator {
    lut: wgpu::Buffer,
    pieces: wgpu::Buffer,
    params: Params,
    /// Which specialisation of the 2D kernel decodes it.
    kernel: Kernel2d,
    volume: Option<Params3>,
    bytes: usize,
}

impl GpuOperator {
    /// Device memory it holds.
    pub fn bytes(&self) -> usize {
        self.bytes
    }
}

/// A device with the decoding pipeline.
pub struct Gpu {
    device: wgpu::Device,
    queue: wgpu::Queue,
    /// The 2D kernel's specialisations, by [`Kernel2d::index`].
    pipelines2d: Vec<wgpu::ComputePipeline>,
    pipeline3: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    info: wgpu::AdapterInfo,
    max_binding: u64,
    chunk: usize,
    batcher: batch::Batcher,
}

impl Gpu {
    /// The first high-performance adapter of any backend. `Err(NoAdapter)` when there is none,
    /// for the caller to fall back to the CPU.
    pub fn new() -> Result<Gpu, GpuError> {
        pollster::block_on(Self::open())
    }

    /// Whether this machine may have a hardware adapter: on Linux, a DRM render node
    /// (`/dev/dri/renderD*`), an NVIDIA device (`/dev/nvidia0`) or WSL's (`/dev/dxg`); elsewhere
    /// always. Without any, only a software adapter could open, which `auto` never decodes on,
    /// so callers on `auto` skip the probe: it loads the Vulkan loader and its layers, which
    /// print to stderr (Mesa's device-select layer: "XDG_RUNTIME_DIR is invalid") in the
    /// middle of our own output, on machines that have no GPU to find.
    pub fn hardware_may_exist() -> bool {
        if !cfg!(target_os = "linux") {
            return true;
        }
        let render_node = std::fs::read_dir("/dev/dri").is_ok_and(|d| {
            d.flatten()
                .any(|e| e.file_name().to_string_lossy().starts_with("renderD"))
        });
        render_node
            || ["/dev/nvidia0", "/dev/dxg"]
                .iter()
                .any(|p| std::path::Path::new(p).exists())
    }

    /// Whether the adapter [`Gpu::new`] would open is a software rasteriser, found without
    /// opening a device (which is what takes memory: Mesa's lavapipe holds 82 MB once open).
    pub fn adapter_is_software() -> Result<bool, GpuError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        Ok(adapter.get_info().device_type == wgpu::DeviceType::Cpu)
    }

    async fn open() -> Result<Gpu, GpuError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle());
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("fractile"),
                required_features: wgpu::Features::empty(),
                // The adapter's own limits: storage bindings as large as it allows.
                required_limits: limits.clone(),
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::Device(e.to_string()))?;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("decode2d"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let module3 = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("decode3d"),
            source: wgpu::ShaderSource::Wgsl(SHADER_3D.into()),
        });
        let entry = |binding: u32, ty: wgpu::BufferBindingType| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let read = wgpu::BufferBindingType::Storage { read_only: true };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("decode2d"),
            entries: &[
                entry(0, wgpu::BufferBindingType::Uniform),
                entry(1, read),
                entry(2, read),
                entry(3, read),
                entry(4, wgpu::BufferBindingType::Storage { read_only: false }),
                entry(5, wgpu::BufferBindingType::Storage { read_only: false }),
                entry(6, wgpu::BufferBindingType::Storage { read_only: false }),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("decode2d"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        // A pipeline of the 2D kernel for each form of tables: a branch on a uniform in the
        // loop cost 40% of the kernel's time on lavapipe (a 256 x 256 grid, 7.2 -> 10.0-11.4
        // ms), where pipeline constants leave each its own code.
        let pipelines2d = Kernel2d::ALL
            .iter()
            .map(|k| {
                device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some("decode2d"),
                    layout: Some(&pipeline_layout),
                    module: &module,
                    entry_point: Some("main"),
                    compilation_options: wgpu::PipelineCompilationOptions {
                        constants: &[
                            ("LATTICE", f64::from(u8::from(k.lattice))),
                            ("BLOCKS", f64::from(u8::from(k.blocks))),
                            ("ENDS", f64::from(u8::from(k.ends))),
                        ],
                        ..Default::default()
                    },
                    cache: None,
                })
            })
            .collect();
        // The 3D kernel binds the same buffers: one layout for both.
        let pipeline3 = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("decode3d"),
            layout: Some(&pipeline_layout),
            module: &module3,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let max_binding = limits.max_storage_buffer_binding_size;
        Ok(Gpu {
            device,
            queue,
            pipelines2d,
            pipeline3,
            layout,
            info,
            max_binding,
            chunk: CHUNK,
            batcher: Default::default(),
        })
    }

    /// The 2D kernel for `op`'s tables.
    fn kernel2d(&self, op: &GpuOperator) -> &wgpu::ComputePipeline {
        &self.pipelines2d[op.kernel.index()]
    }

    /// The adapter, as "name (backend, device type)".
    pub fn adapter(&self) -> String {
        format!(
            "{} ({:?}, {:?})",
            self.info.name, self.info.backend, self.info.device_type
        )
    }

    /// Whether the adapter is a software rasteriser (lavapipe, llvmpipe, WARP).
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Rounds of small grids submitted together, and the grids they held, since the device
    /// was opened ([`Gpu::grid_values`]; a round of one is a grid alone).
    pub fn rounds(&self) -> (u64, u64) {
        self.batcher.stats()
    }

    /// Points per dispatch (default [`CHUNK`]); smaller values exercise chunking in tests.
    pub fn set_chunk(&mut self, points: usize) {
        self.chunk = points.clamp(1, CHUNK);
    }

    /// The two storage buffers of an operator: its lookup map and its cells.
    fn tables(&self, lut: &[u8], cells: &[u8]) -> Result<(wgpu::Buffer, wgpu::Buffer), GpuError> {
        if lut.len() as u64 > self.max_binding || cells.len() as u64 > self.max_binding {
            return Err(GpuError::TooLarge(format!(
                "operator tables of {} bytes exceed a binding of {} bytes",
                lut.len() + cells.len(),
                self.max_binding
            )));
        }
        let init = |label, contents: &[u8]| {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::STORAGE,
                })
        };
        Ok((init("lut", lut), init("cells", cells)))
    }

    /// Uploads a flattened operator (as a lattice when its table is one). A table does not say
    /// where its chains end: an operator whose chains end on its samples (the projected codec)
    /// goes up with [`Gpu::upload_flat`] to be decoded as on the CPU; from its table its chains
    /// end on the constant seed, within a wider bound.
    pub fn upload(&self, table: &PieceTable) -> Result<GpuOperator, GpuError> {
        match table.lattice() {
            Some(l) => self.upload_lattice(&l),
            None => self.upload_pieces(table),
        }
    }

    /// Uploads an operator as [`fractile_codec::core::pieces::Flatten::flat`] gives it.
    pub fn upload_flat(&self, flat: &Flat) -> Result<GpuOperator, GpuError> {
        match flat {
            Flat::Lattice(l) => self.upload_lattice(l),
            Flat::Pieces(t) => self.upload_pieces(t),
        }
    }

    fn upload_pieces(&self, t: &PieceTable) -> Result<GpuOperator, GpuError> {
        let pieces: Vec<f32> = t.pieces.iter().flat_map(|p| p.to_array()).collect();
        let tables = self.tables(bytemuck::cast_slice(&t.lut), bytemuck::cast_slice(&pieces))?;
        let shape = Shape {
            frame: t.frame,
            valid: t.valid,
            lut_origin: t.lut_origin,
            lut_cell: t.lut_cell,
            lut_size: t.lut_size,
            interval: t.interval,
        };
        Ok(shape.operator(tables, t.device_bytes(), None))
    }

    /// A lattice goes as its offsets, with the maps of its columns then rows where the lookup
    /// table would be (a fifth of the bytes).
    fn upload_lattice(&self, l: &Lattice) -> Result<GpuOperator, GpuError> {
        let maps = [l.columns.as_slice(), l.rows.as_slice()].concat();
        // The ends, if any, follow the maps in the same buffer: the samples, then the cells'
        // residual bounds (a binding of their own would be one more for every kernel).
        let mut lut: Vec<u8> = bytemuck::cast_slice(&maps).to_vec();
        if let Some(e) = &l.ends {
            lut.extend_from_slice(bytemuck::cast_slice(&e.samples));
            lut.extend_from_slice(bytemuck::cast_slice(&e.residual));
        }
        let offsets: Vec<u8> = match &l.offsets {
            Offsets::Cells(c) => bytemuck::cast_slice(c).to_vec(),
            Offsets::Blocks(b) => {
                let [lx, ly] = l.lut_size.map(|n| n as usize);
                if lx % 2 != 0 || ly % 2 != 0 || 4 * b.len() != lx * ly {
                    return Err(GpuError::Tables(format!(
                        "a lattice of {lx} x {ly} cells cannot hold its offsets in {} blocks of 2 x 2",
                        b.len()
                    )));
                }
                // Whole vec4s: the kernel reads the blocks' values from an array of vec4.
                let mut v = bytemuck::cast_slice(b).to_vec();
                v.resize(l.offsets.device_bytes(), 0);
                v
            }
        };
        let tables = self.tables(&lut, &offsets)?;
        let shape = Shape {
            frame: l.frame,
            valid: l.valid,
            lut_origin: l.lut_origin,
            lut_cell: l.lut_cell,
            lut_size: l.lut_size,
            interval: l.interval,
        };
        Ok(shape.operator(tables, l.device_bytes(), Some(l)))
    }

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

    /// Uploads a 3D octree operator (IFS3D).
    pub fn upload_volume(&self, op: &OctreeOperator) -> Result<GpuOperator, GpuError> {
        let (lut, cell) = op.lookup();
        let mut cells: Vec<f32> = Vec::with_capacity(op.cells().len() * 12);
        for c in op.cells() {
            cells.extend_from_slice(&[c.c[0], c.c[1], c.c[2], c.contrast]);
            cells.extend_from_slice(&[c.coef[0], c.coef[1], c.coef[2], c.offset]);
            cells.extend(c.perm.map(|p| f32::from_bits(p as u32)));
            cells.push(0.0);
        }
        let bytes = lut.len() * 4 + cells.len() * 4;
        let (lut, cells) = self.tables(bytemuck::cast_slice(lut), bytemuck::cast_slice(&cells))?;
        let (lo, hi) = op.invariant_interval();
        let frame = op.frame()[0];
        Ok(GpuOperator {
            lut,
            pieces: cells,
            params: Params::default(),
            kernel: Kernel2d::default(),
            volume: Some(Params3 {
                seed: (lo + hi) * 0.5,
                half: (hi - lo) * 0.5,
                side: (frame / cell as f32) as u32,
                inv_cell: 1.0 / cell as f32,
                valid: op.valid()[0],
                quantum: fractile_codec::core::decode::position_quantum(&op.frame()),
                inv_quantum: 1.0 / fractile_codec::core::decode::position_quantum(&op.frame()),
                ..Params3::default()
            }),
            bytes,
        })
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
    fn volume_box(
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
        let axes = fractile_codec::core::decode::volume_axes(lo, hi, dims.map(|d| d as usize));
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

    /// The answer to a codec's continuous hook (`fractile_codec::extract::ContinuousHook`):
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
    fn grid_dispatches(
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
    fn pipelined(
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

    fn dispatch(
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
    fn dispatch_with(
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
    fn run(&self, d: Dispatch<'_>) -> Result<Vec<PointValue>, GpuError> {
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
    fn submit(&self, d: Dispatch<'_>) -> Result<Option<Pending>, GpuError> {
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

    /// A buffer of `size` bytes the host maps to read.
    fn readback(&self, size: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// Records one dispatch of `count` points into `encoder`: its buffers, bind group and
    /// workgroups (what [`Gpu::submit`] submits alone and `batch` many to a submission).
    fn record(&self, encoder: &mut wgpu::CommandEncoder, d: Dispatch<'_>) -> Recorded {
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

    /// Waits until `mapped` says its buffer is mapped, by polling without blocking: a blocking
    /// poll holds the device's resource lock for the whole wait, and the submissions and buffer
    /// drops of other requests queue behind it (measured on an H100: a tile sampled in 0.65 ms
    /// alone took 1.85 ms with 16 in flight).
    fn wait_mapped(&self, mapped: &Mapped) -> Result<(), GpuError> {
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
    fn finish(&self, pending: Pending, sink: &mut dyn FnMut(Readback<'_>)) -> Result<(), GpuError> {
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

/// The uniforms of a grid's dispatch of `count` points from point `first`, `width` a row.
fn grid_params(
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

/// A grid's width, height and axes (unit x of each column, then unit y of each row).
fn grid_axes(grid: &Grid) -> (u32, u32, Vec<f32>) {
    match grid {
        // A window is the separable grid of its pixel centres, made as the CPU makes them
        // (in f64, rounded once): both must start every chain at the same f32 point.
        Grid::Window {
            rect,
            width,
            height,
        } => {
            let (xs, ys) =
                fractile_codec::core::decode::window_axes(*rect, *width as usize, *height as usize);
            (
                *width,
                *height,
                xs.into_iter().chain(ys).collect::<Vec<f32>>(),
            )
        }
        Grid::Separable { xs, ys } => (
            xs.len() as u32,
            ys.len() as u32,
            xs.iter().chain(ys).copied().collect::<Vec<f32>>(),
        ),
    }
}

/// Appends `src` to `dst` (whose capacity already holds it) on every core, each thread copying
/// a block into its place. Hand-written because a parallel copy into a vector's spare capacity
/// is what rayon's collect does only for its own iterators, and `extend_from_slice` is one
/// thread.
fn append_parallel(dst: &mut Vec<f32>, src: &[f32]) {
    use rayon::prelude::*;
    const BLOCK: usize = 1 << 16;
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
