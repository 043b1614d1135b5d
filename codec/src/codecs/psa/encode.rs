//! The piecewise self-affine model's encoder: the lattice pipeline (`encode::lattice`) with
//! its domain search and fit.

use crate::Error;
use crate::codecs::psa::fit::fit;
use crate::codecs::psa::{PsaHeader, PsaSettings, codec_name, encode_params};
use crate::encode::lattice::{Lattice, encode_lattice};
use crate::encode::source::{Encoded, PlaneEncoder};
use crate::io::asset::Asset;
use crate::io::raster::Raster;

/// Encodes a grey image or a height field with the piecewise self-affine model
/// ([`crate::codecs::psa`]); `settings.target_bpp` picks the region size (see `encode_lattice`).
pub fn encode_psa(raster: &Raster, settings: &PsaSettings) -> Result<Encoded, Error> {
    if !(settings.max_scaling > 0.0 && settings.max_scaling < 1.0) {
        return Err(Error::settings("max scaling must be in (0, 1)"));
    }
    let lattice = Lattice {
        spacing: settings.region,
        height_step: None,
        target_bpp: settings.target_bpp,
    };
    encode_lattice(
        raster,
        &lattice,
        |source, region, height_step, meta, mask, _budget| {
            let header = PsaHeader {
                samples: [source.width as u32, source.height as u32],
                region,
                ratio: settings.ratio,
                tiling: settings.tiling,
                domains: settings.domains,
                radius: settings.radius,
                height_step,
                scaling_bits: settings.scaling_bits,
                max_scaling: settings.max_scaling,
            };
            let params = fit(source, &header)?;
            let stream = encode_params(&header, &params);
            let mut m = meta.clone();
            m.encoder = format!(
                "{} spacing={region} ratio={} domains={:?} radius={} height_step={}",
                codec_name(settings.tiling),
                settings.ratio,
                settings.domains,
                settings.radius,
                height_step as f64 * (meta.value_max - meta.value_min)
            );
            Asset::from_coded(m, vec![(header, stream)], mask)
        },
    )
}

impl PlaneEncoder for PsaSettings {
    fn encode(
        &self,
        raster: &Raster,
        _progress: &(dyn Fn(u64, u64) + Sync),
    ) -> Result<Encoded, Error> {
        encode_psa(raster, self)
    }
}
