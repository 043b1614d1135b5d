//! Continuous decoding: the value at real points by inverse iteration (chains), with their
//! a-priori bounds, and separable grids of points by blocks that step together.

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
pub(super) fn seed_of<const D: usize, O: Operator<D> + ?Sized>(op: &O) -> (f32, f32) {
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
pub(super) fn run_chains<const D: usize, O: Operator<D> + ?Sized>(
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
