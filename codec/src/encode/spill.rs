//! Where chunk files wait while the others are coded ([`Spill`]): memory, or an unnamed
//! temporary file beside the output.

use std::io::Write;
use std::path::Path;

use crate::Error;
use crate::io::asset::write_atomic_with;

/// Where chunk files wait while the others are coded: memory for a file built in memory, an
/// unnamed temporary file (and its length) for one written to disk.
pub(super) enum Spill {
    Memory(Vec<u8>),
    File(std::fs::File, u64),
}

impl Spill {
    /// An unnamed temporary file in `output`'s folder (the same file system, and nothing
    /// left behind if the process is killed).
    pub(super) fn beside(output: &Path) -> Result<Spill, Error> {
        let dir = output
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let file = tempfile::tempfile_in(dir).map_err(|e| {
            Error::output(format!("{}: {e}", output.display()))
                .at(output)
                .caused_by(e)
        })?;
        Ok(Spill::File(file, 0))
    }

    /// Appends a chunk's file; returns where it starts.
    pub(super) fn push(&mut self, file: &[u8]) -> std::io::Result<u64> {
        match self {
            Spill::Memory(v) => {
                v.extend_from_slice(file);
                Ok((v.len() - file.len()) as u64)
            }
            Spill::File(f, len) => {
                f.write_all(file)?;
                *len += file.len() as u64;
                Ok(*len - file.len() as u64)
            }
        }
    }

    /// Copies `len` bytes from `at` to `out`.
    pub(super) fn copy(&self, at: u64, len: u64, out: &mut dyn Write) -> std::io::Result<()> {
        match self {
            Spill::Memory(v) => out.write_all(&v[at as usize..(at + len) as usize]),
            Spill::File(f, _) => {
                let mut buf = vec![0u8; len as usize];
                crate::io::layout::read_exact_at(f, &mut buf, at)?;
                out.write_all(&buf)
            }
        }
    }
}

/// Writes `head` then the spilled files at `order` (start, length) to `output`, atomically;
/// returns the file's length.
pub(super) fn write_spilled(
    output: &Path,
    head: &[u8],
    order: impl Iterator<Item = (u64, u64)> + Clone,
    spill: &Spill,
) -> Result<u64, Error> {
    let mut length = 0;
    write_atomic_with(output, &mut |f| {
        let mut f = std::io::BufWriter::new(f);
        f.write_all(head)?;
        length = head.len() as u64;
        for (at, len) in order.clone() {
            spill.copy(at, len, &mut f)?;
            length += len;
        }
        f.flush()
    })?;
    Ok(length)
}
