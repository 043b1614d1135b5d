//! `fractile`: encode rasters into fractal assets, decode them at any size, inspect and compare,
//! and serve them over HTTP (`fractile serve`). The command line only: the math is the codec's
//! (`fractile-codec`), the service the server library's (`fractile_server`).
//!
//! `encoding` holds the `encode` command, `decoding` the commands that decode (rasters, meshes,
//! curves); this file the command tree, `serve`, `info` and `compare`.

mod decoding;
mod encoding;
mod progress;
mod remote;

use decoding::*;
use encoding::*;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use fractile_codec::{Asset, Method, Raster};
use fractile_codec::{metrics, raster};
use fractile_proto::{AssetKind, SampleFormat};
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
    ///
    /// How long: the default DEM encode (bounded) takes about half a minute a million cells
    /// on two cores, an image under a second; an encode over a second shows its progress and
    /// an estimate of the time left on stderr (--quiet: none).
    Encode(EncodeArgs),
    /// Join the part files of an encode split with `encode --part I/N` into the asset, the
    /// overviews coded from the rows the parts hand on (the same bytes as the encode in one
    /// process).
    Assemble {
        /// Every part file, in any order (files, or `s3://bucket/key` objects).
        #[arg(required = true, num_args = 1..)]
        parts: Vec<PathBuf>,
        /// The asset to write (a file, or an `s3://bucket/key` object).
        #[arg(short, long)]
        output: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
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
        /// Directory of `.fra` assets, or an S3 bucket and prefix (`s3://bucket/prefix`; the
        /// endpoint and keys from AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY,
        /// AWS_REGION, AWS_ALLOW_HTTP).
        #[arg(long, env = "FRACTILE_ASSETS")]
        assets: Option<PathBuf>,
        /// Address to listen on [default: 127.0.0.1:8080].
        #[arg(long, env = "FRACTILE_BIND")]
        bind: Option<std::net::SocketAddr>,
        /// A `fractile.toml` with any of: assets, bind, public_url, write_token,
        /// allow_anonymous_writes, cache_control, rescan_seconds, disk_cache, disk_cache_mib,
        /// max_upload_mib, max_iterations, max_concurrent_requests, tile_cache_mib,
        /// coarse_cache_mib, chunk_cache_mib, prefetch_chunks, max_asset_pixels,
        /// max_decode_mib, backend, gpu_memory_mib, cesium_dir (docs/operations.md). Flags and
        /// environment variables override it.
        #[arg(long, env = "FRACTILE_CONFIG")]
        config: Option<PathBuf>,
        /// Public base URL for absolute links in TileJSON (behind a proxy).
        #[arg(long, env = "FRACTILE_PUBLIC_URL")]
        public_url: Option<String>,
        /// Bearer token that uploads and deletes need (from the environment, not argv, in
        /// production: argv is visible to other users).
        #[arg(long, env = "FRACTILE_WRITE_TOKEN", hide_env_values = true)]
        write_token: Option<String>,
        /// With no write token, let anyone upload and delete (a demo, a private network);
        /// without this flag such a server refuses writes with 403.
        #[arg(long, env = "FRACTILE_ALLOW_ANONYMOUS_WRITES")]
        allow_anonymous_writes: bool,
        /// Where continuous decoding runs: cpu, gpu or auto (the GPU for work of a tile or more
        /// on a hardware adapter); requests may override it with `backend=`.
        #[arg(long, env = "FRACTILE_BACKEND")]
        backend: Option<String>,
        /// A folder with CesiumJS's build (tools/fetch-cesium.sh): the viewer adds a globe.
        #[arg(long, env = "FRACTILE_CESIUM")]
        cesium: Option<PathBuf>,
        /// A folder with the browser's decoder (wasm/build.sh writes target/wasm-web): the
        /// viewer can decode the DEM in the browser, beside the server's tiles.
        #[arg(long, env = "FRACTILE_WASM")]
        wasm: Option<PathBuf>,
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

fn main() {
    // Mesa's Vulkan device-select layer orders adapters for programs that take the first one
    // (we choose ours), and prints "error: XDG_RUNTIME_DIR is invalid or not set" wherever
    // that variable is unset, which reads as our error. Off unless the user set it.
    if std::env::var_os("NODEVICE_SELECT").is_none() {
        // SAFETY: the first statement of main, before any thread exists (no runtime yet).
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
    let matches = <Cli as clap::CommandFactory>::command().get_matches();
    let cli =
        <Cli as clap::FromArgMatches>::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
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
        Command::Assemble {
            parts,
            output,
            json,
        } => run_assemble(&parts, &output, json),
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
            allow_anonymous_writes,
            backend,
            cesium,
            wasm,
        } => run_serve(
            assets,
            bind,
            config,
            public_url,
            (write_token, allow_anonymous_writes),
            (backend, cesium, wasm),
        ),
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
    (write_token, allow_anonymous_writes): (Option<String>, bool),
    (backend, cesium, wasm): (Option<String>, Option<PathBuf>, Option<PathBuf>),
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
    if cesium.is_some() {
        file.cesium_dir = cesium;
    }
    if wasm.is_some() {
        file.wasm_dir = wasm;
    }
    if allow_anonymous_writes {
        file.allow_anonymous_writes = Some(true);
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

fn run_info(path: &Path, as_json: bool) -> Result<()> {
    let asset = Asset::read(path)?;
    let bytes = std::fs::metadata(path).context("asset size")?.len();
    let m = &asset.meta;
    let ranges: usize = asset
        .planes()
        .iter()
        .map(|p| p.operator.transforms())
        .sum::<usize>()
        + asset.volume().map_or(0, |v| v.operator.leaves().len());
    // The file's own version (bytes 8-9), not this build's.
    let version = {
        let mut head = [0u8; 10];
        std::io::Read::read_exact(&mut std::fs::File::open(path)?, &mut head)?;
        u16::from_le_bytes([head[8], head[9]])
    };
    // A chunked asset's maps are its chunks': the encoder's count.
    let ranges = if asset.chunked().is_some() {
        m.stats.transforms as usize
    } else {
        ranges
    };
    let info = json!({
        "kind": format!("{:?}", m.kind), "width": m.width, "height": m.height, "channels": m.channels,
        "colour": format!("{:?}", m.colour), "sample": format!("{:?}", m.sample), "units": m.units,
        "value_range": [m.value_min, m.value_max], "nodata": m.nodata,
        "georef": m.georef.as_ref().map(|g| json!({"epsg": g.epsg, "origin": g.origin, "pixel_size": g.pixel_size})),
        "codec": asset.codec_name(), "format_version": version,
        "bytes": bytes, "source_bytes": m.source_bytes(), "ratio": m.source_bytes() as f64 / bytes as f64,
        "bpp": bytes as f64 * 8.0 / (m.width as f64 * m.height as f64),
        "transforms": ranges, "max_contrast": asset.max_contrast(),
        "error_bound_after_10_steps": asset.bound_after(10),
        "encoder": m.encoder,
        "encode_stats": {"rmse": m.stats.rmse, "psnr": m.stats.psnr, "max_error": m.stats.max_error, "seconds": m.stats.seconds},
    });
    let mut info = info;
    if let Some(c) = &asset.chunked() {
        let t = &c.table;
        info["chunks"] = json!({"chunk": t.chunk, "overlap": t.overlap,
            "levels": t.levels.iter().enumerate().map(|(i, l)| json!({"width": l.width, "height": l.height,
                "chunks": l.chunks.len(), "empty": l.chunks.iter().filter(|e| e.length == 0).count(),
                "view": t.is_view(i)}))
                .collect::<Vec<_>>()});
    }
    if let Some(c) = &asset.curves() {
        let h = &c.header;
        info["curve"] = json!({"polylines": h.rings.len(), "finest_level": c.set.finest(),
            "tolerance": h.tolerance, "metric": format!("{:?}", h.metric),
            "level_bounds": c.set.level_bounds, "subdivision": h.scheme.t, "details": h.scheme.u,
            "ratio_f64": 2.0 * m.source_bytes() as f64 / bytes as f64});
    }
    if let Some(v) = &asset.volume() {
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
