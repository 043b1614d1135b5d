//! The fractal interpolation surfaces' encoder: the lattice pipeline (`codecs::lattice`) with
//! the collage fit of node heights and scalings, and the scalings' shrink measured.

use fractile_proto::AssetKind;

use crate::Error;
use crate::codecs::coded::PlaneEncoder;
use crate::codecs::coded::{Coded, Measure};
use crate::codecs::fis::fit::fit;
use crate::codecs::fis::{
    FisHeader, FisParams, FisSettings, codec_name, encode_params, scaling_of_codec,
};
use crate::codecs::lattice::{Lattice, encode_lattice};
use crate::codecs::options::{Named, Options};
use crate::codecs::plane::Build;
use crate::core::metrics::Errors;
use crate::io::raster::Raster;

/// Encodes a height field as a fractal interpolation surface ([`crate::codecs::fis`]).
/// `settings.target_bpp`, when given, overrides `settings.spacing` (and the automatic height step); see
/// `encode_lattice`.
fn encode_fis(
    raster: &Raster,
    settings: &FisSettings,
    measure: &dyn Measure,
) -> Result<(Coded, Errors), Error> {
    if raster.kind != AssetKind::HeightField {
        return Err(Error::settings(
            "fractal interpolation surfaces code height fields (use quadtree-pifs or psa2d for \
             images)",
        ));
    }
    if !(settings.max_scaling > 0.0 && settings.max_scaling < 1.0) {
        return Err(Error::settings("max scaling must be in (0, 1)"));
    }
    let lattice = Lattice {
        spacing: settings.spacing,
        height_step: settings.height_step,
        target_bpp: settings.target_bpp,
    };
    encode_lattice(
        raster,
        &lattice,
        measure,
        |source, spacing, height_step, meta, mask, budget| {
            let header = FisHeader {
                samples: [source.width as u32, source.height as u32],
                spacing,
                scaling: settings.scaling,
                height_step,
                scaling_bits: settings.scaling_bits,
                max_scaling: settings.max_scaling,
            };
            let fitted = fit(source, &header)?;
            let mut m = meta.clone();
            m.encoder = format!(
                "{} spacing={spacing} height_step={} scaling_bits={} max_scaling={}",
                codec_name(settings.scaling),
                height_step as f64 * (meta.value_max - meta.value_min),
                settings.scaling_bits,
                settings.max_scaling
            );
            // The fit minimises the collage error, not the attractor's: on rough terrain the
            // collage-optimal scalings can make the decoded surface worse than plain bilinear
            // interpolation of the nodes (fis-bilinear on etopo20 at spacing 2: 30 dB against
            // 40), and they cost bits. So every s is shrunk by one of these factors (1: the fit
            // as is; 0: bilinear), measured, not guessed: under a byte budget (rate control) the
            // best PSNR that fits (else the smallest, which tells rate control nothing fits:
            // the all-zero scalings are the cheapest, so "fits" grows with the step as the
            // bisection needs); otherwise the least `SSE + mu * bits`, `mu` the rate-distortion
            // slope of the node heights' own quantiser (a halved step costs a bit a node and
            // saves 3/4 of `step^2 / 12` on each of the ~k^2 samples a node weighs on).
            let (lo, span) = (meta.value_min, meta.value_max - meta.value_min);
            let step = f64::from(height_step) * span;
            let mu = 0.75 * step * step / 12.0 * f64::from(spacing * spacing) * 4.0 / 9.0;
            let mut best: Option<(f64, Coded)> = None;
            for shrink in [1.0f32, 0.75, 0.5, 0.25, 0.0] {
                let params = FisParams {
                    heights: fitted.heights.clone(),
                    scalings: fitted
                        .scalings
                        .iter()
                        .map(|&q| header.scaling_index(shrink * header.scaling_of(q)))
                        .collect(),
                };
                let stream = encode_params(&header, &params);
                let planes = vec![(header.clone(), stream)];
                let a = Coded::new(m.clone(), planes, mask.clone(), Build::Whole)?;
                let (a, decoded) = measure.decoded(a);
                let sse: f64 = decoded[0]
                    .iter()
                    .zip(source.values)
                    .filter(|(z, _)| z.is_finite())
                    .map(|(&z, &v)| (f64::from(z) - (lo + f64::from(v) * span)).powi(2))
                    .sum();
                let size = a.file_size();
                let cost = match budget {
                    // Fitting candidates by error; the others after them, by size.
                    Some(b) if size <= b => sse,
                    Some(_) => f64::MAX / 2.0 + size as f64,
                    None => sse + mu * 8.0 * size as f64,
                };
                if best.as_ref().is_none_or(|(b, _)| cost < *b) {
                    best = Some((cost, a));
                }
                if params.scalings.iter().all(|&q| q == 0) {
                    break; // a smaller shrink gives the same surface
                }
            }
            Ok(best.expect("one candidate at least").1)
        },
    )
}

impl PlaneEncoder for FisSettings {
    fn encode(
        &self,
        raster: &Raster,
        measure: &dyn Measure,
        _progress: &(dyn Fn(u64, u64) + Sync),
    ) -> Result<(Coded, Errors), Error> {
        encode_fis(raster, self, measure)
    }
}

impl Named for FisSettings {
    const NAMES: &'static [(&'static str, &'static str)] = &[
        (
            "fis-bilinear",
            "Fractal interpolation surface, s per node (Wu and Zhou).",
        ),
        ("fis-rect", "Fractal interpolation surface, s per cell."),
        (
            "fis-rect-global",
            "Fractal interpolation surface, one s (Drakopoulos and Manousopoulos).",
        ),
    ];
    const TAKES: &'static [&'static str] = &[
        "target-bpp",
        "spacing",
        "height-step",
        "scaling-bits",
        "max-contrast",
    ];

    /// The layout of s the name says, the defaults under the options given.
    fn named(name: &str, o: &Options, _kind: AssetKind) -> Result<Self, Error> {
        let d = FisSettings::default();
        Ok(FisSettings {
            scaling: scaling_of_codec(name).unwrap_or(d.scaling),
            spacing: o.spacing.unwrap_or(d.spacing),
            height_step: o.height_step,
            scaling_bits: o.scaling_bits.unwrap_or(d.scaling_bits),
            max_scaling: o.max_contrast.unwrap_or(d.max_scaling),
            target_bpp: o.target_bpp,
        })
    }
}
