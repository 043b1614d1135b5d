//! The catalog and its writes: list, describe, upload (authorised before its body is read), delete.

use super::request::*;
use super::state::*;
use fractile_proto::ErrorCode;

use crate::error::Path;
use axum::Json;
use axum::body::Bytes;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use fractile_proto::{AssetKind, AssetSummary, Catalog};

use crate::error::AppError;
use crate::store::StoredAsset;

pub(super) fn summary(state: &AppState, a: &StoredAsset) -> AssetSummary {
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
        // The file's own code, geographic (4326) too, as `fractile info` prints it; the
        // projected placement's where the file named none.
        epsg: m
            .georef
            .as_ref()
            .and_then(|g| g.epsg)
            .or_else(|| a.placement.as_ref().and_then(|p| p.epsg())),
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

pub(super) async fn list_assets(State(state): Shared) -> Json<Catalog> {
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
    let token = match &state.writes {
        super::state::Writes::Token(t) => t,
        super::state::Writes::Anyone => return Ok(()),
        super::state::Writes::Refused => {
            return Err(AppError {
                status: StatusCode::FORBIDDEN,
                code: ErrorCode::WritesDisabled,
                detail: "this server takes no writes: it was started with no write token (set FRACTILE_WRITE_TOKEN, or pass --allow-anonymous-writes on a private network)".into(),
            retry_after: None,
});
        }
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
            code: ErrorCode::Unauthorised,
            detail: "writes need Authorization: Bearer <token>".into(),
            retry_after: None,
        })
    }
}

/// Reads a request body of at most `limit` bytes once the bodies-in-flight budget has room for
/// it (its declared length, or `limit` when it declares none): a body over `limit` is a 413,
/// refused before a byte is read when its length says so. The permit holds the room until
/// the caller is done with the bytes.
pub(super) async fn read_body(
    state: &AppState,
    headers: &HeaderMap,
    body: axum::body::Body,
    limit: usize,
) -> Result<(Bytes, tokio::sync::OwnedSemaphorePermit), AppError> {
    let too_large = || AppError {
        status: StatusCode::PAYLOAD_TOO_LARGE,
        code: ErrorCode::TooLarge,
        detail: format!("this request's body is at most {} bytes", limit),
        retry_after: None,
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
        // The limit's own error type, wherever it sits in the chain (axum wraps it).
        let over = std::iter::successors(std::error::Error::source(&e), |s| s.source())
            .any(|s| s.is::<http_body_util::LengthLimitError>());
        if over {
            too_large()
        } else {
            AppError::bad_request(ErrorCode::BadBody, format!("reading the body: {e}"))
        }
    })?;
    Ok((bytes, room))
}

pub(super) async fn put_asset(
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

pub(super) async fn delete_asset(
    State(state): Shared,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<StatusCode, AppError> {
    authorise(&state, &headers)?;
    // A bucket's delete is requests to the object store: off the executor.
    let st = state.clone();
    tokio::task::spawn_blocking(move || st.store.delete(&id))
        .await
        .map_err(|_| AppError::internal("the delete did not finish"))??;
    Ok(StatusCode::NO_CONTENT)
}

pub(super) async fn asset_info(
    State(state): Shared,
    Path(id): Path<String>,
) -> Result<Json<AssetSummary>, AppError> {
    let a = state.store.get(&id)?;
    Ok(Json(summary(&state, &a)))
}
