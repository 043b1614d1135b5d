//! An asset's file as stored, whole or by byte range (RFC 9110 `Range: bytes=a-b`): what a
//! client that decodes by itself reads (the browser's WebAssembly reader, `wasm/js/reader.js`;
//! a script with the codec), only the header, table and chunks it needs.

use super::request::chunk_unavailable;
use super::state::Shared;
use crate::error::{AppError, Path};
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use fractile_proto::ErrorCode;

/// The most bytes one answer carries: a whole small file, or one range of a large one (a
/// chunk of 1,024 x 1,024 cells is a few hundred kilobytes; the browser asks for one at a time).
pub(super) const MOST_BYTES: u64 = 64 << 20;

/// The one byte range a `Range` header asks for, within a file of `len` bytes.
fn asked_range(headers: &HeaderMap, len: u64) -> Result<Option<(u64, u64)>, AppError> {
    let Some(v) = headers.get(header::RANGE) else {
        return Ok(None);
    };
    let unsatisfiable = |why: &str| AppError {
        status: StatusCode::RANGE_NOT_SATISFIABLE,
        code: ErrorCode::BadRange,
        detail: format!("{why} (the file has {len} bytes; one range, as bytes=FIRST-LAST)"),
        retry_after: None,
    };
    // Parsed by http-range-header, the parser tower-http's file server uses.
    let ranges = v
        .to_str()
        .ok()
        .and_then(|s| http_range_header::parse_range_header(s).ok())
        .ok_or_else(|| unsatisfiable("the Range header is not a byte range"))?
        .validate(len)
        .map_err(|_| unsatisfiable("the range is not within the file"))?;
    match ranges.as_slice() {
        [r] => Ok(Some((*r.start(), *r.end()))),
        _ => Err(unsatisfiable(
            "several ranges in one request are not served",
        )),
    }
}

/// `GET /v1/assets/{id}/file`: the file, or the range asked (206 with `Content-Range`).
pub(super) async fn asset_file(
    State(state): Shared,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, AppError> {
    let a = state.store.get(&id)?;
    let len = match &a.asset.chunks {
        Some(c) => c.len(),
        None => a.bytes,
    };
    let range = asked_range(&headers, len)?;
    let (first, last) = range.unwrap_or((0, len.saturating_sub(1)));
    let n = last + 1 - first;
    if n > MOST_BYTES {
        return Err(AppError {
            status: StatusCode::PAYLOAD_TOO_LARGE,
            code: ErrorCode::TooLarge,
            detail: format!("{n} bytes in one answer, over {MOST_BYTES}: ask by Range"),
            retry_after: None,
        });
    }
    // A chunked file is read where it lies (a file, a bucket: blocking reads, off the async
    // executor); a whole asset is small and held decoded, and written back as its file.
    let asset = a.clone();
    let bytes = tokio::task::spawn_blocking(move || match &asset.asset.chunks {
        Some(c) => c.read(first, n as usize).map_err(chunk_unavailable),
        None => {
            let whole = asset.asset.to_bytes();
            Ok(whole[first as usize..=last as usize].to_vec())
        }
    })
    .await
    .map_err(|_| AppError::internal("the read did not finish"))??;
    let etag = format!("\"{:08x}-{len}\"", a.hash);
    let mut response = (
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static("application/octet-stream"),
            ),
            (header::ACCEPT_RANGES, HeaderValue::from_static("bytes")),
        ],
        bytes,
    )
        .into_response();
    let h = response.headers_mut();
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    if range.is_some() {
        *response.status_mut() = StatusCode::PARTIAL_CONTENT;
        if let Ok(v) = HeaderValue::from_str(&format!("bytes {first}-{last}/{len}")) {
            response.headers_mut().insert(header::CONTENT_RANGE, v);
        }
    }
    Ok(response)
}
