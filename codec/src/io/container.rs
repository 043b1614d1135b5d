//! The frame of an asset file (layout in `io::asset`, spec in docs/asset-format.md): its
//! versions, what a reader lets a file cost ([`AssetLimits`]), the magic and what a file is
//! when it has none, and the frame read and written around a codec's payload. No codec here:
//! the payload is bytes.

use fractile_proto::{AssetKind, AssetMeta};

pub use super::frame::FORMAT_VERSION;
use super::frame::{MAGIC, SHARED_SINCE_VERSION, kind_byte};

use crate::Error;
use crate::codecs::registry::Codec;

/// The last version of files that are not chunked before [`FORMAT_VERSION`] (6 to 8 name
/// chunked containers only).
pub(crate) const LAST_UNCHUNKED_VERSION: u16 = 5;
/// The oldest format version this build reads (codecs 1-4 only).
pub const OLDEST_READ_VERSION: u16 = 1;
/// The oldest format version of curve assets this build reads.
pub const OLDEST_CURVE_VERSION: u16 = 3;

/// What a reader lets one asset file cost before it allocates anything: sizes the file claims
/// are checked against these (and against what its bytes can hold) first, so that a small
/// hostile file cannot make a reader allocate gigabytes or decode for minutes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AssetLimits {
    /// Most samples of the source grid (width x height; voxels of a volume; vertices of curves).
    pub max_pixels: u64,
    /// Most bytes that decoding the asset may take: its operators and mask, resident while it
    /// is served, plus one full-resolution discrete decode (what `fractile decode` and a
    /// server's coarse tiles run), estimated from the headers before anything is decoded.
    pub max_decode_bytes: u64,
}

impl Default for AssetLimits {
    /// 2^28 samples (16384 x 16384) and 3 GiB: every asset of the demo and the benches, and a
    /// 16384^2 DEM, fit; anything larger is the chunked assets' job.
    fn default() -> Self {
        AssetLimits {
            max_pixels: 1 << 28,
            max_decode_bytes: 3 << 30,
        }
    }
}

impl AssetLimits {
    /// Checks the grid a file claims.
    pub(crate) fn check_pixels(&self, what: &str, pixels: u64) -> Result<(), Error> {
        if pixels > self.max_pixels {
            return Err(Error::asset(format!(
                "{what} of {pixels} samples is over this reader's limit of {} (max_asset_pixels)",
                self.max_pixels
            )));
        }
        Ok(())
    }

    /// Checks the estimated cost of decoding.
    pub(crate) fn check_cost(&self, bytes: u64) -> Result<(), Error> {
        if bytes > self.max_decode_bytes {
            return Err(Error::asset(format!(
                "decoding it would take about {} MiB, over this reader's limit of {} MiB (max_decode_mib)",
                bytes >> 20,
                self.max_decode_bytes >> 20
            )));
        }
        Ok(())
    }
}

/// Whether a file that is not chunked, `len` bytes starting with `head` (12 bytes, or all of
/// a shorter file), may be read whole under `limits`: one that is no asset, or one larger than
/// any asset that is not chunked can be (its decoded planes, which `max_decode_bytes` bounds,
/// are larger than its bytes), is refused from its length and first bytes, before anything is
/// allocated. Every reader (the server, the CLI, Python) goes through it: a 100 GB sparse file
/// aborted a process that asked for its size in memory, and a 3 GB junk file took 3 GB and 15 s
/// to say "bad magic".
pub fn check_whole_file(head: &[u8], len: u64, limits: &AssetLimits) -> Result<(), Error> {
    check_magic(head)?;
    if len > limits.max_decode_bytes {
        return Err(Error::asset(format!(
            "{len} bytes, over any asset that is not chunked (max_decode_mib {}): chunk it \
             (fractile encode --chunk N)",
            limits.max_decode_bytes >> 20
        )));
    }
    Ok(())
}

/// Whether a file's first bytes (8 or more) are an asset's, before the rest is read: the
/// error says what the file is instead (see [`crate::io::asset::Asset::from_bytes`]).
pub fn check_magic(head: &[u8]) -> Result<(), Error> {
    if head.len() >= 8 && &head[..8] == MAGIC {
        Ok(())
    } else {
        Err(Error::asset(not_an_asset(head)))
    }
}

/// What a file that does not start with an asset's magic is, and what to do with it: rasters
/// and meshes are the encoder's input, and uploading one is a common first mistake.
fn not_an_asset(bytes: &[u8]) -> String {
    let kind = if bytes.starts_with(b"II*\0") || bytes.starts_with(b"MM\0*") {
        Some("a TIFF (GeoTIFF) raster")
    } else if bytes.starts_with(b"\x89PNG") {
        Some("a PNG image")
    } else if bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
        Some("a JPEG image")
    } else if bytes.starts_with(b"OFF") || bytes.starts_with(b"ply") || bytes.starts_with(b"solid")
    {
        Some("a mesh")
    } else {
        None
    };
    match kind {
        Some(k) => format!(
            "not a fractile asset (bad magic): this is {k}; encode it with `fractile encode` first"
        ),
        None => "not a fractile asset (bad magic): assets are what `fractile encode` writes".into(),
    }
}

/// A file's frame, read: codec byte, metadata, payload and source-error map bytes.
pub(crate) type Container<'a> = (u8, AssetMeta, &'a [u8], &'a [u8]);

/// The container's frame: magic, version, checksum, codec, metadata (checked against the
/// kind byte and the size limits of a grid) and the codec's payload.
pub(crate) fn container(bytes: &[u8]) -> Result<Container<'_>, Error> {
    let bad = |m: String| Error::asset(m);
    if bytes.len() < 24 {
        return Err(bad(format!(
            "{} bytes is too short for an asset",
            bytes.len()
        )));
    }
    if &bytes[..8] != MAGIC {
        return Err(bad(not_an_asset(bytes)));
    }
    let version = u16::from_le_bytes([bytes[8], bytes[9]]);
    if !(OLDEST_READ_VERSION..=LAST_UNCHUNKED_VERSION).contains(&version)
        && !(SHARED_SINCE_VERSION..=FORMAT_VERSION).contains(&version)
    {
        return Err(bad(format!(
            "format version {version} is not supported by this build (reads versions {OLDEST_READ_VERSION} to {LAST_UNCHUNKED_VERSION} and {SHARED_SINCE_VERSION} to {FORMAT_VERSION}; 6 to 8 are chunked)"
        )));
    }
    let body = bytes.len() - 4;
    let crc = u32::from_le_bytes(bytes[body..].try_into().expect("4 bytes"));
    if crc32fast::hash(&bytes[..body]) != crc {
        return Err(bad(
            "checksum mismatch: the file is corrupt or truncated".into()
        ));
    }
    let (kind, codec) = (bytes[10], bytes[11]);
    if Codec::from_byte(codec).is_none() {
        let mut known: Vec<Codec> = Codec::ALL.to_vec();
        known.sort_by_key(|c| c.byte());
        let known: Vec<String> = known
            .iter()
            .map(|c| format!("{} {}", c.byte(), c.label()))
            .collect();
        return Err(bad(format!(
            "unknown codec {codec} (this build reads {})",
            known.join(", ")
        )));
    }
    if codec == Codec::Curve.byte() && version < OLDEST_CURVE_VERSION {
        return Err(bad(format!(
            "a curve asset of format version {version} is not read by this build (its curve coding changed in version {OLDEST_CURVE_VERSION}): encode the source again"
        )));
    }
    let read_len = |at: usize| -> Result<usize, Error> {
        let b = bytes
            .get(at..at + 4)
            .ok_or_else(|| bad("truncated length field".into()))?;
        Ok(u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize)
    };
    let m_len = read_len(12)?;
    let meta_bytes = bytes
        .get(16..16 + m_len)
        .ok_or_else(|| bad("truncated metadata".into()))?;
    let p_len = read_len(16 + m_len)?;
    let p_start = 20 + m_len;
    let p_end = p_start
        .checked_add(p_len)
        .filter(|&e| e <= body)
        .ok_or_else(|| bad("payload length does not match the file size".into()))?;
    // Version 5 on: the source-error map after the payload.
    let section = if version >= 5 {
        let s_len = read_len(p_end)?;
        bytes
            .get(p_end + 4..p_end + 4 + s_len)
            .filter(|_| p_end + 4 + s_len == body)
            .ok_or_else(|| bad("source-error map length does not match the file size".into()))?
    } else if p_end == body {
        &[][..]
    } else {
        return Err(bad("payload length does not match the file size".into()));
    };
    let meta: AssetMeta = fractile_proto::decode(meta_bytes).map_err(|e| bad(e.to_string()))?;
    if kind_byte(meta.kind) != kind {
        return Err(bad("kind byte and metadata disagree".into()));
    }
    // Curves count vertices in `width` (one row); grids are at most 2^16 a side.
    let max_width = if meta.kind == AssetKind::Curve {
        1 << 26
    } else {
        1 << 16
    };
    if meta.width == 0 || meta.height == 0 || meta.width > max_width || meta.height > 1 << 16 {
        return Err(bad(format!(
            "bad size {}x{} in the metadata",
            meta.width, meta.height
        )));
    }
    Ok((codec, meta, &bytes[p_start..p_end], section))
}
