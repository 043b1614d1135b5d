//! Rasters in chunks (format version 6, `io::chunked`): the raster and its overviews cut into
//! chunks, each coded on its own by any 2D codec, on every core.
//!
//! Every chunk is coded with the same settings (a rate is a rate per chunk, so the file's rate
//! is the chunks'; a bounded error is bounded in every chunk). Overviews are the raster
//! box-averaged by 2 (nodata cells left out of the mean) until a level fits in one chunk: they
//! add about a third to the cells coded, as a COG's overviews do, and let a coarse tile decode
//! a few chunks of a coarse level instead of the whole raster.

use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use super::pyramid::Pyramid;
use super::{Encoded, Written};
use crate::Error;
use crate::core::metrics::Errors;
use crate::io::asset::{Asset, write_atomic_with};
use crate::io::chunked::{self, ChunkEntry, ChunkTable, OVERLAP};
use crate::io::mosaic;
use crate::io::raster::Raster;
use crate::io::rows::{Header, InMemory, Rows};

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

/// Counts chunks coded: `progress(done, total)`.
pub type Progress<'a> = dyn Fn(u64, u64) + Sync + 'a;

/// Rows read from the source at a time: a level holds its chunk row in progress and at most
/// this many rows more.
const READ_ROWS: usize = 128;

/// Codes `raster` in chunks of `chunk` cells (a power of two in
/// [`chunked::CHUNK_SIDES`]), each by `encode_one`, in parallel; `progress(done, total)`
/// counts chunks. The errors reported are those of the source level's chunks over their coded
/// cells. The file is built in memory: [`encode_chunked_file`] writes one of any size.
pub fn encode_chunked(
    raster: &Raster,
    chunk: u32,
    encode_one: &EncodeOne<'_>,
    progress: &Progress<'_>,
) -> Result<Encoded, Error> {
    let mut spill = Spill::Memory(Vec::new());
    let mut coded = code_streamed(
        &mut InMemory::new(raster),
        chunk,
        (encode_one, progress),
        &mut spill,
    )?;
    let mut bytes = chunked::header(&coded.meta, &mut coded.table);
    for (at, len) in coded.order() {
        spill
            .copy(at, len, &mut bytes)
            .map_err(|e| Error::Output(e.to_string()))?;
    }
    let asset = Asset::from_bytes(&bytes)?;
    Ok(Encoded {
        asset,
        bytes,
        errors: coded.errors,
        transforms: coded.transforms,
        seconds: coded.start.elapsed().as_secs_f64(),
    })
}

/// Codes the raster `rows` reads in chunks (as [`encode_chunked`]) and writes the file to
/// `output`, in memory bounded whatever the raster's size: rows are read a band at a time
/// and dropped once the chunks (and overview rows) that need them are made, and each chunk's
/// file goes to an unnamed temporary file as it is coded. The output appears whole or not at
/// all ([`write_atomic_with`]).
pub fn encode_chunked_file(
    rows: &mut dyn Rows,
    chunk: u32,
    encode_one: &EncodeOne<'_>,
    progress: &Progress<'_>,
    output: &Path,
) -> Result<Written, Error> {
    let dir = output
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let out = |e: std::io::Error| Error::Output(format!("{}: {e}", output.display()));
    let mut spill = Spill::File(tempfile::tempfile_in(dir).map_err(out)?, 0);
    let mut coded = code_streamed(rows, chunk, (encode_one, progress), &mut spill)?;
    let head = chunked::header(&coded.meta, &mut coded.table);
    let mut length = head.len() as u64;
    write_atomic_with(output, &mut |f| {
        let mut f = std::io::BufWriter::new(f);
        f.write_all(&head)?;
        for (at, len) in coded.order() {
            spill.copy(at, len, &mut f)?;
            length += len;
        }
        f.flush()
    })?;
    Ok(Written {
        asset: Asset::read(output)?,
        length,
        errors: coded.errors,
        transforms: coded.transforms,
        seconds: coded.start.elapsed().as_secs_f64(),
    })
}

/// Where chunk files wait while the others are coded: memory for a file built in memory, an
/// unnamed temporary file (and its length) for one written to disk.
enum Spill {
    Memory(Vec<u8>),
    File(std::fs::File, u64),
}

impl Spill {
    /// Appends a chunk's file; returns where it starts.
    fn push(&mut self, file: &[u8]) -> std::io::Result<u64> {
        match self {
            Spill::Memory(v) => {
                v.extend_from_slice(file);
                Ok((v.len() - file.len()) as u64)
            }
            Spill::File(f, len) => {
                f.write_all(file)?;
                *len += file.len() as u64;
                Ok(*len - file.len() as u64)
            }
        }
    }

    /// Copies `len` bytes from `at` to `out`.
    fn copy(&self, at: u64, len: u64, out: &mut dyn Write) -> std::io::Result<()> {
        match self {
            Spill::Memory(v) => out.write_all(&v[at as usize..(at + len) as usize]),
            Spill::File(f, _) => {
                use std::os::unix::fs::FileExt;
                let mut buf = vec![0u8; len as usize];
                f.read_exact_at(&mut buf, at)?;
                out.write_all(&buf)
            }
        }
    }
}

/// What a streaming encode coded: the file's metadata and table (lengths and CRCs set,
/// offsets not yet), where each chunk's file lies in the spill, and the source level's errors.
struct Streamed {
    meta: fractile_proto::AssetMeta,
    table: ChunkTable,
    /// `(start, length)` in the spill of every chunk, level by level (length 0: no file).
    spilled: Vec<Vec<(u64, u64)>>,
    errors: Errors,
    transforms: usize,
    start: Instant,
}

impl Streamed {
    /// Every chunk's place in the spill, in the file's order.
    fn order(&self) -> impl Iterator<Item = (u64, u64)> + '_ {
        self.spilled.iter().flatten().copied()
    }
}

/// Every chunk of every level of the raster `rows` reads, coded by `encode_one` on all cores
/// as soon as the rows it covers are read (see [`Pyramid`]), its file pushed to `spill`.
fn code_streamed(
    rows: &mut dyn Rows,
    chunk: u32,
    work: (&EncodeOne<'_>, &Progress<'_>),
    spill: &mut Spill,
) -> Result<Streamed, Error> {
    let start = Instant::now();
    let (lo, hi) = chunked::CHUNK_SIDES;
    if !chunk.is_power_of_two() || !(lo..=hi).contains(&chunk) {
        return Err(Error::Settings(format!(
            "--chunk {chunk}: a power of two from {lo} to {hi}"
        )));
    }
    let header = rows.header().clone();
    if header.width == 0 || header.height == 0 {
        return Err(Error::Input("the grid is empty (0 samples)".into()));
    }
    if header.width > mosaic::MAX_WIDTH || header.height > 1 << 24 {
        return Err(Error::Input(format!(
            "{}x{}: a chunked raster is at most {} cells wide (a band of its rows is held in memory) and 2^24 high",
            header.width,
            header.height,
            mosaic::MAX_WIDTH
        )));
    }
    let sizes = ChunkTable::level_sizes(header.width as u32, header.height as u32, chunk);
    let table = ChunkTable {
        chunk,
        overlap: OVERLAP,
        codec: 0,
        max_contrast: 0.0,
        seed_bound: 0.0,
        smallest_source_error: None,
        levels: Vec::new(),
    };
    let mut pyramid = Pyramid::new(&header, &sizes, &table);
    let mut tally = Tally::new(blank(&table, &sizes), work, spill);
    let mut code = |l, i, part| tally.push(l, i, part);
    let mut y = 0;
    while y < header.height {
        let y1 = (y + READ_ROWS).min(header.height);
        let band = rows.read(y, y1)?;
        if band.width != header.width || band.height != y1 - y {
            return Err(Error::Input(format!(
                "rows {y}..{y1} read as {}x{}, not {}x{}",
                band.width,
                band.height,
                header.width,
                y1 - y
            )));
        }
        pyramid.push(0, &band, &mut code)?;
        y = y1;
    }
    tally.flush()?;
    tally.finish(&header, table, &sizes, start)
}
/// A table entry (its cells, nothing yet of its file) for every chunk of every level.
fn blank(table: &ChunkTable, sizes: &[(u32, u32)]) -> Vec<Vec<ChunkEntry>> {
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

/// Chunks waiting to be coded (a batch of a chunk a core), and what the file keeps of those
/// coded: table entries, places in the spill, the table's and the metadata's figures.
struct Tally<'w, 's> {
    entries: Vec<Vec<ChunkEntry>>,
    spilled: Vec<Vec<(u64, u64)>>,
    queue: Vec<(usize, u32, Raster)>,
    work: (&'w EncodeOne<'w>, &'w Progress<'w>),
    spill: &'s mut Spill,
    done: AtomicU64,
    total: u64,
    codec: u8,
    max_contrast: f32,
    seed_bound: f32,
    smallest_source_error: Option<f32>,
    value_range: [f64; 2],
    /// Squared and absolute error sums, samples and largest error of the source level.
    sums: (f64, f64, u64, f64),
    transforms: usize,
    template: Option<fractile_proto::AssetMeta>,
}

impl<'w, 's> Tally<'w, 's> {
    fn new(
        entries: Vec<Vec<ChunkEntry>>,
        work: (&'w EncodeOne<'w>, &'w Progress<'w>),
        spill: &'s mut Spill,
    ) -> Self {
        let total = entries.iter().map(Vec::len).sum::<usize>() as u64;
        (work.1)(0, total);
        Tally {
            spilled: entries.iter().map(|l| vec![(0, 0); l.len()]).collect(),
            entries,
            queue: Vec::new(),
            work,
            spill,
            done: AtomicU64::new(0),
            total,
            codec: 0,
            max_contrast: 0.0,
            seed_bound: 0.0,
            smallest_source_error: None,
            value_range: [f64::INFINITY, f64::NEG_INFINITY],
            sums: (0.0, 0.0, 0, 0.0),
            transforms: 0,
            template: None,
        }
    }

    /// Queues chunk `i` of level `l`; codes the queue once it holds a chunk a core.
    fn push(&mut self, l: usize, i: u32, part: Raster) -> Result<(), Error> {
        self.queue.push((l, i, part));
        if self.queue.len() >= rayon::current_num_threads().max(1) {
            self.flush()?;
        }
        Ok(())
    }

    /// Codes every queued chunk on all cores and records each.
    fn flush(&mut self) -> Result<(), Error> {
        let jobs = std::mem::take(&mut self.queue);
        let (encode_one, progress) = self.work;
        let (done, total) = (&self.done, self.total);
        // One chunk a task: a core waiting inside a chunk's own parallel work would otherwise
        // steal further chunks, and hold more of them in memory than there are cores.
        let coded: Vec<_> = jobs
            .into_par_iter()
            .with_max_len(1)
            .map(|(l, i, part)| {
                let any_valid = part.valid.as_ref().is_none_or(|v| v.contains(&true));
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
        for (l, i, c) in coded {
            if let Some(c) = c {
                self.record(l, i as usize, c)?;
            }
        }
        Ok(())
    }

    fn record(&mut self, l: usize, i: usize, c: Coded) -> Result<(), Error> {
        if self.codec != 0 && self.codec != c.codec {
            return Err(Error::Settings("chunks coded by different codecs".into()));
        }
        self.codec = c.codec;
        self.max_contrast = self.max_contrast.max(c.max_contrast);
        self.seed_bound = self.seed_bound.max(c.seed_bound);
        if let Some(e) = c.smallest_source_error {
            let s = self.smallest_source_error.get_or_insert(e);
            *s = s.min(e);
        }
        let [lo, hi] = &mut self.value_range;
        *lo = lo.min(c.meta.value_min);
        *hi = hi.max(c.meta.value_max);
        if l == 0 {
            let (e, s) = (&c.errors, &mut self.sums);
            s.0 += e.rmse * e.rmse * e.samples as f64;
            s.1 += e.mae * e.samples as f64;
            s.2 += e.samples;
            s.3 = s.3.max(e.max_error);
            self.transforms += c.transforms;
            self.template.get_or_insert_with(|| c.meta.clone());
        }
        let at = self
            .spill
            .push(&c.bytes)
            .map_err(|e| Error::Output(format!("spilling a chunk: {e}")))?;
        let entry = &mut self.entries[l][i];
        entry.value_range = [c.meta.value_min, c.meta.value_max];
        entry.length = c.bytes.len() as u64;
        entry.crc = chunked::file_crc(&c.bytes);
        self.spilled[l][i] = (at, entry.length);
        Ok(())
    }

    /// The file's metadata and table from every chunk recorded.
    fn finish(
        self,
        header: &Header,
        mut table: ChunkTable,
        sizes: &[(u32, u32)],
        start: Instant,
    ) -> Result<Streamed, Error> {
        let Some(mut meta) = self.template else {
            return Err(Error::Input("no cell of the raster has data".into()));
        };
        table.codec = self.codec;
        table.max_contrast = self.max_contrast;
        table.seed_bound = self.seed_bound;
        table.smallest_source_error = self.smallest_source_error;
        for (entries, &(w, h)) in self.entries.into_iter().zip(sizes) {
            table.levels.push(chunked::Level {
                width: w,
                height: h,
                chunks: entries,
            });
        }
        meta.width = header.width as u32;
        meta.height = header.height as u32;
        meta.georef = header.georef.clone();
        // Images keep their fixed 0-255 range; height fields span every chunk's.
        if meta.kind == fractile_proto::AssetKind::HeightField {
            [meta.value_min, meta.value_max] = self.value_range;
        }
        let (sq, abs, samples, max_error) = self.sums;
        let rmse = (sq / samples.max(1) as f64).sqrt();
        let psnr = if rmse > 0.0 {
            20.0 * (meta.psnr_peak() / rmse).log10()
        } else {
            f64::INFINITY
        };
        meta.encoder = format!("chunked {}: {}", table.chunk, meta.encoder);
        meta.stats = fractile_proto::EncodeStats {
            transforms: self.transforms as u64,
            rmse,
            psnr,
            max_error,
            seconds: start.elapsed().as_secs_f64(),
        };
        Ok(Streamed {
            meta,
            table,
            spilled: self.spilled,
            errors: Errors {
                rmse,
                mae: abs / samples.max(1) as f64,
                max_error,
                psnr,
                samples,
            },
            transforms: self.transforms,
            start,
        })
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    fn testdata(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../testdata")
            .join(name)
    }

    /// Where a chunk lies: its level (pixel size), corner and size.
    fn key(r: &Raster) -> (u64, u64, u64, usize, usize) {
        let g = r.georef.as_ref().expect("georeferenced");
        (
            g.pixel_size[0].to_bits(),
            g.origin[0].to_bits(),
            g.origin[1].to_bits(),
            r.width,
            r.height,
        )
    }

    /// The cells `[x0, y0, x1, y1)` of a whole raster (its georeference moved to the corner).
    fn crop(r: &Raster, [x0, y0, x1, y1]: [u32; 4]) -> Raster {
        let (x0, y0, x1, y1) = (x0 as usize, y0 as usize, x1 as usize, y1 as usize);
        let rows = |p: &[f32]| -> Vec<f32> {
            (y0..y1)
                .flat_map(|y| p[y * r.width + x0..y * r.width + x1].to_vec())
                .collect()
        };
        let valid = r.valid.as_ref().map(|v| {
            (y0..y1)
                .flat_map(|y| v[y * r.width + x0..y * r.width + x1].to_vec())
                .collect::<Vec<bool>>()
        });
        Header::of(r).band(
            [x0, y0],
            x1 - x0,
            r.channels.iter().map(|c| rows(c)).collect(),
            valid.filter(|v| v.contains(&false)),
        )
    }

    /// The chunks a streaming encode codes, read a band at a time, are the cells a chunk of
    /// the raster held whole (and of its overviews, halved whole) holds: nodata cells, odd
    /// sizes and the last lone row of a level included.
    #[test]
    fn streamed_chunks_are_the_whole_rasters_chunks() {
        // 344 x 363 with nodata around the rotated source: levels of 344 x 363, 172 x 182,
        // 86 x 91 in chunks of 64.
        let raster = Raster::open(&testdata("jacksboro-utm.tif")).unwrap();
        let seen = Mutex::new(Vec::new());
        let one = |part: &Raster| {
            seen.lock().unwrap().push(part.clone());
            crate::encode_default(part, 0.8, &|_, _| {})
        };
        let enc = encode_chunked(&raster, 64, &one, &|_, _| {}).unwrap();
        let table = &enc.asset.chunks.as_ref().unwrap().table;
        let mut level = raster.clone();
        let mut expected = Vec::new();
        for (l, lev) in table.levels.iter().enumerate() {
            if l > 0 {
                level = super::super::pyramid::halve(&level);
            }
            assert_eq!(
                (lev.width as usize, lev.height as usize),
                (level.width, level.height)
            );
            for e in &lev.chunks {
                let part = crop(&level, e.cells);
                if part.valid.as_ref().is_none_or(|v| v.contains(&true)) {
                    expected.push(part);
                }
            }
        }
        let mut seen = seen.into_inner().unwrap();
        assert_eq!(seen.len(), expected.len());
        assert!(
            table.levels.len() == 3 && expected.len() > 30,
            "{}",
            expected.len()
        );
        seen.sort_by_key(key);
        expected.sort_by_key(key);
        for (s, e) in seen.iter().zip(&expected) {
            assert_eq!(key(s), key(e));
            assert_eq!(s.valid, e.valid, "{:?}", key(e));
            for (a, b) in s.channels[0].iter().zip(&e.channels[0]) {
                assert!(
                    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()),
                    "{a} {b}"
                );
            }
        }
    }
}
