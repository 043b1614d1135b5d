//! GPU decoding of fractile's operators with wgpu compute, on any adapter (a discrete GPU,
//! an integrated one, or Mesa's lavapipe on machines without one).
//!
//! A 2D operator is flattened once ([`fractile_codec::pieces`]) and uploaded as two storage
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

mod batch;
mod dispatch;
mod grid;
mod readback;
mod upload;

use dispatch::*;
pub use grid::Grid;
use grid::*;
pub use readback::GridValues;
use readback::*;
pub use upload::GpuOperator;
use upload::*;

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
}
