//! A volume's 3D Tiles fetched to a folder for offline use: `tileset.json`, every subtree a
//! viewer can reach and every tile content they list, under the same relative paths, so that
//! the folder served by any static file server (or opened from disk by a viewer that reads
//! files) is the same tileset. The client reads the subtrees' availability (a wire format,
//! `fractile_proto::subtree`); it decodes nothing.

use std::path::Path;

use fractile_proto::subtree::{Subtree, descendant};

use crate::{Client, ClientError};

/// What a fetch wrote.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Fetched {
    /// Subtree files.
    pub subtrees: usize,
    /// Tile contents (GLB).
    pub contents: usize,
    /// Bytes of every file written, `tileset.json` included.
    pub bytes: u64,
}

impl Client {
    /// `GET /v1/assets/{id}/tileset.json` and everything it reaches, written under `dir`
    /// (created if need be) at the paths the tileset names.
    pub async fn fetch_tileset(&self, id: &str, dir: &Path) -> Result<Fetched, ClientError> {
        let base = self.asset_path(id, "")?;
        let mut fetched = Fetched::default();
        let write = |rel: &str, bytes: &[u8], fetched: &mut Fetched| {
            let path = dir.join(rel);
            let made = path
                .parent()
                .map_or(Ok(()), std::fs::create_dir_all)
                .and_then(|()| std::fs::write(&path, bytes));
            fetched.bytes += bytes.len() as u64;
            made.map_err(|source| ClientError::Write {
                path: path.display().to_string(),
                source,
            })
        };
        let raw = self.get_bytes(&format!("{base}/tileset.json")).await?;
        let tileset: serde_json::Value = serde_json::from_slice(&raw)
            .map_err(|e| ClientError::malformed("tileset.json", e.to_string()))?;
        write("tileset.json", &raw, &mut fetched)?;
        let implicit = &tileset["root"]["implicitTiling"];
        let number = |v: &serde_json::Value| v.as_u64().map(|n| n as u32);
        let (Some(per), Some(levels)) = (
            number(&implicit["subtreeLevels"]),
            number(&implicit["availableLevels"]),
        ) else {
            return Err(ClientError::malformed(
                "tileset.json",
                "no implicit tiling's subtreeLevels and availableLevels",
            ));
        };
        let mut pending = vec![(0u32, [0u32; 3])];
        while let Some((level, at)) = pending.pop() {
            let rel = format!(
                "3dtiles/subtrees/{level}/{}/{}/{}.subtree",
                at[0], at[1], at[2]
            );
            let raw = self.get_bytes(&format!("{base}/{rel}")).await?;
            let s = Subtree::from_bytes(&raw, per)
                .map_err(|e| ClientError::malformed(rel.clone(), e.to_string()))?;
            write(&rel, &raw, &mut fetched)?;
            fetched.subtrees += 1;
            let mut i = 0;
            for r in 0..per {
                for k in 0..1usize << (3 * r) {
                    if s.content[i] && level + r < levels {
                        let t = descendant(at, r, k as u64);
                        let rel = format!("3dtiles/{}/{}/{}/{}.glb", level + r, t[0], t[1], t[2]);
                        let glb = self.get_bytes(&format!("{base}/{rel}")).await?;
                        write(&rel, &glb, &mut fetched)?;
                        fetched.contents += 1;
                    }
                    i += 1;
                }
            }
            if level + per < levels {
                for (k, _) in s.children.iter().enumerate().filter(|(_, c)| **c) {
                    pending.push((level + per, descendant(at, per, k as u64)));
                }
            }
        }
        Ok(fetched)
    }
}
