//! Sample grids in and out: images (PNG, JPEG through `image`) and height fields (GeoTIFF through
//! `tiff`, 16-bit PNG). A [`Raster`] holds values in their own units plus a validity mask; the
//! codec normalises them itself.

use std::path::Path;

use fractile_proto::{AssetKind, ColourModel, Georef, SampleFormat};

use crate::Error;

/// The largest magnitude of a value that is coded: far beyond any height (the deepest trench
/// is 1.1e4 m) or image, and far enough from float32's 3.4e38 that a range between two such
/// values and the codecs' arithmetic on it stay finite.
pub const MAX_MAGNITUDE: f64 = 1e30;

/// A grid of samples in source units, row-major, row 0 at the top (north).
#[derive(Clone, Debug)]
pub struct Raster {
    /// Width in samples.
    pub width: usize,
    /// Height in samples.
    pub height: usize,
    /// One plane per channel (1 grey/height, 3 RGB).
    pub channels: Vec<Vec<f32>>,
    /// `false` where a cell has no data (nodata value, NaN); `None` when every cell is valid.
    pub valid: Option<Vec<bool>>,
    /// Image or height field.
    pub kind: AssetKind,
    /// Sample type of the source file.
    pub sample: SampleFormat,
    /// Units of the values, when known.
    pub units: Option<String>,
    /// The source's nodata value.
    pub nodata: Option<f64>,
    /// Georeference, for GeoTIFFs that carry one.
    pub georef: Option<Georef>,
}

// `Raster::open` (a file by its extension) is in `rows`, beside the GeoTIFF reader it uses.
impl Raster {
    /// A single-channel raster from values (NaN marks nodata).
    pub fn from_values(
        width: usize,
        height: usize,
        values: Vec<f32>,
        kind: AssetKind,
    ) -> Result<Raster, Error> {
        Raster::from_channels(width, height, vec![values], kind, SampleFormat::F32, None)
    }

    /// A raster of `channels` (a row-major plane each, 1 or 3) of the source's `sample` type:
    /// NaN cells and cells equal to `nodata` have no data.
    pub fn from_channels(
        width: usize,
        height: usize,
        channels: Vec<Vec<f32>>,
        kind: AssetKind,
        sample: SampleFormat,
        nodata: Option<f64>,
    ) -> Result<Raster, Error> {
        if let Some(c) = channels.iter().find(|c| c.len() != width * height) {
            return Err(Error::input(format!(
                "{} values for a {width}x{height} grid",
                c.len()
            )));
        }
        if !matches!(channels.len(), 1 | 3) {
            return Err(Error::input(format!(
                "{} channels: 1 (grey or heights) or 3 (colour)",
                channels.len()
            )));
        }
        let mut r = Raster {
            width,
            height,
            channels,
            valid: None,
            kind,
            sample,
            units: None,
            nodata,
            georef: None,
        };
        r.mask_invalid();
        r.check()?;
        Ok(r)
    }

    /// Colour model of the channels.
    pub fn colour(&self) -> ColourModel {
        if self.channels.len() == 3 {
            ColourModel::YCbCr
        } else {
            ColourModel::Grey
        }
    }

    /// Whether cell `i` holds data.
    pub fn is_valid(&self, i: usize) -> bool {
        self.valid.as_ref().is_none_or(|v| v[i])
    }

    /// Marks NaN cells and cells equal to the nodata value as invalid.
    fn mask_invalid(&mut self) {
        let nodata = self.nodata.map(|v| v as f32);
        let n = self.width * self.height;
        let mut valid = vec![true; n];
        let mut any = false;
        for ch in &self.channels {
            for (i, &v) in ch.iter().enumerate() {
                if !v.is_finite() || Some(v) == nodata {
                    valid[i] = false;
                    any = true;
                }
            }
        }
        self.valid = any.then_some(valid);
    }

    pub(crate) fn check(&self) -> Result<(), Error> {
        if self.width == 0 || self.height == 0 {
            return Err(Error::input("the grid is empty (0 samples)"));
        }
        const MAX_SIDE: usize = 1 << 15;
        if self.width > MAX_SIDE || self.height > MAX_SIDE {
            return Err(Error::input(format!(
                "{}x{} is larger than the {MAX_SIDE} samples a side this version encodes",
                self.width, self.height
            )));
        }
        if let Some(v) = &self.valid
            && !v.iter().any(|&b| b)
        {
            return Err(Error::input("every cell is nodata: nothing to encode"));
        }
        self.check_magnitudes()
    }

    /// Refuses values whose magnitude is over [`MAX_MAGNITUDE`]: the codecs normalise values
    /// over their range in float32, and a range wider than float32 holds (+-3.4e38, GDAL's
    /// usual float nodata, left undeclared) decoded to infinity while the encoder reported no
    /// error. Such a value is nearly always a nodata marker: the message says how to declare it.
    pub(crate) fn check_magnitudes(&self) -> Result<(), Error> {
        for ch in &self.channels {
            for (i, &v) in ch.iter().enumerate() {
                if self.is_valid(i) && f64::from(v).abs() > MAX_MAGNITUDE {
                    let (x, y) = (i % self.width, i / self.width);
                    return Err(Error::input(format!(
                        "the value {v:e} at column {x}, row {y} is beyond the {MAX_MAGNITUDE:e} this \
                         version codes; if it marks cells without data (GDAL's float nodata is \
                         -3.4028235e38), declare it as the nodata value"
                    )));
                }
            }
        }
        Ok(())
    }

    /// Min and max of the valid values over all channels.
    pub fn value_range(&self) -> (f64, f64) {
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for ch in &self.channels {
            for (i, &v) in ch.iter().enumerate() {
                if self.is_valid(i) {
                    lo = lo.min(v as f64);
                    hi = hi.max(v as f64);
                }
            }
        }
        (lo, hi)
    }
}

pub(crate) fn read_image(path: &Path) -> Result<Raster, Error> {
    use image::DynamicImage as D;
    let img = image::ImageReader::open(path)
        .map_err(|e| {
            Error::input(format!("{}: {e}", path.display()))
                .at(path)
                .caused_by(e)
        })?
        .with_guessed_format()
        .map_err(|e| {
            Error::input(format!("{}: {e}", path.display()))
                .at(path)
                .caused_by(e)
        })?;
    // Neither the content nor the name says an image: say what the encoder reads, rather than
    // the image crate's "The file extension `.\"txt\"` was not recognized".
    if img.format().is_none() {
        return Err(Error::input(format!(
            "{}: not a raster, mesh or curve the encoder reads: GeoTIFF (.tif, .tiff), PNG \
             (8- or 16-bit), JPEG, a folder of GeoTIFFs, OFF, OBJ, PLY or STL meshes, or \
             GeoJSON curves (.geojson, .json)",
            path.display()
        )));
    }
    let img = img.decode().map_err(|e| {
        Error::input(format!("{}: {e}", path.display()))
            .at(path)
            .caused_by(e)
    })?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (channels, kind, sample) = match &img {
        D::ImageLuma8(_) | D::ImageLumaA8(_) => (
            vec![
                img.to_luma8()
                    .into_raw()
                    .into_iter()
                    .map(f32::from)
                    .collect(),
            ],
            AssetKind::Image,
            SampleFormat::U8,
        ),
        // A 16-bit grey PNG is how many DEMs travel: treat it as a height field.
        D::ImageLuma16(_) | D::ImageLumaA16(_) => (
            vec![
                img.to_luma16()
                    .into_raw()
                    .into_iter()
                    .map(f32::from)
                    .collect(),
            ],
            AssetKind::HeightField,
            SampleFormat::U16,
        ),
        D::ImageRgb16(_) | D::ImageRgba16(_) => (
            split_rgb(&img.to_rgb16().into_raw()),
            AssetKind::Image,
            SampleFormat::U16,
        ),
        D::ImageRgb32F(_) | D::ImageRgba32F(_) => (
            split_rgb(&img.to_rgb32f().into_raw()),
            AssetKind::Image,
            SampleFormat::F32,
        ),
        _ => (
            split_rgb(&img.to_rgb8().into_raw()),
            AssetKind::Image,
            SampleFormat::U8,
        ),
    };
    let mut r = Raster {
        width: w,
        height: h,
        channels,
        valid: None,
        kind,
        sample,
        units: None,
        nodata: None,
        georef: None,
    };
    r.mask_invalid();
    Ok(r)
}

fn split_rgb<T: Copy + Into<f64>>(px: &[T]) -> Vec<Vec<f32>> {
    (0..3)
        .map(|c| {
            px.iter()
                .skip(c)
                .step_by(3)
                .map(|&v| v.into() as f32)
                .collect()
        })
        .collect()
}

/// The EPSG code in a GeoKeyDirectory: ProjectedCSTypeGeoKey (3072) or GeographicTypeGeoKey (2048).
pub(crate) fn epsg_of(keys: &[u16]) -> Option<u32> {
    let entries = keys.get(4..)?;
    let find = |id: u16| {
        entries
            .chunks_exact(4)
            .find(|e| e[0] == id && e[1] == 0)
            .map(|e| e[3] as u32)
    };
    find(3072)
        .or_else(|| find(2048))
        .filter(|&c| c != 0 && c != 32767)
}

/// Writes 8-bit grey or RGB (channels 1 or 3) PNG; values are clamped and rounded.
pub fn write_png8(
    path: &Path,
    width: usize,
    height: usize,
    channels: &[Vec<f32>],
) -> Result<(), Error> {
    let n = width * height;
    let q = |v: f32| v.round().clamp(0.0, 255.0) as u8;
    let img = if channels.len() == 3 {
        let mut px = Vec::with_capacity(n * 3);
        for i in 0..n {
            px.extend(channels.iter().map(|c| q(c[i])));
        }
        image::DynamicImage::ImageRgb8(
            image::RgbImage::from_raw(width as u32, height as u32, px).expect("size"),
        )
    } else {
        let px = channels[0].iter().map(|&v| q(v)).collect();
        image::DynamicImage::ImageLuma8(
            image::GrayImage::from_raw(width as u32, height as u32, px).expect("size"),
        )
    };
    img.save(path).map_err(|e| {
        Error::output(format!("{}: {e}", path.display()))
            .at(path)
            .caused_by(e)
    })
}

/// Writes a 16-bit grey PNG of values already mapped to 0..=65535.
pub fn write_png16(path: &Path, width: usize, height: usize, values: &[f32]) -> Result<(), Error> {
    let px = values
        .iter()
        .map(|&v| v.round().clamp(0.0, 65535.0) as u16)
        .collect();
    let img: image::ImageBuffer<image::Luma<u16>, Vec<u16>> =
        image::ImageBuffer::from_raw(width as u32, height as u32, px).expect("size");
    img.save(path).map_err(|e| {
        Error::output(format!("{}: {e}", path.display()))
            .at(path)
            .caused_by(e)
    })
}

/// Writes a float32 GeoTIFF, with georeference and nodata tags when given (atomically).
pub fn write_geotiff_f32(
    path: &Path,
    width: usize,
    height: usize,
    values: &[f32],
    georef: Option<&Georef>,
    nodata: Option<f64>,
) -> Result<(), Error> {
    let bytes = geotiff_f32(width, height, values, georef, nodata).map_err(|e| match e {
        Error::Output { .. } => e.within(path.display()).at(path),
        e => e,
    })?;
    crate::io::asset::write_atomic(path, &bytes)
}

/// A float32 GeoTIFF in memory, with georeference and nodata tags when given.
pub fn geotiff_f32(
    width: usize,
    height: usize,
    values: &[f32],
    georef: Option<&Georef>,
    nodata: Option<f64>,
) -> Result<Vec<u8>, Error> {
    use tiff::encoder::{TiffEncoder, colortype::Gray32Float};
    use tiff::tags::Tag;
    let err = |e: tiff::TiffError| Error::output(format!("GeoTIFF: {e}"));
    let mut out = std::io::Cursor::new(Vec::new());
    let mut enc = TiffEncoder::new(&mut out).map_err(err)?;
    let mut img = enc
        .new_image::<Gray32Float>(width as u32, height as u32)
        .map_err(err)?;
    if let Some(g) = georef {
        let d = img.encoder();
        d.write_tag(
            Tag::ModelPixelScaleTag,
            &[g.pixel_size[0], -g.pixel_size[1], 0.0][..],
        )
        .map_err(err)?;
        d.write_tag(
            Tag::ModelTiepointTag,
            &[0.0, 0.0, 0.0, g.origin[0], g.origin[1], 0.0][..],
        )
        .map_err(err)?;
        if let Some(code) = g.epsg {
            // GeoKeyDirectory v1.1.0: model type, raster type PixelIsArea, the CRS code.
            // Asked of the CRS definitions; a code they do not hold is taken as projected
            // unless it is 4326's family by number (4000-4999), as before.
            let geographic = crate::geo::epsg_is_geographic(code)
                .unwrap_or_else(|| (4000..5000).contains(&code));
            let (model, key) = if geographic {
                (2u16, 2048u16)
            } else {
                (1u16, 3072u16)
            };
            let keys: [u16; 16] = [
                1,
                1,
                0,
                3,
                1024,
                0,
                1,
                model,
                1025,
                0,
                1,
                1,
                key,
                0,
                1,
                code as u16,
            ];
            d.write_tag(Tag::GeoKeyDirectoryTag, &keys[..])
                .map_err(err)?;
        }
    }
    if let Some(nd) = nodata {
        img.encoder()
            .write_tag(Tag::GdalNodata, format!("{nd}").as_str())
            .map_err(err)?;
    }
    img.write_data(values).map_err(err)?;
    Ok(out.into_inner())
}
