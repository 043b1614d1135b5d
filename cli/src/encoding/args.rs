//! `fractile encode`'s arguments: the codec named, its settings, and the rate of a file coded in
//! chunks.

use std::path::PathBuf;

use anyhow::{Result, bail};
use clap::ValueEnum;
use fractile_codec::codecs::fis::FisSettings;
use fractile_codec::codecs::projected::ProjectedSettings;
use fractile_codec::codecs::psa::{Domains, PsaSettings, Tiling};
use fractile_codec::encode::chunked::chunk_bpp;
use fractile_codec::encode::rate::{FileRate, Quality, Target};
use fractile_codec::{CodecSettings, QuadtreeSettings, Quantiser, RateMode, Roi, SearchMode};
use fractile_proto::AssetKind;

#[derive(Clone, Copy, Debug, ValueEnum)]
pub(crate) enum Search {
    /// Every domain and isometry (slow; the reference).
    Full,
    /// Fisher's quadrant-brightness classes.
    Classified,
    /// Saupe's nearest-neighbour search on normalised block features.
    Nearest,
}

/// `--codec`: the closed set of codecs `encode` writes (names as the API spells them).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum CodecArg {
    /// Quadtree partitioned IFS (images and height fields).
    QuadtreePifs,
    /// Fractal interpolation surface, s per node (Wu and Zhou).
    FisBilinear,
    /// Fractal interpolation surface, s per cell.
    FisRect,
    /// Fractal interpolation surface, one s (Drakopoulos and Manousopoulos).
    FisRectGlobal,
    /// Piecewise self-affine model, rectangular regions.
    Psa2dRect,
    /// Piecewise self-affine model, triangular regions.
    Psa2dTri,
    /// Projected IFS with details (GeoJSON curves).
    Curve,
    /// Projected IFS with details on a grid: fitted subdivision plus details (height fields and
    /// grey images; --max-error or --target-bpp).
    Projected,
}

impl CodecArg {
    /// The layout of s of a FIS codec.
    pub(crate) fn fis_scaling(self) -> Option<fractile_codec::codecs::fis::Scaling> {
        use fractile_codec::codecs::fis::Scaling;
        match self {
            CodecArg::FisBilinear => Some(Scaling::PerNode),
            CodecArg::FisRect => Some(Scaling::PerCell),
            CodecArg::FisRectGlobal => Some(Scaling::Global),
            _ => None,
        }
    }

    /// The tiling of a psa2d codec.
    pub(crate) fn psa_tiling(self) -> Option<Tiling> {
        match self {
            CodecArg::Psa2dRect => Some(Tiling::Rectangular),
            CodecArg::Psa2dTri => Some(Tiling::Triangular),
            _ => None,
        }
    }

    /// The name as the CLI and the API spell it.
    pub(crate) fn name(self) -> String {
        self.to_possible_value()
            .map_or_else(String::new, |v| v.get_name().to_string())
    }
}

/// `--domains` of psa2d.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum DomainsArg {
    /// Domains that tile the plane.
    Touching,
    /// Domains at every region corner.
    Overlapping,
}

#[derive(clap::Args, Debug)]
pub(crate) struct EncodeArgs {
    /// Input: a raster, a mesh or a GeoJSON file; or, for a mosaic, several GeoTIFFs (or a
    /// folder of them) on one grid, read as one raster (cells none covers are nodata).
    #[arg(required = true, num_args = 1..)]
    pub(crate) inputs: Vec<PathBuf>,
    /// Output asset file, or object (`s3://bucket/key`, the AWS variables as for `serve`).
    #[arg(short, long)]
    pub(crate) output: PathBuf,
    /// Largest file size in bits per source pixel (rate control): the whole file's, a chunked
    /// one's overviews and table included.
    #[arg(long, group = "rate")]
    pub(crate) target_bpp: Option<f64>,
    /// projected: the largest |decoded - source| at any valid cell, in source units (metres,
    /// grey levels); 0 is lossless for integer samples.
    #[arg(long, group = "rate")]
    pub(crate) max_error: Option<f64>,
    /// projected with --target-bpp: the smallest max error whose file fits the rate (every
    /// cell within it, reported as max_error_bound), instead of the best PSNR (which is
    /// about 1.8 dB higher on DEMs at the same rate, with no bound a cell keeps).
    #[arg(long)]
    pub(crate) bounded: bool,
    /// Split ranges while their RMS collage error exceeds this (source units: grey levels,
    /// metres; voxels for meshes). Curves: the largest error of a vertex, degrees of arc for
    /// GeoJSON (0.009 is about 1 km); 0 (the default) keeps every detail exactly.
    #[arg(long, group = "rate")]
    pub(crate) tolerance: Option<f32>,
    /// Split until this many ranges (the seed's "quad N").
    #[arg(long, group = "rate")]
    pub(crate) transforms: Option<usize>,
    /// A regular grid of R x R ranges (the seed's "const range R"; 1 = quasi-lossless).
    #[arg(long, group = "rate")]
    pub(crate) const_range: Option<u32>,
    /// Region of interest `x0,y0,x1,y1:tolerance[:min_range]` in source pixels (repeatable).
    #[arg(long, value_parser = parse_roi)]
    pub(crate) roi: Vec<Roi>,
    /// Smallest range side (power of two).
    #[arg(long, default_value_t = QuadtreeSettings::default().min_range)]
    pub(crate) min_range: u32,
    /// Largest range side (power of two).
    #[arg(long, default_value_t = QuadtreeSettings::default().max_range)]
    pub(crate) max_range: u32,
    /// quadtree-pifs: encoder speed preset, 0 (slowest, best) to 4 (fastest). Sets the domain
    /// lattice, the search's candidates and the attractor passes (`--domain-step`,
    /// `--candidates` and `--attractor-passes` override it).
    #[arg(long, default_value_t = fractile_codec::codecs::quadtree::DEFAULT_SPEED)]
    pub(crate) speed: u8,
    /// Domain lattice step, as a fraction of the range side [default: from --speed, 2].
    #[arg(long)]
    pub(crate) domain_step: Option<f32>,
    /// Bits of the contrast index.
    #[arg(long, default_value_t = QuadtreeSettings::default().quantiser.contrast_bits)]
    pub(crate) contrast_bits: u8,
    /// Bits of the offset index [default: 6]. Height fields under --target-bpp without this or
    /// --slope-bits: offsets and slopes are coded at 5, 6, 7 and 8 bits and the best kept.
    #[arg(long)]
    pub(crate) offset_bits: Option<u8>,
    /// Bits of each slope of a planar offset term (0: constant offsets, the seed's codec).
    /// Default: 6 for height fields (see --offset-bits), 0 for images.
    #[arg(long)]
    pub(crate) slope_bits: Option<u8>,
    /// Largest |contrast| (< 1).
    #[arg(long, default_value_t = QuadtreeSettings::default().quantiser.max_contrast)]
    pub(crate) max_contrast: f32,
    /// Domain search.
    #[arg(long, value_enum, default_value_t = Search::Nearest)]
    pub(crate) search: Search,
    /// Candidates scored per range by the nearest-neighbour search [default: from --speed, 32].
    #[arg(long)]
    pub(crate) candidates: Option<usize>,
    /// quadtree-pifs: passes that search again with domains read from the decoded attractor,
    /// keeping the asset that decodes closest to the source; each costs one more search
    /// [default: from --speed, 0].
    #[arg(long)]
    pub(crate) attractor_passes: Option<u32>,
    /// Codec: FIS codecs take height fields, psa2d grey images and height fields; GeoJSON input
    /// is always `curve`, a mesh IFS3D. Default for a height field: `projected` under a bounded
    /// rate (`--target-bpp B --bounded`, B = 0.8 unless given; or `--max-error E`), whose every
    /// cell is within the bound it answers; for an image, or a height field with a flag only
    /// the quadtree reads (--tolerance, --transforms, --const-range, --roi, --speed, ...):
    /// `quadtree-pifs`.
    #[arg(long, value_enum)]
    pub(crate) codec: Option<CodecArg>,
    /// psa2d: touching or overlapping domains.
    #[arg(long, value_enum, default_value_t = DomainsArg::Overlapping)]
    pub(crate) domains: DomainsArg,
    /// psa2d: domain side in regions.
    #[arg(long, default_value_t = fractile_codec::codecs::psa::PsaSettings::default().ratio)]
    pub(crate) domain_ratio: u32,
    /// psa2d: domain search radius (regions, or domains when touching).
    #[arg(long, default_value_t = fractile_codec::codecs::psa::PsaSettings::default().radius)]
    pub(crate) radius: u32,
    /// FIS and psa2d: samples between interpolation points (ignored with --target-bpp, which
    /// picks it).
    #[arg(long, default_value_t = FisSettings::default().spacing)]
    pub(crate) spacing: u32,
    /// FIS: node height step in source units (default: the source's quantum).
    #[arg(long)]
    pub(crate) height_step: Option<f64>,
    /// Meshes: samples per side of the signed distance grid.
    #[arg(long, default_value_t = 64)]
    pub(crate) grid: usize,
    /// Meshes: half-width of the distance band in voxels (distances are clamped to it).
    #[arg(long, default_value_t = 4.0)]
    pub(crate) band: f64,
    /// FIS: bits of each vertical scaling.
    #[arg(long, default_value_t = FisSettings::default().scaling_bits)]
    pub(crate) scaling_bits: u8,
    /// Rasters: code in chunks of N x N cells (a power of two, 64 to 16384), each on its own,
    /// on every core, with overviews for coarse zooms; 0 never chunks. Default: chunks of
    /// 1024 for rasters over 2048 cells on a side, one operator for smaller ones.
    #[arg(long)]
    pub(crate) chunk: Option<u32>,
    /// Rasters in chunks: code only share I of N of the chunks (chunk k, counted level by
    /// level, when k mod N = I) into the part file -o names; `fractile assemble` joins the N
    /// parts into the asset, the same bytes as one encode. Runs N processes or machines.
    #[arg(long, value_name = "I/N")]
    pub(crate) part: Option<String>,
    /// Print JSON (and no progress).
    #[arg(long)]
    pub(crate) json: bool,
    /// No progress on stderr (by default a bar on a terminal, elsewhere a line every 10 s,
    /// for any encode that runs over a second).
    #[arg(long, short)]
    pub(crate) quiet: bool,
    /// The quadtree-only flags given on the command line (by `main`, from clap's matches: the
    /// flags with defaults cannot tell given from defaulted otherwise).
    #[arg(skip)]
    pub(crate) quadtree_flags: Vec<&'static str>,
}

/// The flags only the quadtree PIFS reads, by clap id: given any, a height field with no
/// `--codec` is coded by the quadtree, as before the projected default.
pub(crate) const QUADTREE_FLAGS: &[&str] = &[
    "tolerance",
    "transforms",
    "const_range",
    "roi",
    "min_range",
    "max_range",
    "speed",
    "domain_step",
    "contrast_bits",
    "offset_bits",
    "slope_bits",
    "search",
    "candidates",
    "attractor_passes",
];

pub(crate) fn parse_roi(s: &str) -> Result<Roi, String> {
    let mut parts = s.split(':');
    let rect: Vec<f32> = parts
        .next()
        .unwrap_or("")
        .split(',')
        .map(|v| v.trim().parse::<f32>().map_err(|e| format!("{v:?}: {e}")))
        .collect::<Result<_, _>>()?;
    if rect.len() != 4 {
        return Err("expected x0,y0,x1,y1:tolerance[:min_range]".into());
    }
    let tolerance = parts
        .next()
        .ok_or("missing :tolerance")?
        .parse::<f32>()
        .map_err(|e| e.to_string())?;
    let min_range = parts
        .next()
        .map(|m| m.parse::<u32>().map_err(|e| e.to_string()))
        .transpose()?;
    Ok(Roi {
        rect: [rect[0], rect[1], rect[2], rect[3]],
        tolerance,
        min_range,
    })
}

impl EncodeArgs {
    /// The arguments with `--codec` decided when none was given (see its help): `projected`
    /// under a bounded rate for a height field unless a quadtree-only flag is given, or for
    /// any raster with `--max-error` or `--bounded`; `quadtree-pifs` otherwise.
    pub(crate) fn with_default_codec(mut self, kind: AssetKind) -> EncodeArgs {
        if self.codec.is_some() {
            return self;
        }
        let quadtree = !self.quadtree_flags.is_empty();
        let projected = !quadtree
            && (kind == AssetKind::HeightField || self.max_error.is_some() || self.bounded);
        self.codec = Some(if projected {
            CodecArg::Projected
        } else {
            CodecArg::QuadtreePifs
        });
        if projected && self.max_error.is_none() {
            self.bounded = true;
            self.target_bpp = self
                .target_bpp
                .or(Some(fractile_codec::encode::DEFAULT_HEIGHT_FIELD_BPP));
        }
        self
    }

    /// The codec (decided by [`Self::with_default_codec`] for rasters).
    pub(crate) fn codec(&self) -> CodecArg {
        self.codec.unwrap_or(CodecArg::QuadtreePifs)
    }

    /// The one input of a kind that does not mosaic (a mesh, a GeoJSON file).
    pub(crate) fn input(&self) -> Result<&PathBuf> {
        match self.inputs.as_slice() {
            [one] => Ok(one),
            _ => bail!("only GeoTIFFs make a mosaic: give one mesh or GeoJSON file"),
        }
    }
}

impl EncodeArgs {
    /// The settings of the codec named (decided by [`Self::with_default_codec`] for rasters)
    /// from its flags, for a raster of `kind`; another codec's flags are refused by name.
    pub(crate) fn codec_settings(&self, kind: AssetKind) -> Result<CodecSettings> {
        let codec = self.codec();
        if (self.max_error.is_some() || self.bounded) && codec != CodecArg::Projected {
            bail!("--max-error and --bounded are for --codec projected");
        }
        if self.bounded && self.target_bpp.is_none() {
            bail!("--bounded bounds the error under --target-bpp B");
        }
        let quadtree_rate =
            self.tolerance.is_some() || self.transforms.is_some() || self.const_range.is_some();
        if codec != CodecArg::QuadtreePifs && quadtree_rate {
            bail!(
                "--codec {} takes --spacing, --max-error or --target-bpp",
                codec.name()
            );
        }
        let domains = match self.domains {
            DomainsArg::Touching => Domains::Touching,
            DomainsArg::Overlapping => Domains::Overlapping,
        };
        Ok(match codec {
            CodecArg::QuadtreePifs => self.quadtree_settings(kind)?.into(),
            CodecArg::Projected => {
                if self.max_error.is_none() && self.target_bpp.is_none() {
                    bail!("--codec projected takes --max-error E (source units) or --target-bpp B");
                }
                ProjectedSettings {
                    max_error: self.max_error,
                    bounded: self.bounded,
                    target_bpp: self.target_bpp,
                    ..Default::default()
                }
                .into()
            }
            CodecArg::Psa2dRect | CodecArg::Psa2dTri => PsaSettings {
                tiling: codec.psa_tiling().unwrap_or(Tiling::Rectangular),
                domains,
                region: self.spacing,
                ratio: self.domain_ratio,
                radius: self.radius,
                max_scaling: self.max_contrast,
                target_bpp: self.target_bpp,
                ..PsaSettings::default()
            }
            .into(),
            CodecArg::FisBilinear | CodecArg::FisRect | CodecArg::FisRectGlobal => FisSettings {
                scaling: codec
                    .fis_scaling()
                    .unwrap_or(fractile_codec::codecs::fis::Scaling::PerNode),
                spacing: self.spacing,
                height_step: self.height_step,
                scaling_bits: self.scaling_bits,
                max_scaling: self.max_contrast,
                target_bpp: self.target_bpp,
            }
            .into(),
            CodecArg::Curve => bail!("--codec curve is for GeoJSON input"),
        })
    }

    /// The quadtree's settings: the speed preset's, with the flags given over it.
    fn quadtree_settings(&self, kind: AssetKind) -> Result<QuadtreeSettings> {
        let rate = match (
            self.target_bpp,
            self.tolerance,
            self.transforms,
            self.const_range,
        ) {
            (Some(b), ..) => RateMode::TargetBpp(b),
            (_, Some(t), ..) => RateMode::Tolerance(t),
            (_, _, Some(n), _) => RateMode::Transforms(n),
            (.., Some(r)) => RateMode::ConstRange(r),
            _ => RateMode::Tolerance(f32::NAN),
        };
        let preset = QuadtreeSettings::at_speed(self.speed)?;
        let candidates = match preset.search {
            SearchMode::Nearest(k) => self.candidates.unwrap_or(k),
            _ => self.candidates.unwrap_or(32),
        };
        let quantiser = Quantiser {
            contrast_bits: self.contrast_bits,
            offset_bits: self.offset_bits.unwrap_or(preset.quantiser.offset_bits),
            max_contrast: self.max_contrast,
            slope_bits: self
                .slope_bits
                .unwrap_or(QuadtreeSettings::default_slope_bits(kind)),
        };
        // Bits the user gave are kept as given; otherwise the encoder weighs the kind's choices.
        let quantiser_choices = if self.offset_bits.is_none() && self.slope_bits.is_none() {
            QuadtreeSettings::default_quantiser_choices(kind, quantiser)
        } else {
            Vec::new()
        };
        Ok(QuadtreeSettings {
            rate,
            min_range: self.min_range,
            max_range: self.max_range,
            domain_step: self.domain_step.unwrap_or(preset.domain_step),
            quantiser,
            quantiser_choices,
            search: match self.search {
                Search::Full => SearchMode::Full,
                Search::Classified => SearchMode::Classified,
                Search::Nearest => SearchMode::Nearest(candidates.max(1)),
            },
            rois: self.roi.clone(),
            attractor_passes: self.attractor_passes.unwrap_or(preset.attractor_passes),
            ..preset
        })
    }
}

/// The one quality of a chunked encode's chunks (`fractile_codec::encode::rate`): for the
/// projected codec of one channel, `--max-error E` (every source chunk within E, the coded
/// overviews' bound doubled a level) or the file's rate under `--target-bpp` (the DEM default
/// among them), whose chunks share one step or one bound. `None`: each chunk coded on its own
/// ([`EncodeArgs::chunk_rate`]).
pub(crate) fn file_rate(a: &EncodeArgs, channels: usize) -> Option<Target> {
    if a.codec() != CodecArg::Projected || channels != 1 {
        return None;
    }
    if let Some(e) = a.max_error {
        return Some(Quality::Bound(e).into());
    }
    a.target_bpp.map(|bpp| {
        FileRate {
            bpp,
            bounded: a.bounded,
        }
        .into()
    })
}

impl EncodeArgs {
    /// These settings with the rate of one chunk of a file coded chunk by chunk, so that the
    /// whole file, overviews included, is within `--target-bpp` ([`chunk_bpp`]).
    pub(crate) fn chunk_rate(&self, width: usize, height: usize, chunk: u32) -> EncodeArgs {
        EncodeArgs {
            inputs: self.inputs.clone(),
            output: self.output.clone(),
            quadtree_flags: self.quadtree_flags.clone(),
            roi: self.roi.clone(),
            part: self.part.clone(),
            target_bpp: self.target_bpp.map(|b| chunk_bpp(width, height, chunk, b)),
            ..*self
        }
    }
}
