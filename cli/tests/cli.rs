//! The `fractile` command line as a user runs it, on the repo's real test data.

use std::path::{Path, PathBuf};
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_fractile"))
}

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

fn json(out: &std::process::Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("JSON on stdout")
}

fn tempdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("fractile-cli-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn encode_info_decode_compare_round_trip_on_a_dem() {
    let dir = tempdir("dem");
    let asset = dir.join("topo.fra");
    let enc = json(
        &bin()
            .arg("encode")
            .arg(data("topobathy.tif"))
            .arg("-o")
            .arg(&asset)
            .args(["--tolerance", "4", "--json"])
            .output()
            .unwrap(),
    );
    let bytes = std::fs::metadata(&asset).unwrap().len();
    assert_eq!(enc["bytes"].as_u64(), Some(bytes));
    assert!(enc["ratio"].as_f64().unwrap() > 2.0);

    let info = json(
        &bin()
            .arg("info")
            .arg(&asset)
            .arg("--json")
            .output()
            .unwrap(),
    );
    assert_eq!(info["kind"], "HeightField");
    assert_eq!(
        (info["width"].as_u64(), info["height"].as_u64()),
        (Some(120), Some(91))
    );
    assert_eq!(info["georef"]["epsg"], 4326);

    // Float GeoTIFF at native size: `compare` must find the error the encoder reported.
    let tif = dir.join("topo.tif");
    let out = bin()
        .arg("decode")
        .arg(&asset)
        .arg("-o")
        .arg(&tif)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let cmp = json(
        &bin()
            .arg("compare")
            .arg(data("topobathy.tif"))
            .arg(&tif)
            .arg("--json")
            .output()
            .unwrap(),
    );
    let (a, b) = (cmp["rmse"].as_f64().unwrap(), enc["rmse"].as_f64().unwrap());
    assert!(
        (a - b).abs() < 1e-3 * b.max(1.0),
        "compare {a} vs encoder {b}"
    );

    // Any size, and a window decoded continuously.
    let big = dir.join("big.png");
    assert!(
        bin()
            .arg("decode")
            .arg(&asset)
            .arg("-o")
            .arg(&big)
            .args(["--scale", "2.5"])
            .status()
            .unwrap()
            .success()
    );
    let img = image::open(&big).unwrap();
    assert_eq!((img.width(), img.height()), (300, 228));
    let win = dir.join("win.tif");
    let st = bin()
        .arg("decode")
        .arg(&asset)
        .arg("-o")
        .arg(&win)
        .args([
            "--window",
            "0.25,0.25,0.5,0.75",
            "--width",
            "64",
            "--method",
            "continuous",
            "--iterations",
            "12",
        ])
        .status()
        .unwrap();
    assert!(st.success());
    let r = fractile_codec::Raster::open(&win).unwrap();
    assert_eq!((r.width, r.height), (64, 97));
    assert!(r.georef.is_some(), "the window keeps a georeference");
}

#[test]
fn target_bpp_lands_at_or_under_the_target() {
    let dir = tempdir("bpp");
    let asset = dir.join("cam.fra");
    let enc = json(
        &bin()
            .arg("encode")
            .arg(data("camera.png"))
            .arg("-o")
            .arg(&asset)
            .args(["--target-bpp", "0.25", "--json"])
            .output()
            .unwrap(),
    );
    let bpp = enc["bpp"].as_f64().unwrap();
    assert!(bpp <= 0.25 && bpp > 0.2, "{bpp}");
    assert!(enc["psnr"].as_f64().unwrap() > 25.0);
}

#[test]
fn bad_input_gives_a_clear_error_and_no_output() {
    let dir = tempdir("bad");
    let junk = dir.join("junk.fra");
    std::fs::write(&junk, b"FRACTILE not really an asset").unwrap();
    let out = bin().arg("info").arg(&junk).output().unwrap();
    assert!(!out.status.success());
    let msg = String::from_utf8_lossy(&out.stderr);
    assert!(msg.contains("asset") && msg.contains("junk.fra"), "{msg}");

    let missing = bin()
        .arg("encode")
        .arg(dir.join("nope.png"))
        .arg("-o")
        .arg(dir.join("x.fra"))
        .output()
        .unwrap();
    assert!(!missing.status.success());
    assert!(!dir.join("x.fra").exists());

    let bad = bin()
        .arg("encode")
        .arg(data("camera.png"))
        .arg("-o")
        .arg(dir.join("y.fra"))
        .args(["--min-range", "3"])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&bad.stderr).contains("powers of two"));
    assert!(!dir.join("y.fra").exists());

    let fast = bin()
        .arg("encode")
        .arg(data("camera.png"))
        .arg("-o")
        .arg(dir.join("z.fra"))
        .args(["--speed", "9"])
        .output()
        .unwrap();
    assert!(!fast.status.success());
    assert!(String::from_utf8_lossy(&fast.stderr).contains("not a preset"));
    assert!(!dir.join("z.fra").exists());
}

#[test]
fn a_mesh_encodes_to_a_volume_and_back_to_a_closed_mesh() {
    let dir = tempdir("mesh");
    let asset = dir.join("knot.fra");
    let enc = json(
        &bin()
            .arg("encode")
            .arg(data("mesh/knot2.off"))
            .args(["-o"])
            .arg(&asset)
            .args(["--grid", "40", "--json"])
            .output()
            .unwrap(),
    );
    assert_eq!(enc["codec"], "ifs3d-octree");
    assert_eq!(enc["grid"], 40);
    let bytes = std::fs::metadata(&asset).unwrap().len();
    assert_eq!(enc["bytes"].as_u64().unwrap(), bytes);
    // The ratio against signed bytes is the grid's bytes over the file's.
    let ratio = enc["ratio_i8"].as_f64().unwrap();
    assert!(
        (ratio - 64000.0 / bytes as f64).abs() < 1e-9 && ratio > 10.0,
        "{enc}"
    );
    // The seed's "const range R": every range 4 voxels, more maps than the adaptive octree.
    let fixed = json(
        &bin()
            .arg("encode")
            .arg(data("mesh/knot2.off"))
            .arg("-o")
            .arg(dir.join("fixed.fra"))
            .args(["--grid", "40", "--const-range", "4", "--json"])
            .output()
            .unwrap(),
    );
    // The 40-voxel grid is padded to a frame of 48 (a multiple of the 16-voxel top ranges).
    assert_eq!(fixed["transforms"], 1728); // (48 / 4)^3
    assert!(fixed["transforms"].as_u64() > enc["transforms"].as_u64());
    // Meshes on both backends: the same surface; OBJ with normals.
    let mut counts = Vec::new();
    for backend in ["cpu", "gpu"] {
        let obj = dir.join(format!("knot-{backend}.obj"));
        let m = json(
            &bin()
                .arg("mesh")
                .arg(&asset)
                .arg("-o")
                .arg(&obj)
                .args(["--resolution", "64", "--json", "--backend", backend])
                .output()
                .unwrap(),
        );
        assert_eq!(m["backend"], backend);
        let text = std::fs::read_to_string(&obj).unwrap();
        let faces = text.lines().filter(|l| l.starts_with("f ")).count();
        assert_eq!(faces as u64, m["triangles"].as_u64().unwrap());
        assert!(text.contains("\nvn "));
        counts.push(faces as f64);
    }
    assert!(
        (counts[0] - counts[1]).abs() <= 0.005 * counts[0],
        "{counts:?}"
    );
    // Errors a user can act on.
    let out = bin()
        .arg("mesh")
        .arg(&asset)
        .arg("-o")
        .arg(dir.join("x.stl"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains(".obj, .ply or .glb"));
    let out = bin()
        .arg("decode")
        .arg(&asset)
        .arg("-o")
        .arg(dir.join("x.png"))
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("fractile mesh"));
    let out = bin()
        .arg("encode")
        .arg(data("mesh/knot2.off"))
        .arg("-o")
        .arg(dir.join("y.fra"))
        .args(["--const-range", "5"])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("ranges are [4, 8, 16]"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn geojson_encodes_to_a_curve_asset_and_back_at_any_level() {
    let dir = tempdir("curve");
    let asset = dir.join("coast.fra");
    let enc = json(
        &bin()
            .arg("encode")
            .arg(data("curve/coast5.geojson"))
            .arg("-o")
            .arg(&asset)
            .args(["--codec", "curve", "--tolerance", "0.009", "--json"])
            .output()
            .unwrap(),
    );
    assert_eq!(enc["codec"], "curve-pifs");
    assert_eq!(enc["polylines"], 5);
    let bytes = std::fs::metadata(&asset).unwrap().len();
    assert_eq!(enc["bytes"].as_u64().unwrap(), bytes);
    let points = enc["points"].as_u64().unwrap();
    assert!((enc["ratio_f32"].as_f64().unwrap() - (8 * points) as f64 / bytes as f64).abs() < 1e-9);
    let hausdorff = enc["hausdorff_m"].as_f64().unwrap();
    assert!(hausdorff > 0.0 && hausdorff <= 0.009 * 111_195.0 * 1.000_001);
    // Default level: every input vertex, one feature per ring, in order.
    let out = dir.join("coast.geojson");
    let dec = json(
        &bin()
            .arg("curve")
            .arg(&asset)
            .arg("-o")
            .arg(&out)
            .arg("--json")
            .output()
            .unwrap(),
    );
    assert_eq!(dec["points"].as_u64().unwrap(), points);
    let back =
        fractile_codec::codecs::curve::geojson::read(&std::fs::read_to_string(&out).unwrap())
            .unwrap();
    let src = fractile_codec::codecs::curve::geojson::read(
        &std::fs::read_to_string(data("curve/coast5.geojson")).unwrap(),
    )
    .unwrap();
    assert_eq!(back.len(), src.len());
    for (a, b) in back.iter().zip(&src) {
        assert_eq!(a.points.len(), b.points.len());
        assert_eq!(a.closed, b.closed);
    }
    // A coarser and a deeper level.
    let finest = dec["finest_level"].as_u64().unwrap();
    for (level, fewer) in [(finest - 2, true), (finest + 1, false)] {
        let d = json(
            &bin()
                .arg("curve")
                .arg(&asset)
                .arg("-o")
                .arg(dir.join("l.geojson"))
                .args(["--level", &level.to_string(), "--json"])
                .output()
                .unwrap(),
        );
        assert_eq!(d["points"].as_u64().unwrap() < points, fewer, "{d}");
    }
    // Refusals: a huge level, and a curve asked of a raster asset.
    let huge = bin()
        .arg("curve")
        .arg(&asset)
        .arg("-o")
        .arg(dir.join("h.geojson"))
        .args(["--level", "80"])
        .output()
        .unwrap();
    assert!(!huge.status.success());
    assert!(String::from_utf8_lossy(&huge.stderr).contains("2^26"));
    // `decode` of a curve asset says what decodes curves (it panicked in the raster writer).
    let raster = bin()
        .arg("decode")
        .arg(&asset)
        .arg("-o")
        .arg(dir.join("c.png"))
        .output()
        .unwrap();
    assert_eq!(raster.status.code(), Some(1));
    let err = String::from_utf8_lossy(&raster.stderr);
    assert!(err.contains("fractile curve"), "{err}");
    assert!(!dir.join("c.png").exists());
}

/// The crafted files of issue 35 are refused by `info` and `decode` with a message, never an
/// abort (they made `fractile info` abort on an allocation failure).
#[test]
fn crafted_files_are_refused_by_the_command_line() {
    for name in [
        "frame-bomb-65536.fra",
        "frame-bomb-16384.fra",
        "metadata-bomb-65536.fra",
    ] {
        for cmd in [vec!["info"], vec!["decode", "-o", "/dev/null"]] {
            let out = bin()
                .arg(cmd[0])
                .arg(data(&format!("hostile/{name}")))
                .args(&cmd[1..])
                .output()
                .unwrap();
            assert_eq!(out.status.code(), Some(1), "{name} {cmd:?}");
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(err.starts_with("fractile: asset:"), "{name} {cmd:?}: {err}");
        }
    }
}

/// `--codec projected --max-error E`, as a DEM user runs it: the promise reported and kept
/// (the decoded GeoTIFF compared with the source by `compare`), and the flags it refuses.
#[test]
fn projected_max_error_is_kept_through_encode_decode_and_compare() {
    let dir = tempdir("projected");
    let asset = dir.join("j.fra");
    let enc = json(
        &bin()
            .arg("encode")
            .arg(data("jacksboro.tif"))
            .arg("-o")
            .arg(&asset)
            .args(["--codec", "projected", "--max-error", "3", "--json"])
            .output()
            .unwrap(),
    );
    assert_eq!(enc["codec"], "projected");
    assert_eq!(enc["max_error_bound"], 3.0);
    assert!(enc["max_error"].as_f64().unwrap() <= 3.0 + 1e-3, "{enc}");
    let tif = dir.join("j.tif");
    let out = bin()
        .arg("decode")
        .arg(&asset)
        .arg("-o")
        .arg(&tif)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let cmp = json(
        &bin()
            .arg("compare")
            .arg(data("jacksboro.tif"))
            .arg(&tif)
            .arg("--json")
            .output()
            .unwrap(),
    );
    assert!(cmp["max_error"].as_f64().unwrap() <= 3.0 + 1e-3, "{cmp}");
    // A bounded rate: within the size, every cell within the bound it reports.
    let bounded = json(
        &bin()
            .arg("encode")
            .arg(data("jacksboro.tif"))
            .arg("-o")
            .arg(dir.join("b.fra"))
            .args([
                "--codec",
                "projected",
                "--target-bpp",
                "0.8",
                "--bounded",
                "--json",
            ])
            .output()
            .unwrap(),
    );
    let bound = bounded["max_error_bound"]
        .as_f64()
        .expect("a bound reported");
    assert!(bounded["bpp"].as_f64().unwrap() <= 0.8, "{bounded}");
    assert!(bounded["max_error"].as_f64().unwrap() <= bound, "{bounded}");
    // A bound is for this codec only, and this codec needs a bound or a size.
    for args in [
        vec!["--codec", "quadtree-pifs", "--max-error", "3"],
        vec!["--codec", "projected"],
        vec!["--codec", "projected", "--tolerance", "2"],
        vec!["--codec", "projected", "--max-error", "3", "--bounded"],
        vec!["--codec", "fis-rect", "--target-bpp", "0.8", "--bounded"],
        vec!["--tolerance", "2", "--bounded"],
    ] {
        let out = bin()
            .arg("encode")
            .arg(data("jacksboro.tif"))
            .arg("-o")
            .arg(dir.join("x.fra"))
            .args(&args)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{args:?} was accepted");
        assert!(!dir.join("x.fra").exists(), "{args:?} left a file");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// With no `--codec`, a height field is coded by `projected` under a bounded rate (0.8 bits a
/// cell unless given), so the asset reports the bound every cell keeps; a quadtree-only flag
/// keeps it on the quadtree; an image goes to the quadtree.
#[test]
fn a_raster_without_a_codec_is_coded_projected() {
    let dir = std::env::temp_dir().join(format!("fractile-cli-auto-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let encode = |input: &str, args: &[&str]| {
        let out = bin()
            .arg("encode")
            .arg(data(input))
            .arg("-o")
            .arg(dir.join("a.fra"))
            .args(args)
            .arg("--json")
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
    };
    for (args, bpp) in [(vec![], 0.8), (vec!["--target-bpp", "1.6"], 1.6)] {
        let r = encode("jacksboro.tif", &args);
        assert_eq!(r["codec"], "projected", "{args:?}: {r}");
        assert!(r["bpp"].as_f64().unwrap() <= bpp, "{r}");
        // A bounded rate spends most of it (a file far under the rate would be an unbounded
        // default or another codec).
        assert!(r["bpp"].as_f64().unwrap() > 0.8 * bpp, "{r}");
        let bound = r["max_error_bound"].as_f64().expect("a bound");
        assert!(r["max_error"].as_f64().unwrap() <= bound, "{r}");
    }
    // A warped DEM with nodata wedges: its mask is coded beside the streams, and the file still
    // keeps the rate (it went 1.8% over before the encoder counted it).
    let r = encode("jacksboro-utm.tif", &[]);
    assert_eq!(r["codec"], "projected", "{r}");
    assert!(r["bpp"].as_f64().unwrap() <= 0.8, "{r}");
    let r = encode("jacksboro.tif", &["--max-error", "5"]);
    assert_eq!(r["codec"], "projected", "{r}");
    assert!(r["max_error"].as_f64().unwrap() <= 5.0, "{r}");
    for (input, args) in [
        ("jacksboro.tif", vec!["--tolerance", "3"]),
        ("jacksboro.tif", vec!["--speed", "3", "--target-bpp", "0.8"]),
        ("camera.png", vec!["--speed", "3"]),
    ] {
        let r = encode(input, &args);
        assert_eq!(r["codec"], "quadtree-pifs", "{input} {args:?}: {r}");
        assert!(r["max_error_bound"].is_null(), "{r}");
    }
    // Images (issue 77): projected under the rate, 0.75 bits a pixel unless given, grey or
    // colour; the rate buys PSNR, not a bound.
    for (input, args, bpp) in [
        ("camera.png", vec![], 0.75),
        ("astronaut.png", vec![], 0.75),
        ("camera.png", vec!["--target-bpp", "0.25"], 0.25),
    ] {
        let r = encode(input, &args);
        assert_eq!(r["codec"], "projected", "{input} {args:?}: {r}");
        let got = r["bpp"].as_f64().unwrap();
        assert!(got <= bpp && got > 0.9 * bpp, "{input} {args:?}: {r}");
        assert!(r["max_error_bound"].is_null(), "{r}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Issue 30's mosaics: a real DEM cut into four GeoTIFFs (sharing an edge row and column, as
/// SRTM tiles do), given as files or as their folder, encodes as the DEM itself does; an input
/// on another grid is resampled onto theirs.
#[test]
fn geotiffs_that_tile_an_area_encode_as_one_asset() {
    use fractile_codec::raster::write_geotiff_f32;
    let dir = tempdir("mosaic");
    let tiles = dir.join("tiles");
    std::fs::create_dir_all(&tiles).unwrap();
    let src = fractile_codec::Raster::open(&data("jacksboro.tif")).unwrap();
    let g = src.georef.clone().expect("georeferenced");
    let (w, h) = (src.width, src.height);
    let write = |path: &std::path::Path, [x0, y0, x1, y1]: [usize; 4]| {
        let values: Vec<f32> = (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| (x, y)))
            .map(|(x, y)| src.channels[0][y * w + x])
            .collect();
        let georef = fractile_proto::Georef {
            origin: [
                g.origin[0] + x0 as f64 * g.pixel_size[0],
                g.origin[1] + y0 as f64 * g.pixel_size[1],
            ],
            ..g.clone()
        };
        write_geotiff_f32(path, x1 - x0, y1 - y0, &values, Some(&georef), src.nodata).unwrap();
    };
    // The whole DEM as one float32 file: what the mosaic must equal.
    let whole = dir.join("whole.tif");
    write(&whole, [0, 0, w, h]);
    let (mx, my) = (w / 2, h / 2);
    let parts: Vec<PathBuf> = [
        [0, 0, mx + 1, my + 1],
        [mx, 0, w, my + 1],
        [0, my, mx + 1, h],
        [mx, my, w, h],
    ]
    .iter()
    .enumerate()
    .map(|(k, win)| {
        let p = tiles.join(format!("t{k}.tif"));
        write(&p, *win);
        p
    })
    .collect();
    let encode = |inputs: &[PathBuf], out: &std::path::Path| {
        bin()
            .arg("encode")
            .args(inputs)
            .arg("-o")
            .arg(out)
            .args(["--target-bpp", "0.8", "--json"])
            .output()
            .unwrap()
    };
    let one = json(&encode(&[whole], &dir.join("whole.fra")));
    for (label, inputs) in [("files", parts.clone()), ("folder", vec![tiles.clone()])] {
        let out = dir.join(format!("{label}.fra"));
        let m = json(&encode(&inputs, &out));
        assert_eq!(m["inputs"].as_array().map(Vec::len), Some(4), "{label}");
        assert_eq!(
            (m["width"].as_u64(), m["height"].as_u64()),
            (Some(w as u64), Some(h as u64))
        );
        // The same raster, so the same encode: the same bytes and errors.
        for key in ["bytes", "psnr", "max_error"] {
            assert_eq!(m[key], one[key], "{label}: {key}");
        }
        let info = json(&bin().arg("info").arg(&out).arg("--json").output().unwrap());
        assert_eq!(
            info["georef"]["origin"][0].as_f64(),
            Some(g.origin[0]),
            "{label}"
        );
    }
    // A tile on another grid (half a pixel off), last by name: resampled onto the others'
    // grid (issue 78), where the earlier tiles' cells win: the same raster, the same coded
    // bytes, its encoder line saying the resampling (the file longer by that alone).
    let off = tiles.join("t9.tif");
    let values = vec![300.0f32; 64];
    let georef = fractile_proto::Georef {
        origin: [g.origin[0] + 0.5 * g.pixel_size[0], g.origin[1]],
        ..g.clone()
    };
    write_geotiff_f32(&off, 8, 8, &values, Some(&georef), None).unwrap();
    let out = dir.join("resampled.fra");
    let m = json(&encode(std::slice::from_ref(&tiles), &out));
    assert_eq!(m["resampled_inputs"], 1, "{m}");
    for key in ["psnr", "max_error"] {
        assert_eq!(m[key], one[key], "{key}");
    }
    let encoder = |path: &Path| {
        let info = json(&bin().arg("info").arg(path).arg("--json").output().unwrap());
        info["encoder"].as_str().unwrap().to_string()
    };
    let (plain, said) = (encoder(&dir.join("whole.fra")), encoder(&out));
    let lineage = said
        .strip_prefix(&plain)
        .expect("the encoder line, then the lineage");
    assert!(
        lineage.starts_with("; 1 of 5 inputs resampled onto this grid (bilinear"),
        "{said}"
    );
    assert_eq!(
        m["bytes"].as_u64().unwrap(),
        one["bytes"].as_u64().unwrap() + lineage.len() as u64,
        "{m}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Issue 32: `--backend auto` never decodes on a software adapter (Mesa's lavapipe is slower
/// than the CPU), in the CLI as in the server; where the only adapter is one (CI, this
/// machine), a million-pixel continuous decode runs on the CPU.
#[test]
fn auto_never_decodes_on_a_software_adapter() {
    let dir = tempdir("auto-backend");
    let asset = dir.join("j.fra");
    json(
        &bin()
            .arg("encode")
            .arg(data("jacksboro.tif"))
            .arg("-o")
            .arg(&asset)
            .args(["--target-bpp", "0.8", "--json"])
            .output()
            .unwrap(),
    );
    // 3x jacksboro: 1209 x 1032, over the million pixels from which auto takes a GPU.
    let out = bin()
        .arg("decode")
        .arg(&asset)
        .arg("-o")
        .arg(dir.join("x3.tif"))
        .args([
            "--scale",
            "3",
            "--method",
            "continuous",
            "--backend",
            "auto",
        ])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{said}");
    let hardware = fractile_gpu::Gpu::new().ok().filter(|g| !g.is_software());
    match hardware {
        None => assert!(said.contains(", CPU)"), "{said}"),
        Some(g) => assert!(said.contains(&g.adapter()), "{said}"),
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// `--chunk N` codes a DEM in chunks (format version 8) that `info` describes and `decode`
/// brings back within the error the encoder measured; a chunk side that is not a power of two
/// in range is refused with no output.
#[test]
fn a_dem_coded_in_chunks_is_described_and_decoded_like_any_asset() {
    let dir = tempdir("chunked");
    let asset = dir.join("j.fra");
    let enc = json(
        &bin()
            .arg("encode")
            .arg(data("jacksboro.tif"))
            .arg("-o")
            .arg(&asset)
            .args(["--chunk", "128", "--json"])
            .output()
            .unwrap(),
    );
    assert_eq!(enc["codec"], "projected");
    let info = json(
        &bin()
            .arg("info")
            .arg(&asset)
            .arg("--json")
            .output()
            .unwrap(),
    );
    assert_eq!(info["format_version"], 10);
    assert_eq!(info["chunks"]["chunk"], 128);
    let levels = info["chunks"]["levels"].as_array().unwrap();
    // 403 x 344 in chunks of 128: 3 x 3 (the last of each row and column takes the
    // remainder), then two views of those chunks, 202 x 172 and 101 x 86 (which would fit in
    // one chunk, but a view is read from its source chunks, so a coded level lies above
    // them), then 51 x 43 in one.
    let sizes: Vec<(u64, u64, u64)> = levels
        .iter()
        .map(|l| {
            let n = |k: &str| l[k].as_u64().unwrap();
            (n("width"), n("height"), n("chunks"))
        })
        .collect();
    assert_eq!(
        sizes,
        [(403, 344, 9), (202, 172, 9), (101, 86, 9), (51, 43, 1)],
        "{info}"
    );
    // The bounded default's first two overviews are views of the source chunks (level 0's
    // grid of chunks, no bytes of their own), and so are rate mode's, whose file is still
    // within its rate.
    let viewed: Vec<bool> = levels.iter().map(|l| l["view"] == true).collect();
    assert_eq!(viewed, [false, true, true, false], "{info}");
    let rated = dir.join("r.fra");
    let st = bin()
        .arg("encode")
        .arg(data("jacksboro.tif"))
        .arg("-o")
        .arg(&rated)
        .args([
            "--chunk",
            "128",
            "--codec",
            "projected",
            "--target-bpp",
            "0.8",
        ])
        .status()
        .unwrap();
    assert!(st.success());
    let info = json(
        &bin()
            .arg("info")
            .arg(&rated)
            .arg("--json")
            .output()
            .unwrap(),
    );
    let levels = info["chunks"]["levels"].as_array().unwrap();
    assert_eq!(levels[1]["view"], true, "{info}");
    assert_eq!(levels[2]["view"], true, "{info}");
    assert_eq!(levels[1]["chunks"], 9, "{info}");
    assert!(info["bpp"].as_f64().unwrap() <= 0.8, "{info}");
    let out = dir.join("j.tif");
    let st = bin()
        .arg("decode")
        .arg(&asset)
        .arg("-o")
        .arg(&out)
        .status()
        .unwrap();
    assert!(st.success());
    let cmp = json(
        &bin()
            .arg("compare")
            .arg(data("jacksboro.tif"))
            .arg(&out)
            .arg("--json")
            .output()
            .unwrap(),
    );
    let (rmse, written) = (cmp["rmse"].as_f64().unwrap(), enc["rmse"].as_f64().unwrap());
    assert!(
        (rmse - written).abs() < 0.05 * written,
        "decoded {rmse}, encoded {written}"
    );
    // On the GPU (lavapipe in CI), chunk by chunk: as close to the source as the CPU's decode,
    // and to the CPU's decode within the chains' own error (the device ends a chain on the
    // constant seed, the CPU on the interpolant, each within its bound).
    let gpu = bin()
        .arg("decode")
        .arg(&asset)
        .arg("-o")
        .arg(dir.join("g.tif"))
        .args(["--backend", "gpu"])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&gpu.stderr);
    assert!(gpu.status.success(), "{said}");
    assert!(!said.contains(", CPU)"), "{said}");
    let against = |a: &Path, b: &Path| {
        let out = bin().arg("compare").arg(a).arg(b).arg("--json").output();
        json(&out.unwrap())
    };
    let on_gpu = against(&data("jacksboro.tif"), &dir.join("g.tif"));
    let rmse_gpu = on_gpu["rmse"].as_f64().unwrap();
    assert!(
        (rmse_gpu - rmse).abs() < 0.05 * rmse,
        "GPU {rmse_gpu}, CPU {rmse}"
    );
    let apart = against(&out, &dir.join("g.tif"));
    assert!(
        apart["rmse"].as_f64().unwrap() < 0.1 * rmse,
        "GPU against CPU: {apart}, CPU against the source: {rmse}"
    );
    let bad = bin()
        .arg("encode")
        .arg(data("jacksboro.tif"))
        .arg("-o")
        .arg(dir.join("bad.fra"))
        .args(["--chunk", "100"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("power of two"));
    assert!(!dir.join("bad.fra").exists());
}

/// Ctrl-C during a long encode leaves no file behind: the asset is written once, whole, by a
/// temporary file renamed over the output at the end.
#[test]
fn an_encode_interrupted_by_ctrl_c_leaves_no_file() {
    use std::os::unix::process::CommandExt;
    let dir = tempdir("interrupted");
    let mut encode = bin();
    encode
        .arg("encode")
        .arg(data("etopo20.tif"))
        .arg("-o")
        .arg(dir.join("e.fra"))
        .args(["--chunk", "64", "--target-bpp", "3"]);
    // SIGINT as a terminal delivers it: to a process that has not inherited it ignored (a
    // test run started in the background of a non-interactive shell would hand it down).
    // SAFETY: between fork and exec, only an async-signal-safe call (signal(2)).
    unsafe {
        encode.pre_exec(|| {
            libc::signal(libc::SIGINT, libc::SIG_DFL);
            Ok(())
        });
    }
    let mut child = encode.spawn().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(400));
    assert!(
        child.try_wait().unwrap().is_none(),
        "the encode ended before it could be interrupted"
    );
    let pid = child.id().to_string();
    let kill = Command::new("kill").args(["-INT", &pid]).status().unwrap();
    assert!(kill.success());
    let status = child.wait().unwrap();
    assert!(!status.success(), "{status}");
    let left: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert!(left.is_empty(), "{left:?}");
}

/// An encode split over 4 processes (`--part I/4`, run at once) and joined by `assemble` is
/// the file one `encode` writes (chunks coded by settings of their own, here a max error);
/// assembling without every part fails and writes nothing.
#[test]
fn an_encode_split_over_four_processes_assembles_into_the_same_file() {
    let dir = tempdir("parts");
    let input = data("jacksboro-utm.tif");
    let single = dir.join("single.fra");
    let out = bin()
        .arg("encode")
        .arg(&input)
        .args(["--chunk", "64", "--max-error", "2", "--json", "-o"])
        .arg(&single)
        .output()
        .unwrap();
    json(&out);
    let children: Vec<_> = (0..4)
        .map(|i| {
            bin()
                .arg("encode")
                .arg(&input)
                .args([
                    "--chunk",
                    "64",
                    "--max-error",
                    "2",
                    "--json",
                    "--part",
                    &format!("{i}/4"),
                    "-o",
                ])
                .arg(dir.join(format!("part{i}")))
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    let mut chunks = 0;
    for c in children {
        let v = json(&c.wait_with_output().unwrap());
        chunks += v["chunks"].as_u64().unwrap();
    }
    // The parts code the source level's 30 chunks (5 x 6) less those without data, each
    // part its band of rows; `assemble` codes the overviews.
    assert!(
        (20..=30).contains(&chunks),
        "{chunks} chunks coded over the parts"
    );
    let parts: Vec<PathBuf> = (0..4).map(|i| dir.join(format!("part{i}"))).collect();
    let joined = dir.join("joined.fra");
    let v = json(
        &bin()
            .arg("assemble")
            .args(&parts)
            .arg("--json")
            .arg("-o")
            .arg(&joined)
            .output()
            .unwrap(),
    );
    assert_eq!(v["codec"], "projected");
    let (a, b) = (
        std::fs::read(&single).unwrap(),
        std::fs::read(&joined).unwrap(),
    );
    assert!(a == b, "the assembled file differs from the single encode");
    assert_eq!(v["bytes"].as_u64(), Some(b.len() as u64));
    let fails = bin()
        .arg("assemble")
        .args(&parts[..3])
        .arg("-o")
        .arg(dir.join("three.fra"))
        .output()
        .unwrap();
    assert!(!fails.status.success());
    assert!(String::from_utf8_lossy(&fails.stderr).contains("part 3/4 is missing"));
    assert!(!dir.join("three.fra").exists());
    // A raster coded whole has no chunks to share.
    let whole = bin()
        .arg("encode")
        .arg(data("jacksboro.tif"))
        .args(["--part", "0/2", "-o"])
        .arg(dir.join("whole"))
        .output()
        .unwrap();
    assert!(!whole.status.success());
    assert!(String::from_utf8_lossy(&whole.stderr).contains("--chunk N"));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The default encode split in parts, under a file's rate: every part finds the same bound on
/// the same sample (`assemble` refuses parts whose settings differ), and the joined file is
/// within the rate, each of its cells within the bound the parts agreed on.
#[test]
fn a_split_default_encode_keeps_the_files_rate() {
    let dir = tempdir("parts-rate");
    let input = data("jacksboro-utm.tif");
    let mut parts = Vec::new();
    for i in 0..3 {
        let part = dir.join(format!("part{i}"));
        let v = json(
            &bin()
                .arg("encode")
                .arg(&input)
                .args(["--chunk", "64", "--target-bpp", "3", "--json", "--part"])
                .arg(format!("{i}/3"))
                .arg("-o")
                .arg(&part)
                .output()
                .unwrap(),
        );
        // A band of 2 of the source level's 6 rows of 5 chunks a part (less those without
        // data; the views' bytes are level 0's, the coded overviews `assemble`'s).
        let chunks = v["chunks"].as_u64().unwrap();
        assert!((5..=10).contains(&chunks), "{v}");
        parts.push(part);
    }
    let joined = dir.join("joined.fra");
    let v = json(
        &bin()
            .arg("assemble")
            .args(&parts)
            .arg("--json")
            .arg("-o")
            .arg(&joined)
            .output()
            .unwrap(),
    );
    let bytes = std::fs::metadata(&joined).unwrap().len();
    let budget = (3.0 * 344.0 * 363.0 / 8.0) as u64;
    assert!(bytes <= budget, "{bytes} over {budget}");
    assert!(bytes as f64 > 0.85 * budget as f64, "{bytes} of {budget}");
    let max = v["max_error"].as_f64().unwrap();
    assert!(max > 0.0 && max <= 64.0, "{max}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Runs `fractile ARGS` under `script` (a pseudo-terminal, as a user's shell gives it) for at
/// most `seconds`, and returns when each piece of its terminal output arrived and the output.
fn on_a_terminal(args: &[&str], seconds: u32) -> (Vec<f32>, String) {
    use std::io::Read;
    let command = format!(
        "timeout {seconds} {} {}",
        env!("CARGO_BIN_EXE_fractile"),
        args.join(" ")
    );
    let started = std::time::Instant::now();
    let mut child = Command::new("script")
        .args(["-qefc", &command, "/dev/null"])
        .env_remove("NODEVICE_SELECT")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("script (util-linux) runs");
    let mut out = child.stdout.take().unwrap();
    let (mut times, mut text, mut buf) = (Vec::new(), Vec::new(), [0u8; 4096]);
    while let Ok(n) = out.read(&mut buf) {
        if n == 0 {
            break;
        }
        times.push(started.elapsed().as_secs_f32());
        text.extend_from_slice(&buf[..n]);
    }
    let _ = child.wait();
    (times, String::from_utf8_lossy(&text).into_owned())
}

#[test]
fn a_long_encode_shows_its_progress_on_a_terminal_every_two_seconds() {
    // A 4096 x 4096 DEM: topobathy decoded 35 times finer, as a float32 GeoTIFF (64 MB).
    let dir = tempdir("progress");
    let (small, big) = (dir.join("small.fra"), dir.join("big.tif"));
    let run = |c: &mut Command| assert!(c.status().unwrap().success());
    run(bin()
        .args(["encode", "--quiet"])
        .arg(data("topobathy.tif"))
        .arg("-o")
        .arg(&small));
    run(bin()
        .arg("decode")
        .arg(&small)
        .arg("-o")
        .arg(&big)
        .args(["--width", "4096", "--height", "4096"]));
    let out = dir.join("big.fra");
    let (big, out) = (big.to_str().unwrap(), out.to_str().unwrap());
    // Watched for 8 s (the whole encode takes minutes on two cores).
    let (times, text) = on_a_terminal(&["encode", big, "-o", out], 8);
    assert!(text.contains("coding chunks"), "no progress bar: {text:?}");
    assert!(text.contains("so far"), "no elapsed time: {text:?}");
    let mut last = 0.0f32;
    for &t in times.iter().filter(|&&t| t < 7.5) {
        assert!(
            t - last <= 2.0,
            "nothing printed from {last} s to {t} s: {times:?}"
        );
        last = t;
    }
    assert!(last > 5.0, "the output stopped at {last} s: {times:?}");
    // --quiet: nothing.
    let (_, text) = on_a_terminal(&["encode", big, "-o", out, "--quiet"], 3);
    assert!(!text.contains("coding"), "{text:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_port_in_use_and_an_input_of_another_kind_say_what_to_do() {
    let dir = tempdir("newcomer");
    // A port in use: the address and --bind named, before any asset is loaded.
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let o = bin()
        .args(["serve", "--bind", &addr, "--assets"])
        .arg(&dir)
        .env("FRACTILE_BACKEND", "cpu")
        .output()
        .unwrap();
    assert!(!o.status.success());
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(err.contains(&addr) && err.contains("--bind"), "{err}");
    assert!(
        !out.contains("serving") && !err.contains("serving"),
        "{out}"
    );
    // A file the encoder does not read: what it reads, not the image crate's words.
    let txt = dir.join("notes.txt");
    std::fs::write(&txt, "a text file\n").unwrap();
    let o = bin()
        .arg("encode")
        .arg(&txt)
        .arg("-o")
        .arg(dir.join("notes.fra"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("GeoTIFF") && err.contains("PNG"), "{err}");
    assert!(!err.contains("not recognized"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
