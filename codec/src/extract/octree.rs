//! A volume as OGC 3D Tiles 1.1 with implicit octree tiling: the cube of the volume's grid
//! halved level by level, each tile's content the surface inside its box sampled at
//! [`CELLS`] cells a side (so the resolution doubles with the level, past the encoded grid
//! by continuous decoding), subtrees that say which tiles exist and which hold a surface,
//! and the tileset that ties them (the server only routes them).
//!
//! Errors are world units (mesh units). A tile's `geometricError` bounds how far its surface
//! is from the surface of the encoded field: marching tetrahedra on samples `c` apart put
//! every vertex on an edge whose ends straddle the surface, within `c` of it, and each sample
//! is within the decode's bound plus the encode's largest error of the field (and the field
//! places the source's surface to half a voxel's diagonal between its samples); the tile states
//! `sqrt(3) c` plus those (a cell's diagonal: conservative), plus what simplifying the tile's
//! surface may move it ([`SIMPLIFIED_CELLS`] cells). Implicit tiling halves the error a level,
//! so the root's is chosen for every level to hold: `(sqrt(3) + s) c_0 + 2^(L-1) e`.
//!
//! Neighbours at a level sample the same lattice on their shared face (their boxes are
//! exact binary fractions of the root's), so their surfaces meet edge to edge: no cracks.

use crate::Error;
use crate::extract::volume::VolumeGridHook;
use crate::io::asset::Asset;
use crate::mesh::Mesh;
pub use fractile_proto::subtree::Subtree;

/// Cells along each side of a tile's box: 16 keeps a tile of a smooth surface at about 500
/// triangles (a few tens of KB as GLB), so a level adds detail where the camera looks.
pub const CELLS: usize = 16;

/// Levels a subtree file holds (1 + 8 + 64 tiles, their availability from one lattice of
/// `CELLS * 4 + 1` samples a side: a 65^3 decode).
pub const SUBTREE_LEVELS: u32 = 3;

/// How far a tile's surface may move when it is simplified, in cells of its level: one cell,
/// which leaves a flat face a few triangles where marching gave it hundreds (fandisk's tiles:
/// see docs/benchmarks.md), and adds a cell to the error each tile states.
pub const SIMPLIFIED_CELLS: f64 = 1.0;

/// How far past the encoded grid the deepest level samples: 4 times finer than its cells.
const PAST_THE_GRID: usize = 4;

/// One tile of the octree: its level and its index along x, y and z (each under `2^level`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TileId {
    /// Level (0: the root).
    pub level: u32,
    /// Index along x.
    pub x: u32,
    /// Index along y.
    pub y: u32,
    /// Index along z.
    pub z: u32,
}

impl TileId {
    /// The root tile.
    pub const ROOT: TileId = TileId {
        level: 0,
        x: 0,
        y: 0,
        z: 0,
    };

    /// The tile `k` (a Morton index over `depth` levels) below this one, `depth` levels down.
    fn descendant(self, depth: u32, k: u64) -> TileId {
        let [x, y, z] = fractile_proto::subtree::descendant([self.x, self.y, self.z], depth, k);
        TileId {
            level: self.level + depth,
            x,
            y,
            z,
        }
    }
}

/// The octree of a volume asset: its root cube, levels and error.
#[derive(Clone, Debug, PartialEq)]
pub struct Octree {
    /// The root cube's lowest corner, world units.
    pub lo: [f64; 3],
    /// The root cube's side, world units.
    pub side: f64,
    /// Levels that exist (0 to `levels - 1`).
    pub levels: u32,
    /// The field's error every tile adds to its sampling's: the encode's largest error of the
    /// field at its samples plus half a voxel's diagonal (world units).
    pub field_error: f64,
}

impl Octree {
    /// Whether `t` is a tile of the octree (a level that exists, indices inside it).
    pub fn holds(&self, t: TileId) -> bool {
        let n = 1u64 << t.level.min(31);
        t.level < self.levels && [t.x, t.y, t.z].iter().all(|&v| u64::from(v) < n)
    }

    /// The box of tile `t`: (lowest corner, highest corner), world units.
    pub fn tile_box(&self, t: TileId) -> ([f64; 3], [f64; 3]) {
        let side = self.side / f64::from(1u32 << t.level);
        let at = [t.x, t.y, t.z];
        let lo: [f64; 3] = std::array::from_fn(|a| self.lo[a] + f64::from(at[a]) * side);
        (lo, lo.map(|v| v + side))
    }

    /// Distance between samples at `level`, world units.
    pub fn spacing(&self, level: u32) -> f64 {
        self.side / (CELLS as f64 * f64::from(1u32 << level))
    }

    /// The root's `geometricError` (every level's is it halved, as implicit tiling has it),
    /// for a decode whose samples are within `bound` of the encoded field: at least each
    /// level's own `(sqrt(3) + SIMPLIFIED_CELLS) c + bound + field_error` (see the module's
    /// note).
    pub fn root_error(&self, bound: f64) -> f64 {
        let e = bound + self.field_error;
        (0..self.levels)
            .map(|l| {
                ((3f64.sqrt() + SIMPLIFIED_CELLS) * self.spacing(l) + e) * f64::from(1u32 << l)
            })
            .fold(0.0, f64::max)
    }

    /// `tileset.json` (3D Tiles 1.1): the root box, the implicit octree, the templates of its
    /// content (`3dtiles/{level}/{x}/{y}/{z}.glb`) and subtrees (`3dtiles/subtrees/...`),
    /// relative to the tileset's URL; `transform` (column-major, glTF's and 3D Tiles' order)
    /// places the tiles' units on the globe, none leaves them in mesh units.
    pub fn tileset(&self, bound: f64, transform: Option<[f64; 16]>) -> serde_json::Value {
        let h = self.side / 2.0;
        let c = self.lo.map(|v| v + h);
        let root_error = self.root_error(bound);
        let mut root = serde_json::json!({
            "boundingVolume": {"box": [c[0], c[1], c[2], h, 0.0, 0.0, 0.0, h, 0.0, 0.0, 0.0, h]},
            "geometricError": root_error,
            "refine": "REPLACE",
            "content": {"uri": "3dtiles/{level}/{x}/{y}/{z}.glb"},
            "implicitTiling": {
                "subdivisionScheme": "OCTREE",
                "subtreeLevels": SUBTREE_LEVELS,
                "availableLevels": self.levels,
                "subtrees": {"uri": "3dtiles/subtrees/{level}/{x}/{y}/{z}.subtree"}
            }
        });
        if let Some(m) = transform {
            root["transform"] = serde_json::json!(m);
        }
        serde_json::json!({
            "asset": {"version": "1.1", "generator": "fractile"},
            "geometricError": 2.0 * root_error,
            "root": root
        })
    }
}

/// How a tile's GLB packs its buffers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Compression {
    /// Quantized buffers as they are (KHR_mesh_quantization): what every glTF reader takes.
    Plain,
    /// The same buffers through meshoptimizer's codecs (EXT_meshopt_compression, which
    /// CesiumJS, cesium-native, three.js with its meshopt decoder and loaders.gl read): about
    /// a third of the bytes, decoded by the viewer in microseconds. Without the `simplify`
    /// feature (meshoptimizer, which WebAssembly builds leave out) tiles are plain.
    #[default]
    Meshopt,
}

/// A tile's vertices as the GLB stores them: positions as 16-bit steps of the box (x, y, z,
/// and a pad that keeps 4-byte alignment), normals as 8-bit normalized (and a pad).
type Quantized = ([u16; 4], [i8; 4]);

/// The glTF 2.0 binary of tile `t`'s mesh: positions and normals turned to glTF's y-up
/// (`(x, z, -y)`, which 3D Tiles turns back to z-up when it draws glTF content) and quantized
/// (KHR_mesh_quantization, which CesiumJS, three.js and the Khronos validator read):
/// positions as 16-bit steps of the tile's box (the node's translation and scale map them
/// back; a step is the box's side / 65535, under a thousandth of a cell), normals as 8-bit
/// normalized, indices 16-bit where the vertices allow: 12 bytes a vertex and 6 a triangle
/// where the plain GLB takes 24 and 12; then, by default, compressed (`compression`) where
/// that makes it smaller (a tile of a few triangles gains less than the extension's JSON).
pub fn tile_glb(octree: &Octree, t: TileId, mesh: &Mesh, compression: Compression) -> Vec<u8> {
    let plain = glb_of(octree, t, mesh, false);
    if cfg!(feature = "simplify") && compression == Compression::Meshopt {
        let packed = glb_of(octree, t, mesh, true);
        if packed.len() < plain.len() {
            return packed;
        }
    }
    plain
}

/// [`tile_glb`] with meshopt's codecs or without.
fn glb_of(octree: &Octree, t: TileId, mesh: &Mesh, meshopt: bool) -> Vec<u8> {
    let (lo, hi) = octree.tile_box(t);
    let side = hi[0] - lo[0];
    // The box's lowest corner in glTF's axes.
    let origin = [lo[0], lo[2], -hi[1]];
    let step = side / 65535.0;
    let normals = mesh.has_normals();
    let vertices = quantized(mesh, origin, step);
    let indices: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
    // Triangles in vertex-cache order, vertices in first-use order: what the codecs (and the
    // GPU) predict best.
    #[cfg(feature = "simplify")]
    let (indices, vertices) = match meshopt {
        true => {
            let mut indices = meshopt::optimize_vertex_cache(&indices, vertices.len());
            let vertices = meshopt::optimize_vertex_fetch(&mut indices, &vertices);
            (indices, vertices)
        }
        false => (indices, vertices),
    };
    let (mut qlo, mut qhi) = ([u16::MAX; 3], [0u16; 3]);
    for (q, _) in &vertices {
        for a in 0..3 {
            qlo[a] = qlo[a].min(q[a]);
            qhi[a] = qhi[a].max(q[a]);
        }
    }
    let wide = vertices.len() > usize::from(u16::MAX);
    let positions: Vec<u8> = vertices
        .iter()
        .flat_map(|(q, _)| q.iter().flat_map(|v| v.to_le_bytes()))
        .collect();
    let normal_bytes: Vec<u8> = match normals {
        true => vertices
            .iter()
            .flat_map(|(_, n)| n.map(|v| v as u8))
            .collect(),
        false => Vec::new(),
    };
    let index_bytes: Vec<u8> = match wide {
        true => indices.iter().flat_map(|i| i.to_le_bytes()).collect(),
        false => indices
            .iter()
            .flat_map(|&i| (i as u16).to_le_bytes())
            .collect(),
    };
    // The views as a reader sees them (decoded), and the streams the binary chunk holds.
    let layout = [
        (positions, 8, 34962),
        (normal_bytes, 4, 34962),
        (index_bytes, 0, 34963),
    ];
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut decoded = 0;
    for (k, (bytes, stride, target)) in layout.iter().enumerate() {
        if bytes.is_empty() && k == 1 {
            continue;
        }
        let offset = if meshopt { decoded } else { bin.len() };
        let mut view = serde_json::json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len(), "target": target});
        if *stride > 0 {
            view["byteStride"] = serde_json::json!(stride);
        }
        if meshopt {
            let (stream, mode, width, count) = meshopt_stream(k, &vertices, &indices, wide);
            view["buffer"] = serde_json::json!(1);
            view["extensions"] = serde_json::json!({"EXT_meshopt_compression": {
                "buffer": 0, "byteOffset": bin.len(), "byteLength": stream.len(),
                "byteStride": width, "mode": mode, "count": count}});
            bin.extend_from_slice(&stream);
            // Each view decodes to 4-byte aligned memory.
            decoded += bytes.len().div_ceil(4) * 4;
        } else {
            bin.extend_from_slice(bytes);
        }
        bin.resize(bin.len().div_ceil(4) * 4, 0);
        views.push(view);
    }
    let count = vertices.len();
    let mut attributes = serde_json::json!({"POSITION": 0});
    let mut accessors = vec![
        serde_json::json!({"bufferView": 0, "componentType": 5123, "count": count, "type": "VEC3",
                           "min": qlo, "max": qhi}),
        serde_json::json!({"bufferView": views.len() - 1, "componentType": if wide { 5125 } else { 5123 },
                           "count": indices.len(), "type": "SCALAR"}),
    ];
    if normals {
        attributes["NORMAL"] = serde_json::json!(2);
        accessors.push(serde_json::json!({"bufferView": 1, "componentType": 5120, "normalized": true, "count": count, "type": "VEC3"}));
    }
    let mut extensions = vec!["KHR_mesh_quantization"];
    let mut buffers = vec![serde_json::json!({"byteLength": bin.len()})];
    if meshopt {
        extensions.push("EXT_meshopt_compression");
        // The decoded views live in a buffer with no bytes of its own (the extension's
        // fallback), which readers of the extension fill.
        buffers.push(serde_json::json!({"byteLength": decoded,
            "extensions": {"EXT_meshopt_compression": {"fallback": true}}}));
    }
    let json = serde_json::json!({
        "asset": {"version": "2.0", "generator": "fractile"},
        "extensionsUsed": extensions,
        "extensionsRequired": extensions,
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": origin, "scale": [step, step, step]}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": 1, "mode": 4}]}],
        "buffers": buffers,
        "bufferViews": views,
        "accessors": accessors,
    });
    crate::mesh::glb(json.to_string().into_bytes(), bin)
}

/// `mesh`'s vertices in glTF's axes as [`Quantized`]: positions in steps of `step` from
/// `origin`, normals (zero where the mesh has none) as 8-bit normalized.
fn quantized(mesh: &Mesh, origin: [f64; 3], step: f64) -> Vec<Quantized> {
    let normals = mesh.has_normals();
    let mut vertices: Vec<Quantized> = Vec::with_capacity(mesh.positions.len());
    for (i, p) in mesh.positions.iter().enumerate() {
        let up = [f64::from(p[0]), f64::from(p[2]), -f64::from(p[1])];
        // The box's faces are steps 0 and 65535, and only vertices on them (the ones a
        // neighbour shares) land there: one near a face is not rounded onto it.
        let q: [u16; 3] = std::array::from_fn(|a| match (up[a] - origin[a]) / step {
            v if v.abs() < 1e-3 => 0,
            v if (v - 65535.0).abs() < 1e-3 => 65535,
            v => v.round().clamp(1.0, 65534.0) as u16,
        });
        let n = match normals {
            true => {
                let n = mesh.normals[i];
                [n[0], n[2], -n[1], 0.0].map(|v| (v.clamp(-1.0, 1.0) * 127.0).round() as i8)
            }
            false => [0; 4],
        };
        vertices.push(([q[0], q[1], q[2], 0], n));
    }
    vertices
}

/// View `k` (positions, normals, indices) through meshoptimizer's codecs: the stream, its
/// mode, the width of an element and how many there are. Vertex streams use the codec's
/// version 0 and indices version 1, the versions EXT_meshopt_compression names.
#[cfg(feature = "simplify")]
fn meshopt_stream(
    k: usize,
    vertices: &[Quantized],
    indices: &[u32],
    wide: bool,
) -> (Vec<u8>, &'static str, usize, usize) {
    // Encoding into a buffer sized by meshoptimizer's own bound cannot fail.
    let or_empty = |r: meshopt::Result<Vec<u8>>| r.unwrap_or_default();
    match k {
        0 => {
            let p: Vec<[u16; 4]> = vertices.iter().map(|v| v.0).collect();
            (
                or_empty(meshopt::encode_vertex_buffer(&p)),
                "ATTRIBUTES",
                8,
                p.len(),
            )
        }
        1 => {
            let n: Vec<[i8; 4]> = vertices.iter().map(|v| v.1).collect();
            (
                or_empty(meshopt::encode_vertex_buffer(&n)),
                "ATTRIBUTES",
                4,
                n.len(),
            )
        }
        _ => {
            let stream = or_empty(meshopt::encode_index_buffer(indices, vertices.len()));
            (stream, "TRIANGLES", if wide { 4 } else { 2 }, indices.len())
        }
    }
}

#[cfg(not(feature = "simplify"))]
fn meshopt_stream(
    _: usize,
    _: &[Quantized],
    _: &[u32],
    _: bool,
) -> (Vec<u8>, &'static str, usize, usize) {
    unreachable!("meshopt is false without the simplify feature")
}

impl Asset {
    /// The octree of a volume asset: its grid's cube, levels down to 4 times
    /// finer than the encoded grid.
    pub fn octree(&self) -> Result<Octree, Error> {
        let v = self
            .volume()
            .ok_or_else(|| Error::settings("3D Tiles are made of volumes"))?;
        let (lo, hi) = v.bounds();
        let finest = (v.size() * PAST_THE_GRID).div_ceil(CELLS).max(1);
        Ok(Octree {
            lo,
            side: hi[0] - lo[0],
            levels: finest.next_power_of_two().trailing_zeros() + 1,
            // The field's largest error at the grid's samples (what the encoder measured),
            // plus half a voxel's diagonal: the sampled distance field places the source's
            // surface only to about that between its samples (a tube thinner than a voxel,
            // a sharp edge). Measured on knot2 at 4x past its grid: 0.045 from the source,
            // where the samples' error alone would have stated 0.036.
            field_error: self.meta.stats.max_error.max(0.0)
                + 0.5 * 3f64.sqrt() * (hi[0] - lo[0]) / v.size() as f64,
        })
    }

    /// The surface inside tile `t`'s box, sampled at [`CELLS`] cells a side (continuous
    /// decoding, offered to `hook` first), and the decode's largest bound.
    pub fn octree_tile(
        &self,
        octree: &Octree,
        t: TileId,
        (iterations, tolerance): (u32, f32),
        hook: Option<&VolumeGridHook>,
    ) -> Result<(Mesh, f32), Error> {
        if !octree.holds(t) {
            return Err(Error::settings(format!("no tile {t:?} in the octree")));
        }
        let (lo, hi) = octree.tile_box(t);
        let dims = [CELLS + 1; 3];
        let (values, bound) = self.distance_grid_with(lo, hi, dims, iterations, tolerance, hook)?;
        let spacing = [octree.spacing(t.level); 3];
        let mesh = crate::codecs::ifs3d::isosurface::extract(&values, dims, 0.0, lo, spacing);
        // Simplified within SIMPLIFIED_CELLS, its border (on the box's faces) kept: the
        // neighbours still meet. A surface thinner than that may collapse whole (knot2's tube
        // at level 0): the tile keeps its marching then, since its subtree lists it as content.
        #[cfg(feature = "simplify")]
        let mesh = match mesh.simplified(SIMPLIFIED_CELLS * spacing[0]) {
            m if m.triangles.is_empty() => mesh,
            m => m,
        };
        Ok((mesh, bound))
    }

    /// The availability of the subtree rooted at `root` (a level that is a multiple of
    /// [`SUBTREE_LEVELS`]), from one lattice over the root's box at its deepest level's
    /// spacing: a tile has content where its samples straddle the surface (exactly where
    /// its mesh has triangles), and exists where its parent does and its samples come within
    /// half a cell's diagonal plus the field's error of the surface (or it has content).
    /// The root exists: its parent subtree said so.
    pub fn octree_subtree(
        &self,
        octree: &Octree,
        root: TileId,
        (iterations, tolerance): (u32, f32),
        hook: Option<&VolumeGridHook>,
    ) -> Result<(Subtree, f32), Error> {
        if !octree.holds(root) || !root.level.is_multiple_of(SUBTREE_LEVELS) {
            return Err(Error::settings(format!("no subtree at {root:?}")));
        }
        let depth = SUBTREE_LEVELS.min(octree.levels - root.level);
        // The lattice: the deepest level's spacing over the root's box.
        let n = CELLS << (depth - 1);
        let (lo, hi) = octree.tile_box(root);
        let dims = [n + 1; 3];
        let (values, bound) = self.distance_grid_with(lo, hi, dims, iterations, tolerance, hook)?;
        let spacing = octree.spacing(root.level + depth - 1);
        let near = 0.5 * 3f64.sqrt() * spacing + f64::from(bound) + octree.field_error;
        // Over the samples of the box of side `cells` lattice steps at `at` (in steps):
        // whether any is inside, any outside, and the least |distance|.
        let scan = |at: [usize; 3], cells: usize, stride: usize| {
            let (mut inside, mut outside, mut least) = (false, false, f64::INFINITY);
            for k in (at[2]..=at[2] + cells).step_by(stride) {
                for j in (at[1]..=at[1] + cells).step_by(stride) {
                    for i in (at[0]..=at[0] + cells).step_by(stride) {
                        let v = values[(k * (n + 1) + j) * (n + 1) + i];
                        // As the surface's extraction reads them: NaN is outside.
                        if v < 0.0 {
                            inside = true;
                        } else {
                            outside = true;
                        }
                        if v.is_finite() {
                            least = least.min(f64::from(v.abs()));
                        }
                    }
                }
            }
            (inside && outside, least)
        };
        let mut tiles = Vec::new();
        let mut content = Vec::new();
        for r in 0..depth {
            // Tiles at relative level r: 8^r of them, each `n >> r` steps a side, sampled
            // every `stride` steps (their own level's spacing).
            let (side, stride) = (n >> r, 1usize << (depth - 1 - r));
            for k in 0..1u64 << (3 * r) {
                let t = TileId::ROOT.descendant(r, k);
                let at = [t.x, t.y, t.z].map(|v| v as usize * side);
                let parent = match r {
                    0 => true,
                    _ => tiles[level_start(r - 1) + (k >> 3) as usize],
                };
                let (straddles, _) = scan(at, side, stride);
                let (_, least) = scan(at, side, 1);
                let has = parent && straddles;
                tiles.push(r == 0 || has || (parent && least <= near));
                content.push(has);
            }
        }
        // A subtree file holds every level of a subtree, those past the octree's last too.
        for r in depth..SUBTREE_LEVELS {
            tiles.resize(tiles.len() + (1 << (3 * r)), false);
            content.resize(content.len() + (1 << (3 * r)), false);
        }
        // Child subtrees: the tiles one level under the last, each half a deepest tile.
        let mut children = Vec::new();
        if root.level + depth < octree.levels {
            let side = CELLS / 2;
            for k in 0..1u64 << (3 * depth) {
                let t = TileId::ROOT.descendant(depth, k);
                let at = [t.x, t.y, t.z].map(|v| v as usize * side);
                let parent = tiles[level_start(depth - 1) + (k >> 3) as usize];
                let (straddles, least) = scan(at, side, 1);
                children.push(parent && (straddles || least <= near));
            }
        }
        Ok((
            Subtree {
                tiles,
                content,
                children,
            },
            bound,
        ))
    }
}

/// Index of the first tile of relative level `r` in a subtree's level-then-Morton order.
fn level_start(r: u32) -> usize {
    ((1usize << (3 * r)) - 1) / 7
}
