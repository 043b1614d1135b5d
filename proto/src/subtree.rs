//! The subtree file of 3D Tiles 1.1 implicit tiling (`.subtree`), written by the server and
//! read by the client: which tiles of a subtree exist, which hold content, which child
//! subtrees exist. Hand-written: no maintained Rust crate reads or writes 3D Tiles subtrees,
//! and the format is a 24-byte header, a JSON chunk and bitstreams.

/// A subtree's availability. Tiles are in level order, then Morton order within a level
/// (`x` in bit 0 of each triple, `y` in bit 1, `z` in bit 2); an octree's subtree of `L`
/// levels has `(8^L - 1) / 7` tiles and `8^L` child subtrees.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Subtree {
    /// Tiles that exist.
    pub tiles: Vec<bool>,
    /// Tiles with content, in the same order.
    pub content: Vec<bool>,
    /// Child subtrees that exist (the tiles one level under the subtree's last), by Morton
    /// index; empty for none.
    pub children: Vec<bool>,
}

/// The tile `k` (a Morton index: `x` in bit 0 of each triple, `y` in bit 1, `z` in bit 2)
/// `depth` levels under the tile at `(x, y, z)`: where the subtree's bits point.
pub fn descendant([x, y, z]: [u32; 3], depth: u32, k: u64) -> [u32; 3] {
    let axis = |a: u32| (0..depth).fold(0u32, |v, b| v | (((k >> (3 * b + a)) & 1) as u32) << b);
    [
        (x << depth) | axis(0),
        (y << depth) | axis(1),
        (z << depth) | axis(2),
    ]
}

/// The most levels a subtree read here may have.
pub const MAX_LEVELS: u32 = 6;

/// Why a subtree file does not read.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SubtreeError(pub String);

impl std::fmt::Display for SubtreeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "subtree file: {}", self.0)
    }
}

impl std::error::Error for SubtreeError {}

impl Subtree {
    /// The subtree file: the header (`subt`, version 1, the two chunks' lengths), the JSON of
    /// its availability and one buffer of bitstreams (least significant bit first, each view
    /// on 8 bytes); a set that is all of one value is a constant, as the format prefers.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut bin: Vec<u8> = Vec::new();
        let mut views = Vec::new();
        let mut availability = |bits: &[bool]| -> serde_json::Value {
            let count = bits.iter().filter(|&&b| b).count();
            if count == 0 || count == bits.len() {
                return serde_json::json!({"constant": u8::from(count > 0)});
            }
            let offset = bin.len();
            let mut bytes = vec![0u8; bits.len().div_ceil(8)];
            for (i, _) in bits.iter().enumerate().filter(|(_, b)| **b) {
                bytes[i / 8] |= 1 << (i % 8);
            }
            bin.extend_from_slice(&bytes);
            views.push(
                serde_json::json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()}),
            );
            bin.resize(bin.len().div_ceil(8) * 8, 0);
            serde_json::json!({"bitstream": views.len() - 1, "availableCount": count})
        };
        let tiles = availability(&self.tiles);
        let content = availability(&self.content);
        let children = match self.children.is_empty() {
            true => serde_json::json!({"constant": 0}),
            false => availability(&self.children),
        };
        let mut json = serde_json::json!({
            "tileAvailability": tiles,
            "contentAvailability": [content],
            "childSubtreeAvailability": children,
        });
        if !bin.is_empty() {
            json["buffers"] = serde_json::json!([{"byteLength": bin.len()}]);
            json["bufferViews"] = serde_json::json!(views);
        }
        let mut text = json.to_string().into_bytes();
        text.resize(text.len().div_ceil(8) * 8, b' ');
        let mut out = Vec::with_capacity(24 + text.len() + bin.len());
        out.extend_from_slice(b"subt");
        out.extend_from_slice(&1u32.to_le_bytes());
        out.extend_from_slice(&(text.len() as u64).to_le_bytes());
        out.extend_from_slice(&(bin.len() as u64).to_le_bytes());
        out.extend_from_slice(&text);
        out.extend_from_slice(&bin);
        out
    }

    /// Reads an octree's subtree file of `levels` levels (the tileset's `subtreeLevels`), its
    /// bitstreams in this file's own buffer; a constant set reads as that many of its value.
    pub fn from_bytes(raw: &[u8], levels: u32) -> Result<Subtree, SubtreeError> {
        let err = |m: &str| SubtreeError(m.to_string());
        if raw.len() < 24 || &raw[..4] != b"subt" {
            return Err(err("no 'subt' header"));
        }
        if raw[4..8] != 1u32.to_le_bytes() {
            return Err(err("version is not 1"));
        }
        let len = |r: &[u8]| u64::from_le_bytes(r.try_into().expect("8 bytes")) as usize;
        let (json_len, bin_len) = (len(&raw[8..16]), len(&raw[16..24]));
        let Some(json) = raw.get(24..24usize.saturating_add(json_len)) else {
            return Err(err("shorter than its JSON chunk"));
        };
        let bin = &raw[24 + json_len..];
        if bin.len() < bin_len {
            return Err(err("shorter than its binary chunk"));
        }
        let json: serde_json::Value =
            serde_json::from_slice(json).map_err(|e| SubtreeError(e.to_string()))?;
        let bits = |av: &serde_json::Value, n: usize| -> Result<Vec<bool>, SubtreeError> {
            if let Some(c) = av.get("constant") {
                return Ok(vec![c.as_u64() == Some(1); n]);
            }
            let view = av["bitstream"]
                .as_u64()
                .and_then(|v| json["bufferViews"].get(v as usize))
                .ok_or_else(|| err("a bitstream names no buffer view"))?;
            let offset = view["byteOffset"].as_u64().unwrap_or(0) as usize;
            let bytes = bin
                .get(offset..offset + n.div_ceil(8))
                .ok_or_else(|| err("a bitstream runs past the buffer"))?;
            Ok((0..n).map(|i| bytes[i / 8] >> (i % 8) & 1 == 1).collect())
        };
        // 8^levels child bits are allocated: refused past what any tileset here names (6:
        // 262,144 bits) before anything is.
        if !(1..=MAX_LEVELS).contains(&levels) {
            return Err(SubtreeError(format!(
                "{levels} levels a subtree: 1 to {MAX_LEVELS} are read"
            )));
        }
        let tiles = ((1usize << (3 * levels)) - 1) / 7;
        Ok(Subtree {
            tiles: bits(&json["tileAvailability"], tiles)?,
            content: bits(&json["contentAvailability"][0], tiles)?,
            children: bits(&json["childSubtreeAvailability"], 1 << (3 * levels))?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_subtree_reads_back_as_written_with_constants_and_bitstreams() {
        // Two levels: 9 tiles, 64 child subtrees. Mixed sets are bitstreams, full and empty
        // ones constants.
        let tiles = vec![true, true, false, true, false, false, false, false, true];
        let content = vec![false, true, false, true, false, false, false, false, false];
        let children: Vec<bool> = (0..64).map(|k| k % 7 == 3).collect();
        let s = Subtree {
            tiles,
            content,
            children,
        };
        let raw = s.to_bytes();
        assert_eq!(&raw[..4], b"subt");
        // The JSON chunk is padded to 8 bytes, and so the binary chunk starts on 8.
        assert_eq!(u64::from_le_bytes(raw[8..16].try_into().unwrap()) % 8, 0);
        assert_eq!(Subtree::from_bytes(&raw, 2).unwrap(), s);
        let all = Subtree {
            tiles: vec![true; 9],
            content: vec![false; 9],
            children: vec![false; 64],
        };
        let raw = all.to_bytes();
        assert!(String::from_utf8_lossy(&raw).contains(r#""constant":1"#));
        assert_eq!(Subtree::from_bytes(&raw, 2).unwrap(), all);
        // Morton order: k = 0b110_001 two levels down is x = 1 (bit 0), y = 2 (bit 4), z = 2
        // (bit 5), under (1, 0, 0): x = 1 * 4 + 1.
        assert_eq!(descendant([1, 0, 0], 2, 0b110_001), [5, 2, 2]);
        // Truncated or foreign files are errors, not panics.
        for bad in [&raw[..10], &raw[..30], b"glTF\x02\0\0\0".as_slice()] {
            assert!(Subtree::from_bytes(bad, 2).is_err());
        }
        assert!(Subtree::from_bytes(&raw, 7).is_err() && Subtree::from_bytes(&raw, 0).is_err());
    }
}
