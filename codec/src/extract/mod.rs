//! Asset-level decoding: the operator decoders of [`crate::core::decode`] applied to every plane, then
//! brought back to source terms — value units, RGB from YCbCr, nodata where the source had none.
//! This is what the CLI and the server call.

mod chunked;
pub mod volume;

use fractile_proto::{ColourModel, SampleFormat};
use std::sync::Arc;

use rayon::prelude::*;

use crate::core::decode::{self, DiscreteOptions, DiscreteReport, Grid, Method};
use crate::core::operator::Operator;
use crate::geo::{self, Pixels};
use crate::io::asset::Asset;
use crate::render::colour::{rgb_bound, ycbcr_to_rgb};

/// How near a sample centre (in cells) a point counts as on it at least, for assets whose codec
/// knows its samples (see [`sample_snap`]): far below any real offset.
pub const SAMPLE_SNAP: f32 = 1e-4;

/// How near a sample centre (in cells) a point counts as on it, on an axis of `cells` cells:
/// [`SAMPLE_SNAP`], or eight times the rounding of a unit coordinate in f32 (`cells x 2^-25`)
/// where that is more (1.0e-3 of a cell on a 4,320-cell axis, 0.016 on 65,536). Why: a position
/// that names a centre (a native decode's pixel, a longitude on the georeference's own grid)
/// reaches the decoder a few roundings off it, and the continuation of a rough surface (rho
/// 0.9, a Hölder exponent of 0.15) moves by a quarter of its detail amplitude within 2^-12 of
/// a cell: 100-260 m on a global DEM, where the centre itself is within the coded error.
pub fn sample_snap(cells: u32) -> f32 {
    SAMPLE_SNAP.max(cells as f32 * 2f32.powi(-22))
}

/// `t` (unit coordinates on an axis of `cells` cells) moved onto the sample centre within
/// [`sample_snap`] of it, if there is one.
fn snap_axis(t: f32, cells: u32) -> f32 {
    let n = cells as f64;
    let x = f64::from(t) * n - 0.5;
    if (x - x.round()).abs() < f64::from(sample_snap(cells)) {
        ((x.round() + 0.5) / n) as f32
    } else {
        t
    }
}

/// The part of an asset's smallest source error that its default tolerance may reach (see
/// [`Asset::default_tolerance`]): an eighth, so that the convergence adds at most 12.5% to a
/// bound that the source error makes anyway.
pub const SETTLED_FRACTION: f32 = 0.125;

/// Decodes one plane's point chains elsewhere (a GPU): `(plane, unit points, iterations,
/// normalised tolerance)`, or `None` to leave them to the CPU.
pub type ContinuousHook<'a> =
    dyn Fn(PlaneRef<'_>, Sites<'_>, u32, f32) -> Option<Answer> + Sync + 'a;

/// The plane a [`ContinuousHook`] is asked to decode: where it is in its asset, and its
/// operator. A device keeps operators resident by `(chunk, index)` within one asset, so the
/// hook is handed the operator itself rather than looking it up: a chunk's operator lives in
/// the chunk, not in the asset the caller holds.
#[derive(Clone, Copy)]
pub struct PlaneRef<'a> {
    /// The plane's index among its asset's (or its chunk's) planes.
    pub index: usize,
    /// The chunk, for chunked assets: `(level, index in the level)`; `None` for a whole asset.
    pub chunk: Option<(usize, usize)>,
    /// The plane's decoding operator.
    pub operator: &'a crate::io::asset::PlaneOperator,
}

impl<'a> PlaneRef<'a> {
    /// Plane `index` of a whole asset (a chunked asset's chunks name themselves on the way).
    pub fn whole(index: usize, operator: &'a crate::io::asset::PlaneOperator) -> PlaneRef<'a> {
        PlaneRef {
            index,
            chunk: None,
            operator,
        }
    }
}

/// One plane's chains decoded at a [`ContinuousHook`]'s sites (normalised).
#[derive(Clone, Debug, PartialEq)]
pub enum Answer {
    /// A value, bound and step count a site.
    Points(Vec<decode::PointValue>),
    /// The values alone, with the largest bound and the most steps: what a grid (a tile, one
    /// bound for its pixels) needs, kept as a device reads it back. A record a site, built and
    /// taken apart again, doubled a 256 x 256 tile's host time from the device's values to
    /// the tile's heights (134 against 70 us on this project's 2-core machine, 2026-11-26),
    /// where a GPU tile has about 300 us to spend.
    Values {
        /// A value a site.
        values: Vec<f32>,
        /// The largest bound.
        error_bound: f32,
        /// The most steps.
        iterations: u32,
    },
}

impl Answer {
    /// A record a site (values share their one bound).
    pub fn into_points(self) -> Vec<decode::PointValue> {
        match self {
            Answer::Points(p) => p,
            Answer::Values {
                values,
                error_bound,
                iterations,
            } => values
                .into_iter()
                .map(|value| decode::PointValue {
                    value,
                    error_bound,
                    iterations,
                })
                .collect(),
        }
    }

    /// The answer kept in the neighbourhood of the data
    /// ([`crate::io::asset::PlaneOperator::limit_points`]), at the sites it answers.
    pub fn limited(mut self, op: &crate::io::asset::PlaneOperator, sites: Sites<'_>) -> Answer {
        match &mut self {
            Answer::Points(p) => {
                let mut values: Vec<f32> = p.iter().map(|r| r.value).collect();
                sites.limit(op, &mut values);
                for (r, v) in p.iter_mut().zip(values) {
                    r.value = v;
                }
            }
            Answer::Values { values, .. } => sites.limit(op, values),
        }
        self
    }

    /// The values, and the largest bound (`f32::max`'s: a NaN bound is passed over).
    pub fn into_values(self) -> (Vec<f32>, f32) {
        match self {
            Answer::Points(p) => {
                let worst = p.iter().fold(0.0f32, |m, r| m.max(r.error_bound));
                (p.into_iter().map(|r| r.value).collect(), worst)
            }
            Answer::Values {
                values,
                error_bound,
                ..
            } => (values, error_bound),
        }
    }
}

/// Hands out the discrete decode of every plane at `(width, height, iterations, tolerance)`
/// (normalised), as [`Asset::discrete_planes`] computes it: a server keeps recent ones, since
/// every tile of a zoom level coarser than the source samples the same grid.
pub type DiscreteHook<'a> =
    dyn Fn(usize, usize, u32, f32) -> Arc<Vec<(Grid, DiscreteReport)>> + Sync + 'a;

/// Asked between bands of work: `true` when whoever wanted the answer has given up (a server's
/// request that timed out or whose client left), so that the work stops instead of running on.
pub type CancelHook<'a> = dyn Fn() -> bool + Sync + 'a;

/// Work that [`Asset::sample_with`] lets its caller do elsewhere or keep.
pub struct Delegates<'a> {
    /// Continuous chains (a GPU).
    pub continuous: &'a ContinuousHook<'a>,
    /// Discrete decodes for coarse pixels (a cache).
    pub discrete: &'a DiscreteHook<'a>,
    /// Whether to stop (see [`CancelHook`]).
    pub cancelled: &'a CancelHook<'a>,
}

/// [`Asset::sample_with`] stopped because its [`CancelHook`] said so.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cancelled;

/// Why [`Asset::sample_with`] gave no answer.
#[derive(Clone, Debug)]
pub enum SampleError {
    /// Its [`CancelHook`] said to stop.
    Cancelled,
    /// A chunk of a chunked asset could not be read or decoded (a corrupt or missing part of
    /// the file, or its store unreachable).
    Chunk(crate::Error),
}

impl From<Cancelled> for SampleError {
    fn from(_: Cancelled) -> SampleError {
        SampleError::Cancelled
    }
}

/// Points decoded between two questions to a [`CancelHook`]: a few tens of milliseconds of
/// work on one core, and a 512 x 512 tile in one band (no split, no cost).
const BAND_POINTS: usize = 1 << 18;

/// The unit points a [`ContinuousHook`] is asked for.
#[derive(Clone, Copy, Debug)]
pub enum Sites<'a> {
    /// Points in the order given.
    List(&'a [[f32; 2]]),
    /// The separable grid `(xs[i], ys[j])`, row-major.
    Grid {
        /// Unit x of each column.
        xs: &'a [f32],
        /// Unit y of each row.
        ys: &'a [f32],
    },
}

impl Sites<'_> {
    /// [`crate::io::asset::PlaneOperator::limit_points`] of `values` at these sites.
    fn limit(&self, op: &crate::io::asset::PlaneOperator, values: &mut [f32]) {
        match self {
            Sites::List(points) => op.limit_points(points, values),
            Sites::Grid { xs, ys } => op.limit_grid(xs, ys, values),
        }
    }

    /// How many points.
    pub fn len(&self) -> usize {
        match self {
            Sites::List(p) => p.len(),
            Sites::Grid { xs, ys } => xs.len() * ys.len(),
        }
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Delegates that keep all work on the CPU and never stop (chunked assets, which ask their
/// chunks' own discrete decodes).
fn no_delegates() -> Delegates<'static> {
    Delegates {
        continuous: &|_, _, _, _| None,
        discrete: &|_, _, _, _| Arc::new(Vec::new()),
        cancelled: &|| false,
    }
}

/// A decoded raster in source units.
#[derive(Clone, Debug)]
pub struct Decoded {
    /// Width in samples.
    pub width: usize,
    /// Height in samples.
    pub height: usize,
    /// One plane per source channel (RGB for colour), NaN where the source had no data.
    pub channels: Vec<Vec<f32>>,
}

/// One point of an asset, in source units.
#[derive(Clone, Debug, PartialEq)]
pub struct PointSample {
    /// One value per source channel (NaN on nodata).
    pub values: Vec<f32>,
    /// Bound on the error against the attractor, in source units (largest over channels):
    /// how far the iterations are from converged.
    pub error_bound: f32,
    /// The asset's measured error against its source where the point lies (its
    /// source-error map; `None` for assets without one): added to `error_bound`, it bounds
    /// the distance to the data that was encoded.
    pub source_error: Option<f32>,
    /// Inverse steps taken (largest over channels).
    pub iterations: u32,
}

impl Asset {
    fn span(&self) -> f32 {
        (self.meta.value_max - self.meta.value_min) as f32
    }

    fn peak(&self) -> f32 {
        match self.meta.sample {
            SampleFormat::U16 => 65535.0,
            _ => 255.0,
        }
    }

    /// Largest |s| over every map, for choosing iteration counts.
    pub fn max_contrast(&self) -> f32 {
        if let Some(c) = &self.chunks {
            return c.table.max_contrast;
        }
        self.planes
            .iter()
            .map(|p| p.operator.max_contrast())
            .chain(self.volume.iter().map(|v| v.operator.max_contrast()))
            .fold(0.0, f32::max)
    }

    /// A-priori bound (source units) after `n` iterations everywhere, from the largest |s|.
    pub fn bound_after(&self, n: u32) -> f32 {
        if let Some(c) = &self.chunks {
            // The largest chunk's bound at n is at most max |s|^n times the largest seed bound.
            return c.table.max_contrast.powi(n as i32) * c.table.seed_bound;
        }
        let half = self
            .planes
            .iter()
            .map(|p| p.operator.invariant_interval())
            .chain(self.volume.iter().map(|v| {
                use crate::core::operator::Operator;
                v.operator.invariant_interval()
            }))
            .map(|(lo, hi)| (hi - lo) / 2.0)
            .fold(0.0, f32::max);
        let b = self.max_contrast().powi(n as i32) * half * self.span();
        if self.meta.colour == ColourModel::YCbCr {
            rgb_bound(b, b, b)
        } else {
            b
        }
    }

    /// Brings normalised planes sampled at unit points back to source units.
    fn to_source(
        &self,
        planes: Vec<Vec<f32>>,
        points: impl Fn(usize) -> (f32, f32) + Sync,
        footprint: Option<[f32; 4]>,
    ) -> Vec<Vec<f32>> {
        let (lo, span) = (self.meta.value_min as f32, self.span());
        let mut out: Vec<Vec<f32>> = match self.meta.colour {
            ColourModel::Grey => planes
                .into_iter()
                .map(|mut p| {
                    p.iter_mut().for_each(|v| *v = lo + *v * span);
                    p
                })
                .collect(),
            ColourModel::YCbCr => {
                let peak = self.peak();
                let n = planes[0].len();
                let mut rgb = vec![
                    Vec::with_capacity(n),
                    Vec::with_capacity(n),
                    Vec::with_capacity(n),
                ];
                for ((&y, &cb), &cr) in planes[0].iter().zip(&planes[1]).zip(&planes[2]) {
                    let c = ycbcr_to_rgb(y * span + lo, cb * span + lo, cr * span + lo, peak);
                    for (plane, v) in rgb.iter_mut().zip(c) {
                        plane.push(v);
                    }
                }
                rgb
            }
        };
        // A footprint (a box holding every point) with no nodata cell under it skips the
        // per-point lookups.
        let mask = self
            .mask
            .as_ref()
            .filter(|m| !footprint.is_some_and(|f| m.all_valid(f)));
        if let Some(mask) = mask {
            // Once for every channel; in chunks of 16k points, so that a tile is a few tasks
            // (a task per few points cost a fifth of a tile's time).
            let n = out.first().map_or(0, Vec::len);
            let valid: Vec<bool> = (0..n)
                .into_par_iter()
                .with_min_len(1 << 14)
                .map(|i| {
                    let (u, v) = points(i);
                    mask.at(u, v)
                })
                .collect();
            for ch in &mut out {
                for (v, &ok) in ch.iter_mut().zip(&valid) {
                    if !ok {
                        *v = f32::NAN;
                    }
                }
            }
        }
        out
    }

    /// Discrete decoding of the whole asset at `width x height`.
    pub fn decode(
        &self,
        width: usize,
        height: usize,
        opts: DiscreteOptions,
    ) -> (Decoded, DiscreteReport) {
        if self.chunks.is_some() {
            return self.decode_chunked(width, height, opts);
        }
        let results: Vec<(Grid, DiscreteReport)> = self
            .planes
            .iter()
            .map(|p| self.discrete(&p.operator, width, height, opts))
            .collect();
        let report = DiscreteReport {
            iterations: results.iter().map(|r| r.1.iterations).max().unwrap_or(0),
            last_change: results.iter().map(|r| r.1.last_change).fold(0.0, f32::max),
            error_bound: results.iter().map(|r| r.1.error_bound).fold(0.0, f32::max),
        };
        let planes = results.into_iter().map(|r| r.0.values).collect();
        let channels = self.to_source(
            planes,
            |i| {
                (
                    ((i % width) as f32 + 0.5) / width as f32,
                    ((i / width) as f32 + 0.5) / height as f32,
                )
            },
            None,
        );
        (
            Decoded {
                width,
                height,
                channels,
            },
            report,
        )
    }

    /// A plane's discrete decode at `width` x `height`. An operator that knows its attractor at
    /// the source's own sample centres ([`crate::io::asset::PlaneOperator::samples`]) answers
    /// that size, and any coarser one, without iterating: a coarser grid is the samples' area
    /// means (the box filter of its cells, exact; a decode at that size would sample the
    /// continuation between the samples, iterating to a bound, and the filtered taps of
    /// [`Asset::sample`] would then average those).
    fn discrete(
        &self,
        op: &crate::io::asset::PlaneOperator,
        width: usize,
        height: usize,
        opts: DiscreteOptions,
    ) -> (Grid, DiscreteReport) {
        let native = [self.meta.width as usize, self.meta.height as usize];
        match op.samples() {
            Some(z) if [width, height] == native && z.len() == width * height => (
                Grid {
                    width,
                    height,
                    values: z.to_vec(),
                },
                DiscreteReport {
                    iterations: 0,
                    last_change: 0.0,
                    error_bound: 0.0,
                },
            ),
            Some(z)
                if width <= native[0]
                    && height <= native[1]
                    && z.len() == native[0] * native[1] =>
            {
                let samples = Grid {
                    width: native[0],
                    height: native[1],
                    values: z.to_vec(),
                };
                (
                    samples.area_means(width, height),
                    DiscreteReport {
                        iterations: 0,
                        last_change: 0.0,
                        error_bound: 0.0,
                    },
                )
            }
            _ => {
                let (mut grid, report) = decode::discrete(op, width, height, opts);
                let centres = |n: usize| -> Vec<f32> {
                    (0..n).map(|i| (i as f32 + 0.5) / n as f32).collect()
                };
                // Pixels finer than the cells sample the continuation; coarser ones average
                // cells, whose range their centre's neighbourhood need not hold.
                if width >= native[0] && height >= native[1] {
                    op.limit_grid(&centres(width), &centres(height), &mut grid.values);
                }
                (grid, report)
            }
        }
    }

    /// [`Asset::decode`] of a chunked asset: its chunks sample the pixel centres (continuously;
    /// coarser than the source, from the overview of their size), each to within the
    /// options' tolerance or iterations. A chunk that cannot be read leaves NaN, and the
    /// report an infinite bound.
    fn decode_chunked(
        &self,
        width: usize,
        height: usize,
        opts: DiscreteOptions,
    ) -> (Decoded, DiscreteReport) {
        let centres = |n: usize| (0..n).map(|i| Some((i as f32 + 0.5) / n as f32)).collect();
        let pixels = Pixels {
            sites: geo::Sites::Grid {
                xs: centres(width),
                ys: centres(height),
            },
            footprint: [1.0 / width as f32, 1.0 / height as f32],
        };
        let delegates = no_delegates();
        // Fixed iterations stay fixed; a change criterion becomes the default tolerance.
        let tolerance = if opts.max_error > 0.0 {
            opts.max_error * self.span()
        } else if opts.min_change > 0.0 {
            self.default_tolerance()
        } else {
            0.0
        };
        let (channels, bound) =
            match self.sample_with(&pixels, opts.max_iterations, tolerance, &delegates) {
                Ok(r) => r,
                Err(_) => (
                    vec![vec![f32::NAN; width * height]; self.meta.channels as usize],
                    f32::INFINITY,
                ),
            };
        (
            Decoded {
                width,
                height,
                channels,
            },
            DiscreteReport {
                iterations: opts.max_iterations,
                last_change: 0.0,
                error_bound: bound / self.span().max(f32::MIN_POSITIVE),
            },
        )
    }

    /// Discrete decoding at the source's own size.
    pub fn decode_native(&self) -> (Decoded, DiscreteReport) {
        self.decode(
            self.meta.width as usize,
            self.meta.height as usize,
            DiscreteOptions::default(),
        )
    }

    /// Continuous decoding of one unit point (u, v) with `iterations` inverse steps.
    pub fn point(&self, u: f32, v: f32, iterations: u32) -> PointSample {
        if self.chunks.is_some() {
            return self.points(&[[u, v]], iterations, 0.0).remove(0);
        }
        let [u, v] = self.snap_to_samples(&[[u, v]]).map_or([u, v], |p| p[0]);
        let pv: Vec<_> = self
            .planes
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
    fn snap_to_samples(&self, pts: &[[f32; 2]]) -> Option<Vec<[f32; 2]>> {
        self.planes.first()?.operator.samples()?;
        let (w, h) = (self.meta.width, self.meta.height);
        Some(
            pts.iter()
                .map(|&[u, v]| [snap_axis(u, w), snap_axis(v, h)])
                .collect(),
        )
    }

    /// [`Self::snap_to_samples`] of a raster's pixels (the points of patches stay as they are:
    /// they are off the centres of the source's grid).
    fn snap_pixels(&self, pixels: &Pixels) -> Option<Pixels> {
        self.planes.first()?.operator.samples()?;
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
            .or_else(|| self.chunks.as_ref()?.table.smallest_source_error)
            .map(|e| match self.planes.first().and_then(|p| p.promise()) {
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
        let default = self.default_tolerance();
        Ok(self
            .source_error_over(pixels)?
            .filter(|e| e.is_finite())
            .map_or(default, |e| default.max(SETTLED_FRACTION * e)))
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
            .planes
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
    /// [`ContinuousHook`]).
    pub fn points_with(
        &self,
        pts: &[[f32; 2]],
        iterations: u32,
        tolerance: f32,
        continuous: &ContinuousHook<'_>,
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
        continuous: &ContinuousHook<'_>,
    ) -> Result<Vec<PointSample>, crate::Error> {
        if let Some(c) = &self.chunks {
            return c.points(&self.meta, pts, (iterations, tolerance), continuous);
        }
        let tol = tolerance / self.span().max(f32::MIN_POSITIVE);
        let snapped = self.snap_to_samples(pts);
        let pts = snapped.as_deref().unwrap_or(pts);
        let per_plane: Vec<Vec<decode::PointValue>> = self
            .planes
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

    /// Normalised planes of a `width x height` window `[u0, v0, u1, v1]` decoded elsewhere (the
    /// GPU), kept in the neighbourhood of the data and brought back to source units as
    /// [`Asset::window`] does.
    pub fn window_from_planes(
        &self,
        rect: [f32; 4],
        width: usize,
        height: usize,
        mut planes: Vec<Vec<f32>>,
    ) -> Decoded {
        let [u0, v0, u1, v1] = rect;
        // Pixels no larger than a cell sample the continuation; coarser ones average cells,
        // whose range their centre's neighbourhood need not hold.
        let fine = (u1 - u0).abs() * self.meta.width as f32 <= width as f32
            && (v1 - v0).abs() * self.meta.height as f32 <= height as f32;
        if fine {
            let (xs, ys) = decode::window_axes(rect, width, height);
            for (p, values) in self.planes.iter().zip(planes.iter_mut()) {
                p.operator.limit_grid(&xs, &ys, values);
            }
        }
        let channels = self.to_source(
            planes,
            |i| {
                (
                    u0 + ((i % width) as f32 + 0.5) / width as f32 * (u1 - u0),
                    v0 + ((i / width) as f32 + 0.5) / height as f32 * (v1 - v0),
                )
            },
            None,
        );
        Decoded {
            width,
            height,
            channels,
        }
    }

    /// A window `[u0, v0, u1, v1]` of the unit square at `width x height`.
    pub fn window(
        &self,
        rect: [f32; 4],
        width: usize,
        height: usize,
        iterations: Option<u32>,
        method: Method,
    ) -> (Decoded, Method) {
        self.window_with(rect, width, height, (iterations, method), &|_, _, _, _| {
            None
        })
    }

    /// [`Asset::window`], a chunked asset's chains offered to `continuous` chunk by chunk (a
    /// GPU). A whole asset's window is decoded here on the CPU: a device makes its grid
    /// itself (`fractile_gpu`'s `Grid::Window`), which the caller asks for directly.
    pub fn window_with(
        &self,
        rect: [f32; 4],
        width: usize,
        height: usize,
        (iterations, method): (Option<u32>, Method),
        continuous: &ContinuousHook<'_>,
    ) -> (Decoded, Method) {
        if self.chunks.is_some() {
            // Chunks answer continuously (the overview of the pixels' size where they are
            // coarser than the source), whatever the method asked.
            let (xs, ys) = decode::window_axes(rect, width, height);
            let pixels = Pixels {
                sites: geo::Sites::Grid {
                    xs: xs.into_iter().map(Some).collect(),
                    ys: ys.into_iter().map(Some).collect(),
                },
                footprint: [
                    (rect[2] - rect[0]).abs() / width as f32,
                    (rect[3] - rect[1]).abs() / height as f32,
                ],
            };
            let n = iterations
                .unwrap_or(crate::core::decode::DiscreteOptions::default().max_iterations);
            let tolerance = if iterations.is_some() {
                0.0
            } else {
                self.default_tolerance()
            };
            let delegates = Delegates {
                continuous,
                ..no_delegates()
            };
            let channels = match self.sample_with(&pixels, n, tolerance, &delegates) {
                Ok((c, _)) => c,
                Err(_) => vec![vec![f32::NAN; width * height]; self.meta.channels as usize],
            };
            return (
                Decoded {
                    width,
                    height,
                    channels,
                },
                Method::Continuous,
            );
        }
        let mut chosen = method;
        let planes = self
            .planes
            .iter()
            .map(|p| {
                let (g, m) = decode::window(&p.operator, rect, width, height, iterations, method);
                chosen = m;
                g.values
            })
            .collect();
        (self.window_from_planes(rect, width, height, planes), chosen)
    }

    /// Values at the pixels of a raster (row-major; a pixel outside the asset is answered as
    /// NaN), each standing for `pixels.footprint` (unit coordinates): a tile, a region or a
    /// mesh. Where a pixel covers more than a source cell the asset is decoded discretely at the
    /// pixels' own scale and sampled (a filtered answer, no aliasing); otherwise each point is
    /// decoded continuously ([`crate::io::asset::PlaneOperator::grid`] for separable grids,
    /// [`crate::io::asset::PlaneOperator::points`] for point lists) with at most `iterations`
    /// steps, stopping once its bound is at most `tolerance` (source units; 0: never early).
    /// Returns the channels and the a-priori error bound (source units, largest over the
    /// points). A chunk of a chunked asset that cannot be read leaves NaN and an infinite
    /// bound ([`Asset::sample_with`] says why).
    pub fn sample(&self, pixels: &Pixels, iterations: u32, tolerance: f32) -> (Vec<Vec<f32>>, f32) {
        let discrete = |w, h, n, t| Arc::new(self.discrete_planes(w, h, n, t));
        let delegates = Delegates {
            continuous: &|_, _, _, _| None,
            discrete: &discrete,
            cancelled: &|| false,
        };
        self.sample_with(pixels, iterations, tolerance, &delegates)
            .unwrap_or_else(|_| {
                let nan = vec![f32::NAN; pixels.len()];
                (vec![nan; self.meta.channels as usize], f32::INFINITY)
            })
    }

    /// The asset's measured error against its source over the pixels (the largest of its
    /// source-error map over their extent, each pixel's footprint included); `None` for assets
    /// without a map and for pixels wholly outside. For pixels coarser than the source (a
    /// filtered answer) this is the largest point error under them, which bounds the filtered
    /// answer against the source filtered the same way. Fails where a chunk of a chunked
    /// asset under the pixels cannot be read (its map is in the chunk).
    pub fn source_error_over(&self, pixels: &Pixels) -> Result<Option<f32>, crate::Error> {
        if let Some(c) = &self.chunks {
            return c.source_error_over(&self.meta, pixels);
        }
        Ok(self.source_error_map_over(pixels))
    }

    /// [`Asset::source_error_over`] of an asset that is one operator.
    fn source_error_map_over(&self, pixels: &Pixels) -> Option<f32> {
        let map = self.source_error.as_ref()?;
        let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        let mut take = |p: [f32; 2]| {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        };
        match &pixels.sites {
            crate::geo::Sites::Grid { xs, ys } => {
                // A grid's extent: its extreme columns and rows (once there is one of each).
                if ys.iter().any(Option::is_some) {
                    let y = ys.iter().flatten().copied();
                    let (y0, y1) = y.fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), v| {
                        (a.min(v), b.max(v))
                    });
                    for &x in xs.iter().flatten() {
                        take([x, y0]);
                        take([x, y1]);
                    }
                }
            }
            crate::geo::Sites::List { points, .. } => {
                points.iter().flatten().for_each(|&p| take(p))
            }
        }
        if lo[0] > hi[0] {
            return None;
        }
        let [fx, fy] = pixels.footprint.map(|f| f / 2.0);
        Some(map.over([lo[0] - fx, lo[1] - fy, hi[0] + fx, hi[1] + fy]))
    }

    /// Every plane decoded discretely at `width x height` (normalised values) with at most
    /// `iterations` steps, fewer once each is within `tolerance` (normalised; 0: all of them) of
    /// its discrete attractor: what coarse pixels of [`Asset::sample`] are sampled from.
    pub fn discrete_planes(
        &self,
        width: usize,
        height: usize,
        iterations: u32,
        tolerance: f32,
    ) -> Vec<(Grid, DiscreteReport)> {
        if let Some(c) = &self.chunks {
            // Coarse pixels of a chunked asset are filtered from its top level, one chunk.
            return c.top_discrete_planes(width, height, iterations, tolerance);
        }
        let opts = DiscreteOptions::within(tolerance, iterations);
        self.planes
            .iter()
            .map(|p| self.discrete(&p.operator, width, height, opts))
            .collect()
    }

    /// [`Asset::sample`], with the continuous chains of each plane offered first to
    /// `delegates.continuous(plane, grid, iterations, tolerance)` (normalised tolerance), which
    /// may answer them elsewhere (a GPU) or return `None` to leave them to the CPU, and the
    /// discrete decodes of coarse pixels taken from `delegates.discrete`. Large requests are
    /// decoded in bands of rows or points, asking `delegates.cancelled` before each: the
    /// answers are the same (every point is decoded on its own), and a caller that gave up
    /// gets [`Cancelled`] within a band's time.
    pub fn sample_with(
        &self,
        pixels: &Pixels,
        iterations: u32,
        tolerance: f32,
        delegates: &Delegates<'_>,
    ) -> Result<(Vec<Vec<f32>>, f32), SampleError> {
        if let Some(c) = &self.chunks {
            return c.sample(&self.meta, pixels, (iterations, tolerance), delegates);
        }
        let snapped = self.snap_pixels(pixels);
        let pixels = snapped.as_ref().unwrap_or(pixels);
        let stop = || {
            if (delegates.cancelled)() {
                Err(Cancelled)
            } else {
                Ok(())
            }
        };
        stop()?;
        let footprint = pixels.footprint;
        // Decode the pixels inside the asset, then put them back in place.
        let inside = Inside::of(&pixels.sites);
        let (w, h) = (self.meta.width as f32, self.meta.height as f32);
        let coarse = footprint[0] * w > 1.0 || footprint[1] * h > 1.0;
        let tol = tolerance / self.span().max(f32::MIN_POSITIVE);
        // Largest per-point bound of the continuous path (normalised).
        let mut worst = 0.0f32;
        // A-posteriori bound of the discrete decodes (normalised).
        let mut coarse_bound = f32::INFINITY;
        let planes: Vec<Vec<f32>> = if coarse {
            let (planes, bound) = self.filtered(&inside, footprint, delegates, iterations, tol);
            coarse_bound = bound;
            planes
        } else {
            let mut planes = Vec::with_capacity(self.planes.len());
            for k in 0..self.planes.len() {
                let (values, bound) = self
                    .continuous_plane(k, &inside, (iterations, tol), delegates)?
                    .into_values();
                worst = worst.max(bound);
                planes.push(values);
            }
            planes
        };
        stop()?;
        let inner = self.to_source(planes, |k| inside.at(k), inside.footprint());
        let channels = inner
            .into_iter()
            .map(|ch| inside.scatter(ch, pixels.len()))
            .collect();
        let bound = if coarse {
            // Against the discrete attractor at the pixels' scale; the a-priori bound holds
            // too, so the smaller of the two.
            let b = coarse_bound * self.span();
            let b = if self.meta.colour == ColourModel::YCbCr {
                rgb_bound(b, b, b)
            } else {
                b
            };
            b.min(self.bound_after(iterations))
        } else {
            let b = worst * self.span();
            if self.meta.colour == ColourModel::YCbCr {
                rgb_bound(b, b, b)
            } else {
                b
            }
        };
        Ok((channels, bound))
    }

    /// Pixels coarser than the source, filtered: a mip level per axis, the source size halved
    /// while its cells stay no larger than a pixel (so cells measure between half a pixel and a
    /// pixel), and a pixel averages 2 x 2 bilinear taps spread over its footprint, which covers
    /// every cell under it: filtered, never aliased. Tiles of one zoom share their grid within
    /// each band of latitude where Mercator keeps a pixel's height within one power of two;
    /// an asset spanning many latitudes has a few grids per zoom (one per band), each decoded
    /// once. One grid for the whole zoom would alias at one end of the band or blur at the
    /// other (by cos(latitude): 11x at 85 degrees). Returns the planes and the discrete
    /// decodes' a-posteriori bound (normalised).
    fn filtered(
        &self,
        inside: &Inside,
        footprint: [f32; 2],
        delegates: &Delegates<'_>,
        iterations: u32,
        tol: f32,
    ) -> (Vec<Vec<f32>>, f32) {
        let level = |fp: f32, n: u32| {
            let cells = (fp * n as f32).max(1.0);
            let halvings = cells.log2().floor().clamp(0.0, 30.0) as u32;
            (n as usize).div_ceil(1 << halvings).max(1)
        };
        let (gw, gh) = (
            level(footprint[0], self.meta.width),
            level(footprint[1], self.meta.height),
        );
        let (qx, qy) = (
            0.25 * footprint[0] * gw as f32,
            0.25 * footprint[1] * gh as f32,
        );
        // At the source's own size, planes that hold their samples are their grids: a tile's
        // pixels are filtered from them in place (no copy a tile, nothing for a cache to keep;
        // a chunk's pixels of one to 1.4 of its cells are all filtered so).
        let native = [self.meta.width as usize, self.meta.height as usize];
        if let Inside::Grid { ix, iy, .. } = inside
            && [gw, gh] == native
        {
            let samples: Option<Vec<&[f32]>> = self
                .planes
                .iter()
                .map(|p| p.operator.samples().filter(|z| z.len() == gw * gh))
                .collect();
            if let Some(samples) = samples {
                let planes = samples
                    .iter()
                    .map(|z| filter_separable((z, gw, gh), (ix, iy), [qx, qy]))
                    .collect();
                return (planes, 0.0);
            }
        }
        let grids = (delegates.discrete)(gw, gh, iterations, tol);
        let bound = grids.iter().map(|(_, r)| r.error_bound).fold(0.0, f32::max);
        let planes = grids
            .iter()
            .map(|(g, _)| {
                if let Inside::Grid { ix, iy, .. } = inside {
                    return filter_separable((&g.values, g.width, g.height), (ix, iy), [qx, qy]);
                }
                (0..inside.len())
                    .map(|k| {
                        let (u, v) = inside.at(k);
                        let (x, y) = (u * gw as f32 - 0.5, v * gh as f32 - 0.5);
                        0.25 * (decode::sample_bilinear(g, x - qx, y - qy)
                            + decode::sample_bilinear(g, x + qx, y - qy)
                            + decode::sample_bilinear(g, x - qx, y + qy)
                            + decode::sample_bilinear(g, x + qx, y + qy))
                    })
                    .collect()
            })
            .collect();
        (planes, bound)
    }

    /// Plane `k` at the pixels inside the asset by continuous decoding: offered to
    /// `delegates.continuous` first, else on the CPU in bands, asking `delegates.cancelled`
    /// before each.
    fn continuous_plane(
        &self,
        k: usize,
        inside: &Inside,
        (iterations, tol): (u32, f32),
        delegates: &Delegates<'_>,
    ) -> Result<Answer, Cancelled> {
        let stop = || {
            if (delegates.cancelled)() {
                Err(Cancelled)
            } else {
                Ok(())
            }
        };
        let p = &self.planes[k];
        Ok(match inside {
            Inside::Grid { ix, iy, .. } => {
                let at = Sites::Grid { xs: ix, ys: iy };
                // Where the CPU takes the same steps at every pixel (a subdivision), the
                // device and every band take exactly those, so that all answer alike.
                let (iterations, tol) = match p.operator.grid_steps(ix, iy, iterations, tol) {
                    Some(k) => (k, 0.0),
                    None => (iterations, tol),
                };
                let answer = match (delegates.continuous)(
                    PlaneRef::whole(k, &p.operator),
                    at,
                    iterations,
                    tol,
                ) {
                    Some(v) => v,
                    None => {
                        let rows = (BAND_POINTS / ix.len().max(1)).max(1);
                        let mut v = Vec::with_capacity(ix.len() * iy.len());
                        for band in iy.chunks(rows) {
                            stop()?;
                            v.extend(p.operator.grid(ix, band, iterations, tol));
                        }
                        Answer::Points(v)
                    }
                };
                answer.limited(&p.operator, at)
            }
            Inside::List {
                points,
                loose,
                patches,
                ..
            } => match (delegates.continuous)(
                PlaneRef::whole(k, &p.operator),
                Sites::List(points),
                iterations,
                tol,
            )
            .map(|a| a.limited(&p.operator, Sites::List(points)))
            {
                Some(v) => v,
                None => {
                    let mut v = Vec::with_capacity(points.len());
                    for band in points[..*loose].chunks(BAND_POINTS) {
                        stop()?;
                        v.extend(p.operator.points(band, iterations, tol));
                    }
                    for (pa, inside) in patches {
                        stop()?;
                        let all = p.operator.patch(&pa.patch, iterations, tol);
                        if inside.iter().all(|&i| i) {
                            v.extend_from_slice(&all);
                            continue;
                        }
                        v.extend(
                            all.into_iter()
                                .zip(inside)
                                .filter(|(_, i)| **i)
                                .map(|(r, _)| r),
                        );
                    }
                    Answer::Points(v).limited(&p.operator, Sites::List(points))
                }
            },
        })
    }
}

/// [`Asset::sample`]'s filter of a coarse grid (its values, row-major, width and height) at a
/// separable grid of unit points: per point
/// the mean of four bilinear taps `(x +- qx, y +- qy)` (grid pixels), which is separable: each
/// axis's two taps are at most four weighed cells, so the grid's rows are filtered along x
/// once, then the columns along y. The same values as tapping point by point (to f32
/// rounding), for a pass over the rows the points need instead of sixteen reads a point.
fn filter_separable(
    (values, width, height): (&[f32], usize, usize),
    (xs, ys): (&[f32], &[f32]),
    [qx, qy]: [f32; 2],
) -> Vec<f32> {
    // Per point of an axis of n cells: its taps' cells and weights (the mean of the two taps
    // folded in: half each).
    fn taps(list: &[f32], n: usize, q: f32) -> Vec<[(usize, f32); 4]> {
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
enum Inside {
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
    fn of(sites: &geo::Sites) -> Inside {
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
    fn len(&self) -> usize {
        match self {
            Inside::Grid { ix, iy, .. } => ix.len() * iy.len(),
            Inside::List { points, .. } => points.len(),
        }
    }

    /// The unit point of inside pixel k.
    fn at(&self, k: usize) -> (f32, f32) {
        match self {
            Inside::Grid { ix, iy, .. } => (ix[k % ix.len()], iy[k / ix.len()]),
            Inside::List { points, .. } => (points[k][0], points[k][1]),
        }
    }

    /// The unit box that holds every inside point (`None` if a coordinate is NaN).
    fn footprint(&self) -> Option<[f32; 4]> {
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
    fn scatter(&self, values: Vec<f32>, len: usize) -> Vec<f32> {
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
