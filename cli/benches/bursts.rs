//! Issue 54's bars, measured on the release `fractile` binary as an operator would meet them:
//! a separate server process on loopback, its memory read from /proc, requests over raw TCP.
//! Prints one table row per bar.
//!
//! `cargo bench -p fractile-cli --bench bursts -- [seconds of the crafted-file loop, default 30]`
//!
//! 1. 8 concurrent 2048 x 2048 f32 regions of etopo20: at least one served, every refusal
//!    answered within 2 s with `Retry-After`.
//! 2. 16 slow readers of 64 MB regions: peak memory, and memory 30 s after they finish against
//!    the idle server's (bar: within 256 MB of it).
//! 4. 8 concurrent GeoJSON answers of a coastline's deepest level the server answers: peak
//!    memory within 256 MB of idle (issue 60).
//! 3. Crafted files (the hostile test files, truncated and corrupted copies of a real asset,
//!    a 100 GB sparse file, junk) replaced in the assets folder every 200 ms under a 1 s
//!    rescan: the server stays up, its memory within 256 MB of idle, and a broken file that does
//!    not change is logged once.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

#[path = "../tests/harness/mod.rs"]
mod harness;

use harness::{Server, binary, data, get, header};

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
        let _ = self.thread.join();
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

/// A GET whose body is read `chunk` bytes at a time with `pause` between reads: status, the
/// `Retry-After` header, bytes after the headers (a chunked body's framing included), time to
/// the status line.
fn slow_get(
    port: u16,
    path: &str,
    chunk: usize,
    pause: Duration,
) -> (u16, Option<String>, u64, f64) {
    let t = Instant::now();
    let Ok(mut s) = TcpStream::connect(("127.0.0.1", port)) else {
        return (0, None, 0, 0.0);
    };
    let _ = s.set_read_timeout(Some(Duration::from_secs(120)));
    let head = format!("GET {path} HTTP/1.1\r\nHost: bench\r\nConnection: close\r\n\r\n");
    if s.write_all(head.as_bytes()).is_err() {
        return (0, None, 0, 0.0);
    }
    let mut raw = Vec::new();
    let mut buf = vec![0u8; chunk];
    let (mut status, mut retry, mut first, mut body) = (0u16, None, 0.0, 0u64);
    loop {
        let n = match s.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        if status == 0 {
            raw.extend_from_slice(&buf[..n]);
            if let Some(split) = raw.windows(4).position(|w| w == b"\r\n\r\n") {
                let headers = String::from_utf8_lossy(&raw[..split]).into_owned();
                status = headers
                    .split_whitespace()
                    .nth(1)
                    .and_then(|c| c.parse().ok())
                    .unwrap_or(0);
                retry = header(&headers, "retry-after").map(str::to_string);
                first = t.elapsed().as_secs_f64();
                body = (raw.len() - split - 4) as u64;
            }
        } else {
            body += n as u64;
        }
        if !pause.is_zero() {
            std::thread::sleep(pause);
        }
    }
    (status, retry, body, first)
}

/// The crafted files the loop writes: the hostile test files, a real asset truncated and with
/// a byte flipped, junk; and `None` for the 100 GB sparse file.
fn crafted(good: &[u8]) -> Vec<Option<Vec<u8>>> {
    let mut files: Vec<Option<Vec<u8>>> = std::fs::read_dir(data("hostile"))
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "fra"))
        .map(|p| Some(std::fs::read(p).unwrap()))
        .collect();
    for cut in [12, 100, good.len() / 2, good.len() - 1] {
        files.push(Some(good[..cut].to_vec()));
    }
    for at in [8, 40, good.len() / 3] {
        let mut flipped = good.to_vec();
        flipped[at] ^= 0x5a;
        files.push(Some(flipped));
    }
    files.push(Some(vec![0xab; 3 << 20]));
    files.push(None);
    files
}

fn main() {
    let seconds: u64 = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(30);
    let work = std::env::temp_dir().join(format!("fractile-bursts-bench-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&work);
    let dir = work.join("assets");
    std::fs::create_dir_all(&dir).unwrap();
    let etopo = dir.join("etopo.fra");
    let encoded = std::process::Command::new(binary())
        .args(["encode", "-q"])
        .arg(data("etopo20.tif"))
        .arg("-o")
        .arg(&etopo)
        .status()
        .expect("fractile encode runs");
    assert!(encoded.success());
    let good = std::fs::read(&etopo).unwrap();
    let coded = std::process::Command::new(binary())
        .args(["encode", "-q"])
        .arg(data("curve/coast5.geojson"))
        .arg("-o")
        .arg(dir.join("coast.fra"))
        .status()
        .expect("fractile encode runs");
    assert!(coded.success());
    std::fs::write(dir.join("broken.fra"), &good[..good.len() / 2]).unwrap();
    let config = work.join("fractile.toml");
    std::fs::write(&config, "rescan_seconds = 1\n").unwrap();
    let port = harness::free_port();
    let log = work.join("server.log");
    let server = Server::start(
        dir.to_str().unwrap(),
        port,
        &["--config", config.to_str().unwrap()],
        &[],
        &log,
    );
    let pid = server.pid();
    println!(
        "issue 54 bars on {}, {} cores\n",
        binary(),
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    println!("| bar | measured | target | met |");
    println!("|---|---|---|---|");
    let _ = get(port, "/v1/assets/etopo/tiles/0/0/0.png");
    std::thread::sleep(Duration::from_secs(1));
    let idle = rss_of(pid);

    // 1. Concurrent heavy regions.
    let region = "/v1/assets/etopo/region?bbox=-180,-90,180,90&width=2048&height=2048&format=f32";
    let runs: Vec<_> = (0..8)
        .map(|_| std::thread::spawn(move || slow_get(port, region, 1 << 20, Duration::ZERO)))
        .collect();
    let answers: Vec<_> = runs.into_iter().map(|t| t.join().unwrap()).collect();
    let served = answers.iter().filter(|a| a.0 == 200).count();
    let refused: Vec<_> = answers.iter().filter(|a| a.0 == 503).collect();
    let slowest = refused.iter().map(|a| a.3).fold(0.0, f64::max);
    let with_retry = refused.iter().filter(|a| a.1.is_some()).count();
    let served_s: Vec<String> = answers
        .iter()
        .filter(|a| a.0 == 200)
        .map(|a| format!("{:.1}", a.3))
        .collect();
    row(
        "8 concurrent 2048^2 f32 regions",
        format!(
            "{served} served (in {} s), {} refused (slowest {slowest:.2} s, {with_retry} with Retry-After), other {:?}",
            served_s.join(", "),
            refused.len(),
            answers
                .iter()
                .filter(|a| a.0 != 200 && a.0 != 503)
                .map(|a| a.0)
                .collect::<Vec<_>>()
        ),
        ">= 1 served, refusals < 2 s with Retry-After",
        served >= 1 && slowest < 2.0 && with_retry == refused.len(),
    );

    // 2. Slow readers of 96 MB regions.
    let big = "/v1/assets/etopo/region?bbox=-180,-90,180,90&width=4096&height=4096&format=f32";
    let peak = Peak::watch(pid);
    let readers: Vec<_> = (0..16)
        .map(|_| {
            std::thread::spawn(move || slow_get(port, big, 256 << 10, Duration::from_millis(20)))
        })
        .collect();
    let answers: Vec<_> = readers.into_iter().map(|t| t.join().unwrap()).collect();
    let peak = peak.end();
    let done = rss_of(pid);
    std::thread::sleep(Duration::from_secs(30));
    let after = rss_of(pid);
    let full = answers
        .iter()
        .filter(|a| a.0 == 200 && a.2 >= 4096 * 4096 * 4)
        .count();
    let busy = answers
        .iter()
        .filter(|a| a.0 == 503 && a.1.is_some())
        .count();
    row(
        "16 slow readers of 64 MB regions",
        format!(
            "{full} read whole, {busy} refused with Retry-After; idle {:.0} MiB, peak {:.0}, at the end {:.0}, 30 s later {:.0} MiB",
            mib(idle),
            mib(peak),
            mib(done),
            mib(after)
        ),
        "30 s later < idle + 256 MiB",
        after < idle + (256 << 20) && full + busy == 16,
    );

    // 4. The deepest curve level answered, 8 at once.
    let deepest = (0..64)
        .take_while(|l| {
            get(port, &format!("/v1/assets/coast/curve?level={l}"))
                .is_some_and(|r| r.0 == 200 || r.0 == 503)
        })
        .last()
        .unwrap_or(0);
    let curve = format!("/v1/assets/coast/curve?level={deepest}");
    std::thread::sleep(Duration::from_secs(2));
    let idle = rss_of(pid);
    let peak = Peak::watch(pid);
    let runs: Vec<_> = (0..8)
        .map(|_| {
            let curve = curve.clone();
            std::thread::spawn(move || slow_get(port, &curve, 1 << 20, Duration::ZERO))
        })
        .collect();
    let answers: Vec<_> = runs.into_iter().map(|t| t.join().unwrap()).collect();
    let peak = peak.end();
    let served = answers.iter().filter(|a| a.0 == 200).count();
    let busy = answers
        .iter()
        .filter(|a| a.0 == 503 && a.1.is_some())
        .count();
    let body = answers.iter().map(|a| a.2).max().unwrap_or(0);
    row(
        "8 concurrent deepest curve levels",
        format!(
            "level {deepest} ({:.1} MB), {served} served, {busy} refused with Retry-After; idle {:.0} MiB, peak {:.0} MiB",
            body as f64 / 1e6,
            mib(idle),
            mib(peak)
        ),
        "peak < idle + 256 MiB",
        peak < idle + (256 << 20) && served >= 1 && served + busy == 8,
    );

    // 3. Crafted files replaced under a 1 s rescan.
    let files = crafted(&good);
    let idle = rss_of(pid);
    let peak = Peak::watch(pid);
    let t = Instant::now();
    let mut alive = true;
    let mut k = 0usize;
    while t.elapsed() < Duration::from_secs(seconds) {
        let name = dir.join(format!("crafted-{}.fra", k % 4));
        let _ = std::fs::remove_file(&name);
        match &files[k % files.len()] {
            Some(bytes) => write_in_steps(&name, bytes),
            None => {
                let f = std::fs::File::create(&name).unwrap();
                f.set_len(100 << 30).unwrap();
            }
        }
        k += 1;
        std::thread::sleep(Duration::from_millis(200));
        if get(port, "/healthz").map(|r| r.0) != Some(200) {
            alive = false;
            break;
        }
    }
    let peak = peak.end();
    let text = std::fs::read_to_string(&log).unwrap_or_default();
    let broken_logged = text.lines().filter(|l| l.contains("broken.fra")).count();
    let tile = get(port, "/v1/assets/etopo/tiles/1/0/0.png").map_or(0, |r| r.0);
    row(
        "crafted files replaced every 200 ms, 1 s rescan",
        format!(
            "{k} files in {seconds} s, server {}, tile {tile}, idle {:.0} MiB, peak {:.0} MiB, an unchanged broken file logged {broken_logged} times",
            if alive { "up" } else { "DOWN" },
            mib(idle),
            mib(peak)
        ),
        "up, peak < idle + 256 MiB, logged once",
        alive && tile == 200 && peak < idle + (256 << 20) && broken_logged == 1,
    );
    server.stop();
    let _ = std::fs::remove_dir_all(&work);
}

/// Writes `bytes` to `path` in a few writes with pauses, as a copy in progress does (a rescan
/// may read it half-written).
fn write_in_steps(path: &Path, bytes: &[u8]) {
    let Ok(mut f) = std::fs::File::create(path) else {
        return;
    };
    for part in bytes.chunks(bytes.len().div_ceil(3).max(1)) {
        let _ = f.write_all(part);
        let _ = f.flush();
        std::thread::sleep(Duration::from_millis(20));
    }
}
