//! Meshes in files: OFF, OBJ, PLY and STL read; OBJ, PLY and GLB (binary glTF) written.

use std::path::Path;

use crate::Error;
use crate::mesh::Mesh;

impl Mesh {
    /// Reads a triangle mesh from an OFF, OBJ, PLY or STL file (chosen by extension). Polygons
    /// are fanned into triangles; faces naming a missing vertex and non-finite coordinates are
    /// errors, not silent holes.
    pub fn read(path: &Path) -> Result<Mesh, Error> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .unwrap_or_default();
        let named = |e: Error| e.within(path.display()).at(path);
        let mesh = match ext.as_str() {
            "off" => {
                let text = std::fs::read_to_string(path)
                    .map_err(|e| named(Error::input(e.to_string())))?;
                Mesh::parse_off(&text).map_err(named)?
            }
            "obj" => {
                let opts = tobj::LoadOptions {
                    triangulate: true,
                    single_index: true,
                    ..Default::default()
                };
                let (models, _) =
                    tobj::load_obj(path, &opts).map_err(|e| named(Error::input(e.to_string())))?;
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
                let mut f =
                    std::fs::File::open(path).map_err(|e| named(Error::input(e.to_string())))?;
                let stl =
                    stl_io::read_stl(&mut f).map_err(|e| named(Error::input(e.to_string())))?;
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
                return Err(named(Error::input(format!(
                    "unknown mesh extension {ext:?} (off, obj, ply or stl)"
                ))));
            }
        };
        mesh.check().map_err(named)?;
        Ok(mesh)
    }

    /// Parses OFF text: `OFF`, `V F E`, V lines of `x y z`, F lines of `n i j k ...`.
    pub fn parse_off(text: &str) -> Result<Mesh, crate::Error> {
        // Comments run from '#' to the end of a line; the counts may share the OFF line.
        let mut words = text
            .lines()
            .map(|l| l.split('#').next().unwrap_or(""))
            .flat_map(str::split_whitespace);
        match words.next() {
            Some(w) if w.ends_with("OFF") => {}
            _ => return Err(crate::Error::input("not an OFF file (no OFF header)")),
        }
        let mut number = |what: &str| -> Result<f64, crate::Error> {
            words
                .next()
                .ok_or_else(|| crate::Error::input(format!("truncated OFF: expected {what}")))?
                .parse::<f64>()
                .map_err(|e| crate::Error::input(format!("bad {what} in OFF: {e}")))
        };
        let (v, f) = (number("vertex count")?, number("face count")?);
        number("edge count")?;
        if !(v >= 0.0 && f >= 0.0 && v < 1e8 && f < 1e8) {
            return Err(crate::Error::input(format!("bad OFF counts {v} {f}")));
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
                return Err(crate::Error::input(format!("OFF face of {n} vertices")));
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

    fn read_ply(path: &Path) -> Result<Mesh, crate::Error> {
        use ply_rs_bw::ply::Property;
        let mut f = std::io::BufReader::new(
            std::fs::File::open(path).map_err(|e| crate::Error::input(e.to_string()))?,
        );
        let parser = ply_rs_bw::parser::Parser::<ply_rs_bw::ply::DefaultElement>::new();
        let ply = parser
            .read_ply(&mut f)
            .map_err(|e| crate::Error::input(e.to_string()))?;
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
                return Err(crate::Error::input("a PLY vertex without numeric x, y, z"));
            };
            m.positions.push([x, y, z]);
        }
        for f in ply.payload.get("face").map(Vec::as_slice).unwrap_or(&[]) {
            let idx = list(f.get("vertex_indices"))
                .or_else(|| list(f.get("vertex_index")))
                .ok_or(crate::Error::input("a PLY face without vertex_indices"))?;
            for k in 1..idx.len().saturating_sub(1) {
                m.triangles.push([idx[0], idx[k], idx[k + 1]]);
            }
        }
        Ok(m)
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
        glb(json.into_bytes(), bin)
    }
}

/// A glTF 2.0 binary container of a JSON chunk and a binary chunk, each padded to 4 bytes
/// (the JSON with spaces, the binary with zeros), as the format asks.
pub(crate) fn glb(mut json: Vec<u8>, mut bin: Vec<u8>) -> Vec<u8> {
    json.resize(json.len().div_ceil(4) * 4, b' ');
    bin.resize(bin.len().div_ceil(4) * 4, 0);
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
