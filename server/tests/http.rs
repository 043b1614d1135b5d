//! The HTTP API in-process (tower `oneshot`), on assets encoded from the repo's real test data.

use std::sync::{Arc, OnceLock};

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use fractile_codec::geo::{self, Placement};
use fractile_codec::{QuadtreeSettings, Raster, RateMode, encode};
use fractile_server::AppState;
use fractile_server::Store;
use http_body_util::BodyExt;
use tower::ServiceExt;

fn data(name: &str) -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// Encoding RMSE of the jacksboro asset, measured by the encoder.
static JACKSBORO_RMSE: OnceLock<f64> = OnceLock::new();

fn state() -> Arc<AppState> {
    static STATE: OnceLock<Arc<AppState>> = OnceLock::new();
    STATE
        .get_or_init(|| {
            let dir = std::env::temp_dir().join(format!("fractile-http-{}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            for (id, file, bpp) in [
                ("jacksboro", "jacksboro.tif", 1.6),
                // The same terrain on a UTM 16N grid (a projected CRS).
                ("jacksboro-utm", "jacksboro-utm.tif", 1.6),
                ("camera", "camera.png", 0.48),
            ] {
                let r = Raster::open(&data(file)).unwrap();
                let mut s = QuadtreeSettings {
                    rate: RateMode::TargetBpp(bpp),
                    ..QuadtreeSettings::default()
                };
                s.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(r.kind);
                let enc = encode(&r, &s, &|_, _| {}).unwrap();
                if id == "jacksboro" {
                    JACKSBORO_RMSE.set(enc.errors.rmse).unwrap();
                }
                std::fs::write(dir.join(format!("{id}.fra")), &enc.bytes).unwrap();
            }
            // A volume (IFS3D) from a real mesh.
            let mesh = fractile_codec::mesh::Mesh::read(&data("mesh/fandisk.off")).unwrap();
            let vol = fractile_codec::encode::volume::encode_mesh(
                &mesh,
                &fractile_codec::encode::volume::MeshSettings {
                    grid: 40,
                    ..Default::default()
                },
                "fandisk.off",
            )
            .unwrap();
            std::fs::write(dir.join("fandisk.fra"), &vol.bytes).unwrap();
            // Curves: five real coastlines, coded to about 1 km.
            let text = std::fs::read_to_string(data("curve/coast5.geojson")).unwrap();
            let lines = fractile_codec::codecs::curve::geojson::read(&text).unwrap();
            let settings = fractile_codec::codecs::curve::CurveSettings {
                tolerance: 0.009,
                ..Default::default()
            };
            let c =
                fractile_codec::encode::curve::encode_asset(&lines, &settings, "coast5").unwrap();
            std::fs::write(dir.join("coast.fra"), &c.bytes).unwrap();
            // A broken file must be skipped, not stop the server.
            std::fs::write(dir.join("broken.fra"), b"FRACTILE garbage").unwrap();
            let (store, skipped) = Store::open(&dir).unwrap();
            assert_eq!(skipped.len(), 1, "{skipped:?}");
            Arc::new(AppState::new(store, "http://test".into()))
        })
        .clone()
}

async fn get(uri: &str) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    send(Request::get(uri).body(Body::empty()).unwrap()).await
}

async fn send(req: Request<Body>) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    let resp = fractile_server::app(state()).oneshot(req).await.unwrap();
    let (parts, body) = resp.into_parts();
    (
        parts.status,
        parts.headers,
        body.collect().await.unwrap().to_bytes().to_vec(),
    )
}

/// POSTs a JSON body to `uri` and reads the JSON answer, which must be 200.
async fn post_json(uri: &str, body: serde_json::Value) -> serde_json::Value {
    let req = Request::post(uri)
        .header(header::CONTENT_TYPE, "application/json")
        .body(Body::from(body.to_string()))
        .unwrap();
    let (s, _, b) = send(req).await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    json(&b)
}

fn json(b: &[u8]) -> serde_json::Value {
    serde_json::from_slice(b).unwrap()
}

fn terrain_rgb(p: [u8; 3]) -> f64 {
    -10000.0 + (p[0] as f64 * 65536.0 + p[1] as f64 * 256.0 + p[2] as f64) * 0.1
}

#[tokio::test]
async fn catalog_metadata_and_tilejson() {
    let (s, _, b) = get("/v1/assets").await;
    assert_eq!(s, StatusCode::OK);
    let ids: Vec<String> = json(&b)["assets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["id"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(
        ids,
        ["camera", "coast", "fandisk", "jacksboro", "jacksboro-utm"]
    );
    let (s, _, b) = get("/v1/assets/jacksboro").await;
    assert_eq!(s, StatusCode::OK);
    let m = json(&b);
    assert_eq!(m["kind"], "HeightField");
    assert!(m["ratio"].as_f64().unwrap() > 5.0);
    let (_, _, b) = get("/v1/assets/jacksboro/tilejson.json").await;
    let tj = json(&b);
    assert_eq!(tj["tilejson"], "3.0.0");
    assert!(
        tj["tiles"][0]
            .as_str()
            .unwrap()
            .starts_with("http://test/v1/assets/jacksboro/tiles/{z}/{x}/{y}.png")
    );
    // Deeper than the source: jacksboro's 3" cells are about zoom 12 at 256 px.
    assert!(tj["maxzoom"].as_u64().unwrap() >= 14, "{tj}");
}

/// `.webp` tiles are lossless: the same pixels as the `.png` of the same tile (terrain-RGB,
/// Terrarium, a visual one, a colour image), as `image/webp`, with their own ETag; 16-bit
/// grey, which WebP has not, is refused by name.
#[tokio::test]
async fn webp_tiles_are_the_png_pixels_losslessly() {
    use image::GenericImageView;
    let (x, y) = geo::lonlat_tile(14, -84.25, 36.6);
    let tiles = [
        format!("jacksboro/tiles/14/{x}/{y}.{{}}?encoding=terrainrgb"),
        format!("jacksboro/tiles/14/{x}/{y}.{{}}?encoding=terrarium"),
        format!("jacksboro/tiles/14/{x}/{y}.{{}}?rescale=200,600"),
        "camera/tiles/1/0/0.{}".to_string(),
    ];
    for t in &tiles {
        let (sp, hp, png) = get(&format!("/v1/assets/{}", t.replace("{}", "png"))).await;
        let (sw, hw, webp) = get(&format!("/v1/assets/{}", t.replace("{}", "webp"))).await;
        assert_eq!((sp, sw), (StatusCode::OK, StatusCode::OK), "{t}");
        assert_eq!(hw[header::CONTENT_TYPE], "image/webp", "{t}");
        assert_ne!(hp[header::ETAG], hw[header::ETAG], "{t}");
        assert_eq!(&webp[..4], b"RIFF", "{t}");
        let (a, b) = (
            image::load_from_memory_with_format(&png, image::ImageFormat::Png).unwrap(),
            image::load_from_memory_with_format(&webp, image::ImageFormat::WebP).unwrap(),
        );
        assert_eq!(a.dimensions(), b.dimensions(), "{t}");
        assert_eq!(
            a.to_rgba8().as_raw(),
            b.to_rgba8().as_raw(),
            "{t}: other pixels"
        );
        assert!(
            a.to_rgba8().pixels().any(|p| p.0 != [0, 0, 0, 0]),
            "{t}: no picture"
        );
    }
    let (s, _, b) = get(&format!(
        "/v1/assets/jacksboro/tiles/14/{x}/{y}.webp?encoding=gray16"
    ))
    .await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert_eq!(json(&b)["code"], "bad_encoding");
}

#[tokio::test]
async fn terrain_rgb_tile_matches_the_source_within_the_encoding_error() {
    let st = state();
    let a = st.store.get("jacksboro").unwrap();
    let place: Placement = a.placement.clone().unwrap();
    let (x, y) = geo::lonlat_tile(12, -84.25, 36.6);
    let (s, h, b) = get(&format!(
        "/v1/assets/jacksboro/tiles/12/{x}/{y}.png?encoding=terrainrgb"
    ))
    .await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    assert_eq!(h[header::CONTENT_TYPE], "image/png");
    assert!(h.contains_key("x-error-bound") && h.contains_key(header::ETAG));
    let img = image::load_from_memory(&b).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (256, 256));
    // Heights against the source DEM sampled bilinearly at the same points.
    let src = Raster::open(&data("jacksboro.tif")).unwrap();
    let (pts, _) = geo::tile_points(Some(&place), 12, x, y, 256);
    let (mut se, mut n) = (0.0, 0);
    for (k, p) in pts.iter().enumerate() {
        let Some([u, v]) = p else { continue };
        let (fx, fy) = (u * src.width as f32 - 0.5, v * src.height as f32 - 0.5);
        if fx < 0.0 || fy < 0.0 || fx > (src.width - 1) as f32 || fy > (src.height - 1) as f32 {
            continue;
        }
        let g = fractile_codec::decode::Grid {
            width: src.width,
            height: src.height,
            values: src.channels[0].clone(),
        };
        let truth = fractile_codec::decode::sample_bilinear(&g, fx, fy) as f64;
        let got = terrain_rgb(img.get_pixel((k % 256) as u32, (k / 256) as u32).0);
        se += (got - truth).powi(2);
        n += 1;
    }
    assert!(n > 10_000, "{n} pixels inside");
    let rmse = (se / n as f64).sqrt();
    let enc = *JACKSBORO_RMSE.get().unwrap();
    assert!(
        rmse < enc + 8.0,
        "tile RMSE {rmse} m vs encoding RMSE {enc} m"
    );
}

#[tokio::test]
async fn points_at_source_pixel_centres_are_as_good_as_the_encoding() {
    let st = state();
    let a = st.store.get("jacksboro").unwrap();
    let g = a.asset.meta.georef.clone().unwrap();
    let src = Raster::open(&data("jacksboro.tif")).unwrap();
    let mut pts = Vec::new();
    let mut truth = Vec::new();
    for j in (0..src.height).step_by(7) {
        for i in (0..src.width).step_by(7) {
            let lon = g.origin[0] + (i as f64 + 0.5) * g.pixel_size[0];
            let lat = g.origin[1] + (j as f64 + 0.5) * g.pixel_size[1];
            pts.push([lon, lat]);
            truth.push(src.channels[0][j * src.width + i] as f64);
        }
    }
    let r = post_json(
        "/v1/assets/jacksboro/points",
        serde_json::json!({"points": pts, "iterations": 20}),
    )
    .await;
    let results = r["results"].as_array().unwrap();
    assert_eq!(results.len(), pts.len());
    let se: f64 = results
        .iter()
        .zip(&truth)
        .map(|(r, t)| (r["values"][0].as_f64().unwrap() - t).powi(2))
        .sum();
    let rmse = (se / truth.len() as f64).sqrt();
    let enc = *JACKSBORO_RMSE.get().unwrap();
    assert!(rmse < 1.25 * enc, "point RMSE {rmse} vs encoding {enc}");
    // The single-point form answers the same.
    let (s, _, b) = get(&format!(
        "/v1/assets/jacksboro/point/{},{}?iterations=20",
        pts[5][0], pts[5][1]
    ))
    .await;
    assert_eq!(s, StatusCode::OK);
    let p = json(&b);
    assert!(
        (p["values"][0].as_f64().unwrap() - results[5]["values"][0].as_f64().unwrap()).abs() < 1e-3
    );
    // Against the source: the measured source error there plus convergence.
    assert!(p["error_bound"].as_f64().unwrap() >= p["convergence_bound"].as_f64().unwrap());
    assert!(p["convergence_bound"].as_f64().unwrap() >= 0.0);
    // Without steps or a tolerance, each point converges to the asset's default tolerance (an
    // eighth of its smallest source error where that is over half a metre), not to the step
    // limit's bound: its convergence bound is within that tolerance, and the tolerance is what
    // the codec says it is.
    let tolerance = f64::from(a.asset.default_tolerance());
    let smallest = a.asset.source_error.as_ref().and_then(|m| m.smallest());
    assert_eq!(
        tolerance,
        f64::from(0.5f32.max(smallest.expect("a source-error map") / 8.0))
    );
    let r = post_json(
        "/v1/assets/jacksboro/points",
        serde_json::json!({"points": pts}),
    )
    .await;
    let mut loosest = 0.0f64;
    for r in r["results"].as_array().unwrap() {
        let c = r["convergence_bound"].as_f64().unwrap();
        // The f32 rounding of a chain's sums on top (a few ulps of the value range).
        assert!(c <= tolerance * 1.001 + 1e-3, "{r} against {tolerance}");
        assert!(r["error_bound"].as_f64().unwrap() >= c);
        loosest = loosest.max(c);
    }
    // Chains stopped at that tolerance, not at half a metre as they did before it (this
    // asset's tolerance is over a metre).
    assert!(tolerance > 1.0 && loosest > 0.5, "{loosest} of {tolerance}");
}

#[tokio::test]
async fn neighbouring_tiles_meet_without_a_seam() {
    let (x, y) = geo::lonlat_tile(13, -84.25, 36.6);
    let tile = |x: u32| async move {
        let (s, _, b) = get(&format!("/v1/assets/jacksboro/tiles/13/{x}/{y}.f32")).await;
        assert_eq!(s, StatusCode::OK);
        b.chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect::<Vec<f32>>()
    };
    let (left, right) = (tile(x).await, tile(x + 1).await);
    let (mut seam, mut inner) = (0.0f32, 0.0f32);
    for j in 0..256 {
        seam = seam.max((left[j * 256 + 255] - right[j * 256]).abs());
        inner = inner
            .max((left[j * 256 + 254] - left[j * 256 + 255]).abs())
            .max((right[j * 256] - right[j * 256 + 1]).abs());
    }
    assert!(
        seam <= inner * 1.5 + 1e-3,
        "seam jump {seam} vs inner jumps {inner}"
    );
}

#[tokio::test]
async fn etag_answers_304_and_tiles_are_cacheable() {
    let uri = "/v1/assets/camera/tiles/1/0/1.png";
    let (s, h, b) = get(uri).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(image::load_from_memory(&b).unwrap().width(), 256);
    assert_eq!(h[header::CACHE_CONTROL], "public, max-age=3600");
    let tag = h[header::ETAG].to_str().unwrap().to_string();
    let req = Request::get(uri)
        .header(header::IF_NONE_MATCH, &tag)
        .body(Body::empty())
        .unwrap();
    let (s, _, b) = send(req).await;
    assert_eq!(s, StatusCode::NOT_MODIFIED);
    assert!(b.is_empty());
    // Other parameters, other tag.
    let (_, h2, _) = get("/v1/assets/camera/tiles/1/0/1.png?iterations=3").await;
    assert_ne!(h2[header::ETAG], tag.as_str());
}

#[tokio::test]
async fn regions_at_any_resolution() {
    let (s, _, b) =
        get("/v1/assets/camera/region?bbox=0.4,0.2,0.5,0.3&width=300&height=200&format=f32").await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(b.len(), 300 * 200 * 4);
    let (s, h, b) =
        get("/v1/assets/jacksboro/region?bbox=-84.3,36.5,-84.2,36.6&width=128&height=128").await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(h[header::CONTENT_TYPE], "image/png");
    assert_eq!(image::load_from_memory(&b).unwrap().height(), 128);
    // A float GeoTIFF of heights, georeferenced to the box: readable by our own reader.
    let (s, h, b) = get(
        "/v1/assets/jacksboro/region?bbox=-84.3,36.5,-84.2,36.6&width=100&height=80&format=tif",
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(h[header::CONTENT_TYPE], "image/tiff");
    let path = std::env::temp_dir().join(format!("fractile-region-{}.tif", std::process::id()));
    std::fs::write(&path, &b).unwrap();
    let r = Raster::open(&path).unwrap();
    assert_eq!((r.width, r.height), (100, 80));
    let g = r.georef.unwrap();
    assert!(
        (g.origin[0] + 84.3).abs() < 1e-9
            && (g.origin[1] - 36.6).abs() < 1e-9
            && (g.pixel_size[0] - 0.001).abs() < 1e-12
    );
    let m = &state().store.get("jacksboro").unwrap().asset.meta;
    let (lo, hi) = (m.value_min as f32 - 50.0, m.value_max as f32 + 50.0);
    assert!(
        r.channels[0].iter().all(|v| (lo..hi).contains(v)),
        "heights in metres within {lo}..{hi}"
    );
    let (s, _, _) =
        get("/v1/assets/camera/region?bbox=0,0,1,1&width=10&height=10&format=tif").await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
}

#[tokio::test]
async fn bad_requests_get_precise_errors() {
    for (uri, status, code) in [
        ("/v1/assets/nope", StatusCode::NOT_FOUND, "unknown_asset"),
        (
            "/v1/assets/..%2F..%2Fetc",
            StatusCode::BAD_REQUEST,
            "bad_id",
        ),
        ("/v1/assets/.hidden", StatusCode::BAD_REQUEST, "bad_id"),
        (
            "/v1/assets/camera/tiles/2/9/0.png",
            StatusCode::NOT_FOUND,
            "no_tile",
        ),
        (
            "/v1/assets/camera/tiles/2/0/0.jpg",
            StatusCode::BAD_REQUEST,
            "bad_format",
        ),
        (
            "/v1/assets/camera/tiles/2/0/0.f32",
            StatusCode::BAD_REQUEST,
            "bad_format",
        ),
        (
            "/v1/assets/camera/tiles/2/0/0.png?tilesize=300",
            StatusCode::BAD_REQUEST,
            "bad_tilesize",
        ),
        (
            "/v1/assets/camera/tiles/2/0/0.png?iterations=100000",
            StatusCode::BAD_REQUEST,
            "bad_iterations",
        ),
        (
            "/v1/assets/jacksboro/tiles/12/0/0.png",
            StatusCode::NOT_FOUND,
            "outside",
        ),
        (
            "/v1/assets/jacksboro/tiles/10/0/0.png?encoding=lerc",
            StatusCode::BAD_REQUEST,
            "bad_encoding",
        ),
        (
            "/v1/assets/jacksboro/tiles/10/0/0.f32?encoding=terrarium",
            StatusCode::BAD_REQUEST,
            "bad_encoding",
        ),
        (
            "/v1/assets/jacksboro/point/10,10",
            StatusCode::NOT_FOUND,
            "outside",
        ),
        (
            "/v1/assets/jacksboro/point/abc",
            StatusCode::BAD_REQUEST,
            "bad_point",
        ),
        (
            "/v1/assets/camera/region?bbox=0,0,1,1&width=100000&height=100000",
            StatusCode::BAD_REQUEST,
            "bad_size",
        ),
        (
            "/v1/assets/camera/region?bbox=1,0,0,1&width=10&height=10",
            StatusCode::BAD_REQUEST,
            "bad_bbox",
        ),
        // What axum rejects before a handler runs has the same JSON shape.
        (
            "/v1/assets/coast/curve?level=-1",
            StatusCode::BAD_REQUEST,
            "bad_query",
        ),
        (
            "/v1/assets/camera/tiles/2/0/0.png?iterations=many",
            StatusCode::BAD_REQUEST,
            "bad_query",
        ),
        (
            "/v1/assets/camera/tiles/abc/0/0.png",
            StatusCode::BAD_REQUEST,
            "bad_path",
        ),
        (
            "/v1/assets/camera/tiles/300/0/0.png",
            StatusCode::BAD_REQUEST,
            "bad_path",
        ),
        ("/v1/nothing", StatusCode::NOT_FOUND, "no_route"),
    ] {
        let (s, _, b) = get(uri).await;
        assert_eq!(s, status, "{uri}: {}", String::from_utf8_lossy(&b));
        assert_eq!(json(&b)["code"], code, "{uri}");
        assert!(json(&b)["detail"].as_str().is_some_and(|d| !d.is_empty()));
    }
    let req = Request::post("/v1/assets/camera/points")
        .header(header::CONTENT_TYPE, "application/json")
        .body(Body::from("{\"points\": 3}"))
        .unwrap();
    let (s, _, b) = send(req).await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert_eq!(json(&b)["code"], "bad_body");
    // A method a route does not answer: 405 in JSON, with the methods it does answer.
    let req = Request::delete("/v1/assets").body(Body::empty()).unwrap();
    let (s, h, b) = send(req).await;
    assert_eq!(s, StatusCode::METHOD_NOT_ALLOWED);
    assert_eq!(json(&b)["code"], "method_not_allowed");
    let allow = h
        .get(header::ALLOW)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    assert!(allow.contains("GET"), "Allow: {allow:?}");
}

/// A store of its own (writes must not disturb the shared one), with a token and a small limit.
fn writable(token: Option<&str>, max_upload: usize) -> (Arc<AppState>, Vec<u8>) {
    let dir = std::env::temp_dir().join(format!(
        "fractile-http-w-{}-{}",
        std::process::id(),
        token.unwrap_or("open")
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let (store, _) = Store::open(&dir).unwrap();
    let mut st = AppState::new(store, "http://test".into());
    st.writes = fractile_server::Writes::from_options(token.map(str::to_string), true);
    st.max_upload = max_upload;
    let r = Raster::open(&data("topobathy.tif")).unwrap();
    let enc = encode(
        &r,
        &QuadtreeSettings {
            rate: RateMode::TargetBpp(1.0),
            ..QuadtreeSettings::default()
        },
        &|_, _| {},
    )
    .unwrap();
    (Arc::new(st), enc.bytes)
}

async fn call(st: &Arc<AppState>, req: Request<Body>) -> (StatusCode, Vec<u8>) {
    let resp = fractile_server::app(st.clone()).oneshot(req).await.unwrap();
    let s = resp.status();
    (
        s,
        resp.into_body()
            .collect()
            .await
            .unwrap()
            .to_bytes()
            .to_vec(),
    )
}

#[tokio::test]
async fn upload_replace_and_delete() {
    let (st, bytes) = writable(None, 1 << 20);
    let put = |b: Vec<u8>| Request::put("/v1/assets/topo").body(Body::from(b)).unwrap();
    let (s, b) = call(&st, put(bytes.clone())).await;
    assert_eq!(s, StatusCode::CREATED, "{}", String::from_utf8_lossy(&b));
    assert_eq!(json(&b)["kind"], "HeightField");
    let (s, _) = call(
        &st,
        Request::get("/v1/assets/topo/point/-125.5,49.5")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    let (s, _) = call(&st, put(bytes.clone())).await;
    assert_eq!(s, StatusCode::OK, "replacing an asset answers 200");
    // A corrupt upload is refused and loses nothing: the old asset still serves.
    let mut bad = bytes.clone();
    bad[40] ^= 0xFF;
    let (s, b) = call(&st, put(bad)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY);
    assert_eq!(json(&b)["code"], "bad_asset");
    let (s, _) = call(
        &st,
        Request::get("/v1/assets/topo").body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    // Bad ids never reach the disk.
    let (s, _) = call(
        &st,
        Request::put("/v1/assets/..")
            .body(Body::from(bytes.clone()))
            .unwrap(),
    )
    .await;
    assert_ne!(s, StatusCode::CREATED);
    let (s, _) = call(
        &st,
        Request::delete("/v1/assets/topo")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::NO_CONTENT);
    let (s, _) = call(
        &st,
        Request::get("/v1/assets/topo").body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    let (s, _) = call(
        &st,
        Request::delete("/v1/assets/topo")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::NOT_FOUND);
}

#[tokio::test]
async fn with_no_token_writes_are_refused_unless_anonymous_writes_are_allowed() {
    use fractile_server::Writes;
    // What `fractile serve` runs with when neither a token nor --allow-anonymous-writes is
    // given, and a state built with no policy at all: both refuse.
    assert_eq!(Writes::from_options(None, false), Writes::Refused);
    let dir = std::env::temp_dir().join(format!("fractile-http-default-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (store, _) = Store::open(&dir).unwrap();
    assert_eq!(
        AppState::new(store, "http://t".into()).writes,
        Writes::Refused
    );
    let (mut st, bytes) = writable(None, 1 << 20);
    Arc::get_mut(&mut st).unwrap().writes = Writes::Refused;
    for req in [
        Request::put("/v1/assets/topo").body(Body::from(bytes.clone())),
        Request::delete("/v1/assets/topo").body(Body::empty()),
    ] {
        let (s, b) = call(&st, req.unwrap()).await;
        assert_eq!(s, StatusCode::FORBIDDEN);
        assert_eq!(json(&b)["code"], "writes_disabled");
        assert!(
            json(&b)["detail"]
                .as_str()
                .unwrap()
                .contains("--allow-anonymous-writes")
        );
    }
    assert_eq!(
        call(
            &st,
            Request::get("/v1/assets/topo").body(Body::empty()).unwrap()
        )
        .await
        .0,
        StatusCode::NOT_FOUND,
        "nothing was stored"
    );
    // Asked for by name, anyone may write; a token, when set, wins over it.
    assert_eq!(Writes::from_options(None, true), Writes::Anyone);
    assert_eq!(
        Writes::from_options(Some("t".into()), true),
        Writes::Token("t".into())
    );
    let (open, bytes) = writable(None, 1 << 20);
    let put = Request::put("/v1/assets/topo").body(Body::from(bytes));
    assert_eq!(call(&open, put.unwrap()).await.0, StatusCode::CREATED);
}

#[tokio::test]
async fn writes_need_the_token_and_respect_the_size_limit() {
    let (st, bytes) = writable(Some("s3cret"), 1 << 20);
    let (s, b) = call(
        &st,
        Request::put("/v1/assets/topo")
            .body(Body::from(bytes.clone()))
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    assert_eq!(json(&b)["code"], "unauthorised");
    let wrong = Request::put("/v1/assets/topo")
        .header(header::AUTHORIZATION, "Bearer nope")
        .body(Body::from(bytes.clone()))
        .unwrap();
    assert_eq!(call(&st, wrong).await.0, StatusCode::UNAUTHORIZED);
    let right = Request::put("/v1/assets/topo")
        .header(header::AUTHORIZATION, "Bearer s3cret")
        .body(Body::from(bytes.clone()))
        .unwrap();
    assert_eq!(call(&st, right).await.0, StatusCode::CREATED);
    let del = Request::delete("/v1/assets/topo")
        .body(Body::empty())
        .unwrap();
    assert_eq!(call(&st, del).await.0, StatusCode::UNAUTHORIZED);

    let (small, bytes) = writable(Some("t"), 100);
    let big = Request::put("/v1/assets/topo")
        .header(header::AUTHORIZATION, "Bearer t")
        .body(Body::from(bytes))
        .unwrap();
    let (s, b) = call(&small, big).await;
    assert_eq!(s, StatusCode::PAYLOAD_TOO_LARGE);
    // The code the README names for a body over a route's limit.
    assert_eq!(json(&b)["code"], "too_large");
}

#[tokio::test]
async fn metrics_count_requests_by_route_and_cache_hits() {
    let uri = "/v1/assets/camera/tiles/2/1/1.png";
    get(uri).await;
    get(uri).await;
    let (s, _, b) = get("/metrics").await;
    assert_eq!(s, StatusCode::OK);
    let text = String::from_utf8(b).unwrap();
    assert!(
        text.contains(
            "fractile_requests_total{route=\"/v1/assets/{id}/tiles/{z}/{x}/{tile}\",status=\"200\"}"
        ),
        "{text}"
    );
    assert!(
        text.contains("fractile_tile_cache_total{result=\"hit\"}"),
        "{text}"
    );
    assert!(text.contains("fractile_request_seconds_bucket"), "{text}");
    assert!(text.contains("fractile_decode_seconds"), "{text}");
    // An uncached tile's stages, each timed.
    for stage in ["sites", "sample", "encode"] {
        let name = format!("fractile_tile_stage_seconds_count{{stage=\"{stage}\"}}");
        assert!(text.contains(&name), "{name} in {text}");
    }
}

#[tokio::test]
async fn point_batches_in_bincode_answer_the_same_as_json() {
    use fractile_proto::{BINARY_MEDIA_TYPE, PointsRequest, PointsResponse};
    let req = PointsRequest {
        points: vec![[0.25, 0.5], [0.9, 0.1], [2.0, 2.0]],
        iterations: Some(12),
        tolerance: None,
    };
    let bin = Request::post("/v1/assets/camera/points")
        .header(header::CONTENT_TYPE, BINARY_MEDIA_TYPE)
        .body(Body::from(fractile_proto::encode(&req)))
        .unwrap();
    let (s, h, b) = send(bin).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(h[header::CONTENT_TYPE], BINARY_MEDIA_TYPE);
    let from_bin: PointsResponse = fractile_proto::decode(&b).unwrap();
    let js = Request::post("/v1/assets/camera/points")
        .header(header::CONTENT_TYPE, "application/json")
        .body(Body::from(serde_json::to_vec(&req).unwrap()))
        .unwrap();
    let (_, _, b) = send(js).await;
    let from_json: PointsResponse = serde_json::from_slice(&b).unwrap();
    assert_eq!(from_bin, from_json);
    assert!(from_bin.results[2].outside && from_bin.results[2].values.is_none());
    assert!(from_bin.results[0].values.as_ref().unwrap()[0].unwrap() > 0.0);
    // A batch at the point limit in JSON (several MB) is accepted; one over it is refused.
    let many: Vec<[f64; 2]> = (0..100_000)
        .map(|i| {
            [
                (i as f64 * 0.618_033_988_7) % 1.0,
                (i as f64 * 0.414_213_562_3) % 1.0,
            ]
        })
        .collect();
    let big = serde_json::to_vec(&PointsRequest {
        points: many.clone(),
        iterations: Some(4),
        tolerance: None,
    })
    .unwrap();
    assert!(big.len() > 2_000_000);
    let (s, _, b) = send(
        Request::post("/v1/assets/camera/points")
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(big))
            .unwrap(),
    )
    .await;
    assert_eq!(
        s,
        StatusCode::OK,
        "{}",
        String::from_utf8_lossy(&b[..b.len().min(200)])
    );
    let mut over = many;
    over.push([0.5, 0.5]);
    let body = serde_json::to_vec(&PointsRequest {
        points: over,
        iterations: Some(4),
        tolerance: None,
    })
    .unwrap();
    let (s, _, b) = send(
        Request::post("/v1/assets/camera/points")
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(body))
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::PAYLOAD_TOO_LARGE);
    assert_eq!(json(&b)["code"], "too_many_points");
    // A body past the route's byte limit is refused by a layer before the handler: still JSON.
    let huge = vec![b' '; 64 * state().limits.max_points + 1];
    let (s, _, b) = send(
        Request::post("/v1/assets/camera/points")
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(huge))
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::PAYLOAD_TOO_LARGE);
    assert_eq!(json(&b)["code"], "too_large");
    // Garbage in the binary form is a 400, not a panic.
    let junk = Request::post("/v1/assets/camera/points")
        .header(header::CONTENT_TYPE, BINARY_MEDIA_TYPE)
        .body(Body::from(vec![7u8; 5]))
        .unwrap();
    assert_eq!(send(junk).await.0, StatusCode::BAD_REQUEST);
}

#[tokio::test]
async fn terrain_meshes_in_three_formats() {
    let bbox = "-84.3,36.5,-84.2,36.6";
    let (s, h, b) = get(&format!(
        "/v1/assets/jacksboro/mesh?bbox={bbox}&resolution=65&format=obj"
    ))
    .await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    assert_eq!(h[header::CONTENT_TYPE], "text/plain");
    let obj = String::from_utf8(b).unwrap();
    let zs: Vec<f64> = obj
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| l.split(' ').nth(2).unwrap().parse().unwrap())
        .collect();
    assert_eq!(zs.len(), 65 * 65);
    assert_eq!(
        obj.lines().filter(|l| l.starts_with("f ")).count(),
        2 * 64 * 64
    );
    // The south-west vertex (last row, first column) is the height at the box's corner.
    let (_, _, p) = get("/v1/assets/jacksboro/point/-84.3,36.5").await;
    let corner = json(&p)["values"][0].as_f64().unwrap();
    assert!(
        (zs[64 * 65] - corner).abs() < 15.0,
        "{} vs {corner}",
        zs[64 * 65]
    );
    // About 9 km east-west at 36.5 N: the last vertex of the first row.
    let x_east: f64 = obj
        .lines()
        .filter(|l| l.starts_with("v "))
        .nth(64)
        .unwrap()
        .split(' ')
        .nth(1)
        .unwrap()
        .parse()
        .unwrap();
    assert!((x_east - 8_950.0).abs() < 100.0, "{x_east}");
    let (s, h, b) = get(&format!(
        "/v1/assets/jacksboro/mesh?bbox={bbox}&resolution=33&format=glb"
    ))
    .await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(h[header::CONTENT_TYPE], "model/gltf-binary");
    assert_eq!(&b[..4], b"glTF");
    let (s, _, b) = get(&format!(
        "/v1/assets/jacksboro/mesh?bbox={bbox}&resolution=33&format=ply"
    ))
    .await;
    assert_eq!(s, StatusCode::OK);
    assert!(b.starts_with(b"ply\n"));
    // Adaptive: resolution 60 rounds up to the 65 x 65 grid above; its vertices are some of
    // that grid's, with fewer triangles, and the bound grows by max_error.
    let (s, h_grid, _) = get(&format!(
        "/v1/assets/jacksboro/mesh?bbox={bbox}&resolution=65&format=obj"
    ))
    .await;
    assert_eq!(s, StatusCode::OK);
    let (s, h, b) = get(&format!(
        "/v1/assets/jacksboro/mesh?bbox={bbox}&resolution=60&max_error=5&format=obj"
    ))
    .await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    let adaptive = String::from_utf8(b).unwrap();
    let vertices = |text: &str| -> Vec<String> {
        text.lines()
            .filter(|l| l.starts_with("v "))
            .map(str::to_string)
            .collect()
    };
    let grid_vertices: std::collections::HashSet<String> = vertices(&obj).into_iter().collect();
    let adaptive_vertices = vertices(&adaptive);
    assert!(
        adaptive_vertices.len() < 65 * 65,
        "{}",
        adaptive_vertices.len()
    );
    assert!(adaptive_vertices.iter().all(|v| grid_vertices.contains(v)));
    let faces = adaptive.lines().filter(|l| l.starts_with("f ")).count();
    assert!(faces < 2 * 64 * 64, "{faces} triangles");
    let bound = |h: &axum::http::HeaderMap| -> f32 {
        h["x-error-bound"].to_str().unwrap().parse().unwrap()
    };
    assert!((bound(&h) - bound(&h_grid) - 5.0).abs() < 1e-3);
    for (uri, code) in [
        ("/v1/assets/camera/mesh", "not_terrain"),
        ("/v1/assets/jacksboro/mesh?resolution=1", "bad_resolution"),
        ("/v1/assets/jacksboro/mesh?format=stl", "bad_format"),
        ("/v1/assets/jacksboro/mesh?max_error=-1", "bad_max_error"),
        ("/v1/assets/jacksboro/mesh?max_error=NaN", "bad_max_error"),
        ("/v1/assets/fandisk/mesh?max_error=1", "bad_max_error"),
    ] {
        let (s, _, b) = get(uri).await;
        assert_eq!(s, StatusCode::BAD_REQUEST, "{uri}");
        assert_eq!(json(&b)["code"], code);
    }
}

/// The document lists every error code (the one list in `fractile-proto`), and a few that
/// answers carry here are among them.
#[tokio::test]
async fn the_document_lists_every_error_code() {
    let (_, _, b) = get("/v1/openapi.json").await;
    let doc = json(&b);
    let listed: Vec<&str> = doc["components"]["responses"]["Error"]["content"]["application/json"]
        ["schema"]["properties"]["code"]["enum"]
        .as_array()
        .expect("the codes")
        .iter()
        .map(|c| c.as_str().unwrap())
        .collect();
    let all: Vec<&str> = fractile_proto::ErrorCode::ALL
        .iter()
        .map(|c| c.as_str())
        .collect();
    assert_eq!(listed, all);
    for uri in [
        "/v1/assets/nope",
        "/v1/assets/camera/tiles/0/0/0.png?encoding=nope",
        "/nowhere",
    ] {
        let (_, _, b) = get(uri).await;
        let code = json(&b)["code"].as_str().unwrap().to_string();
        assert!(listed.contains(&code.as_str()), "{uri}: {code}");
    }
}

#[tokio::test]
async fn every_documented_path_is_routed() {
    let (s, _, b) = get("/v1/openapi.json").await;
    assert_eq!(s, StatusCode::OK);
    let doc = json(&b);
    assert_eq!(doc["openapi"], "3.1.0");
    let paths = doc["paths"].as_object().unwrap();
    assert!(paths.len() >= 13);
    for (path, ops) in paths {
        let uri = path
            .replace("{id}", "camera")
            .replace("{z}/{x}/{y}.{format}", "0/0/0.png")
            .replace("{coords}", "0.5,0.5");
        for (method, _) in ops
            .as_object()
            .unwrap()
            .iter()
            .filter(|(k, _)| *k != "parameters")
        {
            if method != "get" {
                continue; // writes are exercised by their own tests
            }
            let (s, _, body) = get(&uri).await;
            // An unrouted path is axum's bare 404; our handlers always explain themselves.
            assert!(
                !(s == StatusCode::NOT_FOUND && body.is_empty()),
                "{path} is documented but not routed"
            );
            assert_ne!(s, StatusCode::METHOD_NOT_ALLOWED, "{path}");
        }
    }
}

/// The other way: every route of the router (read from its source, `api/mod.rs`) is documented,
/// with every method it answers.
#[tokio::test]
async fn every_route_is_documented() {
    let (_, _, b) = get("/v1/openapi.json").await;
    let doc = json(&b);
    let src = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/api/mod.rs"),
    )
    .unwrap();
    let router = &src[src.find("fn router(").expect("the router")..];
    let router = &router[..router.find("\n}\n").expect("the router's end")];
    let mut routes = 0;
    for part in router.split(".route(").skip(1) {
        let path = part.split('"').nth(1).expect("a route's path");
        // Tile routes name their last segment {tile}: {y}.{format} in the document, or
        // {y}.terrain for Cesium terrain.
        let last = if path.contains("/terrain/") {
            "{y}.terrain"
        } else {
            "{y}.{format}"
        };
        let documented = path.replace("{tile}", last);
        let ops = doc["paths"][&documented]
            .as_object()
            .unwrap_or_else(|| panic!("route {path} is not documented"));
        // The methods the route's handler chain names, up to the next route.
        let chain = part.split(".route(").next().unwrap();
        for method in ["get", "put", "post", "delete"] {
            if chain.contains(&format!("{method}(")) || chain.contains(&format!(".{method}(")) {
                assert!(
                    ops.contains_key(method),
                    "{method} {path} is not documented"
                );
            }
        }
        routes += 1;
    }
    assert!(routes >= 16, "{routes} routes found");
    // Closed choices name what the server parses.
    let tile = &doc["paths"]["/v1/assets/{id}/tiles/{z}/{x}/{y}.{format}"]["get"]["parameters"];
    let backend = tile
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "backend")
        .unwrap();
    for name in backend["schema"]["enum"].as_array().unwrap() {
        let (s, _, _) = get(&format!(
            "/v1/assets/camera/tiles/0/0/0.png?backend={}",
            name.as_str().unwrap()
        ))
        .await;
        assert!(
            s == StatusCode::OK || s == StatusCode::BAD_REQUEST,
            "{name}: {s}"
        );
    }
}

/// A tile is cached and tagged by the request as checked, not as spelt: two spellings of the
/// same parameters are one ETag; other parameters another.
#[tokio::test]
async fn spellings_of_one_tile_share_its_etag() {
    let (x, y) = geo::lonlat_tile(12, -84.25, 36.6);
    let base = format!("/v1/assets/jacksboro/tiles/12/{x}/{y}.png");
    let tag = |h: &axum::http::HeaderMap| h[header::ETAG].to_str().unwrap().to_string();
    let mut tags = Vec::new();
    for q in [
        "colormap=gray&rescale=300,900&tolerance=1",
        "colormap=grey&rescale=300.0,900&tolerance=1.0",
    ] {
        let (s, h, _) = get(&format!("{base}?{q}")).await;
        assert_eq!(s, StatusCode::OK, "{q}");
        tags.push(tag(&h));
    }
    assert_eq!(tags[0], tags[1]);
    let (_, h, _) = get(&format!(
        "{base}?colormap=terrain&rescale=300,900&tolerance=1"
    ))
    .await;
    assert_ne!(tag(&h), tags[0]);
}

#[tokio::test]
async fn visual_tiles_with_colormap_and_hillshade() {
    let (x, y) = geo::lonlat_tile(12, -84.25, 36.6);
    let base = format!("/v1/assets/jacksboro/tiles/12/{x}/{y}.png");
    let (s, _, grey) = get(&base).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(
        image::load_from_memory(&grey).unwrap().color(),
        image::ColorType::L8
    );
    let (s, _, b) = get(&format!("{base}?colormap=terrain&hillshade=true")).await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    let shaded = image::load_from_memory(&b).unwrap().to_rgb8();
    let (_, _, b) = get(&format!("{base}?colormap=terrain")).await;
    let flat = image::load_from_memory(&b).unwrap().to_rgb8();
    // Shading darkens (never brightens) the ramp, and varies with the relief.
    let (mut darker, mut differ) = (0, 0);
    for (a, b) in shaded.pixels().zip(flat.pixels()) {
        darker += usize::from(a.0.iter().zip(b.0).all(|(s, f)| *s <= f));
        differ += usize::from(a.0 != b.0);
    }
    assert_eq!(darker, 256 * 256);
    assert!(differ > 256 * 256 / 2, "{differ}");
    // Seamless: the shaded tile's edge column continues into its eastern neighbour.
    let (_, _, b) = get(&format!(
        "/v1/assets/jacksboro/tiles/12/{}/{y}.png?hillshade=true",
        x + 1
    ))
    .await;
    let east = image::load_from_memory(&b).unwrap().to_rgb8();
    let (_, _, b) = get(&format!("{base}?hillshade=true")).await;
    let west = image::load_from_memory(&b).unwrap().to_rgb8();
    let seam: f32 = (0..256)
        .map(|j| (west.get_pixel(255, j).0[0] as f32 - east.get_pixel(0, j).0[0] as f32).abs())
        .sum::<f32>()
        / 256.0;
    let inner: f32 = (0..256)
        .map(|j| (west.get_pixel(254, j).0[0] as f32 - west.get_pixel(255, j).0[0] as f32).abs())
        .sum::<f32>()
        / 256.0;
    assert!(seam <= 2.0 * inner + 2.0, "seam {seam} vs inner {inner}");
    for (q, code) in [
        ("colormap=magma", "bad_colormap"),
        ("encoding=terrainrgb&hillshade=true", "bad_hillshade"),
    ] {
        let (s, _, b) = get(&format!("{base}?{q}")).await;
        assert_eq!(s, StatusCode::BAD_REQUEST);
        assert_eq!(json(&b)["code"], code);
    }
}

#[tokio::test]
async fn visual_tiles_are_transparent_outside_the_data() {
    // A zoom-10 tile that holds the whole DEM and much around it.
    let (x, y) = geo::lonlat_tile(10, -84.25, 36.6);
    let (s, _, b) = get(&format!(
        "/v1/assets/jacksboro/tiles/10/{x}/{y}.png?colormap=terrain"
    ))
    .await;
    assert_eq!(s, StatusCode::OK);
    let img = image::load_from_memory(&b).unwrap().to_rgba8();
    let transparent = img.pixels().filter(|p| p.0[3] == 0).count();
    let opaque = img.pixels().filter(|p| p.0[3] == 255).count();
    assert!(
        transparent > 0 && opaque > 0,
        "{transparent} transparent, {opaque} opaque"
    );
    assert_eq!(transparent + opaque, 256 * 256);
}

/// A tile that overlaps a small asset but where no pixel centre falls on it (jacksboro, a
/// fraction of a pixel at zooms 0 to 2) is a tile of nodata, not a 404: map clients then draw
/// those zooms. Tiles wholly outside stay 404.
#[tokio::test]
async fn tiles_overlapping_the_asset_in_any_part_answer_200() {
    for z in 0..=2u8 {
        let (x, y) = geo::lonlat_tile(z, -84.25, 36.6);
        let (s, _, b) = get(&format!("/v1/assets/jacksboro/tiles/{z}/{x}/{y}.png")).await;
        assert_eq!(
            s,
            StatusCode::OK,
            "zoom {z}: {}",
            String::from_utf8_lossy(&b)
        );
        let img = image::load_from_memory(&b).unwrap().to_rgba8();
        assert_eq!(img.dimensions(), (256, 256));
        let opaque = img.pixels().filter(|p| p.0[3] != 0).count();
        // At most the pixels whose centre lies on the asset (a handful at zoom 2).
        assert!(opaque <= 4, "zoom {z}: {opaque} opaque pixels");
        let (s, _, _) = get(&format!(
            "/v1/assets/jacksboro/tiles/{z}/{x}/{y}.png?encoding=terrainrgb"
        ))
        .await;
        assert_eq!(s, StatusCode::OK, "zoom {z} terrain-RGB");
    }
    // The tile across the world from it still has no part of it.
    let (x, y) = geo::lonlat_tile(2, 100.0, -40.0);
    let (s, _, b) = get(&format!("/v1/assets/jacksboro/tiles/2/{x}/{y}.png")).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    assert_eq!(json(&b)["code"], "outside");
}

/// Tiles of one coarse zoom share one discrete decode: the second tile that needs it is a hit
/// of the coarse cache (counted, and shown in /metrics), not a second decode.
#[tokio::test]
async fn coarse_tiles_share_their_decode_and_count_it() {
    state();
    // A state of its own over the same assets, so that its coarse cache starts empty.
    let dir = std::env::temp_dir().join(format!("fractile-http-{}", std::process::id()));
    let (store, _) = Store::open(&dir).unwrap();
    let st = Arc::new(AppState::new(store, "http://test".into()));
    let (x, y) = geo::lonlat_tile(9, -84.25, 36.6);
    // Two answers from one grid: the rescale changes the tile (and its cache key), not the grid.
    for rescale in ["", "&rescale=0,2000"] {
        let uri = format!("/v1/assets/jacksboro/tiles/9/{x}/{y}.png?iterations=7{rescale}");
        let (s, _) = call(&st, Request::get(uri).body(Body::empty()).unwrap()).await;
        assert_eq!(s, StatusCode::OK);
    }
    assert_eq!(st.coarse.len(), 1, "one grid for the zoom");
    let counts = st.coarse.counts();
    assert_eq!((counts.misses, counts.hits), (1, 1), "{counts:?}");
    // The counts reach /metrics (a counter the process shares with the other tests' states:
    // at least this state's).
    let (s, b) = call(&st, Request::get("/metrics").body(Body::empty()).unwrap()).await;
    assert_eq!(s, StatusCode::OK);
    let text = String::from_utf8(b).unwrap();
    for result in ["miss", "hit"] {
        let name = format!("fractile_coarse_cache_total{{result=\"{result}\"}} ");
        let n: f64 = text
            .lines()
            .find_map(|l| l.strip_prefix(&name))
            .map_or(0.0, |v| v.trim().parse().unwrap());
        assert!(n >= 1.0, "{result}: {text}");
    }
}

/// A fresh state (empty caches) over etopo20, a global DEM, encoded once per test run at 0.8
/// bits a cell.
fn etopo20_state() -> Arc<AppState> {
    static DIR: OnceLock<std::path::PathBuf> = OnceLock::new();
    let dir = DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("fractile-http-etopo-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let r = Raster::open(&data("etopo20.tif")).unwrap();
        let mut s = QuadtreeSettings {
            rate: RateMode::TargetBpp(0.8),
            ..QuadtreeSettings::default()
        };
        s.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(r.kind);
        let bytes = encode(&r, &s, &|_, _| {}).unwrap().bytes;
        std::fs::write(dir.join("etopo20.fra"), bytes).unwrap();
        dir
    });
    let (store, _) = Store::open(dir).unwrap();
    Arc::new(AppState::new(store, "http://test".into()))
}

/// A coarse grid that is a power-of-two shrink of one already cached (a band of latitude of
/// a zoom next to a finer band, or the same zoom in 256- and 512-pixel tiles) is derived from
/// it by block means instead of decoded again, and agrees with its own decode.
#[tokio::test]
async fn a_coarse_grid_derives_from_a_finer_one_cached() {
    async fn zoom0(st: &Arc<AppState>, size: u32) -> Vec<f32> {
        let req = Request::get(format!(
            "/v1/assets/etopo20/tiles/0/0/0.f32?tilesize={size}"
        ))
        .body(Body::empty())
        .unwrap();
        let (s, b) = call(st, req).await;
        assert_eq!(s, StatusCode::OK);
        b.chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect()
    }
    // etopo20 (1080 x 540) at zoom 0: a 256-pixel tile samples a grid of 270 columns, a
    // 512-pixel one a grid of 540.
    let decoded = zoom0(&etopo20_state(), 256).await;
    let st = etopo20_state();
    zoom0(&st, 512).await;
    let derived = zoom0(&st, 256).await;
    assert_eq!(st.coarse.len(), 2, "two grids");
    let metrics = String::from_utf8(get("/metrics").await.2).unwrap();
    assert!(
        metrics.contains("fractile_coarse_cache_total{result=\"derived\"}"),
        "{metrics}"
    );
    // The block means of the finer decode against the coarser decode: both approximate the
    // attractor's cell means, within a small part of the coding error.
    let rmse = st.store.get("etopo20").unwrap().asset.meta.stats.rmse as f32;
    let pairs = decoded.iter().zip(&derived).filter(|(a, _)| a.is_finite());
    let (mut sum, mut n, mut max) = (0.0f32, 0usize, 0.0f32);
    for (a, b) in pairs {
        sum += (a - b).abs();
        max = max.max((a - b).abs());
        n += 1;
    }
    let mean = sum / n as f32;
    eprintln!("derived against decoded: mean {mean} m, max {max} m, encoding RMSE {rmse} m");
    assert!(n > 30_000 && mean > 0.0, "{n} pixels, mean {mean}");
    assert!(mean < 0.25 * rmse, "mean {mean} m, encoding RMSE {rmse} m");
}

#[tokio::test]
async fn global_tiles_join_across_the_antimeridian() {
    // etopo20 spans all longitudes from -180: tile x = 0 and x = 2^z - 1 meet at +-180.
    let r = Raster::open(&data("etopo20.tif")).unwrap();
    let st = etopo20_state();
    for z in [3u8, 6] {
        let last = (1u32 << z) - 1;
        let y = (1u32 << z) / 2 - 1; // just north of the equator
        let tile = |x: u32| {
            let st = st.clone();
            async move {
                let req = Request::get(format!("/v1/assets/etopo20/tiles/{z}/{x}/{y}.f32"))
                    .body(Body::empty())
                    .unwrap();
                let (s, b) = call(&st, req).await;
                assert_eq!(s, StatusCode::OK);
                b.chunks_exact(4)
                    .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                    .collect::<Vec<f32>>()
            }
        };
        let (east_edge, west_edge) = (tile(last).await, tile(0).await);
        // No seam beyond what the data and the codec's error explain: the decoded jump across
        // +-180 against the source's own jump between its last and first columns, same rows.
        let a = st.store.get("etopo20").unwrap();
        let rmse = a.asset.meta.stats.rmse as f32;
        let place = a.placement.clone().unwrap();
        let [_, s, _, n] = geo::tile_bounds(z, 0, y);
        let rows: Vec<usize> = (0..r.height)
            .filter(|&j| {
                let lat = 90.0 - (j as f64 + 0.5) / 3.0;
                lat > s && lat < n
            })
            .collect();
        let src_jump = rows
            .iter()
            .map(|&j| (r.channels[0][j * r.width + r.width - 1] - r.channels[0][j * r.width]).abs())
            .sum::<f32>()
            / rows.len() as f32;
        let seam: Vec<f32> = (0..256)
            .map(|j| (east_edge[j * 256 + 255] - west_edge[j * 256]).abs())
            .collect();
        let mean = seam.iter().sum::<f32>() / 256.0;
        let mut inside_max = 0.0f32;
        for t in [&east_edge, &west_edge] {
            for j in 0..256 {
                for i in 0..255 {
                    inside_max = inside_max.max((t[j * 256 + i] - t[j * 256 + i + 1]).abs());
                }
            }
        }
        let seam_max = seam.iter().cloned().fold(0.0, f32::max);
        eprintln!(
            "z{z}: decoded jump across +-180 mean {mean} max {seam_max}; source jump {src_jump}; encoding RMSE {rmse}; inside max {inside_max}"
        );
        assert!(place.unit(180.0, 0.0).is_some() && place.unit(-180.0, 0.0).is_some());
        assert!(
            mean <= src_jump + 2.0 * rmse,
            "z{z}: decoded jump {mean} m vs the source's {src_jump} m + 2 x {rmse} m"
        );
        assert!(
            seam_max <= inside_max,
            "z{z}: jump across +-180 {seam_max} m, largest inside {inside_max} m"
        );
    }
}

#[test]
fn config_files_parse_and_reject_typos() {
    let dir = std::env::temp_dir().join(format!("fractile-config-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let good = dir.join("fractile.toml");
    std::fs::write(
        &good,
        "bind = \"127.0.0.1:9999\"\nmax_iterations = 20\ncache_control = \"public, max-age=60\"\ncoarse_cache_mib = 256\n",
    )
    .unwrap();
    let c = fractile_server::FileConfig::load(&good).unwrap();
    assert_eq!(c.bind.unwrap().port(), 9999);
    assert_eq!(c.max_iterations, Some(20));
    assert_eq!(c.coarse_cache_mib, Some(256));
    let bad = dir.join("typo.toml");
    std::fs::write(&bad, "max_iteration = 20\n").unwrap();
    let e = fractile_server::FileConfig::load(&bad)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("max_iteration") && e.contains("typo.toml"),
        "{e}"
    );
}

/// A response's `X-Convergence-Bound` (NaN when there is none).
fn convergence_bound(h: &axum::http::HeaderMap) -> f32 {
    h.get("x-convergence-bound")
        .and_then(|v| v.to_str().ok()?.parse().ok())
        .unwrap_or(f32::NAN)
}

/// The GPU backend (lavapipe in CI) answers tiles like the CPU, per request; a bad or
/// unavailable backend is a typed 400.
#[tokio::test]
async fn tiles_decode_alike_on_the_gpu_and_the_cpu() {
    state(); // writes the assets
    let dir = std::env::temp_dir().join(format!("fractile-http-{}", std::process::id()));
    let (store, _) = Store::open(&dir).unwrap();
    let mut st = AppState::new(store, "http://test".into());
    let gpu = fractile_server::GpuBackend::open(64 << 20)
        .unwrap_or_else(|e| panic!("{e} (install mesa-vulkan-drivers)"));
    st.gpu = Some(Arc::new(gpu));
    let st = Arc::new(st);
    // A zoom-15 tile inside the DEM: finer than the source, so every pixel is a point chain.
    let (lon, lat, z) = (-84.25f64, 36.6f64, 15u32);
    let n = f64::from(1u32 << z);
    let x = ((lon + 180.0) / 360.0 * n) as u32;
    let r = lat.to_radians();
    let y = ((1.0 - (r.tan() + 1.0 / r.cos()).ln() / std::f64::consts::PI) / 2.0 * n) as u32;
    let fetch = |backend: &str| {
        let st = st.clone();
        let uri =
            format!("/v1/assets/jacksboro/tiles/{z}/{x}/{y}.f32?iterations=12&backend={backend}");
        async move {
            let resp = fractile_server::app(st)
                .oneshot(Request::get(uri).body(Body::empty()).unwrap())
                .await
                .unwrap();
            let status = resp.status();
            let bound = convergence_bound(resp.headers());
            let body = resp
                .into_body()
                .collect()
                .await
                .unwrap()
                .to_bytes()
                .to_vec();
            (status, body, bound)
        }
    };
    let (s, cpu, cpu_bound) = fetch("cpu").await;
    assert_eq!(s, StatusCode::OK);
    // The tile cache would answer the second request from the first: a different key is needed,
    // and the tolerance is part of it.
    let uri = format!(
        "/v1/assets/jacksboro/tiles/{z}/{x}/{y}.f32?iterations=12&tolerance=0.000001&backend=gpu"
    );
    let resp = fractile_server::app(st.clone())
        .oneshot(Request::get(&uri).body(Body::empty()).unwrap())
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    // The device's one bound for the tile is the CPU's largest point bound (the same chains).
    let gpu_bound = convergence_bound(resp.headers());
    assert!(
        cpu_bound > 0.0 && (gpu_bound - cpu_bound).abs() <= 1e-3 * cpu_bound,
        "convergence bounds: GPU {gpu_bound} m, CPU {cpu_bound} m"
    );
    let gpu = resp
        .into_body()
        .collect()
        .await
        .unwrap()
        .to_bytes()
        .to_vec();
    let f = |b: &[u8]| -> Vec<f32> {
        b.chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect()
    };
    let (a, b) = (f(&cpu), f(&gpu));
    assert_eq!(a.len(), 256 * 256);
    // 1e-4 of the value range (236..1076 m), plus the 1e-6 m tolerance the GPU request used.
    let worst = a
        .iter()
        .zip(&b)
        .map(|(p, q)| (p - q).abs())
        .fold(0.0f32, f32::max);
    assert!(worst <= 0.084, "worst difference {worst} m");
    // The GPU tile went through the device's rounds, which /metrics reports.
    let resp = fractile_server::app(st.clone())
        .oneshot(Request::get("/metrics").body(Body::empty()).unwrap())
        .await
        .unwrap();
    let text = String::from_utf8(
        resp.into_body()
            .collect()
            .await
            .unwrap()
            .to_bytes()
            .to_vec(),
    )
    .unwrap();
    let counter = |name: &str| -> u64 {
        text.lines()
            .find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
            .unwrap_or_else(|| panic!("{name} in /metrics"))
    };
    let (rounds, grids) = (
        counter("fractile_gpu_rounds_total"),
        counter("fractile_gpu_round_grids_total"),
    );
    assert!(
        rounds >= 1 && grids >= rounds,
        "{rounds} rounds, {grids} grids"
    );
    // Its operator was uploaded, once.
    assert_eq!(
        counter(r#"fractile_gpu_uploads_total{result="resident"}"#),
        1
    );
    // A batch of points, on each backend.
    let pts: Vec<[f64; 2]> = (0..3000)
        .map(|i| {
            let (a, b) = ((i as f64 * 0.618).fract(), (i as f64 * 0.377).fract());
            [-84.40 + 0.3 * a, 36.46 + 0.25 * b]
        })
        .collect();
    let body = serde_json::to_vec(&serde_json::json!({"points": pts, "iterations": 12})).unwrap();
    let mut answers = Vec::new();
    for backend in ["cpu", "gpu"] {
        let req = Request::post(format!("/v1/assets/jacksboro/points?backend={backend}"))
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(body.clone()))
            .unwrap();
        let resp = fractile_server::app(st.clone()).oneshot(req).await.unwrap();
        assert_eq!(resp.status(), StatusCode::OK);
        let v = json(&resp.into_body().collect().await.unwrap().to_bytes());
        let heights: Vec<f64> = v["results"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r["values"][0].as_f64().unwrap())
            .collect();
        answers.push(heights);
    }
    assert_eq!(answers[0].len(), 3000);
    let worst = answers[0]
        .iter()
        .zip(&answers[1])
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(worst <= 0.084, "points: worst difference {worst} m");
    let (s, body, _) = fetch("quantum").await;
    assert_eq!(
        (s, json(&body)["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("bad_backend"))
    );
    // The shared state has no GPU: asking for one is refused, not silently served by the CPU.
    let (s, _, body) = get(&format!(
        "/v1/assets/jacksboro/tiles/{z}/{x}/{y}.f32?backend=gpu"
    ))
    .await;
    assert_eq!(
        (s, json(&body)["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("gpu_unavailable"))
    );
    // A volume's mesh on each backend: the same triangles, vertices within rounding.
    let mesh_of = |backend: &'static str| {
        let st = st.clone();
        async move {
            let uri = format!(
                "/v1/assets/fandisk/mesh?format=obj&resolution=48&iterations=12&backend={backend}"
            );
            let resp = fractile_server::app(st)
                .oneshot(Request::get(uri).body(Body::empty()).unwrap())
                .await
                .unwrap();
            assert_eq!(resp.status(), StatusCode::OK);
            let text = String::from_utf8(
                resp.into_body()
                    .collect()
                    .await
                    .unwrap()
                    .to_bytes()
                    .to_vec(),
            )
            .unwrap();
            text.lines()
                .filter_map(|l| l.strip_prefix("v "))
                .map(|l| {
                    l.split(' ')
                        .map(|x| x.parse::<f32>().unwrap())
                        .collect::<Vec<_>>()
                })
                .collect::<Vec<_>>()
        }
    };
    let (vc, vg) = (mesh_of("cpu").await, mesh_of("gpu").await);
    // A sample within rounding of the surface may fall on either side on either device and
    // change a few triangles: then only the counts can be compared.
    let (a, b) = (vc.len() as f64, vg.len() as f64);
    assert!((a - b).abs() <= 0.005 * a, "{a} vs {b} vertices");
    let worst = if vc.len() != vg.len() {
        0.0
    } else {
        vc.iter()
            .zip(&vg)
            .flat_map(|(a, b)| a.iter().zip(b).map(|(x, y)| (x - y).abs()))
            .fold(0.0f32, f32::max)
    };
    assert!(worst < 1e-3, "vertex difference {worst}");
}

/// Tiles that want an operator the GPU does not hold yet wait for one upload, and an operator
/// it refuses (here: tables over the whole `gpu_memory_mib`) is decoded on the CPU without the
/// device being asked again: each attempt flattens the operator anew (0.1 s of a core for a
/// projected etopo20).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gpu_uploads_happen_once_and_refusals_are_remembered() {
    state(); // writes the assets
    let dir = std::env::temp_dir().join(format!("fractile-http-{}", std::process::id()));
    for (memory, expected) in [(4u64 << 10, (0, 1)), (64 << 20, (1, 0))] {
        let (store, _) = Store::open(&dir).unwrap();
        let mut st = AppState::new(store, "http://test".into());
        let gpu = Arc::new(
            fractile_server::GpuBackend::open(memory)
                .unwrap_or_else(|e| panic!("{e} (install mesa-vulkan-drivers)")),
        );
        st.gpu = Some(gpu.clone());
        let st = Arc::new(st);
        // Twelve zoom-15 tiles of the DEM, none cached: eight at once, then four one by one.
        let tile = |k: u32| {
            let st = st.clone();
            async move {
                let uri = format!(
                    "/v1/assets/jacksboro/tiles/15/{}/12810.f32?iterations=12&backend=gpu",
                    8700 + k
                );
                let resp = fractile_server::app(st)
                    .oneshot(Request::get(uri).body(Body::empty()).unwrap())
                    .await
                    .unwrap();
                let bound = convergence_bound(resp.headers());
                (resp.status(), bound)
            }
        };
        let mut answers = futures_util::future::join_all((0..8).map(tile)).await;
        for k in 8..12 {
            answers.push(tile(k).await);
        }
        for (k, (status, bound)) in answers.iter().enumerate() {
            assert_eq!(
                *status,
                StatusCode::OK,
                "tile {k}, {memory} bytes of GPU memory"
            );
            assert!(bound.is_finite(), "tile {k}: a convergence bound");
        }
        assert_eq!(
            gpu.uploads(),
            expected,
            "(uploaded, refused) with {memory} bytes of GPU memory"
        );
    }
}

#[tokio::test]
async fn volume_meshes_points_and_refusals() {
    let (s, _, b) = get("/v1/assets/fandisk").await;
    assert_eq!(s, StatusCode::OK);
    let m = json(&b);
    assert_eq!(m["kind"], "Volume");
    assert_eq!(m["codec"], "ifs3d-octree");
    // The whole surface as OBJ: closed (every edge in two triangles), with its bound.
    let (s, h, b) = get("/v1/assets/fandisk/mesh?format=obj&resolution=40").await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    // A volume holds no source-error map: its bound is against the attractor only.
    assert!(
        h["x-convergence-bound"]
            .to_str()
            .unwrap()
            .parse::<f32>()
            .unwrap()
            >= 0.0
    );
    assert!(!h.contains_key("x-error-bound"));
    let text = String::from_utf8(b).unwrap();
    let verts: Vec<[f64; 3]> = text
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| {
            let v: Vec<f64> = l.split(' ').map(|x| x.parse().unwrap()).collect();
            [v[0], v[1], v[2]]
        })
        .collect();
    let faces: Vec<[usize; 3]> = text
        .lines()
        .filter_map(|l| l.strip_prefix("f "))
        .map(|l| {
            let v: Vec<usize> = l
                .split(' ')
                .map(|x| x.split('/').next().unwrap().parse().unwrap())
                .collect();
            [v[0], v[1], v[2]]
        })
        .collect();
    assert!(faces.len() > 1000 && text.contains("\nvn "));
    let mut uses = std::collections::HashMap::new();
    for f in &faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            *uses.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    assert!(uses.values().all(|&u| u == 2));
    // The vertices lie on the source mesh's surface: near some source vertex (fandisk's
    // vertices are dense), within a few voxels of 40.
    let src = fractile_codec::mesh::Mesh::read(&data("mesh/fandisk.off")).unwrap();
    let (lo, hi) = src.bounds();
    let diag = (0..3)
        .map(|k| ((hi[k] - lo[k]) as f64).powi(2))
        .sum::<f64>()
        .sqrt();
    for v in verts.iter().step_by(301) {
        let near = src
            .positions
            .iter()
            .map(|p| {
                (0..3)
                    .map(|k| (p[k] as f64 - v[k]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .fold(f64::INFINITY, f64::min);
        assert!(near < 0.06 * diag, "{v:?} is {near} from the source");
    }
    // A box of it, as GLB.
    let c: Vec<f64> = (0..3).map(|k| 0.5 * (lo[k] + hi[k]) as f64).collect();
    let bbox = format!("{},{},{},{},{},{}", lo[0], lo[1], lo[2], c[0], c[1], c[2]);
    let (s, h, b) = get(&format!(
        "/v1/assets/fandisk/mesh?bbox={bbox}&resolution=32"
    ))
    .await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(h[header::CONTENT_TYPE], "model/gltf-binary");
    assert_eq!(&b[..4], b"glTF");
    // The signed distance at a point of the surface is near zero; far in the grid, the band.
    let p = src.positions[100];
    let (s, _, b) = get(&format!(
        "/v1/assets/fandisk/point?x={}&y={}&z={}",
        p[0], p[1], p[2]
    ))
    .await;
    assert_eq!(s, StatusCode::OK);
    let r = json(&b);
    let band = m["value_range"][1].as_f64().unwrap();
    assert!(r["distance"].as_f64().unwrap().abs() < 0.3 * band, "{r}");
    assert!(r["error_bound"].as_f64().unwrap() >= 0.0);
    // Refusals: 2D requests, a 2D bbox, a huge box, a point without z, outside the grid.
    for (uri, code) in [
        ("/v1/assets/fandisk/tiles/0/0/0.png", "volume_asset"),
        ("/v1/assets/fandisk/tilejson.json", "volume_asset"),
        ("/v1/assets/fandisk/mesh?bbox=0,0,1,1", "bad_bbox"),
        ("/v1/assets/fandisk/mesh?resolution=400", "too_many_samples"),
        (
            "/v1/assets/fandisk/mesh?resolution=100000",
            "bad_resolution",
        ),
        ("/v1/assets/fandisk/point?x=0&y=0", "bad_point"),
        ("/v1/assets/jacksboro/point?x=0.5&y=0.5&z=1", "bad_point"),
    ] {
        let (s, _, b) = get(uri).await;
        assert_eq!(s, StatusCode::BAD_REQUEST, "{uri}");
        assert_eq!(json(&b)["code"], code, "{uri}");
    }
    let (s, _, b) = get("/v1/assets/fandisk/point?x=1e9&y=0&z=0").await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    assert_eq!(json(&b)["code"], "outside");
}

#[tokio::test]
async fn curves_as_geojson_at_any_level_and_deformed() {
    let text = std::fs::read_to_string(data("curve/coast5.geojson")).unwrap();
    let source = fractile_codec::codecs::curve::geojson::read(&text).unwrap();
    let (st, hd, body) = get("/v1/assets/coast/curve").await;
    assert_eq!(st, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    assert_eq!(hd[header::CONTENT_TYPE], "application/geo+json");
    let doc = json(&body);
    let features = doc["features"].as_array().unwrap();
    assert_eq!(features.len(), source.len(), "one feature per input ring");
    let finest = doc["fractile"]["finest_level"].as_u64().unwrap();
    let bound = doc["fractile"]["error_bound"].as_f64().unwrap();
    // The tolerance, stored as f32 rounded up.
    assert!(bound <= 0.009 * (1.0 + 1e-6), "finest bound {bound}");
    for (f, l) in features.iter().zip(&source) {
        let pts = f["geometry"]["coordinates"].as_array().unwrap();
        // One point per input vertex, ring closed, the whole line within the bound
        // (Hausdorff, measured every tolerance/16 along segments).
        assert_eq!(pts.len(), l.points.len() + 1);
        let pts: Vec<[f64; 2]> = pts
            .iter()
            .map(|p| [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()])
            .collect();
        let mut src = l.points.clone();
        src.push(src[0]);
        let h = fractile_codec::codecs::curve::hausdorff(
            fractile_codec::codecs::curve::Metric::Sphere,
            &src,
            &pts,
            0.009 / 16.0,
        );
        assert!(h <= bound, "Hausdorff {h} over {bound}");
    }
    // Coarser levels have fewer points and larger bounds; deeper ones more points.
    let count = |doc: &serde_json::Value| -> usize {
        doc["features"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["geometry"]["coordinates"].as_array().unwrap().len())
            .sum()
    };
    let (_, _, coarse) = get(&format!("/v1/assets/coast/curve?level={}", finest - 2)).await;
    let coarse = json(&coarse);
    assert!(count(&coarse) < count(&doc) / 3);
    assert!(coarse["fractile"]["error_bound"].as_f64().unwrap() > bound);
    let (_, _, deep) = get(&format!("/v1/assets/coast/curve?level={}", finest + 1)).await;
    assert!(count(&json(&deep)) > count(&doc) * 3 / 2);
    // Control points, then a global deformation by a translation: the curve moves with them.
    let (_, _, ctrl) = get("/v1/assets/coast/curve?control=true").await;
    let ctrl = json(&ctrl);
    let ring0: Vec<[f64; 2]> = ctrl["features"][0]["geometry"]["coordinates"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| [p[0].as_f64().unwrap() + 1.0, p[1].as_f64().unwrap() - 0.5])
        .collect();
    let req =
        serde_json::json!({"deformations": [{"type": "control", "ring": 0, "points": ring0}]});
    let (st, body) = call(
        &state(),
        Request::post("/v1/assets/coast/curve/deform")
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(req.to_string()))
            .unwrap(),
    )
    .await;
    assert_eq!(st, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    let moved = json(&body);
    let a = features[0]["geometry"]["coordinates"].as_array().unwrap();
    let b = moved["features"][0]["geometry"]["coordinates"]
        .as_array()
        .unwrap();
    assert_eq!(a.len(), b.len());
    for (p, q) in a.iter().zip(b) {
        assert!((q[0].as_f64().unwrap() - p[0].as_f64().unwrap() - 1.0).abs() < 1e-9);
        assert!((q[1].as_f64().unwrap() - p[1].as_f64().unwrap() + 0.5).abs() < 1e-9);
    }
    // The stored asset is unchanged (stateless).
    let (_, _, again) = get("/v1/assets/coast/curve").await;
    assert_eq!(json(&again), doc);
    // Refusals: a huge level, a tile of a curve asset, a bad deformation.
    let (st, _, body) = get("/v1/assets/coast/curve?level=60").await;
    assert_eq!(
        (st, json(&body)["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("too_many_points"))
    );
    let (st, _, body) = get("/v1/assets/coast/tiles/0/0/0.png").await;
    assert_eq!(
        (st, json(&body)["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("curve_asset"))
    );
    let (st, _, body) = get("/v1/assets/camera/curve").await;
    assert_eq!(
        (st, json(&body)["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("not_curve"))
    );
    let bad = serde_json::json!({"deformations": [{"type": "local", "ring": 9, "level": 1, "index": 0, "to": [0, 0]}]});
    let (st, body) = call(
        &state(),
        Request::post("/v1/assets/coast/curve/deform")
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(bad.to_string()))
            .unwrap(),
    )
    .await;
    assert_eq!(
        (st, json(&body)["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("bad_deformation"))
    );
}

#[tokio::test]
async fn coarse_tiles_share_one_discrete_decode_and_answer_as_without_it() {
    // A fresh state over the shared assets, so that its caches start empty.
    state();
    let dir = std::env::temp_dir().join(format!("fractile-http-{}", std::process::id()));
    let (store, _) = Store::open(&dir).unwrap();
    let st = Arc::new(AppState::new(store, "http://test".into()));
    let a = st.store.get("jacksboro").unwrap();
    let [w, s, e, n] = a.placement.as_ref().unwrap().bounds();
    // Zoom 10: a pixel is about 120 m here, coarser than the source, so tiles are filtered.
    let z = 10u8;
    let first = geo::lonlat_tile(z, w + 0.01, n - 0.01);
    let last = geo::lonlat_tile(z, e - 0.01, s + 0.01);
    assert_ne!(first, last, "the asset spans more than one zoom-10 tile");
    for (k, (x, y)) in [first, last].into_iter().enumerate() {
        let req = Request::get(format!(
            "/v1/assets/jacksboro/tiles/{z}/{x}/{y}.f32?iterations=12"
        ))
        .body(Body::empty())
        .unwrap();
        let (status, body) = call(&st, req).await;
        assert_eq!(status, StatusCode::OK);
        // Both tiles sample the one grid decoded for the first.
        assert_eq!(st.coarse.len(), 1, "after tile {k}");
        // And they answer what the codec answers with no cache in between.
        let grid = geo::tile_pixels(a.placement.as_ref(), z, x, y, 256, 0);
        let served: Vec<f32> = body
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        let (direct, _) = a.asset.sample(&grid, 12, 0.0);
        assert_eq!(served.len(), direct[0].len());
        let same = served
            .iter()
            .zip(&direct[0])
            .all(|(p, q)| p == q || (p.is_nan() && q.is_nan()));
        assert!(same, "tile {k} differs from the uncached decode");
    }
}

/// An f32 tile or region as floats.
fn floats(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

/// RMS difference of two rasters where both have data, and how many pixels that is.
fn rms_where_both(a: &[f32], b: &[f32]) -> (f64, usize) {
    let d: Vec<f64> = a
        .iter()
        .zip(b)
        .filter(|(p, q)| p.is_finite() && q.is_finite())
        .map(|(p, q)| (*p as f64 - *q as f64).powi(2))
        .collect();
    (
        (d.iter().sum::<f64>() / d.len().max(1) as f64).sqrt(),
        d.len(),
    )
}

#[tokio::test]
async fn projected_assets_are_reprojected_to_lon_lat_and_web_mercator() {
    // jacksboro-utm is jacksboro warped onto a 90 m UTM 16N grid by GDAL (testdata/README.md),
    // an implementation independent of ours: served in lon/lat and Web Mercator, both assets
    // must show the same terrain at the same places.
    let (s, _, b) = get("/v1/assets/jacksboro-utm").await;
    assert_eq!(s, StatusCode::OK);
    let info = json(&b);
    assert_eq!(info["georeferenced"], true);
    assert_eq!(info["epsg"], 32616);
    // Its lon/lat box from gdalinfo's corner coordinates (degrees, minutes, seconds).
    let dms = |d: f64, m: f64, s: f64| d.signum() * (d.abs() + m / 60.0 + s / 3600.0);
    let expected = [
        dms(-84.0, 25.0, 23.87),
        dms(36.0, 26.0, 18.65),
        dms(-84.0, 4.0, 1.65),
        dms(36.0, 44.0, 26.48),
    ];
    for (k, e) in expected.iter().enumerate() {
        let got = info["bounds"][k].as_f64().unwrap();
        assert!((got - e).abs() < 1e-4, "bound {k}: {got} vs {e}");
    }
    // The same tile of both assets: heights agree to the encodings' and the warp's errors,
    // far better than the same tile against itself shifted 8 pixels (about 120 m) east.
    let z = 13;
    let (x, y) = geo::lonlat_tile(z, -84.25, 36.6);
    let tile = |id: &str| format!("/v1/assets/{id}/tiles/{z}/{x}/{y}.f32?iterations=12");
    let (s1, _, geo_tile) = get(&tile("jacksboro")).await;
    let (s2, _, utm_tile) = get(&tile("jacksboro-utm")).await;
    assert_eq!((s1, s2), (StatusCode::OK, StatusCode::OK));
    let (g, u) = (floats(&geo_tile), floats(&utm_tile));
    let (rms, n) = rms_where_both(&g, &u);
    assert!(n > 60_000, "{n} pixels on both");
    let shifted: Vec<f32> = (0..256 * 256)
        .map(|k| if k % 256 < 248 { g[k + 8] } else { f32::NAN })
        .collect();
    let (control, _) = rms_where_both(&shifted, &u);
    eprintln!("tile: rms {rms} m, shifted 8 px {control} m");
    assert!(rms < 12.0 && rms < 0.4 * control, "{rms} m vs {control} m");
    // Points, in lon/lat like every georeferenced asset.
    let pts: Vec<[f64; 2]> = (0..100)
        .map(|k| {
            [
                -84.38 + 0.28 * (k % 10) as f64 / 9.0,
                36.47 + 0.24 * (k / 10) as f64 / 9.0,
            ]
        })
        .collect();
    let body = serde_json::json!({"points": pts, "iterations": 14}).to_string();
    let heights = |id: &str| {
        let req = Request::post(format!("/v1/assets/{id}/points"))
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(body.clone()))
            .unwrap();
        async move {
            let (s, _, b) = send(req).await;
            assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
            json(&b)["results"]
                .as_array()
                .unwrap()
                .iter()
                .map(|r| r["values"][0].as_f64().unwrap_or(f64::NAN) as f32)
                .collect::<Vec<f32>>()
        }
    };
    let (g, u) = (heights("jacksboro").await, heights("jacksboro-utm").await);
    let (rms, n) = rms_where_both(&g, &u);
    eprintln!("points: rms {rms} m over {n}");
    assert!(n == 100 && rms < 15.0, "{rms} m over {n} points");
    // A region (north-up lon/lat box) and an adaptive mesh of it.
    let region = |id: &str| {
        format!("/v1/assets/{id}/region?bbox=-84.3,36.5,-84.2,36.6&width=96&height=96&format=f32")
    };
    let (_, _, g) = get(&region("jacksboro")).await;
    let (s, _, u) = get(&region("jacksboro-utm")).await;
    assert_eq!(s, StatusCode::OK);
    let (rms, n) = rms_where_both(&floats(&g), &floats(&u));
    assert!(n == 96 * 96 && rms < 12.0, "region: {rms} m over {n}");
    // As a GeoTIFF: in lon/lat (EPSG:4326), the box's georeference, not the asset's UTM.
    let (s, _, b) = get(
        "/v1/assets/jacksboro-utm/region?bbox=-84.3,36.5,-84.2,36.6&width=50&height=40&format=tif",
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    let path = std::env::temp_dir().join(format!("fractile-utm-region-{}.tif", std::process::id()));
    std::fs::write(&path, &b).unwrap();
    let r = Raster::open(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    let g = r.georef.unwrap();
    assert_eq!(g.epsg, Some(4326));
    assert!((g.origin[0] + 84.3).abs() < 1e-9 && (g.origin[1] - 36.6).abs() < 1e-9);
    let (s, h, _) =
        get("/v1/assets/jacksboro-utm/mesh?bbox=-84.3,36.5,-84.2,36.6&resolution=65&max_error=5")
            .await;
    assert_eq!(s, StatusCode::OK);
    assert!(h.contains_key("x-error-bound"));
    // Outside the grid but inside its lon/lat box: the rotated frame leaves corners empty.
    let [w, _, _, n] = expected;
    let (s, _, _) = get(&format!(
        "/v1/assets/jacksboro-utm/point/{},{}",
        w + 0.001,
        n - 0.001
    ))
    .await;
    assert_eq!(s, StatusCode::NOT_FOUND);
}

/// An asset of format version 4 (before source-error maps) still serves: its answers carry a
/// convergence bound and say nothing about the source (`error_bound: null`, no
/// `X-Error-Bound`), while a version-5 asset's do.
#[tokio::test]
async fn assets_without_a_source_error_map_answer_no_error_bound() {
    let (st, new) = writable(Some("old-assets"), 1 << 20);
    let old = std::fs::read(data("golden/v4-quadtree-jacksboro-utm.fra")).unwrap();
    let req = |uri: &str, bytes: &[u8]| {
        Request::put(uri)
            .header(header::AUTHORIZATION, "Bearer old-assets")
            .body(Body::from(bytes.to_vec()))
            .unwrap()
    };
    let (s, b) = call(&st, req("/v1/assets/old", &old)).await;
    assert_eq!(s, StatusCode::CREATED, "{}", String::from_utf8_lossy(&b));
    let get = |uri: &str| Request::get(uri).body(Body::empty()).unwrap();
    let (s, b) = call(&st, get("/v1/assets/old/point/-84.25,36.6")).await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    let p = json(&b);
    assert!(p["error_bound"].is_null(), "{p}");
    assert!(p["convergence_bound"].as_f64().unwrap() >= 0.0, "{p}");
    let resp = fractile_server::app(st.clone())
        .oneshot(get(
            "/v1/assets/old/tiles/12/1089/1599.png?encoding=terrainrgb",
        ))
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    assert!(resp.headers().contains_key("x-convergence-bound"));
    assert!(!resp.headers().contains_key("x-error-bound"));
    // A version-5 asset (topobathy, encoded by this build) has a map.
    let (s, _) = call(&st, req("/v1/assets/topo", &new)).await;
    assert_eq!(s, StatusCode::CREATED);
    let (s, b) = call(&st, get("/v1/assets/topo/point/-125.5,49.5")).await;
    assert_eq!(s, StatusCode::OK);
    let p = json(&b);
    assert!(
        p["error_bound"].as_f64().unwrap() >= p["convergence_bound"].as_f64().unwrap(),
        "{p}"
    );
}

/// A projected asset (issue 29) uploaded and served as any other: points at the source's cell
/// centres within their `error_bound`, which is the encoder's promise there, and tiles.
#[tokio::test]
async fn projected_assets_serve_points_within_their_promise_and_tiles() {
    use fractile_codec::codecs::projected::ProjectedSettings;
    let (st, _) = writable(Some("p"), 1 << 22);
    let src = Raster::open(&data("jacksboro.tif")).unwrap();
    let settings = ProjectedSettings {
        max_error: Some(5.0),
        ..Default::default()
    };
    let enc = fractile_codec::encode(&src, &settings, &|_, _| {}).unwrap();
    let put = Request::put("/v1/assets/jp")
        .header(header::AUTHORIZATION, "Bearer p")
        .body(Body::from(enc.bytes.clone()))
        .unwrap();
    let (s, b) = call(&st, put).await;
    assert_eq!(s, StatusCode::CREATED, "{}", String::from_utf8_lossy(&b));
    assert_eq!(json(&b)["codec"], "projected");
    let g = enc.asset.meta.georef.clone().unwrap();
    let (mut pts, mut truth) = (Vec::new(), Vec::new());
    for j in (0..src.height).step_by(11) {
        for i in (0..src.width).step_by(13) {
            pts.push([
                g.origin[0] + (i as f64 + 0.5) * g.pixel_size[0],
                g.origin[1] + (j as f64 + 0.5) * g.pixel_size[1],
            ]);
            truth.push(f64::from(src.channels[0][j * src.width + i]));
        }
    }
    let body = serde_json::json!({"points": pts, "iterations": 30}).to_string();
    let req = Request::post("/v1/assets/jp/points")
        .header(header::CONTENT_TYPE, "application/json")
        .body(Body::from(body))
        .unwrap();
    let (s, b) = call(&st, req).await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    let r = json(&b);
    for (res, t) in r["results"].as_array().unwrap().iter().zip(&truth) {
        let (v, bound) = (
            res["values"][0].as_f64().unwrap(),
            res["error_bound"].as_f64().unwrap(),
        );
        assert!((v - t).abs() <= bound, "{v} for {t}, bound {bound}");
        assert!(bound < 5.1, "the promise bounds cell centres: {bound}");
    }
    let (x, y) = geo::lonlat_tile(12, -84.25, 36.6);
    let req = Request::get(format!(
        "/v1/assets/jp/tiles/12/{x}/{y}.png?encoding=terrainrgb"
    ))
    .body(Body::empty())
    .unwrap();
    let (s, b) = call(&st, req).await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    let img = image::load_from_memory(&b).unwrap().to_rgb8();
    let heights: Vec<f64> = img.pixels().map(|p| terrain_rgb(p.0)).collect();
    let (lo, hi) = heights
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &h| (a.min(h), b.max(h)));
    // jacksboro's relief is several hundred metres: a tile of it is not flat.
    assert!(hi - lo > 50.0, "tile heights {lo}..{hi}");
}

/// `GET /v1/assets/{id}/file`: the file as stored, whole or by one byte range, for clients that
/// decode by themselves; ranges that cannot be served are 416 `bad_range`.
#[tokio::test]
async fn asset_files_are_served_whole_and_by_range() {
    state();
    let dir = std::env::temp_dir().join(format!("fractile-http-{}", std::process::id()));
    let file = std::fs::read(dir.join("jacksboro.fra")).unwrap();
    let (s, h, b) = get("/v1/assets/jacksboro/file").await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(b, file, "the whole file, as stored");
    assert_eq!(h["accept-ranges"], "bytes");
    let (s, h, b) = send(
        Request::get("/v1/assets/jacksboro/file")
            .header("Range", "bytes=10-99")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::PARTIAL_CONTENT);
    assert_eq!(b, &file[10..100]);
    assert_eq!(
        h["content-range"],
        format!("bytes 10-99/{}", file.len()).as_str()
    );
    // The last bytes, by suffix.
    let (s, _, b) = send(
        Request::get("/v1/assets/jacksboro/file")
            .header("Range", "bytes=-4")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::PARTIAL_CONTENT);
    assert_eq!(b, &file[file.len() - 4..]);
    for bad in [
        format!("bytes={}-", file.len() + 10),
        "bytes=0-1,5-9".to_string(),
        "lines=1-2".to_string(),
    ] {
        let (s, _, b) = send(
            Request::get("/v1/assets/jacksboro/file")
                .header("Range", bad.as_str())
                .body(Body::empty())
                .unwrap(),
        )
        .await;
        assert_eq!(s, StatusCode::RANGE_NOT_SATISFIABLE, "{bad}");
        assert_eq!(json(&b)["code"], "bad_range", "{bad}");
    }
    let (s, _, b) = get("/v1/assets/nothing/file").await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    assert_eq!(json(&b)["code"], "unknown_asset");
}
