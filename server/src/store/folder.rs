//! The default backing: a folder of `{id}.fra` files on a local or shared volume. A file is
//! replaced by a temporary file of its own and a rename, so a reader holds the old file or the
//! new one, never a mix; its version is its length, modification time and inode (an atomic
//! replace is a new inode), read without opening it.

use std::path::{Path, PathBuf};

use fractile_codec::chunked::{ChunkSource, FileSource};

use super::backing::{Backing, Listing, validate_id};

/// A folder of asset files.
pub(crate) struct Folder {
    dir: PathBuf,
}

impl Folder {
    /// The folder `dir`; temporary files left there by an interrupted write whose writer is
    /// gone are removed (see `stale_temporary`).
    pub(crate) fn open(dir: &Path) -> std::io::Result<Folder> {
        for e in std::fs::read_dir(dir)? {
            let Ok(e) = e else { continue };
            let path = e.path();
            if let Some(tmp) = stale_temporary(&path) {
                match std::fs::remove_file(&path) {
                    Ok(()) => tracing::info!("removed {tmp}, left by an interrupted write"),
                    Err(err) => tracing::warn!("could not remove {tmp}: {err}"),
                }
            }
        }
        Ok(Folder {
            dir: dir.to_path_buf(),
        })
    }

    fn path(&self, id: &str) -> PathBuf {
        self.dir.join(format!("{id}.fra"))
    }
}

/// A file's version: what tells that it changed without reading it.
fn stamp(path: &Path) -> Option<String> {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::symlink_metadata(path).ok()?;
    let modified = m
        .modified()
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos());
    Some(format!("{}:{modified}:{}", m.len(), m.ino()))
}

impl Backing for Folder {
    fn list(&self) -> std::io::Result<Listing> {
        let mut listing = Listing::default();
        for e in std::fs::read_dir(&self.dir)? {
            let Ok(e) = e else { continue };
            // `file_type` does not follow links.
            let Ok(kind) = e.file_type() else { continue };
            let path = e.path();
            if path.extension().and_then(|e| e.to_str()) != Some("fra") {
                continue;
            }
            if kind.is_symlink() {
                listing.skipped.push(format!(
                    "{}: a symbolic link (only the folder's own files are served)",
                    path.display()
                ));
                continue;
            }
            let Some(id) = path.file_stem().and_then(|s| s.to_str()) else {
                continue;
            };
            if !kind.is_file() {
                continue;
            }
            if validate_id(id).is_err() {
                listing
                    .skipped
                    .push(format!("{}: not a valid asset id", path.display()));
                continue;
            }
            if let Some(version) = stamp(&path) {
                listing.files.push((id.to_string(), version));
            }
        }
        listing.files.sort();
        Ok(listing)
    }

    fn open(&self, id: &str, _version: &str) -> std::io::Result<Box<dyn ChunkSource>> {
        Ok(Box::new(FileSource::open(&self.path(id))?))
    }

    fn put(&self, id: &str, bytes: &[u8]) -> std::io::Result<String> {
        let path = self.path(id);
        fractile_codec::asset::write_atomic(&path, bytes).map_err(std::io::Error::other)?;
        stamp(&path).ok_or_else(|| std::io::Error::other("the file stored is gone"))
    }

    fn delete(&self, id: &str) -> std::io::Result<()> {
        std::fs::remove_file(self.path(id))
    }

    fn describe(&self) -> String {
        self.dir.display().to_string()
    }

    fn current(&self, id: &str) -> Option<String> {
        stamp(&self.path(id))
    }

    fn locate(&self, id: &str) -> String {
        self.path(id).display().to_string()
    }
}

/// Whether `path` is a temporary file of [`fractile_codec::asset::write_atomic`] that no
/// running writer owns (its process is gone, or it is over an hour old): its name, if so.
fn stale_temporary(path: &Path) -> Option<String> {
    let name = path.file_name()?.to_str()?;
    let owner = fractile_codec::asset::temporary_owner(name)?;
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
