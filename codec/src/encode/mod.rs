//! The encoder: a [`Raster`] becomes an [`Asset`].
//!
//! Flow: normalise values to [0, 1] -> colour to YCbCr (chroma at half resolution) -> fill nodata
//! (push-pull) and pad to the frame (edge replication; padding and nodata weigh 0 in every fit)
//! -> fit every block of every size ([`Pyramid`]) -> choose the partition (tolerance, N ranges,
//! const range, or a target rate by bisection) -> entropy code -> decode once to report the real
//! error.

pub mod chunked;
pub mod curve;
pub mod fidelity;
pub mod parts;
pub mod projected;
mod pyramid;
pub mod rate;
mod source;
pub mod volume;

pub use source::{Encoded, Written};
use source::{
    SourcePlane, coding_range, decoded_errors, fill_invalid, measured, source_meta, source_planes,
    without_map,
};

use std::time::Instant;

use fractile_proto::{AssetKind, AssetMeta, ColourModel, SampleFormat};

use crate::Error;
use crate::codecs::fis::{FisHeader, FisSettings};
use crate::codecs::psa::{PsaHeader, PsaSettings};
use crate::codecs::quadtree::partition::{
    Limits, Partition, Pyramid, greedy_order, partitions_after,
};
use crate::codecs::quadtree::search::{CodingPlane, SearchMode};
use crate::codecs::quadtree::stream::{PlaneHeader, encode_plane};
use crate::core::decode::{self, DiscreteOptions};
use crate::core::metrics::Errors;
use crate::core::transform::Quantiser;
use crate::io::asset::{Asset, Mask, PlaneOperator};
use crate::io::raster::Raster;

/// What decides how many ranges the encoder spends.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RateMode {
    /// Split while a range's RMS collage error exceeds this, in source value units
    /// (grey levels for 8-bit images, metres for DEMs).
    Tolerance(f32),
    /// The seed's "quad N": split until this many ranges (over all channels).
    Transforms(usize),
    /// The seed's "const range R": a regular grid of R x R ranges. R = 1 works on the image
    /// supersampled 2x (ranges of 2 there), the seed's quasi-lossless mode.
    ConstRange(u32),
    /// The largest number of ranges whose whole file stays at or under this many bits per pixel.
    TargetBpp(f64),
}

/// A region of interest with its own tolerance and smallest range size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Roi {
    /// x0, y0, x1, y1 in source pixels.
    pub rect: [f32; 4],
    /// Tolerance in source value units.
    pub tolerance: f32,
    /// Smallest range side inside the region (a power of two); the global one if `None`.
    pub min_range: Option<u32>,
}

/// Encoder settings.
#[derive(Clone, Debug, PartialEq)]
pub struct EncodeSettings {
    /// How many ranges to spend.
    pub rate: RateMode,
    /// Smallest range side (power of two).
    pub min_range: u32,
    /// Largest range side (power of two).
    pub max_range: u32,
    /// Domain lattice step as a fraction of the range side (1.0: a step of n for domains of 2n).
    pub domain_step: f32,
    /// Contrast/offset quantisation.
    pub quantiser: Quantiser,
    /// Domain search.
    pub search: SearchMode,
    /// Regions of interest.
    pub rois: Vec<Roi>,
    /// Weight of chroma error against luma error (greedy modes), and the factor on the tolerance
    /// for chroma (tolerance mode) is its inverse square root: chroma gets a lower rate.
    pub chroma_weight: f32,
    /// Attractor passes after the first encode: search again with domains read from the
    /// decoded attractor of the latest pass instead of the source, and keep whichever asset
    /// decodes closest to the source (within the target size, or no larger than the first
    /// asset in the other rate modes). The collage fit assumes the
    /// decoder reads domains from the source, but it reads them from its own output; fitting
    /// against that output removes part of the difference. Each pass costs one more search.
    /// 0: collage coding only (the seed's encoder).
    pub attractor_passes: u32,
    /// Further quantisers weighed under a target size ([`RateMode::TargetBpp`]): one search fits
    /// every block under `quantiser` and under each of these (the candidate domains do not
    /// depend on the quantiser), rate control runs for each, and the encoder keeps the asset
    /// that decodes closest to the source (every one fits the target); each attractor pass
    /// weighs them again on one search. Each must agree with `quantiser` on whether it has slopes. Empty:
    /// `quantiser` alone. Ignored in the other rate modes, where a finer quantiser would buy
    /// its quality with more bytes. Height fields weigh
    /// [`EncodeSettings::default_quantiser_choices`].
    pub quantiser_choices: Vec<Quantiser>,
}

impl Default for EncodeSettings {
    fn default() -> Self {
        EncodeSettings {
            rate: RateMode::Tolerance(f32::NAN),
            // Defaults measured with the codec bench on camera.png (0.48 and 0.20 bpp) and
            // checked on etopo20 and jacksboro: domain step 2 (coarser lattice: cheaper indices, 2x faster) with
            // 32 candidates, ranges up to 64, 6-bit offsets and 4-bit contrasts gave +0.11 dB at
            // 0.48 bpp in 60% of the time of step 1 / 24 candidates / 32 / 7 / 5 (README, Tuning).
            min_range: 4,
            max_range: 64,
            domain_step: 2.0,
            quantiser: Quantiser {
                contrast_bits: 4,
                offset_bits: 6,
                max_contrast: 0.9,
                slope_bits: 0,
            },
            search: SearchMode::Nearest(32),
            rois: Vec::new(),
            chroma_weight: 0.25,
            attractor_passes: 0,
            quantiser_choices: Vec::new(),
        }
    }
}

/// One encoder speed preset ([`SPEEDS`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpeedPreset {
    /// Domain lattice step as a fraction of the range side: a step of 1 has 4 times the domains
    /// of the default 2.
    pub domain_step: f32,
    /// Candidates the nearest-neighbour search scores per range.
    pub candidates: usize,
    /// [`EncodeSettings::attractor_passes`].
    pub attractor_passes: u32,
}

const fn preset(domain_step: f32, candidates: usize, attractor_passes: u32) -> SpeedPreset {
    SpeedPreset {
        domain_step,
        candidates,
        attractor_passes,
    }
}

/// Encoder speed presets, as rav1e's `--speed`: 0 is the slowest and best, [`DEFAULT_SPEED`] is
/// [`EncodeSettings::default`], the last is the fastest.
///
/// Chosen from sweeps with the CLI (release, this project's 2-core machine, README "Speed
/// presets"): per step, the setting with the most PSNR for its encode time on camera.png at 0.2
/// and 0.48 bpp and etopo20 at 20:1. Denser lattices than a step of 1 (0.5) gained under 0.07 dB
/// for 2-3 times the time, so no preset uses them. An attractor pass costs about one more
/// search: at the default lattice one pass (+0.12 to +0.18 dB on camera, 2.2x the time) does
/// less than speed 1 in about the same time, so only the slowest preset runs them, two (+0.11
/// to +0.16 dB on camera, +0.03 on etopo20, about 3x the time).
pub const SPEEDS: [SpeedPreset; 5] = [
    preset(1.0, 128, 2),
    preset(1.0, 64, 0),
    preset(2.0, 32, 0),
    preset(2.0, 16, 0),
    preset(2.0, 8, 0),
];

/// Most attractor passes an encode accepts.
pub const MAX_ATTRACTOR_PASSES: u32 = 16;

/// The preset [`EncodeSettings::default`] uses (the speed the 2 s bar is measured at).
pub const DEFAULT_SPEED: u8 = 2;

impl EncodeSettings {
    /// The file size a [`RateMode::TargetBpp`] grants `cells` source cells (`None` in the
    /// other rate modes).
    pub fn target_bytes(&self, cells: usize) -> Option<usize> {
        match self.rate {
            RateMode::TargetBpp(bpp) => Some((bpp * cells as f64 / 8.0).floor() as usize),
            _ => None,
        }
    }

    /// The default settings at speed preset `speed` ([`SPEEDS`]): only the domain lattice, the
    /// search's candidates and the attractor passes change.
    pub fn at_speed(speed: u8) -> Result<EncodeSettings, Error> {
        let p = SPEEDS.get(speed as usize).ok_or_else(|| {
            Error::settings(format!(
                "speed {speed} is not a preset: 0 (slowest, best) to {} (fastest)",
                SPEEDS.len() - 1
            ))
        })?;
        Ok(EncodeSettings {
            domain_step: p.domain_step,
            search: SearchMode::Nearest(p.candidates),
            attractor_passes: p.attractor_passes,
            ..EncodeSettings::default()
        })
    }

    fn validate(&self) -> Result<(), Error> {
        let pow2 = |v: u32| v >= 1 && v.is_power_of_two();
        if !pow2(self.min_range)
            || !pow2(self.max_range)
            || self.min_range > self.max_range
            || self.max_range > 256
        {
            return Err(Error::settings(format!(
                "range sizes must be powers of two with min <= max <= 256 (min {}, max {})",
                self.min_range, self.max_range
            )));
        }
        if !(self.domain_step > 0.0 && self.domain_step <= 8.0) {
            return Err(Error::settings(format!(
                "domain step {} must be in (0, 8]",
                self.domain_step
            )));
        }
        self.quantiser.validate().map_err(Error::settings)?;
        for q in &self.quantiser_choices {
            q.validate().map_err(Error::settings)?;
            // One search serves every quantiser, and its domain features differ with slopes.
            if (q.slope_bits > 0) != (self.quantiser.slope_bits > 0) {
                return Err(Error::settings(format!(
                    "quantiser choice {q:?} and the quantiser {:?} must both have slopes or both \
                     not",
                    self.quantiser
                )));
            }
        }
        if self.attractor_passes > MAX_ATTRACTOR_PASSES {
            return Err(Error::settings(format!(
                "attractor passes {} must be at most {MAX_ATTRACTOR_PASSES} (each costs a search; \
                 gains stop after a few)",
                self.attractor_passes
            )));
        }
        match self.rate {
            RateMode::Tolerance(t) if t < 0.0 => {
                return Err(Error::settings("tolerance must be >= 0"));
            }
            RateMode::Transforms(0) => {
                return Err(Error::settings("at least one transform"));
            }
            RateMode::ConstRange(r) if r == 0 || r > 256 => {
                return Err(Error::settings("const range must be in 1..=256"));
            }
            RateMode::TargetBpp(b) if b.is_nan() || b <= 0.0 => {
                return Err(Error::settings("target bpp must be > 0"));
            }
            _ => {}
        }
        for r in &self.rois {
            if r.min_range.is_some_and(|m| !pow2(m))
                || r.tolerance.is_nan()
                || r.tolerance < 0.0
                || r.rect[2] <= r.rect[0]
                || r.rect[3] <= r.rect[1]
            {
                return Err(Error::settings(format!("bad region of interest {r:?}")));
            }
        }
        if let (RateMode::ConstRange(_), false) = (self.rate, self.rois.is_empty()) {
            return Err(Error::settings(
                "regions of interest need a quadtree mode, not const range",
            ));
        }
        Ok(())
    }

    /// Default bits for the planar offset term by kind of data: measured with the bench, slopes
    /// gain 1.2 dB on etopo20 at 20:1 and cost 0.1 dB on camera.png at 0.2 bpp, so height fields
    /// get 6 bits and images none (the seed's constant offsets).
    pub fn default_slope_bits(kind: AssetKind) -> u8 {
        match kind {
            AssetKind::HeightField => 6,
            _ => 0,
        }
    }

    /// Quantisers weighed beside `quantiser` by default ([`EncodeSettings::quantiser_choices`]),
    /// by kind of data. Height fields: offsets and slopes both at 5, 7 and 8 bits beside the
    /// default 6 (contrast as given). Which one wins depends on the data and the rate, by up to
    /// 2.6 dB (docs/benchmarks.md has the figures): a fixed step cannot follow the rate, so the
    /// encoder measures. The search is shared, so weighing four costs four rate controls and
    /// decodes, about a third more encode time on etopo20.
    /// Images weigh none: camera's 2 s bar leaves little room, and their 6-bit offsets were
    /// tuned at the rates they are coded at.
    pub fn default_quantiser_choices(kind: AssetKind, quantiser: Quantiser) -> Vec<Quantiser> {
        match kind {
            AssetKind::HeightField => [5u8, 7, 8]
                .into_iter()
                .map(|bits| Quantiser {
                    offset_bits: bits,
                    slope_bits: bits,
                    ..quantiser
                })
                .filter(|q| *q != quantiser)
                .collect(),
            _ => Vec::new(),
        }
    }

    /// A one-line description stored in the asset for provenance.
    pub fn describe(&self) -> String {
        format!(
            "{:?} ranges={}..{} domain_step={} contrast_bits={} offset_bits={} slope_bits={} max_contrast={} search={:?} rois={} attractor_passes={}",
            self.rate,
            self.min_range,
            self.max_range,
            self.domain_step,
            self.quantiser.contrast_bits,
            self.quantiser.offset_bits,
            self.quantiser.slope_bits,
            self.quantiser.max_contrast,
            self.search,
            self.rois.len(),
            self.attractor_passes
        )
    }
}

/// The rate of a height field's default encode: 0.8 bits a cell (20:1 against 16-bit samples),
/// where issue 34's measurements put every bar (bound within 2.7x of the actual error, tiles
/// within 1.4x of TiTiler's bytes).
pub const DEFAULT_HEIGHT_FIELD_BPP: f64 = 0.8;

/// What `fractile encode` writes when no codec is named, at `target_bpp` bits a source cell: for
/// a height field the projected IFS with details under a bounded rate (the smallest max error
/// whose file fits, so every cell is within the `error_bound` it answers: the quadtree's
/// per-block bounds are 9 to 19 times its actual errors on DEMs, and its PSNR is 2-3 dB lower
/// at the same bytes); for an image the quadtree PIFS with the kind's default quantisers (the
/// projected codec has no colour path). The server's demo and the benches encode this way.
pub fn encode_default(
    raster: &Raster,
    target_bpp: f64,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<Encoded, Error> {
    if raster.kind == AssetKind::HeightField {
        let settings = crate::codecs::projected::ProjectedSettings {
            bounded: true,
            ..Default::default()
        };
        return projected::encode_projected(raster, &settings, Some(target_bpp));
    }
    let mut settings = EncodeSettings {
        rate: RateMode::TargetBpp(target_bpp),
        ..EncodeSettings::default()
    };
    settings.quantiser.slope_bits = EncodeSettings::default_slope_bits(raster.kind);
    settings.quantiser_choices =
        EncodeSettings::default_quantiser_choices(raster.kind, settings.quantiser);
    encode(raster, &settings, progress)
}

/// Owned form of [`Limits`].
type BoxedLimits = Box<dyn Fn(usize, usize, usize) -> (f32, usize) + Sync>;

/// Encodes a raster. `progress(done, total)` is called as blocks are fitted.
pub fn encode(
    raster: &Raster,
    settings: &EncodeSettings,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<Encoded, Error> {
    let start = Instant::now();
    settings.validate()?;
    let (w, h) = (raster.width, raster.height);
    let (lo, hi, colour, sources) = source_planes(raster);
    let span = (hi - lo) as f32;

    // Frame geometry shared by every plane.
    let (min_size, levels, supersample, narrow) = frame_levels(settings, w, h);
    let planes: Vec<CodingPlane> = sources
        .iter()
        .map(|s| coding_plane(s, min_size as usize, supersample))
        .collect();
    // headers_by_quantiser[q][plane]
    let headers_by_quantiser = plane_headers(settings, &planes, min_size, levels);
    let headers = &headers_by_quantiser[0];

    // Every attractor pass searches again, as long as the first search.
    let total: u64 =
        headers.iter().map(Pyramid::work).sum::<u64>() * (1 + u64::from(settings.attractor_passes));
    let done = std::sync::atomic::AtomicU64::new(0);
    let tick = |k: u64| {
        let d = done.fetch_add(k, std::sync::atomic::Ordering::Relaxed) + k;
        if d.is_multiple_of(256) || d == total {
            progress(d, total);
        }
    };
    // Limits per plane: tolerance (normalised) and smallest size for a block in frame coordinates.
    let limit_fns = plane_limits(settings, &planes, w, span, narrow);
    let limits: Vec<Limits> = limit_fns.iter().map(|f| f.as_ref() as Limits).collect();
    // Chroma planes are a quarter of the pixels: weighed by their share and the setting.
    let weights: Vec<f32> = (0..planes.len())
        .map(|i| {
            if i == 0 {
                1.0
            } else {
                4.0 * settings.chroma_weight
            }
        })
        .collect();

    let mask = raster.valid.as_ref().map(|v| Mask::new(w, h, v.clone()));
    let meta = source_meta(raster, settings.describe(), (lo, hi), colour);
    // The metadata of an asset coded with quantiser `q`: its description names `q` (and its
    // length is part of the size rate control fits).
    let meta_for = |q: Quantiser| AssetMeta {
        encoder: EncodeSettings {
            quantiser: q,
            ..settings.clone()
        }
        .describe(),
        ..meta.clone()
    };
    // What rate control fits: the target less the source-error map's share.
    let target_bytes = settings.target_bytes(w * h).map(without_map);
    // The partition the rate mode asks for, from one set of fits.
    let choose = |pyramids: &[Pyramid]| -> Result<Vec<Partition>, Error> {
        let meta = meta_for(pyramids[0].header.quantiser);
        // The size alone (no stream decoding, no operator). The stats `measured` fills in
        // later are fixed-width fields, so the final file has exactly this size.
        let file_size = |parts: &[Partition]| {
            Asset::quadtree_file_size(&meta, code_planes(pyramids, parts), mask.as_ref())
        };
        let max_bytes = target_bytes.unwrap_or(usize::MAX);
        partitions_for(
            settings,
            pyramids,
            (&limits, &weights),
            max_bytes,
            &file_size,
        )
    };
    let build = |pyramids: &[Pyramid]| -> Result<Asset, Error> {
        Asset::from_parts(
            meta_for(pyramids[0].header.quantiser),
            code_planes(pyramids, &choose(pyramids)?),
            mask.clone(),
        )
    };
    // One search per plane serves every quantiser, with domains read from `avg2[plane]`; rate
    // control runs for each. Under a target size every quantiser's asset fits it: the one that
    // decodes closest to the source wins (the settings' own on a tie).
    let weigh = |avg2: &[Vec<f32>]| -> Result<(Asset, Errors), Error> {
        let pyramids_by_quantiser =
            search_planes(&planes, avg2, &headers_by_quantiser, settings.search, &tick);
        let mut weighed: Option<(Asset, Errors)> = None;
        for pyramids in &pyramids_by_quantiser {
            let asset = build(pyramids)?;
            let errors = decoded_errors(&asset, raster);
            let better = weighed
                .as_ref()
                .is_none_or(|(best, e)| preferred((&asset, &errors), (best, e), target_bytes));
            if better {
                weighed = Some((asset, errors));
            }
        }
        Ok(weighed.expect("at least the settings' own quantiser"))
    };
    let own_domains: Vec<Vec<f32>> = planes.iter().map(CodingPlane::average2).collect();
    let (latest, errors) = weigh(&own_domains)?;
    if settings.attractor_passes == 0 {
        progress(total, total);
        return Ok(measured(latest, start, errors, raster));
    }
    // A pass must not buy its quality with bytes the user did not grant: under a target size
    // any asset within it will do; otherwise it may be no larger than the first.
    let max_size = target_bytes.unwrap_or(latest.file_size());
    let passes = settings.attractor_passes;
    let (best, best_errors) =
        attractor_passes(&planes, (latest, errors), passes, max_size, &weigh)?;
    progress(total, total);
    Ok(measured(best, start, best_errors, raster))
}

/// One search with the given domains per plane, under every quantiser: the asset that decodes
/// closest to the source, and its errors.
type Weigh<'a> = dyn Fn(&[Vec<f32>]) -> Result<(Asset, Errors), Error> + 'a;

/// Searches `passes` more times with domains read from the latest asset's decoded attractor
/// instead of the source, and keeps the asset that decodes closest to the source within
/// `max_size` bytes (the first on a tie).
fn attractor_passes(
    planes: &[CodingPlane],
    first: (Asset, Errors),
    passes: u32,
    max_size: usize,
    weigh: &Weigh,
) -> Result<(Asset, Errors), Error> {
    let (mut latest, mut best_errors) = first;
    let mut best = latest.clone();
    for _ in 0..passes {
        let domains: Vec<Vec<f32>> = planes
            .iter()
            .zip(&latest.planes)
            .map(|(p, coded)| attractor(p, &coded.operator))
            .collect();
        let errors;
        (latest, errors) = weigh(&domains)?;
        if errors.rmse < best_errors.rmse && latest.file_size() <= max_size {
            best = latest.clone();
            best_errors = errors;
        }
    }
    Ok((best, best_errors))
}

/// The plane headers of every quantiser weighed (`[quantiser][plane]`): the settings' own,
/// then its choices under a target size.
fn plane_headers(
    settings: &EncodeSettings,
    planes: &[CodingPlane],
    min_size: u32,
    levels: u32,
) -> Vec<Vec<PlaneHeader>> {
    let quantisers: Vec<Quantiser> = std::iter::once(settings.quantiser)
        .chain(match settings.rate {
            RateMode::TargetBpp(_) => settings.quantiser_choices.clone(),
            _ => Vec::new(),
        })
        .collect();
    quantisers
        .iter()
        .map(|&quantiser| {
            planes
                .iter()
                .map(|p| PlaneHeader {
                    frame: [p.width as u32, p.height as u32],
                    valid: p.valid,
                    min_size,
                    levels,
                    domain_steps: (0..levels)
                        .map(|l| {
                            (((min_size << l) as f32 * settings.domain_step).round() as u32).max(1)
                        })
                        .collect(),
                    quantiser,
                })
                .collect()
        })
        .collect()
}

/// The partitions the rate mode asks for, from one set of fits (`[plane]`), with each plane's
/// limits and weight; under a target size, the best whose file (`file_size`) fits `max_bytes`.
fn partitions_for(
    settings: &EncodeSettings,
    pyramids: &[Pyramid],
    (limits, weights): (&[Limits], &[f32]),
    max_bytes: usize,
    file_size: &dyn Fn(&[Partition]) -> usize,
) -> Result<Vec<Partition>, Error> {
    let pyr_refs: Vec<&Pyramid> = pyramids.iter().collect();
    Ok(match settings.rate {
        RateMode::ConstRange(_) => pyramids.iter().map(Partition::whole_level).collect(),
        RateMode::Tolerance(_) => pyramids
            .iter()
            .zip(limits)
            .map(|(p, l)| Partition::by_tolerance(p, *l))
            .collect(),
        RateMode::Transforms(n) => {
            let (initial, order) = greedy_order(&pyr_refs, weights, limits);
            partitions_after(&pyr_refs, &order, n.saturating_sub(initial).div_ceil(3))
        }
        RateMode::TargetBpp(_) => {
            let at = |lambda: f32| -> Vec<Partition> {
                pyramids
                    .iter()
                    .zip(limits)
                    .zip(weights)
                    .map(|((p, l), &wt)| Partition::by_lagrangian(p, lambda, wt, *l))
                    .collect()
            };
            at(smallest_lambda(
                |lambda| Ok(file_size(&at(lambda))),
                max_bytes,
            )?)
        }
    })
}

/// Each plane's header and coded stream under its partition.
fn code_planes(pyramids: &[Pyramid], parts: &[Partition]) -> Vec<(PlaneHeader, Vec<u8>)> {
    pyramids
        .iter()
        .zip(parts)
        .map(|(p, part)| {
            (
                p.header.clone(),
                encode_plane(&p.header, &|l, bx, by| part.decide(p, l, bx, by)),
            )
        })
        .collect()
}

/// One search per plane, fitted under every quantiser's header (`[quantiser][plane]`), with
/// domains read from `avg2[plane]`.
fn search_planes(
    planes: &[CodingPlane],
    avg2: &[Vec<f32>],
    headers_by_quantiser: &[Vec<PlaneHeader>],
    search: SearchMode,
    tick: &(dyn Fn(u64) + Sync),
) -> Vec<Vec<Pyramid>> {
    let mut pyramids_by_quantiser: Vec<Vec<Pyramid>> =
        headers_by_quantiser.iter().map(|_| Vec::new()).collect();
    for (i, (p, domains)) in planes.iter().zip(avg2).enumerate() {
        let each: Vec<PlaneHeader> = headers_by_quantiser.iter().map(|h| h[i].clone()).collect();
        let built = Pyramid::build_each(p, domains, &each, search, tick);
        for (q, pyramid) in built.into_iter().enumerate() {
            pyramids_by_quantiser[q].push(pyramid);
        }
    }
    pyramids_by_quantiser
}

/// The smallest range, the number of range sizes, whether to supersample (quasi-lossless), and
/// the largest power of two that fits half the raster's short side.
fn frame_levels(settings: &EncodeSettings, w: usize, h: usize) -> (u32, u32, bool, u32) {
    let roi_min = settings
        .rois
        .iter()
        .filter_map(|r| r.min_range)
        .min()
        .unwrap_or(settings.min_range);
    let half = (w.min(h) / 2).max(1) as u32;
    let narrow = 1u32 << (31 - half.leading_zeros()); // largest power of two <= half
    let (min_size, levels, supersample) = match settings.rate {
        RateMode::ConstRange(1) => (2u32, 1u32, true),
        RateMode::ConstRange(r) => (r, 1, false),
        _ => {
            // Narrow inputs (a 3 x 1000 strip) cannot hold a domain of twice the smallest range:
            // shrink the smallest range until one fits, down to single samples.
            let m = settings.min_range.min(roi_min).min(narrow);
            (
                m,
                settings.max_range.max(m).trailing_zeros() - m.trailing_zeros() + 1,
                false,
            )
        }
    };
    (min_size, levels, supersample, narrow)
}

/// Per plane, the tolerance (normalised) and smallest range for a block at (x, y) of side n in
/// frame coordinates: the plane's own, tightened inside regions of interest.
fn plane_limits(
    settings: &EncodeSettings,
    planes: &[CodingPlane],
    w: usize,
    span: f32,
    narrow: u32,
) -> Vec<BoxedLimits> {
    let base_tol = match settings.rate {
        RateMode::Tolerance(t) if t.is_nan() => 0.02,
        RateMode::Tolerance(t) => t / span,
        _ => 1.0,
    };
    let chroma_tol = 1.0 / settings.chroma_weight.max(1e-3).sqrt();
    planes
        .iter()
        .enumerate()
        .map(|(i, p)| {
            // Frame samples per source pixel.
            let k = p.valid[0] / w as f32;
            let plane_tol = base_tol * if i > 0 { chroma_tol } else { 1.0 };
            let rois: Vec<([f32; 4], f32, usize)> = settings
                .rois
                .iter()
                .map(|r| {
                    (
                        r.rect.map(|v| v * k),
                        (r.tolerance / span).min(plane_tol),
                        r.min_range.unwrap_or(settings.min_range) as usize,
                    )
                })
                .collect();
            let global_min = settings.min_range.min(narrow) as usize;
            let f: BoxedLimits = Box::new(move |x, y, n| {
                let (x0, y0, x1, y1) = (x as f32, y as f32, (x + n) as f32, (y + n) as f32);
                let (mut tol, mut min) = (plane_tol, global_min);
                for &(r, t, m) in &rois {
                    if x0 < r[2] && x1 > r[0] && y0 < r[3] && y1 > r[1] {
                        tol = tol.min(t);
                        min = min.min(m);
                    }
                }
                (tol, min)
            });
            f
        })
        .collect()
}

/// The smallest lambda (best quality) whose file fits `max_bytes`: bisection on log(lambda);
/// the size falls as lambda grows.
fn smallest_lambda(
    size_at: impl Fn(f32) -> Result<usize, Error>,
    max_bytes: usize,
) -> Result<f32, Error> {
    let (mut lo_l, mut hi_l) = (-30.0f32, 10.0f32);
    if size_at(lo_l.exp2())? <= max_bytes {
        hi_l = lo_l;
    } else {
        for _ in 0..28 {
            let mid = 0.5 * (lo_l + hi_l);
            if size_at(mid.exp2())? <= max_bytes {
                hi_l = mid
            } else {
                lo_l = mid
            }
        }
    }
    Ok(hi_l.exp2())
}

/// The 2x2 means ([`CodingPlane::average2`]) of a plane's decoded attractor over its whole
/// frame: what the decoder's domains read. Discrete decoding covers the source extent; the
/// padding beyond it repeats the edge, as the encoder pads the source.
fn attractor(plane: &CodingPlane, op: &PlaneOperator) -> Vec<f32> {
    let (gw, gh) = (
        (plane.valid[0].ceil() as usize).clamp(1, plane.width),
        (plane.valid[1].ceil() as usize).clamp(1, plane.height),
    );
    let (g, _) = decode::discrete(op, gw, gh, DiscreteOptions::default());
    let mut frame = plane.clone();
    for y in 0..plane.height {
        let row = &g.values[y.min(gh - 1) * gw..][..gw];
        for x in 0..plane.width {
            frame.values[y * plane.width + x] = row[x.min(gw - 1)];
        }
    }
    frame.average2()
}

/// Whether `candidate` beats `best` under a target size: an asset within the target beats one
/// over it (rate control returns its smallest where nothing fits); then the smaller mean square
/// error (what PSNR ranks by), or between two over the target, the smaller file.
fn preferred(candidate: (&Asset, &Errors), best: (&Asset, &Errors), target: Option<usize>) -> bool {
    let fits = |a: &Asset| target.is_none_or(|t| a.file_size() <= t);
    match (fits(candidate.0), fits(best.0)) {
        (true, false) => true,
        (false, true) => false,
        (true, true) => candidate.1.rmse < best.1.rmse,
        (false, false) => candidate.0.file_size() < best.0.file_size(),
    }
}

/// Fills invalid cells (push-pull: averages of valid cells over a pyramid, pulled back down),
/// optionally supersamples 2x, and pads to a multiple of `align` by edge replication.
fn coding_plane(s: &SourcePlane, align: usize, supersample: bool) -> CodingPlane {
    let mut values = s.values.clone();
    fill_invalid(&mut values, &s.valid, s.width, s.height);
    let (mut w, mut h, mut weights) = (
        s.width,
        s.height,
        s.valid
            .iter()
            .map(|&v| f32::from(u8::from(v)))
            .collect::<Vec<_>>(),
    );
    // The source extent in frame units: chroma keeps the exact half of the source (w / 2) so
    // that unit coordinates line up with luma.
    let mut valid = s.extent;
    if supersample {
        let (w2, h2) = (2 * w, 2 * h);
        let mut v2 = vec![0.0f32; w2 * h2];
        let mut wt2 = vec![0.0f32; w2 * h2];
        for y in 0..h2 {
            for x in 0..w2 {
                // Bilinear at the supersampled pixel centre.
                let fx = ((x as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, (w - 1) as f32);
                let fy = ((y as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, (h - 1) as f32);
                let (x0, y0) = (fx as usize, fy as usize);
                let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
                let (ax, ay) = (fx - x0 as f32, fy - y0 as f32);
                let top = values[y0 * w + x0] * (1.0 - ax) + values[y0 * w + x1] * ax;
                let bot = values[y1 * w + x0] * (1.0 - ax) + values[y1 * w + x1] * ax;
                v2[y * w2 + x] = top * (1.0 - ay) + bot * ay;
                wt2[y * w2 + x] = weights[(y / 2) * w + x / 2];
            }
        }
        values = v2;
        weights = wt2;
        w = w2;
        h = h2;
        valid = [valid[0] * 2.0, valid[1] * 2.0];
    }
    let (fw, fh) = (w.div_ceil(align) * align, h.div_ceil(align) * align);
    let mut pv = vec![0.0f32; fw * fh];
    let mut pw = vec![0.0f32; fw * fh];
    for y in 0..fh {
        let sy = y.min(h - 1);
        for x in 0..fw {
            let sx = x.min(w - 1);
            pv[y * fw + x] = values[sy * w + sx];
            if x < w && y < h {
                pw[y * fw + x] = weights[y * w + x];
            }
        }
    }
    CodingPlane {
        width: fw,
        height: fh,
        values: pv,
        weights: pw,
        valid,
    }
}

/// Encodes a height field as a fractal interpolation surface ([`crate::codecs::fis`]).
/// `target_bpp`, when given, overrides `settings.spacing` (and the automatic height step); see
/// `encode_lattice`.
pub fn encode_fis(
    raster: &Raster,
    settings: &FisSettings,
    target_bpp: Option<f64>,
) -> Result<Encoded, Error> {
    if raster.kind != AssetKind::HeightField {
        return Err(Error::settings(
            "fractal interpolation surfaces code height fields (use quadtree-pifs or psa2d for \
             images)",
        ));
    }
    if !(settings.max_scaling > 0.0 && settings.max_scaling < 1.0) {
        return Err(Error::settings("max scaling must be in (0, 1)"));
    }
    let lattice = Lattice {
        spacing: settings.spacing,
        height_step: settings.height_step,
        target_bpp,
    };
    encode_lattice(
        raster,
        &lattice,
        |source, spacing, height_step, meta, mask, budget| {
            let header = FisHeader {
                samples: [source.width as u32, source.height as u32],
                spacing,
                scaling: settings.scaling,
                height_step,
                scaling_bits: settings.scaling_bits,
                max_scaling: settings.max_scaling,
            };
            let fitted = crate::codecs::fis::fit(source, &header)?;
            let mut m = meta.clone();
            m.encoder = format!(
                "{} spacing={spacing} height_step={} scaling_bits={} max_scaling={}",
                crate::codecs::fis::codec_name(settings.scaling),
                height_step as f64 * (meta.value_max - meta.value_min),
                settings.scaling_bits,
                settings.max_scaling
            );
            // The fit minimises the collage error, not the attractor's: on rough terrain the
            // collage-optimal scalings can make the decoded surface worse than plain bilinear
            // interpolation of the nodes (fis-bilinear on etopo20 at spacing 2: 30 dB against
            // 40), and they cost bits. So every s is shrunk by one of these factors (1: the fit
            // as is; 0: bilinear), measured, not guessed: under a byte budget (rate control) the
            // best PSNR that fits (else the smallest, which tells rate control nothing fits:
            // the all-zero scalings are the cheapest, so "fits" grows with the step as the
            // bisection needs); otherwise the least `SSE + mu * bits`, `mu` the rate-distortion
            // slope of the node heights' own quantiser (a halved step costs a bit a node and
            // saves 3/4 of `step^2 / 12` on each of the ~k^2 samples a node weighs on).
            let (lo, span) = (meta.value_min, meta.value_max - meta.value_min);
            let step = f64::from(height_step) * span;
            let mu = 0.75 * step * step / 12.0 * f64::from(spacing * spacing) * 4.0 / 9.0;
            let mut best: Option<(f64, Asset)> = None;
            for shrink in [1.0f32, 0.75, 0.5, 0.25, 0.0] {
                let params = crate::codecs::fis::FisParams {
                    heights: fitted.heights.clone(),
                    scalings: fitted
                        .scalings
                        .iter()
                        .map(|&q| header.scaling_index(shrink * header.scaling_of(q)))
                        .collect(),
                };
                let stream = crate::codecs::fis::encode_params(&header, &params);
                let a =
                    Asset::from_fis_parts(m.clone(), vec![(header.clone(), stream)], mask.clone())?;
                let (d, _) = a.decode_native();
                let sse: f64 = d.channels[0]
                    .iter()
                    .zip(source.values)
                    .filter(|(z, _)| z.is_finite())
                    .map(|(&z, &v)| (f64::from(z) - (lo + f64::from(v) * span)).powi(2))
                    .sum();
                let size = a.file_size();
                let cost = match budget {
                    // Fitting candidates by error; the others after them, by size.
                    Some(b) if size <= b => sse,
                    Some(_) => f64::MAX / 2.0 + size as f64,
                    None => sse + mu * 8.0 * size as f64,
                };
                if best.as_ref().is_none_or(|(b, _)| cost < *b) {
                    best = Some((cost, a));
                }
                if params.scalings.iter().all(|&q| q == 0) {
                    break; // a smaller shrink gives the same surface
                }
            }
            Ok(best.expect("one candidate at least").1)
        },
    )
}

/// Encodes a grey image or a height field with the piecewise self-affine model
/// ([`crate::codecs::psa`]); `target_bpp` picks the region size (see `encode_lattice`).
pub fn encode_psa(
    raster: &Raster,
    settings: &PsaSettings,
    target_bpp: Option<f64>,
) -> Result<Encoded, Error> {
    if !(settings.max_scaling > 0.0 && settings.max_scaling < 1.0) {
        return Err(Error::settings("max scaling must be in (0, 1)"));
    }
    let lattice = Lattice {
        spacing: settings.region,
        height_step: None,
        target_bpp,
    };
    encode_lattice(
        raster,
        &lattice,
        |source, region, height_step, meta, mask, _budget| {
            let header = PsaHeader {
                samples: [source.width as u32, source.height as u32],
                region,
                ratio: settings.ratio,
                tiling: settings.tiling,
                domains: settings.domains,
                radius: settings.radius,
                height_step,
                scaling_bits: settings.scaling_bits,
                max_scaling: settings.max_scaling,
            };
            let params = crate::codecs::psa::fit(source, &header)?;
            let stream = crate::codecs::psa::encode_params(&header, &params);
            let mut m = meta.clone();
            m.encoder = format!(
                "{} spacing={region} ratio={} domains={:?} radius={} height_step={}",
                crate::codecs::psa::codec_name(settings.tiling),
                settings.ratio,
                settings.domains,
                settings.radius,
                height_step as f64 * (meta.value_max - meta.value_min)
            );
            Asset::from_psa_parts(m, vec![(header, stream)], mask)
        },
    )
}

/// How a lattice codec's vertices are placed and quantised.
struct Lattice {
    /// Samples between vertices.
    spacing: u32,
    /// Vertex height step, source units (`None`: automatic).
    height_step: Option<f64>,
    /// Rate control: overrides `spacing` and the automatic height step.
    target_bpp: Option<f64>,
}

/// How many spacings finer than the first that fits rate control weighs (each costs about eight
/// encodes; fis-bilinear on etopo20 at 32:1 fits first at 6 and is best at 2).
const FINER_SPACINGS: u32 = 4;

/// The pipeline of the lattice codecs (interpolation surfaces, psa2d): one grey channel,
/// normalised, nodata filled (and masked), vertices every `spacing` samples, then measured.
///
/// The automatic height step is the largest power-of-two multiple of the source's quantum under
/// a quarter of the RMS error of bilinear interpolation between the vertices, so quantising them
/// adds under 1/190 of the error's variance (`(1/4)^2 / 12`) while each halving would cost a bit
/// per vertex for nothing.
///
/// Rate control: the spacing moves the size in steps (x2.25 from 2 to 3) and the height step
/// fills in between. The smallest spacing that fits at its own height step is weighed against
/// up to [`FINER_SPACINGS`] finer spacings, each with the finest coarser height step that fits
/// (eighth-octave steps, found by bisection); the best PSNR wins. Coarse heights on a fine
/// lattice often beat fine heights on a coarse one: etopo20 at 32:1 scored 36.5 dB at spacing 3
/// and its own step, 39.5 dB at spacing 2 with a 235 m step (before the heights' rounding).
/// Weighing only the next finer spacing missed that: spacing 4 fits first there. Under rate
/// control `build` gets the byte budget, so that a codec with choices of its own (the FIS
/// scalings' shrink) takes the best one that fits.
fn encode_lattice(
    raster: &Raster,
    lattice: &Lattice,
    build: impl Fn(
        &crate::codecs::fis::Source,
        u32,
        f32,
        &AssetMeta,
        Option<Mask>,
        Option<usize>,
    ) -> Result<Asset, Error>,
) -> Result<Encoded, Error> {
    let start = Instant::now();
    if raster.channels.len() != 1 {
        return Err(Error::settings(format!(
            "this codec codes one grey channel; the input has {} (use quadtree-pifs for colour)",
            raster.channels.len()
        )));
    }
    let (w, h) = (raster.width, raster.height);
    if w < 2 || h < 2 {
        return Err(Error::input(format!(
            "a {w}x{h} grid is too small for a vertex lattice (2x2 at least)"
        )));
    }
    let (lo, hi) = coding_range(raster);
    let span = hi - lo;
    let mut values: Vec<f32> = raster.channels[0]
        .iter()
        .map(|&x| ((x as f64 - lo) / span).clamp(0.0, 1.0) as f32)
        .collect();
    let valid = raster.valid.clone().unwrap_or_else(|| vec![true; w * h]);
    fill_invalid(&mut values, &valid, w, h);
    let quantum = match raster.sample {
        SampleFormat::F32 => span / 65535.0,
        _ => 1.0,
    };
    let source = crate::codecs::fis::Source {
        width: w,
        height: h,
        values: &values,
    };
    let mask = raster.valid.as_ref().map(|v| Mask::new(w, h, v.clone()));
    let meta = source_meta(raster, String::new(), (lo, hi), ColourModel::Grey);
    let auto_step = |spacing: u32| {
        lattice.height_step.unwrap_or_else(|| {
            let limit =
                crate::codecs::fis::interpolation_rmse(&source, spacing) as f64 * span / 4.0;
            let mut step = quantum;
            while step * 2.0 <= limit {
                step *= 2.0;
            }
            step
        })
    };
    let make = |spacing: u32, step: f64, budget: Option<usize>| {
        let height_step = ((step / span) as f32).clamp(1e-9, 1.0);
        build(&source, spacing, height_step, &meta, mask.clone(), budget)
    };
    let asset = match lattice.target_bpp {
        None => {
            let k = lattice.spacing.max(1);
            make(k, auto_step(k), None)?
        }
        Some(bpp) => {
            // The source-error map comes on top of what is fitted here.
            let max_bytes = without_map((bpp * (w * h) as f64 / 8.0).floor() as usize);
            let largest = (w.max(h) - 1).clamp(1, 4096) as u32;
            let mut found = None;
            for k in 1..=largest {
                let a = make(k, auto_step(k), Some(max_bytes))?;
                if a.file_size() <= max_bytes {
                    found = Some((k, a));
                    break;
                }
            }
            let Some((k, a)) = found else {
                return Err(Error::settings(format!(
                    "nothing fits in {bpp} bits per pixel (the coarsest lattice takes more)"
                )));
            };
            let mut best = (decoded_errors(&a, raster).psnr, a);
            if lattice.height_step.is_none() {
                for finer in (k.saturating_sub(FINER_SPACINGS).max(1)..k).rev() {
                    // Steps base * 2^(m/8): m = 0 did not fit (the spacing is under k), find
                    // the smallest m that does (sizes fall as the step grows).
                    let base = auto_step(finer);
                    let step = |m: u32| base * (f64::from(m) / 8.0).exp2();
                    let (mut lo, mut hi) = (0u32, 8 * 12);
                    let mut fit = make(finer, step(hi), Some(max_bytes))?;
                    if fit.file_size() > max_bytes {
                        continue;
                    }
                    while hi - lo > 1 {
                        let mid = (lo + hi) / 2;
                        let a = make(finer, step(mid), Some(max_bytes))?;
                        if a.file_size() <= max_bytes {
                            (hi, fit) = (mid, a);
                        } else {
                            lo = mid;
                        }
                    }
                    // No early stop on a lower PSNR: with per-node or per-cell scalings the
                    // best can lie past a worse spacing.
                    let psnr = decoded_errors(&fit, raster).psnr;
                    if psnr > best.0 {
                        best = (psnr, fit);
                    }
                }
            }
            best.1
        }
    };
    let errors = decoded_errors(&asset, raster);
    Ok(measured(asset, start, errors, raster))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fill_invalid_interpolates_from_neighbours() {
        let (w, h) = (8, 8);
        let mut v: Vec<f32> = (0..64).map(|i| (i % 8) as f32).collect();
        let mut valid = vec![true; 64];
        for i in [9, 10, 17, 18, 63] {
            valid[i] = false;
            v[i] = 1000.0;
        }
        fill_invalid(&mut v, &valid, w, h);
        for i in [9, 10, 17, 18, 63] {
            assert!((0.0..=7.0).contains(&v[i]), "cell {i} filled with {}", v[i]);
        }
    }
}
