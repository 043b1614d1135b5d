//! The HTTP API (versioned under /v1). Handlers parse and check requests, run decoding on the
//! blocking pool (bounded by a semaphore, never on the async workers), and encode answers.
//! The server adds no fractal math: it calls the codec.

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
use crate::work::{BodyWriter, Cancel, Head, Lanes};

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
    /// Bearer token that PUT and DELETE need; `None` leaves writes open (demo and local use).
    pub write_token: Option<String>,
    /// Largest asset upload in bytes.
    pub max_upload: usize,
    /// Where continuous decoding runs unless a request says otherwise.
    pub backend: Backend,
    /// The GPU, when the server has one.
    pub gpu: Option<Arc<GpuBackend>>,
}

/// Default of `max_decode_mib`: what the heavy lane may hold at once, and what one asset may
/// cost to decode ([`fractile_codec::AssetLimits::max_decode_bytes`]).
pub const DEFAULT_DECODE_MIB: u32 = 3 * 1024;

/// Key of [`AppState::coarse`]: asset id, checksum, width, height, iterations, tolerance bits.
pub type CoarseKey = (String, u32, usize, usize, u32, u32);

/// A cached answer.
pub struct Cached {
    content_type: &'static str,
    body: Bytes,
    error_bound: f32,
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
            lanes: Lanes::new(cores, DEFAULT_DECODE_MIB),
            uploads: Arc::new(Semaphore::new(2 * 64)),
            uploads_mib: 2 * 64,
            cache: moka::sync::Cache::builder()
                .weigher(|_k: &String, v: &Arc<Cached>| v.body.len().try_into().unwrap_or(u32::MAX))
                .max_capacity(256 * 1024 * 1024)
                .build(),
            coarse: moka::sync::Cache::builder()
                .weigher(|_k: &CoarseKey, v: &Arc<Vec<CoarsePlane>>| {
                    let floats: usize = v.iter().map(|(g, _)| g.values.len()).sum();
                    (floats * 4).try_into().unwrap_or(u32::MAX)
                })
                .max_capacity(64 * 1024 * 1024)
                .build(),
            cache_control: "public, max-age=3600".into(),
            public_url,
            write_token: None,
            max_upload: 64 * 1024 * 1024,
            backend: Backend::Auto,
            gpu: None,
        }
    }
}

type Shared = State<Arc<AppState>>;

/// The router of the whole API.
pub fn router(state: Arc<AppState>) -> Router {
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
        .route("/v1/assets/{id}/point", get(point_unit))
        .route("/v1/assets/{id}/point/{coords}", get(point_lonlat))
        // The batch's body limit is applied as it is read (`read_body`).
        .route("/v1/assets/{id}/points", post(points))
        .route("/v1/assets/{id}/region", get(region))
        .route("/v1/assets/{id}/mesh", get(mesh))
        .route("/v1/assets/{id}/curve", get(curve))
        .route(
            "/v1/assets/{id}/curve/deform",
            post(curve_deform).layer(axum::extract::DefaultBodyLimit::max(16 * 1024 * 1024)),
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
            "this server has no GPU adapter: use backend=cpu or auto",
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
    tolerance: f32,
) -> Result<(Vec<Vec<f32>>, f32), AppError> {
    let gpu = gpu.filter(|g| g.takes(choice, pixels.len()));
    let continuous =
        |k, p: fractile_codec::extract::Sites<'_>, n, t| gpu.and_then(|g| g.points(a, k, p, n, t));
    let discrete = |w, h, n, t: f32| {
        coarse.get_with((a.id.clone(), a.hash, w, h, n, t.to_bits()), || {
            Arc::new(a.asset.discrete_planes(w, h, n, t))
        })
    };
    let cancelled = || cancel.is_set();
    let delegates = fractile_codec::extract::Delegates {
        continuous: &continuous,
        discrete: &discrete,
        cancelled: &cancelled,
    };
    a.asset
        .sample_with(pixels, iterations, tolerance, &delegates)
        .map_err(|_| AppError {
            status: StatusCode::SERVICE_UNAVAILABLE,
            code: "cancelled",
            detail: "the request was given up before its decode finished".into(),
        })
}

/// Discrete decodes for coarse tiles (see [`AppState::coarse`]).
pub type CoarseCache = moka::sync::Cache<CoarseKey, Arc<Vec<CoarsePlane>>>;

/// A plane decoded discretely for coarse tiles, with what the decoder reported.
pub type CoarsePlane = (
    fractile_codec::decode::Grid,
    fractile_codec::decode::DiscreteReport,
);

fn summary(state: &AppState, a: &StoredAsset) -> AssetSummary {
    let m = &a.asset.meta;
    AssetSummary {
        id: a.id.clone(),
        kind: m.kind,
        width: m.width,
        height: m.height,
        channels: m.channels,
        colour: m.colour,
        bounds: a.placement.as_ref().map(|p| p.bounds()),
        georeferenced: a.placement.is_some(),
        epsg: a.placement.as_ref().and_then(|p| p.epsg()),
        value_range: [m.value_min, m.value_max],
        units: m.units.clone(),
        nodata: m.nodata,
        codec: a.asset.codec_name().into(),
        bytes: a.bytes,
        ratio: m.source_bytes() as f64 / a.bytes as f64,
        transforms: m.stats.transforms,
        encode_psnr: m.stats.psnr,
        encode_rmse: m.stats.rmse,
        max_contrast: a.asset.max_contrast(),
        seed_bound: a.asset.bound_after(0),
        tilejson: matches!(m.kind, AssetKind::Image | AssetKind::HeightField)
            .then(|| format!("{}/v1/assets/{}/tilejson.json", state.public_url, a.id)),
    }
}

async fn list_assets(State(state): Shared) -> Json<Catalog> {
    Json(Catalog {
        assets: state
            .store
            .list()
            .iter()
            .map(|a| summary(&state, a))
            .collect(),
    })
}

fn authorise(state: &AppState, headers: &HeaderMap) -> Result<(), AppError> {
    let Some(token) = &state.write_token else {
        return Ok(());
    };
    let given = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "));
    // Constant-time comparison: the token must not leak through timing.
    let ok = given.is_some_and(|g| {
        g.len() == token.len()
            && g.bytes()
                .zip(token.bytes())
                .fold(0u8, |acc, (a, b)| acc | (a ^ b))
                == 0
    });
    if ok {
        Ok(())
    } else {
        Err(AppError {
            status: StatusCode::UNAUTHORIZED,
            code: "unauthorised",
            detail: "writes need Authorization: Bearer <token>".into(),
        })
    }
}

/// Reads a request body of at most `limit` bytes once the bodies-in-flight budget has room for
/// it (its declared length, or `limit` when it declares none): a body over `limit` is a 413,
/// refused before a byte is read when its length says so. The permit holds the room until
/// the caller is done with the bytes.
async fn read_body(
    state: &AppState,
    headers: &HeaderMap,
    body: axum::body::Body,
    limit: usize,
) -> Result<(Bytes, tokio::sync::OwnedSemaphorePermit), AppError> {
    let too_large = || AppError {
        status: StatusCode::PAYLOAD_TOO_LARGE,
        code: "too_large",
        detail: format!("this request's body is at most {} bytes", limit),
    };
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|n| n > limit as u64) {
        return Err(too_large());
    }
    let mib =
        (declared.unwrap_or(limit as u64).div_ceil(1 << 20) as u32).clamp(1, state.uploads_mib);
    let room = state
        .uploads
        .clone()
        .acquire_many_owned(mib)
        .await
        .map_err(|_| AppError::internal("the body budget is closed"))?;
    let bytes = axum::body::to_bytes(body, limit).await.map_err(|e| {
        let over = std::error::Error::source(&e)
            .is_some_and(|s| s.is::<http_body_util::LengthLimitError>())
            || e.to_string().contains("length limit");
        if over {
            too_large()
        } else {
            AppError::bad_request("bad_body", format!("reading the body: {e}"))
        }
    })?;
    Ok((bytes, room))
}

async fn put_asset(
    State(state): Shared,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: axum::body::Body,
) -> Result<Response, AppError> {
    // Who and what first: nothing of the body is read before the token and the id are checked
    // and the declared length fits, so an unauthorised upload costs no memory.
    authorise(&state, &headers)?;
    crate::store::validate_id(&id)?;
    let (body, room) = read_body(&state, &headers, body, state.max_upload).await?;
    let existed = state.store.get(&id).is_ok();
    let st = state.clone();
    let id2 = id.clone();
    // Parsing checks the whole file (checksum, headers, streams) before anything is written;
    // its cost is bounded by the asset limits, and it runs in the heavy lane when large.
    let cost = (body.len() as u64).saturating_mul(16);
    let stored = decode(&state, cost, move |_| {
        let out = st.store.put(&id2, &body);
        drop(room);
        out
    })
    .await??;
    let status = if existed {
        StatusCode::OK
    } else {
        StatusCode::CREATED
    };
    Ok((status, Json(summary(&state, &stored))).into_response())
}

async fn delete_asset(
    State(state): Shared,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<StatusCode, AppError> {
    authorise(&state, &headers)?;
    state.store.delete(&id)?;
    Ok(StatusCode::NO_CONTENT)
}

async fn asset_info(
    State(state): Shared,
    Path(id): Path<String>,
) -> Result<Json<AssetSummary>, AppError> {
    let a = state.store.get(&id)?;
    Ok(Json(summary(&state, &a)))
}

/// Zoom at which a tile pixel is about the size of a source cell (deeper zooms decode detail the
/// source never had: the point of a fractal codec, hence `maxzoom` goes 4 levels further).
fn native_zoom(a: &StoredAsset, tile_size: usize) -> u8 {
    let width = a.asset.meta.width as f64;
    let degrees = a
        .placement
        .as_ref()
        .map(|p| p.bounds()[2] - p.bounds()[0])
        .unwrap_or(360.0);
    let pixels_world = width * 360.0 / degrees;
    (pixels_world / tile_size as f64)
        .log2()
        .ceil()
        .clamp(0.0, 22.0) as u8
}

async fn tilejson(
    State(state): Shared,
    Path(id): Path<String>,
) -> Result<Json<TileJson>, AppError> {
    let a = planar(state.store.get(&id)?)?;
    let heights = a.asset.meta.kind == AssetKind::HeightField;
    let (ext, query) = if heights {
        ("png", "?encoding=terrarium")
    } else {
        ("png", "")
    };
    let native = native_zoom(&a, 256);
    let bounds = a.placement.as_ref().map(|p| {
        let [w, s, e, n] = p.bounds();
        [
            w.max(-180.0),
            s.max(-geo::MAX_LATITUDE),
            e.min(180.0),
            n.min(geo::MAX_LATITUDE),
        ]
    });
    Ok(Json(TileJson {
        tilejson: "3.0.0".into(),
        name: a.id.clone(),
        tiles: vec![format!(
            "{}/v1/assets/{}/tiles/{{z}}/{{x}}/{{y}}.{ext}{query}",
            state.public_url, a.id
        )],
        minzoom: 0,
        maxzoom: (native + 4).min(state.limits.max_zoom),
        bounds: bounds.unwrap_or([-180.0, -geo::MAX_LATITUDE, 180.0, geo::MAX_LATITUDE]),
        tile_size: 256,
        encoding: heights.then(|| "terrarium".into()),
    }))
}

#[derive(Deserialize)]
struct TileQuery {
    iterations: Option<u32>,
    tolerance: Option<f32>,
    backend: Option<String>,
    tilesize: Option<usize>,
    encoding: Option<String>,
    rescale: Option<String>,
    colormap: Option<String>,
    hillshade: Option<bool>,
}

/// Steps and per-point tolerance of a request. `iterations` alone: exactly that many steps.
/// `tolerance` (value units): each point stops once its own a-priori bound is under it, within
/// `iterations` or the limit. Neither: the tolerance is half a quantisation step of the source
/// (1 for integer samples, 1/65535 of the range for floats).
fn iterations_for(
    state: &AppState,
    a: &StoredAsset,
    asked: Option<u32>,
    tolerance: Option<f32>,
) -> Result<(u32, f32), AppError> {
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
        (_, Some(t)) => Ok((n, t)),
        (Some(n), None) => Ok((n, 0.0)),
        (None, None) => {
            let m = &a.asset.meta;
            let step = match m.sample {
                fractile_proto::SampleFormat::F32 => (m.value_max - m.value_min) / 65535.0,
                fractile_proto::SampleFormat::I8 => (m.value_max - m.value_min) / 254.0,
                _ => 1.0,
            };
            Ok((max, 0.5 * step as f32))
        }
    }
}

fn etag(a: &StoredAsset, key: &str) -> String {
    let mut h = std::hash::DefaultHasher::new();
    (a.hash, key).hash(&mut h);
    format!("\"{:016x}\"", h.finish())
}

fn cached_response(state: &AppState, tag: &str, c: &Cached) -> Response {
    let mut r = (StatusCode::OK, c.body.clone()).into_response();
    let h = r.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(c.content_type),
    );
    h.insert(header::ETAG, HeaderValue::from_str(tag).expect("hex etag"));
    if let Ok(v) = HeaderValue::from_str(&state.cache_control) {
        h.insert(header::CACHE_CONTROL, v);
    }
    h.insert(
        "x-error-bound",
        HeaderValue::from_str(&format!("{}", c.error_bound)).expect("number"),
    );
    r
}

fn not_modified(headers: &HeaderMap, tag: &str) -> bool {
    headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == tag))
}

async fn tile(
    State(state): Shared,
    Path((id, z, x, tile)): Path<(String, u8, u32, String)>,
    Query(q): Query<TileQuery>,
    headers: HeaderMap,
) -> Result<Response, AppError> {
    let a = planar(state.store.get(&id)?)?;
    let (y, ext) = tile
        .split_once('.')
        .ok_or_else(|| AppError::bad_request("bad_tile", "expected {y}.png or {y}.f32"))?;
    let y: u32 = y
        .parse()
        .map_err(|_| AppError::bad_request("bad_tile", format!("bad tile row {y:?}")))?;
    if z > state.limits.max_zoom || x >= (1u32 << z) || y >= (1u32 << z) {
        return Err(AppError::not_found(
            "no_tile",
            format!("tile {z}/{x}/{y} does not exist"),
        ));
    }
    let size = q.tilesize.unwrap_or(256);
    if size != 256 && size != 512 {
        return Err(AppError::bad_request(
            "bad_tilesize",
            "tilesize must be 256 or 512",
        ));
    }
    let heights = a.asset.meta.kind == AssetKind::HeightField;
    let format = match (ext, heights, q.encoding.as_deref()) {
        ("f32", true, _) => encoding::TileFormat::F32,
        ("f32", false, _) => {
            return Err(AppError::bad_request(
                "bad_format",
                "f32 tiles are for height fields",
            ));
        }
        ("png", true, Some("terrainrgb")) => {
            encoding::TileFormat::Heights(HeightEncoding::TerrainRgb)
        }
        ("png", true, Some("terrarium")) => {
            encoding::TileFormat::Heights(HeightEncoding::Terrarium)
        }
        ("png", true, Some("gray16")) => encoding::TileFormat::Heights(HeightEncoding::Gray16),
        ("png", true, None) => encoding::TileFormat::Visual(parse_rescale(&q.rescale, &a)?),
        ("png", false, None) => encoding::TileFormat::Visual(None),
        ("png", _, Some(e)) => {
            return Err(AppError::bad_request(
                "bad_encoding",
                format!("unknown encoding {e:?} (terrainrgb, terrarium, gray16)"),
            ));
        }
        (e, ..) => {
            return Err(AppError::bad_request(
                "bad_format",
                format!("unknown tile format {e:?} (png, f32)"),
            ));
        }
    };
    let (iterations, tolerance) = iterations_for(&state, &a, q.iterations, q.tolerance)?;
    let visual_heights = heights && ext == "png" && q.encoding.is_none();
    let colormap = match q.colormap.as_deref() {
        None => None,
        Some(name) if visual_heights => Some(
            fractile_codec::render::Colormap::parse(name).ok_or_else(|| {
                AppError::bad_request(
                    "bad_colormap",
                    format!("unknown colormap {name:?} (gray, terrain, viridis)"),
                )
            })?,
        ),
        Some(_) => {
            return Err(AppError::bad_request(
                "bad_colormap",
                "colormap is for visual PNG tiles of height fields",
            ));
        }
    };
    let shade = q.hillshade.unwrap_or(false);
    if shade && !visual_heights {
        return Err(AppError::bad_request(
            "bad_hillshade",
            "hillshade is for visual PNG tiles of height fields",
        ));
    }
    // Outside the asset: 404, so that map clients over-zoom the parent instead. Checked on the
    // tile's bounds first (cheap); a tile that only grazes the asset is decoded.
    if let Some(p) = &a.placement {
        let [w, s, e, n] = geo::tile_bounds(z, x, y);
        let [aw, as_, ae, an] = p.bounds();
        let global = ae - aw >= 360.0 - 1e-9;
        if (!global && (e <= aw || w >= ae)) || n <= as_ || s >= an {
            return Err(AppError::not_found(
                "outside",
                format!("tile {z}/{x}/{y} is outside the asset"),
            ));
        }
    }
    // Checked before the cache, so that a bad parameter is refused even for a cached tile.
    let choice = backend_for(&state, q.backend.as_deref())?;
    // The asset's checksum is part of the key: a replaced asset never serves stale tiles.
    let key = format!(
        "{id}@{:08x}/{z}/{x}/{y}.{ext}?{:?}&{:?}&{size}&{:?}&{:?}&{:?}&{shade}",
        a.hash, q.iterations, q.tolerance, q.encoding, q.rescale, q.colormap
    );
    let tag = etag(&a, &key);
    if not_modified(&headers, &tag) {
        return Ok((StatusCode::NOT_MODIFIED, [(header::ETAG, tag)]).into_response());
    }
    if let Some(c) = state.cache.get(&key) {
        metrics::counter!("fractile_tile_cache_total", "result" => "hit").increment(1);
        return Ok(cached_response(&state, &tag, &c));
    }
    metrics::counter!("fractile_tile_cache_total", "result" => "miss").increment(1);
    let asset = a.clone();
    let gpu = state.gpu.clone();
    let coarse = state.coarse.clone();
    let side = size + 2 * usize::from(shade);
    let cost = sampling_bytes(side * side, a.asset.meta.channels);
    let cached = decode(&state, cost, move |cancel| {
        // Hillshading needs each pixel's neighbours: decode a one-pixel margin around the tile,
        // so that shading is seamless across tiles.
        let margin = usize::from(shade);
        let grid = geo::tile_pixels(asset.placement.as_ref(), z, x, y, size, margin);
        if grid.is_outside() {
            return Ok(None);
        }
        let footprint = grid.footprint;
        let (mut channels, bound) = sample_on(
            (gpu.as_deref(), &coarse, cancel),
            choice,
            &asset,
            &grid,
            iterations,
            tolerance,
        )?;
        let style = (colormap.is_some() || shade).then(|| {
            let side = size + 2 * margin;
            let shade = shade.then(|| {
                // Cell size in the heights' units: metres for geographic assets, source pixels
                // otherwise.
                let spacing = match &asset.placement {
                    Some(_) => {
                        let [w, s, e, n] = geo::tile_bounds(z, x, y);
                        let m = geo::metres_per_degree(0.5 * (s + n));
                        [
                            ((e - w) / size as f64 * m[0]) as f32,
                            ((n - s) / size as f64 * m[1]) as f32,
                        ]
                    }
                    None => [
                        footprint[0] * asset.asset.meta.width as f32,
                        footprint[1] * asset.asset.meta.height as f32,
                    ],
                };
                fractile_codec::render::hillshade(&channels[0], size, size, spacing, 315.0, 45.0)
            });
            if margin > 0 {
                for ch in &mut channels {
                    *ch = (0..size * size)
                        .map(|k| ch[(k / size + margin) * side + k % size + margin])
                        .collect();
                }
            }
            encoding::Style { colormap, shade }
        });
        let (content_type, body) =
            encoding::encode_tile(&asset.asset.meta, &channels, size, format, style);
        Ok::<_, AppError>(Some(Cached {
            content_type,
            body: Bytes::from(body),
            error_bound: bound,
        }))
    })
    .await??
    .ok_or_else(|| {
        AppError::not_found("outside", format!("tile {z}/{x}/{y} is outside the asset"))
    })?;
    let cached = Arc::new(cached);
    state.cache.insert(key, cached.clone());
    Ok(cached_response(&state, &tag, &cached))
}

fn parse_rescale(r: &Option<String>, a: &StoredAsset) -> Result<Option<(f32, f32)>, AppError> {
    let Some(r) = r else {
        return Ok(Some((
            a.asset.meta.value_min as f32,
            a.asset.meta.value_max as f32,
        )));
    };
    let v: Vec<f32> = r.split(',').filter_map(|s| s.trim().parse().ok()).collect();
    match v[..] {
        [lo, hi] if hi > lo => Ok(Some((lo, hi))),
        _ => Err(AppError::bad_request(
            "bad_rescale",
            "rescale must be min,max with max > min",
        )),
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

#[derive(Deserialize)]
struct PointQuery {
    x: Option<f64>,
    y: Option<f64>,
    /// Volumes only: the third coordinate.
    z: Option<f64>,
    iterations: Option<u32>,
    tolerance: Option<f32>,
}

async fn point_unit(
    State(state): Shared,
    Path(id): Path<String>,
    Query(q): Query<PointQuery>,
) -> Result<Response, AppError> {
    let a = state.store.get(&id)?;
    if a.asset.meta.kind == AssetKind::Curve {
        planar(a.clone())?;
    }
    if a.asset.meta.kind == AssetKind::Volume {
        return volume_point(&state, a, &q)
            .await
            .map(|r| Json(r).into_response());
    }
    if q.z.is_some() {
        return Err(AppError::bad_request(
            "bad_point",
            "z is for volume assets; this one is 2D",
        ));
    }
    let (Some(x), Some(y)) = (q.x, q.y) else {
        return Err(AppError::bad_request(
            "bad_point",
            "give ?x=&y= in unit coordinates (or /point/{lon},{lat})",
        ));
    };
    answer_points(
        &state,
        &id,
        vec![[x, y]],
        (q.iterations, q.tolerance),
        true,
        Backend::Cpu,
    )
    .await
    .map(|mut v| Json(v.remove(0)).into_response())
}

/// The signed distance of a volume at world point (x, y, z).
async fn volume_point(
    state: &Arc<AppState>,
    a: Arc<StoredAsset>,
    q: &PointQuery,
) -> Result<DistanceResult, AppError> {
    let (Some(x), Some(y), Some(z)) = (q.x, q.y, q.z) else {
        return Err(AppError::bad_request(
            "bad_point",
            "give ?x=&y=&z= in the mesh's units for a volume asset",
        ));
    };
    let p = [x, y, z];
    if p.iter().any(|v| !v.is_finite()) {
        return Err(AppError::bad_request(
            "bad_point",
            "coordinates must be finite",
        ));
    }
    let (n, tolerance) = iterations_for(state, &a, q.iterations, q.tolerance)?;
    let sample = decode(state, 0, move |_| a.asset.distances(&[p], n, tolerance))
        .await?
        .map_err(|e| AppError::internal(e.to_string()))?
        .remove(0);
    match sample {
        Some(s) => Ok(DistanceResult {
            coordinates: p,
            distance: Some(s.distance),
            error_bound: Some(s.error_bound),
            iterations: s.iterations,
            outside: false,
        }),
        None => Err(AppError::not_found(
            "outside",
            format!("point {p:?} is outside the volume's grid"),
        )),
    }
}

async fn point_lonlat(
    State(state): Shared,
    Path((id, coords)): Path<(String, String)>,
    Query(q): Query<PointQuery>,
) -> Result<Json<PointResult>, AppError> {
    let c: Vec<f64> = coords
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .collect();
    let [lon, lat] = c[..] else {
        return Err(AppError::bad_request(
            "bad_point",
            format!("expected lon,lat, got {coords:?}"),
        ));
    };
    // One chain: never worth a device round trip.
    answer_points(
        &state,
        &id,
        vec![[lon, lat]],
        (q.iterations, q.tolerance),
        true,
        Backend::Cpu,
    )
    .await
    .map(|mut v| Json(v.remove(0)))
}

#[derive(Deserialize)]
struct PointsQuery {
    backend: Option<String>,
}

async fn points(
    State(state): Shared,
    Path(id): Path<String>,
    Query(q): Query<PointsQuery>,
    headers: HeaderMap,
    body: axum::body::Body,
) -> Result<Response, AppError> {
    let choice = backend_for(&state, q.backend.as_deref())?;
    // A full batch in JSON is about 40 bytes a point: room for the point limit, and more.
    let limit = 64 * state.limits.max_points.max(1);
    let (body, _room) = read_body(&state, &headers, body, limit).await?;
    let binary = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with(BINARY_MEDIA_TYPE));
    let req: PointsRequest = if binary {
        fractile_proto::decode(&body)
            .map_err(|e| AppError::bad_request("bad_body", e.to_string()))?
    } else {
        serde_json::from_slice(&body)
            .map_err(|e| AppError::bad_request("bad_body", e.to_string()))?
    };
    if req.points.len() > state.limits.max_points {
        return Err(AppError {
            status: StatusCode::PAYLOAD_TOO_LARGE,
            code: "too_many_points",
            detail: format!(
                "{} points over the limit {}",
                req.points.len(),
                state.limits.max_points
            ),
        });
    }
    let results = answer_points(
        &state,
        &id,
        req.points,
        (req.iterations, req.tolerance),
        false,
        choice,
    )
    .await?;
    let resp = PointsResponse { results };
    Ok(if binary {
        (
            [(header::CONTENT_TYPE, BINARY_MEDIA_TYPE)],
            fractile_proto::encode(&resp),
        )
            .into_response()
    } else {
        Json(resp).into_response()
    })
}

async fn answer_points(
    state: &Arc<AppState>,
    id: &str,
    coords: Vec<[f64; 2]>,
    (iterations, tolerance): (Option<u32>, Option<f32>),
    single: bool,
    choice: Backend,
) -> Result<Vec<PointResult>, AppError> {
    let a = planar(state.store.get(id)?)?;
    let (n, tolerance) = iterations_for(state, &a, iterations, tolerance)?;
    let units: Vec<Option<[f32; 2]>> = coords.iter().map(|&c| unit_of(&a, c)).collect();
    if single && units[0].is_none() {
        return Err(AppError::not_found(
            "outside",
            format!("point {:?} is outside the asset", coords[0]),
        ));
    }
    let gpu = state.gpu.clone();
    let cost = sampling_bytes(coords.len(), a.asset.meta.channels);
    decode(state, cost, move |_| {
        let inside: Vec<[f32; 2]> = units.iter().map(|u| u.unwrap_or([0.0, 0.0])).collect();
        let samples = match gpu.as_deref().filter(|g| g.takes(choice, inside.len())) {
            Some(g) => a.asset.points_with(&inside, n, tolerance, &|k, p, n, t| {
                g.points(&a, k, p, n, t)
            }),
            None => a.asset.points(&inside, n, tolerance),
        };
        coords
            .iter()
            .zip(&units)
            .zip(samples)
            .map(|((&c, u), s)| match u {
                Some(_) => PointResult {
                    coordinates: c,
                    values: Some(
                        s.values
                            .iter()
                            .map(|v| v.is_finite().then_some(*v))
                            .collect(),
                    ),
                    error_bound: Some(s.error_bound),
                    iterations: s.iterations,
                    outside: false,
                },
                None => PointResult {
                    coordinates: c,
                    values: None,
                    error_bound: None,
                    iterations: 0,
                    outside: true,
                },
            })
            .collect()
    })
    .await
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

#[derive(Deserialize)]
struct MeshQuery {
    bbox: Option<String>,
    resolution: Option<usize>,
    /// Height fields: an adaptive triangulation whose surface stays within this many height
    /// units of the decoded grid (absent: the regular grid).
    max_error: Option<f32>,
    iterations: Option<u32>,
    tolerance: Option<f32>,
    backend: Option<String>,
    format: Option<String>,
}

/// A terrain mesh of a region: a regular grid of `resolution x resolution` vertices, or with
/// `max_error` an adaptive triangulation (RTIN) of the grid of the next `2^k + 1` vertices a
/// side whose surface stays within `max_error` of every decoded height. For georeferenced
/// assets x and y are metres east and north of the box's south-west corner (a local tangent
/// plane) and z is the height; otherwise x and y are source pixels. `X-Error-Bound` is the
/// decoding bound, plus `max_error` for adaptive meshes.
async fn mesh(
    State(state): Shared,
    Path(id): Path<String>,
    Query(q): Query<MeshQuery>,
) -> Result<Response, AppError> {
    let a = state.store.get(&id)?;
    if a.asset.meta.kind == AssetKind::Volume {
        return volume_mesh(&state, a, q).await;
    }
    if a.asset.meta.kind != AssetKind::HeightField {
        return Err(AppError::bad_request(
            "not_terrain",
            "meshes are made of height fields and volumes",
        ));
    }
    let n = q.resolution.unwrap_or(256);
    if !(2..=2048).contains(&n) {
        return Err(AppError::bad_request(
            "bad_resolution",
            "resolution must be 2..=2048 vertices a side",
        ));
    }
    let max_error = q.max_error;
    if max_error.is_some_and(|e| !(e.is_finite() && e >= 0.0)) {
        return Err(AppError::bad_request(
            "bad_max_error",
            "max_error must be a number >= 0 (height units)",
        ));
    }
    // The network splits squares in halves down to single cells: 2^k + 1 vertices a side.
    let n = match max_error {
        Some(_) => (n - 1).next_power_of_two() + 1,
        None => n,
    };
    let format = q.format.unwrap_or_else(|| "glb".into());
    if !matches!(format.as_str(), "obj" | "ply" | "glb") {
        return Err(AppError::bad_request(
            "bad_format",
            "format must be obj, ply or glb",
        ));
    }
    let [x0, y0, x1, y1] = match &q.bbox {
        Some(b) => parse_bbox(b)?,
        None => match &a.placement {
            Some(p) => p.bounds(),
            None => [0.0, 0.0, 1.0, 1.0],
        },
    };
    let (iterations, tolerance) = iterations_for(&state, &a, q.iterations, q.tolerance)?;
    let geo_ref = a.placement.is_some();
    // Vertex (i, j): i east, j south, corners included.
    let frac = |k: usize| k as f64 / (n - 1) as f64;
    let grid = box_pixels(
        &a,
        (n, |i| x0 + frac(i) * (x1 - x0)),
        (n, |j| {
            if geo_ref {
                y1 - frac(j) * (y1 - y0)
            } else {
                y0 + frac(j) * (y1 - y0)
            }
        }),
        cell_size([x0, y0, x1, y1], n - 1, n - 1),
    );
    if grid.is_outside() {
        return Err(AppError::not_found(
            "outside",
            "the box is outside the asset",
        ));
    }
    let (extent_x, extent_y) = if geo_ref {
        let m = geo::metres_per_degree(0.5 * (y0 + y1));
        ((x1 - x0) * m[0], (y1 - y0) * m[1])
    } else {
        (
            (x1 - x0) * a.asset.meta.width as f64,
            (y1 - y0) * a.asset.meta.height as f64,
        )
    };
    let (choice, gpu, coarse) = (
        backend_for(&state, q.backend.as_deref())?,
        state.gpu.clone(),
        state.coarse.clone(),
    );
    // Samples, then the mesh (a vertex and two triangles a sample, with normals) and its
    // writer's buffers: about 96 bytes a vertex.
    let cost = sampling_bytes(n * n, 1) + (n * n) as u64 * 96;
    state
        .lanes
        .stream(cost, move |cancel| {
            let (channels, bound) = sample_on(
                (gpu.as_deref(), &coarse, cancel),
                choice,
                &a,
                &grid,
                iterations,
                tolerance,
            )?;
            let spacing = [
                (extent_x / (n - 1) as f64) as f32,
                (extent_y / (n - 1) as f64) as f32,
            ];
            let origin = [0.0, extent_y as f32];
            let m = match max_error {
                Some(e) => {
                    fractile_codec::mesh::Mesh::adaptive(&channels[0], n, origin, spacing, e)
                        .map_err(|e| AppError::internal(e.to_string()))?
                }
                None => fractile_codec::mesh::Mesh::grid(&channels[0], n, n, origin, spacing),
            };
            Ok(mesh_body(m, &format, bound + max_error.unwrap_or(0.0)))
        })
        .await
}

/// The head and writer of a mesh answer in `format` (obj, ply or glb): text and PLY are
/// written as they stream; GLB, whose header holds its length, is built whole (it is the
/// compact one, about 24 bytes a vertex).
fn mesh_body(m: fractile_codec::mesh::Mesh, format: &str, error_bound: f32) -> (Head, BodyWriter) {
    let (content_type, writer): (&'static str, BodyWriter) = match format {
        "obj" => ("text/plain", Box::new(move |w| m.write_obj(w))),
        "ply" => (
            "application/octet-stream",
            Box::new(move |w| m.write_ply(w)),
        ),
        _ => (
            "model/gltf-binary",
            Box::new(move |w: &mut dyn std::io::Write| w.write_all(&m.to_glb())),
        ),
    };
    (
        Head {
            content_type,
            error_bound,
        },
        writer,
    )
}

/// Largest samples a volume mesh request decodes (256^3).
const MAX_VOLUME_SAMPLES: usize = 1 << 24;

/// The surface of a volume inside `bbox=x0,y0,z0,x1,y1,z1` (world units; default the whole
/// grid) with `resolution` samples along the box's longest side (default the encoded grid).
async fn volume_mesh(
    state: &Arc<AppState>,
    a: Arc<StoredAsset>,
    q: MeshQuery,
) -> Result<Response, AppError> {
    if q.max_error.is_some() {
        return Err(AppError::bad_request(
            "bad_max_error",
            "max_error (an adaptive triangulation) is for height fields",
        ));
    }
    let grid = a.asset.volume.as_ref().map_or(64, |v| v.size());
    let n = q.resolution.unwrap_or(grid);
    if !(2..=512).contains(&n) {
        return Err(AppError::bad_request(
            "bad_resolution",
            "resolution must be 2..=512 samples along the box's longest side",
        ));
    }
    let format = q.format.unwrap_or_else(|| "glb".into());
    if !matches!(format.as_str(), "obj" | "ply" | "glb") {
        return Err(AppError::bad_request(
            "bad_format",
            "format must be obj, ply or glb",
        ));
    }
    let bbox = match &q.bbox {
        None => None,
        Some(b) => {
            let v: Vec<f64> = b.split(',').filter_map(|s| s.trim().parse().ok()).collect();
            match v[..] {
                [x0, y0, z0, x1, y1, z1]
                    if x1 > x0 && y1 > y0 && z1 > z0 && v.iter().all(|c| c.is_finite()) =>
                {
                    Some(([x0, y0, z0], [x1, y1, z1]))
                }
                _ => {
                    return Err(AppError::bad_request(
                        "bad_bbox",
                        "a volume's bbox is x0,y0,z0,x1,y1,z1 with max > min on every axis",
                    ));
                }
            }
        }
    };
    // The samples the box will take, refused before any decoding.
    if let Some((lo, hi)) = bbox {
        let longest = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
        let samples: f64 = (0..3)
            .map(|k| ((hi[k] - lo[k]) / longest * (n - 1) as f64).round() + 1.0)
            .product();
        if samples > MAX_VOLUME_SAMPLES as f64 {
            return Err(AppError::bad_request(
                "too_many_samples",
                format!("the box takes {samples} samples, over {MAX_VOLUME_SAMPLES}"),
            ));
        }
    } else if n.pow(3) > MAX_VOLUME_SAMPLES {
        return Err(AppError::bad_request(
            "too_many_samples",
            format!(
                "resolution {n} takes {} samples, over {MAX_VOLUME_SAMPLES}",
                n.pow(3)
            ),
        ));
    }
    let (iterations, tolerance) = iterations_for(state, &a, q.iterations, q.tolerance)?;
    let (choice, gpu) = (backend_for(state, q.backend.as_deref())?, state.gpu.clone());
    let samples = match bbox {
        Some((lo, hi)) => {
            let longest = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
            (0..3)
                .map(|k| ((hi[k] - lo[k]) / longest * (n - 1) as f64).round() + 1.0)
                .product::<f64>() as u64
        }
        None => (n as u64).pow(3),
    };
    // A distance a sample, and a surface of up to a few vertices per surface cell.
    let cost = samples * 16 + (n as u64).pow(2) * 256;
    state
        .lanes
        .stream(cost, move |_| {
            let on_gpu = |lo, hi, dims: [usize; 3], n, t| {
                gpu.as_deref()
                    .filter(|g| g.takes(choice, dims.iter().product()))
                    .and_then(|g| g.volume_grid(&a, (lo, hi, dims), n, t))
            };
            let (m, bound) = a
                .asset
                .volume_mesh_with(bbox, n, iterations, tolerance, Some(&on_gpu))
                .map_err(|e| AppError::bad_request("bad_request", e.to_string()))?;
            Ok(mesh_body(m, &format, bound))
        })
        .await
}

#[derive(Deserialize)]
struct RegionQuery {
    bbox: String,
    width: usize,
    height: usize,
    iterations: Option<u32>,
    tolerance: Option<f32>,
    backend: Option<String>,
    format: Option<String>,
}

async fn region(
    State(state): Shared,
    Path(id): Path<String>,
    Query(q): Query<RegionQuery>,
) -> Result<Response, AppError> {
    let a = planar(state.store.get(&id)?)?;
    let [x0, y0, x1, y1] = parse_bbox(&q.bbox)?;
    if q.width == 0
        || q.height == 0
        || q.width.saturating_mul(q.height) > state.limits.max_region_pixels
    {
        return Err(AppError::bad_request(
            "bad_size",
            format!(
                "width x height must be 1..={} pixels",
                state.limits.max_region_pixels
            ),
        ));
    }
    let (n, tolerance) = iterations_for(&state, &a, q.iterations, q.tolerance)?;
    let format = q.format.as_deref().unwrap_or("png");
    if format == "tif" && a.asset.meta.kind != AssetKind::HeightField {
        return Err(AppError::bad_request(
            "bad_format",
            "GeoTIFF regions are for height fields (use png)",
        ));
    }
    if !matches!(format, "png" | "f32" | "tif") {
        return Err(AppError::bad_request(
            "bad_format",
            "format must be png, f32 or tif",
        ));
    }
    let (w, h) = (q.width, q.height);
    // Pixel centres in the request's coordinates: lon/lat (north up) or unit x/y (y down).
    let geo_ref = a.placement.is_some();
    let grid = box_pixels(
        &a,
        (w, |i| x0 + (i as f64 + 0.5) / w as f64 * (x1 - x0)),
        (h, |j| {
            let fy = (j as f64 + 0.5) / h as f64;
            if geo_ref {
                y1 - fy * (y1 - y0)
            } else {
                y0 + fy * (y1 - y0)
            }
        }),
        cell_size([x0, y0, x1, y1], w, h),
    );
    let f32_out = format == "f32";
    let tif_out = format == "tif";
    // The GeoTIFF's georeference is the requested box (north-up, lon/lat for georeferenced
    // assets).
    let tif_georef = a
        .asset
        .meta
        .georef
        .as_ref()
        .map(|g| fractile_proto::Georef {
            // Boxes are lon/lat: the region of a projected asset is in EPSG:4326 too.
            epsg: match a.placement.as_ref().and_then(|p| p.epsg()) {
                Some(_) => Some(4326),
                None => g.epsg,
            },
            origin: [x0, y1],
            pixel_size: [(x1 - x0) / w as f64, -(y1 - y0) / h as f64],
        });
    let (choice, gpu, coarse) = (
        backend_for(&state, q.backend.as_deref())?,
        state.gpu.clone(),
        state.coarse.clone(),
    );
    let channels = a.asset.meta.channels;
    // Sampling, then the encoded body (at most 4 bytes a value).
    let cost = sampling_bytes(w * h, channels) + (w * h) as u64 * 4 * u64::from(channels);
    state
        .lanes
        .stream(cost, move |cancel| {
            let (channels, bound) = sample_on(
                (gpu.as_deref(), &coarse, cancel),
                choice,
                &a,
                &grid,
                n,
                tolerance,
            )?;
            let (content_type, body) = if tif_out {
                let nodata = a.asset.meta.nodata;
                let values: Vec<f32> = match nodata {
                    Some(nd) => channels[0]
                        .iter()
                        .map(|&v| if v.is_nan() { nd as f32 } else { v })
                        .collect(),
                    None => channels[0].clone(),
                };
                let tif =
                    fractile_codec::raster::geotiff_f32(w, h, &values, tif_georef.as_ref(), nodata)
                        .map_err(|e| AppError::internal(e.to_string()))?;
                ("image/tiff", tif)
            } else if f32_out {
                (
                    "application/octet-stream",
                    channels
                        .iter()
                        .flat_map(|c| c.iter().flat_map(|v| v.to_le_bytes()))
                        .collect(),
                )
            } else {
                let fmt = if a.asset.meta.kind == AssetKind::HeightField {
                    encoding::TileFormat::Visual(Some((
                        a.asset.meta.value_min as f32,
                        a.asset.meta.value_max as f32,
                    )))
                } else {
                    encoding::TileFormat::Visual(None)
                };
                encoding::encode_raster(&a.asset.meta, &channels, w, h, fmt, None)
            };
            let head = Head {
                content_type,
                error_bound: bound,
            };
            let writer: BodyWriter =
                Box::new(move |out: &mut dyn std::io::Write| out.write_all(&body));
            Ok((head, writer))
        })
        .await
}

/// The default request timeout.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);

/// Query of `GET /v1/assets/{id}/curve`.
#[derive(Deserialize)]
pub struct CurveQuery {
    /// Asset level; the finest (the input's) when absent.
    level: Option<usize>,
    /// `true`: each ring's base control points (level 0 of the model, what a `control`
    /// deformation moves) instead of the curve. They are in the model's frame: along a ring
    /// that crosses the antimeridian, longitudes are unwrapped (may pass ±180°).
    #[serde(default)]
    control: bool,
}

/// Most points one curve answer may hold (each level doubles them).
const MAX_CURVE_POINTS: u128 = 1 << 22;

fn curves_of(a: &StoredAsset) -> Result<&fractile_codec::curve::Curves, AppError> {
    a.asset.curve.as_ref().ok_or_else(|| {
        AppError::bad_request(
            "not_curve",
            format!("{} is not a curve asset ({:?})", a.id, a.asset.meta.kind),
        )
    })
}

fn check_level(set: &fractile_codec::curve::CurveSet, level: usize) -> Result<(), AppError> {
    if set.points_at(level) > MAX_CURVE_POINTS {
        return Err(AppError::bad_request(
            "too_many_points",
            format!(
                "level {level} would answer over {MAX_CURVE_POINTS} points (the finest level is {})",
                set.finest()
            ),
        ));
    }
    Ok(())
}

fn geojson_response(doc: serde_json::Value) -> Response {
    ([(header::CONTENT_TYPE, "application/geo+json")], Json(doc)).into_response()
}

/// A curve asset as GeoJSON at any level (deeper than the source: self-similar detail), one
/// LineString Feature per input ring, with the level's Hausdorff error bound.
async fn curve(
    State(state): Shared,
    Path(id): Path<String>,
    Query(q): Query<CurveQuery>,
) -> Result<Response, AppError> {
    let a = state.store.get(&id)?;
    let set = &curves_of(&a)?.set;
    let level = q.level.unwrap_or_else(|| set.finest());
    check_level(set, level)?;
    let units = a.asset.meta.units.clone().unwrap_or_default();
    let control = q.control;
    let a2 = a.clone();
    let doc = decode(&state, 0, move |_| {
        let c = a2.asset.curve.as_ref().expect("checked above");
        if control {
            let lines = c.set.rings.iter().map(|r| r.base.clone()).collect();
            let closed = c.set.rings.iter().map(|r| r.closed).collect();
            let level = fractile_codec::curve::CurveLevel {
                level: 0,
                lines,
                closed,
                error_bound: f64::NAN,
            };
            return fractile_codec::curve::geojson::write(&level, c.set.finest(), &units);
        }
        let decoded = c.set.at_level(level);
        fractile_codec::curve::geojson::write(&decoded, c.set.finest(), &units)
    })
    .await?;
    Ok(geojson_response(doc))
}

/// Deforms a curve asset (stateless: the stored asset is unchanged) and answers GeoJSON.
async fn curve_deform(
    State(state): Shared,
    Path(id): Path<String>,
    body: Result<Json<fractile_proto::DeformRequest>, axum::extract::rejection::JsonRejection>,
) -> Result<Response, AppError> {
    let Json(req) = body.map_err(|e| AppError::bad_request("bad_body", e.body_text()))?;
    let a = state.store.get(&id)?;
    let set = &curves_of(&a)?.set;
    if req.deformations.len() > 1024 {
        return Err(AppError::bad_request(
            "bad_body",
            "at most 1024 deformations per request",
        ));
    }
    let level = req.level.unwrap_or_else(|| set.finest());
    check_level(set, level)?;
    let units = a.asset.meta.units.clone().unwrap_or_default();
    let a2 = a.clone();
    let doc = decode(&state, 0, move |_| {
        let c = a2.asset.curve.as_ref().expect("checked above");
        let deformed = fractile_codec::curve::deform::apply(&c.set, &req.deformations)?;
        let decoded = deformed.at_level(level);
        Ok::<_, String>(fractile_codec::curve::geojson::write(
            &decoded,
            deformed.finest(),
            &units,
        ))
    })
    .await?
    .map_err(|e| AppError::bad_request("bad_deformation", e))?;
    Ok(geojson_response(doc))
}
