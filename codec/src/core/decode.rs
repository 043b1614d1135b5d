//! Decoding a partitioned affine operator, three ways, for any [`Operator`].
//!
//! * [`discrete`]: iterate W on a grid of any size. The previous iterate is averaged over the
//!   domain footprint of each output pixel (a box of `expansion` output pixels, sampled
//!   bilinearly) — exactly what the encoder fitted at the native size, and the seed's decoder.
//! * [`point`]: the value at one real point by inverse iteration (seed Fig. 5): follow phi n times,
//!   then `value = seed * prod(s) + sum_k g_k prod_{j<k} s_j`, with the a-priori bound
//!   `prod |s_k| * max |seed - f|`. This *samples* the attractor of the point operator; discrete
//!   decoding *averages*. On smooth content the two agree closely; at sharp edges they differ by
//!   up to the local contrast, and the point form has more fine detail at deep zoom
//!   (the bench measures the difference).
//! * [`window`]: a rectangle at any resolution, answered by whichever of the two is cheaper.

use rayon::prelude::*;

use crate::core::operator::{AxisAligned, Chain, ISOMETRY_MATRICES, Operator, active};

/// The value of the attractor at one point, with its a-priori error bound.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PointValue {
    /// Value (normalised units).
    pub value: f32,
    /// Bound on |value - attractor(p)| (normalised units).
    pub error_bound: f32,
    /// Inverse steps taken (fewer than asked when a map with s = 0 ends the chain early: the
    /// value is then exact).
    pub iterations: u32,
}

/// Continuous decoding of the point `p` given in unit coordinates (`[0, 1]` per axis over the
/// source extent), with `iterations` inverse steps.
#[inline]
pub fn point<const D: usize, O: Operator<D> + ?Sized>(
    op: &O,
    p: [f32; D],
    iterations: u32,
) -> PointValue {
    let valid = op.valid();
    let quantum = position_quantum(&op.frame());
    let mut q = [0.0f32; D];
    for d in 0..D {
        q[d] = to_frame(p[d], valid[d], quantum);
    }
    let (lo, hi) = op.invariant_interval();
    let (seed, half) = ((lo + hi) * 0.5, (hi - lo) * 0.5);
    let (mut acc_g, mut acc_s) = (0.0f32, 1.0f32);
    let mut taken = 0;
    while taken < iterations {
        let st = op.step(q);
        acc_g += acc_s * st.offset;
        acc_s *= st.contrast;
        taken += 1;
        if acc_s == 0.0 {
            break;
        }
        q = st.next;
    }
    PointValue {
        value: acc_g + acc_s * seed,
        error_bound: acc_s.abs() * half,
        iterations: taken,
    }
}

/// Continuous decoding of many points (unit coordinates), in the order given. Points are taken
/// eight at a time and stepped in lockstep: each chain of steps is a sequence of dependent
/// loads, and interleaving independent chains lets the CPU overlap them (measured in the bench).
///
/// A chain also stops as soon as its own bound `prod |s| * max |seed - f|` is at most
/// `tolerance` (normalised; 0 runs every chain the full `iterations` unless a constant map ends it
/// exactly). Along most paths |s| is well below its maximum, so this stops far earlier than a
/// count computed from the largest |s|. Each chain's answer depends on its point alone, never on
/// the other points of its batch.
pub fn points<const D: usize, O: Operator<D> + ?Sized>(
    op: &O,
    pts: &[[f32; D]],
    iterations: u32,
    tolerance: f32,
) -> Vec<PointValue> {
    let valid = op.valid();
    let quantum = position_quantum(&op.frame());
    let mut chains: Vec<Chain<D>> = pts
        .iter()
        .map(|p| Chain::start(std::array::from_fn(|d| to_frame(p[d], valid[d], quantum))))
        .collect();
    run_chains(op, &mut chains, iterations, tolerance);
    let (seed, half) = seed_of(op);
    chains.iter().map(|c| c.finish(seed, half)).collect()
}

/// A unit coordinate clamped into `[0, 1]`, scaled to the frame's `valid` extent and rounded to
/// a multiple of `quantum` ([`position_quantum`] of the operator's frame). NaN is taken as 0 (an edge of the asset), so
/// that every decoding path and operator layout gives the same finite answer for it. The GPU
/// kernel starts its chains with the same three operations (`shaders/decode2d.wgsl`).
#[inline]
pub fn to_frame(t: f32, valid: f32, quantum: f32) -> f32 {
    if t.is_nan() {
        0.0
    } else {
        let x = t.clamp(0.0, 1.0) * valid;
        // x / quantum is exact (a power of two) and under 2^22, so + 0.5 and the rounding to
        // an integer are too. Truncation is the kernel's floor here (x >= 0), and a conversion
        // instruction where `f32::floor` calls libm on baseline x86-64 (+11% on a quadtree
        // point decode, measured).
        ((x * (1.0 / quantum) + 0.5) as i32 as f32) * quantum
    }
}

/// The fixed-point step of chain positions in a frame of `frame` samples a side: the power of
/// two `2^-F` with `F = 24 - ceil(log2(4 max(frame)))`.
///
/// Why: a chain's next position is `a x + b y + c`, with a and b in {0, +-1, +-2} times a power
/// of two on the lattice codecs (the quadtree's scale-2 isometries, the projected codec's
/// `2 t - c`) and c a multiple of the lattice. No intermediate of a step leaves
/// `[-2 frame, 3 frame]`, so a position that is a multiple of `2^-F` needs at most 24
/// significant bits there, and every product and sum of a step is exact in f32, whatever the
/// order of the operations or whether the hardware fuses them: the CPU (in lattice units) and
/// the GPU (in samples, through its piece table) then visit the same cells for every point, bit
/// for bit, where before a point on a cell boundary (every dyadic grid has them) went either
/// way with the last bit of rounding. Positions carry integers times `2^-F` in f32 rather than
/// i32: the same bits, one kernel for every codec. The cost is moving starts by up to
/// `2^-(F + 1)` of a sample (1/4096 on etopo20's frame of about 1,100), about what f32 itself
/// resolves at the frame's far edge. FIS and psa2d maps scale by ratios that are not powers of
/// two: their steps round, and CPU and GPU may still part at boundaries there.
pub fn position_quantum(frame: &[f32]) -> f32 {
    let side = frame.iter().fold(1.0f32, |m, &v| m.max(v)).min(1e6);
    let bits = (4.0 * side).log2().ceil() as i32;
    2f32.powi(bits - 24)
}

/// The seed value (the middle of the invariant interval) and its largest distance from the
/// attractor (the half-width).
fn seed_of<const D: usize, O: Operator<D> + ?Sized>(op: &O) -> (f32, f32) {
    let (lo, hi) = op.invariant_interval();
    ((lo + hi) * 0.5, (hi - lo) * 0.5)
}

impl<const D: usize> Chain<D> {
    /// A chain at frame point `q` that has taken no step.
    pub(crate) fn start(q: [f32; D]) -> Self {
        Chain {
            q,
            acc_g: 0.0,
            acc_s: 1.0,
            taken: 0,
        }
    }

    /// The chain's answer from a seed `seed` within `half` of the attractor.
    pub(crate) fn finish(&self, seed: f32, half: f32) -> PointValue {
        PointValue {
            value: self.acc_g + self.acc_s * seed,
            error_bound: self.acc_s.abs() * half,
            iterations: self.taken,
        }
    }
}

/// Runs every chain until it has taken `iterations` steps in all or stopped (see [`points`]),
/// through the operator's own [`Operator::run_chains`].
fn run_chains<const D: usize, O: Operator<D> + ?Sized>(
    op: &O,
    chains: &mut [Chain<D>],
    iterations: u32,
    tolerance: f32,
) {
    op.run_chains(chains, iterations, tolerance);
}

/// Continuous decoding of a separable grid of unit points: point (i, j) is `(xs[i], ys[j])`;
/// row-major, `ys.len()` rows of `xs.len()`. The answers are bit for bit those of [`points`] on
/// the same points (a test checks it), found with less work: the pixels of a tile or a region
/// form such a grid, and the points of the grid that lie in one cell of an [`AxisAligned`]
/// operator map onto a separable grid again, so a whole block of them steps at once. Blocks
/// split as their images cross cell boundaries; below [`MIN_BLOCK`] points the chains go on
/// one by one. The saving grows with zoom: at a tile 30 times finer than the source most points
/// share their first five steps (measured in the bench).
pub fn grid<O: AxisAligned + ?Sized>(
    op: &O,
    xs: &[f32],
    ys: &[f32],
    iterations: u32,
    tolerance: f32,
) -> Vec<PointValue> {
    let (nx, ny) = (xs.len(), ys.len());
    let valid = op.valid();
    let (seed, half) = seed_of(op);
    // Coordinate lists, all in one arena: a block refers to a slice for its columns and one for
    // its rows; a block that steps appends its images.
    let mut arena: Vec<f32> = Vec::with_capacity(4 * (nx + ny));
    let quantum = position_quantum(&op.frame());
    arena.extend(xs.iter().map(|&x| to_frame(x, valid[0], quantum)));
    arena.extend(ys.iter().map(|&y| to_frame(y, valid[1], quantum)));
    // Where the grid is about as coarse as the lattice, blocks would hold a few points and
    // cost more than they share: decode point by point (the same answers). The bench puts the
    // break-even near 32 points per lattice square (a 256-pixel window over 256 source pixels,
    // 16 a square: 1.0x either way).
    let squares = |list: &[f32], axis: usize| {
        1 + list
            .windows(2)
            .filter(|w| op.lattice(axis, w[0]) != op.lattice(axis, w[1]))
            .count()
    };
    let per_square =
        (nx * ny) as f32 / (squares(&arena[..nx], 0) as f32 * squares(&arena[nx..], 1) as f32);
    if per_square < (4 * MIN_BLOCK) as f32 {
        let mut chains: Vec<Chain<2>> = arena[nx..]
            .iter()
            .flat_map(|&y| arena[..nx].iter().map(move |&x| Chain::start([x, y])))
            .collect();
        run_chains(op, &mut chains, iterations, tolerance);
        return chains.iter().map(|c| c.finish(seed, half)).collect();
    }
    let mut acc_g = vec![0.0f32; nx * ny];
    let mut out = vec![PointValue::default(); nx * ny];
    let mut chains: Vec<(usize, Chain<2>)> = Vec::new();
    let mut todo = Vec::new();
    let mut terms: Vec<f32> = Vec::new();
    if nx > 0 && ny > 0 {
        todo.push(Block::whole(nx, ny));
    }
    while let Some(b) = todo.pop() {
        let (w, h) = (b.cols[1] - b.cols[0], b.rows[1] - b.rows[0]);
        let at = |list: usize, k: usize| arena[list + k];
        // Frame x and y of the block's column k and row k.
        let (x_list, y_list) = if b.swap {
            (b.row_list, b.col_list)
        } else {
            (b.col_list, b.row_list)
        };
        let point = |i: usize, j: usize| {
            if b.swap {
                [at(x_list, j), at(y_list, i)]
            } else {
                [at(x_list, i), at(y_list, j)]
            }
        };
        if b.taken >= iterations || !active(b.acc_s, half, tolerance) {
            for j in b.rows[0]..b.rows[1] {
                for i in b.cols[0]..b.cols[1] {
                    let k = j * nx + i;
                    out[k] = Chain {
                        q: [0.0; 2],
                        acc_g: acc_g[k],
                        acc_s: b.acc_s,
                        taken: b.taken,
                    }
                    .finish(seed, half);
                }
            }
            continue;
        }
        if w * h < MIN_BLOCK {
            for j in 0..h {
                for i in 0..w {
                    let k = (b.rows[0] + j) * nx + b.cols[0] + i;
                    let c = Chain {
                        q: point(i, j),
                        acc_g: acc_g[k],
                        acc_s: b.acc_s,
                        taken: b.taken,
                    };
                    chains.push((k, c));
                }
            }
            continue;
        }
        // The cell of the block's first point, and the leading columns and rows that stay in it.
        let p = point(0, 0);
        let cell = op.axis_cell(op.lattice(0, p[0]), op.lattice(1, p[1]));
        let inside = |list: usize, n: usize, axis: usize, span: [usize; 2]| {
            (0..n)
                .position(|k| !(span[0]..span[1]).contains(&op.lattice(axis, at(list, k))))
                .unwrap_or(n)
        };
        let (cw, ch) = if b.swap {
            (
                inside(y_list, w, 1, cell.rows),
                inside(x_list, h, 0, cell.cols),
            )
        } else {
            (
                inside(x_list, w, 0, cell.cols),
                inside(y_list, h, 1, cell.rows),
            )
        };
        debug_assert!(cw > 0 && ch > 0);
        b.split_rest(cw, ch, &mut todo);
        // One step of the leading block: g at every point (the same expression as `step`),
        // phi on the coordinate lists.
        let m = cell.map;
        // g = (offset + gx x) + gy y, split into a term per column and one per row (the same
        // operations in the same order as `step`, so the same bits).
        terms.clear();
        let (col_terms, row_terms) = if b.swap {
            terms.extend((0..cw).map(|i| m.gy * at(y_list, i)));
            terms.extend((0..ch).map(|j| m.offset + m.gx * at(x_list, j)));
            terms.split_at(cw)
        } else {
            terms.extend((0..cw).map(|i| m.offset + m.gx * at(x_list, i)));
            terms.extend((0..ch).map(|j| m.gy * at(y_list, j)));
            terms.split_at(cw)
        };
        for (j, &rt) in row_terms.iter().enumerate() {
            let row = (b.rows[0] + j) * nx + b.cols[0];
            for (g, &ct) in acc_g[row..row + cw].iter_mut().zip(col_terms) {
                *g += b.acc_s * (ct + rt);
            }
        }
        let [ax, bx, ay, by] = ISOMETRY_MATRICES[m.isometry as usize & 7];
        let (col_list, row_list) = (arena.len(), arena.len() + cw);
        // The list that carried frame x carries the new x if phi_x reads x (ax != 0), else the
        // new y; the other list carries the other coordinate.
        let cols_carry_x = !b.swap;
        let cols_to_x = (ax != 0.0) == cols_carry_x;
        for (list, n, carries_x) in [
            (b.col_list, cw, cols_carry_x),
            (b.row_list, ch, !cols_carry_x),
        ] {
            let to_x = (ax != 0.0) == carries_x;
            let (a, c) = match (to_x, carries_x) {
                (true, true) => (ax, m.cx),
                (true, false) => (bx, m.cx),
                (false, true) => (ay, m.cy),
                (false, false) => (by, m.cy),
            };
            for k in 0..n {
                let t = arena[list + k];
                arena.push(a * t + c);
            }
        }
        todo.push(Block {
            cols: [b.cols[0], b.cols[0] + cw],
            rows: [b.rows[0], b.rows[0] + ch],
            col_list,
            row_list,
            swap: !cols_to_x,
            acc_s: b.acc_s * m.contrast,
            taken: b.taken + 1,
        });
    }
    let mut states: Vec<Chain<2>> = chains.iter().map(|&(_, c)| c).collect();
    run_chains(op, &mut states, iterations, tolerance);
    for (&(k, _), c) in chains.iter().zip(&states) {
        out[k] = c.finish(seed, half);
    }
    out
}

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
struct ChainF64 {
    q: [f64; 2],
    acc_g: f64,
    acc_s: f32,
    taken: u32,
}

/// [`run_chains`] for [`ChainF64`]s: eight in lockstep, each until it has taken `iterations`
/// steps or its bound is within `tolerance`.
fn run_chains_f64<O: AxisAligned + ?Sized>(
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
struct PatchBlock {
    cols: [usize; 2],
    rows: [usize; 2],
    p: [[f64; 2]; 4],
    g: [f64; 4],
    acc_s: f32,
    taken: u32,
    /// Whether no step has been taken (points are still to be clamped into the frame).
    first: bool,
}

/// Below this many points a block of [`grid`] is decoded chain by chain: stepping a block costs
/// a few lookups and list copies on top of the per-point work.
pub const MIN_BLOCK: usize = 8;

/// A block of a separable grid in flight in [`grid`]: columns and rows of the output, the
/// arena offsets of their coordinate lists, which list holds frame x, and the shared part of the
/// chain state (every point of a block has met the same maps).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Block {
    pub(crate) cols: [usize; 2],
    pub(crate) rows: [usize; 2],
    pub(crate) col_list: usize,
    pub(crate) row_list: usize,
    /// Whether the columns carry frame y (and the rows frame x).
    pub(crate) swap: bool,
    pub(crate) acc_s: f32,
    pub(crate) taken: u32,
}

impl Block {
    /// The whole grid of `nx x ny` points, its column list first in the arena and its row
    /// list after it, before any step.
    pub(crate) fn whole(nx: usize, ny: usize) -> Block {
        Block {
            cols: [0, nx],
            rows: [0, ny],
            col_list: 0,
            row_list: nx,
            swap: false,
            acc_s: 1.0,
            taken: 0,
        }
    }

    /// Puts on `todo` what is left of the block once its leading `cw` columns and `ch` rows
    /// step: the rest waits at the same step, its other columns beside the leading rows, then
    /// every column below them.
    pub(crate) fn split_rest(&self, cw: usize, ch: usize, todo: &mut Vec<Block>) {
        if cw < self.cols[1] - self.cols[0] {
            todo.push(Block {
                cols: [self.cols[0] + cw, self.cols[1]],
                rows: [self.rows[0], self.rows[0] + ch],
                col_list: self.col_list + cw,
                ..*self
            });
        }
        if ch < self.rows[1] - self.rows[0] {
            todo.push(Block {
                rows: [self.rows[0] + ch, self.rows[1]],
                row_list: self.row_list + ch,
                ..*self
            });
        }
    }
}

/// A decoded grid (normalised values), row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    /// Width in samples.
    pub width: usize,
    /// Height in samples.
    pub height: usize,
    /// Values, row-major.
    pub values: Vec<f32>,
}

impl Grid {
    /// The grid resampled to `width x height` (no larger) by area means: each new cell the mean
    /// of the cells it covers, each weighed by the part of it covered (the cells are boxes on
    /// the unit square, as pixels are). What a coarser grid of samples is, exactly, without a
    /// decode: the box filter. NaN cells weigh nothing (NaN where all are).
    pub fn area_means(&self, width: usize, height: usize) -> Grid {
        // Per output cell along an axis of n cells onto m: the first cell it covers and the
        // weights of those it covers.
        fn weights(n: usize, m: usize) -> Vec<(usize, Vec<f32>)> {
            let r = n as f64 / m as f64;
            (0..m)
                .map(|i| {
                    let (a, b) = (i as f64 * r, ((i + 1) as f64 * r).min(n as f64));
                    let first = a.floor() as usize;
                    let last = (b.ceil() as usize).clamp(first + 1, n);
                    let w = (first..last)
                        .map(|k| ((b.min(k as f64 + 1.0) - a.max(k as f64)).max(0.0)) as f32)
                        .collect();
                    (first, w)
                })
                .collect()
        }
        let (wx, wy) = (weights(self.width, width), weights(self.height, height));
        // Rows first (sums and weights of finite values), then columns.
        let mut rows = vec![(0.0f32, 0.0f32); width * self.height];
        for (row, out) in self
            .values
            .chunks_exact(self.width)
            .zip(rows.chunks_exact_mut(width))
        {
            for (o, (first, w)) in out.iter_mut().zip(&wx) {
                for (&v, &w) in row[*first..].iter().zip(w) {
                    if v.is_finite() {
                        o.0 += w * v;
                        o.1 += w;
                    }
                }
            }
        }
        let mut values = Vec::with_capacity(width * height);
        for (first, w) in &wy {
            let mut acc = vec![(0.0f32, 0.0f32); width];
            for (k, &w) in w.iter().enumerate() {
                let src = &rows[(first + k) * width..(first + k + 1) * width];
                for (a, &(s, n)) in acc.iter_mut().zip(src) {
                    a.0 += w * s;
                    a.1 += w * n;
                }
            }
            values.extend(
                acc.into_iter()
                    .map(|(s, n)| if n > 0.0 { s / n } else { f32::NAN }),
            );
        }
        Grid {
            width,
            height,
            values,
        }
    }

    /// The grid `fx` x `fy` times coarser: each cell the mean of the finite values of its block
    /// (NaN where there are none, as nodata stays nodata). `None` unless the factors divide the
    /// size. A discrete decode at a coarser size is itself an approximation of the attractor's
    /// cell means; the mean of a finer decode is a closer one, and costs a pass over the grid
    /// instead of a decode.
    pub fn shrink(&self, fx: usize, fy: usize) -> Option<Grid> {
        if fx == 0 || fy == 0 || !self.width.is_multiple_of(fx) || !self.height.is_multiple_of(fy) {
            return None;
        }
        let (w, h) = (self.width / fx, self.height / fy);
        let mut sums = vec![(0.0f32, 0u32); w * h];
        for (y, row) in self.values.chunks_exact(self.width).enumerate() {
            let out = &mut sums[(y / fy) * w..][..w];
            for (x, &v) in row.iter().enumerate() {
                if v.is_finite() {
                    let c = &mut out[x / fx];
                    c.0 += v;
                    c.1 += 1;
                }
            }
        }
        Some(Grid {
            width: w,
            height: h,
            values: sums
                .into_iter()
                .map(|(s, n)| if n > 0 { s / n as f32 } else { f32::NAN })
                .collect(),
        })
    }
}

/// When discrete decoding stops.
#[derive(Clone, Copy, Debug)]
pub struct DiscreteOptions {
    /// Stop when the mean absolute change between two iterates falls under this (normalised;
    /// the seed's criterion is 0.002 of the value range).
    pub min_change: f32,
    /// Never more than this many iterations; exactly this many when `min_change` and
    /// `max_error` are 0.
    pub max_iterations: u32,
    /// Stop once the a-posteriori bound on the distance to the discrete attractor
    /// ([`DiscreteReport::error_bound`]) is at most this (normalised; 0: never on that account).
    pub max_error: f32,
}

impl Default for DiscreteOptions {
    fn default() -> Self {
        DiscreteOptions {
            min_change: 0.002,
            max_iterations: 40,
            max_error: 0.0,
        }
    }
}

impl DiscreteOptions {
    /// Exactly `n` iterations.
    pub fn fixed(n: u32) -> Self {
        DiscreteOptions {
            min_change: 0.0,
            max_iterations: n,
            max_error: 0.0,
        }
    }

    /// At most `n` iterations, fewer once the iterate is provably within `max_error` of the
    /// discrete attractor.
    pub fn within(max_error: f32, n: u32) -> Self {
        DiscreteOptions {
            min_change: 0.0,
            max_iterations: n,
            max_error,
        }
    }
}

/// What discrete decoding did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DiscreteReport {
    /// Iterations run.
    pub iterations: u32,
    /// Mean absolute change of the last iteration (normalised).
    pub last_change: f32,
    /// A-posteriori bound on the largest distance of the result to the discrete attractor at
    /// this size (normalised): `s / (1 - s) * max |f_n - f_(n-1)|` over the whole frame, with s
    /// the largest |contrast| of the discrete operator (averaging and interpolation do not
    /// expand the sup norm, so that operator contracts by s). Usually far below the a-priori
    /// `s^n * max |seed - f|`, since the last change reflects the contrasts actually met.
    pub error_bound: f32,
}

/// Per output pixel: where the operator reads and how it scales what it reads.
struct PixelMap {
    offset: f32,
    contrast: f32,
    index: u32,
    fx: f32,
    fy: f32,
}

/// Discrete decoding of the whole source extent at `width x height` (any size: smaller, equal or
/// larger than the source, any ratio).
pub fn discrete<O: Operator<2> + ?Sized>(
    op: &O,
    width: usize,
    height: usize,
    opts: DiscreteOptions,
) -> (Grid, DiscreteReport) {
    let valid = op.valid();
    let frame = op.frame();
    let e = op.expansion().max(1) as usize;
    let sx = width as f32 / valid[0];
    let sy = height as f32 / valid[1];
    // The iteration runs over the whole frame at the output scale (domains may lie in padding).
    let fw = ((frame[0] * sx).ceil() as usize).max(width).max(e);
    let fh = ((frame[1] * sy).ceil() as usize).max(height).max(e);
    let (dw, dh) = (fw - e + 1, fh - e + 1);
    let half = e as f32 * 0.5;
    let maps: Vec<PixelMap> = (0..fw * fh)
        .into_par_iter()
        .map(|i| {
            let (px, py) = ((i % fw) as f32 + 0.5, (i / fw) as f32 + 0.5);
            let st = op.step([px / sx, py / sy]);
            // Top-left of the e x e box centred on phi(p), in output pixels.
            let bx = (st.next[0] * sx - half).clamp(0.0, (dw - 1) as f32);
            let by = (st.next[1] * sy - half).clamp(0.0, (dh - 1) as f32);
            let (ix, iy) = (
                (bx as usize).min(dw.saturating_sub(2)),
                (by as usize).min(dh.saturating_sub(2)),
            );
            PixelMap {
                offset: st.offset,
                contrast: st.contrast,
                index: (iy * dw + ix) as u32,
                fx: if dw > 1 { bx - ix as f32 } else { 0.0 },
                fy: if dh > 1 { by - iy as f32 } else { 0.0 },
            }
        })
        .collect();
    let contraction = maps.iter().fold(0.0f32, |m, p| m.max(p.contrast.abs()));
    let (lo, hi) = op.invariant_interval();
    let mut f = vec![(lo + hi) * 0.5; fw * fh];
    let mut next = vec![0.0f32; fw * fh];
    let mut boxed = vec![0.0f32; dw * dh];
    let norm = 1.0 / (e * e) as f32;
    let mut report = DiscreteReport {
        iterations: 0,
        last_change: f32::INFINITY,
        error_bound: f32::INFINITY,
    };
    let (step_x, step_y) = (usize::from(dw > 1), if dh > 1 { dw } else { 0 });
    while report.iterations < opts.max_iterations {
        // Box average of the iterate over e x e, at every position.
        boxed.par_chunks_mut(dw).enumerate().for_each(|(y, row)| {
            for (x, out) in row.iter_mut().enumerate() {
                let mut acc = 0.0;
                for yy in y..y + e {
                    acc += f[yy * fw + x..yy * fw + x + e].iter().sum::<f32>();
                }
                *out = acc * norm;
            }
        });
        let (change, largest) = next
            .par_chunks_mut(fw)
            .zip(maps.par_chunks(fw))
            .enumerate()
            .map(|(y, (row, mrow))| {
                let (mut ch, mut mx) = (0.0f64, 0.0f32);
                for (x, (out, m)) in row.iter_mut().zip(mrow).enumerate() {
                    let i = m.index as usize;
                    let top = boxed[i] + (boxed[i + step_x] - boxed[i]) * m.fx;
                    let bot =
                        boxed[i + step_y] + (boxed[i + step_y + step_x] - boxed[i + step_y]) * m.fx;
                    let v = m.offset + m.contrast * (top + (bot - top) * m.fy);
                    let d = (v - f[y * fw + x]).abs();
                    if x < width && y < height {
                        ch += d as f64;
                    }
                    mx = mx.max(d);
                    *out = v;
                }
                (ch, mx)
            })
            .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1.max(b.1)));
        std::mem::swap(&mut f, &mut next);
        report.iterations += 1;
        report.last_change = (change / (width * height) as f64) as f32;
        report.error_bound = contraction / (1.0 - contraction) * largest;
        if report.last_change < opts.min_change || report.error_bound <= opts.max_error {
            break;
        }
    }
    let mut values = Vec::with_capacity(width * height);
    for y in 0..height {
        values.extend_from_slice(&f[y * fw..y * fw + width]);
    }
    (
        Grid {
            width,
            height,
            values,
        },
        report,
    )
}

/// How a window is decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Method {
    /// Whichever is cheaper for this window (the default).
    #[default]
    Auto,
    /// Discrete decoding of the whole extent at the window's scale, then sampling the window.
    Discrete,
    /// Continuous decoding of each window pixel centre.
    Continuous,
}

/// The unit coordinates of the pixel centres of a `width x height` window over `rect`
/// (`[u0, v0, u1, v1]`): columns, then rows. Computed in f64 and rounded once; the GPU's windows
/// take the same axes, so both decode the same points.
pub fn window_axes(rect: [f32; 4], width: usize, height: usize) -> (Vec<f32>, Vec<f32>) {
    let axis = |a: f32, b: f32, n: usize| -> Vec<f32> {
        let (a, d) = (f64::from(a), f64::from((b - a).max(1e-9)));
        (0..n)
            .map(|i| (a + (i as f64 + 0.5) / n as f64 * d) as f32)
            .collect()
    };
    (
        axis(rect[0], rect[2], width),
        axis(rect[1], rect[3], height),
    )
}

/// A window `[u0, v0, u1, v1]` of the unit square decoded at `width x height`: value at each
/// pixel centre. `iterations` counts inverse steps (continuous) or iterations (discrete);
/// `None` lets each method use its own stopping rule (point: 12 steps).
pub fn window<O: Operator<2> + ?Sized>(
    op: &O,
    rect: [f32; 4],
    width: usize,
    height: usize,
    iterations: Option<u32>,
    method: Method,
) -> (Grid, Method) {
    let [u0, v0, u1, v1] = rect;
    let (du, dv) = ((u1 - u0).max(1e-9), (v1 - v0).max(1e-9));
    // Full decode at the window's scale costs its pixels times ~10 iterations; point decoding
    // costs the window's pixels times the steps. Discrete needs the whole extent in memory.
    let full_w = (width as f32 / du).ceil() as usize;
    let full_h = (height as f32 / dv).ceil() as usize;
    let full = full_w as f64 * full_h as f64;
    let chosen = match method {
        Method::Auto if full <= 3.0 * (width * height) as f64 && full < 16e6 => Method::Discrete,
        Method::Auto => Method::Continuous,
        m => m,
    };
    let (xs, ys) = window_axes(rect, width, height);
    let centre = |i: usize, j: usize| [xs[i], ys[j]];
    let values = match chosen {
        Method::Discrete => {
            let opts = iterations.map(DiscreteOptions::fixed).unwrap_or_default();
            let (g, _) = discrete(op, full_w.max(1), full_h.max(1), opts);
            (0..width * height)
                .into_par_iter()
                .map(|k| {
                    let [u, v] = centre(k % width, k / width);
                    sample_bilinear(&g, u * g.width as f32 - 0.5, v * g.height as f32 - 0.5)
                })
                .collect()
        }
        _ => {
            let n = iterations.unwrap_or(12);
            let mut values = vec![0.0f32; width * height];
            values
                .par_chunks_mut(width)
                .enumerate()
                .for_each(|(j, row)| {
                    let pts: Vec<[f32; 2]> = (0..width).map(|i| centre(i, j)).collect();
                    for (v, p) in row.iter_mut().zip(points(op, &pts, n, 0.0)) {
                        *v = p.value;
                    }
                });
            values
        }
    };
    (
        Grid {
            width,
            height,
            values,
        },
        chosen,
    )
}

/// Discrete decoding of a 3D operator over the source extent at `dims` samples per axis (x
/// fastest): the 2D [`discrete`] one dimension up. Each iteration averages the previous iterate
/// over boxes of `expansion^3` voxels and reads it trilinearly at phi of each voxel centre.
/// Memory: about 40 bytes a voxel of the frame at the output scale.
pub fn discrete_volume<O: Operator<3> + ?Sized>(
    op: &O,
    dims: [usize; 3],
    opts: DiscreteOptions,
) -> (Vec<f32>, DiscreteReport) {
    let valid = op.valid();
    let frame = op.frame();
    let e = op.expansion().max(1) as usize;
    let scale: [f32; 3] = std::array::from_fn(|a| dims[a] as f32 / valid[a]);
    let fd: [usize; 3] = std::array::from_fn(|a| {
        ((frame[a] * scale[a]).ceil() as usize)
            .max(dims[a])
            .max(e + 1)
    });
    let bd: [usize; 3] = fd.map(|v| v - e + 1);
    let half = e as f32 * 0.5;
    struct VoxelMap {
        offset: f32,
        contrast: f32,
        index: u32,
        frac: [f32; 3],
    }
    let total = fd[0] * fd[1] * fd[2];
    let maps: Vec<VoxelMap> = (0..total)
        .into_par_iter()
        .map(|i| {
            let c = [i % fd[0], i / fd[0] % fd[1], i / (fd[0] * fd[1])];
            let p: [f32; 3] = std::array::from_fn(|a| (c[a] as f32 + 0.5) / scale[a]);
            let st = op.step(p);
            let mut idx = [0usize; 3];
            let mut frac = [0.0f32; 3];
            for a in 0..3 {
                let b = (st.next[a] * scale[a] - half).clamp(0.0, (bd[a] - 1) as f32);
                idx[a] = (b as usize).min(bd[a] - 2);
                frac[a] = b - idx[a] as f32;
            }
            VoxelMap {
                offset: st.offset,
                contrast: st.contrast,
                index: ((idx[2] * bd[1] + idx[1]) * bd[0] + idx[0]) as u32,
                frac,
            }
        })
        .collect();
    let contraction = maps.iter().fold(0.0f32, |m, p| m.max(p.contrast.abs()));
    let (lo, hi) = op.invariant_interval();
    let mut f = vec![(lo + hi) * 0.5; total];
    let mut next = vec![0.0f32; total];
    let mut boxed = vec![0.0f32; bd[0] * bd[1] * bd[2]];
    let norm = 1.0 / (e * e * e) as f32;
    let (sx, sy, sz) = (1, bd[0], bd[0] * bd[1]);
    let mut report = DiscreteReport {
        iterations: 0,
        last_change: f32::INFINITY,
        error_bound: f32::INFINITY,
    };
    let inside = dims[0] * dims[1] * dims[2];
    while report.iterations < opts.max_iterations {
        boxed
            .par_chunks_mut(bd[0] * bd[1])
            .enumerate()
            .for_each(|(z, slab)| {
                for y in 0..bd[1] {
                    for x in 0..bd[0] {
                        let mut acc = 0.0;
                        for zz in z..z + e {
                            for yy in y..y + e {
                                let row = (zz * fd[1] + yy) * fd[0] + x;
                                acc += f[row..row + e].iter().sum::<f32>();
                            }
                        }
                        slab[y * bd[0] + x] = acc * norm;
                    }
                }
            });
        let (change, largest) = next
            .par_chunks_mut(fd[0])
            .zip(maps.par_chunks(fd[0]))
            .enumerate()
            .map(|(row, (out, mrow))| {
                let (y, z) = (row % fd[1], row / fd[1]);
                let (mut ch, mut mx) = (0.0f64, 0.0f32);
                for (x, (o, m)) in out.iter_mut().zip(mrow).enumerate() {
                    let i = m.index as usize;
                    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
                    let [fx, fy, fz] = m.frac;
                    let plane = |k: usize| {
                        lerp(
                            lerp(boxed[k], boxed[k + sx], fx),
                            lerp(boxed[k + sy], boxed[k + sy + sx], fx),
                            fy,
                        )
                    };
                    let v = m.offset + m.contrast * lerp(plane(i), plane(i + sz), fz);
                    let d = (v - f[row * fd[0] + x]).abs();
                    if x < dims[0] && y < dims[1] && z < dims[2] {
                        ch += d as f64;
                    }
                    mx = mx.max(d);
                    *o = v;
                }
                (ch, mx)
            })
            .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1.max(b.1)));
        std::mem::swap(&mut f, &mut next);
        report.iterations += 1;
        report.last_change = (change / inside as f64) as f32;
        report.error_bound = contraction / (1.0 - contraction) * largest;
        if report.last_change < opts.min_change || report.error_bound <= opts.max_error {
            break;
        }
    }
    let mut values = Vec::with_capacity(inside);
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            let row = (z * fd[1] + y) * fd[0];
            values.extend_from_slice(&f[row..row + dims[0]]);
        }
    }
    (values, report)
}

/// The unit coordinates of the samples of a box `[lo, hi]` of the unit cube at `dims` samples
/// per axis: the corners and evenly between them (one sample: the middle). Computed in f64 and
/// rounded once; the GPU's boxes take the same axes, so both decode the same points.
pub fn volume_axes(lo: [f32; 3], hi: [f32; 3], dims: [usize; 3]) -> [Vec<f32>; 3] {
    std::array::from_fn(|a| {
        let (l, h) = (f64::from(lo[a]), f64::from(hi[a]));
        match dims[a] {
            0 => Vec::new(),
            1 => vec![(0.5 * (l + h)) as f32],
            n => (0..n)
                .map(|i| (l + (h - l) * i as f64 / (n - 1) as f64) as f32)
                .collect(),
        }
    })
}

/// Continuous decoding of a box `[lo, hi]` of the unit cube at `dims` samples per axis (x
/// fastest), the samples at the corners and evenly between them (what an isosurface wants:
/// neighbouring boxes share their faces). Returns the values and the largest error bound.
pub fn volume_window<O: Operator<3> + ?Sized>(
    op: &O,
    lo: [f32; 3],
    hi: [f32; 3],
    dims: [usize; 3],
    iterations: u32,
    tolerance: f32,
) -> (Vec<f32>, f32) {
    let [xs, ys, zs] = volume_axes(lo, hi, dims);
    let rows: Vec<(Vec<f32>, f32)> = (0..dims[1] * dims[2])
        .into_par_iter()
        .map(|r| {
            let (y, z) = (ys[r % dims[1]], zs[r / dims[1]]);
            let pts: Vec<[f32; 3]> = xs.iter().map(|&x| [x, y, z]).collect();
            let pv = points(op, &pts, iterations, tolerance);
            let bound = pv.iter().fold(0.0f32, |m, p| m.max(p.error_bound));
            (pv.into_iter().map(|p| p.value).collect(), bound)
        })
        .collect();
    let bound = rows.iter().fold(0.0f32, |m, r| m.max(r.1));
    (rows.into_iter().flat_map(|r| r.0).collect(), bound)
}

/// Bilinear sample of a grid at continuous pixel coordinates (pixel centres at integers), clamped.
pub fn sample_bilinear(g: &Grid, x: f32, y: f32) -> f32 {
    let x = x.clamp(0.0, (g.width - 1) as f32);
    let y = y.clamp(0.0, (g.height - 1) as f32);
    let (x0, y0) = (x as usize, y as usize);
    let (x1, y1) = ((x0 + 1).min(g.width - 1), (y0 + 1).min(g.height - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = |x: usize, y: usize| g.values[y * g.width + x];
    let top = at(x0, y0) + (at(x1, y0) - at(x0, y0)) * fx;
    let bot = at(x0, y1) + (at(x1, y1) - at(x0, y1)) * fx;
    top + (bot - top) * fy
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::operator::{Step, invariant_interval};

    /// Area means: whole blocks where the sizes divide, weighed parts where they do not (each
    /// new cell's mean of the box it covers, on a grid that is x + 10 y, whose box means are
    /// the box centre's value), and NaN cells left out.
    #[test]
    fn area_means_are_the_means_of_the_boxes_covered() {
        let plane = |w: usize, h: usize| Grid {
            width: w,
            height: h,
            values: (0..w * h)
                .map(|k| (k % w) as f32 + 10.0 * (k / w) as f32)
                .collect(),
        };
        // The grid is separable and linear in the cell index, so a box's mean is the mean
        // index covered along x plus ten times along y, each cell weighed by its overlap.
        let mean_index = |i: usize, n: usize, m: usize| {
            let (a, b) = (
                i as f64 * n as f64 / m as f64,
                (i + 1) as f64 * n as f64 / m as f64,
            );
            let (mut sum, mut weight) = (0.0, 0.0);
            for k in 0..n {
                let o = (b.min(k as f64 + 1.0) - a.max(k as f64)).max(0.0);
                sum += o * k as f64;
                weight += o;
            }
            sum / weight
        };
        for (w, h, nw, nh) in [(8, 6, 4, 3), (7, 5, 3, 2), (9, 9, 4, 4), (5, 3, 5, 1)] {
            let got = plane(w, h).area_means(nw, nh);
            for (k, v) in got.values.iter().enumerate() {
                let want = (mean_index(k % nw, w, nw) + 10.0 * mean_index(k / nw, h, nh)) as f32;
                if w % nw == 0 && h % nh == 0 {
                    // Whole blocks: the block's centre.
                    let (fx, fy) = ((w / nw) as f32, (h / nh) as f32);
                    let (i, j) = ((k % nw) as f32, (k / nw) as f32);
                    let centre = (i + 0.5) * fx - 0.5 + 10.0 * ((j + 0.5) * fy - 0.5);
                    assert!((want - centre).abs() < 1e-4);
                }
                assert!(
                    (v - want).abs() < 1e-4,
                    "{w}x{h} -> {nw}x{nh} at {k}: {v} {want}"
                );
            }
        }
        let mut g = plane(4, 2);
        g.values[0] = f32::NAN;
        g.values[2] = f32::NAN;
        g.values[3] = f32::NAN;
        g.values[7] = f32::NAN;
        let got = g.area_means(2, 1);
        // Left box: 1, 10 and 11 remain; right box: 12 alone.
        assert_eq!(got.values[0], (1.0 + 10.0 + 11.0) / 3.0);
        assert_eq!(got.values[1], 12.0);
        let none = Grid {
            width: 2,
            height: 1,
            values: vec![f32::NAN; 2],
        };
        assert!(none.area_means(1, 1).values[0].is_nan());
    }

    #[test]
    fn volume_axes_hold_the_corners_and_even_steps_between() {
        let [xs, ys, zs] = volume_axes([0.1, 0.25, 0.3], [0.7, 0.75, 0.3], [7, 5, 1]);
        assert_eq!((xs[0], xs[6]), (0.1, 0.7));
        assert_eq!(ys, [0.25, 0.375, 0.5, 0.625, 0.75]);
        // One sample: the middle of the span.
        assert_eq!(zs, [0.3]);
        // Evenly spaced to f32 rounding: 0.1 + k * 0.1 for k = 0..6.
        for (k, x) in xs.iter().enumerate() {
            assert!((x - (0.1 + 0.1 * k as f32)).abs() <= 1e-7, "{k}: {x}");
        }
    }

    #[test]
    fn shrink_averages_blocks_and_keeps_nodata() {
        // 4 x 2 -> 2 x 1: blocks {1, 2, 5, 6} and {3, NaN, 7, NaN}.
        let g = Grid {
            width: 4,
            height: 2,
            values: vec![1.0, 2.0, 3.0, f32::NAN, 5.0, 6.0, 7.0, f32::NAN],
        };
        let c = g.shrink(2, 2).unwrap();
        assert_eq!((c.width, c.height), (2, 1));
        assert_eq!(c.values, vec![3.5, 5.0]);
        // Rows only, and a block of nodata alone.
        let r = Grid {
            width: 1,
            height: 4,
            values: vec![f32::NAN, f32::NAN, 2.0, 4.0],
        }
        .shrink(1, 2)
        .unwrap();
        assert!(r.values[0].is_nan() && r.values[1] == 3.0);
        assert!(g.shrink(3, 1).is_none() && g.shrink(0, 1).is_none());
    }

    /// Four cells of 4 on an 8x8 frame, each mapping its quadrant onto the whole frame (a flip
    /// for some), with constant contrast and offset: decoders are tested on the operator form
    /// alone, without a codec.
    struct Toy;

    /// (contrast, offset, flip x, flip y) of the cells, row-major.
    const CELLS: [(f32, f32, bool, bool); 4] = [
        (0.5, 0.1, false, false),
        (-0.5, 0.7, true, false),
        (0.25, 0.3, true, true),
        (0.0, 0.9, false, false),
    ];

    impl Operator<2> for Toy {
        fn frame(&self) -> [f32; 2] {
            [8.0, 8.0]
        }
        fn valid(&self) -> [f32; 2] {
            [8.0, 8.0]
        }
        fn expansion(&self) -> u32 {
            2
        }
        fn step(&self, p: [f32; 2]) -> Step<2> {
            let p = p.map(|t| t.clamp(0.0, 8.0));
            let (cx, cy) = (usize::from(p[0] >= 4.0), usize::from(p[1] >= 4.0));
            let (contrast, offset, fx, fy) = CELLS[cy * 2 + cx];
            let local = |t: f32, c: usize, flip: bool| {
                let u = ((t - 4.0 * c as f32) / 4.0).clamp(0.0, 1.0);
                8.0 * if flip { 1.0 - u } else { u }
            };
            Step {
                offset,
                contrast,
                next: [local(p[0], cx, fx), local(p[1], cy, fy)],
            }
        }
        fn invariant_interval(&self) -> (f32, f32) {
            invariant_interval(CELLS.iter().map(|&(s, o, _, _)| (s, o, o)))
        }
    }

    fn toy() -> Toy {
        Toy
    }

    #[test]
    fn point_values_satisfy_the_fixed_point_equation() {
        // f(p) = o + s f(phi(p)) must hold for the decoded values, up to the bounds.
        let op = toy();
        for &(u, v) in &[(0.1f32, 0.2f32), (0.7, 0.1), (0.3, 0.9), (0.55, 0.45)] {
            let a = point(&op, [u, v], 40);
            let st = op.step([u * 8.0, v * 8.0]);
            let b = point(&op, [st.next[0] / 8.0, st.next[1] / 8.0], 40);
            let rhs = st.offset + st.contrast * b.value;
            assert!(
                (a.value - rhs).abs() <= a.error_bound + b.error_bound + 1e-5,
                "{a:?} vs {rhs}"
            );
        }
    }

    #[test]
    fn bound_holds_and_shrinks() {
        let op = toy();
        let mut last = f32::INFINITY;
        for n in 1..20 {
            let r = point(&op, [0.2, 0.3], n);
            let reference = point(&op, [0.2, 0.3], 200);
            assert!((r.value - reference.value).abs() <= r.error_bound + 1e-6);
            assert!(r.error_bound <= last);
            last = r.error_bound;
        }
    }

    #[test]
    fn constant_map_is_exact_in_one_step() {
        let r = point(&toy(), [0.9, 0.9], 10);
        assert_eq!(r.iterations, 1);
        assert_eq!(r.error_bound, 0.0);
        assert!((r.value - 0.9).abs() < 1e-6);
    }

    #[test]
    fn discrete_decoding_at_any_size_converges_to_the_same_picture() {
        let op = toy();
        let (a, ra) = discrete(&op, 8, 8, DiscreteOptions::fixed(60));
        assert!(ra.last_change < 1e-5);
        // Each output pixel must satisfy the discrete fixed-point equation exactly at size 8.
        let (b, _) = discrete(&op, 32, 32, DiscreteOptions::fixed(60));
        let (c, _) = discrete(&op, 5, 13, DiscreteOptions::fixed(60));
        // Means over quadrants agree across sizes (same attractor, other sampling).
        let mean = |g: &Grid| g.values.iter().sum::<f32>() / g.values.len() as f32;
        assert!(
            (mean(&a) - mean(&b)).abs() < 0.02,
            "{} {}",
            mean(&a),
            mean(&b)
        );
        assert!(
            (mean(&a) - mean(&c)).abs() < 0.05,
            "{} {}",
            mean(&a),
            mean(&c)
        );
        // The constant range decodes to its offset everywhere.
        assert!((b.values[31 * 32 + 31] - 0.9).abs() < 1e-6);
    }

    #[test]
    fn batched_points_equal_single_points() {
        let op = toy();
        let pts: Vec<[f32; 2]> = (0..37)
            .map(|i| [(i as f32 * 0.37) % 1.0, (i as f32 * 0.61) % 1.0])
            .collect();
        let batch = points(&op, &pts, 15, 0.0);
        for (p, b) in pts.iter().zip(&batch) {
            let single = point(&op, *p, 15);
            assert!(
                (single.value - b.value).abs() < 1e-6 && single.iterations == b.iterations,
                "{single:?} {b:?}"
            );
        }
    }
}
