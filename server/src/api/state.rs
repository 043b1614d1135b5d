//! The API's shared state: limits, caches, lanes and backends, the write policy, and the
//! request timeout.

use std::sync::Arc;
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::State;
use tokio::sync::Semaphore;

use crate::backend::{Backend, GpuBackend};
use crate::store::Store;
use crate::work::{Bounds, Lanes};

/// Limits on what one request may ask for.
#[derive(Clone, Debug)]
pub struct Limits {
    /// Most inverse steps or iterations a request may ask for.
    pub max_iterations: u32,
    /// Most pixels of a region.
    pub max_region_pixels: usize,
    /// Most points of a batch.
    pub max_points: usize,
    /// Deepest zoom served.
    pub max_zoom: u8,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_iterations: 64,
            max_region_pixels: 4096 * 4096,
            max_points: 100_000,
            max_zoom: 24,
        }
    }
}

/// Shared state of the handlers.
pub struct AppState {
    /// The catalog.
    pub store: Store,
    /// Request limits.
    pub limits: Limits,
    /// Where decoding runs and what it may cost at once (light slots, heavy budget).
    pub lanes: Lanes,
    /// Request bodies in flight (uploads, point batches), in MiB: a body waits for room before
    /// it is read.
    pub uploads: Arc<Semaphore>,
    /// Size of `uploads`, in MiB (twice the largest upload).
    pub uploads_mib: u32,
    /// Encoded tiles keyed like their ETag, bounded in bytes.
    pub cache: moka::sync::Cache<String, Arc<Cached>>,
    /// Discrete decodes of whole assets at the scale of a coarse zoom level, keyed by asset id
    /// and checksum (`StoredAsset::coarse_key`), grid size and steps, bounded in bytes: every
    /// tile of a zoom coarser than the source samples the same grid, so it is decoded once
    /// (concurrent requests wait for it).
    pub coarse: CoarseCache,
    /// `Cache-Control` value of tiles.
    pub cache_control: String,
    /// Public base URL for absolute links (TileJSON), e.g. behind a proxy.
    pub public_url: String,
    /// Who may PUT and DELETE assets (nobody unless a token or anonymous writes are set).
    pub writes: Writes,
    /// Largest asset upload in bytes.
    pub max_upload: usize,
    /// Where continuous decoding runs unless a request says otherwise.
    pub backend: Backend,
    /// The GPU, when the server has one.
    pub gpu: Option<Arc<GpuBackend>>,
    /// CesiumJS's build, served at `/vendor/cesium/` when set (`cesium_dir`).
    pub cesium_dir: Option<std::path::PathBuf>,
    /// The browser's decoder, served at `/wasm/` when set (`wasm_dir`).
    pub wasm_dir: Option<std::path::PathBuf>,
}

/// Default of `coarse_cache_mib`: every coarse zoom of a 9.3 Mpx DEM takes 73 MB (its zoom
/// 4 grid alone 37 MB), and 64 MiB made that grid decode four times over a zoom's tiles
/// (docs/benchmarks.md, `coarse_zooms`).
pub const DEFAULT_COARSE_CACHE_MIB: u64 = 256;

/// A coarse-decode cache of `mib` MiB, weighed by the bytes of its grids.
pub fn coarse_cache(mib: u64) -> CoarseCache {
    Arc::new(fractile_codec::extract::CoarseGrids::new(
        mib.saturating_mul(1024 * 1024),
    ))
}

/// A cached answer.
pub struct Cached {
    pub(crate) content_type: &'static str,
    /// `Content-Encoding` of the body (`gzip` for Cesium terrain to clients that accept it).
    pub(crate) content_encoding: Option<&'static str>,
    pub(crate) body: Bytes,
    pub(crate) bounds: Bounds,
}

impl Cached {
    /// Bytes it holds (its weight in the cache).
    pub fn size(&self) -> usize {
        self.body.len()
    }
}

impl AppState {
    /// State over a store with default limits, a 256 MiB tile cache and one decoder per core.
    pub fn new(store: Store, public_url: String) -> AppState {
        let cores = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(2);
        AppState {
            store,
            limits: Limits::default(),
            lanes: Lanes::new(cores, crate::memory::default_decode_mib()),
            uploads: Arc::new(Semaphore::new(2 * 64)),
            uploads_mib: 2 * 64,
            cache: moka::sync::Cache::builder()
                .weigher(|_k: &String, v: &Arc<Cached>| v.body.len().try_into().unwrap_or(u32::MAX))
                .max_capacity(256 * 1024 * 1024)
                .build(),
            coarse: coarse_cache(DEFAULT_COARSE_CACHE_MIB),
            cache_control: "public, max-age=3600".into(),
            public_url,
            writes: Writes::Refused,
            max_upload: 64 * 1024 * 1024,
            backend: Backend::Auto,
            gpu: None,
            cesium_dir: None,
            wasm_dir: None,
        }
    }
}

pub(super) type Shared = State<Arc<AppState>>;

/// Discrete decodes for coarse tiles (see [`AppState::coarse`]): the codec's, shared.
pub type CoarseCache = Arc<fractile_codec::extract::CoarseGrids>;

/// The default request timeout.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);

/// Who may PUT and DELETE assets. Secure by default: a server started with no write token
/// takes no writes at all (403), since one reachable by others would otherwise let anyone
/// replace or delete its assets; anonymous writes are for a demo or a private network, and
/// must be asked for by name.
#[derive(Clone, Debug, PartialEq)]
pub enum Writes {
    /// Requests with `Authorization: Bearer <token>`.
    Token(String),
    /// Anyone (`--allow-anonymous-writes`).
    Anyone,
    /// Nobody: no token is configured (the default).
    Refused,
}

impl Writes {
    /// The policy a server's options ask for: the token if one is set, else anyone if
    /// anonymous writes are allowed, else nobody.
    pub fn from_options(token: Option<String>, allow_anonymous: bool) -> Writes {
        match token {
            Some(t) => Writes::Token(t),
            None if allow_anonymous => Writes::Anyone,
            None => Writes::Refused,
        }
    }
}
