//! Asset-level decoding: the operator decoders of [`crate::decode`] applied to every plane, then
//! brought back to source terms — value units, RGB from YCbCr, nodata where the source had none.
//! This is what the CLI and the server call.

mod answer;
mod chunked;
mod filter;
pub mod octree;
mod points;
mod resources;
mod sample;
pub mod volume;

pub use answer::{Distances, Points, Question, Request, Sampled};
pub use resources::{CoarseCounts, CoarseGrids, Resources};

use fractile_proto::{ColourModel, SampleFormat};

use rayon::prelude::*;

use crate::codecs::projected::deliver_plane;
use crate::core::decode::{self, DiscreteOptions, DiscreteReport, Grid};
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

/// The sample `i` of an axis of `cells` cells whose centre `t` (unit coordinates) is exactly, as
/// [`snap_axis`] puts a position onto it; `None` off every centre.
fn centre_index(t: f32, cells: usize) -> Option<usize> {
    let n = cells as f64;
    let i = (f64::from(t) * n - 0.5).round();
    (i >= 0.0 && i < n && ((i + 0.5) / n) as f32 == t).then_some(i as usize)
}

/// Indices that follow one another from the first (`first..first + n`): a window's columns,
/// whose values are then copied a row at a time instead of one by one.
fn consecutive(indices: &[usize]) -> Option<std::ops::Range<usize>> {
    let &first = indices.first()?;
    let run = first..first + indices.len();
    indices.iter().copied().eq(run.clone()).then_some(run)
}

/// The part of an asset's smallest source error that its default tolerance may reach (see
/// [`Asset::default_tolerance`]): an eighth, so that the convergence adds at most 12.5% to a
/// bound that the source error makes anyway.
pub const SETTLED_FRACTION: f32 = 0.125;

/// A device that decodes one plane's point chains (a GPU): `(plane, unit points, iterations,
/// normalised tolerance)`, or `None` to leave them to the CPU ([`Resources::device`]).
pub type ChainDevice<'a> = dyn Fn(PlaneRef<'_>, Sites<'_>, u32, f32) -> Option<Answer> + Sync + 'a;

/// The plane a [`ChainDevice`] is asked to decode: where it is in its asset, and its
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

/// One plane's chains decoded at a [`ChainDevice`]'s sites (normalised).
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

/// [`Asset::sample_with`] stopped because its asker gave up ([`Resources::given_up`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cancelled;

/// Why [`Asset::sample_with`] gave no answer.
#[derive(Clone, Debug)]
pub enum SampleError {
    /// Its asker gave up ([`Resources::given_up`]).
    Cancelled,
    /// A chunk of a chunked asset could not be read or decoded (a corrupt or missing part of
    /// the file, or its store unreachable).
    Chunk(crate::Error),
    /// The asset answers no question of this kind (distances of a raster, a tile of a volume).
    Refused(crate::Error),
}

impl SampleError {
    /// The crate's error for it: a chunk's own, or, given up, unavailable (asking again may
    /// answer).
    pub fn into_error(self) -> crate::Error {
        match self {
            SampleError::Cancelled => crate::Error::unavailable("the answer was given up"),
            SampleError::Chunk(e) | SampleError::Refused(e) => e,
        }
    }
}

impl From<Cancelled> for SampleError {
    fn from(_: Cancelled) -> SampleError {
        SampleError::Cancelled
    }
}

/// Points decoded between two looks at [`Resources::given_up`]: a few tens of milliseconds of
/// work on one core, and a 512 x 512 tile in one band (no split, no cost).
const BAND_POINTS: usize = 1 << 18;

/// The unit points a [`ChainDevice`] is asked for.
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
        if let Some(c) = &self.chunked() {
            return c.table.max_contrast;
        }
        self.planes()
            .iter()
            .map(|p| p.operator.max_contrast())
            .chain(self.volume().iter().map(|v| v.operator.max_contrast()))
            .fold(0.0, f32::max)
    }

    /// A-priori bound (source units) after `n` iterations everywhere, from the largest |s|.
    pub fn bound_after(&self, n: u32) -> f32 {
        if let Some(c) = &self.chunked() {
            // The largest chunk's bound at n is at most max |s|^n times the largest seed bound.
            return c.table.max_contrast.powi(n as i32) * c.table.seed_bound;
        }
        let half = self
            .planes()
            .iter()
            .map(|p| p.operator.invariant_interval())
            .chain(self.volume().iter().map(|v| {
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
            ColourModel::Grey => {
                // In f64, and onto the quantum where an answer lies within the float32
                // roundings of one: a promise holds in what users receive (issue 73).
                let (lo, span) = (
                    self.meta.value_min,
                    self.meta.value_max - self.meta.value_min,
                );
                let onto = match self.planes() {
                    [p] => match &p.coding {
                        crate::io::asset::Coding::Projected { header, .. } => {
                            header.delivered_quantum()
                        }
                        _ => None,
                    },
                    _ => None,
                };
                planes
                    .into_iter()
                    .map(|mut p| {
                        deliver_plane(&mut p, (lo, span), onto);
                        p
                    })
                    .collect()
            }
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
            .mask()
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
        if self.chunked().is_some() {
            return self.decode_chunked(width, height, opts);
        }
        let results: Vec<(Grid, DiscreteReport)> = self
            .planes()
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
        let resources = Resources::CPU;
        // Fixed iterations stay fixed; a change criterion becomes the default tolerance.
        let tolerance = if opts.max_error > 0.0 {
            opts.max_error * self.span()
        } else if opts.min_change > 0.0 {
            self.default_tolerance()
        } else {
            0.0
        };
        let (channels, bound) =
            match self.sample_with(&pixels, opts.max_iterations, tolerance, &resources) {
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
}
