//! A chunked encode split over processes or machines (issue 31): `fractile encode --part I/N`
//! codes share I of the source's chunk rows ([`Share`], `encode::band`) into a part file, and
//! `fractile assemble` (`encode::assembly`) joins the N part files into the asset, coding the
//! overviews from the rows the parts hand on: the same bytes as one process's encode (chunk
//! files and the file's metadata hold no encode time, and the file's figures are summed in
//! table order).
//!
//! A part file: `FRAPART\0`, a u16 version (5), a u32 length and that many bytes of its
//! header (`PartHeader`, bincode through `fractile_proto`; docs/asset-format.md), the header's
//! CRC-32, the files of its chunks in the header's order, then the overview rows it hands on
//! (`encode::band::row_bytes` a row).

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::band::{Handoff, code_band, row_bytes};
use super::chunked::{EncodeOne, Progress, Share};
use super::rate::Quality;
use super::spill::Spill;
use super::summary::ChunkRecord;
use crate::Error;
use crate::codecs::options::Options;
use crate::core::format::FormatError;
use crate::io::asset::write_atomic_with;
use crate::io::chunked;
use crate::io::layout::read_exact_at;
use crate::io::rows::{Header, Rows};

const MAGIC: &[u8; 8] = b"FRAPART\0";
/// 4: the header says whether the file has views (their layout has a coded level above them).
/// 5: a part is a band of chunk rows; it hands on its overview rows and how to code them.
const VERSION: u16 = 5;

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
    /// The source's header: the overviews `assemble` cuts are of its kind, sample and units.
    header: Header,
    /// How the encode codes a chunk, for the overviews `assemble` codes (`encode::plan`);
    /// `None` from a caller of its own coding function, who assembles with it.
    recipe: Option<Recipe>,
    /// The rows of the first coded overview level the part hands on, after its chunk files.
    handoff: Option<HandedRows>,
}

/// How an encode codes its chunks, kept in its parts for the overviews `assemble` codes: the
/// codec and its options as the command line gave them, and the file's quality where the codec
/// has one (found by the part on its sample, or given).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Recipe {
    /// The codec's name (`--codec`).
    pub codec: String,
    /// Its options.
    pub options: Options,
    /// The file's quality, where its chunks are coded at one.
    pub quality: Option<Quality>,
}

/// Which overview rows a part hands on: level `level`'s rows `top..top + rows`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub(super) struct HandedRows {
    pub(super) level: u32,
    pub(super) top: u32,
    pub(super) rows: u32,
    /// The CRC-32 of their bytes.
    pub(super) crc: u32,
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

/// Codes the chunks of `share`'s band of the raster `rows` reads (as
/// [`super::chunked::encode_chunked_file`] codes them all) into the part file `output`, with
/// the band's overview rows for `assemble`. `settings` names the encode's settings
/// (`assemble` refuses parts whose settings differ); `recipe`, how `fractile assemble` codes
/// the overviews (`None`: the caller assembles with `encode_one`).
pub fn encode_chunked_part(
    rows: &mut dyn Rows,
    (chunk, share, settings, recipe): (u32, Share, &str, Option<&Recipe>),
    encode_one: &EncodeOne<'_>,
    progress: &Progress<'_>,
    output: &Path,
) -> Result<PartWritten, Error> {
    let mut spill = Spill::beside(output)?;
    let (coded, handoff) = code_band(
        rows,
        (chunk, share),
        (&|_, r: &crate::Raster| encode_one(r), progress),
        (&mut spill, Spill::beside(output)?),
    )?;
    let head = (chunk, share, settings, None);
    write_part(head, (coded, handoff, recipe.cloned()), &spill, output)
}

/// A part's chunks, coded, written to its file with its header and its overview rows.
fn write_part(
    (chunk, share, settings, budget): (u32, Share, &str, Option<u64>),
    (coded, handoff, recipe): (super::chunked::Streamed, Option<Handoff>, Option<Recipe>),
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
        header: coded.header.clone(),
        recipe,
        handoff: handoff.as_ref().map(|h| HandedRows {
            level: h.level as u32,
            top: h.top,
            rows: h.rows,
            crc: h.crc,
        }),
    };
    let head = part_head(&header);
    let mut length = 0;
    write_atomic_with(output, &mut |f| {
        let mut f = std::io::BufWriter::new(f);
        f.write_all(&head)?;
        length = head.len() as u64;
        for (at, len) in coded.order() {
            spill.copy(at, len, &mut f)?;
            length += len;
        }
        if let Some(h) = &handoff {
            // In pieces: a band of an image's first overview may be gigabytes.
            let piece = 8 << 20;
            let mut at = 0;
            while at < h.length {
                let len = piece.min(h.length - at);
                h.spill.copy(at, len, &mut f)?;
                at += len;
            }
            length += h.length;
        }
        f.flush()
    })?;
    Ok(PartWritten {
        chunks: header.records.len(),
        length,
        seconds: coded.start.elapsed().as_secs_f64(),
    })
}

/// [`encode_chunked_part`] at one quality for the file: given (`--max-error`), or under a
/// file's rate ([`super::rate`]), where each process finds the quality on the same sample (the
/// same quality in every process, which goes in the part's settings, so that `assemble`
/// refuses parts that disagree), then codes its share at it. The sample reads the whole
/// raster, so a split encode under a rate reads every input once more in each part; a quality
/// given (`--max-error`) reads each input once over all the parts. A single encode codes its
/// file again, coarser, should it come out over the rate; a split one cannot know the whole
/// file's size until `assemble`, so its parts aim lower ([`super::rate::PART_AIM`]; their
/// bytes are then not a single encode's), and `assemble` refuses a file over the rate, saying
/// what rate to ask for.
pub fn encode_chunked_part_at(
    rows: &mut dyn Rows,
    (chunk, share, settings, recipe): (u32, Share, &str, Option<&Recipe>),
    (rate, encode_at): (impl Into<super::rate::Target>, &super::rate::EncodeAt<'_>),
    progress: &Progress<'_>,
    output: &Path,
) -> Result<PartWritten, Error> {
    let aim = super::rate::PART_AIM;
    let (quality, budget) = super::chunked::quality_for(rows, chunk, (rate, encode_at), aim)?;
    let settings = format!("{settings} at {}", quality.describe());
    let mut spill = Spill::beside(output)?;
    let one = |l: usize, r: &crate::Raster| encode_at(r, quality.at_level(l), false);
    let (coded, handoff) = code_band(
        rows,
        (chunk, share),
        (&one, progress),
        (&mut spill, Spill::beside(output)?),
    )?;
    let recipe = recipe.map(|r| Recipe {
        quality: Some(quality),
        ..r.clone()
    });
    let head = (chunk, share, settings.as_str(), budget);
    write_part(head, (coded, handoff, recipe), &spill, output)
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

/// A part file opened: its header, the file, where its chunk files start and where the
/// overview rows it hands on start.
pub(super) struct Part {
    pub(super) path: PathBuf,
    header: PartHeader,
    pub(super) file: std::fs::File,
    pub(super) body: u64,
    pub(super) handoff_at: u64,
}

impl Part {
    /// The share the part coded.
    pub(super) fn share(&self) -> Share {
        self.header.share
    }

    /// The chunks it coded, in the order their files follow its header.
    pub(super) fn records(&self) -> &[ChunkRecord] {
        &self.header.records
    }

    /// The overview rows it hands on: their level, first row and count, and their CRC-32.
    pub(super) fn handed(&self) -> Option<(usize, u32, u32, u32)> {
        self.header
            .handoff
            .map(|h| (h.level as usize, h.top, h.rows, h.crc))
    }

    /// The encode's chunk side, whether it has views, and its source's header.
    pub(super) fn layout(&self) -> (u32, bool, &Header) {
        (self.header.chunk, self.header.viewed, &self.header.header)
    }

    /// The file's bytes at most, under a rate.
    pub(super) fn budget(&self) -> Option<u64> {
        self.header.budget
    }
}

/// How the part `path` was coded (its recipe, settings, chunk side and source
/// header), for `fractile assemble` to code the overviews alike (`encode::plan`).
pub fn recipe_of(path: &Path) -> Result<(Option<Recipe>, String, u32, Header), Error> {
    let p = open_part(path)?;
    let h = p.header;
    Ok((h.recipe, h.settings, h.chunk, h.header))
}

pub(super) fn open_part(path: &Path) -> Result<Part, Error> {
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
    let handed = header.handoff.map_or(0, |h| {
        let sizes = level_sizes(&header);
        let width = sizes[h.level as usize].0 as usize;
        u64::from(h.rows) * row_bytes(width, header.header.channels)
    });
    if body.checked_add(total).and_then(|b| b.checked_add(handed)) != Some(len) {
        return Err(bad(format!(
            "{} bytes of chunks and overview rows after its header, {} listed (a part cut short?)",
            len - body,
            total.saturating_add(handed)
        )));
    }
    Ok(Part {
        path: path.to_path_buf(),
        handoff_at: body + total,
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
    let src = &h.header;
    if (src.width, src.height) != (h.width as usize, h.height as usize)
        || !(1..=4).contains(&src.channels)
    {
        return Err(FormatError::header(format!(
            "a source of {} x {} cells and {} channels in a raster of {} x {}",
            src.width, src.height, src.channels, h.width, h.height
        )));
    }
    let sizes = level_sizes(h);
    let chunks: u64 = sizes
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
    let rows = h.height.saturating_add(h.chunk / 2) / h.chunk;
    if count == 0 || count > rows.max(1) || index >= count {
        return Err(FormatError::header(format!(
            "share {index}/{count} (shares go from 0 to count - 1, and a raster of {rows} \
             rows of chunks has at most {rows})"
        )));
    }
    if let Some(handed) = h.handoff {
        let level = handed.level as usize;
        if level == 0 || level >= sizes.len() || handed.rows > sizes[level].1 {
            return Err(FormatError::header(format!(
                "overview rows of level {level} ({} rows) in a file of {} levels",
                handed.rows,
                sizes.len()
            )));
        }
    }
    Ok(())
}

/// Every level's size of the file a part's header describes.
fn level_sizes(h: &PartHeader) -> Vec<(u32, u32)> {
    chunked::ChunkTable::level_sizes(h.width, h.height, h.chunk, h.viewed)
}

/// Every part of one encode is there, once: same sources, settings and count, each share once.
pub(super) fn check_shares(parts: &[Part]) -> Result<(), Error> {
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
            encode_chunked_part(&mut rows, (64, share, "s", None), &one, &|_, _| {}, &real)
                .unwrap();
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
    fn crafted_part_headers_are_refused_by_name() {
        let dir = std::env::temp_dir().join(format!("fractile-crafted-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        type Case = (&'static str, fn(&mut PartHeader), &'static str);
        let cases: [Case; 8] = [
            (
                "handoff",
                |h| h.handoff.as_mut().unwrap().level = 40,
                "overview rows of level 40",
            ),
            ("source", |h| h.header.channels = 9, "9 channels"),
            ("share", |h| h.share.index = 5, "share 5/2"),
            ("count", |h| h.share.count = u32::MAX, "share 0/4294967295"),
            (
                "size",
                |h| {
                    (h.width, h.height) = (u32::MAX, u32::MAX);
                    (h.header.width, h.header.height) = (u32::MAX as usize, u32::MAX as usize);
                },
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
            let err = match open_part(&part) {
                Err(e) => e.to_string(),
                Ok(_) => panic!("{name}: opened"),
            };
            assert!(err.contains(says), "{name}: {err}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
