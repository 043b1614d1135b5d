//! The HTTP API (versioned under /v1): the shared state, the router, and what every resource's
//! handlers share (lanes, backends, sampling, parameters). Handlers live with their resource
//! (`assets`, `tiles`, `terrain`, `points`, `regions`, `meshes`, `curves`): each parses and checks a
//! request, runs decoding in a lane of [`crate::work`] (never on the async workers), and
//! encodes the answer. The server adds no fractal math: it calls the codec.

mod assets;
mod curves;
mod meshes;
mod points;
mod regions;
mod terrain;
mod tiles;

use assets::*;
pub use curves::CurveQuery;
use curves::*;
use meshes::*;
use points::*;
use regions::*;
use terrain::*;
use tiles::*;

use std::hash::{Hash, Hasher};
use std::sync::Arc;
use std::time::Duration;

use crate::error::{Path, Query};
use axum::body::Bytes;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use fractile_codec::geo;
use fractile_proto::{
    AssetKind, AssetSummary, BINARY_MEDIA_TYPE, Catalog, DistanceResult, PointResult,
    PointsRequest, PointsResponse, TileJson,
};
use serde::Deserialize;
use tokio::sync::Semaphore;

use crate::backend::{Backend, GpuBackend};
use crate::encoding::{self, HeightEncoding};
use crate::error::AppError;
use crate::store::{Store, StoredAsset};
use crate::work::{BodyWriter, Bounds, Cancel, Head, Lanes};

/// Limits on what one request may ask for.
#[derive(Clone, Debug)]
pub struct Limits {
    /// Most inverse steps or iterations a request may ask for.
    pub max_iterations: u32,
    /// Most pixels of a region.
    pub max_region_pixels: usize,
    /// Most points of a batch.
    pub max_points: usize,
    /// Deepest zoom served.
    pub max_zoom: u8,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_iterations: 64,
            max_region_pixels: 4096 * 4096,
            max_points: 100_000,
            max_zoom: 24,
        }
    }
}

/// Shared state of the handlers.
pub struct AppState {
    /// The catalog.
    pub store: Store,
    /// Request limits.
    pub limits: Limits,
    /// Where decoding runs and what it may cost at once (light slots, heavy budget).
    pub lanes: Lanes,
    /// Request bodies in flight (uploads, point batches), in MiB: a body waits for room before
    /// it is read.
    pub uploads: Arc<Semaphore>,
    /// Size of `uploads`, in MiB (twice the largest upload).
    pub uploads_mib: u32,
    /// Encoded tiles keyed like their ETag, bounded in bytes.
    pub cache: moka::sync::Cache<String, Arc<Cached>>,
    /// Discrete decodes of whole assets at the scale of a coarse zoom level, keyed by asset id,
    /// checksum, grid size and steps, bounded in bytes: every tile of a zoom coarser than the
    /// source samples the same grid, so it is decoded once (concurrent requests wait for it).
    pub coarse: CoarseCache,
    /// `Cache-Control` value of tiles.
    pub cache_control: String,
    /// Public base URL for absolute links (TileJSON), e.g. behind a proxy.
    pub public_url: String,
    /// Who may PUT and DELETE assets (nobody unless a token or anonymous writes are set).
    pub writes: Writes,
    /// Largest asset upload in bytes.
    pub max_upload: usize,
    /// Where continuous decoding runs unless a request says otherwise.
    pub backend: Backend,
    /// The GPU, when the server has one.
    pub gpu: Option<Arc<GpuBackend>>,
    /// CesiumJS's build, served at `/vendor/cesium/` when set (`cesium_dir`).
    pub cesium_dir: Option<std::path::PathBuf>,
}

/// Default of `coarse_cache_mib`: every coarse zoom of a 9.3 Mpx DEM takes 73 MB (its zoom
/// 4 grid alone 37 MB), and 64 MiB made that grid decode four times over a zoom's tiles
/// (docs/benchmarks.md, `coarse_zooms`).
pub const DEFAULT_COARSE_CACHE_MIB: u64 = 256;

/// A coarse-decode cache of `mib` MiB, weighed by the bytes of its grids.
pub fn coarse_cache(mib: u64) -> CoarseCache {
    moka::sync::Cache::builder()
        .weigher(|_k: &CoarseKey, v: &Arc<Vec<CoarsePlane>>| {
            let floats: usize = v.iter().map(|(g, _)| g.values.len()).sum();
            (floats * 4).try_into().unwrap_or(u32::MAX)
        })
        .max_capacity(mib.saturating_mul(1024 * 1024))
        .build()
}

/// Key of [`AppState::coarse`]: asset id, checksum, width, height, iterations, tolerance bits.
pub type CoarseKey = (String, u32, usize, usize, u32, u32);

/// A cached answer.
pub struct Cached {
    content_type: &'static str,
    /// `Content-Encoding` of the body (`gzip` for Cesium terrain to clients that accept it).
    content_encoding: Option<&'static str>,
    body: Bytes,
    bounds: Bounds,
}

impl Cached {
    /// Bytes it holds (its weight in the cache).
    pub fn size(&self) -> usize {
        self.body.len()
    }
}

impl AppState {
    /// State over a store with default limits, a 256 MiB tile cache and one decoder per core.
    pub fn new(store: Store, public_url: String) -> AppState {
        let cores = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(2);
        AppState {
            store,
            limits: Limits::default(),
            lanes: Lanes::new(cores, crate::memory::default_decode_mib()),
            uploads: Arc::new(Semaphore::new(2 * 64)),
            uploads_mib: 2 * 64,
            cache: moka::sync::Cache::builder()
                .weigher(|_k: &String, v: &Arc<Cached>| v.body.len().try_into().unwrap_or(u32::MAX))
                .max_capacity(256 * 1024 * 1024)
                .build(),
            coarse: coarse_cache(DEFAULT_COARSE_CACHE_MIB),
            cache_control: "public, max-age=3600".into(),
            public_url,
            writes: Writes::Refused,
            max_upload: 64 * 1024 * 1024,
            backend: Backend::Auto,
            gpu: None,
            cesium_dir: None,
        }
    }
}

type Shared = State<Arc<AppState>>;

/// The router of the whole API.
pub fn router(state: Arc<AppState>) -> Router {
    // Read the build's id now rather than on the first tile request.
    tiles::build_id();
    Router::new()
        .route("/healthz", get(|| async { "ok" }))
        .route("/readyz", get(ready))
        .route(
            "/v1/openapi.json",
            get(|| async { Json(crate::openapi::document()) }),
        )
        .route("/v1/assets", get(list_assets))
        .route(
            "/v1/assets/{id}",
            get(asset_info)
                .put(put_asset)
                .delete(delete_asset)
                .layer(axum::extract::DefaultBodyLimit::max(state.max_upload)),
        )
        .route("/v1/assets/{id}/tilejson.json", get(tilejson))
        .route("/v1/assets/{id}/tiles/{z}/{x}/{tile}", get(tile))
        .route("/v1/assets/{id}/layer.json", get(layer))
        .route("/v1/assets/{id}/terrain/{z}/{x}/{tile}", get(terrain_tile))
        .route("/v1/assets/{id}/point", get(point_unit))
        .route("/v1/assets/{id}/point/{coords}", get(point_lonlat))
        // The batch's body limit is applied as it is read (`read_body`).
        .route("/v1/assets/{id}/points", post(points))
        .route("/v1/assets/{id}/region", get(region))
        .route("/v1/assets/{id}/mesh", get(mesh))
        .route("/v1/assets/{id}/curve", get(curve))
        .route(
            "/v1/assets/{id}/curve/deform",
            post(curve_deform).layer(
                tower::ServiceBuilder::new()
                    .layer(axum::extract::DefaultBodyLimit::max(curves::DEFORM_BODY))
                    .layer(tower_http::limit::RequestBodyLimitLayer::new(
                        curves::DEFORM_BODY,
                    )),
            ),
        )
        .with_state(state)
}

/// Readiness: the assets are loaded (the server listens only after loading them) and a light
/// decode slot is free, so a load balancer sends cheap requests elsewhere while every slot is
/// busy.
async fn ready(State(state): Shared) -> Result<&'static str, AppError> {
    if state.lanes.light_free() {
        Ok("ready")
    } else {
        Err(AppError {
            status: StatusCode::SERVICE_UNAVAILABLE,
            code: "busy",
            detail: "every decode slot is busy".into(),
            retry_after: None,
        })
    }
}

/// The asset of a request that works on 2D planes (tiles, regions, lon/lat and batch points):
/// a volume is a 400 naming what it does answer instead.
fn planar(a: Arc<StoredAsset>) -> Result<Arc<StoredAsset>, AppError> {
    if a.asset.meta.kind == AssetKind::Curve {
        return Err(AppError::bad_request(
            "curve_asset",
            format!(
                "{} is a curve asset: ask /curve?level=N (GeoJSON) or POST /curve/deform",
                a.id
            ),
        ));
    }
    if a.asset.meta.kind == AssetKind::Volume {
        return Err(AppError::bad_request(
            "volume_asset",
            format!(
                "{} is a volume: ask /mesh?bbox=x0,y0,z0,x1,y1,z1 or /point?x=&y=&z=",
                a.id
            ),
        ));
    }
    Ok(a)
}

/// Runs `f` on the blocking pool in the lane of its estimated `bytes` (see [`crate::work`]).
async fn decode<T: Send + 'static>(
    state: &AppState,
    bytes: u64,
    f: impl FnOnce(&Cancel) -> T + Send + 'static,
) -> Result<T, AppError> {
    state.lanes.run(bytes, f).await
}

/// Bytes a decode of `pixels` points of `channels` channels holds at its peak: the points
/// (8), a chain result per channel (12), the values in source units and their encoding (8).
fn sampling_bytes(pixels: usize, channels: u8) -> u64 {
    pixels as u64 * (8 + 20 * u64::from(channels.max(1)))
}

/// A tile's zoom, column and row from their path segments, or a 400 `bad_path` (the code of
/// every path that does not parse) that says which numbers are tiles (zooms 0 to `max_zoom`, columns up to `columns x 2^z - 1`, rows up to
/// `2^z - 1`). Numbers that parse but name no tile are the caller's 404.
fn tile_numbers(
    z: &str,
    x: &str,
    y: &str,
    max_zoom: u8,
    columns: u64,
) -> Result<(u8, u32, u32), AppError> {
    let z: u8 = z.parse().map_err(|_| {
        AppError::bad_request(
            "bad_path",
            format!("bad zoom {z:?}: zooms are whole numbers from 0 to {max_zoom}"),
        )
    })?;
    let span = |k: u64| (k << z.min(32)).saturating_sub(1);
    let number = |t: &str, what: &str, most: u64| {
        t.parse::<u32>().map_err(|_| {
            AppError::bad_request(
                "bad_path",
                format!("bad tile {what} {t:?}: at zoom {z} {what}s go from 0 to {most}"),
            )
        })
    };
    Ok((
        z,
        number(x, "column", span(columns))?,
        number(y, "row", span(1))?,
    ))
}

/// The backend of a request: its `backend` parameter, else the server's. Asking for the GPU
/// of a server without one is an error, not a silent fallback.
fn backend_for(state: &AppState, asked: Option<&str>) -> Result<Backend, AppError> {
    let b = match asked {
        Some(s) => s
            .parse::<Backend>()
            .map_err(|e| AppError::bad_request("bad_backend", e))?,
        None => state.backend,
    };
    if b == Backend::Gpu && state.gpu.is_none() {
        return Err(AppError::bad_request(
            "gpu_unavailable",
            "this server decodes on the CPU (it found no hardware GPU, or was started with \
             backend cpu; `fractile serve --backend gpu` opens any adapter, a software one too): \
             use backend=cpu or auto",
        ));
    }
    Ok(b)
}

/// `Asset::sample` of a raster's pixels on the chosen backend, with coarse decodes shared
/// through `coarse` (runs inside `decode`, on the blocking pool).
fn sample_on(
    (gpu, coarse, cancel): (Option<&GpuBackend>, &CoarseCache, &Cancel),
    choice: Backend,
    a: &StoredAsset,
    pixels: &geo::Pixels,
    iterations: u32,
    tolerance: Tolerance,
) -> Result<(Vec<Vec<f32>>, Bounds), AppError> {
    let tolerance = tolerance.over(a, pixels)?;
    let gpu = gpu.filter(|g| g.takes(choice, a, pixels.len()));
    // The GPU's round trip runs off the request's core slot (see `work`), the operator's
    // upload on it.
    let continuous =
        |k: fractile_codec::extract::PlaneRef<'_>, p: fractile_codec::extract::Sites<'_>, n, t| {
            let (g, op) = gpu.and_then(|g| Some((g, g.operator(a, k)?)))?;
            cancel.off_core(|| g.points(a, &op, p, n, t))
        };
    let discrete = |w: usize, h: usize, n, t: f32| {
        let result = std::cell::Cell::new("hit");
        let key = |w, h| (a.id.clone(), a.hash, w, h, n, t.to_bits());
        let grids = coarse.get_with(key(w, h), || {
            // A zoom's tiles ask for grids that differ by powers of two (a band of latitude
            // has half the rows of the next): one cached at 2, 4 or 8 times the size on
            // either axis gives this one by block means, in a pass instead of a decode.
            let finer = (0..=3)
                .flat_map(|i| (0..=3).map(move |j| (i, j)))
                .filter(|&ij| ij != (0, 0))
                .find_map(|(i, j)| Some(((i, j), coarse.get(&key(w << i, h << j))?)));
            if let Some(((i, j), fine)) = finer {
                let shrunk: Option<Vec<CoarsePlane>> = fine
                    .iter()
                    .map(|(g, r)| Some((g.shrink(1 << i, 1 << j)?, *r)))
                    .collect();
                if let Some(planes) = shrunk {
                    result.set("derived");
                    return Arc::new(planes);
                }
            }
            result.set("miss");
            Arc::new(a.asset.discrete_planes(w, h, n, t))
        });
        let result = result.get();
        metrics::counter!("fractile_coarse_cache_total", "result" => result).increment(1);
        grids
    };
    let cancelled = || cancel.is_set();
    let delegates = fractile_codec::extract::Delegates {
        continuous: &continuous,
        discrete: &discrete,
        cancelled: &cancelled,
    };
    let (channels, attractor) = a
        .asset
        .sample_with(pixels, iterations, tolerance, &delegates)
        .map_err(|e| match e {
            fractile_codec::extract::SampleError::Cancelled => AppError {
                status: StatusCode::SERVICE_UNAVAILABLE,
                code: "cancelled",
                detail: "the request was given up before its decode finished".into(),
                retry_after: None,
            },
            fractile_codec::extract::SampleError::Chunk(e) => chunk_unavailable(e),
        })?;
    let source = a
        .asset
        .source_error_over(pixels)
        .map_err(chunk_unavailable)?;
    Ok((channels, Bounds { attractor, source }))
}

/// A chunk of a chunked asset that could not be read or decoded. Read failures (a store that
/// is down, a file replaced under the reader) are 503 `chunk_unavailable` with `Retry-After`,
/// since a store that comes back answers again; a chunk whose bytes are not what its table
/// says is 500 `corrupt_chunk`: no retry mends it (the asset must be uploaded again), and the
/// chunk is not decoded again for the next request (`Chunked::chunk` remembers it). Where and
/// why go to the log, not to the client.
pub(crate) fn chunk_unavailable(e: fractile_codec::Error) -> AppError {
    tracing::error!("{e}");
    match e {
        fractile_codec::Error::Unavailable(_) => AppError {
            status: StatusCode::SERVICE_UNAVAILABLE,
            code: "chunk_unavailable",
            detail: "a chunk of the asset could not be read; try again".into(),
            retry_after: Some(1),
        },
        _ => AppError {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            code: "corrupt_chunk",
            detail:
                "a chunk of the asset is corrupt (not what its table says); upload the asset again"
                    .into(),
            retry_after: None,
        },
    }
}

/// Discrete decodes for coarse tiles (see [`AppState::coarse`]).
pub type CoarseCache = moka::sync::Cache<CoarseKey, Arc<Vec<CoarsePlane>>>;

/// A plane decoded discretely for coarse tiles, with what the decoder reported.
pub type CoarsePlane = (
    fractile_codec::core::decode::Grid,
    fractile_codec::core::decode::DiscreteReport,
);

/// A request's tolerance (value units): what it asked for (0 with fixed steps), or, where it
/// named neither steps nor a tolerance, settled by the codec for what is answered.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Tolerance {
    /// Asked for (0: none, `iterations` steps exactly).
    Asked(f32),
    /// Neither asked: see [`Tolerance::over`] and [`Tolerance::anywhere`].
    Settled,
}

impl Tolerance {
    /// The tolerance of an answer at `pixels`: a settled one is `Asset::tolerance_over` them
    /// (an eighth of the largest source error their bound carries anyway, or the asset's
    /// default where that is larger); 503 where a chunk under them cannot be read.
    fn over(self, a: &StoredAsset, pixels: &geo::Pixels) -> Result<f32, AppError> {
        match self {
            Tolerance::Asked(t) => Ok(t),
            Tolerance::Settled => a.asset.tolerance_over(pixels).map_err(chunk_unavailable),
        }
    }

    /// The tolerance of answers anywhere (points, each with its own bound): a settled one is
    /// the asset's default (see `Asset::default_tolerance`).
    fn anywhere(self, a: &StoredAsset) -> f32 {
        match self {
            Tolerance::Asked(t) => t,
            Tolerance::Settled => a.asset.default_tolerance(),
        }
    }
}

/// Steps and per-point tolerance of a request. `iterations` alone: exactly that many steps.
/// `tolerance` (value units): each point stops once its own a-priori bound is under it, within
/// `iterations` or the limit. Neither: a tolerance settled by what is answered (see
/// [`Tolerance`]).
fn iterations_for(
    state: &AppState,
    asked: Option<u32>,
    tolerance: Option<f32>,
) -> Result<(u32, Tolerance), AppError> {
    let max = state.limits.max_iterations;
    let n = match asked {
        Some(0) => {
            return Err(AppError::bad_request(
                "bad_iterations",
                "iterations must be at least 1",
            ));
        }
        Some(n) if n > max => {
            return Err(AppError::bad_request(
                "bad_iterations",
                format!("iterations {n} over the limit {max}"),
            ));
        }
        Some(n) => n,
        None => max,
    };
    match (asked, tolerance) {
        (_, Some(t)) if !(t.is_finite() && t > 0.0) => Err(AppError::bad_request(
            "bad_tolerance",
            "tolerance must be a positive number (value units)",
        )),
        (_, Some(t)) => Ok((n, Tolerance::Asked(t))),
        (Some(n), None) => Ok((n, Tolerance::Asked(0.0))),
        (None, None) => Ok((max, Tolerance::Settled)),
    }
}

/// Unit coordinates of a request point: lon/lat for georeferenced assets, unit x/y otherwise.
fn unit_of(a: &StoredAsset, c: [f64; 2]) -> Option<[f32; 2]> {
    match &a.placement {
        Some(p) => p.unit(c[0], c[1]),
        None => c
            .iter()
            .all(|t| (0.0..=1.0).contains(t))
            .then_some([c[0] as f32, c[1] as f32]),
    }
}

/// The pixels of a box's samples: column i at request x `x(i)`, row j at request y `y(j)`
/// (lon/lat for georeferenced assets, a north-up box; unit coordinates otherwise), each
/// `[dx, dy]` request units wide.
fn box_pixels(
    a: &StoredAsset,
    (w, x): (usize, impl Fn(usize) -> f64),
    (h, y): (usize, impl Fn(usize) -> f64),
    [dx, dy]: [f64; 2],
) -> geo::Pixels {
    let xs: Vec<f64> = (0..w).map(x).collect();
    let ys: Vec<f64> = (0..h).map(y).collect();
    match &a.placement {
        Some(p) => {
            let centre = |v: &[f64]| 0.5 * (v[0] + v[v.len() - 1]);
            let footprint = p.footprint(centre(&xs), centre(&ys), dx, dy);
            p.pixels(&xs, &ys, footprint)
        }
        None => {
            let unit = |t: f64| (0.0..=1.0).contains(&t).then_some(t as f32);
            geo::Pixels::grid(
                xs.into_iter().map(unit).collect(),
                ys.into_iter().map(unit).collect(),
                [dx as f32, dy as f32],
            )
        }
    }
}

/// `minx,miny,maxx,maxy` with max > min.
fn parse_bbox(b: &str) -> Result<[f64; 4], AppError> {
    let v: Vec<f64> = b.split(',').filter_map(|s| s.trim().parse().ok()).collect();
    match v[..] {
        [x0, y0, x1, y1] if x1 > x0 && y1 > y0 => Ok([x0, y0, x1, y1]),
        _ => Err(AppError::bad_request(
            "bad_bbox",
            "bbox must be minx,miny,maxx,maxy with max > min",
        )),
    }
}

/// Size in request units of one of `w x h` cells over a box.
fn cell_size([x0, y0, x1, y1]: [f64; 4], w: usize, h: usize) -> [f64; 2] {
    [(x1 - x0) / w.max(1) as f64, (y1 - y0) / h.max(1) as f64]
}

/// The default request timeout.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);

/// Who may PUT and DELETE assets. Secure by default: a server started with no write token
/// takes no writes at all (403), since one reachable by others would otherwise let anyone
/// replace or delete its assets; anonymous writes are for a demo or a private network, and
/// must be asked for by name.
#[derive(Clone, Debug, PartialEq)]
pub enum Writes {
    /// Requests with `Authorization: Bearer <token>`.
    Token(String),
    /// Anyone (`--allow-anonymous-writes`).
    Anyone,
    /// Nobody: no token is configured (the default).
    Refused,
}

impl Writes {
    /// The policy a server's options ask for: the token if one is set, else anyone if
    /// anonymous writes are allowed, else nobody.
    pub fn from_options(token: Option<String>, allow_anonymous: bool) -> Writes {
        match token {
            Some(t) => Writes::Token(t),
            None if allow_anonymous => Writes::Anyone,
            None => Writes::Refused,
        }
    }
}
