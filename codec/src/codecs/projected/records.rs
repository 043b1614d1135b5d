//! The continuation's records (g at the nine half-lattice points of a cell) and residual
//! bounds for any window of cells, and what an operator built lazily keeps.
//!
//! Why windows: an operator of a chunk of a chunked asset that kept a record and a residual
//! bound a cell (40 bytes) would make a 37 Mpx asset 2 GB of operators, so a server could keep
//! a few of its chunks and rebuilt one for nearly every random tile (records 80 ms and a
//! per-cell fixpoint 140 ms a 1024^2 chunk, on one core, against 5-7 ms for the tile itself).
//! A lazily built operator keeps its samples and a residual bound a cell coded in a byte (5
//! bytes a cell), the bounds made a block at a time when first read ([`super::residual`]); a
//! request builds the records of the cells under it and drops them after. A chain never
//! leaves the even-aligned 2 x 2 block of cells it starts in (each such block maps onto
//! itself), so a window needs a margin of two cells whatever the steps. Records are computed
//! with the whole grid's edge clamping, so a window's records are the whole operator's bit
//! for bit, and a chain outside its window (a caller's far-flung points) reads records
//! evaluated directly: the same bits again, slower.

use std::sync::Arc;

use super::operator::{ProjectedOperator, Region, block, catmull_rom};

/// Rows of cells a task of the passes over many cells takes (records, or their excesses).
pub(super) const BAND: usize = 32;

/// A Catmull-Rom interpolant (edges replicated) on its half lattice over a rectangle of
/// samples: at the samples, halfway between two along either axis, and at cell centres, by
/// separable 4-tap passes whose products and sums are those of the tensor-product evaluation
/// at those points (the weights at 0 and 1 select one sample exactly), so the values are the
/// same bits. Taps past the rectangle read the grid's own samples (clamped at the grid's
/// edges, not the rectangle's), so a rectangle's values are the whole lattice's.
pub(super) struct HalfLattice {
    /// Samples of the whole grid along each axis.
    n: [usize; 2],
    /// The rectangle's first sample.
    origin: [usize; 2],
    /// Half-lattice points a row of `values`.
    width: usize,
    /// At half-lattice point (2 origin + (x, y)), index `y width + x`: the interpolant at
    /// (origin + (x, y) / 2) in sample coordinates.
    values: Vec<f32>,
}

impl HalfLattice {
    /// The half lattice over samples `[x0, x1] x [y0, y1]` (inclusive, inside the grid) of the
    /// grid of `n` samples whose sample (x, y) is `get(x, y)`.
    pub(super) fn over(
        n: [usize; 2],
        [x0, y0, x1, y1]: [usize; 4],
        get: impl Fn(usize, usize) -> f32,
    ) -> HalfLattice {
        let weights = catmull_rom(0.5);
        let [w, h] = n;
        let clamp = |t: usize, a: usize, last: usize| (t + a).saturating_sub(1).min(last);
        // Halfway along x on the rows the rectangle's cell centres tap (defined left of the
        // last column, as the lattice is).
        let (r0, r1) = (y0.saturating_sub(1), (y1 + 2).min(h - 1));
        let cols = x1 - x0 + 1;
        let mut across = vec![0.0f32; cols * (r1 - r0 + 1)];
        for y in r0..=r1 {
            for x in x0..=x1.min(w.saturating_sub(2)) {
                let mut r = 0.0;
                for (a, wa) in weights.iter().enumerate() {
                    r += wa * get(clamp(x, a, w - 1), y);
                }
                across[(y - r0) * cols + x - x0] = r;
            }
        }
        let width = 2 * (x1 - x0) + 1;
        let mut values = vec![0.0f32; width * (2 * (y1 - y0) + 1)];
        for y in y0..=y1 {
            for x in x0..=x1 {
                let at = 2 * (y - y0) * width + 2 * (x - x0);
                values[at] = get(x, y);
                if x < x1 {
                    values[at + 1] = across[(y - r0) * cols + x - x0];
                }
                if y < y1 {
                    let mut r = 0.0;
                    for (b, wb) in weights.iter().enumerate() {
                        r += wb * get(x, clamp(y, b, h - 1));
                    }
                    values[at + width] = r;
                    if x < x1 {
                        let mut r = 0.0;
                        for (b, wb) in weights.iter().enumerate() {
                            r += wb * across[(clamp(y, b, h - 1) - r0) * cols + x - x0];
                        }
                        values[at + width + 1] = r;
                    }
                }
            }
        }
        HalfLattice {
            n,
            origin: [x0, y0],
            width,
            values,
        }
    }
}

impl ProjectedOperator {
    /// The records of the cells `[i0, i1) x [j0, j1)` into `out`, row-major.
    pub(super) fn records_into(&self, [i0, j0, i1, j1]: [usize; 4], out: &mut [[f32; 9]]) {
        let [nx, ny] = self.size;
        let z = &self.z;
        let fine = HalfLattice::over(self.size, [i0, j0, i1, j1], |x, y| z[y * nx + x]);
        // phi of the cells' half-lattice points lies within two samples of them; the even
        // lattice has a sample every two.
        let (ex, ey) = ((nx - 1) / 2 + 1, (ny - 1) / 2 + 1);
        let even = [
            (i0 / 2).saturating_sub(2),
            (j0 / 2).saturating_sub(2),
            (i1 / 2 + 2).min(ex - 1),
            (j1 / 2 + 2).min(ey - 1),
        ];
        let coarse = HalfLattice::over([ex, ey], even, |x, y| z[2 * y * nx + 2 * x]);
        // Every record is `fine - rho coarse` at points inside both rectangles (at a sample,
        // the sample less rho times the sample at phi: the even lattice's sample there, the
        // same bits as `Self::half_point`); only the even lattice clamps, at its last sample.
        let top = 2 * (coarse.n[0] - 1);
        let bottom = 2 * (coarse.n[1] - 1);
        let mut cells = out.iter_mut();
        for j in j0..j1 {
            let cy = block(j, ny);
            let fine_rows: [usize; 3] = std::array::from_fn(|b| (2 * (j - j0) + b) * fine.width);
            let coarse_rows: [usize; 3] = std::array::from_fn(|b| {
                ((2 * j + b - cy).min(bottom) - 2 * coarse.origin[1]) * coarse.width
            });
            for i in i0..i1 {
                let cx = block(i, nx);
                let fine_cols: [usize; 3] = std::array::from_fn(|a| 2 * (i - i0) + a);
                let coarse_cols: [usize; 3] =
                    std::array::from_fn(|a| (2 * i + a - cx).min(top) - 2 * coarse.origin[0]);
                let cell = cells.next().expect("a record a cell");
                *cell = std::array::from_fn(|n| {
                    let (a, b) = (n % 3, n / 3);
                    fine.values[fine_rows[b] + fine_cols[a]]
                        - self.rho * coarse.values[coarse_rows[b] + coarse_cols[a]]
                });
            }
        }
    }

    /// Every cell's records.
    pub(super) fn all_records(&self) -> Vec<[f32; 9]> {
        let [nx, ny] = self.size;
        self.records_for([0, 0, nx - 1, ny - 1])
    }

    /// The records of the cells `[i0, i1) x [j0, j1)`, row-major, by bands of rows on all
    /// cores.
    pub(super) fn records_for(&self, [i0, j0, i1, j1]: [usize; 4]) -> Vec<[f32; 9]> {
        use rayon::prelude::*;
        // Into their place, by bands (a collect of unknown length would grow its vector,
        // twice the records' bytes at a time: measured, 70 MB more on a chunked encode).
        let w = i1 - i0;
        let mut out = vec![[0.0; 9]; w * (j1 - j0)];
        out.par_chunks_mut(BAND * w)
            .enumerate()
            .for_each(|(b, band)| {
                let j = j0 + b * BAND;
                self.records_into([i0, j, i1, (j + BAND).min(j1)], band);
            });
        out
    }

    /// D_c of [`Self::residual_bounds`]: the largest |g + rho S o phi - S| over cell (i, j),
    /// at its nine half-lattice points (`rec`: its records), plus the f32 rounding of the
    /// records, the blend and the chain's sums (a few ulps of the range).
    pub(super) fn excess(&self, (i, j): (usize, usize), rec: &[f32; 9]) -> f32 {
        let (cx, cy) = (
            block(i, self.size[0]) as isize,
            block(j, self.size[1]) as isize,
        );
        // The cell's corners (inside the grid: a cell's far corner is a sample), loaded once;
        // the sums below are those of each half-lattice point's four samples in the same
        // order, so the same bits as summing clamped loads (what this did, 2.3 times slower).
        let nx = self.size[0];
        let (top, bottom) = (
            &self.z[j * nx + i..j * nx + i + 2],
            &self.z[(j + 1) * nx + i..],
        );
        let corner = |dx: usize, dy: usize| if dy == 0 { top[dx] } else { bottom[dx] };
        let mut m = 0.0f32;
        for b in 0..3usize {
            let (y0, y1) = (b / 2, b.div_ceil(2));
            for a in 0..3usize {
                // S at the half-lattice point: the mean of the samples around it.
                let (x0, x1) = (a / 2, a.div_ceil(2));
                let here =
                    0.25 * (corner(x0, y0) + corner(x1, y0) + corner(x0, y1) + corner(x1, y1));
                // phi of a half-lattice point is a sample: 2 (i + a/2) - c.
                let (px, py) = (
                    2 * i as isize + a as isize - cx,
                    2 * j as isize + b as isize - cy,
                );
                m = m.max((rec[3 * b + a] + self.rho * self.at(px, py) - here).abs());
            }
        }
        m + 1e-5
    }

    /// The records and residual bounds ([`Self::residual_bounds`]) of the cells `[i0, i1) x
    /// [j0, j1)` (inside the grid), row-major: the same bits as those of the operator built
    /// whole. A bound reads the excesses of the block phi maps its cell onto, within two
    /// cells before it and one after, so those cells' records are made too. On the calling
    /// thread alone: it makes a lazily built operator's blocks of bounds, each under a lock
    /// that a rayon worker of another request may wait on, and a worker that stole work here
    /// could wait on the very block it is making.
    pub(super) fn bounds_for(&self, [i0, j0, i1, j1]: [usize; 4]) -> (Vec<[f32; 9]>, Vec<f32>) {
        let [nx, ny] = self.size;
        let (e0, f0) = (i0.saturating_sub(2), j0.saturating_sub(2));
        let (e1, f1) = ((i1 + 1).min(nx - 1), (j1 + 1).min(ny - 1));
        let ew = e1 - e0;
        let mut records = vec![[0.0f32; 9]; ew * (f1 - f0)];
        self.records_into([e0, f0, e1, f1], &mut records);
        let d: Vec<f32> = records
            .iter()
            .enumerate()
            .map(|(k, rec)| self.excess((e0 + k % ew, f0 + k / ew), rec))
            .collect();
        let (w, h) = (i1 - i0, j1 - j0);
        let local = |i: usize, j: usize| (j - f0) * ew + i - e0;
        let mut out = Vec::with_capacity(w * h);
        for j in j0..j1 {
            out.extend_from_slice(&records[local(i0, j)..local(i0, j) + w]);
        }
        let bound = |k: usize| {
            let (i, j) = (i0 + k % w, j0 + k / w);
            let here = d[local(i, j)];
            if self.rho >= 1.0 {
                return f32::INFINITY;
            }
            // Axes of fewer than four samples have rho 0 (no pair of cells for phi): R = D.
            if self.rho == 0.0 {
                return here;
            }
            // The block phi maps the cell onto: cells 2 i - c and 2 i - c + 1 along each axis.
            let q = local(2 * i - block(i, nx), 2 * j - block(j, ny));
            let most = d[q].max(d[q + 1]).max(d[q + ew]).max(d[q + ew + 1]);
            here + self.rho * most / (1.0 - self.rho)
        };
        let residual = (0..w * h).map(bound).collect();
        (out, residual)
    }

    /// The operator with the records and residual bounds of the cells `[i0, i1) x [j0, j1)`
    /// (clamped into the grid) at hand, for answers there: of a lazily built operator, a
    /// window; of one built whole, itself.
    pub fn window(&self, [i0, j0, i1, j1]: [usize; 4]) -> std::borrow::Cow<'_, ProjectedOperator> {
        if !self.is_lazy() {
            return std::borrow::Cow::Borrowed(self);
        }
        let [nx, ny] = self.size;
        // Even starts keep each cell's records those of the whole (they are anyway, but the
        // even lattice's rectangle then starts on a sample of it).
        let (i0, j0) = (i0.min(nx - 2) & !1, j0.min(ny - 2) & !1);
        let (i1, j1) = (i1.clamp(i0 + 1, nx - 1), j1.clamp(j0 + 1, ny - 1));
        std::borrow::Cow::Owned(self.with_region([i0, j0, i1, j1]))
    }

    /// The operator with the records and residual bounds of the cells `[i0, i1) x [j0, j1)`
    /// (inside the grid) at hand: a lazily built operator's bounds as coded, else evaluated.
    pub(super) fn with_region(&self, [i0, j0, i1, j1]: [usize; 4]) -> ProjectedOperator {
        let (records, residual) = match &self.bounds {
            Some(b) => {
                // A request's window in one pass, not by bands: each band's half lattices read
                // rows past it (10% more time on a tile's window). All rows (a lattice for a
                // device) by bands, on every core.
                let records = if j1 - j0 + 1 < self.size[1] {
                    let mut records = vec![[0.0; 9]; (i1 - i0) * (j1 - j0)];
                    self.records_into([i0, j0, i1, j1], &mut records);
                    records
                } else {
                    self.records_for([i0, j0, i1, j1])
                };
                let make = |rect| self.bounds_for(rect).1;
                (records, b.rect_bounds(&make, [i0, j0, i1, j1]))
            }
            None => self.bounds_for([i0, j0, i1, j1]),
        };
        let residual_max = residual.iter().fold(0.0, |m: f32, &r| m.max(r));
        ProjectedOperator {
            records,
            residual,
            residual_max,
            region: Region {
                origin: [i0, j0],
                size: [i1 - i0, j1 - j0],
            },
            z: Arc::clone(&self.z),
            bounds: self.bounds.clone(),
            ..*self
        }
    }
}

/// Cells a window reaches past the cells of its points: a chain never leaves the even-aligned
/// 2 x 2 block of cells it starts in (each maps onto itself), but for the unpaired last cell of
/// an even axis, which maps onto the two before it.
const MARGIN: usize = 2;

impl ProjectedOperator {
    /// Whether answers need a window first: a lazily built operator, not yet a window.
    pub(super) fn needs_window(&self) -> bool {
        self.is_lazy() && self.records.is_empty()
    }

    /// The window for answers at frame points within `[x0, y0, x1, y1]` (see [`Self::window`]).
    pub(super) fn window_over(
        &self,
        [x0, y0, x1, y1]: [f32; 4],
    ) -> std::borrow::Cow<'_, ProjectedOperator> {
        let m = MARGIN;
        // A NaN or infinite corner saturates to the grid's edge.
        let cell = |t: f32, n: usize| ((t - 0.5).max(0.0) as usize).min(n - 2);
        let (i0, j0) = (cell(x0, self.size[0]), cell(y0, self.size[1]));
        let (i1, j1) = (cell(x1, self.size[0]), cell(y1, self.size[1]));
        self.window([
            i0.saturating_sub(m),
            j0.saturating_sub(m),
            i1.saturating_add(m + 1),
            j1.saturating_add(m + 1),
        ])
    }

    /// Continuous decoding of unit points ([`crate::core::decode::points`]), through a window
    /// of a lazily built operator when the points are near enough together for one to pay
    /// (its cells under 64 a point); far-flung points are answered by the operator itself.
    pub fn points(
        &self,
        pts: &[[f32; 2]],
        iterations: u32,
        tolerance: f32,
    ) -> Vec<crate::core::decode::PointValue> {
        use crate::core::operator::Operator;
        if self.needs_window() && !pts.is_empty() {
            let v = self.valid();
            let mut b = [
                f32::INFINITY,
                f32::INFINITY,
                f32::NEG_INFINITY,
                f32::NEG_INFINITY,
            ];
            for p in pts {
                b = [
                    b[0].min(p[0] * v[0]),
                    b[1].min(p[1] * v[1]),
                    b[2].max(p[0] * v[0]),
                    b[3].max(p[1] * v[1]),
                ];
            }
            let m = 2.0 * MARGIN as f32 + 1.0;
            let cells = (b[2] - b[0] + m) * (b[3] - b[1] + m);
            if cells <= 64.0 * pts.len() as f32 {
                let w = self.window_over(b);
                return crate::core::decode::points(&*w, pts, iterations, tolerance);
            }
        }
        crate::core::decode::points(self, pts, iterations, tolerance)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codecs::projected::tests::{grid as rough, header};
    use crate::core::decode;
    use crate::core::operator::Operator;

    // (150, 70): cells in blocks of 64, six of them.
    const SIZES: [(usize, usize); 7] = [
        (33, 20),
        (16, 9),
        (64, 41),
        (4, 4),
        (5, 6),
        (2, 5),
        (150, 70),
    ];

    fn operators(w: usize, h: usize) -> (ProjectedOperator, ProjectedOperator) {
        let g = rough(w, h);
        let hd = header(w, h, &g);
        (
            ProjectedOperator::new(&hd, &g).expect("whole"),
            ProjectedOperator::lazy(&hd, g.clone()).expect("lazy"),
        )
    }

    #[test]
    fn windows_hold_the_whole_operators_records_and_bounds_no_tighter() {
        // A cell's coded bound: no tighter than the whole operator's, at most 2^(1/8) over it
        // (or down to the smallest code).
        let close = |coded: f32, exact: f32, largest: f32, at: &str| {
            assert!(coded >= exact, "{at}: {coded} under {exact}");
            assert!(
                coded <= exact * 1.0906 + 1e-9 * largest,
                "{at}: {coded} over {exact}"
            );
        };
        for (w, h) in SIZES {
            let (whole, lazy) = operators(w, h);
            assert!(lazy.needs_window());
            // Samples and a byte a cell against 44 bytes.
            let (a, b) = (lazy.resident_bytes(), whole.resident_bytes());
            assert!(a < b / 5 || w * h < 500, "{w}x{h}: {a} against {b} bytes");
            let (cx, cy) = (w - 1, h - 1);
            // Cells outside any window, read one by one (their blocks made as they come).
            for j in 0..cy {
                for i in 0..cx {
                    let (coded, exact) = (lazy.residual_of(i, j), whole.residual[j * cx + i]);
                    close(
                        coded,
                        exact,
                        whole.residual_max,
                        &format!("{w}x{h} ({i}, {j})"),
                    );
                }
            }
            for rect in [
                [0, 0, 2, 2],
                [3, 1, 9, 7],
                [cx.saturating_sub(3), cy.saturating_sub(3), cx, cy],
                [1, 1, cx - 1, cy - 1],
                [0, 0, usize::MAX, usize::MAX],
            ] {
                let win = lazy.window(rect);
                assert!(!win.needs_window(), "{w}x{h} {rect:?}");
                let r = win.region;
                assert!(r.size[0] > 0 && r.size[1] > 0);
                for y in 0..r.size[1] {
                    for x in 0..r.size[0] {
                        let (i, j) = (r.origin[0] + x, r.origin[1] + y);
                        let (k, kw) = (y * r.size[0] + x, j * cx + i);
                        let bits = |rec: &[f32; 9]| rec.map(f32::to_bits);
                        assert_eq!(bits(&win.records[k]), bits(&whole.records[kw]));
                        let (coded, exact) = (win.residual[k], whole.residual[kw]);
                        close(
                            coded,
                            exact,
                            whole.residual_max,
                            &format!("{w}x{h} ({i}, {j})"),
                        );
                        assert_eq!(coded, lazy.residual_of(i, j));
                    }
                }
            }
        }
    }

    /// A chain never leaves the 2 x 2 block of cells it starts in, but for the unpaired last
    /// cell of an even axis, which maps onto the pair before it (and its own last sample onto
    /// itself): what lets a window's margin be [`MARGIN`] cells, whatever the steps.
    #[test]
    fn chains_stay_within_two_cells_of_their_start() {
        for (w, h) in SIZES {
            let (whole, _) = operators(w, h);
            if whole.rho == 0.0 {
                continue;
            }
            // The cells a chain from cell i may visit along an axis of n samples.
            let allowed = |i: usize, n: usize, at: usize| {
                let pair = if i + 2 < n || i % 2 == 1 {
                    i & !1
                } else {
                    i - 2
                };
                at == i || at / 2 == pair / 2
            };
            for k in 0..2000 {
                let mut p = [
                    (k as f32 * 0.618_034).fract() * (w as f32 + 0.2) - 0.1,
                    (k as f32 * 0.414_214).fract() * (h as f32 + 0.2) - 0.1,
                ];
                let (i0, _) = whole.locate(p[0], w);
                let (j0, _) = whole.locate(p[1], h);
                for step in 0..40 {
                    p = whole.step(p).next;
                    let (i, _) = whole.locate(p[0], w);
                    let (j, _) = whole.locate(p[1], h);
                    assert!(
                        allowed(i0, w, i) && allowed(j0, h, j),
                        "{w}x{h} point {k} from ({i0}, {j0}) at ({i}, {j}) after {step} steps"
                    );
                    assert!(i.abs_diff(i0) <= MARGIN && j.abs_diff(j0) <= MARGIN);
                }
            }
        }
    }

    #[test]
    fn lazy_operators_answer_as_whole_ones() {
        for (w, h) in SIZES {
            let (whole, lazy) = operators(w, h);
            let probe: Vec<[f32; 2]> = (0..997)
                .map(|i| {
                    [
                        (i as f32 * 0.618_034).fract(),
                        (i as f32 * 0.414_214).fract(),
                    ]
                })
                .collect();
            // Fixed steps: the same chains, so the same values to rounding; bounds no tighter.
            let a = lazy.points(&probe, 9, 0.0);
            let b = decode::points(&whole, &probe, 9, 0.0);
            for (x, y) in a.iter().zip(&b) {
                assert!((x.value - y.value).abs() <= 1e-5, "{w}x{h}: {x:?} {y:?}");
                assert!(x.error_bound >= y.error_bound, "{w}x{h}: {x:?} {y:?}");
            }
            // To a tolerance: within the sum of the bounds.
            let a = lazy.points(&probe, 400, 1e-3);
            let b = decode::points(&whole, &probe, 400, 1e-3);
            for (x, y) in a.iter().zip(&b) {
                assert!((x.value - y.value).abs() <= x.error_bound + y.error_bound);
            }
            // A grid, through a window: as the whole operator's grid at fixed steps.
            let xs: Vec<f32> = (0..40)
                .map(|i| (i as f32 + 0.3) / 40.0 * 0.6 + 0.2)
                .collect();
            let ys: Vec<f32> = (0..30).map(|i| (i as f32 + 0.7) / 30.0 * 0.5).collect();
            let a = lazy.grid(&xs, &ys, 9, 0.0);
            let b = whole.grid(&xs, &ys, 9, 0.0);
            for (x, y) in a.iter().zip(&b) {
                assert!((x.value - y.value).abs() <= 1e-5, "{w}x{h}: {x:?} {y:?}");
            }
        }
    }
}
