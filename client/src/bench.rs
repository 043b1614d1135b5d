//! A bounded, self-stopping load generator: each request kind runs for a fixed duration at a
//! fixed concurrency, and the report gives throughput, p50/p95/p99 latency and error counts per
//! kind. Kinds run one after another rather than interleaved so that each figure is that kind's
//! own (a mix would charge cold tiles' decoding to the points' latency).
//!
//! - tiles, cold: a pyramid walk, zoom 0 down to the TileJSON's `maxzoom`, row by row over the
//!   asset's bounds, every tile asked once, so each is a cache miss on a freshly started server;
//! - tiles, warm: the tiles the cold walk fetched, again (cache hits);
//! - terrain, cold: the same walk over Cesium terrain (quantized-mesh) tiles, level by level
//!   through `layer.json`'s available tiles, to the level as wide as the raster walk's deepest
//!   zoom, asked for as CesiumJS asks (normals, gzip);
//! - points: batches of random points in the asset's bounds, binary encoding, default steps;
//! - regions: random boxes of an eighth of the asset a side, sampled on a float32 grid.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};

use crate::tile::{TileAddress, TileEncoding, TileRequest};
use crate::{
    AssetKind, Client, ClientError, PointsEncoding, PointsRequest, RegionFormat, RegionRequest,
    TileRange,
};

/// A request kind of the load test.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    /// Tiles never asked before.
    TilesCold,
    /// Tiles asked before.
    TilesWarm,
    /// Cesium terrain tiles never asked before (height fields).
    TerrainCold,
    /// Point batches.
    Points,
    /// Float32 regions.
    Regions,
}

impl Kind {
    /// Every kind, in the order they run (terrain only for georeferenced height fields).
    pub const ALL: [Kind; 5] = [
        Kind::TilesCold,
        Kind::TilesWarm,
        Kind::TerrainCold,
        Kind::Points,
        Kind::Regions,
    ];

    /// Parses `tiles-cold`, `tiles-warm`, `terrain-cold`, `points`, `regions`.
    pub fn parse(s: &str) -> Option<Kind> {
        Some(match s {
            "tiles-cold" => Kind::TilesCold,
            "tiles-warm" => Kind::TilesWarm,
            "terrain-cold" => Kind::TerrainCold,
            "points" => Kind::Points,
            "regions" => Kind::Regions,
            _ => return None,
        })
    }

    fn label(self) -> &'static str {
        match self {
            Kind::TilesCold => "tiles, cold",
            Kind::TilesWarm => "tiles, warm",
            Kind::TerrainCold => "terrain, cold",
            Kind::Points => "point batches",
            Kind::Regions => "regions",
        }
    }

    fn unit(self) -> &'static str {
        match self {
            Kind::TilesCold | Kind::TilesWarm | Kind::TerrainCold => "tiles",
            Kind::Points => "points",
            Kind::Regions => "pixels",
        }
    }
}

/// What to run.
#[derive(Clone, Debug)]
pub struct BenchOptions {
    /// The asset to load.
    pub asset: String,
    /// Requests in flight.
    pub concurrency: usize,
    /// How long each kind runs.
    pub duration: Duration,
    /// Kinds to run, in order (tiles-warm replays what tiles-cold fetched).
    pub kinds: Vec<Kind>,
    /// Points per batch.
    pub batch: usize,
    /// How the tile kinds ask for a height field's tiles (pictures are always PNGs):
    /// Terrarium by default, what MapLibre's `raster-dem` sources most often read; issue 32's
    /// GPU bar is stated for terrain-RGB.
    pub heights: TileEncoding,
    /// Region side in pixels.
    pub region_side: u32,
    /// Seed of the random points and boxes.
    pub seed: u64,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            asset: "jacksboro".into(),
            concurrency: 16,
            duration: Duration::from_secs(10),
            kinds: Kind::ALL.to_vec(),
            batch: 1000,
            heights: TileEncoding::Terrarium,
            region_side: 256,
            seed: 1,
        }
    }
}

/// Figures of one kind.
#[derive(Clone, Debug, serde::Serialize)]
pub struct KindReport {
    /// The kind.
    pub kind: Kind,
    /// Requests answered (successes and errors).
    pub requests: usize,
    /// Requests that failed.
    pub errors: usize,
    /// The first failure, for the report.
    pub first_error: Option<String>,
    /// Items (tiles, points, pixels) per second of successful requests.
    pub items_per_second: f64,
    /// What an item is.
    pub unit: &'static str,
    /// Latency percentiles of successful requests, milliseconds.
    pub p50_ms: f64,
    /// 95th percentile.
    pub p95_ms: f64,
    /// 99th percentile.
    pub p99_ms: f64,
}

/// One request's outcome: items it carried and its latency, or its error.
type Outcome = Result<(usize, Duration), String>;

/// The pyramid walk over `bounds`, zoom by zoom, at most `cap` tiles.
pub fn pyramid(bounds: [f64; 4], max_zoom: u8, cap: usize) -> Vec<TileAddress> {
    let [w, s, e, n] = bounds;
    let mut out = Vec::new();
    for z in 0..=max_zoom {
        let a = TileAddress::containing(z, w, n);
        let b = TileAddress::containing(z, e - 1e-9, s + 1e-9);
        for y in a.y..=b.y {
            for x in a.x..=b.x {
                if out.len() == cap {
                    return out;
                }
                out.push(TileAddress { z, x, y });
            }
        }
    }
    out
}

/// Every tile of a terrain layer's `available` ranges, level by level, rows then columns.
pub fn terrain_walk(available: &[Vec<TileRange>]) -> Vec<(u8, u32, u32)> {
    let mut out = Vec::new();
    for (z, ranges) in available.iter().enumerate() {
        for r in ranges {
            for y in r.start_y..=r.end_y {
                for x in r.start_x..=r.end_x {
                    out.push((z as u8, x, y));
                }
            }
        }
    }
    out
}

fn percentile(sorted: &[Duration], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let k = ((p * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
    sorted[k].as_secs_f64() * 1e3
}

/// Runs `concurrency` workers until `duration` is over; `job(worker, i)` makes request `i`.
async fn drive<F, Fut>(concurrency: usize, duration: Duration, job: F) -> (Vec<Outcome>, f64)
where
    F: Fn(usize) -> Fut + Send + Sync + 'static,
    Fut: std::future::Future<Output = Option<Outcome>> + Send,
{
    let job = Arc::new(job);
    let counter = Arc::new(AtomicUsize::new(0));
    let start = Instant::now();
    let deadline = start + duration;
    let mut set = tokio::task::JoinSet::new();
    for _ in 0..concurrency.max(1) {
        let (job, counter) = (job.clone(), counter.clone());
        set.spawn(async move {
            let mut out = Vec::new();
            while Instant::now() < deadline {
                let i = counter.fetch_add(1, Ordering::Relaxed);
                match job(i).await {
                    Some(o) => out.push(o),
                    None => break,
                }
            }
            out
        });
    }
    let mut all = Vec::new();
    while let Some(r) = set.join_next().await {
        all.extend(r.unwrap_or_else(|e| std::panic::resume_unwind(e.into_panic())));
    }
    (all, start.elapsed().as_secs_f64())
}

fn report(kind: Kind, outcomes: Vec<Outcome>, seconds: f64) -> KindReport {
    let mut lat: Vec<Duration> = outcomes
        .iter()
        .filter_map(|o| o.as_ref().ok())
        .map(|o| o.1)
        .collect();
    lat.sort();
    let items: usize = outcomes
        .iter()
        .filter_map(|o| o.as_ref().ok())
        .map(|o| o.0)
        .sum();
    let errors: Vec<&String> = outcomes.iter().filter_map(|o| o.as_ref().err()).collect();
    KindReport {
        kind,
        requests: outcomes.len(),
        errors: errors.len(),
        first_error: errors.first().map(|e| e.to_string()),
        items_per_second: items as f64 / seconds,
        unit: kind.unit(),
        p50_ms: percentile(&lat, 0.50),
        p95_ms: percentile(&lat, 0.95),
        p99_ms: percentile(&lat, 0.99),
    }
}

/// Runs the load test against `client`'s server.
pub async fn run(client: &Client, options: &BenchOptions) -> Result<Vec<KindReport>, ClientError> {
    let asset = client.asset(&options.asset).await?;
    let tj = client.tilejson(&options.asset).await?;
    let bounds = asset.bounds.unwrap_or([0.0, 0.0, 1.0, 1.0]);
    let heights = asset.kind == AssetKind::HeightField;
    let encoding = tile_encoding(asset.kind, options.heights);
    let walk: Arc<Vec<TileAddress>> = Arc::new(pyramid(tj.bounds, tj.maxzoom, 1_000_000));
    let mut cold_done = 0usize;
    let mut reports = Vec::new();
    for &kind in &options.kinds {
        let (client, id) = (client.clone(), options.asset.clone());
        let (outcomes, seconds) = match kind {
            Kind::TilesCold | Kind::TilesWarm => {
                let walk = walk.clone();
                let replay = cold_done;
                if kind == Kind::TilesWarm && replay == 0 {
                    return Err(ClientError::malformed(
                        "bench",
                        "tiles-warm replays tiles-cold: run that first",
                    ));
                }
                drive(options.concurrency, options.duration, move |i| {
                    let (client, id, walk) = (client.clone(), id.clone(), walk.clone());
                    async move {
                        let t = match kind {
                            Kind::TilesCold => *walk.get(i)?,
                            _ => walk[i % replay],
                        };
                        let start = Instant::now();
                        let r = client.tile_body(&id, &TileRequest::new(t, encoding)).await;
                        Some(match r {
                            Ok(_) => Ok((1, start.elapsed())),
                            // Tiles of the walk's edge rows may miss the asset: the server says
                            // 404 `outside`, which maps ask for and over-zoom. Not an error.
                            Err(e) if e.code() == Some("outside") => Ok((0, start.elapsed())),
                            Err(e) => Err(e.to_string()),
                        })
                    }
                })
                .await
            }
            Kind::TerrainCold => {
                // Cesium terrain exists for georeferenced height fields only.
                if !(heights && asset.bounds.is_some()) {
                    continue;
                }
                // Down to the level whose tiles are as wide as the raster walk's deepest
                // (geographic level z spans what Web Mercator zoom z + 1 does), so that the
                // two walks compare the same zooms.
                let layer = client.layer_json(&options.asset).await?;
                let levels = usize::from(tj.maxzoom).min(layer.available.len());
                let walk = Arc::new(terrain_walk(&layer.available[..levels]));
                drive(options.concurrency, options.duration, move |i| {
                    let (client, id, walk) = (client.clone(), id.clone(), walk.clone());
                    async move {
                        let t = *walk.get(i)?;
                        let start = Instant::now();
                        Some(match client.terrain_tile_body(&id, t).await {
                            Ok(_) => Ok((1, start.elapsed())),
                            Err(e) => Err(e.to_string()),
                        })
                    }
                })
                .await
            }
            Kind::Points => points(client, id, options, bounds).await,
            Kind::Regions => regions(client, id, options, bounds).await,
        };
        if kind == Kind::TilesCold {
            cold_done = outcomes
                .iter()
                .filter(|o| o.is_ok())
                .count()
                .min(walk.len());
        }
        reports.push(report(kind, outcomes, seconds));
    }
    Ok(reports)
}

/// Random point batches for `options.duration`.
async fn points(
    client: Client,
    id: String,
    options: &BenchOptions,
    bounds: [f64; 4],
) -> (Vec<Outcome>, f64) {
    let (batch, seed) = (options.batch, options.seed);
    drive(options.concurrency, options.duration, move |i| {
        let (client, id) = (client.clone(), id.clone());
        let mut rng =
            rand::rngs::SmallRng::seed_from_u64(seed ^ (i as u64).wrapping_mul(0x9E37_79B9));
        let points: Vec<[f64; 2]> = (0..batch)
            .map(|_| {
                [
                    rng.random_range(bounds[0]..bounds[2]),
                    rng.random_range(bounds[1]..bounds[3]),
                ]
            })
            .collect();
        async move {
            let req = PointsRequest {
                points,
                iterations: None,
                tolerance: None,
            };
            let start = Instant::now();
            Some(
                match client.points(&id, &req, PointsEncoding::Binary).await {
                    Ok(r) => Ok((r.results.len(), start.elapsed())),
                    Err(e) => Err(e.to_string()),
                },
            )
        }
    })
    .await
}

/// Random float32 regions for `options.duration`.
async fn regions(
    client: Client,
    id: String,
    options: &BenchOptions,
    bounds: [f64; 4],
) -> (Vec<Outcome>, f64) {
    let (side, seed) = (options.region_side, options.seed);
    drive(options.concurrency, options.duration, move |i| {
        let (client, id) = (client.clone(), id.clone());
        let mut rng =
            rand::rngs::SmallRng::seed_from_u64(seed ^ (i as u64).wrapping_mul(0x85EB_CA6B));
        let (dw, dh) = ((bounds[2] - bounds[0]) / 8.0, (bounds[3] - bounds[1]) / 8.0);
        let (x0, y0) = (
            rng.random_range(bounds[0]..bounds[2] - dw),
            rng.random_range(bounds[1]..bounds[3] - dh),
        );
        async move {
            let req = RegionRequest {
                bbox: [x0, y0, x0 + dw, y0 + dh],
                width: side,
                height: side,
                iterations: None,
                tolerance: None,
                format: RegionFormat::F32,
            };
            let start = Instant::now();
            Some(match client.region(&id, &req).await {
                Ok(_) => Ok(((side * side) as usize, start.elapsed())),
                Err(e) => Err(e.to_string()),
            })
        }
    })
    .await
}

/// The reports as a Markdown table.
pub fn table(reports: &[KindReport], concurrency: usize) -> String {
    let mut s = String::from(
        "| kind | concurrency | requests | throughput | p50 ms | p95 ms | p99 ms | errors |\n|---|---|---|---|---|---|---|---|\n",
    );
    for r in reports {
        s += &format!(
            "| {} | {concurrency} | {} | {:.0} {}/s | {:.1} | {:.1} | {:.1} | {} |\n",
            r.kind.label(),
            r.requests,
            r.items_per_second,
            r.unit,
            r.p50_ms,
            r.p95_ms,
            r.p99_ms,
            r.errors
        );
    }
    s
}

/// How the tile kinds ask for an asset's tiles: a height field's as `heights` says (PNG when
/// `heights` is not a height encoding), anything else's as a picture.
fn tile_encoding(kind: AssetKind, heights: TileEncoding) -> TileEncoding {
    if kind == AssetKind::HeightField && heights.is_heights() {
        heights
    } else {
        TileEncoding::Visual
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn terrain_walks_every_available_tile_once_level_by_level() {
        // The ranges of a small DEM's layer.json (both root tiles, then one area).
        let b = [-84.41, 36.45, -84.08, 36.73];
        let available = fractile_proto::tiles::geographic_available(b, 11);
        let w = terrain_walk(&available);
        assert_eq!(&w[..2], &[(0, 0, 0), (0, 1, 0)]);
        let mut seen = std::collections::HashSet::new();
        for (pair, t) in w.windows(2).zip(&w) {
            assert!(pair[0].0 <= pair[1].0);
            assert!(seen.insert(*t), "{t:?} twice");
        }
        for &(z, x, y) in &w[2..] {
            let [tw, ts, te, tn] = fractile_proto::tiles::geographic_bounds(z, x, y);
            assert!(
                tw < b[2] && te > b[0] && ts < b[3] && tn > b[1],
                "{z}/{x}/{y}"
            );
        }
        assert_eq!(w.last().unwrap().0, 11);
    }

    #[test]
    fn pyramid_walks_zoom_by_zoom_over_the_bounds() {
        let b = [-98.5, 33.0, -97.5, 34.0];
        let w = pyramid(b, 10, 10_000);
        assert_eq!(w[0], TileAddress { z: 0, x: 0, y: 0 });
        for pair in w.windows(2) {
            assert!(pair[0].z <= pair[1].z);
        }
        // Every tile meets the bounds.
        for t in &w {
            let [tw, ts, te, tn] = t.bounds();
            assert!(tw < b[2] && te > b[0] && ts < b[3] && tn > b[1], "{t}");
        }
        assert_eq!(pyramid(b, 10, 5).len(), 5);
    }

    #[test]
    fn tiles_of_height_fields_take_the_chosen_encoding_pictures_png() {
        for e in [
            TileEncoding::Terrarium,
            TileEncoding::TerrainRgb,
            TileEncoding::F32,
        ] {
            assert_eq!(tile_encoding(AssetKind::HeightField, e), e);
            assert_eq!(tile_encoding(AssetKind::Image, e), TileEncoding::Visual);
        }
        assert_eq!(
            tile_encoding(AssetKind::HeightField, TileEncoding::Visual),
            TileEncoding::Visual
        );
    }

    #[test]
    fn percentiles_take_the_upper_rank() {
        let v: Vec<Duration> = (1..=100).map(Duration::from_millis).collect();
        assert_eq!(percentile(&v, 0.5), 50.0);
        assert_eq!(percentile(&v, 0.99), 99.0);
        assert!(percentile(&[], 0.5).is_nan());
    }
}
