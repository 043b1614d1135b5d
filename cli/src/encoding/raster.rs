//! Rasters coded by the codec the arguments name: whole, or chunk by chunk into a file.

use std::path::Path;

use anyhow::{Result, bail};
use fractile_codec::codecs::fis::FisSettings;
use fractile_codec::codecs::psa::{Domains, PsaSettings};
use fractile_codec::encode::chunked::{encode_chunked_file, encode_chunked_file_at};
use fractile_codec::io::rows::Rows;
use fractile_codec::{EncodeSettings, Quantiser, Raster, RateMode, SearchMode, encode};

use super::args::{CodecArg, DomainsArg, EncodeArgs, Search, file_rate};
use crate::progress::Progress;

/// A raster coded in chunks of `c` into `output`: under a file's rate ([`file_rate`]) or each
/// chunk by the settings of `a` with its share of the rate.
pub(super) fn encode_chunks(
    a: &EncodeArgs,
    rows: &mut dyn Rows,
    c: u32,
    output: &Path,
) -> Result<fractile_codec::encode::Written> {
    let (width, height) = (rows.header().width, rows.header().height);
    let mut bar = Progress::start("coding chunks", a.quiet || a.json);
    let progress = |done: u64, total: u64| bar.update(done, total);
    let enc = match file_rate(a, rows.header().channels) {
        Some(rate) => {
            let at =
                |r: &Raster, q, trial| fractile_codec::encode::projected::encode_at(r, q, trial);
            encode_chunked_file_at(rows, c, (rate, &at), &progress, output)?
        }
        None => {
            let per_chunk = a.chunk_rate(width, height, c);
            let one = |r: &Raster| {
                encode_with(&per_chunk, r, false)
                    .map_err(|e| fractile_codec::Error::settings(e.to_string()))
            };
            encode_chunked_file(rows, c, &one, &progress, output)?
        }
    };
    bar.finish();
    Ok(enc)
}

/// `raster` coded by the codec `a` names (chunked or not, the same settings); `bar`: whether a
/// long quadtree encode shows its own progress bar (not for chunks, which share one).
pub(super) fn encode_with(
    a: &EncodeArgs,
    raster: &Raster,
    bar: bool,
) -> Result<fractile_codec::Encoded> {
    Ok(if a.codec() == CodecArg::QuadtreePifs {
        encode_quadtree(a, raster, bar)?
    } else if a.codec() == CodecArg::Projected {
        let settings = fractile_codec::codecs::projected::ProjectedSettings {
            max_error: a.max_error,
            bounded: a.bounded,
            ..Default::default()
        };
        fractile_codec::encode::projected::encode_projected(raster, &settings, a.target_bpp)?
    } else if let Some(tiling) = a.codec().psa_tiling() {
        let domains = match a.domains {
            DomainsArg::Touching => Domains::Touching,
            DomainsArg::Overlapping => Domains::Overlapping,
        };
        let settings = PsaSettings {
            tiling,
            domains,
            region: a.spacing,
            ratio: a.domain_ratio,
            radius: a.radius,
            max_scaling: a.max_contrast,
            ..PsaSettings::default()
        };
        fractile_codec::encode::encode_psa(raster, &settings, a.target_bpp)?
    } else {
        let Some(scaling) = a.codec().fis_scaling() else {
            bail!("--codec curve is for GeoJSON input");
        };
        let settings = FisSettings {
            scaling,
            spacing: a.spacing,
            height_step: a.height_step,
            scaling_bits: a.scaling_bits,
            max_scaling: a.max_contrast,
        };
        fractile_codec::encode::encode_fis(raster, &settings, a.target_bpp)?
    })
}

pub(crate) fn encode_quadtree(
    a: &EncodeArgs,
    raster: &Raster,
    show_bar: bool,
) -> Result<fractile_codec::Encoded> {
    let rate = match (a.target_bpp, a.tolerance, a.transforms, a.const_range) {
        (Some(b), ..) => RateMode::TargetBpp(b),
        (_, Some(t), ..) => RateMode::Tolerance(t),
        (_, _, Some(n), _) => RateMode::Transforms(n),
        (.., Some(r)) => RateMode::ConstRange(r),
        _ => RateMode::Tolerance(f32::NAN),
    };
    let preset = EncodeSettings::at_speed(a.speed)?;
    let candidates = match preset.search {
        SearchMode::Nearest(k) => a.candidates.unwrap_or(k),
        _ => a.candidates.unwrap_or(32),
    };
    let quantiser = Quantiser {
        contrast_bits: a.contrast_bits,
        offset_bits: a.offset_bits.unwrap_or(preset.quantiser.offset_bits),
        max_contrast: a.max_contrast,
        slope_bits: a
            .slope_bits
            .unwrap_or(EncodeSettings::default_slope_bits(raster.kind)),
    };
    // Bits the user gave are kept as given; otherwise the encoder weighs the kind's choices.
    let quantiser_choices = if a.offset_bits.is_none() && a.slope_bits.is_none() {
        EncodeSettings::default_quantiser_choices(raster.kind, quantiser)
    } else {
        Vec::new()
    };
    let settings = EncodeSettings {
        rate,
        min_range: a.min_range,
        max_range: a.max_range,
        domain_step: a.domain_step.unwrap_or(preset.domain_step),
        quantiser,
        quantiser_choices,
        search: match a.search {
            Search::Full => SearchMode::Full,
            Search::Classified => SearchMode::Classified,
            Search::Nearest => SearchMode::Nearest(candidates.max(1)),
        },
        rois: a.roi.clone(),
        attractor_passes: a.attractor_passes.unwrap_or(preset.attractor_passes),
        ..preset
    };
    let mut bar = Progress::start("fitting blocks", a.quiet || a.json || !show_bar);
    let progress = |done: u64, total: u64| bar.update(done, total);
    let enc = encode(raster, &settings, &progress)?;
    bar.finish();
    Ok(enc)
}
