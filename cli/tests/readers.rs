//! The readers outside the server's tiles, as an attacker or a careless user meets them
//! (issue 74): `fractile serve`'s `/v1/assets/{id}/file` as a static host serves a file (the
//! stored bytes of every format version, ETags, conditional requests, ranges, HEAD, CORS, and
//! memory under many and slow readers, over real TCP), and the command line's reads (a 100 GB
//! sparse file, reads 8x and more coarser than a chunked asset, sizes over the limit).

#[path = "harness/mod.rs"]
mod harness;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use harness::{Server, binary, data, free_port, header, request};

fn tempdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("fractile-readers-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn run(args: &[&str]) -> std::process::Output {
    Command::new(binary())
        .args(args)
        .output()
        .expect("the fractile binary runs")
}

fn ok(out: std::process::Output) -> std::process::Output {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// `fractile encode INPUT -o OUT FLAGS...`, which must succeed.
fn encode(input: &Path, out: &Path, flags: &[&str]) {
    let mut args = vec![
        "encode",
        input.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(flags);
    ok(run(&args));
}

/// `fractile serve --assets ASSETS` on a free loopback port with `args`, its log in `log_dir`.
fn serve(assets: &Path, args: &[&str], log_dir: &Path) -> Server {
    Server::start(
        assets.to_str().unwrap(),
        free_port(),
        args,
        &[],
        &log_dir.join("server.log"),
    )
}

/// A request with extra header lines (each ending in `\r\n`): status, headers, body.
fn ask(port: u16, method: &str, path: &str, extra: &str) -> (u16, String, Vec<u8>) {
    request(
        port,
        &format!("{method} {path} HTTP/1.1\r\nHost: test\r\n{extra}Connection: close\r\n\r\n"),
        &[],
    )
    .expect("an answer")
}

/// The golden files of format versions 1 to 4 (and 5 to 7) in a folder the server reads.
fn golden_folder(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files = Vec::new();
    for e in std::fs::read_dir(data("golden")).unwrap() {
        let path = e.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("fra") {
            continue;
        }
        let id = path
            .file_stem()
            .unwrap()
            .to_str()
            .unwrap()
            .replace('.', "_");
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(dir.join(format!("{id}.fra")), &bytes).unwrap();
        files.push((id, bytes));
    }
    files.sort();
    files
}

/// `/file` answers as a static host: the stored bytes of every format version under an ETag
/// that is stable and changes with the file; If-None-Match, If-Match and If-Range; 416 with
/// `Content-Range: bytes */LEN`; suffix ranges longer than the file; HEAD without a body; CORS
/// that lets a page on another origin see Content-Range and ETag; a file replaced in the
/// folder served new, never cut to the old length under the old ETag.
#[test]
fn files_are_served_as_a_static_host_serves_them() {
    let dir = tempdir("static");
    let files = golden_folder(&dir);
    assert!(files.iter().any(|(id, _)| id.starts_with("v1-")));
    // No rescan: what `/file` answers of a replaced file is its own doing.
    let config = dir.join("fractile.toml");
    std::fs::write(&config, "rescan_seconds = 0\n").unwrap();
    let server = serve(&dir, &["--config", config.to_str().unwrap()], &dir);
    let port = server.port;
    // Curves of versions 1 and 2 are not served (their coding changed in version 3): every
    // other file is.
    let (_, _, catalog) = ask(port, "GET", "/v1/assets", "");
    let catalog = String::from_utf8_lossy(&catalog).into_owned();
    let files: Vec<(String, Vec<u8>)> = files
        .into_iter()
        .filter(|(id, _)| catalog.contains(&format!("\"{id}\"")))
        .collect();
    for v in ["v1-", "v2-", "v3-", "v4-", "v5-", "v6-", "v7-"] {
        assert!(
            files.iter().any(|(id, _)| id.starts_with(v)),
            "no {v} file served"
        );
    }
    for (id, bytes) in &files {
        let path = format!("/v1/assets/{id}/file");
        let (s, h, b) = ask(port, "GET", &path, "");
        assert_eq!(s, 200, "{id}: {}", String::from_utf8_lossy(&b));
        assert!(b == *bytes, "{id}: the stored bytes, whatever the version");
        let etag = header(&h, "etag").expect("an ETag").to_string();
        assert_eq!(
            header(&h, "content-length"),
            Some(&*bytes.len().to_string())
        );
        // Stable: the same tag again.
        let (_, h2, _) = ask(port, "GET", &path, "Range: bytes=0-0\r\n");
        assert_eq!(header(&h2, "etag"), Some(etag.as_str()), "{id}");
        // A range of an old version is its own bytes (a re-serialised body cut to the old
        // length failed its checksum).
        let (s, h, b) = ask(port, "GET", &path, "Range: bytes=8-40\r\n");
        assert_eq!(s, 206, "{id}");
        assert_eq!(b, bytes[8..=40], "{id}");
        assert_eq!(
            header(&h, "content-range"),
            Some(&*format!("bytes 8-40/{}", bytes.len()))
        );
    }
    let (id, bytes) = files
        .iter()
        .find(|(id, _)| id.starts_with("v2-fis"))
        .expect("v2 fis");
    let path = format!("/v1/assets/{id}/file");
    let len = bytes.len();
    let (_, h, _) = ask(port, "HEAD", &path, "");
    let etag = header(&h, "etag").unwrap().to_string();
    // HEAD: the length, no body.
    let (s, h, b) = ask(port, "HEAD", &path, "");
    assert_eq!(s, 200);
    assert!(b.is_empty());
    assert_eq!(header(&h, "content-length"), Some(&*len.to_string()));
    // If-None-Match: 304 for the same version (weak comparison), 200 otherwise.
    let (s, h, b) = ask(port, "GET", &path, &format!("If-None-Match: {etag}\r\n"));
    assert_eq!(s, 304);
    assert!(b.is_empty());
    assert_eq!(header(&h, "etag"), Some(etag.as_str()));
    let (s, _, _) = ask(port, "GET", &path, &format!("If-None-Match: W/{etag}\r\n"));
    assert_eq!(s, 304);
    let (s, _, _) = ask(port, "GET", &path, "If-None-Match: \"other\"\r\n");
    assert_eq!(s, 200);
    // If-Match: 412 for another version.
    let (s, _, b) = ask(port, "GET", &path, "If-Match: \"other\"\r\n");
    assert_eq!(s, 412);
    assert_eq!(
        serde_json::from_slice::<serde_json::Value>(&b).unwrap()["code"],
        "precondition_failed"
    );
    let (s, _, _) = ask(port, "GET", &path, &format!("If-Match: {etag}\r\n"));
    assert_eq!(s, 200);
    // If-Range: the range while the tag is current, the whole file once it is not.
    let (s, _, b) = ask(
        port,
        "GET",
        &path,
        &format!("Range: bytes=0-9\r\nIf-Range: {etag}\r\n"),
    );
    assert_eq!((s, b.len()), (206, 10));
    let (s, _, b) = ask(
        port,
        "GET",
        &path,
        "Range: bytes=0-9\r\nIf-Range: \"stale\"\r\n",
    );
    assert_eq!((s, b.len()), (200, len));
    // RFC 9110: a suffix longer than the file is all of it; a last byte past the end is the end.
    let (s, h, b) = ask(port, "GET", &path, "Range: bytes=-100000000\r\n");
    assert_eq!(s, 206);
    assert!(b == *bytes);
    assert_eq!(
        header(&h, "content-range"),
        Some(&*format!("bytes 0-{}/{len}", len - 1))
    );
    let (s, _, b) = ask(port, "GET", &path, "Range: bytes=10-100000000\r\n");
    assert_eq!(s, 206);
    assert_eq!(b, bytes[10..]);
    // 416 carries the length.
    let (s, h, _) = ask(
        port,
        "GET",
        &path,
        &format!("Range: bytes={}-\r\n", len + 5),
    );
    assert_eq!(s, 416);
    assert_eq!(
        header(&h, "content-range"),
        Some(&*format!("bytes */{len}"))
    );
    // CORS: a page on another origin may ask by range and read the headers a reader needs.
    let (s, h, _) = ask(
        port,
        "OPTIONS",
        &path,
        "Origin: http://elsewhere.test\r\nAccess-Control-Request-Method: GET\r\nAccess-Control-Request-Headers: range,if-none-match\r\n",
    );
    assert!(s == 200 || s == 204, "preflight: {s}");
    let allowed = header(&h, "access-control-allow-headers")
        .unwrap_or_default()
        .to_ascii_lowercase();
    assert!(
        allowed.contains("range") && allowed.contains("if-none-match"),
        "{allowed}"
    );
    let (_, h, _) = ask(
        port,
        "GET",
        &path,
        "Origin: http://elsewhere.test\r\nRange: bytes=0-3\r\n",
    );
    assert_eq!(header(&h, "access-control-allow-origin"), Some("*"));
    let exposed = header(&h, "access-control-expose-headers")
        .unwrap_or_default()
        .to_ascii_lowercase();
    for name in ["content-range", "etag", "content-length"] {
        assert!(exposed.contains(name), "{name} not exposed: {exposed}");
    }
    // Replaced in the folder (renamed over, as `cp` to a temporary and `mv` do), with no rescan
    // for an hour: the next answer is the new file under a new tag, never a mix.
    let other = files
        .iter()
        .find(|(i, _)| i.starts_with("v5-projected-lifted"))
        .expect("v5 projected")
        .1
        .clone();
    let tmp = dir.join("replacing.tmp");
    std::fs::write(&tmp, &other).unwrap();
    std::fs::rename(&tmp, dir.join(format!("{id}.fra"))).unwrap();
    let (s, h, b) = ask(port, "GET", &path, "");
    assert_eq!(s, 200);
    assert!(b == other, "the new file whole ({} bytes)", b.len());
    assert_ne!(header(&h, "etag"), Some(etag.as_str()));
    // Rewritten in place (the same inode) with the first file again: that file whole, under
    // its own tag again (the tag is the content's, equal on every replica).
    std::fs::write(dir.join(format!("{id}.fra")), bytes).unwrap();
    let (s, h, b) = ask(port, "GET", &path, "");
    assert_eq!(s, 200);
    assert!(b == *bytes);
    assert_eq!(header(&h, "etag"), Some(etag.as_str()));
    server.stop();
}

/// The resident memory of process `pid`, in bytes.
fn rss_of(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_default()
        .lines()
        .find(|l| l.starts_with("VmRSS:"))
        .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
        .map_or(0, |kb| kb * 1024)
}

/// Samples the peak resident memory of `pid` every 20 ms until `stop`.
fn peak_rss(pid: u32, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<u64> {
    std::thread::spawn(move || {
        let peak = AtomicU64::new(0);
        while !stop.load(Ordering::Relaxed) {
            peak.fetch_max(rss_of(pid), Ordering::Relaxed);
            std::thread::sleep(Duration::from_millis(20));
        }
        peak.into_inner()
    })
}

/// `/file` holds a piece per reader, not a file: 200 concurrent whole reads of a
/// multi-megabyte asset and 200 concurrent one-byte ranges, each checked byte for byte, and
/// 200 readers that take a byte a second, grow the server's resident memory by under 256 MB
/// (they took it from 620 MB to 2,369 MB, and +1,768 MB, when answers were built whole).
#[test]
fn many_and_slow_readers_hold_little_memory() {
    let dir = tempdir("memory");
    let assets = dir.join("assets");
    std::fs::create_dir_all(&assets).unwrap();
    // etopo20 at twice its resolution, coded near-losslessly: a file of some megabytes.
    let exact = dir.join("etopo.fra");
    encode(&data("etopo20.tif"), &exact, &["--max-error", "0"]);
    let fine = dir.join("etopo-x2.tif");
    ok(run(&[
        "decode",
        exact.to_str().unwrap(),
        "-o",
        fine.to_str().unwrap(),
        "--scale",
        "2",
    ]));
    let asset = assets.join("big.fra");
    encode(&fine, &asset, &["--max-error", "0.25"]);
    let bytes = Arc::new(std::fs::read(&asset).unwrap());
    assert!(bytes.len() > 2 << 20, "{} bytes", bytes.len());
    let server = serve(&assets, &[], &dir);
    let port = server.port;
    let pid = server.pid();
    // Warm: the asset is loaded and a first answer made.
    let (s, _, b) = ask(port, "GET", "/v1/assets/big/file", "");
    assert_eq!(s, 200);
    assert_eq!(b.len(), bytes.len());
    std::thread::sleep(Duration::from_millis(300));
    let base = rss_of(pid);
    let stop = Arc::new(AtomicBool::new(false));
    let sampler = peak_rss(pid, stop.clone());
    let readers: Vec<_> = (0..200)
        .map(|_| {
            let bytes = bytes.clone();
            std::thread::spawn(move || {
                let (s, _, b) = ask(port, "GET", "/v1/assets/big/file", "");
                s == 200 && b == *bytes
            })
        })
        .collect();
    let whole = readers
        .into_iter()
        .filter_map(|r| r.join().ok())
        .filter(|read| *read)
        .count();
    // 200 concurrent one-byte ranges (each re-serialised the file before: +1.1 GB).
    let ranges: Vec<_> = (0..200)
        .map(|i| {
            let bytes = bytes.clone();
            std::thread::spawn(move || {
                let at = i * 9973 % bytes.len();
                let (s, _, b) = ask(
                    port,
                    "GET",
                    "/v1/assets/big/file",
                    &format!("Range: bytes={at}-{at}\r\n"),
                );
                s == 206 && b == [bytes[at]]
            })
        })
        .collect();
    let ranged = ranges
        .into_iter()
        .filter_map(|r| r.join().ok())
        .filter(|read| *read)
        .count();
    // Slow readers: each asks for the file and takes a byte a second for 5 s.
    let mut slow: Vec<TcpStream> = (0..200)
        .filter_map(|_| {
            let mut s = TcpStream::connect(("127.0.0.1", port)).ok()?;
            s.set_read_timeout(Some(Duration::from_secs(2))).ok()?;
            s.write_all(b"GET /v1/assets/big/file HTTP/1.1\r\nHost: test\r\n\r\n")
                .ok()?;
            Some(s)
        })
        .collect();
    for _ in 0..5 {
        for s in &mut slow {
            let mut one = [0u8; 1];
            let _ = s.read(&mut one);
        }
        std::thread::sleep(Duration::from_secs(1));
    }
    let held = slow.len();
    stop.store(true, Ordering::Relaxed);
    let peak = sampler.join().unwrap();
    drop(slow);
    let growth = peak.saturating_sub(base);
    println!(
        "base {} MB, peak {} MB, growth {} MB ({whole} whole reads of {} bytes, {held} slow readers)",
        base >> 20,
        peak >> 20,
        growth >> 20,
        bytes.len()
    );
    assert_eq!(whole, 200, "every whole read got the file");
    assert_eq!(ranged, 200, "every one-byte range got its byte");
    assert_eq!(held, 200);
    assert!(growth < 256 << 20, "grew {} MB", growth >> 20);
    server.stop();
}

/// A 100 GB sparse file is refused from its length, fast and in little memory, by `info` and
/// `decode` (it aborted the process asking for 107,374,182,400 bytes).
#[test]
fn a_huge_file_is_refused_before_it_is_read() {
    let dir = tempdir("huge");
    let path = dir.join("huge.fra");
    let f = std::fs::File::create(&path).unwrap();
    f.set_len(100 << 30).unwrap();
    let mut f = f;
    f.write_all(b"FRACTILE\x05\x00\x01\x06").unwrap();
    drop(f);
    for args in [
        vec!["info", path.to_str().unwrap()],
        vec![
            "decode",
            path.to_str().unwrap(),
            "-o",
            dir.join("out.tif").to_str().unwrap(),
        ],
    ] {
        let t = std::time::Instant::now();
        let out = run(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert!(
            err.contains("over any asset that is not chunked"),
            "{args:?}: {err}"
        );
        assert!(t.elapsed() < Duration::from_secs(10), "{args:?}");
    }
    let _ = std::fs::remove_file(&path);
}

/// Reads 8x and more coarser than a chunked asset's source (coarser than its top overview)
/// are the server's values, not NaN (`fractile decode --width 64` of etopo20 in chunks of 256
/// was all NaN, exit 0); and a read over the size limit is refused before it is made.
#[test]
fn coarse_reads_of_chunked_assets_are_the_servers() {
    let dir = tempdir("coarse");
    let assets = dir.join("assets");
    std::fs::create_dir_all(&assets).unwrap();
    let asset = assets.join("etopo.fra");
    encode(&data("etopo20.tif"), &asset, &["--chunk", "256"]);
    let server = serve(&assets, &[], &dir);
    let (s, _, meta) = ask(server.port, "GET", "/v1/assets/etopo", "");
    assert_eq!(s, 200);
    let meta: serde_json::Value = serde_json::from_slice(&meta).unwrap();
    let bounds: Vec<f64> = serde_json::from_value(meta["bounds"].clone()).unwrap();
    let relief =
        meta["value_range"][1].as_f64().unwrap() - meta["value_range"][0].as_f64().unwrap();
    // 1080 x 540 cells, the top overview 270 x 135: 17x and 34x coarser.
    for (w, h) in [(64, 32), (32, 16), (8, 4)] {
        let out = dir.join(format!("coarse-{w}.tif"));
        ok(run(&[
            "decode",
            asset.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--width",
            &w.to_string(),
            "--height",
            &h.to_string(),
        ]));
        let ours = fractile_codec::Raster::open(&out)
            .unwrap()
            .channels
            .remove(0);
        let bbox = format!("{},{},{},{}", bounds[0], bounds[1], bounds[2], bounds[3]);
        let (s, _, body) = ask(
            server.port,
            "GET",
            &format!("/v1/assets/etopo/region?bbox={bbox}&width={w}&height={h}&format=f32"),
            "",
        );
        assert_eq!(s, 200, "{}", String::from_utf8_lossy(&body));
        let theirs = f32s(&dechunked(&body));
        assert_eq!(ours.len(), w * h);
        assert_eq!(theirs.len(), w * h);
        assert!(
            ours.iter().all(|v| v.is_finite()),
            "{w}x{h}: NaN in the read"
        );
        // The same decode; the pixel centres differ by the rounding of the box's degrees.
        let worst = ours
            .iter()
            .zip(&theirs)
            .map(|(a, b)| f64::from((a - b).abs()))
            .fold(0.0, f64::max);
        assert!(
            worst <= 1e-4 * relief,
            "{w}x{h}: {worst} m from the server's"
        );
    }
    server.stop();
    let out = run(&[
        "decode",
        asset.to_str().unwrap(),
        "-o",
        dir.join("huge.tif").to_str().unwrap(),
        "--width",
        "20000",
        "--height",
        "20000",
    ]);
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("read the asset in windows"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A body sent in HTTP/1.1 chunked transfer coding, decoded (the harness reads raw bytes).
fn dechunked(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let line = b
            .windows(2)
            .position(|w| w == b"\r\n")
            .expect("a chunk size");
        let size = usize::from_str_radix(std::str::from_utf8(&b[..line]).unwrap().trim(), 16)
            .expect("a hexadecimal chunk size");
        if size == 0 {
            return out;
        }
        out.extend_from_slice(&b[line + 2..line + 2 + size]);
        b = &b[line + 2 + size + 2..];
    }
}

/// Little-endian f32s.
fn f32s(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}
