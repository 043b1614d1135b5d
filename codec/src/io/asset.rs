//! The asset file: a versioned container of metadata and the coded operator(s).
//!
//! Layout (all integers little-endian; specified in docs/asset-format.md):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 8 | magic `FRACTILE` |
//! | 8 | 2 | format version (5; 1 to 4 are still read, 3 on only for curves) |
//! | 10 | 1 | kind (0 image, 1 height field, 2 volume, 3 curve) |
//! | 11 | 1 | codec (1 quadtree PIFS, 2 fractal interpolation surface, 3 piecewise self-affine, 4 octree PIFS of a volume, 5 projected IFS of curves) |
//! | 12 | 4 | metadata length M |
//! | 16 | M | metadata ([`AssetMeta`], proto's binary encoding) |
//! | 16+M | 4 | payload length P |
//! | 20+M | P | payload (codec-specific) |
//! | 20+M+P | 4 | source-error map length S (version 5 on; 0: none) |
//! | 24+M+P | S | source-error map ([`SourceError`]) |
//! | end-4 | 4 | CRC-32 (IEEE) of every byte before it |
//!
//! Reading checks all of it before any decoding: a truncated, corrupt or newer file is an
//! [`Error::asset`] naming what is wrong, never a panic.

use std::io::Write;
use std::path::Path;
use std::sync::Arc;

use fractile_proto::{AssetKind, AssetMeta};
use serde::{Deserialize, Serialize};

use super::layout::{ChunkSource, ChunkTable, FileSource, InMemory, MAGIC, is_chunked, kind_byte};
use crate::Error;
use crate::codecs::fis::{FisHeader, FisOperator};
use crate::codecs::projected::{ProjectedHeader, ProjectedOperator};
use crate::codecs::psa::{PsaHeader, PsaOperator};
use crate::codecs::quadtree::operator::{QuadtreeOperator, RangeMap};
use crate::codecs::quadtree::stream::{self, PlaneHeader};
use crate::core::decode;
use crate::core::entropy::{Bit, Decoder, Encoder};
use crate::core::fidelity::SourceError;
use crate::core::operator::{Operator, Step};

/// The format version this build writes. Versions 2 to 4 changed only the curve payload
/// (codec 5; version 3: hexagonal lattice for details, shared coarse contexts, an `f32`
/// tolerance and one stored bound, no length fields; version 4: a ring may carry its
/// antimeridian crossings and start vertex, which a version-3 reader would misread as levels);
/// the other payloads are the same in all four, so version-1 to -3 files of codecs 1-4 are
/// still read, version-3 curve assets too (they hold neither), and an older curve asset is
/// refused by name (re-encode its GeoJSON).
pub const FORMAT_VERSION: u16 = 5;
/// The oldest format version this build reads (codecs 1-4 only).
pub const OLDEST_READ_VERSION: u16 = 1;
/// The oldest format version of curve assets this build reads.
pub const OLDEST_CURVE_VERSION: u16 = 3;

/// What a reader lets one asset file cost before it allocates anything: sizes the file claims
/// are checked against these (and against what its bytes can hold) first, so that a small
/// hostile file cannot make a reader allocate gigabytes or decode for minutes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AssetLimits {
    /// Most samples of the source grid (width x height; voxels of a volume; vertices of curves).
    pub max_pixels: u64,
    /// Most bytes that decoding the asset may take: its operators and mask, resident while it
    /// is served, plus one full-resolution discrete decode (what `fractile decode` and a
    /// server's coarse tiles run), estimated from the headers before anything is decoded.
    pub max_decode_bytes: u64,
}

/// How an asset's operators are built when it is read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Build {
    /// Whole: everything an answer reads, made once (every asset but chunks).
    Whole,
    /// Lazily where the codec can (projected: [`ProjectedOperator::lazy`]): chunks of chunked
    /// assets, which a server keeps by the hundred.
    Lazy,
}

impl Default for AssetLimits {
    /// 2^28 samples (16384 x 16384) and 3 GiB: every asset of the demo and the benches, and a
    /// 16384^2 DEM, fit; anything larger is the chunked assets' job.
    fn default() -> Self {
        AssetLimits {
            max_pixels: 1 << 28,
            max_decode_bytes: 3 << 30,
        }
    }
}

impl AssetLimits {
    /// Checks the grid a file claims.
    pub(crate) fn check_pixels(&self, what: &str, pixels: u64) -> Result<(), Error> {
        if pixels > self.max_pixels {
            return Err(Error::asset(format!(
                "{what} of {pixels} samples is over this reader's limit of {} (max_asset_pixels)",
                self.max_pixels
            )));
        }
        Ok(())
    }

    /// Checks the estimated cost of decoding.
    fn check_cost(&self, bytes: u64) -> Result<(), Error> {
        if bytes > self.max_decode_bytes {
            return Err(Error::asset(format!(
                "decoding it would take about {} MiB, over this reader's limit of {} MiB (max_decode_mib)",
                bytes >> 20,
                self.max_decode_bytes >> 20
            )));
        }
        Ok(())
    }
}

/// Checks that a plane's coded extent is the metadata's grid (chroma: half of it; a
/// supersampled plane: twice): a file may not claim a grid its planes do not code.
fn check_extent(meta: &AssetMeta, valid: [f32; 2]) -> Result<(), String> {
    let (w, h) = (meta.width as f32, meta.height as f32);
    let fits = [0.5f32, 1.0, 2.0]
        .iter()
        .any(|&k| (valid[0] - k * w).abs() <= 0.5 * k && (valid[1] - k * h).abs() <= 0.5 * k);
    if fits {
        Ok(())
    } else {
        Err(format!(
            "the plane codes an extent of {}x{} where the metadata says {}x{}",
            valid[0], valid[1], meta.width, meta.height
        ))
    }
}

/// Validates the header of every plane of a lattice codec and counts their nodes (before any
/// node grid is allocated).
fn lattice_nodes<H>(
    planes: &[(H, Vec<u8>)],
    validate: impl Fn(&H) -> Result<(), String>,
    nodes: impl Fn(&H) -> [usize; 2],
) -> Result<u64, Error> {
    let mut total = 0u64;
    for (i, (header, _)) in planes.iter().enumerate() {
        validate(header).map_err(|e| Error::asset(format!("plane {i}: {e}")))?;
        total += nodes(header).iter().map(|&n| n as u64).product::<u64>();
    }
    Ok(total)
}

/// Codec identifiers of the payload.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Codec {
    /// Quadtree partitioned IFS, 2D (images and height fields).
    QuadtreePifs = 1,
    /// Fractal interpolation surfaces (height fields), any layout of the vertical scaling.
    Fis = 2,
    /// Piecewise self-affine model on a rectangular lattice (psa2d), grey images and heights.
    Psa = 3,
    /// Octree partitioned IFS of a signed distance volume (IFS3D).
    Octree = 4,
    /// Projected IFS with details of a set of curves.
    Curve = 5,
    /// Projected IFS with details on a grid (height fields, grey images).
    Projected = 6,
}

impl Codec {
    /// The codec of a codec byte.
    pub fn from_byte(b: u8) -> Option<Codec> {
        Some(match b {
            1 => Codec::QuadtreePifs,
            2 => Codec::Fis,
            3 => Codec::Psa,
            4 => Codec::Octree,
            5 => Codec::Curve,
            6 => Codec::Projected,
            _ => return None,
        })
    }
}

/// How a plane is coded: the header a reader needs and the entropy-coded stream.
#[derive(Clone, Debug)]
pub enum Coding {
    /// Quadtree PIFS: partition and maps.
    Quadtree {
        /// Frame, sizes, quantiser.
        header: PlaneHeader,
        /// The transform stream.
        stream: Vec<u8>,
    },
    /// Fractal interpolation surface: node heights and vertical scalings.
    Fis {
        /// Node grid, layout of s, quantisers.
        header: FisHeader,
        /// The parameter stream.
        stream: Vec<u8>,
    },
    /// Piecewise self-affine model: vertex heights and region codes.
    Psa {
        /// Lattice, tiling, domains, quantisers.
        header: PsaHeader,
        /// The parameter stream.
        stream: Vec<u8>,
    },
    /// Projected IFS with details: control grid, fitted masks and details.
    Projected {
        /// Grid, levels, quantiser, roughness.
        header: ProjectedHeader,
        /// The detail stream.
        stream: Vec<u8>,
    },
}

/// The decoding operator of a plane, whichever codec made it. Decoders see only
/// [`Operator`]; the match costs one predictable branch a step.
#[derive(Clone, Debug)]
pub enum PlaneOperator {
    /// A quadtree PIFS.
    Quadtree(QuadtreeOperator),
    /// A fractal interpolation surface.
    Fis(FisOperator),
    /// A piecewise self-affine surface.
    Psa(PsaOperator),
    /// A projected IFS with details, continued past its finest level.
    Projected(ProjectedOperator),
}

/// Whether a file's first bytes (8 or more) are an asset's, before the rest is read: the
/// error says what the file is instead (see [`Asset::from_bytes`]).
pub fn check_magic(head: &[u8]) -> Result<(), Error> {
    if head.len() >= 8 && &head[..8] == MAGIC {
        Ok(())
    } else {
        Err(Error::asset(not_an_asset(head)))
    }
}

/// What a file that does not start with an asset's magic is, and what to do with it: rasters
/// and meshes are the encoder's input, and uploading one is a common first mistake.
fn not_an_asset(bytes: &[u8]) -> String {
    let kind = if bytes.starts_with(b"II*\0") || bytes.starts_with(b"MM\0*") {
        Some("a TIFF (GeoTIFF) raster")
    } else if bytes.starts_with(b"\x89PNG") {
        Some("a PNG image")
    } else if bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
        Some("a JPEG image")
    } else if bytes.starts_with(b"OFF") || bytes.starts_with(b"ply") || bytes.starts_with(b"solid")
    {
        Some("a mesh")
    } else {
        None
    };
    match kind {
        Some(k) => format!(
            "not a fractile asset (bad magic): this is {k}; encode it with `fractile encode` first"
        ),
        None => "not a fractile asset (bad magic): assets are what `fractile encode` writes".into(),
    }
}

impl PlaneOperator {
    /// The quadtree's ranges (empty for other codecs).
    pub fn ranges(&self) -> &[RangeMap] {
        match self {
            PlaneOperator::Quadtree(q) => q.ranges(),
            PlaneOperator::Fis(_) | PlaneOperator::Psa(_) | PlaneOperator::Projected(_) => &[],
        }
    }

    /// [`decode::points`] with the codec resolved once per batch rather than once per inverse
    /// step: through the enum, `step` is a match that the compiler does not inline into the
    /// chain loop (measured: 37% of an uncached tile's time in the out-of-line `step`).
    pub fn points(
        &self,
        pts: &[[f32; 2]],
        iterations: u32,
        tolerance: f32,
    ) -> Vec<decode::PointValue> {
        match self {
            PlaneOperator::Quadtree(q) => decode::points(q, pts, iterations, tolerance),
            PlaneOperator::Fis(f) => decode::points(f, pts, iterations, tolerance),
            PlaneOperator::Psa(f) => decode::points(f, pts, iterations, tolerance),
            PlaneOperator::Projected(f) => f.points(pts, iterations, tolerance),
        }
    }

    /// Continuous decoding of the separable grid `(xs[i], ys[j])`, row-major: [`decode::grid`]
    /// for the quadtree and [`ProjectedOperator::grid`] for the projected continuation (whose
    /// blocks of points step together), [`Self::points`] on the listed points for codecs whose
    /// cells are not axis-aligned boxes. Same answers either way.
    pub fn grid(
        &self,
        xs: &[f32],
        ys: &[f32],
        iterations: u32,
        tolerance: f32,
    ) -> Vec<decode::PointValue> {
        match self {
            PlaneOperator::Quadtree(q) => decode::grid(q, xs, ys, iterations, tolerance),
            PlaneOperator::Projected(p) => p.grid(xs, ys, iterations, tolerance),
            _ => {
                let pts: Vec<[f32; 2]> = ys
                    .iter()
                    .flat_map(|&y| xs.iter().map(move |&x| [x, y]))
                    .collect();
                self.points(&pts, iterations, tolerance)
            }
        }
    }

    /// The steps [`Self::grid`] takes at every point of the separable grid `(xs[i], ys[j])`
    /// where it takes the same everywhere (the projected continuation's subdivision: see
    /// `ProjectedOperator::grid_steps`); `None` where each chain takes its own. A device asked
    /// for the grid is asked for that many steps exactly, so that it answers as the CPU does.
    pub fn grid_steps(
        &self,
        xs: &[f32],
        ys: &[f32],
        iterations: u32,
        tolerance: f32,
    ) -> Option<u32> {
        match self {
            PlaneOperator::Projected(p) => p.grid_steps(xs, ys, iterations, tolerance),
            _ => None,
        }
    }

    /// Continuous decoding of a bilinear [`decode::Patch`] of points, row-major:
    /// [`decode::patch`] for the quadtree (whose blocks step together), [`Self::points`] on the
    /// patch's points otherwise.
    pub fn patch(
        &self,
        patch: &decode::Patch,
        iterations: u32,
        tolerance: f32,
    ) -> Vec<decode::PointValue> {
        match self {
            PlaneOperator::Quadtree(q) => decode::patch(q, patch, iterations, tolerance),
            _ => {
                let pts: Vec<[f32; 2]> = (0..patch.height)
                    .flat_map(|j| (0..patch.width).map(move |i| patch.at(i, j).map(|t| t as f32)))
                    .collect();
                self.points(&pts, iterations, tolerance)
            }
        }
    }

    /// [`decode::point`] with the codec resolved once (see [`Self::points`]).
    pub fn point(&self, p: [f32; 2], iterations: u32) -> decode::PointValue {
        match self {
            PlaneOperator::Quadtree(q) => decode::point(q, p, iterations),
            PlaneOperator::Fis(f) => decode::point(f, p, iterations),
            PlaneOperator::Psa(f) => decode::point(f, p, iterations),
            // Through its own chains, which end on the bilinear interpolant (see
            // `ProjectedOperator::run_chains`), so that one point and a batch agree.
            PlaneOperator::Projected(f) => f.points(&[p], iterations, 0.0)[0],
        }
    }

    /// The attractor's values at the source's own sample centres where the codec knows them
    /// without iterating (the projected codec's decoded samples, which its continuation passes
    /// through), normalised and row-major.
    pub fn samples(&self) -> Option<&[f32]> {
        match self {
            PlaneOperator::Projected(f) => Some(f.samples()),
            _ => None,
        }
    }

    /// Keeps continuous answers `values` (normalised) at unit points `pts` in the neighbourhood
    /// of the data, for codecs whose continuation could leave it (the projected codec: see
    /// `codecs::projected::neighbourhood`); the others' answers are left as they are.
    /// Applied to every continuous answer, the CPU's and a device's alike.
    pub fn limit_points(&self, pts: &[[f32; 2]], values: &mut [f32]) {
        if let PlaneOperator::Projected(f) = self {
            f.limit_points(pts, values);
        }
    }

    /// [`Self::limit_points`] on the separable grid `(xs[i], ys[j])`, row-major.
    pub fn limit_grid(&self, xs: &[f32], ys: &[f32], values: &mut [f32]) {
        if let PlaneOperator::Projected(f) = self {
            f.limit_grid(xs, ys, values);
        }
    }

    /// Largest |s| anywhere.
    pub fn max_contrast(&self) -> f32 {
        match self {
            PlaneOperator::Quadtree(q) => q
                .ranges()
                .iter()
                .fold(0.0f32, |m, r| m.max(r.contrast.abs())),
            PlaneOperator::Fis(f) => f.max_scaling(),
            PlaneOperator::Psa(f) => f.max_scaling(),
            PlaneOperator::Projected(f) => f.roughness(),
        }
    }

    /// Maps of the operator: ranges, or cells of the node grid.
    pub fn transforms(&self) -> usize {
        match self {
            PlaneOperator::Quadtree(q) => q.ranges().len(),
            PlaneOperator::Fis(f) => f.cells(),
            PlaneOperator::Psa(f) => f.regions(),
            PlaneOperator::Projected(f) => f.cells(),
        }
    }
}

impl crate::core::pieces::Flatten for PlaneOperator {
    fn pieces(&self) -> crate::core::pieces::PieceTable {
        match self {
            PlaneOperator::Quadtree(q) => q.pieces(),
            PlaneOperator::Fis(f) => f.pieces(),
            PlaneOperator::Psa(f) => f.pieces(),
            PlaneOperator::Projected(f) => f.pieces(),
        }
    }

    fn flat(&self) -> crate::core::pieces::Flat {
        match self {
            PlaneOperator::Quadtree(q) => q.flat(),
            PlaneOperator::Fis(f) => f.flat(),
            PlaneOperator::Psa(f) => f.flat(),
            PlaneOperator::Projected(f) => f.flat(),
        }
    }
}

impl Operator<2> for PlaneOperator {
    fn frame(&self) -> [f32; 2] {
        match self {
            PlaneOperator::Quadtree(q) => q.frame(),
            PlaneOperator::Fis(f) => f.frame(),
            PlaneOperator::Psa(f) => f.frame(),
            PlaneOperator::Projected(f) => f.frame(),
        }
    }
    fn valid(&self) -> [f32; 2] {
        match self {
            PlaneOperator::Quadtree(q) => q.valid(),
            PlaneOperator::Fis(f) => f.valid(),
            PlaneOperator::Psa(f) => f.valid(),
            PlaneOperator::Projected(f) => f.valid(),
        }
    }
    fn expansion(&self) -> u32 {
        match self {
            PlaneOperator::Quadtree(q) => q.expansion(),
            PlaneOperator::Fis(f) => f.expansion(),
            PlaneOperator::Psa(f) => f.expansion(),
            PlaneOperator::Projected(f) => f.expansion(),
        }
    }
    #[inline]
    fn step(&self, p: [f32; 2]) -> Step<2> {
        match self {
            PlaneOperator::Quadtree(q) => q.step(p),
            PlaneOperator::Fis(f) => f.step(p),
            PlaneOperator::Psa(f) => f.step(p),
            PlaneOperator::Projected(f) => f.step(p),
        }
    }
    fn invariant_interval(&self) -> (f32, f32) {
        match self {
            PlaneOperator::Quadtree(q) => q.invariant_interval(),
            PlaneOperator::Fis(f) => f.invariant_interval(),
            PlaneOperator::Psa(f) => f.invariant_interval(),
            PlaneOperator::Projected(f) => f.invariant_interval(),
        }
    }
    fn run_chains(
        &self,
        chains: &mut [crate::core::operator::Chain<2>],
        iterations: u32,
        tolerance: f32,
    ) {
        match self {
            PlaneOperator::Quadtree(q) => q.run_chains(chains, iterations, tolerance),
            PlaneOperator::Fis(f) => f.run_chains(chains, iterations, tolerance),
            PlaneOperator::Psa(f) => f.run_chains(chains, iterations, tolerance),
            PlaneOperator::Projected(f) => f.run_chains(chains, iterations, tolerance),
        }
    }
}

/// A coded plane: how it is coded and the operator decoded from that.
#[derive(Clone, Debug)]
pub struct Plane {
    /// Header and stream, as stored.
    pub coding: Coding,
    /// The decoding operator.
    pub operator: PlaneOperator,
}

impl Plane {
    /// The largest |decoded sample - source| the encoder promised at every valid sample centre
    /// (source units), for codecs that promise one (projected under `--max-error`).
    pub fn promise(&self) -> Option<f32> {
        match &self.coding {
            Coding::Projected { header, .. } => header.promise().map(|e| e as f32),
            _ => None,
        }
    }

    /// The quadtree header, for quadtree planes.
    pub fn header(&self) -> Option<&PlaneHeader> {
        match &self.coding {
            Coding::Quadtree { header, .. } => Some(header),
            Coding::Fis { .. } | Coding::Psa { .. } | Coding::Projected { .. } => None,
        }
    }
}

/// Which source cells held data (height fields with nodata).
#[derive(Clone, Debug, PartialEq)]
pub struct Mask {
    width: usize,
    height: usize,
    valid: Vec<bool>,
    /// Summed-area table over blocks of `BLOCK x BLOCK` cells of "holds a nodata cell", so
    /// that a tile whose footprint has none skips the per-pixel lookups in O(1) (they were a
    /// tenth of a reprojected tile's time); 4 bytes per block.
    gaps: Vec<u32>,
}

/// Side of a block of [`Mask`]'s summary, in cells.
const BLOCK: usize = 16;

impl Mask {
    /// The mask of a `width x height` grid from its row-major validity.
    pub fn new(width: usize, height: usize, valid: Vec<bool>) -> Mask {
        assert_eq!(valid.len(), width * height, "a validity per cell");
        let (bw, bh) = (width.div_ceil(BLOCK), height.div_ceil(BLOCK));
        let mut gap = vec![0u32; bw * bh];
        for (i, &ok) in valid.iter().enumerate() {
            if !ok {
                gap[(i / width / BLOCK) * bw + (i % width) / BLOCK] = 1;
            }
        }
        let mut gaps = vec![0u32; (bw + 1) * (bh + 1)];
        for by in 0..bh {
            for bx in 0..bw {
                gaps[(by + 1) * (bw + 1) + bx + 1] = gap[by * bw + bx]
                    + gaps[by * (bw + 1) + bx + 1]
                    + gaps[(by + 1) * (bw + 1) + bx]
                    - gaps[by * (bw + 1) + bx];
            }
        }
        Mask {
            width,
            height,
            valid,
            gaps,
        }
    }

    /// Width of the source grid.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height of the source grid.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Row-major validity of the source cells.
    pub fn valid(&self) -> &[bool] {
        &self.valid
    }

    /// The source cell (column, row) under unit point (u, v): monotonic in each coordinate.
    fn cell(&self, u: f32, v: f32) -> (usize, usize) {
        (
            ((u * self.width as f32) as usize).min(self.width - 1),
            ((v * self.height as f32) as usize).min(self.height - 1),
        )
    }

    /// Validity of the source cell under unit point (u, v).
    pub fn at(&self, u: f32, v: f32) -> bool {
        let (x, y) = self.cell(u, v);
        self.valid[y * self.width + x]
    }

    /// Whether every point of the unit box `[u0, u1] x [v0, v1]` is known valid (`at` is true
    /// there: a point maps to a cell between those of the box's corners). Conservative: true
    /// when no nodata cell lies in the blocks of `BLOCK x BLOCK` cells under the box.
    pub fn all_valid(&self, [u0, v0, u1, v1]: [f32; 4]) -> bool {
        let ((x0, y0), (x1, y1)) = (self.cell(u0, v0), self.cell(u1, v1));
        let (bx0, by0, bx1, by1) = (x0 / BLOCK, y0 / BLOCK, x1 / BLOCK + 1, y1 / BLOCK + 1);
        if bx1 <= bx0 || by1 <= by0 {
            return false; // a box given backwards: no claim
        }
        let row = self.width.div_ceil(BLOCK) + 1;
        let at = |bx: usize, by: usize| self.gaps[by * row + bx];
        at(bx1, by1) + at(bx0, by0) == at(bx0, by1) + at(bx1, by0)
    }

    fn encode(&self) -> Vec<u8> {
        // Context: the left and upper neighbours; runs of nodata cost almost nothing.
        let mut enc = Encoder::new();
        let mut ctx = [Bit::default(); 4];
        for y in 0..self.height {
            for x in 0..self.width {
                let c = context(&self.valid, self.width, x, y);
                enc.bit(&mut ctx[c], self.valid[y * self.width + x]);
            }
        }
        enc.finish()
    }

    fn decode(width: usize, height: usize, bytes: &[u8]) -> Result<Mask, Error> {
        // A decision per cell: a mask larger than its stream can hold is refused unallocated.
        if (width as u64) * (height as u64) > crate::core::entropy::most_decisions(bytes.len()) {
            return Err(Error::asset(format!(
                "a nodata mask of {width}x{height} needs more than its {} bytes",
                bytes.len()
            )));
        }
        let mut valid = vec![false; width * height];
        let mut dec = Decoder::new(bytes);
        let mut ctx = [Bit::default(); 4];
        for y in 0..height {
            for x in 0..width {
                let c = context(&valid, width, x, y);
                valid[y * width + x] = dec.bit(&mut ctx[c]);
            }
            if dec.overrun() {
                break;
            }
        }
        if dec.overrun() {
            return Err(Error::asset("the nodata mask is truncated"));
        }
        Ok(Mask::new(width, height, valid))
    }
}

/// The coding context of cell (x, y): validity of its left and upper neighbours.
fn context(valid: &[bool], width: usize, x: usize, y: usize) -> usize {
    let left = x > 0 && valid[y * width + x - 1];
    let up = y > 0 && valid[(y - 1) * width + x];
    usize::from(left) | usize::from(up) << 1
}

#[derive(Serialize, Deserialize)]
struct Payload {
    planes: Vec<(PlaneHeader, Vec<u8>)>,
    mask: Option<Vec<u8>>,
}

#[derive(Serialize, Deserialize)]
struct PsaPayload {
    planes: Vec<(PsaHeader, Vec<u8>)>,
    mask: Option<Vec<u8>>,
}

#[derive(Serialize, Deserialize)]
struct ProjectedPayload {
    planes: Vec<(ProjectedHeader, Vec<u8>)>,
    mask: Option<Vec<u8>>,
}

#[derive(Serialize, Deserialize)]
struct VolumePayload {
    header: crate::codecs::ifs3d::octree::OctreeHeader,
    stream: Vec<u8>,
    placement: crate::codecs::ifs3d::volume::Placement,
}

#[derive(Serialize, Deserialize)]
struct FisPayload {
    planes: Vec<(FisHeader, Vec<u8>)>,
    mask: Option<Vec<u8>>,
}

/// A decoded asset file: metadata, planes with their operators, and the nodata mask.
#[derive(Clone, Debug)]
pub struct Asset {
    /// What the asset is.
    pub meta: AssetMeta,
    /// One plane per coded channel (Y, Cb, Cr for colour).
    pub planes: Vec<Plane>,
    /// Source validity, for height fields with nodata.
    pub mask: Option<Mask>,
    /// The coded volume, for volume assets (which have no planes).
    pub volume: Option<crate::codecs::ifs3d::volume::Volume>,
    /// The coded curves, for curve assets (which have no planes).
    pub curve: Option<crate::codecs::curve::Curves>,
    /// Each block's measured error against the source (format version 5 on; `None` in older
    /// files and for volumes and curves): what answers' `error_bound` adds to convergence.
    pub source_error: Option<SourceError>,
    /// The chunks of a chunked asset (format version 6), read and decoded on demand; such an
    /// asset has no planes of its own, and its answers are its chunks' (`extract::chunked`).
    pub chunks: Option<Arc<Chunked>>,
}

// The chunked container's own state and the cache of its decoded chunks are declared here,
// beside the asset that holds them and that they hold (an asset's chunks are assets); their
// behaviour is in `chunked`.
/// Decoded chunks of every chunked asset of a process, bounded in bytes (their estimated
/// resident size: operators and masks), least recently used out first. moka's cache also makes
/// concurrent requests for one chunk decode it once.
#[derive(Clone)]
pub struct ChunkCache {
    pub(crate) cache: moka::sync::Cache<(u64, u8, u32), Arc<Asset>>,
    /// Chunks being decoded now, and the most at once.
    pub(crate) decoding: Arc<(std::sync::Mutex<usize>, std::sync::Condvar)>,
    pub(crate) most_decoding: usize,
}

/// A chunked container opened for reading: its table, its bytes by range, and the cache its
/// decoded chunks go to.
pub struct Chunked {
    /// The chunk table.
    pub table: ChunkTable,
    pub(crate) source: Box<dyn ChunkSource>,
    pub(crate) limits: AssetLimits,
    pub(crate) cache: ChunkCache,
    /// This container's key in the shared cache.
    pub(crate) key: u64,
    /// CRC-32 of the header (magic to table): names this version of the asset.
    pub header_crc: u32,
    /// Chunks found corrupt, and why: a corrupt chunk stays corrupt, so it is decoded once and
    /// its error answered again after (the cache keeps only what loaded).
    pub(crate) corrupt: std::sync::Mutex<std::collections::HashMap<(usize, usize), Error>>,
}

impl Asset {
    /// Builds an asset from coded planes, decoding each stream (so that what is served is exactly
    /// what a reader of the file gets).
    pub fn from_parts(
        meta: AssetMeta,
        planes: Vec<(PlaneHeader, Vec<u8>)>,
        mask: Option<Mask>,
    ) -> Result<Asset, Error> {
        Asset::assemble(meta, planes, mask, |_, header, stream| {
            let leaves = stream::decode_plane(&header, &stream)?;
            let operator = stream::operator(&header, &leaves)?;
            Ok(Plane {
                coding: Coding::Quadtree { header, stream },
                operator: PlaneOperator::Quadtree(operator),
            })
        })
    }

    /// Size in bytes of the file [`Asset::from_parts`] would build from the same parts, without
    /// decoding the streams or building operators: rate control asks it of every trial
    /// partition and builds the asset once, for the one it keeps.
    pub fn quadtree_file_size(
        meta: &AssetMeta,
        planes: Vec<(PlaneHeader, Vec<u8>)>,
        mask: Option<&Mask>,
    ) -> usize {
        let payload = fractile_proto::encode(&Payload {
            planes,
            mask: mask.map(Mask::encode),
        });
        assemble(meta, Codec::QuadtreePifs, &payload, &[]).len()
    }

    /// Builds an asset of fractal interpolation surfaces from coded planes (height fields).
    pub fn from_fis_parts(
        meta: AssetMeta,
        planes: Vec<(FisHeader, Vec<u8>)>,
        mask: Option<Mask>,
    ) -> Result<Asset, Error> {
        if meta.kind != AssetKind::HeightField {
            return Err(Error::asset(
                "fractal interpolation surfaces code height fields only",
            ));
        }
        Asset::assemble(meta, planes, mask, |meta, header, stream| {
            if header.samples != [meta.width, meta.height] {
                return Err("sample grid and metadata disagree".into());
            }
            let params = crate::codecs::fis::decode_params(&header, &stream)?;
            let operator = FisOperator::new(&header, &params)?;
            Ok(Plane {
                coding: Coding::Fis { header, stream },
                operator: PlaneOperator::Fis(operator),
            })
        })
    }

    /// Builds a piecewise self-affine asset from coded planes (one grey plane).
    pub fn from_psa_parts(
        meta: AssetMeta,
        planes: Vec<(PsaHeader, Vec<u8>)>,
        mask: Option<Mask>,
    ) -> Result<Asset, Error> {
        Asset::assemble(meta, planes, mask, |meta, header, stream| {
            if header.samples != [meta.width, meta.height] {
                return Err("sample grid and metadata disagree".into());
            }
            let params = crate::codecs::psa::decode_params(&header, &stream)?;
            let operator = PsaOperator::new(&header, &params)?;
            Ok(Plane {
                coding: Coding::Psa { header, stream },
                operator: PlaneOperator::Psa(operator),
            })
        })
    }

    /// Builds a projected asset from coded planes (one grey plane), decoding each stream.
    pub fn from_projected_parts(
        meta: AssetMeta,
        planes: Vec<(ProjectedHeader, Vec<u8>)>,
        mask: Option<Mask>,
    ) -> Result<Asset, Error> {
        Asset::from_projected_built(meta, planes, mask, Build::Whole)
    }

    /// [`Asset::from_projected_parts`], the operators built as `build` says.
    fn from_projected_built(
        meta: AssetMeta,
        planes: Vec<(ProjectedHeader, Vec<u8>)>,
        mask: Option<Mask>,
        build: Build,
    ) -> Result<Asset, Error> {
        Asset::assemble(meta, planes, mask, |meta, header, stream| {
            let (w, h) = (meta.width, meta.height);
            // Chroma of a colour asset is coded at half resolution (as the quadtree's).
            let chroma = meta.colour == fractile_proto::ColourModel::YCbCr
                && header.samples == [w.div_ceil(2), h.div_ceil(2)];
            if header.samples != [w, h] && !chroma {
                return Err("sample grid and metadata disagree".into());
            }
            let grid = crate::codecs::projected::decode_grid(&header, &stream)?;
            let mut operator = match build {
                Build::Whole => ProjectedOperator::new(&header, &grid)?,
                Build::Lazy => ProjectedOperator::lazy(&header, grid)?,
            };
            if chroma && header.samples != [w, h] {
                operator = operator.with_valid([w as f32 / 2.0, h as f32 / 2.0]);
            }
            Ok(Plane {
                coding: Coding::Projected { header, stream },
                operator: PlaneOperator::Projected(operator),
            })
        })
    }

    /// Decodes every coded plane with `plane` (errors name the plane) and checks the whole.
    fn assemble<H>(
        meta: AssetMeta,
        planes: Vec<(H, Vec<u8>)>,
        mask: Option<Mask>,
        plane: impl Fn(&AssetMeta, H, Vec<u8>) -> Result<Plane, String>,
    ) -> Result<Asset, Error> {
        let planes = planes
            .into_iter()
            .enumerate()
            .map(|(i, (header, stream))| {
                plane(&meta, header, stream).map_err(|e| Error::asset(format!("plane {i}: {e}")))
            })
            .collect::<Result<Vec<_>, Error>>()?;
        let asset = Asset {
            meta,
            planes,
            mask,
            volume: None,
            curve: None,
            source_error: None,
            chunks: None,
        };
        asset.check()?;
        Ok(asset)
    }

    /// Builds a volume asset from its coded stream (decoding it, as a reader would).
    pub fn from_volume_parts(
        meta: AssetMeta,
        header: crate::codecs::ifs3d::octree::OctreeHeader,
        stream: Vec<u8>,
        placement: crate::codecs::ifs3d::volume::Placement,
    ) -> Result<Asset, Error> {
        let bad = |m: String| Error::asset(format!("volume: {m}"));
        if meta.kind != AssetKind::Volume || meta.channels != 1 || meta.width != meta.height {
            return Err(bad(
                "metadata is not that of a cubic one-channel volume".into()
            ));
        }
        if header.valid != meta.width as f32 {
            return Err(bad("grid size and metadata disagree".into()));
        }
        placement.validate().map_err(bad)?;
        let leaves = crate::codecs::ifs3d::octree::decode_stream(&header, &stream).map_err(bad)?;
        let operator =
            crate::codecs::ifs3d::octree::OctreeOperator::new(&header, leaves).map_err(bad)?;
        let asset = Asset {
            meta,
            planes: Vec::new(),
            mask: None,
            volume: Some(crate::codecs::ifs3d::volume::Volume {
                header,
                stream,
                operator,
                placement,
            }),
            curve: None,
            source_error: None,
            chunks: None,
        };
        asset.check()?;
        Ok(asset)
    }

    /// Builds a curve asset from its coded stream (decoding it, as a reader would).
    pub fn from_curve_parts(
        meta: AssetMeta,
        header: crate::codecs::curve::code::CurveHeader,
        stream: Vec<u8>,
    ) -> Result<Asset, Error> {
        let bad = |m: String| Error::asset(format!("curve: {m}"));
        if meta.kind != AssetKind::Curve {
            return Err(bad("metadata is not that of a curve asset".into()));
        }
        let set = crate::codecs::curve::code::decode(&header, &stream).map_err(bad)?;
        let asset = Asset {
            meta,
            planes: Vec::new(),
            mask: None,
            volume: None,
            curve: Some(crate::codecs::curve::Curves {
                header,
                stream,
                set,
            }),
            source_error: None,
            chunks: None,
        };
        asset.check()?;
        Ok(asset)
    }

    /// The codec of the planes.
    pub fn codec(&self) -> Codec {
        if let Some(c) = &self.chunks {
            return Codec::from_byte(c.table.codec).unwrap_or(Codec::QuadtreePifs);
        }
        if self.curve.is_some() {
            return Codec::Curve;
        }
        if self.volume.is_some() {
            return Codec::Octree;
        }
        match self.planes.first().map(|p| &p.coding) {
            Some(Coding::Fis { .. }) => Codec::Fis,
            Some(Coding::Psa { .. }) => Codec::Psa,
            Some(Coding::Projected { .. }) => Codec::Projected,
            _ => Codec::QuadtreePifs,
        }
    }

    /// The codec's name as the CLI and the API spell it.
    pub fn codec_name(&self) -> &'static str {
        if let Some(c) = &self.chunks {
            // The chunks' codec: by its byte, or (a FIS or psa2d name needs a chunk's header)
            // from the first chunk with data.
            match Codec::from_byte(c.table.codec) {
                Some(Codec::QuadtreePifs) => return "quadtree-pifs",
                Some(Codec::Projected) => return crate::codecs::projected::CODEC_NAME,
                _ => {}
            }
            let first = c.table.levels[0].chunks.iter().position(|e| e.length > 0);
            return match first.map(|i| c.chunk(0, i)) {
                Some(Ok(Some(a))) => a.codec_name(),
                _ => "chunked",
            };
        }
        if self.curve.is_some() {
            return "curve-pifs";
        }
        if self.volume.is_some() {
            return "ifs3d-octree";
        }
        match self.planes.first().map(|p| &p.coding) {
            Some(Coding::Fis { header, .. }) => crate::codecs::fis::codec_name(header.scaling),
            Some(Coding::Psa { header, .. }) => crate::codecs::psa::codec_name(header.tiling),
            Some(Coding::Projected { .. }) => crate::codecs::projected::CODEC_NAME,
            _ => "quadtree-pifs",
        }
    }

    fn check(&self) -> Result<(), Error> {
        let m = &self.meta;
        if (m.kind == AssetKind::Volume) != self.volume.is_some() {
            return Err(Error::asset(
                "a volume asset must hold a volume, and only it",
            ));
        }
        if (m.kind == AssetKind::Curve) != self.curve.is_some() {
            return Err(Error::asset("a curve asset must hold curves, and only it"));
        }
        let expected = match m.colour {
            _ if self.volume.is_some() || self.curve.is_some() => 0,
            fractile_proto::ColourModel::Grey => 1,
            fractile_proto::ColourModel::YCbCr => 3,
        };
        if self.planes.len() != expected
            || (expected > 0 && m.channels as usize != expected)
            || (self.curve.is_some() && m.channels != 2)
        {
            return Err(Error::asset(format!(
                "{} planes and {} channels for colour model {:?}",
                self.planes.len(),
                m.channels,
                m.colour
            )));
        }
        if m.width == 0
            || m.height == 0
            || m.value_max < m.value_min
            || !m.value_min.is_finite()
            || !m.value_max.is_finite()
        {
            return Err(Error::asset("bad size or value range in the metadata"));
        }
        Ok(())
    }

    /// The file's bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        if let Some(c) = &self.chunks {
            // Empty if its source cannot be read: `write` says why instead.
            return c.bytes().unwrap_or_default();
        }
        let mask = self.mask.as_ref().map(Mask::encode);
        let payload = match self.codec() {
            Codec::QuadtreePifs => fractile_proto::encode(&Payload {
                planes: self
                    .planes
                    .iter()
                    .filter_map(|p| match &p.coding {
                        Coding::Quadtree { header, stream } => {
                            Some((header.clone(), stream.clone()))
                        }
                        _ => None,
                    })
                    .collect(),
                mask,
            }),
            Codec::Fis => fractile_proto::encode(&FisPayload {
                planes: self
                    .planes
                    .iter()
                    .filter_map(|p| match &p.coding {
                        Coding::Fis { header, stream } => Some((header.clone(), stream.clone())),
                        _ => None,
                    })
                    .collect(),
                mask,
            }),
            Codec::Octree => {
                let v = self
                    .volume
                    .as_ref()
                    .expect("an octree asset holds a volume");
                fractile_proto::encode(&VolumePayload {
                    header: v.header.clone(),
                    stream: v.stream.clone(),
                    placement: v.placement.clone(),
                })
            }
            Codec::Curve => self
                .curve
                .as_ref()
                .expect("a curve asset holds curves")
                .payload(),
            Codec::Psa => fractile_proto::encode(&PsaPayload {
                planes: self
                    .planes
                    .iter()
                    .filter_map(|p| match &p.coding {
                        Coding::Psa { header, stream } => Some((header.clone(), stream.clone())),
                        _ => None,
                    })
                    .collect(),
                mask,
            }),
            Codec::Projected => fractile_proto::encode(&ProjectedPayload {
                planes: self
                    .planes
                    .iter()
                    .filter_map(|p| match &p.coding {
                        Coding::Projected { header, stream } => {
                            Some((header.clone(), stream.clone()))
                        }
                        _ => None,
                    })
                    .collect(),
                mask,
            }),
        };
        let section = self
            .source_error
            .as_ref()
            .map(SourceError::encode)
            .unwrap_or_default();
        assemble(&self.meta, self.codec(), &payload, &section)
    }

    /// Size of the file in bytes.
    pub fn file_size(&self) -> usize {
        self.to_bytes().len()
    }

    /// Parses and checks a file's bytes under the default [`AssetLimits`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Asset, Error> {
        Asset::from_bytes_limited(bytes, &AssetLimits::default())
    }

    /// The container's frame: magic, version, checksum, codec, metadata (checked against the
    /// kind byte and the size limits of a grid) and the codec's payload.
    fn container(bytes: &[u8]) -> Result<Container<'_>, Error> {
        let bad = |m: String| Error::asset(m);
        if bytes.len() < 24 {
            return Err(bad(format!(
                "{} bytes is too short for an asset",
                bytes.len()
            )));
        }
        if &bytes[..8] != MAGIC {
            return Err(bad(not_an_asset(bytes)));
        }
        let version = u16::from_le_bytes([bytes[8], bytes[9]]);
        if !(OLDEST_READ_VERSION..=FORMAT_VERSION).contains(&version) {
            return Err(bad(format!(
                "format version {version} is not supported by this build (reads versions {OLDEST_READ_VERSION} to {FORMAT_VERSION})"
            )));
        }
        let body = bytes.len() - 4;
        let crc = u32::from_le_bytes(bytes[body..].try_into().expect("4 bytes"));
        if crc32fast::hash(&bytes[..body]) != crc {
            return Err(bad(
                "checksum mismatch: the file is corrupt or truncated".into()
            ));
        }
        let (kind, codec) = (bytes[10], bytes[11]);
        if !(1..=6).contains(&codec) {
            return Err(bad(format!(
                "unknown codec {codec} (this build reads 1 quadtree PIFS, 2 FIS, 3 psa2d, 4 IFS3D, 5 curves, 6 projected)"
            )));
        }
        if codec == Codec::Curve as u8 && version < OLDEST_CURVE_VERSION {
            return Err(bad(format!(
                "a curve asset of format version {version} is not read by this build (its curve coding changed in version {OLDEST_CURVE_VERSION}): encode the source again"
            )));
        }
        let read_len = |at: usize| -> Result<usize, Error> {
            let b = bytes
                .get(at..at + 4)
                .ok_or_else(|| bad("truncated length field".into()))?;
            Ok(u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize)
        };
        let m_len = read_len(12)?;
        let meta_bytes = bytes
            .get(16..16 + m_len)
            .ok_or_else(|| bad("truncated metadata".into()))?;
        let p_len = read_len(16 + m_len)?;
        let p_start = 20 + m_len;
        let p_end = p_start
            .checked_add(p_len)
            .filter(|&e| e <= body)
            .ok_or_else(|| bad("payload length does not match the file size".into()))?;
        // Version 5 on: the source-error map after the payload.
        let section = if version >= 5 {
            let s_len = read_len(p_end)?;
            bytes
                .get(p_end + 4..p_end + 4 + s_len)
                .filter(|_| p_end + 4 + s_len == body)
                .ok_or_else(|| bad("source-error map length does not match the file size".into()))?
        } else if p_end == body {
            &[][..]
        } else {
            return Err(bad("payload length does not match the file size".into()));
        };
        let meta: AssetMeta = fractile_proto::decode(meta_bytes).map_err(|e| bad(e.to_string()))?;
        if kind_byte(meta.kind) != kind {
            return Err(bad("kind byte and metadata disagree".into()));
        }
        // Curves count vertices in `width` (one row); grids are at most 2^16 a side.
        let max_width = if meta.kind == AssetKind::Curve {
            1 << 26
        } else {
            1 << 16
        };
        if meta.width == 0 || meta.height == 0 || meta.width > max_width || meta.height > 1 << 16 {
            return Err(bad(format!(
                "bad size {}x{} in the metadata",
                meta.width, meta.height
            )));
        }
        Ok((codec, meta, &bytes[p_start..p_end], section))
    }

    /// Parses and checks a file's bytes; the sizes it claims are checked against `limits` and
    /// against what its streams can hold before anything is allocated for them.
    pub fn from_bytes_limited(bytes: &[u8], limits: &AssetLimits) -> Result<Asset, Error> {
        Asset::from_bytes_built(bytes, limits, Build::Whole)
    }

    /// [`Asset::from_bytes_limited`], its operators built as `build` says.
    pub(crate) fn from_bytes_built(
        bytes: &[u8],
        limits: &AssetLimits,
        build: Build,
    ) -> Result<Asset, Error> {
        if is_chunked(bytes) {
            let source = InMemory(bytes.into());
            return Asset::open_chunked(Box::new(source), limits, ChunkCache::shared());
        }
        let (codec, meta, payload, section) = Asset::container(bytes)?;
        let (w, h) = (meta.width as usize, meta.height as usize);
        let span = (meta.value_max - meta.value_min) as f32;
        let mut asset = Asset::from_payload(codec, meta, payload, limits, build)?;
        if !section.is_empty() {
            if asset.planes.is_empty() {
                return Err(Error::asset(
                    "a source-error map in an asset without planes",
                ));
            }
            let map = SourceError::decode(section, w, h, span)
                .map_err(|e| Error::asset(format!("source-error map: {e}")))?;
            asset.source_error = Some(map);
        }
        Ok(asset)
    }

    /// The asset of a codec's payload, its sizes checked against `limits`.
    fn from_payload(
        codec: u8,
        meta: AssetMeta,
        payload: &[u8],
        limits: &AssetLimits,
        build: Build,
    ) -> Result<Asset, Error> {
        let bad = |m: String| Error::asset(m);
        let (w, h) = (u64::from(meta.width), u64::from(meta.height));
        let mask = |m: Option<Vec<u8>>| -> Result<Option<Mask>, Error> {
            m.map(|m| Mask::decode(meta.width as usize, meta.height as usize, &m))
                .transpose()
        };
        // A mask is a byte per cell and a small summary; a full-resolution discrete decode
        // holds two f32 grids per plane.
        let mask_bytes = |m: &Option<Vec<u8>>| m.as_ref().map_or(0, |_| w * h + w * h / 64);
        let discrete = |planes: usize| 8 * w * h * planes as u64;
        if codec == Codec::Curve as u8 {
            // The header delimits itself and the stream runs to the payload's end.
            let (header, stream) = crate::codecs::curve::code::compact::read(payload)
                .map_err(|e| bad(format!("curve: {e}")))?;
            let points: u64 = header
                .rings
                .iter()
                .map(|r| (u64::from(r.pieces) << (u32::from(r.levels) + 1)).min(1 << 40))
                .fold(0, u64::saturating_add);
            limits.check_pixels("a curve set", points)?;
            // A point at every level (a geometric series: twice the finest) as two f64, its
            // details and the level's working copies: about 64 bytes per finest point.
            limits.check_cost(points.saturating_mul(64))?;
            return Asset::from_curve_parts(meta, header, stream.to_vec());
        }
        if codec == Codec::Octree as u8 {
            let p: VolumePayload =
                fractile_proto::decode(payload).map_err(|e| bad(e.to_string()))?;
            limits.check_pixels("a volume", w * w * w)?;
            let cells = (u64::from(p.header.frame) / u64::from(p.header.min_size.max(1))).pow(3);
            limits.check_cost(cells * 4 + 8 * w * w * w)?;
            return Asset::from_volume_parts(meta, p.header, p.stream, p.placement);
        }
        limits.check_pixels("a grid", w * h)?;
        if codec == Codec::Psa as u8 {
            let p: PsaPayload = fractile_proto::decode(payload).map_err(|e| bad(e.to_string()))?;
            // Vertex heights and region maps, about 64 bytes a vertex.
            let vertices = lattice_nodes(&p.planes, PsaHeader::validate, PsaHeader::vertices)?;
            limits.check_cost(vertices * 64 + mask_bytes(&p.mask) + discrete(p.planes.len()))?;
            let mask = mask(p.mask)?;
            return Asset::from_psa_parts(meta, p.planes, mask);
        }
        if codec == Codec::Projected as u8 {
            let p: ProjectedPayload =
                fractile_proto::decode(payload).map_err(|e| bad(e.to_string()))?;
            // The decoded grid as f64 while decoding, then the samples as f32 and g at nine
            // half-lattice points a cell: about 48 bytes a sample.
            let cells = lattice_nodes(&p.planes, ProjectedHeader::validate, |h| {
                [h.samples[0] as usize, h.samples[1] as usize]
            })?;
            limits.check_cost(cells * 48 + mask_bytes(&p.mask) + discrete(p.planes.len()))?;
            let mask = mask(p.mask)?;
            return Asset::from_projected_built(meta, p.planes, mask, build);
        }
        if codec == Codec::Fis as u8 {
            let p: FisPayload = fractile_proto::decode(payload).map_err(|e| bad(e.to_string()))?;
            // Node heights, scalings and a piece per cell, about 64 bytes a node.
            let nodes = lattice_nodes(&p.planes, FisHeader::validate, FisHeader::nodes)?;
            limits.check_cost(nodes * 64 + mask_bytes(&p.mask) + discrete(p.planes.len()))?;
            let mask = mask(p.mask)?;
            return Asset::from_fis_parts(meta, p.planes, mask);
        }
        let p: Payload = fractile_proto::decode(payload).map_err(|e| bad(e.to_string()))?;
        for (i, (header, _)) in p.planes.iter().enumerate() {
            header
                .validate()
                .and_then(|()| check_extent(&meta, header.valid))
                .map_err(|e| bad(format!("plane {i}: {e}")))?;
        }
        let operators: u64 = p
            .planes
            .iter()
            .map(|(hd, stream)| hd.operator_bytes(stream.len()))
            .sum();
        limits.check_cost(operators + mask_bytes(&p.mask) + discrete(p.planes.len()))?;
        let mask = mask(p.mask)?;
        Asset::from_parts(meta, p.planes, mask)
    }

    /// The coarse view at `depth` of a chunk's file (a single-plane projected height field):
    /// its multiresolution's coarse samples ([`crate::codecs::projected::decode_coarse`]) as
    /// an asset of `ceil(w / 2^depth) x ceil(h / 2^depth)` cells, its mask valid where any of
    /// a cell's `2^depth x 2^depth` source cells is (as the box means of overviews are). No
    /// source-error map: a chunked file keeps the view's in its table.
    pub(crate) fn coarse_view(
        bytes: &[u8],
        limits: &AssetLimits,
        depth: u32,
        build: Build,
    ) -> Result<Asset, Error> {
        let (codec, meta, payload, _) = Asset::container(bytes)?;
        if codec != Codec::Projected as u8 || meta.kind != AssetKind::HeightField {
            return Err(Error::asset(
                "a coarse view of a chunk that is no projected height field",
            ));
        }
        let p: ProjectedPayload =
            fractile_proto::decode(payload).map_err(|e| Error::asset(e.to_string()))?;
        let [(header, stream)] = <[_; 1]>::try_from(p.planes)
            .map_err(|_| Error::asset("a coarse view of a chunk of several planes"))?;
        header.validate().map_err(Error::asset)?;
        if header.samples != [meta.width, meta.height] {
            return Err(Error::asset("sample grid and metadata disagree"));
        }
        let (w, h) = (meta.width as usize, meta.height as usize);
        limits.check_pixels("a grid", (w * h) as u64)?;
        // The source grid as f64 while decoding (the finest band is never read), then the
        // view's samples.
        limits.check_cost((w * h) as u64 * 8 + ((w * h) >> (2 * depth)) as u64 * 48)?;
        let (view, grid, _) = crate::codecs::projected::decode_coarse(&header, &stream, depth)
            .map_err(|e| Error::asset(format!("coarse view: {e}")))?;
        let [cw, ch] = [view.samples[0] as usize, view.samples[1] as usize];
        let mask = p
            .mask
            .map(|m| Mask::decode(w, h, &m))
            .transpose()?
            .map(|m| {
                let s = 1usize << depth;
                let mut valid = vec![false; cw * ch];
                for (i, _) in m.valid().iter().enumerate().filter(|(_, v)| **v) {
                    valid[(i / w / s) * cw + (i % w) / s] = true;
                }
                Mask::new(cw, ch, valid)
            });
        let operator = match build {
            Build::Whole => ProjectedOperator::new(&view, &grid),
            Build::Lazy => ProjectedOperator::lazy(&view, grid),
        }
        .map_err(Error::asset)?;
        let asset = Asset {
            meta: AssetMeta {
                width: cw as u32,
                height: ch as u32,
                ..meta
            },
            planes: vec![Plane {
                coding: Coding::Projected {
                    header: view,
                    stream: Vec::new(),
                },
                operator: PlaneOperator::Projected(operator),
            }],
            mask,
            volume: None,
            curve: None,
            source_error: None,
            chunks: None,
        };
        asset.check()?;
        Ok(asset)
    }

    /// A chunked container from `source`: its header is read now, its chunks when answers
    /// need them, decoded into `cache`.
    pub fn open_chunked(
        source: Box<dyn ChunkSource>,
        limits: &AssetLimits,
        cache: ChunkCache,
    ) -> Result<Asset, Error> {
        let (meta, chunked) = Chunked::open(source, limits, cache)?;
        Ok(Asset {
            meta,
            planes: Vec::new(),
            mask: None,
            volume: None,
            curve: None,
            source_error: None,
            chunks: Some(Arc::new(chunked)),
        })
    }

    /// Opens an asset file under `limits`: a chunked one by its header alone (its chunks are
    /// read by range when needed, decoded into `cache`), any other whole.
    pub fn open(path: &Path, limits: &AssetLimits, cache: ChunkCache) -> Result<Asset, Error> {
        let input = |e: std::io::Error| {
            Error::input(format!("{}: {e}", path.display()))
                .at(path)
                .caused_by(e)
        };
        let mut head = [0u8; 12];
        let n = {
            use std::io::Read;
            let mut f = std::fs::File::open(path).map_err(input)?;
            let mut n = 0;
            while n < head.len() {
                match f.read(&mut head[n..]).map_err(input)? {
                    0 => break,
                    k => n += k,
                }
            }
            n
        };
        if is_chunked(&head[..n]) {
            let source = FileSource::open(path).map_err(input)?;
            return Asset::open_chunked(Box::new(source), limits, cache);
        }
        let bytes = std::fs::read(path).map_err(input)?;
        Asset::from_bytes_limited(&bytes, limits).map_err(|e| match e {
            Error::Asset { .. } => e.within(path.display()).at(path),
            e => e,
        })
    }

    /// Reads an asset file under the default limits (a chunked one by its header; its chunks
    /// go to the process's shared cache).
    pub fn read(path: &Path) -> Result<Asset, Error> {
        Asset::open(path, &AssetLimits::default(), ChunkCache::shared())
    }

    /// Writes the file atomically: a temporary file beside it, synced, then renamed over it.
    pub fn write(&self, path: &Path) -> Result<(), Error> {
        if let Some(c) = &self.chunks {
            return write_atomic(path, &c.bytes()?);
        }
        write_atomic(path, &self.to_bytes())
    }
}

/// A file's frame, read: codec byte, metadata, payload and source-error map bytes.
type Container<'a> = (u8, AssetMeta, &'a [u8], &'a [u8]);

fn assemble(meta: &AssetMeta, codec: Codec, payload: &[u8], section: &[u8]) -> Vec<u8> {
    let meta_bytes = fractile_proto::encode(meta);
    let mut out = Vec::with_capacity(28 + meta_bytes.len() + payload.len() + section.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.push(kind_byte(meta.kind));
    out.push(codec as u8);
    out.extend_from_slice(&(meta_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(&meta_bytes);
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(payload);
    out.extend_from_slice(&(section.len() as u32).to_le_bytes());
    out.extend_from_slice(section);
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

/// What names a temporary file of [`write_atomic`]: `.{name}.tmp-{pid}-{n}`.
const TEMPORARY: &str = ".tmp-";

/// The process that writes the temporary file named `name`, if `name` is one of
/// [`write_atomic`]'s (so that a reader of the folder can remove those a crash left behind).
pub fn temporary_owner(name: &str) -> Option<u32> {
    let rest = name.strip_prefix('.')?;
    let (_, tail) = rest.rsplit_once(TEMPORARY)?;
    let (pid, n) = tail.split_once('-')?;
    n.parse::<u64>().ok()?;
    pid.parse().ok()
}

/// Writes bytes to `path` atomically (temporary file in the same directory, fsync, rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), Error> {
    write_atomic_with(path, &mut |f| f.write_all(bytes))
}

/// Writes to `path` atomically what `write` writes into the temporary file (a file too large
/// to hold in memory is written in parts): the temporary file is synced, then renamed over
/// `path`, or removed if `write` fails.
pub fn write_atomic_with(
    path: &Path,
    write: &mut dyn FnMut(&mut std::fs::File) -> std::io::Result<()>,
) -> Result<(), Error> {
    let err = |e: std::io::Error| {
        Error::output(format!("{}: {e}", path.display()))
            .at(path)
            .caused_by(e)
    };
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .ok_or_else(|| Error::output(format!("{}: not a file path", path.display())))?;
    // A name of its own per write (process and a counter): concurrent writers of one path
    // each rename a whole file, and never write into another's.
    static WRITES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = WRITES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = dir.join(format!(
        ".{}{TEMPORARY}{}-{n}",
        name.to_string_lossy(),
        std::process::id()
    ));
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        write(&mut f)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.map_err(err)
}

#[cfg(test)]
mod tests {
    use super::Mask;
    use proptest::prelude::*;

    proptest! {
        /// The block summary answers what looking at every cell under the box answers.
        #[test]
        fn mask_summary_agrees_with_the_cells(
            w in 1usize..80,
            h in 1usize..80,
            holes in proptest::collection::vec((0usize..80, 0usize..80), 0..4),
            b in (-0.1f32..1.1, -0.1f32..1.1, 0.0f32..0.6, 0.0f32..0.6),
        ) {
            let mut valid = vec![true; w * h];
            for (x, y) in holes {
                valid[(y % h) * w + x % w] = false;
            }
            let m = Mask::new(w, h, valid);
            let bx = [b.0, b.1, b.0 + b.2, b.1 + b.3];
            let ((x0, y0), (x1, y1)) = (m.cell(bx[0], bx[1]), m.cell(bx[2], bx[3]));
            let cells_valid = (y0..=y1).all(|y| (x0..=x1).all(|x| m.valid[y * w + x]));
            // The blocks under the box, cell by cell.
            let (bx0, by0) = (x0 / super::BLOCK * super::BLOCK, y0 / super::BLOCK * super::BLOCK);
            let (bx1, by1) = (((x1 / super::BLOCK + 1) * super::BLOCK).min(w), ((y1 / super::BLOCK + 1) * super::BLOCK).min(h));
            let blocks_valid = (by0..by1).all(|y| (bx0..bx1).all(|x| m.valid[y * w + x]));
            let got = m.all_valid(bx);
            prop_assert_eq!(got, blocks_valid);
            prop_assert!(!got || cells_valid);
            // And every point of the box is then valid.
            if got {
                for k in 0..=16 {
                    let t = k as f32 / 16.0;
                    prop_assert!(m.at(bx[0] + t * b.2, bx[1] + (1.0 - t) * b.3));
                }
            }
        }
    }
}
