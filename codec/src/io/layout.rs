//! The layout of a chunked file (`docs/asset-format.md`), below the assets it holds: the magic
//! and the versions, the chunk table and its checks, the sources a file is read from by range,
//! and a file's header and assembly. What reads a chunk into an asset is `chunked`.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use fractile_proto::AssetMeta;
use serde::{Deserialize, Serialize};

use crate::core::format::FormatError;

pub use super::frame::MAGIC;
use super::frame::kind_byte;

/// The format version of a chunked container. Single-operator files stay version 5 (their
/// layout did not change), so readers of version 5 keep reading what they read. Version 8: a
/// file with views has a coded level above them ([`ChunkTable::level_sizes`]); 7 is read.
/// Version 9 (the number files that are not chunked take too): the chunks are files of
/// version 9, whose projected details are coded with two-rate contexts; the table is 8's.
/// Version 10: chunks of version 10 (lifted coefficients in two-rate contexts); 9 is read.
pub const CHUNKED_VERSION: u16 = super::frame::FORMAT_VERSION;

/// The first chunked version whose files with views keep a coded level above them.
pub const CODED_TOP_VERSION: u16 = 8;

/// The oldest chunked version read (6: every overview level coded, no views).
pub const OLDEST_CHUNKED_VERSION: u16 = 6;

/// The most overview levels that are views of the source chunks (see the module's doc): level
/// `l` of a view reads the source chunk's stream to depth `l`, whose coarse part is about
/// `4^-l` of it; deeper views would read and decode a chunk whole for a few of its cells.
pub const VIEW_DEPTH: u32 = 2;

/// The codec byte of a chunked container (its chunks name their own codec).
pub const CHUNKED_CODEC: u8 = crate::codecs::registry::CHUNKED_BYTE;

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
/// at a time, never whole (see [`crate::io::chunked::Chunked::open`]).
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
/// source-error map (`core::fidelity::SourceError`'s encoding; empty for a chunk
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
    pub(crate) fn decode(bytes: &[u8], version: u16) -> Result<ChunkTable, FormatError> {
        if version >= 7 {
            return fractile_proto::decode(bytes).map_err(|e| FormatError::stream(e.to_string()));
        }
        let t: ChunkTableV6 =
            fractile_proto::decode(bytes).map_err(|e| FormatError::stream(e.to_string()))?;
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
    /// (rounding up) until a level fits in one chunk. A file with views (`viewed`, format 8)
    /// that needs overviews at all keeps halving until a coded level lies above the
    /// [`VIEW_DEPTH`] views: a view reads its source chunks whole, so a raster of 4320 x 2160
    /// whose top level was a view would answer its coarsest zoom from the whole file; its
    /// third level (1/64 of the cells) is coded instead of its second (1/16), which the
    /// bounded default coded at 4 times its bound for 6% of its file (measured).
    pub fn level_sizes(width: u32, height: u32, chunk: u32, viewed: bool) -> Vec<(u32, u32)> {
        let mut sizes = vec![(width, height)];
        let one = |n: u32| n < chunk + chunk / 2;
        let least = if viewed { VIEW_DEPTH as usize + 2 } else { 1 };
        while let Some(&(w, h)) = sizes.last() {
            let fits = one(w) && one(h) && (sizes.len() == 1 || sizes.len() >= least);
            if fits || sizes.len() >= 32 {
                break;
            }
            sizes.push((w.div_ceil(2), h.div_ceil(2)));
        }
        sizes
    }

    /// Checks the table against the metadata and the file's length: every size and range is
    /// the one the layout implies, every chunk lies in the file after the header.
    pub(crate) fn validate(
        &self,
        meta: &AssetMeta,
        (header_end, file_len): (u64, u64),
        version: u16,
    ) -> Result<(), FormatError> {
        let (lo, hi) = CHUNK_SIDES;
        if !self.chunk.is_power_of_two() || self.chunk < lo || self.chunk > hi {
            return Err(FormatError::header(format!(
                "chunk side {} is not a power of two in {lo}..={hi}",
                self.chunk
            )));
        }
        if self.overlap > self.chunk / 4 {
            return Err(FormatError::header(format!(
                "overlap {} is over a quarter chunk",
                self.overlap
            )));
        }
        if !(1..=6).contains(&self.codec) || self.codec == 4 || self.codec == 5 {
            return Err(FormatError::header(format!(
                "chunks of codec {} are not rasters",
                self.codec
            )));
        }
        if !(self.max_contrast.is_finite() && self.seed_bound.is_finite()) {
            return Err(FormatError::header("non-finite contrast or bound"));
        }
        let viewed = version >= CODED_TOP_VERSION && !self.views.is_empty();
        let sizes = ChunkTable::level_sizes(meta.width, meta.height, self.chunk, viewed);
        if sizes.len() != self.levels.len() {
            return Err(FormatError::header(format!(
                "{} levels where a {}x{} raster in chunks of {} has {}",
                self.levels.len(),
                meta.width,
                meta.height,
                self.chunk,
                sizes.len()
            )));
        }
        let total: usize = self.levels.iter().map(|l| l.chunks.len()).sum();
        if total > MAX_CHUNKS {
            return Err(FormatError::header(format!(
                "{total} chunks, over the limit of {MAX_CHUNKS}"
            )));
        }
        if self.views.len() > ChunkTable::view_levels(self.levels.len())
            || (!self.views.is_empty() && !self.overlap.is_multiple_of(1 << self.views.len()))
        {
            return Err(FormatError::header(format!(
                "{} view levels of {} levels with an overlap of {}",
                self.views.len(),
                self.levels.len(),
                self.overlap
            )));
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
                return Err(FormatError::header(format!(
                    "level {l} does not have the layout's size"
                )));
            }
            if self.is_view(l) && self.views[l - 1].maps.len() != level.chunks.len() {
                return Err(FormatError::header(format!(
                    "level {l} has not a map a chunk"
                )));
            }
            for (i, e) in level.chunks.iter().enumerate() {
                let (cx, cy) = (i as u32 % nx, i as u32 / nx);
                let cells = if self.is_view(l) {
                    let source = &self.levels[0].chunks[i];
                    if (e.offset, e.length, e.crc) != (source.offset, source.length, source.crc) {
                        return Err(FormatError::header(format!(
                            "chunk {i} of view level {l} is not level 0's"
                        )));
                    }
                    ChunkTable::view_cells(source.cells, l)
                } else {
                    self.coded_cells(w, h, cx, cy)
                };
                if e.cells != cells {
                    return Err(FormatError::header(format!(
                        "chunk {i} of level {l} claims other cells"
                    )));
                }
                let end = e.offset.checked_add(e.length);
                if e.length > 0 && (e.offset < header_end || end.is_none_or(|e| e > file_len)) {
                    return Err(FormatError::header(format!(
                        "chunk {i} of level {l} lies outside the file"
                    )));
                }
                if e.length > 0
                    && e.value_range[0]
                        .partial_cmp(&e.value_range[1])
                        .is_none_or(|o| o.is_gt())
                {
                    return Err(FormatError::header(format!(
                        "chunk {i} of level {l} has a bad value range"
                    )));
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
    /// Where `len` bytes from `offset` end; `UnexpectedEof` past the end of the container.
    fn end_of(&self, offset: u64, len: usize) -> std::io::Result<u64> {
        offset
            .checked_add(len as u64)
            .filter(|&e| e <= self.len())
            .ok_or_else(|| std::io::Error::from(std::io::ErrorKind::UnexpectedEof))
    }
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
        let mut buf = vec![0u8; len];
        read_exact_at(&self.file, &mut buf, offset)?;
        Ok(buf)
    }

    fn describe(&self) -> String {
        self.path.display().to_string()
    }
}

/// Fills `buf` from `file` at `offset`: a positioned read on Unix (no shared cursor, so
/// concurrent reads need no lock), a seek and a read elsewhere (WebAssembly builds, which
/// open no files but compile this).
pub(crate) fn read_exact_at(
    file: &std::fs::File,
    buf: &mut [u8],
    offset: u64,
) -> std::io::Result<()> {
    #[cfg(unix)]
    return std::os::unix::fs::FileExt::read_exact_at(file, buf, offset);
    #[cfg(not(unix))]
    {
        use std::io::{Read, Seek};
        let mut f = file;
        f.seek(std::io::SeekFrom::Start(offset))?;
        f.read_exact(buf)
    }
}

/// Whether `bytes` (at least the first 12 of a file) start a chunked container: versions 6
/// to 8 are chunked, versions 9 on (which number both containers) with the chunked codec byte.
pub fn is_chunked(bytes: &[u8]) -> bool {
    let shared = super::frame::SHARED_SINCE_VERSION;
    bytes.len() >= 12
        && &bytes[..8] == MAGIC
        && match u16::from_le_bytes([bytes[8], bytes[9]]) {
            v if (shared..=CHUNKED_VERSION).contains(&v) => bytes[11] == CHUNKED_CODEC,
            v => (OLDEST_CHUNKED_VERSION..shared).contains(&v),
        }
}

/// The bytes of a chunked container: the header (magic, version, kind, codec, metadata, table,
/// CRC) then the chunk files in the order given. `chunks[l][i]` is level `l`'s chunk `i`'s
/// file, empty for a chunk with no valid cell; a view level's are not written (its chunks are
/// level 0's bytes, whatever is given for them). The table's offsets, lengths and CRCs are
/// filled in here.
pub fn assemble(meta: &AssetMeta, mut table: ChunkTable, chunks: &[Vec<Vec<u8>>]) -> Vec<u8> {
    let views = table.views.len();
    let coded = |l: usize| l == 0 || l > views;
    for (l, (level, files)) in table.levels.iter_mut().zip(chunks).enumerate() {
        if !coded(l) {
            continue;
        }
        for (entry, file) in level.chunks.iter_mut().zip(files) {
            entry.length = file.len() as u64;
            entry.crc = file_crc(file);
        }
    }
    let mut out = header(meta, &mut table);
    for (_, files) in chunks.iter().enumerate().filter(|(l, _)| coded(*l)) {
        for file in files {
            out.extend_from_slice(file);
        }
    }
    out
}

/// Every chunk's file of a chunked container's `bytes`, by level and index as its `table` lists
/// them (a view level's are level 0's bytes): what [`assemble`] takes back.
pub fn chunk_files(table: &ChunkTable, bytes: &[u8]) -> Vec<Vec<Vec<u8>>> {
    table
        .levels
        .iter()
        .map(|l| {
            l.chunks
                .iter()
                .map(|e| bytes[e.offset as usize..(e.offset + e.length) as usize].to_vec())
                .collect()
        })
        .collect()
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
    out.push(kind_byte(meta.kind));
    out.push(CHUNKED_CODEC);
    out.extend_from_slice(&(meta_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(&meta_bytes);
    out.extend_from_slice(&(table_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(&table_bytes);
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}
