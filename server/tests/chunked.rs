//! A chunked asset served from the folder (read by range, chunks decoded on demand): its tiles
//! across chunk edges agree with the single-operator asset of the same DEM within the two
//! bounds they answer, its ETag names its version, and a corrupt chunk costs only the tiles
//! that need it (503 by name), never the others; an upload with a corrupt chunk is refused.

use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use fractile_codec::encode::chunked::encode_chunked;
use fractile_codec::{Raster, encode_default};
use fractile_server::AppState;
use fractile_server::Store;
use http_body_util::BodyExt;
use tower::ServiceExt;

fn data(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// etopo20 whole and in chunks of 256 cells (4 x 2 chunks, a chunk edge at 256 cells, -94.67
/// degrees), and the chunked file with its last source chunk corrupt.
fn state() -> Arc<AppState> {
    let (store, skipped) = Store::open(dir()).unwrap();
    assert!(skipped.is_empty(), "{skipped:?}");
    Arc::new(AppState::new(store, "http://test".into()))
}

/// The folder of the assets, written once a test binary.
fn dir() -> &'static std::path::PathBuf {
    static DIR: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
    DIR.get_or_init(write_assets)
}

fn write_assets() -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("fractile-chunked-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let r = Raster::open(&data("etopo20.tif")).unwrap();
    let one = |part: &Raster| encode_default(part, 0.8, &|_, _| {});
    std::fs::write(dir.join("single.fra"), one(&r).unwrap().bytes).unwrap();
    let chunked = encode_chunked(&r, 256, &one, &|_, _| {}).unwrap();
    std::fs::write(dir.join("chunked.fra"), &chunked.bytes).unwrap();
    let last = chunked.asset.chunked().unwrap().table.levels[0]
        .chunks
        .last()
        .unwrap()
        .clone();
    let mut bytes = chunked.bytes.clone();
    bytes[(last.offset + last.length / 2) as usize] ^= 0x10;
    std::fs::write(dir.join("corrupt.fra"), bytes).unwrap();
    dir
}

async fn get(st: &Arc<AppState>, uri: &str) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    let req = Request::get(uri).body(Body::empty()).unwrap();
    let r = fractile_server::app(st.clone()).oneshot(req).await.unwrap();
    let (parts, body) = r.into_parts();
    let bytes = body.collect().await.unwrap().to_bytes().to_vec();
    (parts.status, parts.headers, bytes)
}

fn floats(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

#[tokio::test]
async fn tiles_across_chunk_edges_agree_with_the_whole_asset_within_their_bounds() {
    let st = state();
    let a = st.store.get("chunked").unwrap();
    assert!(a.asset.chunked().is_some(), "served chunked");
    // Zoom 3, tile (1, 3) spans -135 to -90 degrees: the chunk edge at -94.67 crosses it
    // (and the equator's chunk edge at 256 rows is near its north). Zoom 2 is coarser than
    // the source (its pixels from level 0 still); zoom 5 deeper.
    for (z, x, y) in [(3, 1, 3), (3, 1, 4), (2, 0, 1), (5, 6, 14)] {
        let uri = |id: &str| format!("/v1/assets/{id}/tiles/{z}/{x}/{y}.f32");
        let (s1, h1, b1) = get(&st, &uri("single")).await;
        let (s2, h2, b2) = get(&st, &uri("chunked")).await;
        assert_eq!((s1, s2), (StatusCode::OK, StatusCode::OK));
        let bound = |h: &axum::http::HeaderMap| -> f32 {
            h["x-error-bound"].to_str().unwrap().parse().unwrap()
        };
        let (e1, e2) = (bound(&h1), bound(&h2));
        assert!(e2.is_finite() && e2 > 0.0);
        let (v1, v2) = (floats(&b1), floats(&b2));
        assert_eq!(v1.len(), v2.len());
        let mut worst = 0.0f32;
        for (p, q) in v1.iter().zip(&v2) {
            assert!(q.is_finite());
            worst = worst.max((p - q).abs());
        }
        assert!(worst <= e1 + e2, "zoom {z}: {worst} over {e1} + {e2}");
        // The same version answers the same ETag, and it is not the whole asset's.
        let (_, again, _) = get(&st, &uri("chunked")).await;
        assert_eq!(h2["etag"], again["etag"]);
        assert_ne!(h1["etag"], h2["etag"]);
    }
}

/// A corrupt chunk is a permanent fault, not "try later": 500 `corrupt_chunk` without
/// `Retry-After`, for the tiles and points that need it alone, and answered again without
/// decoding the chunk again.
#[tokio::test]
async fn a_corrupt_chunk_costs_only_the_tiles_that_need_it() {
    let st = state();
    // The last source chunk is the south-east one: zoom 3's tile (7, 7) lies in it.
    let (s, h, body) = get(&st, "/v1/assets/corrupt/tiles/3/7/7.png").await;
    assert_eq!(s, StatusCode::INTERNAL_SERVER_ERROR);
    assert!(h.get("retry-after").is_none(), "no retry mends it");
    let body = String::from_utf8_lossy(&body);
    assert!(body.contains("corrupt_chunk"), "{body}");
    assert!(!body.contains("/tmp"), "no path to the client: {body}");
    let (s, _, _) = get(&st, "/v1/assets/corrupt/tiles/3/0/1.png").await;
    assert_eq!(s, StatusCode::OK);
    // Points: the same.
    let (s, _, _) = get(&st, "/v1/assets/corrupt/point/170,-80").await;
    assert_eq!(s, StatusCode::INTERNAL_SERVER_ERROR);
    let (s, _, _) = get(&st, "/v1/assets/corrupt/point/-170,80").await;
    assert_eq!(s, StatusCode::OK);
}

/// An upload is checked chunk by chunk before it is stored: the file with one corrupt chunk
/// is refused (422, naming the chunk) and leaves nothing behind; the sound one is stored, and
/// served from its file.
#[test]
fn an_upload_with_a_corrupt_chunk_is_refused_whole() {
    let uploads = dir().join("uploads");
    std::fs::create_dir_all(&uploads).unwrap();
    let (store, _) = Store::open(&uploads).unwrap();
    let corrupt = std::fs::read(dir().join("corrupt.fra")).unwrap();
    let Err(e) = store.put("etopo", &corrupt) else {
        panic!("a file with a corrupt chunk was stored")
    };
    assert_eq!(e.status, StatusCode::UNPROCESSABLE_ENTITY);
    assert!(e.detail.contains("chunk"), "{}", e.detail);
    assert!(store.get("etopo").is_err());
    assert!(!uploads.join("etopo.fra").exists());
    let sound = std::fs::read(dir().join("chunked.fra")).unwrap();
    let Ok(served) = store.put("etopo", &sound) else {
        panic!("the sound file was refused")
    };
    assert_eq!(std::fs::read(uploads.join("etopo.fra")).unwrap(), sound);
    // Served from the stored file by range, not from the upload's bytes held in memory.
    let source = format!("{:?}", served.asset.chunked().unwrap());
    assert!(source.contains("etopo.fra"), "{source}");
}

/// A chunked asset decodes on the GPU (lavapipe in CI) chunk by chunk, each chunk's operator
/// resident under its own key: a tile across chunk edges is the CPU's within 1e-4 of the value
/// range, with the same bound (chains end on the samples' interpolant on both), and so are
/// points in two chunks; one upload a chunk and plane.
#[tokio::test]
async fn chunked_assets_decode_on_the_gpu_chunk_by_chunk() {
    let (store, _) = Store::open(dir()).unwrap();
    let mut st = AppState::new(store, "http://test".into());
    let gpu = fractile_server::GpuBackend::open(256 << 20)
        .unwrap_or_else(|e| panic!("{e} (install mesa-vulkan-drivers)"));
    let gpu = Arc::new(gpu);
    st.gpu = Some(gpu.clone());
    // Tiles are cached whatever decoded them: the CPU's answers come from a server of its own.
    let (on_gpu, on_cpu) = (Arc::new(st), state());
    // Zoom 3, tile (1, 3), finer than the source, at the settled tolerance (chains stop on
    // their cells' residual bounds, on both backends).
    let tile = "/v1/assets/chunked/tiles/3/1/3.f32";
    let mut answers = Vec::new();
    for (st, backend) in [(&on_cpu, "cpu"), (&on_gpu, "gpu")] {
        let (s, h, body) = get(st, &format!("{tile}?backend={backend}")).await;
        assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
        let bound: f32 = h["x-convergence-bound"].to_str().unwrap().parse().unwrap();
        answers.push((floats(&body), bound));
    }
    let ((cpu, b_cpu), (gpu_values, b_gpu)) = (&answers[0], &answers[1]);
    // Four chunks (the edges at -94.67 degrees and at 4.67 degrees north cross the tile), one
    // plane: four uploads, none refused.
    assert_eq!(gpu.uploads(), (4, 0));
    let worst = cpu
        .iter()
        .zip(gpu_values)
        .filter(|(c, _)| c.is_finite())
        .map(|(c, g)| (c - g).abs())
        .fold(0.0f32, f32::max);
    assert!(cpu.iter().filter(|c| c.is_finite()).count() > 60_000);
    // etopo20's heights span about 16,000 m.
    assert!(worst <= 1e-4 * 16_000.0, "GPU against CPU: {worst} m");
    assert!(
        (b_cpu - b_gpu).abs() <= 1e-3 * b_cpu,
        "bounds {b_cpu} and {b_gpu}"
    );
    assert!(worst > 0.0, "the GPU's own answer, not the CPU's");
    // Points in two chunks of level 0, on the GPU, against the CPU's.
    let mut points = Vec::new();
    for (st, backend) in [(&on_cpu, "cpu"), (&on_gpu, "gpu")] {
        let req = Request::post(format!("/v1/assets/chunked/points?backend={backend}"))
            .header("content-type", "application/json")
            .body(Body::from(r#"{"points": [[-100.0, 40.0], [10.0, -20.0]]}"#))
            .unwrap();
        let r = fractile_server::app((*st).clone())
            .oneshot(req)
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::OK);
        let body = r.into_body().collect().await.unwrap().to_bytes();
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        points.push(v);
    }
    let at = |v: &serde_json::Value, k: usize, f: &str| -> f64 {
        let p = &v["results"][k];
        match f {
            "value" => p["values"][0].as_f64().unwrap(),
            _ => p[f].as_f64().unwrap(),
        }
    };
    for k in 0..2 {
        let (c, g) = (at(&points[0], k, "value"), at(&points[1], k, "value"));
        let (bc, bg) = (
            at(&points[0], k, "convergence_bound"),
            at(&points[1], k, "convergence_bound"),
        );
        assert!((c - g).abs() <= 1.6, "point {k}: CPU {c}, GPU {g}");
        assert!(
            (bc - bg).abs() <= 1e-3 * bc,
            "point {k}: bounds {bc} and {bg}"
        );
    }
    assert_eq!(gpu.uploads().1, 0);
    assert!(gpu.uploads().0 > 4, "the points' chunks uploaded too");
}

/// Pixels coarser than a chunked asset's top level share its grids through the server's
/// coarse cache (one a grid size), as a whole asset's do, instead of a discrete decode a
/// request; their heights are the whole asset's within the two bounds.
#[tokio::test]
async fn coarse_pixels_of_a_chunked_asset_share_cached_grids() {
    let st = state();
    // Regions of the whole globe with pixels of 34, 17 and 22 source cells: the top level
    // (etopo20's 1080 x 540 halved three times, 135 x 68 cells, one chunk, above two views)
    // filtered from its grids of 34 x 17, 68 x 34 and 68 x 34 cells (a pixel's cells between
    // half a pixel and one).
    let sizes = [(32, 16), (64, 32), (48, 24)];
    for (w, h) in sizes {
        let uri = |id: &str| {
            format!("/v1/assets/{id}/region?bbox=-180,-90,180,90&width={w}&height={h}&format=f32")
        };
        let (s, hc, body) = get(&st, &uri("chunked")).await;
        assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
        let (_, hw, whole) = get(&st, &uri("single")).await;
        let bound = |h: &axum::http::HeaderMap| -> f32 {
            h["x-error-bound"].to_str().unwrap().parse().unwrap()
        };
        let within = bound(&hc) + bound(&hw);
        let (a, b) = (floats(&body), floats(&whole));
        assert_eq!(a.len(), w * h);
        for (p, q) in a.iter().zip(&b) {
            // The overview averages 2 x 2 source cells where the whole asset's grid averages
            // its own decode: both filter the same cells, each within its bound.
            assert!(
                (p - q).abs() <= within,
                "{w}x{h}: {p} against {q} within {within}"
            );
        }
    }
    let key = st.store.get("chunked").expect("stored").coarse_key();
    let grids = st.coarse.len_of(key);
    assert_eq!(grids, 2, "the chunked asset's grids in the coarse cache");
}

/// Chunked uploads whose every checksum holds but whose chunks are not what the table says are
/// refused with 422 at upload (they were stored, then answered 503 at every request): a chunk
/// of other cells in a chunk's place, a chunked file as a chunk, a level-0 chunk as the
/// coarsest; and sound chunks under a claim of 16,777,216 x 8,192 cells, under a raster past
/// the pole, and a table of nothing but empty chunks (each was stored, and showed impossible
/// bounds in the catalog or held megabytes for nothing).
#[test]
fn crafted_chunk_tables_are_refused_at_upload() {
    let sound = std::fs::read(dir().join("chunked.fra")).unwrap();
    let asset = fractile_codec::Asset::from_bytes(&sound).unwrap();
    let c = asset.chunked().unwrap();
    // Every chunk's file, by level and index.
    type Files = Vec<Vec<Vec<u8>>>;
    let files: Files = fractile_codec::chunked::chunk_files(&c.table, &sound);
    let craft = |edit: &dyn Fn(&mut Files)| {
        let mut f = files.clone();
        edit(&mut f);
        fractile_codec::chunked::assemble(&asset.meta, c.table.clone(), &f)
    };
    let row = c.table.levels[0].chunks.len();
    let top = files.len() - 1;
    let small = encode_chunked(
        &Raster::open(&data("topobathy.tif")).unwrap(),
        64,
        &|r: &Raster| encode_default(r, 0.8, &|_, _| {}),
        &|_, _| {},
    )
    .unwrap()
    .bytes;
    // Sealed as a chunk is, so that its checksum holds: its last four bytes the CRC of the rest.
    let mut small = small;
    small.extend_from_slice(&crc32fast::hash(&small).to_le_bytes());
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        (
            "another chunk's cells",
            craft(&|f| f[0][0] = f[0][row - 1].clone()),
            "cells where the table says",
        ),
        (
            "a chunked file as a chunk",
            craft(&|f| f[0][0] = small.clone()),
            "a chunked file as a chunk",
        ),
        (
            "a level-0 chunk as the coarsest",
            craft(&|f| f[top][0] = f[0][0].clone()),
            "cells where the table says",
        ),
    ];
    let mut cases = cases;
    // Sound chunks under metadata that claims 16,777,216 x 8,192 cells (over 16 x
    // max_asset_pixels), and metadata that puts the raster past the north pole.
    let mut huge = asset.meta.clone();
    (huge.width, huge.height) = (1 << 24, 8192);
    cases.push((
        "16,777,216 x 8,192 cells",
        fractile_codec::chunked::assemble(&huge, c.table.clone(), &files),
        "for a chunked asset",
    ));
    let mut north = asset.meta.clone();
    north
        .georef
        .as_mut()
        .expect("etopo20 is georeferenced")
        .origin[1] = 400.0;
    cases.push((
        "a raster past the pole",
        fractile_codec::chunked::assemble(&north, c.table.clone(), &files),
        "not on the globe",
    ));
    // A table of 21,845 empty chunks of 64 cells (8192^2 cells of nodata): 1.3 MB of table
    // for no chunk at all.
    let mut empty = asset.meta.clone();
    (empty.width, empty.height) = (8192, 8192);
    let mut table = c.table.clone();
    table.chunk = 64;
    table.levels = fractile_codec::chunked::ChunkTable::level_sizes(8192, 8192, 64, false)
        .into_iter()
        .map(|(w, h)| {
            let (nx, ny) = table.grid(w, h);
            fractile_codec::chunked::Level {
                width: w,
                height: h,
                chunks: (0..nx * ny)
                    .map(|i| fractile_codec::chunked::ChunkEntry {
                        offset: 0,
                        length: 0,
                        cells: table.coded_cells(w, h, i % nx, i / nx),
                        value_range: [0.0, 0.0],
                        crc: 0,
                    })
                    .collect(),
            }
        })
        .collect();
    let levels = vec![Vec::new(); table.levels.len()];
    cases.push((
        "a table of empty chunks",
        fractile_codec::chunked::assemble(&empty, table, &levels),
        "bytes of chunks",
    ));
    let uploads = dir().join("crafted-uploads");
    std::fs::create_dir_all(&uploads).unwrap();
    let (store, _) = Store::open(&uploads).unwrap();
    for (what, bytes, says) in cases {
        let Err(e) = store.put("crafted", &bytes) else {
            panic!("{what}: stored")
        };
        assert_eq!(e.status, StatusCode::UNPROCESSABLE_ENTITY, "{what}");
        assert!(e.detail.contains(says), "{what}: {}", e.detail);
        assert!(!uploads.join("crafted.fra").exists(), "{what}");
    }
}
