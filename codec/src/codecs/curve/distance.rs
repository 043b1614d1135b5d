//! Points of curves and the distances between them: the metric (planar, or metres on the
//! sphere for longitude and latitude), a point to a segment, the deviation of a span and the
//! Hausdorff distance between polylines (on a grid of segments).

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
