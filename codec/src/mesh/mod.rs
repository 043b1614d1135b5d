//! Triangle meshes and their files: a regular-grid terrain mesh from sampled heights, readers
//! for OFF, OBJ, PLY and STL (IFS3D's input), and writers for OBJ (text), PLY (binary
//! little-endian) and glTF 2.0 binary (GLB).
//!
//! Reading uses the maintained crates where they exist (`tobj` for OBJ, `ply-rs-bw` for PLY,
//! `stl_io` for STL); OFF has no maintained crate and is a three-line format, so it is parsed
//! here. Writing is hand-written: each format is a page of spec, and the crates that write them
//! pull in far more than these few lines (the glTF crate's writer needs its full JSON model).

use std::path::Path;

use crate::Error;

pub mod quantized;
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

    /// Reads a triangle mesh from an OFF, OBJ, PLY or STL file (chosen by extension). Polygons
    /// are fanned into triangles; faces naming a missing vertex and non-finite coordinates are
    /// errors, not silent holes.
    pub fn read(path: &Path) -> Result<Mesh, Error> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .unwrap_or_default();
        let named = |e: String| Error::input(format!("{}: {e}", path.display())).at(path);
        let mesh = match ext.as_str() {
            "off" => {
                let text = std::fs::read_to_string(path).map_err(|e| named(e.to_string()))?;
                Mesh::parse_off(&text).map_err(named)?
            }
            "obj" => {
                let opts = tobj::LoadOptions {
                    triangulate: true,
                    single_index: true,
                    ..Default::default()
                };
                let (models, _) = tobj::load_obj(path, &opts).map_err(|e| named(e.to_string()))?;
                let mut m = Mesh::default();
                for model in models {
                    let base = m.positions.len() as u32;
                    m.positions.extend(
                        model
                            .mesh
                            .positions
                            .chunks_exact(3)
                            .map(|c| [c[0], c[1], c[2]]),
                    );
                    m.triangles.extend(
                        model
                            .mesh
                            .indices
                            .chunks_exact(3)
                            .map(|t| [base + t[0], base + t[1], base + t[2]]),
                    );
                }
                m
            }
            "stl" => {
                let mut f = std::fs::File::open(path).map_err(|e| named(e.to_string()))?;
                let stl = stl_io::read_stl(&mut f).map_err(|e| named(e.to_string()))?;
                Mesh {
                    positions: stl.vertices.iter().map(|v| v.0).collect(),
                    triangles: stl
                        .faces
                        .iter()
                        .map(|f| f.vertices.map(|i| i as u32))
                        .collect(),
                    normals: Vec::new(),
                }
            }
            "ply" => Mesh::read_ply(path).map_err(named)?,
            _ => {
                return Err(named(format!(
                    "unknown mesh extension {ext:?} (off, obj, ply or stl)"
                )));
            }
        };
        mesh.check().map_err(named)?;
        Ok(mesh)
    }

    /// Parses OFF text: `OFF`, `V F E`, V lines of `x y z`, F lines of `n i j k ...`.
    pub fn parse_off(text: &str) -> Result<Mesh, String> {
        // Comments run from '#' to the end of a line; the counts may share the OFF line.
        let mut words = text
            .lines()
            .map(|l| l.split('#').next().unwrap_or(""))
            .flat_map(str::split_whitespace);
        match words.next() {
            Some(w) if w.ends_with("OFF") => {}
            _ => return Err("not an OFF file (no OFF header)".into()),
        }
        let mut number = |what: &str| -> Result<f64, String> {
            words
                .next()
                .ok_or_else(|| format!("truncated OFF: expected {what}"))?
                .parse::<f64>()
                .map_err(|e| format!("bad {what} in OFF: {e}"))
        };
        let (v, f) = (number("vertex count")?, number("face count")?);
        number("edge count")?;
        if !(v >= 0.0 && f >= 0.0 && v < 1e8 && f < 1e8) {
            return Err(format!("bad OFF counts {v} {f}"));
        }
        let mut m = Mesh::default();
        for _ in 0..v as usize {
            m.positions.push([
                number("x")? as f32,
                number("y")? as f32,
                number("z")? as f32,
            ]);
        }
        for _ in 0..f as usize {
            let n = number("face size")? as usize;
            if !(3..=1024).contains(&n) {
                return Err(format!("OFF face of {n} vertices"));
            }
            let idx = (0..n)
                .map(|_| number("vertex index").map(|i| i as u32))
                .collect::<Result<Vec<_>, _>>()?;
            for k in 1..n - 1 {
                m.triangles.push([idx[0], idx[k], idx[k + 1]]);
            }
        }
        Ok(m)
    }

    fn read_ply(path: &Path) -> Result<Mesh, String> {
        use ply_rs_bw::ply::Property;
        let mut f = std::io::BufReader::new(std::fs::File::open(path).map_err(|e| e.to_string())?);
        let parser = ply_rs_bw::parser::Parser::<ply_rs_bw::ply::DefaultElement>::new();
        let ply = parser.read_ply(&mut f).map_err(|e| e.to_string())?;
        let scalar = |p: Option<&Property>| -> Option<f32> {
            Some(match p? {
                Property::Float(v) => *v,
                Property::Double(v) => *v as f32,
                Property::Int(v) => *v as f32,
                Property::UInt(v) => *v as f32,
                Property::Short(v) => *v as f32,
                Property::UShort(v) => *v as f32,
                Property::Char(v) => *v as f32,
                Property::UChar(v) => *v as f32,
                _ => return None,
            })
        };
        let list = |p: Option<&Property>| -> Option<Vec<u32>> {
            Some(match p? {
                Property::ListInt(v) => v.iter().map(|&i| i as u32).collect(),
                Property::ListUInt(v) => v.clone(),
                Property::ListShort(v) => v.iter().map(|&i| i as u32).collect(),
                Property::ListUShort(v) => v.iter().map(|&i| i as u32).collect(),
                Property::ListUChar(v) => v.iter().map(|&i| i as u32).collect(),
                Property::ListChar(v) => v.iter().map(|&i| i as u32).collect(),
                _ => return None,
            })
        };
        let mut m = Mesh::default();
        for v in ply.payload.get("vertex").map(Vec::as_slice).unwrap_or(&[]) {
            let c = ["x", "y", "z"].map(|k| scalar(v.get(k)));
            let [Some(x), Some(y), Some(z)] = c else {
                return Err("a PLY vertex without numeric x, y, z".into());
            };
            m.positions.push([x, y, z]);
        }
        for f in ply.payload.get("face").map(Vec::as_slice).unwrap_or(&[]) {
            let idx = list(f.get("vertex_indices"))
                .or_else(|| list(f.get("vertex_index")))
                .ok_or("a PLY face without vertex_indices")?;
            for k in 1..idx.len().saturating_sub(1) {
                m.triangles.push([idx[0], idx[k], idx[k + 1]]);
            }
        }
        Ok(m)
    }

    /// Rejects meshes no encoder can use: no triangles, indices past the vertex list,
    /// non-finite coordinates.
    pub fn check(&self) -> Result<(), String> {
        if self.triangles.is_empty() {
            return Err("the mesh has no triangles".into());
        }
        let n = self.positions.len() as u32;
        if let Some(t) = self.triangles.iter().find(|t| t.iter().any(|&i| i >= n)) {
            return Err(format!(
                "triangle {t:?} names a vertex past the {n} vertices"
            ));
        }
        if self.positions.iter().flatten().any(|v| !v.is_finite()) {
            return Err("a vertex has a NaN or infinite coordinate".into());
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

    /// Wavefront OBJ text.
    pub fn to_obj(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.positions.len() * 32 + self.triangles.len() * 24);
        self.write_obj(&mut out).expect("writing to memory");
        out
    }

    /// Writes Wavefront OBJ text as it goes (a server streams large meshes instead of holding
    /// their text whole).
    pub fn write_obj(&self, out: &mut (impl std::io::Write + ?Sized)) -> std::io::Result<()> {
        use std::io::Write;
        let mut w = std::io::BufWriter::with_capacity(1 << 16, out);
        writeln!(w, "# fractile mesh")?;
        for p in &self.positions {
            writeln!(w, "v {} {} {}", p[0], p[1], p[2])?;
        }
        let normals = self.has_normals();
        if normals {
            for n in &self.normals {
                writeln!(w, "vn {} {} {}", n[0], n[1], n[2])?;
            }
        }
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| i + 1);
            if normals {
                writeln!(w, "f {a}//{a} {b}//{b} {c}//{c}")?;
            } else {
                writeln!(w, "f {a} {b} {c}")?;
            }
        }
        w.flush()
    }

    /// Binary little-endian PLY.
    pub fn to_ply(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.positions.len() * 24 + self.triangles.len() * 13);
        self.write_ply(&mut out).expect("writing to memory");
        out
    }

    /// Writes binary little-endian PLY as it goes (see [`Mesh::write_obj`]).
    pub fn write_ply(&self, out: &mut (impl std::io::Write + ?Sized)) -> std::io::Result<()> {
        use std::io::Write;
        let normals = self.has_normals();
        let mut w = std::io::BufWriter::with_capacity(1 << 16, out);
        write!(
            w,
            "ply\nformat binary_little_endian 1.0\ncomment fractile mesh\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n{}element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
            self.positions.len(),
            if normals {
                "property float nx\nproperty float ny\nproperty float nz\n"
            } else {
                ""
            },
            self.triangles.len()
        )?;
        for (i, p) in self.positions.iter().enumerate() {
            for v in p {
                w.write_all(&v.to_le_bytes())?;
            }
            if normals {
                for v in &self.normals[i] {
                    w.write_all(&v.to_le_bytes())?;
                }
            }
        }
        for t in &self.triangles {
            w.write_all(&[3])?;
            for v in t {
                w.write_all(&v.to_le_bytes())?;
            }
        }
        w.flush()
    }

    /// glTF 2.0 binary (GLB): one mesh, positions and u32 indices in one buffer.
    pub fn to_glb(&self) -> Vec<u8> {
        let mut bin = Vec::with_capacity(self.positions.len() * 12 + self.triangles.len() * 12);
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for p in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
                bin.extend_from_slice(&p[k].to_le_bytes());
            }
        }
        if self.positions.is_empty() {
            (lo, hi) = ([0.0; 3], [0.0; 3]);
        }
        let pos_len = bin.len();
        if self.has_normals() {
            for n in &self.normals {
                n.iter()
                    .for_each(|v| bin.extend_from_slice(&v.to_le_bytes()));
            }
        }
        let nrm_len = bin.len() - pos_len;
        for t in &self.triangles {
            t.iter()
                .for_each(|v| bin.extend_from_slice(&v.to_le_bytes()));
        }
        let idx_len = bin.len() - pos_len - nrm_len;
        // Views: 0 positions, 1 indices, 2 normals (when present); accessors likewise.
        let (normal_attr, normal_view, normal_accessor) = if nrm_len > 0 {
            (
                r#","NORMAL":2"#.to_string(),
                format!(
                    r#",{{"buffer":0,"byteOffset":{pos_len},"byteLength":{nrm_len},"target":34962}}"#
                ),
                format!(
                    r#",{{"bufferView":2,"componentType":5126,"count":{},"type":"VEC3"}}"#,
                    self.normals.len()
                ),
            )
        } else {
            Default::default()
        };
        let json = format!(
            concat!(
                r#"{{"asset":{{"version":"2.0","generator":"fractile"}},"scene":0,"scenes":[{{"nodes":[0]}}],"#,
                r#""nodes":[{{"mesh":0}}],"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0{}}},"indices":1,"mode":4}}]}}],"#,
                r#""buffers":[{{"byteLength":{}}}],"#,
                r#""bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":{},"target":34962}},{{"buffer":0,"byteOffset":{},"byteLength":{},"target":34963}}{}],"#,
                r#""accessors":[{{"bufferView":0,"componentType":5126,"count":{},"type":"VEC3","min":[{},{},{}],"max":[{},{},{}]}},"#,
                r#"{{"bufferView":1,"componentType":5125,"count":{},"type":"SCALAR"}}{}]}}"#
            ),
            normal_attr,
            bin.len(),
            pos_len,
            pos_len + nrm_len,
            idx_len,
            normal_view,
            self.positions.len(),
            lo[0],
            lo[1],
            lo[2],
            hi[0],
            hi[1],
            hi[2],
            self.triangles.len() * 3,
            normal_accessor
        );
        let mut json = json.into_bytes();
        while json.len() % 4 != 0 {
            json.push(b' ');
        }
        while bin.len() % 4 != 0 {
            bin.push(0);
        }
        let total = 12 + 8 + json.len() + 8 + bin.len();
        let mut out = Vec::with_capacity(total);
        out.extend_from_slice(b"glTF");
        out.extend_from_slice(&2u32.to_le_bytes());
        out.extend_from_slice(&(total as u32).to_le_bytes());
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(b"JSON");
        out.extend_from_slice(&json);
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&bin);
        out
    }
}

impl Mesh {
    fn has_normals(&self) -> bool {
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

/// The inputs of an adaptive mesh: `2^k + 1` heights a side and a finite `max_error >= 0`.
fn check_rtin(heights: &[f32], n: usize, max_error: f32) -> Result<(), Error> {
    if n < 2 || !(n - 1).is_power_of_two() || heights.len() != n * n {
        return Err(Error::input(format!(
            "an adaptive mesh needs 2^k + 1 heights a side, got {n} ({} heights)",
            heights.len()
        )));
    }
    if !(max_error.is_finite() && max_error >= 0.0) {
        return Err(Error::input(format!(
            "max_error must be a finite number >= 0, got {max_error}"
        )));
    }
    Ok(())
}

/// The vertices an edge of `samples` keeps on its own (Douglas-Peucker: split at the sample
/// farthest from the chord while one leaves it by more than `max_error`; the ends always) and
/// the edge's heights with every other sample moved onto its chord. The farthest sample, not
/// the middle: an edge carries no dyadic constraint (the greedy TIN takes vertices anywhere),
/// and the farthest split keeps 1.5-2x fewer vertices on small tiles. Nodata is off every chord
/// and splits there first, down to single cells.
fn edge_chords(samples: &[f32], max_error: f32) -> (Vec<bool>, Vec<f32>) {
    let last = samples.len() - 1;
    let mut kept = vec![false; samples.len()];
    let mut chords = samples.to_vec();
    (kept[0], kept[last]) = (true, true);
    let mut stack = vec![(0, last)];
    while let Some((a, b)) = stack.pop() {
        let (ha, hb) = (f64::from(samples[a]), f64::from(samples[b]));
        let chord = |k: usize| (ha * (b - k) as f64 + hb * (k - a) as f64) / (b - a) as f64;
        // The first farthest sample (NaN: nodata, infinitely far); both tiles on the edge
        // walk it in the same order and pick the same one.
        let mut far = (a, f64::from(max_error));
        for (k, &h) in samples.iter().enumerate().take(b).skip(a + 1) {
            let d = (f64::from(h) - chord(k)).abs();
            let d = if d.is_nan() { f64::INFINITY } else { d };
            if d > far.1 {
                far = (k, d);
            }
        }
        if far.0 != a {
            kept[far.0] = true;
            stack.extend([(a, far.0), (far.0, b)]);
        } else {
            for (k, c) in chords.iter_mut().enumerate().take(b).skip(a + 1) {
                *c = chord(k) as f32;
            }
        }
    }
    (kept, chords)
}

/// Corners `[ax, ay, bx, by, cx, cy]` (a, b: the long edge; c: the right angle) of triangle
/// `id` of the RTIN over a `tile x tile` grid, numbered as a binary heap: 2 and 3 are the two
/// halves of the square, and triangle k splits into 2k and 2k + 1 (Martini's numbering).
fn rtin_triangle(mut id: usize, tile: usize) -> [usize; 6] {
    let [mut ax, mut ay, mut bx, mut by, mut cx, mut cy] = if id & 1 == 1 {
        [0, 0, tile, tile, tile, 0]
    } else {
        [tile, tile, 0, 0, 0, tile]
    };
    while {
        id >>= 1;
        id > 1
    } {
        let (mx, my) = ((ax + bx) / 2, (ay + by) / 2);
        if id & 1 == 1 {
            (bx, by, ax, ay) = (ax, ay, cx, cy);
        } else {
            (ax, ay, bx, by) = (bx, by, cx, cy);
        }
        (cx, cy) = (mx, my);
    }
    [ax, ay, bx, by, cx, cy]
}

/// The largest vertical distance between the plane through a triangle's corners and the
/// heights of the grid points it covers (infinite where one is nodata).
fn rtin_error(heights: &[f32], n: usize, [ax, ay, bx, by, cx, cy]: [usize; 6]) -> f32 {
    let h = |x: usize, y: usize| heights[y * n + x] as f64;
    let (ha, hb, hc) = (h(ax, ay), h(bx, by), h(cx, cy));
    if !(ha.is_finite() && hb.is_finite() && hc.is_finite()) {
        return f32::INFINITY;
    }
    let [ax, ay, bx, by, cx, cy] = [ax, ay, bx, by, cx, cy].map(|v| v as i64);
    let det = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax);
    let sign = det.signum();
    // Each barycentric numerator is linear in x along a row, `alpha x + beta(y)`; the points
    // inside have all three of det's sign, an interval of x per row found exactly in integers
    // (scanning only it measured 2x faster than testing every point of the bounding box).
    let floor_div = |a: i64, b: i64| {
        let q = a / b;
        if a % b != 0 && ((a < 0) != (b < 0)) {
            q - 1
        } else {
            q
        }
    };
    let mut worst = 0.0f64;
    for y in ay.min(by).min(cy)..=ay.max(by).max(cy) {
        let (ab, bb) = (cy - ay, -ax * (cy - ay) - (y - ay) * (cx - ax));
        let (ac, bc) = (-(by - ay), (bx - ax) * (y - ay) + (by - ay) * ax);
        let (aa, ba) = (-(ab + ac), det - bb - bc);
        let (mut lo, mut hi) = (ax.min(bx).min(cx), ax.max(bx).max(cx));
        for (alpha, beta) in [(ab, bb), (ac, bc), (aa, ba)] {
            // sign * (alpha x + beta) >= 0, i.e. a x >= b.
            let (a, b) = (sign * alpha, -sign * beta);
            match a.cmp(&0) {
                std::cmp::Ordering::Greater => lo = lo.max(-floor_div(-b, a)),
                std::cmp::Ordering::Less => hi = hi.min(floor_div(b, a)),
                std::cmp::Ordering::Equal if b > 0 => hi = lo - 1,
                std::cmp::Ordering::Equal => {}
            }
        }
        for x in lo..=hi {
            let nb = (x - ax) * (cy - ay) - (y - ay) * (cx - ax);
            let nc = (bx - ax) * (y - ay) - (by - ay) * (x - ax);
            let z = ha + (nb as f64 * (hb - ha) + nc as f64 * (hc - ha)) / det as f64;
            let d = (h(x as usize, y as usize) - z).abs();
            if !d.is_finite() {
                return f32::INFINITY;
            }
            worst = worst.max(d);
        }
    }
    // Rounded up, so that the f32 comparison never lets a triangle slip over the bound.
    let w = worst as f32;
    if (w as f64) < worst { w.next_up() } else { w }
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
