//! Rasters read by bands of rows, so that one larger than memory can be encoded (issue 30).
//! A chunked encode asks its source for a few hundred rows at a time and keeps only the rows
//! its chunks in progress need. A GeoTIFF is read strip by strip or tile by tile through
//! `tiff`'s `read_chunk`, and a mosaic of GeoTIFFs ([`super::mosaic`]) band by band from each
//! input. PNG and JPEG files are decoded whole: `image` has no row-by-row reader.

use std::path::{Path, PathBuf};

use fractile_proto::{AssetKind, Georef, SampleFormat};

use std::sync::Arc;

use crate::Error;
use crate::io::ranged::{RangeReader, RangedFile};
use crate::io::raster::Raster;

/// The widest mosaic in cells: a band of rows of it is held in memory while it encodes
/// (about 5 bytes a cell for 1,030 rows of each overview level). Inputs far apart would
/// otherwise ask for a grid of mostly nodata. The same side limit as a single raster has.
pub const MAX_WIDTH: usize = 1 << 15;

/// The tallest mosaic in cells: rows are read a band at a time, so height costs time, not
/// memory; this bounds the time that inputs far apart would spend on nodata.
pub const MAX_HEIGHT: usize = 1 << 20;

/// What a raster is without its cells: everything its file's header says.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Header {
    /// Width in samples.
    pub width: usize,
    /// Height in samples.
    pub height: usize,
    /// Channels (1 grey/height, 3 RGB).
    pub channels: usize,
    /// Image or height field.
    pub kind: AssetKind,
    /// Sample type of the source.
    pub sample: SampleFormat,
    /// Units of the values, when known.
    pub units: Option<String>,
    /// The source's nodata value.
    pub nodata: Option<f64>,
    /// Georeference of the raster's top-left corner.
    pub georef: Option<Georef>,
    /// What was done to the inputs to make these cells, for the asset's provenance (a mosaic
    /// of resampled inputs says so); `None` for cells as read.
    #[serde(default)]
    pub lineage: Option<String>,
}

impl Header {
    /// The header of a raster in memory.
    pub fn of(r: &Raster) -> Header {
        Header {
            width: r.width,
            height: r.height,
            channels: r.channels.len(),
            kind: r.kind,
            sample: r.sample,
            units: r.units.clone(),
            nodata: r.nodata,
            georef: r.georef.clone(),
            lineage: None,
        }
    }

    /// The cells from `[x0, y0]` on, `width` wide, as a raster of their own holding
    /// `channels` and `valid`, its georeference moved to its top-left corner.
    pub fn band(
        &self,
        [x0, y0]: [usize; 2],
        width: usize,
        channels: Vec<Vec<f32>>,
        valid: Option<Vec<bool>>,
    ) -> Raster {
        let height = channels.first().map_or(0, |c| c.len() / width.max(1));
        Raster {
            width,
            height,
            channels,
            valid,
            kind: self.kind,
            sample: self.sample,
            units: self.units.clone(),
            nodata: self.nodata,
            georef: self
                .georef
                .as_ref()
                .map(|g| cut_at(g, [x0 as f64, y0 as f64])),
        }
    }
}

/// The georeference of the grid `g` cut at its cell `(x, y)` (that cell's corner the origin):
/// a band's, a window's, a mosaic's.
pub(crate) fn cut_at(g: &Georef, [x, y]: [f64; 2]) -> Georef {
    Georef {
        origin: [
            g.origin[0] + x * g.pixel_size[0],
            g.origin[1] + y * g.pixel_size[1],
        ],
        ..g.clone()
    }
}

/// A raster read by bands of rows.
pub trait Rows: Send {
    /// The raster's size, channels and metadata.
    fn header(&self) -> &Header;

    /// Rows `y0..y1` (full width) as a raster whose georeference is the band's. `valid` is
    /// `None` where every cell of the band holds data.
    fn read(&mut self, y0: usize, y1: usize) -> Result<Raster, Error>;

    /// Every row: the raster whole (checked as [`Raster::open`] checks a file).
    fn read_all(&mut self) -> Result<Raster, Error> {
        let h = self.header().height;
        let r = self.read(0, h)?;
        r.check()?;
        Ok(r)
    }
}

/// A raster already in memory, read by bands (a PNG or JPEG input, tests, benches).
pub struct InMemory<'a> {
    raster: std::borrow::Cow<'a, Raster>,
    header: Header,
}

impl<'a> InMemory<'a> {
    /// Bands of `raster`, borrowed.
    pub fn new(raster: &'a Raster) -> InMemory<'a> {
        InMemory {
            header: Header::of(raster),
            raster: std::borrow::Cow::Borrowed(raster),
        }
    }

    /// Bands of `raster`, owned.
    pub fn owned(raster: Raster) -> InMemory<'static> {
        InMemory {
            header: Header::of(&raster),
            raster: std::borrow::Cow::Owned(raster),
        }
    }
}

impl Rows for InMemory<'_> {
    fn header(&self) -> &Header {
        &self.header
    }

    fn read(&mut self, y0: usize, y1: usize) -> Result<Raster, Error> {
        let r = &*self.raster;
        let y1 = y1.min(r.height);
        let span = y0 * r.width..y1 * r.width;
        let valid = r.valid.as_ref().map(|v| v[span.clone()].to_vec());
        let channels = r
            .channels
            .iter()
            .map(|c| c[span.clone()].to_vec())
            .collect();
        Ok(self.header.band(
            [0, y0],
            r.width,
            channels,
            valid.filter(|v| v.contains(&false)),
        ))
    }

    fn read_all(&mut self) -> Result<Raster, Error> {
        Ok(self.raster.clone().into_owned())
    }
}

/// Where a GeoTIFF's bytes are.
#[derive(Clone)]
pub enum TiffSource {
    /// A local file.
    File(PathBuf),
    /// A file read by range (an object in a bucket, a file on a web server).
    Ranged(Arc<RangedFile>),
}

impl TiffSource {
    /// The file's path or address, for messages.
    pub fn name(&self) -> String {
        match self {
            TiffSource::File(p) => p.display().to_string(),
            TiffSource::Ranged(r) => r.describe(),
        }
    }
}

/// A GeoTIFF read by its own strips or tiles. The file is opened again for each band (a
/// mosaic of thousands of tiles would otherwise hold thousands of descriptors), and the
/// row of strips or tiles a band ends inside is kept for the next band. A file read by range
/// fetches each band's chunks ahead, in as few requests as their layout allows.
pub struct GeoTiff {
    source: TiffSource,
    header: Header,
    /// Rows of one strip or one row of tiles (0: a declared file whose header is not read).
    chunk_rows: usize,
    /// The last row of chunks decoded: its index and its values (full width).
    last: Option<(usize, Vec<f32>)>,
    /// Each chunk's byte offset and length (a file read by range; read once).
    spans: Option<Vec<(u64, u64)>>,
}

/// What `tiff` reads through: a buffered file or a [`RangeReader`].
trait ReadSeek: std::io::Read + std::io::Seek + Send {}
impl<T: std::io::Read + std::io::Seek + Send> ReadSeek for T {}

type Decoder = tiff::decoder::Decoder<Box<dyn ReadSeek>>;

impl GeoTiff {
    /// Reads the header of the GeoTIFF at `path` (none of its cells).
    pub fn open(path: &Path) -> Result<GeoTiff, Error> {
        GeoTiff::open_source(TiffSource::File(path.to_path_buf()))
    }

    /// Reads the header of the GeoTIFF `source` holds (none of its cells).
    pub fn open_source(source: TiffSource) -> Result<GeoTiff, Error> {
        use tiff::tags::Tag;
        let name = source.name();
        let path = Path::new(&name);
        let mut dec = decoder(&source)?;
        let bad = |e: tiff::TiffError| {
            Error::input(format!("{}: {e}", path.display()))
                .at(path)
                .caused_by(e)
        };
        let (w, h) = dec.dimensions().map_err(bad)?;
        let nodata = dec
            .find_tag(Tag::GdalNodata)
            .ok()
            .flatten()
            .and_then(|v| v.into_string().ok())
            .and_then(|s| s.trim_matches(char::from(0)).trim().parse::<f64>().ok());
        let tie = dec.get_tag_f64_vec(Tag::ModelTiepointTag).ok();
        let scale = dec.get_tag_f64_vec(Tag::ModelPixelScaleTag).ok();
        let keys = dec.get_tag_u16_vec(Tag::GeoKeyDirectoryTag).ok();
        let samples = dec
            .find_tag_unsigned::<u16>(Tag::SamplesPerPixel)
            .ok()
            .flatten()
            .unwrap_or(1);
        if samples != 1 {
            return Err(Error::input(format!(
                "{}: {samples} samples a pixel: only single-band GeoTIFFs are supported",
                path.display()
            )));
        }
        let sample = sample_format(&mut dec)
            .ok_or_else(|| Error::input(format!("{}: unsupported sample type", path.display())))?;
        let georef = match (tie, scale) {
            (Some(t), Some(s)) if t.len() >= 6 && s.len() >= 2 => Some(Georef {
                epsg: keys.as_deref().and_then(super::raster::epsg_of),
                origin: [t[3] - t[0] * s[0], t[4] + t[1] * s[1]],
                pixel_size: [s[0], -s[1]],
            }),
            _ => None,
        };
        let chunk_rows = dec.chunk_dimensions().1.max(1) as usize;
        Ok(GeoTiff {
            source,
            spans: None,
            header: Header {
                width: w as usize,
                height: h as usize,
                channels: 1,
                kind: AssetKind::HeightField,
                sample,
                // GeoTIFF DEMs are in metres unless a vertical-units key says otherwise; we
                // read no vertical units key, so we say metres only for georeferenced grids.
                units: georef.as_ref().map(|_| "m".to_string()),
                nodata,
                georef,
                lineage: None,
            },
            chunk_rows,
            last: None,
        })
    }

    /// The GeoTIFF `source` holds, placed by what its catalog says of it (`header`, a STAC
    /// item's grid) without reading its header, which is read and checked against `header`
    /// when its cells are first read: a part of a split encode so opens only the inputs its
    /// band of rows crosses.
    pub fn declared(source: TiffSource, header: Header) -> GeoTiff {
        GeoTiff {
            source,
            header,
            chunk_rows: 0,
            last: None,
            spans: None,
        }
    }

    /// A declared file's header, read once and checked against what was declared: a catalog
    /// that says another grid than its file holds is an error that names both.
    fn checked(&mut self) -> Result<(), Error> {
        if self.chunk_rows > 0 {
            return Ok(());
        }
        let real = GeoTiff::open_source(self.source.clone())?;
        let (said, held) = (&self.header, &real.header);
        let georef = match (&said.georef, &held.georef) {
            (Some(a), Some(b)) => {
                let px = a.pixel_size[0].abs().min(a.pixel_size[1].abs());
                a.epsg == b.epsg
                    && (0..2).all(|i| {
                        (a.origin[i] - b.origin[i]).abs() <= 1e-6 * px
                            && (a.pixel_size[i] - b.pixel_size[i]).abs() <= 1e-9 * px
                    })
            }
            (a, b) => a.is_none() && b.is_none(),
        };
        let same = (said.width, said.height, said.sample) == (held.width, held.height, held.sample)
            && said.nodata == held.nodata;
        if !(same && georef) {
            let grid = |h: &Header| {
                format!(
                    "{}x{} {:?} cells, nodata {:?}, {:?}",
                    h.width, h.height, h.sample, h.nodata, h.georef
                )
            };
            return Err(Error::input(format!(
                "{}: its catalog says {}; the file holds {}",
                self.source.name(),
                grid(said),
                grid(held)
            )));
        }
        self.chunk_rows = real.chunk_rows;
        Ok(())
    }

    /// Where the file's bytes are.
    pub fn source(&self) -> &TiffSource {
        &self.source
    }

    /// Row `row` of the file's chunks (one strip, or one row of tiles), full width.
    fn chunk_row(&mut self, dec: &mut Decoder, row: usize) -> Result<&[f32], Error> {
        if self.last.as_ref().is_none_or(|(r, _)| *r != row) {
            let values = self.decode_chunk_row(dec, row)?;
            self.last = Some((row, values));
        }
        Ok(&self.last.as_ref().expect("just decoded").1)
    }

    fn decode_chunk_row(&mut self, dec: &mut Decoder, row: usize) -> Result<Vec<f32>, Error> {
        let name = self.source.name();
        let w = self.header.width;
        let (tw, _) = dec.chunk_dimensions();
        let across = match dec.get_chunk_type() {
            tiff::decoder::ChunkType::Tile => w.div_ceil(tw.max(1) as usize),
            _ => 1,
        };
        let rows = self
            .chunk_rows
            .min(self.header.height - row * self.chunk_rows);
        let TiffSource::Ranged(file) = &self.source else {
            return self.decode_chunks(dec, row, across, rows);
        };
        let file = file.clone();
        if self.spans.is_none() {
            self.spans = Some(chunk_spans(dec).map_err(|e| input_error(&name, e))?);
        }
        let spans = self.spans.as_deref().unwrap_or_default();
        let row_spans = spans
            .get(row * across..(row + 1) * across)
            .unwrap_or_default();
        file.fetch_ahead(row_spans)
            .map_err(|e| input_error(&name, e))?;
        let decoded = self.decode_chunks(dec, row, across, rows);
        file.release();
        decoded
    }

    /// The `across` chunks of chunk row `row`, `rows` high, side by side (full width).
    fn decode_chunks(
        &self,
        dec: &mut Decoder,
        row: usize,
        across: usize,
        rows: usize,
    ) -> Result<Vec<f32>, Error> {
        let name = self.source.name();
        let path = Path::new(&name);
        let bad = |e: tiff::TiffError| input_error(&name, e);
        let w = self.header.width;
        let mut out = vec![0f32; w * rows];
        let mut x0 = 0;
        for k in 0..across {
            let index = (row * across + k) as u32;
            let data = dec.read_chunk(index).map_err(bad)?;
            let (cw, ch) = dec.chunk_data_dimensions(index);
            let (cw, ch) = (cw as usize, ch as usize);
            let values = values_of(data);
            if values.len() != cw * ch || ch != rows || x0 + cw > w {
                return Err(Error::input(format!(
                    "{}: chunk {index} holds {} samples for {cw}x{ch}: only single-band GeoTIFFs are supported",
                    path.display(),
                    values.len()
                )));
            }
            for y in 0..rows {
                out[y * w + x0..y * w + x0 + cw].copy_from_slice(&values[y * cw..(y + 1) * cw]);
            }
            x0 += cw;
        }
        Ok(out)
    }
}

impl Rows for GeoTiff {
    fn header(&self) -> &Header {
        &self.header
    }

    fn read(&mut self, y0: usize, y1: usize) -> Result<Raster, Error> {
        self.checked()?;
        let (w, h) = (self.header.width, self.header.height);
        let y1 = y1.min(h);
        let mut values = Vec::with_capacity(w * (y1.saturating_sub(y0)));
        let mut dec = decoder(&self.source)?;
        let per = self.chunk_rows;
        let mut y = y0;
        while y < y1 {
            let row = y / per;
            let top = row * per;
            let end = ((row + 1) * per).min(y1);
            let rows = self.chunk_row(&mut dec, row)?;
            values.extend_from_slice(&rows[(y - top) * w..(end - top) * w]);
            y = end;
        }
        // Keep the last chunk row only if the next band starts inside it: a mosaic holds one
        // reader an input, and would otherwise keep a chunk row of every input read so far.
        if y1 % per == 0 || y1 == h {
            self.last = None;
        }
        let nodata = self.header.nodata.map(|v| v as f32);
        let valid: Vec<bool> = values
            .iter()
            .map(|&v| v.is_finite() && Some(v) != nodata)
            .collect();
        let valid = valid.contains(&false).then_some(valid);
        Ok(self.header.band([0, y0], w, vec![values], valid))
    }
}

fn decoder(source: &TiffSource) -> Result<Decoder, Error> {
    let name = source.name();
    let path = Path::new(&name);
    let reader: Box<dyn ReadSeek> = match source {
        TiffSource::File(p) => Box::new(std::io::BufReader::new(std::fs::File::open(p).map_err(
            |e| {
                Error::input(format!("{}: {e}", p.display()))
                    .at(p)
                    .caused_by(e)
            },
        )?)),
        TiffSource::Ranged(file) => Box::new(RangeReader::new(file.clone())),
    };
    // The decoder's default limits stay: they bound one strip or tile (256 MiB), not the
    // raster, since nothing here reads a whole image at once.
    tiff::decoder::Decoder::new(reader).map_err(|e| {
        Error::input(format!("{}: {e}", path.display()))
            .at(path)
            .caused_by(e)
    })
}

/// An input error about the file `name`, caused by `e`.
fn input_error(name: &str, e: impl std::error::Error + Send + Sync + 'static) -> Error {
    Error::input(format!("{name}: {e}")).at(name).caused_by(e)
}

/// Each chunk's (strip's or tile's) byte offset and length, from the file's tags.
fn chunk_spans(dec: &mut Decoder) -> Result<Vec<(u64, u64)>, tiff::TiffError> {
    use tiff::tags::Tag;
    let (offsets, counts) = match dec.get_chunk_type() {
        tiff::decoder::ChunkType::Tile => (Tag::TileOffsets, Tag::TileByteCounts),
        _ => (Tag::StripOffsets, Tag::StripByteCounts),
    };
    let offsets = dec.get_tag_u64_vec(offsets)?;
    let counts = dec.get_tag_u64_vec(counts)?;
    Ok(offsets.into_iter().zip(counts).collect())
}

/// The sample type a GeoTIFF's tags announce, as [`values_of`] converts it: integers of up to
/// 16 bits keep their type (an 8-bit signed one widens to 16), the rest are read as f32.
fn sample_format(dec: &mut Decoder) -> Option<SampleFormat> {
    use tiff::ColorType as C;
    use tiff::tags::{SampleFormat as F, Tag};
    let format = dec
        .find_tag_unsigned::<u16>(Tag::SampleFormat)
        .ok()
        .flatten()
        .map_or(F::Uint, F::from_u16_exhaustive);
    let bits = match dec.colortype().ok()? {
        C::Gray(b) => b,
        _ => return None,
    };
    Some(match (format, bits) {
        (F::Uint, 8) => SampleFormat::U8,
        (F::Uint, 16) => SampleFormat::U16,
        (F::Int, 8 | 16) => SampleFormat::I16,
        (F::Uint | F::Int, 32 | 64) | (F::IEEEFP, 16 | 32 | 64) => SampleFormat::F32,
        _ => return None,
    })
}

/// A chunk's decoded samples as f32.
fn values_of(data: tiff::decoder::DecodingResult) -> Vec<f32> {
    use tiff::decoder::DecodingResult as R;
    match data {
        R::U8(v) => v.into_iter().map(f32::from).collect(),
        R::U16(v) => v.into_iter().map(f32::from).collect(),
        R::I16(v) => v.into_iter().map(f32::from).collect(),
        R::I8(v) => v.into_iter().map(f32::from).collect(),
        R::I32(v) => v.into_iter().map(|x| x as f32).collect(),
        R::U32(v) => v.into_iter().map(|x| x as f32).collect(),
        R::I64(v) => v.into_iter().map(|x| x as f32).collect(),
        R::U64(v) => v.into_iter().map(|x| x as f32).collect(),
        R::F32(v) => v,
        R::F64(v) => v.into_iter().map(|x| x as f32).collect(),
        R::F16(v) => v.into_iter().map(f32::from).collect(),
    }
}

/// Files opened whole: here rather than in `raster`, beside the GeoTIFF reader they use.
impl Raster {
    /// Reads an image (PNG, JPEG) or a height field (GeoTIFF, 16-bit grey PNG) by file extension.
    pub fn open(path: &Path) -> Result<Raster, Error> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        let r = match ext.as_str() {
            "tif" | "tiff" => read_geotiff(path)?,
            _ => super::raster::read_image(path)?,
        };
        r.check()?;
        Ok(r)
    }
}

/// A GeoTIFF whole: every row of [`GeoTiff`] (one reader of the format).
fn read_geotiff(path: &Path) -> Result<Raster, Error> {
    let mut file = GeoTiff::open(path)?;
    let h = file.header().height;
    file.read(0, h)
}

/// Whether `path` names a TIFF by its extension.
pub fn is_tiff(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("tif") || e.eq_ignore_ascii_case("tiff"))
}
