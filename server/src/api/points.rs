//! Values at points: one unit point, one lon/lat, or a batch; signed distances of volumes.

use super::assets::read_body;
use super::request::*;
use super::state::*;
use fractile_proto::ErrorCode;
use std::sync::Arc;

use fractile_codec::extract::{Distances, PlaneRef, Points, Resources, Sites};

use crate::error::{Path, Query};
use axum::Json;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use fractile_proto::{
    AssetKind, BINARY_MEDIA_TYPE, DistanceResult, PointResult, PointsRequest, PointsResponse,
};
use serde::Deserialize;

use crate::backend::Backend;
use crate::error::AppError;
use crate::store::StoredAsset;

#[derive(Deserialize)]
pub(super) struct PointQuery {
    x: Option<f64>,
    y: Option<f64>,
    /// Volumes only: the third coordinate.
    z: Option<f64>,
    iterations: Option<u32>,
    tolerance: Option<f32>,
}

pub(super) async fn point_unit(
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
            ErrorCode::BadPoint,
            "z is for volume assets; this one is 2D",
        ));
    }
    let (Some(x), Some(y)) = (q.x, q.y) else {
        return Err(AppError::bad_request(
            ErrorCode::BadPoint,
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
            ErrorCode::BadPoint,
            "give ?x=&y=&z= in the mesh's units for a volume asset",
        ));
    };
    let p = [x, y, z];
    if p.iter().any(|v| !v.is_finite()) {
        return Err(AppError::bad_request(
            ErrorCode::BadPoint,
            "coordinates must be finite",
        ));
    }
    let (n, tolerance) = iterations_for(state, q.iterations, q.tolerance)?;
    let sample = decode(state, 0, move |_| {
        let question = Distances {
            points: &[p],
            iterations: n,
            tolerance: tolerance.asked(),
        };
        a.asset.answer(&question, &Resources::CPU)
    })
    .await?
    .map_err(super::request::sample_error)?
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
            ErrorCode::Outside,
            format!("point {p:?} is outside the volume's grid"),
        )),
    }
}

pub(super) async fn point_lonlat(
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
            ErrorCode::BadPoint,
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
pub(super) struct PointsQuery {
    backend: Option<String>,
}

pub(super) async fn points(
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
            .map_err(|e| AppError::bad_request(ErrorCode::BadBody, e.to_string()))?
    } else {
        serde_json::from_slice(&body)
            .map_err(|e| AppError::bad_request(ErrorCode::BadBody, e.to_string()))?
    };
    if req.points.len() > state.limits.max_points {
        return Err(AppError {
            status: StatusCode::PAYLOAD_TOO_LARGE,
            code: ErrorCode::TooManyPoints,
            detail: format!(
                "{} points over the limit {}",
                req.points.len(),
                state.limits.max_points
            ),
            retry_after: None,
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
    let (n, tolerance) = iterations_for(state, iterations, tolerance)?;
    let units: Vec<Option<[f32; 2]>> = coords.iter().map(|&c| unit_of(&a, c)).collect();
    if single && units[0].is_none() {
        return Err(AppError::not_found(
            ErrorCode::Outside,
            format!("point {:?} is outside the asset", coords[0]),
        ));
    }
    let gpu = state.gpu.clone();
    let cost = sampling_bytes(coords.len(), a.asset.meta.channels);
    decode(state, cost, move |cancel| {
        let inside: Vec<[f32; 2]> = units.iter().map(|u| u.unwrap_or([0.0, 0.0])).collect();
        let gpu = gpu.as_deref().filter(|g| g.takes(choice, &a, inside.len()));
        let device = |k: PlaneRef<'_>, p: Sites<'_>, n, t| {
            let (g, op) = gpu.and_then(|g| Some((g, g.operator(&a, k)?)))?;
            cancel.off_core(|| g.points(&a, &op, p, n, t))
        };
        let question = Points {
            points: &inside,
            iterations: n,
            tolerance: tolerance.asked(),
        };
        let resources = Resources {
            device: Some(&device),
            ..Resources::CPU
        };
        let samples = a
            .asset
            .answer(&question, &resources)
            .map_err(super::request::sample_error)?;
        Ok(coords
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
                    error_bound: s.source_error.map(|e| e + s.error_bound),
                    convergence_bound: Some(s.error_bound),
                    iterations: s.iterations,
                    outside: false,
                },
                None => PointResult {
                    coordinates: c,
                    values: None,
                    error_bound: None,
                    convergence_bound: None,
                    iterations: 0,
                    outside: true,
                },
            })
            .collect())
    })
    .await?
}
