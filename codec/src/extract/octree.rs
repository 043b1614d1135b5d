//! A volume as OGC 3D Tiles 1.1 with implicit octree tiling: the cube of the volume's grid
//! halved level by level, each tile's content the surface inside its box sampled at
//! [`CELLS`] cells a side (so the resolution doubles with the level, past the encoded grid
//! by continuous decoding), subtrees that say which tiles exist and which hold a surface,
//! and the tileset that ties them (the server only routes them).
//!
//! Errors are world units (mesh units). A tile's `geometricError` bounds how far its surface
//! is from the surface of the encoded field: marching tetrahedra on samples `c` apart put
//! every vertex on an edge whose ends straddle the surface, within `c` of it, and each sample
//! is within the decode's bound plus the encode's largest error of the field; the tile states
//! `sqrt(3) c` plus those (a cell's diagonal: conservative). Implicit tiling halves the error
//! a level, so the root's is chosen for every level to hold: `sqrt(3) c_0 + 2^(L-1) e`.
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
        let (mut x, mut y, mut z) = (0u32, 0u32, 0u32);
        for bit in 0..depth {
            x |= ((k >> (3 * bit)) & 1) as u32 * (1 << bit);
            y |= ((k >> (3 * bit + 1)) & 1) as u32 * (1 << bit);
            z |= ((k >> (3 * bit + 2)) & 1) as u32 * (1 << bit);
        }
        TileId {
            level: self.level + depth,
            x: (self.x << depth) | x,
            y: (self.y << depth) | y,
            z: (self.z << depth) | z,
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
    /// field (world units).
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
    /// level's own `sqrt(3) c + bound + field_error` (see the module's note).
    pub fn root_error(&self, bound: f64) -> f64 {
        let e = bound + self.field_error;
        (0..self.levels)
            .map(|l| (3f64.sqrt() * self.spacing(l) + e) * f64::from(1u32 << l))
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

/// The glTF 2.0 binary of a tile's mesh, its positions and normals turned to glTF's y-up
/// (`(x, z, -y)`), which 3D Tiles turns back to z-up when it draws glTF content.
pub fn tile_glb(mesh: &Mesh) -> Vec<u8> {
    let up = |p: &[f32; 3]| [p[0], p[2], -p[1]];
    Mesh {
        positions: mesh.positions.iter().map(up).collect(),
        triangles: mesh.triangles.clone(),
        normals: mesh.normals.iter().map(up).collect(),
    }
    .to_glb()
}

impl Asset {
    /// The octree of a volume asset: its grid's cube, levels down to [`PAST_THE_GRID`] times
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
            field_error: self.meta.stats.max_error.max(0.0),
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
        if !octree.holds(root) || root.level % SUBTREE_LEVELS != 0 {
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
