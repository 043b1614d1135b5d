//! `fractile`: encode rasters into fractal assets, decode them at any size, inspect and compare,
//! and serve them over HTTP (`fractile serve`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use fractile_codec::fis::FisSettings;
use fractile_codec::psa::{Domains, PsaSettings, Tiling};
use fractile_codec::{
    Asset, DiscreteOptions, EncodeSettings, Method, Quantiser, Raster, RateMode, Roi, SearchMode,
    encode, metrics, raster,
};
use fractile_proto::{AssetKind, SampleFormat};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde_json::json;

#[derive(Parser)]
#[command(
    name = "fractile",
    version,
    about = "Fractal (IFS) compression of images and terrain, decoded at any resolution"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Encode an image (PNG, JPEG), a height field (GeoTIFF, 16-bit PNG), a mesh (OFF, OBJ,
    /// PLY, STL: a signed distance volume, IFS3D) or curves (GeoJSON: projected IFS with
    /// details) into an asset.
    Encode(EncodeArgs),
    /// Decode a curve asset to GeoJSON at any level (one feature per input ring, in order).
    Curve(CurveArgs),
    /// Extract the surface of a volume asset as a mesh (OBJ, PLY or GLB by extension), at any
    /// resolution (above the encoded grid, the fractal adds detail) and any box.
    Mesh(MeshArgs),
    /// Decode an asset to PNG (images, 16-bit for height fields) or float32 GeoTIFF (height fields).
    Decode(DecodeArgs),
    /// Describe an asset.
    Info {
        /// The asset file.
        asset: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Serve assets over HTTP (tiles, points, regions); with no --assets, the built-in demo assets.
    Serve {
        /// Directory of `.fra` assets.
        #[arg(long, env = "FRACTILE_ASSETS")]
        assets: Option<PathBuf>,
        /// Address to listen on [default: 127.0.0.1:8080].
        #[arg(long, env = "FRACTILE_BIND")]
        bind: Option<std::net::SocketAddr>,
        /// A `fractile.toml` with any of: assets, bind, public_url, write_token, cache_control,
        /// max_upload_mib, max_iterations, max_concurrent_requests, tile_cache_mib, backend,
        /// gpu_memory_mib. Flags and environment variables override it.
        #[arg(long, env = "FRACTILE_CONFIG")]
        config: Option<PathBuf>,
        /// Public base URL for absolute links in TileJSON (behind a proxy).
        #[arg(long, env = "FRACTILE_PUBLIC_URL")]
        public_url: Option<String>,
        /// Bearer token that uploads and deletes need (from the environment, not argv, in
        /// production: argv is visible to other users).
        #[arg(long, env = "FRACTILE_WRITE_TOKEN", hide_env_values = true)]
        write_token: Option<String>,
        /// Where continuous decoding runs: cpu, gpu or auto (the GPU for work of a tile or more
        /// on a hardware adapter); requests may override it with `backend=`.
        #[arg(long, env = "FRACTILE_BACKEND")]
        backend: Option<String>,
    },
    /// Compare a decoded raster with its original: PSNR, RMSE, MAE, max error.
    Compare {
        /// The original raster.
        original: PathBuf,
        /// The decoded raster (same size).
        decoded: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
}

#[derive(clap::Args)]
struct CurveArgs {
    /// The curve asset.
    asset: PathBuf,
    /// Output GeoJSON file.
    #[arg(short, long)]
    output: PathBuf,
    /// Level: 0 is the coarsest, the default the input's finest; deeper levels continue the
    /// details self-similarly.
    #[arg(long)]
    level: Option<usize>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Clone, Copy, ValueEnum)]
enum Search {
    /// Every domain and isometry (slow; the reference).
    Full,
    /// Fisher's quadrant-brightness classes.
    Classified,
    /// Saupe's nearest-neighbour search on normalised block features.
    Nearest,
}

/// `--codec`: the closed set of codecs `encode` writes (names as the API spells them).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum CodecArg {
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
}

impl CodecArg {
    /// The layout of s of a FIS codec.
    fn fis_scaling(self) -> Option<fractile_codec::fis::Scaling> {
        use fractile_codec::fis::Scaling;
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
enum DomainsArg {
    /// Domains that tile the plane.
    Touching,
    /// Domains at every region corner.
    Overlapping,
}

#[derive(clap::Args)]
struct EncodeArgs {
    /// Input raster.
    input: PathBuf,
    /// Output asset file.
    #[arg(short, long)]
    output: PathBuf,
    /// Largest file size in bits per source pixel (rate control).
    #[arg(long, group = "rate")]
    target_bpp: Option<f64>,
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
    /// is always `curve`.
    #[arg(long, value_enum, default_value_t = CodecArg::QuadtreePifs)]
    codec: CodecArg,
    /// psa2d: touching or overlapping domains.
    #[arg(long, value_enum, default_value_t = DomainsArg::Overlapping)]
    domains: DomainsArg,
    /// psa2d: domain side in regions.
    #[arg(long, default_value_t = fractile_codec::psa::PsaSettings::default().ratio)]
    domain_ratio: u32,
    /// psa2d: domain search radius (regions, or domains when touching).
    #[arg(long, default_value_t = fractile_codec::psa::PsaSettings::default().radius)]
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
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct MeshArgs {
    /// The volume asset.
    asset: PathBuf,
    /// Output: .obj, .ply or .glb.
    #[arg(short, long)]
    output: PathBuf,
    /// Samples along the box's longest side [default: the encoded grid].
    #[arg(long)]
    resolution: Option<usize>,
    /// Box `x0,y0,z0,x1,y1,z1` in the mesh's units [default: the whole grid]; it may start
    /// with a minus sign (`--bbox -0.5,-0.5,-0.5,0,0,0.2`).
    #[arg(long, value_parser = parse_box3, allow_hyphen_values = true)]
    bbox: Option<([f64; 3], [f64; 3])>,
    /// Inverse steps of continuous decoding.
    #[arg(long, default_value_t = 16)]
    iterations: u32,
    /// Where the box is decoded: cpu, gpu (fails without an adapter), or auto (the GPU for a
    /// million samples or more when a hardware adapter exists, else the CPU).
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    backend: BackendArg,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

fn parse_box3(s: &str) -> Result<([f64; 3], [f64; 3]), String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>().map_err(|e| format!("{x:?}: {e}")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x0, y0, z0, x1, y1, z1] if x1 > x0 && y1 > y0 && z1 > z0 => {
            Ok(([x0, y0, z0], [x1, y1, z1]))
        }
        _ => Err("expected x0,y0,z0,x1,y1,z1 with max > min on every axis".into()),
    }
}

#[derive(clap::Args)]
struct DecodeArgs {
    /// The asset file.
    asset: PathBuf,
    /// Output: .png or .tif/.tiff (float32 GeoTIFF, height fields).
    #[arg(short, long)]
    output: PathBuf,
    /// Scale factor against the source size (any positive real).
    #[arg(long, conflicts_with_all = ["width", "height"])]
    scale: Option<f32>,
    /// Output width (height follows the aspect ratio unless given).
    #[arg(long)]
    width: Option<usize>,
    /// Output height.
    #[arg(long)]
    height: Option<usize>,
    /// Iterations (discrete) or inverse steps (continuous); default: until converged.
    #[arg(long)]
    iterations: Option<u32>,
    /// Window `u0,v0,u1,v1` of the unit square (default: all of it).
    #[arg(long, value_parser = parse_window)]
    window: Option<[f32; 4]>,
    /// Decoding method.
    #[arg(long, value_enum, default_value_t = MethodArg::Auto)]
    method: MethodArg,
    /// Where continuous decoding runs: cpu, gpu (fails without an adapter), or auto (the GPU
    /// for windows of a million pixels or more when an adapter exists, else the CPU).
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    backend: BackendArg,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum BackendArg {
    Cpu,
    Gpu,
    Auto,
}

#[derive(Clone, Copy, ValueEnum)]
enum MethodArg {
    Auto,
    Discrete,
    Continuous,
}

fn parse_roi(s: &str) -> Result<Roi, String> {
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

fn parse_window(s: &str) -> Result<[f32; 4], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|v| v.trim().parse::<f32>().map_err(|e| e.to_string()))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [a, b, c, d]
            if (0.0..=1.0).contains(&a)
                && (0.0..=1.0).contains(&b)
                && c > a
                && d > b
                && c <= 1.0
                && d <= 1.0 =>
        {
            Ok([a, b, c, d])
        }
        _ => Err("expected u0,v0,u1,v1 with 0 <= u0 < u1 <= 1 and 0 <= v0 < v1 <= 1".into()),
    }
}

fn main() {
    let cli = Cli::parse();
    // `fractile info x.fra | head` should end quietly as Unix tools do, not panic on the closed
    // pipe (Rust ignores SIGPIPE, rust-lang/rust#62569). Not for `serve`: a server must see
    // EPIPE on a socket whose peer left, not die of the signal.
    #[cfg(unix)]
    if !matches!(cli.command, Command::Serve { .. }) {
        // SAFETY: restores the default disposition before any thread or I/O exists.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    let result = match cli.command {
        Command::Encode(a) => run_encode(a),
        Command::Mesh(a) => run_mesh(a),
        Command::Curve(a) => run_curve(a),
        Command::Decode(a) => run_decode(a),
        Command::Info { asset, json } => run_info(&asset, json),
        Command::Compare {
            original,
            decoded,
            json,
        } => run_compare(&original, &decoded, json),
        Command::Serve {
            assets,
            bind,
            config,
            public_url,
            write_token,
            backend,
        } => run_serve(assets, bind, config, public_url, write_token, backend),
    };
    if let Err(e) = result {
        eprintln!("fractile: {e:#}");
        std::process::exit(1);
    }
}

fn run_serve(
    assets: Option<PathBuf>,
    bind: Option<std::net::SocketAddr>,
    config: Option<PathBuf>,
    public_url: Option<String>,
    write_token: Option<String>,
    backend: Option<String>,
) -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    let mut file = match &config {
        Some(p) => fractile_server::FileConfig::load(p)?,
        None => fractile_server::FileConfig::default(),
    };
    if backend.is_some() {
        file.backend = backend;
    }
    let opts = fractile_server::ServeOptions {
        assets: assets.or(file.assets.take()),
        bind: bind
            .or(file.bind)
            .unwrap_or_else(|| "127.0.0.1:8080".parse().expect("address")),
        public_url: public_url.or(file.public_url.take()),
        write_token: write_token.or(file.write_token.take()),
        file,
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    rt.block_on(fractile_server::serve(opts))
}

/// Whether a path names a mesh (by extension).
fn is_mesh(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["off", "obj", "ply", "stl"].contains(&e.to_ascii_lowercase().as_str()))
}

/// `fractile encode mesh.off --grid N [--tolerance T | --transforms N]`: IFS3D. The octree's
/// ranges are 4 to 16 voxels and its quantiser is its own (`octree::VolumeSettings`); the
/// raster flags of range sizes and bits do not apply.
fn encode_volume(a: &EncodeArgs) -> Result<()> {
    use fractile_codec::octree::Partition3;
    if a.target_bpp.is_some() || a.codec != CodecArg::QuadtreePifs {
        bail!("meshes take --grid, --band and --tolerance (voxels), --transforms or --const-range");
    }
    let mesh = fractile_codec::mesh::Mesh::read(&a.input)?;
    let mut s = fractile_codec::volume::MeshSettings {
        grid: a.grid,
        band: a.band,
        ..Default::default()
    };
    s.codec.partition = match (a.tolerance, a.transforms, a.const_range) {
        (Some(t), ..) if !(t.is_finite() && t > 0.0) => bail!("--tolerance {t} must be positive"),
        // Voxels -> normalised units: the field spans 2 band voxels.
        (Some(t), ..) => Partition3::Tolerance(t / (2.0 * a.band) as f32),
        (_, Some(n), _) => Partition3::Transforms(n),
        (.., Some(r)) => {
            let sizes: Vec<u32> = (0..s.codec.levels).map(|l| s.codec.min_size << l).collect();
            match sizes.iter().position(|&n| n == r) {
                Some(l) => Partition3::ConstRange(l),
                None => bail!("--const-range {r}: the octree's ranges are {sizes:?} voxels"),
            }
        }
        // 0.08 voxel RMS collage error: the bench's setting, past the seed's quality bars.
        _ => Partition3::Tolerance((0.08 / (2.0 * a.band)) as f32),
    };
    let name = a
        .input
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let enc = fractile_codec::volume::encode_mesh(&mesh, &s, &name)?;
    fractile_codec::asset::write_atomic(&a.output, &enc.bytes)?;
    let file_bytes = std::fs::metadata(&a.input).map(|m| m.len()).unwrap_or(0);
    let report = json!({
        "input": a.input, "output": a.output, "codec": enc.asset.codec_name(),
        "grid": enc.field.size, "band_voxels": a.band, "voxel": enc.field.voxel,
        "bytes": enc.bytes.len(), "ratio_i8": enc.ratio_i8(), "ratio_f32": enc.ratio_f32(),
        "ratio_mesh_file": file_bytes as f64 / enc.bytes.len() as f64,
        "transforms": enc.asset.meta.stats.transforms, "seconds": enc.seconds,
        "field_seconds": enc.field_seconds, "psnr": enc.psnr(), "rmse": enc.asset.meta.stats.rmse,
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{} -> {}: ifs3d-octree {}^3, {} bytes, {:.2}:1 against i8 ({:.2}:1 f32, {:.2}:1 the mesh file), {} maps, {:.2} s ({:.2} s distance field), PSNR {:.2} dB",
            a.input.display(),
            a.output.display(),
            enc.field.size,
            enc.bytes.len(),
            enc.ratio_i8(),
            enc.ratio_f32(),
            file_bytes as f64 / enc.bytes.len() as f64,
            enc.asset.meta.stats.transforms,
            enc.seconds,
            enc.field_seconds,
            enc.psnr()
        );
    }
    Ok(())
}

fn run_mesh(a: MeshArgs) -> Result<()> {
    let asset = Asset::read(&a.asset)?;
    let Some(volume) = &asset.volume else {
        bail!(
            "{} is not a volume asset (terrain meshes: the server's /v1/assets/{{id}}/mesh)",
            a.asset.display()
        );
    };
    let resolution = a.resolution.unwrap_or(volume.size());
    if !(2..=1024).contains(&resolution) {
        bail!("--resolution {resolution} must be 2..=1024");
    }
    let ext = a
        .output
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    if !["obj", "ply", "glb"].contains(&ext.as_str()) {
        bail!(
            "output {} must end in .obj, .ply or .glb",
            a.output.display()
        );
    }
    let started = Instant::now();
    let samples = resolution.pow(3);
    let gpu = match a.backend {
        BackendArg::Cpu => None,
        BackendArg::Gpu => Some(fractile_gpu::Gpu::new()?),
        BackendArg::Auto if samples >= 1 << 20 => match fractile_gpu::Gpu::new() {
            Ok(g) if !g.is_software() => Some(g),
            Ok(_) => None,
            Err(e) => {
                eprintln!("fractile: no GPU ({e}), decoding on the CPU");
                None
            }
        },
        BackendArg::Auto => None,
    };
    let device = match &gpu {
        Some(g) => Some((g, g.upload_volume(&volume.operator)?)),
        None => None,
    };
    let on_gpu = |lo, hi, dims: [usize; 3], n, t| {
        let (g, op) = device.as_ref()?;
        let v = g
            .volume_grid(op, lo, hi, dims.map(|d| d as u32), n, t)
            .ok()?;
        let bound = v.iter().fold(0.0f32, |m, p| m.max(p.error_bound));
        Some((v.into_iter().map(|p| p.value).collect(), bound))
    };
    let (mesh, bound) =
        asset.volume_mesh_with(a.bbox, resolution, a.iterations, 0.0, Some(&on_gpu))?;
    let body = match ext.as_str() {
        "obj" => mesh.to_obj(),
        "ply" => mesh.to_ply(),
        _ => mesh.to_glb(),
    };
    fractile_codec::asset::write_atomic(&a.output, &body)?;
    let report = json!({
        "output": a.output, "resolution": resolution, "vertices": mesh.positions.len(),
        "triangles": mesh.triangles.len(), "error_bound": bound, "seconds": started.elapsed().as_secs_f64(),
        "backend": if device.is_some() { "gpu" } else { "cpu" },
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{}: {} vertices, {} triangles at resolution {resolution}, distance error bound {bound:.3e}, {:.2} s",
            a.output.display(),
            mesh.positions.len(),
            mesh.triangles.len(),
            started.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

/// Whether a path names GeoJSON (by extension).
fn is_geojson(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["geojson", "json"].contains(&e.to_ascii_lowercase().as_str()))
}

/// `fractile encode coast.geojson -o coast.fra [--codec curve] [--tolerance T]`.
fn encode_curve(a: &EncodeArgs) -> Result<()> {
    if ![CodecArg::Curve, CodecArg::QuadtreePifs].contains(&a.codec)
        || a.target_bpp.is_some()
        || a.transforms.is_some()
        || a.const_range.is_some()
    {
        bail!("GeoJSON takes --codec curve and --tolerance (degrees of arc; 0 keeps every detail)");
    }
    let tolerance = f64::from(a.tolerance.unwrap_or(0.0));
    if !(tolerance.is_finite() && tolerance >= 0.0) {
        bail!("--tolerance {tolerance} must be a distance >= 0");
    }
    let text = std::fs::read_to_string(&a.input)
        .with_context(|| format!("reading {}", a.input.display()))?;
    let lines = fractile_codec::curve::geojson::read(&text).map_err(|e| anyhow::anyhow!(e))?;
    let settings = fractile_codec::curve::CurveSettings {
        tolerance,
        ..Default::default()
    };
    let name = a
        .input
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let enc = fractile_codec::curve::encode_asset(&lines, &settings, &name)?;
    fractile_codec::asset::write_atomic(&a.output, &enc.bytes)?;
    let set = &enc.asset.curve.as_ref().expect("a curve asset").set;
    let m = &enc.asset.meta;
    let report = json!({
        "input": a.input, "output": a.output, "codec": enc.asset.codec_name(),
        "polylines": set.rings.len(), "points": enc.points, "bytes": enc.bytes.len(),
        "ratio_f64": (enc.points * 16) as f64 / enc.bytes.len() as f64,
        "ratio_f32": (enc.points * 8) as f64 / enc.bytes.len() as f64,
        "tolerance_degrees": tolerance,
        "tolerance_m": tolerance * fractile_codec::curve::METRES_PER_DEGREE,
        "hausdorff_m": m.stats.max_error * fractile_codec::curve::METRES_PER_DEGREE,
        "finest_level": set.finest(), "fit": enc.fit, "seconds": m.stats.seconds,
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{} -> {}: {} polylines, {} points, {} bytes ({:.2}:1 vs float32, {:.2}:1 vs float64), Hausdorff distance to the source {:.0} m, {} levels, {:.2} s",
            a.input.display(),
            a.output.display(),
            set.rings.len(),
            enc.points,
            enc.bytes.len(),
            report["ratio_f32"].as_f64().unwrap_or(0.0),
            report["ratio_f64"].as_f64().unwrap_or(0.0),
            report["hausdorff_m"].as_f64().unwrap_or(0.0),
            set.finest(),
            m.stats.seconds
        );
    }
    Ok(())
}

/// `fractile curve coast.fra -o out.geojson [--level N]`.
fn run_curve(a: CurveArgs) -> Result<()> {
    let asset = Asset::read(&a.asset)?;
    let Some(c) = &asset.curve else {
        bail!(
            "{} is not a curve asset (it is {:?})",
            a.asset.display(),
            asset.meta.kind
        );
    };
    let finest = c.set.finest();
    let level = a.level.unwrap_or(finest);
    // Each level doubles the points: refuse what would not fit in memory before decoding.
    if c.set.points_at(level) > 1 << 26 {
        bail!("level {level} would have over 2^26 points (the finest is {finest})");
    }
    let decoded = c.set.at_level(level);
    let units = asset.meta.units.clone().unwrap_or_default();
    let doc = fractile_codec::curve::geojson::write(&decoded, finest, &units);
    let text = serde_json::to_vec(&doc)?;
    fractile_codec::asset::write_atomic(&a.output, &text)?;
    let points: usize = decoded.lines.iter().map(Vec::len).sum();
    let report = json!({"output": a.output, "level": level, "finest_level": finest,
        "polylines": decoded.lines.len(), "points": points, "error_bound": decoded.error_bound,
        "units": units});
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{} -> {}: level {level} of {finest}, {} polylines, {points} points, error bound {} {units}",
            a.asset.display(),
            a.output.display(),
            decoded.lines.len(),
            decoded.error_bound
        );
    }
    Ok(())
}

fn run_encode(a: EncodeArgs) -> Result<()> {
    if is_mesh(&a.input) {
        return encode_volume(&a);
    }
    if is_geojson(&a.input) || a.codec == CodecArg::Curve {
        return encode_curve(&a);
    }
    let raster = Raster::open(&a.input)?;
    let lattice = |a: &EncodeArgs| {
        if a.tolerance.is_some() || a.transforms.is_some() || a.const_range.is_some() {
            bail!("--codec {} takes --spacing or --target-bpp", a.codec.name());
        }
        Ok(())
    };
    let enc = if a.codec == CodecArg::QuadtreePifs {
        encode_quadtree(&a, &raster)?
    } else if let Some(tiling) = a.codec.psa_tiling() {
        lattice(&a)?;
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
        fractile_codec::encode::encode_psa(&raster, &settings, a.target_bpp)?
    } else {
        let Some(scaling) = a.codec.fis_scaling() else {
            bail!("--codec curve is for GeoJSON input");
        };
        lattice(&a)?;
        let settings = FisSettings {
            scaling,
            spacing: a.spacing,
            height_step: a.height_step,
            scaling_bits: a.scaling_bits,
            max_scaling: a.max_contrast,
        };
        fractile_codec::encode::encode_fis(&raster, &settings, a.target_bpp)?
    };
    fractile_codec::asset::write_atomic(&a.output, &enc.bytes)?;
    let report = json!({
        "input": a.input, "output": a.output, "codec": enc.asset.codec_name(),
        "bytes": enc.bytes.len(), "source_bytes": enc.asset.meta.source_bytes(),
        "ratio": enc.ratio(), "bpp": enc.bpp(), "transforms": enc.transforms,
        "seconds": enc.seconds, "psnr": enc.errors.psnr, "rmse": enc.errors.rmse,
        "max_error": enc.errors.max_error,
    });
    if a.json {
        println!("{report}");
    } else {
        println!(
            "{} -> {}: {} {} bytes, {:.2}:1, {:.3} bpp, {} transforms, {:.2} s, PSNR {:.2} dB, RMSE {:.3}",
            a.input.display(),
            a.output.display(),
            enc.asset.codec_name(),
            enc.bytes.len(),
            enc.ratio(),
            enc.bpp(),
            enc.transforms,
            enc.seconds,
            enc.errors.psnr,
            enc.errors.rmse
        );
    }
    Ok(())
}

fn encode_quadtree(a: &EncodeArgs, raster: &Raster) -> Result<fractile_codec::Encoded> {
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
    // The bar appears only once an encode has run for a second (short encodes stay quiet).
    let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::hidden());
    bar.set_style(
        ProgressStyle::with_template("{spinner} fitting blocks {bar:30} {pos}/{len} {elapsed}")
            .expect("template"),
    );
    let started = Instant::now();
    let shown = std::sync::atomic::AtomicBool::new(false);
    let progress = |done: u64, total: u64| {
        bar.set_length(total);
        bar.set_position(done);
        if !a.json
            && started.elapsed().as_secs_f32() > 1.0
            && !shown.swap(true, std::sync::atomic::Ordering::Relaxed)
        {
            bar.set_draw_target(ProgressDrawTarget::stderr());
        }
    };
    let enc = encode(raster, &settings, &progress)?;
    bar.finish_and_clear();
    Ok(enc)
}

fn run_decode(a: DecodeArgs) -> Result<()> {
    let asset = Asset::read(&a.asset)?;
    if asset.volume.is_some() {
        bail!(
            "{} is a volume: extract its surface with `fractile mesh`",
            a.asset.display()
        );
    }
    if asset.curve.is_some() {
        bail!(
            "{} holds curves: decode them to GeoJSON with `fractile curve {} -o out.geojson`",
            a.asset.display(),
            a.asset.display()
        );
    }
    let (sw, sh) = (asset.meta.width as f32, asset.meta.height as f32);
    let window = a.window.unwrap_or([0.0, 0.0, 1.0, 1.0]);
    let (ww, wh) = ((window[2] - window[0]) * sw, (window[3] - window[1]) * sh);
    let (width, height) = match (a.scale, a.width, a.height) {
        (Some(s), ..) if s > 0.0 && s.is_finite() => {
            ((ww * s).round() as usize, (wh * s).round() as usize)
        }
        (Some(s), ..) => bail!("scale {s} must be a positive number"),
        (None, Some(w), Some(h)) => (w, h),
        (None, Some(w), None) => (w, (w as f32 * wh / ww).round() as usize),
        (None, None, Some(h)) => ((h as f32 * ww / wh).round() as usize, h),
        (None, None, None) => (ww.round() as usize, wh.round() as usize),
    };
    const MAX_PIXELS: usize = 1 << 28;
    if width == 0 || height == 0 || width.saturating_mul(height) > MAX_PIXELS {
        bail!("output size {width}x{height} must be at least 1x1 and at most {MAX_PIXELS} pixels");
    }
    let started = Instant::now();
    let method = match a.method {
        MethodArg::Auto => Method::Auto,
        MethodArg::Discrete => Method::Discrete,
        MethodArg::Continuous => Method::Continuous,
    };
    // The GPU runs continuous decoding: asked for, or (auto) a continuous-capable request of a
    // million pixels or more, where the transfer pays for itself.
    let wants_gpu = match a.backend {
        BackendArg::Cpu => false,
        BackendArg::Gpu => true,
        BackendArg::Auto => method != Method::Discrete && width * height >= 1 << 20,
    };
    let gpu = if wants_gpu {
        match fractile_gpu::Gpu::new() {
            Ok(g) => Some(g),
            Err(e) if a.backend == BackendArg::Auto => {
                eprintln!("{e}: decoding on the CPU");
                None
            }
            Err(e) => return Err(e.into()),
        }
    } else {
        None
    };
    let (decoded, used, backend) = if let Some(g) = &gpu {
        // As many steps as the CPU's continuous window takes by default.
        let n = a.iterations.unwrap_or(12);
        let mut planes = Vec::new();
        for p in &asset.planes {
            let dev = g.upload(&fractile_codec::pieces::Flatten::pieces(&p.operator))?;
            let grid = fractile_gpu::Grid::Window {
                rect: window,
                width: width as u32,
                height: height as u32,
            };
            planes.push(
                g.grid(&dev, grid, n, 0.0)?
                    .into_iter()
                    .map(|v| v.value)
                    .collect(),
            );
        }
        let d = asset.window_from_planes(window, width, height, planes);
        (d, Method::Continuous, g.adapter())
    } else if a.window.is_none() && method != Method::Continuous {
        let opts = a.iterations.map(DiscreteOptions::fixed).unwrap_or_default();
        (
            asset.decode(width, height, opts).0,
            Method::Discrete,
            "CPU".into(),
        )
    } else {
        let (d, m) = asset.window(window, width, height, a.iterations, method);
        (d, m, "CPU".into())
    };
    write_decoded(&asset, &decoded, window, &a.output)?;
    eprintln!(
        "decoded {}x{} ({used:?}, {backend}) in {:.1} ms -> {}",
        width,
        height,
        started.elapsed().as_secs_f64() * 1e3,
        a.output.display()
    );
    Ok(())
}

fn write_decoded(
    asset: &Asset,
    d: &fractile_codec::extract::Decoded,
    window: [f32; 4],
    out: &Path,
) -> Result<()> {
    let ext = out
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let m = &asset.meta;
    match (ext.as_str(), m.kind) {
        ("tif" | "tiff", AssetKind::HeightField) => {
            let georef = m.georef.as_ref().map(|g| {
                let sx = (window[2] - window[0]) as f64 * m.width as f64 / d.width as f64;
                let sy = (window[3] - window[1]) as f64 * m.height as f64 / d.height as f64;
                fractile_proto::Georef {
                    epsg: g.epsg,
                    origin: [
                        g.origin[0] + window[0] as f64 * m.width as f64 * g.pixel_size[0],
                        g.origin[1] + window[1] as f64 * m.height as f64 * g.pixel_size[1],
                    ],
                    pixel_size: [g.pixel_size[0] * sx, g.pixel_size[1] * sy],
                }
            });
            let nodata = m.nodata.unwrap_or(f64::NAN);
            let values: Vec<f32> = d.channels[0]
                .iter()
                .map(|&v| if v.is_nan() { nodata as f32 } else { v })
                .collect();
            raster::write_geotiff_f32(
                out,
                d.width,
                d.height,
                &values,
                georef.as_ref(),
                asset.mask.as_ref().map(|_| nodata),
            )?;
        }
        ("tif" | "tiff", _) => bail!("GeoTIFF output is for height fields; write a .png"),
        ("png", AssetKind::HeightField) => {
            // U16 sources keep their own values; others map the value range onto 0..=65535.
            let (lo, span) = (m.value_min as f32, (m.value_max - m.value_min) as f32);
            let values: Vec<f32> = d.channels[0]
                .iter()
                .map(|&v| match (v.is_nan(), m.sample) {
                    (true, _) => 0.0,
                    (false, SampleFormat::U16) => v,
                    _ => (v - lo) / span * 65535.0,
                })
                .collect();
            raster::write_png16(out, d.width, d.height, &values)?;
        }
        ("png", _) => raster::write_png8(out, d.width, d.height, &d.channels)?,
        _ => bail!("unknown output type {:?}: use .png or .tif", out.display()),
    }
    Ok(())
}

fn run_info(path: &Path, as_json: bool) -> Result<()> {
    let asset = Asset::read(path)?;
    let bytes = std::fs::metadata(path).context("asset size")?.len();
    let m = &asset.meta;
    let ranges: usize = asset
        .planes
        .iter()
        .map(|p| p.operator.transforms())
        .sum::<usize>()
        + asset
            .volume
            .as_ref()
            .map_or(0, |v| v.operator.leaves().len());
    let info = json!({
        "kind": format!("{:?}", m.kind), "width": m.width, "height": m.height, "channels": m.channels,
        "colour": format!("{:?}", m.colour), "sample": format!("{:?}", m.sample), "units": m.units,
        "value_range": [m.value_min, m.value_max], "nodata": m.nodata,
        "georef": m.georef.as_ref().map(|g| json!({"epsg": g.epsg, "origin": g.origin, "pixel_size": g.pixel_size})),
        "codec": asset.codec_name(), "format_version": fractile_codec::asset::FORMAT_VERSION,
        "bytes": bytes, "source_bytes": m.source_bytes(), "ratio": m.source_bytes() as f64 / bytes as f64,
        "bpp": bytes as f64 * 8.0 / (m.width as f64 * m.height as f64),
        "transforms": ranges, "max_contrast": asset.max_contrast(),
        "error_bound_after_10_steps": asset.bound_after(10),
        "encoder": m.encoder,
        "encode_stats": {"rmse": m.stats.rmse, "psnr": m.stats.psnr, "max_error": m.stats.max_error, "seconds": m.stats.seconds},
    });
    let mut info = info;
    if let Some(c) = &asset.curve {
        let h = &c.header;
        info["curve"] = json!({"polylines": h.rings.len(), "finest_level": c.set.finest(),
            "tolerance": h.tolerance, "metric": format!("{:?}", h.metric),
            "level_bounds": c.set.level_bounds, "subdivision": h.scheme.t, "details": h.scheme.u,
            "ratio_f64": 2.0 * m.source_bytes() as f64 / bytes as f64});
    }
    if let Some(v) = &asset.volume {
        let (lo, hi) = v.bounds();
        info["volume"] = json!({"grid": v.size(), "bounds": [lo, hi], "voxel": v.placement.voxel,
            "band": m.value_max, "ratio_f32": 4.0 * m.source_bytes() as f64 / bytes as f64});
    }
    if as_json {
        println!("{info:#}");
    } else {
        for (k, v) in info.as_object().expect("object") {
            println!("{k:>28}: {v}");
        }
    }
    Ok(())
}

fn run_compare(original: &Path, decoded: &Path, as_json: bool) -> Result<()> {
    let a = Raster::open(original)?;
    let b = Raster::open(decoded)?;
    if (a.width, a.height, a.channels.len()) != (b.width, b.height, b.channels.len()) {
        bail!(
            "sizes differ: {}x{}x{} vs {}x{}x{}",
            a.width,
            a.height,
            a.channels.len(),
            b.width,
            b.height,
            b.channels.len()
        );
    }
    let peak = match (a.kind, a.sample) {
        (AssetKind::Image, SampleFormat::U8) => 255.0,
        (AssetKind::Image, SampleFormat::U16) => 65535.0,
        _ => {
            let (lo, hi) = a.value_range();
            (hi - lo).max(f64::MIN_POSITIVE)
        }
    };
    let e = metrics::compare(&a.channels, &b.channels, a.valid.as_deref(), peak);
    if as_json {
        println!(
            "{}",
            json!({"psnr": e.psnr, "rmse": e.rmse, "mae": e.mae, "max_error": e.max_error, "peak": peak, "samples": e.samples})
        );
    } else {
        println!(
            "PSNR {:.3} dB (peak {peak}), RMSE {:.4}, MAE {:.4}, max error {:.4}, {} samples",
            e.psnr, e.rmse, e.mae, e.max_error, e.samples
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The CLI's codec names are the codec crate's own (what `info` and the API report).
    #[test]
    fn codec_names_are_the_codecs_own() {
        for c in CodecArg::value_variants() {
            if let Some(s) = c.fis_scaling() {
                assert_eq!(c.name(), fractile_codec::fis::codec_name(s));
            }
            if let Some(t) = c.psa_tiling() {
                assert_eq!(c.name(), fractile_codec::psa::codec_name(t));
            }
        }
        assert_eq!(CodecArg::QuadtreePifs.name(), "quadtree-pifs");
        assert_eq!(CodecArg::Curve.name(), "curve");
    }
}
