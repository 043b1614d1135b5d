//! Files of the command line that live in object storage: `encode --part I/N -o s3://...` and
//! `fractile assemble s3://... -o s3://...` move the part files and the asset through a bucket
//! (the standard AWS variables, as `serve --assets s3://...`), so that the machines of a split
//! encode share no volume. A remote output is written to a local temporary file and then
//! uploaded in parts (bounded memory, whatever its size); a remote input is downloaded to one.
//! An asset assembled into the bucket as `{prefix}/{id}.fra` is served by replicas over that
//! prefix at their next listing.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use futures_util::StreamExt;
use object_store::{ObjectStoreExt, WriteMultipart};
use tokio::io::AsyncWriteExt;

/// Whether `p` names an object (`s3://bucket/key`) rather than a local file.
pub(crate) fn is_remote(p: &Path) -> bool {
    p.to_str().is_some_and(|s| s.starts_with("s3://"))
}

/// A local file standing for `path`: `path` itself, or, for an object, a file in a temporary
/// folder that [`Local::finish`] uploads (outputs) or that was downloaded (inputs).
pub(crate) struct Local {
    file: PathBuf,
    object: Option<String>,
    _dir: Option<tempfile::TempDir>,
}

impl Local {
    /// Where to write `path` locally.
    pub(crate) fn output(path: &Path) -> Result<Local> {
        if !is_remote(path) {
            return Ok(Local {
                file: path.to_path_buf(),
                object: None,
                _dir: None,
            });
        }
        let dir = tempfile::tempdir().context("a temporary folder for the upload")?;
        Ok(Local {
            file: dir.path().join("upload.fra"),
            object: Some(path.display().to_string()),
            _dir: Some(dir),
        })
    }

    /// `path` as a local file: itself, or the object downloaded.
    pub(crate) fn input(path: &Path) -> Result<Local> {
        if !is_remote(path) {
            return Local::output(path);
        }
        let dir = tempfile::tempdir().context("a temporary folder for the download")?;
        // The object's own name, so that messages about the file name the part.
        let file = dir
            .path()
            .join(path.file_name().unwrap_or("download.fra".as_ref()));
        let url = path.display().to_string();
        block_on(download(&url, &file)).with_context(|| format!("reading {url}"))?;
        Ok(Local {
            file,
            object: None,
            _dir: Some(dir),
        })
    }

    /// The local file.
    pub(crate) fn path(&self) -> &Path {
        &self.file
    }

    /// Uploads an output to its object (nothing for a local file).
    pub(crate) fn finish(self) -> Result<()> {
        if let Some(url) = &self.object {
            block_on(upload(&self.file, url)).with_context(|| format!("writing {url}"))?;
        }
        Ok(())
    }
}

fn block_on<F: std::future::Future>(f: F) -> F::Output {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("a tokio runtime")
        .block_on(f)
}

async fn upload(file: &Path, url: &str) -> Result<()> {
    let (store, key) = fractile_server::s3_store(url)?;
    let mut from = tokio::fs::File::open(file).await?;
    let mut to = WriteMultipart::new(store.put_multipart(&key).await?);
    let mut buf = vec![0u8; 8 << 20];
    loop {
        let n = tokio::io::AsyncReadExt::read(&mut from, &mut buf).await?;
        if n == 0 {
            break;
        }
        // At most a few parts in flight: memory stays bounded by them.
        to.wait_for_capacity(4).await?;
        to.write(&buf[..n]);
    }
    to.finish().await?;
    Ok(())
}

async fn download(url: &str, file: &Path) -> Result<()> {
    let (store, key) = fractile_server::s3_store(url)?;
    let mut stream = store.get(&key).await?.into_stream();
    let mut to = tokio::fs::File::create(file).await?;
    while let Some(bytes) = stream.next().await {
        to.write_all(&bytes?).await?;
    }
    to.flush().await?;
    Ok(())
}
