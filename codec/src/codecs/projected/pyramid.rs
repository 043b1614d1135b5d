//! The multiresolution of the projected codec: an interpolating subdivision of the sample grid
//! whose masks are fitted to the data level by level, and the details that correct each level's
//! prediction, quantised in closed loop and range coded.
//!
//! Level 0 holds the samples on multiples of `2^levels` in both axes. Each refinement halves the
//! spacing S in three passes, each with its own fitted mask (the subdivision matrix of the
//! projected IFS, one per level and pass):
//!
//! 0. points between two level samples along a row (x an odd multiple of S/2, y a multiple of
//!    S), predicted by the four-point mask `m12 + a (m12 - m03)` over the row (m12 the mean of
//!    the two nearest, m03 of the two next; a = 1/16 is Dubuc-Deslauriers);
//! 1. the same along a column;
//! 2. face centres, by the column mask over pass 0's points plus `b` times the difference of the
//!    row mask over pass 1's points and the column mask (a fitted blend of both directions).
//!
//! The encoder fits a and b by least squares on the *decoded* coarser points (closed loop), so
//! that the decoder predicts exactly what the encoder did. A detail is `round(residual / step)`;
//! the decoded value is `prediction + detail * step`, so every decoded sample is within half a
//! step of its source (max-error mode), whatever the levels above did. When the source lies on
//! a quantum (integers), predictions are rounded to it and the step is an odd multiple of it,
//! as in JPEG-LS's near-lossless mode: a bound of `delta` quanta costs a step of `2 delta + 1`.
//!
//! Every pass walks the grid the same way in the encoder and the decoder through
//! [`walk`], which asks a [`Details`] for each sample's decoded value: the encoder quantises
//! and codes, the decoder reads. One walk, so the two cannot drift apart.

use crate::core::lattice::med;

/// Contexts of the detail coder per pass: local relief over the step (8 buckets) times the
/// magnitudes of the pass's details already coded west and north (5 buckets).
const RELIEF_BUCKETS: usize = 8;
const NEIGHBOUR_BUCKETS: usize = 5;
pub(super) const CONTEXTS: usize = RELIEF_BUCKETS * NEIGHBOUR_BUCKETS;
/// Where the coarsest grid's contexts start (after the three passes').
const LEVEL0: usize = 3 * CONTEXTS;
/// Fixed-point denominator of the fitted mask weights.
pub const WEIGHT_ONE: f64 = 1024.0;
/// Largest |weight| index (weights in [-2, 2]).
pub(super) const WEIGHT_LIMIT: i32 = 2048;

/// What a walk needs to know about the grid and the quantiser.
#[derive(Clone, Copy, Debug)]
pub struct Layout {
    /// Samples along x and y.
    pub size: [usize; 2],
    /// Refinement levels (level 0 spacing `2^levels`).
    pub levels: u32,
    /// Quantiser step of the finest level, source units.
    pub step: f64,
    /// Step growth per level towards the coarse ones (`step_j = step * growth^(levels - j)`);
    /// 1 in max-error mode.
    pub growth: f64,
    /// Quantum the source lies on (predictions are rounded to it), or 0 for continuous data.
    pub quantum: f64,
    /// The order of each level's passes.
    pub order: Order,
}

impl Layout {
    /// The step of refinement level `j` (`j = levels` is the coarsest grid's own coding).
    fn step_at(&self, j: u32) -> f64 {
        let k = self.levels.saturating_sub(j);
        if self.growth == 1.0 {
            return self.step;
        }
        let s = self.step * self.growth.powi(k as i32);
        if self.quantum > 0.0 {
            // Odd multiples of the quantum keep decoded values on it.
            let q = ((s / self.quantum - 1.0) / 2.0).round().max(0.0);
            (2.0 * q + 1.0) * self.quantum
        } else {
            s
        }
    }

    fn snap(&self, v: f64) -> f64 {
        if self.quantum > 0.0 {
            (v / self.quantum).round() * self.quantum
        } else {
            v
        }
    }
}

/// One sample to decode: where it is, its prediction and coding context.
pub struct Sample {
    /// Row-major index.
    pub index: usize,
    /// The prediction (snapped to the quantum).
    pub prediction: f64,
    /// Quantiser step here.
    pub step: f64,
    /// Coding context.
    pub context: usize,
    /// Context of the detail's sign: 1 (0) where the signs of the details coded west and
    /// north sum to more (less) than 0, else 2. Read only by the two-rate coding.
    pub sign: usize,
}

/// The two sides of the walk: the encoder quantises the source and codes the detail, the decoder
/// reads the detail; both return the decoded value.
pub trait Details {
    /// The decoded value of `s`.
    fn sample(&mut self, s: &Sample) -> f64;
    /// The mask weights of a pass: the encoder codes those it fitted on what the walk has
    /// decoded so far, the decoder reads them.
    fn weights(&mut self, fitted: Option<[i32; FEATURES]>) -> [i32; FEATURES];
}

/// Features of a pass's prediction. Each is the mean of a group of samples (offsets in units
/// of half the coarser spacing) less the mean of the nearest samples (group 0, whose mean is
/// the plain prediction). The fitted masks weigh them, so a pass can lean on the direction
/// the terrain runs in. Two orders of the passes ([`Order`]); an empty group is a feature
/// that is always 0.
pub const FEATURES: usize = 3;
type Groups = [&'static [[i64; 2]]; FEATURES + 1];
const GROUPS: [[Groups; 3]; 2] = [
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

/// The multiresolution of a plane: the pyramid's order of a level's three passes and how its
/// details are coded, or a lifted kernel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Order {
    /// Points between two coarser samples along rows, then along columns (each from its own
    /// axis), then face centres from their four edge neighbours: suits grids whose rows and
    /// columns differ (a global grid's rows near the poles).
    Separable,
    /// Face centres from the four coarser corners, then rows and columns from four neighbours
    /// each (two coarser, two faces).
    Quincunx,
    /// Not this pyramid: the lifted multiresolution of rate mode ([`super::lifting`]), whose
    /// coarse samples are local means, with the fitted four-point kernel.
    Lifted,
    /// The lifted multiresolution with the CDF 9/7 kernel.
    Lifted97,
    /// [`Order::Separable`], its details coded with two-rate contexts and their signs in the
    /// context of their neighbours' (format 9, what encoders write).
    SeparableTwoRate,
    /// [`Order::Quincunx`], its details coded as [`Order::SeparableTwoRate`]'s.
    QuincunxTwoRate,
}

impl Order {
    /// The pyramid's orders this build writes (the encoder keeps the one that codes smaller).
    pub const PYRAMIDS: [Order; 2] = [Order::SeparableTwoRate, Order::QuincunxTwoRate];

    /// The order of the passes alone: [`Order::Separable`] or [`Order::Quincunx`] (a lifted
    /// one is itself).
    pub fn passes(self) -> Order {
        match self {
            Order::SeparableTwoRate => Order::Separable,
            Order::QuincunxTwoRate => Order::Quincunx,
            o => o,
        }
    }

    /// Whether the details are coded with [`crate::core::entropy::TwoRateBit`] contexts and
    /// signs in context.
    pub fn two_rate(self) -> bool {
        matches!(self, Order::SeparableTwoRate | Order::QuincunxTwoRate)
    }

    /// The fewest bits a coded sample takes (its zero flag's): what a reader checks a header's
    /// sample count against before it allocates.
    pub(crate) fn min_bits_per_sample(self) -> f64 {
        if self.two_rate() {
            crate::core::entropy::MIN_BITS_PER_TWO_RATE_DECISION
        } else {
            crate::core::entropy::MIN_BITS_PER_DECISION
        }
    }
}

/// Levels for a grid: the control grid keeps about 8 samples on its shorter side (its samples
/// are coded by a causal predictor, the levels below by interpolation, which predicts better).
pub fn levels_for(w: usize, h: usize) -> u8 {
    let mut l = 0u8;
    while l < 12 && (w.min(h) >> (l + 1)) >= 8 {
        l += 1;
    }
    l
}

/// Relief bucket of a spread over a step.
fn relief(spread: f64, step: f64) -> usize {
    let a = spread / step;
    if a < 0.5 {
        0
    } else {
        ((a / 0.5).log2() as usize + 1).min(RELIEF_BUCKETS - 1)
    }
}

/// Points of pass `pass` at spacing `s` (the coarser grid's), in walk order.
fn pass_points(
    size: [usize; 2],
    s: usize,
    order: Order,
    pass: usize,
) -> impl Iterator<Item = (usize, usize)> {
    let half = s / 2;
    let (x0, y0) = match (order.passes(), pass) {
        (Order::Separable, 0) | (Order::Quincunx, 1) => (half, 0),
        (Order::Separable, 1) | (Order::Quincunx, 2) => (0, half),
        _ => (half, half),
    };
    (y0..size[1])
        .step_by(s)
        .flat_map(move |y| (x0..size[0]).step_by(s).map(move |x| (x, y)))
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

/// [`ring`] about row-major index `i` of a grid `w` wide, every offset known to lie in it.
fn ring_inside(
    g: &[f64],
    w: usize,
    i: usize,
    half: usize,
    offsets: &[[i64; 2]],
) -> (f64, usize, f64, f64) {
    let (mut sum, mut lo, mut hi) = (0.0, f64::INFINITY, f64::NEG_INFINITY);
    for [dx, dy] in offsets {
        let v = g[(i as i64 + (dx + dy * w as i64) * half as i64) as usize];
        sum += v;
        lo = lo.min(v);
        hi = hi.max(v);
    }
    let n = offsets.len();
    (if n > 0 { sum / n as f64 } else { 0.0 }, n, lo, hi)
}

/// The prediction of `(x, y)` in pass `pass` with weights `w`: the mean of the nearest samples
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
    // Groups reach 3 halves away: a point that far from every edge reads them unchecked (the
    // same sums in the same order, so the same prediction).
    let reach = 3 * half;
    let inside = x >= reach && y >= reach && x + reach < size[0] && y + reach < size[1];
    let ring = |offsets: &[[i64; 2]]| {
        if inside {
            ring_inside(g, size[0], y * size[0] + x, half, offsets)
        } else {
            ring(g, size, x, y, half, offsets)
        }
    };
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
pub fn fit_weights(rows: &[(f64, [f64; FEATURES])]) -> [i32; FEATURES] {
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

/// Bucket of the sum of two neighbours' |detail|: 0, 1, 2, 3-4, 5 and more.
fn neighbour_bucket(n: u32) -> usize {
    match n {
        0..=2 => n as usize,
        3..=4 => 3,
        _ => 4,
    }
}

/// The context of a detail's sign from the sum of its west and north neighbours' signs
/// (see [`Sample::sign`]).
fn sign_context(sum: i8) -> usize {
    match sum {
        1.. => 1,
        ..=-1 => 0,
        0 => 2,
    }
}

/// The west, north and north-west neighbours of (x, y) on a coarse grid of spacing `s` in a
/// row-major grid `w` wide, for LOCO-I's median: a missing one takes the other's value, and the
/// first sample has zeros.
pub(crate) fn causal_neighbours<T: Copy + Default>(
    g: &[T],
    w: usize,
    (x, y): (usize, usize),
    s: usize,
) -> (T, T, T) {
    let i = y * w + x;
    match (x >= s, y >= s) {
        (true, true) => (g[i - s], g[i - s * w], g[i - s * w - s]),
        (true, false) => (g[i - s], g[i - s], g[i - s]),
        (false, true) => (g[i - s * w], g[i - s * w], g[i - s * w]),
        (false, false) => (T::default(), T::default(), T::default()),
    }
}

/// Walks the whole pyramid, filling `g` (row-major, `size[0] * size[1]`) with decoded values.
/// `target` gives the encoder's source values for fitting (the decoder passes `None`).
pub fn walk(
    layout: &Layout,
    g: &mut [f64],
    details: &mut dyn Details,
    target: Option<&dyn Fn(usize) -> Option<f64>>,
) {
    walk_to(layout, g, details, target, 0);
}

/// [`walk`] down to the level of spacing `2^depth` only (0: every level): the decoded samples
/// on multiples of `2^depth` are then final (closed loop: no finer level changes them), and
/// the stream's rest is left unread.
pub fn walk_to(
    layout: &Layout,
    g: &mut [f64],
    details: &mut dyn Details,
    target: Option<&dyn Fn(usize) -> Option<f64>>,
    depth: u32,
) {
    assert!(
        layout.order.lifting().is_none(),
        "a lifted plane is not walked by the pyramid"
    );
    let [w, h] = layout.size;
    let s0 = 1usize << layout.levels;
    // Level 0: MED over the coarse grid in raster order.
    let step = layout.step_at(layout.levels + 1);
    for y in (0..h).step_by(s0) {
        for x in (0..w).step_by(s0) {
            let i = y * w + x;
            let (a, b, c) = causal_neighbours(g, w, (x, y), s0);
            let prediction = layout.snap(med(a, b, c));
            let context = relief((a - b).abs().max((a - c).abs()), step);
            let context = LEVEL0 + context * NEIGHBOUR_BUCKETS;
            g[i] = details.sample(&Sample {
                index: i,
                prediction,
                step,
                context,
                sign: 2,
            });
        }
    }
    for level in 0..layout.levels.saturating_sub(depth) {
        let s = s0 >> level;
        let half = s / 2;
        let step = layout.step_at(level + 1);
        for (pass, groups) in GROUPS[layout.order.passes() as usize].iter().enumerate() {
            let grid = &*g;
            let fit = |source: &dyn Fn(usize) -> Option<f64>| {
                let rows: Vec<_> = pass_points(layout.size, s, layout.order, pass)
                    .filter_map(|(x, y)| {
                        let t = source(y * w + x)?;
                        let (m, f, _) =
                            predict(grid, layout.size, x, y, half, groups, [0.0; FEATURES]);
                        Some((t - m, f))
                    })
                    .collect();
                fit_weights(&rows)
            };
            let wq = details.weights(target.map(fit));
            let wf = wq.map(|v| f64::from(v) / WEIGHT_ONE);
            // The details (clamped to +-255) of this pass's points in the row above and in this
            // row, by column: their magnitudes and their signs are the contexts of the next.
            let (mut above, mut row) = (vec![0i16; w], vec![0i16; w]);
            let mut row_y = usize::MAX;
            let mut west = 0i16;
            for (x, y) in pass_points(layout.size, s, layout.order, pass) {
                if y != row_y {
                    if row_y != usize::MAX {
                        std::mem::swap(&mut above, &mut row);
                    }
                    row_y = y;
                    west = 0;
                }
                let (pred, _, spread) = predict(g, layout.size, x, y, half, groups, wf);
                let prediction = layout.snap(pred);
                let i = y * w + x;
                let (north, west_q) = (above[x], west);
                let magnitudes = u32::from(west_q.unsigned_abs()) + u32::from(north.unsigned_abs());
                let context = pass * CONTEXTS
                    + relief(spread, step) * NEIGHBOUR_BUCKETS
                    + neighbour_bucket(magnitudes);
                let v = details.sample(&Sample {
                    index: i,
                    prediction,
                    step,
                    context,
                    sign: sign_context((west_q.signum() + north.signum()) as i8),
                });
                let q = ((v - prediction) / step).round().clamp(-255.0, 255.0) as i16;
                (west, row[x]) = (q, q);
                g[i] = v;
            }
        }
    }
}
