//! The curve stream's models and quantisers: integers on adaptive contexts by level class,
//! the lattices details are quantised on (square, then hexagonal from level 2), and the
//! closed-loop quantiser of a ring's details.

use super::distance::{Metric, Pt};
use crate::core::entropy::{BitTree, CountedBit as Bit, Dir, Model};

/// Adaptive model of signed integers: zero flag, sign, magnitude class (a bit tree over the bit
/// length), and the bits below the leading one (the top two adaptive per class).
#[derive(Clone)]
pub(super) struct IntModel {
    pub(super) zero: Bit,
    pub(super) sign: Bit,
    pub(super) class: BitTree<Bit>,
    pub(super) mantissa: Vec<[Bit; 2]>,
    pub(super) low: Bit,
}

impl IntModel {
    pub(super) fn new() -> Self {
        IntModel {
            zero: Bit::default(),
            sign: Bit::default(),
            class: BitTree::new(6),
            mantissa: vec![[Bit::default(); 2]; 64],
            low: Bit::default(),
        }
    }

    pub(super) fn code(&mut self, dir: &mut Dir, v: i64) -> i64 {
        if !dir.bit(&mut self.zero, v != 0) {
            return 0;
        }
        let negative = dir.bit(&mut self.sign, v < 0);
        let m = v.unsigned_abs().max(1);
        let class = dir.tree(&mut self.class, 63 - m.leading_zeros()) as usize;
        let mut out: u64 = 1;
        for k in (0..class).rev() {
            let bit = (m >> k) & 1 == 1;
            let depth = class - 1 - k;
            let ctx = if depth < 2 {
                &mut self.mantissa[class][depth]
            } else {
                &mut self.low
            };
            out = (out << 1) | u64::from(dir.bit(ctx, bit));
        }
        let out = out.min(i64::MAX as u64) as i64;
        if negative { -out } else { out }
    }

    /// What coding `v` would cost now, in bits.
    pub(super) fn cost(&self, v: i64) -> f64 {
        if v == 0 {
            return self.zero.cost(false);
        }
        let m = v.unsigned_abs();
        let class = (63 - m.leading_zeros()) as usize;
        let mut bits = self.zero.cost(true) + self.sign.cost(v < 0) + self.class.cost(class as u32);
        for k in (0..class).rev() {
            let depth = class - 1 - k;
            let ctx = if depth < 2 {
                &self.mantissa[class][depth]
            } else {
                &self.low
            };
            bits += ctx.cost((m >> k) & 1 == 1);
        }
        bits
    }
}

/// Contexts by level counted from the finest (the last one shared by all coarser levels).
/// Contexts by the activity of neighbouring points and by the other axis's class were tried
/// and cost 1-4% on the coastlines (too few symbols per context to learn them).
pub(super) const LEVEL_CLASSES: usize = 3;

/// The first detail level (from the coarsest, 0) quantised on the hexagonal lattice (see
/// [`Lattice`]); 1 codes the coastlines 0.1% smaller but leaves a prediction across a
/// thousand kilometres on it.
pub(super) const HEXAGONAL_FROM: usize = 2;

/// All adaptive contexts of one stream.
pub(super) struct Models {
    /// Detail symbols: the finest level's row (across the chord) and column (along it) apart,
    /// each coarser level class one model for both axes (its residuals are isotropic, and one
    /// model learns in half the symbols: 0.2-0.6% smaller on the five longest coastlines).
    pub(super) detail: Vec<IntModel>,
    pub(super) base: [IntModel; 2],
    pub(super) gaps: IntModel,
    pub(super) raw: Vec<Bit>,
}

impl Models {
    pub(super) fn new() -> Self {
        Models {
            detail: vec![IntModel::new(); LEVEL_CLASSES + 1],
            base: [IntModel::new(), IntModel::new()],
            gaps: IntModel::new(),
            raw: vec![Bit::default(); 128],
        }
    }

    /// The model of detail symbols of level class `ctx` on `axis` (0: row, 1: column).
    pub(super) fn detail(&self, ctx: usize, axis: usize) -> &IntModel {
        &self.detail[Self::detail_index(ctx, axis)]
    }

    pub(super) fn detail_mut(&mut self, ctx: usize, axis: usize) -> &mut IntModel {
        &mut self.detail[Self::detail_index(ctx, axis)]
    }

    pub(super) fn detail_index(ctx: usize, axis: usize) -> usize {
        if ctx == 0 { axis } else { ctx + 1 }
    }

    /// An exact `f64` (lossless mode), bit by bit with one context per bit position.
    pub(super) fn raw(&mut self, dir: &mut Dir, axis: usize, v: f64) -> f64 {
        let bits = v.to_bits();
        let mut out = 0u64;
        for k in (0..64).rev() {
            let b = dir.bit(&mut self.raw[axis * 64 + k], (bits >> k) & 1 == 1);
            out |= u64::from(b) << k;
        }
        f64::from_bits(out)
    }
}

/// A quantisation lattice of covering radius `tol`, in rows: symbols are (row, column) and the
/// point is at `((column + shift(row))·col, row·row)` in the lattice's plane.
///
/// Detail points use the hexagonal lattice (rows `1.5·tol` apart, points `√3·tol` apart, odd
/// rows staggered by half a point): 2.60·tol² a point against the square lattice's 2·tol², which
/// codes the coastlines 2.3% smaller. Base points and the first two detail levels use the square
/// lattice (step `√2·tol`): their predictions are up to a continent away, and on the sphere each
/// row's columns are laid out at its own latitude's scale from the prediction's longitude, so
/// far from the prediction consecutive rows slide against each other. The square lattice's
/// covering radius does not depend on how its rows are aligned; the hexagonal one's grows to
/// 1.15·tol with rows aligned (hexagonal everywhere, a 500 m encode of the coastlines put a
/// first-level point, predicted from base points 2,500 km apart, 524 m from its vertex). From
/// the third level on, predictions are within half a degree and the slide under 1% of a
/// column; `encode`'s verification reports any hair over the tolerance in the level bounds.
#[derive(Clone, Copy)]
pub(super) struct Lattice {
    pub(super) row: f64,
    pub(super) col: f64,
    pub(super) stagger: f64,
}

impl Lattice {
    pub(super) fn square(tolerance: f64) -> Self {
        Lattice {
            row: std::f64::consts::SQRT_2 * tolerance,
            col: std::f64::consts::SQRT_2 * tolerance,
            stagger: 0.0,
        }
    }

    pub(super) fn hexagonal(tolerance: f64) -> Self {
        Lattice {
            row: 1.5 * tolerance,
            col: 3f64.sqrt() * tolerance,
            stagger: 0.5,
        }
    }

    /// Half a point on odd rows (`b & 1` is 1 for negative odd rows too).
    pub(super) fn shift(&self, b: i64) -> f64 {
        if b & 1 == 1 { self.stagger } else { 0.0 }
    }

    /// The offset along the row of column `a` on row `b`.
    pub(super) fn along(&self, b: i64, a: i64) -> f64 {
        (a as f64 + self.shift(b)) * self.col
    }

    /// The symbols of the lattice point nearest `(u, v)` (`v` across the rows), where
    /// `u_of_row(b)` gives `u` in the row's own frame (on the sphere a row's longitude scale is
    /// its latitude's): the nearest of the three rows around `v`.
    pub(super) fn nearest(&self, v: f64, u_of_row: impl Fn(i64) -> f64) -> (i64, i64) {
        let b0 = (v / self.row).round() as i64;
        let mut best = (f64::INFINITY, b0, 0);
        for b in [b0, b0 - 1, b0 + 1] {
            let u = u_of_row(b);
            let a = (u / self.col - self.shift(b)).round() as i64;
            let (du, dv) = (u - self.along(b, a), v - b as f64 * self.row);
            let d = du * du + dv * dv;
            if d < best.0 {
                best = (d, b, a);
            }
        }
        (best.1, best.2)
    }
}

/// The quantiser: residual → symbols → reconstructed offset, on the lattice of
/// covering radius `tol` in the metric's local frame (rows along latitude).
#[derive(Clone, Copy)]
pub(super) struct Quantiser {
    pub(super) metric: Metric,
    pub(super) tolerance: f64,
    pub(super) square: Lattice,
    pub(super) hexagonal: Lattice,
}

impl Quantiser {
    pub(super) fn new(metric: Metric, tolerance: f64) -> Self {
        Quantiser {
            metric,
            tolerance,
            square: Lattice::square(tolerance),
            hexagonal: Lattice::hexagonal(tolerance),
        }
    }

    pub(super) fn lossless(&self) -> bool {
        self.tolerance == 0.0
    }

    /// Codes the offset from `pred` to `target` (ignored when decoding); returns the decoded
    /// point. `ctx` is the detail context (`None` for base points).
    pub(super) fn point(
        &self,
        dir: &mut Dir,
        m: &mut Models,
        ctx: Option<usize>,
        lattice: &Lattice,
        pred: Pt,
        target: Pt,
    ) -> Pt {
        if self.lossless() {
            let rx = m.raw(dir, 0, target[0] - pred[0]);
            let ry = m.raw(dir, 1, target[1] - pred[1]);
            return [pred[0] + rx, pred[1] + ry];
        }
        let (qb, qa) = self.nearest(lattice, pred, target);
        let b = match ctx {
            Some(c) => m.detail_mut(c, 0).code(dir, qb),
            None => m.base[1].code(dir, qb),
        };
        let a = match ctx {
            Some(c) => m.detail_mut(c, 1).code(dir, qa),
            None => m.base[0].code(dir, qa),
        };
        self.at(lattice, pred, b, a)
    }

    /// The lattice of points predicted at level `l` (`None`: base points, predicted from
    /// the previous base point).
    pub(super) fn lattice(&self, l: Option<usize>) -> &Lattice {
        match l {
            Some(l) if l >= HEXAGONAL_FROM => &self.hexagonal,
            _ => &self.square,
        }
    }

    /// The lattice point nearest `target`. A row's longitude step is set by the row's
    /// latitude, which is within the tolerance of the source's (a step from the prediction's
    /// latitude would be wrong by the cosine ratio when the prediction is far, as a ring's
    /// first base point is).
    pub(super) fn nearest(&self, lattice: &Lattice, pred: Pt, target: Pt) -> (i64, i64) {
        lattice.nearest(target[1] - pred[1], |b| {
            (target[0] - pred[0]) * self.metric.x_scale(pred[1] + b as f64 * lattice.row)
        })
    }

    /// The point of symbols `(b, a)` on `lattice` around `pred`.
    pub(super) fn at(&self, lattice: &Lattice, pred: Pt, b: i64, a: i64) -> Pt {
        let y = pred[1] + b as f64 * lattice.row;
        [pred[0] + lattice.along(b, a) / self.metric.x_scale(y), y]
    }

    /// The cheapest symbols (at the models' current rates) that `admissible` accepts, among
    /// those from zero to `nearest` (the symbols nearest the target), one step wider; `nearest`
    /// when none cheaper is.
    pub(super) fn cheapest(
        &self,
        m: &Models,
        ctx: usize,
        nearest: (i64, i64),
        admissible: impl Fn(i64, i64) -> bool,
    ) -> (i64, i64) {
        let (m0, m1) = (m.detail(ctx, 0), m.detail(ctx, 1));
        let nearest_cost = m0.cost(nearest.0) + m1.cost(nearest.1);
        // Far predictions are rare and keep the nearest point.
        const MAX_SIDE: i64 = 24;
        let range = |q: i64| (q.min(0) - 1, q.max(0) + 1);
        let ((lo0, hi0), (lo1, hi1)) = (range(nearest.0), range(nearest.1));
        if hi0 - lo0 > MAX_SIDE || hi1 - lo1 > MAX_SIDE {
            return nearest;
        }
        let mut candidates = Vec::new();
        for q0 in lo0..=hi0 {
            let c0 = m0.cost(q0);
            for q1 in lo1..=hi1 {
                let c = c0 + m1.cost(q1);
                if c < nearest_cost && (q0, q1) != nearest {
                    candidates.push((c, q0, q1));
                }
            }
        }
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0));
        candidates
            .into_iter()
            .map(|(_, q0, q1)| (q0, q1))
            .find(|&(q0, q1)| admissible(q0, q1))
            .unwrap_or(nearest)
    }
}
