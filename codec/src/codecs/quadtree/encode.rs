//! The quadtree encoder: a [`Raster`] becomes coded planes ([`Coded`]).
//!
//! Flow: normalise values to [0, 1] -> colour to YCbCr (chroma at half resolution) -> fill nodata
//! (push-pull) and pad to the frame (edge replication; padding and nodata weigh 0 in every fit)
//! -> fit every block of every size ([`Pyramid`]) -> choose the partition (tolerance, N ranges,
//! const range, or a target rate by bisection) -> entropy code -> decode once to report the real
//! error.

use fractile_proto::AssetMeta;

use crate::Error;
use crate::codecs::coded::PlaneEncoder;
use crate::codecs::coded::{Coded, Measure};
use crate::codecs::plane::Build;
use crate::codecs::quadtree::partition::{
    Limits, Partition, Pyramid, greedy_order, partitions_after,
};
use crate::codecs::quadtree::search::{CodingPlane, SearchMode};
use crate::codecs::quadtree::settings::{QuadtreeSettings, RateMode};
use crate::codecs::quadtree::stream::{PlaneHeader, encode_plane};
use crate::codecs::registry::PlaneOperator;
use crate::codecs::source::{SourcePlane, fill_invalid, source_meta, source_planes, without_map};
use crate::core::decode::{self, DiscreteOptions};
use crate::core::metrics::Errors;
use crate::core::transform::Quantiser;
use crate::io::mask::Mask;
use crate::io::raster::Raster;

/// Owned form of [`Limits`].
type BoxedLimits = Box<dyn Fn(usize, usize, usize) -> (f32, usize) + Sync>;

/// Encodes a raster. `progress(done, total)` is called as blocks are fitted.
pub(crate) fn encode(
    raster: &Raster,
    settings: &QuadtreeSettings,
    measure: &dyn Measure,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<(Coded, Errors), Error> {
    settings.validate()?;
    let (w, h) = (raster.width, raster.height);
    let (lo, hi, colour, sources) = source_planes(raster);
    let span = (hi - lo) as f32;

    // Frame geometry shared by every plane.
    let (min_size, levels, supersample, narrow) = frame_levels(settings, w, h);
    let planes: Vec<CodingPlane> = sources
        .iter()
        .map(|s| coding_plane(s, min_size as usize, supersample))
        .collect();
    // headers_by_quantiser[q][plane]
    let headers_by_quantiser = plane_headers(settings, &planes, min_size, levels);
    let headers = &headers_by_quantiser[0];

    // Every attractor pass searches again, as long as the first search.
    let total: u64 =
        headers.iter().map(Pyramid::work).sum::<u64>() * (1 + u64::from(settings.attractor_passes));
    let done = std::sync::atomic::AtomicU64::new(0);
    let tick = |k: u64| {
        let d = done.fetch_add(k, std::sync::atomic::Ordering::Relaxed) + k;
        if d.is_multiple_of(256) || d == total {
            progress(d, total);
        }
    };
    // Limits per plane: tolerance (normalised) and smallest size for a block in frame coordinates.
    let limit_fns = plane_limits(settings, &planes, w, span, narrow);
    let limits: Vec<Limits> = limit_fns.iter().map(|f| f.as_ref() as Limits).collect();
    // Chroma planes are a quarter of the pixels: weighed by their share and the setting.
    let weights: Vec<f32> = (0..planes.len())
        .map(|i| {
            if i == 0 {
                1.0
            } else {
                4.0 * settings.chroma_weight
            }
        })
        .collect();

    let mask = raster.valid.as_ref().map(|v| Mask::new(w, h, v.clone()));
    let meta = source_meta(raster, settings.describe(), (lo, hi), colour);
    // The metadata of an asset coded with quantiser `q`: its description names `q` (and its
    // length is part of the size rate control fits).
    let meta_for = |q: Quantiser| AssetMeta {
        encoder: QuadtreeSettings {
            quantiser: q,
            ..settings.clone()
        }
        .describe(),
        ..meta.clone()
    };
    // What rate control fits: the target less the source-error map's share.
    let target_bytes = settings.target_bytes(w * h).map(without_map);
    // The partition the rate mode asks for, from one set of fits.
    let choose = |pyramids: &[Pyramid]| -> Result<Vec<Partition>, Error> {
        let meta = meta_for(pyramids[0].header.quantiser);
        // The size alone (no stream decoding, no operator). The stats `measured` fills in
        // later are fixed-width fields, so the final file has exactly this size.
        let file_size = |parts: &[Partition]| {
            Coded::file_size_of(&meta, code_planes(pyramids, parts), mask.as_ref())
        };
        let max_bytes = target_bytes.unwrap_or(usize::MAX);
        partitions_for(
            settings,
            pyramids,
            (&limits, &weights),
            max_bytes,
            &file_size,
        )
    };
    let build = |pyramids: &[Pyramid]| -> Result<Coded, Error> {
        Coded::new(
            meta_for(pyramids[0].header.quantiser),
            code_planes(pyramids, &choose(pyramids)?),
            mask.clone(),
            Build::Whole,
        )
    };
    // One search per plane serves every quantiser, with domains read from `avg2[plane]`; rate
    // control runs for each. Under a target size every quantiser's asset fits it: the one that
    // decodes closest to the source wins (the settings' own on a tie).
    let weigh = |avg2: &[Vec<f32>]| -> Result<(Coded, Errors), Error> {
        let pyramids_by_quantiser =
            search_planes(&planes, avg2, &headers_by_quantiser, settings.search, &tick);
        let mut weighed: Option<(Coded, Errors)> = None;
        for pyramids in &pyramids_by_quantiser {
            let (asset, errors) = build(pyramids)?.errors(raster, measure);
            let better = weighed
                .as_ref()
                .is_none_or(|(best, e)| preferred((&asset, &errors), (best, e), target_bytes));
            if better {
                weighed = Some((asset, errors));
            }
        }
        Ok(weighed.expect("at least the settings' own quantiser"))
    };
    let own_domains: Vec<Vec<f32>> = planes.iter().map(CodingPlane::average2).collect();
    let (latest, errors) = weigh(&own_domains)?;
    if settings.attractor_passes == 0 {
        progress(total, total);
        return Ok((measure.kept(latest, raster, &errors), errors));
    }
    // A pass must not buy its quality with bytes the user did not grant: under a target size
    // any asset within it will do; otherwise it may be no larger than the first.
    let max_size = target_bytes.unwrap_or(latest.file_size());
    let passes = settings.attractor_passes;
    let (best, best_errors) =
        attractor_passes(&planes, (latest, errors), passes, max_size, &weigh)?;
    progress(total, total);
    Ok((measure.kept(best, raster, &best_errors), best_errors))
}

/// One search with the given domains per plane, under every quantiser: the asset that decodes
/// closest to the source, and its errors.
type Weigh<'a> = dyn Fn(&[Vec<f32>]) -> Result<(Coded, Errors), Error> + 'a;

/// Searches `passes` more times with domains read from the latest asset's decoded attractor
/// instead of the source, and keeps the asset that decodes closest to the source within
/// `max_size` bytes (the first on a tie).
fn attractor_passes(
    planes: &[CodingPlane],
    first: (Coded, Errors),
    passes: u32,
    max_size: usize,
    weigh: &Weigh,
) -> Result<(Coded, Errors), Error> {
    let (mut latest, mut best_errors) = first;
    let mut best = latest.clone();
    for _ in 0..passes {
        let domains: Vec<Vec<f32>> = planes
            .iter()
            .zip(&latest.planes)
            .map(|(p, coded)| attractor(p, &coded.operator))
            .collect();
        let errors;
        (latest, errors) = weigh(&domains)?;
        if errors.rmse < best_errors.rmse && latest.file_size() <= max_size {
            best = latest.clone();
            best_errors = errors;
        }
    }
    Ok((best, best_errors))
}

/// The plane headers of every quantiser weighed (`[quantiser][plane]`): the settings' own,
/// then its choices under a target size.
fn plane_headers(
    settings: &QuadtreeSettings,
    planes: &[CodingPlane],
    min_size: u32,
    levels: u32,
) -> Vec<Vec<PlaneHeader>> {
    let quantisers: Vec<Quantiser> = std::iter::once(settings.quantiser)
        .chain(match settings.rate {
            RateMode::TargetBpp(_) => settings.quantiser_choices.clone(),
            _ => Vec::new(),
        })
        .collect();
    quantisers
        .iter()
        .map(|&quantiser| {
            planes
                .iter()
                .map(|p| PlaneHeader {
                    frame: [p.width as u32, p.height as u32],
                    valid: p.valid,
                    min_size,
                    levels,
                    domain_steps: (0..levels)
                        .map(|l| {
                            (((min_size << l) as f32 * settings.domain_step).round() as u32).max(1)
                        })
                        .collect(),
                    quantiser,
                })
                .collect()
        })
        .collect()
}

/// The partitions the rate mode asks for, from one set of fits (`[plane]`), with each plane's
/// limits and weight; under a target size, the best whose file (`file_size`) fits `max_bytes`.
fn partitions_for(
    settings: &QuadtreeSettings,
    pyramids: &[Pyramid],
    (limits, weights): (&[Limits], &[f32]),
    max_bytes: usize,
    file_size: &dyn Fn(&[Partition]) -> usize,
) -> Result<Vec<Partition>, Error> {
    let pyr_refs: Vec<&Pyramid> = pyramids.iter().collect();
    Ok(match settings.rate {
        RateMode::ConstRange(_) => pyramids.iter().map(Partition::whole_level).collect(),
        RateMode::Tolerance(_) => pyramids
            .iter()
            .zip(limits)
            .map(|(p, l)| Partition::by_tolerance(p, *l))
            .collect(),
        RateMode::Transforms(n) => {
            let (initial, order) = greedy_order(&pyr_refs, weights, limits);
            partitions_after(&pyr_refs, &order, n.saturating_sub(initial).div_ceil(3))
        }
        RateMode::TargetBpp(_) => {
            let at = |lambda: f32| -> Vec<Partition> {
                pyramids
                    .iter()
                    .zip(limits)
                    .zip(weights)
                    .map(|((p, l), &wt)| Partition::by_lagrangian(p, lambda, wt, *l))
                    .collect()
            };
            at(smallest_lambda(
                |lambda| Ok(file_size(&at(lambda))),
                max_bytes,
            )?)
        }
    })
}

/// Each plane's header and coded stream under its partition.
fn code_planes(pyramids: &[Pyramid], parts: &[Partition]) -> Vec<(PlaneHeader, Vec<u8>)> {
    pyramids
        .iter()
        .zip(parts)
        .map(|(p, part)| {
            (
                p.header.clone(),
                encode_plane(&p.header, &|l, bx, by| part.decide(p, l, bx, by)),
            )
        })
        .collect()
}

/// One search per plane, fitted under every quantiser's header (`[quantiser][plane]`), with
/// domains read from `avg2[plane]`.
fn search_planes(
    planes: &[CodingPlane],
    avg2: &[Vec<f32>],
    headers_by_quantiser: &[Vec<PlaneHeader>],
    search: SearchMode,
    tick: &(dyn Fn(u64) + Sync),
) -> Vec<Vec<Pyramid>> {
    let mut pyramids_by_quantiser: Vec<Vec<Pyramid>> =
        headers_by_quantiser.iter().map(|_| Vec::new()).collect();
    for (i, (p, domains)) in planes.iter().zip(avg2).enumerate() {
        let each: Vec<PlaneHeader> = headers_by_quantiser.iter().map(|h| h[i].clone()).collect();
        let built = Pyramid::build_each(p, domains, &each, search, tick);
        for (q, pyramid) in built.into_iter().enumerate() {
            pyramids_by_quantiser[q].push(pyramid);
        }
    }
    pyramids_by_quantiser
}

/// The smallest range, the number of range sizes, whether to supersample (quasi-lossless), and
/// the largest power of two that fits half the raster's short side.
fn frame_levels(settings: &QuadtreeSettings, w: usize, h: usize) -> (u32, u32, bool, u32) {
    let roi_min = settings
        .rois
        .iter()
        .filter_map(|r| r.min_range)
        .min()
        .unwrap_or(settings.min_range);
    let half = (w.min(h) / 2).max(1) as u32;
    let narrow = 1u32 << (31 - half.leading_zeros()); // largest power of two <= half
    let (min_size, levels, supersample) = match settings.rate {
        RateMode::ConstRange(1) => (2u32, 1u32, true),
        RateMode::ConstRange(r) => (r, 1, false),
        _ => {
            // Narrow inputs (a 3 x 1000 strip) cannot hold a domain of twice the smallest range:
            // shrink the smallest range until one fits, down to single samples.
            let m = settings.min_range.min(roi_min).min(narrow);
            (
                m,
                settings.max_range.max(m).trailing_zeros() - m.trailing_zeros() + 1,
                false,
            )
        }
    };
    (min_size, levels, supersample, narrow)
}

/// Per plane, the tolerance (normalised) and smallest range for a block at (x, y) of side n in
/// frame coordinates: the plane's own, tightened inside regions of interest.
fn plane_limits(
    settings: &QuadtreeSettings,
    planes: &[CodingPlane],
    w: usize,
    span: f32,
    narrow: u32,
) -> Vec<BoxedLimits> {
    let base_tol = match settings.rate {
        RateMode::Tolerance(t) if t.is_nan() => 0.02,
        RateMode::Tolerance(t) => t / span,
        _ => 1.0,
    };
    let chroma_tol = 1.0 / settings.chroma_weight.max(1e-3).sqrt();
    planes
        .iter()
        .enumerate()
        .map(|(i, p)| {
            // Frame samples per source pixel.
            let k = p.valid[0] / w as f32;
            let plane_tol = base_tol * if i > 0 { chroma_tol } else { 1.0 };
            let rois: Vec<([f32; 4], f32, usize)> = settings
                .rois
                .iter()
                .map(|r| {
                    (
                        r.rect.map(|v| v * k),
                        (r.tolerance / span).min(plane_tol),
                        r.min_range.unwrap_or(settings.min_range) as usize,
                    )
                })
                .collect();
            let global_min = settings.min_range.min(narrow) as usize;
            let f: BoxedLimits = Box::new(move |x, y, n| {
                let (x0, y0, x1, y1) = (x as f32, y as f32, (x + n) as f32, (y + n) as f32);
                let (mut tol, mut min) = (plane_tol, global_min);
                for &(r, t, m) in &rois {
                    if x0 < r[2] && x1 > r[0] && y0 < r[3] && y1 > r[1] {
                        tol = tol.min(t);
                        min = min.min(m);
                    }
                }
                (tol, min)
            });
            f
        })
        .collect()
}

/// The smallest lambda (best quality) whose file fits `max_bytes`: bisection on log(lambda);
/// the size falls as lambda grows.
fn smallest_lambda(
    size_at: impl Fn(f32) -> Result<usize, Error>,
    max_bytes: usize,
) -> Result<f32, Error> {
    let (mut lo_l, mut hi_l) = (-30.0f32, 10.0f32);
    if size_at(lo_l.exp2())? <= max_bytes {
        hi_l = lo_l;
    } else {
        for _ in 0..28 {
            let mid = 0.5 * (lo_l + hi_l);
            if size_at(mid.exp2())? <= max_bytes {
                hi_l = mid
            } else {
                lo_l = mid
            }
        }
    }
    Ok(hi_l.exp2())
}

/// The 2x2 means ([`CodingPlane::average2`]) of a plane's decoded attractor over its whole
/// frame: what the decoder's domains read. Discrete decoding covers the source extent; the
/// padding beyond it repeats the edge, as the encoder pads the source.
fn attractor(plane: &CodingPlane, op: &PlaneOperator) -> Vec<f32> {
    let (gw, gh) = (
        (plane.valid[0].ceil() as usize).clamp(1, plane.width),
        (plane.valid[1].ceil() as usize).clamp(1, plane.height),
    );
    let (g, _) = decode::discrete(op, gw, gh, DiscreteOptions::default());
    let mut frame = plane.clone();
    for y in 0..plane.height {
        let row = &g.values[y.min(gh - 1) * gw..][..gw];
        for x in 0..plane.width {
            frame.values[y * plane.width + x] = row[x.min(gw - 1)];
        }
    }
    frame.average2()
}

/// Whether `candidate` beats `best` under a target size: an asset within the target beats one
/// over it (rate control returns its smallest where nothing fits); then the smaller mean square
/// error (what PSNR ranks by), or between two over the target, the smaller file.
fn preferred(candidate: (&Coded, &Errors), best: (&Coded, &Errors), target: Option<usize>) -> bool {
    let fits = |a: &Coded| target.is_none_or(|t| a.file_size() <= t);
    match (fits(candidate.0), fits(best.0)) {
        (true, false) => true,
        (false, true) => false,
        (true, true) => candidate.1.rmse < best.1.rmse,
        (false, false) => candidate.0.file_size() < best.0.file_size(),
    }
}

/// Fills invalid cells (push-pull: averages of valid cells over a pyramid, pulled back down),
/// optionally supersamples 2x, and pads to a multiple of `align` by edge replication.
fn coding_plane(s: &SourcePlane, align: usize, supersample: bool) -> CodingPlane {
    let mut values = s.values.clone();
    fill_invalid(&mut values, &s.valid, s.width, s.height);
    let (mut w, mut h, mut weights) = (
        s.width,
        s.height,
        s.valid
            .iter()
            .map(|&v| f32::from(u8::from(v)))
            .collect::<Vec<_>>(),
    );
    // The source extent in frame units: chroma keeps the exact half of the source (w / 2) so
    // that unit coordinates line up with luma.
    let mut valid = s.extent;
    if supersample {
        let (w2, h2) = (2 * w, 2 * h);
        let mut v2 = vec![0.0f32; w2 * h2];
        let mut wt2 = vec![0.0f32; w2 * h2];
        for y in 0..h2 {
            for x in 0..w2 {
                // Bilinear at the supersampled pixel centre.
                let fx = ((x as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, (w - 1) as f32);
                let fy = ((y as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, (h - 1) as f32);
                let (x0, y0) = (fx as usize, fy as usize);
                let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
                let (ax, ay) = (fx - x0 as f32, fy - y0 as f32);
                let top = values[y0 * w + x0] * (1.0 - ax) + values[y0 * w + x1] * ax;
                let bot = values[y1 * w + x0] * (1.0 - ax) + values[y1 * w + x1] * ax;
                v2[y * w2 + x] = top * (1.0 - ay) + bot * ay;
                wt2[y * w2 + x] = weights[(y / 2) * w + x / 2];
            }
        }
        values = v2;
        weights = wt2;
        w = w2;
        h = h2;
        valid = [valid[0] * 2.0, valid[1] * 2.0];
    }
    let (fw, fh) = (w.div_ceil(align) * align, h.div_ceil(align) * align);
    let mut pv = vec![0.0f32; fw * fh];
    let mut pw = vec![0.0f32; fw * fh];
    for y in 0..fh {
        let sy = y.min(h - 1);
        for x in 0..fw {
            let sx = x.min(w - 1);
            pv[y * fw + x] = values[sy * w + sx];
            if x < w && y < h {
                pw[y * fw + x] = weights[y * w + x];
            }
        }
    }
    CodingPlane {
        width: fw,
        height: fh,
        values: pv,
        weights: pw,
        valid,
    }
}

impl PlaneEncoder for QuadtreeSettings {
    fn encode(
        &self,
        raster: &Raster,
        measure: &dyn Measure,
        progress: &(dyn Fn(u64, u64) + Sync),
    ) -> Result<(Coded, Errors), Error> {
        encode(raster, self, measure, progress)
    }
}
