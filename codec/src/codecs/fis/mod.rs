//! Fractal interpolation surfaces (FIS) for height fields, written as the same partitioned
//! affine operator as the quadtree IFS, so every decoder serves them unchanged.
//!
//! Interpolation points are a regular subsample of the height field: every `spacing`-th sample
//! in both directions (the last row and column of nodes may lie past the source, on its
//! edge-extended values). The node grid splits the frame into cells; the map of cell c sends the
//! **whole** node grid onto c (Drakopoulos and Manousopoulos; Wu and Zhou), so
//! `phi_c(p)` takes a point of c back to the whole grid, reflected on odd columns and odd rows
//! (the vertex labelling of chromatic number 4: the two cells beside a shared edge both map it
//! from the same edge of the grid, so the surface joins continuously there when s does). For p in
//! c, with corners k and `w_k(p)` their bilinear weights:
//!
//! `(W f)(p) = sum_k w_k(p) (z_k - s_k z_{d(k)}) + s(p) f(phi_c(p))`
//!
//! where `z_k` is the height at corner k, `z_{d(k)}` the height at the grid corner that phi maps
//! onto k, and `s(p)` the vertical scaling. Since phi maps nodes to nodes and g is fitted at the
//! corners, W maps the node heights to themselves: the attractor passes exactly through every
//! interpolation point, whatever s is.
//!
//! Three layouts of s, the three codecs of `fractile encode --codec`:
//! - [`Scaling::Global`] (`fis-rect-global`): one s for the surface, Drakopoulos and
//!   Manousopoulos' model (F_i = a x + b y + g x y + s z + c fitted to the four corners);
//! - [`Scaling::PerCell`] (`fis-rect`): one s per cell, by least squares against the source (the
//!   paper's future work); the surface may then step across cell edges;
//! - [`Scaling::PerNode`] (`fis-bilinear`): s bilinear over each cell with one parameter per
//!   node (Wu and Zhou), fitted by their local iteration algorithm: each node's s in turn is
//!   the least-squares optimum over its (up to) four cells, the others held, until no s moves
//!   (a Gauss-Seidel solve of the collage least squares). Continuous across edges.
//!
//! The fit is a collage fit: `f(p) - B_z(p) ≈ s(p) (f(phi(p)) - B_{z_d}(p))` over every source
//! sample, with B the bilinear interpolants of the corner and the mapped-corner heights; it is
//! linear in the s parameters.

pub(crate) mod encode;
pub(crate) mod fit;
pub(crate) mod plane;

use serde::{Deserialize, Serialize};

use crate::core::entropy::{Decoder, Encoder};
use crate::core::format::FormatError;
use crate::core::lattice::{get_grid, lattice_frame, lattice_locate, put_grid, top_index};
use crate::core::operator::{Operator, Step};

/// How the vertical scaling varies over the surface.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Scaling {
    /// One s for every cell.
    Global,
    /// One s per cell.
    PerCell,
    /// One s per node, bilinear over each cell.
    PerNode,
}

/// What a reader needs to decode a plane's stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FisHeader {
    /// Source width and height in samples.
    pub samples: [u32; 2],
    /// Samples between interpolation points.
    pub spacing: u32,
    /// Layout of s.
    pub scaling: Scaling,
    /// Node heights are multiples of this step (normalised value units, 0..1).
    pub height_step: f32,
    /// Bits of an s index (levels -L..=L, L = 2^(bits-1) - 1).
    pub scaling_bits: u8,
    /// Largest |s|, below 1.
    pub max_scaling: f32,
}

impl FisHeader {
    /// Nodes along x and y.
    pub fn nodes(&self) -> [usize; 2] {
        let n = |s: u32| ((s.max(2) - 1).div_ceil(self.spacing) + 1) as usize;
        [n(self.samples[0]), n(self.samples[1])]
    }

    /// Number of s parameters.
    pub fn parameters(&self) -> usize {
        let [nx, ny] = self.nodes();
        match self.scaling {
            Scaling::Global => 1,
            Scaling::PerCell => (nx - 1) * (ny - 1),
            Scaling::PerNode => nx * ny,
        }
    }

    /// Rejects headers no encoder writes (a corrupt or hostile asset must not reach a decoder).
    pub fn validate(&self) -> Result<(), FormatError> {
        let [w, h] = self.samples;
        if !(2..=1 << 16).contains(&w) || !(2..=1 << 16).contains(&h) {
            return Err(FormatError::header(format!(
                "bad FIS sample grid {w}x{h} (2..=65536 a side)"
            )));
        }
        if !(1..=4096).contains(&self.spacing) {
            return Err(FormatError::header(format!(
                "bad FIS spacing {}",
                self.spacing
            )));
        }
        if !(self.height_step > 1e-9 && self.height_step <= 1.0) {
            return Err(FormatError::header(format!(
                "bad FIS height step {}",
                self.height_step
            )));
        }
        let contracts = self.max_scaling > 0.0 && self.max_scaling < 1.0;
        if !(2..=12).contains(&self.scaling_bits) || !contracts {
            return Err(FormatError::header(format!(
                "bad FIS scaling quantiser: {} bits, max {}",
                self.scaling_bits, self.max_scaling
            )));
        }
        Ok(())
    }

    fn scaling_levels(&self) -> i32 {
        (1 << (self.scaling_bits - 1)) - 1
    }

    /// The s of an index.
    pub fn scaling_of(&self, index: i32) -> f32 {
        index as f32 / self.scaling_levels() as f32 * self.max_scaling
    }

    /// The nearest index of an s (clamped into the quantiser's range).
    pub fn scaling_index(&self, s: f32) -> i32 {
        let l = self.scaling_levels();
        ((s / self.max_scaling * l as f32).round() as i32).clamp(-l, l)
    }
}

/// The coded parameters of a surface: node heights (indices of `height_step`) and s indices.
#[derive(Clone, Debug, PartialEq)]
pub struct FisParams {
    /// Row-major node height indices, `nodes()[0] * nodes()[1]`.
    pub heights: Vec<i32>,
    /// s indices, `parameters()` of them (row-major cells or nodes).
    pub scalings: Vec<i32>,
}

/// Codes the parameters: heights by MED prediction, s indices by the same predictor on their own
/// grid (s varies smoothly where the terrain's roughness does).
pub fn encode_params(header: &FisHeader, p: &FisParams) -> Vec<u8> {
    let mut enc = Encoder::new();
    put_grid(&mut enc, &p.heights, header.nodes()[0]);
    put_grid(&mut enc, &p.scalings, scaling_grid(header).0);
    enc.finish()
}

fn scaling_grid(header: &FisHeader) -> (usize, usize) {
    let [nx, ny] = header.nodes();
    match header.scaling {
        Scaling::Global => (1, 1),
        Scaling::PerCell => (nx - 1, ny - 1),
        Scaling::PerNode => (nx, ny),
    }
}

/// Reads the parameters back (a truncated stream is an error, never a panic).
pub fn decode_params(header: &FisHeader, bytes: &[u8]) -> Result<FisParams, FormatError> {
    header.validate()?;
    let mut dec = Decoder::new(bytes);
    let top = top_index(header.height_step);
    let heights = get_grid(&mut dec, header.nodes(), 0..=top, "node height index")?;
    let (sx, sy) = scaling_grid(header);
    let l = header.scaling_levels() as i64;
    let scalings = get_grid(&mut dec, [sx, sy], -l..=l, "scaling index")?;
    if dec.overrun() {
        return Err(FormatError::stream("the FIS stream is truncated"));
    }
    Ok(FisParams { heights, scalings })
}

/// The decoding operator of a fractal interpolation surface.
#[derive(Clone, Debug)]
pub struct FisOperator {
    nodes: [usize; 2],
    spacing: f32,
    valid: [f32; 2],
    scaling: Scaling,
    /// Node heights, normalised.
    z: Vec<f32>,
    /// s per the layout.
    s: Vec<f32>,
    interval: (f32, f32),
    /// The same maps flattened; `step` walks these, so that the CPU and the GPU kernel do the
    /// same arithmetic. phi expands lengths by the number of cells a side, so a last-bit
    /// difference in u grows that much each step and two formulas would soon follow different
    /// chains (both valid, but not comparable point by point).
    table: crate::core::pieces::PieceTable,
}

impl FisOperator {
    /// Builds the operator of decoded parameters.
    pub fn new(header: &FisHeader, params: &FisParams) -> Result<FisOperator, FormatError> {
        header.validate()?;
        let [nx, ny] = header.nodes();
        if params.heights.len() != nx * ny || params.scalings.len() != header.parameters() {
            return Err(FormatError::stream(
                "FIS parameter counts do not match the header",
            ));
        }
        let mut op = FisOperator {
            nodes: [nx, ny],
            spacing: header.spacing as f32,
            valid: [header.samples[0] as f32, header.samples[1] as f32],
            scaling: header.scaling,
            z: params
                .heights
                .iter()
                .map(|&q| q as f32 * header.height_step)
                .collect(),
            s: params
                .scalings
                .iter()
                .map(|&q| header.scaling_of(q))
                .collect(),
            interval: (0.0, 1.0),
            table: crate::core::pieces::PieceTable {
                frame: [0.0; 2],
                valid: [0.0; 2],
                lut_origin: [0.0; 2],
                lut_cell: [1.0; 2],
                lut_size: [0; 2],
                lut: Vec::new(),
                pieces: Vec::new(),
                interval: (0.0, 1.0),
            },
        };
        op.interval = crate::core::operator::invariant_interval(op.cell_bounds().into_iter());
        op.table = crate::core::pieces::Flatten::pieces(&op);
        Ok(op)
    }

    /// Node heights (normalised), row-major.
    pub fn heights(&self) -> &[f32] {
        &self.z
    }

    /// Node grid size.
    pub fn nodes(&self) -> [usize; 2] {
        self.nodes
    }

    /// Samples between nodes.
    pub fn spacing(&self) -> f32 {
        self.spacing
    }

    /// Largest |s|.
    pub fn max_scaling(&self) -> f32 {
        self.s.iter().fold(0.0f32, |m, s| m.max(s.abs()))
    }

    /// Cells of the node grid.
    pub fn cells(&self) -> usize {
        (self.nodes[0] - 1) * (self.nodes[1] - 1)
    }

    /// For the invariant interval: per cell, (s, g_min, g_max) at both extremes of s.
    fn cell_bounds(&self) -> Vec<(f32, f32, f32)> {
        let [nx, ny] = self.nodes;
        let mut out = Vec::with_capacity(2 * self.cells());
        for cj in 0..ny - 1 {
            for ci in 0..nx - 1 {
                let corners = self.corners(ci, cj);
                let g: Vec<f32> = corners.iter().map(|c| c.z - c.s * c.zd).collect();
                let (glo, ghi) = g
                    .iter()
                    .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
                        (a.min(v), b.max(v))
                    });
                let (slo, shi) = corners
                    .iter()
                    .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), c| {
                        (a.min(c.s), b.max(c.s))
                    });
                out.push((slo, glo, ghi));
                out.push((shi, glo, ghi));
            }
        }
        out
    }

    /// The four corners of cell (ci, cj) in the order (0,0), (1,0), (0,1), (1,1).
    #[inline]
    fn corners(&self, ci: usize, cj: usize) -> [Corner; 4] {
        let [nx, ny] = self.nodes;
        let (fx, fy) = (ci & 1, cj & 1);
        std::array::from_fn(|k| {
            let (a, b) = (k & 1, k >> 1);
            let node = (cj + b) * nx + ci + a;
            // phi maps the grid corner ((a ^ fx), (b ^ fy)) onto this corner.
            let dnode = ((b ^ fy) * (ny - 1)) * nx + (a ^ fx) * (nx - 1);
            let s = match self.scaling {
                Scaling::Global => self.s[0],
                Scaling::PerCell => self.s[cj * (nx - 1) + ci],
                Scaling::PerNode => self.s[node],
            };
            Corner {
                z: self.z[node],
                zd: self.z[dnode],
                s,
            }
        })
    }

    /// The cell of a point in sample coordinates and the local coordinates in it.
    #[inline]
    fn locate(&self, t: [f32; 2]) -> (usize, usize, f32, f32) {
        lattice_locate(self.nodes, self.spacing, t)
    }
}

#[derive(Clone, Copy)]
struct Corner {
    z: f32,
    zd: f32,
    s: f32,
}

impl Operator<2> for FisOperator {
    fn frame(&self) -> [f32; 2] {
        lattice_frame(self.nodes, self.spacing)
    }

    fn valid(&self) -> [f32; 2] {
        self.valid
    }

    /// 1: an FIS is a continuous surface fitted on point samples, so the discrete decoder
    /// samples the previous iterate at phi(p) (bilinearly) instead of averaging a footprint.
    fn expansion(&self) -> u32 {
        1
    }

    /// Frame pixels have centres at k + 0.5; samples (and nodes) sit on those centres. The cell
    /// of p and its local (u, v), then g and s bilinear from the corners and phi onto the
    /// mirrored grid, as flattened in `pieces` (see the `table` field for why).
    #[inline]
    fn step(&self, p: [f32; 2]) -> Step<2> {
        self.table.step(p)
    }

    fn invariant_interval(&self) -> (f32, f32) {
        self.interval
    }
}

impl crate::core::pieces::Flatten for FisOperator {
    /// One piece per cell: g and s bilinear from the corners, phi onto the (mirrored) grid.
    fn pieces(&self) -> crate::core::pieces::PieceTable {
        use crate::core::pieces::{Piece, PieceTable, bilinear};
        let [nx, ny] = self.nodes;
        let k = self.spacing;
        let span = [(nx - 1) as f32 * k, (ny - 1) as f32 * k];
        let mut pieces = Vec::with_capacity(self.cells());
        for cj in 0..ny - 1 {
            for ci in 0..nx - 1 {
                let c = self.corners(ci, cj);
                let axis = |flip: bool, span: f32| {
                    if flip {
                        (span + 0.5, -span)
                    } else {
                        (0.5, span)
                    }
                };
                let (x0, xu) = axis(ci & 1 == 1, span[0]);
                let (y0, yv) = axis(cj & 1 == 1, span[1]);
                pieces.push(Piece {
                    origin: [0.5 + ci as f32 * k, 0.5 + cj as f32 * k],
                    inv_size: [1.0 / k; 2],
                    g: bilinear(std::array::from_fn(|q| c[q].z - c[q].s * c[q].zd)),
                    s: bilinear(std::array::from_fn(|q| c[q].s)),
                    next_x: [x0, xu, 0.0, 0.0],
                    next_y: [y0, 0.0, yv, 0.0],
                });
            }
        }
        PieceTable {
            frame: self.frame(),
            valid: self.valid,
            lut_origin: [0.5; 2],
            lut_cell: [k; 2],
            lut_size: [(nx - 1) as u32, (ny - 1) as u32],
            lut: (0..pieces.len() as u32).collect(),
            pieces,
            interval: self.interval,
        }
    }
}

/// The codec's name for a layout of s (`fractile encode --codec NAME`).
pub fn codec_name(scaling: Scaling) -> &'static str {
    match scaling {
        Scaling::Global => "fis-rect-global",
        Scaling::PerCell => "fis-rect",
        Scaling::PerNode => "fis-bilinear",
    }
}

/// The layout of s of a codec name.
pub fn scaling_of_codec(name: &str) -> Option<Scaling> {
    [Scaling::Global, Scaling::PerCell, Scaling::PerNode]
        .into_iter()
        .find(|&s| codec_name(s) == name)
}

/// Settings of the FIS encoder.
#[derive(Clone, Debug, PartialEq)]
pub struct FisSettings {
    /// Layout of s (which of the three codecs).
    pub scaling: Scaling,
    /// Samples between interpolation points.
    pub spacing: u32,
    /// Node height step in source units (`None`: automatic, see
    /// `codecs::lattice`).
    pub height_step: Option<f64>,
    /// Bits of an s index.
    pub scaling_bits: u8,
    /// Largest |s|.
    pub max_scaling: f32,
    /// Rate control: at most this many bits a source cell, overriding `spacing` and the
    /// automatic height step (see `codecs::lattice`).
    pub target_bpp: Option<f64>,
}

impl Default for FisSettings {
    fn default() -> Self {
        FisSettings {
            scaling: Scaling::PerNode,
            spacing: 8,
            height_step: None,
            // 6 bits: finer s buys nothing measurable on the DEMs (checked at 4..8 bits).
            scaling_bits: 6,
            max_scaling: 0.9,
            target_bpp: None,
        }
    }
}
