//! Volumes as 3D Tiles (issue 79): the tileset of a real mesh's volume walked as a viewer
//! walks it (subtrees, then the content they list), each tile's surface inside its box and
//! whole, neighbours meeting without cracks, every level within the geometric error it
//! states of the source mesh, and the GLBs read by the Khronos glTF validator (npm), which we
//! did not write.

use std::collections::{BTreeMap, HashSet};
use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use fractile_codec::mesh::Mesh;
use fractile_codec::mesh::distance::surface_distance;
use fractile_server::{AppState, Store};
use http_body_util::BodyExt;
use tower::ServiceExt;

fn root() -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

async fn get(state: &Arc<AppState>, uri: &str) -> (StatusCode, Vec<u8>) {
    let (status, _, body) = get_gzip(state, uri, false).await;
    (status, body)
}

/// `uri`'s status, content encoding and body, asked with `Accept-Encoding: gzip` or not.
async fn get_gzip(
    state: &Arc<AppState>,
    uri: &str,
    gzip: bool,
) -> (StatusCode, Option<String>, Vec<u8>) {
    let mut req = Request::get(uri);
    if gzip {
        req = req.header("accept-encoding", "gzip, deflate, br");
    }
    let resp = fractile_server::app(state.clone())
        .oneshot(req.body(Body::empty()).unwrap())
        .await
        .unwrap();
    let status = resp.status();
    let encoding = resp
        .headers()
        .get("content-encoding")
        .map(|v| v.to_str().unwrap().to_string());
    let body = resp.into_body().collect().await.unwrap().to_bytes();
    (status, encoding, body.to_vec())
}

/// The length of `bytes` gzipped as the server gzips (flate2's default level).
fn gzip_len(bytes: &[u8]) -> usize {
    let mut z = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    std::io::Write::write_all(&mut z, bytes).unwrap();
    z.finish().unwrap().len()
}

/// A mesh's triangles as corner positions, each turned to start at its least corner (the
/// winding kept), sorted: equal for two meshes that differ only in vertex and triangle order.
fn triangle_set(m: &Mesh) -> Vec<[[u32; 3]; 3]> {
    let mut out: Vec<[[u32; 3]; 3]> = m
        .triangles
        .iter()
        .map(|t| {
            let c = t.map(|v| m.positions[v as usize].map(f32::to_bits));
            // The least of its three rotations (two corners may share a position).
            (0..3)
                .map(|k| [c[k], c[(k + 1) % 3], c[(k + 2) % 3]])
                .min()
                .unwrap()
        })
        .collect();
    out.sort();
    out
}

/// A subtree file's availability sets: (tiles, content, child subtrees).
fn read_subtree(raw: &[u8], levels: u32) -> (Vec<bool>, Vec<bool>, Vec<bool>) {
    assert_eq!(&raw[..4], b"subt");
    assert_eq!(u32::from_le_bytes(raw[4..8].try_into().unwrap()), 1);
    let json_len = u64::from_le_bytes(raw[8..16].try_into().unwrap()) as usize;
    let bin_len = u64::from_le_bytes(raw[16..24].try_into().unwrap()) as usize;
    assert_eq!(json_len % 8, 0, "the JSON chunk is padded to 8 bytes");
    assert_eq!(raw.len(), 24 + json_len + bin_len);
    let json: serde_json::Value = serde_json::from_slice(&raw[24..24 + json_len]).unwrap();
    let bin = &raw[24 + json_len..];
    let bits = |av: &serde_json::Value, n: usize| -> Vec<bool> {
        if let Some(c) = av.get("constant") {
            return vec![c.as_u64() == Some(1); n];
        }
        let view = &json["bufferViews"][av["bitstream"].as_u64().unwrap() as usize];
        let offset = view["byteOffset"].as_u64().unwrap() as usize;
        assert_eq!(offset % 8, 0, "bitstreams start on 8 bytes");
        let bits: Vec<bool> = (0..n)
            .map(|i| bin[offset + i / 8] >> (i % 8) & 1 == 1)
            .collect();
        let count = bits.iter().filter(|&&b| b).count() as u64;
        assert_eq!(av["availableCount"].as_u64(), Some(count));
        bits
    };
    let tiles = ((1usize << (3 * levels)) - 1) / 7;
    (
        bits(&json["tileAvailability"], tiles),
        bits(&json["contentAvailability"][0], tiles),
        bits(&json["childSubtreeAvailability"], 1 << (3 * levels)),
    )
}

/// The tile `k` (Morton order) `depth` levels under (x, y, z).
fn descendant([x, y, z]: [u32; 3], depth: u32, k: usize) -> [u32; 3] {
    let axis = |a: usize| {
        (0..depth).fold(0u32, |v, b| {
            v | ((k >> (3 * b as usize + a) & 1) as u32) << b
        })
    };
    [
        x << depth | axis(0),
        y << depth | axis(1),
        z << depth | axis(2),
    ]
}

/// A GLB's positions (through its node's translation and scale, as a viewer places them)
/// and triangles, turned back from glTF's y-up to the tiles' z-up. Reads float or 16-bit
/// positions and 16- or 32-bit indices.
fn read_glb(glb: &[u8]) -> Mesh {
    assert_eq!(&glb[..4], b"glTF");
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let json: serde_json::Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    let bin = &glb[20 + json_len + 8..];
    let node = &json["nodes"][0];
    let vec3 = |v: &serde_json::Value, default: f64| -> [f64; 3] {
        std::array::from_fn(|a| v.get(a).and_then(|x| x.as_f64()).unwrap_or(default))
    };
    let (t, s) = (vec3(&node["translation"], 0.0), vec3(&node["scale"], 1.0));
    // Each view's bytes, decoded by meshoptimizer's decoder where the view is compressed
    // (EXT_meshopt_compression), as a viewer decodes them.
    let views: Vec<Vec<u8>> = json["bufferViews"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| {
            let number = |v: &serde_json::Value, key: &str| v[key].as_u64().unwrap() as usize;
            let Some(m) = v["extensions"].get("EXT_meshopt_compression") else {
                let offset = number(v, "byteOffset");
                return bin[offset..offset + number(v, "byteLength")].to_vec();
            };
            let offset = number(m, "byteOffset");
            let stream = &bin[offset..offset + number(m, "byteLength")];
            let (count, stride) = (number(m, "count"), number(m, "byteStride"));
            match (m["mode"].as_str().unwrap(), stride) {
                ("ATTRIBUTES", 8) => meshopt::decode_vertex_buffer::<[u8; 8]>(stream, count)
                    .unwrap()
                    .concat(),
                ("ATTRIBUTES", 4) => meshopt::decode_vertex_buffer::<[u8; 4]>(stream, count)
                    .unwrap()
                    .concat(),
                ("TRIANGLES", 2) => meshopt::decode_index_buffer::<u16>(stream, count)
                    .unwrap()
                    .iter()
                    .flat_map(|i| i.to_le_bytes())
                    .collect(),
                ("TRIANGLES", 4) => meshopt::decode_index_buffer::<u32>(stream, count)
                    .unwrap()
                    .iter()
                    .flat_map(|i| i.to_le_bytes())
                    .collect(),
                (mode, stride) => panic!("meshopt mode {mode}, stride {stride}"),
            }
        })
        .collect();
    // Each element of an accessor as f64 (component type, view and stride).
    let read = |accessor: usize| -> Vec<Vec<f64>> {
        let a = &json["accessors"][accessor];
        let k = a["bufferView"].as_u64().unwrap() as usize;
        let (v, data) = (&json["bufferViews"][k], &views[k]);
        let n = a["count"].as_u64().unwrap() as usize;
        let width = if a["type"] == "VEC3" { 3 } else { 1 };
        let (size, get): (usize, fn(&[u8]) -> f64) = match a["componentType"].as_u64().unwrap() {
            5126 => (4, |b| f64::from(f32::from_le_bytes(b.try_into().unwrap()))),
            5125 => (4, |b| f64::from(u32::from_le_bytes(b.try_into().unwrap()))),
            5123 => (2, |b| f64::from(u16::from_le_bytes(b.try_into().unwrap()))),
            c => panic!("component type {c}"),
        };
        let stride = v["byteStride"]
            .as_u64()
            .map_or(size * width, |s| s as usize);
        (0..n)
            .map(|i| {
                (0..width)
                    .map(|c| get(&data[i * stride + c * size..][..size]))
                    .collect()
            })
            .collect()
    };
    let prim = &json["meshes"][0]["primitives"][0];
    let positions = read(prim["attributes"]["POSITION"].as_u64().unwrap() as usize)
        .into_iter()
        .map(|p| {
            let [x, y, z]: [f64; 3] = std::array::from_fn(|a| t[a] + s[a] * p[a]);
            [x as f32, -z as f32, y as f32]
        })
        .collect();
    let indices: Vec<u32> = read(prim["indices"].as_u64().unwrap() as usize)
        .into_iter()
        .map(|i| i[0] as u32)
        .collect();
    let triangles = indices
        .chunks_exact(3)
        .map(|t| [t[0], t[1], t[2]])
        .collect();
    Mesh {
        positions,
        triangles,
        normals: Vec::new(),
    }
}

/// An npm package installed under target/test-tools/`name` on first use, with `script`
/// written beside it; the script's path, or `None` without node and npm.
fn npm_tool(name: &str, package: &str, script: &str) -> Option<std::path::PathBuf> {
    let tools = root().join("target/test-tools").join(name);
    if !tools.join("node_modules").join(name).exists() {
        std::fs::create_dir_all(&tools).ok()?;
        // Install scripts stay off (npm's default): the parts used here are plain JavaScript.
        let ok = std::process::Command::new("npm")
            .args(["install", "--silent", "--no-audit", "--no-fund", "--prefix"])
            .arg(&tools)
            .arg(package)
            .status()
            .ok()?
            .success();
        if !ok {
            return None;
        }
    }
    let path = tools.join("check.mjs");
    std::fs::write(&path, script).ok()?;
    Some(path)
}

/// CesiumGS's 3D Tiles tools (npm `3d-tiles-tools`) and a script that traverses a tileset
/// folder as they do (implicit tiling through its subtree files), checks that each content
/// it names is a file there, and prints each content tile's URI, box and geometric error.
/// (Their validator, `3d-tiles-validator`, is not in this machine's npm registry.)
fn tiles_tools() -> Option<std::path::PathBuf> {
    npm_tool(
        "3d-tiles-tools",
        "3d-tiles-tools@0.5.4",
        r#"import { TilesetSources, TilesetTraversers } from '3d-tiles-tools';
import fs from 'fs';
import path from 'path';
const dir = process.argv[2];
const source = await TilesetSources.createAndOpen(dir);
const root = await TilesetTraversers.createTraversedRootTile(source, 'tileset.json');
const out = [];
for await (const t of TilesetTraversers.createIterableFromTraversedTile(root, false, false)) {
  if (t.isImplicitTilesetRoot()) continue;
  const tile = t.asFinalTile();
  for (const c of t.getFinalContents()) {
    if (!fs.existsSync(path.join(dir, c.uri))) throw new Error(`no file for ${c.uri}`);
    out.push({ content: c.uri, box: tile.boundingVolume.box, error: tile.geometricError });
  }
}
console.log(JSON.stringify(out));
"#,
    )
}

/// The Khronos glTF validator (npm `gltf-validator`) and a script that validates every GLB
/// of a folder and prints the counts as JSON.
fn gltf_validator() -> Option<std::path::PathBuf> {
    npm_tool(
        "gltf-validator",
        "gltf-validator@2.0.0-dev.3.10",
        r#"import validator from 'gltf-validator';
import fs from 'fs';
import path from 'path';
const dir = process.argv[2];
let files = 0, errors = 0, warnings = 0;
for (const f of fs.readdirSync(dir)) {
  const r = await validator.validateBytes(new Uint8Array(fs.readFileSync(path.join(dir, f))));
  files++; errors += r.issues.numErrors; warnings += r.issues.numWarnings;
  for (const m of r.issues.messages) if (m.severity === 0) console.error(f, m.code, m.message);
}
console.log(JSON.stringify({files, errors, warnings}));
"#,
    )
}

#[tokio::test]
async fn a_volume_streams_as_3d_tiles_whole_and_within_its_errors() {
    // The repository's meshes: a CAD part with sharp features, and a torus knot (genus 1).
    // Held-out meshes (not in the repository): `TILESET_EXTRA=a.off:b.off`.
    let extra = std::env::var("TILESET_EXTRA").unwrap_or_default();
    let mut meshes: Vec<std::path::PathBuf> = ["fandisk", "knot2"]
        .iter()
        .map(|n| root().join(format!("testdata/mesh/{n}.off")))
        .collect();
    meshes.extend(extra.split(':').filter(|p| !p.is_empty()).map(Into::into));
    for path in meshes {
        walk_the_tileset_of(&path).await;
    }
}

async fn walk_the_tileset_of(path: &std::path::Path) {
    let name = &path
        .file_stem()
        .unwrap()
        .to_string_lossy()
        .replace(|c: char| !c.is_ascii_alphanumeric(), "-");
    println!("\n{name}:");
    let text = std::fs::read_to_string(path).unwrap();
    let source = Mesh::parse_off(&text).unwrap();
    let enc = fractile_codec::encode::volume::encode_mesh(
        &source,
        &fractile_codec::encode::volume::MeshSettings::default(),
        name,
    )
    .unwrap();
    let dir = std::env::temp_dir().join(format!("fractile-3dtiles-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join(format!("{name}.fra")), &enc.bytes).unwrap();
    let (store, _) = Store::open(&dir).unwrap();
    let state = Arc::new(AppState::new(store, "http://test".into()));
    let base = &format!("/v1/assets/{name}");

    let (status, body) = get(&state, &format!("{base}/tileset.json")).await;
    assert_eq!(status, StatusCode::OK);
    let tileset: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(tileset["asset"]["version"], "1.1");
    let root_tile = &tileset["root"];
    // Plain tiles asked of the tileset are what its content template asks for.
    let (_, plain) = get(&state, &format!("{base}/tileset.json?compression=plain")).await;
    let plain: serde_json::Value = serde_json::from_slice(&plain).unwrap();
    assert_eq!(
        plain["root"]["content"]["uri"],
        "3dtiles/{level}/{x}/{y}/{z}.glb?compression=plain"
    );
    let implicit = &root_tile["implicitTiling"];
    assert_eq!(implicit["subdivisionScheme"], "OCTREE");
    let (levels, per) = (
        implicit["availableLevels"].as_u64().unwrap() as u32,
        implicit["subtreeLevels"].as_u64().unwrap() as u32,
    );
    let b: Vec<f64> = root_tile["boundingVolume"]["box"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let (centre, half) = ([b[0], b[1], b[2]], b[3]);
    let root_error = root_tile["geometricError"].as_f64().unwrap();
    assert!(tileset["geometricError"].as_f64().unwrap() > root_error);
    // The root box bounds the source mesh (the volume's grid is around it).
    for p in &source.positions {
        for a in 0..3 {
            assert!(
                (f64::from(p[a]) - centre[a]).abs() <= half,
                "{p:?} outside the root"
            );
        }
    }
    let tile_box = |level: u32, t: [u32; 3]| {
        let side = 2.0 * half / f64::from(1u32 << level);
        let lo: [f64; 3] = std::array::from_fn(|a| centre[a] - half + f64::from(t[a]) * side);
        (lo, lo.map(|v| v + side))
    };

    // Walk every subtree a viewer can reach; fetch every content tile they list.
    let mut meshes: BTreeMap<(u32, [u32; 3]), Mesh> = BTreeMap::new();
    let mut glbs: Vec<(String, Vec<u8>)> = Vec::new();
    let mut gzipped: BTreeMap<(u32, [u32; 3]), usize> = BTreeMap::new();
    // Every file at the path the tileset names, for 3D Tiles tools to read as a folder.
    let folder = dir.join("tileset");
    let keep = |rel: &str, bytes: &[u8]| {
        let path = folder.join(rel);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, bytes).unwrap();
    };
    keep("tileset.json", &body);
    let mut empty: Vec<(u32, [u32; 3])> = Vec::new();
    let mut pending = vec![(0u32, [0u32; 3])];
    while let Some((level, at)) = pending.pop() {
        let uri = format!(
            "{base}/3dtiles/subtrees/{level}/{}/{}/{}.subtree",
            at[0], at[1], at[2]
        );
        let (status, raw) = get(&state, &uri).await;
        assert_eq!(status, StatusCode::OK, "{uri}");
        keep(&uri[base.len() + 1..], &raw);
        let (tiles, content, children) = read_subtree(&raw, per);
        assert!(tiles[0], "{uri}: a subtree's root exists");
        let mut i = 0;
        for r in 0..per {
            for k in 0..1usize << (3 * r) {
                let (l, t) = (level + r, descendant(at, r, k));
                assert!(
                    !content[i] || tiles[i],
                    "content without its tile at {l} {t:?}"
                );
                if r > 0 && tiles[i] {
                    let parent = ((1usize << (3 * (r - 1))) - 1) / 7 + (k >> 3);
                    assert!(tiles[parent], "a tile without its parent at {l} {t:?}");
                }
                if l >= levels {
                    assert!(!tiles[i], "a tile past the available levels");
                } else if content[i] {
                    let uri = format!("{base}/3dtiles/{l}/{}/{}/{}.glb", t[0], t[1], t[2]);
                    let (status, glb) = get(&state, &uri).await;
                    assert_eq!(status, StatusCode::OK, "{uri}");
                    let mesh = read_glb(&glb);
                    let name = format!("{l}_{}_{}_{}", t[0], t[1], t[2]);
                    // Every third tile also plain (what the validator reads whole) and
                    // gzipped: the same surface, the same bytes.
                    if meshes.len().is_multiple_of(3) {
                        let plain = format!("{uri}?compression=plain");
                        let (status, raw) = get(&state, &plain).await;
                        assert_eq!(status, StatusCode::OK, "{plain}");
                        let same = triangle_set(&read_glb(&raw)) == triangle_set(&mesh);
                        assert!(same, "{uri}: meshopt's surface is not the plain tile's");
                        assert!(raw.len() >= glb.len(), "{uri}: meshopt larger");
                        glbs.push((format!("{name}_plain.glb"), raw));
                        let (status, coding, zipped) = get_gzip(&state, &uri, true).await;
                        assert_eq!((status, coding.as_deref()), (StatusCode::OK, Some("gzip")));
                        let mut unzipped = Vec::new();
                        std::io::Read::read_to_end(
                            &mut flate2::read::GzDecoder::new(&zipped[..]),
                            &mut unzipped,
                        )
                        .unwrap();
                        assert_eq!(unzipped, glb, "{uri} gzipped");
                    }
                    meshes.insert((l, t), mesh);
                    keep(&uri[base.len() + 1..], &glb);
                    gzipped.insert((l, t), gzip_len(&glb));
                    glbs.push((format!("{name}.glb"), glb));
                } else if tiles[i] && empty.len() < 8 {
                    empty.push((l, t));
                }
                i += 1;
            }
        }
        if level + per < levels {
            for (k, &c) in children.iter().enumerate() {
                if c {
                    pending.push((level + per, descendant(at, per, k)));
                }
            }
        } else {
            assert!(
                children.iter().all(|&c| !c),
                "child subtrees past the last level"
            );
        }
    }
    // A tile that exists without content has no surface to send.
    for (l, t) in &empty {
        let uri = format!("{base}/3dtiles/{l}/{}/{}/{}.glb", t[0], t[1], t[2]);
        assert_eq!(get(&state, &uri).await.0, StatusCode::NOT_FOUND, "{uri}");
    }

    // Each tile: a surface (no empty content), inside its box.
    for ((l, t), m) in &meshes {
        assert!(!m.triangles.is_empty(), "empty content at {l} {t:?}");
        let (lo, hi) = tile_box(*l, *t);
        for p in &m.positions {
            for a in 0..3 {
                let v = f64::from(p[a]);
                assert!(
                    v >= lo[a] - 1e-5 && v <= hi[a] + 1e-5,
                    "{p:?} outside {l} {t:?}"
                );
            }
        }
    }
    // No cracks: where two tiles of a level touch, their surfaces cross the shared face at
    // the same vertices.
    let mut faces = 0;
    for ((l, t), m) in &meshes {
        let (_, hi) = tile_box(*l, *t);
        for a in 0..3 {
            let mut n = *t;
            n[a] += 1;
            let Some(other) = meshes.get(&(*l, n)) else {
                continue;
            };
            let on_face = |m: &Mesh| -> HashSet<[i64; 3]> {
                m.positions
                    .iter()
                    .filter(|p| (f64::from(p[a]) - hi[a]).abs() < 1e-7)
                    .map(|p| p.map(|v| (f64::from(v) * 1e5).round() as i64))
                    .collect()
            };
            let (mine, theirs) = (on_face(m), on_face(other));
            assert_eq!(mine, theirs, "a crack between {l} {t:?} and {n:?}");
            faces += usize::from(!mine.is_empty());
        }
    }
    assert!(
        faces > 10,
        "only {faces} shared faces crossed by the surface"
    );

    // Every level within the geometric error it states, of the source mesh (Hausdorff,
    // sampled both ways).
    // The level whose sampling is the encoded grid's (deeper ones add the continuous
    // decode's detail, not the source's): what a viewer fetches to get there, refining level
    // by level (each level replaces its parent), against the source mesh as GLB.
    let grid = fractile_codec::Asset::from_bytes(&enc.bytes)
        .unwrap()
        .volume()
        .unwrap()
        .size();
    let source_level = (grid / fractile_codec::extract::octree::CELLS)
        .max(1)
        .ilog2();
    let (mut fetched, mut fetched_gzip) = (0usize, 0usize);
    println!(
        "| level | tiles | mean GLB bytes | bytes fetched to this level | gzipped | geometricError | Hausdorff to the source |"
    );
    println!("|---|---|---|---|---|---|---|");
    for level in 0..levels {
        let mut whole = Mesh::default();
        let mut tiles = 0;
        let bytes: usize = glbs
            .iter()
            .filter(|(name, _)| name.starts_with(&format!("{level}_")) && !name.contains("plain"))
            .map(|(_, g)| g.len())
            .sum();
        fetched_gzip += gzipped
            .range((level, [0; 3])..(level + 1, [0; 3]))
            .map(|(_, n)| n)
            .sum::<usize>();
        for ((l, _), m) in meshes.range((level, [0; 3])..(level + 1, [0; 3])) {
            debug_assert_eq!(*l, level);
            let base = whole.positions.len() as u32;
            whole.positions.extend_from_slice(&m.positions);
            whole
                .triangles
                .extend(m.triangles.iter().map(|t| t.map(|v| v + base)));
            tiles += 1;
        }
        let error = root_error / f64::from(1u32 << level);
        let d = surface_distance(&whole, &source, 100_000);
        fetched += bytes;
        println!(
            "| {level} | {tiles} | {} | {fetched} | {fetched_gzip} | {error:.4} | {:.4} |",
            bytes / tiles.max(1),
            d.hausdorff
        );
        if level == source_level {
            let source_glb = source.to_glb().len();
            println!(
                "the source mesh as GLB: {source_glb} bytes ({} gzipped); to level {level}: \
                 {fetched} ({fetched_gzip} gzipped)",
                gzip_len(&source.to_glb())
            );
            assert!(
                fetched <= source_glb,
                "{fetched} bytes to reach the encoded grid's detail, the source is {source_glb}"
            );
        }
        assert!(tiles > 0, "level {level} has no content");
        assert!(
            d.hausdorff <= error,
            "level {level}: {} from the source, stating {error}",
            d.hausdorff
        );
    }

    // The tileset, read by CesiumGS's 3D Tiles tools: their implicit tiling reads our
    // subtrees and names the content tiles, their boxes and geometric errors, which must be
    // ours (every tile's surface inside the box they compute, the error they halve).
    match tiles_tools() {
        Some(script) => {
            let out = std::process::Command::new("node")
                .arg(&script)
                .arg(&folder)
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "3d-tiles-tools: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            let listed: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap();
            let mut seen = HashSet::new();
            for tile in &listed {
                let uri = tile["content"].as_str().unwrap();
                let at: Vec<u32> = uri
                    .trim_start_matches("3dtiles/")
                    .trim_end_matches(".glb")
                    .split('/')
                    .map(|v| v.parse().unwrap())
                    .collect();
                let (l, t) = (at[0], [at[1], at[2], at[3]]);
                let m = meshes
                    .get(&(l, t))
                    .unwrap_or_else(|| panic!("3d-tiles-tools lists {uri}, the walk did not"));
                let b: Vec<f64> = tile["box"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_f64().unwrap())
                    .collect();
                let (c, h) = ([b[0], b[1], b[2]], [b[3], b[7], b[11]]);
                for p in &m.positions {
                    for a in 0..3 {
                        let d = (f64::from(p[a]) - c[a]).abs();
                        assert!(
                            d <= h[a] + 1e-5,
                            "{p:?} outside {uri}'s box by 3d-tiles-tools"
                        );
                    }
                }
                let error = tile["error"].as_f64().unwrap();
                let ours = root_error / f64::from(1u32 << l);
                assert!(
                    (error - ours).abs() <= 1e-9 * ours,
                    "{uri}: {error} against {ours}"
                );
                seen.insert((l, t));
            }
            assert_eq!(seen.len(), listed.len(), "a content listed twice");
            assert_eq!(
                seen.len(),
                meshes.len(),
                "3d-tiles-tools and the walk differ"
            );
            println!("3d-tiles-tools: {} content tiles, as walked", listed.len());
        }
        None if std::env::var_os("CI").is_some() => {
            panic!("3D Tiles tools (npm 3d-tiles-tools) are needed under CI")
        }
        None => println!("no node/npm here: 3d-tiles-tools were not run"),
    }

    // The GLBs, read by a validator we did not write: the Khronos glTF validator.
    let files = dir.join("glb");
    std::fs::create_dir_all(&files).unwrap();
    for (name, glb) in &glbs {
        std::fs::write(files.join(name), glb).unwrap();
    }
    match gltf_validator() {
        Some(script) => {
            let out = std::process::Command::new("node")
                .arg(&script)
                .arg(&files)
                .output()
                .unwrap();
            let report = String::from_utf8_lossy(&out.stdout);
            println!("gltf-validator: {report}");
            assert!(
                out.status.success(),
                "{report} {}",
                String::from_utf8_lossy(&out.stderr)
            );
            let r: serde_json::Value = serde_json::from_str(report.trim()).unwrap();
            assert_eq!(r["files"].as_u64(), Some(glbs.len() as u64));
            assert_eq!(r["errors"].as_u64(), Some(0), "{report}");
        }
        None if std::env::var_os("CI").is_some() => {
            panic!("the glTF validator (npm gltf-validator) is needed under CI")
        }
        None => println!("no node/npm here: the glTF validator was not run"),
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// What a viewer or a hand can get wrong gets a clear error, never a panic or a tile: levels
/// past the last, indices past a level, words for numbers, another extension, subtrees off
/// their levels, a placement half given, and a raster asked for 3D Tiles.
#[tokio::test]
async fn bad_3d_tiles_requests_get_clear_errors() {
    let text = std::fs::read_to_string(root().join("testdata/mesh/knot2.off")).unwrap();
    let mesh = Mesh::parse_off(&text).unwrap();
    let settings = fractile_codec::encode::volume::MeshSettings {
        grid: 32,
        ..Default::default()
    };
    let enc = fractile_codec::encode::volume::encode_mesh(&mesh, &settings, "knot2").unwrap();
    let dir = std::env::temp_dir().join(format!("fractile-3dtiles-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("knot.fra"), &enc.bytes).unwrap();
    let raster = fractile_codec::Raster::open(&root().join("testdata/camera.png")).unwrap();
    let image = fractile_codec::encode_default(&raster, 0.25, &|_, _| {}).unwrap();
    std::fs::write(dir.join("camera.fra"), &image.bytes).unwrap();
    let (store, _) = Store::open(&dir).unwrap();
    let state = Arc::new(AppState::new(store, "http://test".into()));
    let (status, body) = get(&state, "/v1/assets/knot/tileset.json").await;
    assert_eq!(status, StatusCode::OK);
    let levels = serde_json::from_slice::<serde_json::Value>(&body).unwrap()["root"]
        ["implicitTiling"]["availableLevels"]
        .as_u64()
        .unwrap();
    let cases = [
        (
            format!("/v1/assets/knot/3dtiles/{levels}/0/0/0.glb"),
            404,
            "no_tile",
        ),
        ("/v1/assets/knot/3dtiles/1/2/0/0.glb".into(), 404, "no_tile"),
        (
            "/v1/assets/knot/3dtiles/1/0/0/x.glb".into(),
            400,
            "bad_path",
        ),
        (
            "/v1/assets/knot/3dtiles/1/0/0/99999999999.glb".into(),
            400,
            "bad_path",
        ),
        (
            "/v1/assets/knot/3dtiles/0/0/0/0.png".into(),
            404,
            "no_route",
        ),
        (
            "/v1/assets/knot/3dtiles/subtrees/1/0/0/0.subtree".into(),
            404,
            "no_tile",
        ),
        (
            "/v1/assets/knot/3dtiles/subtrees/0/0/0/0.glb".into(),
            404,
            "no_route",
        ),
        (
            "/v1/assets/knot/tileset.json?lon=10".into(),
            400,
            "bad_point",
        ),
        (
            "/v1/assets/knot/tileset.json?lon=10&lat=95".into(),
            400,
            "bad_point",
        ),
        (
            "/v1/assets/knot/tileset.json?lon=10&lat=5&scale=0".into(),
            400,
            "bad_point",
        ),
        (
            "/v1/assets/knot/3dtiles/0/0/0/0.glb?compression=draco".into(),
            400,
            "bad_encoding",
        ),
        (
            "/v1/assets/knot/tileset.json?compression=zip".into(),
            400,
            "bad_encoding",
        ),
        ("/v1/assets/camera/tileset.json".into(), 400, "not_volume"),
        (
            "/v1/assets/camera/3dtiles/0/0/0/0.glb".into(),
            400,
            "not_volume",
        ),
        (
            "/v1/assets/nothing/tileset.json".into(),
            404,
            "unknown_asset",
        ),
    ];
    for (uri, want, code) in cases {
        let (status, body) = get(&state, &uri).await;
        assert_eq!(
            status.as_u16(),
            want,
            "{uri}: {}",
            String::from_utf8_lossy(&body)
        );
        let err: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(err["code"], code, "{uri}");
    }
    // A placement: the root's transform is the east-north-up frame there (its origin on the
    // ellipsoid's surface, its up axis the ellipsoid's normal).
    let (_, body) = get(&state, "/v1/assets/knot/tileset.json?lon=0&lat=90&scale=2").await;
    let t: Vec<f64> =
        serde_json::from_slice::<serde_json::Value>(&body).unwrap()["root"]["transform"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
    assert_eq!(t.len(), 16);
    // Up (the third column) is +z at the pole, scaled by 2; the origin 6,356,752 m up z.
    assert!((t[8]).abs() < 1e-9 && (t[9]).abs() < 1e-9 && (t[10] - 2.0).abs() < 1e-9);
    assert!((t[14] - 6_356_752.3).abs() < 1.0, "{t:?}");
    std::fs::remove_dir_all(&dir).ok();
}
