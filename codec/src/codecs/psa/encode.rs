//! The piecewise self-affine model's encoder: the lattice pipeline (`codecs::lattice`) with
//! its domain search and fit.

use fractile_proto::AssetKind;

use crate::Error;
use crate::codecs::coded::PlaneEncoder;
use crate::codecs::coded::{Coded, Measure};
use crate::codecs::lattice::{Lattice, encode_lattice};
use crate::codecs::options::{Named, Options};
use crate::codecs::plane::Build;
use crate::codecs::psa::fit::fit;
use crate::codecs::psa::{PsaHeader, PsaSettings, Tiling, codec_name, encode_params};
use crate::core::metrics::Errors;
use crate::io::raster::Raster;

/// Encodes a grey image or a height field with the piecewise self-affine model
/// ([`crate::codecs::psa`]); `settings.target_bpp` picks the region size (see `encode_lattice`).
fn encode_psa(
    raster: &Raster,
    settings: &PsaSettings,
    measure: &dyn Measure,
) -> Result<(Coded, Errors), Error> {
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
        measure,
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
            Coded::new(m, vec![(header, stream)], mask, Build::Whole)
        },
    )
}

impl PlaneEncoder for PsaSettings {
    fn encode(
        &self,
        raster: &Raster,
        measure: &dyn Measure,
        _progress: &(dyn Fn(u64, u64) + Sync),
    ) -> Result<(Coded, Errors), Error> {
        encode_psa(raster, self, measure)
    }
}

impl Named for PsaSettings {
    const NAMES: &'static [(&'static str, &'static str)] = &[
        (
            "psa2d-rect",
            "Piecewise self-affine model, rectangular regions.",
        ),
        (
            "psa2d-tri",
            "Piecewise self-affine model, triangular regions.",
        ),
    ];
    const TAKES: &'static [&'static str] = &[
        "target-bpp",
        "spacing",
        "domains",
        "domain-ratio",
        "radius",
        "max-contrast",
    ];

    /// The tiling the name says, the defaults under the options given (`spacing`: the
    /// region's side).
    fn named(name: &str, o: &Options, _kind: AssetKind) -> Result<Self, Error> {
        let d = PsaSettings::default();
        Ok(PsaSettings {
            tiling: if name == codec_name(Tiling::Triangular) {
                Tiling::Triangular
            } else {
                Tiling::Rectangular
            },
            domains: o.domains.unwrap_or(d.domains),
            region: o.spacing.unwrap_or(d.region),
            ratio: o.domain_ratio.unwrap_or(d.ratio),
            radius: o.radius.unwrap_or(d.radius),
            max_scaling: o.max_contrast.unwrap_or(d.max_scaling),
            target_bpp: o.target_bpp,
            ..d
        })
    }
}
