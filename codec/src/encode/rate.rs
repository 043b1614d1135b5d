//! The rate of a chunked file is the file's: one quality for every chunk (a quantiser step
//! under `--target-bpp`, a max error under the bounded default), the finest whose whole file,
//! overviews, table and maps included, fits `bpp x cells / 8` bytes.
//!
//! Why one quality and not one rate a chunk: equal steps spend the bits where they lower the
//! file's squared error most (equal slopes, as JPEG 2000's rate allocation does across code
//! blocks); a rate a chunk gives a flat ocean chunk as many bits as a mountain range. And a
//! bounded file has one bound, the same in every chunk and across their seams.
//!
//! Why a sample and not a search of whole encodes: the quality is found on a sample of the
//! chunks (of every level, about a quarter of the cells, at most [`SAMPLE_CHUNKS`] chunks), by
//! a safeguarded secant on the logarithm of the bytes, then every chunk is coded once at it.
//! The sample's bytes per valid cell stand for their level's; should the file still come out
//! over the rate, it is coded again at a step the sample's slope says fits (rare: the sample
//! aims [`AIM`] of the budget).

use rayon::prelude::*;

use super::CodecSettings;
use super::encoded::Encoded;
use crate::Error;
pub use crate::codecs::projected::Quality;
use crate::codecs::projected::pyramid::Order;
use crate::codecs::projected::{AtStep, ProjectedSettings};
use crate::io::raster::Raster;

/// What a file's rate asks for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FileRate {
    /// Bits per source cell of the whole file, at most.
    pub bpp: f64,
    /// The smallest max error that fits (the DEM default) rather than the best PSNR.
    pub bounded: bool,
}

/// What a chunked file's chunks are coded at: the file's rate (a quality searched for), or a
/// quality given (`--max-error E`: every source chunk within E). Either way one quality for
/// every chunk, the coded overviews' scaled by [`Quality::at_level`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Target {
    /// The finest quality whose file fits this rate.
    Rate(FileRate),
    /// This quality.
    Quality(Quality),
}

impl Target {
    /// The file's rate, where the quality is to be found.
    pub fn rate(&self) -> Option<FileRate> {
        match self {
            Target::Rate(rate) => Some(*rate),
            Target::Quality(_) => None,
        }
    }
}

impl From<FileRate> for Target {
    fn from(rate: FileRate) -> Target {
        Target::Rate(rate)
    }
}

impl From<Quality> for Target {
    fn from(quality: Quality) -> Target {
        Target::Quality(quality)
    }
}

impl FileRate {
    /// The file's budget in bytes for a raster of `cells`.
    pub fn budget(&self, cells: u64) -> Result<u64, Error> {
        if !(self.bpp.is_finite() && self.bpp > 0.0) {
            return Err(Error::settings(format!(
                "--target-bpp {} must be positive",
                self.bpp
            )));
        }
        Ok((self.bpp * cells as f64 / 8.0).floor() as u64)
    }
}

/// Codes one chunk at a quality; `trial`: a coding of the search, whose file is not kept and
/// may leave its source-error map out (its bytes are then counted as the map's reserve).
pub type EncodeAt<'a> = dyn Fn(&Raster, Quality, bool) -> Result<Encoded, Error> + Sync + 'a;

/// Most chunks a sample codes (12 Mpx of chunks of 1024).
pub const SAMPLE_CHUNKS: usize = 12;
/// The share of the cells a sample takes when that is fewer chunks.
pub const SAMPLE_SHARE: f64 = 0.25;
/// What the sample's estimate aims at, of the budget: the estimate's error on the rasters
/// measured was within 1% (docs/benchmarks.md), and a file over the budget is coded again.
pub const AIM: f64 = 0.985;
/// What the parts of a split encode aim at: they cannot code again (no process knows the whole
/// file's size until `assemble`, which refuses a file over the rate), so they leave room for
/// the sample's error (the first pass of the rates measured came out 0.3-1.6% over
/// [`AIM`]).
pub const PART_AIM: f64 = 0.95;
/// Sample codings at most in one search.
const SEARCH_STEPS: usize = 12;

/// The chunks a sample codes, of each level of a table of `counts[l]` chunks: evenly spaced,
/// about [`SAMPLE_SHARE`] of each level (one at least), at most [`SAMPLE_CHUNKS`] in all.
pub fn sample_indices(counts: &[u32]) -> Vec<Vec<u32>> {
    let all: u32 = counts.iter().sum();
    let share = SAMPLE_SHARE.min(SAMPLE_CHUNKS as f64 / f64::from(all.max(1)));
    counts
        .iter()
        .map(|&n| {
            let m = ((f64::from(n) * share).ceil() as u32).clamp(1, n.max(1));
            (0..m)
                .map(|j| ((f64::from(j) + 0.5) * f64::from(n) / f64::from(m)) as u32)
                .filter(|&i| i < n)
                .collect()
        })
        .collect()
}

/// A sample of a file's chunks: each chunk's level and cells, and what stands for the rest.
pub struct Sample {
    /// The sampled chunks: level and raster.
    pub chunks: Vec<(usize, Raster)>,
    /// Per level: its valid cells over the sample's valid cells of that level.
    pub scale: Vec<f64>,
    /// Bytes of the file that are not chunks (header and table).
    pub overhead: u64,
    /// Overview levels that are views of the source chunks (`io::chunked`): not coded, their
    /// error maps in the table, a share of their source chunk's map budget each.
    pub views: usize,
}

/// Valid cells of a chunk.
pub fn valid_cells(r: &Raster) -> u64 {
    r.valid.as_ref().map_or((r.width * r.height) as u64, |v| {
        v.iter().filter(|&&b| b).count() as u64
    })
}

/// One coding of the sample: the estimated file bytes, the summed squared error and the
/// valid cells compared.
#[derive(Clone, Copy, Debug)]
struct Trial {
    bytes: f64,
    squared: f64,
    samples: u64,
}

impl Sample {
    /// Codes every sampled chunk at `q` on all cores; the file's estimated bytes.
    fn code(&self, q: Quality, encode_at: &EncodeAt<'_>) -> Result<Trial, Error> {
        let coded: Vec<(usize, f64, f64, u64)> = self
            .chunks
            .par_iter()
            .with_max_len(1)
            .filter(|(_, r)| valid_cells(r) > 0)
            .map(|(l, r)| {
                let e = encode_at(r, q.at_level(*l), true)?;
                let sq = e.errors.rmse * e.errors.rmse * e.errors.samples as f64;
                let map = match e.asset.source_error {
                    Some(_) => 0,
                    None => crate::core::fidelity::reserve(e.bytes.len()),
                };
                let views: usize = match *l {
                    0 => (1..=self.views)
                        .map(|d| crate::core::fidelity::reserve(e.bytes.len() >> (2 * d)))
                        .sum(),
                    _ => 0,
                };
                let map = map + views;
                Ok((*l, (e.bytes.len() + map) as f64, sq, e.errors.samples))
            })
            .collect::<Result<_, Error>>()?;
        let mut t = Trial {
            bytes: self.overhead as f64,
            squared: 0.0,
            samples: 0,
        };
        for (l, bytes, sq, n) in coded {
            t.bytes += bytes * self.scale[l];
            t.squared += sq;
            t.samples += n;
        }
        Ok(t)
    }
}

/// What the search of a quality keeps: the points tried (parameter, bytes), to correct the
/// quality should the whole file miss the budget.
pub struct Search<'a> {
    sample: &'a Sample,
    rate: FileRate,
    budget: u64,
    encode_at: &'a EncodeAt<'a>,
    /// Whole quanta for a bound (a source on a quantum): the bound's parameter is then
    /// `ln(E / quantum + 1)` on whole E.
    quantum: f64,
    span: f64,
    design: Option<Order>,
    tried: Vec<(f64, f64)>,
}

impl<'a> Search<'a> {
    /// A search over `sample` for a file of `budget` bytes.
    pub fn new(
        sample: &'a Sample,
        rate: FileRate,
        budget: u64,
        encode_at: &'a EncodeAt<'a>,
    ) -> Search<'a> {
        let (mut lo, mut hi, mut whole) = (f64::INFINITY, f64::NEG_INFINITY, true);
        for (_, r) in &sample.chunks {
            for (i, &v) in r.channels[0].iter().enumerate() {
                if r.valid.as_ref().is_none_or(|m| m[i]) && v.is_finite() {
                    lo = lo.min(f64::from(v));
                    hi = hi.max(f64::from(v));
                    whole &= v.fract() == 0.0;
                }
            }
        }
        let span = if hi > lo { hi - lo } else { 1.0 };
        Search {
            sample,
            rate,
            budget,
            encode_at,
            quantum: if whole { 1.0 } else { 0.0 },
            span,
            design: Some(Order::LiftedTwoRate),
            tried: Vec::new(),
        }
    }

    /// The quality of parameter `t` (a finer quality for a smaller `t`), and `t` snapped to
    /// what it names (whole quanta of a bound).
    fn quality(&self, t: f64) -> (Quality, f64) {
        if !self.rate.bounded {
            let step = t.exp();
            return (
                Quality::Step(AtStep {
                    step,
                    design: self.design,
                }),
                t,
            );
        }
        if self.quantum > 0.0 {
            let e = (t.exp() - 1.0).max(0.0).round();
            (Quality::Bound(e * self.quantum), (e + 1.0).ln())
        } else {
            // No finer than the projected codec codes a continuous plane of this range (a
            // constant sample fits the budget at any bound, and the search went on down).
            let finest = crate::codecs::projected::finest_bound(self.span);
            let e = t.exp().max(finest);
            (Quality::Bound(e), e.ln())
        }
    }

    /// The finest quality whose estimated file fits `aim` of the budget ([`AIM`] for an
    /// encode that can code again, [`PART_AIM`] for the parts of a split one).
    pub fn find(&mut self, aim: f64) -> Result<Quality, Error> {
        // Where the lifted DEMs' steps lay (step / span 2^-5.4 at 1.6 bpp to 2^-2.2 at 0.2),
        // and a bound about a quarter of that: a first try within a few of the secant's.
        let step = self.span * (-1.8 - 2.0 * self.rate.bpp).exp2();
        let guess = if self.rate.bounded { step / 4.0 } else { step };
        let t0 = match (self.rate.bounded, self.quantum > 0.0) {
            (true, true) => (guess / self.quantum + 1.0).ln(),
            _ => guess.ln(),
        };
        let t = self.solve(t0, aim)?;
        if self.rate.bounded {
            return Ok(self.quality(t).0);
        }
        // The other lifted kernel, scored at the same step by the high-rate trade of 6.02 dB
        // a bit a cell: kept, and searched again, only if it scores better.
        let (q, _) = self.quality(t);
        let ours = self.sample.code(q, self.encode_at)?;
        self.design = Some(Order::Lifted97TwoRate);
        let (q97, _) = self.quality(t);
        let theirs = self.sample.code(q97, self.encode_at)?;
        let score = |x: &Trial| {
            let mse = x.squared / x.samples.max(1) as f64;
            10.0 * mse.max(1e-30).log10() + 6.02 * 8.0 * x.bytes / x.samples.max(1) as f64
        };
        if score(&theirs) < score(&ours) {
            self.tried.clear();
            let t = self.solve(t, aim)?;
            return Ok(self.quality(t).0);
        }
        self.design = Some(Order::LiftedTwoRate);
        Ok(q)
    }

    /// A coarser quality after a whole file of `bytes` came out over the budget at `q`: the
    /// sample's slope around `q` carries the file from `bytes` to [`AIM`] of the budget.
    pub fn coarser(&mut self, q: Quality, bytes: u64) -> Result<Quality, Error> {
        let t = match q {
            Quality::Step(s) => s.step.ln(),
            Quality::Bound(e) if self.quantum > 0.0 => (e / self.quantum + 1.0).ln(),
            Quality::Bound(e) => e.ln(),
        };
        let slope = self.slope_near(t);
        let next = t + (AIM * self.budget as f64 / bytes as f64).ln() / slope;
        let (coarser, _) = self.quality(next.max(t + 1e-3));
        Ok(match (coarser, q) {
            // Whole quanta: one more at least.
            (Quality::Bound(a), Quality::Bound(b)) if a <= b => Quality::Bound(b + self.quantum),
            _ => coarser,
        })
    }

    /// d ln(bytes) / dt from the two tried points nearest `t`; -1.3 without two (what the
    /// lifted DEMs measured from 10:1 to 80:1).
    fn slope_near(&self, t: f64) -> f64 {
        let mut pts = self.tried.clone();
        pts.sort_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()));
        match pts.as_slice() {
            [a, b, ..] if (a.0 - b.0).abs() > 1e-9 && a.1 > 0.0 && b.1 > 0.0 => {
                let s = (a.1.ln() - b.1.ln()) / (a.0 - b.0);
                if s < -1e-3 { s.max(-20.0) } else { -1.3 }
            }
            _ => -1.3,
        }
    }

    /// The smallest `t` whose estimate is within `aim` of the budget, by a secant on
    /// ln(bytes) safeguarded by the bracket found so far.
    fn solve(&mut self, t0: f64, aim: f64) -> Result<f64, Error> {
        let target = aim * self.budget as f64;
        // (t, bytes): the largest t still over, the smallest t within.
        let mut over: Option<(f64, f64)> = None;
        let mut within: Option<(f64, f64)> = None;
        let mut t = t0;
        for _ in 0..SEARCH_STEPS {
            let (q, snapped) = self.quality(t);
            let trial = self.sample.code(q, self.encode_at)?;
            self.tried.push((snapped, trial.bytes));
            if trial.bytes <= target {
                if within.is_none_or(|w| snapped < w.0) {
                    within = Some((snapped, trial.bytes));
                }
            } else if over.is_none_or(|o| snapped > o.0) {
                over = Some((snapped, trial.bytes));
            }
            if let Some(w) = within
                && w.1 >= 0.99 * target
            {
                break;
            }
            if let (Some(o), Some(w)) = (over, within)
                && self.quality(o.0).0 != self.quality(w.0).0
                && self.adjacent(o.0, w.0)
            {
                break;
            }
            let slope = self.slope_near(snapped);
            let mut next = snapped + (target.ln() - trial.bytes.ln()) / slope;
            if let (Some(o), Some(w)) = (over, within) {
                let (a, b) = (o.0, w.0);
                let margin = 0.1 * (b - a);
                next = next.clamp(a + margin, b - margin);
            } else {
                // No bracket yet: at most a factor of 16 a try.
                next = next.clamp(snapped - 2.8, snapped + 2.8);
            }
            // A try that names the quality just tried moves one quantum (or 1%) on.
            if self.quality(next).0 == q {
                let up = trial.bytes > target;
                next = match q {
                    Quality::Bound(e) if self.quantum > 0.0 => {
                        let e = e / self.quantum + if up { 1.0 } else { -1.0 };
                        (e.max(0.0) + 1.0).ln()
                    }
                    _ => snapped + if up { 0.01 } else { -0.01 },
                };
            }
            t = next;
        }
        if let Some(w) = within {
            return Ok(w.0);
        }
        // Nothing tried fits: the coarsest quality, whose bytes are mostly what no quality
        // saves (each chunk's header, metadata and map).
        let coarsest = match (self.rate.bounded, self.quantum > 0.0) {
            (true, true) => (self.span / self.quantum + 1.0).ln(),
            _ => self.span.ln(),
        };
        let (q, _) = self.quality(coarsest);
        let floor = self.sample.code(q, self.encode_at)?.bytes;
        if floor > target {
            return Err(Error::settings(format!(
                "--target-bpp {}: the file's {} bytes are less than its chunks take at the coarsest quality (about {:.0} bytes, most of it each chunk's own header and maps): give larger chunks (--chunk) or a higher rate",
                self.rate.bpp, self.budget, floor
            )));
        }
        // Bisection between the finest over and the coarsest.
        let (mut lo, mut hi) = (over.map_or(t0, |o| o.0), coarsest);
        for _ in 0..SEARCH_STEPS {
            if self.adjacent(lo, hi) {
                break;
            }
            let mid = 0.5 * (lo + hi);
            let (q, snapped) = self.quality(mid);
            let bytes = self.sample.code(q, self.encode_at)?.bytes;
            self.tried.push((snapped, bytes));
            if bytes <= target {
                hi = snapped;
            } else {
                lo = snapped;
            }
        }
        Ok(hi)
    }

    /// Whether no quality lies between parameters `a` < `b` worth another try: whole quanta
    /// next to each other, or steps within 0.2%.
    fn adjacent(&self, a: f64, b: f64) -> bool {
        if self.rate.bounded && self.quantum > 0.0 {
            let e = |t: f64| (t.exp() - 1.0).round();
            e(b) - e(a) <= 1.0
        } else {
            (b - a).abs() < 2e-3
        }
    }
}

/// One chunk of a file whose rate is the file's, coded at its `quality` by the projected codec
/// (`ProjectedSettings::at`); `trial`: a coding whose file is not kept, without its
/// source-error map. What the chunked encoders take as their [`EncodeAt`].
pub fn encode_at(raster: &Raster, quality: Quality, trial: bool) -> Result<Encoded, Error> {
    super::encode(
        raster,
        &ProjectedSettings::at(quality, raster, trial),
        &|_, _| {},
    )
}

/// The one quality of a chunked file's chunks under `settings`, for a raster of `channels`: the
/// projected codec's on one channel (its max error, or the file's rate: the smallest bound or
/// the finest step that fits it); `None` for the other codecs, each of whose chunks is coded on
/// its own at its share of the rate (`chunked::chunk_bpp`).
pub fn file_target(settings: &CodecSettings, channels: usize) -> Option<Target> {
    match settings {
        CodecSettings::Projected(p) if channels == 1 => match (p.max_error, p.target_bpp) {
            (Some(e), _) => Some(Quality::Bound(e).into()),
            (None, Some(bpp)) => Some(
                FileRate {
                    bpp,
                    bounded: p.bounded,
                }
                .into(),
            ),
            (None, None) => None,
        },
        _ => None,
    }
}
