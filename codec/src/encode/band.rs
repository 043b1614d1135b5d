//! One part of a split encode (`fractile encode --part I/N`, [`Share`]): a band of the
//! source's rows of chunks, read once and coded, and the band's rows of the first coded
//! overview level handed on to `fractile assemble`, which codes the overviews
//! (`encode::assembly`; the part file's format is `encode::parts`).
//!
//! A part reads only its band's rows (and a chunk's overlap beyond them), so the parts of a
//! split encode read each input once between them, where parts that each coded a share of
//! every level each read every input (4 parts fetched 4.0 times the inputs' bytes). The
//! overview rows a part hands on are its own rows box-averaged as the pyramid averages them
//! (`encode::pyramid`): a band starts on a chunk row, a multiple of every power of two up to
//! the handed level, so its averages are the whole raster's, and the assembled file is the
//! bytes of the encode in one process.

use std::time::Instant;

use super::chunked::{Levels, Progress, Share, Streamed, checked_header, read_levels};
use super::pyramid::{Level, halve};
use super::spill::Spill;
use super::summary::blank;
use super::tally::Tally;
use super::views::{EncodeLevel, viewed};
use crate::Error;
use crate::io::raster::Raster;
use crate::io::rows::Rows;

/// The rows of one overview level a part hands on: level `level`'s rows `top..top + rows`,
/// in `spill` from its start, [`row_bytes`] a row.
pub(super) struct Handoff {
    pub(super) level: usize,
    pub(super) top: u32,
    pub(super) rows: u32,
    pub(super) spill: Spill,
    pub(super) length: u64,
    /// The CRC-32 of the rows' bytes.
    pub(super) crc: u32,
}

/// Bytes of one handed row of `width` cells and `channels`: each channel's cells as
/// little-endian f32, then a byte a cell, 1 where it holds data.
pub(super) fn row_bytes(width: usize, channels: usize) -> u64 {
    (width * (4 * channels + 1)) as u64
}

/// Handed rows (whole rows of `width` cells, [`row_bytes`] each) back as channels and
/// validity.
pub(super) fn read_rows(bytes: &[u8], width: usize, channels: usize) -> (Vec<Vec<f32>>, Vec<bool>) {
    let n = bytes.len() / row_bytes(width, channels) as usize;
    let mut planes = vec![Vec::with_capacity(n * width); channels];
    let mut valid = Vec::with_capacity(n * width);
    for row in bytes.chunks_exact(row_bytes(width, channels) as usize) {
        for (c, plane) in planes.iter_mut().enumerate() {
            let cells = &row[4 * width * c..4 * width * (c + 1)];
            plane.extend(
                cells
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            );
        }
        valid.extend(row[4 * width * channels..].iter().map(|&b| b != 0));
    }
    (planes, valid)
}

/// `raster`'s rows as [`row_bytes`] lays them down, appended to `spill`.
fn hand_on(raster: &Raster, spill: &mut Spill, crc: &mut crc32fast::Hasher) -> Result<u64, Error> {
    let w = raster.width;
    let mut bytes =
        Vec::with_capacity(row_bytes(w, raster.channels.len()) as usize * raster.height);
    for y in 0..raster.height {
        for c in &raster.channels {
            for v in &c[y * w..(y + 1) * w] {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
        bytes.extend(
            (y * w..(y + 1) * w).map(|i| u8::from(raster.valid.as_ref().is_none_or(|v| v[i]))),
        );
    }
    crc.update(&bytes);
    spill
        .push(&bytes)
        .map_err(|e| Error::output(format!("spilling overview rows: {e}")))?;
    Ok(bytes.len() as u64)
}

/// The first overview level that is coded (the views are not), if the file has one.
pub(super) fn first_coded(levels: usize, views: usize) -> Option<usize> {
    (views + 1 < levels).then_some(views + 1)
}

/// The level-0 chunks of `share`'s band of the raster `rows` reads, coded by `encode_one` on
/// all cores into `spill` as their rows arrive; and the band's rows of the first coded
/// overview level, box-averaged from its own rows, into `handoff`.
pub(super) fn code_band(
    rows: &mut dyn Rows,
    (chunk, share): (u32, Share),
    work: (&EncodeLevel<'_>, &Progress<'_>),
    (spill, mut handoff): (&mut Spill, Spill),
) -> Result<(Streamed, Option<Handoff>), Error> {
    let start = Instant::now();
    let header = checked_header(rows, chunk)?;
    let Levels {
        viewed,
        sizes,
        views,
        table,
    } = Levels::of(&header, chunk, viewed(&header, work.0));
    let (w, h) = sizes[0];
    let (nx, ny) = table.grid(w, h);
    let band = share.rows(ny)?;
    let level = first_coded(sizes.len(), views);
    let wants = |l: usize, i: u32| l == 0 && band.contains(&(i / nx));
    let mut tally = Tally::new((&blank(&table, &sizes), views), &wants, work, spill);
    let cells = |row: u32| table.coded_cells(w, h, 0, row);
    let span = cells(band.start)[1] as usize..cells(band.end - 1)[3] as usize;
    let mut held = Level::new(header.clone(), span.start);
    let (mut next, mut handed, mut length) = (band.start, 0u32, 0u64);
    let mut crc = crc32fast::Hasher::new();
    read_levels(rows, &header, span, &mut |read| {
        held.append(read);
        while next < band.end && held.bottom() >= cells(next)[3] as usize {
            for cx in 0..nx {
                let part = held.crop(table.coded_cells(w, h, cx, next));
                tally.push(0, next * nx + cx, part)?;
            }
            if let Some(level) = level {
                // The chunk row's own rows (the last takes the raster's remainder), averaged
                // down to the handed level.
                let end = if next + 1 == ny {
                    h
                } else {
                    (next + 1) * chunk
                };
                let mut own = held.crop([0, next * chunk, w, end]);
                for _ in 0..level {
                    own = halve(&own);
                }
                handed += own.height as u32;
                length += hand_on(&own, &mut handoff, &mut crc)?;
            }
            next += 1;
            if next < band.end {
                held.release(cells(next)[1] as usize);
            }
        }
        Ok(())
    })?;
    tally.flush()?;
    let handoff = level.map(|level| Handoff {
        level,
        top: (band.start * chunk) >> level,
        rows: handed,
        spill: handoff,
        length,
        crc: crc.finalize(),
    });
    Ok((
        Streamed {
            header,
            sizes,
            viewed,
            records: tally.records,
            start,
        },
        handoff,
    ))
}
