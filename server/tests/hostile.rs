//! Hostile files and clients (issue 35): uploads are authorised before their bodies are read,
//! concurrent writers of one id leave the file and the served asset the same version, a folder
//! of crafted files starts, stale temporary files and links are not served, work that nobody
//! waits for stops, and connections that never finish their headers are closed.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::http::{Request, StatusCode, header};
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

fn fresh_dir(tag: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("fractile-hostile-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Two different real assets (camera at two rates), so concurrent writers are told apart.
fn two_assets() -> (Vec<u8>, Vec<u8>) {
    let r = Raster::open(&data("camera.png")).unwrap();
    let at = |bpp| {
        let s = QuadtreeSettings {
            rate: RateMode::TargetBpp(bpp),
            ..QuadtreeSettings::at_speed(4).unwrap()
        };
        encode(&r, &s, &|_, _| {}).unwrap().bytes
    };
    (at(0.2), at(0.4))
}

async fn send(state: &Arc<AppState>, req: Request<Body>) -> (StatusCode, Vec<u8>) {
    let resp = fractile_server::app(state.clone())
        .oneshot(req)
        .await
        .unwrap();
    let status = resp.status();
    let body = resp
        .into_body()
        .collect()
        .await
        .unwrap()
        .to_bytes()
        .to_vec();
    (status, body)
}

fn crc_tail(bytes: &[u8]) -> u32 {
    u32::from_le_bytes(bytes[bytes.len() - 4..].try_into().unwrap())
}

/// A body that counts what is read of it: 64 MiB in 1 MiB chunks, made only when asked for.
fn counted_body(read: Arc<AtomicUsize>) -> Body {
    let chunks = (0..64).map(move |_| {
        read.fetch_add(1 << 20, Ordering::SeqCst);
        Ok::<_, std::io::Error>(Bytes::from(vec![0u8; 1 << 20]))
    });
    Body::from_stream(futures_util::stream::iter(chunks))
}

#[tokio::test]
async fn an_unauthorised_upload_is_refused_before_its_body_is_read() {
    let dir = fresh_dir("auth");
    let (store, _) = Store::open(&dir).unwrap();
    let mut st = AppState::new(store, "http://test".into());
    st.writes = fractile_server::Writes::Token("sesame".into());
    let st = Arc::new(st);
    let read = Arc::new(AtomicUsize::new(0));
    let req = Request::put("/v1/assets/big")
        .header(header::CONTENT_LENGTH, 64 << 20)
        .body(counted_body(read.clone()))
        .unwrap();
    let (status, body) = send(&st, req).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    assert!(String::from_utf8_lossy(&body).contains("unauthorised"));
    assert_eq!(
        read.load(Ordering::SeqCst),
        0,
        "no byte of the body was read"
    );
    // Authorised but declaring more than the limit: refused before reading too.
    let req = Request::put("/v1/assets/big")
        .header(header::AUTHORIZATION, "Bearer sesame")
        .header(header::CONTENT_LENGTH, 65 << 20)
        .body(counted_body(read.clone()))
        .unwrap();
    let (status, _) = send(&st, req).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
    assert_eq!(read.load(Ordering::SeqCst), 0);
    // No length declared and over the limit: read up to the limit, then 413.
    let req = Request::put("/v1/assets/big")
        .header(header::AUTHORIZATION, "Bearer sesame")
        .body(Body::from_stream(futures_util::stream::iter((0..80).map(
            |_| Ok::<_, std::io::Error>(Bytes::from(vec![0u8; 1 << 20])),
        ))))
        .unwrap();
    let (status, _) = send(&st, req).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_writes_of_one_id_serialise_and_match_the_file() {
    let dir = fresh_dir("race");
    let (store, _) = Store::open(&dir).unwrap();
    let st = Arc::new(anonymous_writes(store));
    let (a, b) = two_assets();
    for round in 0..6 {
        let mut tasks = Vec::new();
        for k in 0..8 {
            let body = if (k + round) % 2 == 0 {
                a.clone()
            } else {
                b.clone()
            };
            let st = st.clone();
            tasks.push(tokio::spawn(async move {
                let req = Request::put("/v1/assets/same")
                    .body(Body::from(body))
                    .unwrap();
                send(&st, req).await
            }));
        }
        for t in tasks {
            let (status, body) = t.await.unwrap();
            let text = String::from_utf8_lossy(&body);
            assert!(status.is_success(), "round {round}: {status} {text}");
            assert!(
                !text.contains(dir.to_str().unwrap()),
                "a server path in {text}"
            );
        }
        let file = std::fs::read(dir.join("same.fra")).unwrap();
        let served = st.store.get("same").unwrap();
        assert_eq!(
            served.hash,
            crc_tail(&file),
            "round {round}: served and stored differ"
        );
    }
    // A restart reads the same version.
    let (again, _) = Store::open(&dir).unwrap();
    assert_eq!(
        again.get("same").unwrap().hash,
        st.store.get("same").unwrap().hash
    );
    // And no temporary file is left behind.
    let leftovers: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".tmp-"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[tokio::test]
async fn a_folder_of_crafted_files_starts_and_names_each() {
    let dir = fresh_dir("folder");
    let (good, _) = two_assets();
    std::fs::write(dir.join("camera.fra"), &good).unwrap();
    let crafted: Vec<String> = std::fs::read_dir(data("hostile"))
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains("bomb"))
        .collect();
    assert!(crafted.len() >= 5, "{crafted:?}");
    for name in &crafted {
        std::fs::copy(data(&format!("hostile/{name}")), dir.join(name)).unwrap();
    }
    // A temporary file of a writer that is gone (no such process) 10 minutes ago, and one of a
    // live writer (this process), which must stay; so must a fresh one of a pid not alive
    // here (another replica's upload in progress, in its own pid namespace).
    std::fs::write(dir.join(".x.fra.tmp-999999999-0"), b"partial").unwrap();
    std::fs::File::options()
        .write(true)
        .open(dir.join(".x.fra.tmp-999999999-0"))
        .unwrap()
        .set_modified(std::time::SystemTime::now() - Duration::from_secs(600))
        .unwrap();
    let replica = ".z.fra.tmp-999999998-0";
    std::fs::write(dir.join(replica), b"another replica's upload").unwrap();
    let live = format!(".y.fra.tmp-{}-7", std::process::id());
    std::fs::write(dir.join(&live), b"being written").unwrap();
    // A link to a valid asset elsewhere is not served.
    let outside = fresh_dir("outside");
    std::fs::write(outside.join("elsewhere.fra"), &good).unwrap();
    #[cfg(unix)]
    std::os::unix::fs::symlink(outside.join("elsewhere.fra"), dir.join("linked.fra")).unwrap();

    let (store, skipped) = Store::open(&dir).unwrap();
    let ids: Vec<String> = store.list().iter().map(|a| a.id.clone()).collect();
    assert_eq!(ids, vec!["camera".to_string()]);
    for name in &crafted {
        assert!(
            skipped.iter().any(|s| s.contains(name.as_str())),
            "{name} not named in {skipped:?}"
        );
    }
    #[cfg(unix)]
    assert!(
        skipped
            .iter()
            .any(|s| s.contains("linked.fra") && s.contains("link"))
    );
    assert!(
        !dir.join(".x.fra.tmp-999999999-0").exists(),
        "a stale temporary file stays"
    );
    assert!(dir.join(&live).exists(), "a live writer's file was removed");
    assert!(
        dir.join(replica).exists(),
        "a fresh upload of another pid namespace was removed"
    );
}

#[tokio::test]
async fn crafted_uploads_are_refused_with_422() {
    let dir = fresh_dir("put");
    let (store, _) = Store::open(&dir).unwrap();
    let st = Arc::new(anonymous_writes(store));
    for entry in std::fs::read_dir(data("hostile")).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        if !name.contains("bomb") {
            continue;
        }
        let req = Request::put("/v1/assets/crafted")
            .body(Body::from(std::fs::read(&path).unwrap()))
            .unwrap();
        let (status, body) = send(&st, req).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{name}");
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["code"], "bad_asset", "{name}");
    }
    assert!(st.store.list().is_empty());
}

/// A request larger than the whole heavy budget is refused up front, naming the setting.
#[tokio::test]
async fn a_request_over_the_decode_budget_is_413() {
    let dir = fresh_dir("budget");
    let (good, _) = two_assets();
    std::fs::write(dir.join("camera.fra"), &good).unwrap();
    let (store, _) = Store::open(&dir).unwrap();
    let mut st = AppState::new(store, "http://test".into());
    st.lanes = fractile_server::Lanes::new(2, 64);
    let st = Arc::new(st);
    let req = Request::get("/v1/assets/camera/region?bbox=0,0,1,1&width=4096&height=4096")
        .body(Body::empty())
        .unwrap();
    let (status, body) = send(&st, req).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
    assert!(String::from_utf8_lossy(&body).contains("max_decode_mib"));
    // One that fits is served.
    let req = Request::get("/v1/assets/camera/region?bbox=0,0,1,1&width=512&height=512")
        .body(Body::empty())
        .unwrap();
    assert_eq!(send(&st, req).await.0, StatusCode::OK);
}

/// Work whose request was dropped sees its cancel flag and stops; the budget it held comes
/// back only then.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dropped_requests_cancel_their_work() {
    let lanes = Arc::new(fractile_server::Lanes::new(2, 100));
    let (tx, rx) = std::sync::mpsc::channel();
    let l2 = lanes.clone();
    let request = tokio::spawn(async move {
        l2.run(80 << 20, move |cancel| {
            let start = std::time::Instant::now();
            while !cancel.is_set() && start.elapsed() < Duration::from_secs(20) {
                std::thread::sleep(Duration::from_millis(5));
            }
            tx.send(cancel.is_set()).unwrap();
        })
        .await
    });
    tokio::time::sleep(Duration::from_millis(200)).await;
    request.abort();
    let saw = tokio::task::spawn_blocking(move || rx.recv_timeout(Duration::from_secs(5)))
        .await
        .unwrap();
    assert_eq!(saw, Ok(true), "the work did not see its request go");
    // The budget is whole again: a request of the whole budget is admitted.
    let whole = tokio::time::timeout(Duration::from_secs(5), lanes.run(100 << 20, |_| 1)).await;
    assert_eq!(whole.unwrap().unwrap(), 1);
}

/// Connections that send nothing, or headers that never end, are closed after the header
/// timeout; a real request on another connection is answered meanwhile.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_that_never_finish_their_headers_are_closed() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let dir = fresh_dir("slowloris");
    let (store, _) = Store::open(&dir).unwrap();
    let st = Arc::new(AppState::new(store, "http://test".into()));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(fractile_server::run(
        listener,
        fractile_server::app(st),
        async {
            let _ = stop_rx.await;
        },
        Duration::from_millis(800),
    ));
    let mut idle = Vec::new();
    for k in 0..60 {
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        if k % 2 == 0 {
            s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
                .await
                .unwrap();
        }
        idle.push(s);
    }
    // A whole request is still answered.
    let mut ok = tokio::net::TcpStream::connect(addr).await.unwrap();
    ok.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let mut answer = String::new();
    ok.read_to_string(&mut answer).await.unwrap();
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    tokio::time::sleep(Duration::from_millis(2500)).await;
    for (k, mut s) in idle.into_iter().enumerate() {
        let mut buf = [0u8; 512];
        let read = tokio::time::timeout(Duration::from_secs(2), s.read(&mut buf)).await;
        // Closed: end of stream (possibly after a 408 the server sends), or a reset.
        let closed = match read {
            Ok(Ok(0)) | Ok(Err(_)) => true,
            Ok(Ok(n)) => {
                let rest = tokio::time::timeout(Duration::from_secs(2), s.read(&mut buf)).await;
                n > 0 && matches!(rest, Ok(Ok(0)) | Ok(Err(_)))
            }
            Err(_) => false,
        };
        assert!(closed, "connection {k} is still open");
    }
    let _ = stop_tx.send(());
    tokio::time::timeout(Duration::from_secs(5), server)
        .await
        .unwrap()
        .unwrap();
}

/// Readiness means a light decode slot is free: busy while every slot decodes, ready after.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readiness_follows_the_decode_slots() {
    let dir = fresh_dir("ready");
    let (store, _) = Store::open(&dir).unwrap();
    let mut st = AppState::new(store, "http://test".into());
    st.lanes = fractile_server::Lanes::new(1, 64);
    let st = Arc::new(st);
    let ready = || Request::get("/readyz").body(Body::empty()).unwrap();
    assert_eq!(send(&st, ready()).await.0, StatusCode::OK);
    let (tx, rx) = std::sync::mpsc::channel::<()>();
    let st2 = st.clone();
    let busy = tokio::spawn(async move {
        st2.lanes
            .run(0, move |_| {
                let _ = rx.recv_timeout(Duration::from_secs(10));
            })
            .await
    });
    // Until the work holds its slot.
    let mut seen = StatusCode::OK;
    for _ in 0..100 {
        seen = send(&st, ready()).await.0;
        if seen != StatusCode::OK {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert_eq!(seen, StatusCode::SERVICE_UNAVAILABLE);
    tx.send(()).unwrap();
    busy.await.unwrap().unwrap();
    assert_eq!(send(&st, ready()).await.0, StatusCode::OK);
}

/// A state that lets anyone write (`--allow-anonymous-writes`): these tests are about what
/// an upload holds, not about who sends it.
fn anonymous_writes(store: Store) -> AppState {
    let mut st = AppState::new(store, "http://test".into());
    st.writes = fractile_server::Writes::Anyone;
    st
}

#[tokio::test]
async fn the_cesium_folder_serves_its_own_files_and_no_links() {
    let assets = fresh_dir("cesium-assets");
    let cesium = fresh_dir("cesium");
    let outside = fresh_dir("cesium-outside");
    std::fs::write(cesium.join("Cesium.js"), "// CesiumJS").unwrap();
    std::fs::create_dir_all(cesium.join("Workers")).unwrap();
    std::fs::write(cesium.join("Workers/a.js"), "// a worker").unwrap();
    std::fs::write(outside.join("secret"), "not to be served").unwrap();
    std::os::unix::fs::symlink(outside.join("secret"), cesium.join("leak.js")).unwrap();
    std::os::unix::fs::symlink(&outside, cesium.join("linked")).unwrap();
    let (store, _) = Store::open(&assets).unwrap();
    let mut st = AppState::new(store, "http://test".into());
    st.cesium_dir = Some(cesium);
    let st = Arc::new(st);
    let get = |uri: &str| Request::get(uri).body(Body::empty()).unwrap();
    for (uri, status) in [
        ("/vendor/cesium/Cesium.js", StatusCode::OK),
        ("/vendor/cesium/Workers/a.js", StatusCode::OK),
        ("/vendor/cesium/leak.js", StatusCode::NOT_FOUND),
        ("/vendor/cesium/%6Ceak.js", StatusCode::NOT_FOUND),
        ("/vendor/cesium/linked/secret", StatusCode::NOT_FOUND),
        ("/vendor/cesium/Workers/../leak.js", StatusCode::NOT_FOUND),
        ("/vendor/cesium/nothing.js", StatusCode::NOT_FOUND),
    ] {
        let (s, body) = send(&st, get(uri)).await;
        assert_eq!(s, status, "{uri}");
        assert!(
            !String::from_utf8_lossy(&body).contains("not to be served"),
            "{uri}"
        );
    }
}

#[test]
fn huge_and_junk_files_in_the_folder_are_refused_before_they_are_read() {
    let dir = fresh_dir("huge");
    let (good, _) = two_assets();
    std::fs::write(dir.join("camera.fra"), &good).unwrap();
    // 100 GB, sparse: an asset's magic, then nothing. Read whole, it aborted the process.
    let huge = std::fs::File::create(dir.join("sparse.fra")).unwrap();
    std::io::Write::write_all(&mut &huge, b"FRACTILE").unwrap();
    huge.set_len(100 << 30).unwrap();
    // Junk of 64 MB with no magic.
    let junk = std::fs::File::create(dir.join("junk.fra")).unwrap();
    junk.set_len(64 << 20).unwrap();
    let (store, skipped) = Store::open(&dir).unwrap();
    assert!(store.get("camera").is_ok(), "the good asset is served");
    let said = skipped.join("\n");
    assert!(
        said.contains("sparse.fra") && said.contains("chunk it"),
        "{said}"
    );
    assert!(
        said.contains("junk.fra") && said.contains("not a fractile asset"),
        "{said}"
    );
}

#[tokio::test]
async fn deformation_bodies_over_their_limit_are_413_before_or_as_they_are_read() {
    let dir = fresh_dir("deform");
    let text = std::fs::read_to_string(data("curve/coast5.geojson")).unwrap();
    let lines = fractile_codec::codecs::curve::geojson::read(&text).unwrap();
    let settings = fractile_codec::codecs::curve::CurveSettings {
        tolerance: 0.009,
        ..Default::default()
    };
    let c = fractile_codec::encode::curve::encode_asset(&lines, &settings, "coast5").unwrap();
    std::fs::write(dir.join("coast.fra"), &c.bytes).unwrap();
    let (store, _) = Store::open(&dir).unwrap();
    let st = Arc::new(AppState::new(store, "http://test".into()));
    let uri = "/v1/assets/coast/curve/deform";
    // Declared 1 GiB, sending nothing: refused from the header, not waited for.
    let read = Arc::new(AtomicUsize::new(0));
    let req = Request::post(uri)
        .header(header::CONTENT_TYPE, "application/json")
        .header(header::CONTENT_LENGTH, (1u64 << 30).to_string())
        .body(counted_body(read.clone()))
        .unwrap();
    let (s, body) = send(&st, req).await;
    assert_eq!(
        s,
        StatusCode::PAYLOAD_TOO_LARGE,
        "{}",
        String::from_utf8_lossy(&body)
    );
    assert_eq!(read.load(Ordering::SeqCst), 0, "the body was read");
    // 17 MB with no declared length: 413 too, as every other body over its limit.
    let big = format!(
        "{{\"deformations\": [], \"pad\": \"{}\"}}",
        "x".repeat(17 << 20)
    );
    let req = Request::post(uri)
        .header(header::CONTENT_TYPE, "application/json")
        .body(Body::from_stream(futures_util::stream::once(async move {
            Ok::<_, std::io::Error>(big)
        })))
        .unwrap();
    let (s, body) = send(&st, req).await;
    assert_eq!(
        s,
        StatusCode::PAYLOAD_TOO_LARGE,
        "{}",
        String::from_utf8_lossy(&body)
    );
    assert!(String::from_utf8_lossy(&body).contains("too_large"));
}
