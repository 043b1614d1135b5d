//! `fractile encode --part I/N` and `fractile assemble`: a chunked encode split over processes
//! or machines, and its parts joined (`fractile_codec::encode::parts`).

use std::path::{Path, PathBuf};

use anyhow::{Result, bail};
use fractile_codec::encode::Plan;
use fractile_codec::encode::chunked::Share;
use fractile_codec::rows::Rows;
use serde_json::json;

use super::args::EncodeArgs;

/// `encode --part I/N`: one share of a chunked encode into a part file, as `plan` codes it
/// (its fingerprint, which every part must share, in the part file).
pub(super) fn encode_part(
    a: &EncodeArgs,
    plan: &Plan,
    rows: &mut dyn Rows,
    share: Share,
    meter: &super::inputs::Meter,
) -> Result<()> {
    let Some(chunk) = plan.chunk() else {
        bail!("--part splits an encode in chunks, and this one is whole: give --chunk N")
    };
    let mut bar = crate::progress::Progress::start("coding chunks", a.quiet || a.json);
    let progress = |done: u64, total: u64| bar.update(done, total);
    // An s3:// part is written here first, then uploaded: the machines share a bucket.
    let out = crate::remote::Local::output(&a.output)?;
    let w = plan.encode_part(rows, share, out.path(), &progress)?;
    bar.finish();
    out.finish()?;
    let fetched = meter.fetched();
    // One line a part, the summary an operator reads in a pod's log.
    let report = json!({
        "output": a.output, "part": format!("{}/{}", share.index, share.count),
        "chunks": w.chunks, "bytes": w.length, "seconds": w.seconds,
        "fetched_bytes": fetched.map(|f| f.0), "fetched_requests": fetched.map(|f| f.1),
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{} -> {}: part {}/{} of chunks of {chunk}, {} chunks, {} bytes, {:.2} s (join the parts with fractile assemble)",
            a.inputs[0].display(),
            a.output.display(),
            share.index,
            share.count,
            w.chunks,
            w.length,
            w.seconds
        );
    }
    Ok(())
}

/// `fractile assemble`: the part files of a split encode joined into the asset.
pub(crate) fn run_assemble(parts: &[PathBuf], output: &Path, as_json: bool) -> Result<()> {
    // Parts and the asset may be s3:// objects: parts are downloaded, the asset uploaded.
    let local: Vec<crate::remote::Local> = parts
        .iter()
        .map(|p| crate::remote::Local::input(p))
        .collect::<Result<_>>()?;
    let files: Vec<PathBuf> = local.iter().map(|l| l.path().to_path_buf()).collect();
    let out = crate::remote::Local::output(output)?;
    let mut bar = crate::progress::Progress::start("coding overviews", as_json);
    let progress = |done: u64, total: u64| bar.update(done, total);
    let w = fractile_codec::encode::plan::assemble(&files, out.path(), &progress)?;
    bar.finish();
    out.finish()?;
    let m = &w.asset.meta;
    let report = json!({
        "parts": parts, "output": output, "codec": w.asset.codec_name(),
        "width": m.width, "height": m.height, "bytes": w.length, "ratio": w.ratio(),
        "bpp": w.bpp(), "psnr": w.errors.psnr, "rmse": w.errors.rmse,
        "max_error": w.errors.max_error, "seconds": w.seconds,
    });
    if as_json {
        println!("{report}");
    } else {
        println!(
            "{} parts -> {}: {} {}x{}, {} bytes, {:.3} bpp, PSNR {:.2} dB, RMSE {:.3}, max error {:.3}",
            parts.len(),
            output.display(),
            w.asset.codec_name(),
            m.width,
            m.height,
            w.length,
            w.bpp(),
            w.errors.psnr,
            w.errors.rmse,
            w.errors.max_error
        );
    }
    Ok(())
}
