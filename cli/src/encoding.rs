//! `fractile encode`: rasters (quadtree PIFS, projected, FIS, psa2d) into assets, and with `shapes`
//! meshes (IFS3D) and curves.

use super::*;
use fractile_codec::encode::chunked::{
    DEFAULT_CHUNK, Share, chunk_bpp, encode_chunked_file, encode_chunked_file_at, wants_chunks,
};
use fractile_codec::encode::rate::FileRate;
use fractile_codec::io::rows::Rows;

use crate::progress::Progress;

mod parts;
mod shapes;
use parts::encode_part;
pub(crate) use parts::run_assemble;
pub(crate) use shapes::*;

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
    fn fis_scaling(self) -> Option<fractile_codec::codecs::fis::Scaling> {
        use fractile_codec::codecs::fis::Scaling;
        match self {
            CodecArg::FisBilinear => Some(Scaling::PerNode),
            CodecArg::FisRect => Some(Scaling::PerCell),
            CodecArg::FisRectGlobal => Some(Scaling::Global),
            _ => None,
        }
    }

    /// The tiling of a psa2d codec.
    fn psa_tiling(self) -> Option<Tiling> {
        match self {
            CodecArg::Psa2dRect => Some(Tiling::Rectangular),
            CodecArg::Psa2dTri => Some(Tiling::Triangular),
            _ => None,
        }
    }

    /// The name as the CLI and the API spell it.
    fn name(self) -> String {
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
    inputs: Vec<PathBuf>,
    /// Output asset file, or object (`s3://bucket/key`, the AWS variables as for `serve`).
    #[arg(short, long)]
    output: PathBuf,
    /// Largest file size in bits per source pixel (rate control): the whole file's, a chunked
    /// one's overviews and table included.
    #[arg(long, group = "rate")]
    target_bpp: Option<f64>,
    /// projected: the largest |decoded - source| at any valid cell, in source units (metres,
    /// grey levels); 0 is lossless for integer samples.
    #[arg(long, group = "rate")]
    max_error: Option<f64>,
    /// projected with --target-bpp: the smallest max error whose file fits the rate (every
    /// cell within it, reported as max_error_bound), instead of the best PSNR (which is
    /// about 1.8 dB higher on DEMs at the same rate, with no bound a cell keeps).
    #[arg(long)]
    bounded: bool,
    /// Split ranges while their RMS collage error exceeds this (source units: grey levels,
    /// metres; voxels for meshes). Curves: the largest error of a vertex, degrees of arc for
    /// GeoJSON (0.009 is about 1 km); 0 (the default) keeps every detail exactly.
    #[arg(long, group = "rate")]
    tolerance: Option<f32>,
    /// Split until this many ranges (the seed's "quad N").
    #[arg(long, group = "rate")]
    transforms: Option<usize>,
    /// A regular grid of R x R ranges (the seed's "const range R"; 1 = quasi-lossless).
    #[arg(long, group = "rate")]
    const_range: Option<u32>,
    /// Region of interest `x0,y0,x1,y1:tolerance[:min_range]` in source pixels (repeatable).
    #[arg(long, value_parser = parse_roi)]
    roi: Vec<Roi>,
    /// Smallest range side (power of two).
    #[arg(long, default_value_t = EncodeSettings::default().min_range)]
    min_range: u32,
    /// Largest range side (power of two).
    #[arg(long, default_value_t = EncodeSettings::default().max_range)]
    max_range: u32,
    /// quadtree-pifs: encoder speed preset, 0 (slowest, best) to 4 (fastest). Sets the domain
    /// lattice, the search's candidates and the attractor passes (`--domain-step`,
    /// `--candidates` and `--attractor-passes` override it).
    #[arg(long, default_value_t = fractile_codec::encode::DEFAULT_SPEED)]
    speed: u8,
    /// Domain lattice step, as a fraction of the range side [default: from --speed, 2].
    #[arg(long)]
    domain_step: Option<f32>,
    /// Bits of the contrast index.
    #[arg(long, default_value_t = EncodeSettings::default().quantiser.contrast_bits)]
    contrast_bits: u8,
    /// Bits of the offset index [default: 6]. Height fields under --target-bpp without this or
    /// --slope-bits: offsets and slopes are coded at 5, 6, 7 and 8 bits and the best kept.
    #[arg(long)]
    offset_bits: Option<u8>,
    /// Bits of each slope of a planar offset term (0: constant offsets, the seed's codec).
    /// Default: 6 for height fields (see --offset-bits), 0 for images.
    #[arg(long)]
    slope_bits: Option<u8>,
    /// Largest |contrast| (< 1).
    #[arg(long, default_value_t = EncodeSettings::default().quantiser.max_contrast)]
    max_contrast: f32,
    /// Domain search.
    #[arg(long, value_enum, default_value_t = Search::Nearest)]
    search: Search,
    /// Candidates scored per range by the nearest-neighbour search [default: from --speed, 32].
    #[arg(long)]
    candidates: Option<usize>,
    /// quadtree-pifs: passes that search again with domains read from the decoded attractor,
    /// keeping the asset that decodes closest to the source; each costs one more search
    /// [default: from --speed, 0].
    #[arg(long)]
    attractor_passes: Option<u32>,
    /// Codec: FIS codecs take height fields, psa2d grey images and height fields; GeoJSON input
    /// is always `curve`, a mesh IFS3D. Default for a height field: `projected` under a bounded
    /// rate (`--target-bpp B --bounded`, B = 0.8 unless given; or `--max-error E`), whose every
    /// cell is within the bound it answers; for an image, or a height field with a flag only
    /// the quadtree reads (--tolerance, --transforms, --const-range, --roi, --speed, ...):
    /// `quadtree-pifs`.
    #[arg(long, value_enum)]
    codec: Option<CodecArg>,
    /// psa2d: touching or overlapping domains.
    #[arg(long, value_enum, default_value_t = DomainsArg::Overlapping)]
    domains: DomainsArg,
    /// psa2d: domain side in regions.
    #[arg(long, default_value_t = fractile_codec::codecs::psa::PsaSettings::default().ratio)]
    domain_ratio: u32,
    /// psa2d: domain search radius (regions, or domains when touching).
    #[arg(long, default_value_t = fractile_codec::codecs::psa::PsaSettings::default().radius)]
    radius: u32,
    /// FIS and psa2d: samples between interpolation points (ignored with --target-bpp, which
    /// picks it).
    #[arg(long, default_value_t = FisSettings::default().spacing)]
    spacing: u32,
    /// FIS: node height step in source units (default: the source's quantum).
    #[arg(long)]
    height_step: Option<f64>,
    /// Meshes: samples per side of the signed distance grid.
    #[arg(long, default_value_t = 64)]
    grid: usize,
    /// Meshes: half-width of the distance band in voxels (distances are clamped to it).
    #[arg(long, default_value_t = 4.0)]
    band: f64,
    /// FIS: bits of each vertical scaling.
    #[arg(long, default_value_t = FisSettings::default().scaling_bits)]
    scaling_bits: u8,
    /// Rasters: code in chunks of N x N cells (a power of two, 64 to 16384), each on its own,
    /// on every core, with overviews for coarse zooms; 0 never chunks. Default: chunks of
    /// 1024 for rasters over 2048 cells on a side, one operator for smaller ones.
    #[arg(long)]
    chunk: Option<u32>,
    /// Rasters in chunks: code only share I of N of the chunks (chunk k, counted level by
    /// level, when k mod N = I) into the part file -o names; `fractile assemble` joins the N
    /// parts into the asset, the same bytes as one encode. Runs N processes or machines.
    #[arg(long, value_name = "I/N")]
    part: Option<String>,
    /// Print JSON (and no progress).
    #[arg(long)]
    json: bool,
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
    fn with_default_codec(mut self, kind: AssetKind) -> EncodeArgs {
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
    fn codec(&self) -> CodecArg {
        self.codec.unwrap_or(CodecArg::QuadtreePifs)
    }

    /// The one input of a kind that does not mosaic (a mesh, a GeoJSON file).
    fn input(&self) -> Result<&PathBuf> {
        match self.inputs.as_slice() {
            [one] => Ok(one),
            _ => bail!("only GeoTIFFs make a mosaic: give one mesh or GeoJSON file"),
        }
    }
}

pub(crate) fn run_encode(a: EncodeArgs) -> Result<()> {
    if is_mesh(&a.inputs[0]) {
        return encode_volume(&a);
    }
    if is_geojson(&a.inputs[0]) || a.codec == Some(CodecArg::Curve) {
        return encode_curve(&a);
    }
    let files = fractile_codec::io::mosaic::input_files(&a.inputs)?;
    // Rows, not a raster: a chunked encode reads its input a band at a time.
    let mut rows = fractile_codec::io::rows::open(&a.inputs)?;
    let (width, height) = (rows.header().width, rows.header().height);
    let a = a.with_default_codec(rows.header().kind);
    let lattice = |a: &EncodeArgs| {
        if a.tolerance.is_some() || a.transforms.is_some() || a.const_range.is_some() {
            bail!(
                "--codec {} takes --spacing, --max-error or --target-bpp",
                a.codec().name()
            );
        }
        Ok(())
    };
    if (a.max_error.is_some() || a.bounded) && a.codec() != CodecArg::Projected {
        bail!("--max-error and --bounded are for --codec projected");
    }
    if a.bounded && a.target_bpp.is_none() {
        bail!("--bounded bounds the error under --target-bpp B");
    }
    if a.codec() == CodecArg::Projected && a.max_error.is_none() && a.target_bpp.is_none() {
        bail!("--codec projected takes --max-error E (source units) or --target-bpp B");
    }
    if a.codec() == CodecArg::Curve {
        bail!("--codec curve is for GeoJSON input");
    }
    if a.codec() != CodecArg::QuadtreePifs {
        lattice(&a)?;
    }
    let chunk = match a.chunk {
        Some(0) => None,
        Some(c) => Some(c),
        None => wants_chunks(width, height, DEFAULT_CHUNK).then_some(DEFAULT_CHUNK),
    };
    if let Some(text) = &a.part {
        let Some(c) = chunk else {
            bail!("--part splits an encode in chunks, and this one is whole: give --chunk N")
        };
        return encode_part(&a, rows.as_mut(), c, Share::parse(text)?);
    }
    // An s3:// output is written here first, then uploaded.
    let out = crate::remote::Local::output(&a.output)?;
    let enc = match chunk {
        None => {
            // The quadtree counts its blocks in a bar of its own; the other codecs get one that
            // shows how long they have run.
            let quadtree = a.codec() == CodecArg::QuadtreePifs;
            let mut bar = Progress::start("coding", a.quiet || a.json || quadtree);
            let enc = encode_with(&a, &rows.read_all()?, true)?;
            bar.finish();
            enc.write(out.path())?
        }
        Some(c) => encode_chunks(&a, rows.as_mut(), c, out.path())?,
    };
    out.finish()?;
    let report = json!({
        "input": a.inputs[0], "inputs": files, "output": a.output, "codec": enc.asset.codec_name(),
        "width": width, "height": height,
        "bytes": enc.length, "source_bytes": enc.asset.meta.source_bytes(),
        "ratio": enc.ratio(), "bpp": enc.bpp(), "transforms": enc.transforms,
        "seconds": enc.seconds, "psnr": enc.errors.psnr, "rmse": enc.errors.rmse,
        "max_error": enc.errors.max_error,
        // As asked, or what a bounded rate found (the promise the asset keeps, with the
        // f32 slack the server adds).
        "max_error_bound": a.max_error.or_else(|| {
            enc.asset.planes.first().and_then(|p| p.promise()).map(f64::from)
        }),
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{}{} -> {}: {} {} bytes, {:.2}:1, {:.3} bpp, {} transforms, {:.2} s, PSNR {:.2} dB, RMSE {:.3}, max error {:.3}",
            a.inputs[0].display(),
            if files.len() > 1 {
                format!(" (a mosaic of {} files, {}x{})", files.len(), width, height)
            } else {
                String::new()
            },
            a.output.display(),
            enc.asset.codec_name(),
            enc.length,
            enc.ratio(),
            enc.bpp(),
            enc.transforms,
            enc.seconds,
            enc.errors.psnr,
            enc.errors.rmse,
            enc.errors.max_error
        );
    }
    Ok(())
}

/// A raster coded in chunks of `c` into `output`: under a file's rate ([`file_rate`]) or each
/// chunk by the settings of `a` with its share of the rate.
fn encode_chunks(
    a: &EncodeArgs,
    rows: &mut dyn Rows,
    c: u32,
    output: &Path,
) -> Result<fractile_codec::encode::Written> {
    let (width, height) = (rows.header().width, rows.header().height);
    let mut bar = Progress::start("coding chunks", a.quiet || a.json);
    let progress = |done: u64, total: u64| bar.update(done, total);
    let enc = match file_rate(a, rows.header().channels) {
        Some(rate) => {
            let at =
                |r: &Raster, q, trial| fractile_codec::encode::projected::encode_at(r, q, trial);
            encode_chunked_file_at(rows, c, (rate, &at), &progress, output)?
        }
        None => {
            let per_chunk = a.chunk_rate(width, height, c);
            let one = |r: &Raster| {
                encode_with(&per_chunk, r, false)
                    .map_err(|e| fractile_codec::Error::Settings(e.to_string()))
            };
            encode_chunked_file(rows, c, &one, &progress, output)?
        }
    };
    bar.finish();
    Ok(enc)
}

/// The file's rate of a chunked encode (`fractile_codec::encode::rate`): the projected codec
/// of one channel under `--target-bpp` (the DEM default among them), whose chunks share one
/// step or one bound. `None`: each chunk coded on its own ([`EncodeArgs::chunk_rate`]).
pub(super) fn file_rate(a: &EncodeArgs, channels: usize) -> Option<FileRate> {
    let projected = a.codec() == CodecArg::Projected && a.max_error.is_none() && channels == 1;
    a.target_bpp.filter(|_| projected).map(|bpp| FileRate {
        bpp,
        bounded: a.bounded,
    })
}

impl EncodeArgs {
    /// These settings with the rate of one chunk of a file coded chunk by chunk, so that the
    /// whole file, overviews included, is within `--target-bpp` ([`chunk_bpp`]).
    pub(super) fn chunk_rate(&self, width: usize, height: usize, chunk: u32) -> EncodeArgs {
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

/// `raster` coded by the codec `a` names (chunked or not, the same settings); `bar`: whether a
/// long quadtree encode shows its own progress bar (not for chunks, which share one).
fn encode_with(a: &EncodeArgs, raster: &Raster, bar: bool) -> Result<fractile_codec::Encoded> {
    Ok(if a.codec() == CodecArg::QuadtreePifs {
        encode_quadtree(a, raster, bar)?
    } else if a.codec() == CodecArg::Projected {
        let settings = fractile_codec::codecs::projected::ProjectedSettings {
            max_error: a.max_error,
            bounded: a.bounded,
            ..Default::default()
        };
        fractile_codec::encode::projected::encode_projected(raster, &settings, a.target_bpp)?
    } else if let Some(tiling) = a.codec().psa_tiling() {
        let domains = match a.domains {
            DomainsArg::Touching => Domains::Touching,
            DomainsArg::Overlapping => Domains::Overlapping,
        };
        let settings = PsaSettings {
            tiling,
            domains,
            region: a.spacing,
            ratio: a.domain_ratio,
            radius: a.radius,
            max_scaling: a.max_contrast,
            ..PsaSettings::default()
        };
        fractile_codec::encode::encode_psa(raster, &settings, a.target_bpp)?
    } else {
        let Some(scaling) = a.codec().fis_scaling() else {
            bail!("--codec curve is for GeoJSON input");
        };
        let settings = FisSettings {
            scaling,
            spacing: a.spacing,
            height_step: a.height_step,
            scaling_bits: a.scaling_bits,
            max_scaling: a.max_contrast,
        };
        fractile_codec::encode::encode_fis(raster, &settings, a.target_bpp)?
    })
}

pub(crate) fn encode_quadtree(
    a: &EncodeArgs,
    raster: &Raster,
    show_bar: bool,
) -> Result<fractile_codec::Encoded> {
    let rate = match (a.target_bpp, a.tolerance, a.transforms, a.const_range) {
        (Some(b), ..) => RateMode::TargetBpp(b),
        (_, Some(t), ..) => RateMode::Tolerance(t),
        (_, _, Some(n), _) => RateMode::Transforms(n),
        (.., Some(r)) => RateMode::ConstRange(r),
        _ => RateMode::Tolerance(f32::NAN),
    };
    let preset = EncodeSettings::at_speed(a.speed)?;
    let candidates = match preset.search {
        SearchMode::Nearest(k) => a.candidates.unwrap_or(k),
        _ => a.candidates.unwrap_or(32),
    };
    let quantiser = Quantiser {
        contrast_bits: a.contrast_bits,
        offset_bits: a.offset_bits.unwrap_or(preset.quantiser.offset_bits),
        max_contrast: a.max_contrast,
        slope_bits: a
            .slope_bits
            .unwrap_or(EncodeSettings::default_slope_bits(raster.kind)),
    };
    // Bits the user gave are kept as given; otherwise the encoder weighs the kind's choices.
    let quantiser_choices = if a.offset_bits.is_none() && a.slope_bits.is_none() {
        EncodeSettings::default_quantiser_choices(raster.kind, quantiser)
    } else {
        Vec::new()
    };
    let settings = EncodeSettings {
        rate,
        min_range: a.min_range,
        max_range: a.max_range,
        domain_step: a.domain_step.unwrap_or(preset.domain_step),
        quantiser,
        quantiser_choices,
        search: match a.search {
            Search::Full => SearchMode::Full,
            Search::Classified => SearchMode::Classified,
            Search::Nearest => SearchMode::Nearest(candidates.max(1)),
        },
        rois: a.roi.clone(),
        attractor_passes: a.attractor_passes.unwrap_or(preset.attractor_passes),
        ..preset
    };
    let mut bar = Progress::start("fitting blocks", a.quiet || a.json || !show_bar);
    let progress = |done: u64, total: u64| bar.update(done, total);
    let enc = encode(raster, &settings, &progress)?;
    bar.finish();
    Ok(enc)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The CLI's codec names are the codec crate's own (what `info` and the API report).
    #[test]
    fn codec_names_are_the_codecs_own() {
        for c in CodecArg::value_variants() {
            if let Some(s) = c.fis_scaling() {
                assert_eq!(c.name(), fractile_codec::codecs::fis::codec_name(s));
            }
            if let Some(t) = c.psa_tiling() {
                assert_eq!(c.name(), fractile_codec::codecs::psa::codec_name(t));
            }
        }
        assert_eq!(CodecArg::QuadtreePifs.name(), "quadtree-pifs");
        assert_eq!(CodecArg::Curve.name(), "curve");
        assert_eq!(
            CodecArg::Projected.name(),
            fractile_codec::codecs::projected::CODEC_NAME
        );
    }
}
