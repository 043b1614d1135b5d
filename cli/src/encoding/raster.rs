//! Rasters coded as their plan says (`fractile_codec::encode::Plan`): whole, or chunk by chunk
//! into a file.

use std::path::Path;

use anyhow::Result;
use fractile_codec::encode::Plan;
use fractile_codec::rows::Rows;
use fractile_codec::{Raster, encode};

use super::args::EncodeArgs;
use crate::progress::Progress;

/// A raster coded in chunks into `output`, as `plan` says.
pub(super) fn encode_chunks(
    a: &EncodeArgs,
    plan: &Plan,
    rows: &mut dyn Rows,
    output: &Path,
) -> Result<fractile_codec::encode::Written> {
    let mut bar = Progress::start("coding chunks", a.quiet || a.json);
    let progress = |done: u64, total: u64| bar.update(done, total);
    let enc = plan.encode_chunks(rows, output, &progress)?;
    bar.finish();
    Ok(enc)
}

/// `raster` coded whole by the codec `plan` names.
pub(super) fn encode_with(
    a: &EncodeArgs,
    plan: &Plan,
    raster: &Raster,
) -> Result<fractile_codec::Encoded> {
    // The quadtree counts the blocks it fits; the other codecs report no progress.
    let quiet = a.quiet || a.json || a.codec() != "quadtree-pifs";
    let mut bar = Progress::start("fitting blocks", quiet);
    let progress = |done: u64, total: u64| bar.update(done, total);
    let enc = encode(raster, plan.settings(), &progress)?;
    bar.finish();
    Ok(enc)
}
