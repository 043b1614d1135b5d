//! The pyramid's prediction ([`super::pyramid`]): the groups of coarser samples each pass reads,
//! their means as features, the fitted mask weights over them (least squares in the encoder),
//! and the relief of the nearest samples that picks a detail's context. Every sum here is the
//! one formats up to 9 were written with, in the same order: the encoder predicted from these
//! bits, so a decoder must too.

/// Relief buckets of a context (local relief over the step).
pub(super) const RELIEF_BUCKETS: usize = 8;

/// Fixed-point denominator of the fitted mask weights.
pub const WEIGHT_ONE: f64 = 1024.0;
/// Largest |weight| index (weights in [-2, 2]).
pub(super) const WEIGHT_LIMIT: i32 = 2048;

/// Features of a pass's prediction. Each is the mean of a group of samples (offsets in units
/// of half the coarser spacing) less the mean of the nearest samples (group 0, whose mean is
/// the plain prediction). The fitted masks weigh them, so a pass can lean on the direction
/// the terrain runs in. Two orders of the passes ([`super::pyramid::Order`]); an empty group is a feature
/// that is always 0.
pub const FEATURES: usize = 3;
pub(super) type Groups = [&'static [[i64; 2]]; FEATURES + 1];
pub(super) const GROUPS: [[Groups; 3]; 2] = [
    // Separable: rows, then columns, then faces.
    [
        [
            &[[-1, 0], [1, 0]],
            &[[-3, 0], [3, 0]],
            &[[-1, -2], [1, -2], [-1, 2], [1, 2]],
            &[],
        ],
        [
            &[[0, -1], [0, 1]],
            &[[0, -3], [0, 3]],
            &[[-2, -1], [-2, 1], [2, -1], [2, 1]],
            &[[-1, -1], [1, -1], [-1, 1], [1, 1]],
        ],
        [
            &[[-1, 0], [1, 0], [0, -1], [0, 1]],
            &[[-1, 0], [1, 0]],
            &[[-1, -1], [1, -1], [-1, 1], [1, 1]],
            &[[-3, 0], [3, 0], [0, -3], [0, 3]],
        ],
    ],
    // Quincunx: faces from the coarser corners, then rows and columns from four neighbours.
    [
        [
            &[[-1, -1], [1, -1], [-1, 1], [1, 1]],
            &[[-1, -1], [1, 1]],
            &[[-3, -1], [3, -1], [-3, 1], [3, 1]],
            &[[-1, -3], [1, -3], [-1, 3], [1, 3]],
        ],
        [
            &[[-1, 0], [1, 0], [0, -1], [0, 1]],
            &[[-1, 0], [1, 0]],
            &[[-3, 0], [3, 0]],
            &[[0, -3], [0, 3]],
        ],
        [
            &[[0, -1], [0, 1], [-1, 0], [1, 0]],
            &[[0, -1], [0, 1]],
            &[[0, -3], [0, 3]],
            &[[-3, 0], [3, 0]],
        ],
    ],
];

/// Relief bucket of a spread over a step: 0 under half a step, else 1 + floor(log2(2a)) of
/// a = spread / step, at most 7: the definition formats up to 9 were written with, which
/// [`Relief`] reproduces without a division and a call to libm a sample.
fn relief(spread: f64, step: f64) -> usize {
    let a = spread / step;
    if a < 0.5 {
        0
    } else {
        ((a / 0.5).log2() as usize + 1).min(RELIEF_BUCKETS - 1)
    }
}

/// The relief buckets of one step as the spreads where each starts: a sample's bucket is then
/// a count of comparisons. Each edge is the least spread that [`relief`] puts in its bucket or
/// above (it is monotonic in the spread: a correctly rounded quotient, then log2), found from
/// the power of two times the step downwards: log2 rounds quotients within an ulp or two
/// below a power up onto it, so the edge lies a few ulps under the product. Found by the
/// same libm as a decoder of older files on this platform used, so the same buckets.
pub(super) struct Relief([f64; RELIEF_BUCKETS - 1]);

impl Relief {
    pub(super) fn new(step: f64) -> Relief {
        Relief(std::array::from_fn(|b| {
            let mut edge = 0.5 * f64::from(1u32 << b) * step;
            if !(edge.is_finite() && edge > 0.0 && relief(edge, step) > b) {
                // No such step is ever coded (validated headers); any edge will do.
                return edge;
            }
            let below = |e: f64| f64::from_bits(e.to_bits() - 1);
            while edge > 0.0 && relief(below(edge), step) > b {
                edge = below(edge);
            }
            edge
        }))
    }

    #[inline(always)]
    pub(super) fn bucket(&self, spread: f64) -> usize {
        self.0.iter().map(|&e| usize::from(spread >= e)).sum()
    }
}

/// The mean of the samples at `offsets` (times `half`) from (x, y) that lie in the grid, with
/// their count, min and max.
fn ring(
    g: &[f64],
    size: [usize; 2],
    x: usize,
    y: usize,
    half: usize,
    offsets: &[[i64; 2]],
) -> (f64, usize, f64, f64) {
    let (mut sum, mut n, mut lo, mut hi) = (0.0, 0, f64::INFINITY, f64::NEG_INFINITY);
    for [dx, dy] in offsets {
        let (px, py) = (x as i64 + dx * half as i64, y as i64 + dy * half as i64);
        if px < 0 || py < 0 || px >= size[0] as i64 || py >= size[1] as i64 {
            continue;
        }
        let v = g[py as usize * size[0] + px as usize];
        sum += v;
        n += 1;
        lo = lo.min(v);
        hi = hi.max(v);
    }
    (if n > 0 { sum / n as f64 } else { 0.0 }, n, lo, hi)
}

/// [`ring`] about row-major index `i`, every sample known to lie in the grid, at `offsets`
/// from it (row-major, already times `half`): the mean, min and max.
#[inline(always)]
fn ring_inside(g: &[f64], i: usize, offsets: &[isize]) -> (f64, f64, f64) {
    let at = |d: isize| g[i.wrapping_add_signed(d)];
    // Comparisons, not `f64::min`: the same on the finite samples a walk holds, without the
    // NaN fix-ups. Groups of 2 and 4 unrolled, their means by the exact reciprocals (the
    // quotients' bits); the sums in the loop's order.
    let lo = |a: f64, b: f64| if b < a { b } else { a };
    let hi = |a: f64, b: f64| if b > a { b } else { a };
    match *offsets {
        [a, b] => {
            let (va, vb) = (at(a), at(b));
            (((0.0 + va) + vb) * 0.5, lo(va, vb), hi(va, vb))
        }
        [a, b, c, d] => {
            let (va, vb, vc, vd) = (at(a), at(b), at(c), at(d));
            let sum = (((0.0 + va) + vb) + vc) + vd;
            let (l, h) = (lo(lo(va, vb), lo(vc, vd)), hi(hi(va, vb), hi(vc, vd)));
            (sum * 0.25, l, h)
        }
        _ => {
            let (mut sum, mut l, mut h) = (0.0, f64::INFINITY, f64::NEG_INFINITY);
            for &d in offsets {
                let v = at(d);
                sum += v;
                l = l.min(v);
                h = h.max(v);
            }
            let n = offsets.len();
            (if n > 0 { sum / n as f64 } else { 0.0 }, l, h)
        }
    }
}

/// [`ring_inside`] for a group of `N` samples known when compiled (2 or 4: their means by
/// exact reciprocals; 0: an empty group).
#[inline(always)]
fn ring_fixed<const N: usize>(g: &[f64], i: usize, offsets: &[isize; N]) -> (f64, f64, f64) {
    let (mut sum, mut lo, mut hi) = (0.0, f64::INFINITY, f64::NEG_INFINITY);
    for &d in offsets {
        let v = g[i.wrapping_add_signed(d)];
        sum += v;
        lo = if v < lo { v } else { lo };
        hi = if v > hi { v } else { hi };
    }
    let mean = match N {
        0 => 0.0,
        2 => sum * 0.5,
        4 => sum * 0.25,
        _ => sum / N as f64,
    };
    (mean, lo, hi)
}

/// A pass's groups at one level, and their row-major offsets (times `half`) for the points
/// that lie 3 halves or more inside the grid.
pub(super) struct Rings {
    groups: Groups,
    offsets: [Vec<isize>; FEATURES + 1],
    half: usize,
}

impl Rings {
    pub(super) fn new(groups: &Groups, w: usize, half: usize) -> Rings {
        Rings {
            groups: *groups,
            offsets: std::array::from_fn(|k| linear(groups[k], w, half)),
            half,
        }
    }

    /// [`predict`]'s prediction with weights `w` and its spread (the same sums in the same
    /// order, so the same bits).
    #[inline(always)]
    pub(super) fn predict(
        &self,
        (g, size): (&[f64], [usize; 2]),
        (x, y): (usize, usize),
        w: [f64; FEATURES],
    ) -> (f64, f64) {
        if !self.inside(size, x, y) {
            let (pred, _, spread) = predict(g, size, x, y, self.half, &self.groups, w);
            return (pred, spread);
        }
        let (m, f, spread) = self.inner(g, y * size[0] + x);
        let mut pred = m;
        for ((fk, wk), offsets) in f.iter().zip(w).zip(&self.offsets[1..]) {
            if !offsets.is_empty() {
                pred += wk * fk;
            }
        }
        (pred, spread)
    }

    /// [`Self::predict`] for the points `(x0 + k s, y)` of a row, in order, each handed to
    /// `put` as its prediction and spread. The points whose groups all lie in the grid are
    /// predicted by a loop made for the pass's group sizes (every pass has groups of 2 and 4,
    /// or none): no dispatch on a group's size, no test of the edges a point, the same sums.
    /// Why: the walk's predictions were a third of a whole read (issue 75).
    #[inline(always)]
    pub(super) fn predict_row(
        &self,
        (g, size): (&[f64], [usize; 2]),
        y: usize,
        (x0, s): (usize, usize),
        w: [f64; FEATURES],
        mut put: impl FnMut(f64, f64),
    ) {
        let reach = 3 * self.half;
        let count = size[0].saturating_sub(x0).div_ceil(s);
        let (first, end) = if y < reach || y + reach >= size[1] {
            (count, count)
        } else {
            let first = reach.saturating_sub(x0).div_ceil(s).min(count);
            // Points with x + reach < width.
            let end = size[0]
                .saturating_sub(reach + x0)
                .div_ceil(s)
                .clamp(first, count);
            (first, end)
        };
        let edge = |k: usize, put: &mut dyn FnMut(f64, f64)| {
            let (p, spread) = self.predict((g, size), (x0 + k * s, y), w);
            put(p, spread);
        };
        for k in 0..first {
            edge(k, &mut put);
        }
        let i0 = y * size[0] + x0;
        let inner = (i0 + first * s, s, end - first);
        match self.offsets.each_ref().map(Vec::len) {
            [2, 2, 4, 0] => self.inner_row::<2, 2, 4, 0>(g, inner, w, &mut put),
            [2, 2, 4, 4] => self.inner_row::<2, 2, 4, 4>(g, inner, w, &mut put),
            [4, 2, 4, 4] => self.inner_row::<4, 2, 4, 4>(g, inner, w, &mut put),
            [4, 2, 2, 2] => self.inner_row::<4, 2, 2, 2>(g, inner, w, &mut put),
            _ => (first..end).for_each(|k| edge(k, &mut put)),
        }
        for k in end..count {
            edge(k, &mut put);
        }
    }

    /// The points `i, i + s, ...` (`n` of them, every group inside) of a pass whose groups
    /// hold `A`, `B`, `C` and `D` samples: [`Self::inner`] and the weighted sum of
    /// [`Self::predict`], unrolled.
    #[inline(always)]
    fn inner_row<const A: usize, const B: usize, const C: usize, const D: usize>(
        &self,
        g: &[f64],
        (i, s, n): (usize, usize, usize),
        w: [f64; FEATURES],
        put: &mut impl FnMut(f64, f64),
    ) {
        let fixed = |k: usize| self.offsets[k].as_slice();
        let (Ok(a), Ok(b), Ok(c), Ok(d)) = (
            <[isize; A]>::try_from(fixed(0)),
            <[isize; B]>::try_from(fixed(1)),
            <[isize; C]>::try_from(fixed(2)),
            <[isize; D]>::try_from(fixed(3)),
        ) else {
            unreachable!("inner_row is called with its groups' sizes")
        };
        for k in 0..n {
            let at = i + k * s;
            let (m, lo, hi) = ring_fixed(g, at, &a);
            let mut pred = m;
            if B > 0 {
                pred += w[0] * (ring_fixed(g, at, &b).0 - m);
            }
            if C > 0 {
                pred += w[1] * (ring_fixed(g, at, &c).0 - m);
            }
            if D > 0 {
                pred += w[2] * (ring_fixed(g, at, &d).0 - m);
            }
            put(pred, hi - lo);
        }
    }

    /// What a fit reads of `(x, y)`: [`predict`]'s mean of the nearest samples and features.
    pub(super) fn features(
        &self,
        (g, size): (&[f64], [usize; 2]),
        (x, y): (usize, usize),
    ) -> (f64, [f64; FEATURES]) {
        if !self.inside(size, x, y) {
            let (m, f, _) = predict(g, size, x, y, self.half, &self.groups, [0.0; FEATURES]);
            return (m, f);
        }
        let (m, f, _) = self.inner(g, y * size[0] + x);
        (m, f)
    }

    /// Whether every group of `(x, y)` lies in the grid: it reaches 3 halves away.
    #[inline(always)]
    fn inside(&self, size: [usize; 2], x: usize, y: usize) -> bool {
        let reach = 3 * self.half;
        x >= reach && y >= reach && x + reach < size[0] && y + reach < size[1]
    }

    /// The mean of the nearest samples of a point inside (row-major index `i`), its features
    /// and its nearest samples' spread, read unchecked.
    #[inline(always)]
    fn inner(&self, g: &[f64], i: usize) -> (f64, [f64; FEATURES], f64) {
        let (m, lo, hi) = ring_inside(g, i, &self.offsets[0]);
        let mut f = [0.0; FEATURES];
        for (fk, offsets) in f.iter_mut().zip(&self.offsets[1..]) {
            if !offsets.is_empty() {
                *fk = ring_inside(g, i, offsets).0 - m;
            }
        }
        (m, f, hi - lo)
    }
}

/// A group's offsets (times `half`) as row-major offsets in a grid `w` wide.
fn linear(offsets: &[[i64; 2]], w: usize, half: usize) -> Vec<isize> {
    let (w, h) = (w as isize, half as isize);
    offsets
        .iter()
        .map(|&[dx, dy]| (dx as isize + dy as isize * w) * h)
        .collect()
}

/// The prediction of `(x, y)` in pass `pass` with weights `w` near the grid's edges (where
/// [`Rings`] does not read unchecked): the mean of the nearest samples
/// plus the weighted features (a feature whose group leaves the grid counts 0: no say). Also
/// the features (for fitting) and the nearest samples' spread (for the context).
fn predict(
    g: &[f64],
    size: [usize; 2],
    x: usize,
    y: usize,
    half: usize,
    groups: &Groups,
    w: [f64; FEATURES],
) -> (f64, [f64; FEATURES], f64) {
    let ring = |offsets: &[[i64; 2]]| ring(g, size, x, y, half, offsets);
    let (m, _, lo, hi) = ring(groups[0]);
    let mut f = [0.0; FEATURES];
    let mut pred = m;
    for k in 0..FEATURES {
        let (mean, n, ..) = ring(groups[k + 1]);
        if n > 0 && n == groups[k + 1].len() {
            f[k] = mean - m;
            pred += w[k] * f[k];
        }
    }
    (pred, f, hi - lo)
}

/// Least-squares weights (as fixed-point indices) of a pass from its points' features and
/// targets (the source less the plain mean): normal equations with a whisker of ridge, so that a
/// feature that never varies gets weight 0.
pub(super) fn fit_weights(rows: &[(f64, [f64; FEATURES])]) -> [i32; FEATURES] {
    const K: usize = FEATURES;
    let mut a = [[0.0f64; K + 1]; K];
    for (y, f) in rows {
        for i in 0..K {
            for j in 0..K {
                a[i][j] += f[i] * f[j];
            }
            a[i][K] += f[i] * y;
        }
    }
    let scale = (0..K).map(|i| a[i][i]).fold(0.0, f64::max);
    for (i, row) in a.iter_mut().enumerate() {
        row[i] += 1e-9 * scale + 1e-300;
    }
    // Gauss-Jordan with partial pivoting on a 3 x 3 system.
    for c in 0..K {
        let p = (c..K)
            .max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))
            .unwrap_or(c);
        a.swap(c, p);
        let d = a[c][c];
        if d.abs() < 1e-300 {
            return [0; K];
        }
        for v in a[c].iter_mut() {
            *v /= d;
        }
        for r in 0..K {
            if r != c {
                let k = a[r][c];
                let pivot = a[c];
                for (v, pv) in a[r].iter_mut().zip(pivot) {
                    *v -= k * pv;
                }
            }
        }
    }
    std::array::from_fn(|i| {
        ((a[i][K] * WEIGHT_ONE).round() as i32).clamp(-WEIGHT_LIMIT, WEIGHT_LIMIT)
    })
}

#[cfg(test)]
mod tests {
    use super::{Relief, relief};

    /// The relief buckets by their edges are `relief`'s (formats up to 9), at each edge and
    /// the spreads an ulp either side, and at random spreads, on odd steps of integer data and
    /// on steps of float data.
    #[test]
    fn relief_edges_bucket_as_the_quotient_does() {
        use proptest::prelude::Rng;
        // proptest's deterministic generator: the same draws every run.
        let mut rng = proptest::test_runner::TestRng::deterministic_rng(
            proptest::test_runner::RngAlgorithm::ChaCha,
        );
        let mut next = || rng.next_u64();
        let mut moved = 0;
        for k in 0..2000 {
            let step = if k % 2 == 0 {
                (2 * (next() % 400) + 1) as f64
            } else {
                (next() % 1_000_000) as f64 * 1.37e-4 + 1e-9
            };
            let edges = Relief::new(step);
            for (b, &e) in edges.0.iter().enumerate() {
                let below = f64::from_bits(e.to_bits() - 1);
                assert_eq!(edges.bucket(e), b + 1);
                assert_eq!(edges.bucket(below), b);
                for s in [e, below, f64::from_bits(e.to_bits() + 1)] {
                    assert_eq!(edges.bucket(s), relief(s, step), "spread {s} step {step}");
                }
                // Edges below the plain product: log2 rounds up onto the power.
                moved += usize::from(e < 0.5 * f64::from(1u32 << b) * step);
            }
            for _ in 0..20 {
                let s = (next() % 100_000) as f64 * step / 997.0;
                assert_eq!(edges.bucket(s), relief(s, step), "spread {s} step {step}");
            }
        }
        assert!(
            moved > 0,
            "no edge needed the step down: the test proves nothing of it"
        );
    }
}
