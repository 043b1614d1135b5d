//! The curve model: points and metrics, the subdivision scheme, rings and their levels, a
//! prepared polyline, a set of curves by level, and the distances between polylines (see the
//! parent module for the model's maths).

use serde::{Deserialize, Serialize};

/// A point of the plane (x, y), or (longitude, latitude) in degrees.
pub type Pt = [f64; 2];

/// How distances (the tolerance, the error bounds) are measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Metric {
    /// Euclidean in the curve's own units.
    Plane,
    /// Longitude and latitude in degrees; distances in degrees of arc (one degree is 111.195
    /// km), with longitude differences shrunk by the cosine of the latitude. GeoJSON is
    /// always this (RFC 7946): a tolerance of 0.009° then means about 1 km everywhere, not 1 km
    /// at the equator and 330 m at 70°N.
    Sphere,
}

/// Metres in one degree of arc on the mean Earth sphere (radius 6,371,008.8 m).
pub const METRES_PER_DEGREE: f64 = 6_371_008.8 * std::f64::consts::PI / 180.0;

impl Metric {
    /// How much one unit of x is worth at latitude `y`, relative to a unit of y.
    pub fn x_scale(self, y: f64) -> f64 {
        match self {
            Metric::Plane => 1.0,
            // Clamped so that points at the poles (Antarctica's outline runs along -90°) keep a
            // finite quantiser step.
            Metric::Sphere => y.to_radians().cos().abs().max(1.0 / 64.0),
        }
    }

    /// Distance from `p` to the segment `[a, b]`, in the metric's units, measured in the plane
    /// tangent at `p` (exact for Plane, accurate to well under 0.1% for the short distances the
    /// bounds care about on the sphere).
    pub fn point_segment(self, p: Pt, a: Pt, b: Pt) -> f64 {
        point_segment_scaled(p, a, b, self.x_scale(p[1]))
    }

    /// Distance between two points.
    pub fn distance(self, a: Pt, b: Pt) -> f64 {
        self.point_segment(a, b, b)
    }
}

/// [`Metric::point_segment`] with the x scale at `p` given (one cosine for many segments).
pub(crate) fn point_segment_scaled(p: Pt, a: Pt, b: Pt, sx: f64) -> f64 {
    let (ax, ay) = ((a[0] - p[0]) * sx, a[1] - p[1]);
    let (bx, by) = ((b[0] - p[0]) * sx, b[1] - p[1]);
    let (dx, dy) = (bx - ax, by - ay);
    let len2 = dx * dx + dy * dy;
    let t = if len2 > 0.0 {
        (-(ax * dx + ay * dy) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    ((ax + t * dx).powi(2) + (ay + t * dy).powi(2)).sqrt()
}

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
    pub fn validate(&self) -> Result<(), String> {
        for (i, t) in self.t.iter().enumerate() {
            if t.iter().any(|w| !w.is_finite() || w.abs() > MAX_WEIGHT) {
                return Err(format!(
                    "subdivision weights {t:?} of map {i} are out of range"
                ));
            }
            if (t.iter().sum::<f64>() - 1.0).abs() > 1e-9 {
                return Err(format!(
                    "subdivision weights {t:?} of map {i} do not sum to 1"
                ));
            }
        }
        for u in &self.u {
            if u.iter().flatten().any(|w| !w.is_finite())
                || u.iter()
                    .any(|r| r[0].abs() + r[1].abs() > MAX_DETAIL_GAIN + 1e-12)
            {
                return Err(format!("detail matrix {u:?} does not shrink details"));
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

/// Points the encoder needs: the fine polygon of an input polyline, with the number of base
/// pieces and the indices of inserted points.
#[derive(Clone, Debug, PartialEq)]
pub struct Prepared {
    /// Closed ring or open polyline.
    pub closed: bool,
    /// Base pieces `K`.
    pub pieces: usize,
    /// `K·2^(L+1)` (+1 open) points: the input vertices in order, with points inserted on the
    /// input's own segments.
    pub fine: Vec<Pt>,
    /// Indices of the inserted points in `fine`, ascending.
    pub inserted: Vec<u32>,
}

/// Most levels a ring may have (2^25 points per base piece is far beyond any polyline).
pub const MAX_LEVELS: usize = 24;

/// Cuts a polyline into base pieces and inserts points on its longest segments until the
/// count fits `K·2^(L+1)`. Input vertices are never moved or dropped. `points` of a ring need
/// not repeat the first point at the end (a repeated one is removed).
pub fn prepare(points: &[Pt], closed: bool) -> Result<Prepared, String> {
    if let Some(p) = points
        .iter()
        .find(|p| !p[0].is_finite() || !p[1].is_finite())
    {
        return Err(format!("a vertex is not finite: {p:?}"));
    }
    let mut pts = points.to_vec();
    if closed && pts.len() > 1 && pts.first() == pts.last() {
        pts.pop();
    }
    let min = if closed { 3 } else { 2 };
    if pts.len() < min {
        return Err(format!(
            "a {} needs at least {min} vertices, this one has {}",
            if closed { "ring" } else { "polyline" },
            pts.len()
        ));
    }
    // Segments to fill: n for a ring, n - 1 for an open polyline. Pick the levels L and pieces K
    // with K·2^(L+1) >= segments that cost least: an inserted point costs about one coded
    // point (~1 byte), a base piece about two coarsely coded points (~8 bytes).
    let segments = if closed { pts.len() } else { pts.len() - 1 };
    let mut best = (f64::INFINITY, 0, 1);
    for levels in 0..=MAX_LEVELS {
        let per = 2usize << levels;
        let pieces = segments.div_ceil(per).max(if closed { 2 } else { 1 });
        let inserted = pieces * per - segments;
        let cost = inserted as f64 + 8.0 * pieces as f64;
        if cost < best.0 {
            best = (cost, levels, pieces);
        }
        if per > segments {
            break;
        }
    }
    let (_, levels, pieces) = best;
    let extra = pieces * (2 << levels) - segments;
    // Split the longest segments: each input segment s gets k_s extra points, evenly spaced
    // on it, chosen greedily by the length of its sub-segments (a heap of segments).
    let seg_len = |i: usize| {
        let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
    };
    let mut splits = vec![0usize; segments];
    let mut heap: std::collections::BinaryHeap<(OrdF64, usize)> =
        (0..segments).map(|i| (OrdF64(seg_len(i)), i)).collect();
    for _ in 0..extra {
        let (_, i) = heap.pop().expect("segments is non-empty");
        splits[i] += 1;
        heap.push((OrdF64(seg_len(i) / (splits[i] + 1) as f64), i));
    }
    let mut fine = Vec::with_capacity(pieces * (2 << levels) + 1);
    let mut inserted = Vec::with_capacity(extra);
    for (i, &k) in splits.iter().enumerate() {
        let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
        fine.push(a);
        for j in 1..=k {
            let t = j as f64 / (k + 1) as f64;
            inserted.push(fine.len() as u32);
            fine.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
        }
    }
    if !closed {
        fine.push(*pts.last().expect("non-empty"));
    }
    Ok(Prepared {
        closed,
        pieces,
        fine,
        inserted,
    })
}

/// How a ring's coded points relate to its input: where it crosses the antimeridian (fine
/// indices) and the input vertex it starts at ([`Ring::start`]).
pub type Frame = (Vec<SeamCrossing>, Option<u32>);

/// The fine index of input vertex `i`: `i` plus the inserted points before it.
fn fine_index(inserted: &[u32], i: usize) -> usize {
    let mut f = i;
    for &k in inserted {
        if k as usize <= f {
            f += 1;
        }
    }
    f
}

/// The seam of input vertex indices as fine indices of `p` (inserted points shift them).
pub(super) fn seam_to_fine(seam: &[SeamCrossing], p: &Prepared) -> Vec<SeamCrossing> {
    seam.iter()
        .map(|c| SeamCrossing {
            at: fine_index(&p.inserted, c.at as usize) as u32,
            turns: c.turns,
        })
        .collect()
}

/// Total order on lengths for the heap (lengths are finite: vertices were checked).
#[derive(Clone, Copy)]
struct OrdF64(f64);
impl PartialEq for OrdF64 {
    fn eq(&self, o: &Self) -> bool {
        self.cmp(o).is_eq()
    }
}
impl Eq for OrdF64 {}
impl PartialOrd for OrdF64 {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for OrdF64 {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&o.0)
    }
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

/// Largest distance from a point of `fine` to the segment of `coarse` whose span holds it
/// (`fine` refines `coarse` by a power of two per segment).
pub fn span_deviation(metric: Metric, coarse: &[Pt], fine: &[Pt], closed: bool) -> f64 {
    let segs = coarse.len() - usize::from(!closed);
    let fsegs = fine.len() - usize::from(!closed);
    if segs == 0 {
        return 0.0;
    }
    let per = fsegs / segs;
    let mut worst = 0.0f64;
    for (j, &p) in fine.iter().enumerate() {
        let s = (j / per).min(segs - 1);
        let (a, b) = (coarse[s], coarse[(s + 1) % coarse.len()]);
        worst = worst.max(metric.point_segment(p, a, b));
    }
    worst
}

/// The Hausdorff distance between two polylines, both ways, in the metric's units (for figures
/// and tests): from every vertex and from points every `spacing` along every segment to the
/// other polyline (exact to within `spacing / 2`, since distance to a polyline is
/// 1-Lipschitz; `spacing = 0` measures from vertices only).
pub fn hausdorff(metric: Metric, a: &[Pt], b: &[Pt], spacing: f64) -> f64 {
    directed(metric, a, b, spacing).max(directed(metric, b, a, spacing))
}

fn directed(metric: Metric, from: &[Pt], to: &[Pt], spacing: f64) -> f64 {
    if from.is_empty() || to.is_empty() {
        return f64::INFINITY;
    }
    let grid = SegmentGrid::new(to);
    let mut worst = 0.0f64;
    for (k, &p) in from.iter().enumerate() {
        worst = worst.max(grid.distance(metric, p));
        let Some(&q) = from.get(k + 1) else { continue };
        if spacing > 0.0 {
            let n = (metric.distance(p, q) / spacing).ceil().min(1e6) as usize;
            for j in 1..n {
                let t = j as f64 / n as f64;
                let s = [p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])];
                worst = worst.max(grid.distance(metric, s));
            }
        }
    }
    worst
}

/// The segments of a polyline bucketed on a regular grid of lon/lat cells, for nearest-segment
/// queries. Hand-written: the metric scales x by the cosine at the query point, which the
/// spatial-index crates' fixed metrics do not express, and a grid is a dozen lines.
pub(crate) struct SegmentGrid {
    segs: Vec<(Pt, Pt)>,
    origin: Pt,
    cell: f64,
    size: [i64; 2],
    cells: Vec<Vec<u32>>,
}

impl SegmentGrid {
    pub(crate) fn new(line: &[Pt]) -> Self {
        let segs: Vec<(Pt, Pt)> = if line.len() == 1 {
            vec![(line[0], line[0])]
        } else {
            line.windows(2).map(|w| (w[0], w[1])).collect()
        };
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        let mut total = 0.0;
        for &(a, b) in &segs {
            for k in 0..2 {
                lo[k] = lo[k].min(a[k]).min(b[k]);
                hi[k] = hi[k].max(a[k]).max(b[k]);
            }
            total += (a[0] - b[0]).abs().max((a[1] - b[1]).abs());
        }
        // Cells about twice a mean segment, at most ~1M of them.
        let span = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1e-12);
        let cell = (2.0 * total / segs.len() as f64)
            .max(span / 1024.0)
            .max(1e-12);
        let size = [
            ((hi[0] - lo[0]) / cell) as i64 + 1,
            ((hi[1] - lo[1]) / cell) as i64 + 1,
        ];
        let mut cells = vec![Vec::new(); (size[0] * size[1]) as usize];
        for (i, &(a, b)) in segs.iter().enumerate() {
            let c0 = |k: usize| ((a[k].min(b[k]) - lo[k]) / cell) as i64;
            let c1 = |k: usize| (((a[k].max(b[k]) - lo[k]) / cell) as i64).min(size[k] - 1);
            for y in c0(1)..=c1(1) {
                for x in c0(0)..=c1(0) {
                    cells[(y * size[0] + x) as usize].push(i as u32);
                }
            }
        }
        SegmentGrid {
            segs,
            origin: lo,
            cell,
            size,
            cells,
        }
    }

    /// Distance from `p` to the nearest segment: rings of cells outward from `p`'s cell until
    /// the next ring cannot hold anything nearer (a cell `r` rings away is at least
    /// `(r - 1)·cell` away in x or in y, and the metric scales x by at most 1).
    pub(crate) fn distance(&self, metric: Metric, p: Pt) -> f64 {
        let c = [0, 1].map(|k| ((p[k] - self.origin[k]) / self.cell).floor() as i64);
        let scale = metric.x_scale(p[1]).min(1.0);
        let reach = (0..2)
            .map(|k| (c[k]).abs().max((c[k] - self.size[k] + 1).abs()))
            .max()
            .unwrap_or(0);
        let mut best = f64::INFINITY;
        for r in 0..=reach {
            if best <= (r - 1) as f64 * self.cell * scale {
                break;
            }
            for y in (c[1] - r)..=(c[1] + r) {
                if y < 0 || y >= self.size[1] {
                    continue;
                }
                let edge = y == c[1] - r || y == c[1] + r;
                let mut x = c[0] - r;
                while x <= c[0] + r {
                    if x >= 0 && x < self.size[0] {
                        for &i in &self.cells[(y * self.size[0] + x) as usize] {
                            let (a, b) = self.segs[i as usize];
                            best = best.min(metric.point_segment(p, a, b));
                        }
                    }
                    // Inner rows only visit the ring's two end cells.
                    x += if edge || r == 0 { 1 } else { 2 * r };
                }
            }
        }
        best
    }
}
