//! The lifting's kernels: the predict and update steps along one axis (a fitted four-point
//! predict with the update of the 5/3 family, or CDF 9/7), the lines of a level they run on,
//! their fit, forward and inverse transforms, and the synthesis gains that set band steps.

use super::pyramid::{Order, WEIGHT_ONE};

/// The (4, 4) update after the fitted prediction: `u1 (d-1 + d+1) + u3 (d-3 + d+3)`.
pub(super) const UPDATE: [f64; 2] = [9.0 / 32.0, -1.0 / 32.0];
/// The CDF 9/7 lifting steps (Daubechies and Sweldens), each `(parity of the samples it
/// changes, weight of their two neighbours)`; its final scaling is left out, since a band's
/// step is set from its synthesis gain, which absorbs it.
pub(super) const CDF97: [(isize, f64); 4] = [
    (1, -1.586_134_342_059_924),
    (0, -0.052_980_118_572_961),
    (1, 0.882_911_075_530_934),
    (0, 0.443_506_852_043_971),
];
/// Range of a fitted prediction weight index (a in [-1/4, 1/2]): beyond it the synthesis grows
/// unstable (a = 1/2 already doubles a coarse sample's overshoot).
pub(super) const WEIGHT_RANGE: (i32, i32) = (-256, 512);
/// The lifting steps of every level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    /// The four-point subdivision fitted per level and axis, then the (4, 4) update.
    Fitted,
    /// CDF 9/7.
    Cdf97,
}

/// How a line is continued past its ends.
///
/// Format 6 and before mirror it. The one multiresolution planned for chunked files (issue 52,
/// docs/benchmarks.md "What the overviews cost") needs point symmetry,
/// `f(-k) = 2 f(0) - f(k)`, at an end whose sample is even. There the details are odd about
/// the end, every update step leaves the end sample as it is, and after any number of levels
/// the coarse samples along a chunk's edge are the 1-D transform of that edge alone: the
/// neighbour that shares the edge computes the same ones (with the same prediction weights).
/// Mirroring makes them one-sided means, off by the slope times the filter's width. At an odd
/// end (a line of even length) point symmetry would read the sample being changed, so it
/// mirrors there.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Ends {
    /// Whole-sample symmetric.
    #[default]
    Mirror,
    /// Point-symmetric about an even end sample.
    PointSymmetric,
}

/// A line of the grid: its first index, the stride between samples and their count, and how
/// it continues past its ends.
#[derive(Clone, Copy)]
pub(super) struct Line {
    base: usize,
    stride: usize,
    n: usize,
    ends: Ends,
}

impl Line {
    /// The index of sample `k` of the line, mirrored about its ends.
    #[inline(always)]
    pub(super) fn at(&self, k: isize) -> usize {
        self.base + self.mirrored(k) * self.stride
    }

    /// The position along the line of sample `k`, mirrored about its ends.
    #[inline(always)]
    fn mirrored(&self, k: isize) -> usize {
        let n = self.n as isize;
        if (0..n).contains(&k) {
            // Inside the line, which is nearly always: no remainder to take (a division a
            // tap was a third of a lifted plane's inverse transform, issue 75).
            return k as usize;
        }
        let period = 2 * (n - 1);
        let mut k = k.rem_euclid(period);
        if k >= n {
            k = period - k;
        }
        k as usize
    }

    /// How [`Self::value`] reads sample `k`: the same for every line of a level along an
    /// axis, which [`inverse_columns`] takes once for all of them.
    fn tap(&self, k: isize, detail: bool) -> Tap {
        let n = self.n as isize;
        let end = if k < 0 { 0 } else { n - 1 };
        let mirrored = 2 * end - k;
        if self.ends == Ends::Mirror
            || (0..n).contains(&k)
            || end % 2 != 0
            || !(0..n).contains(&mirrored)
        {
            Tap::Plain(self.mirrored(k))
        } else if detail {
            Tap::Negated(mirrored as usize)
        } else {
            Tap::Reflected(end as usize, mirrored as usize)
        }
    }

    /// Sample `k` of the line, continued past its ends: read as a detail (`detail`, an odd
    /// sample once predicted) or as a value.
    #[inline(always)]
    pub(super) fn value(&self, g: &[f64], k: isize, detail: bool) -> f64 {
        let n = self.n as isize;
        if self.ends == Ends::Mirror || (0..n).contains(&k) {
            return g[self.at(k)];
        }
        let end = if k < 0 { 0 } else { n - 1 };
        let mirrored = 2 * end - k;
        if end % 2 != 0 || !(0..n).contains(&mirrored) {
            return g[self.at(k)];
        }
        let x = g[self.base + mirrored as usize * self.stride];
        if detail {
            -x
        } else {
            2.0 * g[self.base + end as usize * self.stride] - x
        }
    }

    /// The plain mean of the two nearest samples of odd sample `k`, and that of the next two.
    pub(super) fn means(&self, g: &[f64], k: isize) -> (f64, f64) {
        let m12 = 0.5 * (self.value(g, k - 1, false) + self.value(g, k + 1, false));
        let m03 = 0.5 * (self.value(g, k - 3, false) + self.value(g, k + 3, false));
        (m12, m03)
    }

    /// Adds `sign` times the fitted prediction to every odd sample.
    pub(super) fn predict(&self, g: &mut [f64], a: f64, sign: f64) {
        for k in (1..self.n as isize).step_by(2) {
            let (m12, m03) = self.means(g, k);
            g[self.at(k)] += sign * (m12 + a * (m12 - m03));
        }
    }

    /// Adds `sign` times the (4, 4) update to every even sample.
    pub(super) fn update(&self, g: &mut [f64], sign: f64) {
        for k in (0..self.n as isize).step_by(2) {
            let u = UPDATE[0] * (self.value(g, k - 1, true) + self.value(g, k + 1, true))
                + UPDATE[1] * (self.value(g, k - 3, true) + self.value(g, k + 3, true));
            g[self.at(k)] += sign * u;
        }
    }

    /// Adds `c` times the sum of their two neighbours to the samples of one parity (the even
    /// ones read the odd ones, details).
    pub(super) fn step(&self, g: &mut [f64], (parity, c): (isize, f64)) {
        let detail = parity == 0;
        for k in (parity..self.n as isize).step_by(2) {
            let v = c * (self.value(g, k - 1, detail) + self.value(g, k + 1, detail));
            g[self.at(k)] += v;
        }
    }

    /// One level of analysis along the line (prediction weight `a` for the fitted kernel).
    pub(super) fn forward(&self, g: &mut [f64], kernel: Kernel, a: f64) {
        if self.n < 2 {
            return;
        }
        match kernel {
            Kernel::Fitted => {
                self.predict(g, a, -1.0);
                self.update(g, 1.0);
            }
            Kernel::Cdf97 => CDF97.iter().for_each(|&st| self.step(g, st)),
        }
    }

    /// The exact inverse of [`Line::forward`].
    pub(super) fn inverse(&self, g: &mut [f64], kernel: Kernel, a: f64) {
        if self.n < 2 {
            return;
        }
        match kernel {
            Kernel::Fitted => {
                self.update(g, -1.0);
                self.predict(g, a, 1.0);
            }
            Kernel::Cdf97 => CDF97.iter().rev().for_each(|&(p, c)| self.step(g, (p, -c))),
        }
    }
}

/// What [`Line::value`] makes of a sample past a line's end, by position along the line:
/// itself, its negation (a detail, point-symmetric ends), or `2 f(end) - f(k)`.
#[derive(Clone, Copy, PartialEq)]
enum Tap {
    Plain(usize),
    Negated(usize),
    Reflected(usize, usize),
}

/// [`Line::inverse`] of every line of level `l` along y (the columns) at once, along rows: a
/// sample's update or prediction reads its own column only, and samples of the other parity
/// only, which that step leaves as they are, so the order of the samples changes no sum. Why:
/// down a column, each sample read a cache line of its own (the columns were a third of a
/// lifted plane's decode, issue 75); along a row one line serves eight.
pub(super) fn inverse_columns(
    g: &mut [f64],
    (size, l): ([usize; 2], u32),
    (kernel, ends): (Kernel, Ends),
    a: f64,
) {
    let s = 1usize << l;
    let [w, h] = size;
    // Positions along every column (the line's own base and stride are unused).
    let line = Line {
        base: 0,
        stride: 1,
        n: (h - 1) / s + 1,
        ends,
    };
    if line.n < 2 {
        return;
    }
    let n = line.n as isize;
    // Row start of position p; the value of a tap in column x.
    let row = |p: usize| p * s * w;
    let read = |g: &[f64], t: Tap, x: usize| match t {
        Tap::Plain(p) => g[row(p) + x],
        Tap::Negated(p) => -g[row(p) + x],
        Tap::Reflected(end, p) => 2.0 * g[row(end) + x] - g[row(p) + x],
    };
    // Adds `f` of the four taps `k - 1, k + 1, k - 3, k + 3` (read as details or not) to
    // every sample of position k in the columns.
    let each = |g: &mut [f64], k: isize, detail: bool, f: &dyn Fn([f64; 4]) -> f64| {
        let t = [-1, 1, -3, 3].map(|d| line.tap(k + d, detail));
        let at = row(k as usize);
        if let [
            Tap::Plain(p0),
            Tap::Plain(p1),
            Tap::Plain(p2),
            Tap::Plain(p3),
        ] = t
        {
            let r = [p0, p1, p2, p3].map(row);
            for x in (0..w).step_by(s) {
                let v = f(r.map(|r| g[r + x]));
                g[at + x] += v;
            }
        } else {
            for x in (0..w).step_by(s) {
                let v = f(t.map(|t| read(g, t, x)));
                g[at + x] += v;
            }
        }
    };
    match kernel {
        Kernel::Fitted => {
            // `update(g, -1)` then `predict(g, a, 1)`, their sums.
            let sign = -1.0;
            for k in (0..n).step_by(2) {
                each(g, k, true, &|v| {
                    sign * (UPDATE[0] * (v[0] + v[1]) + UPDATE[1] * (v[2] + v[3]))
                });
            }
            let sign = 1.0;
            for k in (1..n).step_by(2) {
                each(g, k, false, &|v| {
                    let (m12, m03) = (0.5 * (v[0] + v[1]), 0.5 * (v[2] + v[3]));
                    sign * (m12 + a * (m12 - m03))
                });
            }
        }
        Kernel::Cdf97 => {
            for &(parity, c) in CDF97.iter().rev() {
                let c = -c;
                for k in (parity..n).step_by(2) {
                    each(g, k, parity == 0, &|v| c * (v[0] + v[1]));
                }
            }
        }
    }
}

/// The lines of level `l` along x (`axis` 0, the rows) or y (1) of a `size` grid.
pub(super) fn lines(
    size: [usize; 2],
    l: u32,
    axis: usize,
    ends: Ends,
) -> impl Iterator<Item = Line> + Clone {
    let s = 1usize << l;
    let [w, h] = size;
    let (count, n) = if axis == 0 {
        (h.div_ceil(s), (w - 1) / s + 1)
    } else {
        (w.div_ceil(s), (h - 1) / s + 1)
    };
    (0..count).map(move |i| {
        if axis == 0 {
            Line {
                base: i * s * w,
                stride: s,
                n,
                ends,
            }
        } else {
            Line {
                base: i * s,
                stride: s * w,
                n,
                ends,
            }
        }
    })
}

/// The least-squares prediction weight (fixed-point index) of a level's lines. (Weights fitted
/// to the least absolute detail instead, nearer to what the details cost, measured the same
/// within 0.05 dB.)
pub(super) fn fit(g: &[f64], lines: impl Iterator<Item = Line>) -> i32 {
    let (mut ff, mut ft) = (0.0, 0.0);
    for line in lines {
        for k in (1..line.n as isize).step_by(2) {
            let (m12, m03) = line.means(g, k);
            let f = m12 - m03;
            ff += f * f;
            ft += f * (g[line.at(k)] - m12);
        }
    }
    let a = if ff > 0.0 { ft / ff } else { 0.0 };
    ((a * WEIGHT_ONE).round() as i32).clamp(WEIGHT_RANGE.0, WEIGHT_RANGE.1)
}

/// The forward transform in place; returns the fitted weights, two a level (rows, columns;
/// zeros for CDF 9/7).
pub(super) fn forward(
    g: &mut [f64],
    size: [usize; 2],
    levels: u32,
    (kernel, ends): (Kernel, Ends),
) -> Vec<i32> {
    let mut weights = Vec::with_capacity(2 * levels as usize);
    for l in 0..levels {
        for axis in 0..2 {
            let wq = match kernel {
                Kernel::Fitted => fit(g, lines(size, l, axis, ends)),
                Kernel::Cdf97 => 0,
            };
            let a = f64::from(wq) / WEIGHT_ONE;
            for line in lines(size, l, axis, ends) {
                line.forward(g, kernel, a);
            }
            weights.push(wq);
        }
    }
    weights
}

/// The inverse transform in place, of the levels from `levels` down to `depth` (0: all).
pub(super) fn inverse(
    g: &mut [f64],
    (size, levels, depth): ([usize; 2], u32, u32),
    (kernel, ends): (Kernel, Ends),
    weights: &[i32],
) {
    for l in (depth..levels).rev() {
        let a = |axis: usize| f64::from(weights[2 * l as usize + axis]) / WEIGHT_ONE;
        inverse_columns(g, (size, l), (kernel, ends), a(1));
        for line in lines(size, l, 0, ends) {
            line.inverse(g, kernel, a(0));
        }
    }
}

/// Synthesis energies of one axis: `(low[j], high[j])` for j = 1..=levels (index j - 1), the
/// squared norm of the function that a unit coefficient at depth j makes on the finest grid,
/// for a coefficient left in the coarse samples after j levels and for a detail of level j
/// (away from the edges).
pub(super) fn gains(kernel: Kernel, weights: &[i32], axis: usize, levels: u32) -> Vec<(f64, f64)> {
    let n = (32usize << levels) + 1;
    let energy = |position: usize, depth: u32| {
        let mut x = vec![0.0; n];
        x[position] = 1.0;
        for l in (0..depth).rev() {
            let a = f64::from(weights[2 * l as usize + axis]) / WEIGHT_ONE;
            let s = 1usize << l;
            let line = Line {
                base: 0,
                stride: s,
                n: (n - 1) / s + 1,
                ends: Ends::Mirror,
            };
            line.inverse(&mut x, kernel, a);
        }
        x.iter().map(|v| v * v).sum::<f64>()
    };
    (1..=levels)
        .map(|j| {
            let mid = (n / 2) >> j << j;
            (energy(mid, j), energy(mid + (1 << (j - 1)), j))
        })
        .collect()
}

/// What one level of `kernel` multiplies a constant line by in its coarse samples (the
/// prediction of a constant is exact, so its details are zero and the update adds nothing
/// but the kernel's own scaling): 1 for the fitted kernel, about 1.23 for CDF 9/7, whose
/// final scaling the coder leaves out. A coarse band at depth d is the source's local means
/// times this to the power 2 d (two axes a level).
pub fn dc_gain(kernel: Kernel) -> f64 {
    let mut line = vec![1.0; 17];
    let l = Line {
        base: 0,
        stride: 1,
        n: line.len(),
        ends: Ends::Mirror,
    };
    l.forward(&mut line, kernel, 0.125);
    line[8]
}

// Here rather than in `pyramid`, which the lifting builds on (the kernels are this module's).
impl Order {
    /// The kernel of a lifted plane; `None` for the pyramid's orders.
    pub fn lifting(self) -> Option<Kernel> {
        match self {
            Order::Separable
            | Order::Quincunx
            | Order::SeparableTwoRate
            | Order::QuincunxTwoRate => None,
            Order::Lifted | Order::LiftedTwoRate => Some(Kernel::Fitted),
            Order::Lifted97 | Order::Lifted97TwoRate => Some(Kernel::Cdf97),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{CDF97, Ends, Kernel, inverse_columns, lines};

    /// The columns inverted along rows are the columns inverted one by one, bit for bit: both
    /// kernels, both ends, lines of odd and even lengths, short ones, and every level's
    /// spacing.
    #[test]
    fn columns_along_rows_are_columns_one_by_one() {
        use proptest::prelude::RngExt;
        // proptest's deterministic generator: the same draws every run.
        let mut rng = proptest::test_runner::TestRng::deterministic_rng(
            proptest::test_runner::RngAlgorithm::ChaCha,
        );
        let mut next = || rng.random::<f64>() * 200.0 - 100.0;
        let mut ends_met = 0;
        for kernel in [Kernel::Fitted, Kernel::Cdf97] {
            for ends in [Ends::Mirror, Ends::PointSymmetric] {
                for size in [[37, 29], [16, 17], [9, 2], [64, 33], [5, 40]] {
                    for l in 0..3u32 {
                        let g: Vec<f64> = (0..size[0] * size[1]).map(|_| next()).collect();
                        let a = [0.0625, -0.2, 0.4][l as usize];
                        let mut one_by_one = g.clone();
                        for line in lines(size, l, 1, ends) {
                            line.inverse(&mut one_by_one, kernel, a);
                        }
                        let mut along_rows = g.clone();
                        inverse_columns(&mut along_rows, (size, l), (kernel, ends), a);
                        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                        assert_eq!(bits(&one_by_one), bits(&along_rows), "{size:?} level {l}");
                        if (size[1] - 1) >> l > 0 {
                            assert_ne!(bits(&g), bits(&along_rows), "nothing was inverted");
                        }
                        ends_met += usize::from(
                            ends == Ends::PointSymmetric && (size[1] - 1) / (1 << l) % 2 == 0,
                        );
                    }
                }
            }
        }
        assert!(ends_met > 0 && CDF97.len() == 4);
    }
}
