//! Rasters in chunks (format version 6, `io::chunked`): the raster and its overviews cut into
//! chunks, each coded on its own by any 2D codec, on every core.
//!
//! Every chunk is coded with the same settings (a rate is a rate per chunk, so the file's rate
//! is the chunks'; a bounded error is bounded in every chunk). Overviews are the raster
//! box-averaged by 2 (nodata cells left out of the mean) until a level fits in one chunk: they
//! add about a third to the cells coded, as a COG's overviews do, and let a coarse tile decode
//! a few chunks of a coarse level instead of the whole raster.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use super::Encoded;
use crate::Error;
use crate::core::metrics::Errors;
use crate::io::asset::Asset;
use crate::io::chunked::{self, ChunkEntry, ChunkTable, Level, OVERLAP};
use crate::io::raster::Raster;

/// The chunk side `fractile encode` picks: 1024 cells (a chunk's lazily built projected
/// operator holds about 5.3 MB decoded, and decodes in about 100 ms of a core; 512 cost 0.33
/// dB on the 37 Mpx mosaic).
pub const DEFAULT_CHUNK: u32 = 1024;

/// Whether a raster of `width x height` is coded in chunks of `chunk` by default: when it is
/// over twice a chunk on a side. Smaller rasters stay one operator (version 5), whose answers
/// need no chunk lookups and whose coarse zooms need no overviews.
pub fn wants_chunks(width: usize, height: usize, chunk: u32) -> bool {
    width > 2 * chunk as usize || height > 2 * chunk as usize
}

/// Codes one chunk (a raster of its own) by whichever 2D codec and settings the caller chose.
pub type EncodeOne<'a> = dyn Fn(&Raster) -> Result<Encoded, Error> + Sync + 'a;

/// Codes `raster` in chunks of `chunk` cells (a power of two in
/// [`chunked::CHUNK_SIDES`]), each by `encode_one`, in parallel; `progress(done, total)`
/// counts chunks. The errors reported are those of the source level's chunks over their coded
/// cells.
pub fn encode_chunked(
    raster: &Raster,
    chunk: u32,
    encode_one: &EncodeOne<'_>,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<Encoded, Error> {
    let start = Instant::now();
    let (lo, hi) = chunked::CHUNK_SIDES;
    if !chunk.is_power_of_two() || !(lo..=hi).contains(&chunk) {
        return Err(Error::Settings(format!(
            "--chunk {chunk}: a power of two from {lo} to {hi}"
        )));
    }
    if raster.width > 1 << 24 || raster.height > 1 << 24 {
        return Err(Error::Input("a raster over 2^24 cells a side".into()));
    }
    let sizes = ChunkTable::level_sizes(raster.width as u32, raster.height as u32, chunk);
    let mut levels = vec![None];
    for _ in 1..sizes.len() {
        let finer = levels.last().and_then(Option::as_ref).unwrap_or(raster);
        levels.push(Some(halve(finer)));
    }
    let mut table = ChunkTable {
        chunk,
        overlap: OVERLAP,
        codec: 0,
        max_contrast: 0.0,
        seed_bound: 0.0,
        smallest_source_error: None,
        levels: Vec::new(),
    };
    let coded = code_chunks(raster, &levels, &table, &sizes, (encode_one, progress))?;
    let (mut files, mut entries) = blank(&table, &sizes);
    // Squared error sums of the source level's chunks, for the file's errors.
    let (mut sq, mut abs, mut samples, mut max_error) = (0.0f64, 0.0f64, 0u64, 0.0f64);
    let (mut transforms, mut template) = (0usize, None);
    let (mut value_min, mut value_max) = (f64::INFINITY, f64::NEG_INFINITY);
    for (l, i, coded) in coded {
        let Some(c) = coded else { continue };
        if table.codec != 0 && table.codec != c.codec {
            return Err(Error::Settings("chunks coded by different codecs".into()));
        }
        table.codec = c.codec;
        table.max_contrast = table.max_contrast.max(c.max_contrast);
        table.seed_bound = table.seed_bound.max(c.seed_bound);
        if let Some(e) = c.smallest_source_error {
            let s = table.smallest_source_error.get_or_insert(e);
            *s = s.min(e);
        }
        let entry = &mut entries[l][i as usize];
        entry.value_range = [c.meta.value_min, c.meta.value_max];
        value_min = value_min.min(c.meta.value_min);
        value_max = value_max.max(c.meta.value_max);
        if l == 0 {
            let e = &c.errors;
            sq += e.rmse * e.rmse * e.samples as f64;
            abs += e.mae * e.samples as f64;
            samples += e.samples;
            max_error = max_error.max(e.max_error);
            transforms += c.transforms;
            template.get_or_insert(c.meta);
        }
        files[l][i as usize] = c.bytes;
    }
    let Some(mut meta) = template else {
        return Err(Error::Input("no cell of the raster has data".into()));
    };
    for (entries, &(w, h)) in entries.into_iter().zip(&sizes) {
        table.levels.push(Level {
            width: w,
            height: h,
            chunks: entries,
        });
    }
    meta.width = raster.width as u32;
    meta.height = raster.height as u32;
    meta.georef = raster.georef.clone();
    // Images keep their fixed 0-255 range; height fields span every chunk's.
    if meta.kind == fractile_proto::AssetKind::HeightField {
        meta.value_min = value_min;
        meta.value_max = value_max;
    }
    let rmse = (sq / samples.max(1) as f64).sqrt();
    let psnr = if rmse > 0.0 {
        20.0 * (meta.psnr_peak() / rmse).log10()
    } else {
        f64::INFINITY
    };
    meta.encoder = format!("chunked {chunk}: {}", meta.encoder);
    meta.stats = fractile_proto::EncodeStats {
        transforms: transforms as u64,
        rmse,
        psnr,
        max_error,
        seconds: start.elapsed().as_secs_f64(),
    };
    let bytes = chunked::assemble(&meta, table, &files);
    drop(files);
    let asset = Asset::from_bytes(&bytes)?;
    Ok(Encoded {
        asset,
        bytes,
        errors: Errors {
            rmse,
            mae: abs / samples.max(1) as f64,
            max_error,
            psnr,
            samples,
        },
        transforms,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// An empty file and a table entry (its cells, nothing yet of its bytes) for every chunk of
/// every level.
#[allow(clippy::type_complexity)]
fn blank(table: &ChunkTable, sizes: &[(u32, u32)]) -> (Vec<Vec<Vec<u8>>>, Vec<Vec<ChunkEntry>>) {
    let files: Vec<Vec<Vec<u8>>> = sizes
        .iter()
        .map(|&(w, h)| {
            let (nx, ny) = table.grid(w, h);
            vec![Vec::new(); (nx * ny) as usize]
        })
        .collect();
    let entries: Vec<Vec<ChunkEntry>> = sizes
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
        .collect();
    (files, entries)
}

/// What the file keeps of a chunk's encode: its bytes and the figures of its table entry and
/// of the file's metadata. The decoded asset an encode returns (a projected one holds 48 bytes
/// a cell) is dropped as soon as the chunk is coded, so that memory holds the chunks in flight,
/// not every chunk coded so far.
struct Coded {
    bytes: Vec<u8>,
    codec: u8,
    max_contrast: f32,
    seed_bound: f32,
    smallest_source_error: Option<f32>,
    meta: fractile_proto::AssetMeta,
    errors: Errors,
    transforms: usize,
}

impl Coded {
    fn of(enc: Encoded) -> Coded {
        let a = &enc.asset;
        Coded {
            codec: a.codec() as u8,
            max_contrast: a.max_contrast(),
            seed_bound: a.bound_after(0),
            smallest_source_error: a.source_error.as_ref().and_then(|m| m.smallest()),
            meta: a.meta.clone(),
            errors: enc.errors,
            transforms: enc.transforms,
            bytes: enc.bytes,
        }
    }
}

/// Every chunk of every level coded by `encode_one` on all cores: `(level, index, coded)`,
/// `None` for a chunk with no valid cell.
fn code_chunks(
    raster: &Raster,
    levels: &[Option<Raster>],
    table: &ChunkTable,
    sizes: &[(u32, u32)],
    (encode_one, progress): (&EncodeOne<'_>, &(dyn Fn(u64, u64) + Sync)),
) -> Result<Vec<(usize, u32, Option<Coded>)>, Error> {
    // Every chunk of every level, coarse levels first (they are small, and a slow start on
    // the big level would leave a core idle at the end).
    let mut jobs = Vec::new();
    for (l, &(w, h)) in sizes.iter().enumerate() {
        let (nx, ny) = table.grid(w, h);
        for i in 0..nx * ny {
            jobs.push((l, i, table.coded_cells(w, h, i % nx, i / nx)));
        }
    }
    jobs.reverse();
    let total = jobs.len() as u64;
    let done = AtomicU64::new(0);
    progress(0, total);
    // In batches of a chunk a core: a core waiting inside a chunk's own parallel work would
    // otherwise steal further chunks, and hold more of them in memory than there are cores.
    let mut coded = Vec::with_capacity(jobs.len());
    for batch in jobs.chunks(rayon::current_num_threads().max(1)) {
        let part: Vec<_> = batch
            .par_iter()
            .with_max_len(1)
            .map(|&(l, i, cells)| {
                let source = levels[l].as_ref().unwrap_or(raster);
                let part = crop(source, cells);
                let any_valid = part.valid.as_ref().is_none_or(|v| v.iter().any(|&b| b));
                let enc = if any_valid {
                    let enc = encode_one(&part).map_err(|e| match e {
                        Error::Input(m) => Error::Input(format!("chunk {i} of level {l}: {m}")),
                        e => e,
                    })?;
                    Some(Coded::of(enc))
                } else {
                    None
                };
                progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                Ok((l, i, enc))
            })
            .collect::<Result<_, Error>>()?;
        coded.extend(part);
    }
    Ok(coded)
}

/// The cells `[x0, y0, x1, y1)` of `raster` as a raster of their own (georeference moved to
/// its corner).
fn crop(raster: &Raster, [x0, y0, x1, y1]: [u32; 4]) -> Raster {
    let (x0, y0, x1, y1) = (x0 as usize, y0 as usize, x1 as usize, y1 as usize);
    let w = raster.width;
    let rows = |plane: &[f32]| -> Vec<f32> {
        (y0..y1)
            .flat_map(|y| plane[y * w + x0..y * w + x1].iter().copied())
            .collect()
    };
    let valid = raster.valid.as_ref().map(|v| {
        (y0..y1)
            .flat_map(|y| v[y * w + x0..y * w + x1].iter().copied())
            .collect::<Vec<bool>>()
    });
    Raster {
        width: x1 - x0,
        height: y1 - y0,
        channels: raster.channels.iter().map(|c| rows(c)).collect(),
        valid: valid.filter(|v| v.iter().any(|&b| !b)),
        kind: raster.kind,
        sample: raster.sample,
        units: raster.units.clone(),
        nodata: raster.nodata,
        georef: raster.georef.as_ref().map(|g| fractile_proto::Georef {
            origin: [
                g.origin[0] + x0 as f64 * g.pixel_size[0],
                g.origin[1] + y0 as f64 * g.pixel_size[1],
            ],
            ..g.clone()
        }),
    }
}

/// The raster box-averaged by 2 (sizes rounded up): each cell the mean of the valid cells of
/// its 2 x 2 block (rounded for integer samples), nodata where none is.
pub(crate) fn halve(raster: &Raster) -> Raster {
    let (w, h) = (raster.width, raster.height);
    let (hw, hh) = (w.div_ceil(2), h.div_ceil(2));
    let valid_at = |i: usize| raster.valid.as_ref().is_none_or(|v| v[i]);
    // Integer samples stay integers (rounded means): an overview of an integer source is of
    // its sample type, and the codecs that keep a bound per sample count on its quantum.
    let whole = raster.sample != fractile_proto::SampleFormat::F32;
    let mut valid = vec![true; hw * hh];
    let mut channels = vec![vec![f32::NAN; hw * hh]; raster.channels.len()];
    for y in 0..hh {
        for x in 0..hw {
            let cells = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .into_iter()
                .map(|(dx, dy)| (2 * x + dx, 2 * y + dy))
                .filter(|&(cx, cy)| cx < w && cy < h)
                .map(|(cx, cy)| cy * w + cx)
                .filter(|&i| valid_at(i));
            let (mut n, mut sums) = (0u32, [0f64; 4]);
            for i in cells {
                n += 1;
                for (s, c) in sums.iter_mut().zip(&raster.channels) {
                    *s += f64::from(c[i]);
                }
            }
            valid[y * hw + x] = n > 0;
            if n > 0 {
                for (c, s) in channels.iter_mut().zip(sums) {
                    let mean = s / f64::from(n);
                    c[y * hw + x] = if whole { mean.round() } else { mean } as f32;
                }
            }
        }
    }
    Raster {
        width: hw,
        height: hh,
        channels,
        valid: raster.valid.as_ref().map(|_| valid),
        kind: raster.kind,
        sample: raster.sample,
        units: raster.units.clone(),
        nodata: raster.nodata,
        georef: raster.georef.as_ref().map(|g| fractile_proto::Georef {
            pixel_size: [g.pixel_size[0] * 2.0, g.pixel_size[1] * 2.0],
            ..g.clone()
        }),
    }
}
