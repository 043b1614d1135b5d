//! Two servers over one asset folder, as replicas on a shared volume: what one stores,
//! replaces or deletes, the other serves after its next rescan (`Store::refresh`), with the
//! same ETag; a changed file that does not load leaves the version served before.

use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use fractile_codec::{QuadtreeSettings, Raster, RateMode, encode};
use fractile_server::{AppState, Writes};
use fractile_server::{Refreshed, Store};
use tower::ServiceExt;

fn data(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

fn asset_bytes(name: &str) -> Vec<u8> {
    let r = Raster::open(&data(name)).unwrap();
    let settings = QuadtreeSettings {
        rate: RateMode::TargetBpp(1.0),
        ..QuadtreeSettings::default()
    };
    encode(&r, &settings, &|_, _| {}).unwrap().bytes
}

fn replica(dir: &std::path::Path) -> Arc<AppState> {
    let (store, skipped) = Store::open(dir).unwrap();
    assert!(skipped.is_empty(), "{skipped:?}");
    let mut st = AppState::new(store, "http://test".into());
    st.writes = Writes::Token("t".into());
    Arc::new(st)
}

/// Status and ETag of a tile of `id`.
async fn tile(st: &Arc<AppState>, id: &str) -> (StatusCode, Option<String>) {
    let req = Request::get(format!("/v1/assets/{id}/tiles/0/0/0.png"))
        .body(Body::empty())
        .unwrap();
    let resp = fractile_server::app(st.clone()).oneshot(req).await.unwrap();
    let etag = resp
        .headers()
        .get(header::ETAG)
        .map(|v| v.to_str().unwrap().to_string());
    (resp.status(), etag)
}

async fn write(st: &Arc<AppState>, req: axum::http::request::Builder, body: Body) -> StatusCode {
    let req = req
        .header(header::AUTHORIZATION, "Bearer t")
        .body(body)
        .unwrap();
    fractile_server::app(st.clone())
        .oneshot(req)
        .await
        .unwrap()
        .status()
}

#[tokio::test]
async fn what_one_replica_stores_the_other_serves_after_a_rescan() {
    let dir = std::env::temp_dir().join(format!("fractile-replicas-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let (a, b) = (replica(&dir), replica(&dir));
    assert_eq!(
        b.store.refresh(),
        Refreshed::default(),
        "nothing changed yet"
    );

    let topo = asset_bytes("topobathy.tif");
    let put = |bytes: Vec<u8>| {
        let a = a.clone();
        async move { write(&a, Request::put("/v1/assets/dem"), Body::from(bytes)).await }
    };
    assert_eq!(put(topo.clone()).await, StatusCode::CREATED);
    assert_eq!(
        tile(&b, "dem").await.0,
        StatusCode::NOT_FOUND,
        "not before a rescan"
    );
    let found = b.store.refresh();
    assert_eq!(found.loaded, vec!["dem".to_string()]);
    let (sa, ea) = tile(&a, "dem").await;
    let (sb, eb) = tile(&b, "dem").await;
    assert_eq!((sa, sb), (StatusCode::OK, StatusCode::OK));
    assert!(
        ea.is_some() && ea == eb,
        "one ETag for one version: {ea:?} {eb:?}"
    );
    // The writer's own rescan finds nothing new: it loaded what it wrote.
    assert_eq!(a.store.refresh(), Refreshed::default());

    // Replaced through one replica: the other serves the new version, under a new ETag.
    assert_eq!(put(asset_bytes("jacksboro.tif")).await, StatusCode::OK);
    assert_eq!(b.store.refresh().loaded, vec!["dem".to_string()]);
    let (_, eb2) = tile(&b, "dem").await;
    assert_eq!(eb2, tile(&a, "dem").await.1);
    assert_ne!(eb2, eb, "the replaced version has its own ETag");

    // A changed file that does not load: the version served before stays.
    std::fs::write(dir.join("dem.fra"), b"FRACTILE truncated").unwrap();
    let found = b.store.refresh();
    assert!(
        found.loaded.is_empty() && found.skipped.len() == 1,
        "{found:?}"
    );
    assert_eq!(tile(&b, "dem").await, (StatusCode::OK, eb2.clone()));
    // Reported once per change: the same broken file is not read nor reported again, and a
    // junk file beside it is reported once too; when it changes, it is read again.
    std::fs::write(dir.join("junk.fra"), vec![7u8; 4096]).unwrap();
    let found = b.store.refresh();
    assert!(
        found.skipped.len() == 1 && found.skipped[0].contains("junk"),
        "{found:?}"
    );
    assert_eq!(b.store.refresh(), Refreshed::default(), "nothing changed");
    std::fs::write(dir.join("junk.fra"), vec![7u8; 8192]).unwrap();
    assert_eq!(b.store.refresh().skipped.len(), 1, "the junk file changed");
    std::fs::remove_file(dir.join("junk.fra")).unwrap();
    assert_eq!(b.store.refresh(), Refreshed::default());

    // Deleted through one replica: gone from the other after its rescan.
    std::fs::write(dir.join("dem.fra"), &topo).unwrap();
    assert_eq!(b.store.refresh().loaded, vec!["dem".to_string()]);
    assert_eq!(
        write(&a, Request::delete("/v1/assets/dem"), Body::empty()).await,
        StatusCode::NO_CONTENT
    );
    assert_eq!(b.store.refresh().removed, vec!["dem".to_string()]);
    assert_eq!(tile(&b, "dem").await.0, StatusCode::NOT_FOUND);
    std::fs::remove_dir_all(&dir).unwrap();
}
