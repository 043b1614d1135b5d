//! Any 2D operator of fractile flattened into two tables that a GPU kernel can walk with
//! lookups and multiply-adds only: a grid of lookup cells naming pieces, and per piece the maps
//! in local coordinates. The kernel in `shaders/decode2d.wgsl` mirrors [`PieceTable::step`]
//! line by line; `PieceTable` is itself an [`Operator`], so the CPU decoders check the
//! flattening against the codec's own operator (tests below) and the GPU against both.
//!
//! For a frame point p: the lookup cell is `clamp(floor((p - lut_origin) * (1 / lut_cell)), 0, n-1)`
//! (a product: exact for power-of-two cells, where a WGSL division need not be);
//! its entry names a piece (the low 31 bits) and, with the top bit set, says the cell is split
//! along its diagonal into two pieces (the second for local `u + v > 1`, psa2d's triangles).
//! Local coordinates `(u, v) = clamp((p - origin) * inv_size, 0, 1)`; then
//! `g = g0 + gu u + gv v + guv u v`, the same for s, and `phi(p) = n0 + nu u + nv v` per axis.

use crate::core::operator::{Operator, Step};

/// One piece: a range, a cell or a triangle, with its maps in local coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Piece {
    /// Frame point at local (0, 0).
    pub origin: [f32; 2],
    /// 1 / the piece's extent, per axis.
    pub inv_size: [f32; 2],
    /// g: constant, u, v and u v coefficients.
    pub g: [f32; 4],
    /// s: constant, u, v and u v coefficients.
    pub s: [f32; 4],
    /// phi's x: constant, u and v coefficients (and a pad).
    pub next_x: [f32; 4],
    /// phi's y: constant, u and v coefficients (and a pad).
    pub next_y: [f32; 4],
}

impl Piece {
    /// The piece as 20 f32 (five vec4 in the kernel): origin and inverse size, g, s, phi x, phi y.
    pub fn to_array(&self) -> [f32; 20] {
        let mut a = [0.0; 20];
        a[..2].copy_from_slice(&self.origin);
        a[2..4].copy_from_slice(&self.inv_size);
        a[4..8].copy_from_slice(&self.g);
        a[8..12].copy_from_slice(&self.s);
        a[12..16].copy_from_slice(&self.next_x);
        a[16..20].copy_from_slice(&self.next_y);
        a
    }
}

/// Bit of a lookup entry that marks a cell split along its diagonal.
pub const SPLIT: u32 = 1 << 31;

/// The flattened operator.
#[derive(Clone, Debug, PartialEq)]
pub struct PieceTable {
    /// The operator's frame.
    pub frame: [f32; 2],
    /// The operator's valid extent (unit coordinates map onto it).
    pub valid: [f32; 2],
    /// Frame point of the lookup grid's corner.
    pub lut_origin: [f32; 2],
    /// Side of a lookup cell, frame units.
    pub lut_cell: [f32; 2],
    /// Lookup grid columns and rows.
    pub lut_size: [u32; 2],
    /// Row-major lookup entries: piece index, or'ed with [`SPLIT`].
    pub lut: Vec<u32>,
    /// The pieces.
    pub pieces: Vec<Piece>,
    /// The operator's invariant interval.
    pub interval: (f32, f32),
}

impl PieceTable {
    /// Bytes the two tables take on a device.
    pub fn device_bytes(&self) -> usize {
        self.lut.len() * 4 + self.pieces.len() * 80
    }

    #[inline]
    fn piece(&self, p: [f32; 2]) -> (&Piece, f32, f32) {
        let [cx, cy] = lookup(p, self.lut_origin, self.lut_cell, self.lut_size);
        let entry = self.lut[cy * self.lut_size[0] as usize + cx];
        let mut k = (entry & !SPLIT) as usize;
        let local = |pc: &Piece| {
            (
                ((p[0] - pc.origin[0]) * pc.inv_size[0]).clamp(0.0, 1.0),
                ((p[1] - pc.origin[1]) * pc.inv_size[1]).clamp(0.0, 1.0),
            )
        };
        let (u, v) = local(&self.pieces[k]);
        if entry & SPLIT != 0 && u + v > 1.0 {
            k += 1;
        }
        (&self.pieces[k], u, v)
    }
}

/// The lookup cell of frame point `p`: `clamp(floor((p - origin) * (1 / cell)), 0, size - 1)`
/// per axis, as the kernel computes it.
#[inline]
fn lookup(p: [f32; 2], origin: [f32; 2], cell: [f32; 2], size: [u32; 2]) -> [usize; 2] {
    std::array::from_fn(|d| {
        let c = ((p[d] - origin[d]) * (1.0 / cell[d])).floor();
        (c.max(0.0) as usize).min(size[d] as usize - 1)
    })
}

impl Operator<2> for PieceTable {
    fn frame(&self) -> [f32; 2] {
        self.frame
    }

    fn valid(&self) -> [f32; 2] {
        self.valid
    }

    /// Pieces serve continuous decoding, which does not use the footprint.
    fn expansion(&self) -> u32 {
        1
    }

    #[inline]
    fn step(&self, p: [f32; 2]) -> Step<2> {
        let (pc, u, v) = self.piece(p);
        let bil = |c: [f32; 4]| c[0] + c[1] * u + c[2] * v + c[3] * u * v;
        Step {
            offset: bil(pc.g),
            contrast: bil(pc.s),
            next: [
                pc.next_x[0] + pc.next_x[1] * u + pc.next_x[2] * v,
                pc.next_y[0] + pc.next_y[1] * u + pc.next_y[2] * v,
            ],
        }
    }

    fn invariant_interval(&self) -> (f32, f32) {
        self.interval
    }
}

/// A [`PieceTable`] whose pieces are its lookup cells, one a cell and none split, with one
/// contrast for all, each piece's map along x set by its column and along y by its row (the
/// projected codec's quarter cells): what a device needs of it is then each piece's offset
/// ([`Offsets`]), a map a column and a row, and the contrast. 16 bytes a piece against 84 (80
/// for the piece and 4 of lookup), 9 where cells share corners in blocks: the projected
/// codec's tables take 36 bytes a sample instead of 336 (etopo20's 1080 x 540: 21 MB against
/// 195), 44 with its [`Ends`]. [`PieceTable::lattice`] finds one in a table. Its `step` is the
/// table's (the same data, the same arithmetic, bit for bit), written as the kernel's lattice
/// branch computes it: the origin from the cell, the maps from the column and row.
#[derive(Clone, Debug, PartialEq)]
pub struct Lattice {
    /// The operator's frame.
    pub frame: [f32; 2],
    /// The operator's valid extent.
    pub valid: [f32; 2],
    /// Frame point of the lattice's corner.
    pub lut_origin: [f32; 2],
    /// Side of a cell, frame units: a power of two, so that a cell's origin
    /// `lut_origin + index * lut_cell` is exact whether or not a multiply-add is fused.
    pub lut_cell: [f32; 2],
    /// Columns and rows.
    pub lut_size: [u32; 2],
    /// The contrast of every piece: constant, u, v and u v coefficients.
    pub contrast: [f32; 4],
    /// Each cell's offset.
    pub offsets: Offsets,
    /// phi's x (constant, u, v, pad) of each column.
    pub columns: Vec<[f32; 4]>,
    /// phi's y (constant, u, v, pad) of each row.
    pub rows: Vec<[f32; 4]>,
    /// The operator's invariant interval.
    pub interval: (f32, f32),
    /// Where chains end, for an operator whose chains end on its samples' interpolant rather
    /// than on a constant seed (the projected codec's); `None`: on the seed.
    pub ends: Option<Ends>,
}

/// Chains that end on S, the bilinear interpolant of samples at frame points `k + 0.5`, where
/// the attractor is S plus a residual within a bound a cell (the projected codec's
/// `run_chains`): a chain stops once `|prod s|` times its cell's bound is within the
/// tolerance, and answers `acc_g + acc_s S(q)` within `|acc_s| R(q)` plus its own f32
/// rounding, `(steps + 4) * ulps`. 8 bytes a sample on a device, for bounds as tight as the
/// CPU's and the CPU's values, where a constant seed's bound is the whole invariant interval.
#[derive(Clone, Debug, PartialEq)]
pub struct Ends {
    /// Samples along x and y (at least two each).
    pub size: [u32; 2],
    /// The samples, normalised, row-major.
    pub samples: Vec<f32>,
    /// Each cell's bound on |f - S| (cells between samples, `(size - 1)` a side), row-major.
    pub residual: Vec<f32>,
    /// A chain's f32 rounding a step, added to its bound.
    pub ulps: f32,
}

/// The offsets of a [`Lattice`]'s cells, bilinear in each cell.
#[derive(Clone, Debug, PartialEq)]
pub enum Offsets {
    /// Each cell's coefficients (constant, u, v, u v), row-major: any lattice.
    Cells(Vec<[f32; 4]>),
    /// Each block of 2 x 2 cells' values at its 3 x 3 corners (row-major in the block; blocks
    /// row-major, half the cells a side): cell (x, y)'s offset is [`bilinear`] of the corners
    /// `(x % 2 + a, y % 2 + b)` of block `(x / 2, y / 2)`, the coefficients `Cells` would hold
    /// to the bit. The projected codec's quarter cells, whose corners each of its cells
    /// shares among its four quarters: 36 bytes a block against 64.
    Blocks(Vec<[f32; 9]>),
}

impl Offsets {
    /// Cell `(x, y)`'s coefficients, on a lattice of `columns` cells a row.
    #[inline]
    pub fn of(&self, x: usize, y: usize, columns: usize) -> [f32; 4] {
        match self {
            Offsets::Cells(c) => c[y * columns + x],
            Offsets::Blocks(b) => {
                let r = &b[(y / 2) * (columns / 2) + x / 2];
                let n = 3 * (y % 2) + x % 2;
                bilinear([r[n], r[n + 1], r[n + 3], r[n + 4]])
            }
        }
    }

    /// Cells they cover.
    pub fn cells(&self) -> usize {
        match self {
            Offsets::Cells(c) => c.len(),
            Offsets::Blocks(b) => 4 * b.len(),
        }
    }

    /// Their bytes on a device.
    pub fn device_bytes(&self) -> usize {
        match self {
            Offsets::Cells(c) => 16 * c.len(),
            // Padded to whole vec4s: the kernel reads them from an array of vec4.
            Offsets::Blocks(b) => (36 * b.len()).next_multiple_of(16),
        }
    }
}

impl Lattice {
    /// Bytes the tables take on a device.
    pub fn device_bytes(&self) -> usize {
        let ends = self
            .ends
            .as_ref()
            .map_or(0, |e| 4 * (e.samples.len() + e.residual.len()));
        self.offsets.device_bytes() + (self.columns.len() + self.rows.len()) * 16 + ends
    }
}

impl PieceTable {
    /// The table as a [`Lattice`], when it is one: every lookup cell its own piece (the
    /// identity lookup), whose origin and size are the cell's, one contrast, and maps that
    /// depend on the column (x) and the row (y) alone, with power-of-two cells.
    pub fn lattice(&self) -> Option<Lattice> {
        let [lx, ly] = self.lut_size.map(|n| n as usize);
        let power_of_two = |c: f32| c > 0.0 && c.is_finite() && c.to_bits() & 0x7f_ffff == 0;
        if lx * ly == 0
            || self.pieces.len() != lx * ly
            || !self.lut_cell.iter().all(|&c| power_of_two(c))
        {
            return None;
        }
        let inv = self.lut_cell.map(|c| 1.0 / c);
        let contrast = self.pieces[0].s;
        let columns: Vec<[f32; 4]> = self.pieces[..lx].iter().map(|p| p.next_x).collect();
        let rows: Vec<[f32; 4]> = self.pieces.iter().step_by(lx).map(|p| p.next_y).collect();
        let same = |a: [f32; 4], b: [f32; 4]| a.map(f32::to_bits) == b.map(f32::to_bits);
        for (k, (p, &entry)) in self.pieces.iter().zip(&self.lut).enumerate() {
            let (cx, cy) = (k % lx, k / lx);
            let origin = [
                self.lut_origin[0] + cx as f32 * self.lut_cell[0],
                self.lut_origin[1] + cy as f32 * self.lut_cell[1],
            ];
            let fits = entry == k as u32
                && p.origin == origin
                && p.inv_size == inv
                && same(p.s, contrast)
                && same(p.next_x, columns[cx])
                && same(p.next_y, rows[cy]);
            if !fits {
                return None;
            }
        }
        Some(Lattice {
            frame: self.frame,
            valid: self.valid,
            lut_origin: self.lut_origin,
            lut_cell: self.lut_cell,
            lut_size: self.lut_size,
            contrast,
            offsets: Offsets::Cells(self.pieces.iter().map(|p| p.g).collect()),
            columns,
            rows,
            interval: self.interval,
            ends: None,
        })
    }
}

impl Operator<2> for Lattice {
    fn frame(&self) -> [f32; 2] {
        self.frame
    }

    fn valid(&self) -> [f32; 2] {
        self.valid
    }

    fn expansion(&self) -> u32 {
        1
    }

    #[inline]
    fn step(&self, p: [f32; 2]) -> Step<2> {
        let [cx, cy] = lookup(p, self.lut_origin, self.lut_cell, self.lut_size);
        let local = |d: usize, c: usize| {
            let origin = self.lut_origin[d] + c as f32 * self.lut_cell[d];
            ((p[d] - origin) * (1.0 / self.lut_cell[d])).clamp(0.0, 1.0)
        };
        let (u, v) = (local(0, cx), local(1, cy));
        let bil = |c: [f32; 4]| c[0] + c[1] * u + c[2] * v + c[3] * u * v;
        let (nx, ny) = (self.columns[cx], self.rows[cy]);
        Step {
            offset: bil(self.offsets.of(cx, cy, self.lut_size[0] as usize)),
            contrast: bil(self.contrast),
            next: [nx[0] + nx[1] * u + nx[2] * v, ny[0] + ny[1] * u + ny[2] * v],
        }
    }

    fn invariant_interval(&self) -> (f32, f32) {
        self.interval
    }
}

/// A flattened operator as a device takes it.
#[derive(Clone, Debug, PartialEq)]
pub enum Flat {
    /// A table that is a lattice, as one.
    Lattice(Lattice),
    /// Any other table.
    Pieces(PieceTable),
}

/// Operators that can be flattened.
pub trait Flatten {
    /// The operator as lookup and piece tables.
    fn pieces(&self) -> PieceTable;

    /// The operator as a device takes it: a [`Lattice`] when its table is one, else the
    /// table. A codec whose table is always a lattice builds the lattice directly, without
    /// the table's five times the bytes.
    fn flat(&self) -> Flat {
        let t = self.pieces();
        match t.lattice() {
            Some(l) => Flat::Lattice(l),
            None => Flat::Pieces(t),
        }
    }
}

/// Coefficients (constant, u, v, u v) of the bilinear function through four corner values in the
/// order (0,0), (1,0), (0,1), (1,1).
pub fn bilinear(c: [f32; 4]) -> [f32; 4] {
    [c[0], c[1] - c[0], c[2] - c[0], c[0] - c[1] - c[2] + c[3]]
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::core::decode;

    /// Asserts that `op` and its flattening decode 4,004 points alike (each codec's tests call
    /// this on its own operators).
    pub(crate) fn agree<O: Operator<2> + Flatten>(op: &O, what: &str) {
        let t = op.pieces();
        let pts: Vec<[f32; 2]> = (0..4000)
            .map(|i| {
                let h = (i as u32).wrapping_mul(2_654_435_761) as f32 / u32::MAX as f32;
                let k = (i as u32).wrapping_mul(40_503).wrapping_add(7) as f32 / u32::MAX as f32;
                [h, (k * 977.0).fract()]
            })
            .chain([[0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 0.0]])
            .collect();
        let a = decode::points(op, &pts, 12, 0.0);
        let b = decode::points(&t, &pts, 12, 0.0);
        // A table that is a lattice decodes as one bit for bit (the GPU uploads it so).
        if let Some(l) = t.lattice() {
            let c = decode::points(&l, &pts, 12, 0.0);
            for (k, (x, y)) in b.iter().zip(&c).enumerate() {
                assert_eq!(
                    (x.value.to_bits(), x.error_bound.to_bits(), x.iterations),
                    (y.value.to_bits(), y.error_bound.to_bits(), y.iterations),
                    "{what} point {:?}: pieces against lattice",
                    pts[k]
                );
            }
        }
        for (k, (x, y)) in a.iter().zip(&b).enumerate() {
            assert!(
                (x.value - y.value).abs() < 1e-4,
                "{what} point {:?}: operator {} pieces {}",
                pts[k],
                x.value,
                y.value
            );
        }
    }
}
