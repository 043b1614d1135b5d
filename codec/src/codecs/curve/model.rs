//! The curve model: points and metrics, the subdivision scheme, rings and their levels, a
//! prepared polyline, a set of curves by level (see the parent module for the model's maths).

use serde::{Deserialize, Serialize};

use crate::codecs::curve::distance::{Metric, Pt, span_deviation};
use crate::core::format::FormatError;

/// The subdivision scheme shared by all rings of an asset: the subdivision matrices `T_i` (as
/// barycentric weights) and the detail matrices `U_i`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scheme {
    /// Weights of the new point of map `i` on the piece's `(A, C, B)`; each triple sums to 1.
    pub t: [[f64; 3]; 2],
    /// `u[i][j][k]`: how much of the parent's detail `k` child `i` inherits as its detail `j`.
    pub u: [[[f64; 2]; 2]; 2],
}

impl Default for Scheme {
    /// Quadratic Lagrange interpolation through `(A, C, B)` at the quarter points, and no
    /// inherited detail: the starting point of the fit and the scheme of `--no-fit` encodes.
    fn default() -> Self {
        Scheme {
            t: [[0.375, 0.75, -0.125], [-0.125, 0.75, 0.375]],
            u: [[[0.0; 2]; 2]; 2],
        }
    }
}

/// Largest |weight| a subdivision matrix may hold; beyond it the scheme is far from any curve.
const MAX_WEIGHT: f64 = 4.0;
/// Largest norm (max row sum) of a detail matrix: inherited details must shrink level by level
/// so that synthesis beyond the source converges (the curve analogue of |s| < 1).
pub const MAX_DETAIL_GAIN: f64 = 0.9;

impl Scheme {
    /// Refuses schemes that are not barycentric, not finite, or whose details do not shrink.
    pub fn validate(&self) -> Result<(), FormatError> {
        for (i, t) in self.t.iter().enumerate() {
            if t.iter().any(|w| !w.is_finite() || w.abs() > MAX_WEIGHT) {
                return Err(FormatError::header(format!(
                    "subdivision weights {t:?} of map {i} are out of range"
                )));
            }
            if (t.iter().sum::<f64>() - 1.0).abs() > 1e-9 {
                return Err(FormatError::header(format!(
                    "subdivision weights {t:?} of map {i} do not sum to 1"
                )));
            }
        }
        for u in &self.u {
            if u.iter().flatten().any(|w| !w.is_finite())
                || u.iter()
                    .any(|r| r[0].abs() + r[1].abs() > MAX_DETAIL_GAIN + 1e-12)
            {
                return Err(FormatError::header(format!(
                    "detail matrix {u:?} does not shrink details"
                )));
            }
        }
        Ok(())
    }

    /// The prediction of the new point of map `i` from a piece's control points.
    #[inline]
    pub fn predict(&self, i: usize, a: Pt, c: Pt, b: Pt) -> Pt {
        let w = &self.t[i];
        [
            w[0] * a[0] + w[1] * c[0] + w[2] * b[0],
            w[0] * a[1] + w[1] * c[1] + w[2] * b[1],
        ]
    }

    /// The details child `i` inherits from its parent's `d`.
    #[inline]
    pub fn inherit(&self, i: usize, d: [Pt; 2]) -> [Pt; 2] {
        let u = &self.u[i];
        let row = |j: usize| {
            [
                u[j][0] * d[0][0] + u[j][1] * d[1][0],
                u[j][0] * d[0][1] + u[j][1] * d[1][1],
            ]
        };
        [row(0), row(1)]
    }

    /// The synthesis matrix `R` of one piece: `(A, E0, C, E1, B) = (A, C, B, d0, d1) · R`.
    pub fn synthesis_matrix(&self) -> nalgebra::SMatrix<f64, 5, 5> {
        let [t0, t1] = self.t;
        #[rustfmt::skip]
        let r = nalgebra::SMatrix::<f64, 5, 5>::from_row_slice(&[
            // A     E0     C    E1     B
            1.0, t0[0], 0.0, t1[0], 0.0, // A
            0.0, t0[1], 1.0, t1[1], 0.0, // C
            0.0, t0[2], 0.0, t1[2], 1.0, // B
            0.0, 1.0,   0.0, 0.0,   0.0, // d0
            0.0, 0.0,   0.0, 1.0,   0.0, // d1
        ]);
        r
    }

    /// The analysis matrix `R⁻¹`: `(A, C, B, d0, d1) = (A, E0, C, E1, B) · R⁻¹`.
    pub fn analysis_matrix(&self) -> nalgebra::SMatrix<f64, 5, 5> {
        self.synthesis_matrix()
            .try_inverse()
            .expect("R is unit triangular after a permutation, hence invertible")
    }
}

/// One ring or open polyline in the model: its base control points and the details of every
/// level down to the source's.
#[derive(Clone, Debug, PartialEq)]
pub struct Ring {
    /// Closed (a ring: the last point joins the first) or open.
    pub closed: bool,
    /// The level-0 polygon: `2K` points for a ring, `2K + 1` for an open polyline.
    pub base: Vec<Pt>,
    /// `details[l][p]`: the two details of piece `p` at level `l` (which refine level `l` into
    /// `l + 1`), inherited part included. `details.len()` is the finest level.
    pub details: Vec<Vec<[Pt; 2]>>,
    /// Indices, in the finest polygon, of the points the encoder inserted on input segments
    /// (ascending). The finest output leaves them out.
    pub inserted: Vec<u32>,
    /// Where the ring crosses the antimeridian (longitude and latitude rings only; empty
    /// otherwise): the model holds unwrapped longitudes, the output the source's.
    pub seam: Vec<SeamCrossing>,
    /// The input vertex the coded ring starts at, when not the input's first (the encoder
    /// tries several starts of a ring and keeps the one that codes smallest), and always for a
    /// ring that winds around a pole (coded open, output closed): the output starts at the
    /// input's first vertex again.
    pub start: Option<u32>,
}

/// A ring on the sphere is coded with its longitudes *unwrapped* (each vertex within 180° of
/// the previous one), so that a coast that crosses the antimeridian (Chukotka, Fiji,
/// Antarctica) is one continuous curve to the predictor instead of a 360° jump: the jump had
/// cost Eurasia 0.7% and Antarctica 0.9% of their bytes (and drew the points inserted to fit
/// the piece count onto a segment around the world). Output longitudes are the source's side
/// of the antimeridian again: from fine index `at` on, `turns` more whole turns (360°) are
/// taken off, and the result is clamped to [-180°, 180°].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SeamCrossing {
    /// The first fine index (finest polygon, inserted points included) of the new turn.
    pub at: u32,
    /// Turns added there (usually 1 or -1).
    pub turns: i32,
}

/// The turns (360° each) to take off the longitude of the point at fine index `f`.
pub fn turns_at(seam: &[SeamCrossing], f: usize) -> i32 {
    seam.iter()
        .take_while(|c| c.at as usize <= f)
        .map(|c| c.turns)
        .sum()
}

/// Longitude back on the source's side of the antimeridian.
fn rewrap(p: Pt, turns: i32) -> Pt {
    [(p[0] - 360.0 * f64::from(turns)).clamp(-180.0, 180.0), p[1]]
}

/// Unwraps the longitudes of a polyline on the sphere: each vertex moved by whole turns to
/// within 180° of the previous one. A ring that winds around a pole (Antarctica in longitude
/// and latitude) cannot close in unwrapped longitudes: it becomes the open polyline from its
/// first vertex around to the same vertex one turn on. Returns the points, whether they are
/// closed, and the seam as input vertex indices (see [`SeamCrossing`]).
pub fn unwrap_longitudes(points: &[Pt], closed: bool) -> (Vec<Pt>, bool, Vec<SeamCrossing>) {
    let mut pts = points.to_vec();
    if closed && pts.len() > 1 && pts.first() == pts.last() {
        pts.pop();
    }
    let mut seam = Vec::new();
    let mut turns = 0i32;
    let mut out: Vec<Pt> = Vec::with_capacity(pts.len() + 1);
    let turns_to = |prev: f64, lon: f64| ((prev - lon) / 360.0).round() as i32;
    for (i, p) in pts.iter().enumerate() {
        if let Some(prev) = out.last() {
            let t = turns_to(prev[0], p[0]);
            if t != turns {
                seam.push(SeamCrossing {
                    at: i as u32,
                    turns: t - turns,
                });
                turns = t;
            }
        }
        out.push([p[0] + 360.0 * f64::from(turns), p[1]]);
    }
    let mut closed = closed;
    if closed && let (Some(first), Some(last)) = (pts.first(), out.last()) {
        let t = turns_to(last[0], first[0]);
        if t != 0 {
            // Winds around a pole: the closing vertex one turn on ends an open polyline.
            if t != turns {
                seam.push(SeamCrossing {
                    at: out.len() as u32,
                    turns: t - turns,
                });
            }
            out.push([first[0] + 360.0 * f64::from(t), first[1]]);
            closed = false;
        }
    }
    (out, closed, seam)
}

impl Ring {
    /// Number of base pieces `K`.
    pub fn pieces(&self) -> usize {
        self.base.len() / 2
    }

    /// The source's level (number of detail levels).
    pub fn finest(&self) -> usize {
        self.details.len()
    }

    /// Points of the polygon at level `l`.
    pub fn len_at(&self, l: usize) -> usize {
        (self.pieces() << (l + 1)) + usize::from(!self.closed)
    }

    /// Analysis (eq. 7): the model of a fine polygon of `K·2^(L+1)` (+1 if open) points.
    pub fn from_fine(
        scheme: &Scheme,
        fine: &[Pt],
        closed: bool,
        pieces: usize,
        inserted: Vec<u32>,
    ) -> Ring {
        let mut levels = 0;
        while (pieces << (levels + 1)) + usize::from(!closed) < fine.len() {
            levels += 1;
        }
        debug_assert_eq!((pieces << (levels + 1)) + usize::from(!closed), fine.len());
        let rinv = scheme.analysis_matrix();
        let mut cur = fine.to_vec();
        let mut details = vec![Vec::new(); levels];
        for l in (0..levels).rev() {
            let n = pieces << l; // pieces at level l
            let mut coarse = Vec::with_capacity(2 * n + 1);
            let mut d = Vec::with_capacity(n);
            for p in 0..n {
                let at = |k: usize| cur[(4 * p + k) % cur.len()];
                let f = [at(0), at(1), at(2), at(3), at(4)];
                let mut out = [[0.0; 2]; 5];
                for (j, o) in out.iter_mut().enumerate() {
                    for (k, fk) in f.iter().enumerate() {
                        let w = rinv[(k, j)];
                        o[0] += fk[0] * w;
                        o[1] += fk[1] * w;
                    }
                }
                coarse.push(out[0]);
                coarse.push(out[1]);
                d.push([out[3], out[4]]);
            }
            if !closed {
                coarse.push(*cur.last().expect("non-empty"));
            }
            details[l] = d;
            cur = coarse;
        }
        Ring {
            closed,
            base: cur,
            details,
            inserted,
            seam: Vec::new(),
            start: None,
        }
    }

    /// Synthesis to the ring's level `level` (which may exceed [`Ring::finest`]: details then
    /// continue through the detail matrices). Inserted points are kept; see [`Ring::output`].
    pub fn polygon(&self, scheme: &Scheme, level: usize) -> Vec<Pt> {
        let mut cur = self.base.clone();
        // The details used one level up: a level past the source inherits from them.
        let mut prev: Vec<[Pt; 2]> = Vec::new();
        for l in 0..level {
            let n = self.pieces() << l;
            let used: Vec<[Pt; 2]> = match self.details.get(l) {
                Some(d) => d.clone(),
                None => (0..n)
                    .map(|p| {
                        let parent = prev.get(p / 2).copied().unwrap_or([[0.0; 2]; 2]);
                        scheme.inherit(p % 2, parent)
                    })
                    .collect(),
            };
            let mut next = Vec::with_capacity(4 * n + 1);
            for (p, d) in used.iter().enumerate() {
                let (a, c, b) = (cur[2 * p], cur[2 * p + 1], cur[(2 * p + 2) % cur.len()]);
                let e0 = scheme.predict(0, a, c, b);
                let e1 = scheme.predict(1, a, c, b);
                next.push(a);
                next.push([e0[0] + d[0][0], e0[1] + d[0][1]]);
                next.push(c);
                next.push([e1[0] + d[1][0], e1[1] + d[1][1]]);
            }
            if !self.closed {
                next.push(*cur.last().expect("non-empty"));
            }
            cur = next;
            prev = used;
        }
        cur
    }

    /// The polygon at level `level` as output: inserted points left out at the finest level
    /// (where every remaining point is an input vertex), the first point repeated at the end of
    /// a ring (GeoJSON's closed rings).
    pub fn output(&self, scheme: &Scheme, level: usize) -> Vec<Pt> {
        let framed = self.framed(scheme, level);
        self.output_map(level).iter().map(|&i| framed[i]).collect()
    }

    /// Where each point of [`Ring::output`] at `level` comes from in [`Ring::polygon`]: the
    /// finest level leaves inserted points out, a rotated ring starts at the input's first
    /// vertex again, a ring repeats its first point at the end, and a ring that winds around a
    /// pole (coded as an open line from its start vertex around to the same vertex one turn on)
    /// is output from the input's first vertex around and back to it, through both ends of the
    /// coded line (two decoded points of the start vertex, each within the tolerance of it).
    pub fn output_map(&self, level: usize) -> Vec<usize> {
        let finest = self.finest();
        let len = self.len_at(level);
        let is_inserted = |i: usize| self.inserted.binary_search(&(i as u32)).is_ok();
        let mut idx: Vec<usize> = if level == finest && !self.inserted.is_empty() {
            (0..len).filter(|&i| !is_inserted(i)).collect()
        } else {
            (0..len).collect()
        };
        let Some(start) = self.start else {
            if self.closed {
                idx.push(idx[0]);
            }
            return idx;
        };
        // The input's first vertex: its index among the coded input vertices, then in the
        // finest polygon.
        let fine_len = self.len_at(finest);
        let vertices = fine_len - self.inserted.len() - usize::from(!self.closed);
        let origin = (vertices - start as usize % vertices.max(1)) % vertices.max(1);
        let f0 = fine_index(&self.inserted, origin);
        let fine = |i: usize| {
            if level <= finest {
                i << (finest - level)
            } else {
                i >> (level - finest).min(usize::BITS as usize - 1)
            }
        };
        let k = idx.iter().position(|&i| fine(i) >= f0).unwrap_or(0);
        if self.closed {
            idx.rotate_left(k);
            idx.push(idx[0]);
            idx
        } else {
            let mut out = idx[k..].to_vec();
            out.extend_from_slice(&idx[..=k]);
            out
        }
    }

    /// [`Ring::polygon`] in the source's longitudes (see [`SeamCrossing`]): what the output
    /// draws, inserted points kept. Error bounds are measured on it.
    pub fn framed(&self, scheme: &Scheme, level: usize) -> Vec<Pt> {
        let mut pts = self.polygon(scheme, level);
        if !self.seam.is_empty() {
            let finest = self.finest();
            for (j, p) in pts.iter_mut().enumerate() {
                // The fine index at or before point j of this level.
                let f = if level <= finest {
                    j << (finest - level)
                } else {
                    j >> (level - finest).min(usize::BITS as usize - 1)
                };
                *p = rewrap(*p, turns_at(&self.seam, f));
            }
        }
        pts
    }
}

/// How a ring's coded points relate to its input: where it crosses the antimeridian (fine
/// indices) and the input vertex it starts at ([`Ring::start`]).
pub type Frame = (Vec<SeamCrossing>, Option<u32>);

/// The fine index of input vertex `i`: `i` plus the inserted points before it.
pub(super) fn fine_index(inserted: &[u32], i: usize) -> usize {
    let mut f = i;
    for &k in inserted {
        if k as usize <= f {
            f += 1;
        }
    }
    f
}

/// A set of rings under one scheme: what a curve asset decodes to.
#[derive(Clone, Debug, PartialEq)]
pub struct CurveSet {
    /// The scheme shared by every ring.
    pub scheme: Scheme,
    /// The rings, in input order.
    pub rings: Vec<Ring>,
    /// How distances are measured.
    pub metric: Metric,
    /// Largest error of a vertex of the finest level against the source (0 when lossless).
    pub tolerance: f64,
    /// `bounds[n]`: a bound on the Hausdorff distance between asset level `n` and the source,
    /// for `n` up to the finest asset level.
    pub level_bounds: Vec<f64>,
}

/// A decoded set of polylines at one asset level, with its error bound.
#[derive(Clone, Debug, PartialEq)]
pub struct CurveLevel {
    /// The asset level.
    pub level: usize,
    /// One polyline per ring, in input order (rings closed by repeating their first point).
    pub lines: Vec<Vec<Pt>>,
    /// Whether each line is a closed ring.
    pub closed: Vec<bool>,
    /// A bound on the Hausdorff distance to the source, in the metric's units.
    pub error_bound: f64,
}

impl CurveSet {
    /// The finest asset level: every ring at its source level.
    pub fn finest(&self) -> usize {
        self.rings.iter().map(Ring::finest).max().unwrap_or(0)
    }

    /// A ring's own level at asset level `level` (rings align on their finest level; a ring
    /// coarser than that is drawn as its base polygon).
    pub fn ring_level(&self, ring: &Ring, level: usize) -> usize {
        // Saturating: a level of usize::MAX wrapped to level 0 (and its bound).
        level
            .saturating_add(ring.finest())
            .saturating_sub(self.finest())
    }

    /// Points that asset level `level` would output (to refuse huge requests before work).
    pub fn points_at(&self, level: usize) -> u128 {
        self.rings
            .iter()
            .map(|r| {
                let l = self.ring_level(r, level).min(120) as u32;
                ((r.pieces() as u128) << (l + 1)) + 2
            })
            .sum()
    }

    /// Decodes every ring at asset level `level`.
    pub fn at_level(&self, level: usize) -> CurveLevel {
        let finest = self.finest();
        let mut lines = Vec::with_capacity(self.rings.len());
        let mut deviation = 0.0f64;
        for r in &self.rings {
            let own = self.ring_level(r, level);
            lines.push(r.output(&self.scheme, own));
            if own > r.finest() {
                deviation = deviation.max(self.continuation_deviation(r, own));
            }
        }
        let error_bound = if level <= finest {
            self.level_bounds
                .get(level)
                .copied()
                .unwrap_or(f64::INFINITY)
        } else {
            // Levels past the source: the finest level's bound plus how far they stray from it.
            self.level_bounds
                .get(finest)
                .copied()
                .unwrap_or(f64::INFINITY)
                + deviation
        };
        CurveLevel {
            level,
            lines,
            closed: self
                .rings
                .iter()
                .map(|r| r.closed || r.start.is_some())
                .collect(),
            error_bound,
        }
    }

    /// How far the points a level past the source adds stray from the source-level polygon:
    /// each lies within its span of that polygon, so this plus the tolerance bounds the
    /// Hausdorff distance both ways (a span's points project onto its whole segment).
    fn continuation_deviation(&self, r: &Ring, level: usize) -> f64 {
        let coarse = r.framed(&self.scheme, r.finest());
        let fine = r.framed(&self.scheme, level);
        span_deviation(self.metric, &coarse, &fine, r.closed)
    }
}
