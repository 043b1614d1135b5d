//! `fractile encode`: rasters (quadtree PIFS, projected, FIS, psa2d) into assets, and with `shapes`
//! meshes (IFS3D) and curves.

use super::*;
use fractile_codec::encode::Plan;
use fractile_codec::encode::chunked::Share;

use crate::progress::Progress;

mod args;
mod inputs;
mod parts;
mod raster;
mod shapes;
pub(crate) use args::*;
use parts::encode_part;
pub(crate) use parts::run_assemble;
use raster::{encode_chunks, encode_with};
pub(crate) use shapes::*;

pub(crate) fn run_encode(a: EncodeArgs) -> Result<()> {
    if is_mesh(&a.inputs[0]) {
        return encode_volume(&a);
    }
    if (is_geojson(&a.inputs[0]) && !inputs::is_stac(&a.inputs[0]))
        || a.codec.as_deref() == Some("curve")
    {
        return encode_curve(&a);
    }
    // Rows, not a raster: a chunked encode reads its input a band at a time.
    let mut inputs = inputs::open(&a.inputs, a.target_grid.as_deref())?;
    let files = inputs.names.clone();
    let meter = inputs.meter();
    let rows = &mut inputs.rows;
    let (width, height) = (rows.header().width, rows.header().height);
    let a = a.with_default_codec(rows.header().kind);
    // The codec, its flags and the chunks, checked before anything is read.
    if a.codec() == "curve" {
        bail!("--codec curve is for GeoJSON input");
    }
    let plan = Plan::new(a.codec(), &a.options(), a.chunk, rows.header())?;
    if let Some(text) = &a.part {
        return encode_part(&a, &plan, rows.as_mut(), Share::parse(text)?, &meter);
    }
    // An s3:// output is written here first, then uploaded.
    let out = crate::remote::Local::output(&a.output)?;
    let enc = match plan.chunk() {
        None => {
            // The quadtree counts its blocks in a bar of its own; the other codecs get one that
            // shows how long they have run.
            let quadtree = a.codec() == "quadtree-pifs";
            let mut bar = Progress::start("coding", a.quiet || a.json || quadtree);
            let lineage = rows.header().lineage.clone();
            let enc = encode_with(&a, &plan, &rows.read_all()?)?.with_lineage(lineage.as_deref());
            bar.finish();
            enc.write(out.path())?
        }
        Some(_) => encode_chunks(&a, &plan, rows.as_mut(), out.path())?,
    };
    out.finish()?;
    let (fetched, requests) = inputs.fetched();
    let report = json!({
        "input": a.inputs[0], "inputs": files, "output": a.output, "codec": enc.asset.codec_name(),
        // Inputs of another pixel size or alignment, resampled onto the finest input's grid
        // (bilinear; each cell between the input cells it is made of).
        "resampled_inputs": inputs.resampled,
        // Read by range (remote inputs): what crossed the network.
        "fetched_bytes": inputs.remote().then_some(fetched),
        "fetched_requests": inputs.remote().then_some(requests),
        "width": width, "height": height,
        "bytes": enc.length, "source_bytes": enc.asset.meta.source_bytes(),
        "ratio": enc.ratio(), "bpp": enc.bpp(), "transforms": enc.transforms,
        "seconds": enc.seconds, "psnr": enc.errors.psnr, "rmse": enc.errors.rmse,
        "max_error": enc.errors.max_error,
        // As asked, or what a bounded rate found (the promise the asset keeps, with the
        // f32 slack the server adds).
        "max_error_bound": a.max_error.or_else(|| {
            enc.asset.planes().first().and_then(|p| p.promise()).map(f64::from)
        }),
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{}{} -> {}: {} {} bytes, {:.2}:1, {:.3} bpp, {} transforms, {:.2} s, PSNR {:.2} dB, RMSE {:.3}, max error {:.3}",
            a.inputs[0].display(),
            if files.len() > 1 {
                format!(" (a mosaic of {} files, {}x{})", files.len(), width, height)
            } else {
                String::new()
            },
            a.output.display(),
            enc.asset.codec_name(),
            enc.length,
            enc.ratio(),
            enc.bpp(),
            enc.transforms,
            enc.seconds,
            enc.errors.psnr,
            enc.errors.rmse,
            enc.errors.max_error
        );
    }
    Ok(())
}
