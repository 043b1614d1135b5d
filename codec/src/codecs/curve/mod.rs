//! Curves as projected IFS with details: multiresolution polylines (coastlines) and their
//! deformation. After Hnaidi, Guérin and Akkouche, "Fractal/wavelet model as a deformation
//! tool" (RR-LIRIS-2008-002, hal-01537655).
//!
//! # Model
//! A ring (closed polyline) or an open polyline is cut into `K` base *pieces*. A piece has three
//! control points `(A, C, B)`: its two ends and a middle point. Two maps subdivide it into the
//! pieces `(A, E0, C)` and `(C, E1, B)`:
//!
//! ```text
//! E_i = t_i · (A, C, B) + d_i          (synthesis, the paper's eq. 6: P_θi = P_θ T_i + dP_θ U_i)
//! ```
//!
//! `t_i` are the barycentric weights of the subdivision matrices `T_i` (each triple sums to 1, so
//! the model commutes with affine maps of the plane) and `d_i` the piece's two *details*. The
//! junction `C` is carried over: the scheme is interpolating, so every control point of every
//! level is a point of the curve. That choice is what makes lossy coding trustworthy: a point's
//! error is its own quantisation error and never accumulates over levels (see `code`).
//!
//! Over the five fine points of a piece, synthesis is one 5×5 matrix `R` (the rows of `T_0, T_1`
//! merged on the shared point `C`, and the two detail rows); analysis is `R⁻¹` (eq. 7), which
//! [`Scheme::analysis_matrix`] computes and [`Ring::from_fine`] applies level by level.
//!
//! Details are self-similar: a piece's children inherit its details through the 2×2 *detail
//! matrices* `U_i` (`d_child = U_i · d_parent` before anything is added). The encoder codes only
//! what inheritance does not predict, and a decoder asked for levels deeper than the source
//! continues the details through `U` (and the shape through `T`): "self-similar detail".
//! `T` and `U` are fitted by Levenberg-Marquardt in the paper's two steps (`fit`).
//!
//! # Levels
//! A ring's own level `l` is its polygon after `l` subdivisions of the base pieces: `K·2^(l+1)`
//! points. The finest level `L` holds every input vertex (plus points the encoder inserted on
//! the input's own segments so that the count fits `K·2^(L+1)`; the output drops them). Asset
//! levels align the rings on their finest level, so that one asset level means one scale.

pub(crate) mod code;
mod contexts;
pub mod deform;
mod distance;
pub(crate) mod fit;
pub mod geojson;
mod header;
mod model;
mod prepare;

// The model (points, schemes, rings, levels, distances) is the codec's vocabulary: its
// parts (`code`, `fit`, `geojson`, `deform`) import it from `model`; users find it here.
pub use distance::*;
pub use model::*;
pub use prepare::*;

use rayon::prelude::*;

/// Settings of the curve encoder.
#[derive(Clone, Debug, PartialEq)]
pub struct CurveSettings {
    /// Largest error of a point, in the metric's units; 0 keeps every detail exactly. The
    /// default is 0: a polyline is the user's data, and loss is something to ask for.
    pub tolerance: f64,
    /// How the tolerance is measured ([`Metric::Sphere`] for GeoJSON).
    pub metric: Metric,
    /// Fit `T` and `U` (the paper's two steps); otherwise [`Scheme::default`].
    pub fit: bool,
    /// Start vertices tried for each closed ring when lossy (evenly spaced; the one that codes
    /// smallest is kept and its index stored): which vertices fall on the coarse levels moves
    /// a ring's size by about ±0.5%, so the best of 16 saves 0.3-0.8% on the longest
    /// coastlines, for 16 times the coding work (spread over the cores). 1: the input's own.
    pub starts: usize,
}

impl Default for CurveSettings {
    fn default() -> Self {
        CurveSettings {
            tolerance: 0.0,
            metric: Metric::Sphere,
            fit: true,
            starts: 16,
        }
    }
}

/// A coded curve set: what an asset stores and what it decodes to.
#[derive(Clone, Debug)]
pub struct Curves {
    /// Scheme, ring shapes, tolerance, the finest level's bound.
    pub header: code::CurveHeader,
    /// The range-coded base points and details.
    pub stream: Vec<u8>,
    /// The decoded model.
    pub set: CurveSet,
}

impl Curves {
    /// The asset's payload: the compact header, then the stream (no length fields: the header
    /// delimits itself and the payload's length ends the stream).
    pub fn payload(&self) -> Vec<u8> {
        let mut out = code::compact::write(&self.header);
        out.extend_from_slice(&self.stream);
        out
    }
}

/// Encodes polylines: preparation, the fit, closed-loop coding.
pub fn encode(
    lines: &[geojson::Polyline],
    settings: &CurveSettings,
) -> Result<(Curves, fit::FitReport), crate::Error> {
    if !(settings.tolerance.is_finite() && settings.tolerance >= 0.0) {
        return Err(crate::Error::settings(format!(
            "tolerance {} must be a finite distance >= 0",
            settings.tolerance
        )));
    }
    // Longitudes are unwrapped only when lossy: adding whole turns rounds the last bit of some
    // coordinates, which lossless coding must not do (it codes the jump instead).
    let unwrap = settings.metric == Metric::Sphere && settings.tolerance > 0.0;
    // A ring started at input vertex `start`: its points rotated, unwrapped, prepared.
    let started =
        |l: &geojson::Polyline, start: usize| -> Result<(Prepared, Frame), crate::Error> {
            let mut pts = l.points.clone();
            if l.closed && pts.len() > 1 && pts.first() == pts.last() {
                pts.pop();
            }
            let len = pts.len().max(1);
            pts.rotate_left(start % len);
            let (points, closed, seam) = if unwrap {
                unwrap_longitudes(&pts, l.closed)
            } else {
                (pts, l.closed, Vec::new())
            };
            let p = prepare(&points, closed)?;
            let seam = seam_to_fine(&seam, &p);
            let winds = l.closed && !closed;
            Ok((p, (seam, (start > 0 || winds).then_some(start as u32))))
        };
    let (prepared, frames): (Vec<Prepared>, Vec<Frame>) = lines
        .par_iter()
        .enumerate()
        .map(|(i, l)| {
            let n = l.points.len();
            let tries = if l.closed && settings.tolerance > 0.0 {
                settings.starts.clamp(1, n / 8 + 1)
            } else {
                1
            };
            // Each start coded alone under the default scheme; the smallest kept (the first
            // on a tie: the input's own start when nothing is gained).
            let mut candidates = (0..tries)
                .into_par_iter()
                .map(|k| {
                    let (p, frame) = started(l, k * n / tries)?;
                    if tries == 1 {
                        return Ok((0, p, frame));
                    }
                    let (header, stream, _) = code::encode(
                        &Scheme::default(),
                        settings.metric,
                        settings.tolerance,
                        std::slice::from_ref(&p),
                        std::slice::from_ref(&frame),
                    )?;
                    Ok((code::compact::write(&header).len() + stream.len(), p, frame))
                })
                .collect::<Result<Vec<_>, crate::Error>>()
                .map_err(|e| e.within(format_args!("polyline {i}")))?;
            let best = (0..candidates.len())
                .min_by_key(|&k| (candidates[k].0, k))
                .expect("at least one start");
            let (_, p, frame) = candidates.swap_remove(best);
            Ok((p, frame))
        })
        .collect::<Result<Vec<_>, crate::Error>>()?
        .into_iter()
        .unzip();
    let coded = |scheme: &Scheme| {
        code::encode(
            scheme,
            settings.metric,
            settings.tolerance,
            &prepared,
            &frames,
        )
    };
    let mut best = coded(&Scheme::default())?;
    let mut report = fit::FitReport::default();
    if settings.fit {
        // The fitted scheme is kept when it codes smaller: the fit minimises distances to the
        // curve, the coder pays for residual bits, and the two need not agree (rav1e's way:
        // decide by measuring the rate).
        let (scheme, r) = fit::fit(&prepared);
        report = r;
        if scheme != Scheme::default() {
            let fitted = coded(&scheme)?;
            report.kept = fitted.1.len() < best.1.len();
            report.bytes_default = best.1.len();
            report.bytes_fitted = fitted.1.len();
            if report.kept {
                best = fitted;
            }
        }
    }
    let (header, stream, set) = best;
    Ok((
        Curves {
            header,
            stream,
            set,
        },
        report,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wiggly(n: usize, closed: bool) -> Vec<Pt> {
        (0..n)
            .map(|i| {
                let t = i as f64 / n as f64 * std::f64::consts::TAU;
                let r = 10.0 + (7.0 * t).sin() + 0.3 * (31.0 * t).cos();
                if closed {
                    [r * t.cos(), r * t.sin()]
                } else {
                    [t, r]
                }
            })
            .collect()
    }

    #[test]
    fn prepare_keeps_every_vertex_and_only_inserts_on_segments() {
        for (n, closed) in [
            (3, true),
            (5, false),
            (97, true),
            (1000, false),
            (1025, true),
        ] {
            let pts = wiggly(n, closed);
            let p = prepare(&pts, closed).unwrap();
            let segs = p.fine.len() - usize::from(!closed);
            assert_eq!(segs % p.pieces, 0);
            assert!((segs / p.pieces).is_power_of_two() && segs / p.pieces >= 2);
            let kept: Vec<Pt> = p
                .fine
                .iter()
                .enumerate()
                .filter(|(i, _)| !p.inserted.contains(&(*i as u32)))
                .map(|(_, q)| *q)
                .collect();
            assert_eq!(kept, pts, "n={n}");
            for &i in &p.inserted {
                let i = i as usize;
                let (a, q) = (p.fine[i - 1], p.fine[i]);
                let b = p.fine[(i + 1) % p.fine.len()];
                let cross = (q[0] - a[0]) * (b[1] - a[1]) - (q[1] - a[1]) * (b[0] - a[0]);
                assert!(cross.abs() < 1e-9, "inserted point off its segment");
            }
        }
    }

    #[test]
    fn analysis_then_synthesis_is_exact() {
        let scheme = Scheme {
            t: [[0.6, 0.5, -0.1], [-0.2, 0.9, 0.3]],
            u: [[[0.3, -0.2], [0.1, 0.4]], [[-0.5, 0.0], [0.2, 0.2]]],
        };
        scheme.validate().unwrap();
        for closed in [true, false] {
            let p = prepare(&wiggly(777, closed), closed).unwrap();
            let ring = Ring::from_fine(&scheme, &p.fine, closed, p.pieces, p.inserted.clone());
            let back = ring.polygon(&scheme, ring.finest());
            assert_eq!(back.len(), p.fine.len());
            for (a, b) in back.iter().zip(&p.fine) {
                assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn analysis_matrix_inverts_synthesis() {
        let s = Scheme::default();
        let id = s.synthesis_matrix() * s.analysis_matrix();
        assert!(
            (id - nalgebra::SMatrix::<f64, 5, 5>::identity())
                .abs()
                .max()
                < 1e-12
        );
    }

    #[test]
    fn levels_past_the_source_add_points_near_the_source_polygon() {
        let scheme = Scheme {
            u: [[[0.4, 0.0], [0.0, 0.4]]; 2],
            ..Default::default()
        };
        let p = prepare(&wiggly(200, true), true).unwrap();
        let ring = Ring::from_fine(&scheme, &p.fine, true, p.pieces, p.inserted);
        let l = ring.finest();
        let deeper = ring.polygon(&scheme, l + 2);
        assert_eq!(deeper.len(), ring.len_at(l + 2));
        let source = ring.polygon(&scheme, l);
        // Every source point is kept (interpolating), in place.
        for (i, q) in source.iter().enumerate() {
            assert_eq!(deeper[4 * i], *q);
        }
        let dev = span_deviation(Metric::Plane, &source, &deeper, true);
        let spacing = Metric::Plane.distance(source[0], source[1]);
        assert!(
            dev > 0.0 && dev < 3.0 * spacing,
            "{dev} vs spacing {spacing}"
        );
    }
}
