//! Files written atomically: a temporary file in the same folder, synced, renamed over the
//! target; temporary files named so that a reader of the folder knows whose they are.

use std::io::Write;
use std::path::Path;

use crate::Error;

/// What names a temporary file of [`write_atomic`]: `.{name}.tmp-{pid}-{n}`.
const TEMPORARY: &str = ".tmp-";

/// The process that writes the temporary file named `name`, if `name` is one of
/// [`write_atomic`]'s (so that a reader of the folder can remove those a crash left behind).
pub fn temporary_owner(name: &str) -> Option<u32> {
    let rest = name.strip_prefix('.')?;
    let (_, tail) = rest.rsplit_once(TEMPORARY)?;
    let (pid, n) = tail.split_once('-')?;
    n.parse::<u64>().ok()?;
    pid.parse().ok()
}

/// Writes bytes to `path` atomically (temporary file in the same directory, fsync, rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), Error> {
    write_atomic_with(path, &mut |f| f.write_all(bytes))
}

/// Writes to `path` atomically what `write` writes into the temporary file (a file too large
/// to hold in memory is written in parts): the temporary file is synced, then renamed over
/// `path`, or removed if `write` fails.
pub fn write_atomic_with(
    path: &Path,
    write: &mut dyn FnMut(&mut std::fs::File) -> std::io::Result<()>,
) -> Result<(), Error> {
    let err = |e: std::io::Error| {
        Error::output(format!("{}: {e}", path.display()))
            .at(path)
            .caused_by(e)
    };
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .ok_or_else(|| Error::output(format!("{}: not a file path", path.display())))?;
    // A name of its own per write (process and a counter): concurrent writers of one path
    // each rename a whole file, and never write into another's.
    static WRITES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = WRITES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = dir.join(format!(
        ".{}{TEMPORARY}{}-{n}",
        name.to_string_lossy(),
        std::process::id()
    ));
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        write(&mut f)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.map_err(err)
}
