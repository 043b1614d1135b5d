//! Triangle meshes and their files: a regular-grid terrain mesh from sampled heights, and
//! writers for OBJ (text), PLY (binary little-endian) and glTF 2.0 binary (GLB). Hand-written:
//! each format is a page of spec, and the crates that write them pull in far more than these
//! few lines (the glTF crate's writer needs its full JSON model).

/// Vertices and triangles.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// Triangles, counter-clockwise seen from +z (up).
    pub triangles: Vec<[u32; 3]>,
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
        }
    }

    /// Wavefront OBJ text.
    pub fn to_obj(&self) -> Vec<u8> {
        use std::fmt::Write;
        let mut s = String::with_capacity(self.positions.len() * 32 + self.triangles.len() * 24);
        s.push_str("# fractile terrain mesh\n");
        for p in &self.positions {
            let _ = writeln!(s, "v {} {} {}", p[0], p[1], p[2]);
        }
        for t in &self.triangles {
            let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
        }
        s.into_bytes()
    }

    /// Binary little-endian PLY.
    pub fn to_ply(&self) -> Vec<u8> {
        let mut out = format!(
            "ply\nformat binary_little_endian 1.0\ncomment fractile terrain mesh\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar uint vertex_indices\nend_header\n",
            self.positions.len(),
            self.triangles.len()
        )
        .into_bytes();
        for p in &self.positions {
            p.iter()
                .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        }
        for t in &self.triangles {
            out.push(3);
            t.iter()
                .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        }
        out
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
        for t in &self.triangles {
            t.iter()
                .for_each(|v| bin.extend_from_slice(&v.to_le_bytes()));
        }
        let idx_len = bin.len() - pos_len;
        let json = format!(
            concat!(
                r#"{{"asset":{{"version":"2.0","generator":"fractile"}},"scene":0,"scenes":[{{"nodes":[0]}}],"#,
                r#""nodes":[{{"mesh":0}}],"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1,"mode":4}}]}}],"#,
                r#""buffers":[{{"byteLength":{}}}],"#,
                r#""bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":{},"target":34962}},{{"buffer":0,"byteOffset":{},"byteLength":{},"target":34963}}],"#,
                r#""accessors":[{{"bufferView":0,"componentType":5126,"count":{},"type":"VEC3","min":[{},{},{}],"max":[{},{},{}]}},"#,
                r#"{{"bufferView":1,"componentType":5125,"count":{},"type":"SCALAR"}}]}}"#
            ),
            bin.len(),
            pos_len,
            pos_len,
            idx_len,
            self.positions.len(),
            lo[0],
            lo[1],
            lo[2],
            hi[0],
            hi[1],
            hi[2],
            self.triangles.len() * 3
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

#[cfg(test)]
mod tests {
    use super::*;

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
