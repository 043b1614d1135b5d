//! The pipeline the lattice codecs share (fractal interpolation surfaces, psa2d): one grey
//! channel normalised, nodata filled and masked, vertices on a lattice, the height step and the
//! spacing chosen, rate control over both.

use fractile_proto::{AssetMeta, ColourModel, SampleFormat};

use crate::Error;
use crate::codecs::coded::{Coded, Measure};
use crate::codecs::source::{coding_range, fill_invalid, source_meta, without_map};
use crate::core::lattice::{Source, interpolation_rmse};
use crate::core::metrics::Errors;
use crate::io::mask::Mask;
use crate::io::raster::Raster;

/// How a lattice codec's vertices are placed and quantised.
pub(crate) struct Lattice {
    /// Samples between vertices.
    pub(crate) spacing: u32,
    /// Vertex height step, source units (`None`: automatic).
    pub(crate) height_step: Option<f64>,
    /// Rate control: overrides `spacing` and the automatic height step.
    pub(crate) target_bpp: Option<f64>,
}

/// How many spacings finer than the first that fits rate control weighs (each costs about eight
/// encodes; fis-bilinear on etopo20 at 32:1 fits first at 6 and is best at 2).
const FINER_SPACINGS: u32 = 4;

/// The pipeline of the lattice codecs (interpolation surfaces, psa2d): one grey channel,
/// normalised, nodata filled (and masked), vertices every `spacing` samples, then measured.
///
/// The automatic height step is the largest power-of-two multiple of the source's quantum under
/// a quarter of the RMS error of bilinear interpolation between the vertices, so quantising them
/// adds under 1/190 of the error's variance (`(1/4)^2 / 12`) while each halving would cost a bit
/// per vertex for nothing.
///
/// Rate control: the spacing moves the size in steps (x2.25 from 2 to 3) and the height step
/// fills in between. The smallest spacing that fits at its own height step is weighed against
/// up to [`FINER_SPACINGS`] finer spacings, each with the finest coarser height step that fits
/// (eighth-octave steps, found by bisection); the best PSNR wins. Coarse heights on a fine
/// lattice often beat fine heights on a coarse one: etopo20 at 32:1 scored 36.5 dB at spacing 3
/// and its own step, 39.5 dB at spacing 2 with a 235 m step (before the heights' rounding).
/// Weighing only the next finer spacing missed that: spacing 4 fits first there. Under rate
/// control `build` gets the byte budget, so that a codec with choices of its own (the FIS
/// scalings' shrink) takes the best one that fits.
pub(crate) fn encode_lattice(
    raster: &Raster,
    lattice: &Lattice,
    measure: &dyn Measure,
    build: impl Fn(&Source, u32, f32, &AssetMeta, Option<Mask>, Option<usize>) -> Result<Coded, Error>,
) -> Result<(Coded, Errors), Error> {
    if raster.channels.len() != 1 {
        return Err(Error::settings(format!(
            "this codec codes one grey channel; the input has {} (use quadtree-pifs for colour)",
            raster.channels.len()
        )));
    }
    let (w, h) = (raster.width, raster.height);
    if w < 2 || h < 2 {
        return Err(Error::input(format!(
            "a {w}x{h} grid is too small for a vertex lattice (2x2 at least)"
        )));
    }
    let (lo, hi) = coding_range(raster);
    let span = hi - lo;
    let mut values: Vec<f32> = raster.channels[0]
        .iter()
        .map(|&x| ((x as f64 - lo) / span).clamp(0.0, 1.0) as f32)
        .collect();
    let valid = raster.valid.clone().unwrap_or_else(|| vec![true; w * h]);
    fill_invalid(&mut values, &valid, w, h);
    let quantum = match raster.sample {
        SampleFormat::F32 => span / 65535.0,
        _ => 1.0,
    };
    let source = Source {
        width: w,
        height: h,
        values: &values,
    };
    let mask = raster.valid.as_ref().map(|v| Mask::new(w, h, v.clone()));
    let meta = source_meta(raster, String::new(), (lo, hi), ColourModel::Grey);
    let auto_step = |spacing: u32| {
        lattice.height_step.unwrap_or_else(|| {
            let limit = interpolation_rmse(&source, spacing) as f64 * span / 4.0;
            let mut step = quantum;
            while step * 2.0 <= limit {
                step *= 2.0;
            }
            step
        })
    };
    let make = |spacing: u32, step: f64, budget: Option<usize>| {
        let height_step = ((step / span) as f32).clamp(1e-9, 1.0);
        build(&source, spacing, height_step, &meta, mask.clone(), budget)
    };
    let coded = match lattice.target_bpp {
        None => {
            let k = lattice.spacing.max(1);
            make(k, auto_step(k), None)?
        }
        Some(bpp) => {
            // The source-error map comes on top of what is fitted here.
            let max_bytes = without_map((bpp * (w * h) as f64 / 8.0).floor() as usize);
            let largest = (w.max(h) - 1).clamp(1, 4096) as u32;
            let mut found = None;
            for k in 1..=largest {
                let a = make(k, auto_step(k), Some(max_bytes))?;
                if a.file_size() <= max_bytes {
                    found = Some((k, a));
                    break;
                }
            }
            let Some((k, a)) = found else {
                return Err(Error::settings(format!(
                    "nothing fits in {bpp} bits per pixel (the coarsest lattice takes more)"
                )));
            };
            let (a, errors) = a.errors(raster, measure);
            let mut best = (errors.psnr, a);
            if lattice.height_step.is_none() {
                for finer in (k.saturating_sub(FINER_SPACINGS).max(1)..k).rev() {
                    // Steps base * 2^(m/8): m = 0 did not fit (the spacing is under k), find
                    // the smallest m that does (sizes fall as the step grows).
                    let base = auto_step(finer);
                    let step = |m: u32| base * (f64::from(m) / 8.0).exp2();
                    let (mut lo, mut hi) = (0u32, 8 * 12);
                    let mut fit = make(finer, step(hi), Some(max_bytes))?;
                    if fit.file_size() > max_bytes {
                        continue;
                    }
                    while hi - lo > 1 {
                        let mid = (lo + hi) / 2;
                        let a = make(finer, step(mid), Some(max_bytes))?;
                        if a.file_size() <= max_bytes {
                            (hi, fit) = (mid, a);
                        } else {
                            lo = mid;
                        }
                    }
                    // No early stop on a lower PSNR: with per-node or per-cell scalings the
                    // best can lie past a worse spacing.
                    let (fit, errors) = fit.errors(raster, measure);
                    if errors.psnr > best.0 {
                        best = (errors.psnr, fit);
                    }
                }
            }
            best.1
        }
    };
    let (coded, errors) = coded.errors(raster, measure);
    Ok((measure.kept(coded, raster, &errors), errors))
}
