//! `fractile assemble`: the part files of a split encode (`encode::parts`) joined into the
//! asset, the overviews coded here from the rows the parts hand on (`encode::band`), on all
//! cores, as the encode in one process codes them: the same bytes.

use std::io::Write;
use std::path::{Path, PathBuf};

use super::band::{first_coded, read_rows, row_bytes};
use super::chunked::{Levels, Progress};
use super::encoded::Written;
use super::parts::{Part, check_shares, open_part};
use super::pyramid::Pyramid;
use super::spill::Spill;
use super::summary::{ChunkRecord, blank, summarise};
use super::tally::Tally;
use super::views::EncodeLevel;
use crate::Error;
use crate::io::asset::{Asset, write_atomic_with};
use crate::io::chunked::{self, ChunkTable};
use crate::io::layout::read_exact_at;
use crate::io::rows::Header;

/// Where a chunk's file is: in part `k` at an offset, or coded here, in the spill.
#[derive(Clone, Copy)]
enum Stored {
    InPart(usize, u64),
    Coded(u64),
}

/// Overview rows read from a part at a time.
const HANDED_ROWS: usize = 256;

/// Joins the part files `parts` (every share of one encode, in any order) into the asset
/// `output`, the overviews coded by `encode_level` (the encode's own: [`super::plan::assemble`]
/// finds it in the parts): the same bytes as the encode in one process. Parts of different
/// sources or settings, a missing or repeated share, a chunk of the wrong share, and a part
/// cut short or corrupt are refused by name, and nothing is written.
pub fn assemble(
    parts: &[PathBuf],
    output: &Path,
    encode_level: &EncodeLevel<'_>,
    progress: &Progress<'_>,
) -> Result<Written, Error> {
    let start = std::time::Instant::now();
    let mut parts = parts
        .iter()
        .map(|p| open_part(p))
        .collect::<Result<Vec<_>, _>>()?;
    if parts.is_empty() {
        return Err(Error::input("assemble: no part files given"));
    }
    check_shares(&parts)?;
    parts.sort_by_key(|p| p.share().index);
    let (chunk, viewed, source) = parts[0].layout();
    let source = source.clone();
    let Levels {
        sizes,
        views,
        table,
        ..
    } = Levels::of(&source, chunk, viewed);
    let entries = blank(&table, &sizes);
    let mut placed: Vec<Vec<Option<(Stored, ChunkRecord)>>> =
        entries.iter().map(|l| vec![None; l.len()]).collect();
    place_parts(&parts, &table, &sizes, &mut placed)?;
    let mut spill = Spill::beside(output)?;
    if let Some(level) = first_coded(sizes.len(), views) {
        let layout = (&source, sizes.as_slice(), &table, views);
        let work = (encode_level, progress);
        code_overviews(&parts, layout, level, work, &mut spill, &mut placed)?;
    }
    let order: Vec<(Stored, ChunkRecord)> = placed.into_iter().flatten().flatten().collect();
    let (meta, mut table, errors, transforms) = summarise(
        (
            source.width,
            source.height,
            source.georef.as_ref(),
            source.lineage.as_deref(),
        ),
        chunk,
        &sizes,
        order.iter().map(|(_, r)| r),
    )?;
    let head = chunked::header(&meta, &mut table);
    let total = head.len() as u64 + order.iter().map(|(_, r)| r.length).sum::<u64>();
    if let Some(budget) = parts[0].budget()
        && total > budget
    {
        let bpp = 8.0 * budget as f64 / (source.width * source.height) as f64;
        return Err(Error::settings(format!(
            "the parts come to {total} bytes, over the rate's {budget} ({bpp:.3} bits a cell): a split encode finds its quality on a sample and cannot code again; encode the parts again with --target-bpp {:.3}",
            bpp * 0.98 * budget as f64 / total as f64
        )));
    }
    let mut length = 0;
    write_atomic_with(output, &mut |f| {
        let mut f = std::io::BufWriter::new(f);
        f.write_all(&head)?;
        length = head.len() as u64;
        for (from, r) in &order {
            match *from {
                Stored::Coded(at) => spill.copy(at, r.length, &mut f)?,
                Stored::InPart(k, at) => f.write_all(&checked_chunk(&parts[k], at, r)?)?,
            }
            length += r.length;
        }
        f.flush()
    })?;
    Ok(Written {
        asset: Asset::read(output)?,
        length,
        errors,
        transforms,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The overviews from `level` up, cut from the rows the parts hand on (in share order) and
/// coded by `encode_level` into `spill`, placed.
fn code_overviews(
    parts: &[Part],
    (source, sizes, table, views): (&Header, &[(u32, u32)], &ChunkTable, usize),
    level: usize,
    work: (&EncodeLevel<'_>, &Progress<'_>),
    spill: &mut Spill,
    placed: &mut [Vec<Option<(Stored, ChunkRecord)>>],
) -> Result<(), Error> {
    let entries = blank(table, sizes);
    let mut pyramid = Pyramid::new(source, sizes, table);
    let wants = |l: usize, _: u32| l >= level;
    let mut tally = Tally::new((&entries, views), &wants, work, spill);
    let width = sizes[level].0 as usize;
    let row = row_bytes(width, source.channels);
    let mut next = 0u32;
    for p in parts {
        let Some((_, top, rows, crc)) = p.handed().filter(|h| h.0 == level && h.1 == next) else {
            return Err(Error::input(format!(
                "{}: it does not hand on level {level}'s rows from row {next}",
                p.path.display()
            )));
        };
        let mut hasher = crc32fast::Hasher::new();
        let mut y = 0;
        while y < rows as usize {
            let n = HANDED_ROWS.min(rows as usize - y);
            let mut bytes = vec![0u8; n * row as usize];
            read_exact_at(&p.file, &mut bytes, p.handoff_at + y as u64 * row)
                .map_err(|e| Error::input(format!("{}: {e}", p.path.display())))?;
            hasher.update(&bytes);
            let (channels, valid) = read_rows(&bytes, width, source.channels);
            let band = source.band([0, 0], width, channels, Some(valid));
            pyramid.push(level, &band, &mut |l, i, r| tally.push(l, i, r))?;
            y += n;
        }
        if hasher.finalize() != crc {
            return Err(Error::input(format!(
                "{}: its overview rows are corrupt (CRC mismatch)",
                p.path.display()
            )));
        }
        next = top + rows;
    }
    if next != sizes[level].1 {
        return Err(Error::input(format!(
            "the parts hand on {next} rows of level {level}, of {}",
            sizes[level].1
        )));
    }
    tally.flush()?;
    for (l, level) in tally.records.iter().enumerate() {
        for (i, coded) in level.iter().enumerate() {
            if let Some((record, at)) = coded {
                placed[l][i] = Some((Stored::Coded(*at), record.clone()));
            }
        }
    }
    Ok(())
}

/// Every part's chunks in their places: each of the source level, in its share's band, once.
fn place_parts(
    parts: &[Part],
    table: &ChunkTable,
    sizes: &[(u32, u32)],
    placed: &mut [Vec<Option<(Stored, ChunkRecord)>>],
) -> Result<(), Error> {
    let (nx, ny) = table.grid(sizes[0].0, sizes[0].1);
    for (k, p) in parts.iter().enumerate() {
        let band = p.share().rows(ny)?;
        let mut at = p.body;
        for r in p.records() {
            let slot = (r.level == 0 && band.contains(&(r.index / nx)))
                .then(|| placed[0].get_mut(r.index as usize))
                .flatten()
                .filter(|s| s.is_none())
                .ok_or_else(|| {
                    Error::input(format!(
                        "{}: chunk {} of level {} is not of its share",
                        p.path.display(),
                        r.index,
                        r.level
                    ))
                })?;
            *slot = Some((Stored::InPart(k, at), r.clone()));
            at += r.length;
        }
    }
    Ok(())
}

/// A chunk's file read from its part, its CRCs checked.
fn checked_chunk(part: &Part, at: u64, r: &ChunkRecord) -> std::io::Result<Vec<u8>> {
    let mut buf = vec![0u8; r.length as usize];
    read_exact_at(&part.file, &mut buf, at)?;
    let whole = buf.len() >= 4 && crc32fast::hash(&buf[..buf.len() - 4]) == chunked::file_crc(&buf);
    if !whole || chunked::file_crc(&buf) != r.crc {
        return Err(std::io::Error::other(format!(
            "{}: chunk {} of level {} is corrupt (CRC mismatch)",
            part.path.display(),
            r.index,
            r.level
        )));
    }
    Ok(buf)
}
