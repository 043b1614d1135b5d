//! The fractile service: an axum router over an asset store (the `api` module), and `serve`, which
//! runs it with logging, timeouts, CORS and graceful shutdown. The binary `fractile` adds the
//! command line (encode, decode, info, compare, serve).

// A server answers bad input with an error, never a panic: no unwrap or expect outside tests,
// and each invariant that stays an expect says why where it is (`#[expect(..., reason)]`).
#![warn(clippy::unwrap_used, clippy::expect_used)]
#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

mod api;
mod backend;
pub mod encoding;
mod error;
mod memory;
mod openapi;
mod store;
mod telemetry;
mod web;
mod work;

// A curated surface (as image-rs's); modules stay private: a handler moved changes no caller.
pub use api::{
    AppState, Cached, CoarseCache, DEFAULT_COARSE_CACHE_MIB, Limits, REQUEST_TIMEOUT, Writes,
    coarse_cache,
};
pub use backend::GpuBackend;
pub use store::{Refreshed, Store, s3_store};
pub use work::Lanes;

use fractile_proto::ErrorCode;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use tower_http::cors::{Any, CorsLayer};
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;

/// Settings of `fractile.toml` (`fractile serve --config`); every key is optional. Command-line
/// flags and `FRACTILE_*` environment variables override the file.
#[derive(Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileConfig {
    /// Asset directory, or an object store's bucket (`s3://bucket/prefix`).
    pub assets: Option<PathBuf>,
    /// With assets in an object store: a folder where the ranges read are also kept (so a
    /// chunk evicted from the chunk cache, or needed again after a restart's prefetch, is read
    /// from local disk); none by default.
    pub disk_cache: Option<PathBuf>,
    /// Size of `disk_cache` in MiB (default 4096).
    pub disk_cache_mib: Option<u64>,
    /// Address to listen on.
    pub bind: Option<SocketAddr>,
    /// Public base URL for absolute links.
    pub public_url: Option<String>,
    /// Bearer token for PUT and DELETE.
    pub write_token: Option<String>,
    /// Whether PUT and DELETE are open to anyone when no write token is set (default false:
    /// they are refused with 403; true for the built-in demo on a loopback address).
    pub allow_anonymous_writes: Option<bool>,
    /// `Cache-Control` of tiles.
    pub cache_control: Option<String>,
    /// How often, in seconds, the asset folder is looked at for files another process (a
    /// replica sharing the volume) stored, replaced or removed (default 10; 0: never).
    pub rescan_seconds: Option<u64>,
    /// Largest upload, in MiB.
    pub max_upload_mib: Option<usize>,
    /// Most inverse steps a request may ask for.
    pub max_iterations: Option<u32>,
    /// Most requests in flight; more wait (and time out after 30 s).
    pub max_concurrent_requests: Option<usize>,
    /// Tile cache size in MiB.
    pub tile_cache_mib: Option<u64>,
    /// Coarse-decode cache size in MiB (default 256): the whole-asset discrete decodes that
    /// tiles coarser than the source sample, a grid per asset, zoom and band of latitude (see
    /// `Asset::answer`; a band's grid is derived from a finer one of the same zoom when
    /// that is cached). Size it to hold the coarse zooms of the largest assets (about 8
    /// bytes a source pixel and plane: 256 MiB holds a 30 Mpx DEM's), or their grids are
    /// decoded again and again.
    pub coarse_cache_mib: Option<u64>,
    /// Decoded chunks of chunked assets in MiB (default 384), shared by all of them: each
    /// request reads the chunks it touches by range and decodes them into this cache (a
    /// 1024^2 chunk of the default DEM codec holds about 5.3 MB). With it, the server's memory
    /// is bounded by its caches, not by the sizes of its assets.
    pub chunk_cache_mib: Option<u64>,
    /// Whether chunks are decoded into the chunk cache ahead of requests at start, coarsest
    /// level first, until it is 90% full (default true; see `Chunked::prefetch`).
    pub prefetch_chunks: Option<bool>,
    /// A folder holding CesiumJS's build (`Build/Cesium` of the npm package `cesium`;
    /// `tools/fetch-cesium.sh` puts one in `target/cesium`), served at `/vendor/cesium/` so that
    /// the viewer shows the DEM on a globe through `layer.json`. Not compiled in: it is 14 MB.
    pub cesium_dir: Option<PathBuf>,
    /// A folder holding the browser's decoder (`wasm/build.sh` writes `target/wasm-web`),
    /// served at `/wasm/` so that the viewer can decode the DEM in the browser beside the
    /// server's tiles. Not compiled in: it is built for another target.
    pub wasm_dir: Option<PathBuf>,
    /// Where continuous decoding runs: `cpu`, `gpu` or `auto` (default; see `backend`).
    pub backend: Option<String>,
    /// GPU memory for resident operators, in MiB (default 1024).
    pub gpu_memory_mib: Option<u64>,
    /// Most samples an asset may claim (width x height; voxels of a volume), default 2^28.
    pub max_asset_pixels: Option<u64>,
    /// Memory decoding may take, in MiB (default: half of the container's or machine's memory
    /// less 1 GiB, within 256..16384; 3072 where it cannot be read): the most one asset may cost to decode
    /// (its operator and a full-resolution decode), and the total of large requests in flight
    /// (regions, meshes: more wait for room; one larger than this is refused with 413).
    pub max_decode_mib: Option<u32>,
}

impl FileConfig {
    /// Reads a TOML file; unknown keys are an error (a typo must not be ignored silently).
    pub fn load(path: &std::path::Path) -> anyhow::Result<FileConfig> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
    }
}

/// How to run the server.
pub struct ServeOptions {
    /// Asset directory or object store bucket (`s3://bucket/prefix`); `None` serves the
    /// built-in demo assets.
    pub assets: Option<PathBuf>,
    /// Address to listen on.
    pub bind: SocketAddr,
    /// Public base URL for absolute links (defaults to `http://{bind}`).
    pub public_url: Option<String>,
    /// Bearer token for PUT and DELETE; without one they are refused, unless the file
    /// config allows anonymous writes.
    pub write_token: Option<String>,
    /// Everything else the config file may set.
    pub file: FileConfig,
}

/// A folder of the viewer's (CesiumJS's, the browser decoder's) as `ServeDir` serves it (which
/// refuses `..`), less what lies behind a symbolic link, which it follows: the assets folder
/// serves only its own files, and so does this one (`leak.js -> /etc/hostname` was served).
fn folder_files(dir: PathBuf) -> axum::Router {
    let served = tower_http::services::ServeDir::new(dir.clone());
    axum::Router::new()
        .fallback_service(served)
        .layer(axum::middleware::from_fn(
            move |req: axum::extract::Request, next: axum::middleware::Next| {
                let dir = dir.clone();
                async move {
                    if through_a_link(&dir, req.uri().path()).await {
                        let refused = error::AppError::not_found(
                            ErrorCode::NoFile,
                            "no such file in the folder (links are not followed)",
                        );
                        return axum::response::IntoResponse::into_response(refused);
                    }
                    next.run(req).await
                }
            },
        ))
}

/// Whether the request path `path` (percent-encoded, under `dir`) passes through a symbolic
/// link, or climbs out with `..`. A part that does not exist ends the walk: `ServeDir` answers
/// 404 for it.
async fn through_a_link(dir: &std::path::Path, path: &str) -> bool {
    let decoded = percent_encoding::percent_decode_str(path).decode_utf8_lossy();
    let mut at = dir.to_path_buf();
    for part in decoded.split('/').filter(|p| !p.is_empty() && *p != ".") {
        if part == ".." {
            return true;
        }
        at.push(part);
        match tokio::fs::symlink_metadata(&at).await {
            Ok(m) if m.file_type().is_symlink() => return true,
            Ok(_) => {}
            Err(_) => return false,
        }
    }
    false
}

/// The full application: API routes and middleware.
pub fn app(state: Arc<api::AppState>) -> axum::Router {
    telemetry::handle();
    // CesiumJS, when a folder of it is configured (ServeDir refuses paths out of it).
    let cesium = state.cesium_dir.clone();
    let wasm = state.wasm_dir.clone();
    let gpu = state.gpu.clone();
    let coarse = state.coarse.clone();
    let router = api::router(state);
    let router = match cesium {
        Some(dir) => router.nest("/vendor/cesium", folder_files(dir)),
        None => router,
    };
    let router = match wasm {
        Some(dir) => router.nest("/wasm", folder_files(dir)),
        None => router,
    };
    router
        .route(
            "/metrics",
            axum::routing::get(|| async move {
                if let Some(g) = &gpu {
                    telemetry::gpu_rounds(g.rounds());
                    telemetry::gpu_uploads(g.uploads());
                }
                telemetry::coarse_grids(coarse.counts());
                telemetry::handle().render()
            }),
        )
        .merge(web::routes())
        .fallback(error::no_route)
        .method_not_allowed_fallback(error::method_not_allowed)
        .layer(axum::middleware::from_fn(telemetry::track))
        .layer(
            // A page on another origin (a static host, the usual serverless case) reads
            // `/file` by range and tiles' bounds: what it must see is exposed, what it sends
            // allowed.
            CorsLayer::new()
                .allow_origin(Any)
                .allow_methods([
                    axum::http::Method::GET,
                    axum::http::Method::HEAD,
                    axum::http::Method::POST,
                ])
                .allow_headers([
                    axum::http::header::RANGE,
                    axum::http::header::IF_MATCH,
                    axum::http::header::IF_NONE_MATCH,
                    axum::http::header::IF_RANGE,
                    axum::http::header::CONTENT_TYPE,
                ])
                .expose_headers([
                    axum::http::header::CONTENT_RANGE,
                    axum::http::header::CONTENT_LENGTH,
                    axum::http::header::ACCEPT_RANGES,
                    axum::http::header::ETAG,
                    axum::http::HeaderName::from_static("x-error-bound"),
                    axum::http::HeaderName::from_static("x-convergence-bound"),
                ]),
        )
        .layer(TimeoutLayer::with_status_code(
            axum::http::StatusCode::SERVICE_UNAVAILABLE,
            api::REQUEST_TIMEOUT,
        ))
        .layer(axum::middleware::map_response(error::json_errors))
        .layer(TraceLayer::new_for_http())
}

/// A listener on `bind`, or an error that names the address and what to do.
async fn listen(bind: std::net::SocketAddr) -> anyhow::Result<tokio::net::TcpListener> {
    tokio::net::TcpListener::bind(bind).await.map_err(|e| {
        let hint = match e.kind() {
            std::io::ErrorKind::AddrInUse => {
                "another program (another fractile serve?) listens there: stop it, or choose \
                 another address with --bind (FRACTILE_BIND), e.g. --bind 127.0.0.1:8081"
            }
            std::io::ErrorKind::PermissionDenied => {
                "ports under 1024 need privileges: choose another with --bind (FRACTILE_BIND)"
            }
            _ => "choose another address with --bind (FRACTILE_BIND)",
        };
        anyhow::anyhow!("cannot listen on {bind}: {e}; {hint}")
    })
}

/// Who may write, logged. The built-in demo (no assets named) on a loopback address takes
/// anonymous writes unless told otherwise: its assets are a throwaway cache only this machine
/// can reach, and the README's upload example should work against the server its first
/// command starts. Anything else refuses writes without a token.
fn writes(opts: &ServeOptions) -> api::Writes {
    let demo_on_loopback = opts.assets.is_none() && opts.bind.ip().is_loopback();
    let writes = api::Writes::from_options(
        opts.write_token.clone(),
        opts.file.allow_anonymous_writes.unwrap_or(demo_on_loopback),
    );
    match &writes {
        api::Writes::Anyone if demo_on_loopback => tracing::info!(
            "the demo on {} takes uploads from this machine without a token (set \
             FRACTILE_WRITE_TOKEN to require one)",
            opts.bind
        ),
        api::Writes::Anyone => tracing::warn!(
            "anonymous writes allowed: PUT and DELETE are open to anyone who can reach {}",
            opts.bind
        ),
        api::Writes::Refused => {
            tracing::info!("no write token configured: PUT and DELETE are refused (403)")
        }
        api::Writes::Token(_) => {}
    }
    writes
}

/// Loads the assets and serves until SIGTERM or ctrl-c (in-flight requests finish).
pub async fn serve(opts: ServeOptions) -> anyhow::Result<()> {
    // The address first, before assets load: a port in use should fail at once and say what
    // to do, not after the start-up log as a bare "os error 98".
    let listener = listen(opts.bind).await?;
    let decode_mib = opts
        .file
        .max_decode_mib
        .unwrap_or_else(memory::default_decode_mib)
        .max(1);
    let limits = fractile_codec::AssetLimits {
        max_pixels: opts
            .file
            .max_asset_pixels
            .unwrap_or(fractile_codec::AssetLimits::default().max_pixels),
        max_decode_bytes: u64::from(decode_mib) << 20,
    };
    let chunks = fractile_codec::chunked::ChunkCache::new(
        opts.file
            .chunk_cache_mib
            .unwrap_or(store::DEFAULT_CHUNK_CACHE_MIB)
            .max(1)
            << 20,
    );
    let backing = backing(&opts).await?;
    let (store, skipped) =
        tokio::task::spawn_blocking(move || store::Store::over(backing, limits, chunks)).await??;
    for s in &skipped {
        tracing::warn!("skipped broken asset {s}");
    }
    tracing::info!(
        "serving {} assets from {}",
        store.list().len(),
        store.describe()
    );
    if opts.file.prefetch_chunks.unwrap_or(true) {
        store.prefetch_in_background();
    }
    let public = opts
        .public_url
        .clone()
        .unwrap_or_else(|| format!("http://{}", opts.bind));
    let mut state = api::AppState::new(store, public.trim_end_matches('/').to_string());
    state.writes = writes(&opts);
    if let Some(c) = &opts.file.cache_control {
        state.cache_control = c.clone();
    }
    if let Some(m) = opts.file.max_upload_mib {
        state.max_upload = m.max(1) * 1024 * 1024;
    }
    // Upload bodies in flight: room for two of the largest.
    state.uploads_mib = (2 * (state.max_upload >> 20)).clamp(1, 1 << 20) as u32;
    state.uploads = Arc::new(tokio::sync::Semaphore::new(state.uploads_mib as usize));
    state.lanes = work::Lanes::new(
        std::thread::available_parallelism().map_or(2, |n| n.get()),
        decode_mib,
    );
    tracing::info!(
        "max_decode_mib {decode_mib}{}, {} large decodes at once",
        if opts.file.max_decode_mib.is_some() {
            ""
        } else {
            " (from the memory limit)"
        },
        state.lanes.heavy_runs()
    );
    if let Some(n) = opts.file.max_iterations {
        state.limits.max_iterations = n.clamp(1, 256);
    }
    if let Some(m) = opts.file.tile_cache_mib {
        state.cache = moka::sync::Cache::builder()
            .weigher(|_k: &String, v: &Arc<api::Cached>| v.size().try_into().unwrap_or(u32::MAX))
            .max_capacity(m * 1024 * 1024)
            .build();
    }
    state.cesium_dir = opts.file.cesium_dir.clone();
    state.wasm_dir = opts.file.wasm_dir.clone();
    if let Some(m) = opts.file.coarse_cache_mib {
        state.coarse = api::coarse_cache(m);
    }
    state.backend = match &opts.file.backend {
        Some(b) => b.parse().map_err(|e: String| anyhow::anyhow!(e))?,
        None => backend::Backend::Auto,
    };
    if state.backend != backend::Backend::Cpu {
        let memory = opts.file.gpu_memory_mib.unwrap_or(1024) * 1024 * 1024;
        state.gpu = open_gpu(state.backend, memory).await?;
    }
    let concurrency = opts.file.max_concurrent_requests.unwrap_or(1024).max(1);
    let state = Arc::new(state);
    let rescan = opts.file.rescan_seconds.unwrap_or(DEFAULT_RESCAN_SECONDS);
    if rescan > 0 {
        tokio::spawn(rescan_assets(state.clone(), rescan));
    }
    tracing::info!("listening on http://{}", listener.local_addr()?);
    let app = app(state).layer(tower::limit::ConcurrencyLimitLayer::new(concurrency));
    run(listener, app, shutdown(), HEADER_READ_TIMEOUT).await;
    Ok(())
}

/// Where `opts` says the assets are: an object store's bucket (`s3://`), a folder, or the
/// demo assets' folder (made at first start). Listed by [`store::Store::over`].
async fn backing(opts: &ServeOptions) -> anyhow::Result<Box<dyn store::Backing>> {
    let url = opts
        .assets
        .as_ref()
        .and_then(|a| a.to_str())
        .filter(|a| a.contains("://"));
    if let Some(url) = url {
        let disk = match &opts.file.disk_cache {
            Some(dir) => Some(
                store::DiskCache::new(dir, opts.file.disk_cache_mib.unwrap_or(4096).max(1) << 20)
                    .map_err(|e| anyhow::anyhow!("disk cache {}: {e}", dir.display()))?,
            ),
            None => None,
        };
        // Nothing is requested yet: the listing (Store::over) is the first request.
        return Ok(Box::new(store::Bucket::connect(url, disk)?));
    }
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
    let folder = tokio::task::spawn_blocking(move || {
        store::Folder::open(&dir).map_err(|e| anyhow::anyhow!("{}: {e}", dir.display()))
    })
    .await??;
    Ok(Box::new(folder))
}

/// How often (seconds) a server looks for assets that another process stored in or removed
/// from its folder (`rescan_seconds`; 0: never): replicas sharing one volume serve what one of
/// them stored within this time.
pub const DEFAULT_RESCAN_SECONDS: u64 = 10;

/// Every `seconds`, brings the catalog up to date with the store ([`store::Store::refresh`]),
/// off the executor (a changed file is read and checked).
async fn rescan_assets(state: Arc<api::AppState>, seconds: u64) {
    let mut every = tokio::time::interval(std::time::Duration::from_secs(seconds));
    every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    every.tick().await;
    loop {
        every.tick().await;
        let st = state.clone();
        let Ok(found) = tokio::task::spawn_blocking(move || st.store.refresh()).await else {
            continue;
        };
        for id in &found.loaded {
            tracing::info!(
                "asset {id} loaded from {} (stored by another process)",
                state.store.describe()
            );
        }
        for id in &found.removed {
            tracing::info!(
                "asset {id} removed from {}: no longer served",
                state.store.describe()
            );
        }
        for m in &found.skipped {
            tracing::warn!("changed asset file not loaded (its previous version stays): {m}");
        }
        if let Some(m) = &found.unreachable {
            tracing::warn!("asset store not listed (the catalog stays as it was): {m}");
        }
    }
}

/// The server's GPU for `backend` (not `cpu`), `memory` bytes of resident operators; `None`
/// (logged) without one. Auto never decodes on a software adapter (slower than the CPU), and
/// an open one holds memory (Mesa's lavapipe: 82 MB resident, measured), so Auto looks at the
/// adapter before opening it. Opening blocks (and may take a second): not on the executor.
async fn open_gpu(
    backend: backend::Backend,
    memory: u64,
) -> anyhow::Result<Option<Arc<backend::GpuBackend>>> {
    let auto = backend == backend::Backend::Auto;
    let opened = tokio::task::spawn_blocking(move || {
        if auto
            && (!fractile_gpu::Gpu::hardware_may_exist()
                || fractile_gpu::Gpu::adapter_is_software().unwrap_or(false))
        {
            return Ok(None);
        }
        backend::GpuBackend::open(memory).map(Some)
    })
    .await?;
    Ok(match opened {
        Ok(Some(g)) => {
            tracing::info!("GPU decoding on {} ({backend:?})", g.adapter());
            Some(Arc::new(g))
        }
        Ok(None) => {
            tracing::info!(
                "no hardware GPU: decoding on the CPU (start with --backend gpu to decode on a \
                 software adapter)"
            );
            None
        }
        Err(e) => {
            tracing::warn!("{e}: decoding on the CPU");
            None
        }
    })
}

/// How long a connection may take to send a request's headers (a new connection: its first
/// byte too) before it is closed, so connections that never finish their headers do not stay
/// open: nginx's `client_header_timeout`. It is also how long an idle keep-alive connection is
/// kept (hyper times the next request's headers from the end of the last answer), and browsers
/// reuse their connections within a page load: measured with the viewer in headless Chromium on
/// a loaded 2-core machine, 30 s closed sockets under it (the coast map stayed empty on 1 of 1
/// loads), 60 s and 3600 s did not (2 of 2 each).
pub const HEADER_READ_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(60);

/// How long a write to a connection may make no progress before the connection is closed:
/// a reader that stops reading (or reads a byte a second) holds its answer's buffered piece
/// and its open file only this long. nginx's `send_timeout` is 60 s too.
pub const SEND_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(60);

/// Serves `app` on `listener` until `stop` resolves, then lets in-flight requests finish
/// (for at most [`api::REQUEST_TIMEOUT`]). What `axum::serve` does, plus the header-read
/// timeout it does not expose: HTTP/1 headers must arrive within `header_timeout`
/// ([`HEADER_READ_TIMEOUT`] in `serve`), and a connection that sends nothing at all is closed
/// after it too.
pub async fn run(
    listener: tokio::net::TcpListener,
    app: axum::Router,
    stop: impl std::future::Future<Output = ()>,
    header_timeout: std::time::Duration,
) {
    use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
    let mut builder = hyper_util::server::conn::auto::Builder::new(TokioExecutor::new());
    builder
        .http1()
        .timer(TokioTimer::new())
        .header_read_timeout(header_timeout);
    builder.http2().timer(TokioTimer::new());
    let graceful = hyper_util::server::graceful::GracefulShutdown::new();
    let service = hyper_util::service::TowerToHyperService::new(app);
    tokio::pin!(stop);
    loop {
        let (stream, _) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(c) => c,
                Err(e) => {
                    // Out of file descriptors, say: wait a little rather than spin.
                    tracing::warn!("accept: {e}");
                    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                    continue;
                }
            },
            () = &mut stop => break,
        };
        let _ = stream.set_nodelay(true);
        let builder = builder.clone();
        let service = service.clone();
        let watcher = graceful.watcher();
        tokio::spawn(async move {
            // The protocol is told by the first bytes: a peer that sends none is dropped.
            let mut first = [0u8; 1];
            match tokio::time::timeout(header_timeout, stream.peek(&mut first)).await {
                Ok(Ok(n)) if n > 0 => {}
                _ => return,
            }
            // A reader that takes nothing for SEND_TIMEOUT is closed, so that it holds no
            // answer's piece and no file open for longer (nginx's send_timeout).
            let mut stream = tokio_io_timeout::TimeoutStream::new(stream);
            stream.set_write_timeout(Some(SEND_TIMEOUT));
            let stream = Box::pin(stream);
            let conn = builder.serve_connection_with_upgrades(TokioIo::new(stream), service);
            let _ = watcher.watch(conn.into_owned()).await;
        });
    }
    drop(listener);
    tokio::select! {
        () = graceful.shutdown() => {}
        () = tokio::time::sleep(api::REQUEST_TIMEOUT) => {
            tracing::warn!("in-flight requests still running after {:?}: stopping", api::REQUEST_TIMEOUT);
        }
    }
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
