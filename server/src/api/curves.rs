//! Curve assets as GeoJSON at any level, and their stateless deformations.

use super::state::*;
use fractile_proto::ErrorCode;

use crate::error::{Path, Query};
use axum::Json;
use axum::extract::State;
use axum::http::StatusCode;
use axum::response::Response;
use serde::Deserialize;

use crate::error::AppError;
use crate::store::StoredAsset;
use crate::work::{BodyWriter, Bounds, Head};

/// Query of `GET /v1/assets/{id}/curve`.
#[derive(Deserialize)]
pub(super) struct CurveQuery {
    /// Asset level; the finest (the input's) when absent.
    level: Option<usize>,
    /// `true`: each ring's base control points (level 0 of the model, what a `control`
    /// deformation moves) instead of the curve. They are in the model's frame: along a ring
    /// that crosses the antimeridian, longitudes are unwrapped (may pass ±180°).
    #[serde(default)]
    control: bool,
}

/// Largest deformation body, bytes: refused by its declared length before it is read, and
/// by the bytes read where it declares none.
pub(super) const DEFORM_BODY: usize = 16 * 1024 * 1024;

/// Most points one curve answer may hold (each level doubles them).
const MAX_CURVE_POINTS: u128 = 1 << 22;

fn curves_of(a: &StoredAsset) -> Result<&fractile_codec::codecs::curve::Curves, AppError> {
    a.asset.curves().ok_or_else(|| {
        AppError::bad_request(
            ErrorCode::NotCurve,
            format!("{} is not a curve asset ({:?})", a.id, a.asset.meta.kind),
        )
    })
}

fn check_level(
    set: &fractile_codec::codecs::curve::CurveSet,
    level: usize,
) -> Result<(), AppError> {
    if set.points_at(level) > MAX_CURVE_POINTS {
        return Err(AppError::bad_request(
            ErrorCode::TooManyPoints,
            format!(
                "level {level} would answer over {MAX_CURVE_POINTS} points (the finest level is {})",
                set.finest()
            ),
        ));
    }
    Ok(())
}

/// A decoded level streamed as GeoJSON (`geojson::write_to` into the body as the client reads
/// it): the text of a deep level (156 MB for the coastlines' level 18) is never held whole,
/// only the level's points. `X-Convergence-Bound` is the level's Hausdorff bound.
fn geojson_body(
    level: fractile_codec::codecs::curve::CurveLevel,
    finest: usize,
    units: String,
) -> (Head, BodyWriter) {
    let bound = level.error_bound as f32;
    let head = Head {
        content_type: "application/geo+json",
        bounds: Bounds {
            attractor: if bound.is_finite() { bound } else { 0.0 },
            source: None,
        },
    };
    let writer: BodyWriter = Box::new(move |out: &mut dyn std::io::Write| {
        fractile_codec::codecs::curve::geojson::write_to(&level, finest, &units, out)
    });
    (head, writer)
}

/// What answering `level` of `set` holds at its peak (its points and their GeoJSON text): the
/// lane it runs in, so that deep levels take from the heavy budget like regions do (8 answers
/// of the deepest level at once took 2 GB, and kept most of it).
fn answer_bytes(set: &fractile_codec::codecs::curve::CurveSet, level: usize) -> u64 {
    fractile_codec::codecs::curve::geojson::write_bytes(set.points_at(level))
}

/// A curve asset as GeoJSON at any level (deeper than the source: self-similar detail), one
/// LineString Feature per input ring, with the level's Hausdorff error bound.
pub(super) async fn curve(
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
    let cost = if control { 0 } else { answer_bytes(set, level) };
    let a2 = a.clone();
    state
        .lanes
        .stream(cost, move |_| {
            let Some(c) = a2.asset.curves() else {
                return Err(AppError::internal("a curve asset without its curves"));
            };
            let decoded = if control {
                fractile_codec::codecs::curve::CurveLevel {
                    level: 0,
                    lines: c.set.rings.iter().map(|r| r.base.clone()).collect(),
                    closed: c.set.rings.iter().map(|r| r.closed).collect(),
                    error_bound: f64::NAN,
                }
            } else {
                c.set.at_level(level)
            };
            Ok(geojson_body(decoded, c.set.finest(), units))
        })
        .await
}

/// Deforms a curve asset (stateless: the stored asset is unchanged) and answers GeoJSON.
pub(super) async fn curve_deform(
    State(state): Shared,
    Path(id): Path<String>,
    body: Result<Json<fractile_proto::DeformRequest>, axum::extract::rejection::JsonRejection>,
) -> Result<Response, AppError> {
    // A body over the limit is a 413, as any other over its limit (it was a 400 "length limit
    // exceeded"); the rest of what the extractor refuses is the body's fault.
    let Json(req) = body.map_err(|e| match e.status() {
        StatusCode::PAYLOAD_TOO_LARGE => AppError {
            status: StatusCode::PAYLOAD_TOO_LARGE,
            code: ErrorCode::TooLarge,
            detail: format!("{} (at most {DEFORM_BODY} bytes)", e.body_text()),
            retry_after: None,
        },
        _ => AppError::bad_request(ErrorCode::BadBody, e.body_text()),
    })?;
    let a = state.store.get(&id)?;
    let set = &curves_of(&a)?.set;
    if req.deformations.len() > 1024 {
        return Err(AppError::bad_request(
            ErrorCode::BadBody,
            "at most 1024 deformations per request",
        ));
    }
    let level = req.level.unwrap_or_else(|| set.finest());
    check_level(set, level)?;
    let units = a.asset.meta.units.clone().unwrap_or_default();
    let cost = answer_bytes(set, level);
    let a2 = a.clone();
    state
        .lanes
        .stream(cost, move |_| {
            let Some(c) = a2.asset.curves() else {
                return Err(AppError::internal("a curve asset without its curves"));
            };
            let deformed = fractile_codec::codecs::curve::deform::apply(&c.set, &req.deformations)
                .map_err(|e| AppError::bad_request(ErrorCode::BadDeformation, e.message()))?;
            Ok(geojson_body(
                deformed.at_level(level),
                deformed.finest(),
                units,
            ))
        })
        .await
}
