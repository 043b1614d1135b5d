//! Coding a curve set: base points and details, quantised in closed loop and range coded.
//!
//! Closed loop: each new point is predicted from the *decoded* coarse points and the decoded
//! parent details, exactly as the decoder will, and only the difference to the source point is
//! quantised. With an interpolating scheme every point of every level is then within the
//! tolerance of its source point, whatever happened above it; nothing accumulates. The
//! quantiser is a square lattice of step `√2·tol` in the metric's local frame (longitude
//! steps widened by 1/cos(latitude) on the sphere), so the error of a point is at most `tol`.
//! Tolerance 0 codes every residual as its exact `f64` (lossless).
//!
//! Symbols go through the adaptive binary range coder of [`crate::entropy`], with contexts by
//! level counted from the finest.

use super::{CurveSet, Metric, Prepared, Pt, Ring, Scheme, span_deviation};
use crate::entropy::{Bit, BitTree, Decoder, Dir, Encoder};
use serde::{Deserialize, Serialize};

/// What the stream needs to be read: the scheme and the shape of every ring.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CurveHeader {
    /// The scheme (subdivision and detail matrices).
    pub scheme: Scheme,
    /// How the tolerance is measured.
    pub metric: Metric,
    /// Largest error of a point (0: lossless).
    pub tolerance: f64,
    /// The rings, in input order.
    pub rings: Vec<RingHeader>,
    /// Bounds on the Hausdorff distance to the source per asset level (see [`CurveSet`]).
    pub level_bounds: Vec<f64>,
}

/// The shape of one ring.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RingHeader {
    /// Closed ring or open polyline.
    pub closed: bool,
    /// Base pieces `K`.
    pub pieces: u32,
    /// Detail levels `L`.
    pub levels: u8,
    /// Points inserted on input segments.
    pub inserted: u32,
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
            if r.pieces == 0 || r.levels as usize > super::MAX_LEVELS {
                return Err(format!(
                    "ring {i}: {} pieces, {} levels",
                    r.pieces, r.levels
                ));
            }
            let n = (r.pieces as u64) << (r.levels as u32 + 1);
            if r.inserted as u64 >= n {
                return Err(format!("ring {i}: more inserted points than points"));
            }
            total = total.saturating_add(n);
        }
        if total > MAX_POINTS {
            return Err(format!(
                "{total} points is more than this build reads ({MAX_POINTS})"
            ));
        }
        if self.level_bounds.iter().any(|b| b.is_nan() || *b < 0.0) {
            return Err("bad level bounds".into());
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
    class: BitTree,
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
}

/// Contexts by level counted from the finest (the last one shared by all coarser levels).
/// Contexts by the activity of neighbouring points and by the other axis's class were tried
/// and cost 1-4% on the coastlines (too few symbols per context to learn them).
const LEVEL_CLASSES: usize = 6;

/// All adaptive contexts of one stream.
struct Models {
    detail_x: Vec<IntModel>,
    detail_y: Vec<IntModel>,
    base: [IntModel; 2],
    gaps: IntModel,
    raw: Vec<Bit>,
}

impl Models {
    fn new() -> Self {
        Models {
            detail_x: vec![IntModel::new(); LEVEL_CLASSES],
            detail_y: vec![IntModel::new(); LEVEL_CLASSES],
            base: [IntModel::new(), IntModel::new()],
            gaps: IntModel::new(),
            raw: vec![Bit::default(); 128],
        }
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

/// The quantiser: residual → symbols → reconstructed offset, in the metric's local frame.
#[derive(Clone, Copy)]
struct Quantiser {
    metric: Metric,
    step: f64,
}

impl Quantiser {
    fn new(metric: Metric, tolerance: f64) -> Self {
        Quantiser {
            metric,
            step: tolerance * std::f64::consts::SQRT_2,
        }
    }

    fn lossless(&self) -> bool {
        self.step == 0.0
    }

    /// Codes the offset from `pred` to `target` (ignored when decoding); returns the decoded
    /// point. `ctx` is the detail context (`None` for base points).
    fn point(&self, dir: &mut Dir, m: &mut Models, ctx: Option<usize>, pred: Pt, target: Pt) -> Pt {
        if self.lossless() {
            let rx = m.raw(dir, 0, target[0] - pred[0]);
            let ry = m.raw(dir, 1, target[1] - pred[1]);
            return [pred[0] + rx, pred[1] + ry];
        }
        // y first: x's step then depends on the decoded latitude, which is within the
        // tolerance of the source's (a step from the prediction's latitude would be wrong by
        // the cosine ratio when the prediction is far, as a ring's first base point is).
        let qb = ((target[1] - pred[1]) / self.step).round() as i64;
        let b = match ctx {
            Some(c) => m.detail_y[c].code(dir, qb),
            None => m.base[1].code(dir, qb),
        };
        let y = pred[1] + b as f64 * self.step;
        let sx = self.step / self.metric.x_scale(y);
        let qa = ((target[0] - pred[0]) / sx).round() as i64;
        let a = match ctx {
            Some(c) => m.detail_x[c].code(dir, qa),
            None => m.base[0].code(dir, qa),
        };
        [pred[0] + a as f64 * sx, y]
    }
}

/// Walks every ring in a fixed order, coding (encoder, with `sources`) or decoding.
fn walk(
    dir: &mut Dir,
    header: &CurveHeader,
    sources: Option<&[Prepared]>,
) -> Result<Vec<Ring>, String> {
    let q = Quantiser::new(header.metric, header.tolerance);
    let scheme = &header.scheme;
    let mut m = Models::new();
    let mut rings = Vec::with_capacity(header.rings.len());
    let mut last_base = [0.0, 0.0];
    for (ri, rh) in header.rings.iter().enumerate() {
        let src = sources.map(|s| &s[ri]);
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
            let p = q.point(dir, &mut m, None, last_base, source(0, i));
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
                    let pred = [t[0] + inherited[i][0], t[1] + inherited[i][1]];
                    let target = source(l + 1, 4 * p + 1 + 2 * i);
                    let e = q.point(dir, &mut m, Some(ctx), pred, target);
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
) -> Result<(CurveHeader, Vec<u8>, CurveSet), String> {
    let mut header = CurveHeader {
        scheme: scheme.clone(),
        metric,
        tolerance,
        rings: sources
            .iter()
            .map(|s| {
                let segs = s.fine.len() - usize::from(!s.closed);
                RingHeader {
                    closed: s.closed,
                    pieces: s.pieces as u32,
                    levels: (segs / s.pieces).ilog2() as u8 - 1,
                    inserted: s.inserted.len() as u32,
                }
            })
            .collect(),
        level_bounds: Vec::new(),
    };
    header.validate()?;
    let mut enc = Encoder::new();
    let rings = walk(&mut Dir::Enc(&mut enc), &header, Some(sources))?;
    let stream = enc.finish();
    header.level_bounds = level_bounds(scheme, metric, tolerance, &rings, sources);
    let set = CurveSet {
        scheme: scheme.clone(),
        rings,
        metric,
        tolerance,
        level_bounds: header.level_bounds.clone(),
    };
    Ok((header, stream, set))
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
        scheme: header.scheme.clone(),
        rings,
        metric: header.metric,
        tolerance: header.tolerance,
        level_bounds: header.level_bounds.clone(),
    })
}

/// Per asset level, a bound on the Hausdorff distance between the decoded level and the source:
/// the larger of the tolerance and the largest distance from a source point to the decoded
/// segment whose span holds it. Source to decoded: distance to a segment is convex along a
/// source segment, so its vertices bound it. Decoded to source: the span's source path runs
/// from within `tol` of one end of the segment to within `tol` of the other, so its projection
/// covers the segment but for the ends, whose points are within `tol` of the end vertices.
fn level_bounds(
    scheme: &Scheme,
    metric: Metric,
    tolerance: f64,
    rings: &[Ring],
    sources: &[Prepared],
) -> Vec<f64> {
    let finest = rings.iter().map(Ring::finest).max().unwrap_or(0);
    let mut bounds = vec![tolerance; finest + 1];
    for (r, s) in rings.iter().zip(sources) {
        let own: Vec<f64> = (0..=r.finest())
            .map(|l| {
                let poly = r.polygon(scheme, l);
                tolerance.max(span_deviation(metric, &poly, &s.fine, r.closed))
            })
            .collect();
        for (n, b) in bounds.iter_mut().enumerate() {
            let l = (n + r.finest()).saturating_sub(finest);
            *b = b.max(own[l]);
        }
    }
    bounds
}
