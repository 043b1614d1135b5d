//! Every endpoint of a real server (TCP, ephemeral port, assets encoded from the repo's test
//! data) through the client, errors included, and progressive refinement converging.

use fractile_client::refine::{RefineOptions, Stop};
use fractile_client::view::{Camera, PlanLimits};
use fractile_client::{
    AssetKind, Client, ClientError, MeshFormat, MeshRequest, PointsEncoding, PointsRequest,
    RegionFormat, RegionRequest, TileAddress, TileEncoding, TileRequest,
};
use fractile_e2e::{MAX_POINTS, TOKEN, server};

fn client() -> Client {
    Client::new(&server()).unwrap()
}

/// A tile two zooms deeper than jacksboro's source resolution, inside it.
async fn deep_tile(c: &Client) -> TileAddress {
    let a = c.asset("jacksboro").await.unwrap();
    let [w, s, e, n] = a.bounds.unwrap();
    let tj = c.tilejson("jacksboro").await.unwrap();
    TileAddress::containing(tj.maxzoom - 2, 0.5 * (w + e), 0.5 * (s + n))
}

#[tokio::test]
async fn catalog_metadata_and_tilejson() {
    let c = client();
    c.ready().await.unwrap();
    let assets = c.assets().await.unwrap();
    let ids: Vec<&str> = assets.iter().map(|a| a.id.as_str()).collect();
    assert!(
        ids.contains(&"jacksboro") && ids.contains(&"camera"),
        "{ids:?}"
    );
    let dem = c.asset("jacksboro").await.unwrap();
    assert_eq!(dem.kind, AssetKind::HeightField);
    assert!(dem.georeferenced && dem.units.as_deref() == Some("m"));
    // jacksboro.tif is 403 x 344 (testdata/README.md).
    assert_eq!((dem.width, dem.height), (403, 344));
    assert!(dem.max_contrast > 0.0 && dem.max_contrast < 1.0);
    assert!(dem.ratio > 5.0 && dem.encode_psnr > 30.0, "{dem:?}");
    let tj = c.tilejson("jacksboro").await.unwrap();
    assert_eq!(tj.tilejson, "3.0.0");
    assert_eq!(tj.encoding.as_deref(), Some("terrarium"));
    let [w, s, e, n] = dem.bounds.unwrap();
    assert!((tj.bounds[0] - w).abs() < 1e-9 && (tj.bounds[3] - n).abs() < 1e-9);
    assert!(tj.bounds[2] > tj.bounds[0] && e > w && n > s);
    assert!(tj.tiles[0].starts_with(&server()), "{:?}", tj.tiles);
    let img = c.asset("camera").await.unwrap();
    assert!(!img.georeferenced && img.kind == AssetKind::Image);

    let err = c.asset("nope").await.unwrap_err();
    assert!(
        matches!(&err, ClientError::NotFound { code, detail } if code == "unknown_asset" && detail.contains("nope")),
        "{err:?}"
    );
    // Ids that could walk out of a path are refused before they leave the client.
    assert!(matches!(
        c.asset("../etc").await.unwrap_err(),
        ClientError::Malformed { .. }
    ));
    assert!(matches!(
        Client::new("ftp://example.org"),
        Err(ClientError::Malformed { .. })
    ));
}

#[tokio::test]
async fn tiles_in_every_encoding_agree() {
    let c = client();
    let dem = c.asset("jacksboro").await.unwrap();
    let t = deep_tile(&c).await;
    let get = |e| {
        let c = c.clone();
        async move { c.tile("jacksboro", &TileRequest::new(t, e)).await.unwrap() }
    };
    let f32 = get(TileEncoding::F32).await;
    assert_eq!((f32.size, f32.values.len()), (256, 256 * 256));
    let [lo, hi] = dem.value_range;
    let b = f32.convergence_bound as f64;
    assert!(
        f32.values
            .iter()
            .all(|&v| v as f64 >= lo - b - 1.0 && v as f64 <= hi + b + 1.0)
    );
    // Each PNG encoding at full precision reads back to the float32 heights within its own
    // quantum; by default, terrain-RGB and Terrarium round further, by at most what their
    // error bound grew by over the float32 tile's.
    let worst = |p: &fractile_client::Tile| {
        p.values
            .iter()
            .zip(&f32.values)
            .map(|(a, b)| (a - b).abs() as f64)
            .fold(0.0, f64::max)
    };
    for (e, quantum) in [
        (TileEncoding::Terrarium, 1.0 / 256.0),
        (TileEncoding::TerrainRgb, 0.1),
        (TileEncoding::Gray16, (hi - lo) / 65535.0),
    ] {
        let full = TileRequest {
            precision: Some(fractile_client::Precision::Full),
            ..TileRequest::new(t, e)
        };
        let p = c.tile("jacksboro", &full).await.unwrap();
        assert!(p.body.starts_with(b"\x89PNG"), "{e:?}");
        let w = worst(&p);
        assert!(w <= quantum * 0.5 + 1e-3, "{e:?}: {w} > {quantum}/2");
        let rounded = get(e).await;
        let grown = (rounded.error_bound.unwrap() - f32.error_bound.unwrap()) as f64;
        let w = worst(&rounded);
        assert!(
            w <= grown + quantum * 0.5 + 1e-3,
            "{e:?}: rounded by {w}, its bound grew by {grown}"
        );
        if e != TileEncoding::Gray16 {
            assert!(grown > 0.0 && rounded.body.len() < p.body.len(), "{e:?}");
        }
    }
    let visual = get(TileEncoding::Visual).await;
    assert_eq!(visual.values.len(), 256 * 256 * visual.channels as usize);
    // The ETag comes back and is stable.
    assert_eq!(get(TileEncoding::F32).await.etag, f32.etag);
    assert!(f32.etag.is_some());
    let big = c
        .tile(
            "jacksboro",
            &TileRequest {
                tile_size: 512,
                ..TileRequest::new(t, TileEncoding::F32)
            },
        )
        .await
        .unwrap();
    assert_eq!(big.values.len(), 512 * 512);
}

#[tokio::test]
async fn the_decoding_backend_is_the_clients_to_ask_for() {
    let c = client();
    let t = deep_tile(&c).await;
    let req = TileRequest::new(t, TileEncoding::F32);
    let cpu = c
        .clone()
        .with_backend(Some(fractile_client::Backend::Cpu))
        .tile("jacksboro", &req)
        .await
        .unwrap();
    let auto = c
        .clone()
        .with_backend(Some(fractile_client::Backend::Auto))
        .tile("jacksboro", &req)
        .await
        .unwrap();
    assert_eq!(cpu.values, auto.values);
    // The test server has no GPU: asking for one is refused with the server's reason.
    let e = c
        .clone()
        .with_backend(Some(fractile_client::Backend::Gpu))
        .tile("jacksboro", &req)
        .await
        .unwrap_err();
    assert_eq!(e.code(), Some("gpu_unavailable"), "{e}");
    let pts = PointsRequest {
        points: vec![[-84.2, 36.6]],
        iterations: None,
        tolerance: None,
    };
    let e = c
        .clone()
        .with_backend(Some(fractile_client::Backend::Gpu))
        .points("jacksboro", &pts, PointsEncoding::Binary)
        .await
        .unwrap_err();
    assert_eq!(e.code(), Some("gpu_unavailable"), "{e}");
}

#[tokio::test]
async fn bad_tile_requests_are_typed_errors() {
    let c = client();
    let code = |r: Result<_, ClientError>| r.map(|_| ()).unwrap_err();
    let t = |z, x, y| TileRequest::new(TileAddress { z, x, y }, TileEncoding::Terrarium);
    let e = code(c.tile("jacksboro", &t(3, 9, 0)).await);
    assert_eq!((e.status(), e.code()), (Some(404), Some("no_tile")), "{e}");
    // A tile on the other side of the world.
    let e = code(c.tile("jacksboro", &t(4, 15, 15)).await);
    assert_eq!(e.code(), Some("outside"), "{e}");
    let e = code(
        c.tile(
            "jacksboro",
            &TileRequest {
                tile_size: 300,
                ..t(0, 0, 0)
            },
        )
        .await,
    );
    assert_eq!(e.code(), Some("bad_tilesize"), "{e}");
    let e = code(
        c.tile(
            "jacksboro",
            &TileRequest {
                iterations: Some(10_000),
                ..t(0, 0, 0)
            },
        )
        .await,
    );
    assert!(
        matches!(&e, ClientError::BadRequest { code, detail, .. } if code == "bad_iterations" && detail.contains("10000")),
        "{e}"
    );
    let e = code(
        c.tile(
            "jacksboro",
            &TileRequest {
                tolerance: Some(-1.0),
                ..t(0, 0, 0)
            },
        )
        .await,
    );
    assert_eq!(e.code(), Some("bad_tolerance"), "{e}");
    // Float tiles are for heights.
    let e = code(
        c.tile(
            "camera",
            &TileRequest::new(TileAddress { z: 0, x: 0, y: 0 }, TileEncoding::F32),
        )
        .await,
    );
    assert_eq!(e.code(), Some("bad_format"), "{e}");
}

#[tokio::test]
async fn points_in_json_and_binary_agree_with_single_points() {
    let c = client();
    let dem = c.asset("jacksboro").await.unwrap();
    let [w, s, e, n] = dem.bounds.unwrap();
    let pts: Vec<[f64; 2]> = (0..50)
        .map(|k| {
            let f = (k as f64 + 0.5) / 50.0;
            [w + f * (e - w), n - f * f * (n - s)]
        })
        .chain([[w - 1.0, s]])
        .collect();
    let req = PointsRequest {
        points: pts.clone(),
        iterations: Some(20),
        tolerance: None,
    };
    let json = c
        .points("jacksboro", &req, PointsEncoding::Json)
        .await
        .unwrap();
    let bin = c
        .points("jacksboro", &req, PointsEncoding::Binary)
        .await
        .unwrap();
    // Same answers; coordinates may differ in the last bit (JSON prints them shortest).
    assert_eq!(json.results.len(), bin.results.len());
    for (a, b) in json.results.iter().zip(&bin.results) {
        assert!((a.coordinates[0] - b.coordinates[0]).abs() < 1e-9);
        assert!((a.coordinates[1] - b.coordinates[1]).abs() < 1e-9);
        assert_eq!(
            (&a.values, a.convergence_bound, a.iterations, a.outside),
            (&b.values, b.convergence_bound, b.iterations, b.outside)
        );
    }
    assert_eq!(json.results.len(), 51);
    let last = json.results.last().unwrap();
    assert!(last.outside && last.values.is_none());
    let one = c
        .point_lonlat("jacksboro", pts[7][0], pts[7][1], Some(20))
        .await
        .unwrap();
    assert_eq!(one.values, json.results[7].values);
    // Each point stops once its own bound is under the default tolerance, within the 20 asked.
    assert_eq!(
        (one.convergence_bound, one.iterations),
        (
            json.results[7].convergence_bound,
            json.results[7].iterations
        )
    );
    assert!(one.iterations <= 20);
    let [lo, hi] = dem.value_range;
    for r in &json.results[..50] {
        let v = r.values.as_ref().unwrap()[0].unwrap() as f64;
        let b = r.convergence_bound.unwrap() as f64;
        assert!(
            v >= lo - b - 1.0 && v <= hi + b + 1.0,
            "{v} outside [{lo}, {hi}] +- {b}"
        );
    }
    // Unit coordinates for an image.
    let p = c.point_unit("camera", 0.5, 0.5, None).await.unwrap();
    assert_eq!(p.values.as_ref().unwrap().len(), 1);
    let e = c
        .point_lonlat("jacksboro", w - 1.0, s, None)
        .await
        .unwrap_err();
    assert_eq!(e.code(), Some("outside"), "{e}");
    // Over the batch limit: 413 with the server's detail.
    let over = PointsRequest {
        points: vec![[w, s]; MAX_POINTS + 1],
        iterations: Some(1),
        tolerance: None,
    };
    let e = c
        .points("jacksboro", &over, PointsEncoding::Binary)
        .await
        .unwrap_err();
    assert!(
        matches!(&e, ClientError::TooLarge { code, .. } if code == "too_many_points"),
        "{e}"
    );
}

#[tokio::test]
async fn regions_and_meshes() {
    let c = client();
    let dem = c.asset("jacksboro").await.unwrap();
    let [w, s, e, n] = dem.bounds.unwrap();
    // A box 1/32 of the DEM a side at 64 x 48 pixels: finer than the source, so every pixel is a
    // continuous point decode (pixels coarser than a source cell are filtered instead).
    let bbox = [
        w + 0.25 * (e - w),
        s + 0.25 * (n - s),
        w + (0.25 + 1.0 / 32.0) * (e - w),
        s + (0.25 + 1.0 / 32.0) * (n - s),
    ];
    assert!(dem.width < 64 * 32 && dem.height < 48 * 32);
    let req = RegionRequest {
        bbox,
        width: 64,
        height: 48,
        iterations: None,
        tolerance: None,
        format: RegionFormat::F32,
    };
    let r = c.region("jacksboro", &req).await.unwrap();
    let v = &r.values.as_ref().unwrap()[0];
    assert_eq!(v.len(), 64 * 48);
    // The region's pixels are the points at the same places (pixel centres, north up).
    let centre = |i: usize, j: usize| {
        [
            bbox[0] + (i as f64 + 0.5) / 64.0 * (bbox[2] - bbox[0]),
            bbox[3] - (j as f64 + 0.5) / 48.0 * (bbox[3] - bbox[1]),
        ]
    };
    let probe = [(0, 0), (63, 47), (20, 30)];
    let pts = PointsRequest {
        points: probe.iter().map(|&(i, j)| centre(i, j)).collect(),
        iterations: None,
        tolerance: None,
    };
    let p = c
        .points("jacksboro", &pts, PointsEncoding::Json)
        .await
        .unwrap();
    for (k, &(i, j)) in probe.iter().enumerate() {
        let pv = p.results[k].values.as_ref().unwrap()[0].unwrap();
        let rv = v[j * 64 + i];
        let tol = r.convergence_bound + p.results[k].convergence_bound.unwrap() + 1e-3;
        assert!(
            (pv - rv).abs() <= tol,
            "pixel {i},{j}: region {rv} point {pv} tol {tol}"
        );
    }
    let tif = c
        .region(
            "jacksboro",
            &RegionRequest {
                format: RegionFormat::Tif,
                ..req.clone()
            },
        )
        .await
        .unwrap();
    assert!(tif.body.starts_with(b"II*\0") || tif.body.starts_with(b"MM\0*"));
    let png = c
        .region(
            "camera",
            &RegionRequest {
                bbox: [0.0, 0.0, 1.0, 1.0],
                format: RegionFormat::Png,
                ..req.clone()
            },
        )
        .await
        .unwrap();
    let img = image::load_from_memory(&png.body).unwrap();
    assert_eq!((img.width(), img.height()), (64, 48));
    let e = c
        .region(
            "jacksboro",
            &RegionRequest {
                width: 100_000,
                height: 100_000,
                ..req.clone()
            },
        )
        .await
        .unwrap_err();
    assert_eq!(e.code(), Some("bad_size"), "{e}");

    let glb = c
        .mesh(
            "jacksboro",
            &MeshRequest {
                bbox: Some(bbox),
                resolution: Some(33),
                ..Default::default()
            },
        )
        .await
        .unwrap();
    assert!(glb.body.starts_with(b"glTF") && glb.content_type == "model/gltf-binary");
    let obj = c
        .mesh(
            "jacksboro",
            &MeshRequest {
                resolution: Some(9),
                format: MeshFormat::Obj,
                ..Default::default()
            },
        )
        .await
        .unwrap();
    let text = String::from_utf8(obj.body).unwrap();
    assert_eq!(text.lines().filter(|l| l.starts_with("v ")).count(), 81);
    // Adaptive: fewer triangles than the regular grid of the same size, a larger bound.
    let faces = |m: &fractile_client::MeshFile| {
        String::from_utf8_lossy(&m.body)
            .lines()
            .filter(|l| l.starts_with("f "))
            .count()
    };
    let req = |max_error| MeshRequest {
        bbox: Some(bbox),
        resolution: Some(129),
        max_error,
        format: MeshFormat::Obj,
        ..Default::default()
    };
    let regular = c.mesh("jacksboro", &req(None)).await.unwrap();
    let adaptive = c.mesh("jacksboro", &req(Some(10.0))).await.unwrap();
    assert_eq!(faces(&regular), 2 * 128 * 128);
    assert!(
        faces(&adaptive) < faces(&regular) / 2,
        "{}",
        faces(&adaptive)
    );
    assert!((adaptive.convergence_bound - regular.convergence_bound - 10.0).abs() < 1e-3);
    let e = c
        .mesh(
            "jacksboro",
            &MeshRequest {
                resolution: Some(1),
                ..Default::default()
            },
        )
        .await
        .unwrap_err();
    assert_eq!(e.code(), Some("bad_resolution"), "{e}");
    let e = c.mesh("camera", &MeshRequest::default()).await.unwrap_err();
    assert_eq!(e.code(), Some("not_terrain"), "{e}");
}

#[tokio::test]
async fn uploads_need_the_token_and_a_valid_file() {
    let c = client();
    let file = fractile_e2e::encode_file("topobathy.tif", 1.6);
    let e = c.upload("uploaded", file.clone()).await.unwrap_err();
    assert!(matches!(e, ClientError::Unauthorised { .. }), "{e}");
    let wrong = client().with_token(Some("wrong".into()));
    assert!(matches!(
        wrong.upload("uploaded", file.clone()).await.unwrap_err(),
        ClientError::Unauthorised { .. }
    ));
    let c = c.with_token(Some(TOKEN.into()));
    let up = c.upload("uploaded", file.clone()).await.unwrap();
    assert!(up.created && up.summary.id == "uploaded" && up.summary.bytes == file.len() as u64);
    let again = c.upload("uploaded", file.clone()).await.unwrap();
    assert!(!again.created);
    assert!(c.assets().await.unwrap().iter().any(|a| a.id == "uploaded"));
    // A corrupt file is refused and the stored one is kept.
    let mut bad = file.clone();
    let mid = bad.len() / 2;
    bad[mid] ^= 0xFF;
    let e = c.upload("uploaded", bad).await.unwrap_err();
    assert!(
        matches!(&e, ClientError::BadRequest { status: 422, code, .. } if code == "bad_asset"),
        "{e}"
    );
    let p = c.point_lonlat("uploaded", -120.0, 0.0, None).await;
    assert!(c.asset("uploaded").await.is_ok(), "{p:?}");
    c.delete("uploaded").await.unwrap();
    let e = c.asset("uploaded").await.unwrap_err();
    assert_eq!(e.code(), Some("unknown_asset"));
    let e = c.delete("uploaded").await.unwrap_err();
    assert_eq!(e.status(), Some(404));
}

#[tokio::test]
async fn tile_refinement_converges_within_its_bound() {
    let c = client();
    let t = deep_tile(&c).await;
    let req = TileRequest::new(t, TileEncoding::F32);
    let options = RefineOptions {
        tolerance: Some(0.5),
        change: 0.0,
        ..Default::default()
    };
    let mut seen = 0;
    let r = c
        .refine_tile("jacksboro", &req, &options, |_| seen += 1)
        .await
        .unwrap();
    assert_eq!(r.stop, Stop::Bound);
    assert_eq!(seen, r.steps.len());
    assert!(r.steps.len() >= 3, "{} steps", r.steps.len());
    for w in r.steps.windows(2) {
        assert!(
            w[1].convergence_bound < w[0].convergence_bound,
            "bound did not fall: {} -> {}",
            w[0].convergence_bound,
            w[1].convergence_bound
        );
        assert_eq!(w[1].iterations, w[0].iterations + 1);
    }
    let last = r.steps.last().unwrap();
    assert!(last.convergence_bound <= 0.5);
    let reference = c
        .tile(
            "jacksboro",
            &TileRequest {
                iterations: Some(100),
                ..req
            },
        )
        .await
        .unwrap();
    let worst = last
        .answer
        .values
        .iter()
        .zip(&reference.values)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    let allowed = last.convergence_bound + reference.convergence_bound + 1e-3;
    assert!(
        worst <= allowed,
        "last step off the reference by {worst} > {allowed}"
    );
    // Successive answers change less and less: the last change is the smallest.
    let changes: Vec<f32> = r.steps.iter().filter_map(|s| s.mean_change).collect();
    assert!(changes.last().unwrap() < &changes[0], "{changes:?}");
}

#[tokio::test]
async fn points_refinement_stops_on_the_seed_criterion() {
    let c = client();
    let dem = c.asset("jacksboro").await.unwrap();
    let [w, s, e, n] = dem.bounds.unwrap();
    let pts: Vec<[f64; 2]> = (0..200)
        .map(|k| {
            [
                w + (k % 20) as f64 / 20.0 * (e - w),
                s + (k / 20) as f64 / 10.0 * (n - s),
            ]
        })
        .collect();
    let r = c
        .refine_points(
            "jacksboro",
            &pts,
            PointsEncoding::Binary,
            &RefineOptions::default(),
            |_| {},
        )
        .await
        .unwrap();
    assert_eq!(r.stop, Stop::Converged);
    let range = (dem.value_range[1] - dem.value_range[0]) as f32;
    let last = r.steps.last().unwrap();
    assert!(last.mean_change.unwrap() <= 0.002 * range);
    // Earlier steps had not converged.
    for s in &r.steps[1..r.steps.len() - 1] {
        assert!(s.mean_change.unwrap() > 0.002 * range);
    }
    for w in r.steps.windows(2) {
        assert!(w[1].convergence_bound < w[0].convergence_bound);
    }
    // A region refines too, and a schedule is honoured.
    let options = RefineOptions {
        schedule: vec![1, 4, 16],
        change: 0.0,
        ..Default::default()
    };
    let req = RegionRequest {
        bbox: [w, s, e, n],
        width: 32,
        height: 32,
        iterations: None,
        tolerance: None,
        format: RegionFormat::F32,
    };
    let r = c
        .refine_region("jacksboro", &req, &options, |_| {})
        .await
        .unwrap();
    assert_eq!(r.stop, Stop::Schedule);
    let its: Vec<u32> = r.steps.iter().map(|s| s.iterations).collect();
    assert_eq!(its, vec![1, 4, 16]);
}

#[tokio::test]
async fn view_fetches_nearest_first_within_each_tolerance() {
    let c = client();
    let dem = c.asset("jacksboro").await.unwrap();
    let tj = c.tilejson("jacksboro").await.unwrap();
    let [w, s, e, n] = dem.bounds.unwrap();
    // A camera 300 m over the south-west corner, looking over the whole DEM.
    let cam = Camera::new(
        w + 0.1 * (e - w),
        s + 0.1 * (n - s),
        dem.value_range[1] + 300.0,
    );
    let limits = PlanLimits {
        min_zoom: tj.minzoom,
        max_zoom: tj.maxzoom,
        max_tiles: 64,
        // The shared server's limit: enough for the tightest tolerance of this camera.
        max_iterations: 128,
    };
    let plan = fractile_client::view::plan(&cam, tj.bounds, &dem, limits).unwrap();
    assert!(plan.len() > 4 && plan.len() <= 64, "{}", plan.len());
    let mut order = Vec::new();
    let tiles = c
        .fetch_view("jacksboro", &plan, TileEncoding::F32, 1, |p, _| {
            order.push(p.distance)
        })
        .await;
    // With one request in flight the answers arrive nearest first.
    assert!(order.windows(2).all(|w| w[0] <= w[1]));
    let mut ok = 0;
    for (p, t) in plan.iter().zip(&tiles) {
        match t {
            Ok(t) => {
                ok += 1;
                assert!(
                    t.convergence_bound <= p.tolerance * 1.0001,
                    "{}: bound {} over tolerance {} ({} steps, s {} seed {})",
                    p.address,
                    t.convergence_bound,
                    p.tolerance,
                    p.iterations,
                    dem.max_contrast,
                    dem.seed_bound
                );
            }
            // A tile of the plan's edge may only graze the DEM, with no pixel centre inside.
            Err(e) => assert_eq!(e.code(), Some("outside"), "{}: {e}", p.address),
        }
    }
    assert!(ok * 10 >= plan.len() * 8, "{ok} of {}", plan.len());
    let near = plan.first().unwrap();
    let far = plan.last().unwrap();
    assert!(
        near.address.z >= far.address.z && near.tolerance <= far.tolerance,
        "{near:?} {far:?}"
    );
}

#[tokio::test]
async fn volume_surfaces_and_distances_through_the_client() {
    use fractile_client::{MeshFormat, VolumeMeshRequest};
    let c = client();
    let v = c.asset("fandisk").await.unwrap();
    assert_eq!(v.kind, AssetKind::Volume);
    assert_eq!(v.codec, "ifs3d-octree");
    // The whole surface at two resolutions: more triangles above the encoded grid, and the
    // bound reported with each.
    let req = |resolution| VolumeMeshRequest {
        resolution: Some(resolution),
        format: MeshFormat::Ply,
        ..Default::default()
    };
    let count = |b: &[u8]| -> usize {
        let head = String::from_utf8_lossy(&b[..b.len().min(400)]).into_owned();
        head.lines()
            .find_map(|l| l.strip_prefix("element face "))
            .unwrap()
            .parse()
            .unwrap()
    };
    let coarse = c.volume_mesh("fandisk", &req(48)).await.unwrap();
    let fine = c.volume_mesh("fandisk", &req(96)).await.unwrap();
    assert!(count(&fine.body) > 3 * count(&coarse.body));
    assert!(coarse.convergence_bound >= 0.0 && coarse.convergence_bound.is_finite());
    // Distances: about zero on a vertex of the source, the band far from it, 404 outside.
    let mesh = fractile_codec::mesh::Mesh::read(&fractile_e2e::data("mesh/fandisk.off")).unwrap();
    let p = mesh.positions[1234].map(f64::from);
    let band = v.value_range[1];
    let d = c.distance("fandisk", p, Some(20)).await.unwrap();
    assert!(d.distance.unwrap().abs() < 0.3 * band as f32, "{d:?}");
    let e = c
        .distance("fandisk", [1e6, 0.0, 0.0], None)
        .await
        .unwrap_err();
    assert_eq!(e.code(), Some("outside"));
    // 2D requests on a volume are refused with the code that says why.
    let e = c.point_unit("fandisk", 0.5, 0.5, None).await.unwrap_err();
    assert_eq!(e.code(), Some("bad_point"));
}

/// The asset's file through the client: whole, it reads back as the asset the catalog
/// describes; by range, its bytes are the whole file's.
#[tokio::test]
async fn asset_files_whole_and_by_range() {
    let c = client();
    let whole = c.file_bytes("jacksboro", None).await.unwrap();
    let asset = fractile_codec::Asset::from_bytes(&whole).unwrap();
    let info = c.asset("jacksboro").await.unwrap();
    assert_eq!(whole.len() as u64, info.bytes);
    assert_eq!(
        (asset.meta.width, asset.meta.height),
        (info.width, info.height)
    );
    let part = c.file_bytes("jacksboro", Some((7, 1030))).await.unwrap();
    assert_eq!(part, &whole[7..=1030]);
    let err = c
        .file_bytes(
            "jacksboro",
            Some((whole.len() as u64 + 1, whole.len() as u64 + 5)),
        )
        .await
        .unwrap_err();
    assert!(format!("{err:?}").contains("bad_range"), "{err:?}");
}
