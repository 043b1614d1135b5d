//! The `fractile-client` binary against the shared in-process test server: what a user types.

use std::path::Path;
use std::process::{Command, Output};

fn cli(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fractile-client"))
        .arg("--server")
        .arg(fractile_e2e::server())
        .args(args)
        .env_remove("FRACTILE_WRITE_TOKEN")
        .output()
        .expect("the binary runs")
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

#[test]
fn refining_a_tile_writes_every_step_and_one_json_object_each() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t.f32");
    let o = cli(&[
        "--json",
        "tile",
        "jacksboro",
        "12",
        "1088",
        "1599",
        "-o",
        out.to_str().unwrap(),
        "--refine",
        "--tolerance",
        "0.5",
        "--schedule",
        "1,2,4,8,16,32",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let steps: Vec<serde_json::Value> = stdout(&o)
        .lines()
        .map(|l| serde_json::from_str(l).expect("one JSON object per line"))
        .collect();
    assert!(steps.len() >= 2, "{steps:?}");
    let bounds: Vec<f64> = steps
        .iter()
        .map(|s| s["convergence_bound"].as_f64().unwrap())
        .collect();
    assert!(bounds.windows(2).all(|w| w[1] <= w[0]), "{bounds:?}");
    let its: Vec<u64> = steps
        .iter()
        .map(|s| s["iterations"].as_u64().unwrap())
        .collect();
    assert_eq!(its, [1, 2, 4, 8, 16, 32][..its.len()].to_vec());
    // Every step is on disk, 256 x 256 float32 heights each, and the last is also at -o.
    for k in 1..=steps.len() {
        let p = dir.path().join(format!("t.step{k:02}.f32"));
        assert_eq!(
            std::fs::metadata(&p).unwrap().len(),
            256 * 256 * 4,
            "{}",
            p.display()
        );
    }
    let last = dir.path().join(format!("t.step{:02}.f32", steps.len()));
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(last).unwrap());
}

#[test]
fn points_from_a_csv_come_back_in_order_with_outside_marked() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("p.csv");
    // Inside, inside, and far outside the DEM.
    std::fs::write(&csv, "lon,lat\n-84.2,36.6\n-84.3,36.5\n-90,0\n").unwrap();
    let answers = dir.path().join("a.csv");
    let o = cli(&[
        "points",
        "jacksboro",
        csv.to_str().unwrap(),
        "-o",
        answers.to_str().unwrap(),
        "--binary",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(&answers).unwrap();
    let rows: Vec<Vec<&str>> = text
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(rows.len(), 3);
    assert_eq!(
        (rows[0][0], rows[1][1], rows[2][0]),
        ("-84.2", "36.5", "-90")
    );
    for r in &rows[..2] {
        let h: f64 = r[2].parse().unwrap();
        assert!((236.0..=1076.0).contains(&h), "{r:?}");
    }
    assert_eq!(rows[2][2], "", "outside has no value");
    // The same point by the single-point command agrees.
    let one = cli(&["--json", "point", "jacksboro", "-84.2", "36.6"]);
    let v: serde_json::Value = serde_json::from_slice(&one.stdout).unwrap();
    let h = v["values"][0].as_f64().unwrap();
    assert!((h - rows[0][2].parse::<f64>().unwrap()).abs() < 1e-3, "{v}");
}

#[test]
fn errors_exit_non_zero_with_the_servers_detail() {
    let o = cli(&["info", "no-such-asset"]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("unknown_asset"), "{err}");
    let o = cli(&[
        "upload",
        Path::new("Cargo.toml").to_str().unwrap(),
        "--id",
        "x",
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("unauthorised"));
}

#[test]
fn a_server_without_a_scheme_is_plain_http_and_errors_print_one_line() {
    let base = fractile_e2e::server();
    let bare = base.strip_prefix("http://").expect("an http URL");
    let run = |server: &str, args: &[&str], backtrace: &str| {
        Command::new(env!("CARGO_BIN_EXE_fractile-client"))
            .arg("--server")
            .arg(server)
            .args(args)
            .env("RUST_BACKTRACE", backtrace)
            .output()
            .expect("the binary runs")
    };
    // `127.0.0.1:PORT`, as the default is written in the README.
    let o = run(bare, &["info", "jacksboro"], "0");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout(&o).contains("jacksboro"));
    // An error, with the backtraces many Rust users' shells ask for: one line all the same.
    let o = run(&base, &["info", "no-such-asset"], "1");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(err.starts_with("fractile-client: ") && err.contains("unknown_asset"));
    // -v: the error with its backtrace.
    let o = run(&base, &["-v", "info", "no-such-asset"], "1");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("backtrace"), "{err}");
}

/// A volume's 3D Tiles fetched to a folder (issue 79): the folder holds the tileset, every
/// subtree and tile it reaches, byte for byte what the server answers at the same paths.
#[test]
fn a_tileset_fetched_to_a_folder_is_the_servers_files() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("fandisk");
    let o = cli(&["--json", "tileset", "fandisk", "-o", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value = serde_json::from_str(stdout(&o).trim()).unwrap();
    let files: Vec<std::path::PathBuf> = walk(&out);
    let glbs: Vec<&std::path::PathBuf> = files
        .iter()
        .filter(|p| p.extension().is_some_and(|e| e == "glb"))
        .collect();
    let subtrees = files
        .iter()
        .filter(|p| p.extension().is_some_and(|e| e == "subtree"))
        .count();
    assert_eq!(report["contents"].as_u64(), Some(glbs.len() as u64));
    assert_eq!(report["subtrees"].as_u64(), Some(subtrees as u64));
    assert!(glbs.len() > 20 && subtrees > 2, "{report}");
    let total: u64 = files
        .iter()
        .map(|p| std::fs::metadata(p).unwrap().len())
        .sum();
    assert_eq!(report["bytes"].as_u64(), Some(total));
    // The same bytes as the server's, at the same relative paths.
    let server = fractile_e2e::server();
    let rt = tokio::runtime::Runtime::new().unwrap();
    for p in files.iter().step_by(files.len() / 12 + 1) {
        let rel = p
            .strip_prefix(&out)
            .unwrap()
            .to_string_lossy()
            .replace('\\', "/");
        let url = format!("{server}/v1/assets/fandisk/{rel}");
        let body = rt.block_on(async { reqwest::get(&url).await?.bytes().await });
        assert_eq!(&body.unwrap()[..], &std::fs::read(p).unwrap()[..], "{rel}");
    }
}

/// Every file under `dir`.
fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}
