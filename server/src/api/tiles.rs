//! TileJSON and tiles: Web Mercator (or unit-square) tiles by continuous extraction, cached by ETag.

use fractile_proto::ErrorCode;
use fractile_proto::query::{Colormap, Precision};

use super::request::*;
use super::state::*;
use std::hash::{Hash, Hasher};
use std::sync::Arc;

use crate::error::{Path, Query};
use axum::Json;
use axum::body::Bytes;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use fractile_codec::geo;
use fractile_proto::{AssetKind, TileJson};
use serde::Deserialize;

use crate::backend::{Backend, GpuBackend};
use crate::encoding::{self, HeightEncoding};
use crate::error::AppError;
use crate::store::StoredAsset;
use crate::work::{Bounds, Cancel};

pub(super) async fn tilejson(
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
    let native = geo::native_zoom(a.placement.as_ref(), a.asset.meta.width, 256);
    let bounds = geo::map_bounds(a.placement.as_ref());
    Ok(Json(TileJson {
        tilejson: "3.0.0".into(),
        name: a.id.clone(),
        tiles: vec![format!(
            "{}/v1/assets/{}/tiles/{{z}}/{{x}}/{{y}}.{ext}{query}",
            state.public_url, a.id
        )],
        minzoom: 0,
        maxzoom: (native + 4).min(state.limits.max_zoom),
        bounds,
        tile_size: 256,
        encoding: heights.then(|| "terrarium".into()),
    }))
}

#[derive(Deserialize)]
pub(super) struct TileQuery {
    iterations: Option<u32>,
    tolerance: Option<f32>,
    backend: Option<String>,
    tilesize: Option<usize>,
    encoding: Option<String>,
    rescale: Option<String>,
    colormap: Option<String>,
    hillshade: Option<bool>,
    precision: Option<String>,
}

/// A tile's ETag: the asset's version, the request's key and the build that drew it. A new
/// server build may draw the same tile differently (as when terrain edges were stitched), so
/// a client must not keep an old tile on a 304; replicas running the same binary still agree.
pub(super) fn etag(a: &StoredAsset, key: &str) -> String {
    let mut h = std::hash::DefaultHasher::new();
    (a.hash, key, build_id()).hash(&mut h);
    format!("\"{:016x}\"", h.finish())
}

/// A hash of this server's executable, read once (about 30 ms for 30 MB at startup, see
/// [`super::router`]); the package version where the executable cannot be read. Hashing the
/// binary itself needs no build script and cannot be forgotten the way a hand-bumped
/// revision number can.
pub(super) fn build_id() -> u64 {
    static ID: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *ID.get_or_init(|| {
        let mut h = std::hash::DefaultHasher::new();
        match std::env::current_exe().and_then(std::fs::read) {
            Ok(bytes) => bytes.hash(&mut h),
            Err(_) => env!("CARGO_PKG_VERSION").hash(&mut h),
        }
        h.finish()
    })
}

pub(super) fn cached_response(state: &AppState, tag: &str, c: &Cached) -> Response {
    let mut r = (StatusCode::OK, c.body.clone()).into_response();
    let h = r.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(c.content_type),
    );
    if let Ok(v) = HeaderValue::from_str(tag) {
        h.insert(header::ETAG, v);
    }
    if let Some(e) = c.content_encoding {
        h.insert(header::CONTENT_ENCODING, HeaderValue::from_static(e));
    }
    if let Ok(v) = HeaderValue::from_str(&state.cache_control) {
        h.insert(header::CACHE_CONTROL, v);
    }
    c.bounds.write(h);
    r
}

pub(super) fn not_modified(headers: &HeaderMap, tag: &str) -> bool {
    headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == tag))
}

/// A tile request, checked: which tile, how to decode it and how to encode it.
struct TileJob {
    z: u8,
    x: u32,
    y: u32,
    size: usize,
    format: encoding::TileFormat,
    colormap: Option<fractile_codec::render::Colormap>,
    shade: bool,
    precision: Precision,
    iterations: u32,
    tolerance: super::request::Tolerance,
    /// A lossless WebP (`.webp`) rather than a PNG.
    webp: bool,
}

pub(super) async fn tile(
    State(state): Shared,
    Path((id, z, x, tile)): Path<(String, String, String, String)>,
    Query(q): Query<TileQuery>,
    headers: HeaderMap,
) -> Result<Response, AppError> {
    let a = planar(state.store.get(&id)?)?;
    let (z, x, y, ext) = tile_address(&state, &z, &x, &tile)?;
    let job = tile_job(&state, &a, (z, x, y), ext, &q)?;
    check_inside(&a, z, x, y)?;
    // Checked before the cache, so that a bad parameter is refused even for a cached tile.
    let choice = backend_for(&state, q.backend.as_deref())?;
    // The asset's checksum is part of the key: a replaced asset never serves stale tiles. The
    // rest is the request as checked, not as spelt (`colormap=grey` and `gray`, `rescale=0,1`
    // and `0.0,1.0` are one tile, one cache entry and one ETag).
    let key = format!(
        "{id}@{:08x}/{z}/{x}/{y}.{ext}?{}&{:?}&{}&{:?}&{:?}&{}&{}",
        a.hash,
        job.iterations,
        job.tolerance,
        job.size,
        job.format,
        job.colormap,
        job.shade,
        job.precision
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
    let (gpu, coarse) = (state.gpu.clone(), state.coarse.clone());
    let side = job.size + 2 * usize::from(job.shade);
    let cost = sampling_bytes(side * side, a.asset.meta.channels);
    let asset = a.clone();
    let drawn = decode(&state, cost, move |cancel| {
        draw_tile((gpu.as_deref(), &coarse, cancel), choice, &asset, &job)
    })
    .await??;
    let cached = Arc::new(drawn);
    state.cache.insert(key, cached.clone());
    Ok(cached_response(&state, &tag, &cached))
}

/// The zoom, column, row and extension of `{z}/{x}/{y}.{ext}`: a 400 that says the valid
/// numbers for what is not a tile number (a zoom past 255, a column past 2^32: axum's own
/// rejection would say "Cannot parse value"), and a 404 that says them for a tile that no
/// zoom level has.
fn tile_address<'a>(
    state: &AppState,
    z: &str,
    x: &str,
    tile: &'a str,
) -> Result<(u8, u32, u32, &'a str), AppError> {
    let (y, ext) = tile.split_once('.').ok_or_else(|| {
        AppError::bad_request(ErrorCode::BadTile, "expected {y}.png, {y}.webp or {y}.f32")
    })?;
    let (z, x, y) = super::request::tile_numbers(z, x, y, state.limits.max_zoom, 1)?;
    if z > state.limits.max_zoom || x >= (1u32 << z) || y >= (1u32 << z) {
        return Err(AppError::not_found(
            ErrorCode::NoTile,
            format!(
                "tile {z}/{x}/{y} does not exist: zooms go from 0 to {}, and at zoom {z} \
                 columns and rows from 0 to {}",
                state.limits.max_zoom,
                (1u64 << z.min(32)) - 1
            ),
        ));
    }
    Ok((z, x, y, ext))
}

/// The query checked against the asset: size, format, style, iterations.
fn tile_job(
    state: &AppState,
    a: &StoredAsset,
    (z, x, y): (u8, u32, u32),
    ext: &str,
    q: &TileQuery,
) -> Result<TileJob, AppError> {
    let size = q.tilesize.unwrap_or(256);
    if size != 256 && size != 512 {
        return Err(AppError::bad_request(
            ErrorCode::BadTilesize,
            "tilesize must be 256 or 512",
        ));
    }
    let heights = a.asset.meta.kind == AssetKind::HeightField;
    let format = tile_format(ext, heights, q, a)?;
    let (iterations, tolerance) = iterations_for(state, q.iterations, q.tolerance)?;
    let visual_heights = heights && matches!(ext, "png" | "webp") && q.encoding.is_none();
    let colormap = match q.colormap.as_deref() {
        None => None,
        Some(name) if visual_heights => Some(ramp(name.parse().map_err(|_| {
            AppError::bad_request(
                ErrorCode::BadColormap,
                format!("unknown colormap {name:?} (gray, terrain, viridis)"),
            )
        })?)),
        Some(_) => {
            return Err(AppError::bad_request(
                ErrorCode::BadColormap,
                "colormap is for visual PNG tiles of height fields",
            ));
        }
    };
    let shade = q.hillshade.unwrap_or(false);
    if shade && !visual_heights {
        return Err(AppError::bad_request(
            ErrorCode::BadHillshade,
            "hillshade is for visual PNG tiles of height fields",
        ));
    }
    let precision = match q.precision.as_deref() {
        None => Precision::default(),
        Some(p) => p
            .parse()
            .map_err(|e: String| AppError::bad_request(ErrorCode::BadPrecision, e))?,
    };
    Ok(TileJob {
        z,
        x,
        y,
        size,
        format,
        colormap,
        shade,
        precision,
        iterations,
        tolerance,
        webp: ext == "webp",
    })
}

/// The renderer's colour ramp of the API's `colormap`.
fn ramp(c: Colormap) -> fractile_codec::render::Colormap {
    match c {
        Colormap::Gray => fractile_codec::render::Colormap::Gray,
        Colormap::Terrain => fractile_codec::render::Colormap::Terrain,
        Colormap::Viridis => fractile_codec::render::Colormap::Viridis,
    }
}

/// What the tile's extension and `encoding` ask for, if the asset has it.
fn tile_format(
    ext: &str,
    heights: bool,
    q: &TileQuery,
    a: &StoredAsset,
) -> Result<encoding::TileFormat, AppError> {
    Ok(match (ext, heights, q.encoding.as_deref()) {
        ("f32", true, None) => encoding::TileFormat::F32,
        // Refused rather than ignored: the caller expects encoded PNG heights.
        ("f32", true, Some(e)) => {
            return Err(AppError::bad_request(
                ErrorCode::BadEncoding,
                format!(
                    "encoding={e} is for png and webp tiles; an f32 tile is raw float32 heights"
                ),
            ));
        }
        ("f32", false, _) => {
            return Err(AppError::bad_request(
                ErrorCode::BadFormat,
                "f32 tiles are for height fields",
            ));
        }
        ("webp", true, Some(e)) if e.parse::<HeightEncoding>() == Ok(HeightEncoding::Gray16) => {
            return Err(AppError::bad_request(
                ErrorCode::BadEncoding,
                "gray16 is 16-bit grey, which WebP has not: ask {y}.png or {y}.f32",
            ));
        }
        ("png" | "webp", true, Some(e)) if let Ok(h) = e.parse::<HeightEncoding>() => {
            encoding::TileFormat::Heights(h)
        }
        ("png" | "webp", true, None) => encoding::TileFormat::Visual(parse_rescale(&q.rescale, a)?),
        ("png" | "webp", false, None) => encoding::TileFormat::Visual(None),
        ("png" | "webp", _, Some(e)) => {
            return Err(AppError::bad_request(
                ErrorCode::BadEncoding,
                format!("unknown encoding {e:?} (terrainrgb, terrarium, gray16)"),
            ));
        }
        (e, ..) => {
            return Err(AppError::bad_request(
                ErrorCode::BadFormat,
                format!("unknown tile format {e:?} (png, webp, f32)"),
            ));
        }
    })
}

/// Wholly outside the asset: 404, so that map clients over-zoom the parent instead. Checked on
/// the tile's bounds; a tile that overlaps the asset in any part is answered (200).
fn check_inside(a: &StoredAsset, z: u8, x: u32, y: u32) -> Result<(), AppError> {
    if let Some(p) = &a.placement {
        let [w, s, e, n] = geo::tile_bounds(z, x, y);
        let [aw, as_, ae, an] = p.bounds();
        let global = ae - aw >= 360.0 - 1e-9;
        if (!global && (e <= aw || w >= ae)) || n <= as_ || s >= an {
            return Err(AppError::not_found(
                ErrorCode::Outside,
                format!("tile {z}/{x}/{y} is outside the asset"),
            ));
        }
    }
    Ok(())
}

/// Decodes and encodes one tile (on a decode lane). Pixels off the asset are nodata
/// (transparent in visual tiles).
fn draw_tile(
    delegates: (Option<&GpuBackend>, &CoarseCache, &Cancel),
    choice: Backend,
    asset: &StoredAsset,
    job: &TileJob,
) -> Result<Cached, AppError> {
    let (z, x, y, size) = (job.z, job.x, job.y, job.size);
    // Hillshading needs each pixel's neighbours: decode a one-pixel margin around the tile, so
    // that shading is seamless across tiles.
    let margin = usize::from(job.shade);
    // Where an uncached tile's time goes, for /metrics: its pixels' sites, their sampling
    // (the decode, on the CPU or the GPU), and the rest (style, rounding, PNG).
    let started = std::time::Instant::now();
    let stage = |name: &'static str, since: std::time::Instant| {
        metrics::histogram!("fractile_tile_stage_seconds", "stage" => name)
            .record(since.elapsed().as_secs_f64());
        std::time::Instant::now()
    };
    let grid = geo::tile_pixels(asset.placement.as_ref(), z, x, y, size, margin);
    let sampled = stage("sites", started);
    let (mut channels, bound) = if grid.is_outside() {
        // The tile overlaps the asset's bounds, but no pixel centre falls on it (a small asset
        // at a coarse zoom): a tile of nodata, not a 404, so that map clients draw the zoom
        // instead of over-zooming a parent that does not exist either.
        let planes = usize::from(asset.asset.meta.channels.max(1));
        let bounds = Bounds {
            attractor: 0.0,
            source: asset.asset.source_error.as_ref().map(|_| 0.0),
        };
        (vec![vec![f32::NAN; grid.len()]; planes], bounds)
    } else {
        sample_on(
            delegates,
            choice,
            asset,
            &grid,
            job.iterations,
            job.tolerance,
        )?
    };
    let encoded = stage("sample", sampled);
    let style = (job.colormap.is_some() || job.shade).then(|| {
        let side = size + 2 * margin;
        let shade = job.shade.then(|| {
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
                    grid.footprint[0] * asset.asset.meta.width as f32,
                    grid.footprint[1] * asset.asset.meta.height as f32,
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
        encoding::Style {
            colormap: job.colormap,
            shade,
        }
    });
    // Heights rounded to what the tile's bound justifies; the bounds then include the
    // rounding, so they still hold for the heights as sent.
    let rounding = match (job.format, job.precision, bound.error_bound()) {
        (encoding::TileFormat::Heights(e), Precision::Bound, Some(b)) => {
            encoding::Rounding::for_tile(
                e,
                b,
                encoding::relief(&channels[0], size),
                asset.asset.meta.stats.rmse as f32,
            )
        }
        _ => encoding::Rounding::default(),
    };
    let (content_type, body) = encoding::encode_tile(
        &asset.asset.meta,
        &channels,
        size,
        job.format,
        style,
        (
            rounding,
            match job.webp {
                true => encoding::Container::WebP,
                false => encoding::Container::Png(encoding::Deflate::for_tile(rounding)),
            },
        ),
    );
    stage("encode", encoded);
    Ok(Cached {
        content_type,
        content_encoding: None,
        body: Bytes::from(body),
        bounds: bound.plus(rounding.error),
    })
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
            ErrorCode::BadRescale,
            "rescale must be min,max with max > min",
        )),
    }
}
