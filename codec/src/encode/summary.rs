//! What a chunked file keeps of each chunk's encode ([`ChunkRecord`]), and the file's table,
//! metadata and errors summarised from the records in table order.

use super::encoded::Encoded;
use super::views::level_zero_views;
use crate::Error;
use crate::core::metrics::Errors;
use crate::io::chunked::{self, ChunkEntry, ChunkTable, overlap_for};
use serde::{Deserialize, Serialize};

/// What the file keeps of one chunk's encode: the figures of its table entry and of the
/// file's metadata (its bytes go to the spill).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub(super) struct ChunkRecord {
    pub(super) level: u32,
    pub(super) index: u32,
    pub(super) length: u64,
    pub(super) crc: u32,
    pub(super) codec: u8,
    pub(super) max_contrast: f32,
    pub(super) seed_bound: f32,
    pub(super) smallest_source_error: Option<f32>,
    pub(super) meta: fractile_proto::AssetMeta,
    /// A source chunk's views' source-error maps (levels 1, 2, ...; none where the overviews
    /// are coded, see `io::chunked`).
    pub(super) views: Vec<Vec<u8>>,
    /// RMSE, MAE and largest error over its coded cells, and their count.
    pub(super) errors: [f64; 3],
    pub(super) samples: u64,
    pub(super) transforms: u64,
}

/// A chunk coded: its file and its record.
pub(super) struct Coded {
    pub(super) bytes: Vec<u8>,
    pub(super) record: ChunkRecord,
}

impl Coded {
    /// The file of a chunk's encode, with no encode time in its metadata: an encode of one
    /// input is then the same bytes however it ran (split in parts or not, on any machine).
    /// The decoded asset an encode returns (a projected one holds 48 bytes a cell) is
    /// dropped here, so that memory holds the chunks in flight, not every chunk coded.
    /// Nor does a chunk's file name its encoder (format 9): the file's header does, and the
    /// 80-odd bytes a chunk were 3% of a file of nine chunks at a high ratio.
    pub(super) fn of(enc: Encoded, level: usize, index: u32, views: Vec<Vec<u8>>) -> Coded {
        let mut a = enc.asset;
        a.meta.stats.seconds = 0.0;
        let encoder = std::mem::take(&mut a.meta.encoder);
        let bytes = a.to_bytes();
        a.meta.encoder = encoder;
        let e = enc.errors;
        Coded {
            record: ChunkRecord {
                level: level as u32,
                index,
                length: bytes.len() as u64,
                crc: chunked::file_crc(&bytes),
                codec: a.codec().byte(),
                max_contrast: a.max_contrast(),
                seed_bound: a.bound_after(0),
                smallest_source_error: a.source_error.as_ref().and_then(|m| m.smallest()),
                meta: a.meta.clone(),
                views,
                errors: [e.rmse, e.mae, e.max_error],
                samples: e.samples,
                transforms: enc.transforms as u64,
            },
            bytes,
        }
    }
}

/// The file's metadata, table (offsets not yet set) and source-level errors from the records
/// of every chunk of `header`'s raster, taken in table order so that the same chunks give the
/// same file however they were coded.
pub(super) fn summarise<'r>(
    (width, height, georef, lineage): (usize, usize, Option<&fractile_proto::Georef>, Option<&str>),
    chunk: u32,
    sizes: &[(u32, u32)],
    records: impl Iterator<Item = &'r ChunkRecord>,
) -> Result<(fractile_proto::AssetMeta, ChunkTable, Errors, usize), Error> {
    let records: Vec<&ChunkRecord> = records.collect();
    // The source chunks' records say how many levels are views (their maps), and so the
    // overlap they were cut with.
    let view_count = records
        .iter()
        .filter(|c| c.level == 0)
        .map(|c| c.views.len())
        .max()
        .unwrap_or(0);
    let mut table = new_table(chunk, view_count);
    let mut entries = blank(&table, sizes);
    let mut views: Vec<Vec<Vec<u8>>> = Vec::new();
    let (mut sq, mut abs, mut samples, mut max_error) = (0.0f64, 0.0f64, 0u64, 0.0f64);
    let (mut transforms, mut template) = (0u64, None::<&fractile_proto::AssetMeta>);
    let mut value_range = [f64::INFINITY, f64::NEG_INFINITY];
    for c in records {
        if table.codec != 0 && table.codec != c.codec {
            return Err(Error::settings("chunks coded by different codecs"));
        }
        table.codec = c.codec;
        table.max_contrast = table.max_contrast.max(c.max_contrast);
        table.seed_bound = table.seed_bound.max(c.seed_bound);
        if let Some(e) = c.smallest_source_error {
            let s = table.smallest_source_error.get_or_insert(e);
            *s = s.min(e);
        }
        value_range[0] = value_range[0].min(c.meta.value_min);
        value_range[1] = value_range[1].max(c.meta.value_max);
        if c.level == 0 {
            let [rmse, mae, max] = c.errors;
            sq += rmse * rmse * c.samples as f64;
            abs += mae * c.samples as f64;
            samples += c.samples;
            max_error = max_error.max(max);
            transforms += c.transforms;
            template.get_or_insert(&c.meta);
            for (l, map) in c.views.iter().enumerate() {
                if views.len() <= l {
                    views.push(vec![Vec::new(); entries[0].len()]);
                }
                if let Some(m) = views[l].get_mut(c.index as usize) {
                    m.clone_from(map);
                }
            }
        }
        let entry = entries
            .get_mut(c.level as usize)
            .and_then(|l| l.get_mut(c.index as usize))
            .ok_or_else(|| Error::input(format!("no chunk {} of level {}", c.index, c.level)))?;
        entry.value_range = [c.meta.value_min, c.meta.value_max];
        entry.length = c.length;
        entry.crc = c.crc;
    }
    let Some(mut meta) = template.cloned() else {
        return Err(Error::input("no cell of the raster has data"));
    };
    // A view level's entries: level 0's (value ranges too), with the view's cells; their
    // offsets are level 0's, set by `chunked::header`.
    let zero = entries[0].clone();
    for (l, level) in entries.iter_mut().enumerate().skip(1).take(views.len()) {
        *level = level_zero_views(&zero, l);
    }
    for (entries, &(w, h)) in entries.into_iter().zip(sizes) {
        table.levels.push(chunked::Level {
            width: w,
            height: h,
            chunks: entries,
        });
    }
    table.views = views
        .into_iter()
        .map(|maps| chunked::ViewLevel { maps })
        .collect();
    meta.width = width as u32;
    meta.height = height as u32;
    meta.georef = georef.cloned();
    // Images keep their fixed 0-255 range; height fields span every chunk's.
    if meta.kind == fractile_proto::AssetKind::HeightField {
        [meta.value_min, meta.value_max] = value_range;
    }
    let rmse = (sq / samples.max(1) as f64).sqrt();
    let psnr = if rmse > 0.0 {
        20.0 * (meta.psnr_peak() / rmse).log10()
    } else {
        f64::INFINITY
    };
    meta.encoder = match lineage {
        Some(l) => format!("chunked {chunk}: {}; {l}", meta.encoder),
        None => format!("chunked {chunk}: {}", meta.encoder),
    };
    // No encode time (see `Coded::of`): the command line reports it.
    meta.stats = fractile_proto::EncodeStats {
        transforms,
        rmse,
        psnr,
        max_error,
        seconds: 0.0,
    };
    let errors = Errors {
        rmse,
        mae: abs / samples.max(1) as f64,
        max_error,
        psnr,
        samples,
    };
    Ok((meta, table, errors, transforms as usize))
}

/// An empty table for chunks of `chunk` cut for `views` view levels.
pub(super) fn new_table(chunk: u32, views: usize) -> ChunkTable {
    ChunkTable {
        chunk,
        overlap: overlap_for(views),
        codec: 0,
        max_contrast: 0.0,
        seed_bound: 0.0,
        smallest_source_error: None,
        levels: Vec::new(),
        views: Vec::new(),
    }
}

/// A table entry (its cells, nothing yet of its file) for every chunk of every level.
pub(super) fn blank(table: &ChunkTable, sizes: &[(u32, u32)]) -> Vec<Vec<ChunkEntry>> {
    sizes
        .iter()
        .map(|&(w, h)| {
            let (nx, ny) = table.grid(w, h);
            (0..nx * ny)
                .map(|i| ChunkEntry {
                    offset: 0,
                    length: 0,
                    cells: table.coded_cells(w, h, i % nx, i / nx),
                    value_range: [0.0, 0.0],
                    crc: 0,
                })
                .collect()
        })
        .collect()
}

/// A table of every chunk of levels `sizes` (nothing yet of their files).
pub(super) fn table_of(chunk: u32, sizes: &[(u32, u32)], views: usize) -> ChunkTable {
    let mut table = new_table(chunk, views);
    for (entries, &(w, h)) in blank(&table, sizes).into_iter().zip(sizes) {
        table.levels.push(chunked::Level {
            width: w,
            height: h,
            chunks: entries,
        });
    }
    table
}

/// What a chunked file's header may take beside its chunks: the table (its size is fixed by
/// its entry count), and 512 bytes for the metadata (an encoder line, a georeference: about
/// 235 bytes measured).
pub(super) fn header_allowance(table: &ChunkTable) -> u64 {
    (fractile_proto::encode(table).len() + 512) as u64
}
