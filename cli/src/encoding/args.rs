//! `fractile encode`'s arguments: the codec named, its settings, and the rate of a file coded in
//! chunks.

use std::path::PathBuf;

use anyhow::{Result, bail};
use clap::ValueEnum;
use clap::builder::{PossibleValue, PossibleValuesParser};

use fractile_codec::encode::{Domains, Options};
use fractile_codec::{CodecSettings, Roi};
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

/// `--codec`'s values: every plane codec's names with their help, from the codec's registry
/// (a codec added there is named here with no edit), and `curve` for GeoJSON.
pub(crate) fn codec_names() -> PossibleValuesParser {
    let planes = CodecSettings::names();
    let curve = [("curve", "Projected IFS with details (GeoJSON curves).")];
    PossibleValuesParser::new(
        planes
            .into_iter()
            .chain(curve)
            .map(|(name, help)| PossibleValue::new(name).help(help)),
    )
}

/// The codecs named by the CLI's defaults (`EncodeArgs::with_default_codec`).
const PROJECTED: &str = fractile_codec::codecs::projected::CODEC_NAME;
const QUADTREE: &str = "quadtree-pifs";

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
    /// GeoTIFFs may be `s3://bucket/key.tif`, every `.tif` under `s3://bucket/prefix/`,
    /// `https://...tif` (read by range), or named by a `.txt` list or a STAC ItemCollection.
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
    /// Smallest range side (power of two) [default: 4].
    #[arg(long)]
    pub(crate) min_range: Option<u32>,
    /// Largest range side (power of two) [default: 64].
    #[arg(long)]
    pub(crate) max_range: Option<u32>,
    /// quadtree-pifs: encoder speed preset, 0 (slowest, best) to 4 (fastest) [default: 2]. Sets
    /// the domain lattice, the search's candidates and the attractor passes (`--domain-step`,
    /// `--candidates` and `--attractor-passes` override it).
    #[arg(long)]
    pub(crate) speed: Option<u8>,
    /// Domain lattice step, as a fraction of the range side [default: from --speed, 2].
    #[arg(long)]
    pub(crate) domain_step: Option<f32>,
    /// Bits of the contrast index [default: 4].
    #[arg(long)]
    pub(crate) contrast_bits: Option<u8>,
    /// Bits of the offset index [default: 6]. Height fields under --target-bpp without this or
    /// --slope-bits: offsets and slopes are coded at 5, 6, 7 and 8 bits and the best kept.
    #[arg(long)]
    pub(crate) offset_bits: Option<u8>,
    /// Bits of each slope of a planar offset term (0: constant offsets, the seed's codec).
    /// Default: 6 for height fields (see --offset-bits), 0 for images.
    #[arg(long)]
    pub(crate) slope_bits: Option<u8>,
    /// Largest |contrast| (< 1): the quadtree's, FIS's and psa2d's [default: 0.9].
    #[arg(long)]
    pub(crate) max_contrast: Option<f32>,
    /// Domain search [default: nearest].
    #[arg(long, value_enum)]
    pub(crate) search: Option<Search>,
    /// Candidates scored per range by the nearest-neighbour search [default: from --speed, 32].
    #[arg(long)]
    pub(crate) candidates: Option<usize>,
    /// quadtree-pifs: passes that search again with domains read from the decoded attractor,
    /// keeping the asset that decodes closest to the source; each costs one more search
    /// [default: from --speed, 0].
    #[arg(long)]
    pub(crate) attractor_passes: Option<u32>,
    /// Codec: FIS codecs take height fields, psa2d grey images and height fields; GeoJSON input
    /// is always `curve`, a mesh IFS3D. Default: `projected`; for a height field under a
    /// bounded rate (`--target-bpp B --bounded`, B = 0.8 unless given; or `--max-error E`),
    /// whose every cell is within the bound it answers; for an image under the rate
    /// (`--target-bpp B`, B = 0.75 unless given). With a flag only the quadtree reads
    /// (--tolerance, --transforms, --const-range, --roi, --speed, ...): `quadtree-pifs`, the
    /// seed's method. A flag the codec does not read is refused by name.
    #[arg(long, value_parser = codec_names())]
    pub(crate) codec: Option<String>,
    /// psa2d: touching or overlapping domains [default: overlapping].
    #[arg(long, value_enum)]
    pub(crate) domains: Option<DomainsArg>,
    /// psa2d: domain side in regions [default: 2].
    #[arg(long)]
    pub(crate) domain_ratio: Option<u32>,
    /// psa2d: domain search radius (regions, or domains when touching) [default: 8].
    #[arg(long)]
    pub(crate) radius: Option<u32>,
    /// FIS and psa2d: samples between interpolation points (ignored with --target-bpp, which
    /// picks it) [default: 8 for FIS, 4 for psa2d].
    #[arg(long)]
    pub(crate) spacing: Option<u32>,
    /// FIS: node height step in source units (default: the source's quantum).
    #[arg(long)]
    pub(crate) height_step: Option<f64>,
    /// Meshes: samples per side of the signed distance grid.
    #[arg(long, default_value_t = 64)]
    pub(crate) grid: usize,
    /// Meshes: half-width of the distance band in voxels (distances are clamped to it).
    #[arg(long, default_value_t = 4.0)]
    pub(crate) band: f64,
    /// FIS: bits of each vertical scaling [default: 6].
    #[arg(long)]
    pub(crate) scaling_bits: Option<u8>,
    /// Rasters: code in chunks of N x N cells (a power of two, 64 to 16384), each on its own,
    /// on every core, with overviews for coarse zooms; 0 never chunks. Default: chunks of
    /// 1024 for rasters over 2048 cells on a side, one operator for smaller ones.
    #[arg(long)]
    pub(crate) chunk: Option<u32>,
    /// Rasters in chunks: read and code only the I-th of N bands of the rows of chunks (N at
    /// most the rows of chunks) into the part file -o names, with the band's overview rows;
    /// `fractile assemble` codes the overviews and joins the N parts into the asset, the same
    /// bytes as one encode. Runs N processes or machines.
    #[arg(long, value_name = "I/N")]
    pub(crate) part: Option<String>,
    /// The grid GeoTIFF inputs are mosaicked on: that of this GeoTIFF (its CRS, cell size and
    /// alignment; a path or a URL), every input resampled onto it (bilinear, the area average
    /// where coarser) or reprojected. Default: the finest input's grid. (`--grid` is the
    /// volume's voxels.)
    #[arg(long, value_name = "GEOTIFF")]
    pub(crate) target_grid: Option<String>,
    /// Print JSON (and no progress).
    #[arg(long)]
    pub(crate) json: bool,
    /// No progress on stderr (by default a bar on a terminal, elsewhere a line every 10 s,
    /// for any encode that runs over a second).
    #[arg(long, short)]
    pub(crate) quiet: bool,
}

/// The flags only the quadtree PIFS reads (its options no other codec of the registry reads):
/// given any, a height field with no `--codec` is coded by the quadtree, as before the
/// projected default.
fn quadtree_only(option: &str) -> bool {
    let reads = |name: &str| CodecSettings::takes(name).is_some_and(|t| t.contains(&option));
    reads(QUADTREE)
        && !CodecSettings::names()
            .iter()
            .any(|&(name, _)| name != QUADTREE && reads(name))
}

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
    /// unless a quadtree-only flag is given, under a bounded rate for a height field, under
    /// the rate (default [`fractile_codec::codecs::projected::DEFAULT_IMAGE_BPP`]) for an
    /// image; `quadtree-pifs` with a quadtree-only flag.
    pub(crate) fn with_default_codec(mut self, kind: AssetKind) -> EncodeArgs {
        if self.codec.is_some() {
            return self;
        }
        let given = self.options().given();
        let projected = !given.iter().any(|o| quadtree_only(o));
        self.codec = Some(if projected { PROJECTED } else { QUADTREE }.to_string());
        if projected && kind == AssetKind::HeightField && self.max_error.is_none() {
            self.bounded = true;
            self.target_bpp = self
                .target_bpp
                .or(Some(fractile_codec::encode::DEFAULT_HEIGHT_FIELD_BPP));
        }
        self
    }

    /// The codec's name (decided by [`Self::with_default_codec`] for rasters).
    pub(crate) fn codec(&self) -> &str {
        self.codec.as_deref().unwrap_or(QUADTREE)
    }

    /// The one input of a kind that does not mosaic (a mesh, a GeoJSON file).
    pub(crate) fn input(&self) -> Result<&PathBuf> {
        match self.inputs.as_slice() {
            [one] => Ok(one),
            _ => bail!("only GeoTIFFs make a mosaic: give one mesh or GeoJSON file"),
        }
    }

    /// The codec options the flags give (`None` where a flag is not given: the codec's own
    /// default).
    pub(crate) fn options(&self) -> Options {
        Options {
            target_bpp: self.target_bpp,
            max_error: self.max_error,
            bounded: self.bounded,
            tolerance: self.tolerance,
            transforms: self.transforms,
            const_range: self.const_range,
            roi: self.roi.clone(),
            min_range: self.min_range,
            max_range: self.max_range,
            speed: self.speed,
            domain_step: self.domain_step,
            contrast_bits: self.contrast_bits,
            offset_bits: self.offset_bits,
            slope_bits: self.slope_bits,
            max_contrast: self.max_contrast,
            search: self.search.map(|s| match s {
                Search::Full => fractile_codec::encode::Search::Full,
                Search::Classified => fractile_codec::encode::Search::Classified,
                Search::Nearest => fractile_codec::encode::Search::Nearest,
            }),
            candidates: self.candidates,
            attractor_passes: self.attractor_passes,
            domains: self.domains.map(|d| match d {
                DomainsArg::Touching => Domains::Touching,
                DomainsArg::Overlapping => Domains::Overlapping,
            }),
            domain_ratio: self.domain_ratio,
            radius: self.radius,
            spacing: self.spacing,
            height_step: self.height_step,
            scaling_bits: self.scaling_bits,
        }
    }
}
