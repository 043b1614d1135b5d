//! Continuous decoding of a separable grid of points (a tile's or a region's pixels) by blocks,
//! for the projected continuation: what [`crate::core::decode::grid`] does for the quadtree,
//! with the answers of [`Operator::run_chains`] bit for bit.
//!
//! Why a decoder of its own: the continuation's cells are quarter cells of the sample lattice,
//! found per axis, and its phi keeps the axes (scale 2, no isometry), so the points of a grid
//! that lie in one quarter cell map onto a separable grid again, as the quadtree's do; but its g
//! is bilinear in the quarter's local coordinates (the quadtree's is affine in frame ones), its
//! phi clamps at the frame's edges, and its chains end on the bilinear interpolant with a
//! residual bound per cell. Each of those is computed here per axis exactly as
//! [`Operator::step`] computes it per point, so the same bits come out.

// Blocks are `decode::grid`'s, with columns that always carry frame x (no isometries here);
// s is rho everywhere, so every point of a block has the same product.
use crate::core::decode::{Block, MIN_BLOCK, PointValue, position_quantum, to_frame};
use crate::core::operator::{Chain, Operator, active};

use super::operator::{ProjectedOperator, block};

/// What a step does along one axis at frame coordinate t: the quarter of the lattice it is in
/// (`2 cell + half`), its local coordinate in that quarter, and phi's image.
#[derive(Clone, Copy, Debug)]
struct AxisStep {
    quarter: usize,
    local: f32,
    next: f32,
}

impl ProjectedOperator {
    /// One axis of [`Operator::step`], with the same operations.
    #[inline(always)]
    fn axis_step(&self, t: f32, axis: usize) -> AxisStep {
        let n = self.size[axis];
        let (i, u) = self.locate(t, n);
        let half = usize::from(u >= 0.5);
        AxisStep {
            quarter: 2 * i + half,
            local: 2.0 * u - half as f32,
            next: 2.0 * (i as f32 + u) - block(i, n) as f32 + 0.5,
        }
    }

    /// Whether a grid with these frame coordinates has points enough in a quarter cell for
    /// blocks to pay: where they would hold a few points each they cost more than they share,
    /// and the grid goes point by point (the same answers), as `decode::grid` decides.
    fn blocks_pay(&self, cols: &[f32], rows: &[f32]) -> bool {
        let quarters = |list: &[f32], axis: usize| {
            1 + list
                .windows(2)
                .filter(|w| {
                    self.axis_step(w[0], axis).quarter != self.axis_step(w[1], axis).quarter
                })
                .count()
        };
        let points = (cols.len() * rows.len()) as f32;
        points >= (2 * MIN_BLOCK * quarters(cols, 0) * quarters(rows, 1)) as f32
    }

    /// The steps along `axis` of the leading coordinates of `list` that lie in the quarter of
    /// its first one, into `to`.
    fn leading(&self, list: &[f32], axis: usize, to: &mut Vec<AxisStep>) {
        to.clear();
        let first = self.axis_step(list[0], axis);
        to.push(first);
        for &t in &list[1..] {
            let s = self.axis_step(t, axis);
            if s.quarter != first.quarter {
                break;
            }
            to.push(s);
        }
    }

    /// Adds `acc_s g` to the accumulated offsets of a block of points in one quarter of cell
    /// `(i, j)`: its columns' and rows' steps, `acc_g` starting at its first point with rows
    /// `stride` apart. g = top + (bottom - top) v, top and bottom per column (into `tops`): the
    /// operations of [`Operator::step`], in its order.
    fn add_offsets(
        &self,
        (i, j): (usize, usize),
        (cols, rows): (&[AxisStep], &[AxisStep]),
        acc_s: f32,
        (acc_g, stride): (&mut [f32], usize),
        tops: &mut Vec<(f32, f32)>,
    ) {
        let g = self.quarter(i, j, cols[0].quarter % 2, rows[0].quarter % 2);
        tops.clear();
        tops.extend(cols.iter().map(|s| {
            let top = g[0] + (g[1] - g[0]) * s.local;
            let bottom = g[2] + (g[3] - g[2]) * s.local;
            (top, bottom - top)
        }));
        for (r, row) in rows.iter().zip(acc_g.chunks_mut(stride)) {
            for (acc, &(top, rise)) in row.iter_mut().zip(tops.iter()) {
                *acc += acc_s * (top + rise * r.local);
            }
        }
    }

    /// Continuous decoding of the separable grid of unit points `(xs[i], ys[j])`, row-major.
    /// Where the grid is dense in the cells it covers (a tile past the source resolution), by
    /// `super::subdivision`: every answer a chain's of the steps its window needs, to f32
    /// rounding, within the chain's bound. Elsewhere by chains ([`Self::grid_by_chains`]).
    pub fn grid(&self, xs: &[f32], ys: &[f32], iterations: u32, tolerance: f32) -> Vec<PointValue> {
        self.grid_with(xs, ys, iterations, tolerance, true)
    }

    /// Continuous decoding of the separable grid of unit points `(xs[i], ys[j])`, row-major, by
    /// chains: the answers of [`crate::core::decode::points`] on the same points, bit for bit.
    /// Blocks of points in one quarter cell step together; a block splits as its image crosses
    /// quarter boundaries (into about four a step, phi doubling lengths), and below
    /// [`MIN_BLOCK`] points its chains go on one by one.
    pub fn grid_by_chains(
        &self,
        xs: &[f32],
        ys: &[f32],
        iterations: u32,
        tolerance: f32,
    ) -> Vec<PointValue> {
        self.grid_with(xs, ys, iterations, tolerance, false)
    }

    /// [`Self::grid`], by subdivision where it pays if `subdivide`, else by chains.
    fn grid_with(
        &self,
        xs: &[f32],
        ys: &[f32],
        iterations: u32,
        tolerance: f32,
        subdivide: bool,
    ) -> Vec<PointValue> {
        let (nx, ny) = (xs.len(), ys.len());
        let valid = self.valid();
        if self.needs_window() && nx > 0 && ny > 0 {
            let span = |list: &[f32], v: f32| {
                let (lo, hi) = list
                    .iter()
                    .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &t| {
                        (a.min(t), b.max(t))
                    });
                (lo * v, hi * v)
            };
            let ((x0, x1), (y0, y1)) = (span(xs, valid[0]), span(ys, valid[1]));
            let window = self.window_over([x0, y0, x1, y1]);
            return window.grid_with(xs, ys, iterations, tolerance, subdivide);
        }
        let (lo, hi) = self.interval;
        let (seed, half) = ((lo + hi) * 0.5, (hi - lo) * 0.5);
        let mut arena: Vec<f32> = Vec::with_capacity(4 * (nx + ny));
        let quantum = position_quantum(&self.frame());
        arena.extend(xs.iter().map(|&x| to_frame(x, valid[0], quantum)));
        arena.extend(ys.iter().map(|&y| to_frame(y, valid[1], quantum)));
        if subdivide
            && let Some(answers) =
                self.subdivided(&arena[..nx], &arena[nx..], iterations, tolerance)
        {
            return answers;
        }
        let mut chains: Vec<(usize, Chain<2>)> = Vec::new();
        let mut acc_g = vec![0.0f32; nx * ny];
        let mut todo = Vec::new();
        if !self.ends_on_samples() || !self.blocks_pay(&arena[..nx], &arena[nx..]) {
            for (j, &y) in arena[nx..].iter().enumerate() {
                for (i, &x) in arena[..nx].iter().enumerate() {
                    chains.push((j * nx + i, Chain::start([x, y])));
                }
            }
        } else if nx > 0 && ny > 0 {
            todo.push(Block::whole(nx, ny));
        }
        let mut out = vec![PointValue::default(); nx * ny];
        let (mut col_steps, mut row_steps, mut tops) = (Vec::new(), Vec::new(), Vec::new());
        while let Some(b) = todo.pop() {
            let (w, h) = (b.cols[1] - b.cols[0], b.rows[1] - b.rows[0]);
            let chain = |i: usize, j: usize, acc_g: &[f32]| {
                let k = (b.rows[0] + j) * nx + b.cols[0] + i;
                let c = Chain {
                    q: [arena[b.col_list + i], arena[b.row_list + j]],
                    acc_g: acc_g[k],
                    acc_s: b.acc_s,
                    taken: b.taken,
                };
                (k, c)
            };
            if w * h < MIN_BLOCK {
                for j in 0..h {
                    for i in 0..w {
                        chains.push(chain(i, j, &acc_g));
                    }
                }
                continue;
            }
            // The leading columns and rows that stay in the quarter of the block's first point.
            self.leading(&arena[b.col_list..b.col_list + w], 0, &mut col_steps);
            self.leading(&arena[b.row_list..b.row_list + h], 1, &mut row_steps);
            let (cw, ch) = (col_steps.len(), row_steps.len());
            b.split_rest(cw, ch, &mut todo);
            let (qx, qy) = (col_steps[0].quarter, row_steps[0].quarter);
            let (i, j) = (qx / 2, qy / 2);
            let residual = self.residual_of(i, j);
            if b.taken >= iterations || !active(b.acc_s, residual, tolerance) {
                for jj in 0..ch {
                    for ii in 0..cw {
                        let (k, mut c) = chain(ii, jj, &acc_g);
                        self.end_chain(&mut c);
                        out[k] = c.finish(seed, half);
                    }
                }
                continue;
            }
            self.add_offsets(
                (i, j),
                (&col_steps, &row_steps),
                b.acc_s,
                (&mut acc_g[b.rows[0] * nx + b.cols[0]..], nx),
                &mut tops,
            );
            let col_list = arena.len();
            arena.extend(col_steps.iter().map(|s| s.next));
            let row_list = arena.len();
            arena.extend(row_steps.iter().map(|s| s.next));
            todo.push(Block {
                cols: [b.cols[0], b.cols[0] + cw],
                rows: [b.rows[0], b.rows[0] + ch],
                col_list,
                row_list,
                swap: false,
                acc_s: b.acc_s * self.rho,
                taken: b.taken + 1,
            });
        }
        let mut states: Vec<Chain<2>> = chains.iter().map(|&(_, c)| c).collect();
        self.run_chains(&mut states, iterations, tolerance);
        for (&(k, _), c) in chains.iter().zip(&states) {
            out[k] = c.finish(seed, half);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use crate::codecs::projected::ProjectedOperator;
    use crate::codecs::projected::tests::{grid as rough, header};
    use crate::core::decode;

    /// Unit coordinates of `n` points over `[a, b)` of an axis of `size` samples, on the
    /// sample lattice's own dyadic subdivision when `dyadic` (points land on cell and quarter
    /// boundaries), else shifted off it.
    fn axis(n: usize, a: f32, b: f32, size: usize, dyadic: bool) -> Vec<f32> {
        let shift = if dyadic { 0.0 } else { 0.37 };
        (0..n)
            .map(|k| (a + (b - a) * (k as f32 + shift) / n as f32) / size as f32)
            .collect()
    }

    #[test]
    fn grids_by_blocks_answer_as_points_do() {
        for (w, h) in [(33, 20), (16, 9), (4, 4), (2, 5), (64, 64)] {
            let g = rough(w, h);
            let op = ProjectedOperator::new(&header(w, h, &g), &g).expect("operator");
            // From coarser than the lattice to 40 points a cell; windows inside, across an
            // edge of the frame and past it (clamped), dyadic and not.
            let windows = [
                (0.0, w as f32, 0.0, h as f32),
                (1.0, 3.0, 1.5, 2.5),
                (-0.7, 1.3, h as f32 - 1.2, h as f32 + 0.4),
                (0.25, 0.75, 0.5, 1.0),
            ];
            for (n, dyadic) in [(7, false), (64, true), (80, false), (128, true)] {
                for &(x0, x1, y0, y1) in &windows {
                    let xs = axis(n, x0, x1, w, dyadic);
                    let ys = axis(n / 2 + 3, y0, y1, h, dyadic);
                    let pts: Vec<[f32; 2]> = ys
                        .iter()
                        .flat_map(|&y| xs.iter().map(move |&x| [x, y]))
                        .collect();
                    for (iterations, tol) in [(12, 1e-3), (3, 0.0), (40, 1e-6)] {
                        let by_points = decode::points(&op, &pts, iterations, tol);
                        let by_blocks = op.grid_by_chains(&xs, &ys, iterations, tol);
                        assert_eq!(
                            by_points, by_blocks,
                            "{w}x{h}, {n} points over {x0}..{x1} x {y0}..{y1}, {iterations} steps"
                        );
                    }
                }
            }
        }
    }
}
