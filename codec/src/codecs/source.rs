//! The source side of every plane encoder, below the codecs that share it: a raster's planes
//! over its value range (luma and half-resolution chroma for colour), its metadata, nodata
//! filled for coding, and the share of a target size the source-error map takes.

use fractile_proto::{AssetKind, AssetMeta, ColourModel, EncodeStats, SampleFormat};

use crate::io::raster::Raster;
use crate::render::colour::rgb_to_ycbcr;

/// A source channel, normalised, before padding: values, validity, and its extent in source
/// pixels per plane sample (1 for full resolution, 2 for chroma).
pub(crate) struct SourcePlane {
    pub(crate) width: usize,
    pub(crate) height: usize,
    pub(crate) values: Vec<f32>,
    pub(crate) valid: Vec<bool>,
    /// The source's extent in plane samples (w / 2 for chroma: odd sizes end mid-sample).
    pub(crate) extent: [f32; 2],
}

/// The value range coded as [0, 1]: the sample type's for images, the data's for height fields
/// (widened to 1 unit when flat).
pub(crate) fn coding_range(raster: &Raster) -> (f64, f64) {
    match (raster.kind, raster.sample) {
        (AssetKind::Image, SampleFormat::U8) => (0.0, 255.0),
        (AssetKind::Image, SampleFormat::U16) => (0.0, 65535.0),
        _ => {
            let (lo, hi) = raster.value_range();
            (lo, if hi > lo { hi } else { lo + 1.0 })
        }
    }
}

/// The raster's planes normalised to [0, 1] over its value range (luma and half-resolution
/// chroma for colour), with the range and the colour model.
pub(crate) fn source_planes(raster: &Raster) -> (f64, f64, ColourModel, Vec<SourcePlane>) {
    let (w, h) = (raster.width, raster.height);
    let (lo, hi) = coding_range(raster);
    let span = (hi - lo) as f32;
    let valid = raster.valid.clone().unwrap_or_else(|| vec![true; w * h]);
    let norm = |v: &[f32]| -> Vec<f32> {
        v.iter()
            .map(|&x| ((x - lo as f32) / span).clamp(0.0, 1.0))
            .collect()
    };
    let colour = raster.colour();
    let sources: Vec<SourcePlane> = match colour {
        ColourModel::Grey => vec![SourcePlane {
            width: w,
            height: h,
            values: norm(&raster.channels[0]),
            valid: valid.clone(),
            extent: [w as f32, h as f32],
        }],
        ColourModel::YCbCr => {
            let [y, cb, cr] = rgb_to_ycbcr(&raster.channels, hi as f32);
            let full = SourcePlane {
                width: w,
                height: h,
                values: norm(&y),
                valid: valid.clone(),
                extent: [w as f32, h as f32],
            };
            let half = |c: &[f32]| halve(&norm(c), &valid, w, h);
            vec![full, half(&cb), half(&cr)]
        }
    };
    (lo, hi, colour, sources)
}

/// Halves a normalised plane (box average of valid cells) for chroma.
pub(crate) fn halve(values: &[f32], valid: &[bool], w: usize, h: usize) -> SourcePlane {
    let (hw, hh) = (w.div_ceil(2), h.div_ceil(2));
    let mut out = vec![0.0f32; hw * hh];
    let mut ok = vec![false; hw * hh];
    for y in 0..hh {
        for x in 0..hw {
            let (mut s, mut n) = (0.0, 0.0);
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (sx, sy) = (2 * x + dx, 2 * y + dy);
                if sx < w && sy < h && valid[sy * w + sx] {
                    s += values[sy * w + sx];
                    n += 1.0;
                }
            }
            if n > 0.0 {
                out[y * hw + x] = s / n;
                ok[y * hw + x] = true;
            }
        }
    }
    SourcePlane {
        width: hw,
        height: hh,
        values: out,
        valid: ok,
        extent: [w as f32 / 2.0, h as f32 / 2.0],
    }
}

/// The asset's metadata, before the encoder's measurements.
pub(crate) fn source_meta(
    raster: &Raster,
    encoder: String,
    (lo, hi): (f64, f64),
    colour: ColourModel,
) -> AssetMeta {
    let (w, h) = (raster.width, raster.height);
    AssetMeta {
        kind: raster.kind,
        width: w as u32,
        height: h as u32,
        channels: raster.channels.len() as u8,
        colour,
        sample: raster.sample,
        units: raster.units.clone(),
        value_min: lo,
        value_max: hi,
        nodata: raster.nodata,
        georef: raster.georef.clone(),
        encoder,
        stats: EncodeStats::default(),
    }
}

/// Of a target of `bytes`, what the operator may take: the rest is the source-error map's
/// (whose budget, a share of the operator's size, then fits in it).
pub(crate) fn without_map(bytes: usize) -> usize {
    (bytes as f64 / (1.0 + crate::core::fidelity::SHARE)).floor() as usize
        - crate::core::fidelity::reserve(0).min(bytes / 64)
}

/// Push-pull fill of invalid cells from the valid ones.
pub(crate) fn fill_invalid(values: &mut [f32], valid: &[bool], w: usize, h: usize) {
    if valid.iter().all(|&v| v) {
        return;
    }
    // Level 0: (sum, weight) per cell; each coarser level sums 2x2 children.
    // (width, height, (sum, weight) per cell) per level.
    type Level = (usize, usize, Vec<(f32, f32)>);
    let mut levels: Vec<Level> = vec![(
        w,
        h,
        values
            .iter()
            .zip(valid)
            .map(|(&v, &ok)| if ok { (v, 1.0) } else { (0.0, 0.0) })
            .collect(),
    )];
    while levels.last().is_some_and(|(lw, lh, _)| *lw > 1 || *lh > 1) {
        let (lw, lh, cells) = levels.last().expect("non-empty");
        let (nw, nh) = (lw.div_ceil(2), lh.div_ceil(2));
        let mut next = vec![(0.0f32, 0.0f32); nw * nh];
        for y in 0..*lh {
            for x in 0..*lw {
                let c = cells[y * lw + x];
                let n = &mut next[(y / 2) * nw + x / 2];
                n.0 += c.0;
                n.1 += c.1;
            }
        }
        levels.push((nw, nh, next));
    }
    // Pull: every cell without weight takes its parent's mean.
    for li in (0..levels.len() - 1).rev() {
        let (upper, lower) = levels.split_at_mut(li + 1);
        let (lw, lh, cells) = &mut upper[li];
        let (pw, _, parents) = &lower[0];
        for y in 0..*lh {
            for x in 0..*lw {
                let c = &mut cells[y * *lw + x];
                if c.1 == 0.0 {
                    let p = parents[(y / 2) * pw + x / 2];
                    *c = (p.0 / p.1.max(1e-20), 1.0);
                } else {
                    *c = (c.0 / c.1, 1.0);
                }
            }
        }
    }
    for (i, v) in values.iter_mut().enumerate() {
        if !valid[i] {
            *v = levels[0].2[i].0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fill_invalid_interpolates_from_neighbours() {
        let (w, h) = (8, 8);
        let mut v: Vec<f32> = (0..64).map(|i| (i % 8) as f32).collect();
        let mut valid = vec![true; 64];
        for i in [9, 10, 17, 18, 63] {
            valid[i] = false;
            v[i] = 1000.0;
        }
        fill_invalid(&mut v, &valid, w, h);
        for i in [9, 10, 17, 18, 63] {
            assert!((0.0..=7.0).contains(&v[i]), "cell {i} filled with {}", v[i]);
        }
    }
}
