//! Continuous decoding of a separable grid by subdivision: the continuation's values on the
//! dyadic refinement of its cells, built level by level for the subcells the grid's points
//! need, then read bilinearly at the points. Where chains cost their steps at every point, one
//! at a time, this costs a few flops a subcell in regular loops, and a bilinear read a point.
//!
//! Why it is exact: call a square of side `2^-l` of a cell, aligned on its dyadic lattice, a
//! level-l subcell. phi maps a level-l subcell of a cell onto exactly one level-(l-1) subcell
//! of the pair of cells below it (scale 2, no isometry), and g is bilinear on it (a subcell of
//! level 1 or more lies in one quarter cell). A chain of k steps that ends on S (the bilinear
//! interpolant of the samples, [`super::ProjectedOperator`]'s `run_chains`) is therefore, over
//! each level-k subcell, `g + rho (g o phi) + ... + rho^k S o phi^k`: one bilinear function,
//! fixed by its four corners, and those are g's at the corners plus rho times the corners of
//! the image subcell. Level l follows from level l - 1; level 0 is S itself. The value at a
//! point is then the chain's of k steps (up to the f32 rounding of different sums), within the
//! chain's bound, `rho^k` times the residual bound of the cell its k-th image lies in.
//!
//! Why it is cheap: phi keeps the axes, so a subcell's image is found per axis, and the
//! subcells a level needs are the product of the per-axis sets: those holding the grid's
//! columns, at the finest level, and the images of the level above, below it. Each set is no
//! larger than the grid's side, so a level costs at most four corners a point; a grid denser
//! than its finest subcells (a tile deep past the source: pixels of a metre over cells of 90)
//! needs far fewer.
//!
//! The corners are each subcell's own, the limits from inside it: the continuation is not
//! continuous across dyadic lines (phi sends the two sides of a quarter line to the two ends
//! of a pair), so neighbouring subcells keep their corners apart. And unlike chains, the
//! subdivision takes the same k steps at every point of its grid: the fewest that bring the
//! largest residual bound of the cells the grid reaches under the tolerance.

use crate::core::decode::{PointValue, position_quantum, to_frame};
use crate::core::operator::Operator;

use super::operator::{ProjectedOperator, block};

/// Levels past which chains answer instead (subcell indices must fit, and a bound that needs
/// more steps is one no request reaches: rho^30 is under 1e-9 for any fitted roughness but
/// the roughest).
const MOST_LEVELS: u32 = 30;

/// One axis of a subdivision.
struct Axis {
    /// The first cell the grid's chains reach (the pair of its first point's cell) and the
    /// cells from there to past the pair of the last one's: closed under phi.
    first: usize,
    cells: usize,
    /// Per point: its cell (from `first`) and its coordinate in it, in [0, 1].
    at: Vec<(usize, f32)>,
}

/// The subcells one axis of a level-k subdivision needs.
struct Needs {
    /// Per level l in 0..=k, the subcells needed, by index `cell << l | m` (cell from the
    /// axis's first), ascending.
    subcells: Vec<Vec<usize>>,
    /// Per level l in 1..=k and subcell of it, the position of its image in level l - 1.
    images: Vec<Vec<usize>>,
    /// Per point, the position of its subcell at level k and its coordinate in it.
    points: Vec<(usize, f32)>,
    /// Per subcell of level k, the cell (from the axis's first) its k-th image lies in.
    last: Vec<usize>,
}

impl ProjectedOperator {
    /// The first cell of the pair that phi maps cell `i` onto (of an axis of `n` samples).
    #[inline(always)]
    fn pair(i: usize, n: usize) -> usize {
        2 * i - block(i, n)
    }

    /// An axis's frame coordinates `list` located, with the cells their chains reach.
    fn subdivision_axis(&self, list: &[f32], axis: usize) -> Axis {
        let n = self.size[axis];
        let at: Vec<(usize, f32)> = list.iter().map(|&t| self.locate(t, n)).collect();
        let (lo, hi) = at
            .iter()
            .fold((usize::MAX, 0), |(a, b), &(c, _)| (a.min(c), b.max(c)));
        let first = Self::pair(lo, n);
        let last = hi.max(Self::pair(hi, n) + 1);
        Axis {
            first,
            cells: last - first + 1,
            at: at.into_iter().map(|(c, u)| (c - first, u)).collect(),
        }
    }

    /// The subcells of `axis` (of `n` samples) a level-k subdivision needs.
    fn needs(axis: &Axis, n: usize, k: u32) -> Needs {
        let side = 1usize << k;
        let placed: Vec<(usize, f32)> = axis
            .at
            .iter()
            .map(|&(c, u)| {
                let t = u * side as f32;
                let m = (t as usize).min(side - 1);
                (c << k | m, t - m as f32)
            })
            .collect();
        let sorted = |mut v: Vec<usize>| {
            v.sort_unstable();
            v.dedup();
            v
        };
        let finest = sorted(placed.iter().map(|&(g, _)| g).collect());
        let position = |list: &[usize], g: usize| list.binary_search(&g).expect("needed");
        let points = placed
            .iter()
            .map(|&(g, u)| (position(&finest, g), u))
            .collect();
        let mut subcells = vec![finest];
        let mut images = Vec::with_capacity(k as usize);
        for l in (1..=k).rev() {
            let half = 1usize << (l - 1);
            let image_of = |g: usize| {
                let (c, m) = (g >> l, g & (2 * half - 1));
                let cell = Self::pair(axis.first + c, n) - axis.first + m / half;
                cell << (l - 1) | (m % half)
            };
            let above = subcells.last().expect("a level");
            let below = sorted(above.iter().map(|&g| image_of(g)).collect());
            images.push(
                above
                    .iter()
                    .map(|&g| position(&below, image_of(g)))
                    .collect(),
            );
            subcells.push(below);
        }
        subcells.reverse();
        images.push(Vec::new());
        images.reverse();
        let last = (0..subcells[k as usize].len())
            .map(|mut p| {
                for l in (1..=k as usize).rev() {
                    p = images[l][p];
                }
                subcells[0][p]
            })
            .collect();
        Needs {
            subcells,
            images,
            points,
            last,
        }
    }

    /// The steps a subdivision of the separable grid of unit points `(xs[i], ys[j])` takes at
    /// every point ([`Self::grid`] subdivides where this is `Some`): the fewest that bring the
    /// largest residual bound its chains can reach under `tolerance`, at most `iterations`.
    /// What a device decoding the same grid is asked for (that many steps exactly, tolerance
    /// 0), so that its answers are the CPU's.
    pub fn grid_steps(
        &self,
        xs: &[f32],
        ys: &[f32],
        iterations: u32,
        tolerance: f32,
    ) -> Option<u32> {
        let (quantum, valid) = (position_quantum(&self.frame()), self.valid());
        let cols: Vec<f32> = xs.iter().map(|&x| to_frame(x, valid[0], quantum)).collect();
        let rows: Vec<f32> = ys.iter().map(|&y| to_frame(y, valid[1], quantum)).collect();
        let (ax, ay) = (
            self.subdivision_axis(&cols, 0),
            self.subdivision_axis(&rows, 1),
        );
        self.subdivision_steps(&ax, &ay, iterations, tolerance)
            .map(|(k, ..)| k)
    }

    /// The steps of a subdivision over the axes' windows, rho to that power, and the
    /// residual bounds of the windows' cells (row-major); `None` where it does not apply.
    fn subdivision_steps(
        &self,
        ax: &Axis,
        ay: &Axis,
        iterations: u32,
        tolerance: f32,
    ) -> Option<(u32, f32, Vec<f32>)> {
        if self.rho <= 0.0 || !self.ends_on_samples() || ax.at.is_empty() || ay.at.is_empty() {
            return None;
        }
        let wc = ax.cells;
        let residual: Vec<f32> = (0..ay.cells)
            .flat_map(|j| (0..wc).map(move |i| (i, j)))
            .map(|(i, j)| self.residual_of(ax.first + i, ay.first + j))
            .collect();
        let most = residual.iter().copied().fold(0.0f32, f32::max);
        if !most.is_finite() {
            return None;
        }
        // The steps: as a chain's stop (`active`), on the largest bound the chains can reach.
        let (mut k, mut s) = (0u32, 1.0f32);
        while k < iterations && s != 0.0 && s * most > tolerance {
            k += 1;
            s *= self.rho;
            if k > MOST_LEVELS {
                return None;
            }
        }
        Some((k, s, residual))
    }

    /// Continuous decoding of the separable grid of frame points `(cols[i], rows[j])`,
    /// row-major, by subdivision (see the module's documentation), or `None` where chains
    /// answer it (its chains do not end on its samples, or would need more than
    /// [`MOST_LEVELS`] steps). Each answer is the chain's of the steps the grid needs
    /// ([`Self::grid_steps`]), within the same bound.
    pub(super) fn subdivided(
        &self,
        cols: &[f32],
        rows: &[f32],
        iterations: u32,
        tolerance: f32,
    ) -> Option<Vec<PointValue>> {
        let (ax, ay) = (
            self.subdivision_axis(cols, 0),
            self.subdivision_axis(rows, 1),
        );
        let (k, s, residual) = self.subdivision_steps(&ax, &ay, iterations, tolerance)?;
        let wc = ax.cells;
        let (nx, ny) = (
            Self::needs(&ax, self.size[0], k),
            Self::needs(&ay, self.size[1], k),
        );
        let corners = self.subdivide((&ax, &nx), (&ay, &ny), k);
        let ulps = (k + 8) as f32 * self.chain_ulps();
        let width = nx.subcells[k as usize].len();
        let mut out = Vec::with_capacity(cols.len() * rows.len());
        for &(py, v) in &ny.points {
            let row = &corners[4 * py * width..4 * (py + 1) * width];
            let r = &residual[ny.last[py] * wc..(ny.last[py] + 1) * wc];
            out.extend(nx.points.iter().map(|&(px, u)| {
                let c = &row[4 * px..4 * px + 4];
                let top = c[0] + (c[1] - c[0]) * u;
                let bottom = c[2] + (c[3] - c[2]) * u;
                PointValue {
                    value: top + (bottom - top) * v,
                    error_bound: s * r[nx.last[px]] + ulps,
                    iterations: k,
                }
            }));
        }
        Some(out)
    }

    /// The corners of the needed subcells of level k (row-major over the two axes' needed
    /// sets), in the order (0,0), (1,0), (0,1), (1,1).
    fn subdivide(&self, (ax, nx): (&Axis, &Needs), (ay, ny): (&Axis, &Needs), k: u32) -> Vec<f32> {
        let (i0, j0) = (ax.first, ay.first);
        let w = self.size[0];
        // Level 0: S on each cell.
        let mut cur = Vec::with_capacity(4 * nx.subcells[0].len() * ny.subcells[0].len());
        for &cy in &ny.subcells[0] {
            for &cx in &nx.subcells[0] {
                let (a, b) = ((j0 + cy) * w + i0 + cx, (j0 + cy + 1) * w + i0 + cx);
                cur.extend_from_slice(&[self.z[a], self.z[a + 1], self.z[b], self.z[b + 1]]);
            }
        }
        for l in 1..=k as usize {
            let half = 1usize << (l - 1);
            // Per axis and subcell: its cell, quarter and the quarter coordinates of its two
            // ends (those of its image in the pair).
            let ends = |g: usize| {
                let (c, m) = (g >> l, g & (2 * half - 1));
                let mm = m % half;
                let at = |e: usize| e as f32 / half as f32;
                (c, m / half, at(mm), at(mm + 1))
            };
            let xs: Vec<_> = nx.subcells[l].iter().map(|&g| ends(g)).collect();
            let (width, below) = (xs.len(), nx.subcells[l - 1].len());
            let mut next = vec![0.0f32; 4 * width * ny.subcells[l].len()];
            for (py, &gy) in ny.subcells[l].iter().enumerate() {
                let (cy, qb, v0, v1) = ends(gy);
                let iy = ny.images[l][py];
                let prev = &cur[4 * iy * below..4 * (iy + 1) * below];
                let out = &mut next[4 * py * width..4 * (py + 1) * width];
                let mut key = usize::MAX;
                // g on the subcell's two rows, `a + b u` (bilinear in u and v).
                let (mut a0, mut b0, mut a1, mut b1) = (0.0, 0.0, 0.0, 0.0);
                for (px, &(cx, qa, u0, u1)) in xs.iter().enumerate() {
                    // Neighbouring subcells mostly share their quarter: fetch it once.
                    if 2 * cx + qa != key {
                        key = 2 * cx + qa;
                        let g = self.quarter(i0 + cx, j0 + cy, qa, qb);
                        let row = |v: f32| {
                            let (top, rise) = (g[1] - g[0], g[3] - g[2]);
                            (g[0] + (g[2] - g[0]) * v, top + (rise - top) * v)
                        };
                        ((a0, b0), (a1, b1)) = (row(v0), row(v1));
                    }
                    let ix = nx.images[l][px];
                    let p = &prev[4 * ix..4 * ix + 4];
                    let o = &mut out[4 * px..4 * px + 4];
                    o[0] = a0 + b0 * u0 + self.rho * p[0];
                    o[1] = a0 + b0 * u1 + self.rho * p[1];
                    o[2] = a1 + b1 * u0 + self.rho * p[2];
                    o[3] = a1 + b1 * u1 + self.rho * p[3];
                }
            }
            cur = next;
        }
        cur
    }
}

#[cfg(test)]
mod tests {
    use crate::codecs::projected::ProjectedOperator;
    use crate::codecs::projected::tests::{grid as rough, header};
    use crate::core::decode::{self, position_quantum, to_frame};
    use crate::core::operator::Operator;

    /// The subdivision of a grid against chains at the same points: with fixed steps the same
    /// values (to f32 rounding) and bounds; with a tolerance, within each other's bounds and
    /// under the tolerance; and against a chain of many steps, within its own bound.
    #[test]
    fn subdivisions_answer_as_chains_do_within_their_bound() {
        let (mut ran, mut left) = (0, 0);
        for (w, h) in [(33, 20), (16, 9), (64, 64), (5, 7)] {
            let g = rough(w, h);
            let op = ProjectedOperator::new(&header(w, h, &g), &g).expect("operator");
            let quantum = position_quantum(&op.frame());
            let valid = op.valid();
            let windows = [
                (1.0f32, 3.0f32, 1.5f32, 2.5f32),
                (0.25, 0.75, 0.5, 1.0),
                (-0.7, 1.3, h as f32 - 1.2, h as f32 + 0.4),
                (w as f32 - 2.6, w as f32 + 0.3, 0.1, 0.9),
            ];
            for &(x0, x1, y0, y1) in &windows {
                for (n, shift) in [(96usize, 0.37f32), (128, 0.0)] {
                    let axis = |a: f32, b: f32, size: usize, count: usize| -> Vec<f32> {
                        (0..count)
                            .map(|k| {
                                (a + (b - a) * (k as f32 + shift) / count as f32) / size as f32
                            })
                            .collect()
                    };
                    let (xs, ys) = (axis(x0, x1, w, n), axis(y0, y1, h, n / 2 + 3));
                    let cols: Vec<f32> =
                        xs.iter().map(|&x| to_frame(x, valid[0], quantum)).collect();
                    let rows: Vec<f32> =
                        ys.iter().map(|&y| to_frame(y, valid[1], quantum)).collect();
                    let pts: Vec<[f32; 2]> = ys
                        .iter()
                        .flat_map(|&y| xs.iter().map(move |&x| [x, y]))
                        .collect();
                    let exact = decode::points(&op, &pts, 40, 0.0);
                    // Tolerances that take chains to 4 and 6 steps where the bound is largest.
                    let tight = |k: i32| 0.99 * op.residual_max * op.rho.powi(k);
                    for (iterations, tol) in [(3, 0.0), (5, 0.0), (40, tight(4)), (40, tight(6))] {
                        let sub = op.subdivided(&cols, &rows, iterations, tol);
                        // Without roughness (axes too short to measure it) chains end at
                        // once on S: nothing to subdivide.
                        let Some(sub) = sub else {
                            assert_eq!(op.rho, 0.0, "{w}x{h} {x0}..{x1} n={iterations}");
                            left += 1;
                            continue;
                        };
                        ran += 1;
                        let chains = decode::points(&op, &pts, iterations, tol);
                        for (k, ((s, c), e)) in sub.iter().zip(&chains).zip(&exact).enumerate() {
                            let at =
                                format!("{w}x{h} {x0}..{x1} point {k} n={iterations} tol={tol}");
                            // A point clamped onto the frame's last sample lies on the far
                            // edge of the last cell, where its chain's next image is located
                            // in the cell past that edge and the subdivision keeps the limit
                            // from inside: two sides of a line where the continuation jumps.
                            let far =
                                cols[k % n] >= w as f32 - 0.5 || rows[k / n] >= h as f32 - 0.5;
                            if tol == 0.0 {
                                assert_eq!(s.iterations, c.iterations, "{at}");
                                if !far {
                                    assert!((s.value - c.value).abs() < 2e-6, "{at}: {s:?} {c:?}");
                                }
                                // The cell of the last image may differ where a point
                                // is clamped onto the frame's last sample (a sample: both
                                // values are it), so bounds are compared with the largest.
                                let most = op.residual_max * op.rho.powi(iterations as i32);
                                assert!(s.error_bound <= most + 1e-5, "{at}: {s:?}");
                            } else {
                                assert!(s.error_bound <= tol * 1.001 + 1e-5, "{at}: {s:?}");
                                assert!(
                                    (s.value - c.value).abs() <= s.error_bound + c.error_bound,
                                    "{at}: {s:?} {c:?}"
                                );
                            }
                            assert!(
                                (s.value - e.value).abs() <= s.error_bound + e.error_bound,
                                "{at}: {s:?} against {e:?}"
                            );
                        }
                    }
                }
            }
        }
        assert!(ran >= 3 * left, "{ran} subdivided, {left} left to chains");
    }

    /// A grid sparser than its cells (a point every cell and a half) needs, at every level, no
    /// more subcells an axis than it has points, and answers as chains do.
    #[test]
    fn sparse_grids_need_no_more_subcells_than_points() {
        let (w, h) = (64, 48);
        let g = rough(w, h);
        let op = ProjectedOperator::new(&header(w, h, &g), &g).expect("operator");
        let xs: Vec<f32> = (0..40)
            .map(|i| (1.55 * i as f32 + 0.8) / w as f32)
            .collect();
        let ys: Vec<f32> = (0..30)
            .map(|j| (1.55 * j as f32 + 1.1) / h as f32)
            .collect();
        let (quantum, valid) = (position_quantum(&op.frame()), op.valid());
        let cols: Vec<f32> = xs.iter().map(|&x| to_frame(x, valid[0], quantum)).collect();
        let rows: Vec<f32> = ys.iter().map(|&y| to_frame(y, valid[1], quantum)).collect();
        let k = 7;
        let axis = op.subdivision_axis(&cols, 0);
        let needs = ProjectedOperator::needs(&axis, w, k);
        for (l, level) in needs.subcells.iter().enumerate() {
            assert!(level.len() <= cols.len(), "level {l}: {}", level.len());
        }
        let sub = op.subdivided(&cols, &rows, k, 0.0).expect("subdivided");
        let chains = op.grid_by_chains(&xs, &ys, k, 0.0);
        for (a, b) in sub.iter().zip(&chains) {
            assert!((a.value - b.value).abs() < 2e-6, "{a:?} {b:?}");
        }
    }
}
