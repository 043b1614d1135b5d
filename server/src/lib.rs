//! The fractile service: an axum router over an asset store (see [`api`]), and `serve`, which
//! runs it with logging, timeouts, CORS and graceful shutdown. The binary `fractile` adds the
//! command line (encode, decode, info, compare, serve).

pub mod api;
pub mod encoding;
pub mod error;
pub mod openapi;
pub mod store;
pub mod telemetry;
pub mod web;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use tower_http::cors::{Any, CorsLayer};
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;

/// How to run the server.
pub struct ServeOptions {
    /// Asset directory; `None` serves the built-in demo assets.
    pub assets: Option<PathBuf>,
    /// Address to listen on.
    pub bind: SocketAddr,
    /// Public base URL for absolute links (defaults to `http://{bind}`).
    pub public_url: Option<String>,
    /// Bearer token for PUT and DELETE; writes are open without one.
    pub write_token: Option<String>,
}

/// The full application: API routes and middleware.
pub fn app(state: Arc<api::AppState>) -> axum::Router {
    telemetry::handle();
    api::router(state)
        .route(
            "/metrics",
            axum::routing::get(|| async { telemetry::handle().render() }),
        )
        .merge(web::routes())
        .layer(axum::middleware::from_fn(telemetry::track))
        .layer(
            CorsLayer::new()
                .allow_origin(Any)
                .allow_methods([axum::http::Method::GET, axum::http::Method::POST]),
        )
        .layer(TimeoutLayer::with_status_code(
            axum::http::StatusCode::SERVICE_UNAVAILABLE,
            api::REQUEST_TIMEOUT,
        ))
        .layer(TraceLayer::new_for_http())
}

/// Loads the assets and serves until SIGTERM or ctrl-c (in-flight requests finish).
pub async fn serve(opts: ServeOptions) -> anyhow::Result<()> {
    let dir = match &opts.assets {
        Some(d) => d.clone(),
        None => {
            let d = std::env::var_os("FRACTILE_CACHE")
                .map(PathBuf::from)
                .unwrap_or_else(|| {
                    std::env::temp_dir()
                        .join(format!("fractile-demo-{}", env!("CARGO_PKG_VERSION")))
                });
            let d2 = d.clone();
            tokio::task::spawn_blocking(move || store::ensure_demo_assets(&d2)).await??;
            d
        }
    };
    let (store, skipped) =
        store::Store::open(&dir).map_err(|e| anyhow::anyhow!("{}: {e}", dir.display()))?;
    for s in &skipped {
        tracing::warn!("skipped broken asset {s}");
    }
    tracing::info!(
        "serving {} assets from {}",
        store.list().len(),
        dir.display()
    );
    let public = opts
        .public_url
        .clone()
        .unwrap_or_else(|| format!("http://{}", opts.bind));
    let mut state = api::AppState::new(store, public.trim_end_matches('/').to_string());
    if opts.write_token.is_none() {
        tracing::warn!(
            "no write token configured: PUT and DELETE are open to anyone who can reach {}",
            opts.bind
        );
    }
    state.write_token = opts.write_token.clone();
    let state = Arc::new(state);
    let listener = tokio::net::TcpListener::bind(opts.bind).await?;
    tracing::info!("listening on http://{}", listener.local_addr()?);
    axum::serve(listener, app(state))
        .with_graceful_shutdown(shutdown())
        .await?;
    Ok(())
}

async fn shutdown() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        if let Ok(mut s) = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        {
            s.recv().await;
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! { _ = ctrl_c => {}, _ = term => {} }
    tracing::info!("shutting down: finishing in-flight requests");
}
