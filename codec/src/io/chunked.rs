//! Chunked assets (format version 9; 6 to 8 still read): a raster cut into square chunks, each
//! coded on its own as a whole asset file (of version 9; 5 in files of 6 to 8), behind a table
//! that says where each chunk lies in the file, so that a reader fetches and decodes one chunk
//! by byte range without reading the rest (`docs/asset-format.md`). Coarser levels (overviews:
//! the raster at 2, 4, ... source cells a cell) let a coarse tile of a huge raster decode a few
//! chunks of a coarse level instead of the whole raster.
//!
//! The first [`VIEW_DEPTH`] overview levels of a height field whose chunks are projected planes
//! are not coded (format 7: lifted chunks, rate mode; format 8: the pyramid's too, max-error
//! and bounded): a level-l chunk is the source chunk's own multiresolution read to depth l (the
//! *view*, `Asset::coarse_view`), decoded from the coarse part of the same stream: a lifted
//! plane's coarse band, a pyramid's coarse samples (source cells within the chunk's bound).
//! Coded beside the source, as format 6 did, they took 19-26% of a rate file's bytes and cost
//! it 1-2 dB against JPEG 2000 at the same bytes, and 38-51% of a max-error file's
//! (docs/benchmarks.md); the coded overviews that remain, from level 3 on, are 2% of the cells,
//! and format 8 keeps one above the views (`ChunkTable::level_sizes`). For the views' lattices
//! to be the levels' own, chunks start on multiples of `2^VIEW_DEPTH` ([`VIEW_OVERLAP`]), and a
//! view's sample `k` stands `1/2 - 2^-(l+1)` of a level cell before its box cell's centre (it
//! sits on a source cell, the box mean between cells): the reader places it there
//! ([`ChunkTable::view_shift`]). Each view's source-error map, measured at encode time against
//! what it stands for, is kept in the table.
//!
//! Each chunk codes `OVERLAP` cells beyond its own on every side (clamped at the raster's
//! edges): a point is answered by the chunk that owns it, and every point a chunk owns lies
//! between the centres of cells that chunk coded, so its bilinear neighbourhood never crosses
//! into another chunk. Two neighbours then differ at their shared edge by at most the sum of
//! their coding errors: no seam beyond the chunks' own error.
//!
//! Decoded chunks are kept in a [`ChunkCache`] bounded in bytes, shared by every chunked asset
//! of a process (a server sizes it with `chunk_cache_mib`).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use fractile_proto::{AssetKind, AssetMeta};

use super::asset::{Asset, AssetLimits, Body, Plane};
pub use super::asset::{ChunkCache, Chunked};
use super::container::container;
use super::frame::kind_byte;
pub use super::layout::*;
use super::mask::Mask;
use crate::Error;
use crate::codecs::coded::Payload;
use crate::codecs::plane::Build;
use crate::codecs::projected::{ProjectedHeader, ProjectedOperator};
use crate::codecs::registry::{Codec, Coding, PlaneOperator};
use crate::core::format::FormatError;

impl ChunkCache {
    /// A cache of at most `bytes` of decoded chunks.
    pub fn new(bytes: u64) -> ChunkCache {
        let cache = super::cache::keyed_map(bytes, resident_bytes);
        ChunkCache {
            cache,
            decoding: Arc::default(),
            most_decoding: std::thread::available_parallelism().map_or(2, |n| n.get()),
        }
    }

    /// Runs `decode` once fewer than a chunk a core are being decoded. A decode holds a few
    /// times its chunk's cached bytes while it runs (the f64 grid, the samples, the records of
    /// a band per thread, the excesses), and more decodes at once would not finish sooner on
    /// the cores there are: with sixteen tiles in flight on a cold 37 Mpx asset, the server
    /// peaked at 507 MB without this gate (and with the grid held to the end), 487 MB with
    /// it, the same caches (measured). std has no counting semaphore (tokio's is async).
    fn gated<T>(&self, decode: impl FnOnce() -> T) -> T {
        let (count, freed) = &*self.decoding;
        {
            let mut n = count.lock().unwrap_or_else(|e| e.into_inner());
            while *n >= self.most_decoding {
                n = freed.wait(n).unwrap_or_else(|e| e.into_inner());
            }
            *n += 1;
        }
        struct Release<'a>(&'a (std::sync::Mutex<usize>, std::sync::Condvar));
        impl Drop for Release<'_> {
            fn drop(&mut self) {
                *self.0.0.lock().unwrap_or_else(|e| e.into_inner()) -= 1;
                self.0.1.notify_one();
            }
        }
        let _release = Release(&self.decoding);
        decode()
    }

    /// The process's default cache, 512 MiB: what [`Asset::read`] and [`Asset::from_bytes`]
    /// give chunked assets.
    pub fn shared() -> ChunkCache {
        static SHARED: std::sync::OnceLock<ChunkCache> = std::sync::OnceLock::new();
        SHARED.get_or_init(|| ChunkCache::new(512 << 20)).clone()
    }

    /// The most bytes the cache holds.
    pub fn capacity(&self) -> u64 {
        #[cfg(feature = "moka")]
        return self.cache.policy().max_capacity().unwrap_or(u64::MAX);
        #[cfg(not(feature = "moka"))]
        self.cache.capacity()
    }

    /// Estimated bytes held by the cache now.
    pub fn weighted_bytes(&self) -> u64 {
        #[cfg(feature = "moka")]
        {
            self.cache.run_pending_tasks();
            self.cache.weighted_size()
        }
        #[cfg(not(feature = "moka"))]
        self.cache.weight()
    }
}

/// Estimated resident bytes of a decoded chunk: its operators' (projected ones count theirs;
/// the quadtree's measured 13 B a sample on the 9.3 Mpx mosaic, counted 16), its mask and its
/// coded streams.
fn resident_bytes(a: &Asset) -> u64 {
    let cells = u64::from(a.meta.width) * u64::from(a.meta.height);
    let operators: u64 = a
        .planes()
        .iter()
        .map(|p| p.operator.resident_bytes(cells))
        .sum();
    let streams: usize = a.planes().iter().map(|p| p.coding.stream().len()).sum();
    operators + a.mask().map_or(0, |_| cells) + streams as u64 + 4096
}

impl std::fmt::Debug for Chunked {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Chunked")
            .field("source", &self.source.describe())
            .field("chunk", &self.table.chunk)
            .field("levels", &self.table.levels.len())
            .finish()
    }
}

impl Chunked {
    /// Reads and checks a container's header from `source` (a few kilobytes: nothing of the
    /// chunks is read). Returns the metadata and the opened container.
    pub fn open(
        source: Box<dyn ChunkSource>,
        limits: &AssetLimits,
        cache: ChunkCache,
    ) -> Result<(AssetMeta, Chunked), Error> {
        let bad = |m: String| Error::asset(format!("{}: {m}", source.describe()));
        let io = |e: std::io::Error| Error::asset(format!("{}: {e}", source.describe()));
        let file_len = source.len();
        if file_len < 24 {
            return Err(bad(format!("{file_len} bytes is too short for an asset")));
        }
        let head = source.read(0, 16).map_err(io)?;
        if !is_chunked(&head) {
            return Err(bad("not a chunked fractile asset".into()));
        }
        if head[11] != CHUNKED_CODEC {
            return Err(bad(format!(
                "codec byte {} in a chunked container",
                head[11]
            )));
        }
        let len_at = |b: &[u8], at: usize| u32::from_le_bytes(b[at..at + 4].try_into().expect("4"));
        let m_len = u64::from(len_at(&head, 12));
        // The metadata is a few hundred bytes and the table 64 bytes a chunk.
        let most = 64 + (MAX_CHUNKS as u64) * 64;
        if 20 + m_len > file_len.min(most) {
            return Err(bad("truncated metadata".into()));
        }
        let meta_and_len = source.read(16, m_len as usize + 4).map_err(io)?;
        let t_len = u64::from(len_at(&meta_and_len, m_len as usize));
        let header_end = 20 + m_len + t_len + 4;
        if header_end > file_len || t_len > most {
            return Err(bad("truncated chunk table".into()));
        }
        let rest = source.read(20 + m_len, t_len as usize + 4).map_err(io)?;
        let mut header = head.clone();
        header.extend_from_slice(&meta_and_len);
        header.extend_from_slice(&rest[..t_len as usize]);
        let crc = u32::from_le_bytes(rest[t_len as usize..].try_into().expect("4"));
        if crc32fast::hash(&header) != crc {
            return Err(bad(
                "header checksum mismatch: the file is corrupt or truncated".into(),
            ));
        }
        let meta: AssetMeta = fractile_proto::decode(&meta_and_len[..m_len as usize])
            .map_err(|e| bad(e.to_string()))?;
        if kind_byte(meta.kind) != head[10] {
            return Err(bad("kind byte and metadata disagree".into()));
        }
        if meta.width == 0 || meta.height == 0 || meta.width > 1 << 24 || meta.height > 1 << 24 {
            return Err(bad(format!(
                "bad size {}x{} in the metadata",
                meta.width, meta.height
            )));
        }
        // A chunked asset's memory is its table and the chunks a request decodes, not its
        // cells: it may claim CHUNKED_PIXELS_FACTOR times max_asset_pixels (2^32 cells by
        // default, 65536^2), and a file claiming 16,777,216 x 8,192 cells is refused.
        let cells = u64::from(meta.width) * u64::from(meta.height);
        let most = limits.max_pixels.saturating_mul(CHUNKED_PIXELS_FACTOR);
        if cells > most {
            return Err(bad(format!(
                "{} x {} cells, over this reader's limit of {most} for a chunked asset \
                 ({CHUNKED_PIXELS_FACTOR} x max_asset_pixels)",
                meta.width, meta.height
            )));
        }
        // The table indexes chunks: larger than them (and over 1 MiB) it is no table of a
        // raster but a table for its own sake (a million empty chunks, 54 MB, held 65 MiB of
        // the server's memory for nothing).
        let chunk_bytes = file_len - header_end;
        if t_len > chunk_bytes.max(1 << 20) {
            return Err(bad(format!(
                "a chunk table of {t_len} bytes for {chunk_bytes} bytes of chunks"
            )));
        }
        let version = u16::from_le_bytes([head[8], head[9]]);
        let table =
            ChunkTable::decode(&rest[..t_len as usize], version).map_err(|e| bad(e.to_string()))?;
        table
            .validate(&meta, (header_end, file_len), version)
            .map_err(|e| bad(e.to_string()))?;
        // Each chunk is read under the limits as its own asset; the chunk side bounds its
        // grid (a last chunk takes up to half a chunk more), so a chunk over the limits is
        // refused when the file opens.
        let side = u64::from(table.chunk + table.chunk / 2 + 2 * table.overlap);
        limits.check_pixels("a chunk", side * side)?;
        static NEXT: AtomicU64 = AtomicU64::new(0);
        Ok((
            meta,
            Chunked {
                table,
                source,
                limits: *limits,
                cache,
                key: NEXT.fetch_add(1, Ordering::Relaxed),
                header_crc: crc,
                corrupt: Default::default(),
            },
        ))
    }

    /// Chunk `index` of level `level`, decoded (from the cache, or read by range and checked);
    /// `None` for a chunk with no valid cell.
    pub fn chunk(&self, level: usize, index: usize) -> Result<Option<Arc<Asset>>, Error> {
        let entry = self
            .table
            .levels
            .get(level)
            .and_then(|l| l.chunks.get(index))
            .ok_or_else(|| Error::asset(format!("no chunk {index} in level {level}")))?;
        if entry.length == 0 {
            return Ok(None);
        }
        if let Some(e) = self.corrupt_chunks().get(&(level, index)) {
            return Err(e.clone());
        }
        let load = || -> Result<Arc<Asset>, Error> {
            let what = format!("{}: chunk {index} of level {level}", self.source.describe());
            let bytes = self
                .source
                .read(entry.offset, entry.length as usize)
                .map_err(|e| Error::unavailable(format!("{what}: {e}")))?;
            let crc = bytes
                .len()
                .checked_sub(4)
                .map(|n| u32::from_le_bytes(bytes[n..].try_into().expect("4")));
            if crc != Some(entry.crc) {
                return Err(Error::asset(format!(
                    "{what}: its checksum is not the table's (corrupt file)"
                )));
            }
            // The top level is one chunk, which coarse pixels decode discretely: whole.
            let build = if level + 1 == self.table.levels.len() {
                crate::codecs::plane::Build::Whole
            } else {
                crate::codecs::plane::Build::Lazy
            };
            let asset = self
                .cache
                .gated(|| {
                    if !self.table.is_view(level) {
                        return Asset::from_bytes_built(&bytes, &self.limits, build);
                    }
                    let mut view = Asset::coarse_view(&bytes, &self.limits, level as u32, build)?;
                    let map = &self.table.views[level - 1].maps[index];
                    let span = (view.meta.value_max - view.meta.value_min) as f32;
                    let (w, h) = (view.meta.width as usize, view.meta.height as usize);
                    view.source_error = Some(
                        crate::core::fidelity::SourceError::decode(map, w, h, span)
                            .map_err(|e| Error::asset(format!("the view's error map: {e}")))?,
                    );
                    Ok(view)
                })
                .map_err(|e| Error::asset(format!("{what}: {e}")))?;
            let [x0, y0, x1, y1] = entry.cells;
            if asset.chunked().is_some()
                || (asset.meta.width, asset.meta.height) != (x1 - x0, y1 - y0)
                || asset.codec().byte() != self.table.codec
            {
                return Err(Error::asset(format!(
                    "{what}: not the {}x{} raster of the table's codec",
                    x1 - x0,
                    y1 - y0
                )));
            }
            Ok(Arc::new(asset))
        };
        let key = (self.key, level as u8, index as u32);
        #[cfg(feature = "moka")]
        let loaded = self
            .cache
            .cache
            .try_get_with(key, load)
            .map_err(|e| (*e).clone());
        #[cfg(not(feature = "moka"))]
        let loaded = self.cache.cache.get_or_insert_with(&key, load);
        loaded.map(Some).map_err(|e| {
            if matches!(e, Error::Asset { .. }) {
                self.corrupt_chunks().insert((level, index), e.clone());
            }
            e
        })
    }

    fn corrupt_chunks(
        &self,
    ) -> std::sync::MutexGuard<'_, std::collections::HashMap<(usize, usize), Error>> {
        // A map of finished entries: a panic elsewhere cannot leave one half-written.
        self.corrupt.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Decodes chunks into the cache ahead of requests, coarsest level first (a level's chunks
    /// serve a zoom's tiles, and coarser levels are smaller), while the cache holds under
    /// `budget` bytes and the next chunk, weighed as the last one, still fits: a server's
    /// first tiles then wait on no chunk (a 1024^2 chunk takes about 100 ms of a core to
    /// decode). Chunks that fail are left for requests to report. Returns the chunks now
    /// cached and their bytes.
    pub fn prefetch(&self, budget: u64) -> (usize, u64) {
        let (mut count, mut bytes, mut last) = (0usize, 0u64, 0u64);
        for (level, l) in self.table.levels.iter().enumerate().rev() {
            for index in 0..l.chunks.len() {
                if self.cache.weighted_bytes() + last > budget {
                    return (count, bytes);
                }
                if let Ok(Some(a)) = self.chunk(level, index) {
                    last = resident_bytes(&a);
                    count += 1;
                    bytes += last;
                }
            }
        }
        (count, bytes)
    }

    /// Checks every chunk's bytes against its checksum, reading them all and decoding none:
    /// how an upload is validated, so that a file corrupt in any chunk is refused whole rather
    /// than stored and served until a tile reads the bad chunk (about 1 GB/s of CRC-32).
    pub fn verify(&self) -> Result<(), Error> {
        // A view level's bytes are level 0's, checked there.
        let coded = |&(level, _): &(usize, &Level)| !self.table.is_view(level);
        for (level, l) in self.table.levels.iter().enumerate().filter(coded) {
            for (index, entry) in l.chunks.iter().enumerate().filter(|(_, e)| e.length > 0) {
                let what = format!("{}: chunk {index} of level {level}", self.source.describe());
                let bytes = self
                    .source
                    .read(entry.offset, entry.length as usize)
                    .map_err(|e| Error::asset(format!("{what}: {e}")))?;
                let body = bytes.len().saturating_sub(4);
                if bytes.len() < 4
                    || file_crc(&bytes) != entry.crc
                    || crc32fast::hash(&bytes[..body]) != entry.crc
                {
                    return Err(Error::asset(format!(
                        "{what}: its checksum does not match (corrupt file)"
                    )));
                }
                self.check_chunk_header(&bytes, entry)
                    .map_err(|e| Error::asset(format!("{what}: {e}")))?;
            }
        }
        Ok(())
    }

    /// Whether a chunk's own header is what the table says of it, read from its first bytes
    /// and metadata without decoding its planes: an asset, not itself chunked, of the
    /// table's codec and of the cells its entry covers. A checksum alone passed a chunk
    /// replaced by another valid asset, a chunked file as a chunk, and tables that point
    /// elsewhere: stored, then answered 503 at every request that touched them (what
    /// [`Chunked::chunk`] finds at serving time, found at upload).
    fn check_chunk_header(&self, bytes: &[u8], entry: &ChunkEntry) -> Result<(), FormatError> {
        if is_chunked(bytes) {
            return Err(FormatError::header("a chunked file as a chunk"));
        }
        if bytes.len() < 16 || &bytes[..8] != MAGIC {
            return Err(FormatError::header("not an asset"));
        }
        if bytes[11] != self.table.codec {
            return Err(FormatError::header(format!(
                "codec {} where the table says {}",
                bytes[11], self.table.codec
            )));
        }
        let m_len = u32::from_le_bytes(bytes[12..16].try_into().expect("4")) as usize;
        let meta: AssetMeta = bytes
            .get(16..16usize.saturating_add(m_len))
            .ok_or(FormatError::header("truncated metadata"))
            .and_then(|m| {
                fractile_proto::decode(m).map_err(|_| FormatError::header("unreadable metadata"))
            })?;
        let [x0, y0, x1, y1] = entry.cells;
        if (meta.width, meta.height) != (x1 - x0, y1 - y0) {
            return Err(FormatError::header(format!(
                "{} x {} cells where the table says {} x {}",
                meta.width,
                meta.height,
                x1 - x0,
                y1 - y0
            )));
        }
        Ok(())
    }

    /// The container's length in bytes.
    pub fn len(&self) -> u64 {
        self.source.len()
    }

    /// Whether the container is empty (never, once opened).
    pub fn is_empty(&self) -> bool {
        self.source.is_empty()
    }

    /// `len` bytes of the container from `offset`, read where it lies (what a server hands a
    /// client that decodes itself, by range).
    pub fn read(&self, offset: u64, len: usize) -> Result<Vec<u8>, Error> {
        self.source.read(offset, len).map_err(|e| {
            Error::unavailable(format!("{}: {e}", self.source.describe())).caused_by(e)
        })
    }

    /// The container's bytes, whole (for `Asset::to_bytes`).
    pub fn bytes(&self) -> Result<Vec<u8>, Error> {
        self.source
            .read(0, self.source.len() as usize)
            .map_err(|e| Error::asset(format!("{}: {e}", self.source.describe())))
    }
}

impl Asset {
    /// The coarse view at `depth` of a chunk's file (a single-plane projected height field):
    /// its multiresolution's coarse samples ([`crate::codecs::projected::decode_coarse`]) as
    /// an asset of `ceil(w / 2^depth) x ceil(h / 2^depth)` cells, its mask valid where any of
    /// a cell's `2^depth x 2^depth` source cells is (as the box means of overviews are) for a
    /// lifted plane, where the cell on the lattice is for a pyramid (whose samples there are
    /// the source's, and whose nodata cells are coded to no bound). No
    /// source-error map: a chunked file keeps the view's in its table.
    pub(crate) fn coarse_view(
        bytes: &[u8],
        limits: &AssetLimits,
        depth: u32,
        build: Build,
    ) -> Result<Asset, Error> {
        let (codec, meta, payload, _) = container(bytes)?;
        if codec != Codec::Projected.byte() || meta.kind != AssetKind::HeightField {
            return Err(Error::asset(
                "a coarse view of a chunk that is no projected height field",
            ));
        }
        let p: Payload<ProjectedHeader> =
            fractile_proto::decode(payload).map_err(|e| Error::asset(e.to_string()))?;
        let [(header, stream)] = <[_; 1]>::try_from(p.planes)
            .map_err(|_| Error::asset("a coarse view of a chunk of several planes"))?;
        header.validate().map_err(|e| Error::asset(e.to_string()))?;
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
                let decimated = header.order.lifting().is_none();
                let valid = super::mask::coarse_valid(m.valid(), [w, h], 1 << depth, decimated);
                Mask::new(cw, ch, valid)
            });
        let operator = match build {
            Build::Whole => ProjectedOperator::new(&view, &grid),
            Build::Lazy => ProjectedOperator::lazy(&view, grid),
        }
        .map_err(|e| Error::asset(e.to_string()))?;
        let asset = Asset {
            meta: AssetMeta {
                width: cw as u32,
                height: ch as u32,
                ..meta
            },
            body: Body::Planes {
                planes: vec![Plane {
                    coding: Coding::Projected {
                        header: view,
                        stream: Vec::new(),
                    },
                    operator: PlaneOperator::Projected(operator),
                }],
                mask,
            },
            source_error: None,
        };
        asset.check()?;
        Ok(asset)
    }
}
