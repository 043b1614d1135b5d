//! One error type for every handler: a status, a stable machine code and a human detail,
//! answered as `{"detail": "...", "code": "..."}` (axum's recommended pattern).

use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

/// An error answered to an HTTP client.
#[derive(Debug)]
pub struct AppError {
    /// HTTP status.
    pub status: StatusCode,
    /// Stable code clients can match on.
    pub code: &'static str,
    /// What went wrong, for people.
    pub detail: String,
}

impl AppError {
    /// 400 with a code.
    pub fn bad_request(code: &'static str, detail: impl Into<String>) -> Self {
        AppError {
            status: StatusCode::BAD_REQUEST,
            code,
            detail: detail.into(),
        }
    }
    /// 404 with a code.
    pub fn not_found(code: &'static str, detail: impl Into<String>) -> Self {
        AppError {
            status: StatusCode::NOT_FOUND,
            code,
            detail: detail.into(),
        }
    }
    /// 500: a bug or a lost worker, never the client's fault.
    pub fn internal(detail: impl Into<String>) -> Self {
        AppError {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            code: "internal",
            detail: detail.into(),
        }
    }
}

impl IntoResponse for AppError {
    fn into_response(self) -> Response {
        let body = Json(fractile_proto::ErrorBody {
            detail: self.detail,
            code: self.code.into(),
        });
        (self.status, body).into_response()
    }
}
