//! One error type for every handler: a status, a stable machine code and a human detail,
//! answered as `{"detail": "...", "code": "..."}` (axum's recommended pattern).

use axum::Json;
use axum::extract::FromRequestParts;
use axum::http::request::Parts;
use axum::http::{Method, StatusCode, Uri};
use axum::response::{IntoResponse, Response};
use fractile_proto::ErrorCode;

/// An error answered to an HTTP client.
#[derive(Debug)]
pub struct AppError {
    /// HTTP status.
    pub status: StatusCode,
    /// Stable code clients can match on (one list: [`ErrorCode`]).
    pub code: ErrorCode,
    /// What went wrong, for people.
    pub detail: String,
    /// Seconds after which a retry may succeed (`Retry-After`), for refusals that are the
    /// server's state, not the request's (a full queue, a store that is down).
    pub retry_after: Option<u32>,
}

impl AppError {
    /// 400 with a code.
    pub fn bad_request(code: ErrorCode, detail: impl Into<String>) -> Self {
        AppError {
            status: StatusCode::BAD_REQUEST,
            code,
            detail: detail.into(),
            retry_after: None,
        }
    }
    /// 404 with a code.
    pub fn not_found(code: ErrorCode, detail: impl Into<String>) -> Self {
        AppError {
            status: StatusCode::NOT_FOUND,
            code,
            detail: detail.into(),
            retry_after: None,
        }
    }
    /// 500: a bug or a lost worker, never the client's fault.
    pub fn internal(detail: impl Into<String>) -> Self {
        AppError {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            code: ErrorCode::Internal,
            detail: detail.into(),
            retry_after: None,
        }
    }
}

impl IntoResponse for AppError {
    fn into_response(self) -> Response {
        let body = Json(fractile_proto::ErrorBody {
            detail: self.detail,
            code: self.code.as_str().into(),
        });
        let mut response = (self.status, body).into_response();
        if let Some(secs) = self.retry_after {
            response.headers_mut().insert(
                axum::http::header::RETRY_AFTER,
                axum::http::HeaderValue::from(secs),
            );
        }
        response
    }
}

/// axum's `Query`, answering a query string that does not parse (`?level=-1`) with an
/// [`AppError`] (`bad_query`) instead of axum's plain-text rejection, so that every 4xx a client
/// sees has the same JSON shape.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Query<T>(pub T);

impl<T, S> FromRequestParts<S> for Query<T>
where
    T: serde::de::DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = AppError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        match axum::extract::Query::<T>::from_request_parts(parts, state).await {
            Ok(axum::extract::Query(v)) => Ok(Query(v)),
            Err(e) => Err(AppError::bad_request(ErrorCode::BadQuery, e.body_text())),
        }
    }
}

/// axum's `Path`, answering a path segment that does not parse (a zoom of `abc` or `300`) with
/// an [`AppError`] (`bad_path`, or axum's own status where it is not the client's fault).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Path<T>(pub T);

impl<T, S> FromRequestParts<S> for Path<T>
where
    T: serde::de::DeserializeOwned + Send,
    S: Send + Sync,
{
    type Rejection = AppError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        match axum::extract::Path::<T>::from_request_parts(parts, state).await {
            Ok(axum::extract::Path(v)) => Ok(Path(v)),
            Err(e) if e.status().is_client_error() => Err(AppError {
                status: e.status(),
                code: ErrorCode::BadPath,
                detail: e.body_text(),
                retry_after: None,
            }),
            Err(e) => Err(AppError::internal(e.body_text())),
        }
    }
}

/// The answer to a path no route serves (the router's fallback).
pub(crate) async fn no_route(method: Method, uri: Uri) -> AppError {
    AppError::not_found(
        ErrorCode::NoRoute,
        format!(
            "no route for {method} {} (see /v1/openapi.json)",
            uri.path()
        ),
    )
}

/// The answer to a method a route does not serve (axum adds the `Allow` header).
pub(crate) async fn method_not_allowed(method: Method, uri: Uri) -> AppError {
    AppError {
        status: StatusCode::METHOD_NOT_ALLOWED,
        code: ErrorCode::MethodNotAllowed,
        detail: format!("{} does not answer {method}", uri.path()),
        retry_after: None,
    }
}

/// Middleware: gives an error answered by a layer rather than a handler (the body limit's 413,
/// the timeout's 503, a wrong content type's 415) the same JSON body as [`AppError`], keeping
/// its status, headers and text as the detail. Answers that are JSON already pass untouched.
pub(crate) async fn json_errors(resp: Response) -> Response {
    let status = resp.status();
    let is_json = resp
        .headers()
        .get(axum::http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return resp;
    }
    let (mut parts, body) = resp.into_parts();
    // Layers answer a line of text; more than this is not a rejection text worth keeping.
    let text = axum::body::to_bytes(body, 16 * 1024)
        .await
        .unwrap_or_default();
    let text = String::from_utf8_lossy(&text).trim().to_string();
    let detail = if text.is_empty() {
        status.canonical_reason().unwrap_or("error").to_string()
    } else {
        text
    };
    let code = match status {
        StatusCode::PAYLOAD_TOO_LARGE => ErrorCode::TooLarge,
        StatusCode::SERVICE_UNAVAILABLE => ErrorCode::Unavailable,
        StatusCode::UNSUPPORTED_MEDIA_TYPE => ErrorCode::BadMediaType,
        StatusCode::METHOD_NOT_ALLOWED => ErrorCode::MethodNotAllowed,
        StatusCode::NOT_FOUND => ErrorCode::NoRoute,
        s if s.is_client_error() => ErrorCode::BadRequest,
        _ => ErrorCode::Internal,
    };
    parts.headers.remove(axum::http::header::CONTENT_TYPE);
    parts.headers.remove(axum::http::header::CONTENT_LENGTH);
    let mut out = AppError {
        status,
        code,
        detail,
        retry_after: None,
    }
    .into_response();
    for (name, value) in parts.headers.iter() {
        out.headers_mut().append(name.clone(), value.clone());
    }
    out
}
