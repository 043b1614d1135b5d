//! What a newcomer meets first (issue 53): refusals that say what to do, the catalog agreeing
//! with `fractile info`, and coarse Cesium tiles whose bound is about heights.

use std::sync::{Arc, OnceLock};

use axum::body::Body;
use axum::http::{Request, StatusCode};
use fractile_codec::{Raster, encode_default};
use fractile_server::Store;
use fractile_server::{AppState, Writes};
use http_body_util::BodyExt;
use tower::ServiceExt;

fn data(name: &str) -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// jacksboro by the default DEM codec, writable by anyone (the demo on loopback).
fn state() -> Arc<AppState> {
    static STATE: OnceLock<Arc<AppState>> = OnceLock::new();
    STATE
        .get_or_init(|| {
            let dir = std::env::temp_dir().join(format!("fractile-msg-{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).unwrap();
            let r = Raster::open(&data("jacksboro.tif")).unwrap();
            let enc = encode_default(&r, 0.8, &|_, _| {}).unwrap();
            std::fs::write(dir.join("jacksboro.fra"), &enc.bytes).unwrap();
            let (store, _) = Store::open(&dir).unwrap();
            let mut st = AppState::new(store, "http://test".into());
            st.writes = Writes::from_options(None, true);
            Arc::new(st)
        })
        .clone()
}

async fn send(req: Request<Body>) -> (StatusCode, axum::http::HeaderMap, serde_json::Value) {
    let resp = fractile_server::app(state()).oneshot(req).await.unwrap();
    let (parts, body) = resp.into_parts();
    let bytes = body.collect().await.unwrap().to_bytes();
    let json = serde_json::from_slice(&bytes).unwrap_or(serde_json::Value::Null);
    (parts.status, parts.headers, json)
}

async fn get(uri: &str) -> (StatusCode, axum::http::HeaderMap, serde_json::Value) {
    send(Request::get(uri).body(Body::empty()).unwrap()).await
}

#[tokio::test]
async fn tile_numbers_out_of_range_say_the_valid_ones() {
    // A zoom past the deepest: 404 (no such tile), with the zooms there are.
    let (s, _, b) = get("/v1/assets/jacksboro/tiles/40/0/0.png").await;
    assert_eq!(s, StatusCode::NOT_FOUND, "{b}");
    assert_eq!(b["code"], "no_tile");
    assert!(
        b["detail"].as_str().unwrap().contains("from 0 to 24"),
        "{b}"
    );
    // Numbers that are no tile numbers at all: our 400, not axum's "Cannot parse value".
    for (uri, says) in [
        (
            "/v1/assets/jacksboro/tiles/3/99999999999/0.png",
            "columns go from 0 to 7",
        ),
        (
            "/v1/assets/jacksboro/tiles/3/0/-1.png",
            "rows go from 0 to 7",
        ),
        ("/v1/assets/jacksboro/tiles/300/0/0.png", "from 0 to 24"),
        (
            "/v1/assets/jacksboro/terrain/2/99999999999/0.terrain",
            "columns go from 0 to 7",
        ),
    ] {
        let (s, _, b) = get(uri).await;
        assert_eq!(s, StatusCode::BAD_REQUEST, "{uri}: {b}");
        assert_eq!(b["code"], "bad_path", "{uri}");
        let detail = b["detail"].as_str().unwrap();
        assert!(detail.contains(says), "{uri}: {detail}");
        assert!(!detail.contains("Cannot parse"), "{uri}: {detail}");
    }
}

#[tokio::test]
async fn an_upload_of_a_source_raster_says_to_encode_it_first() {
    let tif = std::fs::read(data("jacksboro.tif")).unwrap();
    let req = Request::put("/v1/assets/raw")
        .body(Body::from(tif))
        .unwrap();
    let (s, _, b) = send(req).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{b}");
    let detail = b["detail"].as_str().unwrap();
    assert!(detail.contains("GeoTIFF"), "{detail}");
    assert!(detail.contains("fractile encode"), "{detail}");
}

#[tokio::test]
async fn the_catalog_names_the_epsg_code_info_prints() {
    let (s, _, b) = get("/v1/assets").await;
    assert_eq!(s, StatusCode::OK);
    let j = b["assets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["id"] == "jacksboro")
        .unwrap();
    let file = Raster::open(&data("jacksboro.tif")).unwrap();
    assert_eq!(j["epsg"], file.georef.unwrap().epsg.unwrap());
    assert_eq!(j["epsg"], 4326);
}

#[tokio::test]
async fn coarse_cesium_tiles_carry_their_meshes_error_on_the_globe() {
    // Level 0's tiles span 180 degrees: the regular 65 x 65 grid they were drew flat triangles
    // 2.8 degrees wide, 1.9 km under the globe at their middles, and reported the decode's
    // bound alone. Now the mesh is simplified to the level's geometric error (77,067 m) on the
    // globe, and the tile's bound carries the error the mesh has: kilometres (the sagittas of
    // its triangles), within that error plus the decode's.
    let (s, h, _) = get("/v1/assets/jacksboro/terrain/0/0/0.terrain").await;
    assert_eq!(s, StatusCode::OK);
    let bound: f64 = h["x-error-bound"].to_str().unwrap().parse().unwrap();
    let (_, _, list) = get("/v1/assets").await;
    let a = list["assets"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["id"] == "jacksboro");
    let range = &a.unwrap()["value_range"];
    let span = range[1].as_f64().unwrap() - range[0].as_f64().unwrap();
    assert!(
        bound > 1_000.0 && bound <= 77_067.0 + span,
        "bound {bound} (the heights' span {span})"
    );
}
