//! Cesium terrain: `layer.json` and quantized-mesh-1.0 tiles of a georeferenced height field, in
//! the geographic tiling scheme CesiumJS uses by default (EPSG:4326, TMS rows from the south,
//! two root tiles). Each tile is an adaptive mesh (right-triangulated irregular network) of a
//! grid of decoded heights (65 x 65, or past the source's resolution as fine as its cells),
//! within the level's geometric error of them on the globe. Terrain has no
//! holes: off the asset and at nodata the surface is the ellipsoid (height 0), and both root
//! tiles exist whatever the asset covers, since Cesium draws nothing until they are in.

use fractile_proto::ErrorCode;
use fractile_proto::LayerJson;
use fractile_proto::tiles::{geographic_available, geographic_bounds};

use super::request::*;
use super::state::*;
use super::tiles::{cached_response, etag, not_modified};
use std::sync::Arc;

use crate::error::{Path, Query};
use axum::Json;
use axum::body::Bytes;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use fractile_codec::geo;
use fractile_proto::AssetKind;
use serde::Deserialize;

use crate::error::AppError;
use crate::store::StoredAsset;
use crate::work::Bounds;

/// Vertices a side of a terrain tile's grid (Cesium's own heightmap tiles use 65).
const GRID: usize = 65;

/// Cesium's geometric error of level 0 for the geographic scheme: the ellipsoid's largest
/// circumference over the 65-sample root tiles, two across, a quarter of it (CesiumJS's
/// `TerrainProvider.getEstimatedLevelZeroGeometricErrorForAHeightmap`: 6378137 x 2 pi x 0.25 /
/// (65 x 2)). Level z halves it z times. Meshing within this error makes Cesium's level of detail
/// choose the tiles it would for its own terrain.
const LEVEL_ZERO_ERROR: f64 = 6_378_137.0 * std::f64::consts::TAU * 0.25 / (65.0 * 2.0);

/// The globe's radius for the curvature a tile's mesh must follow: the WGS84 semi-major axis,
/// the largest (a chord of a given angle falls furthest below the larger circle).
const GLOBE_RADIUS: f64 = 6_378_137.0;

/// The asset as Cesium terrain: a georeferenced height field.
fn terrain_asset(a: Arc<StoredAsset>) -> Result<Arc<StoredAsset>, AppError> {
    if a.asset.meta.kind != AssetKind::HeightField || a.placement.is_none() {
        return Err(AppError::bad_request(
            ErrorCode::NotTerrain,
            format!(
                "{} is not a georeferenced height field: Cesium terrain is for DEMs",
                a.id
            ),
        ));
    }
    Ok(a)
}

/// The asset's bounds in lon/lat, clipped to the globe.
fn asset_bounds(a: &StoredAsset) -> [f64; 4] {
    // `terrain_asset` admits placed assets only; the globe otherwise.
    let [w, s, e, n] = a
        .placement
        .as_ref()
        .map_or([-180.0, -90.0, 180.0, 90.0], |p| p.bounds());
    [w.max(-180.0), s.max(-90.0), e.min(180.0), n.min(90.0)]
}

/// Deepest level: where a tile's 64 cells are as fine as the source's, then 4 levels further
/// (detail past the source, as the raster tiles' `maxzoom`).
fn max_level(state: &AppState, a: &StoredAsset) -> u8 {
    let [w, _, e, _] = asset_bounds(a);
    let pixel = (e - w).max(1e-12) / f64::from(a.asset.meta.width.max(1));
    let native = (180.0 / ((GRID - 1) as f64 * pixel))
        .log2()
        .ceil()
        .clamp(0.0, 22.0) as u8;
    (native + 4).min(state.limits.max_zoom)
}

/// `GET /v1/assets/{id}/layer.json`: the terrain layer Cesium's `CesiumTerrainProvider` reads.
pub(super) async fn layer(
    State(state): Shared,
    Path(id): Path<String>,
) -> Result<Json<LayerJson>, AppError> {
    let a = terrain_asset(state.store.get(&id)?)?;
    let bounds = asset_bounds(&a);
    let max = max_level(&state, &a);
    let available = geographic_available(bounds, max);
    Ok(Json(LayerJson {
        tilejson: "2.1.0".into(),
        name: a.id.clone(),
        version: "1.0.0".into(),
        format: "quantized-mesh-1.0".into(),
        scheme: "tms".into(),
        projection: "EPSG:4326".into(),
        // Relative to this document, as Cesium resolves it.
        tiles: vec!["terrain/{z}/{x}/{y}.terrain".into()],
        minzoom: 0,
        maxzoom: max,
        bounds,
        available,
        extensions: vec!["octvertexnormals".into()],
    }))
}

/// Query of a terrain tile.
#[derive(Deserialize)]
pub(super) struct TerrainQuery {
    iterations: Option<u32>,
    tolerance: Option<f32>,
    backend: Option<String>,
}

/// `GET /v1/assets/{id}/terrain/{z}/{x}/{y}.terrain`: one quantized-mesh tile, with the
/// decode's bound plus the mesh's error in `X-Error-Bound`.
pub(super) async fn terrain_tile(
    State(state): Shared,
    Path((id, z, x, tile)): Path<(String, String, String, String)>,
    Query(q): Query<TerrainQuery>,
    headers: HeaderMap,
) -> Result<Response, AppError> {
    let a = terrain_asset(state.store.get(&id)?)?;
    let y = tile
        .strip_suffix(".terrain")
        .ok_or_else(|| AppError::bad_request(ErrorCode::BadTile, "expected {y}.terrain"))?;
    let top = max_level(&state, &a);
    let (z, x, y) = super::request::tile_numbers(&z, &x, y, top, 2)?;
    if z > top || x >= (2u32 << z) || y >= (1u32 << z) {
        return Err(AppError::not_found(
            ErrorCode::NoTile,
            format!(
                "terrain tile {z}/{x}/{y} does not exist: this asset's levels go from 0 to \
                 {top} (layer.json), and at level {z} columns from 0 to {} and rows from 0 \
                 to {}",
                (2u64 << z.min(31)) - 1,
                (1u64 << z.min(31)) - 1
            ),
        ));
    }
    let [w, s, e, n] = geographic_bounds(z, x, y);
    let [aw, as_, ae, an] = asset_bounds(&a);
    // Cesium draws nothing until both root tiles are in: they always exist (flat outside).
    if z > 0 && (e <= aw || w >= ae || n <= as_ || s >= an) {
        return Err(AppError::not_found(
            ErrorCode::Outside,
            format!("terrain tile {z}/{x}/{y} is outside the asset"),
        ));
    }
    let (iterations, tolerance) = iterations_for(&state, q.iterations, q.tolerance)?;
    // One tolerance for every tile of the asset, not one settled by each tile's own source
    // error: neighbouring tiles share their edge vertices, which must decode alike (no cracks).
    let tolerance = super::request::Tolerance::Asked(tolerance.anywhere(&a));
    let choice = backend_for(&state, q.backend.as_deref())?;
    // quantized-mesh is made to be gzipped (about half the bytes): to clients that accept it,
    // as browsers and Cesium do, the tile goes gzipped, as a variant of its own (key and ETag).
    let gzip = accepts_gzip(&headers);
    // Vertex normals (for Cesium's lighting) when the client asks for them, as Cesium does in
    // its Accept header.
    let normals = headers
        .get_all(header::ACCEPT)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .any(|v| v.contains("octvertexnormals"));
    let key = format!(
        "{id}@{:08x}/terrain/{z}/{x}/{y}?{:?}&{:?}&{gzip}&{normals}",
        a.hash, q.iterations, q.tolerance
    );
    let tag = etag(&a, &key);
    if not_modified(&headers, &tag) {
        return Ok((StatusCode::NOT_MODIFIED, [(header::ETAG, tag)]).into_response());
    }
    // The answer depends on Accept (normals) and Accept-Encoding (gzip).
    let vary = |mut r: Response| {
        r.headers_mut().insert(
            header::VARY,
            HeaderValue::from_static("accept, accept-encoding"),
        );
        r
    };
    if let Some(c) = state.cache.get(&key) {
        return Ok(vary(cached_response(&state, &tag, &c)));
    }
    let detail = q.iterations.is_some() || q.tolerance.is_some();
    let (grid, side) = tile_grid(&a, z, [w, s, e, n], detail);
    let (gpu, coarse) = (state.gpu.clone(), state.coarse.clone());
    let asset = a.clone();
    let cost = sampling_bytes(side * side, 1) + (side * side) as u64 * 64;
    let drawn = decode(&state, cost, move |cancel| {
        let (heights, bound) = if grid.is_outside() {
            (
                vec![f32::NAN; side * side],
                // Nothing of the source in it: no error against it (where the asset
                // measured its error at all).
                Bounds {
                    attractor: 0.0,
                    source: asset.asset.source_error.as_ref().map(|_| 0.0),
                },
            )
        } else {
            let (channels, bound) = sample_on(
                (gpu.as_deref(), &coarse, cancel),
                choice,
                &asset,
                &grid,
                iterations,
                tolerance,
            )?;
            (channels.into_iter().next().unwrap_or_default(), bound)
        };
        mesh_tile((heights, side), (z, [w, s, e, n]), (normals, gzip), bound)
    })
    .await??;
    let cached = Arc::new(drawn);
    state.cache.insert(key, cached.clone());
    Ok(vary(cached_response(&state, &tag, &cached)))
}

/// The quantized-mesh tile of a grid of decoded heights (NaN off the asset) over `bounds` at
/// level `z`, `side` vertices a side, with normals and gzipped as asked; `bound` is the
/// decode's.
fn mesh_tile(
    (heights, side): (Vec<f32>, usize),
    (z, [w, s, e, n]): (u8, [f64; 4]),
    (normals, gzip): (bool, bool),
    bound: Bounds,
) -> Result<Cached, AppError> {
    let max_error = (LEVEL_ZERO_ERROR / f64::from(1u32 << z)) as f32;
    // Cesium places each vertex on the ellipsoid and draws flat triangles between them: a
    // triangle across a wide tile falls below the ground by its sagitta, so the mesh measures
    // its errors on the globe (to second order, `Mesh::adaptive_tile`'s bend). A grid unit
    // spans (e - w) / 64 degrees of longitude and as many of latitude; taken as arcs of a
    // great circle (longitude's are shorter away from the equator: a bound, not the value).
    let unit = ((e - w) / (side - 1) as f64).to_radians();
    let bend = (GLOBE_RADIUS * unit * unit / 2.0) as f32;
    // Terrain has no holes: off the asset (and at nodata) the surface is the ellipsoid.
    let heights: Vec<f32> = heights
        .into_iter()
        .map(|h| if h.is_finite() { h } else { 0.0 })
        .collect();
    // Adaptive tiles are stitched: each edge is meshed from its own heights, so neighbours
    // meet on the same polyline (no cracks). At every level: the wide tiles of levels 0-7 were
    // the regular 65 x 65 grid (8,192 triangles) before their errors took the curvature in
    // (docs/benchmarks.md "Cesium meshes against Delatin").
    let (mesh, mesh_error) = fractile_codec::mesh::Mesh::adaptive_tile(
        &heights,
        side,
        [0.0, 0.0],
        [1.0, 1.0],
        max_error,
        bend,
    )
    .map_err(|e| AppError::internal(e.to_string()))?;
    let grid_normals = normals
        .then(|| fractile_codec::mesh::quantized::grid_normals(&heights, side, [w, s, e, n]));
    let body = fractile_codec::mesh::quantized::TerrainTile {
        mesh: &mesh,
        n: side,
        bounds: [w, s, e, n],
        normals: grid_normals.as_deref(),
    }
    .encode();
    let body = if gzip { gzipped(&body)? } else { body };
    Ok::<_, AppError>(Cached {
        content_type: if normals {
            "application/vnd.quantized-mesh;extensions=octvertexnormals"
        } else {
            "application/vnd.quantized-mesh"
        },
        content_encoding: gzip.then_some("gzip"),
        body: Bytes::from(body),
        // At the tile's grid points: the decode's bound, plus the mesh's own error there (at
        // most the level's geometric error; on the globe: a wide flat triangle's sagitta).
        bounds: bound.plus(mesh_error),
    })
}

/// The vertices of terrain tile `z` over `[w, s, e, n]` as pixels of the asset, and their side
/// (see below); `detail`: the request asked for steps or a tolerance.
fn tile_grid(a: &StoredAsset, z: u8, [w, s, e, n]: [f64; 4], detail: bool) -> (geo::Pixels, usize) {
    // The grid's side: 65 vertices (Cesium's heightmap tiles'), or past the source's
    // resolution the fewest whose spacing is no wider than a source cell, unless
    // `detail` (`iterations` or `tolerance` asked) wants the continuation's below the cells.
    // Why: a mesh is held to its level's geometric error at its grid's points, and 65 points over a
    // tile of a few source cells held it to the continuation's synthetic detail (and, filtered
    // over a cell, to the kinks between cells), which took jacksboro's tiles at levels 13-16 to
    // 2-30x the triangles of Delatin on the source cells (issue 56). A grid as fine as the
    // cells samples all the data holds; the mesh interpolates between its points, as a mesh of
    // the cells does. The side depends on the level alone, so neighbours share their edges'
    // points.
    let side = if detail { GRID } else { grid_side(a, z) };
    // Vertex (i, j): i east, j south, the tile's edges included, so that neighbours share
    // their edge vertices' positions and therefore their decoded heights (no cracks).
    let frac = |k: usize| k as f64 / (side - 1) as f64;
    let mut grid = box_pixels(
        a,
        (side, |i| w + frac(i) * (e - w)),
        (side, |j| n - frac(j) * (n - s)),
        cell_size([w, s, e, n], side - 1, side - 1),
    );
    // Vertices at or coarser than the source are answered as the codec answers a mesh's
    // (`Asset::vertex_pixels`: a projected asset's filtered over a source cell).
    if !detail {
        grid = a.asset.vertex_pixels(grid);
    }
    (grid, side)
}

/// The side of level `z`'s grids past the source's resolution: the fewest vertices (at most
/// [`GRID`]) whose spacing is no wider than a source cell, the cell taken as the
/// asset's width in degrees over its columns (as [`max_level`] takes it: the same for every
/// tile of the level).
fn grid_side(a: &StoredAsset, z: u8) -> usize {
    let [w, _, e, _] = asset_bounds(a);
    let pixel = (e - w).max(1e-12) / f64::from(a.asset.meta.width.max(1));
    let cells = 180.0 / f64::from(1u32 << z.min(31)) / pixel;
    // Any side (the greedy TIN takes any): a dyadic 2^k + 1 took up to 2x the cells' points
    // (9 a side over jacksboro's 6.5 cells at level 15), and the mesh held its error at each.
    (cells.ceil().max(1.0) as usize).min(GRID - 1) + 1
}

/// Whether `Accept-Encoding` allows gzip (with a non-zero weight).
pub(super) fn accepts_gzip(headers: &HeaderMap) -> bool {
    headers
        .get_all(header::ACCEPT_ENCODING)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|item| {
            let mut parts = item.split(';').map(str::trim);
            let coding = parts.next().unwrap_or("");
            let refused =
                parts.any(|p| p.replace(' ', "") == "q=0" || p.replace(' ', "") == "q=0.0");
            (coding.eq_ignore_ascii_case("gzip") || coding == "*") && !refused
        })
}

/// `bytes` gzipped (flate2, level 6).
pub(super) fn gzipped(bytes: &[u8]) -> Result<Vec<u8>, AppError> {
    use std::io::Write;
    let mut z = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    z.write_all(bytes)
        .and_then(|()| z.finish())
        .map_err(|e| AppError::internal(e.to_string()))
}
