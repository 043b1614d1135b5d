//! 3D Tiles for volumes: `tileset.json` (3D Tiles 1.1, implicit octree), its subtrees and its
//! tiles' GLB content, made by the codec (`fractile_codec::extract::octree`) within the
//! request budgets, cached and tagged as map tiles are.

use fractile_codec::extract::octree::{Compression, Octree, SUBTREE_LEVELS, TileId, tile_glb};
use fractile_proto::{AssetKind, ErrorCode};

use super::request::*;
use super::state::*;
use super::terrain::{accepts_gzip, gzipped};
use super::tiles::{cached_response, etag, not_modified};
use std::sync::Arc;

use crate::error::{AppError, Path, Query};
use crate::store::StoredAsset;
use crate::work::Bounds;
use axum::Json;
use axum::body::Bytes;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;

#[derive(Deserialize)]
pub(super) struct TilesetQuery {
    /// Longitude, latitude (degrees) and height (metres) where the volume's origin stands,
    /// for viewers of the globe; absent, the tiles stay in mesh units.
    lon: Option<f64>,
    lat: Option<f64>,
    height: Option<f64>,
    /// Metres a mesh unit (default 1).
    scale: Option<f64>,
    iterations: Option<u32>,
    tolerance: Option<f32>,
    /// `plain` for tiles every glTF reader takes (the content template then asks for them).
    compression: Option<String>,
}

#[derive(Deserialize)]
pub(super) struct ContentQuery {
    iterations: Option<u32>,
    tolerance: Option<f32>,
    backend: Option<String>,
    /// How a tile's GLB packs its buffers: `meshopt` (the default) or `plain`.
    compression: Option<String>,
}

/// The compression a query names: meshopt unless `plain` is asked.
fn compression_of(asked: Option<&str>) -> Result<Compression, AppError> {
    match asked {
        None | Some("meshopt") => Ok(Compression::Meshopt),
        Some("plain") => Ok(Compression::Plain),
        Some(other) => Err(AppError::bad_request(
            ErrorCode::BadEncoding,
            format!(
                "compression={other}: tiles are meshopt (EXT_meshopt_compression, the default) \
                 or plain (KHR_mesh_quantization alone)"
            ),
        )),
    }
}

/// The octree of a volume asset, or a 400 naming what the asset is.
fn octree_of(a: &StoredAsset) -> Result<Octree, AppError> {
    if a.asset.meta.kind != AssetKind::Volume {
        return Err(AppError::bad_request(
            ErrorCode::NotVolume,
            "3D Tiles are made of volumes (an IFS3D asset)",
        ));
    }
    a.asset
        .octree()
        .map_err(|e| AppError::internal(e.to_string()))
}

/// The east-north-up frame at (lon, lat, height) on WGS84, scaled, as a column-major 4 x 4
/// matrix: a volume's x east, y north, z up, its origin there.
fn enu_frame(lon: f64, lat: f64, height: f64, scale: f64) -> [f64; 16] {
    let (l, p) = (lon.to_radians(), lat.to_radians());
    let east = [-l.sin(), l.cos(), 0.0];
    let north = [-p.sin() * l.cos(), -p.sin() * l.sin(), p.cos()];
    let up = [p.cos() * l.cos(), p.cos() * l.sin(), p.sin()];
    let o = fractile_codec::mesh::quantized::ecef(lon, lat, height);
    let s = |v: [f64; 3]| v.map(|c| c * scale);
    let (e, n, u) = (s(east), s(north), s(up));
    [
        e[0], e[1], e[2], 0.0, n[0], n[1], n[2], 0.0, u[0], u[1], u[2], 0.0, o[0], o[1], o[2], 1.0,
    ]
}

/// `GET /v1/assets/{id}/tileset.json`: the volume as 3D Tiles 1.1 (implicit octree; see
/// `fractile_codec::extract::octree` for its errors and levels). `lon`, `lat`, `height` and
/// `scale` place it on the globe.
pub(super) async fn tileset(
    State(state): Shared,
    Path(id): Path<String>,
    Query(q): Query<TilesetQuery>,
) -> Result<Response, AppError> {
    let a = state.store.get(&id)?;
    let octree = octree_of(&a)?;
    let transform = match (q.lon, q.lat) {
        (None, None) => None,
        (Some(lon), Some(lat))
            if (-180.0..=180.0).contains(&lon)
                && (-90.0..=90.0).contains(&lat)
                && q.height.is_none_or(f64::is_finite)
                && q.scale.is_none_or(|s| s.is_finite() && s > 0.0) =>
        {
            Some(enu_frame(
                lon,
                lat,
                q.height.unwrap_or(0.0),
                q.scale.unwrap_or(1.0),
            ))
        }
        _ => {
            return Err(AppError::bad_request(
                ErrorCode::BadPoint,
                "a placement is lon (-180..180) and lat (-90..90) together, with an optional \
                 height (metres) and a positive scale (metres a mesh unit)",
            ));
        }
    };
    // The decode's bound at the steps tiles take: the tolerance they stop at, or what the
    // asset's seed bound shrinks to in those steps where none is asked.
    let (_, tolerance) = iterations_for(&state, q.iterations, q.tolerance)?;
    let bound = f64::from(tolerance.anywhere(&a));
    let mut tileset = octree.tileset(bound, transform);
    // Plain tiles asked of the tileset are asked by its content template (a static copy of
    // the folder ignores the query and serves what was fetched).
    if compression_of(q.compression.as_deref())? == Compression::Plain {
        let uri = &mut tileset["root"]["content"]["uri"];
        *uri = format!("{}?compression=plain", uri.as_str().unwrap_or_default()).into();
    }
    Ok(Json(tileset).into_response())
}

/// The tile named by a path's level, x, y and `{z}.{extension}`, or a 400 / 404.
fn tile_of(octree: &Octree, level: &str, x: &str, y: &str, z: &str) -> Result<TileId, AppError> {
    let number = |s: &str| s.parse::<u32>().ok();
    let t = match (number(level), number(x), number(y), number(z)) {
        (Some(level), Some(x), Some(y), Some(z)) => TileId { level, x, y, z },
        _ => {
            return Err(AppError::bad_request(
                ErrorCode::BadPath,
                "a 3D tile is /{level}/{x}/{y}/{z} with whole numbers",
            ));
        }
    };
    if !octree.holds(t) {
        return Err(AppError::not_found(
            ErrorCode::NoTile,
            format!(
                "no tile {}/{}/{}/{}: levels 0 to {}, indices under 2^level",
                t.level,
                t.x,
                t.y,
                t.z,
                octree.levels - 1
            ),
        ));
    }
    Ok(t)
}

/// The asset, its octree and the tile a 3D Tiles path names: `{level}/{x}/{y}/{z}{extension}`
/// (another extension: 404 `no_route`).
fn tile_at(
    state: &AppState,
    id: &str,
    [level, x, y]: [&str; 3],
    file: &str,
    extension: &str,
) -> Result<(Arc<StoredAsset>, Octree, TileId), AppError> {
    let a = state.store.get(id)?;
    let octree = octree_of(&a)?;
    let Some(z) = file.strip_suffix(extension) else {
        return Err(AppError::not_found(
            ErrorCode::NoRoute,
            format!("this path ends in {{z}}{extension}"),
        ));
    };
    let t = tile_of(&octree, level, x, y, z)?;
    Ok((a, octree, t))
}

/// A tile's content: `GET /v1/assets/{id}/3dtiles/{level}/{x}/{y}/{z}.glb`, the surface in
/// its box (glTF 2.0 binary, y up); 404 where the box holds no surface (its subtree says so).
/// `GET /v1/assets/{id}/3dtiles/subtrees/{level}/{x}/{y}/{z}.subtree` is a subtree.
pub(super) async fn content(
    State(state): Shared,
    Path((id, level, x, y, file)): Path<(String, String, String, String, String)>,
    Query(q): Query<ContentQuery>,
    headers: HeaderMap,
) -> Result<Response, AppError> {
    let (a, octree, t) = tile_at(&state, &id, [&level, &x, &y], &file, ".glb")?;
    answer(&state, a, octree, Made::Tile(t), &q, &headers).await
}

/// `GET /v1/assets/{id}/3dtiles/subtrees/{level}/{x}/{y}/{z}.subtree`: which tiles of the
/// subtree exist and hold a surface, and which child subtrees exist (3D Tiles 1.1 binary).
pub(super) async fn subtree(
    State(state): Shared,
    Path((id, level, x, y, file)): Path<(String, String, String, String, String)>,
    Query(q): Query<ContentQuery>,
    headers: HeaderMap,
) -> Result<Response, AppError> {
    let (a, octree, t) = tile_at(&state, &id, [&level, &x, &y], &file, ".subtree")?;
    if !t.level.is_multiple_of(SUBTREE_LEVELS) {
        return Err(AppError::not_found(
            ErrorCode::NoTile,
            format!("subtrees start at levels that are multiples of {SUBTREE_LEVELS}"),
        ));
    }
    answer(&state, a, octree, Made::Subtree(t), &q, &headers).await
}

/// What a request makes.
#[derive(Clone, Copy, Debug)]
enum Made {
    Tile(TileId),
    Subtree(TileId),
}

/// The cached answer of `made`, or made within the budgets (off the executor) and cached.
async fn answer(
    state: &Arc<AppState>,
    a: Arc<StoredAsset>,
    octree: Octree,
    made: Made,
    q: &ContentQuery,
    headers: &HeaderMap,
) -> Result<Response, AppError> {
    let (iterations, tolerance) = iterations_for(state, q.iterations, q.tolerance)?;
    // One tolerance for every tile: neighbours share their faces' samples (no cracks).
    let tolerance = tolerance.anywhere(&a);
    let choice = backend_for(state, q.backend.as_deref())?;
    let compression = compression_of(q.compression.as_deref())?;
    // A GLB's JSON is up to half its bytes, and meshopt's streams are made to be deflated
    // further: to clients that accept it (browsers do) a tile goes gzipped, as a variant of
    // its own (key and ETag). Subtrees are mostly constant bits, small either way.
    let gzip = matches!(made, Made::Tile(_)) && accepts_gzip(headers);
    let key = format!(
        "{}@{:08x}/3dtiles/{made:?}?{:?}&{:?}&{compression:?}&{gzip}",
        a.id, a.hash, q.iterations, q.tolerance
    );
    let tag = etag(&a, &key);
    let vary = |mut r: Response| {
        r.headers_mut()
            .insert(header::VARY, HeaderValue::from_static("accept-encoding"));
        r
    };
    if not_modified(headers, &tag) {
        return Ok((StatusCode::NOT_MODIFIED, [(header::ETAG, tag)]).into_response());
    }
    if let Some(c) = state.cache.get(&key) {
        return Ok(vary(cached_response(state, &tag, &c)));
    }
    let samples = match made {
        Made::Tile(_) => (fractile_codec::extract::octree::CELLS + 1).pow(3),
        Made::Subtree(_) => (4 * fractile_codec::extract::octree::CELLS + 1).pow(3),
    };
    // A distance a sample, and a surface of a few vertices per surface cell.
    let cost = samples as u64 * 48;
    let gpu = state.gpu.clone();
    let made_now = decode(state, cost, move |cancel| {
        let on_gpu = |lo, hi, dims: [usize; 3], n, t| {
            gpu.as_deref()
                .filter(|g| g.takes(choice, &a, dims.iter().product()))
                .and_then(|g| cancel.off_core(|| g.volume_grid(&a, (lo, hi, dims), n, t)))
        };
        let steps = (iterations, tolerance);
        let (content_type, body, bound) = match made {
            Made::Tile(t) => {
                let (mesh, bound) = a
                    .asset
                    .octree_tile(&octree, t, steps, Some(&on_gpu))
                    .map_err(|e| AppError::internal(e.to_string()))?;
                if mesh.triangles.is_empty() {
                    return Err(AppError::not_found(
                        ErrorCode::NoTile,
                        "this tile's box holds no surface (its subtree lists no content)",
                    ));
                }
                let glb = tile_glb(&octree, t, &mesh, compression);
                let glb = if gzip { gzipped(&glb)? } else { glb };
                ("model/gltf-binary", glb, bound)
            }
            Made::Subtree(t) => {
                let (s, bound) = a
                    .asset
                    .octree_subtree(&octree, t, steps, Some(&on_gpu))
                    .map_err(|e| AppError::internal(e.to_string()))?;
                ("application/octet-stream", s.to_bytes(), bound)
            }
        };
        Ok::<_, AppError>(Cached {
            content_type,
            content_encoding: gzip.then_some("gzip"),
            body: Bytes::from(body),
            // Volumes hold no source-error map.
            bounds: Bounds {
                attractor: bound,
                source: None,
            },
        })
    })
    .await??;
    let cached = Arc::new(made_now);
    state.cache.insert(key, cached.clone());
    Ok(vary(cached_response(state, &tag, &cached)))
}
