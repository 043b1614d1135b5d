//! Cesium's terrain format, quantized-mesh-1.0: a terrain mesh over one tile of the geographic
//! tiling scheme, as CesiumJS streams it (the format's specification is Cesium's
//! `quantized-mesh` repository).
//!
//! A tile is a header (the tile's centre, its height range, a bounding sphere and a horizon
//! occlusion point, all in WGS84 Earth-centred coordinates), the vertices (u, v across the tile
//! and the height across its range, each 0..=32767, zig-zag delta coded), the triangles
//! (high-water-mark coded indices) and the vertices on each of the four edges (for the skirts
//! Cesium hangs there). Written here: no maintained Rust crate writes the format, and it is a
//! few dozen lines over the mesh we already build.

use crate::mesh::Mesh;

/// WGS84 semi-major axis, metres.
const A: f64 = 6_378_137.0;
/// WGS84 semi-minor axis, metres.
const B: f64 = 6_356_752.314_245_179;
/// Largest quantized coordinate.
const Q: f64 = 32767.0;

/// A tile's mesh in grid units, ready to write: vertex `(x, y, h)` at column `x` (west to east,
/// 0..n-1) and row `-y` (north to south) of an `n x n` grid spanning `bounds`.
pub struct TerrainTile<'a> {
    /// Vertices and triangles: positions `(column, -row, height in metres)`, as
    /// [`Mesh::adaptive`] and [`Mesh::grid`] make them with origin (0, 0) and spacing (1, 1).
    pub mesh: &'a Mesh,
    /// Samples a side of the grid the mesh was made on.
    pub n: usize,
    /// West, south, east, north, degrees.
    pub bounds: [f64; 4],
    /// Unit normals (Earth-centred) of the grid's `n x n` points, row-major from the north
    /// ([`grid_normals`]): written as the `octvertexnormals` extension when present.
    pub normals: Option<&'a [[f64; 3]]>,
}

/// Unit normals, Earth-centred, of an `n x n` grid of heights (metres; row 0 north, column 0
/// west) over `bounds` (degrees): from the slopes by central differences (one-sided at the
/// edges) in the local east-north-up frame, turned to Earth-centred axes. Non-finite heights
/// count as 0.
pub fn grid_normals(heights: &[f32], n: usize, bounds: [f64; 4]) -> Vec<[f64; 3]> {
    let [w, s, e, no] = bounds;
    let last = (n.max(2) - 1) as f64;
    let h = |i: usize, j: usize| {
        let v = heights[j * n + i];
        if v.is_finite() { f64::from(v) } else { 0.0 }
    };
    let mut out = Vec::with_capacity(n * n);
    for j in 0..n {
        let lat = no - j as f64 / last * (no - s);
        let (p, c) = (lat.to_radians().sin(), lat.to_radians().cos());
        // Metres per degree along the parallel and the meridian (spherical, enough for slopes).
        let metres = A * std::f64::consts::PI / 180.0;
        let dx = (e - w) / last * metres * c.max(1e-6);
        let dy = (no - s) / last * metres;
        for i in 0..n {
            let lon = w + i as f64 / last * (e - w);
            let (i0, i1) = (i.saturating_sub(1), (i + 1).min(n - 1));
            let (j0, j1) = (j.saturating_sub(1), (j + 1).min(n - 1));
            let dhdx = (h(i1, j) - h(i0, j)) / (dx * (i1 - i0).max(1) as f64);
            // Rows run southwards: north is towards j0.
            let dhdy = (h(i, j0) - h(i, j1)) / (dy * (j1 - j0).max(1) as f64);
            let (ee, nn, uu) = (-dhdx, -dhdy, 1.0);
            let (sl, cl) = (lon.to_radians().sin(), lon.to_radians().cos());
            let east = [-sl, cl, 0.0];
            let north = [-p * cl, -p * sl, c];
            let up = [c * cl, c * sl, p];
            let v: [f64; 3] = std::array::from_fn(|a| ee * east[a] + nn * north[a] + uu * up[a]);
            let len = norm(v);
            out.push(v.map(|x| x / len));
        }
    }
    out
}

/// A unit vector in two bytes: the octahedron projection, as Cesium decodes it.
fn oct_encode(v: [f64; 3]) -> [u8; 2] {
    let l1 = v[0].abs() + v[1].abs() + v[2].abs();
    let (mut x, mut y) = (v[0] / l1, v[1] / l1);
    if v[2] < 0.0 {
        let sign = |t: f64| if t < 0.0 { -1.0 } else { 1.0 };
        (x, y) = ((1.0 - y.abs()) * sign(x), (1.0 - x.abs()) * sign(y));
    }
    [x, y].map(|t| ((t.clamp(-1.0, 1.0) * 0.5 + 0.5) * 255.0).round() as u8)
}

/// Earth-centred, Earth-fixed coordinates of a WGS84 point (degrees, metres above the
/// ellipsoid).
pub fn ecef(lon: f64, lat: f64, h: f64) -> [f64; 3] {
    let (l, p) = (lon.to_radians(), lat.to_radians());
    let e2 = 1.0 - (B * B) / (A * A);
    let n = A / (1.0 - e2 * p.sin().powi(2)).sqrt();
    [
        (n + h) * p.cos() * l.cos(),
        (n + h) * p.cos() * l.sin(),
        (n * (1.0 - e2) + h) * p.sin(),
    ]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// The horizon occlusion point: a point in the ellipsoid's scaled space (coordinates divided
/// by its radii, where the ellipsoid is the unit sphere), along the direction of `towards`,
/// such that when it is below a viewer's horizon so is every one of `points`. For each point,
/// the distance along that direction at which the tangent cone from the unit sphere through
/// the point meets it; the largest of these.
fn horizon_occlusion_point(points: &[[f64; 3]], towards: [f64; 3]) -> [f64; 3] {
    let scaled = |p: [f64; 3]| [p[0] / A, p[1] / A, p[2] / B];
    let d = scaled(towards);
    let len = norm(d);
    if len == 0.0 {
        return [0.0; 3];
    }
    let d = d.map(|v| v / len);
    let mut magnitude = 0.0f64;
    for &p in points {
        let s = scaled(p);
        let m = norm(s).max(1.0);
        let dir = s.map(|v| v / norm(s).max(f64::MIN_POSITIVE));
        let cos_alpha = dot(dir, d).clamp(-1.0, 1.0);
        let sin_alpha = (1.0 - cos_alpha * cos_alpha).max(0.0).sqrt();
        let cos_beta = 1.0 / m;
        let sin_beta = (m * m - 1.0).max(0.0).sqrt() * cos_beta;
        let denominator = cos_alpha * cos_beta - sin_alpha * sin_beta;
        // A point a quarter of the globe away or more has no finite occlusion point: a point
        // a thousand radii out along the tile's direction is hidden only from right behind
        // the globe (the format has no way to say "none").
        magnitude = magnitude.max(if denominator > 0.0 {
            (1.0 / denominator).min(1000.0)
        } else {
            1000.0
        });
    }
    d.map(|v| v * magnitude)
}

/// `v`'s zig-zag code: small magnitudes of either sign become small unsigned numbers.
fn zigzag(v: i32) -> u16 {
    ((v << 1) ^ (v >> 31)) as u16
}

fn put_u32(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put_f64s(out: &mut Vec<u8>, v: &[f64]) {
    for x in v {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

/// Writes an index list as 16-bit or 32-bit little-endian integers.
fn put_indices(out: &mut Vec<u8>, wide: bool, indices: impl IntoIterator<Item = u32>) {
    for i in indices {
        if wide {
            out.extend_from_slice(&i.to_le_bytes());
        } else {
            out.extend_from_slice(&(i as u16).to_le_bytes());
        }
    }
}

/// The bounding sphere (the middle of the vertices' box, and the farthest vertex) and the
/// horizon occlusion point of a tile's vertices (Earth-centred); `centre` when it has none.
fn bounding(world: &[[f64; 3]], centre: [f64; 3]) -> ([f64; 3], f64, [f64; 3]) {
    let (mut bmin, mut bmax) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in world {
        for a in 0..3 {
            bmin[a] = bmin[a].min(p[a]);
            bmax[a] = bmax[a].max(p[a]);
        }
    }
    let sphere = if world.is_empty() {
        centre
    } else {
        std::array::from_fn(|a| 0.5 * (bmin[a] + bmax[a]))
    };
    let radius = world
        .iter()
        .map(|p| norm(sub(*p, sphere)))
        .fold(0.0, f64::max);
    (sphere, radius, horizon_occlusion_point(world, sphere))
}

/// The vertices on the west, south, east and north edges, each list with its count.
fn put_edges(out: &mut Vec<u8>, wide: bool, quantized: &[[u16; 3]]) {
    for on_edge in [
        |q: &[u16; 3]| q[0] == 0,
        |q: &[u16; 3]| q[1] == 0,
        |q: &[u16; 3]| q[0] == Q as u16,
        |q: &[u16; 3]| q[1] == Q as u16,
    ] {
        let edge: Vec<u32> = (0..quantized.len() as u32)
            .filter(|&k| on_edge(&quantized[k as usize]))
            .collect();
        put_u32(out, edge.len() as u32);
        put_indices(out, wide, edge);
    }
}

impl TerrainTile<'_> {
    /// The tile in quantized-mesh-1.0, without extensions. Vertices are renumbered in the
    /// order triangles first use them (what high-water-mark coding needs); unused ones are
    /// dropped. An empty mesh (a tile of nodata) is a valid tile with no triangles.
    pub fn encode(&self) -> Vec<u8> {
        let m = self.mesh;
        let mut order: Vec<u32> = Vec::with_capacity(m.positions.len());
        let mut renumber = vec![u32::MAX; m.positions.len()];
        let mut indices = Vec::with_capacity(m.triangles.len() * 3);
        for t in &m.triangles {
            for &v in t {
                if renumber[v as usize] == u32::MAX {
                    renumber[v as usize] = order.len() as u32;
                    order.push(v);
                }
                indices.push(renumber[v as usize]);
            }
        }
        let [w, s, e, n] = self.bounds;
        let last = (self.n.max(2) - 1) as f64;
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for &v in &order {
            let h = f64::from(m.positions[v as usize][2]);
            lo = lo.min(h);
            hi = hi.max(h);
        }
        if order.is_empty() {
            (lo, hi) = (0.0, 0.0);
        }
        // Grid position and height of each vertex, quantized.
        let quantized: Vec<[u16; 3]> = order
            .iter()
            .map(|&v| {
                let p = m.positions[v as usize];
                let (col, row) = (f64::from(p[0]), -f64::from(p[1]));
                let height = if hi > lo {
                    (f64::from(p[2]) - lo) / (hi - lo)
                } else {
                    0.0
                };
                [col / last, 1.0 - row / last, height]
                    .map(|t| (t.clamp(0.0, 1.0) * Q).round() as u16)
            })
            .collect();
        let world: Vec<[f64; 3]> = quantized
            .iter()
            .map(|q| {
                let t = q.map(|c| f64::from(c) / Q);
                ecef(
                    w + t[0] * (e - w),
                    s + t[1] * (n - s),
                    lo + t[2] * (hi - lo),
                )
            })
            .collect();
        let centre = ecef(0.5 * (w + e), 0.5 * (s + n), 0.5 * (lo + hi));
        let (sphere, radius, horizon) = bounding(&world, centre);
        let mut out = Vec::with_capacity(88 + 4 + 6 * order.len() + 6 * indices.len() + 64);
        put_f64s(&mut out, &centre);
        out.extend_from_slice(&(lo as f32).to_le_bytes());
        out.extend_from_slice(&(hi as f32).to_le_bytes());
        put_f64s(&mut out, &sphere);
        put_f64s(&mut out, &[radius]);
        put_f64s(&mut out, &horizon);
        put_u32(&mut out, order.len() as u32);
        for axis in 0..3 {
            let mut previous = 0i32;
            for q in &quantized {
                let value = i32::from(q[axis]);
                out.extend_from_slice(&zigzag(value - previous).to_le_bytes());
                previous = value;
            }
        }
        // Over 65,536 vertices the indices are 32-bit, aligned to 4 bytes (16-bit ones are
        // aligned already: the header and vertex data have an even length).
        let wide = order.len() > 65_536;
        if wide {
            while !out.len().is_multiple_of(4) {
                out.push(0);
            }
        }
        put_u32(&mut out, (indices.len() / 3) as u32);
        let mut highest = 0u32;
        let coded: Vec<u32> = indices
            .iter()
            .map(|&i| {
                let code = highest - i;
                if code == 0 {
                    highest += 1;
                }
                code
            })
            .collect();
        put_indices(&mut out, wide, coded);
        put_edges(&mut out, wide, &quantized);
        if let Some(normals) = self.normals {
            // Extension 1, octvertexnormals: two bytes a vertex, in vertex order.
            out.push(1);
            put_u32(&mut out, (2 * order.len()) as u32);
            for &v in &order {
                let p = m.positions[v as usize];
                let (col, row) = (p[0].round() as usize, (-p[1]).round() as usize);
                let k = (row * self.n + col).min(normals.len().saturating_sub(1));
                out.extend_from_slice(&oct_encode(normals[k]));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ecef_of_known_points() {
        let p = ecef(0.0, 0.0, 0.0);
        assert!((p[0] - A).abs() < 1e-6 && p[1].abs() < 1e-6 && p[2].abs() < 1e-6);
        let pole = ecef(0.0, 90.0, 0.0);
        assert!((pole[2] - B).abs() < 1e-6, "{pole:?}");
    }

    #[test]
    fn oct_encoding_round_trips_within_a_degree() {
        for v in [
            [0.0, 0.0, 1.0],
            [0.6, -0.8, 0.0],
            [0.267, 0.534, -0.802],
            [-1.0, 0.0, 0.0],
        ] {
            let v: [f64; 3] = v.map(|x| x / norm(v));
            let [a, b] = oct_encode(v).map(|t| f64::from(t) / 255.0 * 2.0 - 1.0);
            let mut d = [a, b, 1.0 - a.abs() - b.abs()];
            if d[2] < 0.0 {
                let sign = |t: f64| if t < 0.0 { -1.0 } else { 1.0 };
                d = [(1.0 - b.abs()) * sign(a), (1.0 - a.abs()) * sign(b), d[2]];
            }
            let cos = dot(d, v) / norm(d);
            assert!(cos > 0.9998, "{v:?}: {cos}");
        }
    }

    #[test]
    fn a_flat_grid_has_the_ellipsoid_up_as_its_normals() {
        let n = 5;
        let normals = grid_normals(&vec![100.0; n * n], n, [10.0, 40.0, 11.0, 41.0]);
        let up = |lon: f64, lat: f64| {
            let (p, l) = (lat.to_radians(), lon.to_radians());
            [p.cos() * l.cos(), p.cos() * l.sin(), p.sin()]
        };
        assert!(dot(normals[0], up(10.0, 41.0)) > 0.999_999);
        assert!(dot(normals[n * n - 1], up(11.0, 40.0)) > 0.999_999);
        // A slope rising eastwards tilts the normal westwards.
        let ramp: Vec<f32> = (0..n * n).map(|k| (k % n) as f32 * 1000.0).collect();
        let tilted = grid_normals(&ramp, n, [10.0, 40.0, 11.0, 41.0]);
        let east = [
            -(10.5f64.to_radians().sin()),
            10.5f64.to_radians().cos(),
            0.0,
        ];
        assert!(
            dot(tilted[2 * n + 2], east) < -0.01,
            "{:?}",
            tilted[2 * n + 2]
        );
    }

    #[test]
    fn zigzag_codes_small_deltas_small() {
        assert_eq!([0, -1, 1, -2, 2].map(zigzag), [0, 1, 2, 3, 4]);
    }

    #[test]
    fn the_occlusion_point_hides_its_vertices() {
        // A viewer on the far side of the globe sees none of them; the point must then be
        // below the horizon too: outside the unit sphere in scaled space, towards the points.
        let pts: Vec<[f64; 3]> = [(10.0, 45.0, 0.0), (10.5, 45.5, 3000.0)]
            .iter()
            .map(|&(lo, la, h)| ecef(lo, la, h))
            .collect();
        let h = horizon_occlusion_point(&pts, ecef(10.25, 45.25, 1500.0));
        assert!(norm(h) > 1.0, "{h:?}");
        // And it lies along the direction of the tile.
        let d = ecef(10.25, 45.25, 0.0);
        let scaled = [d[0] / A, d[1] / A, d[2] / B];
        let cos = dot(h, scaled) / (norm(h) * norm(scaled));
        assert!(cos > 0.999_999, "{cos}");
    }
}
