//! Where a raster's pixels fall inside the asset ([`Inside`]) and the separable filter of a
//! grid coarser than the source.

use crate::geo::{self};

/// [`Asset::sample`]'s filter of a coarse grid (its values, row-major, width and height) at a
/// separable grid of unit points: per point
/// the mean of four bilinear taps `(x +- qx, y +- qy)` (grid pixels), which is separable: each
/// axis's two taps are at most four weighed cells, so the grid's rows are filtered along x
/// once, then the columns along y. The same values as tapping point by point (to f32
/// rounding), for a pass over the rows the points need instead of sixteen reads a point.
pub(super) fn filter_separable(
    (values, width, height): (&[f32], usize, usize),
    (xs, ys): (&[f32], &[f32]),
    [qx, qy]: [f32; 2],
) -> Vec<f32> {
    // Per point of an axis of n cells: its taps' cells and weights (the mean of the two taps
    // folded in: half each).
    pub(super) fn taps(list: &[f32], n: usize, q: f32) -> Vec<[(usize, f32); 4]> {
        let tap = |x: f32| {
            let x = x.clamp(0.0, (n - 1) as f32);
            let x0 = x as usize;
            let f = x - x0 as f32;
            [(x0, 0.5 * (1.0 - f)), ((x0 + 1).min(n - 1), 0.5 * f)]
        };
        list.iter()
            .map(|&t| {
                let x = t * n as f32 - 0.5;
                let (a, b) = (tap(x - q), tap(x + q));
                [a[0], a[1], b[0], b[1]]
            })
            .collect()
    }
    let (tx, ty) = (taps(xs, width, qx), taps(ys, height, qy));
    let (lo, hi) = ty
        .iter()
        .flatten()
        .fold((usize::MAX, 0), |(a, b), &(r, _)| (a.min(r), b.max(r)));
    if ty.is_empty() || tx.is_empty() {
        return Vec::new();
    }
    // The rows the points need, filtered along x.
    let nx = tx.len();
    let mut rows = vec![0.0f32; (hi - lo + 1) * nx];
    for (r, out) in (lo..=hi).zip(rows.chunks_exact_mut(nx)) {
        let src = &values[r * width..(r + 1) * width];
        for (o, t) in out.iter_mut().zip(&tx) {
            *o = t.iter().map(|&(c, w)| w * src[c]).sum();
        }
    }
    let mut out = vec![0.0f32; nx * ty.len()];
    for (t, o) in ty.iter().zip(out.chunks_exact_mut(nx)) {
        for &(r, w) in t {
            for (a, &v) in o.iter_mut().zip(&rows[(r - lo) * nx..(r - lo + 1) * nx]) {
                *a += w * v;
            }
        }
    }
    out
}

/// The pixels of a raster that fall on the asset, as the decoders take them.
pub(super) enum Inside {
    /// The columns `cols` and rows `rows` inside, at unit x `ix` and unit y `iy`.
    Grid {
        cols: Vec<usize>,
        rows: Vec<usize>,
        ix: Vec<f32>,
        iy: Vec<f32>,
        width: usize,
    },
    /// The pixels `index` inside, at `points`: first the `loose` ones, decoded point by point,
    /// then those of each patch, in its order (each patch with which of its points are inside).
    List {
        index: Vec<usize>,
        points: Vec<[f32; 2]>,
        loose: usize,
        patches: Vec<(geo::PatchAt, Vec<bool>)>,
    },
}

impl Inside {
    pub(super) fn of(sites: &geo::Sites) -> Inside {
        match sites {
            geo::Sites::Grid { xs, ys } => {
                let cols: Vec<usize> = (0..xs.len()).filter(|&i| xs[i].is_some()).collect();
                let rows: Vec<usize> = (0..ys.len()).filter(|&j| ys[j].is_some()).collect();
                Inside::Grid {
                    ix: cols.iter().filter_map(|&i| xs[i]).collect(),
                    iy: rows.iter().filter_map(|&j| ys[j]).collect(),
                    cols,
                    rows,
                    width: xs.len(),
                }
            }
            geo::Sites::List {
                width,
                points: all,
                patches,
            } => {
                // Pixels in no patch first (decoded point by point), then each patch's.
                let mut covered = vec![false; all.len()];
                for pa in patches {
                    for j in pa.row..pa.row + pa.patch.height {
                        let start = j * width + pa.col;
                        covered[start..start + pa.patch.width].fill(true);
                    }
                }
                let mut index = Vec::with_capacity(all.len());
                let mut points = Vec::with_capacity(all.len());
                for (k, p) in all.iter().enumerate() {
                    if let (false, Some(p)) = (covered[k], p) {
                        index.push(k);
                        points.push(*p);
                    }
                }
                let loose = index.len();
                let patches = patches
                    .iter()
                    .map(|pa| {
                        let mut inside = Vec::with_capacity(pa.patch.width * pa.patch.height);
                        for j in pa.row..pa.row + pa.patch.height {
                            let start = j * width + pa.col;
                            for (k, p) in all[start..start + pa.patch.width].iter().enumerate() {
                                inside.push(p.is_some());
                                if let Some(p) = p {
                                    index.push(start + k);
                                    points.push(*p);
                                }
                            }
                        }
                        (pa.clone(), inside)
                    })
                    .collect();
                Inside::List {
                    index,
                    points,
                    loose,
                    patches,
                }
            }
        }
    }

    /// How many pixels are inside.
    pub(super) fn len(&self) -> usize {
        match self {
            Inside::Grid { ix, iy, .. } => ix.len() * iy.len(),
            Inside::List { points, .. } => points.len(),
        }
    }

    /// The unit point of inside pixel k.
    pub(super) fn at(&self, k: usize) -> (f32, f32) {
        match self {
            Inside::Grid { ix, iy, .. } => (ix[k % ix.len()], iy[k / ix.len()]),
            Inside::List { points, .. } => (points[k][0], points[k][1]),
        }
    }

    /// The unit box that holds every inside point (`None` if a coordinate is NaN).
    pub(super) fn footprint(&self) -> Option<[f32; 4]> {
        fn span(mut t: impl Iterator<Item = f32>) -> Option<(f32, f32)> {
            t.try_fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), v| {
                (!v.is_nan()).then(|| (lo.min(v), hi.max(v)))
            })
        }
        let ((u0, u1), (v0, v1)) = match self {
            Inside::Grid { ix, iy, .. } => (span(ix.iter().copied())?, span(iy.iter().copied())?),
            Inside::List { points, .. } => (
                span(points.iter().map(|p| p[0]))?,
                span(points.iter().map(|p| p[1]))?,
            ),
        };
        (u0 <= u1 && v0 <= v1).then_some([u0, v0, u1, v1])
    }

    /// The values of the inside pixels put back in a raster of `len` pixels (NaN outside).
    pub(super) fn scatter(&self, values: Vec<f32>, len: usize) -> Vec<f32> {
        // In raster order already: every pixel inside, and none taken out of order by a patch.
        let in_order = match self {
            Inside::Grid { .. } => true,
            Inside::List { patches, .. } => patches.is_empty(),
        };
        if in_order && values.len() == len {
            return values;
        }
        let mut full = vec![f32::NAN; len];
        match self {
            Inside::Grid {
                cols, rows, width, ..
            } => {
                for (r, &j) in rows.iter().enumerate() {
                    for (c, &i) in cols.iter().enumerate() {
                        full[j * width + i] = values[r * cols.len() + c];
                    }
                }
            }
            Inside::List { index, .. } => {
                for (&k, v) in index.iter().zip(values) {
                    full[k] = v;
                }
            }
        }
        full
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::decode;

    /// The separable filter is the four taps a point, as [`Asset::sample`] took them one by
    /// one, on a grid with values that vary along both axes, points inside, on the edges and
    /// past them (clamped).
    #[test]
    fn separable_filtering_is_the_mean_of_four_bilinear_taps() {
        let (w, h) = (37, 23);
        let g = decode::Grid {
            width: w,
            height: h,
            values: (0..w * h)
                .map(|k| ((k % w) as f32 * 0.37).sin() + ((k / w) as f32 * 0.21).cos() * 2.0)
                .collect(),
        };
        let xs: Vec<f32> = (0..50).map(|i| -0.05 + 1.1 * i as f32 / 49.0).collect();
        let ys: Vec<f32> = (0..31).map(|j| 0.02 + 0.97 * j as f32 / 30.0).collect();
        for (qx, qy) in [(0.25, 0.25), (0.6, 0.4), (1.3, 0.9)] {
            let got = filter_separable((&g.values, w, h), (&xs, &ys), [qx, qy]);
            assert_eq!(got.len(), xs.len() * ys.len());
            for (k, v) in got.iter().enumerate() {
                let (x, y) = (
                    xs[k % xs.len()] * w as f32 - 0.5,
                    ys[k / xs.len()] * h as f32 - 0.5,
                );
                let want = 0.25
                    * (decode::sample_bilinear(&g, x - qx, y - qy)
                        + decode::sample_bilinear(&g, x + qx, y - qy)
                        + decode::sample_bilinear(&g, x - qx, y + qy)
                        + decode::sample_bilinear(&g, x + qx, y + qy));
                assert!((v - want).abs() < 1e-5, "point {k}: {v} against {want}");
            }
        }
    }
}
