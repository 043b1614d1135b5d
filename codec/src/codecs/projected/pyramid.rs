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
use crate::core::transform::round_half_away;

pub(super) use super::predict::WEIGHT_LIMIT;
pub use super::predict::{FEATURES, WEIGHT_ONE};
use super::predict::{GROUPS, RELIEF_BUCKETS, Relief, Rings, fit_weights};

/// Contexts of the detail coder per pass: local relief over the step (8 buckets) times the
/// magnitudes of the pass's details already coded west and north (5 buckets).
const NEIGHBOUR_BUCKETS: usize = 5;
pub(super) const CONTEXTS: usize = RELIEF_BUCKETS * NEIGHBOUR_BUCKETS;
/// Where the coarsest grid's contexts start (after the three passes').
const LEVEL0: usize = 3 * CONTEXTS;

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
        if self.quantum == 1.0 {
            // v / 1 and r * 1 are v and r exactly: integer data skips a division a sample.
            round_half_away(v)
        } else if self.quantum > 0.0 {
            round_half_away(v / self.quantum) * self.quantum
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
/// reads the detail; both return the decoded value and the detail (in steps).
pub trait Details {
    /// The decoded value of `s` and its detail: `prediction + detail * step`.
    fn sample(&mut self, s: &Sample) -> (f64, i32);
    /// The mask weights of a pass: the encoder codes those it fitted on what the walk has
    /// decoded so far, the decoder reads them.
    fn weights(&mut self, fitted: Option<[i32; FEATURES]>) -> [i32; FEATURES];
}

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
    /// [`Order::Lifted`], its coefficients coded with two-rate contexts, signs in context and
    /// dequantised to their centroids (format 10, what encoders write).
    LiftedTwoRate,
    /// [`Order::Lifted97`], coded as [`Order::LiftedTwoRate`] is.
    Lifted97TwoRate,
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
        matches!(
            self,
            Order::SeparableTwoRate
                | Order::QuincunxTwoRate
                | Order::LiftedTwoRate
                | Order::Lifted97TwoRate
        )
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

/// The first point of pass `pass` at spacing `s` (the coarser grid's): its points are those
/// from there on multiples of `s` along both axes.
fn pass_origin(s: usize, order: Order, pass: usize) -> (usize, usize) {
    let half = s / 2;
    match (order.passes(), pass) {
        (Order::Separable, 0) | (Order::Quincunx, 1) => (half, 0),
        (Order::Separable, 1) | (Order::Quincunx, 2) => (0, half),
        _ => (half, half),
    }
}

/// Points of pass `pass` at spacing `s` (the coarser grid's), in walk order.
fn pass_points(
    size: [usize; 2],
    s: usize,
    order: Order,
    pass: usize,
) -> impl Iterator<Item = (usize, usize)> {
    let (x0, y0) = pass_origin(s, order, pass);
    (y0..size[1])
        .step_by(s)
        .flat_map(move |y| (x0..size[0]).step_by(s).map(move |x| (x, y)))
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
pub fn walk<D: Details + ?Sized>(
    layout: &Layout,
    g: &mut [f64],
    details: &mut D,
    target: Option<&dyn Fn(usize) -> Option<f64>>,
) {
    walk_to(layout, g, details, target, 0);
}

/// [`walk`] down to the level of spacing `2^depth` only (0: every level): the decoded samples
/// on multiples of `2^depth` are then final (closed loop: no finer level changes them), and
/// the stream's rest is left unread.
pub fn walk_to<D: Details + ?Sized>(
    layout: &Layout,
    g: &mut [f64],
    details: &mut D,
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
    let buckets = Relief::new(step);
    for y in (0..h).step_by(s0) {
        for x in (0..w).step_by(s0) {
            let i = y * w + x;
            let (a, b, c) = causal_neighbours(g, w, (x, y), s0);
            let prediction = layout.snap(med(a, b, c));
            let context = buckets.bucket((a - b).abs().max((a - c).abs()));
            let context = LEVEL0 + context * NEIGHBOUR_BUCKETS;
            g[i] = details
                .sample(&Sample {
                    index: i,
                    prediction,
                    step,
                    context,
                    sign: 2,
                })
                .0;
        }
    }
    for level in 0..layout.levels.saturating_sub(depth) {
        let s = s0 >> level;
        let half = s / 2;
        for (pass, groups) in GROUPS[layout.order.passes() as usize].iter().enumerate() {
            let grid = &*g;
            let rings = Rings::new(groups, w, half);
            let fit = |source: &dyn Fn(usize) -> Option<f64>| {
                let rows: Vec<_> = pass_points(layout.size, s, layout.order, pass)
                    .filter_map(|(x, y)| {
                        let t = source(y * w + x)?;
                        let (m, f) = rings.features((grid, layout.size), (x, y));
                        Some((t - m, f))
                    })
                    .collect();
                fit_weights(&rows)
            };
            let wq = details.weights(target.map(fit));
            let wf = wq.map(|v| f64::from(v) / WEIGHT_ONE);
            walk_pass(layout, g, details, (level, pass), wf);
        }
    }
}

/// The points of one pass of refinement `level` with mask weights `wf`, a row at a time: the
/// row's predictions and relief first (they read coarser passes only), then its details, whose
/// contexts read the details west and north. Why apart: the range decoder is one serial chain
/// of data-dependent branches, and a prediction's loads, division and rounding between two of
/// its symbols waited on it (issue 75).
fn walk_pass<D: Details + ?Sized>(
    layout: &Layout,
    g: &mut [f64],
    details: &mut D,
    (level, pass): (u32, usize),
    wf: [f64; FEATURES],
) {
    let [w, h] = layout.size;
    let s = (1usize << layout.levels) >> level;
    let step = layout.step_at(level + 1);
    let groups = &GROUPS[layout.order.passes() as usize][pass];
    let rings = Rings::new(groups, w, s / 2);
    let buckets = Relief::new(step);
    let (x0, y0) = pass_origin(s, layout.order, pass);
    // The details (clamped to +-255) of this pass's points in the row above and in this row,
    // by column: their magnitudes and their signs are the contexts of the next.
    let (mut above, mut row) = (vec![0i16; w], vec![0i16; w]);
    let mut predicted: Vec<(f64, usize)> = Vec::with_capacity(w / s + 1);
    for y in (y0..h).step_by(s) {
        predicted.clear();
        rings.predict_row((g, layout.size), y, (x0, s), wf, |pred, spread| {
            predicted.push((layout.snap(pred), buckets.bucket(spread)));
        });
        let mut west = 0i16;
        for (x, &(prediction, relief)) in (x0..w).step_by(s).zip(&predicted) {
            let i = y * w + x;
            let north = above[x];
            let magnitudes = u32::from(west.unsigned_abs()) + u32::from(north.unsigned_abs());
            let context =
                pass * CONTEXTS + relief * NEIGHBOUR_BUCKETS + neighbour_bucket(magnitudes);
            let (v, q) = details.sample(&Sample {
                index: i,
                prediction,
                step,
                context,
                sign: sign_context((west.signum() + north.signum()) as i8),
            });
            // The detail as coded: formats up to 9 were written taking it back from the value,
            // `round((v - prediction) / step)`, the same integer (|q| < 2^31).
            let q = q.clamp(-255, 255) as i16;
            (west, row[x]) = (q, q);
            g[i] = v;
        }
        std::mem::swap(&mut above, &mut row);
    }
}
