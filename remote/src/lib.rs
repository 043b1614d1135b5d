//! Assets where they lie: an `s3://` object (S3, SeaweedFS, MinIO, R2) or an `http(s)://`
//! file (the server's `/v1/assets/{id}/file`, nginx, a CDN), read by range as a
//! [`ChunkSource`], so that a chunked asset is opened by its header and only the chunks an
//! answer touches are fetched. What the server's bucket, the command line's transfers and the
//! Python package share; the server adds its disk cache and breaker around [`s3_store`].

use std::sync::Arc;
use std::time::Duration;

use fractile_codec::chunked::ChunkSource;
use object_store::path::Path;
use object_store::{GetOptions, ObjectStore, ObjectStoreExt};

pub mod inputs;

/// The object store of `url` (`s3://bucket` or `s3://bucket/key`) and the key under it, its
/// credentials and endpoint from the standard AWS variables (`AWS_ENDPOINT_URL`,
/// `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`, `AWS_ALLOW_HTTP=true` for a
/// plain-HTTP endpoint). A request that gets no answer fails after a few seconds (a 2 s
/// connect timeout, two retries at most), so that a store that has gone away gives clear
/// errors rather than requests that hang.
pub fn s3_store(url: &str) -> std::io::Result<(Arc<dyn ObjectStore>, Path)> {
    let parsed = url.strip_prefix("s3://").ok_or_else(|| {
        std::io::Error::other(format!(
            "{url}: only s3:// object stores are supported (S3, SeaweedFS, MinIO, R2)"
        ))
    })?;
    let (bucket, key) = parsed.split_once('/').unwrap_or((parsed, ""));
    let retry = object_store::RetryConfig {
        max_retries: 2,
        retry_timeout: Duration::from_secs(10),
        ..Default::default()
    };
    // Set key by key: `with_client_options` would drop those of the environment
    // (AWS_ALLOW_HTTP among them).
    use object_store::ClientConfigKey as C;
    use object_store::aws::AmazonS3ConfigKey as K;
    let store = object_store::aws::AmazonS3Builder::from_env()
        .with_bucket_name(bucket)
        .with_retry(retry)
        .with_config(K::Client(C::ConnectTimeout), "2s")
        .with_config(K::Client(C::Timeout), "30s")
        .build()
        .map_err(|e| std::io::Error::other(format!("{url}: {e}")))?;
    Ok((Arc::new(store), Path::from(key.trim_matches('/'))))
}

/// Whether `location` names a remote asset this crate opens (`s3://`, `http://`, `https://`)
/// rather than a local path.
pub fn is_remote(location: &str) -> bool {
    ["s3://", "http://", "https://"]
        .iter()
        .any(|s| location.starts_with(s))
}

/// The asset at `url`, read by range: an `s3://bucket/key` object or an `http(s)://` file
/// whose server answers `Range` requests (`206 Partial Content`). Its length is asked now;
/// its bytes when a read needs them. A store or server that cannot be reached is an error
/// of kind `ConnectionRefused`, `TimedOut` or `Other`; a missing object `NotFound`.
pub fn open(url: &str) -> std::io::Result<Box<dyn ChunkSource>> {
    open_with(url, READ_TIMEOUT)
}

/// How long an HTTP answer may send nothing (its headers or its next bytes) before the read
/// fails as timed out: a server that stalls mid-body held a reader for minutes.
pub const READ_TIMEOUT: Duration = Duration::from_secs(30);

/// [`open`], an HTTP answer that sends nothing for `read_timeout` failing as timed out.
pub fn open_with(url: &str, read_timeout: Duration) -> std::io::Result<Box<dyn ChunkSource>> {
    let runtime = Runtime::new()?;
    let http = http_client(read_timeout)?;
    let store = match url.starts_with("s3://") {
        true => Some(s3_store(url)?),
        false => None,
    };
    open_on(&runtime, &http, store, url, None)
}

/// The small runtime that drives a reader's requests to their end (the codec's reads are
/// blocking, on decoding threads; `object_store` and `reqwest` are async), shared by the
/// readers one [`inputs::Opener`] opens.
pub(crate) struct Runtime(Option<tokio::runtime::Runtime>);

impl Runtime {
    pub(crate) fn new() -> std::io::Result<Arc<Runtime>> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("fractile-remote")
            .enable_all()
            .build()?;
        Ok(Arc::new(Runtime(Some(runtime))))
    }

    pub(crate) fn block_on<F: std::future::Future>(&self, f: F) -> std::io::Result<F::Output> {
        match &self.0 {
            Some(rt) => Ok(rt.block_on(f)),
            None => Err(std::io::Error::other("the reader is closed")),
        }
    }
}

impl Drop for Runtime {
    fn drop(&mut self) {
        // Dropping a runtime waits for its tasks, which may not happen inside another one.
        if let Some(rt) = self.0.take() {
            rt.shutdown_background();
        }
    }
}

/// The HTTP client of readers: a server that stalls mid-body is left after `read_timeout`
/// without a byte, and no answer takes over 120 s in all.
pub(crate) fn http_client(read_timeout: Duration) -> std::io::Result<reqwest::Client> {
    reqwest::Client::builder()
        .user_agent(concat!("fractile/", env!("CARGO_PKG_VERSION")))
        .connect_timeout(Duration::from_secs(10))
        .read_timeout(read_timeout)
        .timeout(Duration::from_secs(120))
        .build()
        .map_err(std::io::Error::other)
}

/// `url` opened on `runtime`: through `store` (its object store and key) for `s3://`, through
/// `http` otherwise; an object's length asked unless `known` (a listing gave it).
pub(crate) fn open_on(
    runtime: &Arc<Runtime>,
    http: &reqwest::Client,
    store: Option<(Arc<dyn ObjectStore>, Path)>,
    url: &str,
    known: Option<u64>,
) -> std::io::Result<Box<dyn ChunkSource>> {
    let remote = if let Some((store, key)) = store {
        let size = match known {
            Some(size) => size,
            None => runtime.block_on(store.head(&key))?.map_err(io)?.size,
        };
        Remote::Object { store, key }.with(runtime.clone(), size, url)
    } else if url.starts_with("http://") || url.starts_with("https://") {
        let (length, whole) = runtime.block_on(http_length(http, url))??;
        if let Some(bytes) = whole {
            // A server that ignores ranges sent the file whole: keep it.
            return Ok(Box::new(fractile_codec::chunked::InMemory(bytes.into())));
        }
        Remote::Http {
            http: http.clone(),
            url: url.to_string(),
        }
        .with(runtime.clone(), length, url)
    } else {
        return Err(std::io::Error::other(format!(
            "{url}: not a remote location (s3://, http:// or https://)"
        )));
    };
    Ok(Box::new(remote))
}

/// The length of the file at `url` from a one-byte range request (`Content-Range: bytes
/// 0-0/LENGTH`), which every range-capable server answers, unlike `HEAD` with a length
/// (some proxies drop it). A `200` answer is the whole file, returned as it came.
async fn http_length(http: &reqwest::Client, url: &str) -> std::io::Result<(u64, Option<Vec<u8>>)> {
    let r = http
        .get(url)
        .header(reqwest::header::RANGE, "bytes=0-0")
        .send()
        .await
        .map_err(|e| http_error(url, e))?;
    let status = r.status();
    if status == reqwest::StatusCode::OK {
        let bytes = body_at_most(r, MOST_WHOLE, url).await.map_err(|e| {
            std::io::Error::new(
                e.kind(),
                format!("{e} (the server ignores Range requests: serve the file from one that answers them)"),
            )
        })?;
        return Ok((bytes.len() as u64, Some(bytes)));
    }
    if status != reqwest::StatusCode::PARTIAL_CONTENT {
        return Err(status_error(url, status));
    }
    let total = r
        .headers()
        .get(reqwest::header::CONTENT_RANGE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.rsplit_once('/'))
        .and_then(|(_, n)| n.trim().parse::<u64>().ok())
        .ok_or_else(|| {
            std::io::Error::other(format!(
                "{url}: a range answer without the file's length (Content-Range)"
            ))
        })?;
    Ok((total, None))
}

/// The most bytes taken from a server that ignores `Range` and sends a file whole: one
/// that sent a 100 GB file this way was buffered whole.
const MOST_WHOLE: usize = 256 << 20;

/// The body of `r`, `most` bytes at most: a server that says or sends more is an error, and
/// what it sends past that is not read.
async fn body_at_most(
    mut r: reqwest::Response,
    most: usize,
    url: &str,
) -> std::io::Result<Vec<u8>> {
    let over = |n: String| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{url}: the server sends {n} bytes where {most} at most were asked"),
        )
    };
    if let Some(n) = r.content_length()
        && n > most as u64
    {
        return Err(over(n.to_string()));
    }
    let mut out = Vec::with_capacity(r.content_length().map_or(0, |n| n as usize));
    while let Some(piece) = r.chunk().await.map_err(|e| http_error(url, e))? {
        if out.len() + piece.len() > most {
            return Err(over(format!("more than {}", out.len() + piece.len())));
        }
        out.extend_from_slice(&piece);
    }
    Ok(out)
}

fn http_error(url: &str, e: reqwest::Error) -> std::io::Error {
    let kind = if e.is_timeout() {
        std::io::ErrorKind::TimedOut
    } else if e.is_connect() {
        std::io::ErrorKind::ConnectionRefused
    } else {
        std::io::ErrorKind::Other
    };
    std::io::Error::new(kind, format!("{url}: {e}"))
}

fn status_error(url: &str, status: reqwest::StatusCode) -> std::io::Error {
    let kind = match status.as_u16() {
        404 | 410 => std::io::ErrorKind::NotFound,
        401 | 403 => std::io::ErrorKind::PermissionDenied,
        _ => std::io::ErrorKind::Other,
    };
    std::io::Error::new(kind, format!("{url}: the server answered {status}"))
}

fn io(e: object_store::Error) -> std::io::Error {
    e.into()
}

/// Where the bytes come from.
enum Remote {
    Object {
        store: Arc<dyn ObjectStore>,
        key: Path,
    },
    Http {
        http: reqwest::Client,
        url: String,
    },
}

impl Remote {
    fn with(self, runtime: Arc<Runtime>, length: u64, url: &str) -> Ranged {
        Ranged {
            remote: self,
            runtime,
            length,
            url: url.to_string(),
        }
    }
}

/// A remote file read by range, each read driven to its end on a small runtime (its own, or
/// shared by the inputs of an encode).
struct Ranged {
    remote: Remote,
    runtime: Arc<Runtime>,
    length: u64,
    url: String,
}

impl ChunkSource for Ranged {
    fn len(&self) -> u64 {
        self.length
    }

    fn read(&self, offset: u64, len: usize) -> std::io::Result<Vec<u8>> {
        let end = self.end_of(offset, len)?;
        if len == 0 {
            return Ok(Vec::new());
        }
        let runtime = &self.runtime;
        let bytes = match &self.remote {
            Remote::Object { store, key } => runtime.block_on(async {
                let options = GetOptions::new().with_range(Some(offset..end));
                store.get_opts(key, options).await?.bytes().await
            })??,
            Remote::Http { http, url } => runtime.block_on(async {
                let r = http
                    .get(url)
                    .header(
                        reqwest::header::RANGE,
                        format!("bytes={offset}-{}", end - 1),
                    )
                    .send()
                    .await
                    .map_err(|e| http_error(url, e))?;
                if r.status() != reqwest::StatusCode::PARTIAL_CONTENT {
                    return Err(status_error(url, r.status()));
                }
                body_at_most(r, len, url).await.map(Into::into)
            })??,
        };
        if bytes.len() != len {
            return Err(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                format!("{}: {} bytes for a range of {len}", self.url, bytes.len()),
            ));
        }
        Ok(bytes.to_vec())
    }

    fn describe(&self) -> String {
        self.url.clone()
    }
}
