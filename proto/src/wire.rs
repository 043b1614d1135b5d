//! The one binary serializer of the project.
//!
//! bincode is pinned to 2.0.x: 3.0.0 on crates.io is an empty release and the project is
//! unmaintained (RUSTSEC-2025-0141). Nothing outside this file names bincode, so replacing it
//! (postcard, a hand-written format) changes only these two functions.

use serde::Serialize;
use serde::de::DeserializeOwned;

/// A value could not be decoded from bytes.
#[derive(Debug, thiserror::Error)]
#[error("malformed {what}: {reason}")]
pub struct WireError {
    /// What was being decoded (a type name).
    pub what: &'static str,
    /// The serializer's own explanation.
    pub reason: String,
}

fn config() -> impl bincode::config::Config {
    // Fixed-width little-endian integers keep the format easy to describe in the spec; a limit
    // stops a corrupt length prefix from allocating gigabytes.
    bincode::config::standard()
        .with_little_endian()
        .with_fixed_int_encoding()
        .with_limit::<{ 256 * 1024 * 1024 }>()
}

/// Encodes a value to bytes.
pub fn encode<T: Serialize>(value: &T) -> Vec<u8> {
    // Serializing plain data structs into a Vec cannot fail.
    bincode::serde::encode_to_vec(value, config()).expect("serializing plain data never fails")
}

/// Decodes a value from bytes; trailing bytes are an error.
pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, WireError> {
    let what = std::any::type_name::<T>()
        .rsplit("::")
        .next()
        .unwrap_or("value");
    let (value, used) =
        bincode::serde::decode_from_slice(bytes, config()).map_err(|e| WireError {
            what,
            reason: e.to_string(),
        })?;
    if used != bytes.len() {
        return Err(WireError {
            what,
            reason: format!("{} trailing bytes", bytes.len() - used),
        });
    }
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::asset::*;

    #[test]
    fn metadata_round_trips_and_rejects_truncation() {
        let meta = AssetMeta {
            kind: AssetKind::HeightField,
            width: 344,
            height: 403,
            channels: 1,
            colour: ColourModel::Grey,
            sample: SampleFormat::I16,
            units: Some("m".into()),
            value_min: -12.5,
            value_max: 1890.0,
            nodata: Some(-32768.0),
            georef: Some(Georef {
                epsg: Some(4326),
                origin: [-84.5, 36.6],
                pixel_size: [1.0 / 1200.0, -1.0 / 1200.0],
            }),
            encoder: "tolerance=2".into(),
            stats: EncodeStats::default(),
        };
        let bytes = encode(&meta);
        let back: AssetMeta = decode(&bytes).unwrap();
        assert_eq!(back, meta);
        let err = decode::<AssetMeta>(&bytes[..bytes.len() - 3]).unwrap_err();
        assert!(err.to_string().contains("AssetMeta"), "{err}");
        let mut long = bytes.clone();
        long.push(0);
        assert!(decode::<AssetMeta>(&long).is_err());
    }
}
