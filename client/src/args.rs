//! The command line's arguments: the command tree and each command's flags.

use std::path::PathBuf;
use std::time::Duration;

use clap::{Args, Parser, Subcommand};
use fractile_client::refine::RefineOptions;
use fractile_client::{MeshFormat, RegionFormat};

#[derive(Parser)]
#[command(
    name = "fractile-client",
    version,
    about = "Thin client of a fractile server"
)]
pub(crate) struct Cli {
    /// Base URL of the server.
    #[arg(
        long,
        global = true,
        env = "FRACTILE_SERVER",
        default_value = "http://127.0.0.1:8080"
    )]
    pub(crate) server: String,
    /// Bearer token for upload and delete.
    #[arg(
        long,
        global = true,
        env = "FRACTILE_WRITE_TOKEN",
        hide_env_values = true
    )]
    pub(crate) token: Option<String>,
    /// Ask the server to decode on cpu, gpu or auto (default: the server's setting).
    #[arg(long, global = true)]
    pub(crate) backend: Option<fractile_client::Backend>,
    /// Print machine-readable JSON (with --refine: one object per step).
    #[arg(long, global = true)]
    pub(crate) json: bool,
    /// On an error, print its whole chain and a backtrace (where `RUST_BACKTRACE` asks for one)
    /// instead of the one line that says what went wrong.
    #[arg(short, long, global = true)]
    pub(crate) verbose: bool,
    #[command(subcommand)]
    pub(crate) command: Command,
}

/// Options of progressive refinement.
#[derive(Args, Clone)]
pub(crate) struct RefineArgs {
    /// Ask for 1, 2, 3, ... iterations until the answer settles; write every step.
    #[arg(long)]
    pub(crate) refine: bool,
    /// With --refine: stop once the convergence bound (the distance to the fractal's
    /// attractor, which more iterations shrink) is at most this, value units. The error bound
    /// against the source does not shrink with iterations, so refinement never stops on it.
    #[arg(long)]
    pub(crate) tolerance: Option<f32>,
    /// With --refine: stop once the mean change is at most this fraction of the value range.
    #[arg(long, default_value_t = 0.002)]
    pub(crate) change: f32,
    /// With --refine: time budget in milliseconds.
    #[arg(long)]
    pub(crate) budget_ms: Option<u64>,
    /// With --refine: iterations to ask for, e.g. 1,2,4,8 (default 1,2,...,64).
    #[arg(long, value_delimiter = ',')]
    pub(crate) schedule: Option<Vec<u32>>,
    /// Exactly this many iterations (without --refine).
    #[arg(long, conflicts_with = "refine")]
    pub(crate) iterations: Option<u32>,
}

impl RefineArgs {
    pub(crate) fn options(&self) -> RefineOptions {
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
pub(crate) enum Command {
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
    /// A volume's 3D Tiles (tileset.json, its subtrees and tiles) fetched to a folder, for
    /// offline use: the folder is the same tileset for any static file server.
    Tileset {
        id: String,
        /// The folder to write (created if need be).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Load test: each kind for --duration at --concurrency; prints a table per kind.
    Bench(BenchArgs),
}

/// Arguments of `tile`.
#[derive(Args)]
pub(crate) struct TileArgs {
    pub(crate) id: String,
    pub(crate) z: u8,
    pub(crate) x: u32,
    pub(crate) y: u32,
    /// Output file.
    #[arg(short, long)]
    pub(crate) output: PathBuf,
    /// png (visual), terrarium, terrainrgb, gray16 or f32 (default: f32 when the output
    /// ends in .f32, png otherwise).
    #[arg(long)]
    pub(crate) encoding: Option<String>,
    /// 256 or 512.
    #[arg(long, default_value_t = 256)]
    pub(crate) tile_size: u32,
    /// Terrain-RGB and Terrarium tiles: `bound` rounds heights to what the tile's error
    /// bound justifies (smaller PNGs; the server's default), `full` keeps every 0.1 m or
    /// 1/256 m. `--refine` always asks for full precision.
    #[arg(long)]
    pub(crate) precision: Option<String>,
    #[command(flatten)]
    pub(crate) refine: RefineArgs,
}

/// Arguments of `point`.
#[derive(Args)]
pub(crate) struct PointArgs {
    pub(crate) id: String,
    #[arg(allow_hyphen_values = true)]
    pub(crate) lon: f64,
    #[arg(allow_hyphen_values = true)]
    pub(crate) lat: f64,
    /// The coordinates are unit x, y (any asset), not lon, lat.
    #[arg(long)]
    pub(crate) unit: bool,
    #[arg(long)]
    pub(crate) iterations: Option<u32>,
}

/// Arguments of `points`.
#[derive(Args)]
pub(crate) struct PointsArgs {
    pub(crate) id: String,
    pub(crate) file: PathBuf,
    /// Write a CSV of the answers here (default: standard output).
    #[arg(short, long)]
    pub(crate) output: Option<PathBuf>,
    /// Send the batch in the binary encoding.
    #[arg(long)]
    pub(crate) binary: bool,
    #[command(flatten)]
    pub(crate) refine: RefineArgs,
}

/// Arguments of `region`.
#[derive(Args)]
pub(crate) struct RegionArgs {
    pub(crate) id: String,
    /// minx,miny,maxx,maxy (lon/lat, or unit coordinates).
    #[arg(long, allow_hyphen_values = true)]
    pub(crate) bbox: String,
    #[arg(long, default_value_t = 512)]
    pub(crate) width: u32,
    #[arg(long, default_value_t = 512)]
    pub(crate) height: u32,
    /// png, f32 or tif.
    #[arg(long, default_value = "png")]
    pub(crate) format: RegionFormat,
    #[arg(short, long)]
    pub(crate) output: PathBuf,
    #[command(flatten)]
    pub(crate) refine: RefineArgs,
}

/// Arguments of `mesh`.
#[derive(Args)]
pub(crate) struct MeshArgs {
    pub(crate) id: String,
    #[arg(long, allow_hyphen_values = true)]
    pub(crate) bbox: Option<String>,
    /// Vertices a side.
    #[arg(long)]
    pub(crate) resolution: Option<u32>,
    /// glb, obj or ply.
    #[arg(long, default_value = "glb")]
    pub(crate) format: MeshFormat,
    #[arg(long)]
    pub(crate) iterations: Option<u32>,
    /// An adaptive triangulation within this many height units of the decoded grid.
    #[arg(long)]
    pub(crate) max_error: Option<f32>,
    #[arg(short, long)]
    pub(crate) output: PathBuf,
}

/// Arguments of `view`.
#[derive(Args)]
pub(crate) struct ViewArgs {
    pub(crate) id: String,
    /// lon,lat,height (metres above sea level).
    #[arg(long, allow_hyphen_values = true)]
    pub(crate) camera: String,
    /// west,south,east,north (default: the asset's bounds).
    #[arg(long, allow_hyphen_values = true)]
    pub(crate) bbox: Option<String>,
    /// Allowed screen-space error in pixels.
    #[arg(long, default_value_t = 1.0)]
    pub(crate) pixel_error: f64,
    /// Most tiles.
    #[arg(long, default_value_t = 256)]
    pub(crate) max_tiles: usize,
    /// Requests in flight.
    #[arg(long, default_value_t = 8)]
    pub(crate) concurrency: usize,
    /// png, terrarium, terrainrgb, gray16 or f32.
    #[arg(long, default_value = "terrarium")]
    pub(crate) encoding: String,
    /// Only print the plan.
    #[arg(long)]
    pub(crate) plan_only: bool,
    /// Write the tiles under this folder as Z/X/Y.ext.
    #[arg(short, long)]
    pub(crate) output: Option<PathBuf>,
}

/// Arguments of `bench`.
#[derive(Args)]
pub(crate) struct BenchArgs {
    #[arg(long, default_value = "jacksboro")]
    pub(crate) asset: String,
    #[arg(long, default_value_t = 16)]
    pub(crate) concurrency: usize,
    /// Seconds per kind.
    #[arg(long, default_value_t = 10.0)]
    pub(crate) duration: f64,
    /// Kinds, in order: tiles-cold, tiles-warm, terrain-cold (Cesium terrain; skipped for
    /// assets that are not georeferenced height fields), points, regions.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "tiles-cold,tiles-warm,terrain-cold,points,regions"
    )]
    pub(crate) kinds: Vec<String>,
    /// Points per batch.
    #[arg(long, default_value_t = 1000)]
    pub(crate) batch: usize,
    /// Encoding of a height field's tiles (terrarium, terrainrgb, gray16, f32, png); pictures'
    /// tiles are PNGs whatever this says.
    #[arg(long, default_value = "terrarium")]
    pub(crate) encoding: String,
}
