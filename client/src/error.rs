//! The client's one error type: what the server refused (with its stable `code` and human
//! `detail`), what never reached it, and what came back unreadable.

use fractile_proto::ErrorBody;

/// Why a request failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// 400 or 422: the request was malformed (bad tile address, bbox, iterations, ...) or the
    /// uploaded file is not a valid asset.
    #[error("bad request {status} ({code}): {detail}")]
    BadRequest {
        /// 400, or 422 for an unreadable upload.
        status: u16,
        /// The server's stable code, e.g. `bad_tile`.
        code: String,
        /// The server's explanation.
        detail: String,
    },
    /// 401: a write without the right token.
    #[error("unauthorised ({code}): {detail}")]
    Unauthorised {
        /// The server's stable code.
        code: String,
        /// The server's explanation.
        detail: String,
    },
    /// 404: no such asset, or the tile or point lies outside it.
    #[error("not found ({code}): {detail}")]
    NotFound {
        /// `unknown_asset`, `no_tile`, `outside`, ...
        code: String,
        /// The server's explanation.
        detail: String,
    },
    /// 413: over a size limit (points per batch, upload bytes).
    #[error("too large ({code}): {detail}")]
    TooLarge {
        /// The server's stable code, e.g. `too_many_points`.
        code: String,
        /// The server's explanation.
        detail: String,
    },
    /// 429 or 503: the server sheds load; retry later.
    #[error("server busy ({status}): {detail}")]
    Busy {
        /// The HTTP status.
        status: u16,
        /// The server's explanation.
        detail: String,
    },
    /// Any other error status.
    #[error("server error {status} ({code}): {detail}")]
    Server {
        /// The HTTP status.
        status: u16,
        /// The server's stable code (`internal`, or `http` when the body was not ours).
        code: String,
        /// The server's explanation.
        detail: String,
    },
    /// The request never got an answer (connection refused, timeout, TLS).
    #[error("transport: {0}")]
    Transport(#[source] reqwest::Error),
    /// A fetched file that could not be written where it was asked to go.
    #[error("writing {path}: {source}")]
    Write {
        /// The file.
        path: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// An answer or an argument that cannot be read.
    #[error("malformed {what}: {reason}")]
    Malformed {
        /// What was being read.
        what: String,
        /// Why it could not be.
        reason: String,
    },
}

impl ClientError {
    pub(crate) fn malformed(what: impl Into<String>, reason: impl Into<String>) -> ClientError {
        ClientError::Malformed {
            what: what.into(),
            reason: reason.into(),
        }
    }

    /// An error answer: the server's JSON body when it is one, the raw text otherwise (a
    /// proxy's page, a rejection of the framework).
    pub(crate) fn from_answer(status: u16, text: &str) -> ClientError {
        let (code, detail) = match serde_json::from_str::<ErrorBody>(text) {
            Ok(b) => (b.code, b.detail),
            Err(_) => ("http".to_string(), text.trim().chars().take(500).collect()),
        };
        match status {
            400 | 422 => ClientError::BadRequest {
                status,
                code,
                detail,
            },
            401 | 403 => ClientError::Unauthorised { code, detail },
            404 => ClientError::NotFound { code, detail },
            413 => ClientError::TooLarge { code, detail },
            429 | 503 => ClientError::Busy { status, detail },
            _ => ClientError::Server {
                status,
                code,
                detail,
            },
        }
    }

    /// The server's stable code, for errors the server answered.
    pub fn code(&self) -> Option<&str> {
        match self {
            ClientError::BadRequest { code, .. }
            | ClientError::Unauthorised { code, .. }
            | ClientError::NotFound { code, .. }
            | ClientError::TooLarge { code, .. }
            | ClientError::Server { code, .. } => Some(code),
            _ => None,
        }
    }

    /// The HTTP status, for errors the server answered.
    pub fn status(&self) -> Option<u16> {
        Some(match self {
            ClientError::Unauthorised { .. } => 401,
            ClientError::NotFound { .. } => 404,
            ClientError::TooLarge { .. } => 413,
            ClientError::BadRequest { status, .. }
            | ClientError::Busy { status, .. }
            | ClientError::Server { status, .. } => *status,
            _ => return None,
        })
    }
}
