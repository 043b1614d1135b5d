//! Chunked assets (format version 7; 6 still read): a raster cut into square chunks, each coded
//! on its own as a whole asset file of version 5, behind a table that says where each chunk
//! lies in the file, so that a reader fetches and decodes one chunk by byte range without
//! reading the rest (`docs/asset-format.md`). Coarser levels (overviews: the raster at 2, 4,
//! ... source cells a cell) let a coarse tile of a huge raster decode a few chunks of a coarse
//! level instead of the whole raster.
//!
//! The first [`VIEW_DEPTH`] overview levels are not coded in format 7 where a height field's
//! chunks are lifted projected planes (rate mode): a level-l chunk is the source chunk's own
//! multiresolution read to depth l, its coarse band (the *view*, `Asset::coarse_view`),
//! decoded from the coarse part of the same stream. Coded beside the source, as format 6 did,
//! they took 19-26% of a file's bytes and cost it 1-2 dB against JPEG 2000 at the same bytes
//! (docs/benchmarks.md, "What the overviews cost"); the coded overviews that remain, from level
//! 3 on and the top level, are 2-6% of the cells. For the views' lattices to be the levels'
//! own, chunks start on multiples of `2^VIEW_DEPTH` ([`VIEW_OVERLAP`]), and a view's sample
//! `k` stands `1/2 - 2^-(l+1)` of a level cell before its box cell's centre (the low-pass sits
//! on a source cell, the box mean between cells): the reader places it there
//! ([`ChunkTable::view_shift`]). Each view's source-error map, measured at encode time against
//! the same analysis of the source (the low-pass it stands for), is kept in the table.
//!
//! Each chunk codes `OVERLAP` cells beyond its own on every side (clamped at the raster's
//! edges): a point is answered by the chunk that owns it, and every point a chunk owns lies
//! between the centres of cells that chunk coded, so its bilinear neighbourhood never crosses
//! into another chunk. Two neighbours then differ at their shared edge by at most the sum of
//! their coding errors: no seam beyond the chunks' own error.
//!
//! Decoded chunks are kept in a [`ChunkCache`] bounded in bytes, shared by every chunked asset
//! of a process (a server sizes it with `chunk_cache_mib`).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use fractile_proto::AssetMeta;
use serde::{Deserialize, Serialize};

use super::asset::{Asset, AssetLimits, MAGIC};
use crate::Error;

/// The format version of a chunked container. Single-operator files stay version 5 (their
/// layout did not change), so readers of version 5 keep reading what they read.
pub const CHUNKED_VERSION: u16 = 7;

/// The oldest chunked version read (6: every overview level coded, no views).
pub const OLDEST_CHUNKED_VERSION: u16 = 6;

/// The most overview levels that are views of the source chunks (see the module's doc): level
/// `l` of a view reads the source chunk's stream to depth `l`, whose coarse part is about
/// `4^-l` of it; deeper views would read and decode a chunk whole for a few of its cells.
pub const VIEW_DEPTH: u32 = 2;

/// The codec byte of a chunked container (its chunks name their own codec).
pub const CHUNKED_CODEC: u8 = 7;

/// Cells each chunk codes beyond its own on every side (see the module's doc), in a file whose
/// overviews are all coded (and in every file of format 6).
pub const OVERLAP: u32 = 1;

/// The overlap of a file with views: `2^VIEW_DEPTH`, so that every chunk starts on the lattice
/// of every view level. (Files without views keep 1: 0.6% fewer cells coded at chunks of
/// 1024.)
pub const VIEW_OVERLAP: u32 = 1 << VIEW_DEPTH;

/// The overlap of a file with `views` view levels.
pub fn overlap_for(views: usize) -> u32 {
    if views > 0 { VIEW_OVERLAP } else { OVERLAP }
}

/// How many times `max_asset_pixels` a chunked asset may claim: its cells are decoded a chunk
/// at a time, never whole (see [`Chunked::open`]).
pub const CHUNKED_PIXELS_FACTOR: u64 = 16;

/// Most chunks a file may list, over all its levels: 2^20 chunks of 1024^2 cells is a
/// terapixel, and the table of that many is 64 MiB.
pub const MAX_CHUNKS: usize = 1 << 20;

/// Smallest and largest chunk sides (powers of two).
pub const CHUNK_SIDES: (u32, u32) = (64, 1 << 14);

/// One chunk of a level: where its file lies and what it covers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChunkEntry {
    /// Offset of the chunk's file from the container's start.
    pub offset: u64,
    /// Length of the chunk's file; 0 for a chunk with no valid cell (nodata everywhere).
    pub length: u64,
    /// The cells it codes, `[x0, y0, x1, y1)` in its level's cells (its own and the overlap).
    pub cells: [u32; 4],
    /// Smallest and largest value of its valid cells (source units).
    pub value_range: [f64; 2],
    /// The chunk file's own CRC-32 (its last four bytes), checked against the bytes read.
    pub crc: u32,
}

/// One level of the pyramid: level `l` has cells of `2^l` source cells.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Level {
    /// Cells a row: `ceil(width / 2^l)`.
    pub width: u32,
    /// Rows: `ceil(height / 2^l)`.
    pub height: u32,
    /// The chunks in row order, `ceil(width / chunk)` a row.
    pub chunks: Vec<ChunkEntry>,
}

/// An overview level that is a view of the source chunks (format 7): per chunk, its view's
/// source-error map ([`crate::core::fidelity::SourceError`]'s encoding; empty for a chunk
/// with no valid cell).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewLevel {
    /// The maps, in the level's chunk order (level 0's).
    pub maps: Vec<Vec<u8>>,
}

/// The table of a chunked container of version 6.
#[derive(Deserialize)]
struct ChunkTableV6 {
    chunk: u32,
    overlap: u32,
    codec: u8,
    max_contrast: f32,
    seed_bound: f32,
    smallest_source_error: Option<f32>,
    levels: Vec<Level>,
}

/// The table of a chunked container.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChunkTable {
    /// Side of a chunk in cells (a power of two), the overlap aside.
    pub chunk: u32,
    /// Cells each chunk codes beyond its own on every side.
    pub overlap: u32,
    /// The codec byte of the chunks (one codec for the whole asset).
    pub codec: u8,
    /// Largest |s| over every chunk.
    pub max_contrast: f32,
    /// Largest a-priori bound before any step over every chunk (source units):
    /// `bound_after(n)` is at most `max_contrast^n` times it.
    pub seed_bound: f32,
    /// Smallest source error of any chunk's map (source units), for the default tolerance.
    pub smallest_source_error: Option<f32>,
    /// Level 0 (the source's cells) first, then each overview. A view level's entries are
    /// level 0's (the same offsets, lengths and CRCs), with its own cells.
    pub levels: Vec<Level>,
    /// The overview levels 1 to `views.len()` that are views (format 7; none in format 6).
    pub views: Vec<ViewLevel>,
}

impl ChunkTable {
    /// Whether `level` is a view of the source chunks (see the module's doc).
    pub fn is_view(&self, level: usize) -> bool {
        level >= 1 && level <= self.views.len()
    }

    /// How many overview levels of a file of `levels` levels are views: up to [`VIEW_DEPTH`],
    /// never the top level (one chunk, decoded discretely for the coarsest pixels).
    pub fn view_levels(levels: usize) -> usize {
        (VIEW_DEPTH as usize).min(levels.saturating_sub(2))
    }

    /// The cells of level `level`'s view of a source chunk coding `cells`.
    pub fn view_cells(cells: [u32; 4], level: usize) -> [u32; 4] {
        let up = |v: u32| v.div_ceil(1 << level);
        [
            cells[0] >> level,
            cells[1] >> level,
            up(cells[2]),
            up(cells[3]),
        ]
    }

    /// Where a view's samples lie, in level cells before its cells' centres (see the
    /// module's doc); 0 for a coded level.
    pub fn view_shift(&self, level: usize) -> f64 {
        if self.is_view(level) {
            0.5 - 0.5f64.powi(level as i32 + 1)
        } else {
            0.0
        }
    }

    /// Reads a table of container version `version`.
    pub(crate) fn decode(bytes: &[u8], version: u16) -> Result<ChunkTable, String> {
        if version == CHUNKED_VERSION {
            return fractile_proto::decode(bytes).map_err(|e| e.to_string());
        }
        let t: ChunkTableV6 = fractile_proto::decode(bytes).map_err(|e| e.to_string())?;
        Ok(ChunkTable {
            chunk: t.chunk,
            overlap: t.overlap,
            codec: t.codec,
            max_contrast: t.max_contrast,
            seed_bound: t.seed_bound,
            smallest_source_error: t.smallest_source_error,
            levels: t.levels,
            views: Vec::new(),
        })
    }

    /// Chunks a row and rows of chunks of a level of `width x height` cells: the last chunk of
    /// a row or column takes the remainder (so it is between half a chunk and a chunk and a
    /// half): a sliver of a few cells would pay a chunk's fixed bytes for nothing, and under a
    /// rate would be coded far worse than its neighbours.
    pub fn grid(&self, width: u32, height: u32) -> (u32, u32) {
        let count = |n: u32| (n.saturating_add(self.chunk / 2) / self.chunk).max(1);
        (count(width), count(height))
    }

    /// The cells chunk `(cx, cy)` of a level of `width x height` codes: its own and the
    /// overlap, clamped to the level.
    pub fn coded_cells(&self, width: u32, height: u32, cx: u32, cy: u32) -> [u32; 4] {
        let (c, o) = (self.chunk, self.overlap);
        let (nx, ny) = self.grid(width, height);
        let end = |i: u32, n: u32, size: u32| {
            if i + 1 == n {
                size
            } else {
                ((i + 1) * c + o).min(size)
            }
        };
        [
            (cx * c).saturating_sub(o),
            (cy * c).saturating_sub(o),
            end(cx, nx, width),
            end(cy, ny, height),
        ]
    }

    /// The levels' sizes for a source of `width x height` and chunks of `chunk`: halved
    /// (rounding up) until a level fits in one chunk.
    pub fn level_sizes(width: u32, height: u32, chunk: u32) -> Vec<(u32, u32)> {
        let mut sizes = vec![(width, height)];
        let one = |n: u32| n < chunk + chunk / 2;
        while let Some(&(w, h)) = sizes.last() {
            if (one(w) && one(h)) || sizes.len() >= 32 {
                break;
            }
            sizes.push((w.div_ceil(2), h.div_ceil(2)));
        }
        sizes
    }

    /// Checks the table against the metadata and the file's length: every size and range is
    /// the one the layout implies, every chunk lies in the file after the header.
    fn validate(&self, meta: &AssetMeta, header_end: u64, file_len: u64) -> Result<(), String> {
        let (lo, hi) = CHUNK_SIDES;
        if !self.chunk.is_power_of_two() || self.chunk < lo || self.chunk > hi {
            return Err(format!(
                "chunk side {} is not a power of two in {lo}..={hi}",
                self.chunk
            ));
        }
        if self.overlap > self.chunk / 4 {
            return Err(format!("overlap {} is over a quarter chunk", self.overlap));
        }
        if !(1..=6).contains(&self.codec) || self.codec == 4 || self.codec == 5 {
            return Err(format!("chunks of codec {} are not rasters", self.codec));
        }
        if !(self.max_contrast.is_finite() && self.seed_bound.is_finite()) {
            return Err("non-finite contrast or bound".into());
        }
        let sizes = ChunkTable::level_sizes(meta.width, meta.height, self.chunk);
        if sizes.len() != self.levels.len() {
            return Err(format!(
                "{} levels where a {}x{} raster in chunks of {} has {}",
                self.levels.len(),
                meta.width,
                meta.height,
                self.chunk,
                sizes.len()
            ));
        }
        let total: usize = self.levels.iter().map(|l| l.chunks.len()).sum();
        if total > MAX_CHUNKS {
            return Err(format!("{total} chunks, over the limit of {MAX_CHUNKS}"));
        }
        if self.views.len() > ChunkTable::view_levels(self.levels.len())
            || (!self.views.is_empty() && !self.overlap.is_multiple_of(1 << self.views.len()))
        {
            return Err(format!(
                "{} view levels of {} levels with an overlap of {}",
                self.views.len(),
                self.levels.len(),
                self.overlap
            ));
        }
        for (l, (level, &(w, h))) in self.levels.iter().zip(&sizes).enumerate() {
            let (nx, ny) = if self.is_view(l) {
                self.grid(meta.width, meta.height)
            } else {
                self.grid(w, h)
            };
            if (level.width, level.height) != (w, h)
                || level.chunks.len() != (nx as usize) * (ny as usize)
            {
                return Err(format!("level {l} does not have the layout's size"));
            }
            if self.is_view(l) && self.views[l - 1].maps.len() != level.chunks.len() {
                return Err(format!("level {l} has not a map a chunk"));
            }
            for (i, e) in level.chunks.iter().enumerate() {
                let (cx, cy) = (i as u32 % nx, i as u32 / nx);
                let cells = if self.is_view(l) {
                    let source = &self.levels[0].chunks[i];
                    if (e.offset, e.length, e.crc) != (source.offset, source.length, source.crc) {
                        return Err(format!("chunk {i} of view level {l} is not level 0's"));
                    }
                    ChunkTable::view_cells(source.cells, l)
                } else {
                    self.coded_cells(w, h, cx, cy)
                };
                if e.cells != cells {
                    return Err(format!("chunk {i} of level {l} claims other cells"));
                }
                let end = e.offset.checked_add(e.length);
                if e.length > 0 && (e.offset < header_end || end.is_none_or(|e| e > file_len)) {
                    return Err(format!("chunk {i} of level {l} lies outside the file"));
                }
                if e.length > 0
                    && e.value_range[0]
                        .partial_cmp(&e.value_range[1])
                        .is_none_or(|o| o.is_gt())
                {
                    return Err(format!("chunk {i} of level {l} has a bad value range"));
                }
            }
        }
        Ok(())
    }
}

/// Where a chunked container's bytes come from: read by range, so that only the chunks a
/// request touches are read (a file now; object storage next).
pub trait ChunkSource: Send + Sync {
    /// Length of the container in bytes.
    fn len(&self) -> u64;
    /// Whether it is empty.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// `len` bytes from `offset`.
    fn read(&self, offset: u64, len: usize) -> std::io::Result<Vec<u8>>;
    /// Where the bytes are, for messages.
    fn describe(&self) -> String;
}

/// A container held in memory (an upload, a file read whole).
pub struct InMemory(pub Arc<[u8]>);

impl ChunkSource for InMemory {
    fn len(&self) -> u64 {
        self.0.len() as u64
    }

    fn read(&self, offset: u64, len: usize) -> std::io::Result<Vec<u8>> {
        usize::try_from(offset)
            .ok()
            .and_then(|o| self.0.get(o..o.checked_add(len)?))
            .map(<[u8]>::to_vec)
            .ok_or_else(|| std::io::Error::from(std::io::ErrorKind::UnexpectedEof))
    }

    fn describe(&self) -> String {
        "an asset in memory".into()
    }
}

/// A container in a file, read by positioned reads (no shared cursor, so concurrent chunk
/// reads need no lock).
pub struct FileSource {
    file: std::fs::File,
    len: u64,
    path: PathBuf,
}

impl FileSource {
    /// Opens `path` for reading by range.
    pub fn open(path: &Path) -> std::io::Result<FileSource> {
        let file = std::fs::File::open(path)?;
        let len = file.metadata()?.len();
        Ok(FileSource {
            file,
            len,
            path: path.to_path_buf(),
        })
    }
}

impl ChunkSource for FileSource {
    fn len(&self) -> u64 {
        self.len
    }

    fn read(&self, offset: u64, len: usize) -> std::io::Result<Vec<u8>> {
        use std::os::unix::fs::FileExt;
        let mut buf = vec![0u8; len];
        self.file.read_exact_at(&mut buf, offset)?;
        Ok(buf)
    }

    fn describe(&self) -> String {
        self.path.display().to_string()
    }
}

/// Decoded chunks of every chunked asset of a process, bounded in bytes (their estimated
/// resident size: operators and masks), least recently used out first. moka's cache also makes
/// concurrent requests for one chunk decode it once.
#[derive(Clone)]
pub struct ChunkCache {
    cache: moka::sync::Cache<(u64, u8, u32), Arc<Asset>>,
    /// Chunks being decoded now, and the most at once.
    decoding: Arc<(std::sync::Mutex<usize>, std::sync::Condvar)>,
    most_decoding: usize,
}

impl ChunkCache {
    /// A cache of at most `bytes` of decoded chunks.
    pub fn new(bytes: u64) -> ChunkCache {
        ChunkCache {
            cache: moka::sync::Cache::builder()
                .max_capacity(bytes)
                .weigher(|_, a: &Arc<Asset>| resident_bytes(a).min(u64::from(u32::MAX)) as u32)
                .build(),
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
        self.cache.policy().max_capacity().unwrap_or(u64::MAX)
    }

    /// Estimated bytes held by the cache now.
    pub fn weighted_bytes(&self) -> u64 {
        self.cache.run_pending_tasks();
        self.cache.weighted_size()
    }
}

/// Estimated resident bytes of a decoded chunk: its operators' (projected ones count theirs;
/// the quadtree's measured 13 B a sample on the 9.3 Mpx mosaic, counted 16), its mask and its
/// coded streams.
fn resident_bytes(a: &Asset) -> u64 {
    use super::asset::Coding;
    let cells = u64::from(a.meta.width) * u64::from(a.meta.height);
    let operators: u64 = a
        .planes
        .iter()
        .map(|p| match &p.operator {
            super::asset::PlaneOperator::Projected(op) => op.resident_bytes(),
            _ => cells * 16,
        })
        .sum();
    let streams: usize = a
        .planes
        .iter()
        .map(|p| match &p.coding {
            Coding::Quadtree { stream, .. }
            | Coding::Fis { stream, .. }
            | Coding::Psa { stream, .. }
            | Coding::Projected { stream, .. } => stream.len(),
        })
        .sum();
    operators + a.mask.as_ref().map_or(0, |_| cells) + streams as u64 + 4096
}

/// A chunked container opened for reading: its table, its bytes by range, and the cache its
/// decoded chunks go to.
pub struct Chunked {
    /// The chunk table.
    pub table: ChunkTable,
    source: Box<dyn ChunkSource>,
    limits: AssetLimits,
    cache: ChunkCache,
    /// This container's key in the shared cache.
    key: u64,
    /// CRC-32 of the header (magic to table): names this version of the asset.
    pub header_crc: u32,
    /// Chunks found corrupt, and why: a corrupt chunk stays corrupt, so it is decoded once and
    /// its error answered again after (the cache keeps only what loaded).
    corrupt: std::sync::Mutex<std::collections::HashMap<(usize, usize), Error>>,
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

/// Whether `bytes` (at least the first 12 of a file) start a chunked container.
pub fn is_chunked(bytes: &[u8]) -> bool {
    bytes.len() >= 12
        && &bytes[..8] == MAGIC
        && (OLDEST_CHUNKED_VERSION..=CHUNKED_VERSION)
            .contains(&u16::from_le_bytes([bytes[8], bytes[9]]))
}

/// The bytes of a chunked container: the header (magic, version, kind, codec, metadata, table,
/// CRC) then the chunk files in the order given. `chunks[l][i]` is level `l`'s chunk `i`'s
/// file, empty for a chunk with no valid cell; the table's offsets, lengths and CRCs are
/// filled in here.
pub fn assemble(meta: &AssetMeta, mut table: ChunkTable, chunks: &[Vec<Vec<u8>>]) -> Vec<u8> {
    for (level, files) in table.levels.iter_mut().zip(chunks) {
        for (entry, file) in level.chunks.iter_mut().zip(files) {
            entry.length = file.len() as u64;
            entry.crc = file_crc(file);
        }
    }
    let mut out = header(meta, &mut table);
    for file in chunks.iter().flatten() {
        out.extend_from_slice(file);
    }
    out
}

/// The CRC a chunk's file ends with (0 for an empty file): what its table entry repeats.
pub fn file_crc(file: &[u8]) -> u32 {
    file.len()
        .checked_sub(4)
        .map_or(0, |n| u32::from_le_bytes(file[n..].try_into().expect("4")))
}

/// The header of a chunked container (magic, version, kind, codec, metadata, table, CRC) whose
/// chunk files follow it in the table's order, level by level: every entry's offset is set
/// here from the lengths before it (its length and CRC are the caller's).
pub fn header(meta: &AssetMeta, table: &mut ChunkTable) -> Vec<u8> {
    let meta_bytes = fractile_proto::encode(meta);
    // The table's size does not depend on the offsets' values (fixed-width integers).
    let table_len = fractile_proto::encode(&*table).len();
    let header_len = 8 + 2 + 2 + 4 + meta_bytes.len() + 4 + table_len + 4;
    let mut offset = header_len as u64;
    let views = table.views.len();
    for (l, level) in table.levels.iter_mut().enumerate() {
        if l >= 1 && l <= views {
            continue;
        }
        for entry in &mut level.chunks {
            entry.offset = offset;
            offset += entry.length;
        }
    }
    // A view level's chunks are level 0's bytes.
    let (source, overviews) = table.levels.split_at_mut(1);
    for level in overviews.iter_mut().take(views) {
        for (entry, s) in level.chunks.iter_mut().zip(&source[0].chunks) {
            (entry.offset, entry.length, entry.crc) = (s.offset, s.length, s.crc);
        }
    }
    let table_bytes = fractile_proto::encode(&*table);
    debug_assert_eq!(table_bytes.len(), table_len);
    let mut out = Vec::with_capacity(header_len);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&CHUNKED_VERSION.to_le_bytes());
    out.push(super::asset::kind_byte(meta.kind));
    out.push(CHUNKED_CODEC);
    out.extend_from_slice(&(meta_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(&meta_bytes);
    out.extend_from_slice(&(table_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(&table_bytes);
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

impl Chunked {
    /// Reads and checks a container's header from `source` (a few kilobytes: nothing of the
    /// chunks is read). Returns the metadata and the opened container.
    pub fn open(
        source: Box<dyn ChunkSource>,
        limits: &AssetLimits,
        cache: ChunkCache,
    ) -> Result<(AssetMeta, Chunked), Error> {
        let bad = |m: String| Error::Asset(format!("{}: {m}", source.describe()));
        let io = |e: std::io::Error| Error::Asset(format!("{}: {e}", source.describe()));
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
        if super::asset::kind_byte(meta.kind) != head[10] {
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
        let table = ChunkTable::decode(&rest[..t_len as usize], version).map_err(bad)?;
        table.validate(&meta, header_end, file_len).map_err(bad)?;
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
            .ok_or_else(|| Error::Asset(format!("no chunk {index} in level {level}")))?;
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
                .map_err(|e| Error::Unavailable(format!("{what}: {e}")))?;
            let crc = bytes
                .len()
                .checked_sub(4)
                .map(|n| u32::from_le_bytes(bytes[n..].try_into().expect("4")));
            if crc != Some(entry.crc) {
                return Err(Error::Asset(format!(
                    "{what}: its checksum is not the table's (corrupt file)"
                )));
            }
            // The top level is one chunk, which coarse pixels decode discretely: whole.
            let build = if level + 1 == self.table.levels.len() {
                super::asset::Build::Whole
            } else {
                super::asset::Build::Lazy
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
                            .map_err(|e| Error::Asset(format!("the view's error map: {e}")))?,
                    );
                    Ok(view)
                })
                .map_err(|e| Error::Asset(format!("{what}: {e}")))?;
            let [x0, y0, x1, y1] = entry.cells;
            if asset.chunks.is_some()
                || (asset.meta.width, asset.meta.height) != (x1 - x0, y1 - y0)
                || asset.codec() as u8 != self.table.codec
            {
                return Err(Error::Asset(format!(
                    "{what}: not the {}x{} raster of the table's codec",
                    x1 - x0,
                    y1 - y0
                )));
            }
            Ok(Arc::new(asset))
        };
        self.cache
            .cache
            .try_get_with((self.key, level as u8, index as u32), load)
            .map(Some)
            .map_err(|e| {
                let e = (*e).clone();
                if matches!(e, Error::Asset(_)) {
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
                    .map_err(|e| Error::Asset(format!("{what}: {e}")))?;
                let body = bytes.len().saturating_sub(4);
                if bytes.len() < 4
                    || file_crc(&bytes) != entry.crc
                    || crc32fast::hash(&bytes[..body]) != entry.crc
                {
                    return Err(Error::Asset(format!(
                        "{what}: its checksum does not match (corrupt file)"
                    )));
                }
                self.check_chunk_header(&bytes, entry)
                    .map_err(|e| Error::Asset(format!("{what}: {e}")))?;
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
    fn check_chunk_header(&self, bytes: &[u8], entry: &ChunkEntry) -> Result<(), String> {
        if is_chunked(bytes) {
            return Err("a chunked file as a chunk".into());
        }
        if bytes.len() < 16 || &bytes[..8] != MAGIC {
            return Err("not an asset".into());
        }
        if bytes[11] != self.table.codec {
            return Err(format!(
                "codec {} where the table says {}",
                bytes[11], self.table.codec
            ));
        }
        let m_len = u32::from_le_bytes(bytes[12..16].try_into().expect("4")) as usize;
        let meta: AssetMeta = bytes
            .get(16..16usize.saturating_add(m_len))
            .ok_or("truncated metadata")
            .and_then(|m| fractile_proto::decode(m).map_err(|_| "unreadable metadata"))?;
        let [x0, y0, x1, y1] = entry.cells;
        if (meta.width, meta.height) != (x1 - x0, y1 - y0) {
            return Err(format!(
                "{} x {} cells where the table says {} x {}",
                meta.width,
                meta.height,
                x1 - x0,
                y1 - y0
            ));
        }
        Ok(())
    }

    /// The container's bytes, whole (for `Asset::to_bytes`).
    pub fn bytes(&self) -> Result<Vec<u8>, Error> {
        self.source
            .read(0, self.source.len() as usize)
            .map_err(|e| Error::Asset(format!("{}: {e}", self.source.describe())))
    }
}
