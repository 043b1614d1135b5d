//! Metadata of an asset: what it depicts and how to read its values. Shared by the asset file
//! (codec crate), the HTTP API (server) and the client.

use serde::{Deserialize, Serialize};

/// What an asset depicts. Decides which requests make sense (tiles, points, meshes, curves).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum AssetKind {
    /// A picture: grey or colour, values are intensities.
    Image,
    /// A height field (DEM): one channel of elevations in `units`.
    HeightField,
    /// A signed distance field on a 3D grid (IFS3D).
    Volume,
    /// A set of curves (projected IFS with details).
    Curve,
}

/// How the channels of an image relate to colour.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ColourModel {
    /// One channel.
    Grey,
    /// RGB input, coded as Y, Cb, Cr (ITU-R BT.601, full range), chroma at half resolution.
    YCbCr,
}

/// The sample type of the source, which sets the output type of decoders and the ratio baseline.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum SampleFormat {
    /// 8-bit unsigned.
    U8,
    /// 16-bit unsigned (16-bit PNG).
    U16,
    /// 16-bit signed (int16 GeoTIFF).
    I16,
    /// 32-bit float.
    F32,
    /// 8-bit signed: the seed's signed-byte distance volumes, the baseline of IFS3D ratios.
    /// (Appended last so that the binary encoding of earlier files is unchanged.)
    I8,
}

impl SampleFormat {
    /// Bytes per sample of the source, the baseline of every compression ratio.
    pub fn bytes(self) -> usize {
        match self {
            SampleFormat::U8 | SampleFormat::I8 => 1,
            SampleFormat::U16 | SampleFormat::I16 => 2,
            SampleFormat::F32 => 4,
        }
    }
}

/// An affine georeference of a north-up grid (GeoTIFF ModelTiepoint + ModelPixelScale).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Georef {
    /// EPSG code of the coordinate reference system, when the file names one.
    pub epsg: Option<u32>,
    /// Coordinates of the outer top-left corner of pixel (0, 0).
    pub origin: [f64; 2],
    /// Size of a pixel in CRS units; y is negative for north-up grids.
    pub pixel_size: [f64; 2],
}

/// Figures the encoder measured, kept so that `info` and the server can report them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EncodeStats {
    /// Number of affine maps (ranges) over all channels.
    pub transforms: u64,
    /// RMS error of the decoded asset against the source, in value units, valid cells only.
    pub rmse: f64,
    /// PSNR in dB, peak = 255 for 8-bit images, the value range otherwise.
    pub psnr: f64,
    /// Largest absolute error, in value units.
    pub max_error: f64,
    /// Encoding wall time in seconds.
    pub seconds: f64,
}

/// Everything about an asset except its payload.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AssetMeta {
    /// What the asset depicts.
    pub kind: AssetKind,
    /// Width of the source grid in samples.
    pub width: u32,
    /// Height of the source grid in samples.
    pub height: u32,
    /// Channels of the source (1 grey or height, 3 colour).
    pub channels: u8,
    /// How channels map to colour.
    pub colour: ColourModel,
    /// The source's sample type.
    pub sample: SampleFormat,
    /// Units of the values (`m` for DEMs), when known.
    pub units: Option<String>,
    /// Value that the coded 0 stands for (min of the valid source values; 0 for 8-bit images).
    pub value_min: f64,
    /// Value that the coded 1 stands for (max of the valid source values; 255 for 8-bit images).
    pub value_max: f64,
    /// The nodata value of the source, answered where the mask says a cell had no data.
    pub nodata: Option<f64>,
    /// Where the grid lies on the Earth, when it does.
    pub georef: Option<Georef>,
    /// The encoder settings, human-readable, for provenance.
    pub encoder: String,
    /// What the encoder measured.
    pub stats: EncodeStats,
}

impl AssetMeta {
    /// Size of the source at its own sample type, the denominator-free baseline for ratios.
    /// Volumes are cubes: `width` samples a side (`height` equals it).
    pub fn source_bytes(&self) -> u64 {
        let depth = if self.kind == AssetKind::Volume {
            self.width as u64
        } else {
            1
        };
        self.width as u64
            * self.height as u64
            * depth
            * self.channels as u64
            * self.sample.bytes() as u64
    }

    /// Peak value for PSNR: 255 for 8-bit images, the value range for everything else.
    pub fn psnr_peak(&self) -> f64 {
        match (self.kind, self.sample) {
            (AssetKind::Image, SampleFormat::U8) => 255.0,
            (AssetKind::Image, SampleFormat::U16) => 65535.0,
            _ => (self.value_max - self.value_min).max(f64::MIN_POSITIVE),
        }
    }
}
