//! Prometheus metrics: requests and latency by route and status, decode time, tile cache hits,
//! bytes out, the GPU's shared rounds. The `metrics` facade with its Prometheus exporter (no listener of its own: axum
//! serves `/metrics`).

use std::sync::OnceLock;
use std::time::Instant;

use axum::body::HttpBody;
use axum::extract::{MatchedPath, Request};
use axum::middleware::Next;
use axum::response::Response;
use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};

/// The process-wide recorder (installed once, on first use).
#[expect(
    clippy::expect_used,
    reason = "fixed non-empty buckets, and the recorder installed once (the OnceLock) at the first use"
)]
pub(crate) fn handle() -> &'static PrometheusHandle {
    static HANDLE: OnceLock<PrometheusHandle> = OnceLock::new();
    HANDLE.get_or_init(|| {
        let buckets = [
            0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
        ];
        PrometheusBuilder::new()
            .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), &buckets)
            .expect("non-empty buckets")
            .install_recorder()
            .expect("the only metrics recorder of the process")
    })
}

/// Middleware recording every request.
pub(crate) async fn track(req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_string())
        .unwrap_or_else(|| "unmatched".into());
    let start = Instant::now();
    let resp = next.run(req).await;
    let status = resp.status().as_u16().to_string();
    metrics::counter!("fractile_requests_total", "route" => route.clone(), "status" => status)
        .increment(1);
    metrics::histogram!("fractile_request_seconds", "route" => route)
        .record(start.elapsed().as_secs_f64());
    if let Some(n) = resp.body().size_hint().exact() {
        metrics::counter!("fractile_bytes_out_total").increment(n);
    }
    resp
}

/// The GPU's rounds of small grids (tiles) decoded together and the grids they held, as counted
/// by the device (`fractile_gpu_rounds_total`, `fractile_gpu_round_grids_total`; their ratio is
/// the mean round): set when `/metrics` is read.
pub(crate) fn gpu_rounds((rounds, grids): (u64, u64)) {
    metrics::counter!("fractile_gpu_rounds_total").absolute(rounds);
    metrics::counter!("fractile_gpu_round_grids_total").absolute(grids);
}

/// The coarse grids' answers (`fractile_codec::extract::CoarseGrids`): kept, derived from a
/// finer kept grid by block means, or decoded, as `fractile_coarse_cache_total{result}`: set
/// when `/metrics` is read.
pub(crate) fn coarse_grids(c: fractile_codec::extract::CoarseCounts) {
    for (result, n) in [("hit", c.hits), ("derived", c.derived), ("miss", c.misses)] {
        metrics::counter!("fractile_coarse_cache_total", "result" => result).absolute(n);
    }
}

/// Operators uploaded to the GPU and operators it refused (their requests decoded on the CPU
/// for a while: `backend::REFUSAL_TTL`), as `fractile_gpu_uploads_total{result}`: set when
/// `/metrics` is read.
pub(crate) fn gpu_uploads((resident, refused): (u64, u64)) {
    metrics::counter!("fractile_gpu_uploads_total", "result" => "resident").absolute(resident);
    metrics::counter!("fractile_gpu_uploads_total", "result" => "refused").absolute(refused);
}
