//! The assets the server holds, over a [`Backing`]: a folder of `.fra` files ([`Folder`], the
//! default) or a bucket of an object store ([`Bucket`], `--assets s3://bucket/prefix`). The
//! catalog is loaded at start (a broken file is reported and skipped, the rest serve) and kept
//! up to date with what other replicas store ([`Store::refresh`]). Without `--assets`, the
//! built-in demo assets, encoded from small real files shipped in the binary at first start and
//! cached on disk afterwards.

use fractile_proto::ErrorCode;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Arc, RwLock};

use fractile_codec::chunked::{ChunkCache, ChunkSource};
use fractile_codec::geo::Placement;
use fractile_codec::{Asset, AssetLimits};

use crate::error::AppError;

mod backing;
mod breaker;
mod bucket;
mod demo;
mod folder;
pub(crate) use backing::{Backing, validate_id};
pub use bucket::s3_store;
pub(crate) use bucket::{Bucket, DiskCache};
pub(crate) use demo::ensure_demo_assets;
pub(crate) use folder::Folder;

/// An asset with what the server derives from it once.
pub struct StoredAsset {
    /// Its id (file stem).
    pub id: String,
    /// The decoded asset.
    pub asset: Asset,
    /// File size in bytes.
    pub bytes: u64,
    /// Checksum of the file, part of every ETag (so equal on every replica).
    pub hash: u32,
    /// Where it lies on the Earth (geographic georeference), if it does.
    pub placement: Option<Placement>,
}

impl StoredAsset {
    /// Its key among the coarse grids the server keeps ([`fractile_codec::extract::CoarseGrids`]):
    /// its id and checksum hashed, so that a replaced file is decoded anew.
    pub fn coarse_key(&self) -> u64 {
        use std::hash::{Hash, Hasher};
        let mut h = std::collections::hash_map::DefaultHasher::new();
        (&self.id, self.hash).hash(&mut h);
        h.finish()
    }
}

/// An asset's file as stored, opened at the version the catalog serves ([`Store::file`]).
pub struct StoredFile {
    /// The catalog's entry (its checksum and length make the ETag).
    pub asset: Arc<StoredAsset>,
    /// The file, read by range.
    pub source: Box<dyn ChunkSource>,
    /// The backing's version of it.
    pub version: String,
}

/// The asset catalog over a `Backing`.
pub struct Store {
    backing: Box<dyn Backing>,
    assets: RwLock<BTreeMap<String, Arc<StoredAsset>>>,
    /// What one asset may claim and cost (checked on load and on upload).
    limits: AssetLimits,
    /// Decoded chunks of the chunked assets (`chunk_cache_mib`), shared by all of them.
    chunks: ChunkCache,
    /// Held while a file is replaced and the catalog updated, so that concurrent writers of
    /// an id serialise and the file stored is always the version served.
    writes: std::sync::Mutex<()>,
    /// Each served file's version when it was loaded, for [`Store::refresh`].
    versions: std::sync::Mutex<BTreeMap<String, String>>,
    /// The version of each file that did not load: it is not read (nor logged) again until it
    /// changes (a 2 GB junk file was read at every rescan, and every broken file logged).
    failed: std::sync::Mutex<BTreeMap<String, String>>,
}

/// What [`Store::refresh`] found changed in the backing.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Refreshed {
    /// Ids of files new to the catalog, or replaced, and loaded.
    pub loaded: Vec<String>,
    /// Ids whose file is gone, dropped from the catalog.
    pub removed: Vec<String>,
    /// Files that changed but do not load (the version served before stays): one message each.
    pub skipped: Vec<String>,
    /// Why the backing could not be listed, if it could not (the catalog is left as it was).
    pub unreachable: Option<String>,
}

/// A backing that failed, `what` it was doing (storing, deleting, reading): 503, since a store
/// that comes back serves again (a failed write changed nothing). Where and why go to the log,
/// not to the client.
fn storage_unavailable(what: &str, id: &str, e: std::io::Error) -> AppError {
    tracing::error!("{what} asset {id}: {e}");
    AppError {
        status: axum::http::StatusCode::SERVICE_UNAVAILABLE,
        code: ErrorCode::StorageUnavailable,
        detail: format!("the asset store failed ({what}); try again"),
        retry_after: Some(1),
    }
}

impl Store {
    /// Loads every `*.fra` file of `dir` under the default [`AssetLimits`]; returns the store
    /// and one message per skipped file.
    pub fn open(dir: &Path) -> std::io::Result<(Store, Vec<String>)> {
        Store::open_with(dir, AssetLimits::default())
    }

    /// Loads every `*.fra` file of `dir`, refusing those over `limits`: temporary files left by
    /// an interrupted write are removed first, and symbolic links are skipped (the folder's own
    /// files only). Returns the store and one message per skipped file.
    pub fn open_with(dir: &Path, limits: AssetLimits) -> std::io::Result<(Store, Vec<String>)> {
        Store::open_with_cache(dir, limits, ChunkCache::new(DEFAULT_CHUNK_CACHE_MIB << 20))
    }

    /// [`Store::open_with`], the chunked assets' decoded chunks kept in `chunks`. A chunked
    /// file is opened by its header alone; its chunks are read by range when a request needs
    /// them.
    pub fn open_with_cache(
        dir: &Path,
        limits: AssetLimits,
        chunks: ChunkCache,
    ) -> std::io::Result<(Store, Vec<String>)> {
        Store::over(Box::new(Folder::open(dir)?), limits, chunks)
    }

    /// The catalog of every asset file of `backing`, under `limits`, chunks decoded into
    /// `chunks`; an error when the backing cannot be listed. Returns the store and one message
    /// per skipped file.
    pub fn over(
        backing: Box<dyn Backing>,
        limits: AssetLimits,
        chunks: ChunkCache,
    ) -> std::io::Result<(Store, Vec<String>)> {
        let listing = backing
            .list()
            .map_err(|e| std::io::Error::new(e.kind(), format!("{}: {e}", backing.describe())))?;
        let mut skipped = listing.skipped;
        let mut assets = BTreeMap::new();
        let mut versions = BTreeMap::new();
        let mut failed = BTreeMap::new();
        for (id, version) in listing.files {
            match load_from(backing.as_ref(), &id, &version, &limits, &chunks) {
                // A file that changed while read waits for the first rescan.
                Ok(_) | Err(_) if changed_under(backing.as_ref(), &id, &version) => {}
                Ok(a) => {
                    versions.insert(id.clone(), version);
                    assets.insert(id, Arc::new(a));
                }
                Err(e) => {
                    failed.insert(id, version);
                    skipped.push(e);
                }
            }
        }
        Ok((
            Store {
                backing,
                assets: RwLock::new(assets),
                limits,
                chunks,
                writes: std::sync::Mutex::new(()),
                versions: std::sync::Mutex::new(versions),
                failed: std::sync::Mutex::new(failed),
            },
            skipped,
        ))
    }

    /// Where the assets are kept, for messages.
    pub fn describe(&self) -> String {
        self.backing.describe()
    }

    /// Validates an uploaded asset and stores it (see `Backing::put`: readers see the old
    /// file or the new one), replacing any asset of that id. Writers of one id serialise: the
    /// file and the catalog are updated together, so the last writer's version is both.
    /// Blocking.
    pub fn put(&self, id: &str, bytes: &[u8]) -> Result<Arc<StoredAsset>, AppError> {
        validate_id(id)?;
        let bad_asset = |e: fractile_codec::Error| AppError {
            status: axum::http::StatusCode::UNPROCESSABLE_ENTITY,
            code: ErrorCode::BadAsset,
            detail: e.to_string(),
            retry_after: None,
        };
        let stored = load(id, bytes, &self.limits, &self.chunks).map_err(bad_asset)?;
        // A georeference that puts the asset off the globe is a wrong file, not one to serve
        // over the unit square as a folder's file would be: its catalog entry showed a
        // latitude of -18,683.
        let meta = &stored.asset.meta;
        if let Some(g) = &meta.georef
            && let Err(e @ fractile_codec::geo::PlacementError::OffTheGlobe(_)) =
                Placement::of(g, meta.width, meta.height)
        {
            return Err(bad_asset(fractile_codec::Error::asset(e.to_string())));
        }
        // A chunked upload is checked whole: a file is stored only when every chunk is sound.
        if let Some(c) = &stored.asset.chunked() {
            c.verify().map_err(bad_asset)?;
        }
        let stored = Arc::new(stored);
        let _write = self.writes.lock().unwrap_or_else(|e| e.into_inner());
        let version = self
            .backing
            .put(id, bytes)
            .map_err(|e| storage_unavailable("storing", id, e))?;
        // A chunked upload is served from where it is stored, read by range as any replica
        // reads it, not from the upload's bytes: the server's memory stays bounded by its
        // caches, not by what was uploaded to it. Should that read fail, the bytes serve.
        let stored = match &stored.asset.chunked() {
            Some(_) => match load_from(
                self.backing.as_ref(),
                id,
                &version,
                &self.limits,
                &self.chunks,
            ) {
                Ok(reopened) => Arc::new(reopened),
                Err(e) => {
                    tracing::warn!("{id} served from the uploaded bytes until reloaded: {e}");
                    stored
                }
            },
            None => stored,
        };
        self.assets
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .insert(id.to_string(), stored.clone());
        self.versions
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(id.to_string(), version);
        Ok(stored)
    }

    /// Removes an asset and its file. Blocking.
    pub fn delete(&self, id: &str) -> Result<(), AppError> {
        validate_id(id)?;
        let _write = self.writes.lock().unwrap_or_else(|e| e.into_inner());
        if !self
            .assets
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .contains_key(id)
        {
            return Err(AppError::not_found(
                ErrorCode::UnknownAsset,
                format!("no asset {id:?}"),
            ));
        }
        // The file first: when the backing refuses, the asset is still served and still there.
        self.backing
            .delete(id)
            .map_err(|e| storage_unavailable("deleting", id, e))?;
        self.assets
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .remove(id);
        self.versions
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(id);
        Ok(())
    }

    /// The asset `id`, or 404.
    pub fn get(&self, id: &str) -> Result<Arc<StoredAsset>, AppError> {
        validate_id(id)?;
        self.assets
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .get(id)
            .cloned()
            .ok_or_else(|| AppError::not_found(ErrorCode::UnknownAsset, format!("no asset {id:?}")))
    }

    /// The asset `id` and its file as stored, at the version served, for `/file`: the bytes
    /// the catalog's entry (and so its ETag) was made from, whatever format version they are
    /// (never written again from the decoded asset). A file replaced since it was loaded (a
    /// folder's file renamed over or rewritten in place) brings the catalog up to date first;
    /// one still changing is 503. Blocking.
    pub fn file(&self, id: &str) -> Result<StoredFile, AppError> {
        let changing = || AppError {
            status: axum::http::StatusCode::SERVICE_UNAVAILABLE,
            code: ErrorCode::StorageUnavailable,
            detail: format!("the file of {id:?} is being replaced; try again"),
            retry_after: Some(1),
        };
        for attempt in 0..2 {
            let a = self.get(id)?;
            let version = self
                .versions
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .get(id)
                .cloned()
                .ok_or_else(changing)?;
            if changed_under(self.backing.as_ref(), id, &version) {
                if attempt == 0 {
                    self.refresh();
                    continue;
                }
                return Err(changing());
            }
            let source = self
                .backing
                .open(id, &version)
                .map_err(|e| storage_unavailable("reading", id, e))?;
            if source.len() != a.bytes || changed_under(self.backing.as_ref(), id, &version) {
                return Err(changing());
            }
            return Ok(StoredFile {
                asset: a,
                source,
                version,
            });
        }
        Err(changing())
    }

    /// Whether the file of `id` is still at `version` (cheap where the backing can tell, as
    /// a folder can; always where versions cannot change under a reader): what a long answer
    /// from [`Store::file`] checks as it goes, against the version it opened.
    pub fn unchanged(&self, id: &str, version: &str) -> bool {
        !changed_under(self.backing.as_ref(), id, version)
    }

    /// Decodes the chunked assets' chunks into the chunk cache on a thread of its own, until
    /// it is 90% full (see `Chunked::prefetch`), and logs what it cached: the first requests
    /// then wait on no chunk. Requests still run meanwhile; a chunk both want is decoded once.
    pub fn prefetch_in_background(&self) {
        let assets: Vec<Arc<StoredAsset>> = self
            .list()
            .into_iter()
            .filter(|a| a.asset.chunked().is_some())
            .collect();
        if assets.is_empty() {
            return;
        }
        let budget = self.chunks.capacity() / 10 * 9;
        let spawned = std::thread::Builder::new()
            .name("chunk-prefetch".into())
            .spawn(move || {
                let t = std::time::Instant::now();
                for a in assets {
                    if let Some(c) = &a.asset.chunked() {
                        let (n, bytes) = c.prefetch(budget);
                        tracing::info!(
                            "prefetched {n} chunks of {} ({} MiB) in {:.1} s",
                            a.id,
                            bytes >> 20,
                            t.elapsed().as_secs_f64()
                        );
                    }
                }
            });
        if let Err(e) = spawned {
            tracing::warn!("no chunk prefetch: {e}");
        }
    }

    /// Brings the catalog up to date with the backing, as another process sharing it (a
    /// replica on one volume or bucket) left it: files new or replaced since they were loaded
    /// (their version differs) are loaded, ids whose file is gone are dropped. A changed file
    /// that does not load is logged and its previous version kept; a backing that cannot be
    /// listed changes nothing. Reads only the listing and the changed files; `serve` runs it
    /// every `rescan_seconds`. Blocking.
    pub fn refresh(&self) -> Refreshed {
        let mut found = Refreshed::default();
        // Writers of this process wait for the rescan, listing included: a listing taken
        // before a write finished would not hold what it stored, and would drop it.
        let _write = self.writes.lock().unwrap_or_else(|e| e.into_inner());
        let listing = match self.backing.list() {
            Ok(l) => l,
            Err(e) => {
                found.unreachable = Some(format!("{}: {e}", self.backing.describe()));
                return found;
            }
        };
        let changed: Vec<(String, String)> = {
            let versions = self.versions.lock().unwrap_or_else(|e| e.into_inner());
            let mut failed = self.failed.lock().unwrap_or_else(|e| e.into_inner());
            failed.retain(|id, _| listing.files.iter().any(|(i, _)| i == id));
            listing
                .files
                .iter()
                .filter(|(id, v)| versions.get(id) != Some(v) && failed.get(id) != Some(v))
                .cloned()
                .collect()
        };
        let present: std::collections::BTreeSet<&str> =
            listing.files.iter().map(|(id, _)| id.as_str()).collect();
        for (id, version) in changed {
            match load_from(
                self.backing.as_ref(),
                &id,
                &version,
                &self.limits,
                &self.chunks,
            ) {
                // Still being written: read again at the next rescan, whole.
                Ok(_) | Err(_) if changed_under(self.backing.as_ref(), &id, &version) => {}
                Ok(a) => {
                    self.failed
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .remove(&id);
                    self.assets
                        .write()
                        .unwrap_or_else(|e| e.into_inner())
                        .insert(id.clone(), Arc::new(a));
                    self.versions
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .insert(id.clone(), version);
                    found.loaded.push(id);
                }
                Err(e) => {
                    self.failed
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .insert(id, version);
                    found.skipped.push(e);
                }
            }
        }
        let gone: Vec<String> = self
            .assets
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .keys()
            .filter(|id| !present.contains(id.as_str()))
            .cloned()
            .collect();
        for id in gone {
            self.assets
                .write()
                .unwrap_or_else(|e| e.into_inner())
                .remove(&id);
            self.versions
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .remove(&id);
            found.removed.push(id);
        }
        found
    }

    /// Every asset, by id.
    pub fn list(&self) -> Vec<Arc<StoredAsset>> {
        self.assets
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .values()
            .cloned()
            .collect()
    }
}

/// Default of `chunk_cache_mib`: the chunks of a 60 Mpx DEM coded by the default DEM codec and
/// its overviews (a 1024^2 chunk holds its samples and a byte a cell of residual bounds, about
/// 5.3 MB; the top level's one chunk is built whole, 44 bytes a cell), so that random tiles of
/// a 37 Mpx mosaic decode each chunk once (measured: docs/benchmarks.md), with the server's
/// resident memory under 500 MB.
pub(crate) const DEFAULT_CHUNK_CACHE_MIB: u64 = 384;

/// Whether the file of `id`, read as `version`, changed while it was read.
fn changed_under(backing: &dyn Backing, id: &str, version: &str) -> bool {
    backing.current(id).is_some_and(|now| now != version)
}

/// The file of `id` at `version` in `backing`, under `limits`: a chunked one by its header (its
/// chunks read by range into `chunks` when needed), any other whole. The error names the file.
fn load_from(
    backing: &dyn Backing,
    id: &str,
    version: &str,
    limits: &AssetLimits,
    chunks: &ChunkCache,
) -> Result<StoredAsset, String> {
    let what = |e: &dyn std::fmt::Display| format!("{}: {e}", backing.locate(id));
    let source = backing.open(id, version).map_err(|e| what(&e))?;
    let head = source
        .read(0, source.len().min(12) as usize)
        .map_err(|e| what(&e))?;
    if !fractile_codec::chunked::is_chunked(&head) {
        // Before reading it whole (see `check_whole_file`).
        fractile_codec::asset::check_whole_file(&head, source.len(), limits)
            .map_err(|e| what(&e))?;
        let bytes = source
            .read(0, source.len() as usize)
            .map_err(|e| what(&e))?;
        return load(id, &bytes, limits, chunks).map_err(|e| what(&e));
    }
    let size = source.len();
    let asset = Asset::open_chunked(source, limits, chunks.clone()).map_err(|e| what(&e))?;
    let crc = asset.chunked().map_or(0, |c| c.header_crc);
    Ok(stored(id, asset, size, crc))
}

/// Parses an asset file's bytes into a stored asset, under `limits`, a chunked one's chunks
/// decoded into `chunks`.
pub(crate) fn load(
    id: &str,
    bytes: &[u8],
    limits: &AssetLimits,
    chunks: &ChunkCache,
) -> Result<StoredAsset, fractile_codec::Error> {
    let asset = if fractile_codec::chunked::is_chunked(bytes) {
        let source = fractile_codec::chunked::InMemory(bytes.into());
        Asset::open_chunked(Box::new(source), limits, chunks.clone())?
    } else {
        Asset::from_bytes_limited(bytes, limits)?
    };
    // A chunked file's header checksum covers its table, which holds every chunk's.
    let hash = asset
        .chunked()
        .map_or_else(|| crc32(bytes), |c| c.header_crc);
    Ok(stored(id, asset, bytes.len() as u64, hash))
}

/// A stored asset with what the server derives from it once.
fn stored(id: &str, asset: Asset, bytes: u64, hash: u32) -> StoredAsset {
    let placement = asset.meta.georef.as_ref().and_then(|g| {
        match Placement::of(g, asset.meta.width, asset.meta.height) {
            Ok(p) => Some(p),
            Err(e) => {
                // Served still, over the unit square: better than refusing the asset.
                tracing::warn!("asset {id}: {e}; its tiles cover the unit square instead");
                None
            }
        }
    });
    StoredAsset {
        id: id.to_string(),
        asset,
        bytes,
        hash,
        placement,
    }
}

fn crc32(bytes: &[u8]) -> u32 {
    // The asset file ends with its own CRC-32 of everything before it: reuse it.
    bytes
        .len()
        .checked_sub(4)
        .map(|_| {
            bytes
                .last_chunk::<4>()
                .map_or(0, |b| u32::from_le_bytes(*b))
        })
        .unwrap_or(0)
}
