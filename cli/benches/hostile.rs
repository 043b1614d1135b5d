//! Issue 35's bars, measured on the release `fractile` binary as an attacker would meet it:
//! a separate server process on loopback, its memory read from /proc, requests made over raw
//! TCP (so that this process's own buffers never count). Prints one table row per bar.
//!
//! `cargo bench -p fractile-cli --bench hostile -- [seconds of region load, default 20]`
//!
//! 1. A folder holding the crafted files of `testdata/hostile/` starts and logs each; uploading
//!    each answers 422, with the time and the server's peak extra memory.
//! 2. 16 unauthenticated uploads of 64 MiB at once: every one 401, peak extra memory.
//! 3. 8 concurrent uploads of one id, 20 rounds: no 5xx; the served asset is the file's (its
//!    size), and a tile's ETag is the same before and after a restart.
//! 4. Four clients looping maximum regions (4096 x 4096): p99 of cached tiles and of points,
//!    beside the same figures without the load, measured in the same run.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

#[path = "../tests/harness/mod.rs"]
mod harness;

use fractile_codec::{QuadtreeSettings, Raster, RateMode, encode};
use harness::{Server, binary, data, get, header, percentile, put};

const TOKEN: &str = "bench-secret";

/// Starts the server under test on `dir` with the write token.
fn serve(dir: &Path, port: u16, log: PathBuf) -> Option<Server> {
    let assets = dir.to_str().expect("a UTF-8 temp path");
    Server::try_start(assets, port, &[], &[("FRACTILE_WRITE_TOKEN", TOKEN)], &log)
}

/// [`serve`], or a panic with the log.
fn start(dir: &Path, port: u16, log: PathBuf) -> Server {
    serve(dir, port, log.clone()).unwrap_or_else(|| {
        panic!(
            "the server did not start: {}",
            std::fs::read_to_string(&log).unwrap_or_default()
        )
    })
}

/// Resident memory of a process, bytes.
fn rss_of(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find(|l| l.starts_with("VmRSS:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|k| k.parse::<u64>().ok())
        .map_or(0, |k| k * 1024)
}

/// Samples a process's resident memory every 5 ms until stopped; returns the peak.
struct Peak {
    stop: Arc<AtomicBool>,
    peak: Arc<AtomicU64>,
    thread: std::thread::JoinHandle<()>,
}

impl Peak {
    fn watch(pid: u32) -> Peak {
        let (stop, peak) = (
            Arc::new(AtomicBool::new(false)),
            Arc::new(AtomicU64::new(0)),
        );
        let (s, p) = (stop.clone(), peak.clone());
        let thread = std::thread::spawn(move || {
            while !s.load(Ordering::Relaxed) {
                p.fetch_max(rss_of(pid), Ordering::Relaxed);
                std::thread::sleep(Duration::from_millis(5));
            }
        });
        Peak { stop, peak, thread }
    }

    fn end(self) -> u64 {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.join().unwrap();
        self.peak.load(Ordering::Relaxed)
    }
}

fn mib(b: u64) -> f64 {
    b as f64 / (1 << 20) as f64
}

fn row(bar: &str, measured: String, target: &str, pass: bool) {
    println!(
        "| {bar} | {measured} | {target} | {} |",
        if pass { "yes" } else { "NO" }
    );
}

fn main() {
    let seconds: u64 = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(20);
    let work = std::env::temp_dir().join(format!("fractile-hostile-bench-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&work);
    let dir = work.join("assets");
    std::fs::create_dir_all(&dir).unwrap();
    // Real assets: camera at two rates (told apart by size), jacksboro for points.
    let enc = |file: &str, bpp: f64| {
        let r = Raster::open(&data(file)).unwrap();
        let mut s = QuadtreeSettings {
            rate: RateMode::TargetBpp(bpp),
            ..QuadtreeSettings::default()
        };
        s.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(r.kind);
        encode(&r, &s, &|_, _| {}).unwrap().bytes
    };
    let (cam_a, cam_b) = (enc("camera.png", 0.2), enc("camera.png", 0.48));
    std::fs::write(dir.join("camera.fra"), &cam_b).unwrap();
    std::fs::write(dir.join("jacksboro.fra"), enc("jacksboro.tif", 0.8)).unwrap();
    std::fs::write(dir.join("jacksboro-utm.fra"), enc("jacksboro-utm.tif", 0.8)).unwrap();
    std::fs::write(dir.join("astronaut.fra"), enc("astronaut.png", 0.5)).unwrap();
    let crafted: Vec<(String, Vec<u8>)> = std::fs::read_dir(data("hostile"))
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.file_name().unwrap().to_string_lossy().contains("bomb"))
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect();
    for (name, bytes) in &crafted {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
    let port = 18300 + (std::process::id() % 500) as u16;
    let log = work.join("server.log");
    let t = Instant::now();
    let started = serve(&dir, port, log.clone());
    let elapsed = t.elapsed();
    println!(
        "issue 35 bars on {}, {} cores\n",
        binary(),
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    println!("| bar | measured | target | met |");
    println!("|---|---|---|---|");
    let text = std::fs::read_to_string(&log).unwrap_or_default();
    let named = crafted
        .iter()
        .filter(|(n, _)| text.contains(n.as_str()))
        .count();
    row(
        "folder of crafted files: starts, logs each",
        match started {
            Some(_) => format!(
                "up in {:.2} s, {named} of {} logged",
                elapsed.as_secs_f64(),
                crafted.len()
            ),
            None => "did not start".into(),
        },
        "starts, all logged",
        started.is_some() && named == crafted.len(),
    );
    let server = match started {
        Some(s) => s,
        None => {
            // Without the crafted files, so that the other bars are measured all the same.
            for (name, _) in &crafted {
                let _ = std::fs::remove_file(dir.join(name));
            }
            start(&dir, port, work.join("server-plain.log"))
        }
    };

    // 1. Crafted uploads.
    let mut worst = Duration::ZERO;
    let mut statuses = Vec::new();
    let base = rss_of(server.pid());
    let peak = Peak::watch(server.pid());
    for (_, bytes) in &crafted {
        let t = Instant::now();
        statuses.push(put(port, "crafted", bytes, Some(TOKEN)).unwrap_or(0));
        worst = worst.max(t.elapsed());
    }
    let extra = peak.end().saturating_sub(base);
    let all_422 = statuses.iter().all(|&s| s == 422);
    row(
        "crafted uploads: 422, time, extra memory",
        format!(
            "{statuses:?}, slowest {:.1} ms, +{:.1} MiB",
            worst.as_secs_f64() * 1e3,
            mib(extra)
        ),
        "422, < 100 ms, < 50 MB",
        all_422 && worst < Duration::from_millis(100) && extra < 50_000_000,
    );

    // 2. Unauthenticated 64 MiB uploads.
    let big = Arc::new(vec![7u8; 64 << 20]);
    let base = rss_of(server.pid());
    let peak = Peak::watch(server.pid());
    let threads: Vec<_> = (0..16)
        .map(|_| {
            let big = big.clone();
            std::thread::spawn(move || put(port, "intruder", &big, None).unwrap_or(0))
        })
        .collect();
    let statuses: Vec<u16> = threads.into_iter().map(|t| t.join().unwrap()).collect();
    std::thread::sleep(Duration::from_millis(200));
    let extra = peak.end().saturating_sub(base);
    let after = rss_of(server.pid()).saturating_sub(base);
    row(
        "16 unauthenticated 64 MiB uploads",
        format!(
            "{} of 16 answered 401, peak +{:.1} MiB, after +{:.1} MiB",
            statuses.iter().filter(|&&s| s == 401).count(),
            mib(extra),
            mib(after)
        ),
        "all 401, < 100 MB",
        statuses.iter().all(|&s| s == 401) && extra < 100_000_000,
    );

    // 3. Concurrent uploads of one id.
    let (cam_a, cam_b) = (Arc::new(cam_a), Arc::new(cam_b));
    let mut fivexx = 0;
    let mut other = Vec::new();
    let mut mismatched = 0;
    for round in 0..20 {
        let threads: Vec<_> = (0..8)
            .map(|k| {
                let body = if (k + round) % 2 == 0 {
                    cam_a.clone()
                } else {
                    cam_b.clone()
                };
                std::thread::spawn(move || put(port, "race", &body, Some(TOKEN)).unwrap_or(0))
            })
            .collect();
        for t in threads {
            let s = t.join().unwrap();
            if s >= 500 || s == 0 {
                fivexx += 1;
            } else if !(200..300).contains(&s) {
                other.push(s);
            }
        }
        let file = std::fs::metadata(dir.join("race.fra")).map_or(0, |m| m.len());
        let served = get(port, "/v1/assets/race")
            .and_then(|(_, _, b)| serde_json::from_slice::<serde_json::Value>(&b).ok())
            .and_then(|v| v["bytes"].as_u64())
            .unwrap_or(0);
        mismatched += usize::from(file != served);
    }
    let tile = "/v1/assets/race/tiles/1/0/0.png";
    let before = get(port, tile).and_then(|(_, h, _)| header(&h, "etag").map(str::to_string));
    server.stop();
    let server = start(&dir, port, work.join("server2.log"));
    let after_restart =
        get(port, tile).and_then(|(_, h, _)| header(&h, "etag").map(str::to_string));
    row(
        "8 concurrent uploads of one id, 20 rounds",
        format!(
            "{fivexx} 5xx, other {other:?}, {mismatched} rounds served != file, ETag {} across a restart",
            if before.is_some() && before == after_restart {
                "kept"
            } else {
                "CHANGED"
            }
        ),
        "no 5xx, same version",
        fivexx == 0 && mismatched == 0 && before.is_some() && before == after_restart,
    );

    // 4. Heavy regions against cached tiles and points.
    let cached = "/v1/assets/camera/tiles/2/1/1.png";
    let point = "/v1/assets/jacksboro/point/-84.2,36.6";
    let _ = get(port, cached);
    let probe = |path: &'static str, stop: Arc<AtomicBool>, out: Arc<Mutex<Vec<f64>>>| {
        std::thread::spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                let t = Instant::now();
                let ok = get(port, path).is_some_and(|r| r.0 == 200);
                if ok {
                    out.lock().unwrap().push(t.elapsed().as_secs_f64() * 1e3);
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        })
    };
    let measure = |load: bool| {
        let stop = Arc::new(AtomicBool::new(false));
        let (tiles, points) = (
            Arc::new(Mutex::new(Vec::new())),
            Arc::new(Mutex::new(Vec::new())),
        );
        let regions = Arc::new(AtomicU64::new(0));
        // The largest region each, on four kinds of work: a grey image, a colour one (three
        // planes), a projected DEM (reprojected point by point) and a geographic one as f32.
        const REGIONS: [&str; 4] = [
            "/v1/assets/camera/region?bbox=0,0,1,1&width=4096&height=4096",
            "/v1/assets/astronaut/region?bbox=0,0,1,1&width=4096&height=4096",
            "/v1/assets/jacksboro-utm/region?bbox=-84.45,36.4,-84.1,36.7&width=4096&height=4096",
            "/v1/assets/jacksboro/region?bbox=-84.45,36.4,-84.1,36.7&width=4096&height=4096&format=f32",
        ];
        let heavy: Vec<_> = REGIONS[..if load { 4 } else { 0 }]
            .iter()
            .map(|&path| {
                let (stop, regions) = (stop.clone(), regions.clone());
                std::thread::spawn(move || {
                    while !stop.load(Ordering::Relaxed) {
                        let r = get(port, path);
                        if r.is_some_and(|r| r.0 == 200) {
                            regions.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                })
            })
            .collect();
        // Let the heavy clients get going first.
        if load {
            std::thread::sleep(Duration::from_secs(2));
        }
        let base = rss_of(server.pid());
        let peak = Peak::watch(server.pid());
        let probes = [
            probe(cached, stop.clone(), tiles.clone()),
            probe(point, stop.clone(), points.clone()),
        ];
        std::thread::sleep(Duration::from_secs(if load {
            seconds
        } else {
            seconds.min(5)
        }));
        stop.store(true, Ordering::Relaxed);
        for t in probes {
            t.join().unwrap();
        }
        for t in heavy {
            t.join().unwrap();
        }
        let peak = peak.end();
        let t = tiles.lock().unwrap().clone();
        let p = points.lock().unwrap().clone();
        (t, p, regions.load(Ordering::Relaxed), peak.max(base))
    };
    let (t0, p0, _, _) = measure(false);
    let (t1, p1, regions, peak) = measure(true);
    let (tile99, point99) = (percentile(t1.clone(), 0.99), percentile(p1.clone(), 0.99));
    row(
        "cached tiles under 4 clients looping 4096^2 regions",
        format!(
            "p99 {tile99:.1} ms (p50 {:.1}; idle p99 {:.1}), {} probes, {regions} regions in {seconds} s, server peak {:.0} MiB",
            percentile(t1.clone(), 0.5),
            percentile(t0, 0.99),
            t1.len(),
            mib(peak)
        ),
        "p99 < 50 ms",
        tile99 < 50.0,
    );
    row(
        "points under the same load",
        format!(
            "p99 {point99:.1} ms (p50 {:.1}; idle p99 {:.1}), {} probes",
            percentile(p1.clone(), 0.5),
            percentile(p0, 0.99),
            p1.len()
        ),
        "p99 < 20 ms",
        point99 < 20.0,
    );
    server.stop();
    let _ = std::fs::remove_dir_all(&work);
}
