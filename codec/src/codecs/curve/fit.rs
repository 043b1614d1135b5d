//! Fitting the scheme to the curves: the paper's two Levenberg-Marquardt steps.
//!
//! 1. Control points and subdivision matrices `T`, no details: the attractor of the projected
//!    IFS (the curve the base control points make with every detail zero) is fitted to the
//!    source points. The control points enter linearly, so they are solved exactly by least
//!    squares inside every residual evaluation (variable projection), and LM moves the four
//!    free weights of `T`.
//! 2. Detail matrices `U`, with the first levels of details only: the details of the first
//!    [`FIRST_LEVELS`] levels come from the analysis (`R⁻¹`) under the fitted `T`; every deeper
//!    level inherits through `U`; LM moves the eight entries of `U` so that this curve fits the
//!    source. The fitted `U` then predicts details in the coder and continues them past the
//!    source's level.
//!
//! The solver is the `levenberg-marquardt` crate (MINPACK's algorithm); the Jacobians are
//! central differences: 4 and 8 parameters against tens of thousands of residuals.

use super::model::{MAX_DETAIL_GAIN, Ring, Scheme};
use super::prepare::Prepared;
use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{DMatrix, DVector, Dyn, Owned};

/// Levels of details kept in step 2.
pub(crate) const FIRST_LEVELS: usize = 2;

/// What the fit did, for the encoder's report.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct FitReport {
    /// RMS distance between the source points and the detail-free attractor, default `T`.
    pub attractor_rms_before: f64,
    /// The same after step 1.
    pub attractor_rms: f64,
    /// RMS distance with the first levels of details and inherited ones, `U = 0`.
    pub inherited_rms_before: f64,
    /// The same after step 2.
    pub inherited_rms: f64,
    /// Residual evaluations of both steps.
    pub evaluations: usize,
    /// Stream bytes under the default scheme and under the fitted one (0 when not coded).
    pub bytes_default: usize,
    /// See `bytes_default`.
    pub bytes_fitted: usize,
    /// Whether the encoder kept the fitted scheme (it codes smaller).
    pub kept: bool,
    /// The fitted scheme.
    pub scheme: Option<Scheme>,
}

/// The attractor of the scheme in barycentric coordinates of one base piece: the weights of
/// `(A, C, B)` for each of the `2^(levels+1) + 1` points after `levels` subdivisions.
fn basis(t: &[[f64; 3]; 2], levels: usize) -> Vec<[f64; 3]> {
    let mut cur = vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..levels {
        let mut next = Vec::with_capacity(2 * cur.len());
        for p in 0..cur.len() / 2 {
            let (a, c, b) = (cur[2 * p], cur[2 * p + 1], cur[2 * p + 2]);
            let mix =
                |w: &[f64; 3]| std::array::from_fn(|k| w[0] * a[k] + w[1] * c[k] + w[2] * b[k]);
            next.extend([a, mix(&t[0]), c, mix(&t[1])]);
        }
        next.push(*cur.last().expect("non-empty"));
        cur = next;
    }
    cur
}

fn levels_of(s: &Prepared) -> usize {
    let segs = s.fine.len() - usize::from(!s.closed);
    (segs / s.pieces).ilog2() as usize - 1
}

/// Step 1's residuals for weights `t`: source minus the best detail-free attractor.
fn attractor_residuals(t: &[[f64; 3]; 2], rings: &[&Prepared]) -> Vec<f64> {
    let mut out = Vec::new();
    for s in rings {
        let levels = levels_of(s);
        let w = basis(t, levels);
        let per = w.len() - 1;
        let nb = 2 * s.pieces + usize::from(!s.closed);
        let mut g = DMatrix::<f64>::zeros(nb, nb);
        let mut rhs = DMatrix::<f64>::zeros(nb, 2);
        let idx = |p: usize| [2 * p, 2 * p + 1, (2 * p + 2) % nb];
        let rows = |p: usize| {
            let last = !s.closed && p + 1 == s.pieces;
            0..per + usize::from(last)
        };
        for p in 0..s.pieces {
            let ix = idx(p);
            for k in rows(p) {
                let f = s.fine[p * per + k];
                for a in 0..3 {
                    rhs[(ix[a], 0)] += w[k][a] * f[0];
                    rhs[(ix[a], 1)] += w[k][a] * f[1];
                    for b in 0..3 {
                        g[(ix[a], ix[b])] += w[k][a] * w[k][b];
                    }
                }
            }
        }
        let x = match g.clone().cholesky() {
            Some(ch) => ch.solve(&rhs),
            None => match g.lu().solve(&rhs) {
                Some(x) => x,
                None => DMatrix::zeros(nb, 2),
            },
        };
        for p in 0..s.pieces {
            let ix = idx(p);
            for k in rows(p) {
                let f = s.fine[p * per + k];
                for axis in 0..2 {
                    let fit: f64 = (0..3).map(|a| w[k][a] * x[(ix[a], axis)]).sum();
                    out.push(f[axis] - fit);
                }
            }
        }
    }
    out
}

/// Step 2's residuals: source minus the synthesis with the first levels of details.
fn inherited_residuals(scheme: &Scheme, rings: &[(&Prepared, Ring)]) -> Vec<f64> {
    let mut out = Vec::new();
    for (s, ring) in rings {
        let truncated = Ring {
            details: ring.details[..FIRST_LEVELS.min(ring.finest())].to_vec(),
            ..ring.clone()
        };
        let poly = truncated.polygon(scheme, ring.finest());
        for (p, f) in poly.iter().zip(&s.fine) {
            out.extend([f[0] - p[0], f[1] - p[1]]);
        }
    }
    out
}

fn rms(r: &[f64]) -> f64 {
    if r.is_empty() {
        return 0.0;
    }
    (r.iter().map(|v| v * v).sum::<f64>() / (r.len() / 2) as f64).sqrt()
}

/// A least-squares problem over a few parameters with a residual closure and a central
/// difference Jacobian.
struct Problem<F: Fn(&[f64]) -> Vec<f64>> {
    params: DVector<f64>,
    residuals: F,
    evaluations: std::cell::Cell<usize>,
}

impl<F: Fn(&[f64]) -> Vec<f64>> Problem<F> {
    fn eval(&self, x: &[f64]) -> Vec<f64> {
        self.evaluations.set(self.evaluations.get() + 1);
        (self.residuals)(x)
    }
}

impl<F: Fn(&[f64]) -> Vec<f64>> LeastSquaresProblem<f64, Dyn, Dyn> for Problem<F> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.params.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.params.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let r = self.eval(self.params.as_slice());
        r.iter()
            .all(|v| v.is_finite())
            .then(|| DVector::from_vec(r))
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let n = self.params.len();
        let mut columns = Vec::with_capacity(n);
        for j in 0..n {
            let h = 1e-6 * self.params[j].abs().max(1e-2);
            let mut x = self.params.clone_owned();
            x[j] += h;
            let plus = self.eval(x.as_slice());
            x[j] -= 2.0 * h;
            let minus = self.eval(x.as_slice());
            columns.push(DVector::from_iterator(
                plus.len(),
                plus.iter().zip(&minus).map(|(p, m)| (p - m) / (2.0 * h)),
            ));
        }
        let j = DMatrix::from_columns(&columns);
        j.iter().all(|v| v.is_finite()).then_some(j)
    }
}

fn t_of(x: &[f64]) -> [[f64; 3]; 2] {
    [
        [x[0], 1.0 - x[0] - x[1], x[1]],
        [x[2], 1.0 - x[2] - x[3], x[3]],
    ]
}

fn u_of(x: &[f64]) -> [[[f64; 2]; 2]; 2] {
    // Rows scaled down to the largest gain a detail matrix may have.
    let row = |a: f64, b: f64| {
        let g = a.abs() + b.abs();
        let k = if g > MAX_DETAIL_GAIN {
            MAX_DETAIL_GAIN / g
        } else {
            1.0
        };
        [a * k, b * k]
    };
    [
        [row(x[0], x[1]), row(x[2], x[3])],
        [row(x[4], x[5]), row(x[6], x[7])],
    ]
}

/// Rings worth fitting on (with at least two levels), subsampled to about `budget` points so
/// that the fit's cost stays a fraction of the encode.
fn sample(sources: &[Prepared], budget: usize) -> Vec<&Prepared> {
    let mut rings: Vec<&Prepared> = sources.iter().filter(|s| levels_of(s) >= 2).collect();
    rings.sort_by_key(|s| std::cmp::Reverse(s.fine.len()));
    let mut total = 0;
    rings.retain(|s| {
        total += s.fine.len();
        total <= budget || total == s.fine.len()
    });
    rings
}

/// Fits the scheme to prepared rings, starting from [`Scheme::default`]. A step whose result is
/// invalid or no better than where it started keeps the starting values.
pub(crate) fn fit(sources: &[Prepared]) -> (Scheme, FitReport) {
    let mut scheme = Scheme::default();
    let mut report = FitReport::default();
    let rings = sample(sources, 60_000);
    if rings.is_empty() {
        return (scheme, report);
    }
    let lm = LevenbergMarquardt::new().with_patience(30);

    // Step 1: T (and, inside, the control points).
    let t0 = scheme.t;
    let start = vec![t0[0][0], t0[0][2], t0[1][0], t0[1][2]];
    report.attractor_rms_before = rms(&attractor_residuals(&t0, &rings));
    let problem = Problem {
        params: DVector::from_vec(start),
        residuals: |x: &[f64]| attractor_residuals(&t_of(x), &rings),
        evaluations: std::cell::Cell::new(0),
    };
    let (problem, _) = lm.minimize(problem);
    report.evaluations += problem.evaluations.get();
    let fitted = Scheme {
        t: t_of(problem.params.as_slice()),
        ..scheme.clone()
    };
    let after = rms(&attractor_residuals(&fitted.t, &rings));
    if fitted.validate().is_ok() && after < report.attractor_rms_before {
        scheme = fitted;
        report.attractor_rms = after;
    } else {
        report.attractor_rms = report.attractor_rms_before;
    }

    // Step 2: U, with the first levels of details from the analysis under the fitted T.
    let analysed: Vec<(&Prepared, Ring)> = rings
        .iter()
        .map(|s| {
            let ring = Ring::from_fine(&scheme, &s.fine, s.closed, s.pieces, s.inserted.clone());
            (*s, ring)
        })
        .collect();
    report.inherited_rms_before = rms(&inherited_residuals(&scheme, &analysed));
    let base = scheme.clone();
    let problem = Problem {
        params: DVector::zeros(8),
        residuals: |x: &[f64]| {
            let s = Scheme {
                u: u_of(x),
                ..base.clone()
            };
            inherited_residuals(&s, &analysed)
        },
        evaluations: std::cell::Cell::new(0),
    };
    let (problem, _) = lm.minimize(problem);
    report.evaluations += problem.evaluations.get();
    let fitted = Scheme {
        u: u_of(problem.params.as_slice()),
        ..scheme.clone()
    };
    let after = rms(&inherited_residuals(&fitted, &analysed));
    if fitted.validate().is_ok() && after < report.inherited_rms_before {
        scheme = fitted;
        report.inherited_rms = after;
    } else {
        report.inherited_rms = report.inherited_rms_before;
    }
    report.scheme = Some(scheme.clone());
    (scheme, report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codecs::curve::{Pt, prepare};

    /// A curve that *is* the attractor of a known scheme: step 1 must find weights that fit it
    /// far better than the default's.
    #[test]
    fn step_one_recovers_a_known_attractor() {
        let truth = [[0.55, 0.6, -0.15], [-0.05, 0.7, 0.35]];
        let w = basis(&truth, 5);
        let ctrl: [Pt; 4] = [[0.0, 0.0], [3.0, 4.0], [8.0, -1.0], [5.0, -6.0]];
        let mut fine = Vec::new();
        for p in 0..2 {
            let (a, c, b) = (ctrl[2 * p], ctrl[2 * p + 1], ctrl[(2 * p + 2) % 4]);
            for k in &w[..w.len() - 1] {
                fine.push([
                    k[0] * a[0] + k[1] * c[0] + k[2] * b[0],
                    k[0] * a[1] + k[1] * c[1] + k[2] * b[1],
                ]);
            }
        }
        let p = prepare(&fine, true).unwrap();
        assert_eq!(p.pieces, 2, "the preparation keeps the 2 × 64 structure");
        let (scheme, report) = fit(&[p]);
        assert!(report.attractor_rms < 1e-6 * report.attractor_rms_before.max(1.0));
        for (a, b) in scheme.t.iter().flatten().zip(truth.iter().flatten()) {
            assert!((a - b).abs() < 1e-4, "{:?} vs {truth:?}", scheme.t);
        }
    }
}
