//! The quadtree IFS as an operator: ranges that tile the frame, each with its map, found by a
//! separable lookup ([`AxisAligned`]) and flattened for the GPU ([`crate::core::pieces::Flatten`]).

use crate::core::format::FormatError;
use crate::core::operator::{
    AffineCell, AxisAligned, AxisCell, Chain, ISOMETRY_MATRICES, Operator, Step, invariant_interval,
};

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

    /// The range's map in the form the decoders evaluate.
    pub fn affine(&self) -> AffineCell {
        let r = self;
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
    ) -> Result<Self, FormatError> {
        if cell == 0
            || !frame[0].is_multiple_of(cell)
            || !frame[1].is_multiple_of(cell)
            || frame[0] == 0
            || frame[1] == 0
        {
            return Err(FormatError::stream(format!(
                "frame {frame:?} is not a multiple of the cell size {cell}"
            )));
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
                return Err(FormatError::stream(format!(
                    "range {i} ({r:?}) does not fit the frame {frame:?}"
                )));
            }
            let (c0, r0, n) = (
                (r.x / cell) as usize,
                (r.y / cell) as usize,
                (r.size / cell) as usize,
            );
            for row in r0..r0 + n {
                for slot in &mut lut[row * cols + c0..row * cols + c0 + n] {
                    if *slot != u32::MAX {
                        return Err(FormatError::stream(format!(
                            "range {i} overlaps another range"
                        )));
                    }
                    *slot = i as u32;
                }
            }
        }
        if lut.contains(&u32::MAX) {
            return Err(FormatError::stream(
                "the ranges leave part of the frame uncovered",
            ));
        }
        let interval = invariant_interval(ranges.iter().map(|r| {
            let (lo, hi) = r.offset_range();
            (r.contrast, lo, hi)
        }));
        let cells: Vec<AffineCell> = ranges.iter().map(RangeMap::affine).collect();
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
            None => crate::core::operator::run_chains_stepwise(self, chains, iterations, tolerance),
        }
    }
}

/// `t` truncated towards zero; NaN and values out of the `i32` range give some value that
/// the caller clamps. (One instruction on x86-64, where `as i32` adds fix-ups for those.)
#[inline(always)]
pub(crate) fn truncate(t: f32) -> i32 {
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
                    if taken[l] >= iterations
                        || !crate::core::operator::active(acc_s[l], half, tolerance)
                    {
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

impl crate::core::pieces::Flatten for QuadtreeOperator {
    /// One piece per range, looked up through the range map at the smallest range size.
    fn pieces(&self) -> crate::core::pieces::PieceTable {
        let pieces = self
            .ranges
            .iter()
            .zip(&self.cells)
            .map(|(r, c)| {
                let (x, y, n) = (r.x as f32, r.y as f32, r.size as f32);
                let [ax, bx, ay, by] = ISOMETRY_MATRICES[c.isometry as usize & 7];
                crate::core::pieces::Piece {
                    origin: [x, y],
                    inv_size: [1.0 / n; 2],
                    g: [c.offset + c.gx * x + c.gy * y, c.gx * n, c.gy * n, 0.0],
                    s: [c.contrast, 0.0, 0.0, 0.0],
                    next_x: [ax * x + bx * y + c.cx, ax * n, bx * n, 0.0],
                    next_y: [ay * x + by * y + c.cy, ay * n, by * n, 0.0],
                }
            })
            .collect();
        crate::core::pieces::PieceTable {
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
    fn affine_form_agrees_with_the_isometry_definition() {
        use crate::core::transform::isometry;
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
            let c = r.affine();
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
        use crate::core::pieces::Flatten;
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
                crate::core::decode::point(&op, p, 15),
                crate::core::decode::point(&t, p, 15),
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
