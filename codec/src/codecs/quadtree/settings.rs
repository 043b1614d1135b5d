//! The quadtree encoder's settings: the rate (tolerance, ranges, const range, a target size),
//! range sizes, the domain lattice, the quantisers, the search, regions of interest, attractor
//! passes, and the speed presets that set them together.

use fractile_proto::AssetKind;

use crate::Error;
use crate::codecs::options::{Named, Options, Search};
use crate::codecs::quadtree::search::SearchMode;
use crate::core::transform::Quantiser;

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

pub use crate::codecs::options::Roi;

/// Encoder settings.
#[derive(Clone, Debug, PartialEq)]
pub struct QuadtreeSettings {
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
    /// [`QuadtreeSettings::default_quantiser_choices`].
    pub quantiser_choices: Vec<Quantiser>,
}

impl Default for QuadtreeSettings {
    fn default() -> Self {
        QuadtreeSettings {
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
    /// [`QuadtreeSettings::attractor_passes`].
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
/// [`QuadtreeSettings::default`], the last is the fastest.
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

/// The preset [`QuadtreeSettings::default`] uses (the speed the 2 s bar is measured at).
pub const DEFAULT_SPEED: u8 = 2;

impl QuadtreeSettings {
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
    pub fn at_speed(speed: u8) -> Result<QuadtreeSettings, Error> {
        let p = SPEEDS.get(speed as usize).ok_or_else(|| {
            Error::settings(format!(
                "speed {speed} is not a preset: 0 (slowest, best) to {} (fastest)",
                SPEEDS.len() - 1
            ))
        })?;
        Ok(QuadtreeSettings {
            domain_step: p.domain_step,
            search: SearchMode::Nearest(p.candidates),
            attractor_passes: p.attractor_passes,
            ..QuadtreeSettings::default()
        })
    }

    pub(crate) fn validate(&self) -> Result<(), Error> {
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
        self.quantiser
            .validate()
            .map_err(|e| Error::settings(e.to_string()))?;
        for q in &self.quantiser_choices {
            q.validate().map_err(|e| Error::settings(e.to_string()))?;
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

    /// Quantisers weighed beside `quantiser` by default ([`QuadtreeSettings::quantiser_choices`]),
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

impl Named for QuadtreeSettings {
    const NAMES: &'static [(&'static str, &'static str)] = &[(
        "quadtree-pifs",
        "Quadtree partitioned IFS (images and height fields).",
    )];
    const TAKES: &'static [&'static str] = &[
        "target-bpp",
        "tolerance",
        "transforms",
        "const-range",
        "roi",
        "min-range",
        "max-range",
        "speed",
        "domain-step",
        "contrast-bits",
        "offset-bits",
        "slope-bits",
        "max-contrast",
        "search",
        "candidates",
        "attractor-passes",
    ];

    /// The speed preset's settings ([`QuadtreeSettings::at_speed`]) with the options given
    /// over it; the rate: a target size, else a tolerance, a number of ranges or a constant
    /// range, else the default tolerance.
    fn named(_name: &str, o: &Options, kind: AssetKind) -> Result<Self, Error> {
        let rate = match (o.target_bpp, o.tolerance, o.transforms, o.const_range) {
            (Some(b), ..) => RateMode::TargetBpp(b),
            (_, Some(t), ..) => RateMode::Tolerance(t),
            (_, _, Some(n), _) => RateMode::Transforms(n),
            (.., Some(r)) => RateMode::ConstRange(r),
            _ => RateMode::Tolerance(f32::NAN),
        };
        let preset = QuadtreeSettings::at_speed(o.speed.unwrap_or(DEFAULT_SPEED))?;
        let candidates = match preset.search {
            SearchMode::Nearest(k) => o.candidates.unwrap_or(k),
            _ => o.candidates.unwrap_or(32),
        };
        let quantiser = Quantiser {
            contrast_bits: o.contrast_bits.unwrap_or(preset.quantiser.contrast_bits),
            offset_bits: o.offset_bits.unwrap_or(preset.quantiser.offset_bits),
            max_contrast: o.max_contrast.unwrap_or(preset.quantiser.max_contrast),
            slope_bits: o
                .slope_bits
                .unwrap_or(QuadtreeSettings::default_slope_bits(kind)),
        };
        // Bits given are kept as given; otherwise the encoder weighs the kind's choices.
        let quantiser_choices = if o.offset_bits.is_none() && o.slope_bits.is_none() {
            QuadtreeSettings::default_quantiser_choices(kind, quantiser)
        } else {
            Vec::new()
        };
        Ok(QuadtreeSettings {
            rate,
            min_range: o.min_range.unwrap_or(preset.min_range),
            max_range: o.max_range.unwrap_or(preset.max_range),
            domain_step: o.domain_step.unwrap_or(preset.domain_step),
            quantiser,
            quantiser_choices,
            search: match o.search.unwrap_or(Search::Nearest) {
                Search::Full => SearchMode::Full,
                Search::Classified => SearchMode::Classified,
                Search::Nearest => SearchMode::Nearest(candidates.max(1)),
            },
            rois: o.roi.clone(),
            attractor_passes: o.attractor_passes.unwrap_or(preset.attractor_passes),
            ..preset
        })
    }
}
