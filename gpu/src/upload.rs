//! Operators uploaded to the device: their uniforms and tables, in the form of the 2D kernel's
//! specialisation they take, or an IFS3D octree's.

use bytemuck::{Pod, Zeroable};
use fractile_codec::codecs::ifs3d::OctreeOperator;
use fractile_codec::operator::Operator;
use fractile_codec::pieces::{Ends, Flat, Lattice, Offsets, PieceTable};
use wgpu::util::DeviceExt;

use crate::*;

/// Uniforms of one dispatch; the layout of `Params` in the kernel (144 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub(crate) struct Params {
    pub(crate) count: u32,
    pub(crate) first: u32,
    pub(crate) iterations: u32,
    pub(crate) mode: u32,
    pub(crate) tolerance: f32,
    pub(crate) seed: f32,
    pub(crate) half: f32,
    pub(crate) width: u32,
    pub(crate) lut_origin: [f32; 2],
    pub(crate) lut_cell: [f32; 2],
    pub(crate) lut_size: [u32; 2],
    pub(crate) valid: [f32; 2],
    pub(crate) a: [f32; 2],
    pub(crate) b: [f32; 2],
    pub(crate) row: u32,
    /// The fixed-point step of chain positions and its inverse (powers of two; see
    /// `fractile_codec::decode::position_quantum`).
    pub(crate) quantum: f32,
    pub(crate) inv_quantum: f32,
    /// 1: values and a reduced bound ([`Gpu::grid_values`]) instead of four floats a point.
    pub(crate) values_only: u32,
    /// `1 / lut_cell`: the kernel multiplies (exact for the power-of-two cells of the lattice
    /// codecs), where a WGSL division may be off by 2.5 ulp and floor onto the cell before.
    pub(crate) inv_lut_cell: [f32; 2],
    pub(crate) pad: [u32; 2],
    /// A lattice's one contrast.
    pub(crate) contrast: [f32; 4],
    /// Samples along x and y of a lattice whose chains end on them ([`Ends`]), else 0.
    pub(crate) ends_size: [u32; 2],
    /// Their chains' f32 rounding a step.
    pub(crate) ulps: f32,
    pub(crate) pad_ends: u32,
}

/// Uniforms of a 3D dispatch; the layout of `Params` in `decode3d.wgsl` (80 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub(crate) struct Params3 {
    pub(crate) count: u32,
    pub(crate) first: u32,
    pub(crate) iterations: u32,
    pub(crate) mode: u32,
    pub(crate) tolerance: f32,
    pub(crate) seed: f32,
    pub(crate) half: f32,
    pub(crate) side: u32,
    pub(crate) inv_cell: f32,
    pub(crate) valid: f32,
    pub(crate) dims: [u32; 3],
    pub(crate) row: u32,
    /// The fixed-point step of positions and its inverse, as in 2D.
    pub(crate) quantum: f32,
    pub(crate) inv_quantum: f32,
    /// 1: values and a reduced bound ([`Gpu::volume_grid_values`]).
    pub(crate) values_only: u32,
    pub(crate) pad: [u32; 3],
}

/// What a 2D operator's uniforms take from its tables, whichever form they have.
pub(crate) struct Shape {
    pub(crate) frame: [f32; 2],
    pub(crate) valid: [f32; 2],
    pub(crate) lut_origin: [f32; 2],
    pub(crate) lut_cell: [f32; 2],
    pub(crate) lut_size: [u32; 2],
    pub(crate) interval: (f32, f32),
}

impl Shape {
    /// The operator on the device: its two tables, their bytes, and the lattice they are, if
    /// they are one (its contrast, the form of its offsets and its ends).
    pub(crate) fn operator(
        self,
        (lut, pieces): (wgpu::Buffer, wgpu::Buffer),
        bytes: usize,
        lattice: Option<&Lattice>,
    ) -> GpuOperator {
        let ends: Option<&Ends> = lattice.and_then(|l| l.ends.as_ref());
        let quantum = fractile_codec::decode::position_quantum(&self.frame);
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

/// The specialisations of the 2D kernel (its pipeline constants), one a form of tables.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Kernel2d {
    /// The tables are a [`Lattice`]'s (`LATTICE`).
    pub(crate) lattice: bool,
    /// Its offsets are in blocks of cells sharing corners ([`Offsets::Blocks`], `BLOCKS`).
    pub(crate) blocks: bool,
    /// Its chains end on its samples ([`Ends`], `ENDS`).
    pub(crate) ends: bool,
}

impl Kernel2d {
    /// Every form a table can take (`blocks` and `ends` only with `lattice`).
    pub(crate) const ALL: [Kernel2d; 5] = [
        Kernel2d::of(false, false, false),
        Kernel2d::of(true, false, false),
        Kernel2d::of(true, false, true),
        Kernel2d::of(true, true, false),
        Kernel2d::of(true, true, true),
    ];

    pub(crate) const fn of(lattice: bool, blocks: bool, ends: bool) -> Kernel2d {
        Kernel2d {
            lattice,
            blocks,
            ends,
        }
    }

    /// Its place in [`Kernel2d::ALL`].
    pub(crate) fn index(self) -> usize {
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
    pub(crate) lut: wgpu::Buffer,
    pub(crate) pieces: wgpu::Buffer,
    pub(crate) params: Params,
    /// Which specialisation of the 2D kernel decodes it.
    pub(crate) kernel: Kernel2d,
    pub(crate) volume: Option<Params3>,
    pub(crate) bytes: usize,
}

impl GpuOperator {
    /// Device memory it holds.
    pub fn bytes(&self) -> usize {
        self.bytes
    }
}

impl Gpu {
    /// The two storage buffers of an operator: its lookup map and its cells.
    pub(crate) fn tables(
        &self,
        lut: &[u8],
        cells: &[u8],
    ) -> Result<(wgpu::Buffer, wgpu::Buffer), GpuError> {
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

    /// Uploads an operator as [`fractile_codec::pieces::Flatten::flat`] gives it.
    pub fn upload_flat(&self, flat: &Flat) -> Result<GpuOperator, GpuError> {
        match flat {
            Flat::Lattice(l) => self.upload_lattice(l),
            Flat::Pieces(t) => self.upload_pieces(t),
        }
    }

    pub(crate) fn upload_pieces(&self, t: &PieceTable) -> Result<GpuOperator, GpuError> {
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
    pub(crate) fn upload_lattice(&self, l: &Lattice) -> Result<GpuOperator, GpuError> {
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
                quantum: fractile_codec::decode::position_quantum(&op.frame()),
                inv_quantum: 1.0 / fractile_codec::decode::position_quantum(&op.frame()),
                ..Params3::default()
            }),
            bytes,
        })
    }
}
