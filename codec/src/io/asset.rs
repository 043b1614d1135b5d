//! The asset file: a versioned container of metadata and the coded operator(s).
//!
//! The layout (magic, version, kind, codec, metadata, payload, source-error map, CRC-32) is
//! specified in docs/asset-format.md, and its frame read and written in `io::container`.
//!
//! Reading checks all of it before any decoding: a truncated, corrupt or newer file is an
//! [`Error::asset`] naming what is wrong, never a panic.

use std::path::Path;
use std::sync::Arc;

use fractile_proto::{AssetKind, AssetMeta};
use serde::{Deserialize, Serialize};

pub use super::atomic::{temporary_owner, write_atomic, write_atomic_with};
use super::container::container;
pub use super::container::{
    AssetLimits, FORMAT_VERSION, OLDEST_CURVE_VERSION, OLDEST_READ_VERSION, check_magic,
    check_whole_file,
};
use super::cost::{PayloadCost, payload_cost};
use super::layout::{ChunkSource, ChunkTable, FileSource, InMemory, is_chunked};
pub use super::mask::Mask;
use crate::Error;
pub use crate::codecs::coded::Plane;
use crate::codecs::coded::{Coded, Payload, file_bytes, payload};
use crate::codecs::plane::Build;
use crate::codecs::registry::{self, Registered, Visit};
pub use crate::codecs::registry::{Codec, Coding, PlaneOperator};
use crate::core::fidelity::SourceError;
use crate::core::format::FormatError;

#[derive(Serialize, Deserialize)]
struct VolumePayload {
    header: crate::codecs::ifs3d::octree::OctreeHeader,
    stream: Vec<u8>,
    placement: crate::codecs::ifs3d::volume::Placement,
}

/// A decoded asset file: metadata, and what it holds (one [`Body`]).
#[derive(Clone, Debug)]
pub struct Asset {
    /// What the asset is.
    pub meta: AssetMeta,
    /// What it holds: planes, chunks, a volume or curves; answers go by this one type, as
    /// martin's sources answer `get_tile` (an asset with planes and a volume at once is not
    /// made).
    pub body: Body,
    /// Each block's measured error against the source (format version 5 on; `None` in older
    /// files and for volumes and curves): what answers' `error_bound` adds to convergence.
    pub source_error: Option<SourceError>,
}

/// What an [`Asset`] holds.
#[derive(Clone, Debug)]
pub enum Body {
    /// One plane per coded channel (Y, Cb, Cr for colour), and the source's validity where it
    /// had nodata.
    Planes {
        /// The planes with their operators.
        planes: Vec<Plane>,
        /// Source validity, for height fields with nodata.
        mask: Option<Mask>,
    },
    /// The chunks of a chunked asset (format version 6), read and decoded on demand; its
    /// answers are its chunks' (`extract::chunked`).
    Chunked(Arc<Chunked>),
    /// A coded volume.
    Volume(crate::codecs::ifs3d::volume::Volume),
    /// Coded curves.
    Curves(crate::codecs::curve::Curves),
}

// The chunked container's own state and the cache of its decoded chunks are declared here,
// beside the asset that holds them and that they hold (an asset's chunks are assets); their
// behaviour is in `chunked`.
/// Decoded chunks of every chunked asset of a process, bounded in bytes (their estimated
/// resident size: operators and masks), least recently used out first. moka's cache also makes
/// concurrent requests for one chunk decode it once.
#[derive(Clone)]
pub struct ChunkCache {
    pub(crate) cache: super::cache::ChunkMap<Asset>,
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
    /// Its planes (none for chunked assets, volumes and curves).
    pub fn planes(&self) -> &[Plane] {
        match &self.body {
            Body::Planes { planes, .. } => planes,
            _ => &[],
        }
    }

    /// The source's validity, for a height field of planes with nodata.
    pub fn mask(&self) -> Option<&Mask> {
        match &self.body {
            Body::Planes { mask, .. } => mask.as_ref(),
            _ => None,
        }
    }

    /// Its chunks, for a chunked asset.
    pub fn chunked(&self) -> Option<&Arc<Chunked>> {
        match &self.body {
            Body::Chunked(c) => Some(c),
            _ => None,
        }
    }

    /// Its volume, for a volume asset.
    pub fn volume(&self) -> Option<&crate::codecs::ifs3d::volume::Volume> {
        match &self.body {
            Body::Volume(v) => Some(v),
            _ => None,
        }
    }

    /// Its curves, for a curve asset.
    pub fn curves(&self) -> Option<&crate::codecs::curve::Curves> {
        match &self.body {
            Body::Curves(c) => Some(c),
            _ => None,
        }
    }

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
        Asset::from_planes(Coded::new(meta, planes, mask, build)?)
    }

    /// The asset of a plane codec's coded planes (what its encoder returns), checked.
    pub fn from_planes(coded: Coded) -> Result<Asset, Error> {
        let asset = Asset::holding(coded);
        asset.check()?;
        Ok(asset)
    }

    /// The asset that holds `coded` as it is: what an encoder's measures decode.
    pub(crate) fn holding(coded: Coded) -> Asset {
        let Coded {
            meta,
            planes,
            mask,
            source_error,
        } = coded;
        Asset {
            meta,
            body: Body::Planes { planes, mask },
            source_error,
        }
    }

    /// The coded planes an asset of a plane codec holds, given back.
    pub(crate) fn into_planes(self) -> Coded {
        let (planes, mask) = match self.body {
            Body::Planes { planes, mask } => (planes, mask),
            _ => (Vec::new(), None),
        };
        Coded {
            meta: self.meta,
            planes,
            mask,
            source_error: self.source_error,
        }
    }

    /// Builds a volume asset from its coded stream (decoding it, as a reader would).
    pub fn from_volume_parts(
        meta: AssetMeta,
        header: crate::codecs::ifs3d::octree::OctreeHeader,
        stream: Vec<u8>,
        placement: crate::codecs::ifs3d::volume::Placement,
    ) -> Result<Asset, Error> {
        let bad = |e: FormatError| Error::asset(format!("volume: {e}"));
        if meta.kind != AssetKind::Volume || meta.channels != 1 || meta.width != meta.height {
            return Err(bad(FormatError::header(
                "metadata is not that of a cubic one-channel volume",
            )));
        }
        if header.valid != meta.width as f32 {
            return Err(bad(FormatError::header("grid size and metadata disagree")));
        }
        placement.validate().map_err(bad)?;
        let leaves = crate::codecs::ifs3d::octree::decode_stream(&header, &stream).map_err(bad)?;
        let operator =
            crate::codecs::ifs3d::octree::OctreeOperator::new(&header, leaves).map_err(bad)?;
        let asset = Asset {
            meta,
            body: Body::Volume(crate::codecs::ifs3d::volume::Volume {
                header,
                stream,
                operator,
                placement,
            }),
            source_error: None,
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
        let bad = |e: FormatError| Error::asset(format!("curve: {e}"));
        if meta.kind != AssetKind::Curve {
            return Err(bad(FormatError::header(
                "metadata is not that of a curve asset",
            )));
        }
        let set = crate::codecs::curve::code::decode(&header, &stream).map_err(bad)?;
        let asset = Asset {
            meta,
            body: Body::Curves(crate::codecs::curve::Curves {
                header,
                stream,
                set,
            }),
            source_error: None,
        };
        asset.check()?;
        Ok(asset)
    }

    /// The codec of the planes.
    pub fn codec(&self) -> Codec {
        if let Some(c) = &self.chunked() {
            return Codec::from_byte(c.table.codec).unwrap_or(Codec::Quadtree);
        }
        if self.curves().is_some() {
            return Codec::Curve;
        }
        if self.volume().is_some() {
            return Codec::Octree;
        }
        self.planes()
            .first()
            .map_or(Codec::Quadtree, |p| p.coding.codec())
    }

    /// The codec's name as the CLI and the API spell it.
    pub fn codec_name(&self) -> &'static str {
        if let Some(c) = &self.chunked() {
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
        if self.curves().is_some() || self.volume().is_some() {
            return self.codec().name().unwrap_or("chunked");
        }
        self.planes()
            .first()
            .map_or("quadtree-pifs", |p| p.coding.name())
    }

    pub(crate) fn check(&self) -> Result<(), Error> {
        let m = &self.meta;
        if (m.kind == AssetKind::Volume) != self.volume().is_some() {
            return Err(Error::asset(
                "a volume asset must hold a volume, and only it",
            ));
        }
        if (m.kind == AssetKind::Curve) != self.curves().is_some() {
            return Err(Error::asset("a curve asset must hold curves, and only it"));
        }
        let expected = match m.colour {
            _ if self.volume().is_some() || self.curves().is_some() => 0,
            fractile_proto::ColourModel::Grey => 1,
            fractile_proto::ColourModel::YCbCr => 3,
        };
        if self.planes().len() != expected
            || (expected > 0 && m.channels as usize != expected)
            || (self.curves().is_some() && m.channels != 2)
        {
            return Err(Error::asset(format!(
                "{} planes and {} channels for colour model {:?}",
                self.planes().len(),
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
        if let Some(c) = &self.chunked() {
            // Empty if its source cannot be read: `write` says why instead.
            return c.bytes().unwrap_or_default();
        }
        let codec = self.codec();
        let payload = match codec {
            Codec::Octree => {
                let v = self.volume().expect("an octree asset holds a volume");
                fractile_proto::encode(&VolumePayload {
                    header: v.header.clone(),
                    stream: v.stream.clone(),
                    placement: v.placement.clone(),
                })
            }
            Codec::Curve => self.curves().expect("a curve asset holds curves").payload(),
            _ => payload(codec, self.planes(), self.mask()),
        };
        file_bytes(&self.meta, codec, &payload, self.source_error.as_ref())
    }

    /// Size of the file in bytes.
    pub fn file_size(&self) -> usize {
        self.to_bytes().len()
    }

    /// Parses and checks a file's bytes under the default [`AssetLimits`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Asset, Error> {
        Asset::from_bytes_limited(bytes, &AssetLimits::default())
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
        let (codec, meta, payload, section) = container(bytes)?;
        let (w, h) = (meta.width as usize, meta.height as usize);
        let span = (meta.value_max - meta.value_min) as f32;
        let mut asset = Asset::from_payload(codec, meta, payload, limits, build)?;
        if !section.is_empty() {
            if asset.planes().is_empty() {
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
            body: Body::Chunked(Arc::new(chunked)),
            source_error: None,
        })
    }

    /// The asset `source` holds (a file, an object, a URL), under `limits`: a chunked one by
    /// its header alone (its chunks read by range when needed, decoded into `cache`), any
    /// other read whole.
    pub fn from_source(
        source: Box<dyn ChunkSource>,
        limits: &AssetLimits,
        cache: ChunkCache,
    ) -> Result<Asset, Error> {
        let read = |offset, len| {
            source
                .read(offset, len)
                .map_err(|e| Error::unavailable(format!("{}: {e}", source.describe())).caused_by(e))
        };
        let head = read(0, source.len().min(12) as usize)?;
        if is_chunked(&head) {
            return Asset::open_chunked(source, limits, cache);
        }
        check_whole_file(&head, source.len(), limits).map_err(|e| e.within(source.describe()))?;
        let bytes = read(0, usize::try_from(source.len()).unwrap_or(usize::MAX))?;
        Asset::from_bytes_limited(&bytes, limits).map_err(|e| match e {
            Error::Asset { .. } => e.within(source.describe()),
            e => e,
        })
    }

    /// The asset file at `path`, as [`Asset::from_source`] opens it.
    pub fn open(path: &Path, limits: &AssetLimits, cache: ChunkCache) -> Result<Asset, Error> {
        let source = FileSource::open(path)
            .map_err(|e| Error::input(format!("{}: {e}", path.display())).caused_by(e))
            .map_err(|e| e.at(path))?;
        Asset::from_source(Box::new(source), limits, cache).map_err(|e| match e {
            Error::Asset { .. } => e.at(path),
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
        if let Some(c) = &self.chunked() {
            return write_atomic(path, &c.bytes()?);
        }
        write_atomic(path, &self.to_bytes())
    }
}

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
        let p: Payload<H> =
            fractile_proto::decode(payload).map_err(|e| Error::asset(e.to_string()))?;
        limits.check_cost(payload_cost(&meta, &p)?)?;
        let mask = p
            .mask
            .map(|m| Mask::decode(meta.width as usize, meta.height as usize, &m))
            .transpose()?;
        Asset::from_coded_built(meta, p.planes, mask, build)
    }
}

/// Whether the file `bytes` opens under `limits`, from its headers (a plane codec's streams
/// are not decoded): what a writer checks, so that what one reader writes another opens
/// (Python wrote an 8640 x 8640 asset in one piece that it then refused to open).
pub fn check_opens(bytes: &[u8], limits: &AssetLimits) -> Result<(), Error> {
    if is_chunked(bytes) {
        // A chunked file's chunks are each checked when read; its header is small.
        return Ok(());
    }
    let (codec, meta, payload, _) = container(bytes)?;
    let planes = Codec::from_byte(codec).filter(|c| !matches!(c, Codec::Octree | Codec::Curve));
    let Some(plane_codec) = planes else {
        return Asset::from_payload(codec, meta, payload, limits, Build::Whole).map(|_| ());
    };
    limits.check_pixels("a grid", u64::from(meta.width) * u64::from(meta.height))?;
    let cost = PayloadCost {
        meta: &meta,
        payload,
    };
    limits.check_cost(registry::visit(plane_codec, cost).unwrap_or(Ok(0))?)
}
