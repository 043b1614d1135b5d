//! Deforming a curve through its model (what the paper is for): move control points, reshape
//! the details, or edit one level locally. Each works on a copy of the [`CurveSet`].

use super::distance::Pt;
use super::model::{CurveSet, Ring};
use fractile_proto::Deformation;
use nalgebra::{DMatrix, Matrix2, Vector2};

/// Applies deformations in order and returns the deformed set.
pub fn apply(set: &CurveSet, deformations: &[Deformation]) -> Result<CurveSet, crate::Error> {
    let mut out = set.clone();
    for d in deformations {
        match d {
            Deformation::Control { ring, points } => control(&mut out, *ring, points)?,
            Deformation::Details {
                from_level,
                scale,
                rotate_degrees,
                ring,
            } => {
                if !(scale.is_finite() && rotate_degrees.is_finite()) || scale.abs() > 1e3 {
                    return Err(crate::Error::input(
                        "scale and rotation must be finite (|scale| <= 1000)",
                    ));
                }
                let m = similarity(*scale, rotate_degrees.to_radians());
                let finest = out.finest();
                for (i, r) in out.rings.iter_mut().enumerate() {
                    if ring.is_some_and(|k| k != i) {
                        continue;
                    }
                    let first = (*from_level + r.finest()).saturating_sub(finest);
                    for level in r.details.iter_mut().skip(first) {
                        transform_details(level, &m);
                    }
                }
                if let Some(k) = ring.filter(|&k| k >= out.rings.len()) {
                    return Err(crate::Error::input(format!(
                        "no ring {k}: the asset has {}",
                        out.rings.len()
                    )));
                }
            }
            Deformation::Local {
                ring,
                level,
                index,
                to,
                radius,
            } => local(&mut out, *ring, *level, *index, *to, *radius)?,
        }
    }
    // A deformed curve's error against the source is not known any more.
    out.level_bounds.iter_mut().for_each(|b| *b = f64::NAN);
    Ok(out)
}

/// Rotation by `angle` (radians) times `scale`, acting on column vectors.
fn similarity(scale: f64, angle: f64) -> Matrix2<f64> {
    let (s, c) = angle.sin_cos();
    Matrix2::new(c, -s, s, c) * scale
}

fn transform_details(level: &mut [[Pt; 2]], m: &Matrix2<f64>) {
    for pair in level {
        for d in pair {
            let v = m * Vector2::new(d[0], d[1]);
            *d = [v[0], v[1]];
        }
    }
}

fn ring_mut(set: &mut CurveSet, ring: usize) -> Result<&mut Ring, crate::Error> {
    let n = set.rings.len();
    set.rings
        .get_mut(ring)
        .ok_or_else(|| crate::Error::input(format!("no ring {ring}: the asset has {n}")))
}

/// Global deformation: new base control points; details follow the rotation and scale part
/// `L(M)` of the affine map `M` that best takes the old points to the new (least squares, by
/// the pseudo-inverse), i.e. the similarity closest to `M`'s linear part.
fn control(set: &mut CurveSet, ring: usize, points: &[Pt]) -> Result<(), crate::Error> {
    let r = ring_mut(set, ring)?;
    if points.len() != r.base.len() {
        return Err(crate::Error::input(format!(
            "ring {ring} has {} control points, {} were given",
            r.base.len(),
            points.len()
        )));
    }
    if points.iter().flatten().any(|v| !v.is_finite()) {
        return Err(crate::Error::input("control points must be finite"));
    }
    let n = points.len();
    let x = DMatrix::from_fn(n, 3, |i, j| if j < 2 { r.base[i][j] } else { 1.0 });
    let y = DMatrix::from_fn(n, 2, |i, j| points[i][j]);
    let pinv = x
        .pseudo_inverse(1e-12)
        .map_err(|e| crate::Error::input(format!("pseudo-inverse: {e}")))?;
    let a = pinv * y; // rows: x, y, 1 → columns x', y' (row-vector form p' = p·A)
    // Column-vector linear part [[a, c], [b, d]] and its closest similarity.
    let lin = Matrix2::new(a[(0, 0)], a[(1, 0)], a[(0, 1)], a[(1, 1)]);
    let alpha = (lin[(0, 0)] + lin[(1, 1)]) / 2.0;
    let beta = (lin[(1, 0)] - lin[(0, 1)]) / 2.0;
    let l = Matrix2::new(alpha, -beta, beta, alpha);
    r.base = points.to_vec();
    for level in &mut r.details {
        transform_details(level, &l);
    }
    Ok(())
}

/// Falloff of a local edit: 1 at the moved point, 0 past `radius` points, C¹ in between
/// (`(1 - (k/(radius+1))²)²`, Wendland-like). The paper moves neighbours with a decreasing
/// weight; this one is smooth and has compact support, so far stretches stay exactly as coded.
pub fn falloff(k: usize, radius: usize) -> f64 {
    if k > radius {
        return 0.0;
    }
    let t = k as f64 / (radius + 1) as f64;
    (1.0 - t * t).powi(2)
}

/// Local deformation at asset level `level`.
fn local(
    set: &mut CurveSet,
    ring: usize,
    level: usize,
    index: usize,
    to: Pt,
    radius: usize,
) -> Result<(), crate::Error> {
    if !(to[0].is_finite() && to[1].is_finite()) {
        return Err(crate::Error::input("the target point must be finite"));
    }
    let finest = set.finest();
    if level > finest {
        return Err(crate::Error::input(format!(
            "local edits work at the source's levels (0..={finest}), not {level}"
        )));
    }
    let scheme = set.scheme.clone();
    let own = {
        let r = set
            .rings
            .get(ring)
            .ok_or_else(|| crate::Error::input(format!("no ring {ring}")))?;
        set.ring_level(r, level)
    };
    let r = ring_mut(set, ring)?;
    let mut poly = r.polygon(&scheme, own);
    // The index is the output's (inserted points left out, the input's first vertex first);
    // `to` is in the output's longitudes, so the move is measured there.
    let Some(&at) = r.output_map(own).get(index) else {
        return Err(crate::Error::input(format!(
            "ring {ring} has no point {index} at level {level}"
        )));
    };
    let framed = r.framed(&scheme, own);
    let delta = [to[0] - framed[at][0], to[1] - framed[at][1]];
    let n = poly.len() as isize;
    let reach = radius.min(poly.len() / 2);
    for k in -(reach as isize)..=reach as isize {
        let i = at as isize + k;
        let i = if r.closed {
            i.rem_euclid(n)
        } else if (0..n).contains(&i) {
            i
        } else {
            continue;
        };
        let w = falloff(k.unsigned_abs(), radius);
        poly[i as usize][0] += w * delta[0];
        poly[i as usize][1] += w * delta[1];
    }
    // Analysis of the edited level, then the finer details as they were.
    let edited = Ring::from_fine(&scheme, &poly, r.closed, r.pieces(), Vec::new());
    let finer = r.details.split_off(own);
    r.base = edited.base;
    r.details = edited.details;
    r.details.extend(finer);
    Ok(())
}
