//! `fractile encode --part I/N` and `fractile assemble`: a chunked encode split over processes
//! or machines, and its parts joined (`fractile_codec::encode::parts`).

use std::path::{Path, PathBuf};

use anyhow::Result;
use fractile_codec::Raster;
use fractile_codec::encode::chunked::Share;
use fractile_codec::io::rows::Rows;
use serde_json::json;

use super::args::{EncodeArgs, file_rate};
use super::raster::encode_with;
use fractile_codec::encode::parts::{encode_chunked_part, encode_chunked_part_at};

/// `encode --part I/N`: one share of a chunked encode into a part file.
pub(super) fn encode_part(
    a: &EncodeArgs,
    rows: &mut dyn Rows,
    chunk: u32,
    share: Share,
) -> Result<()> {
    // The settings every part must share: the arguments less what names this part's files.
    let settings = format!(
        "{:?}",
        EncodeArgs {
            inputs: Vec::new(),
            output: PathBuf::new(),
            part: None,
            json: false,
            roi: a.roi.clone(),
            codec: a.codec.clone(),
            ..*a
        }
    );
    let mut bar = crate::progress::Progress::start("coding chunks", a.quiet || a.json);
    let progress = |done: u64, total: u64| bar.update(done, total);
    // An s3:// part is written here first, then uploaded: the machines share a bucket.
    let out = crate::remote::Local::output(&a.output)?;
    let (width, height) = (rows.header().width, rows.header().height);
    let w = match file_rate(a, rows.header().kind, rows.header().channels)? {
        Some(rate) => {
            let at = |r: &Raster, q, trial| fractile_codec::encode::rate::encode_at(r, q, trial);
            let how = (chunk, share, settings.as_str());
            encode_chunked_part_at(rows, how, (rate, &at), &progress, out.path())?
        }
        None => {
            let per_chunk = a.chunk_rate(width, height, chunk);
            let one = |r: &Raster| {
                encode_with(&per_chunk, r, false)
                    .map_err(|e| fractile_codec::Error::settings(e.to_string()))
            };
            encode_chunked_part(rows, (chunk, share, &settings), &one, &progress, out.path())?
        }
    };
    bar.finish();
    out.finish()?;
    let report = json!({
        "output": a.output, "part": format!("{}/{}", share.index, share.count),
        "chunks": w.chunks, "bytes": w.length, "seconds": w.seconds,
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
    let w = fractile_codec::encode::parts::assemble(&files, out.path())?;
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
