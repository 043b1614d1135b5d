//! Coding a curve set: base points and details, quantised in closed loop and range coded.
//!
//! Closed loop: each new point is predicted from the *decoded* coarse points and the decoded
//! parent details, exactly as the decoder will, and only the difference to the source point is
//! quantised, so nothing accumulates. The coder's prediction adds to the model's (`T`, `U`)
//! the four-point cubic across pieces (the model itself is unchanged: a detail is still the
//! decoded point less `T`'s prediction). Above the finest level the quantiser is a lattice of
//! covering radius `tol` (`Lattice`: hexagonal, or square where predictions are far) in the
//! metric's local frame (longitude steps widened by 1/cos(latitude) on the sphere): every such
//! point is within `tol` of its source vertex.
//!
//! The finest level (half the points) is held to what the tolerance promises, the Hausdorff
//! distance, not to vertex error: its lattice is turned to the chord between the point's
//! decoded neighbours, and the encoder takes the cheapest lattice point (at the adaptive
//! models' current rates) that keeps the point's span within `tol` of the source span both
//! ways, so a point may slide along the coast where that is cheaper. `encode` then verifies the
//! whole output locally and holds to the nearest lattice point ("strict") the points around
//! any place that strays, and codes again (a few passes). On the 40 Natural Earth coastlines
//! at ~1 km this codes 13% smaller than vertex-accurate coding, at the same Hausdorff
//! distance. The decoder knows none of this: it reads lattice points.
//!
//! Tolerance 0 codes every residual as its exact `f64` (lossless).
//!
//! Symbols go through the adaptive binary range coder of [`crate::core::entropy`], with
//! fast-learning contexts ([`crate::core::entropy::CountedBit`]) by level counted from the finest.

use super::distance::{Metric, Pt, point_segment_scaled, span_deviation};
use super::model::{CurveSet, Frame, Ring, Scheme, SeamCrossing};
use super::prepare::Prepared;
use crate::core::entropy::{BitTree, CountedBit as Bit, Decoder, Dir, Encoder, Model};

/// What the stream needs to be read: the scheme and the shape of every ring. Stored in the
/// compact form of [`compact`], right before the stream (12 bytes for one ring, against 75 as
/// plain fixed-width fields with every level's bound, 2.4% of a 2,500-point coastline's bytes).
#[derive(Clone, Debug, PartialEq)]
pub struct CurveHeader {
    /// The scheme (subdivision and detail matrices); the default one is stored as one byte.
    pub scheme: Scheme,
    /// How the tolerance is measured.
    pub metric: Metric,
    /// Largest error of a point (0: lossless), an `f32` value (the encoder rounds the
    /// requested tolerance down to one).
    pub tolerance: f64,
    /// The rings, in input order.
    pub rings: Vec<RingHeader>,
    /// A bound on the Hausdorff distance between the finest level and the source, as stored
    /// (rounded up by [`compact::bound_up`]: still a bound). The coarser levels' bounds follow
    /// from it and the decoded rings ([`level_bounds`]), so they are not stored.
    pub finest_bound: f64,
}

/// The header's bytes. Hand-written rather than bincode's variable-length integers, which
/// would change every codec's format (they share `fractile_proto`'s fixed-width config), and
/// self-delimiting, so that the stream follows with no length field (the asset's payload length
/// ends it): LEB128 counts, one byte for the scheme when it is the default, the tolerance as
/// `f32`, and the finest level's bound as a 16-bit code `k` of `tolerance · 2^(k/256)` (0.27%
/// steps, rounded up; `u16::MAX`: no bound), or as `f32` rounded up when the tolerance is 0.
pub mod compact {
    use super::{CurveHeader, Metric, RingHeader, Scheme, SeamCrossing};

    fn varint(out: &mut Vec<u8>, mut v: u64) {
        loop {
            let byte = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                out.push(byte);
                return;
            }
            out.push(byte | 0x80);
        }
    }

    /// The largest `f32` value at or under `t` (a tolerance as stored: never looser than asked).
    pub fn tolerance_down(t: f64) -> f64 {
        let f = t as f32;
        f64::from(if f64::from(f) > t { f.next_down() } else { f })
    }

    /// The smallest stored bound at or above `b` for tolerance `tol`.
    pub fn bound_up(tol: f64, b: f64) -> f64 {
        decode_bound(tol, encode_bound(tol, b))
    }

    fn encode_bound(tol: f64, b: f64) -> u32 {
        if tol == 0.0 {
            let f = b as f32;
            let f = if f64::from(f) < b { f.next_up() } else { f };
            return f.to_bits();
        }
        if b.is_nan() || b <= tol {
            return 0; // bounds are never under the tolerance
        }
        let mut k = ((b / tol).log2() * 256.0).ceil().max(0.0);
        if k >= f64::from(u16::MAX) {
            return u32::from(u16::MAX);
        }
        while decode_bound(tol, k as u32) < b {
            k += 1.0;
        }
        (k as u32).min(u32::from(u16::MAX))
    }

    fn decode_bound(tol: f64, k: u32) -> f64 {
        if tol == 0.0 {
            return f64::from(f32::from_bits(k));
        }
        if k >= u32::from(u16::MAX) {
            return f64::INFINITY;
        }
        tol * (f64::from(k) / 256.0).exp2()
    }

    /// The header's bytes (the tolerance must be an `f32` value, as [`tolerance_down`] makes it).
    pub fn write(h: &CurveHeader) -> Vec<u8> {
        let mut out = Vec::with_capacity(16 + 4 * h.rings.len());
        if h.scheme == Scheme::default() {
            out.push(0);
        } else {
            out.push(1);
            for w in h.scheme.t.iter().flatten() {
                out.extend_from_slice(&w.to_le_bytes());
            }
            for w in h.scheme.u.iter().flatten().flatten() {
                out.extend_from_slice(&w.to_le_bytes());
            }
        }
        out.push(match h.metric {
            Metric::Plane => 0,
            Metric::Sphere => 1,
        });
        out.extend_from_slice(&(h.tolerance as f32).to_le_bytes());
        varint(&mut out, h.rings.len() as u64);
        for r in &h.rings {
            // Bit 7: a seam follows; bit 6: a start (levels take at most 5 bits above the
            // closed bit).
            let seam = u8::from(!r.seam.is_empty()) << 7;
            let start = u8::from(r.start.is_some()) << 6;
            out.push(seam | start | (r.levels << 1) | u8::from(r.closed));
            varint(&mut out, u64::from(r.pieces));
            varint(&mut out, u64::from(r.inserted));
            if let Some(s) = r.start {
                varint(&mut out, u64::from(s));
            }
            if !r.seam.is_empty() {
                varint(&mut out, r.seam.len() as u64);
                let mut at = 0;
                for c in &r.seam {
                    // The gap to the previous crossing, with two bits for the turn: +1, -1
                    // (one step between vertices within 180° of each other never turns more),
                    // or another (a zigzag varint follows).
                    let gap = u64::from(c.at - at) << 2;
                    at = c.at;
                    match c.turns {
                        1 => varint(&mut out, gap),
                        -1 => varint(&mut out, gap | 1),
                        t => {
                            varint(&mut out, gap | 2);
                            varint(&mut out, ((t << 1) ^ (t >> 31)) as u32 as u64);
                        }
                    }
                }
            }
        }
        let k = encode_bound(h.tolerance, h.finest_bound);
        if h.tolerance == 0.0 {
            out.extend_from_slice(&k.to_le_bytes());
        } else {
            out.extend_from_slice(&(k as u16).to_le_bytes());
        }
        out
    }

    struct Reader<'a>(&'a [u8]);

    impl Reader<'_> {
        fn bytes<const N: usize>(&mut self) -> Result<[u8; N], String> {
            if self.0.len() < N {
                return Err("the curve header is truncated".into());
            }
            let (head, rest) = self.0.split_at(N);
            self.0 = rest;
            Ok(head.try_into().expect("N bytes"))
        }

        fn f64(&mut self) -> Result<f64, String> {
            Ok(f64::from_le_bytes(self.bytes()?))
        }

        fn varint(&mut self) -> Result<u64, String> {
            let mut v = 0u64;
            for shift in (0..64).step_by(7) {
                let [byte] = self.bytes()?;
                v |= u64::from(byte & 0x7f) << shift;
                if byte & 0x80 == 0 {
                    return Ok(v);
                }
            }
            Err("a count in the curve header is too long".into())
        }

        /// A count that cannot exceed the bytes left (each entry takes at least one).
        fn count(&mut self) -> Result<usize, String> {
            let n = self.varint()?;
            if n > self.0.len() as u64 {
                return Err(format!("the curve header claims {n} entries"));
            }
            Ok(n as usize)
        }
    }

    /// Reads a header from the front of `bytes` (refusing a truncated one;
    /// [`CurveHeader::validate`] checks the rest); returns it and the bytes after it.
    pub fn read(bytes: &[u8]) -> Result<(CurveHeader, &[u8]), String> {
        let mut r = Reader(bytes);
        let scheme = match r.bytes::<1>()? {
            [0] => Scheme::default(),
            [1] => {
                let mut s = Scheme::default();
                for w in s.t.iter_mut().flatten() {
                    *w = r.f64()?;
                }
                for w in s.u.iter_mut().flatten().flatten() {
                    *w = r.f64()?;
                }
                s
            }
            [b] => return Err(format!("unknown scheme tag {b}")),
        };
        let metric = match r.bytes::<1>()? {
            [0] => Metric::Plane,
            [1] => Metric::Sphere,
            [b] => return Err(format!("unknown metric {b}")),
        };
        let tolerance = f64::from(f32::from_le_bytes(r.bytes()?));
        let n = r.count()?;
        let mut rings = Vec::with_capacity(n);
        for _ in 0..n {
            let [flags] = r.bytes()?;
            let pieces = u32::try_from(r.varint()?).map_err(|_| "too many pieces")?;
            let inserted = u32::try_from(r.varint()?).map_err(|_| "too many inserted points")?;
            let start = if flags & 0x40 != 0 {
                Some(u32::try_from(r.varint()?).map_err(|_| "a start index is too large")?)
            } else {
                None
            };
            let mut seam = Vec::new();
            if flags & 0x80 != 0 {
                let n = r.count()?;
                let mut at = 0u64;
                for _ in 0..n {
                    let v = r.varint()?;
                    at += v >> 2;
                    let turns = match v & 3 {
                        0 => 1,
                        1 => -1,
                        2 => {
                            let z = u32::try_from(r.varint()?)
                                .map_err(|_| "a seam turn is too large")?;
                            ((z >> 1) as i32) ^ -((z & 1) as i32)
                        }
                        _ => return Err("unknown seam turn code".into()),
                    };
                    seam.push(SeamCrossing {
                        at: u32::try_from(at).map_err(|_| "a seam index is too large")?,
                        turns,
                    });
                }
            }
            rings.push(RingHeader {
                closed: flags & 1 == 1,
                pieces,
                levels: (flags >> 1) & 0x1f,
                inserted,
                seam,
                start,
            });
        }
        let k = if tolerance == 0.0 {
            u32::from_le_bytes(r.bytes()?)
        } else {
            u32::from(u16::from_le_bytes(r.bytes()?))
        };
        let header = CurveHeader {
            scheme,
            metric,
            tolerance,
            rings,
            finest_bound: decode_bound(tolerance, k),
        };
        Ok((header, r.0))
    }
}

/// The shape of one ring.
#[derive(Clone, Debug, PartialEq)]
pub struct RingHeader {
    /// Closed ring or open polyline.
    pub closed: bool,
    /// Base pieces `K`.
    pub pieces: u32,
    /// Detail levels `L` (at most 127: stored in 7 bits).
    pub levels: u8,
    /// Points inserted on input segments.
    pub inserted: u32,
    /// Where the ring crosses the antimeridian ([`SeamCrossing`]; empty for most rings).
    pub seam: Vec<SeamCrossing>,
    /// The input vertex the coded ring starts at ([`Ring::start`]).
    pub start: Option<u32>,
}

/// Most points a curve asset may decode to at its finest level (a tiny hostile header must not
/// make a reader allocate gigabytes).
pub const MAX_POINTS: u64 = 1 << 26;

impl CurveHeader {
    /// Refuses inconsistent or oversized headers.
    pub fn validate(&self) -> Result<(), String> {
        self.scheme.validate()?;
        if !(self.tolerance.is_finite() && self.tolerance >= 0.0) {
            return Err(format!("tolerance {} is not a distance", self.tolerance));
        }
        let mut total = 0u64;
        for (i, r) in self.rings.iter().enumerate() {
            if r.pieces == 0 || r.levels as usize > super::prepare::MAX_LEVELS {
                return Err(format!(
                    "ring {i}: {} pieces, {} levels",
                    r.pieces, r.levels
                ));
            }
            let n = (r.pieces as u64) << (r.levels as u32 + 1);
            if r.inserted as u64 >= n {
                return Err(format!("ring {i}: more inserted points than points"));
            }
            let fine_len = n + u64::from(!r.closed);
            if r.seam.windows(2).any(|w| w[0].at >= w[1].at)
                || r.seam
                    .iter()
                    .any(|c| c.at as u64 >= fine_len || c.turns == 0 || c.turns.abs() > 1 << 20)
            {
                return Err(format!("ring {i}: bad antimeridian crossings"));
            }
            if r.start.is_some_and(|s| s as u64 >= fine_len) {
                return Err(format!("ring {i}: start vertex past its points"));
            }
            total = total.saturating_add(n);
        }
        if total > MAX_POINTS {
            return Err(format!(
                "{total} points is more than this build reads ({MAX_POINTS})"
            ));
        }
        if self.finest_bound.is_nan() || self.finest_bound < 0.0 {
            return Err(format!("bad error bound {}", self.finest_bound));
        }
        Ok(())
    }
}

/// Adaptive model of signed integers: zero flag, sign, magnitude class (a bit tree over the bit
/// length), and the bits below the leading one (the top two adaptive per class).
#[derive(Clone)]
struct IntModel {
    zero: Bit,
    sign: Bit,
    class: BitTree<Bit>,
    mantissa: Vec<[Bit; 2]>,
    low: Bit,
}

impl IntModel {
    fn new() -> Self {
        IntModel {
            zero: Bit::default(),
            sign: Bit::default(),
            class: BitTree::new(6),
            mantissa: vec![[Bit::default(); 2]; 64],
            low: Bit::default(),
        }
    }

    fn code(&mut self, dir: &mut Dir, v: i64) -> i64 {
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
    fn cost(&self, v: i64) -> f64 {
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
const LEVEL_CLASSES: usize = 3;

/// The first detail level (from the coarsest, 0) quantised on the hexagonal lattice (see
/// [`Lattice`]); 1 codes the coastlines 0.1% smaller but leaves a prediction across a
/// thousand kilometres on it.
const HEXAGONAL_FROM: usize = 2;

/// All adaptive contexts of one stream.
struct Models {
    /// Detail symbols: the finest level's row (across the chord) and column (along it) apart,
    /// each coarser level class one model for both axes (its residuals are isotropic, and one
    /// model learns in half the symbols: 0.2-0.6% smaller on the five longest coastlines).
    detail: Vec<IntModel>,
    base: [IntModel; 2],
    gaps: IntModel,
    raw: Vec<Bit>,
}

impl Models {
    fn new() -> Self {
        Models {
            detail: vec![IntModel::new(); LEVEL_CLASSES + 1],
            base: [IntModel::new(), IntModel::new()],
            gaps: IntModel::new(),
            raw: vec![Bit::default(); 128],
        }
    }

    /// The model of detail symbols of level class `ctx` on `axis` (0: row, 1: column).
    fn detail(&self, ctx: usize, axis: usize) -> &IntModel {
        &self.detail[Self::detail_index(ctx, axis)]
    }

    fn detail_mut(&mut self, ctx: usize, axis: usize) -> &mut IntModel {
        &mut self.detail[Self::detail_index(ctx, axis)]
    }

    fn detail_index(ctx: usize, axis: usize) -> usize {
        if ctx == 0 { axis } else { ctx + 1 }
    }

    /// An exact `f64` (lossless mode), bit by bit with one context per bit position.
    fn raw(&mut self, dir: &mut Dir, axis: usize, v: f64) -> f64 {
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
struct Lattice {
    row: f64,
    col: f64,
    stagger: f64,
}

impl Lattice {
    fn square(tolerance: f64) -> Self {
        Lattice {
            row: std::f64::consts::SQRT_2 * tolerance,
            col: std::f64::consts::SQRT_2 * tolerance,
            stagger: 0.0,
        }
    }

    fn hexagonal(tolerance: f64) -> Self {
        Lattice {
            row: 1.5 * tolerance,
            col: 3f64.sqrt() * tolerance,
            stagger: 0.5,
        }
    }

    /// Half a point on odd rows (`b & 1` is 1 for negative odd rows too).
    fn shift(&self, b: i64) -> f64 {
        if b & 1 == 1 { self.stagger } else { 0.0 }
    }

    /// The offset along the row of column `a` on row `b`.
    fn along(&self, b: i64, a: i64) -> f64 {
        (a as f64 + self.shift(b)) * self.col
    }

    /// The symbols of the lattice point nearest `(u, v)` (`v` across the rows), where
    /// `u_of_row(b)` gives `u` in the row's own frame (on the sphere a row's longitude scale is
    /// its latitude's): the nearest of the three rows around `v`.
    fn nearest(&self, v: f64, u_of_row: impl Fn(i64) -> f64) -> (i64, i64) {
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
struct Quantiser {
    metric: Metric,
    tolerance: f64,
    square: Lattice,
    hexagonal: Lattice,
}

impl Quantiser {
    fn new(metric: Metric, tolerance: f64) -> Self {
        Quantiser {
            metric,
            tolerance,
            square: Lattice::square(tolerance),
            hexagonal: Lattice::hexagonal(tolerance),
        }
    }

    fn lossless(&self) -> bool {
        self.tolerance == 0.0
    }

    /// Codes the offset from `pred` to `target` (ignored when decoding); returns the decoded
    /// point. `ctx` is the detail context (`None` for base points).
    fn point(
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
    fn lattice(&self, l: Option<usize>) -> &Lattice {
        match l {
            Some(l) if l >= HEXAGONAL_FROM => &self.hexagonal,
            _ => &self.square,
        }
    }

    /// The lattice point nearest `target`. A row's longitude step is set by the row's
    /// latitude, which is within the tolerance of the source's (a step from the prediction's
    /// latitude would be wrong by the cosine ratio when the prediction is far, as a ring's
    /// first base point is).
    fn nearest(&self, lattice: &Lattice, pred: Pt, target: Pt) -> (i64, i64) {
        lattice.nearest(target[1] - pred[1], |b| {
            (target[0] - pred[0]) * self.metric.x_scale(pred[1] + b as f64 * lattice.row)
        })
    }

    /// The point of symbols `(b, a)` on `lattice` around `pred`.
    fn at(&self, lattice: &Lattice, pred: Pt, b: i64, a: i64) -> Pt {
        let y = pred[1] + b as f64 * lattice.row;
        [pred[0] + lattice.along(b, a) / self.metric.x_scale(y), y]
    }

    /// The cheapest symbols (at the models' current rates) that `admissible` accepts, among
    /// those from zero to `nearest` (the symbols nearest the target), one step wider; `nearest`
    /// when none cheaper is.
    fn cheapest(
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

/// The finest level's lattice: the lattice of the quantiser turned to the chord between
/// a point's decoded neighbours, in the metric's plane at the prediction. Along a coast the
/// cheapest admissible point is then mostly near the normal through the prediction (rows run
/// along the chord, so a band of the coast's width always holds a whole row): one coordinate
/// to pay for instead of two.
struct Chord {
    pred: Pt,
    sx: f64,
    tangent: Pt,
    lattice: Lattice,
}

impl Chord {
    fn new(q: &Quantiser, pred: Pt, prev: Pt, next: Pt) -> Self {
        let sx = q.metric.x_scale(pred[1]);
        let (dx, dy) = ((next[0] - prev[0]) * sx, next[1] - prev[1]);
        let len = (dx * dx + dy * dy).sqrt();
        let tangent = if len > 0.0 && len.is_finite() {
            [dx / len, dy / len]
        } else {
            [1.0, 0.0]
        };
        Chord {
            pred,
            sx,
            tangent,
            lattice: q.hexagonal,
        }
    }

    /// The point of normal symbol `qn` and tangent symbol `qt`.
    fn at(&self, qn: i64, qt: i64) -> Pt {
        let [tx, ty] = self.tangent;
        let (n, t) = (qn as f64 * self.lattice.row, self.lattice.along(qn, qt));
        [
            self.pred[0] + (t * tx - n * ty) / self.sx,
            self.pred[1] + t * ty + n * tx,
        ]
    }

    /// The symbols of the lattice point nearest `target` in the lattice's plane.
    fn nearest(&self, target: Pt) -> (i64, i64) {
        let [tx, ty] = self.tangent;
        let (rx, ry) = (
            (target[0] - self.pred[0]) * self.sx,
            target[1] - self.pred[1],
        );
        self.lattice
            .nearest(ry * tx - rx * ty, |_| rx * tx + ry * ty)
    }
}

/// Whether every point of polyline `from` is within `limit` of polyline `to`. A segment whose
/// ends are at distances `d0`, `d1` and whose length is `len` is within `(d0 + d1 + len) / 2`
/// everywhere (distance to a polyline is 1-Lipschitz), so segments are halved only until that
/// proves them (or a midpoint refutes them): exact, and a few distances per segment.
fn covered(metric: Metric, from: &[Pt], to: &[Pt], limit: f64) -> bool {
    let distance = |p: Pt| {
        let sx = metric.x_scale(p[1]);
        if to.len() == 1 {
            return point_segment_scaled(p, to[0], to[0], sx);
        }
        to.windows(2)
            .map(|w| point_segment_scaled(p, w[0], w[1], sx))
            .fold(f64::INFINITY, f64::min)
    };
    let d: Vec<f64> = from.iter().map(|&p| distance(p)).collect();
    if d.iter().any(|&x| x > limit) {
        return false;
    }
    let mut halves: Vec<(Pt, Pt, f64, f64, u32)> = from
        .windows(2)
        .zip(d.windows(2))
        .map(|(p, d)| (p[0], p[1], d[0], d[1], 0))
        .collect();
    while let Some((p, q, dp, dq, depth)) = halves.pop() {
        if (dp + dq + metric.distance(p, q)) / 2.0 <= limit {
            continue;
        }
        if depth >= 24 {
            return false; // touching the limit over a stretch: call it out
        }
        let mid = [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0];
        let dm = distance(mid);
        if dm > limit {
            return false;
        }
        halves.push((p, mid, dp, dm, depth + 1));
        halves.push((mid, q, dm, dq, depth + 1));
    }
    true
}

/// Whether two polylines are within `limit` of each other both ways (Hausdorff).
fn within(metric: Metric, a: &[Pt], b: &[Pt], limit: f64) -> bool {
    covered(metric, a, b, limit) && covered(metric, b, a, limit)
}

/// What the encoder knows beyond the stream: the source rings and, per ring and fine index,
/// whether the point must stay at its nearest lattice point ("strict").
struct Plan<'a> {
    sources: &'a [Prepared],
    strict: Vec<Vec<bool>>,
}

/// The fine points at indices `lo..=hi` of a ring (wrapping on a ring, clamped on a line).
fn window(fine: &[Pt], closed: bool, lo: isize, hi: isize) -> Vec<Pt> {
    let n = fine.len() as isize;
    (lo..=hi)
        .filter(|&j| closed || (0..n).contains(&j))
        .map(|j| fine[j.rem_euclid(n) as usize])
        .collect()
}

/// What the four-point cubic adds to the quadratic prediction of map `i`'s new point from the
/// piece `(a, c, b)` and `outer`, the neighbouring piece's point before `a` (`i` = 0) or
/// after `b` (`i` = 1). The cubic (weights -1/16, 9/16, 9/16, -1/16, Dyn-Levin-Gregory)
/// codes the coastlines 2.3-3% smaller than the quadratic alone; a weight of 1.3 on the
/// correction did no better.
fn four_point_correction(i: usize, outer: Pt, a: Pt, c: Pt, b: Pt) -> Pt {
    let quadratic = Scheme::default().predict(i, a, c, b);
    let (p0, p1, p2, p3) = if i == 0 {
        (outer, a, c, b)
    } else {
        (a, c, b, outer)
    };
    std::array::from_fn(|k| (9.0 * (p1[k] + p2[k]) - p0[k] - p3[k]) / 16.0 - quadratic[k])
}

/// Walks every ring in a fixed order, coding (encoder, with `sources`) or decoding.
fn walk(dir: &mut Dir, header: &CurveHeader, plan: Option<&Plan>) -> Result<Vec<Ring>, String> {
    let q = Quantiser::new(header.metric, header.tolerance);
    let scheme = &header.scheme;
    let mut m = Models::new();
    let mut rings = Vec::with_capacity(header.rings.len());
    let mut last_base = [0.0, 0.0];
    for (ri, rh) in header.rings.iter().enumerate() {
        let src = plan.map(|p| &p.sources[ri]);
        let strict = plan.map(|p| &p.strict[ri]);
        let (closed, pieces, levels) = (rh.closed, rh.pieces as usize, rh.levels as usize);
        let fine_len = (pieces << (levels + 1)) + usize::from(!closed);
        // Inserted points, as gaps between ascending indices.
        let mut inserted = Vec::with_capacity(rh.inserted as usize);
        let mut at = 0i64;
        for k in 0..rh.inserted as usize {
            let want = src.map_or(0, |s| s.inserted[k] as i64 - at);
            let gap = m.gaps.code(dir, want);
            at += gap;
            if gap < 1 || at as usize >= fine_len {
                return Err(format!("ring {ri}: bad inserted point index"));
            }
            inserted.push(at as u32);
        }
        // The source point of level `l`, index `i`: the fine polygon subsampled.
        let source = |l: usize, i: usize| -> Pt {
            src.map_or([0.0; 2], |s| s.fine[(i << (levels - l)) % s.fine.len()])
        };
        let base_len = 2 * pieces + usize::from(!closed);
        let mut cur = Vec::with_capacity(base_len);
        for i in 0..base_len {
            let p = q.point(dir, &mut m, None, q.lattice(None), last_base, source(0, i));
            last_base = p;
            cur.push(p);
        }
        let base = cur.clone();
        let mut details: Vec<Vec<[Pt; 2]>> = Vec::with_capacity(levels);
        for l in 0..levels {
            let n = pieces << l;
            let level_class = (levels - 1 - l).min(LEVEL_CLASSES - 1);
            let mut next = Vec::with_capacity(4 * n + 1);
            let mut d_level = Vec::with_capacity(n);
            for p in 0..n {
                // A short stream stops where it ran out, not after decoding its claim.
                if p % 1024 == 0 && dir.overrun() {
                    return Err(format!("ring {ri}: the curve stream is truncated"));
                }
                let (ia, ib) = (2 * p, (2 * p + 2) % cur.len());
                let (a, c, b) = (cur[ia], cur[2 * p + 1], cur[ib]);
                let ctx = level_class;
                let inherited = match l {
                    0 => [[0.0; 2]; 2],
                    _ => scheme.inherit(p % 2, details[l - 1][p / 2]),
                };
                let mut d = [[0.0; 2]; 2];
                let mut new = [[0.0; 2]; 2];
                for i in 0..2 {
                    let t = scheme.predict(i, a, c, b);
                    // The coder predicts across pieces (the model's T sees only its own):
                    // the four-point cubic through the piece's points and the nearest point
                    // of the neighbouring piece, where there is one.
                    let outer = if i == 0 {
                        (closed || p > 0).then(|| cur[(2 * p + cur.len() - 1) % cur.len()])
                    } else {
                        (closed || 2 * p + 3 < cur.len()).then(|| cur[(2 * p + 3) % cur.len()])
                    };
                    let cross = outer.map_or([0.0; 2], |o| four_point_correction(i, o, a, c, b));
                    let pred = [
                        t[0] + inherited[i][0] + cross[0],
                        t[1] + inherited[i][1] + cross[1],
                    ];
                    let at = 4 * p + 1 + 2 * i;
                    let target = source(l + 1, at);
                    let (prev, next) = if i == 0 { (a, c) } else { (c, b) };
                    // Encoding lossy, a point not held strict may take a cheaper lattice
                    // point near the coast instead of the nearest to its vertex: at the
                    // finest level if its span stays within the tolerance of the source span,
                    // above it if it stays within the tolerance of the source between its
                    // fine neighbours. `encode` verifies the result and holds strict the
                    // points around any place where the output strays.
                    let e = if l + 1 == levels && !q.lossless() {
                        // The finest level: a lattice along the chord between the decoded
                        // neighbours. Encoding, a point not held strict takes the cheapest
                        // lattice point that keeps its span within the tolerance of the source
                        // span (it may slide along the coast); `encode` verifies the output
                        // and holds strict the points around any place where it strays.
                        let chord = Chord::new(&q, pred, prev, next);
                        let (qn, qt) = match (src, strict) {
                            (Some(s), Some(strict)) => {
                                let f = (at as isize) << (levels - 1 - l);
                                let nearest = chord.nearest(target);
                                if strict[f as usize] {
                                    nearest
                                } else {
                                    let around = window(&s.fine, closed, f - 1, f + 1);
                                    let (metric, tol) = (header.metric, header.tolerance);
                                    q.cheapest(&m, ctx, nearest, |qn, qt| {
                                        within(
                                            metric,
                                            &[prev, chord.at(qn, qt), next],
                                            &around,
                                            tol,
                                        )
                                    })
                                }
                            }
                            _ => (0, 0),
                        };
                        let qn = m.detail_mut(ctx, 0).code(dir, qn);
                        let qt = m.detail_mut(ctx, 1).code(dir, qt);
                        chord.at(qn, qt)
                    } else {
                        q.point(dir, &mut m, Some(ctx), q.lattice(Some(l)), pred, target)
                    };
                    new[i] = e;
                    d[i] = [e[0] - t[0], e[1] - t[1]];
                }
                next.extend([a, new[0], c, new[1]]);
                d_level.push(d);
            }
            if !closed {
                next.push(*cur.last().expect("non-empty"));
            }
            details.push(d_level);
            cur = next;
        }
        rings.push(Ring {
            closed,
            base,
            details,
            inserted,
            seam: rh.seam.clone(),
            start: rh.start,
        });
    }
    Ok(rings)
}

/// Codes prepared rings under `scheme`; returns the header (with its level bounds), the stream
/// and the curve set a decoder will see.
pub fn encode(
    scheme: &Scheme,
    metric: Metric,
    tolerance: f64,
    sources: &[Prepared],
    frames: &[Frame],
) -> Result<(CurveHeader, Vec<u8>, CurveSet), String> {
    let tolerance = compact::tolerance_down(tolerance);
    let mut header = CurveHeader {
        scheme: scheme.clone(),
        metric,
        tolerance,
        rings: sources
            .iter()
            .zip(frames.iter().chain(std::iter::repeat(&(Vec::new(), None))))
            .map(|(s, (seam, start))| {
                let segs = s.fine.len() - usize::from(!s.closed);
                RingHeader {
                    closed: s.closed,
                    pieces: s.pieces as u32,
                    levels: (segs / s.pieces).ilog2() as u8 - 1,
                    inserted: s.inserted.len() as u32,
                    seam: seam.clone(),
                    start: *start,
                }
            })
            .collect(),
        finest_bound: 0.0,
    };
    header.validate()?;
    // Code, verify the output against the source, hold strict the points around every place
    // where it strays, code again. Marks only grow, and a place whose points are all strict is
    // within the tolerance by convexity (each point within `tol` of its vertex), so this ends;
    // a few passes in practice.
    let mut plan = Plan {
        sources,
        strict: sources.iter().map(|s| vec![false; s.fine.len()]).collect(),
    };
    // The points that end a segment across the antimeridian stay near their vertices: in the
    // output that segment is the source's jump around the world, which a point slid along the
    // coast would tilt.
    for ((rh, src), strict) in header.rings.iter().zip(sources).zip(plan.strict.iter_mut()) {
        for c in &rh.seam {
            let at = c.at as usize;
            let before = (1..=at)
                .map(|k| at - k)
                .find(|&j| src.inserted.binary_search(&(j as u32)).is_err());
            strict[before.unwrap_or(at)..=at].fill(true);
        }
        // A ring whose turns do not sum to zero crosses again where it closes.
        if rh.closed && rh.seam.iter().map(|c| c.turns).sum::<i32>() != 0 {
            let n = src.fine.len();
            let last = (1..n)
                .map(|k| n - k)
                .find(|&j| src.inserted.binary_search(&(j as u32)).is_err())
                .unwrap_or(0);
            for j in (last..n).chain([0]) {
                strict[j] = true;
            }
        }
    }
    let (rings, stream) = loop {
        let mut enc = Encoder::new();
        let rings = walk(&mut Dir::Enc(&mut enc), &header, Some(&plan))?;
        let stream = enc.finish();
        if tolerance == 0.0 {
            break (rings, stream);
        }
        let mut marked = false;
        for ((ring, src), strict) in rings.iter().zip(sources).zip(plan.strict.iter_mut()) {
            for k in strays(scheme, metric, tolerance, ring, src) {
                marked |= !std::mem::replace(&mut strict[k], true);
            }
        }
        if !marked {
            break (rings, stream);
        }
    };
    // The finest level's bound: the tolerance where the output was verified; where it was not
    // (places whose points were all strict already), the largest error of a strict point, by
    // convexity. A strict point is within `tol` of its vertex in the lattice's plane, which at
    // the finest level is the prediction's, not the point's own: on the sphere a hair over
    // `tol` can happen, and is reported. Lossless, the largest rounding error of a vertex.
    let finest = rings
        .iter()
        .zip(sources)
        .zip(&plan.strict)
        .flat_map(|((r, s), strict)| {
            let poly = r.polygon(scheme, r.finest());
            poly.into_iter()
                .zip(&s.fine)
                .zip(strict)
                .filter(|(_, st)| **st || tolerance == 0.0)
                .map(|((p, f), _)| metric.distance(*f, p))
                .collect::<Vec<_>>()
        })
        .fold(tolerance, f64::max);
    header.finest_bound = compact::bound_up(tolerance, finest);
    let set = CurveSet {
        level_bounds: level_bounds(scheme, metric, header.finest_bound, &rings),
        scheme: scheme.clone(),
        rings,
        metric,
        tolerance,
    };
    Ok((header, stream, set))
}

/// Fine indices around the places where a ring's finest level strays from its source by more
/// than the tolerance (Hausdorff, checked locally: each decoded segment against the source
/// near it and each source segment against the decoded points near it), both for the polygon
/// with its inserted points (what levels past the source refine) and for the output without
/// them.
fn strays(scheme: &Scheme, metric: Metric, tol: f64, ring: &Ring, src: &Prepared) -> Vec<usize> {
    let closed = src.closed;
    let poly = ring.polygon(scheme, ring.finest());
    let n = poly.len() as isize;
    let segs = if closed { n } else { n - 1 };
    let mut out = Vec::new();
    let mut mark = |lo: isize, hi: isize| {
        out.extend(
            (lo..=hi)
                .filter(|&j| closed || (0..n).contains(&j))
                .map(|j| j.rem_euclid(n) as usize),
        )
    };
    for k in 0..segs {
        let decoded = window(&poly, closed, k, k + 1);
        let source = window(&src.fine, closed, k, k + 1);
        if !covered(
            metric,
            &decoded,
            &window(&src.fine, closed, k - 2, k + 3),
            tol,
        ) || !covered(metric, &source, &window(&poly, closed, k - 2, k + 3), tol)
        {
            mark(k - 1, k + 2);
        }
    }
    // The output: consecutive kept points (input vertices) u < v, with inserted points
    // between them on the input segment from F_u to F_v.
    let kept: Vec<isize> = (0..n)
        .filter(|&j| src.inserted.binary_search(&(j as u32)).is_err())
        .collect();
    let m = kept.len();
    let pairs = if closed { m } else { m.saturating_sub(1) };
    for t in 0..pairs {
        let u = kept[t];
        let v = if t + 1 < m { kept[t + 1] } else { kept[0] + n };
        if v - u == 1 {
            continue; // the same segment as the polygon's, checked above
        }
        let before = if t > 0 {
            kept[t - 1]
        } else if closed {
            kept[m - 1] - n
        } else {
            u
        };
        let after = if t + 2 < m + usize::from(closed) {
            kept[(t + 2) % m] + if t + 2 >= m { n } else { 0 }
        } else {
            v
        };
        let at = |j: isize| poly[j.rem_euclid(n) as usize];
        let output = [at(before), at(u), at(v), at(after)];
        if !covered(
            metric,
            &[at(u), at(v)],
            &window(&src.fine, closed, u - 2, v + 2),
            tol,
        ) || !covered(metric, &window(&src.fine, closed, u, v), &output, tol)
        {
            mark(u - 1, v + 1);
        }
    }
    out
}

/// Decodes a stream.
pub fn decode(header: &CurveHeader, stream: &[u8]) -> Result<CurveSet, String> {
    header.validate()?;
    let mut dec = Decoder::new(stream);
    let rings = walk(&mut Dir::Dec(&mut dec), header, None)?;
    if dec.overrun() {
        return Err("the curve stream is truncated".into());
    }
    let bad = rings
        .iter()
        .flat_map(|r| r.base.iter().chain(r.details.iter().flatten().flatten()))
        .any(|p| !p[0].is_finite() || !p[1].is_finite());
    if bad {
        return Err("the curve stream decodes to non-finite points".into());
    }
    Ok(CurveSet {
        level_bounds: level_bounds(&header.scheme, header.metric, header.finest_bound, &rings),
        scheme: header.scheme.clone(),
        rings,
        metric: header.metric,
        tolerance: header.tolerance,
    })
}

/// Per asset level, a bound on the Hausdorff distance between the decoded level and the source,
/// from the decoded rings and the finest level's bound alone (so a reader computes them and the
/// header stores one number): the finest level's bound plus the Hausdorff distance between the
/// level and the finest decoded polygon, which [`span_deviation`] bounds both ways (each finest
/// point is within it of its span's segment, and the finest path between a segment's ends,
/// which are its own points, projects onto the whole segment). Triangle inequality: at most the
/// tolerance looser than measuring against the source, which the reader does not have.
pub fn level_bounds(
    scheme: &Scheme,
    metric: Metric,
    finest_bound: f64,
    rings: &[Ring],
) -> Vec<f64> {
    let finest = rings.iter().map(Ring::finest).max().unwrap_or(0);
    let mut bounds = vec![finest_bound; finest + 1];
    for r in rings {
        // In the source's longitudes: a span across the antimeridian is drawn as a jump.
        let fine = r.framed(scheme, r.finest());
        let own: Vec<f64> = (0..r.finest())
            .map(|l| finest_bound + span_deviation(metric, &r.framed(scheme, l), &fine, r.closed))
            .chain([finest_bound])
            .collect();
        for (n, b) in bounds.iter_mut().enumerate() {
            let l = (n + r.finest()).saturating_sub(finest);
            *b = b.max(own[l]);
        }
    }
    bounds
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn coverage_finds_the_farthest_point_between_vertices() {
        // Every vertex of `from` lies on `to`; its midpoint (5, 0) is 3/√10 from `to`'s peak.
        let from = [[0.0, 0.0], [10.0, 0.0]];
        let to = [[-1.0, 0.0], [4.0, 0.0], [5.0, 3.0], [6.0, 0.0], [11.0, 0.0]];
        let far = 3.0 / 10f64.sqrt();
        // (A limit touched exactly is refused: halving cannot prove a maximum to zero margin.)
        assert!(covered(Metric::Plane, &from, &to, far + 1e-4));
        assert!(!covered(Metric::Plane, &from, &to, far - 1e-4));
        // The other way round the peak itself is the farthest point: 3 from `from`.
        assert!(!within(Metric::Plane, &from, &to, 3.0 - 1e-4));
        assert!(within(Metric::Plane, &from, &to, 3.0 + 1e-4));
    }

    #[test]
    fn strays_marks_the_points_around_a_decoded_point_off_the_source() {
        let scheme = Scheme::default();
        let fine: Vec<Pt> = (0..64)
            .map(|i| {
                let t = i as f64 / 64.0 * std::f64::consts::TAU;
                [10.0 * t.cos(), 10.0 * t.sin()]
            })
            .collect();
        let src = Prepared {
            closed: true,
            pieces: 2,
            fine: fine.clone(),
            inserted: Vec::new(),
        };
        let ring = Ring::from_fine(&scheme, &fine, true, 2, Vec::new());
        assert!(strays(&scheme, Metric::Plane, 0.01, &ring, &src).is_empty());
        // Push fine point 21 (a finest-level detail) 0.5 outwards.
        let mut moved = fine.clone();
        moved[21] = [moved[21][0] * 1.05, moved[21][1] * 1.05];
        let ring = Ring::from_fine(&scheme, &moved, true, 2, Vec::new());
        let marks = strays(&scheme, Metric::Plane, 0.01, &ring, &src);
        assert!(marks.contains(&20) && marks.contains(&21) && marks.contains(&22));
        assert!(marks.iter().all(|&k| (17..=25).contains(&k)), "{marks:?}");
    }

    proptest! {
        #[test]
        fn the_coarse_lattice_point_nearest_a_target_is_within_the_tolerance(
            pred in (-170.0..170.0f64, -80.0..80.0f64),
            off in (-0.5..0.5f64, -0.5..0.5f64),
            far in (-20.0..20.0f64, -5.0..5.0f64),
            tol in 0.001..0.05f64,
        ) {
            for metric in [Metric::Plane, Metric::Sphere] {
                let q = Quantiser::new(metric, tol);
                let pred = [pred.0, pred.1];
                // Base points may be a continent from their prediction: the square lattice
                // covers exactly. Detail points are within half a degree: the hexagonal
                // lattice covers exactly in the plane, and within 1% on the sphere, where rows
                // laid out at their own latitude's scale slide against each other.
                let cases = [
                    (None, [pred[0] + far.0, pred[1] + far.1], 1e-9),
                    (Some(HEXAGONAL_FROM), [pred[0] + off.0, pred[1] + off.1], if metric == Metric::Plane { 1e-9 } else { 0.01 }),
                ];
                for (ctx, target, slack) in cases {
                    let lattice = q.lattice(ctx);
                    let (b, a) = q.nearest(lattice, pred, target);
                    // In the row's plane (its latitude's longitude scale).
                    let dist = |b: i64, a: i64| {
                        let p = q.at(lattice, pred, b, a);
                        let sx = metric.x_scale(p[1]);
                        ((p[0] - target[0]) * sx).hypot(p[1] - target[1])
                    };
                    let d = dist(b, a);
                    prop_assert!(d <= tol * (1.0 + slack), "{:?}: {} > {}", ctx, d, tol);
                    // And no lattice point of the neighbouring rows and columns is nearer.
                    for bb in b - 1..=b + 1 {
                        for aa in a - 1..=a + 1 {
                            prop_assert!(dist(bb, aa) >= d - tol * 1e-3);
                        }
                    }
                }
            }
        }

        #[test]
        fn headers_round_trip_with_bounds_rounded_up(
            custom in any::<bool>(),
            sphere in any::<bool>(),
            tol in prop_oneof![Just(0.0), 1e-6..1.0f64],
            rings in proptest::collection::vec((any::<bool>(), 1u32..100_000, 0u8..=24, 0u32..1000,
                proptest::collection::vec((1u32..5000, -3i32..=3), 0..4)), 1..6),
            factor in 1.0..1e6f64,
            stream in proptest::collection::vec(any::<u8>(), 0..8),
        ) {
            let mut scheme = Scheme::default();
            if custom {
                scheme.t[0] = [0.3, 0.8, -0.1];
                scheme.u[1][0] = [0.25, -0.5];
            }
            let tolerance = compact::tolerance_down(tol);
            // Never looser than asked, and at most one f32 step (2^-23) tighter.
            prop_assert!(tolerance <= tol && tolerance >= tol * (1.0 - 2.4e-7));
            let finest_bound = if tol > 0.0 { tolerance * factor } else { factor * 1e-3 };
            let h = CurveHeader {
                scheme,
                metric: if sphere { Metric::Sphere } else { Metric::Plane },
                tolerance,
                rings: rings
                    .iter()
                    .map(|(closed, pieces, levels, inserted, seam)| {
                        // Ascending indices, non-zero turns (what the encoder writes).
                        let mut at = 0;
                        let seam = seam
                            .iter()
                            .map(|&(gap, t)| {
                                at += gap;
                                SeamCrossing { at, turns: if t == 0 { 1 } else { t } }
                            })
                            .collect();
                        let start = (pieces % 3 == 0).then_some(*inserted);
                        RingHeader { closed: *closed, pieces: *pieces, levels: *levels, inserted: *inserted, seam, start }
                    })
                    .collect(),
                finest_bound,
            };
            let bytes = compact::write(&h);
            let mut payload = bytes.clone();
            payload.extend_from_slice(&stream);
            let (back, rest) = compact::read(&payload).unwrap();
            // The header delimits itself: what follows is the stream, untouched.
            prop_assert_eq!(rest, &stream[..]);
            prop_assert_eq!(&back.scheme, &h.scheme);
            prop_assert_eq!(back.metric, h.metric);
            prop_assert_eq!(back.tolerance.to_bits(), h.tolerance.to_bits());
            prop_assert_eq!(&back.rings, &h.rings);
            // Still a bound, and at most one 2^(1/256) step (or one f32 ulp) looser.
            prop_assert!(back.finest_bound >= finest_bound && back.finest_bound <= finest_bound * 1.003,
                "{} {}", back.finest_bound, finest_bound);
            // A stored bound is a fixed point: writing it again changes nothing.
            prop_assert_eq!(compact::write(&back), bytes.clone());
            for cut in 0..bytes.len() {
                prop_assert!(compact::read(&bytes[..cut]).is_err());
            }
        }

        #[test]
        fn the_chord_lattice_point_nearest_a_target_is_within_the_tolerance(
            pred in (-170.0..170.0f64, -80.0..80.0f64),
            prev in (-1.0..1.0f64, -1.0..1.0f64),
            next in (-1.0..1.0f64, -1.0..1.0f64),
            off in (-0.2..0.2f64, -0.2..0.2f64),
            tol in 0.001..0.05f64,
        ) {
            let q = Quantiser::new(Metric::Sphere, tol);
            let pred = [pred.0, pred.1];
            let chord = Chord::new(
                &q,
                pred,
                [pred[0] + prev.0, pred[1] + prev.1],
                [pred[0] + next.0, pred[1] + next.1],
            );
            let target = [pred[0] + off.0, pred[1] + off.1];
            let (qn, qt) = chord.nearest(target);
            let p = chord.at(qn, qt);
            // In the lattice's plane (the prediction's): the lattice's covering radius.
            let (dx, dy) = ((p[0] - target[0]) * chord.sx, p[1] - target[1]);
            prop_assert!((dx * dx + dy * dy).sqrt() <= tol * (1.0 + 1e-9));
        }
    }
}
