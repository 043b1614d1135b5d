//! The HTTP API (versioned under /v1): the shared state, the router, and what every resource's
//! handlers share (lanes, backends, sampling, parameters). Handlers live with their resource
//! (`assets`, `tiles`, `terrain`, `points`, `regions`, `meshes`, `curves`): each parses and checks a
//! request, runs decoding in a lane of [`crate::work`] (never on the async workers), and
//! encodes the answer. The server adds no fractal math: it calls the codec.

mod assets;
mod curves;
mod files;
mod meshes;
mod points;
mod regions;
mod request;
mod state;
mod terrain;
mod tiles;
mod tilesets;

use assets::*;
use curves::*;
use files::*;
use fractile_proto::ErrorCode;
use meshes::*;
use points::*;
use regions::*;
use terrain::*;
use tiles::*;
use tilesets::*;

use state::Shared;
pub use state::{
    AppState, Cached, CoarseCache, DEFAULT_COARSE_CACHE_MIB, Limits, REQUEST_TIMEOUT, Writes,
    coarse_cache,
};

use std::sync::Arc;

use axum::extract::State;
use axum::http::StatusCode;
use axum::routing::{get, post};
use axum::{Json, Router};

use crate::error::AppError;

/// The router of the whole API.
pub(crate) fn router(state: Arc<AppState>) -> Router {
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
        .route("/v1/assets/{id}/file", get(asset_file))
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
        .route("/v1/assets/{id}/tileset.json", get(tileset))
        .route(
            "/v1/assets/{id}/3dtiles/{level}/{x}/{y}/{file}",
            get(content),
        )
        .route(
            "/v1/assets/{id}/3dtiles/subtrees/{level}/{x}/{y}/{file}",
            get(subtree),
        )
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
            code: ErrorCode::Busy,
            detail: "every decode slot is busy".into(),
            retry_after: None,
        })
    }
}
