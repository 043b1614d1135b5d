//! The pipeline of the projected codec ([`crate::codecs::projected`]): one grey channel in source
//! units, nodata filled (and masked, its details forced to zero), then either a bound on the
//! error at every valid sample or a size, and measured like every asset.

use rayon::prelude::*;

use fractile_proto::{AssetKind, ColourModel};

use crate::Error;
use crate::codecs::coded::PlaneEncoder;
use crate::codecs::coded::{Coded, Measure};
use crate::codecs::plane::Build;
use crate::codecs::projected::bound::{
    check_bound, delivery_margin, finest_bound, max_error_step, source_quantum,
};
use crate::codecs::projected::pyramid::Order;
use crate::codecs::projected::{
    self, CODEC_NAME, ProjectedHeader, ProjectedSettings, encode_grid, levels_for,
};
use crate::codecs::registry::Coding;
use crate::codecs::source::{coding_range, fill_invalid, source_meta, source_planes, without_map};
use crate::core::metrics::Errors;
use crate::io::mask::Mask;
use crate::io::raster::Raster;
use crate::render::colour::rgb_to_ycbcr;

/// Rate control's bisection steps on log(step): 2^-14 of the range of steps tried, far finer than
/// a byte of difference.
const BISECTIONS: u32 = 18;

/// Encodes a grey image or a height field with the projected IFS with details: under
/// `settings.max_error` every valid decoded sample is within it of the source; under
/// `settings.target_bpp` the finest step whose file fits is kept.
fn encode_projected(
    raster: &Raster,
    settings: &ProjectedSettings,
    measure: &dyn Measure,
) -> Result<(Coded, Errors), Error> {
    let target_bpp = settings.target_bpp;
    // The streams get the rate less an allowance for the rest of the file, which a nodata
    // mask can overrun (a warped DEM's mask took 1.8% of its 0.8 bpp): a file over the rate
    // is coded again with the streams' budget less the excess. And a file more than 1% under
    // it is coded once more with the slack given to the streams (the allowance is a guess:
    // jacksboro at 0.2 bpp left 6% of its bytes unused, about 0.4 dB).
    let limit = target_bpp
        .filter(|_| settings.max_error.is_none() && settings.at_step.is_none())
        .map(|b| (b * (raster.width * raster.height) as f64 / 8.0).floor() as usize);
    let all = designs(settings);
    let Some(limit) = limit else {
        return encode_within((raster, measure), settings, target_bpp, (0, &all));
    };
    let mut shift = 0i64;
    let mut kept: Option<(Coded, Errors, usize)> = None;
    // Once a file fits, passes for the slack code its design alone.
    let mut tried = all.clone();
    for _ in 0..4 {
        let (coded, errors) =
            encode_within((raster, measure), settings, target_bpp, (shift, &tried))?;
        let len = coded.file_size();
        if len > limit {
            shift += (len - limit) as i64 + 8;
            continue;
        }
        let first_within = kept.is_none();
        // Of two files within the rate, the larger one has the finer step.
        if kept.as_ref().is_none_or(|k| len > k.2) {
            kept = Some((coded, errors, len));
        }
        let slack = limit - len;
        if first_within && slack > limit / 100 + 16 {
            shift -= slack as i64 - 8;
            tried = kept.as_ref().map_or(all.clone(), |k| vec![design_of(&k.0)]);
            continue;
        }
        break;
    }
    match kept {
        Some((coded, errors, _)) => Ok((coded, errors)),
        None => encode_within((raster, measure), settings, target_bpp, (shift, &all)),
    }
}

/// The streams' budget for a rate, `shift` bytes less (or more, if negative).
fn shifted(bpp: f64, raster: &Raster, shift: i64) -> Result<usize, Error> {
    let budget = rate_budget(bpp, raster)? as i64 - shift;
    Ok(budget.max(0) as usize)
}

/// [`encode_projected`] with the streams' budget `shift` bytes under the rate's (over it if
/// negative), trying the `designs` given under a rate.
fn encode_within(
    (raster, measure): (&Raster, &dyn Measure),
    settings: &ProjectedSettings,
    target_bpp: Option<f64>,
    (shift, designs): (i64, &[Option<Order>]),
) -> Result<(Coded, Errors), Error> {
    let (w, h) = (raster.width, raster.height);
    if w < 2 || h < 2 {
        return Err(Error::input(format!(
            "a {w}x{h} grid is too small (2x2 at least)"
        )));
    }
    if raster.channels.len() != 1 {
        if settings.at_step.is_some() {
            return Err(Error::settings(
                "a fixed step codes one channel (colour takes a rate)",
            ));
        }
        return encode_colour((raster, measure), settings, target_bpp, (shift, designs));
    }
    let (lo, hi) = coding_range(raster);
    let span = hi - lo;
    // Filled where invalid (the fill only steers predictions: those samples are not coded).
    let mut filled = raster.channels[0].clone();
    if let Some(valid) = &raster.valid {
        fill_invalid(&mut filled, valid, w, h);
    }
    let source: Vec<f64> = filled.iter().map(|&v| f64::from(v)).collect();
    let valid = raster.valid.as_deref();
    let quantum = source_quantum(raster);
    let mut header = plane_header(w, h, quantum, (lo, span));
    let (stream, grid) = match (settings.max_error, target_bpp) {
        (None, _) if settings.at_step.is_some() => {
            let at = settings.at_step.expect("matched");
            header.growth = settings.growth;
            header.quantum = 0.0;
            header.step = at.step;
            let quantising = (settings.dead_zone, settings.lambda);
            match at.design {
                Some(order) => {
                    header.order = order;
                    encode_grid(&header, &source, valid, quantising)
                }
                None => smaller_order(&mut header, &source, valid, quantising),
            }
        }
        (None, Some(bpp)) if settings.bounded => {
            let budget = shifted(bpp, raster, shift)?;
            let (e, coded) = fit_bound(&mut header, (&source, valid), budget, span);
            check_bound(&coded.1, &source, valid, e, span)?;
            coded
        }
        (Some(e), _) => code_to_bound(&mut header, (&source, valid), e, span)?,
        (None, Some(bpp)) => {
            header.growth = settings.growth;
            // No promise to keep at each sample: steps and predictions need not sit on the
            // quantum, and rate control then moves in fine steps.
            header.quantum = 0.0;
            let budget = shifted(bpp, raster, shift)?;
            // Each design on its own core (their bisections are independent).
            let tries: Vec<(f64, ProjectedHeader, Stream)> = designs
                .par_iter()
                .map(|&lifted| {
                    let mut planes = [(header.clone(), source.as_slice(), valid, 1.0)];
                    let quantising = (settings.dead_zone, settings.lambda);
                    let coded = fit_size(&mut planes, quantising, budget, (span, lifted));
                    let coded = coded.into_iter().next().expect("one plane");
                    let error = squared_error(&coded.1, &source, valid);
                    (error, planes[0].0.clone(), coded)
                })
                .collect();
            let best = tries.into_iter().min_by(|a, b| a.0.total_cmp(&b.0));
            let (_, kept, coded) = best.expect("a design tried");
            header = kept;
            coded
        }
        (None, None) => {
            return Err(Error::settings(
                "projected takes --max-error (source units) or --target-bpp",
            ));
        }
    };
    header.roughness = continued_roughness(raster, &grid, w, h);
    let mut meta = source_meta(raster, String::new(), (lo, hi), ColourModel::Grey);
    meta.encoder = format!(
        "{CODEC_NAME} levels={} order={:?} step={} quantum={} max_error={} roughness={:.3}",
        header.levels,
        header.order,
        header.step,
        header.quantum,
        header.max_error,
        header.roughness
    );
    let mask = raster.valid.as_ref().map(|v| Mask::new(w, h, v.clone()));
    let coded = Coded::new(meta, vec![(header, stream)], mask, Build::Whole)?;
    let (coded, errors) = coded.errors(raster, measure);
    if settings.trial {
        return Ok((coded, errors));
    }
    Ok((measure.kept(coded, raster, &errors), errors))
}

/// The multiresolutions rate mode tries, the best kept (`None` is the closed-loop pyramid): both
/// lifted kernels (the fitted one codes DEMs best, CDF 9/7 photographs) and the pyramid, which
/// wins at high rates on images with large flat areas (held-out moon.png at 2 bpp: 57.15 dB
/// against 54.99; measured in docs/benchmarks.md). `settings.pyramid`: the pyramid alone.
fn designs(settings: &ProjectedSettings) -> Vec<Option<Order>> {
    if settings.pyramid {
        vec![None]
    } else {
        vec![
            Some(Order::LiftedTwoRate),
            Some(Order::Lifted97TwoRate),
            None,
        ]
    }
}

/// The design an asset's first plane was coded with, as [`designs`] names it.
fn design_of(coded: &Coded) -> Option<Order> {
    match &coded.planes[0].coding {
        Coding::Projected { header, .. } => header.order.lifting().map(|_| header.order),
        _ => None,
    }
}

/// The summed squared error of the valid decoded samples.
fn squared_error(grid: &[f64], source: &[f64], valid: Option<&[bool]>) -> f64 {
    grid.iter()
        .zip(source)
        .enumerate()
        .filter(|(i, _)| valid.is_none_or(|v| v[*i]))
        .map(|(_, (g, s))| (g - s) * (g - s))
        .sum()
}

/// Max-error mode: every valid sample within `e` of the source, under the order that codes
/// it smaller.
fn code_to_bound(
    header: &mut ProjectedHeader,
    (source, valid): (&[f64], Option<&[bool]>),
    e: f64,
    span: f64,
) -> Result<Stream, Error> {
    let finest = finest_bound(span);
    if header.quantum == 0.0 && e < finest {
        return Err(Error::settings(format!(
            "--max-error {e} is finer than float32 samples over this range hold ({finest:e}): \
             ask at least that"
        )));
    }
    let margin = delivery_margin(header.value_min, header.value_span);
    header.step = max_error_step(e, header.quantum, margin)?;
    header.max_error = e;
    let (stream, grid) = smaller_order(header, source, valid, (0.0, 0.0));
    check_bound(&grid, source, valid, e, span)?;
    Ok((stream, grid))
}

/// A coded stream and the samples it decodes to.
type Stream = (Vec<u8>, Vec<f64>);

/// Codes under both orders of the passes and keeps the smaller (the order goes in `header`).
fn smaller_order(
    header: &mut ProjectedHeader,
    source: &[f64],
    valid: Option<&[bool]>,
    quantising: (f64, f64),
) -> (Vec<u8>, Vec<f64>) {
    let mut best: Option<(Order, Stream)> = None;
    for order in Order::PYRAMIDS {
        header.order = order;
        let coded = encode_grid(header, source, valid, quantising);
        if best.as_ref().is_none_or(|b| coded.0.len() < b.1.0.len()) {
            best = Some((order, coded));
        }
    }
    let (order, coded) = best.expect("two orders tried");
    header.order = order;
    coded
}

/// One plane under rate control: its header, its source (plane units), validity, and its step
/// as a multiple of the shared one.
type RatePlane<'a> = (ProjectedHeader, &'a [f64], Option<&'a [bool]>, f64);

/// Rate mode: the smallest step, shared by every plane (bisection on its logarithm), whose
/// streams fit `budget` bytes together; each plane takes the lifted kernel given, or with the
/// pyramid (`None`) first the order that codes a middling step smaller. One step for all planes spends bits where they lower the summed
/// squared error most (equal slopes), as the quadtree's one lambda does.
fn fit_size(
    planes: &mut [RatePlane<'_>],
    quantising: (f64, f64),
    budget: usize,
    (span, lifted): (f64, Option<Order>),
) -> Vec<Stream> {
    for (header, source, valid, scale) in planes.iter_mut() {
        header.step = span * 1e-3 * *scale;
        match lifted {
            Some(order) => header.order = order,
            None => {
                smaller_order(header, source, *valid, quantising);
            }
        }
    }
    let (mut lo, mut hi) = ((span * 1e-6).ln(), span.ln());
    let mut try_step = |step: f64| -> Vec<Stream> {
        planes
            .iter_mut()
            .map(|(header, source, valid, scale)| {
                header.step = step * *scale;
                encode_grid(header, source, *valid, quantising)
            })
            .collect()
    };
    let bytes = |c: &[Stream]| c.iter().map(|c| c.0.len()).sum::<usize>();
    let finest = try_step(lo.exp());
    if bytes(&finest) <= budget {
        return finest;
    }
    let mut best = try_step(hi.exp());
    for _ in 0..BISECTIONS {
        let mid = 0.5 * (lo + hi);
        let coded = try_step(mid.exp());
        if bytes(&coded) <= budget {
            (hi, best) = (mid, coded);
        } else {
            lo = mid;
        }
    }
    // The headers hold the last step tried: put back the one kept.
    try_step(hi.exp());
    best
}

/// Bounded rate: the smallest max error (the step of max-error mode) whose stream fits
/// `budget` bytes, by bisection: on whole quanta for a source on a quantum (so the bound is
/// JPEG-LS's odd steps), on the logarithm otherwise. The order is the one that codes a middling
/// bound smaller. Returns the bound kept (also in `header.max_error`) and its stream.
fn fit_bound(
    header: &mut ProjectedHeader,
    (source, valid): (&[f64], Option<&[bool]>),
    budget: usize,
    span: f64,
) -> (f64, Stream) {
    let quantum = header.quantum;
    let margin = delivery_margin(header.value_min, header.value_span);
    let (mut lo, mut hi) = if quantum > 0.0 {
        (0.0, (span / quantum).ceil().max(1.0))
    } else {
        ((span * 1e-6).ln(), span.ln())
    };
    let bound = |x: f64| if quantum > 0.0 { x * quantum } else { x.exp() };
    // The order: the one that codes a bound of 1/1000 of the range smaller.
    let middling = (span * 1e-3).max(quantum);
    header.step = max_error_step(middling, quantum, margin).expect("a positive bound");
    header.max_error = middling;
    smaller_order(header, source, valid, (0.0, 0.0));
    let mut try_bound = |e: f64| -> Stream {
        header.step = max_error_step(e, quantum, margin).expect("a bound >= 0 on a quantum or > 0");
        header.max_error = e;
        encode_grid(header, source, valid, (0.0, 0.0))
    };
    let finest = try_bound(bound(lo));
    // A constant plane is coded at the finest bound whatever the rate: it costs a few bytes at
    // any bound, and a tiny raster (whose header alone is over the rate) decoded a constant 7
    // as 6. So is any plane that a coarser bound codes no smaller.
    let constant = {
        let mut cells = source
            .iter()
            .enumerate()
            .filter(|(i, _)| valid.is_none_or(|v| v[*i]));
        let first = cells.next().map(|(_, v)| *v);
        cells.all(|(_, v)| Some(*v) == first)
    };
    if finest.0.len() <= budget || constant {
        return (bound(lo), finest);
    }
    let mut best = try_bound(bound(hi));
    if best.0.len() >= finest.0.len() {
        let e = bound(lo);
        header.step = max_error_step(e, quantum, margin).expect("a bound tried");
        header.max_error = e;
        return (e, finest);
    }
    let mut steps = 0;
    while steps < BISECTIONS && (quantum == 0.0 || hi - lo > 1.0) {
        let mid = if quantum > 0.0 {
            (0.5 * (lo + hi)).floor()
        } else {
            0.5 * (lo + hi)
        };
        let coded = try_bound(bound(mid));
        if coded.0.len() <= budget {
            (hi, best) = (mid, coded);
        } else {
            lo = mid;
        }
        steps += 1;
    }
    // The header holds the last bound tried: put back the one kept.
    let e = bound(hi);
    header.step = max_error_step(e, quantum, margin).expect("a bound kept");
    header.max_error = e;
    (e, best)
}

/// The roughness the surface continues with past its finest level: the fitted one for a
/// height field (terrain keeps its roughness at every scale, which is what deeper-than-the-
/// source tiles show), none for an image, which past its pixels is the bilinear surface
/// through its decoded samples. Why: an image's roughness sits at its edges and textures, and
/// continued through the operator's even-aligned 2 x 2 blocks it draws their lattice (camera
/// at 8x: steps between neighbours piled 2.2 times their mean on the even samples' phase,
/// a grid of small squares in textured areas; issue 77 asks that a zoomed image stay smooth).
fn continued_roughness(raster: &Raster, grid: &[f64], w: usize, h: usize) -> f32 {
    match raster.kind {
        AssetKind::Image => 0.0,
        _ => projected::fit_roughness(grid, w, h),
    }
}

/// What a unit of error in Y, Cb and Cr adds to the squared error summed over R, G and B: the
/// sums of the squared weights of each plane in the conversion back (`1 + 1 + 1`,
/// `0.344136^2 + 1.772^2`, `1.402^2 + 0.714136^2`).
const RGB_WEIGHTS: [f64; 3] = [3.0, 3.258, 2.476];

/// A plane's step as a multiple of luma's, so that a step costs each plane the same squared
/// RGB error per coded sample (equal slopes): `sqrt(w_Y / (w_k * area))`, `area` the pixels one
/// of its samples covers (4 for chroma at half resolution). Measured on astronaut against the
/// 0.5 used before for chroma at either resolution: the same at 0.25-0.5 bpp, +0.5-0.7 dB at 2
/// bpp (full-resolution chroma then wins).
fn plane_step_scale(k: usize, pixels: usize, samples: usize) -> f64 {
    let area = pixels as f64 / samples as f64;
    (RGB_WEIGHTS[0] / (RGB_WEIGHTS[k] * area)).sqrt()
}

/// A plane to code: its width, height and values (normalised).
type Plane = (usize, usize, Vec<f32>);

/// Colour under rate control: luma and chroma (the YCbCr planes of the quadtree), one shared
/// step scaled per plane by [`plane_step_scale`]. Chroma at half and at full resolution, and
/// each multiresolution of [`designs`], are all coded and the best kept: half resolution wins at
/// low rates, but caps the PSNR at high ones (astronaut: 37.6 dB at 2 bpp with the pyramid,
/// where JPEG 2000 reaches 40.7).
fn encode_colour(
    (raster, measure): (&Raster, &dyn Measure),
    settings: &ProjectedSettings,
    target_bpp: Option<f64>,
    (shift, designs): (i64, &[Option<Order>]),
) -> Result<(Coded, Errors), Error> {
    let Some(bpp) = target_bpp.filter(|_| settings.max_error.is_none()) else {
        return Err(Error::settings(
            "--max-error bounds one channel: projected codes colour under --target-bpp",
        ));
    };
    let budget = shifted(bpp, raster, shift)?;
    let (lo, hi, colour, half) = source_planes(raster);
    let (w, h) = (raster.width, raster.height);
    let full: Vec<Plane> = rgb_to_ycbcr(&raster.channels, hi as f32)
        .into_iter()
        .map(|c| {
            let v = c
                .iter()
                .map(|&x| ((x - lo as f32) / (hi - lo) as f32).clamp(0.0, 1.0));
            (w, h, v.collect())
        })
        .collect();
    let half: Vec<Plane> = half
        .into_iter()
        .map(|p| (p.width, p.height, p.values))
        .collect();
    let tries: Vec<(Vec<Plane>, Option<Order>)> = [half, full]
        .into_iter()
        .flat_map(|planes| designs.iter().map(move |&d| (planes.clone(), d)))
        .collect();
    // Each resolution and design on its own core.
    let coded: Vec<(Coded, Errors)> = tries
        .into_par_iter()
        .map(|(planes, lifted)| {
            let sources: Vec<Vec<f64>> = planes
                .iter()
                .map(|p| p.2.iter().map(|&v| f64::from(v)).collect())
                .collect();
            let mut rate: Vec<RatePlane<'_>> = planes
                .iter()
                .zip(&sources)
                .enumerate()
                .map(|(k, (p, src))| {
                    let mut header = plane_header(p.0, p.1, 0.0, (0.0, 1.0));
                    header.growth = settings.growth;
                    let scale = plane_step_scale(k, w * h, p.0 * p.1);
                    (header, src.as_slice(), None, scale)
                })
                .collect();
            let quantising = (settings.dead_zone, settings.lambda);
            let coded = fit_size(&mut rate, quantising, budget, (1.0, lifted));
            let parts: Vec<(ProjectedHeader, Vec<u8>)> = rate
                .into_iter()
                .zip(coded)
                .zip(&planes)
                .map(|(((mut header, ..), (stream, grid)), p)| {
                    header.roughness = continued_roughness(raster, &grid, p.0, p.1);
                    (header, stream)
                })
                .collect();
            let mut meta = source_meta(raster, String::new(), (lo, hi), colour);
            meta.encoder = format!(
                "{CODEC_NAME} colour step={} chroma={}x{}",
                parts[0].0.step, parts[1].0.samples[0], parts[1].0.samples[1]
            );
            let coded = Coded::new(meta, parts, None, Build::Whole)?;
            Ok(coded.errors(raster, measure))
        })
        .collect::<Result<_, Error>>()?;
    let best = coded
        .into_iter()
        .min_by(|a, b| a.1.rmse.total_cmp(&b.1.rmse));
    let (coded, errors) = best.expect("two chroma resolutions tried");
    Ok((measure.kept(coded, raster, &errors), errors))
}

/// A plane's header before coding: its levels, the quantum, and its value range (what decoded
/// samples are normalised by).
fn plane_header(w: usize, h: usize, quantum: f64, (lo, span): (f64, f64)) -> ProjectedHeader {
    ProjectedHeader {
        samples: [w as u32, h as u32],
        levels: levels_for(w, h),
        step: 1.0,
        growth: 1.0,
        quantum,
        value_min: lo,
        value_span: span,
        roughness: 0.0,
        max_error: 0.0,
        order: Order::QuincunxTwoRate,
    }
}

/// The stream bytes a target rate allows: the file's, less the source-error map's share and
/// what the metadata and mask take.
fn rate_budget(bpp: f64, raster: &Raster) -> Result<usize, Error> {
    if !(bpp.is_finite() && bpp > 0.0) {
        return Err(Error::settings(format!(
            "--target-bpp {bpp} must be positive"
        )));
    }
    let cells = (raster.width * raster.height) as f64;
    Ok(without_map((bpp * cells / 8.0).floor() as usize).saturating_sub(512))
}

impl PlaneEncoder for ProjectedSettings {
    fn encode(
        &self,
        raster: &Raster,
        measure: &dyn Measure,
        progress: &(dyn Fn(u64, u64) + Sync),
    ) -> Result<(Coded, Errors), Error> {
        // One unit of work: the rate's bisections run side by side and have no count worth
        // showing, but a caller's progress (Python's callback, a bar) sees the start and the
        // end.
        progress(0, 1);
        let coded = encode_projected(raster, self, measure)?;
        progress(1, 1);
        Ok(coded)
    }

    /// The operator's 48 bytes a sample (`ProjectedHeader::cost`) and the discrete decode's 8.
    fn reader_bytes_per_cell(&self) -> u64 {
        56
    }
}
