//! Rasters coded by the codec the arguments name: whole, or chunk by chunk into a file.

use std::path::Path;

use anyhow::Result;
use fractile_codec::encode::chunked::{encode_chunked_file, encode_chunked_file_at};
use fractile_codec::io::rows::Rows;
use fractile_codec::{Raster, encode};

use super::args::{EncodeArgs, file_rate};
use crate::progress::Progress;

/// A raster coded in chunks of `c` into `output`: under a file's rate ([`file_rate`]) or each
/// chunk by the settings of `a` with its share of the rate.
pub(super) fn encode_chunks(
    a: &EncodeArgs,
    rows: &mut dyn Rows,
    c: u32,
    output: &Path,
) -> Result<fractile_codec::encode::Written> {
    let (width, height) = (rows.header().width, rows.header().height);
    let mut bar = Progress::start("coding chunks", a.quiet || a.json);
    let progress = |done: u64, total: u64| bar.update(done, total);
    let enc = match file_rate(a, rows.header().kind, rows.header().channels)? {
        Some(rate) => {
            let at = |r: &Raster, q, trial| fractile_codec::encode::rate::encode_at(r, q, trial);
            encode_chunked_file_at(rows, c, (rate, &at), &progress, output)?
        }
        None => {
            let per_chunk = a.chunk_rate(width, height, c);
            let one = |r: &Raster| {
                encode_with(&per_chunk, r, false)
                    .map_err(|e| fractile_codec::Error::settings(e.to_string()))
            };
            encode_chunked_file(rows, c, &one, &progress, output)?
        }
    };
    bar.finish();
    Ok(enc)
}

/// `raster` coded by the codec `a` names (chunked or not, the same settings); `bar`: whether a
/// long quadtree encode shows its own progress bar (not for chunks, which share one).
pub(super) fn encode_with(
    a: &EncodeArgs,
    raster: &Raster,
    bar: bool,
) -> Result<fractile_codec::Encoded> {
    let settings = a.codec_settings(raster.kind)?;
    // The quadtree counts the blocks it fits; the other codecs report no progress.
    let quiet = a.quiet || a.json || !bar || a.codec() != "quadtree-pifs";
    let mut bar = Progress::start("fitting blocks", quiet);
    let progress = |done: u64, total: u64| bar.update(done, total);
    let enc = encode(raster, &settings, &progress)?;
    bar.finish();
    Ok(enc)
}
