//! What an encode returns and measured ([`Encoded`], [`Written`]), and the [`Measure`] that
//! `encode` lends a plane codec's encoder: its planes decoded as a reader decodes them, and
//! the source-error map of the file it keeps.

use std::time::Instant;

use fractile_proto::EncodeStats;

use crate::Error;
use crate::codecs::coded::{Coded, Measure};
use crate::core::metrics::Errors;
use crate::io::asset::Asset;
use crate::io::raster::Raster;

use super::fidelity;

/// What an encode produced and measured.
#[derive(Clone, Debug)]
pub struct Encoded {
    /// The asset (also holds the stats in its metadata).
    pub asset: Asset,
    /// The file's bytes.
    pub bytes: Vec<u8>,
    /// Errors of the decoded asset against the source (valid cells, source units).
    pub errors: Errors,
    /// Ranges over all planes.
    pub transforms: usize,
    /// Wall time in seconds.
    pub seconds: f64,
}

impl Encoded {
    /// The asset with `lineage` (what was done to its inputs, [`crate::rows::Header`]'s) said
    /// after its encoder line, as a chunked file says it.
    pub fn with_lineage(mut self, lineage: Option<&str>) -> Encoded {
        if let Some(l) = lineage {
            self.asset.meta.encoder = format!("{}; {l}", self.asset.meta.encoder);
            self.bytes = self.asset.to_bytes();
        }
        self
    }

    /// Bits per source pixel of the whole file.
    pub fn bpp(&self) -> f64 {
        bpp(&self.asset.meta, self.bytes.len() as u64)
    }

    /// Source bytes (at the source's sample type) over file bytes.
    pub fn ratio(&self) -> f64 {
        self.asset.meta.source_bytes() as f64 / self.bytes.len() as f64
    }

    /// Writes the file to `path` atomically; keeps what was measured. A file that readers
    /// under the default limits would refuse (a large raster in one piece) is not written:
    /// what one reader (the CLI, Python) writes, every reader opens.
    pub fn write(self, path: &std::path::Path) -> Result<Written, Error> {
        crate::io::asset::check_opens(&self.bytes, &crate::AssetLimits::default()).map_err(
            |e| {
                Error::settings(format!(
                    "not written: readers would refuse it ({e}); encode it in chunks (--chunk \
                     1024, Python's chunk=1024)"
                ))
            },
        )?;
        crate::io::asset::write_atomic(path, &self.bytes)?;
        Ok(Written {
            length: self.bytes.len() as u64,
            asset: self.asset,
            errors: self.errors,
            transforms: self.transforms,
            seconds: self.seconds,
        })
    }
}

/// What an encode wrote to a file and measured: [`Encoded::write`], or a chunked encode
/// streamed to disk ([`super::chunked::encode_chunked_file`]), whose bytes were never all in memory.
#[derive(Clone, Debug)]
pub struct Written {
    /// The asset (a chunked one as opened from the file: its header, chunks on demand).
    pub asset: Asset,
    /// The file's length in bytes.
    pub length: u64,
    /// Errors of the decoded asset against the source (a chunked one's: its source level's
    /// chunks over their coded cells).
    pub errors: Errors,
    /// Ranges over all planes (a chunked one's: over its source level's chunks).
    pub transforms: usize,
    /// Wall time in seconds.
    pub seconds: f64,
}

impl Written {
    /// Bits per source pixel of the whole file.
    pub fn bpp(&self) -> f64 {
        bpp(&self.asset.meta, self.length)
    }

    /// Source bytes (at the source's sample type) over file bytes.
    pub fn ratio(&self) -> f64 {
        self.asset.meta.source_bytes() as f64 / self.length as f64
    }
}

pub(crate) fn bpp(meta: &fractile_proto::AssetMeta, length: u64) -> f64 {
    length as f64 * 8.0 / (f64::from(meta.width) * f64::from(meta.height))
}

/// What `encode` lends a plane codec's encoder ([`Measure`]): the decode of its planes as a
/// reader of the file makes it, and the measures of the file it keeps, timed from the start of
/// the encode.
pub(crate) struct Context {
    /// When the encode started.
    pub(crate) start: Instant,
}

impl Context {
    /// A context for an encode starting now.
    pub(crate) fn new() -> Context {
        Context {
            start: Instant::now(),
        }
    }

    /// What the encode returns: the asset of the kept planes, its bytes and what was measured.
    pub(crate) fn encoded(&self, coded: Coded, errors: Errors) -> Result<Encoded, Error> {
        let transforms = coded.transforms();
        let asset = Asset::from_planes(coded)?;
        let bytes = asset.to_bytes();
        Ok(Encoded {
            asset,
            bytes,
            errors,
            transforms,
            seconds: self.start.elapsed().as_secs_f64(),
        })
    }
}

impl Measure for Context {
    fn decoded(&self, coded: Coded) -> (Coded, Vec<Vec<f32>>) {
        let asset = Asset::holding(coded);
        let (decoded, _) = asset.decode_native();
        (asset.into_planes(), decoded.channels)
    }

    fn kept(&self, coded: Coded, source: &Raster, errors: &Errors) -> Coded {
        let transforms = coded.transforms();
        let mut asset = Asset::holding(coded);
        // Its share of the operator's bytes (set aside under a target size, see `encode`).
        let budget = crate::core::fidelity::reserve(asset.file_size());
        asset.source_error = Some(fidelity::measure(&asset, source, budget));
        asset.meta.stats = EncodeStats {
            transforms: transforms as u64,
            rmse: errors.rmse,
            psnr: errors.psnr,
            max_error: errors.max_error,
            seconds: self.start.elapsed().as_secs_f64(),
        };
        asset.into_planes()
    }
}
