//! The bounds of max-error mode: the quantum a source lies on, the finest bound a plane is
//! coded to, the step that keeps a bound, and the check that a coding kept it.

use fractile_proto::SampleFormat;

use crate::Error;
use crate::encode::source::coding_range;
use crate::io::raster::Raster;

/// The quantum the source lies on: 1 for integer samples (and float samples that are all whole
/// numbers, as most DEMs stored as float are not), else 0 (continuous).
pub(crate) fn source_quantum(raster: &Raster) -> f64 {
    if raster.sample != SampleFormat::F32 {
        return 1.0;
    }
    let valid = raster.valid.as_deref();
    let whole = raster.channels[0]
        .iter()
        .enumerate()
        .all(|(i, &v)| valid.is_some_and(|m| !m[i]) || (v.fract() == 0.0 && v.abs() < 1e7));
    if whole { 1.0 } else { 0.0 }
}

/// The span a raster's first plane is coded over (`coding_range`).
pub(crate) fn chunk_span(raster: &Raster) -> f64 {
    let (lo, hi) = coding_range(raster);
    hi - lo
}

/// The finest bound a continuous plane of range `span` is coded to: 2^-20 of the range, a few
/// float32 roundings of the normalised samples the closed loop decodes to. Finer bounds are
/// not kept by what a reader receives, and their steps overflowed the quantiser (a constant
/// float chunk under a file's bound of 6e-10 decoded 6 away).
pub(crate) fn finest_bound(span: f64) -> f64 {
    span * 2f64.powi(-20)
}

/// How far a reader's float32 answer at a sample centre may lie from the decoded sample of a
/// plane coded over `[lo, lo + span]`: the normalised sample's float32 rounding and a chain's
/// (2^-20 of the span, as [`finest_bound`]), and the answer's own (an ulp of the largest
/// magnitude, 2^-23 of it). On a continuous source the step keeps the bound less this, so that
/// what users receive keeps it (issue 73: `--max-error 10` decoded 10.0005 away); on a quantum
/// the decoded samples are whole quanta and readers round an answer this close to one onto it
/// (`Asset::to_source`), so they are received exactly.
pub(crate) fn delivery_margin(lo: f64, span: f64) -> f64 {
    span * 2f64.powi(-20) + lo.abs().max((lo + span).abs()) * 2f64.powi(-23)
}

/// A value in source units as readers deliver it, float32: onto the quantum where it lies
/// within the float32 roundings of one (`onto`: the quantum and that distance,
/// [`super::ProjectedHeader::delivered_quantum`]).
pub(crate) fn delivered(x: f64, onto: Option<(f64, f64)>) -> f32 {
    match onto {
        Some((q, near)) => {
            // x / 1 and r * 1 are exact: integer data skips a division a value.
            let on = if q == 1.0 {
                crate::core::transform::round_half_away(x)
            } else {
                crate::core::transform::round_half_away(x / q) * q
            };
            if (on - x).abs() <= near {
                on as f32
            } else {
                x as f32
            }
        }
        None => x as f32,
    }
}

/// The step that keeps every sample within `e`: `2 delta + 1` quanta for `delta = floor(e /
/// quantum)` on quantised data (JPEG-LS's near-lossless step), `2 (e - margin)` on continuous
/// data ([`delivery_margin`]; `e` where the bound is under twice the margin, which float32
/// answers cannot keep).
pub(crate) fn max_error_step(e: f64, quantum: f64, margin: f64) -> Result<f64, Error> {
    if !(e.is_finite() && e >= 0.0) {
        return Err(Error::settings(format!(
            "--max-error {e} must be a distance >= 0"
        )));
    }
    if quantum > 0.0 {
        Ok((2.0 * (e / quantum).floor() + 1.0) * quantum)
    } else if e > 0.0 {
        Ok(2.0 * (e - margin).max(0.5 * e))
    } else {
        Err(Error::settings(
            "--max-error 0 needs a source on a quantum (integer samples); this one is continuous",
        ))
    }
}

/// Refuses an asset that breaks its promise (a bug, not an input error: the closed loop bounds
/// every sample by construction). The decoded value is an f32 of the normalised range, so the
/// check allows its rounding: 2^-22 of the range.
pub(crate) fn check_bound(
    grid: &[f64],
    source: &[f64],
    valid: Option<&[bool]>,
    e: f64,
    span: f64,
) -> Result<(), Error> {
    let slack = span * 2f64.powi(-22);
    let worst = grid
        .iter()
        .zip(source)
        .enumerate()
        .filter(|(i, _)| valid.is_none_or(|v| v[*i]))
        .map(|(_, (g, s))| (g - s).abs())
        .fold(0.0f64, f64::max);
    if worst > e + slack {
        return Err(Error::settings(format!(
            "internal: a decoded sample is {worst} from its source, over the bound {e}"
        )));
    }
    Ok(())
}
