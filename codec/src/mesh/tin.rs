//! A greedy Delaunay TIN over a square grid of heights (Garland and Heckbert 1995, "Fast
//! polygonal approximation of terrains and height fields"; the form of Mapbox's Delatin): start
//! from the grid's two corner triangles, insert the grid point farthest from the surface, keep
//! the triangulation Delaunay by edge flips, repeat until every point is within the error.
//!
//! Written here rather than taken from the `delatin` crate (0.2, a port of the same method):
//! terrain tiles need vertices forced on their edges (so that neighbours share them), errors
//! measured on one field while vertices stand on another (the globe's curvature), and no
//! candidate on the tile's edges; the crate has none of the three. Its points are the grid's, so
//! every predicate is exact in integers.
//!
//! Against the RTIN ([`super::Mesh::adaptive`]), whose triangles are halves of dyadic squares,
//! a vertex may go anywhere on the grid and triangles take any shape: measured on terrain tiles,
//! 1.3-2.5x fewer triangles at the same error (docs/benchmarks.md "Cesium meshes against
//! Delatin").

use std::collections::BinaryHeap;

/// No twin: the halfedge is on the hull.
const HULL: u32 = u32::MAX;

/// The triangulation being refined. Triangle t has halfedges 3t, 3t + 1, 3t + 2, halfedge e
/// running from `vertices[e]` to the next one's vertex; a triangle's corners turn positively
/// (`orient > 0`) in grid coordinates.
struct Tin<'a> {
    /// Heights the errors are measured on, row-major, `n x n`.
    measured: &'a [f32],
    n: usize,
    /// Grid index of each halfedge's start.
    vertices: Vec<u32>,
    /// Each halfedge's twin in the neighbouring triangle, or [`HULL`].
    twins: Vec<u32>,
    /// Each triangle's farthest interior grid point and its error.
    candidates: Vec<(u32, f32)>,
    /// Each triangle's version: queue entries of an older one are stale.
    versions: Vec<u32>,
    /// Candidates by error (bits of a non-negative f32 order as the floats).
    queue: BinaryHeap<(u32, u32, u32)>,
    /// Triangles changed since their candidates were found.
    changed: Vec<u32>,
    /// Halfedges waiting for the Delaunay test.
    flips: Vec<u32>,
}

/// The greedy TIN over the `n x n` grid (`n >= 2`): errors on `measured`, every grid point in
/// `forced` (on the grid's edges) a vertex, no other vertex on the grid's edges, refined until
/// every interior point is within `max_error`. Returns the triangles as grid indices (positively
/// oriented in grid coordinates: x east, y south) and the largest error left inside.
pub(super) fn greedy(
    measured: &[f32],
    n: usize,
    forced: &[usize],
    max_error: f32,
) -> (Vec<[u32; 3]>, f32) {
    let last = (n - 1) as u32;
    let corner = |x: u32, y: u32| y * n as u32 + x;
    let mut tin = Tin {
        measured,
        n,
        vertices: Vec::new(),
        twins: Vec::new(),
        candidates: Vec::new(),
        versions: Vec::new(),
        queue: BinaryHeap::new(),
        changed: Vec::new(),
        flips: Vec::new(),
    };
    let (nw, ne, se, sw) = (
        corner(0, 0),
        corner(last, 0),
        corner(last, last),
        corner(0, last),
    );
    tin.add([nw, ne, se], [HULL, HULL, HULL]);
    tin.add([nw, se, sw], [2, HULL, HULL]);
    let corners = [nw, ne, se, sw];
    for &g in forced {
        let g = g as u32;
        if !corners.contains(&g) && !tin.vertices.contains(&g) {
            let t = tin.locate(g);
            tin.insert(t, g);
        }
    }
    // Every triangle's candidate, then the farthest point in, while one is out.
    tin.changed = (0..tin.triangles() as u32).collect();
    tin.refresh(max_error);
    while let Some((bits, t, version)) = tin.queue.pop() {
        if tin.versions[t as usize] != version {
            continue;
        }
        if f32::from_bits(bits) <= max_error {
            break;
        }
        let g = tin.candidates[t as usize].0;
        tin.insert(t, g);
        tin.refresh(max_error);
    }
    let worst = tin.candidates.iter().map(|c| c.1).fold(0.0f32, f32::max);
    let triangles = tin
        .vertices
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    (triangles, worst)
}

/// Twice the signed area of (a, b, c) in grid coordinates: positive when they turn from x
/// towards y.
fn orient(a: [i64; 2], b: [i64; 2], c: [i64; 2]) -> i64 {
    (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
}

/// Whether `d` is strictly inside the circle through the positively turning (a, b, c). Exact:
/// grid coordinates in i128.
fn in_circle(a: [i64; 2], b: [i64; 2], c: [i64; 2], d: [i64; 2]) -> bool {
    let [ax, ay, bx, by, cx, cy] = [
        a[0] - d[0],
        a[1] - d[1],
        b[0] - d[0],
        b[1] - d[1],
        c[0] - d[0],
        c[1] - d[1],
    ]
    .map(i128::from);
    let (a2, b2, c2) = (ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy);
    a2 * (bx * cy - cx * by) - b2 * (ax * cy - cx * ay) + c2 * (ax * by - bx * ay) > 0
}

fn next(e: u32) -> u32 {
    if e % 3 == 2 { e - 2 } else { e + 1 }
}

fn prev(e: u32) -> u32 {
    if e.is_multiple_of(3) { e + 2 } else { e - 1 }
}

impl Tin<'_> {
    fn triangles(&self) -> usize {
        self.vertices.len() / 3
    }

    fn point(&self, g: u32) -> [i64; 2] {
        let g = g as usize;
        [(g % self.n) as i64, (g / self.n) as i64]
    }

    /// Links halfedge `e` with `twin` (both ways unless `twin` is the hull).
    /// A twin not made yet (`set` before `add`) is linked back when it is.
    fn link(&mut self, e: u32, twin: u32) {
        self.twins[e as usize] = twin;
        if twin != HULL && (twin as usize) < self.twins.len() {
            self.twins[twin as usize] = e;
        }
    }

    /// Sets triangle `t` (appended when it is the next one) to corners `v` whose halfedges have
    /// the twins `h`.
    fn set(&mut self, t: u32, v: [u32; 3], h: [u32; 3]) {
        let e = 3 * t as usize;
        if e == self.vertices.len() {
            self.vertices.extend([0; 3]);
            self.twins.extend([HULL; 3]);
            self.candidates.push((0, 0.0));
            self.versions.push(0);
        }
        self.vertices[e..e + 3].copy_from_slice(&v);
        for (k, twin) in h.into_iter().enumerate() {
            self.link(3 * t + k as u32, twin);
        }
        self.changed.push(t);
    }

    fn add(&mut self, v: [u32; 3], h: [u32; 3]) -> u32 {
        let t = self.triangles() as u32;
        self.set(t, v, h);
        t
    }

    /// The triangle whose closure holds grid point `g` (a scan: only the few edge vertices are
    /// placed this way, the greedy points come with their triangle).
    fn locate(&self, g: u32) -> u32 {
        let p = self.point(g);
        (0..self.triangles() as u32)
            .find(|&t| {
                let [a, b, c] = [0, 1, 2].map(|k| self.point(self.vertices[3 * t as usize + k]));
                orient(a, b, p) >= 0 && orient(b, c, p) >= 0 && orient(c, a, p) >= 0
            })
            .expect("a grid point lies in the triangulation of its grid")
    }

    /// Inserts grid point `g`, which lies in the closure of triangle `t` and is no vertex, then
    /// restores the Delaunay property.
    fn insert(&mut self, t: u32, g: u32) {
        let p = self.point(g);
        let e0 = 3 * t;
        let on_edge = (0..3).map(|k| e0 + k).find(|&e| {
            orient(
                self.point(self.vertices[e as usize]),
                self.point(self.vertices[next(e) as usize]),
                p,
            ) == 0
        });
        match on_edge {
            None => {
                let [a, b, c] = [0, 1, 2].map(|k| self.vertices[(e0 + k) as usize]);
                let [hab, hbc, hca] = [0, 1, 2].map(|k| self.twins[(e0 + k) as usize]);
                let (t1, t2) = (self.triangles() as u32, self.triangles() as u32 + 1);
                self.set(t, [a, b, g], [hab, 3 * t1 + 2, 3 * t2 + 1]);
                self.add([b, c, g], [hbc, HULL, 3 * t + 1]);
                self.add([c, a, g], [hca, 3 * t + 2, 3 * t1 + 1]);
                self.flips.extend([3 * t, 3 * t1, 3 * t2]);
            }
            Some(e) => self.split(e, g),
        }
        self.legalize();
    }

    /// Inserts grid point `g` on halfedge `e` (x to y, in triangle (x, y, r)): two triangles on
    /// the hull, four inside.
    fn split(&mut self, e: u32, g: u32) {
        let t = e / 3;
        let [x, y, r] = [e, next(e), prev(e)].map(|k| self.vertices[k as usize]);
        let (hyr, hrx) = (self.twins[next(e) as usize], self.twins[prev(e) as usize]);
        let f = self.twins[e as usize];
        let t2 = self.triangles() as u32;
        if f == HULL {
            self.set(t, [x, g, r], [HULL, 3 * t2 + 2, hrx]);
            self.add([g, y, r], [HULL, hyr, 3 * t + 1]);
            self.flips.extend([3 * t + 2, 3 * t2 + 1]);
            return;
        }
        // The other side: (y, x, s).
        let u = f / 3;
        let s = self.vertices[prev(f) as usize];
        let (hxs, hsy) = (self.twins[next(f) as usize], self.twins[prev(f) as usize]);
        let u2 = t2 + 1;
        self.set(t, [x, g, r], [HULL, HULL, hrx]);
        self.set(u, [y, g, s], [HULL, HULL, hsy]);
        self.add([g, y, r], [3 * u, hyr, 3 * t + 1]);
        self.add([g, x, s], [3 * t, hxs, 3 * u + 1]);
        self.flips
            .extend([3 * t + 2, 3 * t2 + 1, 3 * u + 2, 3 * u2 + 1]);
    }

    /// Flips the queued halfedges (each opposite the new point in its triangle) while the
    /// point beyond lies inside the triangle's circumcircle.
    fn legalize(&mut self) {
        while let Some(e) = self.flips.pop() {
            let f = self.twins[e as usize];
            if f == HULL {
                continue;
            }
            let [x, y, p] = [e, next(e), prev(e)].map(|k| self.vertices[k as usize]);
            let q = self.vertices[prev(f) as usize];
            if !in_circle(self.point(x), self.point(y), self.point(p), self.point(q)) {
                continue;
            }
            // Edge x-y becomes p-q: (x, q, p) and (y, p, q).
            let (t, u) = (e / 3, f / 3);
            let (hyp, hpx) = (self.twins[next(e) as usize], self.twins[prev(e) as usize]);
            let (hxq, hqy) = (self.twins[next(f) as usize], self.twins[prev(f) as usize]);
            self.set(t, [x, q, p], [hxq, HULL, hpx]);
            self.set(u, [y, p, q], [hyp, 3 * t + 1, hqy]);
            self.flips.extend([3 * t, 3 * u + 2]);
        }
    }

    /// Finds the changed triangles' candidates and queues those over `max_error`.
    fn refresh(&mut self, max_error: f32) {
        let mut changed = std::mem::take(&mut self.changed);
        changed.sort_unstable();
        changed.dedup();
        for &t in &changed {
            let c = self.candidate(t);
            let t = t as usize;
            self.candidates[t] = c;
            self.versions[t] += 1;
            if c.1 > max_error {
                self.queue.push((c.1.to_bits(), t as u32, self.versions[t]));
            }
        }
        changed.clear();
        self.changed = changed;
    }

    /// The interior grid point of triangle `t` (on its edges too, never on the grid's) farthest
    /// from the plane through its corners, and that distance.
    fn candidate(&self, t: u32) -> (u32, f32) {
        let v = [0, 1, 2].map(|k| self.vertices[3 * t as usize + k]);
        let [a, b, c] = v.map(|g| self.point(g));
        let [za, zb, zc] = v.map(|g| f64::from(self.measured[g as usize]));
        let area = orient(a, b, c) as f64;
        let last = self.n as i64 - 1;
        let mut best = (v[0], 0.0f32);
        let (x0, x1) = (
            a[0].min(b[0]).min(c[0]).max(1),
            a[0].max(b[0]).max(c[0]).min(last - 1),
        );
        let (y0, y1) = (
            a[1].min(b[1]).min(c[1]).max(1),
            a[1].max(b[1]).max(c[1]).min(last - 1),
        );
        for y in y0..=y1 {
            for x in x0..=x1 {
                let p = [x, y];
                let (wa, wb, wc) = (orient(b, c, p), orient(c, a, p), orient(a, b, p));
                // Outside, or a corner (two weights zero: a vertex, error nil).
                if wa < 0
                    || wb < 0
                    || wc < 0
                    || (wa == 0) as u8 + (wb == 0) as u8 + (wc == 0) as u8 >= 2
                {
                    continue;
                }
                let g = (y as usize * self.n + x as usize) as u32;
                let z = (wa as f64 * za + wb as f64 * zb + wc as f64 * zc) / area;
                let err = (z - f64::from(self.measured[g as usize])).abs() as f32;
                if err > best.1 {
                    best = (g, err);
                }
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every interior grid point's distance to the mesh, by a plain scan of each triangle.
    fn largest_error(h: &[f32], n: usize, tris: &[[u32; 3]]) -> f64 {
        let mut worst = 0.0f64;
        let pt = |g: u32| [(g as usize % n) as f64, (g as usize / n) as f64];
        for tri in tris {
            let [a, b, c] = tri.map(pt);
            let det = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
            for g in 0..n * n {
                let p = pt(g as u32);
                let w = |u: [f64; 2], v: [f64; 2]| {
                    ((v[0] - u[0]) * (p[1] - u[1]) - (v[1] - u[1]) * (p[0] - u[0])) / det
                };
                let (wa, wb, wc) = (w(b, c), w(c, a), w(a, b));
                if wa < -1e-12 || wb < -1e-12 || wc < -1e-12 {
                    continue;
                }
                let z = wa * h[tri[0] as usize] as f64
                    + wb * h[tri[1] as usize] as f64
                    + wc * h[tri[2] as usize] as f64;
                worst = worst.max((z - h[g] as f64).abs());
            }
        }
        worst
    }

    #[test]
    fn the_greedy_tin_covers_the_grid_within_its_error_as_a_delaunay_triangulation() {
        let n = 33;
        // Flat edges (the greedy never places a vertex there), structure inside.
        let h: Vec<f32> = (0..n * n)
            .map(|k| {
                let (x, y) = ((k % n) as f32, (k / n) as f32);
                if x == 0.0 || y == 0.0 || x == 32.0 || y == 32.0 {
                    0.0
                } else {
                    (x * 0.4).sin() * (y * 0.3).cos() * 20.0 + ((k * 7919) % 13) as f32 * 0.3
                }
            })
            .collect();
        let (tris, worst) = greedy(&h, n, &[], 1.0);
        assert!(worst <= 1.0);
        assert!(largest_error(&h, n, &tris) <= 1.0 + 1e-4);
        // The triangles tile the square: their areas sum to it, each positively turning.
        let pt = |g: u32| [(g as usize % n) as i64, (g as usize / n) as i64];
        let area: i64 = tris
            .iter()
            .map(|t| orient(pt(t[0]), pt(t[1]), pt(t[2])))
            .sum();
        assert!(
            tris.iter()
                .all(|t| orient(pt(t[0]), pt(t[1]), pt(t[2])) > 0)
        );
        assert_eq!(area, 2 * 32 * 32);
        // Delaunay: no vertex strictly inside any triangle's circumcircle.
        let mut used: Vec<u32> = tris.iter().flatten().copied().collect();
        used.sort_unstable();
        used.dedup();
        for t in &tris {
            for &v in &used {
                assert!(!in_circle(pt(t[0]), pt(t[1]), pt(t[2]), pt(v)));
            }
        }
        // Far fewer triangles than the grid's 2,048.
        assert!(tris.len() < 1_000, "{} triangles", tris.len());
    }

    #[test]
    fn forced_edge_points_are_vertices_and_no_other_edge_point_is() {
        let n = 17;
        let h: Vec<f32> = (0..n * n).map(|k| ((k * 37) % 11) as f32).collect();
        let forced = [4usize, 8, 16 * 17 + 3, 5 * 17, 9 * 17 + 16];
        let (tris, _) = greedy(&h, n, &forced, 0.5);
        let used: std::collections::HashSet<u32> = tris.iter().flatten().copied().collect();
        for g in forced {
            assert!(used.contains(&(g as u32)), "{g} not a vertex");
        }
        let on_edge = |g: u32| {
            let (x, y) = (g as usize % n, g as usize / n);
            x == 0 || y == 0 || x == n - 1 || y == n - 1
        };
        let corners = [0u32, 16, 16 * 17, 16 * 17 + 16];
        for &g in used.iter().filter(|&&g| on_edge(g)) {
            assert!(
                corners.contains(&g) || forced.contains(&(g as usize)),
                "edge vertex {g} not forced"
            );
        }
    }
}
