//! Where asset files are kept, as the catalog sees it: the calls every backing answers (a
//! folder, a bucket), and the ids they may hold.

use fractile_codec::chunked::ChunkSource;
use fractile_proto::ErrorCode;

use crate::error::AppError;

/// Where the asset files are kept. The catalog ([`super::Store`]) is the same over every backing: it
/// lists, opens by range, and replaces through these calls only, all blocking (call them off
/// the async executor).
pub trait Backing: Send + Sync {
    /// The asset files there now, each with its version (an opaque text that changes when the
    /// file does); an error when the backing cannot be read.
    fn list(&self) -> std::io::Result<Listing>;
    /// The file of `id`, as listed at `version`, read by range.
    fn open(&self, id: &str, version: &str) -> std::io::Result<Box<dyn ChunkSource>>;
    /// Stores `bytes` as the file of `id` so that readers see the old file or the new one
    /// whole, never a mix; returns the new version.
    fn put(&self, id: &str, bytes: &[u8]) -> std::io::Result<String>;
    /// Removes the file of `id`.
    fn delete(&self, id: &str) -> std::io::Result<()>;
    /// Where, for messages.
    fn describe(&self) -> String;
    /// Where the file of `id` is, for messages.
    fn locate(&self, id: &str) -> String;
    /// The version of the file of `id` now, where asking is cheap (a folder's `stat`), to tell
    /// a file that changed while it was read; `None` where versions cannot change under a
    /// reader (a bucket's objects are written whole).
    fn current(&self, _id: &str) -> Option<String> {
        None
    }
}

/// What a [`Backing`] holds.
#[derive(Debug, Default)]
pub struct Listing {
    /// `(id, version)` of each asset file, by id.
    pub files: Vec<(String, String)>,
    /// Entries that are not served, one message each (a symbolic link, a bad id).
    pub skipped: Vec<String>,
}

/// Checks an asset id: 1-64 characters of letters, digits, `-` and `_`, not starting with `-`
/// or `_` (so no paths, no `..`, no hidden files).
pub(crate) fn validate_id(id: &str) -> Result<(), AppError> {
    if fractile_proto::valid_asset_id(id) {
        Ok(())
    } else {
        Err(AppError::bad_request(
            ErrorCode::BadId,
            format!("asset id {id:?} must be 1-64 letters, digits, '-' or '_'"),
        ))
    }
}
