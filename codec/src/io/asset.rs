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
use crate::codecs::plane::{Build, PlaneCodec};
use crate::codecs::projected::{ProjectedHeader, ProjectedOperator};
use crate::codecs::quadtree::stream::PlaneHeader;
use crate::codecs::registry::{self, Registered, Visit};
pub use crate::codecs::registry::{Codec, Coding, PlaneOperator};
use crate::core::entropy::{Bit, Decoder, Encoder};
use crate::core::fidelity::SourceError;

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
            _ => None,
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

/// The payload of a plane codec: its planes (header and stream) and the mask. One generic
/// struct for every codec: bincode writes a struct as its fields, so every codec's payload
/// has this layout.
#[derive(Serialize, Deserialize)]
struct Payload<H> {
    planes: Vec<(H, Vec<u8>)>,
    mask: Option<Vec<u8>>,
}

#[derive(Serialize, Deserialize)]
struct VolumePayload {
    header: crate::codecs::ifs3d::octree::OctreeHeader,
    stream: Vec<u8>,
    placement: crate::codecs::ifs3d::volume::Placement,
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
    /// Builds an asset from coded planes of the codec whose header is `H`, decoding each
    /// stream (so that what is served is exactly what a reader of the file gets).
    pub fn from_coded<H: Registered>(
        meta: AssetMeta,
        planes: Vec<(H, Vec<u8>)>,
        mask: Option<Mask>,
    ) -> Result<Asset, Error> {
        Asset::from_coded_built(meta, planes, mask, Build::Whole)
    }

    /// [`Asset::from_coded`], the operators built as `build` says.
    fn from_coded_built<H: Registered>(
        meta: AssetMeta,
        planes: Vec<(H, Vec<u8>)>,
        mask: Option<Mask>,
        build: Build,
    ) -> Result<Asset, Error> {
        H::accepts(&meta)?;
        Asset::assemble(meta, planes, mask, |meta, header, stream| {
            let operator = H::plane_operator(header.operator(meta, &stream, build)?);
            Ok(Plane {
                coding: header.coding(stream),
                operator,
            })
        })
    }

    /// Size in bytes of the file [`Asset::from_coded`] would build from the same parts, without
    /// decoding the streams or building operators: rate control asks it of every trial
    /// partition and builds the asset once, for the one it keeps.
    pub fn coded_file_size<H: PlaneCodec>(
        meta: &AssetMeta,
        planes: Vec<(H, Vec<u8>)>,
        mask: Option<&Mask>,
    ) -> usize {
        let payload = fractile_proto::encode(&Payload {
            planes,
            mask: mask.map(Mask::encode),
        });
        assemble(meta, H::BYTE, &payload, &[]).len()
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
            return Codec::from_byte(c.table.codec).unwrap_or(Codec::Quadtree);
        }
        if self.curve.is_some() {
            return Codec::Curve;
        }
        if self.volume.is_some() {
            return Codec::Octree;
        }
        self.planes
            .first()
            .map_or(Codec::Quadtree, |p| p.coding.codec())
    }

    /// The codec's name as the CLI and the API spell it.
    pub fn codec_name(&self) -> &'static str {
        if let Some(c) = &self.chunks {
            // The chunks' codec: by its byte, or (a FIS or psa2d name needs a chunk's header)
            // from the first chunk with data.
            if let Some(name) = Codec::from_byte(c.table.codec).and_then(Codec::name) {
                return name;
            }
            let first = c.table.levels[0].chunks.iter().position(|e| e.length > 0);
            return match first.map(|i| c.chunk(0, i)) {
                Some(Ok(Some(a))) => a.codec_name(),
                _ => "chunked",
            };
        }
        if self.curve.is_some() || self.volume.is_some() {
            return self.codec().name().unwrap_or("chunked");
        }
        self.planes
            .first()
            .map_or("quadtree-pifs", |p| p.coding.name())
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
        let codec = self.codec();
        let payload = match codec {
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
            _ => registry::visit(
                codec,
                WritePayload {
                    planes: &self.planes,
                    mask,
                },
            )
            .expect("a codec of planes"),
        };
        let section = self
            .source_error
            .as_ref()
            .map(SourceError::encode)
            .unwrap_or_default();
        assemble(&self.meta, codec.byte(), &payload, &section)
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
        if Codec::from_byte(codec).is_none() {
            let mut known: Vec<Codec> = Codec::ALL.to_vec();
            known.sort_by_key(|c| c.byte());
            let known: Vec<String> = known
                .iter()
                .map(|c| format!("{} {}", c.byte(), c.label()))
                .collect();
            return Err(bad(format!(
                "unknown codec {codec} (this build reads {})",
                known.join(", ")
            )));
        }
        if codec == Codec::Curve.byte() && version < OLDEST_CURVE_VERSION {
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
        if codec == Codec::Curve.byte() {
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
        if codec == Codec::Octree.byte() {
            let p: VolumePayload =
                fractile_proto::decode(payload).map_err(|e| bad(e.to_string()))?;
            limits.check_pixels("a volume", w * w * w)?;
            let cells = (u64::from(p.header.frame) / u64::from(p.header.min_size.max(1))).pow(3);
            limits.check_cost(cells * 4 + 8 * w * w * w)?;
            return Asset::from_volume_parts(meta, p.header, p.stream, p.placement);
        }
        limits.check_pixels("a grid", w * h)?;
        let codec = Codec::from_byte(codec).ok_or_else(|| bad(format!("unknown codec {codec}")))?;
        let read = ReadPayload {
            meta,
            payload,
            limits,
            build,
        };
        registry::visit(codec, read).ok_or_else(|| bad(format!("codec {codec:?} has no planes")))?
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
        if codec != Codec::Projected.byte() || meta.kind != AssetKind::HeightField {
            return Err(Error::asset(
                "a coarse view of a chunk that is no projected height field",
            ));
        }
        let p: Payload<ProjectedHeader> =
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

/// Reads the planes of a plane codec's payload: headers checked and the cost estimated
/// before anything is decoded, then every stream decoded.
struct ReadPayload<'a> {
    meta: AssetMeta,
    payload: &'a [u8],
    limits: &'a AssetLimits,
    build: Build,
}

impl Visit for ReadPayload<'_> {
    type Output = Result<Asset, Error>;

    fn visit<H: Registered>(self) -> Result<Asset, Error> {
        let ReadPayload {
            meta,
            payload,
            limits,
            build,
        } = self;
        let (w, h) = (u64::from(meta.width), u64::from(meta.height));
        let p: Payload<H> =
            fractile_proto::decode(payload).map_err(|e| Error::asset(e.to_string()))?;
        let mut operators = 0u64;
        for (i, (header, stream)) in p.planes.iter().enumerate() {
            let bytes = header
                .cost(&meta, stream)
                .map_err(|e| Error::asset(format!("plane {i}: {e}")))?;
            operators = operators.saturating_add(bytes);
        }
        // A mask is a byte per cell and a small summary; a full-resolution discrete decode
        // holds two f32 grids per plane.
        let mask_bytes = p.mask.as_ref().map_or(0, |_| w * h + w * h / 64);
        let discrete = 8 * w * h * p.planes.len() as u64;
        limits.check_cost(operators.saturating_add(mask_bytes + discrete))?;
        let mask = p
            .mask
            .map(|m| Mask::decode(meta.width as usize, meta.height as usize, &m))
            .transpose()?;
        Asset::from_coded_built(meta, p.planes, mask, build)
    }
}

/// Writes the planes of a plane codec's asset as its payload.
struct WritePayload<'a> {
    planes: &'a [Plane],
    mask: Option<Vec<u8>>,
}

impl Visit for WritePayload<'_> {
    type Output = Vec<u8>;

    fn visit<H: Registered>(self) -> Vec<u8> {
        fractile_proto::encode(&Payload {
            planes: self
                .planes
                .iter()
                .filter_map(|p| H::of(&p.coding))
                .map(|(header, stream)| (header.clone(), stream.to_vec()))
                .collect(),
            mask: self.mask,
        })
    }
}

fn assemble(meta: &AssetMeta, codec: u8, payload: &[u8], section: &[u8]) -> Vec<u8> {
    let meta_bytes = fractile_proto::encode(meta);
    let mut out = Vec::with_capacity(28 + meta_bytes.len() + payload.len() + section.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.push(kind_byte(meta.kind));
    out.push(codec);
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
