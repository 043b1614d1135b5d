//! An asset's file as stored, whole or by byte range (RFC 9110 `Range: bytes=a-b`): what a
//! client that decodes by itself reads (the browser's WebAssembly reader, `wasm/js/reader.js`;
//! a script with the codec), only the header, table and chunks it needs.
//!
//! Served as a static host serves a file (nginx, S3), so that a reader behaves the same on
//! either: the stored bytes of the version the catalog serves, whatever format version they
//! are; a strong ETag per version (the file's checksum and length, equal on every replica);
//! `If-None-Match` (304), `If-Match` (412), `If-Range`; 416 with `Content-Range: bytes */LEN`;
//! suffix ranges longer than the file are the whole file; `HEAD` reads nothing. Answers are
//! streamed from where the file lies a piece at a time, so that many or slow readers hold a
//! piece each, not a file each (the connection's send timeout, `lib.rs`, closes a reader
//! that takes nothing).

use super::state::Shared;
use crate::error::{AppError, Path};
use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode, header};
use axum::response::{IntoResponse, Response};
use fractile_codec::chunked::ChunkSource;
use fractile_proto::ErrorCode;
use std::sync::Arc;

/// Bytes read from the store per piece of an answer: what one reader holds in the server at
/// a time (with hyper's write buffer), however large the file.
const PIECE: u64 = 128 << 10;

/// What a `Range` header asks of a file of `len` bytes.
#[derive(Debug, PartialEq, Eq)]
enum Asked {
    /// The whole file (no `Range`, or one `If-Range` says is stale).
    Whole,
    /// Bytes `first..=last`.
    Part(u64, u64),
}

/// The one byte range a `Range` header asks for, within a file of `len` bytes. RFC 9110
/// §14.1.2: a last position past the end is the end, a suffix longer than the file is the
/// whole file, a first position at or past the end is unsatisfiable.
fn asked_range(headers: &HeaderMap, len: u64) -> Result<Asked, AppError> {
    use http_range_header::{EndPosition, StartPosition};
    let Some(v) = headers.get(header::RANGE) else {
        return Ok(Asked::Whole);
    };
    let unsatisfiable = |why: &str| unsatisfiable(why, len);
    // Parsed by http-range-header, the parser tower-http's file server uses; its `validate`
    // refuses a suffix longer than the file, which RFC 9110 serves whole, so positions are
    // resolved here.
    let ranges = v
        .to_str()
        .ok()
        .and_then(|s| http_range_header::parse_range_header(s).ok())
        .ok_or_else(|| unsatisfiable("the Range header is not a byte range"))?;
    let [r] = ranges.ranges.as_slice() else {
        return Err(unsatisfiable(
            "several ranges in one request are not served",
        ));
    };
    let first = match r.start {
        StartPosition::Index(i) => i,
        StartPosition::FromLast(n) => len.saturating_sub(n),
    };
    let last = match r.end {
        EndPosition::Index(i) => i.min(len.saturating_sub(1)),
        EndPosition::LastByte => len.saturating_sub(1),
    };
    if first >= len || first > last {
        return Err(unsatisfiable("the range is not within the file"));
    }
    Ok(Asked::Part(first, last))
}

/// 416 with `Content-Range: bytes */LEN` (RFC 9110 §15.5.17), so that a reader learns the
/// length from the refusal.
fn unsatisfiable(why: &str, len: u64) -> AppError {
    AppError {
        status: StatusCode::RANGE_NOT_SATISFIABLE,
        code: ErrorCode::BadRange,
        detail: format!("{why} (the file has {len} bytes; one range, as bytes=FIRST-LAST)"),
        retry_after: None,
    }
}

/// Whether an `If-None-Match` or `If-Match` list names `etag` (`*` names any). `weak`: the
/// weak comparison of `If-None-Match` (a `W/` tag matches its strong twin).
fn names(list: &HeaderValue, etag: &str, weak: bool) -> bool {
    let Ok(list) = list.to_str() else {
        return false;
    };
    list.split(',').map(str::trim).any(|t| {
        t == "*" || t == etag || (weak && t.strip_prefix("W/").is_some_and(|strong| strong == etag))
    })
}

/// `GET` and `HEAD /v1/assets/{id}/file`: the file, or the range asked (206 with
/// `Content-Range`), under the conditions asked.
pub(super) async fn asset_file(
    State(state): Shared,
    Path(id): Path<String>,
    method: Method,
    headers: HeaderMap,
) -> Result<Response, AppError> {
    let opening = (state.clone(), id.clone());
    // Opening stats and opens a file, or asks a bucket: blocking, off the async executor.
    let file = tokio::task::spawn_blocking(move || opening.0.store.file(&opening.1))
        .await
        .map_err(|_| AppError::internal("the file could not be opened"))??;
    let (a, source) = (file.asset, file.source);
    let len = source.len();
    let etag = format!("\"{:08x}-{len}\"", a.hash);
    let etag_value = HeaderValue::from_str(&etag).map_err(|e| AppError::internal(e.to_string()))?;
    if let Some(want) = headers.get(header::IF_MATCH)
        && !names(want, &etag, false)
    {
        return Err(AppError {
            status: StatusCode::PRECONDITION_FAILED,
            code: ErrorCode::PreconditionFailed,
            detail: format!("the file is now {etag}, not what If-Match names"),
            retry_after: None,
        });
    }
    if let Some(have) = headers.get(header::IF_NONE_MATCH)
        && names(have, &etag, true)
    {
        let mut r = StatusCode::NOT_MODIFIED.into_response();
        r.headers_mut().insert(header::ETAG, etag_value);
        return Ok(r);
    }
    // If-Range: the range only while the reader's copy is this version; else the whole file.
    let current = headers
        .get(header::IF_RANGE)
        .is_none_or(|v| v.to_str().is_ok_and(|v| v.trim() == etag));
    let asked = if current {
        match asked_range(&headers, len) {
            Ok(a) => a,
            Err(e) => {
                let mut r = e.into_response();
                if let Ok(v) = HeaderValue::from_str(&format!("bytes */{len}")) {
                    r.headers_mut().insert(header::CONTENT_RANGE, v);
                }
                return Ok(r);
            }
        }
    } else {
        Asked::Whole
    };
    let (first, last) = match asked {
        Asked::Whole => (0, len.saturating_sub(1)),
        Asked::Part(first, last) => (first, last),
    };
    let n = if len == 0 { 0 } else { last + 1 - first };
    let body = if method == Method::HEAD || n == 0 {
        Body::empty()
    } else {
        let opened = (id, file.version);
        Body::from_stream(pieces(state, opened, Arc::from(source), first, n))
    };
    let mut response = Response::new(body);
    let h = response.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/octet-stream"),
    );
    h.insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    h.insert(header::ETAG, etag_value);
    h.insert(header::CONTENT_LENGTH, HeaderValue::from(n));
    if let Asked::Part(first, last) = asked {
        *response.status_mut() = StatusCode::PARTIAL_CONTENT;
        if let Ok(v) = HeaderValue::from_str(&format!("bytes {first}-{last}/{len}")) {
            response.headers_mut().insert(header::CONTENT_RANGE, v);
        }
    }
    Ok(response)
}

/// `n` bytes of `source` from `first`, a [`PIECE`] at a time, each read off the async
/// executor when the connection asks for it (so a reader that does not read holds no thread
/// and at most a piece). A file that changes under the answer ends it with an error: the
/// reader sees a broken answer, never bytes of two versions under one ETag.
fn pieces(
    state: Arc<super::state::AppState>,
    (id, version): (String, String),
    source: Arc<dyn ChunkSource>,
    first: u64,
    n: u64,
) -> impl futures_util::Stream<Item = std::io::Result<axum::body::Bytes>> {
    let end = first + n;
    futures_util::stream::try_unfold(first, move |at| {
        let (source, state) = (source.clone(), state.clone());
        let (id, version) = (id.clone(), version.clone());
        async move {
            if at >= end {
                return Ok(None);
            }
            let take = PIECE.min(end - at) as usize;
            let piece = tokio::task::spawn_blocking(move || {
                let bytes = source.read(at, take)?;
                if !state.store.unchanged(&id, &version) {
                    return Err(std::io::Error::other(format!(
                        "the file of {id} changed while it was sent"
                    )));
                }
                Ok(bytes)
            })
            .await
            .map_err(std::io::Error::other)??;
            Ok(Some((axum::body::Bytes::from(piece), at + take as u64)))
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn range(v: &str, len: u64) -> Result<Asked, StatusCode> {
        let mut h = HeaderMap::new();
        h.insert(header::RANGE, HeaderValue::from_str(v).unwrap());
        asked_range(&h, len).map_err(|e| e.status)
    }

    #[test]
    fn ranges_resolve_as_rfc_9110_says() {
        assert_eq!(range("bytes=0-9", 100), Ok(Asked::Part(0, 9)));
        // A last position past the end is the end.
        assert_eq!(range("bytes=90-1000", 100), Ok(Asked::Part(90, 99)));
        assert_eq!(range("bytes=90-", 100), Ok(Asked::Part(90, 99)));
        // A suffix longer than the file is all of it.
        assert_eq!(range("bytes=-500", 100), Ok(Asked::Part(0, 99)));
        assert_eq!(range("bytes=-10", 100), Ok(Asked::Part(90, 99)));
        let refused = Err(StatusCode::RANGE_NOT_SATISFIABLE);
        assert_eq!(range("bytes=100-", 100), refused);
        assert_eq!(range("bytes=5-2", 100), refused);
        assert_eq!(range("bytes=0-1,5-6", 100), refused);
        assert_eq!(range("lines=0-1", 100), refused);
    }

    #[test]
    fn conditions_compare_tags() {
        let v = |s: &str| HeaderValue::from_str(s).unwrap();
        assert!(names(&v("\"a\", \"b-1\""), "\"b-1\"", false));
        assert!(names(&v("*"), "\"b-1\"", false));
        assert!(!names(&v("W/\"b-1\""), "\"b-1\"", false));
        assert!(names(&v("W/\"b-1\""), "\"b-1\"", true));
        assert!(!names(&v("\"c\""), "\"b-1\"", true));
    }
}
