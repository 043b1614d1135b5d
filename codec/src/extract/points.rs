//! Points: one or a batch, continuously decoded (snapped to sample centres where a projected
//! asset holds them), and the tolerance a point or a raster converges to.

use crate::core::decode::{self};
use crate::geo::{self, Pixels};
use crate::io::asset::Asset;
use crate::render::colour::rgb_bound;
use fractile_proto::SampleFormat;

use super::*;

impl Asset {
    /// Continuous decoding of one unit point (u, v) with `iterations` inverse steps.
    pub fn point(&self, u: f32, v: f32, iterations: u32) -> PointSample {
        if self.chunked().is_some() {
            return self.points(&[[u, v]], iterations, 0.0).remove(0);
        }
        let [u, v] = self.snap_to_samples(&[[u, v]]).map_or([u, v], |p| p[0]);
        let pv: Vec<_> = self
            .planes()
            .iter()
            .map(|p| {
                let mut r = p.operator.point([u, v], iterations);
                p.operator
                    .limit_points(&[[u, v]], std::slice::from_mut(&mut r.value));
                r
            })
            .collect();
        let span = self.span();
        let bounds: Vec<f32> = pv.iter().map(|p| p.error_bound * span).collect();
        let values = self.to_source(pv.iter().map(|p| vec![p.value]).collect(), |_| (u, v), None);
        PointSample {
            values: values.into_iter().map(|c| c[0]).collect(),
            error_bound: if bounds.len() == 3 {
                rgb_bound(bounds[0], bounds[1], bounds[2])
            } else {
                bounds[0]
            },
            source_error: self.source_error_at(u, v),
            iterations: pv.iter().map(|p| p.iterations).max().unwrap_or(0),
        }
    }

    /// Points within [`sample_snap`] of a sample centre of an asset whose codec knows its
    /// samples (the projected codec), moved onto it: a longitude and latitude converted to
    /// unit coordinates land a rounding away from the centre they name, and the sample is
    /// what the asset codes there (within its promise, under `--max-error`). `None`: no such
    /// asset.
    pub(super) fn snap_to_samples(&self, pts: &[[f32; 2]]) -> Option<Vec<[f32; 2]>> {
        self.planes().first()?.operator.samples()?;
        let (w, h) = (self.meta.width, self.meta.height);
        Some(
            pts.iter()
                .map(|&[u, v]| [snap_axis(u, w), snap_axis(v, h)])
                .collect(),
        )
    }

    /// [`Self::snap_to_samples`] of a raster's pixels (the points of patches stay as they are:
    /// they are off the centres of the source's grid).
    pub(super) fn snap_pixels(&self, pixels: &Pixels) -> Option<Pixels> {
        self.planes().first()?.operator.samples()?;
        let (w, h) = (self.meta.width, self.meta.height);
        let axis = |ts: &[Option<f32>], n: u32| -> Vec<Option<f32>> {
            ts.iter().map(|t| t.map(|t| snap_axis(t, n))).collect()
        };
        let sites = match &pixels.sites {
            geo::Sites::Grid { xs, ys } => geo::Sites::Grid {
                xs: axis(xs, w),
                ys: axis(ys, h),
            },
            geo::Sites::List {
                width,
                points,
                patches,
            } => geo::Sites::List {
                width: *width,
                points: points
                    .iter()
                    .map(|p| p.map(|[u, v]| [snap_axis(u, w), snap_axis(v, h)]))
                    .collect(),
                patches: patches.clone(),
            },
        };
        Some(Pixels {
            sites,
            footprint: pixels.footprint,
        })
    }

    /// The tolerance of a request that names neither steps nor a tolerance (value units): the
    /// larger of half a quantisation step of the source (1 for integer samples, 1/65535 of the
    /// range for floats, 1/254 for 8-bit) and [`SETTLED_FRACTION`] of the smallest bound of its
    /// source-error map, or of its codec's promise where that is smaller (the bound at sample
    /// centres: the map's blocks bound everything between samples too, proven, and are far
    /// larger on rough DEMs). Iterating past that refines an answer far below its distance to
    /// the source: a convergence bound under an eighth of the source error adds at most an
    /// eighth to `error_bound`, and each further step costs as much as the first ones.
    pub fn default_tolerance(&self) -> f32 {
        let m = &self.meta;
        let step = match m.sample {
            SampleFormat::F32 => (m.value_max - m.value_min) / 65535.0,
            SampleFormat::I8 => (m.value_max - m.value_min) / 254.0,
            _ => 1.0,
        };
        let settled = self
            .source_error
            .as_ref()
            .and_then(|map| map.smallest())
            .or_else(|| self.chunked()?.table.smallest_source_error)
            .map(|e| match self.planes().first().and_then(|p| p.promise()) {
                Some(p) => e.min(p),
                None => e,
            })
            .filter(|e| e.is_finite())
            .map_or(0.0, |e| SETTLED_FRACTION * e);
        (0.5 * step as f32).max(settled)
    }

    /// The tolerance of an answer at `pixels` that names neither steps nor a tolerance: an
    /// eighth ([`SETTLED_FRACTION`]) of the largest source error over them, or
    /// [`Self::default_tolerance`] where that is larger. The answer's bound carries that source
    /// error (one bound for all the pixels, as a tile's), so converging further refines values
    /// far below what the bound can tell; the asset's default, an eighth of its smallest
    /// source error anywhere, took rough tiles of a 37 Mpx DEM 6 steps a pixel where 3 keep
    /// the same bound within 12.5% (measured: docs/benchmarks.md). Fails where a chunk of a
    /// chunked asset under the pixels cannot be read: an answer settled on the default instead
    /// would take other steps than the same request answered later, under the same ETag.
    pub fn tolerance_over(&self, pixels: &Pixels) -> Result<f32, crate::Error> {
        Ok(settled_over(
            self.default_tolerance(),
            self.source_error_over(pixels)?,
        ))
    }

    /// The bound on |answer - source| at unit point (u, v) beyond convergence: the source-error
    /// map there, or, on a sample centre of an asset whose codec promised a largest error
    /// (projected `--max-error`), that promise where it is smaller: the map bounds the block's
    /// half-cell lattice, most of which lies between samples, where the continuation leaves the
    /// bilinear source further.
    pub fn source_error_at(&self, u: f32, v: f32) -> Option<f32> {
        let map = self.source_error.as_ref()?.at(u, v);
        let on_sample = |t: f32, n: u32| {
            let x = f64::from(t) * f64::from(n) - 0.5;
            (x - x.round()).abs() < f64::from(sample_snap(n))
        };
        let promise = self
            .planes()
            .first()
            .and_then(|p| p.promise())
            .filter(|_| on_sample(u, self.meta.width) && on_sample(v, self.meta.height));
        Some(promise.map_or(map, |e| e.min(map)))
    }

    /// Continuous decoding of many unit points at once (batched), each with its own bound; a
    /// chain stops early once its bound is at most `tolerance` (source units; 0: never early).
    pub fn points(&self, pts: &[[f32; 2]], iterations: u32, tolerance: f32) -> Vec<PointSample> {
        self.points_with(pts, iterations, tolerance, &|_, _, _, _| None)
    }

    /// [`Asset::points`], each plane's chains offered first to `continuous` (see
    /// [`ChainDevice`]).
    pub fn points_with(
        &self,
        pts: &[[f32; 2]],
        iterations: u32,
        tolerance: f32,
        continuous: &ChainDevice<'_>,
    ) -> Vec<PointSample> {
        self.try_points_with(pts, iterations, tolerance, continuous)
            .unwrap_or_else(|_| {
                let unknown = PointSample {
                    values: vec![f32::NAN; self.meta.channels as usize],
                    error_bound: f32::INFINITY,
                    source_error: None,
                    iterations: 0,
                };
                vec![unknown; pts.len()]
            })
    }

    /// [`Asset::points_with`], with the error of a chunk that cannot be read (chunked assets;
    /// the others always answer). A chunked asset offers each chunk's chains to `continuous`,
    /// the chunk named in its [`PlaneRef`].
    pub fn try_points_with(
        &self,
        pts: &[[f32; 2]],
        iterations: u32,
        tolerance: f32,
        continuous: &ChainDevice<'_>,
    ) -> Result<Vec<PointSample>, crate::Error> {
        if let Some(c) = &self.chunked() {
            return c.points(&self.meta, pts, (iterations, tolerance), continuous);
        }
        let tol = tolerance / self.span().max(f32::MIN_POSITIVE);
        let snapped = self.snap_to_samples(pts);
        let pts = snapped.as_deref().unwrap_or(pts);
        let per_plane: Vec<Vec<decode::PointValue>> = self
            .planes()
            .iter()
            .enumerate()
            .map(|(k, p)| {
                continuous(
                    PlaneRef::whole(k, &p.operator),
                    Sites::List(pts),
                    iterations,
                    tol,
                )
                .unwrap_or_else(|| Answer::Points(p.operator.points(pts, iterations, tol)))
                .limited(&p.operator, Sites::List(pts))
                .into_points()
            })
            .collect();
        let span = self.span();
        let planes: Vec<Vec<f32>> = per_plane
            .iter()
            .map(|v| v.iter().map(|p| p.value).collect())
            .collect();
        let values = self.to_source(planes, |i| (pts[i][0], pts[i][1]), None);
        Ok((0..pts.len())
            .map(|i| {
                let b: Vec<f32> = per_plane.iter().map(|v| v[i].error_bound * span).collect();
                PointSample {
                    values: values.iter().map(|c| c[i]).collect(),
                    error_bound: if b.len() == 3 {
                        rgb_bound(b[0], b[1], b[2])
                    } else {
                        b[0]
                    },
                    source_error: self.source_error_at(pts[i][0], pts[i][1]),
                    iterations: per_plane.iter().map(|v| v[i].iterations).max().unwrap_or(0),
                }
            })
            .collect())
    }
}

/// [`Asset::tolerance_over`]'s rule: the asset's `default` tolerance, or [`SETTLED_FRACTION`]
/// of the largest finite `source` error over the pixels where that is larger.
pub(super) fn settled_over(default: f32, source: Option<f32>) -> f32 {
    source
        .filter(|e| e.is_finite())
        .map_or(default, |e| default.max(SETTLED_FRACTION * e))
}
