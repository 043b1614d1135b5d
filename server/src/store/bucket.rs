//! A backing in a bucket of an S3-compatible object store (AWS S3, SeaweedFS, MinIO, R2),
//! through the Apache Arrow project's `object_store` crate, configured by the standard AWS
//! variables (`AWS_ENDPOINT_URL`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`,
//! `AWS_ALLOW_HTTP=true` for a plain-HTTP endpoint). An asset's header and chunk table are
//! read once; its chunks by range request when a tile needs them, kept decoded in the chunk
//! cache and, optionally, as bytes on local disk ([`DiskCache`]).
//!
//! Layout under the prefix:
//! - `versions/{id}/{sha256}-{length}.fra`: an asset file as uploaded, never changed once
//!   written (its name is the SHA-256 of its bytes and its length, see [`version_object`]);
//! - `{id}.ref`: the pointer, a small JSON object naming the version served;
//! - `{id}.fra`: an asset file put there by another tool (`aws s3 cp`, rclone), served when no
//!   pointer names the id.
//!
//! Why a new key per version and a pointer rather than one overwritten object: S3 replaces an
//! object atomically, but a replica reads a chunked asset's chunks by range for as long as it
//! serves it. Had an upload overwritten the object, a replica that had read the old header
//! would read the new file's bytes at the old offsets. With a key per version the old version
//! stays whole for the replicas still on it, and the pointer switch (one PUT, atomic in S3) is
//! the moment they move: each notices it at its next listing (`rescan_seconds`, one LIST of
//! the prefix). Old versions are deleted by a later upload of the id once [`GRACE`] old, and
//! those of a deleted id by a sweep every [`SWEEP_EVERY`] listings.
//! Conditional puts would order concurrent writers but leave the readers' problem as it was;
//! writers of one id are last-writer-wins, each version whole. A plain `{id}.fra` object is
//! read with `If-Match` its listed ETag, so a replacement by another tool is never mixed
//! either: its reads fail (503) until the next listing loads the new version.

use std::path::{Path as FsPath, PathBuf};

use sha2::Digest;
use std::sync::Arc;
use std::time::Duration;

use fractile_codec::chunked::ChunkSource;
use object_store::path::Path;
use object_store::{GetOptions, ObjectStore, ObjectStoreExt, PutPayload};

use super::backing::{Backing, Listing, validate_id};
use super::breaker::{BREAK, Breaker};

/// How long an old version is kept after it stopped being served: longer than replicas take to
/// notice a new pointer (`rescan_seconds`, default 10) and finish the requests begun on it.
pub(super) const GRACE: Duration = Duration::from_secs(120);

/// A bucket (and prefix) of an object store holding asset files.
pub(crate) struct Bucket {
    remote: Arc<Remote>,
    prefix: Path,
    url: String,
    /// Listings so far: every [`SWEEP_EVERY`]th also removes deleted ids' versions.
    listings: std::sync::atomic::AtomicU64,
}

/// How often (in listings) a replica looks for the versions of deleted ids: with the default
/// `rescan_seconds` of 10, every 10 minutes, one LIST of `versions/` more.
const SWEEP_EVERY: u64 = 60;

/// The object store, the runtime its calls are driven on, and the disk cache of its ranges.
struct Remote {
    store: Arc<dyn ObjectStore>,
    /// `object_store` is async and the [`Backing`] calls are blocking (they run on decoding
    /// threads, not on the server's executor): each call is driven to its end on this small
    /// runtime of the bucket's own, which also works where no runtime is (tests, tools).
    runtime: Option<tokio::runtime::Runtime>,
    disk: Option<DiskCache>,
    /// Whether chunk reads go to the store (see [`Breaker`]).
    breaker: Breaker,
}

impl Remote {
    #[expect(
        clippy::expect_used,
        reason = "the runtime is taken only in drop, after which no call is made"
    )]
    fn block<F: std::future::Future>(&self, f: F) -> F::Output {
        self.runtime
            .as_ref()
            .expect("runtime until dropped")
            .block_on(f)
    }
}

impl Drop for Remote {
    fn drop(&mut self) {
        // Dropping a runtime waits for its tasks, which may not happen inside another one.
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

/// What `{id}.ref` holds.
#[derive(serde::Serialize, serde::Deserialize)]
struct Pointer {
    /// Key of the version served, under the prefix.
    object: String,
    /// Its length in bytes.
    bytes: u64,
}

impl Bucket {
    /// The bucket of `url` (`s3://bucket` or `s3://bucket/prefix`), its credentials and
    /// endpoint from the standard AWS variables. A request that gets no answer fails after a
    /// few seconds (two retries at most), so that a store that has gone away gives clear
    /// errors (503) rather than requests that hang. Ranges read are kept under `disk` when
    /// given. Nothing is read yet.
    pub(crate) fn connect(url: &str, disk: Option<DiskCache>) -> std::io::Result<Bucket> {
        let (store, prefix) = s3_store(url)?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("object-store")
            .enable_all()
            .build()?;
        Ok(Bucket {
            remote: Arc::new(Remote {
                store,
                runtime: Some(runtime),
                disk,
                breaker: Breaker::default(),
            }),
            prefix,
            url: url.to_string(),
            listings: Default::default(),
        })
    }

    fn key(&self, name: &str) -> Path {
        Path::from_iter(self.prefix.parts().chain(Path::from(name).parts()))
    }

    fn versions(&self, id: &str) -> Path {
        self.key(&format!("versions/{id}"))
    }

    /// The pointer of `id`, if there is one.
    fn pointer(&self, id: &str) -> std::io::Result<Option<Pointer>> {
        let got = self.remote.block(async {
            self.remote
                .store
                .get(&self.key(&format!("{id}.ref")))
                .await?
                .bytes()
                .await
        });
        match got {
            Ok(bytes) => serde_json::from_slice(&bytes)
                .map(Some)
                .map_err(|e| std::io::Error::other(format!("the pointer of {id}: {e}"))),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    /// Deletes the versions, over [`GRACE`] old, of the ids under `versions/` that are not
    /// `live`: what a delete left for the replicas still reading them. (A live id's old
    /// versions go when it is next uploaded.) Replicas sweeping at once race harmlessly.
    fn sweep(&self, live: &[&str]) -> std::io::Result<()> {
        let listed = self.remote.block(
            self.remote
                .store
                .list_with_delimiter(Some(&self.key("versions"))),
        )?;
        for dir in listed.common_prefixes {
            match dir.filename() {
                Some(id) if !live.contains(&id) && validate_id(id).is_ok() => {
                    self.collect_versions(id, &[])?
                }
                _ => {}
            }
        }
        Ok(())
    }

    /// Deletes the versions of `id` other than `keep` that are over [`GRACE`] old.
    fn collect_versions(&self, id: &str, keep: &[&str]) -> std::io::Result<()> {
        let listed = self.remote.block(
            self.remote
                .store
                .list_with_delimiter(Some(&self.versions(id))),
        )?;
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs() as i64);
        for o in listed.objects {
            let old = now - o.last_modified.timestamp() > GRACE.as_secs() as i64;
            if old && !keep.contains(&o.location.as_ref()) {
                // Another replica's sweep may have been first.
                match self.remote.block(self.remote.store.delete(&o.location)) {
                    Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                    Err(e) => return Err(e.into()),
                }
            }
        }
        Ok(())
    }
}

/// The object store of `url` and the key under it: [`fractile_remote::s3_store`], which the
/// command line's transfers (`encode --part`, `assemble`) and the Python package open too.
pub use fractile_remote::s3_store;

impl Backing for Bucket {
    fn list(&self) -> std::io::Result<Listing> {
        let listed = self
            .remote
            .block(self.remote.store.list_with_delimiter(Some(&self.prefix)))?;
        // id -> (version, from a pointer)
        let mut found: std::collections::BTreeMap<String, (String, bool)> = Default::default();
        let mut listing = Listing::default();
        for o in listed.objects {
            let Some(name) = o.location.filename() else {
                continue;
            };
            let (id, pointer) = match name.rsplit_once('.') {
                Some((id, "ref")) => (id, true),
                Some((id, "fra")) => (id, false),
                _ => continue,
            };
            if validate_id(id).is_err() {
                listing
                    .skipped
                    .push(format!("{}: not a valid asset id", o.location));
                continue;
            }
            // A pointer's version is its ETag; a plain object's is its ETag too (read with
            // If-Match), or its time and length where the store gives no ETag.
            let tag = o.e_tag.clone().unwrap_or_else(|| {
                format!(
                    "{}:{}",
                    o.last_modified.timestamp_nanos_opt().unwrap_or(0),
                    o.size
                )
            });
            let version = if pointer {
                format!("ref:{tag}")
            } else {
                format!("fra:{tag}")
            };
            let entry = found
                .entry(id.to_string())
                .or_insert((version.clone(), pointer));
            if pointer && !entry.1 {
                *entry = (version, true);
            }
        }
        listing.files = found.into_iter().map(|(id, (v, _))| (id, v)).collect();
        let n = self
            .listings
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if n % SWEEP_EVERY == SWEEP_EVERY - 1 {
            let live: Vec<&str> = listing.files.iter().map(|(id, _)| id.as_str()).collect();
            if let Err(e) = self.sweep(&live) {
                tracing::warn!("{}: versions of deleted assets not swept: {e}", self.url);
            }
        }
        Ok(listing)
    }

    fn open(&self, id: &str, version: &str) -> std::io::Result<Box<dyn ChunkSource>> {
        let (key, length, if_match) = match version.split_once(':') {
            Some(("ref", _)) => {
                // The pointer as it is now: if it moved since the listing, this loads the newer
                // version under the older tag, and the next listing loads it again (never the
                // reverse), which costs a reload and mixes nothing.
                let p = self.pointer(id)?.ok_or_else(|| {
                    std::io::Error::new(std::io::ErrorKind::NotFound, "its pointer is gone")
                })?;
                (self.key(&p.object), p.bytes, None)
            }
            Some(("fra", tag)) => {
                let key = self.key(&format!("{id}.fra"));
                let meta = self.remote.block(self.remote.store.head(&key))?;
                // The ETag listed, so that a replacement since is refused, not mixed in.
                (key, meta.size, meta.e_tag.filter(|t| t == tag))
            }
            _ => return Err(std::io::Error::other(format!("unknown version {version}"))),
        };
        Ok(Box::new(ObjectSource {
            remote: self.remote.clone(),
            cache_name: format!("{key}\n{}", if_match.as_deref().unwrap_or("")),
            key,
            length,
            if_match,
            url: format!("{}/{id}", self.url.trim_end_matches('/')),
        }))
    }

    fn put(&self, id: &str, bytes: &[u8]) -> std::io::Result<String> {
        let object = version_object(id, bytes);
        let previous = self.pointer(id)?;
        let payload = PutPayload::from(bytes.to_vec());
        self.remote
            .block(self.remote.store.put(&self.key(&object), payload))?;
        let pointer = serde_json::to_vec(&Pointer {
            object: object.clone(),
            bytes: bytes.len() as u64,
        })
        .map_err(std::io::Error::other)?;
        let put = self.remote.block(
            self.remote
                .store
                .put(&self.key(&format!("{id}.ref")), PutPayload::from(pointer)),
        )?;
        let keep_new = self.key(&object);
        let keep_old = previous.map(|p| self.key(&p.object));
        let mut keep = vec![keep_new.as_ref()];
        keep.extend(keep_old.as_ref().map(|k| k.as_ref()));
        if let Err(e) = self.collect_versions(id, &keep) {
            // The upload stands; old versions wait for the next one.
            tracing::warn!("old versions of {id} not deleted: {e}");
        }
        Ok(format!("ref:{}", put.e_tag.unwrap_or_default()))
    }

    fn delete(&self, id: &str) -> std::io::Result<()> {
        for name in [format!("{id}.ref"), format!("{id}.fra")] {
            match self
                .remote
                .block(self.remote.store.delete(&self.key(&name)))
            {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(e.into()),
            }
        }
        // Replicas still on a version read it until their next listing drops the id; a
        // request then may fail (503) as it would a moment later with 404.
        if let Err(e) = self.collect_versions(id, &[]) {
            tracing::warn!("versions of the deleted {id} left for a later sweep: {e}");
        }
        Ok(())
    }

    fn describe(&self) -> String {
        self.url.clone()
    }

    fn locate(&self, id: &str) -> String {
        format!("{}/{id}", self.url.trim_end_matches('/'))
    }
}

/// An object read by range (a version's, immutable; or a plain one, read with If-Match).
struct ObjectSource {
    remote: Arc<Remote>,
    key: Path,
    length: u64,
    if_match: Option<String>,
    /// What names these bytes in the disk cache: the key and, for a plain object, its ETag.
    cache_name: String,
    url: String,
}

impl ChunkSource for ObjectSource {
    fn len(&self) -> u64 {
        self.length
    }

    fn read(&self, offset: u64, len: usize) -> std::io::Result<Vec<u8>> {
        let end = self.end_of(offset, len)?;
        let name = format!("{}\n{offset}\n{len}", self.cache_name);
        if let Some(bytes) = self.remote.disk.as_ref().and_then(|d| d.get(&name))
            && bytes.len() == len
        {
            return Ok(bytes);
        }
        let breaker = &self.remote.breaker;
        if !breaker.admit() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::ConnectionRefused,
                format!(
                    "{}: the store did not answer a read in the last {BREAK:?}; not tried again yet",
                    self.url
                ),
            ));
        }
        let options = GetOptions::new()
            .with_range(Some(offset..end))
            .with_if_match(self.if_match.clone());
        let got = self.remote.block(async {
            self.remote
                .store
                .get_opts(&self.key, options)
                .await?
                .bytes()
                .await
        });
        // An answer that is the object's (gone, replaced) is the store answering.
        breaker.found(matches!(
            got,
            Ok(_)
                | Err(object_store::Error::NotFound { .. }
                    | object_store::Error::Precondition { .. }
                    | object_store::Error::NotModified { .. })
        ));
        let bytes = got?;
        if bytes.len() != len {
            return Err(std::io::Error::from(std::io::ErrorKind::UnexpectedEof));
        }
        if let Some(d) = &self.remote.disk {
            d.put(&name, &bytes);
        }
        Ok(bytes.to_vec())
    }

    fn describe(&self) -> String {
        self.url.clone()
    }
}

/// Ranges of objects kept on local disk, bounded in bytes, least recently used out first: a
/// chunk evicted from the (decoded, in-memory) chunk cache is then read from disk, not from
/// the store. The index is in memory, so the folder is emptied at start. Only immutable bytes
/// are kept (a version's, or a plain object's under its ETag), so an entry is never stale.
pub(crate) struct DiskCache {
    dir: PathBuf,
    index: moka::sync::Cache<u64, u32>,
}

impl DiskCache {
    /// A cache of at most `bytes` in `dir` (created; the files of an earlier run removed).
    pub(crate) fn new(dir: &FsPath, bytes: u64) -> std::io::Result<DiskCache> {
        std::fs::create_dir_all(dir)?;
        for e in std::fs::read_dir(dir)?.flatten() {
            let ours = e
                .file_name()
                .to_str()
                .is_some_and(|n| n.ends_with(".range") || n.ends_with(".tmp"));
            if ours {
                let _ = std::fs::remove_file(e.path());
            }
        }
        let folder = dir.to_path_buf();
        let index = moka::sync::Cache::builder()
            .max_capacity(bytes)
            .weigher(|_, len: &u32| *len)
            .eviction_listener(move |k: Arc<u64>, _, cause| {
                if cause != moka::notification::RemovalCause::Replaced {
                    let _ = std::fs::remove_file(folder.join(format!("{:016x}.range", *k)));
                }
            })
            .build();
        Ok(DiskCache {
            dir: dir.to_path_buf(),
            index,
        })
    }

    fn hash(name: &str) -> u64 {
        use std::hash::{Hash, Hasher};
        // 64 bits of SipHash: a collision would give the wrong bytes of the right length,
        // which the chunk's CRC in the table then refuses (read again is not tried: 503).
        let mut h = std::collections::hash_map::DefaultHasher::new();
        name.hash(&mut h);
        h.finish()
    }

    fn path(&self, key: u64) -> PathBuf {
        self.dir.join(format!("{key:016x}.range"))
    }

    fn get(&self, name: &str) -> Option<Vec<u8>> {
        let key = DiskCache::hash(name);
        self.index.get(&key)?;
        std::fs::read(self.path(key)).ok()
    }

    fn put(&self, name: &str, bytes: &[u8]) {
        let key = DiskCache::hash(name);
        let Ok(len) = u32::try_from(bytes.len()) else {
            return;
        };
        static WRITES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = WRITES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let tmp = self.dir.join(format!("{key:016x}.{n}.tmp"));
        let written =
            std::fs::write(&tmp, bytes).and_then(|()| std::fs::rename(&tmp, self.path(key)));
        match written {
            Ok(()) => self.index.insert(key, len),
            Err(e) => {
                let _ = std::fs::remove_file(&tmp);
                tracing::warn!("disk cache {}: {e}", self.dir.display());
            }
        }
    }
}

/// The object of an upload of `bytes` as `id`: named by a digest of the whole file, so that the
/// same upload twice is the same object and different bytes never share one. It was named by
/// the file's last four bytes and length, and a chunked file's last four bytes are only its
/// last chunk's CRC: two files of one length with two chunks swapped shared a version, which
/// an upload through another replica then overwrote under the readers of the first. A
/// content-addressed key needs no check after the PUT: whatever object holds that key holds
/// those bytes.
pub(super) fn version_object(id: &str, bytes: &[u8]) -> String {
    let digest = sha2::Sha256::digest(bytes);
    let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
    format!("versions/{id}/{hex}-{}.fra", bytes.len())
}

#[cfg(test)]
mod tests {
    use super::DiskCache;

    /// Two files of one length and the same last bytes (as a chunked file with two chunks
    /// swapped is) are two versions; one file twice is one.
    #[test]
    fn versions_are_named_by_the_whole_file() {
        let a: Vec<u8> = (0..100u8).collect();
        let mut b = a.clone();
        b.swap(10, 20);
        assert_eq!((a.len(), &a[90..]), (b.len(), &b[90..]));
        let (va, vb) = (
            super::version_object("x", &a),
            super::version_object("x", &b),
        );
        assert_ne!(va, vb);
        assert_eq!(va, super::version_object("x", &a.clone()));
        assert!(
            va.starts_with("versions/x/") && va.ends_with("-100.fra"),
            "{va}"
        );
        // The SHA-256 of the bytes 0..100 (Python's hashlib).
        let sha = "bce0aff19cf5aa6a7469a30d61d04e4376e4bbf6381052ee9e7f33925c954d52";
        assert_eq!(va, format!("versions/x/{sha}-100.fra"));
    }

    fn ranges(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
        std::fs::read_dir(dir)
            .unwrap()
            .flatten()
            .map(|e| e.path())
            .collect()
    }

    /// Ranges come back as they were put, the bytes on disk stay within the bound (evicted
    /// files are deleted), and a new cache on the folder starts empty.
    #[test]
    fn the_disk_cache_keeps_ranges_within_its_bound() {
        let dir = std::env::temp_dir().join(format!("fractile-disk-cache-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let cache = DiskCache::new(&dir, 10_000).unwrap();
        let range = |k: u8| vec![k; 3_000];
        for k in 0..8u8 {
            cache.put(&format!("object\n{k}"), &range(k));
        }
        cache.index.run_pending_tasks();
        let kept: Vec<u8> = (0..8u8)
            .filter(|&k| cache.get(&format!("object\n{k}")).is_some())
            .collect();
        assert!(!kept.is_empty() && kept.len() <= 3, "kept {kept:?}");
        for &k in &kept {
            assert_eq!(cache.get(&format!("object\n{k}")).unwrap(), range(k));
        }
        let on_disk: u64 = ranges(&dir)
            .iter()
            .map(|p| std::fs::metadata(p).unwrap().len())
            .sum();
        assert!(on_disk <= 10_000, "{on_disk} bytes on disk");
        assert!(cache.get("object\nnever").is_none());
        drop(cache);
        let again = DiskCache::new(&dir, 10_000).unwrap();
        assert!(ranges(&dir).is_empty(), "a new cache starts empty");
        assert!(again.get("object\n0").is_none());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
