//! Triangle meshes and their files: a regular-grid terrain mesh from sampled heights, readers
//! for OFF, OBJ, PLY and STL (IFS3D's input), and writers for OBJ (text), PLY (binary
//! little-endian) and glTF 2.0 binary (GLB).
//!
//! Reading uses the maintained crates where they exist (`tobj` for OBJ, `ply-rs-bw` for PLY,
//! `stl_io` for STL); OFF has no maintained crate and is a three-line format, so it is parsed
//! here. Writing is hand-written: each format is a page of spec, and the crates that write them
//! pull in far more than these few lines (the glTF crate's writer needs its full JSON model).

use crate::Error;
use crate::mesh::rtin::{check_rtin, edge_chords, rtin_error, rtin_triangle};

pub mod distance;
mod files;
pub(crate) use files::glb;
pub mod quantized;
mod rtin;
#[cfg(feature = "simplify")]
mod simplify;
mod tin;

/// Vertices and triangles.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// Triangles, counter-clockwise seen from outside (from +z for terrain).
    pub triangles: Vec<[u32; 3]>,
    /// Unit normal per vertex, pointing out; empty when the mesh has none (then the writers
    /// leave normals out and viewers compute flat ones).
    pub normals: Vec<[f32; 3]>,
}

impl Mesh {
    /// A grid mesh of `n x m` heights (row-major, row 0 at the north / top), with vertex (i, j)
    /// at `(x0 + i * dx, y0 - j * dy, height)`. Triangles touching a NaN height are left out
    /// (nodata makes holes, not spikes).
    pub fn grid(heights: &[f32], n: usize, m: usize, origin: [f32; 2], spacing: [f32; 2]) -> Mesh {
        let mut positions = Vec::with_capacity(n * m);
        for j in 0..m {
            for i in 0..n {
                positions.push([
                    origin[0] + i as f32 * spacing[0],
                    origin[1] - j as f32 * spacing[1],
                    heights[j * n + i],
                ]);
            }
        }
        let mut triangles = Vec::with_capacity(2 * n.saturating_sub(1) * m.saturating_sub(1));
        let ok = |k: usize| heights[k].is_finite();
        for j in 0..m.saturating_sub(1) {
            for i in 0..n.saturating_sub(1) {
                let (a, b, c, d) = (
                    j * n + i,
                    j * n + i + 1,
                    (j + 1) * n + i,
                    (j + 1) * n + i + 1,
                );
                // Rows run south as j grows, so (a, c, b) turns counter-clockwise seen from above.
                if ok(a) && ok(b) && ok(c) {
                    triangles.push([a as u32, c as u32, b as u32]);
                }
                if ok(b) && ok(c) && ok(d) {
                    triangles.push([b as u32, c as u32, d as u32]);
                }
            }
        }
        // Vertices of nodata cells stay (indices stay simple) but at height 0, never NaN.
        for p in &mut positions {
            if !p[2].is_finite() {
                p[2] = 0.0;
            }
        }
        Mesh {
            positions,
            triangles,
            normals: Vec::new(),
        }
    }

    /// An adaptive terrain mesh of `n x n` heights laid out as in [`Mesh::grid`]: a right-
    /// triangulated irregular network (RTIN; Evans et al. 1997, in the form of Mapbox's Martini)
    /// whose surface is within `max_error` (height units) of every height of the grid, with no
    /// cracks (neighbouring triangles always share whole edges). `n` must be `2^k + 1`.
    ///
    /// Written here rather than taken from the `martini` crate: Martini measures a triangle's
    /// error at the middle of its long edge only, so its meshes can miss `max_error` inside
    /// triangles (by 25% on a real DEM in our test); here a triangle's error is the largest
    /// over every grid point it covers, so the bound holds everywhere. Nodata (NaN) heights
    /// count as infinite errors, so the network refines down to single cells around them,
    /// where triangles touching them are left out, as in [`Mesh::grid`]. Only the vertices
    /// that triangles use are kept.
    pub fn adaptive(
        heights: &[f32],
        n: usize,
        origin: [f32; 2],
        spacing: [f32; 2],
        max_error: f32,
    ) -> Result<Mesh, Error> {
        check_rtin(heights, n, max_error)?;
        Ok(Self::rtin((heights, heights), n, (origin, spacing), max_error, &[]).0)
    }

    /// [`Mesh::adaptive`] for meshes that tile the plane with their neighbours (terrain tiles):
    /// each edge's vertices depend on that edge's heights alone, so two tiles that decode the
    /// same heights along their shared edge draw the same polyline there, without cracks or
    /// T-junction gaps.
    ///
    /// Each edge is simplified first on its own (split at its farthest height, recursively,
    /// while one leaves the chord by more than `max_error`); those vertices are forced into the
    /// mesh, and the edge's other heights are replaced by the chords' before the interior is
    /// meshed. The interior is a greedy Delaunay TIN (Garland and Heckbert's method, as
    /// Delatin's) that places no other vertex on the edges: 1.3-2x fewer triangles than the
    /// RTIN at the same error on terrain tiles, and any side `n >= 2`. Heights with nodata
    /// (NaN) keep the RTIN of [`Mesh::adaptive`] (`n` then `2^k + 1`), which refines to single
    /// cells around it; an extra edge vertex it asks for lies on the chord, where the
    /// neighbour's mesh passes. The surface stays within `max_error` of every height (edges
    /// through the chords, the interior through the mesh).
    ///
    /// `bend` is the curvature of the surface the heights stand on, as the sagitta of a span of
    /// one grid unit times 4 (a flat chord of L units falls `bend L^2 / 4` below the middle of
    /// its arc; 0 for a plane): on a globe of radius R with `u` radians a grid unit, `R u^2 /
    /// 2`. Errors are then measured on the heights plus `-bend |p - q|^2` (the sphere to second
    /// order about a point q): a flat triangle's distance to the curved surface, where a long
    /// triangle over flat heights can fall below the ground by its sagitta. Any q gives the same
    /// errors (two such paraboloids differ by an affine function, which linear interpolation
    /// reproduces); an edge takes its own middle, so that both tiles on it compute the same bits.
    ///
    /// Returns the mesh and the largest distance between it and the heights (on the globe, at
    /// the grid's points), at most `max_error`: what a tile's bound adds.
    pub fn adaptive_tile(
        heights: &[f32],
        n: usize,
        origin: [f32; 2],
        spacing: [f32; 2],
        max_error: f32,
        bend: f32,
    ) -> Result<(Mesh, f32), Error> {
        let finite = heights.iter().all(|h| h.is_finite());
        if finite && n >= 2 && heights.len() == n * n {
            check_rtin(&heights[..4], 2, max_error)?;
        } else {
            check_rtin(heights, n, max_error)?;
        }
        if !(bend.is_finite() && bend >= 0.0) {
            return Err(Error::input(format!(
                "bend must be a finite number >= 0, got {bend}"
            )));
        }
        let mut stitched = heights.to_vec();
        let mut forced = Vec::new();
        let last = n - 1;
        // West, east (north to south), north, south (west to east): each shared edge is walked
        // in the same direction by both tiles, so both compute the same chords bit for bit.
        let at = |edge: usize, k: usize| match edge {
            0 => k * n,
            1 => k * n + last,
            2 => k,
            _ => last * n + k,
        };
        // The edge's own arc about its middle: the same on both tiles that share the edge.
        let middle = last as f32 / 2.0;
        let arc = |k: usize| -bend * (k as f32 - middle).powi(2);
        // The largest distance of an edge's chords from its heights (NaN: nodata, no bound).
        let mut edge_error = 0.0f32;
        for edge in 0..4 {
            let samples: Vec<f32> = (0..n).map(|k| heights[at(edge, k)] + arc(k)).collect();
            let (kept, chords) = edge_chords(&samples, max_error);
            for (c, h) in chords.iter().zip(&samples) {
                edge_error = edge_error.max((c - h).abs());
            }
            for k in 0..n {
                // Back to heights: off the kept vertices, where the flat chord passes.
                stitched[at(edge, k)] = if kept[k] {
                    heights[at(edge, k)]
                } else {
                    chords[k] - arc(k)
                };
                if kept[k] {
                    forced.push(at(edge, k));
                }
            }
        }
        // The network measures its errors on the heights over the tile's arc about its centre.
        let measured: Vec<f32> = if bend > 0.0 {
            stitched
                .iter()
                .enumerate()
                .map(|(g, &h)| {
                    let (x, y) = ((g % n) as f32 - middle, (g / n) as f32 - middle);
                    h - bend * (x * x + y * y)
                })
                .collect()
        } else {
            stitched.clone()
        };
        // Finite heights take the greedy Delaunay TIN (fewer triangles for the same error);
        // nodata keeps the RTIN, which refines down to single cells around it and leaves out
        // the triangles that touch it.
        let (mesh, inside) = if finite {
            let (triangles, inside) = tin::greedy(&measured, n, &forced, max_error);
            (
                Self::from_grid_triangles(&stitched, n, (origin, spacing), &triangles),
                inside,
            )
        } else {
            Self::rtin(
                (&measured, &stitched),
                n,
                (origin, spacing),
                max_error,
                &forced,
            )
        };
        // Rounded up past the f32 sums that compared them with the bound.
        Ok((mesh, edge_error.max(inside).min(max_error).next_up()))
    }

    /// A mesh of `triangles` given as grid indices of the `n x n` grid of `heights` (laid out
    /// as in [`Mesh::grid`]), keeping only the vertices they use, counter-clockwise from +z.
    fn from_grid_triangles(
        heights: &[f32],
        n: usize,
        (origin, spacing): ([f32; 2], [f32; 2]),
        triangles: &[[u32; 3]],
    ) -> Mesh {
        let mut mesh = Mesh::default();
        let mut vertex = vec![u32::MAX; n * n];
        for corners in triangles {
            let mut tri = corners.map(|g| {
                let g = g as usize;
                if vertex[g] == u32::MAX {
                    vertex[g] = mesh.positions.len() as u32;
                    mesh.positions.push([
                        origin[0] + (g % n) as f32 * spacing[0],
                        origin[1] - (g / n) as f32 * spacing[1],
                        heights[g],
                    ]);
                }
                vertex[g]
            });
            // Rows run south: a triangle turning positively in grid coordinates turns
            // clockwise seen from +z.
            tri.swap(1, 2);
            mesh.triangles.push(tri);
        }
        mesh
    }

    /// The network of [`Mesh::adaptive`] over checked inputs, with the grid points `forced`
    /// always vertices: errors measured on `measured`, vertices at `heights`; and the largest
    /// error of its triangles (at most `max_error`).
    fn rtin(
        (measured, heights): (&[f32], &[f32]),
        n: usize,
        (origin, spacing): ([f32; 2], [f32; 2]),
        max_error: f32,
        forced: &[usize],
    ) -> (Mesh, f32) {
        let tile = n - 1;
        // Each splittable triangle's error, kept at the middle of its long edge, where the
        // triangle beyond that edge keeps its own too: the two split together (no cracks), and
        // a parent's error covers its children's, so a split child always has a split parent.
        let mut errors = vec![0.0f32; n * n];
        // First each triangle's own error, depth first so that a subtree's heights stay in
        // cache (in the numbering's order, level by level across the whole grid, a 2049 grid
        // took 5 s, bound by cache misses).
        let mut stack = vec![[0, 0, tile, tile, tile, 0], [tile, tile, 0, 0, 0, tile]];
        while let Some(t) = stack.pop() {
            let [ax, ay, bx, by, cx, cy] = t;
            if ax.abs_diff(cx) + ay.abs_diff(cy) <= 1 {
                continue;
            }
            let (mx, my) = ((ax + bx) / 2, (ay + by) / 2);
            let mid = my * n + mx;
            errors[mid] = errors[mid].max(rtin_error(measured, n, t));
            stack.push([cx, cy, ax, ay, mx, my]);
            stack.push([bx, by, cx, cy, mx, my]);
        }
        for &g in forced {
            errors[g] = f32::INFINITY;
        }
        // Then each parent takes its children's errors, finest level first, so that both
        // triangles on each side of an edge are in before the parents above them.
        let triangles = 2 * tile * tile - 2;
        let parents = triangles - tile * tile;
        for i in (0..parents).rev() {
            let [ax, ay, bx, by, cx, cy] = rtin_triangle(i + 2, tile);
            let left = ((ay + cy) / 2) * n + (ax + cx) / 2;
            let right = ((by + cy) / 2) * n + (bx + cx) / 2;
            let mid = ((ay + by) / 2) * n + (ax + bx) / 2;
            errors[mid] = errors[mid].max(errors[left]).max(errors[right]);
        }
        let mut mesh = Mesh {
            positions: Vec::new(),
            triangles: Vec::new(),
            normals: Vec::new(),
        };
        let mut vertex = vec![u32::MAX; n * n];
        // The largest error of a triangle kept (its own, or its pair's over the shared long
        // edge: a bound on it).
        let mut worst = 0.0f32;
        stack.extend([[0, 0, tile, tile, tile, 0], [tile, tile, 0, 0, 0, tile]]);
        while let Some([ax, ay, bx, by, cx, cy]) = stack.pop() {
            let (mx, my) = ((ax + bx) / 2, (ay + by) / 2);
            let splittable = ax.abs_diff(cx) + ay.abs_diff(cy) > 1;
            if splittable && errors[my * n + mx] > max_error {
                stack.push([cx, cy, ax, ay, mx, my]);
                stack.push([bx, by, cx, cy, mx, my]);
                continue;
            }
            if splittable {
                worst = worst.max(errors[my * n + mx]);
            }
            let corners = [ay * n + ax, by * n + bx, cy * n + cx];
            if corners.iter().any(|&g| !heights[g].is_finite()) {
                continue;
            }
            let mut tri = corners.map(|g| {
                if vertex[g] == u32::MAX {
                    vertex[g] = mesh.positions.len() as u32;
                    mesh.positions.push([
                        origin[0] + (g % n) as f32 * spacing[0],
                        origin[1] - (g / n) as f32 * spacing[1],
                        heights[g],
                    ]);
                }
                vertex[g]
            });
            // Counter-clockwise seen from above (+z; rows run south), as the grid's triangles.
            let [a, b, c] = tri.map(|v| mesh.positions[v as usize]);
            if (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) < 0.0 {
                tri.swap(1, 2);
            }
            mesh.triangles.push(tri);
        }
        (mesh, worst)
    }

    /// Rejects meshes no encoder can use: no triangles, indices past the vertex list,
    /// non-finite coordinates.
    pub fn check(&self) -> Result<(), crate::Error> {
        if self.triangles.is_empty() {
            return Err(crate::Error::input("the mesh has no triangles"));
        }
        let n = self.positions.len() as u32;
        if let Some(t) = self.triangles.iter().find(|t| t.iter().any(|&i| i >= n)) {
            return Err(crate::Error::input(format!(
                "triangle {t:?} names a vertex past the {n} vertices"
            )));
        }
        if self.positions.iter().flatten().any(|v| !v.is_finite()) {
            return Err(crate::Error::input(
                "a vertex has a NaN or infinite coordinate",
            ));
        }
        Ok(())
    }

    /// Axis-aligned bounds of the vertices that triangles use: (min, max).
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for t in &self.triangles {
            for &i in t {
                let p = self.positions[i as usize];
                for k in 0..3 {
                    lo[k] = lo[k].min(p[k]);
                    hi[k] = hi[k].max(p[k]);
                }
            }
        }
        (lo, hi)
    }

    /// Total area of the triangles.
    pub fn area(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.positions[i as usize].map(f64::from));
                0.5 * norm(cross(sub(b, a), sub(c, a)))
            })
            .sum()
    }

    /// `count` points spread over the surface in proportion to area (deterministic: a
    /// low-discrepancy sequence, not a random one, so that measurements repeat), plus every
    /// vertex. For Chamfer and Hausdorff distances between meshes.
    pub fn surface_samples(&self, count: usize) -> Vec<[f32; 3]> {
        let total = self.area().max(f64::MIN_POSITIVE);
        let mut out: Vec<[f32; 3]> = self
            .triangles
            .iter()
            .flatten()
            .map(|&i| self.positions[i as usize])
            .collect();
        out.sort_unstable_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
        out.dedup();
        let mut carry = 0.0f64;
        let mut k = 0u64;
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| self.positions[i as usize].map(f64::from));
            carry += 0.5 * norm(cross(sub(b, a), sub(c, a))) / total * count as f64;
            while carry >= 1.0 {
                carry -= 1.0;
                k += 1;
                // R2 sequence (Roberts) folded into the triangle.
                let (mut u, mut v) = (
                    (0.5 + k as f64 * 0.754_877_666_246_692_8).fract(),
                    (0.5 + k as f64 * 0.569_840_290_998_053_2).fract(),
                );
                if u + v > 1.0 {
                    (u, v) = (1.0 - u, 1.0 - v);
                }
                out.push(std::array::from_fn(|d| {
                    (a[d] + u * (b[d] - a[d]) + v * (c[d] - a[d])) as f32
                }));
            }
        }
        out
    }
}

impl Mesh {
    pub(crate) fn has_normals(&self) -> bool {
        !self.normals.is_empty() && self.normals.len() == self.positions.len()
    }
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rtin_errors_cover_every_grid_point_of_every_triangle() {
        // Heights with structure at every scale; each triangle of the network's numbering,
        // against a scan of its bounding box with a plain inside test.
        let n = 33;
        let heights: Vec<f32> = (0..n * n)
            .map(|k| ((k as f32 * 0.618).fract() * 40.0 + (k % n) as f32).sin() * 10.0)
            .collect();
        let tile = n - 1;
        for id in 2..2 * tile * tile {
            let t = rtin_triangle(id, tile);
            let [ax, ay, bx, by, cx, cy] = t.map(|v| v as f64);
            let h = |x: usize, y: usize| heights[y * n + x] as f64;
            let (ha, hb, hc) = (h(t[0], t[1]), h(t[2], t[3]), h(t[4], t[5]));
            let det = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax);
            let mut worst = 0.0f64;
            for y in 0..n {
                for x in 0..n {
                    let (xf, yf) = (x as f64, y as f64);
                    let wb = ((xf - ax) * (cy - ay) - (yf - ay) * (cx - ax)) / det;
                    let wc = ((bx - ax) * (yf - ay) - (by - ay) * (xf - ax)) / det;
                    if wb < -1e-12 || wc < -1e-12 || wb + wc > 1.0 + 1e-12 {
                        continue;
                    }
                    let z = ha + wb * (hb - ha) + wc * (hc - ha);
                    worst = worst.max((h(x, y) - z).abs());
                }
            }
            let e = rtin_error(&heights, n, t) as f64;
            assert!(
                e >= worst && e <= worst * (1.0 + 1e-6) + 1e-9,
                "{t:?}: {e} vs {worst}"
            );
        }
    }

    #[test]
    fn grid_mesh_counts_orientation_and_holes() {
        let h = vec![1.0, 2.0, 3.0, 4.0, f32::NAN, 6.0, 7.0, 8.0, 9.0];
        let m = Mesh::grid(&h, 3, 3, [0.0, 0.0], [1.0, 1.0]);
        assert_eq!(m.positions.len(), 9);
        // 8 triangles in a 3x3 grid, minus the 6 that touch the centre.
        assert_eq!(m.triangles.len(), 2);
        let full = Mesh::grid(&[0.0; 9], 3, 3, [0.0, 0.0], [1.0, 1.0]);
        assert_eq!(full.triangles.len(), 8);
        for t in &full.triangles {
            let [a, b, c] = t.map(|i| full.positions[i as usize]);
            let cross_z = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
            assert!(cross_z > 0.0, "triangle {t:?} is clockwise seen from above");
        }
    }

    #[test]
    fn glb_is_well_formed() {
        let m = Mesh::grid(&[0.0, 1.0, 2.0, 3.0], 2, 2, [10.0, 20.0], [1.0, 1.0]);
        let glb = m.to_glb();
        assert_eq!(&glb[..4], b"glTF");
        assert_eq!(
            u32::from_le_bytes(glb[8..12].try_into().unwrap()) as usize,
            glb.len()
        );
        let jlen = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
        assert_eq!(&glb[16..20], b"JSON");
        let json = std::str::from_utf8(&glb[20..20 + jlen]).unwrap();
        assert!(
            json.contains(r#""count":4,"type":"VEC3""#)
                && json.contains(r#""count":6,"type":"SCALAR""#),
            "{json}"
        );
        let blen = u32::from_le_bytes(glb[20 + jlen..24 + jlen].try_into().unwrap()) as usize;
        assert_eq!(&glb[24 + jlen..28 + jlen], b"BIN\0");
        assert_eq!(blen, 4 * 12 + 6 * 4);
        let obj = String::from_utf8(m.to_obj()).unwrap();
        assert_eq!(obj.lines().filter(|l| l.starts_with("v ")).count(), 4);
        assert_eq!(obj.lines().filter(|l| l.starts_with("f ")).count(), 2);
        let ply = m.to_ply();
        assert!(ply.starts_with(b"ply\nformat binary_little_endian 1.0"));
    }
}
