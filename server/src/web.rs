//! The web viewer at `/`: a page, its script and MapLibre GL JS, all compiled into the binary
//! (no CDN, works offline). See `server/web/`.

use axum::Router;
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::get;

fn asset(content_type: &'static str, body: &'static [u8]) -> impl IntoResponse {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CACHE_CONTROL, "public, max-age=300"),
        ],
        body,
    )
}

/// Routes of the viewer.
pub(crate) fn routes<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new()
        .route(
            "/",
            get(|| async {
                asset(
                    "text/html; charset=utf-8",
                    include_bytes!("../web/index.html"),
                )
            }),
        )
        .route(
            "/viewer.js",
            get(|| async { asset("text/javascript", include_bytes!("../web/viewer.js")) }),
        )
        .route(
            "/vendor/maplibre-gl.js",
            get(|| async {
                asset(
                    "text/javascript",
                    include_bytes!("../web/vendor/maplibre-gl.js"),
                )
            }),
        )
        .route(
            "/vendor/maplibre-gl.css",
            get(|| async { asset("text/css", include_bytes!("../web/vendor/maplibre-gl.css")) }),
        )
}
