//! The frame of every asset file, below the codecs that fill it: the magic, the version this
//! build writes, the kind byte, and the frame written around a codec's payload and its
//! source-error map. A codec's encoder sizes its files with it (rate control); reading a frame
//! back, which names the codecs, is `io::container`.

use fractile_proto::{AssetKind, AssetMeta};

/// The format version this build writes. Versions 2 to 4 changed only the curve payload
/// (codec 5; version 3: hexagonal lattice for details, shared coarse contexts, an `f32`
/// tolerance and one stored bound, no length fields; version 4: a ring may carry its
/// antimeridian crossings and start vertex, which a version-3 reader would misread as levels);
/// the other payloads are the same in all four, so version-1 to -3 files of codecs 1-4 are
/// still read, version-3 curve assets too (they hold neither), and an older curve asset is
/// refused by name (re-encode its GeoJSON). Versions 6 to 8 are chunked containers only
/// (`io::layout`); version 9, one number for both containers, codes the projected pyramid's
/// details with two-rate contexts (`pyramid::Order::SeparableTwoRate`), which a reader of
/// version 5 would take for a corrupt header: the version tells it the file is newer. Version
/// 10 codes the projected codec's lifted coefficients with two-rate contexts and their signs in
/// context (`pyramid::Order::Lifted97TwoRate`, `lifting::Code::Contextual`), which a reader of
/// 9 would refuse as an unknown multiresolution; 9 is still read.
pub const FORMAT_VERSION: u16 = 10;

/// The first version that numbers both containers (the one before is 5 for files that are not
/// chunked, 8 for chunked ones).
pub(crate) const SHARED_SINCE_VERSION: u16 = 9;

/// File magic.
pub const MAGIC: &[u8; 8] = b"FRACTILE";

/// The byte of an asset kind in a file's header.
pub(crate) fn kind_byte(k: AssetKind) -> u8 {
    match k {
        AssetKind::Image => 0,
        AssetKind::HeightField => 1,
        AssetKind::Volume => 2,
        AssetKind::Curve => 3,
    }
}

/// The file of a payload: the frame around it, the CRC after.
pub(crate) fn assemble(meta: &AssetMeta, codec: u8, payload: &[u8], section: &[u8]) -> Vec<u8> {
    let meta_bytes = fractile_proto::encode(meta);
    let mut out = Vec::with_capacity(28 + meta_bytes.len() + payload.len() + section.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.push(kind_byte(meta.kind));
    out.push(codec);
    out.extend_from_slice(&(meta_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(&meta_bytes);
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(payload);
    out.extend_from_slice(&(section.len() as u32).to_le_bytes());
    out.extend_from_slice(section);
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}
