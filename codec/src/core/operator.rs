//! The partitioned affine operator every codec of fractile is written as:
//! for a point p in cell c, `(W f)(p) = g_c(p) + s_c(p) * f(phi_c(p))`, |s_c| < 1.
//!
//! Decoders ([`crate::core::decode`]) know nothing else. A codec provides [`Operator::step`], which finds
//! the cell of a point and returns g, s and phi there; the quadtree IFS here has constant g (offset)
//! and s (contrast) per range and phi mapping the range onto its domain (scale 2, one of 8
//! isometries). Fractal interpolation surfaces plug in later with bilinear g and s.

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
    /// `iterations` steps in all or [`crate::core::operator::active`] says it is done. The default steps
    /// them through [`Operator::step`]; a codec may override it with a layout of its maps made
    /// for the loop, giving the same answers bit for bit.
    fn run_chains(&self, chains: &mut [Chain<D>], iterations: u32, tolerance: f32) {
        run_chains_stepwise(self, chains, iterations, tolerance);
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
/// steps together, since its image is again a separable grid; [`crate::core::decode::grid`] uses this.
pub trait AxisAligned: Operator<2> {
    /// The lattice column (`axis` 0) or row (`axis` 1) of frame coordinate `t`, computed exactly as
    /// [`Operator::step`] finds a point's cell.
    fn lattice(&self, axis: usize, t: f32) -> usize;
    /// The cell that covers lattice square (`col`, `row`).
    fn axis_cell(&self, col: usize, row: usize) -> AxisCell;
}

/// The least and the greatest of finite samples. Comparisons, not `f32::min` (a call to libm in
/// WebAssembly: 5% of a first tile there), in eight lanes kept in vector registers (one chain
/// was 5% of a whole read, issue 75): on finite values their order changes nothing.
pub(crate) fn extremes(z: &[f32]) -> (f32, f32) {
    let (lo, hi) = (
        |a: f32, v: f32| if v < a { v } else { a },
        |a: f32, v: f32| if v > a { v } else { a },
    );
    let (mut l, mut h) = ([f32::INFINITY; 8], [f32::NEG_INFINITY; 8]);
    let lanes = z.chunks_exact(8);
    let rest = lanes.remainder();
    for c in lanes {
        for k in 0..8 {
            (l[k], h[k]) = (lo(l[k], c[k]), hi(h[k], c[k]));
        }
    }
    let l = rest.iter().chain(&l).fold(f32::INFINITY, |a, &v| lo(a, v));
    (
        l,
        rest.iter()
            .chain(&h)
            .fold(f32::NEG_INFINITY, |a, &v| hi(a, v)),
    )
}

/// The smallest interval I with `hull(g_c + s_c * I) ⊂ I` over all cells, where each cell gives
/// `(s, g_min, g_max)`, the range of its offset function over the cell; found by iterating that
/// map from [0, 1] (a constant-offset fractile operator keeps [0, 1] invariant, see
/// `crate::core::transform`; a planar one may overshoot it a little, and the iteration finds by how much).
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

/// One inverse-iteration chain in flight: where it is (frame coordinates), and
/// `sum g_k prod_{j<k} s_j`, `prod s` and the steps taken so far.
#[derive(Clone, Copy, Debug)]
pub struct Chain<const D: usize> {
    /// The current point, in frame coordinates.
    pub q: [f32; D],
    /// `sum g_k prod_{j<k} s_j` so far.
    pub acc_g: f32,
    /// `prod s_k` so far.
    pub acc_s: f32,
    /// Inverse steps taken.
    pub taken: u32,
}

/// Whether a chain whose contrast product is `s` still needs steps: it is exact once a map
/// with s = 0 ended it, and good enough once its bound `|s| * half` is under the tolerance.
/// Every decoding path decides with this one function, so that they agree bit for bit.
#[inline(always)]
pub fn active(s: f32, half: f32, tolerance: f32) -> bool {
    s != 0.0 && s.abs() * half > tolerance
}

/// What [`Operator::run_chains`] does unless a codec lays its maps out better: chains eight at a
/// time in lockstep, each stepped by [`Operator::step`] until it has taken `iterations` steps in
/// all or [`active`] says it is done. A finished lane is frozen, so that a chain's answer
/// depends on its point alone, never on the other chains of its batch.
pub fn run_chains_stepwise<const D: usize, O: Operator<D> + ?Sized>(
    op: &O,
    chains: &mut [Chain<D>],
    iterations: u32,
    tolerance: f32,
) {
    const LANES: usize = 8;
    let (lo, hi) = op.invariant_interval();
    let half = (hi - lo) * 0.5;
    for batch in chains.chunks_mut(LANES) {
        let mut q = [[0.0f32; D]; LANES];
        let mut acc_g = [0.0f32; LANES];
        // Padding lanes of the last batch start finished.
        let mut acc_s = [0.0f32; LANES];
        let mut taken = [0u32; LANES];
        for (l, c) in batch.iter().enumerate() {
            (q[l], acc_g[l], acc_s[l], taken[l]) = (c.q, c.acc_g, c.acc_s, c.taken);
        }
        loop {
            let mut any = false;
            for l in 0..LANES {
                if taken[l] >= iterations || !active(acc_s[l], half, tolerance) {
                    continue;
                }
                let st = op.step(q[l]);
                taken[l] += 1;
                acc_g[l] += acc_s[l] * st.offset;
                acc_s[l] *= st.contrast;
                q[l] = st.next;
                any = true;
            }
            if !any {
                break;
            }
        }
        for (l, c) in batch.iter_mut().enumerate() {
            (c.q, c.acc_g, c.acc_s, c.taken) = (q[l], acc_g[l], acc_s[l], taken[l]);
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
}
