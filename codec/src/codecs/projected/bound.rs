//! The bounds of max-error mode: the quantum a source lies on, the finest bound a plane is
//! coded to, the step that keeps a bound, and the check that a coding kept it.

use fractile_proto::SampleFormat;

use crate::Error;
use crate::codecs::source::coding_range;
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
fn delivered(x: f64, onto: Option<(f64, f64)>) -> f32 {
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

/// Normalised answers `values` (of a plane coded over `[lo, lo + span]`) as readers deliver
/// them: [`delivered`] of each, the same bits. On integer data whose values lie in the fast
/// range of the rounding, a loop without branches that the compiler vectorises (a value at a
/// time, the conversion was 8% of a whole read, issue 75): a tie lies half a quantum from
/// both neighbours, farther than `near` (under a quarter quantum), so it is delivered as
/// itself whichever way it rounds, and the nearest integer rounded to even is then the one
/// away from zero.
pub(crate) fn deliver_plane(values: &mut [f32], (lo, span): (f64, f64), onto: Option<(f64, f64)>) {
    const SHIFT: f64 = 6_755_399_441_055_744.0;
    match onto {
        // Normalised answers lie within the plane's invariant interval, a little around
        // [0, 1]: 4 spans is far beyond it, 2^50 well inside the fast range (2^51).
        Some((q, near)) if q == 1.0 && near < 0.25 && lo.abs() + 4.0 * span.abs() < 1e15 => {
            for v in values {
                let x = lo + f64::from(*v) * span;
                let on = ((x + SHIFT) - SHIFT).copysign(x);
                *v = if (on - x).abs() <= near { on } else { x } as f32;
            }
        }
        _ => values
            .iter_mut()
            .for_each(|v| *v = delivered(lo + f64::from(*v) * span, onto)),
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

#[cfg(test)]
mod delivery {
    use super::{deliver_plane, delivered, delivery_margin};

    /// [`deliver_plane`] delivers every value as [`delivered`] does, bit for bit: at whole
    /// quanta and a float32 rounding off them, at ties and near ties, at zeros of both signs,
    /// off the invariant interval, on NaN; on integer and continuous planes.
    #[test]
    fn a_plane_is_delivered_as_each_value() {
        use proptest::prelude::RngExt;
        // proptest's deterministic generator: the same draws every run.
        let mut rng = proptest::test_runner::TestRng::deterministic_rng(
            proptest::test_runner::RngAlgorithm::ChaCha,
        );
        let mut next = || rng.random::<f64>();
        let mut snapped = 0;
        for (lo, span) in [(-9027.0, 15256.0), (0.0, 65535.0), (-0.5, 3.0), (1e6, 4e6)] {
            let near = delivery_margin(lo, span);
            for onto in [Some((1.0, near)), Some((0.5, near)), None] {
                let mut values: Vec<f32> = (0..20_000)
                    .map(|k| {
                        let whole = (lo + (next() * 1.2 - 0.1) * span).round();
                        let off = match k % 5 {
                            0 => 0.0,
                            1 => 0.5,
                            2 => (next() - 0.5) * 4.0 * near,
                            3 => next() - 0.5,
                            _ => 0.5 - near * next(),
                        };
                        ((whole + off - lo) / span) as f32
                    })
                    .collect();
                values.extend([0.0, -0.0, f32::NAN, f32::INFINITY, (-lo / span) as f32]);
                let want: Vec<f32> = values
                    .iter()
                    .map(|&v| delivered(lo + f64::from(v) * span, onto))
                    .collect();
                deliver_plane(&mut values, (lo, span), onto);
                for (k, (got, want)) in values.iter().zip(&want).enumerate() {
                    assert_eq!(got.to_bits(), want.to_bits(), "value {k}: {got} {want}");
                }
                snapped += values.iter().filter(|v| v.fract() == 0.0).count();
            }
        }
        assert!(
            snapped > 10_000,
            "too few values were snapped onto whole quanta"
        );
    }
}
