//! Encodes from a bucket (issue 78): cloud-optimized GeoTIFFs made by GDAL (rasterio's COG
//! driver, `tools/make_cogs.py`) from the repository's etopo20, put in a real S3 server
//! (SeaweedFS on loopback), and encoded from `s3://` by prefix, by a text list and by a STAC
//! ItemCollection, whole and split in 4 parts written to and assembled in the bucket: always
//! the same bytes as the encode of local copies of the same files, the assembled asset served
//! alike by two replicas on the bucket. What crosses the network is counted (at most 1.3 times
//! the inputs' compressed cells; the parts of a split encode read their bands of rows, each
//! reading every input's header besides, or only the inputs its band crosses where STAC items
//! say their grids), and a part's peak memory
//! stays under 1 GB with 200 inputs and with 2,000. And inputs on other grids of one CRS are
//! resampled as GDAL resamples them (rasterio's `reproject`, `tools/resample_reference.py`).
//!
//! The bucket's steps are one sequential test (they share the bucket). Without `weed` or a Python with rasterio
//! (`FRACTILE_RASTERIO_PYTHON`; `.ci/run` installs both) it says so and passes, except under CI.

#[path = "harness/mod.rs"]
mod harness;

use std::path::Path;
use std::process::Command;

use harness::{
    Server, Weed, binary, cogs, data, free_port, get, put_object, rasterio_python, upload,
};

fn get_object(weed: &Weed, key: &str) -> Vec<u8> {
    let (status, _, body) = get(weed.s3_port(), &format!("/{key}")).unwrap();
    assert_eq!(status, 200, "GET {key}");
    body
}

/// `fractile` with `args` and the bucket's environment: its JSON report.
fn fractile(weed: &Weed, args: &[&str]) -> serde_json::Value {
    let out = Command::new(binary())
        .args(args)
        .arg("--json")
        .envs(weed.env())
        .output()
        .expect("the fractile binary runs");
    assert!(
        out.status.success(),
        "fractile {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    serde_json::from_str(text.lines().last().unwrap_or_default()).unwrap()
}

/// The bytes of every strip or tile of the TIFFs in `dir`: their compressed cells.
fn compressed_cells(dir: &Path) -> u64 {
    use tiff::tags::Tag;
    let mut total = 0;
    for e in std::fs::read_dir(dir).unwrap() {
        let file = std::fs::File::open(e.unwrap().path()).unwrap();
        let mut dec = tiff::decoder::Decoder::new(std::io::BufReader::new(file)).unwrap();
        let counts = dec
            .get_tag_u64_vec(Tag::TileByteCounts)
            .or_else(|_| dec.get_tag_u64_vec(Tag::StripByteCounts))
            .unwrap();
        total += counts.iter().sum::<u64>();
    }
    total
}

/// The largest resident memory of any child process waited for so far, in bytes.
fn children_peak() -> u64 {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: getrusage fills the struct it is given.
    let usage = unsafe {
        libc::getrusage(libc::RUSAGE_CHILDREN, usage.as_mut_ptr());
        usage.assume_init()
    };
    usage.ru_maxrss as u64 * 1024
}

#[test]
fn an_encode_from_a_bucket_is_the_encode_of_its_local_copies() {
    let (Some(python), Some(_)) = (rasterio_python(), harness::weed_binary()) else {
        assert!(
            std::env::var_os("CI").is_none(),
            "under CI the bucket test needs weed and FRACTILE_RASTERIO_PYTHON"
        );
        println!("no weed or no Python with rasterio: the bucket test was not run");
        return;
    };
    let work = tempfile::tempdir().unwrap();
    let weed = Weed::start(&work.path().join("weed"), "dem").expect("weed starts");
    let local = work.path().join("etopo");
    let pieces = cogs(&python, &local, 48);
    assert!(pieces >= 200, "{pieces} COGs");
    // One input in UTM (first by name: its cells win where it lies), reprojected onto the
    // COGs' longitude/latitude grid, averaged (its 90 m cells are far finer than 20').
    std::fs::copy(data("jacksboro-utm.tif"), local.join("0-jacksboro-utm.tif")).unwrap();
    let pieces = pieces + 1;
    let urls = upload(&weed, "dem", "etopo", &local);
    let out = |name: &str| work.path().join(name).display().to_string();

    // Whole, from local copies and from the bucket: the same asset.
    // A bound, not a rate: a split encode under a bound is the whole one, byte for byte.
    let chunked = ["--chunk", "128", "--max-error", "2"];
    let from_local = out("local.fra");
    let mut args = vec!["encode", local.to_str().unwrap(), "-o", &from_local];
    args.extend(chunked);
    fractile(&weed, &args);
    let expected = std::fs::read(&from_local).unwrap();
    let from_bucket = out("bucket.fra");
    let mut args = vec!["encode", "s3://dem/etopo/", "-o", &from_bucket];
    args.extend(chunked);
    let report = fractile(&weed, &args);
    assert_eq!(report["inputs"].as_array().unwrap().len(), pieces);
    assert_eq!(report["resampled_inputs"], 1, "the UTM input");
    // The asset says so (its encoder line, which `fractile info` and the server show).
    let said = format!("1 of {pieces} inputs resampled onto this grid");
    assert!(
        expected.windows(said.len()).any(|w| w == said.as_bytes()),
        "the asset does not say: {said}"
    );
    assert!(
        std::fs::read(&from_bucket).unwrap() == expected,
        "the bucket's encode differs"
    );
    let fetched = report["fetched_bytes"].as_u64().unwrap();
    let cells = compressed_cells(&local);
    println!(
        "{pieces} COGs: {fetched} bytes fetched in {} requests for {cells} bytes of compressed cells ({:.2}x)",
        report["fetched_requests"],
        fetched as f64 / cells as f64
    );
    assert!(
        fetched as f64 <= 1.3 * cells as f64,
        "{fetched} bytes fetched for {cells} of cells"
    );

    // By a text list in the bucket and by a STAC ItemCollection: the same asset.
    put_object(&weed, "dem/lists/etopo.txt", urls.join("\n").as_bytes());
    // The COGs' STAC items as make_cogs.py writes them (each says its grid: placed without
    // reading its header) and the UTM file's with its data asset alone (its header read), in
    // the bucket's order.
    let made = std::fs::read_to_string(format!("{}.items.json", local.display())).unwrap();
    let made: serde_json::Value = serde_json::from_str(&made).unwrap();
    let items: Vec<serde_json::Value> = urls
        .iter()
        .map(|u| {
            let name = u.rsplit('/').next().unwrap();
            let said = made["features"].as_array().unwrap().iter().find(|f| f["id"] == name);
            match said {
                Some(f) => {
                    let mut f = f.clone();
                    f["assets"]["data"]["href"] = serde_json::Value::from(u.as_str());
                    f
                }
                None => serde_json::json!({"type": "Feature", "stac_version": "1.0.0", "id": name,
                    "assets": {"thumbnail": {"href": "thumb.png", "roles": ["thumbnail"]},
                               "data": {"href": u, "roles": ["data"],
                                        "type": "image/tiff; application=geotiff; profile=cloud-optimized"}}}),
            }
        })
        .collect();
    assert_eq!(
        items
            .iter()
            .filter(|i| i["properties"]["proj:shape"].is_array())
            .count(),
        pieces - 1
    );
    let stac = work.path().join("items.json");
    let collection = serde_json::json!({"type": "FeatureCollection", "features": items});
    std::fs::write(&stac, collection.to_string()).unwrap();
    for list in ["s3://dem/lists/etopo.txt", stac.to_str().unwrap()] {
        let o = out("listed.fra");
        let mut args = vec!["encode", list, "-o", &o];
        args.extend(chunked);
        fractile(&weed, &args);
        assert!(
            std::fs::read(&o).unwrap() == expected,
            "{list}: another asset"
        );
    }

    // Split in 4 parts from the bucket to the bucket, assembled there: the same asset, which
    // a server on the bucket serves.
    let parts: Vec<String> = (0..4)
        .map(|i| format!("s3://dem/parts/etopo.{i}.fra"))
        .collect();
    let mut part_fetched = 0;
    for (i, part) in parts.iter().enumerate() {
        let share = format!("{i}/4");
        let mut args = vec!["encode", "s3://dem/etopo/", "-o", part, "--part", &share];
        args.extend(chunked);
        // Each part's summary says what it fetched.
        let report = fractile(&weed, &args);
        part_fetched += report["fetched_bytes"]
            .as_u64()
            .expect("a part's fetched bytes");
    }
    // Each part reads its band of rows: the cells are read once over the 4 parts, but each
    // part reads every input's header, its first 4 KiB (here the whole file: these COGs are
    // 3 KB; `benches/bucket_inputs.rs` measures COGs the size of real DEM tiles).
    let headers: u64 = std::fs::read_dir(&local)
        .unwrap()
        .map(|e| e.unwrap().metadata().unwrap().len().min(4096))
        .sum();
    println!(
        "the 4 parts fetched {part_fetched} bytes in all ({:.2}x the compressed cells; {headers} bytes of headers a part)",
        part_fetched as f64 / cells as f64
    );
    assert!(
        part_fetched as f64 <= 1.3 * cells as f64 + 3.0 * headers as f64,
        "the 4 parts fetched {part_fetched} bytes for {cells} of cells and {headers} of headers"
    );
    let mut args = vec!["assemble"];
    args.extend(parts.iter().map(String::as_str));
    args.extend(["-o", "s3://dem/assets/etopo.fra"]);
    fractile(&weed, &args);
    assert!(
        get_object(&weed, "dem/assets/etopo.fra") == expected,
        "the assembled asset differs"
    );
    // Split in 4 parts from the STAC ItemCollection, whose items say their grids: a part opens
    // only the inputs its band crosses (the UTM file's header aside), so the 4 parts read the
    // inputs once between them; the same asset.
    let stac_parts: Vec<String> = (0..4).map(|i| out(&format!("stac.{i}.part"))).collect();
    let mut stac_fetched = 0;
    for (i, part) in stac_parts.iter().enumerate() {
        let share = format!("{i}/4");
        let mut args = vec![
            "encode",
            stac.to_str().unwrap(),
            "-o",
            part,
            "--part",
            &share,
        ];
        args.extend(chunked);
        stac_fetched += fractile(&weed, &args)["fetched_bytes"].as_u64().unwrap();
    }
    // The row of COGs across each of the 3 band edges is read from both sides (a band's
    // chunks code 4 rows beyond it): 48 of the 540 rows each, at these bands of 135 rows.
    let edges = 3.0 * 48.0 / 540.0 * cells as f64;
    println!(
        "the 4 parts from the STAC items fetched {stac_fetched} bytes in all ({:.2}x the compressed cells, {:.2}x with the rows at the edges)",
        stac_fetched as f64 / cells as f64,
        stac_fetched as f64 / (cells as f64 + edges)
    );
    assert!(
        stac_fetched as f64 <= 1.3 * (cells as f64 + edges),
        "the 4 parts from the STAC items fetched {stac_fetched} bytes for {cells} of cells"
    );
    let joined = out("stac.fra");
    let mut args = vec!["assemble"];
    args.extend(stac_parts.iter().map(String::as_str));
    args.extend(["-o", &joined]);
    fractile(&weed, &args);
    assert!(
        std::fs::read(&joined).unwrap() == expected,
        "the parts from the STAC items differ"
    );
    // An item that says another grid than its file holds: the encode fails, naming both.
    let mut wrong: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&stac).unwrap()).unwrap();
    wrong["features"][1]["properties"]["proj:shape"] = serde_json::json!([48, 47]);
    let wrong_path = work.path().join("wrong.json");
    std::fs::write(&wrong_path, wrong.to_string()).unwrap();
    let failed = Command::new(binary())
        .args([
            "encode",
            wrong_path.to_str().unwrap(),
            "-o",
            &out("wrong.fra"),
        ])
        .args(chunked)
        .envs(weed.env())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&failed.stderr);
    assert!(!failed.status.success(), "a wrong catalog encoded");
    assert!(
        err.contains("its catalog says 47x48") && err.contains("the file holds 48x48"),
        "{err}"
    );

    // Two replicas on the bucket serve the assembled asset, the same bytes from each.
    let env: Vec<(&str, String)> = weed.env();
    let env: Vec<(&str, &str)> = env.iter().map(|(k, v)| (*k, v.as_str())).collect();
    let replicas: Vec<(u16, Server)> = (0..2)
        .map(|i| {
            let port = free_port();
            let log = work.path().join(format!("serve{i}.log"));
            let server = Server::try_start("s3://dem/assets", port, &[], &env, &log)
                .expect("a server on the bucket");
            (port, server)
        })
        .collect();
    let tiles: Vec<Vec<u8>> = replicas
        .iter()
        .map(|(port, _)| {
            let (status, _, png) = get(*port, "/v1/assets/etopo/tiles/1/1/0.png").unwrap();
            assert_eq!(status, 200);
            assert!(png.starts_with(b"\x89PNG"));
            png
        })
        .collect();
    assert!(tiles[0] == tiles[1], "the replicas serve different tiles");
    for (_, server) in replicas {
        server.stop();
    }
    let peak_200 = children_peak();

    // 2,000 small COGs: a part's memory is bounded by its chunks, not by its inputs.
    let small = work.path().join("small");
    let many = cogs(&python, &small, 16);
    assert!(many >= 2000, "{many} COGs");
    upload(&weed, "dem", "small", &small);
    let o = out("small.fra");
    let mut args = vec!["encode", "s3://dem/small/", "-o", &o, "--part", "0/4"];
    args.extend(chunked);
    fractile(&weed, &args);
    let peak = children_peak();
    println!(
        "peak resident memory of a child: {:.0} MB with {pieces} inputs, {:.0} MB with {many}",
        peak_200 as f64 / 1e6,
        peak as f64 / 1e6
    );
    assert!(peak < 1 << 30, "{peak} bytes resident");
}

/// A Python with rasterio for `test`, or `None` (said) where there is none outside CI.
fn python_for(test: &str) -> Option<std::path::PathBuf> {
    let python = rasterio_python();
    assert!(
        python.is_some() || std::env::var_os("CI").is_none(),
        "under CI the {test} test needs FRACTILE_RASTERIO_PYTHON"
    );
    if python.is_none() {
        println!("no Python with rasterio: the {test} test was not run");
    }
    python
}

/// `tools/resample_reference.py` with `args`: its JSON line.
fn reference(python: &Path, args: &[&str]) -> serde_json::Value {
    let out = Command::new(python)
        .arg(data("../tools/resample_reference.py"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// `fractile` with `args` (no bucket): its standard output.
fn run(args: &[&str]) -> String {
    let o = Command::new(binary()).args(args).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// `inputs` encoded (`extra` flags added) bounded at 0.001 m into `dir/m.fra` and decoded to
/// `dir/m.tif`: the encode's report.
fn encode_and_decode(dir: &Path, inputs: &[&str], extra: &[&str]) -> serde_json::Value {
    let (fra, tif) = (dir.join("m.fra"), dir.join("m.tif"));
    let (fra, tif) = (fra.to_str().unwrap(), tif.to_str().unwrap());
    let mut args = vec!["encode"];
    args.extend(inputs);
    args.extend(extra);
    args.extend([
        "-o",
        fra,
        "--codec",
        "projected",
        "--max-error",
        "0.001",
        "--json",
    ]);
    let report = serde_json::from_str(run(&args).trim()).unwrap();
    run(&["decode", fra, "-o", tif]);
    report
}

/// The decode's cells against a reference of `resample_reference.py compare`, within the
/// encode's bound (and f32's rounding of heights of a few hundred metres), on more than `cells`.
fn within_the_bound(cmp: &serde_json::Value, cells: u64) {
    assert!(cmp["cells"].as_u64().unwrap() > cells, "{cmp}");
    assert!(
        cmp["max_abs_diff"].as_f64().unwrap() <= 0.001 + 1e-4,
        "{cmp}"
    );
}

/// Inputs on different grids of one CRS (issue 78): jacksboro's west half on its grid and its
/// east part made 1.5 times coarser and 0.37 of a cell off by GDAL; the mosaic resamples the
/// second onto the first's grid, and its cells (through an encode bounded at 0.001 m and its
/// decode) are GDAL's bilinear reprojection of the same input (rasterio's `reproject`) within
/// that bound, every cell 2 or more inside the resampled input's footprint.
#[test]
fn inputs_on_other_grids_are_resampled_as_gdal_resamples_them() {
    let Some(python) = python_for("resampling") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name).display().to_string();
    let source = data("jacksboro.tif").display().to_string();
    let made = reference(&python, &["make", &source, &p("")]);
    let a_cols = made["a"][0].as_u64().unwrap().to_string();
    let report = encode_and_decode(dir.path(), &[&p("a.tif"), &p("b.tif")], &[]);
    assert_eq!(report["resampled_inputs"], 1, "{report}");
    let cmp = reference(
        &python,
        &["compare", &p("ref.tif"), &p("m.tif"), "2", &a_cols],
    );
    println!("against GDAL's bilinear: {cmp}");
    within_the_bound(&cmp, 50_000);
}

/// An input in another CRS (issue 78): jacksboro's UTM grid (EPSG:32616, 90 m) beside a
/// longitude/latitude input of half jacksboro's cells, whose grid the mosaic takes: each cell
/// east of the first input is the bilinear between the four UTM cells around its centre taken
/// to UTM by PROJ (through rasterio), within the encode's bound of 0.001 m. GDAL's own warp
/// (rasterio's `reproject`) is printed beside it: it departs from that bilinear by up to metres
/// on this rotated grid.
#[test]
fn an_input_in_another_crs_is_reprojected_onto_the_lonlat_grid() {
    let Some(python) = python_for("reprojection") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name).display().to_string();
    let (source, utm) = (
        data("jacksboro.tif").display().to_string(),
        data("jacksboro-utm.tif").display().to_string(),
    );
    let made = reference(&python, &["utm", &source, &utm, &p("")]);
    let a_cols = made["a"][0].as_u64().unwrap().to_string();
    let report = encode_and_decode(dir.path(), &[&p("a.tif"), &utm], &[]);
    assert_eq!(report["resampled_inputs"], 1, "{report}");
    let compare =
        |with: &str| reference(&python, &["compare", &p(with), &p("m.tif"), "3", &a_cols]);
    let (bilinear, gdal) = (compare("bilinear.tif"), compare("ref.tif"));
    println!("against PROJ + bilinear: {bilinear}; against GDAL's warp: {gdal}");
    within_the_bound(&bilinear, 200_000);
}

/// `--target-grid` (issue 78): jacksboro onto a grid 3 times coarser and 0.37 of a coarse cell
/// off, named by a GeoTIFF: each cell the area-weighted average of the input cells it covers,
/// GDAL's `average` (rasterio's `reproject`) within the encode's bound of 0.001 m.
#[test]
fn a_target_grid_coarser_than_the_input_averages_as_gdal_does() {
    let Some(python) = python_for("averaging") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name).display().to_string();
    let source = data("jacksboro.tif").display().to_string();
    reference(&python, &["coarse", &source, &p(""), "3", "0.37"]);
    encode_and_decode(dir.path(), &[&source], &["--target-grid", &p("grid.tif")]);
    let cmp = reference(&python, &["compare", &p("ref.tif"), &p("m.tif"), "1", "0"]);
    println!("against GDAL's average: {cmp}");
    within_the_bound(&cmp, 10_000);
}
