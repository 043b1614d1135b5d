//! Issue 78's speed bar: cells a second of an encode that reads its inputs from a bucket
//! (SeaweedFS on loopback, range reads) against the same encode from local copies of the
//! same files, in the same run, on the same machine.
//!
//! `cargo bench -p fractile-cli --bench bucket_inputs -- [runs, default 3]` (needs `weed` and
//! a Python with rasterio, `FRACTILE_RASTERIO_PYTHON`, to make the COGs with GDAL).
//!
//! COGs cut from etopo20 (1080 x 540 cells) at three sizes (`tools/make_cogs.py`: 135, 48 and
//! 16 cells a side: 32, 276 and 2,312 files, a tile each), and from etopo20 resampled 8 times
//! finer (8640 x 4320) in 32 pieces of 1080 cells with tiles of 256, the size of real DEM
//! tiles; each set encoded (`--chunk 256 --max-error 2`) from its folder and from its `s3://`
//! prefix, alternately, `runs` times; the best time of each. Then split in 4 parts from the
//! bucket (`--chunk 128`: the small sets have 4 rows of chunks). Prints a table: seconds,
//! cells a second, the ratio, the bytes fetched, whole and by the 4 parts together (from the
//! prefix, and from the pieces' STAC items, which say their grids), against the files'
//! bytes, and the 4 parts' seconds (summed) and `assemble`'s, which codes the overviews.

#[path = "../tests/harness/mod.rs"]
mod harness;

use std::process::Command;
use std::time::Instant;

use harness::{Weed, binary, cogs_scaled, put_object, rasterio_python, upload};

fn main() {
    let runs: usize = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(3);
    let (Some(python), Some(_)) = (rasterio_python(), harness::weed_binary()) else {
        eprintln!("needs weed (FRACTILE_WEED) and FRACTILE_RASTERIO_PYTHON");
        return;
    };
    let work = tempfile::tempdir().unwrap();
    let weed = Weed::start(&work.path().join("weed"), "dem").expect("weed starts");
    println!(
        "| COGs | cells a side | local s | bucket s | local cells/s | bucket cells/s | bucket / local | fetched / files' bytes | 4 parts fetched / files' bytes | from STAC items | 4 parts s (sum) | assemble s |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (side, scale, tile) in [
        (1080, 8, Some(256)),
        (135, 1, None),
        (48, 1, None),
        (16, 1, None),
    ] {
        let dir = work.path().join(format!("cogs{side}"));
        let n = cogs_scaled(&python, &dir, side, (scale, tile));
        upload(&weed, "dem", &format!("c{side}"), &dir);
        let files: u64 = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().metadata().unwrap().len())
            .sum();
        let out = work.path().join("out.fra");
        let encode_with = |input: &str, more: &[&str]| {
            let t = Instant::now();
            let o = Command::new(binary())
                .args(["encode", input, "-o"])
                .arg(&out)
                .args(["--max-error", "2", "--json"])
                .args(more)
                .envs(weed.env())
                .output()
                .unwrap();
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
            let v: serde_json::Value =
                serde_json::from_str(String::from_utf8_lossy(&o.stdout).trim()).unwrap();
            (t.elapsed().as_secs_f64(), v)
        };
        let encode = |input: &str| encode_with(input, &["--chunk", "256"]);
        let (mut local, mut bucket, mut fetched) = (f64::MAX, f64::MAX, 0);
        let prefix = format!("s3://dem/c{side}/");
        for _ in 0..runs {
            local = local.min(encode(dir.to_str().unwrap()).0);
            let (s, v) = encode(&prefix);
            bucket = bucket.min(s);
            fetched = v["fetched_bytes"].as_u64().unwrap_or(0);
        }
        let (mut parts, mut part_seconds) = (0, 0.0);
        let mut files_of_parts = Vec::new();
        for i in 0..4 {
            let share = format!("{i}/4");
            let (s, v) = encode_with(&prefix, &["--chunk", "128", "--part", &share]);
            parts += v["fetched_bytes"].as_u64().unwrap_or(0);
            part_seconds += s;
            let part = work.path().join(format!("part{i}"));
            std::fs::rename(&out, &part).unwrap();
            files_of_parts.push(part);
        }
        // The same split from the pieces' STAC items (their grids said, hrefs relative to the
        // list): a part opens only the inputs its band crosses.
        let items = std::fs::read_to_string(format!("{}.items.json", dir.display())).unwrap();
        let mut items: serde_json::Value = serde_json::from_str(&items).unwrap();
        for f in items["features"].as_array_mut().unwrap() {
            let name = f["assets"]["data"]["href"].as_str().unwrap().to_string();
            f["assets"]["data"]["href"] = format!("c{side}/{name}").into();
        }
        put_object(
            &weed,
            &format!("dem/c{side}.items.json"),
            items.to_string().as_bytes(),
        );
        let listed = format!("s3://dem/c{side}.items.json");
        let stac: u64 = (0..4)
            .map(|i| {
                let share = format!("{i}/4");
                let (_, v) = encode_with(&listed, &["--chunk", "128", "--part", &share]);
                v["fetched_bytes"].as_u64().unwrap_or(0)
            })
            .sum();
        let t = Instant::now();
        let o = Command::new(binary())
            .arg("assemble")
            .args(&files_of_parts)
            .arg("-o")
            .arg(&out)
            .arg("--json")
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let assemble = t.elapsed().as_secs_f64();
        let cells = 1080.0 * 540.0 * (scale * scale) as f64;
        println!(
            "| {n} | {side} | {local:.2} | {bucket:.2} | {:.0} | {:.0} | {:.2} | {:.2} | {:.2} | {:.2} | {part_seconds:.2} | {assemble:.2} |",
            cells / local,
            cells / bucket,
            local / bucket,
            fetched as f64 / files as f64,
            parts as f64 / files as f64,
            stac as f64 / files as f64
        );
    }
}
