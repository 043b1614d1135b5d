//! The partitioned affine operator every codec of fractile is written as:
//! for a point p in cell c, `(W f)(p) = g_c(p) + s_c(p) * f(phi_c(p))`, |s_c| < 1.
//!
//! Decoders ([`crate::decode`]) know nothing else. A codec provides [`Operator::step`], which finds
//! the cell of a point and returns g, s and phi there; the quadtree IFS here has constant g (offset)
//! and s (contrast) per range and phi mapping the range onto its domain (scale 2, one of 8
//! isometries). Fractal interpolation surfaces plug in later with bilinear g and s.

use crate::decode::Chain;

/// What the operator does at one point: `(W f)(p) = offset + contrast * f(next)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Step<const D: usize> {
    /// g_c(p).
    pub offset: f32,
    /// s_c(p), |s| < 1.
    pub contrast: f32,
    /// phi_c(p), a point of the frame.
    pub next: [f32; D],
}

/// A partitioned affine operator on functions over a D-dimensional frame `[0, frame)`.
///
/// Values are normalised: the source's value range maps to [0, 1].
pub trait Operator<const D: usize>: Send + Sync {
    /// Size of the frame in coding-grid units (the padded grid the encoder worked on).
    fn frame(&self) -> [f32; D];
    /// The part `[0, valid)` of the frame that holds the source; unit coordinates map onto it.
    fn valid(&self) -> [f32; D];
    /// How much phi stretches lengths (domain size / range size). Discrete decoding averages the
    /// previous iterate over this footprint, as the encoder did when it fitted the maps.
    fn expansion(&self) -> u32;
    /// g, s and phi at `p` (clamped into the frame).
    fn step(&self, p: [f32; D]) -> Step<D>;
    /// An interval of values that W maps into itself: every iterate from a seed inside it, and the
    /// attractor, stay inside it. Its half-width bounds `max |seed - f|`.
    fn invariant_interval(&self) -> (f32, f32);
    /// Runs inverse-iteration chains (continuous decoding's hot loop) until each has taken
    /// `iterations` steps in all or [`crate::decode::active`] says it is done. The default steps
    /// them through [`Operator::step`]; a codec may override it with a layout of its maps made
    /// for the loop, giving the same answers bit for bit.
    fn run_chains(&self, chains: &mut [Chain<D>], iterations: u32, tolerance: f32) {
        crate::decode::run_chains_stepwise(self, chains, iterations, tolerance);
    }
}

/// One cell of an [`AxisAligned`] operator: a box of lattice squares and its map, whose phi keeps
/// the axes (a signed permutation scaled by the expansion), whose s is constant and whose g is
/// affine.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisCell {
    /// Lattice columns `cols[0]..cols[1]` that the cell covers.
    pub cols: [usize; 2],
    /// Lattice rows `rows[0]..rows[1]` that the cell covers.
    pub rows: [usize; 2],
    /// The map, exactly as [`Operator::step`] evaluates it in this cell.
    pub map: AffineCell,
}

/// A 2D operator whose cells are boxes of a square lattice, found by a separable lookup (the
/// column from x alone, the row from y alone), each with a map that keeps the axes: the quadtree
/// IFS. On a separable grid of points (a tile, a region) a whole block of points in one cell then
/// steps together, since its image is again a separable grid; [`crate::decode::grid`] uses this.
pub trait AxisAligned: Operator<2> {
    /// The lattice column (`axis` 0) or row (`axis` 1) of frame coordinate `t`, computed exactly as
    /// [`Operator::step`] finds a point's cell.
    fn lattice(&self, axis: usize, t: f32) -> usize;
    /// The cell that covers lattice square (`col`, `row`).
    fn axis_cell(&self, col: usize, row: usize) -> AxisCell;
}

/// The smallest interval I with `hull(g_c + s_c * I) ⊂ I` over all cells, where each cell gives
/// `(s, g_min, g_max)`, the range of its offset function over the cell; found by iterating that
/// map from [0, 1] (a constant-offset fractile operator keeps [0, 1] invariant, see
/// [`crate::transform`]; a planar one may overshoot it a little, and the iteration finds by how much).
pub fn invariant_interval(maps: impl Iterator<Item = (f32, f32, f32)> + Clone) -> (f32, f32) {
    let (mut lo, mut hi) = (0.0f32, 1.0f32);
    for _ in 0..500 {
        let (mut nlo, mut nhi) = (f32::INFINITY, f32::NEG_INFINITY);
        for (s, glo, ghi) in maps.clone() {
            let (a, b) = (s * lo, s * hi);
            nlo = nlo.min(glo + a.min(b));
            nhi = nhi.max(ghi + a.max(b));
        }
        if !nlo.is_finite() {
            return (0.0, 1.0);
        }
        let done = (nlo - lo).abs() < 1e-7 && (nhi - hi).abs() < 1e-7;
        lo = nlo;
        hi = nhi;
        if done {
            break;
        }
    }
    // The iteration approaches the fixed interval from outside only asymptotically: widen by a
    // hair so that rounding never puts a value outside it.
    (lo - 1e-5, hi + 1e-5)
}

/// One range of a 2D quadtree IFS, in frame coordinates, ready for decoding.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RangeMap {
    /// Left edge of the range.
    pub x: u32,
    /// Top edge of the range.
    pub y: u32,
    /// Side of the (square) range.
    pub size: u32,
    /// Left edge of the domain (side 2 * size).
    pub domain_x: u32,
    /// Top edge of the domain.
    pub domain_y: u32,
    /// Isometry index, 0..8.
    pub isometry: u8,
    /// Contrast s.
    pub contrast: f32,
    /// Offset o: the value of g at the range's centre.
    pub offset: f32,
    /// Rise of g across the range along x and y (planar offset term; 0 for the classic codec):
    /// `g(p) = offset + slope_x * (px - cx) / size + slope_y * (py - cy) / size`.
    pub slope: [f32; 2],
}

impl RangeMap {
    /// Least and greatest value of g over the range.
    pub fn offset_range(&self) -> (f32, f32) {
        let half = 0.5 * (self.slope[0].abs() + self.slope[1].abs());
        (self.offset - half, self.offset + half)
    }
}

/// A range's map in the form the decoders evaluate: `phi(p) = L_k p + (cx, cy)` where `L_k` is
/// twice the linear part of isometry k ([`ISOMETRY_MATRICES`]), and `g(p) = offset + gx px + gy
/// py`. Precomputed so that a step is branch-free and has no division; 32 bytes and aligned, so
/// that a cell never straddles two cache lines (the decoders' hot loop is bound by these loads).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub struct AffineCell {
    /// Constant of phi_x.
    pub cx: f32,
    /// Constant of phi_y.
    pub cy: f32,
    /// Contrast s.
    pub contrast: f32,
    /// Constant of g.
    pub offset: f32,
    /// x coefficient of g.
    pub gx: f32,
    /// y coefficient of g.
    pub gy: f32,
    /// Isometry index, 0..8, selecting the linear part of phi.
    pub isometry: u32,
}

/// `[ax, bx, ay, by]` of each isometry with the scale 2 of a domain over its range:
/// `phi_x = ax px + bx py + cx`, `phi_y = ay px + by py + cy`.
pub const ISOMETRY_MATRICES: [[f32; 4]; 8] = {
    let mut m = [[0.0f32; 4]; 8];
    let mut k = 0;
    while k < 8 {
        // Local a' and b' as (coef of a, coef of b), see `transform::isometry`.
        let (mut ua, mut ub) = ([1.0f32, 0.0], [0.0f32, 1.0]);
        if k & 4 != 0 {
            let t = ua;
            ua = ub;
            ub = t;
        }
        if k & 1 != 0 {
            ua = [-ua[0], -ua[1]];
        }
        if k & 2 != 0 {
            ub = [-ub[0], -ub[1]];
        }
        m[k] = [2.0 * ua[0], 2.0 * ua[1], 2.0 * ub[0], 2.0 * ub[1]];
        k += 1;
    }
    m
};

impl AffineCell {
    fn of(r: &RangeMap) -> AffineCell {
        // Local coordinates after the isometry, as (coef of a, coef of b, constant).
        let (mut ua, mut ub) = ([1.0f32, 0.0, 0.0], [0.0f32, 1.0, 0.0]);
        if r.isometry & 4 != 0 {
            std::mem::swap(&mut ua, &mut ub);
        }
        if r.isometry & 1 != 0 {
            ua = [-ua[0], -ua[1], 1.0 - ua[2]];
        }
        if r.isometry & 2 != 0 {
            ub = [-ub[0], -ub[1], 1.0 - ub[2]];
        }
        // a = (px - x) / n; phi = d + 2n a' = 2 ua0 px + 2 ua1 py + (d + 2n ua2 - 2 ua0 x - 2 ua1 y).
        let (x, y, n) = (r.x as f32, r.y as f32, r.size as f32);
        let c = |u: [f32; 3], d: f32| d + 2.0 * n * u[2] - 2.0 * u[0] * x - 2.0 * u[1] * y;
        let (gx, gy) = (r.slope[0] / n, r.slope[1] / n);
        AffineCell {
            cx: c(ua, r.domain_x as f32),
            cy: c(ub, r.domain_y as f32),
            contrast: r.contrast,
            offset: r.offset - gx * (x + 0.5 * n) - gy * (y + 0.5 * n),
            gx,
            gy,
            isometry: r.isometry as u32 & 7,
        }
    }

    /// phi at p.
    #[inline(always)]
    pub fn phi(&self, p: [f32; 2]) -> [f32; 2] {
        let [ax, bx, ay, by] = ISOMETRY_MATRICES[self.isometry as usize & 7];
        [
            ax * p[0] + bx * p[1] + self.cx,
            ay * p[0] + by * p[1] + self.cy,
        ]
    }
}

/// A quadtree partitioned IFS on a 2D frame: ranges that tile the frame, each with its map.
#[derive(Clone, Debug)]
pub struct QuadtreeOperator {
    frame: [u32; 2],
    valid: [f32; 2],
    cell: u32,
    inv_cell: f32,
    lut_cols: usize,
    lut_rows: usize,
    lut: Vec<u32>,
    ranges: Vec<RangeMap>,
    cells: Vec<AffineCell>,
    /// Each range's first lattice column, first row and side in lattice squares (for
    /// [`AxisAligned::axis_cell`], without divisions or a walk through the wide `RangeMap`).
    boxes: Vec<[u32; 3]>,
    interval: (f32, f32),
    /// The maps laid out for inverse iteration, when the lattice square is a power of two.
    walk: Option<Walk>,
}

/// A range's map in lattice units (a lattice square is 1), laid out for the hot loop of
/// continuous decoding: the isometry's matrix inline rather than looked up, one 32-byte
/// aligned record per range (one cache line touched a step), the offset's slopes apart (only
/// planar offsets need them).
///
/// Why: the loop is bound by the loads and floating-point operations in flight, not by its
/// arithmetic; the stepwise form spends a multiplication per axis to reach lattice units, a
/// saturating conversion and a clamp per axis, and a dependent load for the isometry. This
/// form takes 1.5x less time for the same answers: scaling by a power of two is exact in
/// floating point, so positions, sums and lookups are bit for bit those of
/// [`Operator::step`] (a test checks it).
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(32))]
struct WalkMap {
    ax: f32,
    bx: f32,
    cx: f32,
    ay: f32,
    by: f32,
    cy: f32,
    contrast: f32,
    offset: f32,
}

/// See [`WalkMap`].
#[derive(Clone, Debug)]
struct Walk {
    maps: Vec<WalkMap>,
    /// `[gx, gy]` per range in lattice units, empty when every offset is constant.
    slopes: Vec<[f32; 2]>,
}

impl Walk {
    /// `None` when the lattice square is not a power of two (lattice units would round).
    fn of(cell: u32, cells: &[AffineCell]) -> Option<Walk> {
        if !cell.is_power_of_two() {
            return None;
        }
        let (c, inv) = (cell as f32, 1.0 / cell as f32);
        let maps = cells
            .iter()
            .map(|m| {
                let [ax, bx, ay, by] = ISOMETRY_MATRICES[m.isometry as usize & 7];
                WalkMap {
                    ax,
                    bx,
                    cx: m.cx * inv,
                    ay,
                    by,
                    cy: m.cy * inv,
                    contrast: m.contrast,
                    offset: m.offset,
                }
            })
            .collect();
        let slopes = if cells.iter().any(|m| m.gx != 0.0 || m.gy != 0.0) {
            cells.iter().map(|m| [m.gx * c, m.gy * c]).collect()
        } else {
            Vec::new()
        };
        Some(Walk { maps, slopes })
    }
}

impl QuadtreeOperator {
    /// Builds the operator; `cell` is a side that divides every range's position and size
    /// (the smallest range size) and the frame. Fails if the ranges do not tile the frame.
    pub fn new(
        frame: [u32; 2],
        valid: [f32; 2],
        cell: u32,
        ranges: Vec<RangeMap>,
    ) -> Result<Self, String> {
        if cell == 0
            || !frame[0].is_multiple_of(cell)
            || !frame[1].is_multiple_of(cell)
            || frame[0] == 0
            || frame[1] == 0
        {
            return Err(format!(
                "frame {frame:?} is not a multiple of the cell size {cell}"
            ));
        }
        let cols = (frame[0] / cell) as usize;
        let rows = (frame[1] / cell) as usize;
        let mut lut = vec![u32::MAX; cols * rows];
        for (i, r) in ranges.iter().enumerate() {
            let fits = r.size > 0
                && r.size % cell == 0
                && r.x % cell == 0
                && r.y % cell == 0
                && r.x + r.size <= frame[0]
                && r.y + r.size <= frame[1]
                && r.contrast.abs() < 1.0
                && r.contrast.is_finite()
                && r.offset.is_finite()
                && r.slope.iter().all(|v| v.is_finite())
                && (r.contrast == 0.0
                    || (r.domain_x + 2 * r.size <= frame[0]
                        && r.domain_y + 2 * r.size <= frame[1]));
            if !fits {
                return Err(format!(
                    "range {i} ({r:?}) does not fit the frame {frame:?}"
                ));
            }
            let (c0, r0, n) = (
                (r.x / cell) as usize,
                (r.y / cell) as usize,
                (r.size / cell) as usize,
            );
            for row in r0..r0 + n {
                for slot in &mut lut[row * cols + c0..row * cols + c0 + n] {
                    if *slot != u32::MAX {
                        return Err(format!("range {i} overlaps another range"));
                    }
                    *slot = i as u32;
                }
            }
        }
        if lut.contains(&u32::MAX) {
            return Err("the ranges leave part of the frame uncovered".into());
        }
        let interval = invariant_interval(ranges.iter().map(|r| {
            let (lo, hi) = r.offset_range();
            (r.contrast, lo, hi)
        }));
        let cells: Vec<AffineCell> = ranges.iter().map(AffineCell::of).collect();
        let walk = Walk::of(cell, &cells);
        let boxes = ranges
            .iter()
            .map(|r| [r.x / cell, r.y / cell, r.size / cell])
            .collect();
        Ok(QuadtreeOperator {
            frame,
            valid,
            cell,
            inv_cell: 1.0 / cell as f32,
            lut_cols: cols,
            lut_rows: rows,
            lut,
            ranges,
            cells,
            boxes,
            interval,
            walk,
        })
    }

    /// The ranges, in coding order.
    pub fn ranges(&self) -> &[RangeMap] {
        &self.ranges
    }

    /// The ranges' maps in affine form, in the order of [`Self::ranges`].
    pub fn cells(&self) -> &[AffineCell] {
        &self.cells
    }

    /// The cell-index map at the smallest range size (row-major, `frame / cell` per side): what a
    /// GPU kernel uploads to find a point's range.
    pub fn lookup(&self) -> (&[u32], u32) {
        (&self.lut, self.cell)
    }

    /// Index of the range that holds frame point `p` (clamped into the frame).
    #[inline(always)]
    pub fn range_at(&self, p: [f32; 2]) -> usize {
        let x = self.lattice(0, p[0]);
        let y = self.lattice(1, p[1]);
        self.lut[y * self.lut_cols + x] as usize
    }
}

impl AxisAligned for QuadtreeOperator {
    #[inline(always)]
    fn lattice(&self, axis: usize, t: f32) -> usize {
        // A multiplication by the reciprocal, not an integer division: this is the hot path of
        // continuous decoding. (`as usize` saturates: NaN and negatives give 0.)
        let last = if axis == 0 {
            self.lut_cols
        } else {
            self.lut_rows
        } - 1;
        ((t * self.inv_cell) as usize).min(last)
    }

    fn axis_cell(&self, col: usize, row: usize) -> AxisCell {
        let i = self.lut[row * self.lut_cols + col] as usize;
        let [c, rw, n] = self.boxes[i].map(|v| v as usize);
        AxisCell {
            cols: [c, c + n],
            rows: [rw, rw + n],
            map: self.cells[i],
        }
    }
}

impl Operator<2> for QuadtreeOperator {
    fn frame(&self) -> [f32; 2] {
        [self.frame[0] as f32, self.frame[1] as f32]
    }

    fn valid(&self) -> [f32; 2] {
        self.valid
    }

    fn expansion(&self) -> u32 {
        2
    }

    #[inline(always)]
    fn step(&self, p: [f32; 2]) -> Step<2> {
        let c = &self.cells[self.range_at(p)];
        Step {
            offset: c.offset + c.gx * p[0] + c.gy * p[1],
            contrast: c.contrast,
            next: c.phi(p),
        }
    }

    fn invariant_interval(&self) -> (f32, f32) {
        self.interval
    }

    fn run_chains(&self, chains: &mut [Chain<2>], iterations: u32, tolerance: f32) {
        match &self.walk {
            Some(w) if w.slopes.is_empty() => {
                self.walk_chains::<false>(w, chains, iterations, tolerance)
            }
            Some(w) => self.walk_chains::<true>(w, chains, iterations, tolerance),
            None => crate::decode::run_chains_stepwise(self, chains, iterations, tolerance),
        }
    }
}

/// `t` truncated towards zero; NaN and values out of the `i32` range give some value that
/// the caller clamps. (One instruction on x86-64, where `as i32` adds fix-ups for those.)
#[inline(always)]
fn truncate(t: f32) -> i32 {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_cvttss_si32, _mm_set_ss};
        // SAFETY: SSE is part of the x86-64 baseline, so these instructions always exist.
        unsafe { _mm_cvttss_si32(_mm_set_ss(t)) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        t as i32
    }
}

impl QuadtreeOperator {
    /// [`Operator::run_chains`] through the [`Walk`] layout: eight chains in lockstep, in
    /// lattice units, with the same answers as the stepwise form.
    fn walk_chains<const SLOPES: bool>(
        &self,
        walk: &Walk,
        chains: &mut [Chain<2>],
        iterations: u32,
        tolerance: f32,
    ) {
        const LANES: usize = 8;
        let half = (self.interval.1 - self.interval.0) * 0.5;
        let (cell, inv) = (self.cell as f32, self.inv_cell);
        let (last_col, last_row) = (self.lut_cols as i32 - 1, self.lut_rows as i32 - 1);
        for batch in chains.chunks_mut(LANES) {
            let (mut x, mut y) = ([0.0f32; LANES], [0.0f32; LANES]);
            let mut acc_g = [0.0f32; LANES];
            // Padding lanes of the last batch start finished.
            let mut acc_s = [0.0f32; LANES];
            let mut taken = [0u32; LANES];
            for (l, c) in batch.iter().enumerate() {
                (x[l], y[l]) = (c.q[0] * inv, c.q[1] * inv);
                (acc_g[l], acc_s[l], taken[l]) = (c.acc_g, c.acc_s, c.taken);
            }
            loop {
                let mut any = false;
                for l in 0..LANES {
                    if taken[l] >= iterations || !crate::decode::active(acc_s[l], half, tolerance) {
                        continue;
                    }
                    // `as i32` truncates towards zero (and takes NaN to 0), as the stepwise
                    // lookup's `as usize` does for the slightly negative values rounding gives.
                    let col = truncate(x[l]).clamp(0, last_col) as usize;
                    let row = truncate(y[l]).clamp(0, last_row) as usize;
                    let k = self.lut[row * self.lut_cols + col] as usize;
                    let m = &walk.maps[k];
                    let offset = if SLOPES {
                        let [gx, gy] = walk.slopes[k];
                        m.offset + gx * x[l] + gy * y[l]
                    } else {
                        m.offset
                    };
                    taken[l] += 1;
                    acc_g[l] += acc_s[l] * offset;
                    acc_s[l] *= m.contrast;
                    (x[l], y[l]) = (
                        m.ax * x[l] + m.bx * y[l] + m.cx,
                        m.ay * x[l] + m.by * y[l] + m.cy,
                    );
                    any = true;
                }
                if !any {
                    break;
                }
            }
            for (l, c) in batch.iter_mut().enumerate() {
                c.q = [x[l] * cell, y[l] * cell];
                (c.acc_g, c.acc_s, c.taken) = (acc_g[l], acc_s[l], taken[l]);
            }
        }
    }
}

impl crate::pieces::Flatten for QuadtreeOperator {
    /// One piece per range, looked up through the range map at the smallest range size.
    fn pieces(&self) -> crate::pieces::PieceTable {
        let pieces = self
            .ranges
            .iter()
            .zip(&self.cells)
            .map(|(r, c)| {
                let (x, y, n) = (r.x as f32, r.y as f32, r.size as f32);
                let [ax, bx, ay, by] = ISOMETRY_MATRICES[c.isometry as usize & 7];
                crate::pieces::Piece {
                    origin: [x, y],
                    inv_size: [1.0 / n; 2],
                    g: [c.offset + c.gx * x + c.gy * y, c.gx * n, c.gy * n, 0.0],
                    s: [c.contrast, 0.0, 0.0, 0.0],
                    next_x: [ax * x + bx * y + c.cx, ax * n, bx * n, 0.0],
                    next_y: [ay * x + by * y + c.cy, ay * n, by * n, 0.0],
                }
            })
            .collect();
        crate::pieces::PieceTable {
            frame: self.frame(),
            valid: self.valid,
            lut_origin: [0.0; 2],
            lut_cell: [self.cell as f32; 2],
            lut_size: [self.lut_cols as u32, self.lut_rows as u32],
            lut: self.lut.clone(),
            pieces,
            interval: self.interval,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn invariant_interval_is_the_fixed_interval() {
        // Maps x -> 0.5 x and x -> 0.5 x + 0.5: the attractor is [0, 1].
        let (lo, hi) = invariant_interval([(0.5, 0.0, 0.0), (0.5, 0.5, 0.5)].into_iter());
        assert!(lo.abs() < 1e-4 && (hi - 1.0).abs() < 1e-4, "{lo} {hi}");
        // x -> 0.2 x + 0.3 alone: the fixed point 0.375.
        let (lo, hi) = invariant_interval([(0.2, 0.3, 0.3)].into_iter());
        assert!(
            (lo - 0.375).abs() < 1e-4 && (hi - 0.375).abs() < 1e-4,
            "{lo} {hi}"
        );
        // A negative contrast flips the interval: x -> -0.5 x + 0.75 has the fixed point 0.5.
        let (lo, hi) = invariant_interval([(-0.5, 0.75, 0.75)].into_iter());
        assert!(
            (lo - 0.5).abs() < 1e-4 && (hi - 0.5).abs() < 1e-4,
            "{lo} {hi}"
        );
    }

    #[test]
    fn affine_form_agrees_with_the_isometry_definition() {
        use crate::transform::isometry;
        for k in 0..8u8 {
            let r = RangeMap {
                x: 8,
                y: 4,
                size: 4,
                domain_x: 2,
                domain_y: 6,
                isometry: k,
                contrast: 0.5,
                offset: 0.1,
                slope: [0.2, -0.1],
            };
            let c = AffineCell::of(&r);
            assert_eq!(std::mem::size_of::<AffineCell>(), 32);
            // g at the range centre is the offset; at the right edge it has risen by 0.1.
            assert!((c.offset + c.gx * 10.0 + c.gy * 6.0 - 0.1).abs() < 1e-6);
            assert!((c.offset + c.gx * 12.0 + c.gy * 6.0 - 0.2).abs() < 1e-6);
            for &(px, py) in &[(8.0f32, 4.0f32), (9.3, 7.9), (11.99, 5.5)] {
                let (a, b) = isometry(k, (px - 8.0) / 4.0, (py - 4.0) / 4.0);
                let want = (2.0 + 8.0 * a, 6.0 + 8.0 * b);
                let [gx, gy] = c.phi([px, py]);
                let got = (gx, gy);
                assert!(
                    (want.0 - got.0).abs() < 1e-4 && (want.1 - got.1).abs() < 1e-4,
                    "{k}: {want:?} {got:?}"
                );
            }
        }
    }

    #[test]
    fn a_flattened_quadtree_decodes_like_the_operator() {
        use crate::pieces::Flatten;
        // Four ranges of 8 in a 16 x 16 frame, each mapped from a domain with its own isometry.
        let ranges: Vec<RangeMap> = (0..4u32)
            .map(|k| RangeMap {
                x: (k % 2) * 8,
                y: (k / 2) * 8,
                size: 8,
                domain_x: 0,
                domain_y: 0,
                isometry: (k * 3 % 8) as u8,
                contrast: 0.6 - 0.3 * k as f32,
                offset: 0.2 + 0.1 * k as f32,
                slope: [0.05 * k as f32, -0.02],
            })
            .collect();
        let op = QuadtreeOperator::new([16, 16], [15.0, 13.0], 8, ranges).unwrap();
        let t = op.pieces();
        for i in 0..500 {
            let p = [(i as f32 * 0.37).fract(), (i as f32 * 0.731).fract()];
            let (a, b) = (
                crate::decode::point(&op, p, 15),
                crate::decode::point(&t, p, 15),
            );
            assert!(
                (a.value - b.value).abs() < 1e-5,
                "{p:?}: {} {}",
                a.value,
                b.value
            );
        }
    }

    #[test]
    fn ranges_must_tile_the_frame() {
        let r = |x, y, size| RangeMap {
            x,
            y,
            size,
            domain_x: 0,
            domain_y: 0,
            isometry: 0,
            contrast: 0.0,
            offset: 0.5,
            slope: [0.0; 2],
        };
        assert!(QuadtreeOperator::new([8, 8], [8.0, 8.0], 4, vec![r(0, 0, 8)]).is_ok());
        assert!(QuadtreeOperator::new([8, 8], [8.0, 8.0], 4, vec![r(0, 0, 4)]).is_err());
        assert!(
            QuadtreeOperator::new([8, 8], [8.0, 8.0], 4, vec![r(0, 0, 8), r(4, 4, 4)]).is_err()
        );
        assert!(QuadtreeOperator::new([8, 8], [8.0, 8.0], 4, vec![r(4, 4, 8)]).is_err());
    }
}
