//! Rasters in chunks (format version 8, `io::chunked`): the raster and its overviews cut into
//! chunks, each coded on its own by any 2D codec, on every core.
//!
//! Every chunk of a projected file is coded at one quality, a step or a bound, the overviews'
//! scaled by 2 a level: given (`--max-error`) or the file's rate ([`encode_chunked_file_at`],
//! [`rate`]); [`encode_chunked_file`] codes each chunk by its own settings (a codec without a
//! file's rate gets its share of the file, [`chunk_bpp`]). Overviews are the raster
//! box-averaged by 2 (nodata cells left out of the mean) until a level fits in one chunk, and
//! let a coarse tile decode a few chunks of a coarse level instead of the whole raster. Coded,
//! they add about a third to the cells, as a COG's overviews do; so where the chunks are
//! projected planes of a height field, levels 1 and 2 are not coded but are views of the source
//! chunks (their own coarse bands or samples, `io::chunked`), and only their error maps are
//! measured here (`viewed`, `view_maps`).

use std::path::Path;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::encoded::{Encoded, Written};
use super::pyramid::Pyramid;
use super::rate::{self, EncodeAt, Search, Target};
use super::spill::{Spill, write_spilled};
use super::summary::{ChunkRecord, summarise};
use super::summary::{blank, header_allowance, new_table, table_of};
pub use super::tally::Progress;
use super::tally::Tally;
pub use super::views::EncodeLevel;
use super::views::viewed;
use crate::Error;
use crate::core::metrics::Errors;
use crate::io::asset::Asset;
use crate::io::chunked::{self, ChunkTable};
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

/// The rate each chunk takes so that a file of chunks coded one by one at it (codecs without a
/// file's rate, [`rate`]) is at most `bpp` bits a source cell: `bpp` times the source's cells
/// over every level's coded cells (overviews and overlaps included), less 1% for the table.
pub fn chunk_bpp(width: usize, height: usize, chunk: u32, bpp: f64) -> f64 {
    let sizes = ChunkTable::level_sizes(width as u32, height as u32, chunk, false);
    let table = table_of(chunk, &sizes, 0);
    let coded: u64 = table
        .levels
        .iter()
        .flat_map(|l| &l.chunks)
        .map(|e| u64::from(e.cells[2] - e.cells[0]) * u64::from(e.cells[3] - e.cells[1]))
        .sum();
    let file = bpp * (width * height) as f64 / 8.0;
    let chunks = (file - header_allowance(&table) as f64).max(0.0);
    0.99 * 8.0 * chunks / coded.max(1) as f64
}

/// Codes one chunk (a raster of its own) by whichever 2D codec and settings the caller chose.
pub type EncodeOne<'a> = dyn Fn(&Raster) -> Result<Encoded, Error> + Sync + 'a;

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
    let coded = code_streamed(
        &mut InMemory::new(raster),
        chunk,
        (&|_, r: &Raster| encode_one(r), progress),
        &mut spill,
    )?;
    let (meta, mut table, errors, transforms) =
        summarise(coded.size(), chunk, &coded.sizes, coded.records())?;
    let mut bytes = chunked::header(&meta, &mut table);
    for (at, len) in coded.order() {
        spill
            .copy(at, len, &mut bytes)
            .map_err(|e| Error::output(e.to_string()))?;
    }
    let asset = Asset::from_bytes(&bytes)?;
    Ok(Encoded {
        asset,
        bytes,
        errors,
        transforms,
        seconds: coded.start.elapsed().as_secs_f64(),
    })
}

/// Codes the raster `rows` reads in chunks (as [`encode_chunked`]) and writes the file to
/// `output`, in memory bounded whatever the raster's size: rows are read a band at a time
/// and dropped once the chunks (and overview rows) that need them are made, and each chunk's
/// file goes to an unnamed temporary file as it is coded. The output appears whole or not at
/// all ([`crate::io::asset::write_atomic_with`]).
pub fn encode_chunked_file(
    rows: &mut dyn Rows,
    chunk: u32,
    encode_one: &EncodeOne<'_>,
    progress: &Progress<'_>,
    output: &Path,
) -> Result<Written, Error> {
    let mut spill = Spill::beside(output)?;
    let coded = code_streamed(
        rows,
        chunk,
        (&|_, r: &Raster| encode_one(r), progress),
        &mut spill,
    )?;
    let (meta, mut table, errors, transforms) =
        summarise(coded.size(), chunk, &coded.sizes, coded.records())?;
    let head = chunked::header(&meta, &mut table);
    let length = write_spilled(output, &head, coded.order(), &spill)?;
    Ok(Written {
        asset: Asset::read(output)?,
        length,
        errors,
        transforms,
        seconds: coded.start.elapsed().as_secs_f64(),
    })
}

/// Codes `rows` in chunks as [`encode_chunked_file`] does, every chunk at one quality
/// ([`rate::Quality`]): the one given, or the one whose whole file fits a [`rate::FileRate`]
/// ([`rate`]: found on a sample of the chunks, then every chunk coded once; again, coarser,
/// should the file come out over).
pub fn encode_chunked_file_at(
    rows: &mut dyn Rows,
    chunk: u32,
    (rate, encode_at): (impl Into<Target>, &EncodeAt<'_>),
    progress: &Progress<'_>,
    output: &Path,
) -> Result<Written, Error> {
    let spill = || Spill::beside(output);
    let at = code_at_rate(rows, chunk, (rate.into(), encode_at), progress, &spill)?;
    let length = write_spilled(output, &at.head, at.coded.order(), &at.spill)?;
    Ok(Written {
        asset: Asset::read(output)?,
        length,
        errors: at.errors,
        transforms: at.transforms,
        seconds: at.start.elapsed().as_secs_f64(),
    })
}

/// [`encode_chunked_file_at`] into memory.
pub fn encode_chunked_at(
    raster: &Raster,
    chunk: u32,
    (rate, encode_at): (impl Into<Target>, &EncodeAt<'_>),
    progress: &Progress<'_>,
) -> Result<Encoded, Error> {
    let spill = || Ok(Spill::Memory(Vec::new()));
    let at = code_at_rate(
        &mut InMemory::new(raster),
        chunk,
        (rate.into(), encode_at),
        progress,
        &spill,
    )?;
    let mut bytes = at.head.clone();
    for (offset, len) in at.coded.order() {
        at.spill
            .copy(offset, len, &mut bytes)
            .map_err(|e| Error::output(e.to_string()))?;
    }
    Ok(Encoded {
        asset: Asset::from_bytes(&bytes)?,
        bytes,
        errors: at.errors,
        transforms: at.transforms,
        seconds: at.start.elapsed().as_secs_f64(),
    })
}

/// The quality a file of `rows` in chunks of `chunk` is coded at for `target`, aiming at `aim`
/// of its budget under a rate (what each process of a split encode finds alike: the same
/// sample, the same search), and the budget (none for a quality given).
pub fn quality_for(
    rows: &mut dyn Rows,
    chunk: u32,
    (target, encode_at): (impl Into<Target>, &EncodeAt<'_>),
    aim: f64,
) -> Result<(rate::Quality, Option<u64>), Error> {
    let header = checked_header(rows, chunk)?;
    let rate = match target.into() {
        Target::Quality(q) => return Ok((q, None)),
        Target::Rate(rate) => rate,
    };
    let budget = rate.budget((header.width * header.height) as u64)?;
    let sample = sample_chunks(rows, chunk)?;
    let quality = Search::new(&sample, rate, budget, encode_at).find(aim)?;
    Ok((quality, Some(budget)))
}

/// A file coded at its rate: the chunks, where they wait, its header and figures.
struct AtRate {
    /// When the encode began (its sample read first).
    start: Instant,
    coded: Streamed,
    spill: Spill,
    head: Vec<u8>,
    errors: Errors,
    transforms: usize,
}

/// Passes at most: the first at the sample's quality, then coarser ones.
const RATE_PASSES: usize = 4;

fn code_at_rate(
    rows: &mut dyn Rows,
    chunk: u32,
    (target, encode_at): (Target, &EncodeAt<'_>),
    progress: &Progress<'_>,
    spill: &dyn Fn() -> Result<Spill, Error>,
) -> Result<AtRate, Error> {
    let start = Instant::now();
    let header = checked_header(rows, chunk)?;
    let rate = target.rate();
    let cells = (header.width * header.height) as u64;
    let budget = rate
        .map(|r| r.budget(cells))
        .transpose()?
        .unwrap_or(u64::MAX);
    let sample = rate.map(|_| sample_chunks(rows, chunk)).transpose()?;
    let mut search = rate
        .zip(sample.as_ref())
        .map(|(rate, sample)| Search::new(sample, rate, budget, encode_at));
    let mut quality = match (target, search.as_mut()) {
        (Target::Quality(q), _) => q,
        (Target::Rate(_), search) => search.expect("a rate's search").find(rate::AIM)?,
    };
    let mut last = 0;
    for _ in 0..RATE_PASSES {
        let mut sp = spill()?;
        let one = |l: usize, r: &Raster| encode_at(r, quality.at_level(l), false);
        let coded = code_streamed(rows, chunk, (&one, progress), &mut sp)?;
        let (meta, mut table, errors, transforms) =
            summarise(coded.size(), chunk, &coded.sizes, coded.records())?;
        let head = chunked::header(&meta, &mut table);
        last = head.len() as u64 + coded.order().map(|(_, len)| len).sum::<u64>();
        let Some(search) = search.as_mut().filter(|_| last > budget) else {
            return Ok(AtRate {
                start,
                coded,
                spill: sp,
                head,
                errors,
                transforms,
            });
        };
        quality = search.coarser(quality, last)?;
    }
    let bpp = rate.map_or(0.0, |rate| rate.bpp);
    Err(Error::settings(format!(
        "--target-bpp {bpp}: the file came out at {last} bytes, over its {budget}, {RATE_PASSES} times"
    )))
}

/// What a streaming encode coded: every chunk's record and where its file lies in the
/// spill, in table order (`None`: a chunk with no valid cell, or one of another share).
pub(super) struct Streamed {
    pub(super) header: Header,
    pub(super) sizes: Vec<(u32, u32)>,
    /// Whether the first overviews are views (the layout's sizes follow).
    pub(super) viewed: bool,
    pub(super) records: Vec<Vec<Option<(ChunkRecord, u64)>>>,
    pub(super) start: Instant,
}

impl Streamed {
    /// The raster's size, georeference and lineage, as [`summarise`] takes them.
    pub(super) fn size(&self) -> (usize, usize, Option<&fractile_proto::Georef>, Option<&str>) {
        (
            self.header.width,
            self.header.height,
            self.header.georef.as_ref(),
            self.header.lineage.as_deref(),
        )
    }

    /// Every chunk's record in table order.
    pub(super) fn records(&self) -> impl Iterator<Item = &ChunkRecord> + '_ {
        self.records.iter().flatten().flatten().map(|(r, _)| r)
    }

    /// Every chunk's place in the spill (start, length), in table order.
    pub(super) fn order(&self) -> impl Iterator<Item = (u64, u64)> + Clone + '_ {
        self.records
            .iter()
            .flatten()
            .flatten()
            .map(|(r, at)| (*at, r.length))
    }
}

/// The chunks one process codes when an encode is split over several (`fractile encode
/// --part I/N`, then `fractile assemble`): share I codes the I-th of N bands of the source's
/// rows of chunks (as even as whole rows allow), and hands the first coded overview level's
/// rows of its band to `assemble`, which codes the overviews (`encode::band`). Each share so
/// reads its own rows of the inputs, and the inputs are read once over all the shares (a
/// chunk row's overlap and a COG tile row at each band's edges aside); the overviews are a
/// fiftieth of a height field's cells (its first two levels are views) and a third of an
/// image's, coded by `assemble` on its cores.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Share {
    /// Which share, from 0.
    pub index: u32,
    /// Of how many.
    pub count: u32,
}

impl Share {
    /// Every chunk: an encode that is not split.
    pub const WHOLE: Share = Share { index: 0, count: 1 };

    /// `I/N` as the command line writes it.
    pub fn parse(text: &str) -> Result<Share, Error> {
        let bad = || Error::settings(format!("--part {text}: I/N with 0 <= I < N <= 4096"));
        let (i, n) = text.split_once('/').ok_or_else(bad)?;
        let (index, count) = (
            i.trim().parse().map_err(|_| bad())?,
            n.trim().parse().map_err(|_| bad())?,
        );
        if count == 0 || index >= count || count > 4096 {
            return Err(bad());
        }
        Ok(Share { index, count })
    }

    /// The rows of chunks of the source level (of `ny`) this share codes; an error where the
    /// shares outnumber them.
    pub fn rows(&self, ny: u32) -> Result<std::ops::Range<u32>, Error> {
        if self.count > ny {
            return Err(Error::settings(format!(
                "--part {}/{}: this raster has {ny} rows of chunks, so at most {ny} parts",
                self.index, self.count
            )));
        }
        let at = |i: u32| (u64::from(i) * u64::from(ny) / u64::from(self.count)) as u32;
        Ok(at(self.index)..at(self.index + 1))
    }
}

/// Every chunk of every level of the raster `rows` reads, coded by `encode_one` on all cores
/// as soon as the rows it covers are read (see [`Pyramid`]), its file pushed to `spill`.
pub(super) fn code_streamed(
    rows: &mut dyn Rows,
    chunk: u32,
    work: (&EncodeLevel<'_>, &Progress<'_>),
    spill: &mut Spill,
) -> Result<Streamed, Error> {
    let start = Instant::now();
    let header = checked_header(rows, chunk)?;
    let Levels {
        viewed,
        sizes,
        views,
        table,
    } = Levels::of(&header, chunk, viewed(&header, work.0));
    let mut pyramid = Pyramid::new(&header, &sizes, &table);
    let every = |_: usize, _: u32| true;
    let mut tally = Tally::new((&blank(&table, &sizes), views), &every, work, spill);
    let mut code = |l, i, part| tally.push(l, i, part);
    read_levels(rows, &header, 0..header.height, &mut |band| {
        pyramid.push(0, band, &mut code)
    })?;
    tally.flush()?;
    Ok(Streamed {
        header,
        sizes,
        viewed,
        records: tally.records,
        start,
    })
}

/// The levels of a chunked file: whether its first overviews are views, every level's size,
/// how many are views, and the table that cuts them into chunks.
pub(super) struct Levels {
    pub(super) viewed: bool,
    pub(super) sizes: Vec<(u32, u32)>,
    pub(super) views: usize,
    pub(super) table: ChunkTable,
}

impl Levels {
    /// The levels of a raster of `header` in chunks of `chunk`, views or not.
    pub(super) fn of(header: &Header, chunk: u32, viewed: bool) -> Levels {
        let (w, h) = (header.width as u32, header.height as u32);
        let sizes = ChunkTable::level_sizes(w, h, chunk, viewed);
        let views = if viewed {
            ChunkTable::view_levels(sizes.len())
        } else {
            0
        };
        Levels {
            viewed,
            sizes,
            views,
            table: new_table(chunk, views),
        }
    }
}

/// Rows `span` of `rows`, a band at a time, each checked and handed to `band`.
pub(super) fn read_levels(
    rows: &mut dyn Rows,
    header: &Header,
    span: std::ops::Range<usize>,
    band: &mut dyn FnMut(&Raster) -> Result<(), Error>,
) -> Result<(), Error> {
    let mut y = span.start;
    while y < span.end {
        let y1 = (y + READ_ROWS).min(span.end);
        let read = rows.read(y, y1)?;
        read.check_magnitudes()?;
        if read.width != header.width || read.height != y1 - y {
            return Err(Error::input(format!(
                "rows {y}..{y1} read as {}x{}, not {}x{}",
                read.width,
                read.height,
                header.width,
                y1 - y
            )));
        }
        band(&read)?;
        y = y1;
    }
    Ok(())
}

/// The sample of chunks a file's rate is found on ([`rate::sample_indices`]), read as the
/// encode reads them, with every level's valid cells to scale it by. A height field's first
/// overviews are views, whose bytes are their source chunks' (their maps are counted with
/// those): they are left out of the sample.
pub(super) fn sample_chunks(rows: &mut dyn Rows, chunk: u32) -> Result<rate::Sample, Error> {
    let header = checked_header(rows, chunk)?;
    let one_height = header.kind == fractile_proto::AssetKind::HeightField && header.channels == 1;
    let (w, h) = (header.width as u32, header.height as u32);
    let sizes = ChunkTable::level_sizes(w, h, chunk, one_height);
    let views = if one_height {
        ChunkTable::view_levels(sizes.len())
    } else {
        0
    };
    let table = new_table(chunk, views);
    let counts: Vec<u32> = sizes
        .iter()
        .map(|&(w, h)| {
            let (nx, ny) = table.grid(w, h);
            nx * ny
        })
        .collect();
    let mut picked = rate::sample_indices(&counts);
    for p in picked.iter_mut().skip(1).take(views) {
        p.clear();
    }
    let mut pyramid = Pyramid::new(&header, &sizes, &table);
    let (mut chunks, mut all, mut taken) =
        (Vec::new(), vec![0u64; sizes.len()], vec![0u64; sizes.len()]);
    let mut keep = |l: usize, i: u32, part: Raster| {
        let n = rate::valid_cells(&part);
        all[l] += n;
        if picked[l].contains(&i) {
            taken[l] += n;
            chunks.push((l, part));
        }
        Ok(())
    };
    read_levels(rows, &header, 0..header.height, &mut |band| {
        pyramid.push(0, band, &mut keep)
    })?;
    let scale = all
        .iter()
        .zip(&taken)
        .map(|(&a, &t)| if t > 0 { a as f64 / t as f64 } else { 0.0 })
        .collect();
    let overhead = header_allowance(&table_of(chunk, &sizes, views));
    Ok(rate::Sample {
        chunks,
        scale,
        overhead,
        views,
    })
}

/// `rows`' header, checked for a chunked encode in chunks of `chunk`.
pub(super) fn checked_header(rows: &mut dyn Rows, chunk: u32) -> Result<Header, Error> {
    let (lo, hi) = chunked::CHUNK_SIDES;
    if !chunk.is_power_of_two() || !(lo..=hi).contains(&chunk) {
        return Err(Error::settings(format!(
            "--chunk {chunk}: a power of two from {lo} to {hi}"
        )));
    }
    let header = rows.header().clone();
    if header.width == 0 || header.height == 0 {
        return Err(Error::input("the grid is empty (0 samples)"));
    }
    if header.width > mosaic::MAX_WIDTH || header.height > 1 << 24 {
        return Err(Error::input(format!(
            "{}x{}: a chunked raster is at most {} cells wide (a band of its rows is held in memory) and 2^24 high",
            header.width,
            header.height,
            mosaic::MAX_WIDTH
        )));
    }
    Ok(header)
}

#[cfg(test)]
mod tests;
