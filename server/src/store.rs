//! The assets the server holds: loaded from a directory at start (a broken file is reported and
//! skipped, the rest serve), or the built-in demo assets, encoded from small real files shipped
//! in the binary at first start and cached on disk afterwards.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};

use fractile_codec::geo::Placement;
use fractile_codec::io::chunked::ChunkCache;
use fractile_codec::{Asset, AssetLimits, Raster};

use crate::error::AppError;

mod demo;
pub use demo::ensure_demo_assets;

/// An asset with what the server derives from it once.
pub struct StoredAsset {
    /// Its id (file stem).
    pub id: String,
    /// The decoded asset.
    pub asset: Asset,
    /// File size in bytes.
    pub bytes: u64,
    /// Checksum of the file, part of every ETag.
    pub hash: u32,
    /// Where it lies on the Earth (geographic georeference), if it does.
    pub placement: Option<Placement>,
}

/// The asset catalog, backed by a directory of `{id}.fra` files.
pub struct Store {
    dir: PathBuf,
    assets: RwLock<BTreeMap<String, Arc<StoredAsset>>>,
    /// What one asset may claim and cost (checked on load and on upload).
    limits: AssetLimits,
    /// Decoded chunks of the chunked assets (`chunk_cache_mib`), shared by all of them.
    chunks: ChunkCache,
    /// Held while a file is replaced and the catalog updated, so that concurrent writers of
    /// an id serialise and the file on disk is always the version served.
    writes: std::sync::Mutex<()>,
    /// Each served file's stamp when it was loaded, for [`Store::refresh`].
    stamps: std::sync::Mutex<BTreeMap<String, FileStamp>>,
}

/// What tells that a file changed without reading it: its length, modification time and
/// inode (an atomic replace is a new inode).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct FileStamp {
    len: u64,
    modified: Option<std::time::SystemTime>,
    ino: u64,
}

impl FileStamp {
    fn of(path: &Path) -> Option<FileStamp> {
        use std::os::unix::fs::MetadataExt;
        let m = std::fs::symlink_metadata(path).ok()?;
        Some(FileStamp {
            len: m.len(),
            modified: m.modified().ok(),
            ino: m.ino(),
        })
    }
}

/// What [`Store::refresh`] found changed in the folder.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Refreshed {
    /// Ids of files new to the catalog, or replaced, and loaded.
    pub loaded: Vec<String>,
    /// Ids whose file is gone, dropped from the catalog.
    pub removed: Vec<String>,
    /// Files that changed but do not load (the version served before stays): one message each.
    pub skipped: Vec<String>,
}

/// Checks an asset id: 1-64 characters of letters, digits, `-` and `_`, not starting with `-`
/// or `_` (so no paths, no `..`, no hidden files).
pub fn validate_id(id: &str) -> Result<(), AppError> {
    if fractile_proto::valid_asset_id(id) {
        Ok(())
    } else {
        Err(AppError::bad_request(
            "bad_id",
            format!("asset id {id:?} must be 1-64 letters, digits, '-' or '_'"),
        ))
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
        let mut assets = BTreeMap::new();
        let mut stamps = BTreeMap::new();
        let mut skipped = Vec::new();
        let mut entries = Vec::new();
        for e in std::fs::read_dir(dir)? {
            let Ok(e) = e else { continue };
            // `file_type` does not follow links.
            let Ok(kind) = e.file_type() else { continue };
            let path = e.path();
            if let Some(tmp) = stale_temporary(&path) {
                match std::fs::remove_file(&path) {
                    Ok(()) => tracing::info!("removed {tmp}, left by an interrupted write"),
                    Err(err) => tracing::warn!("could not remove {tmp}: {err}"),
                }
                continue;
            }
            if path.extension().and_then(|e| e.to_str()) != Some("fra") {
                continue;
            }
            if kind.is_symlink() {
                skipped.push(format!(
                    "{}: a symbolic link (only the folder's own files are served)",
                    path.display()
                ));
                continue;
            }
            if kind.is_file() {
                entries.push(path);
            }
        }
        entries.sort();
        for path in entries {
            let Some(id) = path
                .file_stem()
                .and_then(|s| s.to_str())
                .map(str::to_string)
            else {
                continue;
            };
            if validate_id(&id).is_err() {
                skipped.push(format!("{}: not a valid asset id", path.display()));
                continue;
            }
            let stamp = FileStamp::of(&path);
            match load_file(&id, &path, &limits, &chunks) {
                Ok(a) => {
                    if let Some(s) = stamp {
                        stamps.insert(id.clone(), s);
                    }
                    assets.insert(id, Arc::new(a));
                }
                Err(e) => skipped.push(format!("{}: {e}", path.display())),
            }
        }
        Ok((
            Store {
                dir: dir.to_path_buf(),
                assets: RwLock::new(assets),
                limits,
                chunks,
                writes: std::sync::Mutex::new(()),
                stamps: std::sync::Mutex::new(stamps),
            },
            skipped,
        ))
    }

    /// Validates an uploaded asset and stores it (atomically: a temporary file of its own,
    /// then a rename), replacing any asset of that id. Writers of one id serialise: the file
    /// and the catalog are updated together, so the last writer's version is both.
    pub fn put(&self, id: &str, bytes: &[u8]) -> Result<Arc<StoredAsset>, AppError> {
        validate_id(id)?;
        let stored =
            Arc::new(
                load(id, bytes, &self.limits, &self.chunks).map_err(|e| AppError {
                    status: axum::http::StatusCode::UNPROCESSABLE_ENTITY,
                    code: "bad_asset",
                    detail: e.to_string(),
                })?,
            );
        let _write = self.writes.lock().unwrap_or_else(|e| e.into_inner());
        fractile_codec::io::asset::write_atomic(&self.dir.join(format!("{id}.fra")), bytes)
            .map_err(|e| {
                // The path and the OS error go to the log, not to the client.
                tracing::error!("storing asset {id}: {e}");
                AppError::internal("the asset could not be stored")
            })?;
        self.assets
            .write()
            .expect("store lock")
            .insert(id.to_string(), stored.clone());
        if let Some(s) = FileStamp::of(&self.dir.join(format!("{id}.fra"))) {
            self.stamps
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .insert(id.to_string(), s);
        }
        Ok(stored)
    }

    /// Removes an asset and its file.
    pub fn delete(&self, id: &str) -> Result<(), AppError> {
        validate_id(id)?;
        let _write = self.writes.lock().unwrap_or_else(|e| e.into_inner());
        let removed = self.assets.write().expect("store lock").remove(id);
        if removed.is_none() {
            return Err(AppError::not_found(
                "unknown_asset",
                format!("no asset {id:?}"),
            ));
        }
        std::fs::remove_file(self.dir.join(format!("{id}.fra"))).map_err(|e| {
            tracing::error!("deleting asset {id}: {e}");
            AppError::internal("the asset's file could not be removed")
        })
    }

    /// The asset `id`, or 404.
    pub fn get(&self, id: &str) -> Result<Arc<StoredAsset>, AppError> {
        validate_id(id)?;
        self.assets
            .read()
            .expect("store lock")
            .get(id)
            .cloned()
            .ok_or_else(|| AppError::not_found("unknown_asset", format!("no asset {id:?}")))
    }

    /// Decodes the chunked assets' chunks into the chunk cache on a thread of its own, until
    /// it is 90% full (see `Chunked::prefetch`), and logs what it cached: the first requests
    /// then wait on no chunk. Requests still run meanwhile; a chunk both want is decoded once.
    pub fn prefetch_in_background(&self) {
        let assets: Vec<Arc<StoredAsset>> = self
            .list()
            .into_iter()
            .filter(|a| a.asset.chunks.is_some())
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
                    if let Some(c) = &a.asset.chunks {
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

    /// Brings the catalog up to date with the folder, as another process sharing it (a
    /// replica on one volume) left it: files new or replaced since they were loaded (by
    /// length, modification time or inode) are loaded, ids whose file is gone are dropped. A
    /// changed file that does not load is logged and its previous version kept. Reads only
    /// the folder's listing and the changed files; `serve` runs it every `rescan_seconds`.
    pub fn refresh(&self) -> Refreshed {
        let mut found = Refreshed::default();
        let Ok(dir) = std::fs::read_dir(&self.dir) else {
            return found;
        };
        let mut present = std::collections::BTreeSet::new();
        let mut changed = Vec::new();
        {
            let stamps = self.stamps.lock().unwrap_or_else(|e| e.into_inner());
            for e in dir.flatten() {
                let path = e.path();
                let is_file = e.file_type().is_ok_and(|k| k.is_file());
                let id = path
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .map(str::to_string);
                let (Some(id), true) = (id, is_file) else {
                    continue;
                };
                if path.extension().and_then(|e| e.to_str()) != Some("fra")
                    || validate_id(&id).is_err()
                {
                    continue;
                }
                let stamp = FileStamp::of(&path);
                if stamp.is_some() && stamps.get(&id) != stamp.as_ref() {
                    changed.push((id.clone(), path, stamp));
                }
                present.insert(id);
            }
        }
        // Writers of this process first finish: the file and the catalog move together.
        let _write = self.writes.lock().unwrap_or_else(|e| e.into_inner());
        for (id, path, stamp) in changed {
            match load_file(&id, &path, &self.limits, &self.chunks) {
                Ok(a) => {
                    self.assets
                        .write()
                        .expect("store lock")
                        .insert(id.clone(), Arc::new(a));
                    if let Some(s) = stamp {
                        self.stamps
                            .lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .insert(id.clone(), s);
                    }
                    found.loaded.push(id);
                }
                Err(e) => found.skipped.push(format!("{}: {e}", path.display())),
            }
        }
        let gone: Vec<String> = self
            .assets
            .read()
            .expect("store lock")
            .keys()
            .filter(|id| !present.contains(*id))
            .cloned()
            .collect();
        for id in gone {
            self.assets.write().expect("store lock").remove(&id);
            self.stamps
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
            .expect("store lock")
            .values()
            .cloned()
            .collect()
    }
}

/// Whether `path` is a temporary file of [`fractile_codec::io::asset::write_atomic`] that no
/// running writer owns (its process is gone, or it is over an hour old): its name, if so.
fn stale_temporary(path: &Path) -> Option<String> {
    let name = path.file_name()?.to_str()?;
    let owner = fractile_codec::io::asset::temporary_owner(name)?;
    // Our own pid counts as alive: another store of this process may be writing (a previous
    // process of the same pid left files that the age rule removes).
    let alive = Path::new(&format!("/proc/{owner}")).exists();
    let age = std::fs::symlink_metadata(path)
        .and_then(|m| m.modified())
        .ok()
        .and_then(|t| t.elapsed().ok())
        .unwrap_or_default();
    let old = age > std::time::Duration::from_secs(3600);
    // Where /proc is missing (not Linux), only age tells. A writer whose process is gone is
    // taken at its word only after 5 minutes: replicas sharing the folder have pids of their
    // own namespaces, and another replica's upload in progress must not be removed (an upload
    // of the largest asset takes seconds).
    let procfs = Path::new("/proc/self").exists();
    let orphan = procfs && !alive && age > std::time::Duration::from_secs(300);
    (old || orphan).then(|| name.to_string())
}

/// Default of `chunk_cache_mib`: the chunks of a 60 Mpx DEM coded by the default DEM codec and
/// its overviews (a 1024^2 chunk holds its samples and a byte a cell of residual bounds, about
/// 5.3 MB; the top level's one chunk is built whole, 44 bytes a cell), so that random tiles of
/// a 37 Mpx mosaic decode each chunk once (measured: docs/benchmarks.md), with the server's
/// resident memory under 500 MB.
pub const DEFAULT_CHUNK_CACHE_MIB: u64 = 384;

/// An asset file of the folder, under `limits`: a chunked one by its header (its chunks read
/// by range into `chunks` when needed), any other whole.
fn load_file(
    id: &str,
    path: &Path,
    limits: &AssetLimits,
    chunks: &ChunkCache,
) -> Result<StoredAsset, String> {
    let asset = Asset::open(path, limits, chunks.clone()).map_err(|e| e.to_string())?;
    let Some(c) = asset.chunks.clone() else {
        // Read whole: load again from its bytes for the size and checksum.
        let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
        return load(id, &bytes, limits, chunks).map_err(|e| e.to_string());
    };
    let size = std::fs::metadata(path).map_err(|e| e.to_string())?.len();
    Ok(stored(id, asset, size, c.header_crc))
}

/// Parses an asset file's bytes into a stored asset, under `limits`, a chunked one's chunks
/// decoded into `chunks`.
pub fn load(
    id: &str,
    bytes: &[u8],
    limits: &AssetLimits,
    chunks: &ChunkCache,
) -> Result<StoredAsset, fractile_codec::Error> {
    let asset = if fractile_codec::io::chunked::is_chunked(bytes) {
        let source = fractile_codec::io::chunked::InMemory(bytes.into());
        Asset::open_chunked(Box::new(source), limits, chunks.clone())?
    } else {
        Asset::from_bytes_limited(bytes, limits)?
    };
    // A chunked file's header checksum covers its table, which holds every chunk's.
    let hash = asset
        .chunks
        .as_ref()
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
        .map(|n| u32::from_le_bytes(bytes[n..].try_into().expect("4 bytes")))
        .unwrap_or(0)
}
