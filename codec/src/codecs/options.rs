//! A plane codec chosen by name with its options, as `fractile encode` and Python's `encode`
//! give them. Each codec's settings are made from the options in its own folder ([`Named`]);
//! the list of names is made from the registry (`plane_codecs!`, as `encode::CodecSettings`),
//! and an option the named codec does not read is refused by name. So a codec added to the
//! registry is reached from the command line and from Python with no other edit.
//!
//! Why one struct of options and not one per codec: the command line has one flat set of flags
//! (`--target-bpp`, `--spacing`, ...), several codecs read the same ones, and Python passes a
//! few of them; each codec says which it reads ([`Named::TAKES`]).

use fractile_proto::AssetKind;
use serde::{Deserialize, Serialize};

use crate::Error;

/// The options of an encode, each `None` (or empty, or false) where not given: the codec's own
/// default then.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Options {
    /// Largest file size in bits per source cell (rate control).
    pub target_bpp: Option<f64>,
    /// The largest |decoded - source| at any valid cell, source units.
    pub max_error: Option<f64>,
    /// Under `target_bpp`: the smallest max error whose file fits, every cell within it.
    pub bounded: bool,
    /// Split ranges while their RMS collage error exceeds this (source units).
    pub tolerance: Option<f32>,
    /// Split until this many ranges.
    pub transforms: Option<usize>,
    /// A regular grid of R x R ranges.
    pub const_range: Option<u32>,
    /// Regions of interest.
    pub roi: Vec<Roi>,
    /// Smallest range side (a power of two).
    pub min_range: Option<u32>,
    /// Largest range side (a power of two).
    pub max_range: Option<u32>,
    /// Encoder speed preset, 0 (slowest, best) to 4.
    pub speed: Option<u8>,
    /// Domain lattice step, as a fraction of the range side.
    pub domain_step: Option<f32>,
    /// Bits of the contrast index.
    pub contrast_bits: Option<u8>,
    /// Bits of the offset index.
    pub offset_bits: Option<u8>,
    /// Bits of each slope of a planar offset term.
    pub slope_bits: Option<u8>,
    /// Largest |contrast| (or vertical scaling), under 1.
    pub max_contrast: Option<f32>,
    /// Domain search.
    pub search: Option<Search>,
    /// Candidates scored per range by the nearest-neighbour search.
    pub candidates: Option<usize>,
    /// Searches again with domains read from the decoded attractor.
    pub attractor_passes: Option<u32>,
    /// Touching or overlapping domains.
    pub domains: Option<Domains>,
    /// Domain side in regions.
    pub domain_ratio: Option<u32>,
    /// Domain search radius.
    pub radius: Option<u32>,
    /// Samples between interpolation points (lattice codecs).
    pub spacing: Option<u32>,
    /// Node height step, source units.
    pub height_step: Option<f64>,
    /// Bits of each vertical scaling.
    pub scaling_bits: Option<u8>,
}

impl Options {
    /// The options given, by the names the command line spells them (`max-error`).
    pub fn given(&self) -> Vec<&'static str> {
        let o = self;
        [
            ("target-bpp", o.target_bpp.is_some()),
            ("max-error", o.max_error.is_some()),
            ("bounded", o.bounded),
            ("tolerance", o.tolerance.is_some()),
            ("transforms", o.transforms.is_some()),
            ("const-range", o.const_range.is_some()),
            ("roi", !o.roi.is_empty()),
            ("min-range", o.min_range.is_some()),
            ("max-range", o.max_range.is_some()),
            ("speed", o.speed.is_some()),
            ("domain-step", o.domain_step.is_some()),
            ("contrast-bits", o.contrast_bits.is_some()),
            ("offset-bits", o.offset_bits.is_some()),
            ("slope-bits", o.slope_bits.is_some()),
            ("max-contrast", o.max_contrast.is_some()),
            ("search", o.search.is_some()),
            ("candidates", o.candidates.is_some()),
            ("attractor-passes", o.attractor_passes.is_some()),
            ("domains", o.domains.is_some()),
            ("domain-ratio", o.domain_ratio.is_some()),
            ("radius", o.radius.is_some()),
            ("spacing", o.spacing.is_some()),
            ("height-step", o.height_step.is_some()),
            ("scaling-bits", o.scaling_bits.is_some()),
        ]
        .into_iter()
        .filter_map(|(name, given)| given.then_some(name))
        .collect()
    }

    /// Refuses, by name, an option given that the codec `name` does not read (`takes`).
    pub(crate) fn refuse_untaken(&self, name: &str, takes: &[&str]) -> Result<(), Error> {
        let untaken: Vec<String> = self
            .given()
            .into_iter()
            .filter(|o| !takes.contains(o))
            .map(|o| format!("--{o}"))
            .collect();
        if untaken.is_empty() {
            return Ok(());
        }
        let takes: Vec<String> = takes.iter().map(|o| format!("--{o}")).collect();
        Err(Error::settings(format!(
            "--codec {name} does not read {} (it takes {})",
            untaken.join(", "),
            takes.join(", ")
        )))
    }
}

/// A plane codec's settings made from [`Options`]: implemented in the codec's folder beside its
/// settings, listed by the registry (`encode::CodecSettings::named`).
pub trait Named: Sized {
    /// The names the codec is chosen by (`--codec`, Python's `codec=`), each with a line of
    /// help; several where the name picks a variant (the FIS scalings).
    const NAMES: &'static [(&'static str, &'static str)];
    /// The options it reads, as [`Options::given`] names them; the others are refused.
    const TAKES: &'static [&'static str];

    /// The settings the codec `name` (one of [`Named::NAMES`]) means with `options`, for a
    /// raster of `kind`.
    fn named(name: &str, options: &Options, kind: AssetKind) -> Result<Self, Error>;
}

/// A domain search, as an option names it (the candidates are an option of their own).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Search {
    /// Every domain and isometry (slow; the reference).
    Full,
    /// Fisher's quadrant-brightness classes.
    Classified,
    /// Saupe's nearest-neighbour search on normalised block features.
    Nearest,
}

/// Where psa2d's domains may start.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Domains {
    /// On multiples of the ratio (domains tile the lattice).
    Touching,
    /// On any vertex.
    Overlapping,
}

/// A region of interest with its own tolerance (the quadtree PIFS's).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Roi {
    /// `[x0, y0, x1, y1]` in source pixels.
    pub rect: [f32; 4],
    /// Tolerance in source value units.
    pub tolerance: f32,
    /// Smallest range side inside the region (a power of two); the global one if `None`.
    pub min_range: Option<u32>,
}
