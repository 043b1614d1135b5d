//! A chunked encode split over processes or machines (issue 31): `fractile encode --part I/N`
//! codes share I of the chunks ([`Share`]) into a part file, and `fractile assemble` joins
//! the N part files into the asset, the same bytes as one process's encode (chunk files and
//! the file's metadata hold no encode time, and the file's figures are summed in table order).
//!
//! A part file: `FRAPART\0`, a u16 version (1), a u32 length and that many bytes of its
//! header (`PartHeader`, bincode through `fractile_proto`; docs/asset-format.md), the header's CRC-32, then the
//! files of its chunks in the header's order.

use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::Written;
use super::chunked::{
    ChunkRecord, EncodeOne, Progress, Share, Spill, code_streamed, summarise, write_spilled,
};
use crate::Error;
use crate::io::asset::{Asset, write_atomic_with};
use crate::io::chunked;
use crate::io::rows::{Header, Rows};

const MAGIC: &[u8; 8] = b"FRAPART\0";
const VERSION: u16 = 1;

/// Most bytes a part file's header may claim: 2^20 chunk records of a few hundred bytes.
const MAX_HEADER: u32 = 1 << 30;

/// What a part file says of itself.
#[derive(Debug, Serialize, Deserialize)]
struct PartHeader {
    share: Share,
    chunk: u32,
    /// The source raster's header and the settings of its encode, as text: the parts of one
    /// asset must agree on both.
    source: String,
    settings: String,
    width: u32,
    height: u32,
    georef: Option<fractile_proto::Georef>,
    /// The chunks this part coded, in table order; their files follow the header in this order.
    records: Vec<ChunkRecord>,
}

/// What a part encode wrote.
#[derive(Clone, Debug)]
pub struct PartWritten {
    /// Chunks coded into the part (chunks of the share with no valid cell are not counted).
    pub chunks: usize,
    /// The part file's length in bytes.
    pub length: u64,
    /// Wall time in seconds.
    pub seconds: f64,
}

/// Codes the chunks of `share` of the raster `rows` reads (as
/// [`super::chunked::encode_chunked_file`] codes them all) into the part file `output`.
/// `settings` names the encode's settings: [`assemble`] refuses parts whose settings differ.
pub fn encode_chunked_part(
    rows: &mut dyn Rows,
    (chunk, share, settings): (u32, Share, &str),
    encode_one: &EncodeOne<'_>,
    progress: &Progress<'_>,
    output: &Path,
) -> Result<PartWritten, Error> {
    let mut spill = Spill::beside(output)?;
    let coded = code_streamed(rows, (chunk, share), (encode_one, progress), &mut spill)?;
    let header = PartHeader {
        share,
        chunk,
        source: source_text(&coded.header),
        settings: settings.to_string(),
        width: coded.header.width as u32,
        height: coded.header.height as u32,
        georef: coded.header.georef.clone(),
        records: coded.records().cloned().collect(),
    };
    let bytes = fractile_proto::encode(&header);
    let mut head = Vec::with_capacity(bytes.len() + 18);
    head.extend_from_slice(MAGIC);
    head.extend_from_slice(&VERSION.to_le_bytes());
    head.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
    head.extend_from_slice(&bytes);
    head.extend_from_slice(&crc32fast::hash(&bytes).to_le_bytes());
    let length = write_spilled(output, &head, coded.order(), &spill)?;
    Ok(PartWritten {
        chunks: header.records.len(),
        length,
        seconds: coded.start.elapsed().as_secs_f64(),
    })
}

/// The source's header as the parts of one asset must agree on it.
fn source_text(h: &Header) -> String {
    format!("{h:?}")
}

/// A chunk's file in a part: which part, its offset there, its record.
type Placed<'a> = (usize, u64, &'a ChunkRecord);

/// A part file opened: its header, the file, and where its chunk files start.
struct Part {
    path: PathBuf,
    header: PartHeader,
    file: std::fs::File,
    body: u64,
}

fn open_part(path: &Path) -> Result<Part, Error> {
    let bad = |m: String| Error::Input(format!("{}: {m}", path.display()));
    let io = |e: std::io::Error| Error::Input(format!("{}: {e}", path.display()));
    let file = std::fs::File::open(path).map_err(io)?;
    let mut head = [0u8; 14];
    file.read_exact_at(&mut head, 0)
        .map_err(|_| bad("not a part file (too short)".into()))?;
    if &head[..8] != MAGIC {
        return Err(bad(
            "not a part file (made by fractile encode --part I/N)".into()
        ));
    }
    let version = u16::from_le_bytes([head[8], head[9]]);
    if version != VERSION {
        return Err(bad(format!(
            "part file version {version}; this fractile reads version {VERSION}"
        )));
    }
    let n = u32::from_le_bytes(head[10..14].try_into().expect("4"));
    let len = file.metadata().map_err(io)?.len();
    if n > MAX_HEADER || 14 + u64::from(n) + 4 > len {
        return Err(bad(format!("a header of {n} bytes in a file of {len}")));
    }
    let mut bytes = vec![0u8; n as usize + 4];
    file.read_exact_at(&mut bytes, 14).map_err(io)?;
    let crc = u32::from_le_bytes(bytes[n as usize..].try_into().expect("4"));
    bytes.truncate(n as usize);
    if crc32fast::hash(&bytes) != crc {
        return Err(bad("its header is corrupt (CRC mismatch)".into()));
    }
    let header: PartHeader =
        fractile_proto::decode(&bytes).map_err(|e| bad(format!("its header: {e}")))?;
    let body = 14 + u64::from(n) + 4;
    let total: u64 = header.records.iter().map(|r| r.length).sum();
    if body + total != len {
        return Err(bad(format!(
            "{} bytes of chunks after its header, {total} listed (a part cut short?)",
            len - body
        )));
    }
    Ok(Part {
        path: path.to_path_buf(),
        header,
        file,
        body,
    })
}

/// Every part of one encode is there, once: same sources, settings and count, each share once.
fn check_shares(parts: &[Part]) -> Result<(), Error> {
    let first = &parts[0];
    let h0 = &first.header;
    let count = h0.share.count;
    let mut seen = vec![None::<&Path>; count as usize];
    for p in parts {
        let h = &p.header;
        let differs = |what: &str| {
            Error::Input(format!(
                "{} and {} are parts of different encodes ({what} differ)",
                p.path.display(),
                first.path.display()
            ))
        };
        if h.share.count != count {
            return Err(differs("their part counts"));
        }
        if h.source != h0.source || h.chunk != h0.chunk {
            return Err(differs("their sources"));
        }
        if h.settings != h0.settings {
            return Err(differs("their settings"));
        }
        if let Some(other) = seen[h.share.index as usize].replace(&p.path) {
            return Err(Error::Input(format!(
                "{} and {} are both part {}/{count}",
                p.path.display(),
                other.display(),
                h.share.index
            )));
        }
    }
    if let Some(missing) = seen.iter().position(Option::is_none) {
        return Err(Error::Input(format!(
            "part {missing}/{count} is missing: assemble takes every part of an encode"
        )));
    }
    Ok(())
}

/// Joins the part files `parts` (every share of one encode, in any order) into the asset
/// `output`: the same bytes as the encode in one process. Parts of different sources or
/// settings, a missing or repeated share, a chunk of the wrong share, and a part cut short or
/// corrupt are refused by name, and nothing is written.
pub fn assemble(parts: &[PathBuf], output: &Path) -> Result<Written, Error> {
    let start = std::time::Instant::now();
    let parts = parts
        .iter()
        .map(|p| open_part(p))
        .collect::<Result<Vec<_>, _>>()?;
    let Some(first) = parts.first() else {
        return Err(Error::Input("assemble: no part files given".into()));
    };
    let h0 = &first.header;
    let count = h0.share.count;
    check_shares(&parts)?;
    let sizes = chunked::ChunkTable::level_sizes(h0.width, h0.height, h0.chunk);
    let levels: Vec<u64> = sizes
        .iter()
        .map(|&(w, h)| {
            let t = chunked::ChunkTable {
                chunk: h0.chunk,
                overlap: chunked::OVERLAP,
                codec: 0,
                max_contrast: 0.0,
                seed_bound: 0.0,
                smallest_source_error: None,
                levels: Vec::new(),
            };
            let (nx, ny) = t.grid(w, h);
            u64::from(nx * ny)
        })
        .collect();
    // Every chunk's record and where its file is: (part, offset in that part).
    let mut placed: Vec<Vec<Option<Placed<'_>>>> =
        levels.iter().map(|&n| vec![None; n as usize]).collect();
    for (k, p) in parts.iter().enumerate() {
        let mut at = p.body;
        for r in &p.header.records {
            let first_of_level: u64 = levels.iter().take(r.level as usize).sum();
            let slot = placed
                .get_mut(r.level as usize)
                .and_then(|l| l.get_mut(r.index as usize))
                .ok_or_else(|| {
                    Error::Input(format!(
                        "{}: chunk {} of level {} is not in the raster",
                        p.path.display(),
                        r.index,
                        r.level
                    ))
                })?;
            let number = first_of_level + u64::from(r.index);
            if number % u64::from(count) != u64::from(p.header.share.index) || slot.is_some() {
                return Err(Error::Input(format!(
                    "{}: chunk {} of level {} is not of its share",
                    p.path.display(),
                    r.index,
                    r.level
                )));
            }
            *slot = Some((k, at, r));
            at += r.length;
        }
    }
    let order: Vec<Placed<'_>> = placed.into_iter().flatten().flatten().collect();
    let (meta, mut table, errors, transforms) = summarise(
        (h0.width as usize, h0.height as usize, h0.georef.as_ref()),
        h0.chunk,
        &sizes,
        order.iter().map(|(_, _, r)| *r),
    )?;
    let head = chunked::header(&meta, &mut table);
    let mut length = 0;
    write_atomic_with(output, &mut |f| {
        let mut f = std::io::BufWriter::new(f);
        f.write_all(&head)?;
        length = head.len() as u64;
        for &(k, at, r) in &order {
            let mut buf = vec![0u8; r.length as usize];
            parts[k].file.read_exact_at(&mut buf, at)?;
            let whole =
                buf.len() >= 4 && crc32fast::hash(&buf[..buf.len() - 4]) == chunked::file_crc(&buf);
            if !whole || chunked::file_crc(&buf) != r.crc {
                return Err(std::io::Error::other(format!(
                    "{}: chunk {} of level {} is corrupt (CRC mismatch)",
                    parts[k].path.display(),
                    r.index,
                    r.level
                )));
            }
            f.write_all(&buf)?;
            length += r.length;
        }
        f.flush()
    })?;
    Ok(Written {
        asset: Asset::read(output)?,
        length,
        errors,
        transforms,
        seconds: start.elapsed().as_secs_f64(),
    })
}
