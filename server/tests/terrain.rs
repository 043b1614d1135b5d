//! Cesium terrain (quantized-mesh-1.0), read back by a decoder we did not write: the Python
//! package quantized-mesh-tile, installed (pinned) into a virtual environment under `target/`
//! the first time (PyPI, as CI's other tools).

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use fractile_codec::{QuadtreeSettings, Raster, RateMode, encode};
use fractile_server::AppState;
use fractile_server::Store;
use http_body_util::BodyExt;
use serde_json::Value;
use tower::ServiceExt;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn state() -> Arc<AppState> {
    static STATE: OnceLock<Arc<AppState>> = OnceLock::new();
    STATE
        .get_or_init(|| {
            let dir = std::env::temp_dir().join(format!("fractile-terrain-{}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            for (id, file, bpp) in [
                ("jacksboro", "jacksboro.tif", 1.6),
                ("etopo20", "etopo20.tif", 0.8),
                ("camera", "camera.png", 0.48),
            ] {
                let r = Raster::open(&root().join("testdata").join(file)).unwrap();
                let mut s = QuadtreeSettings {
                    rate: RateMode::TargetBpp(bpp),
                    ..QuadtreeSettings::default()
                };
                s.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(r.kind);
                let enc = encode(&r, &s, &|_, _| {}).unwrap();
                std::fs::write(dir.join(format!("{id}.fra")), &enc.bytes).unwrap();
            }
            let (store, skipped) = Store::open(&dir).unwrap();
            assert!(skipped.is_empty(), "{skipped:?}");
            Arc::new(AppState::new(store, "http://test".into()))
        })
        .clone()
}

async fn send(req: Request<Body>) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    let r = fractile_server::app(state()).oneshot(req).await.unwrap();
    let (parts, body) = r.into_parts();
    let bytes = body.collect().await.unwrap().to_bytes().to_vec();
    (parts.status, parts.headers, bytes)
}

async fn get(uri: &str) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    send(Request::get(uri).body(Body::empty()).unwrap()).await
}

/// The Python of a virtual environment holding quantized-mesh-tile 0.7.0.
///
/// Made once per test binary behind a `OnceLock`: two tests creating the same venv at once
/// raced (`File exists`) and failed CI.
fn reader_python() -> PathBuf {
    static PYTHON: OnceLock<PathBuf> = OnceLock::new();
    PYTHON.get_or_init(make_reader_python).clone()
}

fn make_reader_python() -> PathBuf {
    let venv = root().join("target/test-tools/quantized-mesh");
    let python = venv.join("bin/python");
    let ready = |p: &Path| {
        std::process::Command::new(p)
            .args(["-c", "import quantized_mesh_tile"])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if !ready(&python) {
        let ok = std::process::Command::new("python3")
            .args(["-m", "venv", "--clear"])
            .arg(&venv)
            .status()
            .is_ok_and(|s| s.success());
        assert!(ok, "python3 -m venv {} failed", venv.display());
        let ok = std::process::Command::new(venv.join("bin/pip"))
            .args(["install", "-q", "quantized-mesh-tile==0.7.0"])
            .status()
            .is_ok_and(|s| s.success());
        assert!(
            ok,
            "pip install quantized-mesh-tile==0.7.0 failed (needs PyPI)"
        );
    }
    python
}

/// Tile (x, y) of level `z` of the geographic TMS scheme that holds (lon, lat), and its bounds.
fn tile_at(z: u8, lon: f64, lat: f64) -> (u32, u32, [f64; 4]) {
    let d = 180.0 / f64::from(1u32 << z);
    let (x, y) = (((lon + 180.0) / d) as u32, ((lat + 90.0) / d) as u32);
    let (w, s) = (-180.0 + f64::from(x) * d, -90.0 + f64::from(y) * d);
    (x, y, [w, s, w + d, s + d])
}

/// Decoded heights at lon/lat points, through the points endpoint, with each one's bound.
async fn decoded(id: &str, points: &[[f64; 2]]) -> Vec<Option<(f64, f64)>> {
    let req = serde_json::json!({ "points": points });
    let (s, _, b) = send(
        Request::post(format!("/v1/assets/{id}/points"))
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(req.to_string()))
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&b));
    let v: Value = serde_json::from_slice(&b).unwrap();
    v["results"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            let v = r["values"].get(0).and_then(Value::as_f64)?;
            Some((v, r["convergence_bound"].as_f64().unwrap_or(0.0)))
        })
        .collect()
}

/// A tile as the independent decoder read it.
struct ReadTile {
    /// `[lon, lat, height]`.
    vertices: Vec<[f64; 3]>,
    /// Vertex indices on the west, south, east and north edges.
    edges: Vec<Vec<usize>>,
    /// The tile's height quantum (its range over 32767).
    step: f64,
}

impl ReadTile {
    /// The height of the tile's edge `side` (0 west, 1 south, 2 east, 3 north) at `t` (the
    /// latitude of a west or east edge, the longitude of the others), by its edge vertices:
    /// the polyline the neighbour across that edge meets.
    fn edge_height(&self, side: usize, t: f64) -> f64 {
        let along = usize::from(side.is_multiple_of(2));
        let mut on: Vec<[f64; 3]> = self.edges[side].iter().map(|&k| self.vertices[k]).collect();
        on.sort_by(|a, b| a[along].total_cmp(&b[along]));
        let k = on
            .iter()
            .position(|p| p[along] >= t - 1e-9)
            .expect("t on the edge");
        if (on[k][along] - t).abs() < 1e-9 || k == 0 {
            return on[k][2];
        }
        let (a, b) = (on[k - 1], on[k]);
        // The flat chord between the two vertices on the globe: straight in the heights over
        // the edge's arc (the sphere to second order about the edge's middle, as the server
        // meshes; `Mesh::adaptive_tile`), where it passes over t.
        let mid = 0.5 * (on[0][along] + on[on.len() - 1][along]);
        let arc = |t: f64| -0.5 * GLOBE * (t - mid).to_radians().powi(2);
        let (ha, hb) = (a[2] + arc(a[along]), b[2] + arc(b[along]));
        ha + (hb - ha) * (t - a[along]) / (b[along] - a[along]) - arc(t)
    }
}

/// The sphere the edges are drawn on (the WGS84 semi-major axis).
const GLOBE: f64 = 6_378_137.0;

/// Reads tile (`z`, the one holding `lon`, `lat`) of asset `id` with the independent decoder and
/// checks it. With `detail` (`?iterations=64`: the continuation's detail on the 65 x 65 grid)
/// its vertices and the mesh between them are checked against the asset's point decodes; the
/// default tiles past the source are the surface filtered over a source cell on a grid as fine
/// as the cells, which point decodes do not give (`lean_terrain.rs` weighs their triangles).
async fn check_tile(id: &str, z: u8, lon: f64, lat: f64, detail: bool) -> ReadTile {
    let (s, _, b) = get(&format!("/v1/assets/{id}/layer.json")).await;
    assert_eq!(s, StatusCode::OK, "{id}: {}", String::from_utf8_lossy(&b));
    let layer: Value = serde_json::from_slice(&b).unwrap();
    assert_eq!(layer["format"], "quantized-mesh-1.0");
    assert_eq!(layer["scheme"], "tms");
    let (x, y, bounds) = tile_at(z, lon, lat);
    let range = &layer["available"][usize::from(z)][0];
    for (key, v) in [("startX", x), ("endX", x), ("startY", y), ("endY", y)] {
        let r = range[key].as_u64().unwrap() as u32;
        assert!(
            if key.starts_with("start") {
                r <= v
            } else {
                r >= v
            },
            "{key} {range}"
        );
    }

    let query = if detail { "?iterations=64" } else { "" };
    let (s, h, body) = get(&format!(
        "/v1/assets/{id}/terrain/{z}/{x}/{y}.terrain{query}"
    ))
    .await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    assert_eq!(h[header::CONTENT_TYPE], "application/vnd.quantized-mesh");
    let bound: f64 = h["x-convergence-bound"].to_str().unwrap().parse().unwrap();
    // A file of this call's own: the tests run side by side and ask for the same tiles, with
    // and without detail (one named by the tile alone was read back by another test while the
    // other tile overwrote it: a crack of 9.6 m that was not in either tile).
    static CALLS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let call = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let file = std::env::temp_dir().join(format!(
        "fractile-{}-{call}-{z}-{x}-{y}-{detail}.terrain",
        std::process::id()
    ));
    std::fs::write(&file, &body).unwrap();
    let out = std::process::Command::new(reader_python())
        .arg(root().join("tests/tools/read_quantized_mesh.py"))
        .arg(&file)
        .args(bounds.map(|v| v.to_string()))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let tile: Value = serde_json::from_slice(&out.stdout).unwrap();
    let vertices: Vec<[f64; 3]> = serde_json::from_value(tile["vertices"].clone()).unwrap();
    let triangles: Vec<[usize; 3]> = serde_json::from_value(tile["triangles"].clone()).unwrap();
    assert!(!triangles.is_empty(), "{id} {z}/{x}/{y}: no triangles");
    let (lo, hi) = (
        tile["header"]["minimumHeight"].as_f64().unwrap(),
        tile["header"]["maximumHeight"].as_f64().unwrap(),
    );
    // Heights travel as 15-bit steps of the tile's range.
    let step = (hi - lo) / 32767.0;

    let edges: Vec<Vec<usize>> = serde_json::from_value(tile["edges"].clone()).unwrap();
    if detail {
        check_heights(id, &vertices, &triangles, &edges, (bounds, bound, step)).await;
    }
    // Every edge vertex lies on its edge.
    let on = [
        (0, bounds[0]),
        (1, bounds[1]),
        (0, bounds[2]),
        (1, bounds[3]),
    ];
    for (edge, (axis, value)) in edges.iter().zip(on) {
        assert!(!edge.is_empty());
        for &k in edge {
            assert!(
                (vertices[k][axis] - value).abs() < 1e-9,
                "{:?} not on {value}",
                vertices[k]
            );
        }
    }
    ReadTile {
        vertices,
        edges,
        step,
    }
}

/// The checks of [`check_tile`] with `detail`: every vertex is a decoded height at its own
/// position, and the mesh between them within the tile's bound of the decoded heights.
async fn check_heights(
    id: &str,
    vertices: &[[f64; 3]],
    triangles: &[[usize; 3]],
    edges: &[Vec<usize>],
    (bounds, bound, step): ([f64; 4], f64, f64),
) {
    // Every vertex is a decoded height at its own position (within the quantisation).
    // Vertices sit on the tile's 65 x 65 grid; the format stores their positions in steps of
    // 1/32767 of the tile, so the decoder's positions are snapped back to the grid (they are
    // within half a step of it) before the asset is decoded there.
    let snap = |t: f64, lo: f64, hi: f64| {
        let k = ((t - lo) / (hi - lo) * 64.0).round();
        assert!(
            ((t - lo) / (hi - lo) * 64.0 - k).abs() < 0.01,
            "{t} off the grid"
        );
        lo + k / 64.0 * (hi - lo)
    };
    let at: Vec<[f64; 2]> = vertices
        .iter()
        .map(|v| {
            [
                snap(v[0], bounds[0], bounds[2]),
                snap(v[1], bounds[1], bounds[3]),
            ]
        })
        .collect();
    // Off the asset, the ellipsoid (height 0). The tile's decode and this one each stop within
    // their own bound of the attractor (chains from slightly different frame coordinates), so
    // they may differ by twice the bound. Edge vertices may instead lie on their edge's chord,
    // where the neighbour's mesh passes (no cracks), within the tile's bound.
    let on_edge: std::collections::HashSet<usize> = edges.iter().flatten().copied().collect();
    for (k, (v, d)) in vertices.iter().zip(decoded(id, &at).await).enumerate() {
        let (d, b) = d.unwrap_or((0.0, 0.0));
        let within = if on_edge.contains(&k) {
            bound + b
        } else {
            2.0 * b
        };
        assert!(
            (v[2] - d).abs() <= step + within + 0.05,
            "{id} {v:?}: decoded {d} +- {b}"
        );
    }
    // Between vertices the mesh stays within the stated bound of the decoded heights on the
    // tile's 65 x 65 grid: interpolate each grid point in the triangle that holds it.
    let n = 65usize;
    let grid: Vec<[f64; 2]> = (0..n * n)
        .map(|k| {
            let (i, j) = ((k % n) as f64 / 64.0, (k / n) as f64 / 64.0);
            [
                bounds[0] + i * (bounds[2] - bounds[0]),
                bounds[1] + j * (bounds[3] - bounds[1]),
            ]
        })
        .collect();
    let heights = decoded(id, &grid).await;
    let mut checked = 0;
    // The mesh's flat triangles, on the globe: straight in the heights over the sphere's
    // second-order arc (about the tile's centre; any point gives the same), as it is meshed.
    let centre = [0.5 * (bounds[0] + bounds[2]), 0.5 * (bounds[1] + bounds[3])];
    let arc = |v: [f64; 2]| {
        -0.5 * GLOBE
            * ((v[0] - centre[0]).to_radians().powi(2) + (v[1] - centre[1]).to_radians().powi(2))
    };
    for (p, d) in grid.iter().zip(heights) {
        let Some((d, b)) = d else { continue };
        let mesh = triangles.iter().find_map(|t| {
            // Each vertex at its grid point (the format quantises positions to 1/32767 of the
            // tile, which on a wide tile moves the arc, kilometres deep, by metres).
            let [a, b, c] = t.map(|k| [at[k][0], at[k][1], vertices[k][2] + arc(at[k])]);
            let det = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1]);
            let l1 = ((b[1] - c[1]) * (p[0] - c[0]) + (c[0] - b[0]) * (p[1] - c[1])) / det;
            let l2 = ((c[1] - a[1]) * (p[0] - c[0]) + (a[0] - c[0]) * (p[1] - c[1])) / det;
            let l3 = 1.0 - l1 - l2;
            let eps = -1e-9;
            (l1 >= eps && l2 >= eps && l3 >= eps)
                .then(|| l1 * a[2] + l2 * b[2] + l3 * c[2] - arc(*p))
        });
        let mesh = mesh.expect("every grid point of a tile inside the asset is in a triangle");
        assert!(
            (mesh - d).abs() <= bound + b + step + 0.05,
            "{p:?}: mesh {mesh}, decoded {d}, bound {bound}"
        );
        checked += 1;
    }
    assert!(checked > 1000, "{id}: {checked}");
}

#[tokio::test]
async fn terrain_tiles_read_back_by_an_independent_decoder_match_the_decoded_heights() {
    // jacksboro at level 12 (adaptive meshes); etopo20, a global DEM of 20' cells, at level 4
    // (a regular grid of 0.18-degree cells: the Alps), level 8 (adaptive, its deepest, in the Andes) and at
    // the antimeridian. Levels whose cells are coarser than the source's (etopo20 at level 3)
    // are filtered, as raster tiles are, so their vertices are not point decodes.
    for (id, z, lon, lat) in [
        ("jacksboro", 12, -84.25, 36.6),
        ("etopo20", 4, 10.0, 46.0),
        ("etopo20", 8, -70.0, -33.0),
        ("etopo20", 5, 179.9, -20.0),
    ] {
        // Each of these tiles lies over relief (or the globe's curvature): a real mesh, not
        // two flat triangles.
        let tile = check_tile(id, z, lon, lat, true).await;
        assert!(tile.vertices.len() > 8, "{id} {z}: {}", tile.vertices.len());
    }
}

#[tokio::test]
async fn neighbouring_terrain_tiles_meet_without_cracks() {
    // Adaptive tiles (jacksboro at level 12, etopo20 at level 8) and their east and north
    // neighbours, as served by default and with the continuation's detail: every vertex on a
    // shared edge lies on the other tile's edge (as drawn on the globe), to the two tiles'
    // height quanta. Meshed each on its own, these edges were up to the level's
    // error apart (cracks that Cesium's skirts hide only from above).
    for (id, z, lon, lat) in [
        ("jacksboro", 12, -84.25, 36.6),
        ("etopo20", 8, -70.0, -33.0),
    ] {
        for detail in [false, true] {
            let d = 180.0 / f64::from(1u32 << z);
            let here = check_tile(id, z, lon, lat, detail).await;
            let east = check_tile(id, z, lon + d, lat, detail).await;
            let north = check_tile(id, z, lon, lat + d, detail).await;
            let mut compared = 0;
            for (a, side, b, other) in [
                (&here, 2usize, &east, 0),
                (&east, 0, &here, 2),
                (&here, 3, &north, 1),
                (&north, 1, &here, 3),
            ] {
                let along = usize::from(side.is_multiple_of(2));
                for &k in &a.edges[side] {
                    let v = a.vertices[k];
                    let across = b.edge_height(other, v[along]);
                    assert!(
                        (v[2] - across).abs() <= a.step + b.step + 1e-3,
                        "{id} {z} (detail {detail}): {v:?} on edge {side}, the neighbour's edge at {across}"
                    );
                    compared += 1;
                }
            }
            // The default tiles past the source have a vertex a source cell at most; edges
            // split at their farthest height keep few (14 on etopo20's level-8 edges).
            let least = if detail { 10 } else { 4 };
            assert!(compared > least, "{id}: {compared} edge vertices");
        }
    }
}

/// Browsers and Cesium accept gzip: the tile then goes gzipped (a variant with its own ETag),
/// and inflates to the same bytes as the plain one.
#[tokio::test]
async fn terrain_tiles_go_gzipped_to_clients_that_accept_it() {
    let (x, y, _) = tile_at(11, -84.25, 36.6);
    let uri = format!("/v1/assets/jacksboro/terrain/11/{x}/{y}.terrain");
    let (s, plain_h, plain) = get(&uri).await;
    assert_eq!(s, StatusCode::OK);
    assert!(plain_h.get(header::CONTENT_ENCODING).is_none());
    let (s, h, gz) = send(
        Request::get(&uri)
            .header(header::ACCEPT_ENCODING, "gzip, deflate, br")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(h[header::CONTENT_ENCODING], "gzip");
    assert_eq!(h[header::VARY], "accept, accept-encoding");
    assert_ne!(h[header::ETAG], plain_h[header::ETAG]);
    let mut inflated = Vec::new();
    std::io::Read::read_to_end(&mut flate2::read::GzDecoder::new(&gz[..]), &mut inflated).unwrap();
    assert_eq!(inflated, plain);
    assert!(
        gz.len() * 10 < plain.len() * 7,
        "{} of {}",
        gz.len(),
        plain.len()
    );
    // q=0 refuses it.
    let (_, h, _) = send(
        Request::get(&uri)
            .header(header::ACCEPT_ENCODING, "gzip;q=0")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert!(h.get(header::CONTENT_ENCODING).is_none());
}

/// Cesium asks for vertex normals in its Accept header (for lighting): the tile then carries
/// the octvertexnormals extension, which the independent decoder reads, with normals that lean
/// with the relief and point up on the whole.
#[tokio::test]
async fn terrain_tiles_carry_vertex_normals_when_asked() {
    let (s, _, b) = get("/v1/assets/jacksboro/layer.json").await;
    assert_eq!(s, StatusCode::OK);
    let layer: Value = serde_json::from_slice(&b).unwrap();
    assert_eq!(layer["extensions"][0], "octvertexnormals");
    let (x, y, bounds) = tile_at(12, -84.25, 36.6);
    let (s, h, body) = send(
        Request::get(format!("/v1/assets/jacksboro/terrain/12/{x}/{y}.terrain"))
            .header(
                header::ACCEPT,
                "application/vnd.quantized-mesh;extensions=octvertexnormals,application/octet-stream;q=0.9",
            )
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(
        h[header::CONTENT_TYPE],
        "application/vnd.quantized-mesh;extensions=octvertexnormals"
    );
    let file =
        std::env::temp_dir().join(format!("fractile-{}-normals.terrain", std::process::id()));
    std::fs::write(&file, &body).unwrap();
    let script = "import sys, json\nfrom quantized_mesh_tile.terrain import TerrainTile\n\
                  from quantized_mesh_tile.utils import octDecode\n\
                  w, s, e, n = map(float, sys.argv[2:6])\n\
                  t = TerrainTile(west=w, south=s, east=e, north=n)\n\
                  t.fromFile(sys.argv[1], hasLighting=True)\n\
                  print(json.dumps({'normals': [list(v) for v in t.vLight], 'vertices': t.getVerticesCoordinates()}))\n";
    let out = std::process::Command::new(reader_python())
        .args(["-c", script])
        .arg(&file)
        .args(bounds.map(|v| v.to_string()))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let normals: Vec<[f64; 3]> = serde_json::from_value(v["normals"].clone()).unwrap();
    let vertices: Vec<[f64; 3]> = serde_json::from_value(v["vertices"].clone()).unwrap();
    assert_eq!(normals.len(), vertices.len());
    let (mut sum_up, mut tilted) = (0.0, 0);
    for (nv, p) in normals.iter().zip(&vertices) {
        let (lat, lon) = (p[1].to_radians(), p[0].to_radians());
        let up = [lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin()];
        let cos = nv[0] * up[0] + nv[1] * up[1] + nv[2] * up[2];
        assert!(cos > 0.2, "a normal {nv:?} far from up at {p:?}");
        sum_up += cos;
        tilted += usize::from(cos < 0.995);
    }
    assert!(
        sum_up / normals.len() as f64 > 0.9,
        "{}",
        sum_up / normals.len() as f64
    );
    // jacksboro is hilly: many normals lean more than 6 degrees.
    assert!(tilted * 10 > normals.len(), "{tilted} of {}", normals.len());
}

#[tokio::test]
async fn terrain_refuses_what_is_not_terrain() {
    let (s, _, b) = get("/v1/assets/camera/layer.json").await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    let v: Value = serde_json::from_slice(&b).unwrap();
    assert_eq!(v["code"], "not_terrain");
    let (x, y, _) = tile_at(10, 100.0, -40.0);
    let (s, _, b) = get(&format!("/v1/assets/jacksboro/terrain/10/{x}/{y}.terrain")).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    let v: Value = serde_json::from_slice(&b).unwrap();
    assert_eq!(v["code"], "outside");
    let (s, _, _) = get("/v1/assets/jacksboro/terrain/1/9/0.terrain").await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    // Both root tiles exist (Cesium needs them), the far one flat.
    for x in 0..2 {
        let (s, _, _) = get(&format!("/v1/assets/jacksboro/terrain/0/{x}/0.terrain")).await;
        assert_eq!(s, StatusCode::OK, "root tile {x}");
    }
}
