//! What every resource's handlers share between parsing a request and encoding its answer: the
//! asset and its backend, tile numbers and boxes, tolerance and iterations, and decoding in a
//! lane off the async executor.

use fractile_proto::ErrorCode;
use std::sync::Arc;

use axum::http::StatusCode;
use fractile_codec::geo;
use fractile_proto::AssetKind;

use crate::backend::{Backend, GpuBackend};
use crate::error::AppError;
use crate::store::StoredAsset;
use crate::work::{Bounds, Cancel};

use super::state::{AppState, CoarseCache};

/// The asset of a request that works on 2D planes (tiles, regions, lon/lat and batch points):
/// a volume is a 400 naming what it does answer instead.
pub(super) fn planar(a: Arc<StoredAsset>) -> Result<Arc<StoredAsset>, AppError> {
    if a.asset.meta.kind == AssetKind::Curve {
        return Err(AppError::bad_request(
            ErrorCode::CurveAsset,
            format!(
                "{} is a curve asset: ask /curve?level=N (GeoJSON) or POST /curve/deform",
                a.id
            ),
        ));
    }
    if a.asset.meta.kind == AssetKind::Volume {
        return Err(AppError::bad_request(
            ErrorCode::VolumeAsset,
            format!(
                "{} is a volume: ask /mesh?bbox=x0,y0,z0,x1,y1,z1 or /point?x=&y=&z=",
                a.id
            ),
        ));
    }
    Ok(a)
}

/// Runs `f` on the blocking pool in the lane of its estimated `bytes` (see [`crate::work`]).
pub(super) async fn decode<T: Send + 'static>(
    state: &AppState,
    bytes: u64,
    f: impl FnOnce(&Cancel) -> T + Send + 'static,
) -> Result<T, AppError> {
    state.lanes.run(bytes, f).await
}

/// Bytes a decode of `pixels` points of `channels` channels holds at its peak: the points
/// (8), a chain result per channel (12), the values in source units and their encoding (8).
pub(super) fn sampling_bytes(pixels: usize, channels: u8) -> u64 {
    pixels as u64 * (8 + 20 * u64::from(channels.max(1)))
}

/// A tile's zoom, column and row from their path segments, or a 400 `bad_path` (the code of
/// every path that does not parse) that says which numbers are tiles (zooms 0 to `max_zoom`, columns up to `columns x 2^z - 1`, rows up to
/// `2^z - 1`). Numbers that parse but name no tile are the caller's 404.
pub(super) fn tile_numbers(
    z: &str,
    x: &str,
    y: &str,
    max_zoom: u8,
    columns: u64,
) -> Result<(u8, u32, u32), AppError> {
    let z: u8 = z.parse().map_err(|_| {
        AppError::bad_request(
            ErrorCode::BadPath,
            format!("bad zoom {z:?}: zooms are whole numbers from 0 to {max_zoom}"),
        )
    })?;
    let span = |k: u64| (k << z.min(32)).saturating_sub(1);
    let number = |t: &str, what: &str, most: u64| {
        t.parse::<u32>().map_err(|_| {
            AppError::bad_request(
                ErrorCode::BadPath,
                format!("bad tile {what} {t:?}: at zoom {z} {what}s go from 0 to {most}"),
            )
        })
    };
    Ok((
        z,
        number(x, "column", span(columns))?,
        number(y, "row", span(1))?,
    ))
}

/// The backend of a request: its `backend` parameter, else the server's. Asking for the GPU
/// of a server without one is an error, not a silent fallback.
pub(super) fn backend_for(state: &AppState, asked: Option<&str>) -> Result<Backend, AppError> {
    let b = match asked {
        Some(s) => s
            .parse::<Backend>()
            .map_err(|e| AppError::bad_request(ErrorCode::BadBackend, e))?,
        None => state.backend,
    };
    if b == Backend::Gpu && state.gpu.is_none() {
        return Err(AppError::bad_request(
            ErrorCode::GpuUnavailable,
            "this server decodes on the CPU (it found no hardware GPU, or was started with \
             backend cpu; `fractile serve --backend gpu` opens any adapter, a software one too): \
             use backend=cpu or auto",
        ));
    }
    Ok(b)
}

/// `Asset::sample` of a raster's pixels on the chosen backend, with coarse decodes shared
/// through `coarse` (runs inside `decode`, on the blocking pool).
pub(super) fn sample_on(
    (gpu, coarse, cancel): (Option<&GpuBackend>, &CoarseCache, &Cancel),
    choice: Backend,
    a: &StoredAsset,
    pixels: &geo::Pixels,
    iterations: u32,
    tolerance: Tolerance,
) -> Result<(Vec<Vec<f32>>, Bounds), AppError> {
    let gpu = gpu.filter(|g| g.takes(choice, a, pixels.len()));
    // The GPU's round trip runs off the request's core slot (see `work`), the operator's
    // upload on it.
    let device =
        |k: fractile_codec::extract::PlaneRef<'_>, p: fractile_codec::extract::Sites<'_>, n, t| {
            let (g, op) = gpu.and_then(|g| Some((g, g.operator(a, k)?)))?;
            cancel.off_core(|| g.points(a, &op, p, n, t))
        };
    let resources = fractile_codec::extract::Resources {
        device: gpu
            .is_some()
            .then_some(&device as &fractile_codec::extract::ChainDevice<'_>),
        coarse: Some((coarse, a.coarse_key())),
        given_up: Some(cancel.flag()),
    };
    // One call: the source error over the pixels, the tolerance settled on it (where the
    // request named none), the values and their convergence bound.
    let request = fractile_codec::extract::Request {
        pixels,
        iterations,
        tolerance: tolerance.asked(),
    };
    let answer = a.asset.answer(&request, &resources).map_err(sample_error)?;
    Ok((
        answer.channels,
        Bounds {
            attractor: answer.convergence,
            source: answer.source,
        },
    ))
}

/// Why the codec gave no answer, as an HTTP answer: the request was given up (503
/// `cancelled`), or a chunk could not be read ([`chunk_unavailable`]).
pub(crate) fn sample_error(e: fractile_codec::extract::SampleError) -> AppError {
    match e {
        fractile_codec::extract::SampleError::Cancelled => AppError {
            status: StatusCode::SERVICE_UNAVAILABLE,
            code: ErrorCode::Cancelled,
            detail: "the request was given up before its decode finished".into(),
            retry_after: None,
        },
        fractile_codec::extract::SampleError::Chunk(e) => chunk_unavailable(e),
        // Handlers check an asset's kind before they ask: a refusal is this server's fault.
        fractile_codec::extract::SampleError::Refused(e) => AppError::internal(e.to_string()),
    }
}

/// A chunk of a chunked asset that could not be read or decoded. Read failures (a store that
/// is down, a file replaced under the reader) are 503 `chunk_unavailable` with `Retry-After`,
/// since a store that comes back answers again; a chunk whose bytes are not what its table
/// says is 500 `corrupt_chunk`: no retry mends it (the asset must be uploaded again), and the
/// chunk is not decoded again for the next request (`Chunked::chunk` remembers it). Where and
/// why go to the log, not to the client.
pub(crate) fn chunk_unavailable(e: fractile_codec::Error) -> AppError {
    tracing::error!("{e}");
    match e {
        fractile_codec::Error::Unavailable { .. } => AppError {
            status: StatusCode::SERVICE_UNAVAILABLE,
            code: ErrorCode::ChunkUnavailable,
            detail: "a chunk of the asset could not be read; try again".into(),
            retry_after: Some(1),
        },
        _ => AppError {
            status: StatusCode::INTERNAL_SERVER_ERROR,
            code: ErrorCode::CorruptChunk,
            detail:
                "a chunk of the asset is corrupt (not what its table says); upload the asset again"
                    .into(),
            retry_after: None,
        },
    }
}

/// A request's tolerance (value units): what it asked for (0 with fixed steps), or, where it
/// named neither steps nor a tolerance, settled by the codec for what is answered.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Tolerance {
    /// Asked for (0: none, `iterations` steps exactly).
    Asked(f32),
    /// Neither asked: see [`Tolerance::over`] and [`Tolerance::anywhere`].
    Settled,
}

impl Tolerance {
    /// The tolerance asked for, or `None`: settled by the codec over what is answered
    /// (`Asset::answer`: an eighth of the largest source error the answer's bound carries
    /// anyway, or the asset's default where that is larger).
    pub(super) fn asked(self) -> Option<f32> {
        match self {
            Tolerance::Asked(t) => Some(t),
            Tolerance::Settled => None,
        }
    }

    /// The tolerance of answers anywhere (points, each with its own bound): a settled one is
    /// the asset's default (see `Asset::default_tolerance`).
    pub(super) fn anywhere(self, a: &StoredAsset) -> f32 {
        match self {
            Tolerance::Asked(t) => t,
            Tolerance::Settled => a.asset.default_tolerance(),
        }
    }
}

/// Steps and per-point tolerance of a request. `iterations` alone: exactly that many steps.
/// `tolerance` (value units): each point stops once its own a-priori bound is under it, within
/// `iterations` or the limit. Neither: a tolerance settled by what is answered (see
/// [`Tolerance`]).
pub(super) fn iterations_for(
    state: &AppState,
    asked: Option<u32>,
    tolerance: Option<f32>,
) -> Result<(u32, Tolerance), AppError> {
    let max = state.limits.max_iterations;
    let n = match asked {
        Some(0) => {
            return Err(AppError::bad_request(
                ErrorCode::BadIterations,
                "iterations must be at least 1",
            ));
        }
        Some(n) if n > max => {
            return Err(AppError::bad_request(
                ErrorCode::BadIterations,
                format!("iterations {n} over the limit {max}"),
            ));
        }
        Some(n) => n,
        None => max,
    };
    match (asked, tolerance) {
        (_, Some(t)) if !(t.is_finite() && t > 0.0) => Err(AppError::bad_request(
            ErrorCode::BadTolerance,
            "tolerance must be a positive number (value units)",
        )),
        (_, Some(t)) => Ok((n, Tolerance::Asked(t))),
        (Some(n), None) => Ok((n, Tolerance::Asked(0.0))),
        (None, None) => Ok((max, Tolerance::Settled)),
    }
}

/// Unit coordinates of a request point: lon/lat for georeferenced assets, unit x/y otherwise.
pub(super) fn unit_of(a: &StoredAsset, c: [f64; 2]) -> Option<[f32; 2]> {
    match &a.placement {
        Some(p) => p.unit(c[0], c[1]),
        None => c
            .iter()
            .all(|t| (0.0..=1.0).contains(t))
            .then_some([c[0] as f32, c[1] as f32]),
    }
}

/// The pixels of a box's samples: column i at request x `x(i)`, row j at request y `y(j)`
/// (lon/lat for georeferenced assets, a north-up box; unit coordinates otherwise), each
/// `[dx, dy]` request units wide.
pub(super) fn box_pixels(
    a: &StoredAsset,
    (w, x): (usize, impl Fn(usize) -> f64),
    (h, y): (usize, impl Fn(usize) -> f64),
    [dx, dy]: [f64; 2],
) -> geo::Pixels {
    let xs: Vec<f64> = (0..w).map(x).collect();
    let ys: Vec<f64> = (0..h).map(y).collect();
    match &a.placement {
        Some(p) => {
            let centre = |v: &[f64]| 0.5 * (v[0] + v[v.len() - 1]);
            let footprint = p.footprint(centre(&xs), centre(&ys), dx, dy);
            p.pixels(&xs, &ys, footprint)
        }
        None => {
            let unit = |t: f64| (0.0..=1.0).contains(&t).then_some(t as f32);
            geo::Pixels::grid(
                xs.into_iter().map(unit).collect(),
                ys.into_iter().map(unit).collect(),
                [dx as f32, dy as f32],
            )
        }
    }
}

/// `minx,miny,maxx,maxy` with max > min.
pub(super) fn parse_bbox(b: &str) -> Result<[f64; 4], AppError> {
    let v: Vec<f64> = b.split(',').filter_map(|s| s.trim().parse().ok()).collect();
    match v[..] {
        [x0, y0, x1, y1] if x1 > x0 && y1 > y0 => Ok([x0, y0, x1, y1]),
        _ => Err(AppError::bad_request(
            ErrorCode::BadBbox,
            "bbox must be minx,miny,maxx,maxy with max > min",
        )),
    }
}

/// Size in request units of one of `w x h` cells over a box.
pub(super) fn cell_size([x0, y0, x1, y1]: [f64; 4], w: usize, h: usize) -> [f64; 2] {
    [(x1 - x0) / w.max(1) as f64, (y1 - y0) / h.max(1) as f64]
}
