//! A chunked encode split over processes or machines (issue 31): `fractile encode --part I/N`
//! codes share I of the chunks ([`Share`]) into a part file, and `fractile assemble` joins
//! the N part files into the asset, the same bytes as one process's encode (chunk files and
//! the file's metadata hold no encode time, and the file's figures are summed in table order).
//!
//! A part file: `FRAPART\0`, a u16 version (1), a u32 length and that many bytes of its
//! header (`PartHeader`, bincode through `fractile_proto`; docs/asset-format.md), the header's CRC-32, then the
//! files of its chunks in the header's order.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::chunked::{EncodeOne, Progress, Share, code_streamed};
use super::encoded::Written;
use super::spill::{Spill, write_spilled};
use super::summary::{ChunkRecord, summarise};
use crate::Error;
use crate::core::format::FormatError;
use crate::io::asset::{Asset, write_atomic_with};
use crate::io::chunked;
use crate::io::layout::read_exact_at;
use crate::io::rows::{Header, Rows};

const MAGIC: &[u8; 8] = b"FRAPART\0";
/// 4: the header says whether the file has views (their layout has a coded level above them).
const VERSION: u16 = 4;

/// Most bytes a part file's header may claim: 2^20 chunk records of a few hundred bytes.
const MAX_HEADER: u32 = 1 << 30;

/// What a part file says of itself.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct PartHeader {
    share: Share,
    chunk: u32,
    /// The source raster's header and the settings of its encode, as text: the parts of one
    /// asset must agree on both.
    source: String,
    settings: String,
    /// The file's bytes at most, under a file's rate ([`super::rate`]): `assemble` refuses
    /// parts that come to more.
    budget: Option<u64>,
    width: u32,
    height: u32,
    georef: Option<fractile_proto::Georef>,
    /// Whether the file's first overviews are views (`ChunkTable::level_sizes`).
    viewed: bool,
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
    let coded = code_streamed(
        rows,
        (chunk, share),
        (&|_, r: &crate::Raster| encode_one(r), progress),
        &mut spill,
    )?;
    write_part((chunk, share, settings, None), coded, &spill, output)
}

/// A part's chunks, coded, written to its file with its header.
fn write_part(
    (chunk, share, settings, budget): (u32, Share, &str, Option<u64>),
    coded: super::chunked::Streamed,
    spill: &Spill,
    output: &Path,
) -> Result<PartWritten, Error> {
    let header = PartHeader {
        share,
        chunk,
        source: source_text(&coded.header),
        settings: settings.to_string(),
        budget,
        width: coded.header.width as u32,
        height: coded.header.height as u32,
        georef: coded.header.georef.clone(),
        viewed: coded.viewed,
        records: coded.records().cloned().collect(),
    };
    let length = write_spilled(output, &part_head(&header), coded.order(), spill)?;
    Ok(PartWritten {
        chunks: header.records.len(),
        length,
        seconds: coded.start.elapsed().as_secs_f64(),
    })
}

/// [`encode_chunked_part`] at one quality for the file: given (`--max-error`), or under a
/// file's rate ([`super::rate`]), where each process finds the quality on the same sample (the same quality in every process, which goes in the part's
/// settings, so that [`assemble`] refuses parts that disagree), then codes its share at it.
/// A single encode codes its file again, coarser, should it come out over the rate; a split
/// one cannot know the whole file's size until [`assemble`], so its parts aim lower
/// ([`super::rate::PART_AIM`]; their bytes are then not a single encode's), and `assemble`
/// refuses a file over the rate, saying what rate to ask for.
pub fn encode_chunked_part_at(
    rows: &mut dyn Rows,
    (chunk, share, settings): (u32, Share, &str),
    (rate, encode_at): (impl Into<super::rate::Target>, &super::rate::EncodeAt<'_>),
    progress: &Progress<'_>,
    output: &Path,
) -> Result<PartWritten, Error> {
    let aim = super::rate::PART_AIM;
    let (quality, budget) = super::chunked::quality_for(rows, chunk, (rate, encode_at), aim)?;
    let settings = format!("{settings} at {}", quality.describe());
    let mut spill = Spill::beside(output)?;
    let one = |l: usize, r: &crate::Raster| encode_at(r, quality.at_level(l), false);
    let coded = code_streamed(rows, (chunk, share), (&one, progress), &mut spill)?;
    write_part((chunk, share, &settings, budget), coded, &spill, output)
}

/// A part file's head: magic, version, the header's length, the header, its CRC.
fn part_head(header: &PartHeader) -> Vec<u8> {
    let bytes = fractile_proto::encode(header);
    let mut head = Vec::with_capacity(bytes.len() + 18);
    head.extend_from_slice(MAGIC);
    head.extend_from_slice(&VERSION.to_le_bytes());
    head.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
    head.extend_from_slice(&bytes);
    head.extend_from_slice(&crc32fast::hash(&bytes).to_le_bytes());
    head
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
    let bad = |m: String| Error::input(format!("{}: {m}", path.display()));
    let io = |e: std::io::Error| {
        Error::input(format!("{}: {e}", path.display()))
            .at(path)
            .caused_by(e)
    };
    let file = std::fs::File::open(path).map_err(io)?;
    let mut head = [0u8; 14];
    read_exact_at(&file, &mut head, 0).map_err(|_| bad("not a part file (too short)".into()))?;
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
    read_exact_at(&file, &mut bytes, 14).map_err(io)?;
    let crc = u32::from_le_bytes(bytes[n as usize..].try_into().expect("4"));
    bytes.truncate(n as usize);
    if crc32fast::hash(&bytes) != crc {
        return Err(bad("its header is corrupt (CRC mismatch)".into()));
    }
    let header: PartHeader =
        fractile_proto::decode(&bytes).map_err(|e| bad(format!("its header: {e}")))?;
    check_header(&header).map_err(|e| bad(e.to_string()))?;
    let body = 14 + u64::from(n) + 4;
    let total = header
        .records
        .iter()
        .try_fold(0u64, |t, r| t.checked_add(r.length))
        .ok_or_else(|| bad("its chunk lengths overflow".into()))?;
    if body.checked_add(total) != Some(len) {
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

/// Refuses a part header no encoder writes, before anything is allocated for it (a crafted
/// header claimed share 5 of 2, 2^32 shares, 2^32 cells a side, or chunks of side 0, and
/// assemble panicked or asked for 100 GB). The raster's size is bounded by its chunk count.
fn check_header(h: &PartHeader) -> Result<(), FormatError> {
    let (lo, hi) = chunked::CHUNK_SIDES;
    if !h.chunk.is_power_of_two() || !(lo..=hi).contains(&h.chunk) {
        return Err(FormatError::header(format!(
            "chunks of {} cells a side (an encode makes powers of two from {lo} to {hi})",
            h.chunk
        )));
    }
    if h.width == 0 || h.height == 0 {
        return Err(FormatError::header(format!(
            "a raster of {} x {} cells",
            h.width, h.height
        )));
    }
    let chunks: u64 = chunked::ChunkTable::level_sizes(h.width, h.height, h.chunk, h.viewed)
        .iter()
        .map(|&(w, h2)| u64::from(w.div_ceil(h.chunk)) * u64::from(h2.div_ceil(h.chunk)))
        .sum();
    if chunks > chunked::MAX_CHUNKS as u64 {
        return Err(FormatError::header(format!(
            "{chunks} chunks (at most {})",
            chunked::MAX_CHUNKS
        )));
    }
    let Share { index, count } = h.share;
    if count == 0 || u64::from(count) > chunks.max(1) || index >= count {
        return Err(FormatError::header(format!(
            "share {index}/{count} (shares go from 0 to count - 1, and an encode of {chunks} \
             chunks has at most {chunks})"
        )));
    }
    Ok(())
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
            Error::input(format!(
                "{} and {} are parts of different encodes ({what} differ)",
                p.path.display(),
                first.path.display()
            ))
        };
        if h.share.count != count {
            return Err(differs("their part counts"));
        }
        if h.source != h0.source || h.chunk != h0.chunk || h.viewed != h0.viewed {
            return Err(differs("their sources"));
        }
        if h.settings != h0.settings {
            return Err(differs("their settings"));
        }
        if let Some(other) = seen[h.share.index as usize].replace(&p.path) {
            return Err(Error::input(format!(
                "{} and {} are both part {}/{count}",
                p.path.display(),
                other.display(),
                h.share.index
            )));
        }
    }
    if let Some(missing) = seen.iter().position(Option::is_none) {
        return Err(Error::input(format!(
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
        return Err(Error::input("assemble: no part files given"));
    };
    let h0 = &first.header;
    let count = h0.share.count;
    check_shares(&parts)?;
    let sizes = chunked::ChunkTable::level_sizes(h0.width, h0.height, h0.chunk, h0.viewed);
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
                views: Vec::new(),
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
                    Error::input(format!(
                        "{}: chunk {} of level {} is not in the raster",
                        p.path.display(),
                        r.index,
                        r.level
                    ))
                })?;
            let number = first_of_level + u64::from(r.index);
            if number % u64::from(count) != u64::from(p.header.share.index) || slot.is_some() {
                return Err(Error::input(format!(
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
    let total = head.len() as u64 + order.iter().map(|(_, _, r)| r.length).sum::<u64>();
    if let Some(budget) = h0.budget
        && total > budget
    {
        let bpp = 8.0 * budget as f64 / f64::from(h0.width) / f64::from(h0.height);
        return Err(Error::settings(format!(
            "the parts come to {total} bytes, over the rate's {budget} ({bpp:.3} bits a cell): a split encode finds its quality on a sample and cannot code again; encode the parts again with --target-bpp {:.3}",
            bpp * 0.98 * budget as f64 / total as f64
        )));
    }
    let mut length = 0;
    write_atomic_with(output, &mut |f| {
        let mut f = std::io::BufWriter::new(f);
        f.write_all(&head)?;
        length = head.len() as u64;
        for &(k, at, r) in &order {
            let mut buf = vec![0u8; r.length as usize];
            read_exact_at(&parts[k].file, &mut buf, at)?;
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A real part (jacksboro in chunks of 64, share 0 of 2) in `dir`, its header rewritten by
    /// `craft` into `name`.
    fn crafted(dir: &Path, name: &str, craft: impl Fn(&mut PartHeader)) -> PathBuf {
        let real = dir.join("real.part");
        if !real.exists() {
            let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("../testdata/jacksboro.tif");
            let mut rows = crate::io::rows::GeoTiff::open(&source).unwrap();
            let one = |r: &crate::Raster| crate::encode_default(r, 0.8, &|_, _| {});
            let share = Share { index: 0, count: 2 };
            encode_chunked_part(&mut rows, (64, share, "s"), &one, &|_, _| {}, &real).unwrap();
        }
        let part = open_part(&real).unwrap();
        let bytes = std::fs::read(&real).unwrap();
        let mut header = part.header.clone();
        craft(&mut header);
        let mut out = part_head(&header);
        out.extend_from_slice(&bytes[part.body as usize..]);
        let path = dir.join(name);
        std::fs::write(&path, out).unwrap();
        path
    }

    #[test]
    fn crafted_part_headers_are_refused_by_name_and_leave_nothing() {
        let dir = std::env::temp_dir().join(format!("fractile-crafted-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        type Case = (&'static str, fn(&mut PartHeader), &'static str);
        let cases: [Case; 6] = [
            ("share", |h| h.share.index = 5, "share 5/2"),
            ("count", |h| h.share.count = u32::MAX, "share 0/4294967295"),
            (
                "size",
                |h| (h.width, h.height) = (u32::MAX, u32::MAX),
                "chunks (at most",
            ),
            ("empty", |h| h.width = 0, "a raster of 0 x"),
            ("side", |h| h.chunk = 0, "chunks of 0 cells"),
            (
                "lengths",
                |h| {
                    h.records[0].length = u64::MAX - 8;
                    h.records[1].length = 64;
                },
                "overflow",
            ),
        ];
        for (name, craft, says) in cases {
            let part = crafted(&dir, name, craft);
            let out = dir.join(format!("{name}.fra"));
            let err = match assemble(&[part], &out) {
                Err(e) => e.to_string(),
                Ok(_) => panic!("{name}: assembled"),
            };
            assert!(err.contains(says), "{name}: {err}");
            assert!(!out.exists(), "{name}: an output was written");
        }
        let left: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| {
                !n.ends_with(".part")
                    && !["share", "count", "size", "empty", "side", "lengths"].contains(&n.as_str())
            })
            .collect();
        assert!(left.is_empty(), "left behind: {left:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
