//! Continuous decoding of a bilinear patch of points (a reprojected tile's), in f64, by the
//! blocks of `grid` line for line.

use crate::core::operator::{AxisAligned, Chain, ISOMETRY_MATRICES, active};

use super::continuous::*;

/// A bilinear patch of points: point (i, j), for `i < width` and `j < height`, is
/// `origin + i a + j b + i j c` (unit coordinates). The pixels of a tile over an asset in a
/// projected CRS form such patches (the reprojection is interpolated bilinearly between lattice
/// points, see [`crate::geo`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Patch {
    /// Point (0, 0).
    pub origin: [f64; 2],
    /// Step per column.
    pub a: [f64; 2],
    /// Step per row.
    pub b: [f64; 2],
    /// Twist (per column and row).
    pub c: [f64; 2],
    /// Points a row.
    pub width: usize,
    /// Rows.
    pub height: usize,
}

impl Patch {
    /// Point (i, j).
    #[inline]
    pub fn at(&self, i: usize, j: usize) -> [f64; 2] {
        let (x, y) = (i as f64, j as f64);
        std::array::from_fn(|d| self.origin[d] + x * self.a[d] + y * self.b[d] + x * y * self.c[d])
    }
}

/// Continuous decoding of a [`Patch`] of points, row-major. A bilinear patch stays bilinear
/// under an affine phi and an affine g sums to a bilinear function over it, so while the four
/// corners of a block of the patch lie in one cell of an [`AxisAligned`] operator (then, the
/// cell being a box, so does every point between them), the whole block steps in constant time:
/// its coefficients go through phi and the cell's g adds to its bilinear sum. A block that
/// straddles cells steps its leading part inside the cell of its first point, the rest waits
/// (as in [`grid`]); below [`MIN_BLOCK`] points the chains go on one by one. Positions and sums are kept in f64 (blocks and chains alike), so the answers are those
/// of f64 chains at each point; [`points`] (f32) differs from them only at points within f32
/// rounding of a cell boundary at some step.
pub fn patch<O: AxisAligned + ?Sized>(
    op: &O,
    patch: &Patch,
    iterations: u32,
    tolerance: f32,
) -> Vec<PointValue> {
    let (w, h) = (patch.width, patch.height);
    let valid = op.valid().map(f64::from);
    let (seed, half) = seed_of(op);
    let scale = |v: [f64; 2]| [v[0] * valid[0], v[1] * valid[1]];
    let mut out = vec![
        PointValue {
            value: 0.0,
            error_bound: 0.0,
            iterations: 0,
        };
        w * h
    ];
    let mut chains: Vec<(usize, ChainF64)> = Vec::new();
    let mut todo = Vec::new();
    if w > 0 && h > 0 {
        todo.push(PatchBlock {
            cols: [0, w],
            rows: [0, h],
            p: [
                scale(patch.origin),
                scale(patch.a),
                scale(patch.b),
                scale(patch.c),
            ],
            g: [0.0; 4],
            acc_s: 1.0,
            taken: 0,
            first: true,
        });
    }
    let frame_at = |b: &PatchBlock, i: usize, j: usize| -> [f64; 2] {
        let (x, y) = (i as f64, j as f64);
        std::array::from_fn(|d| b.p[0][d] + x * b.p[1][d] + y * b.p[2][d] + x * y * b.p[3][d])
    };
    let g_at = |b: &PatchBlock, i: usize, j: usize| -> f64 {
        let (x, y) = (i as f64, j as f64);
        b.g[0] + x * b.g[1] + y * b.g[2] + x * y * b.g[3]
    };
    while let Some(b) = todo.pop() {
        let (bw, bh) = (b.cols[1] - b.cols[0], b.rows[1] - b.rows[0]);
        if b.taken >= iterations || !active(b.acc_s, half, tolerance) {
            for j in b.rows[0]..b.rows[1] {
                for i in b.cols[0]..b.cols[1] {
                    out[j * w + i] = Chain {
                        q: [0.0; 2],
                        acc_g: g_at(&b, i, j) as f32,
                        acc_s: b.acc_s,
                        taken: b.taken,
                    }
                    .finish(seed, half);
                }
            }
            continue;
        }
        let frame = |i: usize, j: usize| frame_at(&b, i, j).map(|t| t as f32);
        // Points are clamped into the valid part of the frame before their first step (as
        // `points` does), which a bilinear block can't follow: blocks reaching outside split in
        // halves until they are inside or small enough to go on chain by chain.
        let outside = b.first
            && [
                (b.cols[0], b.rows[0]),
                (b.cols[1] - 1, b.rows[0]),
                (b.cols[0], b.rows[1] - 1),
                (b.cols[1] - 1, b.rows[1] - 1),
            ]
            .iter()
            .any(|&(i, j)| {
                let q = frame(i, j);
                (0..2).any(|d| !(0.0..=valid[d] as f32).contains(&q[d]))
            });
        if bw * bh < MIN_BLOCK || outside {
            if bw * bh < 2 * MIN_BLOCK {
                for j in b.rows[0]..b.rows[1] {
                    for i in b.cols[0]..b.cols[1] {
                        let mut q = frame_at(&b, i, j);
                        if b.first {
                            q = [q[0].clamp(0.0, valid[0]), q[1].clamp(0.0, valid[1])];
                        }
                        chains.push((
                            j * w + i,
                            ChainF64 {
                                q,
                                acc_g: g_at(&b, i, j),
                                acc_s: b.acc_s,
                                taken: b.taken,
                            },
                        ));
                    }
                }
            } else {
                let halves = if bw >= bh {
                    let mid = b.cols[0] + bw / 2;
                    [[b.cols[0], mid], [mid, b.cols[1]]].map(|cols| PatchBlock { cols, ..b })
                } else {
                    let mid = b.rows[0] + bh / 2;
                    [[b.rows[0], mid], [mid, b.rows[1]]].map(|rows| PatchBlock { rows, ..b })
                };
                todo.extend(halves);
            }
            continue;
        }
        // The cell of the block's first point, and the leading block of points in it: the
        // columns along the first row and the rows along the first column that stay in the
        // cell, then as many columns along the last of those rows. All four corners of that
        // block are then in the cell, hence (the cell being a box, the block a bilinear patch
        // inside the hull of its corners) all of its points. Cell boundaries cross a tile's
        // patch nearly along its rows and columns, so the leading block is most of what is in
        // the cell.
        let (i0, j0) = (b.cols[0], b.rows[0]);
        let first = frame(i0, j0);
        let cell = op.axis_cell(op.lattice(0, first[0]), op.lattice(1, first[1]));
        let in_cell = |q: [f32; 2]| {
            (cell.cols[0]..cell.cols[1]).contains(&op.lattice(0, q[0]))
                && (cell.rows[0]..cell.rows[1]).contains(&op.lattice(1, q[1]))
        };
        // Along a row (or a column) a bilinear patch is a straight line, whose rounded points
        // stay in order, so the points in the (box) cell form one run from the first: its
        // length is found by bisection.
        let run = |inside: &dyn Fn(usize) -> bool, n: usize| {
            if inside(n - 1) {
                return n;
            }
            let (mut lo, mut hi) = (0, n - 1);
            while hi - lo > 1 {
                let mid = (lo + hi) / 2;
                if inside(mid) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            hi
        };
        let run_x = |j: usize, n: usize| run(&|k| in_cell(frame(i0 + k, j)), n);
        let ch = run(&|k| in_cell(frame(i0, j0 + k)), bh);
        let cw = run_x(j0, bw);
        let cw = if ch > 1 { run_x(j0 + ch - 1, cw) } else { cw };
        // The rest waits at the same step: the other columns beside the leading rows, then
        // every column below them.
        if cw < bw {
            todo.push(PatchBlock {
                cols: [i0 + cw, b.cols[1]],
                rows: [j0, j0 + ch],
                ..b
            });
        }
        if ch < bh {
            todo.push(PatchBlock {
                rows: [j0 + ch, b.rows[1]],
                ..b
            });
        }
        let b = PatchBlock {
            cols: [i0, i0 + cw],
            rows: [j0, j0 + ch],
            ..b
        };
        // One step of the whole block. g = offset + gx x + gy y is affine, so over a bilinear
        // block it is bilinear with these coefficients; phi is affine: its linear part maps
        // every coefficient, its constant the origin.
        let m = cell.map;
        let s = f64::from(b.acc_s);
        let (gx, gy) = (f64::from(m.gx), f64::from(m.gy));
        let g = std::array::from_fn(|k| {
            let constant = if k == 0 { f64::from(m.offset) } else { 0.0 };
            b.g[k] + s * (constant + gx * b.p[k][0] + gy * b.p[k][1])
        });
        let [ax, bx, ay, by] = ISOMETRY_MATRICES[m.isometry as usize & 7].map(f64::from);
        let p = std::array::from_fn(|k| {
            let [x, y] = b.p[k];
            let (tx, ty) = if k == 0 {
                (f64::from(m.cx), f64::from(m.cy))
            } else {
                (0.0, 0.0)
            };
            [ax * x + bx * y + tx, ay * x + by * y + ty]
        });
        todo.push(PatchBlock {
            p,
            g,
            acc_s: b.acc_s * m.contrast,
            taken: b.taken + 1,
            first: false,
            ..b
        });
    }
    let mut states: Vec<ChainF64> = chains.iter().map(|&(_, c)| c).collect();
    run_chains_f64(op, &mut states, iterations, tolerance);
    for (&(k, _), c) in chains.iter().zip(&states) {
        out[k] = Chain {
            q: [0.0; 2],
            acc_g: c.acc_g as f32,
            acc_s: c.acc_s,
            taken: c.taken,
        }
        .finish(seed, half);
    }
    out
}

/// A chain of [`patch`] going on on its own, in f64 like the blocks (so that a point's answer
/// does not depend on where its block stopped sharing steps).
#[derive(Clone, Copy, Debug)]
pub(super) struct ChainF64 {
    q: [f64; 2],
    acc_g: f64,
    acc_s: f32,
    taken: u32,
}

/// [`run_chains`] for [`ChainF64`]s: eight in lockstep, each until it has taken `iterations`
/// steps or its bound is within `tolerance`.
pub(super) fn run_chains_f64<O: AxisAligned + ?Sized>(
    op: &O,
    chains: &mut [ChainF64],
    iterations: u32,
    tolerance: f32,
) {
    const LANES: usize = 8;
    let (_, half) = seed_of(op);
    for batch in chains.chunks_mut(LANES) {
        loop {
            let mut any = false;
            for c in batch.iter_mut() {
                if c.taken >= iterations || !active(c.acc_s, half, tolerance) {
                    continue;
                }
                let m = op
                    .axis_cell(op.lattice(0, c.q[0] as f32), op.lattice(1, c.q[1] as f32))
                    .map;
                let [x, y] = c.q;
                c.acc_g += f64::from(c.acc_s)
                    * (f64::from(m.offset) + f64::from(m.gx) * x + f64::from(m.gy) * y);
                c.acc_s *= m.contrast;
                let [ax, bx, ay, by] = ISOMETRY_MATRICES[m.isometry as usize & 7].map(f64::from);
                c.q = [
                    ax * x + bx * y + f64::from(m.cx),
                    ay * x + by * y + f64::from(m.cy),
                ];
                c.taken += 1;
                any = true;
            }
            if !any {
                break;
            }
        }
    }
}

/// A block of a [`Patch`] in flight in [`patch`]: its columns and rows, its points' frame
/// positions as bilinear coefficients `[origin, a, b, c]` (of the patch's own column and row
/// numbers), `sum g_k prod s_j` as bilinear coefficients, and the shared contrast product.
#[derive(Clone, Copy, Debug)]
pub(super) struct PatchBlock {
    cols: [usize; 2],
    rows: [usize; 2],
    p: [[f64; 2]; 4],
    g: [f64; 4],
    acc_s: f32,
    taken: u32,
    /// Whether no step has been taken (points are still to be clamped into the frame).
    first: bool,
}
