//! The psa2d fit: vertex heights by subsampling, and each region's domain by search (the
//! least squared collage error over the region's samples), against the bilinear patch.

use rayon::prelude::*;

use crate::Error;
use crate::codecs::psa::*;
use crate::core::lattice::Source;

/// Fits the model to a normalised source: vertex heights by subsampling, each region's domain by
/// search (least squared error of the collage over the region's samples), against the bilinear
/// patch (kept when no domain beats it).
pub(crate) fn fit(source: &Source, header: &PsaHeader) -> Result<PsaParams, Error> {
    header
        .validate()
        .map_err(|e| Error::settings(e.to_string()))?;
    let [nx, ny] = header.vertices();
    let d = header.region as usize;
    let a = header.ratio as usize;
    let heights: Vec<i32> = (0..ny)
        .flat_map(|j| (0..nx).map(move |i| (i, j)))
        .map(|(i, j)| (source.at(i * d, j * d) / header.height_step).round() as i32)
        .collect();
    let z: Vec<f32> = heights
        .iter()
        .map(|&q| q as f32 * header.height_step)
        .collect();
    let corners = |i: usize, j: usize, k: usize| -> [f32; 4] {
        [
            z[j * nx + i],
            z[j * nx + i + k],
            z[(j + k) * nx + i],
            z[(j + k) * nx + i + k],
        ]
    };
    let r = header.radius as i32;
    let regions: Vec<RegionCode> = (0..(nx - 1) * (ny - 1))
        .into_par_iter()
        .map(|idx| {
            let (ci, cj) = (idx % (nx - 1), idx / (nx - 1));
            let zc = corners(ci, cj, 1);
            // The region's samples: (x, y, u, v, f).
            let pts: Vec<(usize, usize, f32, f32, f32)> = (0..=d)
                .flat_map(|y| (0..=d).map(move |x| (x, y)))
                .map(|(x, y)| {
                    let (sx, sy) = (ci * d + x, cj * d + y);
                    (
                        x,
                        y,
                        x as f32 / d as f32,
                        y as f32 / d as f32,
                        source.at(sx, sy),
                    )
                })
                .collect();
            let pg = patch(zc);
            let mut best_err: f32 = pts
                .iter()
                .map(|&(_, _, u, v, f)| (f - eval(pg, u, v)).powi(2))
                .sum();
            let mut best = RegionCode::Patch;
            for dy in -r..=r {
                for dx in -r..=r {
                    let Some((di, dj)) = header.address(ci, cj, dx, dy) else {
                        continue;
                    };
                    let zd = corners(di, dj, a);
                    let dom = |x: usize, y: usize| source.at(di * d + a * x, dj * d + a * y);
                    match header.tiling {
                        Tiling::Rectangular => {
                            let Some((g, s)) = rectangle(zc, zd, header.max_scaling) else {
                                continue;
                            };
                            let mut e = 0.0f32;
                            for &(x, y, u, v, f) in &pts {
                                e += (f - eval(g, u, v) - s * dom(x, y)).powi(2);
                                if e >= best_err {
                                    break;
                                }
                            }
                            if e < best_err {
                                best_err = e;
                                best = RegionCode::Mapped {
                                    dx,
                                    dy,
                                    s0: 0,
                                    s1: 0,
                                };
                            }
                        }
                        Tiling::Triangular => {
                            // Per half: f - P(zc) ~ s (f(phi) - P(zd)), least squares in s.
                            let mut e = 0.0f32;
                            let mut q = [0i32; 2];
                            for (h, qh) in q.iter_mut().enumerate() {
                                let (pc, pd) = (plane(h, zc), plane(h, zd));
                                let half: Vec<(f32, f32)> = pts
                                    .iter()
                                    .filter(|&&(_, _, u, v, _)| (u + v > 1.0) == (h == 1))
                                    .map(|&(x, y, u, v, f)| {
                                        (f - eval(pc, u, v), dom(x, y) - eval(pd, u, v))
                                    })
                                    .collect();
                                let (num, den) =
                                    half.iter().fold((0.0f32, 0.0f32), |(n, m), &(r, d)| {
                                        (n + r * d, m + d * d)
                                    });
                                let s = if den > 1e-12 { num / den } else { 0.0 };
                                *qh = header.scaling_index(s);
                                let s = header.scaling_of(*qh);
                                e += half.iter().map(|&(r, d)| (r - s * d).powi(2)).sum::<f32>();
                            }
                            if e < best_err {
                                best_err = e;
                                best = RegionCode::Mapped {
                                    dx,
                                    dy,
                                    s0: q[0],
                                    s1: q[1],
                                };
                            }
                        }
                    }
                }
            }
            best
        })
        .collect();
    Ok(PsaParams { heights, regions })
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::core::decode;

    fn header(tiling: Tiling, domains: Domains, w: u32, h: u32) -> PsaHeader {
        PsaHeader {
            samples: [w, h],
            region: 4,
            ratio: 2,
            tiling,
            domains,
            radius: 4,
            height_step: 1.0 / 4096.0,
            scaling_bits: 5,
            max_scaling: 0.9,
        }
    }

    fn surface(w: usize, h: usize) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                0.5 + 0.2 * (x * 0.11).sin() * (y * 0.07).cos()
                    + 0.04 * ((x * 1.3).sin() + (y * 0.9).cos())
            })
            .collect()
    }

    #[test]
    fn every_variant_round_trips_interpolates_and_beats_bilinear_patches() {
        let (w, h) = (49usize, 41usize);
        let values = surface(w, h);
        let src = Source {
            width: w,
            height: h,
            values: &values,
        };
        for tiling in [Tiling::Rectangular, Tiling::Triangular] {
            for domains in [Domains::Touching, Domains::Overlapping] {
                let hd = header(tiling, domains, w as u32, h as u32);
                let p = fit(&src, &hd).unwrap();
                let mapped = p
                    .regions
                    .iter()
                    .filter(|r| **r != RegionCode::Patch)
                    .count();
                assert!(
                    mapped * 2 > p.regions.len(),
                    "{tiling:?} {domains:?}: {mapped} mapped"
                );
                let bytes = encode_params(&hd, &p);
                assert_eq!(decode_params(&hd, &bytes).unwrap(), p);
                assert!(decode_params(&hd, &bytes[..bytes.len() / 2]).is_err());
                let op = PsaOperator::new(&hd, &p).unwrap();
                let [nx, ny] = hd.vertices();
                for j in 0..ny {
                    for i in 0..nx {
                        let (x, y) = ((i * 4) as f32 + 0.5, (j * 4) as f32 + 0.5);
                        if x > w as f32 || y > h as f32 {
                            continue;
                        }
                        let pv = decode::point(&op, [x / w as f32, y / h as f32], 300);
                        let z = p.heights[j * nx + i] as f32 * hd.height_step;
                        assert!(
                            (pv.value - z).abs() <= pv.error_bound + 2e-4,
                            "{tiling:?} {domains:?} vertex {i},{j}: {} vs {z}",
                            pv.value
                        );
                    }
                }
                // The decoded surface is closer to the source than the bilinear patches are.
                let (g, _) = decode::discrete(&op, w, h, decode::DiscreteOptions::fixed(40));
                let patches = PsaParams {
                    heights: p.heights.clone(),
                    regions: vec![RegionCode::Patch; p.regions.len()],
                };
                let flat = PsaOperator::new(&hd, &patches).unwrap();
                let (b, _) = decode::discrete(&flat, w, h, decode::DiscreteOptions::fixed(1));
                let sse = |v: &[f32]| -> f32 {
                    v.iter().zip(&values).map(|(a, b)| (a - b).powi(2)).sum()
                };
                assert!(
                    sse(&g.values) < sse(&b.values),
                    "{tiling:?} {domains:?}: {} vs patches {}",
                    sse(&g.values),
                    sse(&b.values)
                );
            }
        }
    }

    #[test]
    fn flattened_psa2d_decodes_like_its_operator() {
        for tiling in [Tiling::Rectangular, Tiling::Triangular] {
            let h = PsaHeader {
                samples: [41, 33],
                region: 4,
                ratio: 2,
                tiling,
                domains: Domains::Overlapping,
                radius: 3,
                height_step: 1.0 / 1000.0,
                scaling_bits: 5,
                max_scaling: 0.9,
            };
            let src: Vec<f32> = (0..41 * 33)
                .map(|i| {
                    let (x, y) = ((i % 41) as f32, (i / 41) as f32);
                    0.5 + 0.3 * (x * 0.3).sin() * (y * 0.2).cos()
                        + 0.1 * ((i * 31) % 7) as f32 / 7.0
                })
                .collect();
            let source = Source {
                width: 41,
                height: 33,
                values: &src,
            };
            let params = fit(&source, &h).unwrap();
            assert!(params.regions.iter().any(|r| *r != RegionCode::Patch));
            let op = PsaOperator::new(&h, &params).unwrap();
            crate::core::pieces::tests::agree(&op, &format!("{tiling:?}"));
        }
    }
}
