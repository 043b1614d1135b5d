//! Uncached tiles of a 9.3 Mpx DEM over zooms 0-7: per zoom, the first tile (which waits for
//! the zoom's coarse decode), then the rest with `CONCURRENCY` requests in flight: p50, p99,
//! and how many coarse grids were decoded (`CoarseGrids::counts`, as `fractile_coarse_cache_total{result="miss"}` counts them).
//! Prints a table.
//!
//! The DEM is 16 copies of etopo20 (1080 x 540), mirrored so that they join, as one global
//! 4320 x 2160 grid (issue 34 asks for a 9.3 Mpx DEM made from the real data). Its default
//! encode ([`fractile_codec::encode_default`], 0.8 bits a cell) takes about a minute on two
//! cores, so it is kept in `target/bench-data/` (named by codec) and reused; delete it after
//! changing the encoder.
//!
//! `cargo bench -p fractile --bench coarse_zooms [-- TILES_PER_ZOOM IN_FLIGHT COARSE_MIB]`
//! (defaults 256, 8 and the server's `coarse_cache_mib`). `FRACTILE_BENCH_ASSET=FILE` serves
//! that asset instead (any encode of the same mosaic: `fractile encode` of the GeoTIFFs that
//! `cargo bench -p fractile-codec --bench chunked -- tiffs DIR 4` writes, by this build or an
//! older one, to compare formats).

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::Request;
use fractile_codec::{Raster, encode_default};
use fractile_proto::Georef;
use fractile_server::AppState;
use fractile_server::Store;
use http_body_util::BodyExt;
use tower::ServiceExt;

/// etopo20 mirrored 4 x 4 (odd columns of copies flipped left-right, odd rows upside down).
fn mosaic() -> Raster {
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata");
    let src = Raster::open(&root.join("etopo20.tif")).expect("etopo20");
    let mut r = fractile_codec::mosaic::mirrored(&src, 4, 4).unwrap();
    let (mw, mh) = (r.width, r.height);
    r.georef = Some(Georef {
        epsg: Some(4326),
        origin: [-180.0, 90.0],
        pixel_size: [360.0 / mw as f64, -180.0 / mh as f64],
    });
    r
}

/// The encoded mosaic, from `target/bench-data/` when it is there.
fn asset() -> Vec<u8> {
    if let Some(path) = std::env::var_os("FRACTILE_BENCH_ASSET") {
        return std::fs::read(&path).expect("FRACTILE_BENCH_ASSET");
    }
    let dir = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/bench-data");
    let path = dir.join("etopo20-mosaic-9mpx-default.fra");
    if let Ok(bytes) = std::fs::read(&path) {
        return bytes;
    }
    let r = mosaic();
    println!(
        "encoding the {} x {} mosaic (default DEM encode, minutes)...",
        r.width, r.height
    );
    let t = Instant::now();
    let enc = encode_default(
        &r,
        fractile_codec::encode::DEFAULT_HEIGHT_FIELD_BPP,
        &|_, _| {},
    )
    .expect("an encode");
    println!(
        "encoded in {:.0} s, {} bytes",
        t.elapsed().as_secs_f64(),
        enc.bytes.len()
    );
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(&path, &enc.bytes).unwrap();
    enc.bytes
}

async fn get(state: &Arc<AppState>, uri: String) -> Duration {
    let t = Instant::now();
    let req = Request::get(&uri).body(Body::empty()).unwrap();
    let resp = fractile_server::app(state.clone())
        .oneshot(req)
        .await
        .unwrap();
    let ok = resp.status().is_success();
    resp.into_body().collect().await.unwrap();
    assert!(ok, "{uri}");
    t.elapsed()
}

/// Coarse-cache lookups so far that decoded a grid and that derived one from a finer grid.
fn coarse_counts(coarse: &fractile_codec::extract::CoarseGrids) -> [u64; 2] {
    let c = coarse.counts();
    [c.misses, c.derived]
}

fn percentile(sorted: &[Duration], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let k = ((sorted.len() as f64 * p).ceil() as usize).clamp(1, sorted.len()) - 1;
    sorted[k].as_secs_f64() * 1e3
}

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .map(|a| a.parse().expect("a count"))
        .collect();
    let per_zoom = args.first().copied().unwrap_or(256);
    // Requests in flight after a zoom's first tile: a map view asks for its tiles at once.
    let in_flight = args.get(1).copied().unwrap_or(8);
    let coarse_mib = args
        .get(2)
        .map(|&m| m as u64)
        .unwrap_or(fractile_server::DEFAULT_COARSE_CACHE_MIB);
    let dir = std::env::temp_dir().join(format!("fractile-coarse-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("mosaic.fra"), asset()).unwrap();
    let (store, _) = Store::open(&dir).unwrap();
    let mut state = AppState::new(store, "http://bench".into());
    state.coarse = fractile_server::coarse_cache(coarse_mib);
    let state = Arc::new(state);
    let rt = tokio::runtime::Runtime::new().unwrap();
    println!(
        "\n9.3 Mpx mosaic, terrain-RGB tiles, uncached, {in_flight} in flight after each zoom's \
         first tile, coarse cache {coarse_mib} MiB"
    );
    println!("| zoom | tiles | first tile ms | p50 ms | p99 ms | coarse grids decoded | derived |");
    println!("|---|---|---|---|---|---|---|");
    // SplitMix64 for the sample of tiles at deep zooms.
    let mut seed = 7u64;
    let mut next = move |n: u32| {
        seed = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = seed;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) % n as u64) as u32
    };
    let (mut all_after_first, mut coarse_after_first) = (Vec::new(), Vec::new());
    for z in 0u8..=7 {
        let side = 1u32 << z;
        let mut tiles: Vec<(u32, u32)> = if (side * side) as usize <= per_zoom {
            (0..side * side).map(|k| (k % side, k / side)).collect()
        } else {
            let mut seen = std::collections::HashSet::new();
            while seen.len() < per_zoom {
                seen.insert((next(side), next(side)));
            }
            seen.into_iter().collect()
        };
        tiles.sort();
        let uri = |(x, y): (u32, u32)| {
            format!("/v1/assets/mosaic/tiles/{z}/{x}/{y}.png?encoding=terrainrgb")
        };
        let before = coarse_counts(&state.coarse);
        let first = rt.block_on(get(&state, uri(tiles[0])));
        let rest: Vec<Duration> = rt.block_on(async {
            let mut out = Vec::new();
            let mut set = tokio::task::JoinSet::new();
            let mut queue = tiles[1..].iter().copied();
            loop {
                while set.len() < in_flight {
                    let Some(t) = queue.next() else { break };
                    let (state, u) = (state.clone(), uri(t));
                    set.spawn(async move { get(&state, u).await });
                }
                match set.join_next().await {
                    Some(d) => out.push(d.unwrap()),
                    None => break,
                }
            }
            out
        });
        let mut sorted = rest.clone();
        sorted.sort();
        println!(
            "| {z} | {} | {:.0} | {:.1} | {:.1} | {} | {} |",
            tiles.len(),
            first.as_secs_f64() * 1e3,
            percentile(&sorted, 0.5),
            percentile(&sorted, 0.99),
            coarse_counts(&state.coarse)[0] - before[0],
            coarse_counts(&state.coarse)[1] - before[1],
        );
        if z <= 4 {
            coarse_after_first.extend(rest.iter().copied());
        }
        all_after_first.extend(rest);
    }
    coarse_after_first.sort();
    println!(
        "zooms 0-4 after each first tile: {} tiles, p50 {:.1} ms, p99 {:.1} ms",
        coarse_after_first.len(),
        percentile(&coarse_after_first, 0.5),
        percentile(&coarse_after_first, 0.99)
    );
    all_after_first.sort();
    println!(
        "all zooms after each first tile: {} tiles, p50 {:.1} ms, p99 {:.1} ms",
        all_after_first.len(),
        percentile(&all_after_first, 0.5),
        percentile(&all_after_first, 0.99)
    );
    std::fs::remove_dir_all(&dir).ok();
}
