//! The continuation kept in the neighbourhood of the data: every continuous answer of a projected
//! plane is clamped into the range of the decoded samples of its cell's 4 x 4 neighbourhood
//! (the samples the cubic part of the continuation reads).
//!
//! Why: the continuation adds the details of every coarser octave scaled by rho, octave after
//! octave. With rho near its ceiling (0.9, a rough DEM) those sums can climb far past the
//! samples around them: on a global 4,320 x 2,160 DEM a point between four Karakoram samples of
//! at most 7,800 m decoded at 9,650 m. No terrain between samples lies outside the samples'
//! range by more than the coded error, and the source's bilinear value between them (what the
//! error bound is against) lies within the range of its cell's four corners: so the clamp
//! never moves an answer away from it by more than the samples' own error, and the reported
//! bound (the samples' error plus convergence, never less than the former) still holds. The
//! clamp is 1-Lipschitz, so a convergence bound on the chain is one on the clamped answer too.
//!
//! Applied after decoding, by [`crate::io::asset::PlaneOperator::limit_points`] and
//! [`crate::io::asset::PlaneOperator::limit_grid`], so that the CPU's chains and a device's
//! answers get the same clamp and stay equal.

use crate::core::decode::{position_quantum, to_frame};
use crate::core::operator::Operator;

use super::ProjectedOperator;

/// The empty range, which folds start from.
const EMPTY: (f32, f32) = (f32::INFINITY, f32::NEG_INFINITY);

impl ProjectedOperator {
    /// The cell along `axis` of unit coordinate `t`, located as the chains locate their start.
    #[inline]
    fn start_cell(&self, t: f32, axis: usize, quantum: f32) -> usize {
        let n = self.size[axis];
        self.locate(to_frame(t, self.valid()[axis], quantum), n).0
    }

    /// The samples' range over rows `j - 1 ..= j + 2` and columns `i - 1 ..= i + 2` (clamped
    /// into the grid), normalised.
    pub fn neighbourhood(&self, i: usize, j: usize) -> (f32, f32) {
        let [nx, ny] = self.size;
        let (x0, x1) = (i.saturating_sub(1), (i + 2).min(nx - 1));
        let (y0, y1) = (j.saturating_sub(1), (j + 2).min(ny - 1));
        let mut range = EMPTY;
        for y in y0..=y1 {
            for &v in &self.z[y * nx + x0..=y * nx + x1] {
                range = (range.0.min(v), range.1.max(v));
            }
        }
        range
    }

    /// Clamps `values[k]`, the answer at unit point `pts[k]`, into its neighbourhood's range.
    /// A value within its cell's four corners is within the 16 too: those four are read first,
    /// and the 16 only for a value outside them.
    pub fn limit_points(&self, pts: &[[f32; 2]], values: &mut [f32]) {
        let quantum = position_quantum(&self.frame());
        let nx = self.size[0];
        for (p, v) in pts.iter().zip(values.iter_mut()) {
            let (i, j) = (
                self.start_cell(p[0], 0, quantum),
                self.start_cell(p[1], 1, quantum),
            );
            let (a, b) = (
                &self.z[j * nx + i..j * nx + i + 2],
                &self.z[(j + 1) * nx + i..],
            );
            let corners = [a[0], a[1], b[0], b[1]];
            let inside = corners.iter().any(|&c| c <= *v) && corners.iter().any(|&c| c >= *v);
            if !inside && !v.is_nan() {
                let (lo, hi) = self.neighbourhood(i, j);
                *v = v.clamp(lo, hi);
            }
        }
    }

    /// [`Self::limit_points`] on the separable grid `(xs[i], ys[j])`, row-major. Per row of
    /// cells (computed once for every output row in it): the samples' range down each column
    /// of the span the grid's columns need, then across each run of four columns, in low and
    /// high arrays of their own, with comparisons rather than `f32::min` (whose NaN rules cost
    /// instructions: the samples are finite); a pixel then reads its cell's pair. A fold of
    /// (low, high) pairs per pixel cost a quarter of a tile's time at one cell a pixel.
    pub fn limit_grid(&self, xs: &[f32], ys: &[f32], values: &mut [f32]) {
        if xs.is_empty() || ys.is_empty() {
            return;
        }
        let [nx, ny] = self.size;
        let quantum = position_quantum(&self.frame());
        let cols: Vec<usize> = xs.iter().map(|&x| self.start_cell(x, 0, quantum)).collect();
        // Sample columns [first, last] hold every pixel's four.
        let first = cols.iter().min().map_or(0, |&c| c.saturating_sub(1));
        let last = cols.iter().max().map_or(0, |&c| (c + 2).min(nx - 1));
        let span = last - first + 1;
        let (mut down_lo, mut down_hi) = (vec![0.0f32; span], vec![0.0f32; span]);
        // Per cell column of the span (cell `first + k`).
        let (mut lo, mut hi) = (vec![0.0f32; span], vec![0.0f32; span]);
        let mut row_cell = usize::MAX;
        for (r, &y) in ys.iter().enumerate() {
            let j = self.start_cell(y, 1, quantum);
            if j != row_cell {
                row_cell = j;
                let (y0, y1) = (j.saturating_sub(1), (j + 2).min(ny - 1));
                let row = |y: usize| &self.z[y * nx + first..y * nx + first + span];
                down_lo.copy_from_slice(row(y0));
                down_hi.copy_from_slice(row(y0));
                for yy in y0 + 1..=y1 {
                    for ((l, h), &v) in down_lo.iter_mut().zip(down_hi.iter_mut()).zip(row(yy)) {
                        *l = least(*l, v);
                        *h = most(*h, v);
                    }
                }
                across(&down_lo, &mut lo, first, nx, least);
                across(&down_hi, &mut hi, first, nx, most);
            }
            let row = &mut values[r * xs.len()..(r + 1) * xs.len()];
            for (v, &c) in row.iter_mut().zip(&cols) {
                let (l, h) = (lo[c - first], hi[c - first]);
                // NaN (no value) stays NaN: neither comparison holds.
                *v = if *v < l {
                    l
                } else if *v > h {
                    h
                } else {
                    *v
                };
            }
        }
    }
}

impl ProjectedOperator {
    /// Per cell between samples (row-major, `(w - 1) x (h - 1)`), a proven bound on |answer -
    /// source| anywhere in the cell, in source units: what a point or a pixel there answers
    /// after the clamp, against the source's bilinear interpolant of the cell's four samples.
    /// `source` holds the source samples (row-major, this operator's size), `valid` which of
    /// them hold data (a cell with a corner without is bounded by 0: nothing is answered
    /// there), and `(lo, span)` maps normalised values back to source units.
    ///
    /// Two bounds, the smaller kept. With e the cell's largest |decoded - source| at its four
    /// samples: the continuation f is within R (the cell's residual bound, proven in closed
    /// form, as the chains' bounds are) of S, the bilinear interpolant of the decoded samples,
    /// which is within e of the source's; the clamp moves an answer towards the source's value
    /// or leaves it within e of it (that value lies within e of the four decoded samples, which
    /// the clamp's range holds), so `R + e` bounds the answer. And the clamp alone: the answer
    /// lies in the 16 samples' range and the source's value within its four samples' range, so
    /// their farthest ends bound the distance. The source-error map measured on the half-cell
    /// lattice alone was not a bound between its points (issue 56: 1,647 m off under a bound
    /// of 1,447 m on a global DEM).
    pub fn cell_bounds(
        &self,
        source: &[f32],
        valid: Option<&[bool]>,
        (lo, span): (f32, f32),
    ) -> Vec<f32> {
        let [nx, ny] = self.size;
        if nx < 2 || ny < 2 || source.len() != nx * ny {
            return Vec::new();
        }
        // The f32 rounding of an answer's scaling back to source units.
        let rounding = span.abs() * 2f32.powi(-20);
        let unit = |v: f32| lo + v * span;
        let mut out = vec![0.0f32; (nx - 1) * (ny - 1)];
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let corners = [
                    j * nx + i,
                    j * nx + i + 1,
                    (j + 1) * nx + i,
                    (j + 1) * nx + i + 1,
                ];
                if valid.is_some_and(|v| corners.iter().any(|&k| !v[k])) {
                    continue;
                }
                let (mut e, mut s_lo, mut s_hi) = (0.0f32, f32::INFINITY, f32::NEG_INFINITY);
                for &k in &corners {
                    e = e.max((unit(self.z[k]) - source[k]).abs());
                    s_lo = s_lo.min(source[k]);
                    s_hi = s_hi.max(source[k]);
                }
                let residual = self.residual_of(i, j) * span.abs() + e;
                let (c_lo, c_hi) = self.neighbourhood(i, j);
                let clamp = (unit(c_hi) - s_lo).max(s_hi - unit(c_lo));
                let b = residual.min(clamp);
                // NaN (a source sample that is not a number marked valid): no bound.
                out[j * (nx - 1) + i] = if b.is_nan() {
                    f32::INFINITY
                } else {
                    b + rounding
                };
            }
        }
        out
    }
}

/// The smaller of two finite values (one comparison).
#[inline(always)]
fn least(a: f32, b: f32) -> f32 {
    if b < a { b } else { a }
}

/// The larger of two finite values (one comparison).
#[inline(always)]
fn most(a: f32, b: f32) -> f32 {
    if b > a { b } else { a }
}

/// `out[k]`: `pick` over `column[k - 1 ..= k + 2]` (sample columns `first + k - 1 ..= first +
/// k + 2` of a grid of `nx`, clamped into it and into the span), for cell column `first + k`.
fn across(
    column: &[f32],
    out: &mut [f32],
    first: usize,
    nx: usize,
    pick: impl Fn(f32, f32) -> f32 + Copy,
) {
    let span = column.len();
    let slow = |k: usize| {
        let i = first + k;
        // Past the span's end only for cells no pixel is in (the span holds every needed
        // cell's columns).
        let (a, b) = (
            i.saturating_sub(1).max(first),
            (i + 2).min(nx - 1).min(first + span - 1),
        );
        (a..=b).fold(column[a - first], |m, x| pick(m, column[x - first]))
    };
    // Inside, four columns that are all there; the ends, clamped.
    let inner = 1..span.saturating_sub(2);
    for k in (0..span).filter(|k| !inner.contains(k)) {
        out[k] = slow(k);
    }
    for k in inner {
        out[k] = pick(
            pick(column[k - 1], column[k]),
            pick(column[k + 1], column[k + 2]),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codecs::projected::{ProjectedHeader, pyramid};

    /// A rough grid: a peak of one sample among low ones, rho at its ceiling.
    fn spiky() -> ProjectedOperator {
        let (w, h) = (16usize, 16usize);
        let grid: Vec<f64> = (0..w * h)
            .map(|k| {
                let (x, y) = (k % w, k / w);
                if (x, y) == (8, 8) {
                    1000.0
                } else {
                    ((x * 7919 + y * 104_729) % 97) as f64
                }
            })
            .collect();
        let header = ProjectedHeader {
            samples: [w as u32, h as u32],
            levels: 1,
            step: 1.0,
            growth: 1.0,
            quantum: 1.0,
            value_min: 0.0,
            value_span: 1000.0,
            roughness: 0.9,
            max_error: 0.5,
            order: pyramid::Order::Separable,
        };
        ProjectedOperator::new(&header, &grid).unwrap()
    }

    #[test]
    fn grid_and_points_clamp_alike_into_the_brute_force_range() {
        let op = spiky();
        let xs: Vec<f32> = (0..40).map(|i| (i as f32 + 0.5) / 40.0).collect();
        let ys: Vec<f32> = (0..37).map(|i| (i as f32 + 0.3) / 37.0).collect();
        let pts: Vec<[f32; 2]> = ys
            .iter()
            .flat_map(|&y| xs.iter().map(move |&x| [x, y]))
            .collect();
        // Values far outside any range, of both signs.
        let raw: Vec<f32> = (0..pts.len())
            .map(|k| if k % 2 == 0 { 5.0 } else { -5.0 })
            .collect();
        let (mut a, mut b) = (raw.clone(), raw.clone());
        op.limit_grid(&xs, &ys, &mut a);
        op.limit_points(&pts, &mut b);
        assert_eq!(a, b);
        // Each clamped value is the extreme of the 16 samples around its point, found here by
        // position in samples (centres at k + 0.5), not by the operator's own cell lookup.
        for ((p, v), r) in pts.iter().zip(&a).zip(&raw) {
            let cell = |t: f32| (t * 16.0 - 0.5).floor().clamp(0.0, 14.0) as usize;
            let (i, j) = (cell(p[0]), cell(p[1]));
            let mut range = EMPTY;
            for y in j.saturating_sub(1)..=(j + 2).min(15) {
                for x in i.saturating_sub(1)..=(i + 2).min(15) {
                    let s = op.samples()[y * 16 + x];
                    range = (range.0.min(s), range.1.max(s));
                }
            }
            let want = if *r > 0.0 { range.1 } else { range.0 };
            assert_eq!(*v, want, "at {p:?}");
        }
    }

    #[test]
    fn values_inside_the_range_and_nan_pass_unchanged() {
        let op = spiky();
        // The peak is in the first point's neighbourhood (cell 7 holds samples 6 to 9).
        let (lo, hi) = op.neighbourhood(7, 7);
        assert!(lo < hi && hi == 1.0);
        let pts = [[0.5f32, 0.5], [0.52, 0.53]];
        let mut v = [0.5 * (lo + hi), f32::NAN];
        op.limit_points(&pts, &mut v);
        assert_eq!(v[0], 0.5 * (lo + hi));
        assert!(v[1].is_nan());
    }
}
