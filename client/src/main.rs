//! `fractile-client`: the command line of the thin client. Every command takes `--server URL`
//! (or `FRACTILE_SERVER`) and `--json` for machine-readable output.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use fractile_client::refine::{RefineOptions, Step, Stop};
use fractile_client::view::{Camera, PlanLimits};
use fractile_client::{
    Client, MeshFormat, MeshRequest, PointsEncoding, PointsRequest, RegionFormat, RegionRequest,
    TileAddress, TileEncoding, TileRequest, bench,
};
use serde_json::json;

#[derive(Parser)]
#[command(
    name = "fractile-client",
    version,
    about = "Thin client of a fractile server"
)]
struct Cli {
    /// Base URL of the server.
    #[arg(
        long,
        global = true,
        env = "FRACTILE_SERVER",
        default_value = "http://127.0.0.1:8080"
    )]
    server: String,
    /// Bearer token for upload and delete.
    #[arg(
        long,
        global = true,
        env = "FRACTILE_WRITE_TOKEN",
        hide_env_values = true
    )]
    token: Option<String>,
    /// Ask the server to decode on cpu, gpu or auto (default: the server's setting).
    #[arg(long, global = true)]
    backend: Option<fractile_client::Backend>,
    /// Print machine-readable JSON (with --refine: one object per step).
    #[arg(long, global = true)]
    json: bool,
    /// On an error, print its whole chain and a backtrace (where `RUST_BACKTRACE` asks for one)
    /// instead of the one line that says what went wrong.
    #[arg(short, long, global = true)]
    verbose: bool,
    #[command(subcommand)]
    command: Command,
}

/// Options of progressive refinement.
#[derive(Args, Clone)]
struct RefineArgs {
    /// Ask for 1, 2, 3, ... iterations until the answer settles; write every step.
    #[arg(long)]
    refine: bool,
    /// With --refine: stop once the convergence bound (the distance to the fractal's
    /// attractor, which more iterations shrink) is at most this, value units. The error bound
    /// against the source does not shrink with iterations, so refinement never stops on it.
    #[arg(long)]
    tolerance: Option<f32>,
    /// With --refine: stop once the mean change is at most this fraction of the value range.
    #[arg(long, default_value_t = 0.002)]
    change: f32,
    /// With --refine: time budget in milliseconds.
    #[arg(long)]
    budget_ms: Option<u64>,
    /// With --refine: iterations to ask for, e.g. 1,2,4,8 (default 1,2,...,64).
    #[arg(long, value_delimiter = ',')]
    schedule: Option<Vec<u32>>,
    /// Exactly this many iterations (without --refine).
    #[arg(long, conflicts_with = "refine")]
    iterations: Option<u32>,
}

impl RefineArgs {
    fn options(&self) -> RefineOptions {
        let d = RefineOptions::default();
        RefineOptions {
            tolerance: self.tolerance,
            change: self.change,
            budget: self.budget_ms.map(Duration::from_millis),
            schedule: self.schedule.clone().unwrap_or(d.schedule),
        }
    }
}

#[derive(Subcommand)]
enum Command {
    /// List the assets.
    Assets,
    /// Show one asset.
    Info { id: String },
    /// Upload an asset file made by `fractile encode`.
    Upload {
        file: PathBuf,
        #[arg(long)]
        id: String,
    },
    /// Delete an asset.
    Delete { id: String },
    /// Fetch a tile.
    Tile(TileArgs),
    /// The value at one point (lon lat, or x y in unit coordinates with --unit).
    Point(PointArgs),
    /// Values at the points of a CSV file (two columns: lon,lat or x,y; a header is skipped).
    Points(PointsArgs),
    /// A window sampled on a grid.
    Region(RegionArgs),
    /// A terrain mesh.
    Mesh(MeshArgs),
    /// View-dependent fetch: tiles of a region chosen by distance from a camera, nearest first.
    View(ViewArgs),
    /// Load test: each kind for --duration at --concurrency; prints a table per kind.
    Bench(BenchArgs),
}

/// Arguments of `tile`.
#[derive(Args)]
struct TileArgs {
    id: String,
    z: u8,
    x: u32,
    y: u32,
    /// Output file.
    #[arg(short, long)]
    output: PathBuf,
    /// png (visual), terrarium, terrainrgb, gray16 or f32 (default: f32 when the output
    /// ends in .f32, png otherwise).
    #[arg(long)]
    encoding: Option<String>,
    /// 256 or 512.
    #[arg(long, default_value_t = 256)]
    tile_size: u32,
    /// Terrain-RGB and Terrarium tiles: `bound` rounds heights to what the tile's error
    /// bound justifies (smaller PNGs; the server's default), `full` keeps every 0.1 m or
    /// 1/256 m. `--refine` always asks for full precision.
    #[arg(long)]
    precision: Option<String>,
    #[command(flatten)]
    refine: RefineArgs,
}

/// Arguments of `point`.
#[derive(Args)]
struct PointArgs {
    id: String,
    #[arg(allow_hyphen_values = true)]
    lon: f64,
    #[arg(allow_hyphen_values = true)]
    lat: f64,
    /// The coordinates are unit x, y (any asset), not lon, lat.
    #[arg(long)]
    unit: bool,
    #[arg(long)]
    iterations: Option<u32>,
}

/// Arguments of `points`.
#[derive(Args)]
struct PointsArgs {
    id: String,
    file: PathBuf,
    /// Write a CSV of the answers here (default: standard output).
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Send the batch in the binary encoding.
    #[arg(long)]
    binary: bool,
    #[command(flatten)]
    refine: RefineArgs,
}

/// Arguments of `region`.
#[derive(Args)]
struct RegionArgs {
    id: String,
    /// minx,miny,maxx,maxy (lon/lat, or unit coordinates).
    #[arg(long, allow_hyphen_values = true)]
    bbox: String,
    #[arg(long, default_value_t = 512)]
    width: u32,
    #[arg(long, default_value_t = 512)]
    height: u32,
    /// png, f32 or tif.
    #[arg(long, default_value = "png")]
    format: RegionFormat,
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    refine: RefineArgs,
}

/// Arguments of `mesh`.
#[derive(Args)]
struct MeshArgs {
    id: String,
    #[arg(long, allow_hyphen_values = true)]
    bbox: Option<String>,
    /// Vertices a side.
    #[arg(long)]
    resolution: Option<u32>,
    /// glb, obj or ply.
    #[arg(long, default_value = "glb")]
    format: MeshFormat,
    #[arg(long)]
    iterations: Option<u32>,
    /// An adaptive triangulation within this many height units of the decoded grid.
    #[arg(long)]
    max_error: Option<f32>,
    #[arg(short, long)]
    output: PathBuf,
}

/// Arguments of `view`.
#[derive(Args)]
struct ViewArgs {
    id: String,
    /// lon,lat,height (metres above sea level).
    #[arg(long, allow_hyphen_values = true)]
    camera: String,
    /// west,south,east,north (default: the asset's bounds).
    #[arg(long, allow_hyphen_values = true)]
    bbox: Option<String>,
    /// Allowed screen-space error in pixels.
    #[arg(long, default_value_t = 1.0)]
    pixel_error: f64,
    /// Most tiles.
    #[arg(long, default_value_t = 256)]
    max_tiles: usize,
    /// Requests in flight.
    #[arg(long, default_value_t = 8)]
    concurrency: usize,
    /// png, terrarium, terrainrgb, gray16 or f32.
    #[arg(long, default_value = "terrarium")]
    encoding: String,
    /// Only print the plan.
    #[arg(long)]
    plan_only: bool,
    /// Write the tiles under this folder as Z/X/Y.ext.
    #[arg(short, long)]
    output: Option<PathBuf>,
}

/// Arguments of `bench`.
#[derive(Args)]
struct BenchArgs {
    #[arg(long, default_value = "jacksboro")]
    asset: String,
    #[arg(long, default_value_t = 16)]
    concurrency: usize,
    /// Seconds per kind.
    #[arg(long, default_value_t = 10.0)]
    duration: f64,
    /// Kinds, in order: tiles-cold, tiles-warm, terrain-cold (Cesium terrain; skipped for
    /// assets that are not georeferenced height fields), points, regions.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "tiles-cold,tiles-warm,terrain-cold,points,regions"
    )]
    kinds: Vec<String>,
    /// Points per batch.
    #[arg(long, default_value_t = 1000)]
    batch: usize,
    /// Encoding of a height field's tiles (terrarium, terrainrgb, gray16, f32, png); pictures'
    /// tiles are PNGs whatever this says.
    #[arg(long, default_value = "terrarium")]
    encoding: String,
}

fn parse_numbers<const N: usize>(s: &str, what: &str) -> Result<[f64; N]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("{what} {s:?}: not numbers"))?;
    v.try_into()
        .map_err(|_| anyhow::anyhow!("{what} {s:?}: expected {N} comma-separated numbers"))
}

fn encoding(name: &str) -> Result<TileEncoding> {
    TileEncoding::parse(name).with_context(|| {
        format!("unknown encoding {name:?} (png, terrarium, terrainrgb, gray16, f32)")
    })
}

/// `out.png` -> `out.step03.png`.
fn step_path(out: &Path, step: usize) -> PathBuf {
    let stem = out.file_stem().and_then(|s| s.to_str()).unwrap_or("out");
    let name = match out.extension().and_then(|e| e.to_str()) {
        Some(ext) => format!("{stem}.step{step:02}.{ext}"),
        None => format!("{stem}.step{step:02}"),
    };
    out.with_file_name(name)
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

/// Refinement steps of a file answer (tiles, regions): each written beside the output as it
/// arrives (`out.step01.png`, ...) and printed, the last also written to the output itself.
struct StepFiles<'a> {
    output: &'a Path,
    json: bool,
    failed: Option<anyhow::Error>,
}

impl<'a> StepFiles<'a> {
    fn new(output: &'a Path, json: bool) -> StepFiles<'a> {
        print_head(json);
        StepFiles {
            output,
            json,
            failed: None,
        }
    }

    /// Writes and prints a step; the first write error is kept for `finish`.
    fn step<T>(&mut self, s: &Step<T>, body: &[u8]) {
        if let Err(e) = write(&step_path(self.output, s.step), body) {
            self.failed.get_or_insert(e);
        }
        print_step(self.json, s);
    }

    fn finish(self, last: &[u8], stop: Stop) -> Result<()> {
        if let Some(e) = self.failed {
            return Err(e);
        }
        write(self.output, last)?;
        print_stop(self.json, stop);
        Ok(())
    }
}

/// "convergence bound C, error bound E" (or "error bound unknown" for an asset without a
/// source-error map).
fn bound_words(convergence: f32, error: Option<f32>) -> String {
    match error {
        Some(e) => format!("convergence bound {convergence}, error bound {e}"),
        None => format!("convergence bound {convergence}, error bound unknown"),
    }
}

/// Prints one refinement step as it arrives: a table row, or one JSON object per line (the
/// last carries why it is the last in `stop`; the others have `stop: null`).
fn print_step<T>(json: bool, s: &Step<T>) {
    let ms = s.elapsed.as_secs_f64() * 1e3;
    if json {
        println!(
            "{}",
            json!({"step": s.step, "iterations": s.iterations, "convergence_bound": s.convergence_bound,
                   "mean_change": s.mean_change, "ms": ms, "stop": s.stop})
        );
    } else {
        let change = s.mean_change.map_or("-".to_string(), |c| format!("{c:.4}"));
        println!(
            "| {} | {} | {:.4} | {change} | {ms:.1} |",
            s.step, s.iterations, s.convergence_bound
        );
    }
}

fn print_head(json: bool) {
    if !json {
        println!(
            "| step | iterations | convergence bound | mean change | ms |\n|---|---|---|---|---|"
        );
    }
}

fn print_stop(json: bool, stop: Stop) {
    if !json {
        let why = match stop {
            Stop::Bound => "the convergence bound reached the tolerance",
            Stop::Converged => "the answer stopped changing",
            Stop::Budget => "the time budget ran out",
            Stop::Schedule => "the schedule ended",
        };
        println!("stopped: {why}");
    }
}

fn read_points(path: &Path) -> Result<Vec<[f64; 2]>> {
    let mut r = csv::ReaderBuilder::new()
        .has_headers(false)
        .trim(csv::Trim::All)
        .from_path(path)
        .with_context(|| format!("reading {}", path.display()))?;
    let mut out = Vec::new();
    for (k, rec) in r.records().enumerate() {
        let rec = rec.with_context(|| format!("{}: row {}", path.display(), k + 1))?;
        let nums: Option<Vec<f64>> = rec.iter().take(2).map(|f| f.parse().ok()).collect();
        match nums {
            Some(v) if v.len() == 2 => out.push([v[0], v[1]]),
            // A first row that is not numbers is a header.
            _ if k == 0 => {}
            _ => bail!("{}: row {} is not two numbers", path.display(), k + 1),
        }
    }
    Ok(out)
}

fn points_csv(resp: &fractile_client::PointsResponse) -> String {
    let channels = resp
        .results
        .iter()
        .filter_map(|r| r.values.as_ref().map(Vec::len))
        .max()
        .unwrap_or(1);
    let mut s = String::from("x,y");
    for c in 0..channels {
        s += &format!(",value{c}");
    }
    s += ",error_bound,iterations\n";
    for r in &resp.results {
        s += &format!("{},{}", r.coordinates[0], r.coordinates[1]);
        for c in 0..channels {
            let v = r.values.as_ref().and_then(|v| v.get(c).copied().flatten());
            s += &v.map_or(",".into(), |v| format!(",{v}"));
        }
        s += &r.error_bound.map_or(",".into(), |b| format!(",{b}"));
        s += &format!(",{}\n", r.iterations);
    }
    s
}

fn main() -> std::process::ExitCode {
    // Rust ignores SIGPIPE, so `fractile-client ... | head` would panic on the closed pipe; a
    // command-line tool should just stop, as every Unix tool does (rust-lang/rust#62569).
    #[cfg(unix)]
    // SAFETY: restores the default disposition before any thread or I/O exists (the runtime
    // is built below).
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    let verbose = cli.verbose;
    let result = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(anyhow::Error::from)
        .and_then(|rt| rt.block_on(run(cli)));
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // One line by default: anyhow's Debug form adds a backtrace whenever
            // RUST_BACKTRACE is set, as it is in many Rust users' shells.
            if verbose {
                eprintln!("fractile-client: {e:?}");
            } else {
                eprintln!("fractile-client: {e:#}");
            }
            std::process::ExitCode::FAILURE
        }
    }
}

async fn run(cli: Cli) -> Result<()> {
    let client = Client::new(&cli.server)?
        .with_token(cli.token.clone())
        .with_backend(cli.backend);
    let json = cli.json;
    match cli.command {
        Command::Assets => {
            let assets = client.assets().await?;
            if json {
                println!("{}", serde_json::to_string_pretty(&assets)?);
            } else {
                println!(
                    "| id | kind | size | bytes | ratio | PSNR dB |\n|---|---|---|---|---|---|"
                );
                for a in assets {
                    println!(
                        "| {} | {:?} | {}x{} | {} | {:.1} | {:.2} |",
                        a.id, a.kind, a.width, a.height, a.bytes, a.ratio, a.encode_psnr
                    );
                }
            }
        }
        Command::Info { id } => {
            let a = client.asset(&id).await?;
            println!("{}", serde_json::to_string_pretty(&a)?);
        }
        Command::Upload { file, id } => {
            let bytes =
                std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
            let up = client.upload(&id, bytes).await?;
            if json {
                println!("{}", json!({"created": up.created, "asset": up.summary}));
            } else {
                let verb = if up.created { "created" } else { "replaced" };
                println!(
                    "{verb} {} ({} bytes, {:.1}:1)",
                    up.summary.id, up.summary.bytes, up.summary.ratio
                );
            }
        }
        Command::Delete { id } => {
            client.delete(&id).await?;
            if json {
                println!("{}", json!({"deleted": id}));
            } else {
                println!("deleted {id}");
            }
        }
        Command::Tile(a) => tile(&client, json, a).await?,
        Command::Point(a) => point(&client, json, a).await?,
        Command::Points(a) => points(&client, json, a).await?,
        Command::Region(a) => region(&client, json, a).await?,
        Command::Mesh(a) => mesh(&client, json, a).await?,
        Command::View(a) => view(&client, json, a).await?,
        Command::Bench(a) => run_bench(&client, json, a).await?,
    }
    Ok(())
}

/// `tile`: fetches a tile (refined step by step with --refine).
async fn tile(client: &Client, json: bool, a: TileArgs) -> Result<()> {
    let TileArgs {
        id,
        z,
        x,
        y,
        output,
        encoding: enc,
        tile_size,
        precision,
        refine,
    } = a;
    let precision = precision
        .map(|p| p.parse::<fractile_client::Precision>())
        .transpose()
        .map_err(|e| anyhow::anyhow!(e))?;
    let req = TileRequest {
        iterations: refine.iterations,
        tile_size,
        precision,
        ..TileRequest::new(TileAddress { z, x, y }, {
            let by_name = output.extension().is_some_and(|e| e == "f32");
            let name = enc.unwrap_or_else(|| if by_name { "f32" } else { "png" }.into());
            encoding(&name)?
        })
    };
    if refine.refine {
        let mut steps = StepFiles::new(&output, json);
        let r = client
            .refine_tile(&id, &req, &refine.options(), |s| {
                steps.step(s, &s.answer.body)
            })
            .await?;
        let last = &r.steps.last().expect("at least one step").answer.body;
        steps.finish(last, r.stop)?;
    } else {
        let t = client.tile(&id, &req).await?;
        write(&output, &t.body)?;
        if json {
            println!(
                "{}",
                json!({"tile": t.address.to_string(), "bytes": t.body.len(), "convergence_bound": t.convergence_bound, "error_bound": t.error_bound, "ms": t.elapsed.as_secs_f64() * 1e3})
            );
        } else {
            println!(
                "{} -> {} ({} bytes, {})",
                t.address,
                output.display(),
                t.body.len(),
                bound_words(t.convergence_bound, t.error_bound)
            );
        }
    }
    Ok(())
}

/// `point`: prints the value at one point.
async fn point(client: &Client, json: bool, a: PointArgs) -> Result<()> {
    let PointArgs {
        id,
        lon,
        lat,
        unit,
        iterations,
    } = a;
    let p = if unit {
        client.point_unit(&id, lon, lat, iterations).await?
    } else {
        client.point_lonlat(&id, lon, lat, iterations).await?
    };
    if json {
        println!("{}", serde_json::to_string(&p)?);
    } else {
        let values: Vec<String> = p
            .values
            .iter()
            .flatten()
            .map(|v| v.map_or("nodata".into(), |v| v.to_string()))
            .collect();
        println!(
            "{} at {},{} ({}, {} steps)",
            values.join(" "),
            lon,
            lat,
            bound_words(p.convergence_bound.unwrap_or(f32::NAN), p.error_bound),
            p.iterations
        );
    }
    Ok(())
}

/// `points`: values at the points of a CSV file.
async fn points(client: &Client, json: bool, a: PointsArgs) -> Result<()> {
    let PointsArgs {
        id,
        file,
        output,
        binary,
        refine,
    } = a;
    let points = read_points(&file)?;
    let enc = if binary {
        PointsEncoding::Binary
    } else {
        PointsEncoding::Json
    };
    let resp = if refine.refine {
        print_head(json);
        let r = client
            .refine_points(&id, &points, enc, &refine.options(), |s| {
                print_step(json, s);
            })
            .await?;
        print_stop(json, r.stop);
        r.steps
            .into_iter()
            .last()
            .expect("at least one step")
            .answer
    } else {
        let req = PointsRequest {
            points,
            iterations: refine.iterations,
            tolerance: None,
        };
        client.points(&id, &req, enc).await?
    };
    let csv = points_csv(&resp);
    match output {
        Some(path) => write(&path, csv.as_bytes())?,
        None if json && !refine.refine => println!("{}", serde_json::to_string(&resp)?),
        None => print!("{csv}"),
    }
    Ok(())
}

/// `region`: fetches a region.
async fn region(client: &Client, json: bool, a: RegionArgs) -> Result<()> {
    let RegionArgs {
        id,
        bbox,
        width,
        height,
        format,
        output,
        refine,
    } = a;
    let req = RegionRequest {
        bbox: parse_numbers(&bbox, "bbox")?,
        width,
        height,
        iterations: refine.iterations,
        tolerance: None,
        format,
    };
    if refine.refine {
        let mut steps = StepFiles::new(&output, json);
        let r = client
            .refine_region(&id, &req, &refine.options(), |s| {
                steps.step(s, &s.answer.body)
            })
            .await?;
        let last = &r.steps.last().expect("at least one step").answer.body;
        steps.finish(last, r.stop)?;
    } else {
        let r = client.region(&id, &req).await?;
        write(&output, &r.body)?;
        if json {
            println!(
                "{}",
                json!({"bytes": r.body.len(), "convergence_bound": r.convergence_bound, "error_bound": r.error_bound})
            );
        } else {
            println!(
                "{}x{} -> {} ({})",
                width,
                height,
                output.display(),
                bound_words(r.convergence_bound, r.error_bound)
            );
        }
    }
    Ok(())
}

/// `mesh`: fetches a terrain mesh.
async fn mesh(client: &Client, json: bool, a: MeshArgs) -> Result<()> {
    let MeshArgs {
        id,
        bbox,
        resolution,
        format,
        iterations,
        max_error,
        output,
    } = a;
    let req = MeshRequest {
        bbox: bbox.map(|b| parse_numbers(&b, "bbox")).transpose()?,
        resolution,
        iterations,
        tolerance: None,
        max_error,
        format,
    };
    let m = client.mesh(&id, &req).await?;
    write(&output, &m.body)?;
    if json {
        println!(
            "{}",
            json!({"bytes": m.body.len(), "content_type": m.content_type, "convergence_bound": m.convergence_bound, "error_bound": m.error_bound})
        );
    } else {
        println!(
            "{} -> {} ({} bytes, {})",
            m.content_type,
            output.display(),
            m.body.len(),
            bound_words(m.convergence_bound, m.error_bound)
        );
    }
    Ok(())
}

/// `view`: plans and fetches the tiles a camera sees.
async fn view(client: &Client, json: bool, a: ViewArgs) -> Result<()> {
    let ViewArgs {
        id,
        camera,
        bbox,
        pixel_error,
        max_tiles,
        concurrency,
        encoding: enc,
        plan_only,
        output,
    } = a;
    let [lon, lat, h] = parse_numbers(&camera, "camera")?;
    let asset = client.asset(&id).await?;
    let tj = client.tilejson(&id).await?;
    let region = match bbox {
        Some(b) => parse_numbers(&b, "bbox")?,
        None => tj.bounds,
    };
    let cam = Camera {
        pixel_error,
        ..Camera::new(lon, lat, h)
    };
    let limits = PlanLimits {
        min_zoom: tj.minzoom,
        max_zoom: tj.maxzoom,
        max_tiles,
        ..Default::default()
    };
    let plan = fractile_client::view::plan(&cam, region, &asset, limits)?;
    let enc = encoding(&enc)?;
    if !json {
        println!(
            "| tile | distance m | tolerance | iterations | convergence bound | ms |\n|---|---|---|---|---|---|"
        );
    }
    let row = |p: &fractile_client::view::PlannedTile, bound: Option<f32>, ms: Option<f64>| {
        if json {
            println!(
                "{}",
                json!({"tile": p.address.to_string(), "distance": p.distance, "tolerance": p.tolerance, "iterations": p.iterations, "convergence_bound": bound, "ms": ms})
            );
        } else {
            let b = bound.map_or("-".into(), |b| format!("{b:.3}"));
            let ms = ms.map_or("-".into(), |m| format!("{m:.1}"));
            println!(
                "| {} | {:.0} | {:.3} | {} | {b} | {ms} |",
                p.address, p.distance, p.tolerance, p.iterations
            );
        }
    };
    if plan_only {
        plan.iter().for_each(|p| row(p, None, None));
        return Ok(());
    }
    let ext = if enc == TileEncoding::F32 {
        "f32"
    } else {
        "png"
    };
    let mut failures = 0;
    let results = client
        .fetch_view(&id, &plan, enc, concurrency, |p, r| match r {
            Ok(t) => row(
                p,
                Some(t.convergence_bound),
                Some(t.elapsed.as_secs_f64() * 1e3),
            ),
            Err(e) => {
                failures += 1;
                eprintln!("{}: {e}", p.address);
            }
        })
        .await;
    if let Some(dir) = output {
        for t in results.iter().flatten() {
            let a = t.address;
            let folder = dir.join(a.z.to_string()).join(a.x.to_string());
            std::fs::create_dir_all(&folder)
                .with_context(|| format!("creating {}", folder.display()))?;
            write(&folder.join(format!("{}.{ext}", a.y)), &t.body)?;
        }
    }
    if failures > 0 {
        bail!("{failures} of {} tiles failed", plan.len());
    }
    Ok(())
}

/// `bench`: runs the load generator.
async fn run_bench(client: &Client, json: bool, a: BenchArgs) -> Result<()> {
    let BenchArgs {
        asset,
        concurrency,
        duration,
        kinds,
        batch,
        encoding: heights,
    } = a;
    let kinds = kinds
        .iter()
        .map(|k| bench::Kind::parse(k).with_context(|| format!("unknown kind {k:?}")))
        .collect::<Result<Vec<_>>>()?;
    if !(duration > 0.0 && duration <= 3600.0) {
        bail!("duration must be in (0, 3600] seconds");
    }
    let options = bench::BenchOptions {
        asset,
        concurrency,
        duration: Duration::from_secs_f64(duration),
        kinds,
        batch,
        heights: encoding(&heights)?,
        ..Default::default()
    };
    let reports = bench::run(client, &options).await?;
    if json {
        println!("{}", serde_json::to_string_pretty(&reports)?);
    } else {
        print!("{}", bench::table(&reports, concurrency));
        for r in reports.iter().filter(|r| r.errors > 0) {
            eprintln!(
                "{:?}: first error: {}",
                r.kind,
                r.first_error.as_deref().unwrap_or("?")
            );
        }
    }
    Ok(())
}
