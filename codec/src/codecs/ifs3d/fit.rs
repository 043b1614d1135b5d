//! The IFS3D encoder: the octree partition (tolerance, a budget of maps or constant ranges)
//! and each range's domain fit among the 48 cube isometries, searched by octant features.

use std::num::NonZero;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use crate::Error;
use crate::codecs::ifs3d::octree::*;
use crate::core::entropy::{Dir, Encoder};
use crate::core::format::FormatError;
use crate::core::transform::Quantiser;

/// How the encoder partitions the frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Partition3 {
    /// Split a range while its collage RMS error exceeds this (normalised units).
    Tolerance(f32),
    /// Split the range that gains most until there are this many maps (the seed's "quad N").
    Transforms(usize),
    /// Every range at level `l` (side `min_size << l`): the seed's "const range R".
    ConstRange(usize),
}

/// Encoder settings for a volume.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VolumeSettings {
    /// Smallest range side (voxels).
    pub min_size: u32,
    /// Range sizes: `min_size << l` for `l < levels`.
    pub levels: u32,
    /// Contrast and offset quantisation.
    pub quantiser: Quantiser,
    /// Nearest domains scored exactly per range, for r and for -r.
    pub candidates: usize,
    /// How to choose the partition.
    pub partition: Partition3,
}

impl Default for VolumeSettings {
    fn default() -> Self {
        VolumeSettings {
            min_size: 4,
            levels: 3,
            quantiser: Quantiser {
                contrast_bits: 5,
                offset_bits: 8,
                max_contrast: 0.95,
                slope_bits: 0,
            },
            candidates: 12,
            // 0.01 of the field range: 0.08 voxel with the default band of 4 voxels.
            partition: Partition3::Tolerance(0.01),
        }
    }
}

/// A fitted map and its collage error.
#[derive(Clone, Copy, Debug, Default)]
struct Fit3 {
    sse: f64,
    map: Map3,
}

/// Encodes a normalised field (values in [0, 1], `n^3`, x fastest) into a header and a stream.
/// Returns the header, the stream and the decoded operator.
pub fn encode_field(
    values: &[f32],
    n: usize,
    s: &VolumeSettings,
) -> Result<(OctreeHeader, Vec<u8>, OctreeOperator), Error> {
    // A header or stream this encoder makes and its reader refuses comes of the settings.
    let settings = |e: FormatError| Error::settings(e.to_string());
    if values.len() != n * n * n || n == 0 {
        return Err(Error::input(format!(
            "{} values for a {n}^3 grid",
            values.len()
        )));
    }
    let top = (s.min_size as usize) << (s.levels.max(1) - 1);
    let frame = n.div_ceil(top) * top;
    let header = OctreeHeader {
        frame: frame as u32,
        valid: n as f32,
        min_size: s.min_size,
        levels: s.levels,
        domain_steps: (0..s.levels).map(|l| (s.min_size << l).max(2)).collect(),
        quantiser: s.quantiser,
    };
    header.validate().map_err(settings)?;
    // The frame: the field, padded by repeating its last sample (the band is clamped there).
    let mut v = vec![0.0f32; frame * frame * frame];
    for z in 0..frame {
        for y in 0..frame {
            for x in 0..frame {
                v[(z * frame + y) * frame + x] =
                    values[(z.min(n - 1) * n + y.min(n - 1)) * n + x.min(n - 1)];
            }
        }
    }
    let half = frame / 2;
    let mut h = vec![0.0f32; half * half * half];
    h.par_chunks_mut(half * half)
        .enumerate()
        .for_each(|(z, slab)| {
            for y in 0..half {
                for x in 0..half {
                    let mut acc = 0.0;
                    for c in 0..8 {
                        let (dx, dy, dz) = (c & 1, c >> 1 & 1, c >> 2);
                        acc += v[((2 * z + dz) * frame + 2 * y + dy) * frame + 2 * x + dx];
                    }
                    slab[y * half + x] = acc * 0.125;
                }
            }
        });
    let fits: Vec<Vec<Fit3>> = (0..s.levels as usize)
        .map(|l| fit_level(&header, &v, &h, l, s.candidates))
        .collect();
    let stream = {
        let leaf_of = partition(&header, &fits, s.partition);
        let mut enc = Encoder::new();
        code(&mut Dir::Enc(&mut enc), &header, &leaf_of).map_err(settings)?;
        enc.finish()
    };
    let leaves = decode_stream(&header, &stream).map_err(settings)?;
    let op = OctreeOperator::new(&header, leaves).map_err(settings)?;
    Ok((header, stream, op))
}

/// Index of block `b` at a level with `per` blocks a side.
fn block_index(b: [usize; 3], per: usize) -> usize {
    (b[2] * per + b[1]) * per + b[0]
}

/// The partition as a function (level, block) -> leaf map or split.
fn partition<'a>(
    h: &'a OctreeHeader,
    fits: &'a [Vec<Fit3>],
    mode: Partition3,
) -> impl Fn(usize, [usize; 3]) -> Option<Map3> + 'a {
    let top = h.levels as usize - 1;
    let per = |l: usize| h.frame as usize / h.size(l);
    // leaf[l][block] = true where the block is a leaf of the chosen partition.
    let mut leaf: Vec<Vec<bool>> = (0..=top).map(|l| vec![false; per(l).pow(3)]).collect();
    match mode {
        Partition3::ConstRange(l) => {
            let l = l.min(top);
            leaf[l].iter_mut().for_each(|x| *x = true);
        }
        Partition3::Tolerance(t) => {
            let mut stack: Vec<(usize, [usize; 3])> = Vec::new();
            let p = per(top);
            for i in 0..p * p * p {
                stack.push((top, [i % p, i / p % p, i / (p * p)]));
            }
            while let Some((l, b)) = stack.pop() {
                let n = h.size(l) as f64;
                let f = &fits[l][block_index(b, per(l))];
                if l == 0 || f.sse <= (t as f64).powi(2) * n * n * n {
                    leaf[l][block_index(b, per(l))] = true;
                } else {
                    for c in 0..8 {
                        stack.push((
                            l - 1,
                            [
                                2 * b[0] + (c & 1),
                                2 * b[1] + (c >> 1 & 1),
                                2 * b[2] + (c >> 2),
                            ],
                        ));
                    }
                }
            }
        }
        Partition3::Transforms(budget) => {
            // Greedy: split the leaf whose children lower the total error most, until the
            // budget of maps is spent (a split adds 7).
            use std::collections::BinaryHeap;
            #[derive(PartialEq)]
            struct Gain(f64, usize, [usize; 3]);
            impl Eq for Gain {}
            impl PartialOrd for Gain {
                fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
                    Some(self.cmp(o))
                }
            }
            impl Ord for Gain {
                fn cmp(&self, o: &Self) -> std::cmp::Ordering {
                    self.0.total_cmp(&o.0)
                }
            }
            let gain = |l: usize, b: [usize; 3]| -> f64 {
                let parent = fits[l][block_index(b, per(l))].sse;
                let kids: f64 = (0..8)
                    .map(|c| {
                        let cb = [
                            2 * b[0] + (c & 1),
                            2 * b[1] + (c >> 1 & 1),
                            2 * b[2] + (c >> 2),
                        ];
                        fits[l - 1][block_index(cb, per(l - 1))].sse
                    })
                    .sum();
                parent - kids
            };
            let p = per(top);
            let mut heap = BinaryHeap::new();
            let mut count = p * p * p;
            for (i, is_leaf) in leaf[top].iter_mut().enumerate() {
                let b = [i % p, i / p % p, i / (p * p)];
                *is_leaf = true;
                if top > 0 {
                    heap.push(Gain(gain(top, b), top, b));
                }
            }
            while count + 7 <= budget.max(count) {
                let Some(Gain(g, l, b)) = heap.pop() else {
                    break;
                };
                if g <= 0.0 {
                    break;
                }
                leaf[l][block_index(b, per(l))] = false;
                count += 7;
                for c in 0..8 {
                    let cb = [
                        2 * b[0] + (c & 1),
                        2 * b[1] + (c >> 1 & 1),
                        2 * b[2] + (c >> 2),
                    ];
                    leaf[l - 1][block_index(cb, per(l - 1))] = true;
                    if l - 1 > 0 {
                        heap.push(Gain(gain(l - 1, cb), l - 1, cb));
                    }
                }
            }
        }
    }
    move |l: usize, b: [usize; 3]| {
        let i = block_index(b, per(l));
        leaf[l][i].then(|| fits[l][i].map)
    }
}

/// Octant means of an `n^3` block read through `get`, centred and normalised (None if flat).
fn octant_feature(n: usize, get: impl Fn([usize; 3]) -> f32) -> Option<[f32; 8]> {
    let mut f = [0.0f32; 8];
    let h = n / 2;
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let o = usize::from(x >= h) | usize::from(y >= h) << 1 | usize::from(z >= h) << 2;
                f[o] += get([x, y, z]);
            }
        }
    }
    let mean = f.iter().sum::<f32>() / 8.0;
    f.iter_mut().for_each(|v| *v -= mean);
    let norm = f.iter().map(|v| v * v).sum::<f32>().sqrt();
    (norm > 1e-6 * (n * n * n) as f32).then(|| f.map(|v| v / norm))
}

/// Every domain of level `l` with structure, in its 48 orientations: its octant feature
/// (range octant o reads domain octant iso(o)) and `domain * 48 + isometry`.
fn domain_pool(h: &OctreeHeader, half: &[f32], l: usize) -> Vec<([f32; 8], u32)> {
    let hs = h.frame as usize / 2;
    let n = h.size(l);
    let c = h.lattice(l);
    (0..c * c * c)
        .into_par_iter()
        .flat_map_iter(|d| {
            let corner = h.domain_corner(l, d as u32).map(|v| v as usize / 2);
            let get = |p: [usize; 3]| {
                half[((corner[2] + p[2]) * hs + corner[1] + p[1]) * hs + corner[0] + p[0]]
            };
            let base = octant_feature(n, get);
            (0..CUBE_ISOMETRIES).filter_map(move |iso| {
                let b = base?;
                // Range octant o reads domain octant iso(o).
                let g: [f32; 8] = std::array::from_fn(|o| {
                    let r = cube_isometry_index(iso, [o & 1, o >> 1 & 1, o >> 2], 2);
                    b[r[0] | r[1] << 1 | r[2] << 2]
                });
                Some((g, d as u32 * CUBE_ISOMETRIES as u32 + iso as u32))
            })
        })
        .collect()
}

/// The least-squares map from domain `item` (`domain * 48 + isometry`) of level `l` onto the
/// range `r` (mean `mean_r`), quantised; `None` for a flat domain or a zero contrast. `d` is
/// scratch space of the range's size.
fn domain_fit(
    h: &OctreeHeader,
    half: &[f32],
    l: usize,
    item: u32,
    (r, mean_r): (&[f32], f64),
    d: &mut [f32],
) -> Option<Fit3> {
    let hs = h.frame as usize / 2;
    let n = h.size(l);
    let q = h.quantiser;
    let count = r.len() as f64;
    let (dom, iso) = (
        item / CUBE_ISOMETRIES as u32,
        (item % CUBE_ISOMETRIES as u32) as u8,
    );
    let corner = h.domain_corner(l, dom).map(|v| v as usize / 2);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let s = cube_isometry_index(iso, [x, y, z], n);
                d[(z * n + y) * n + x] =
                    half[((corner[2] + s[2]) * hs + corner[1] + s[1]) * hs + corner[0] + s[0]];
            }
        }
    }
    let mean_d = d.iter().map(|&x| x as f64).sum::<f64>() / count;
    let (mut dd, mut dr) = (0.0f64, 0.0f64);
    for (&x, &y) in d.iter().zip(r) {
        let xd = x as f64 - mean_d;
        dd += xd * xd;
        dr += xd * (y as f64 - mean_r);
    }
    if dd < 1e-12 {
        return None;
    }
    let qs = q.contrast_index((dr / dd) as f32);
    if qs == 0 {
        return None;
    }
    let s = q.contrast(qs);
    let qo = q.offset_index(s, (mean_r - s as f64 * mean_d) as f32);
    let o = q.offset(s, qo);
    let sse: f64 = d
        .iter()
        .zip(r)
        .map(|(&x, &y)| ((s * x + o - y) as f64).powi(2))
        .sum();
    Some(Fit3 {
        sse,
        map: Map3 {
            contrast: qs,
            offset: qo,
            isometry: iso,
            domain: dom,
        },
    })
}

/// Fits every block of level `l`.
fn fit_level(h: &OctreeHeader, v: &[f32], half: &[f32], l: usize, k: usize) -> Vec<Fit3> {
    let f = h.frame as usize;
    let n = h.size(l);
    let per = f / n;
    let q = h.quantiser;
    // The pool: every domain with structure, in its 48 orientations.
    let pool = domain_pool(h, half, l);
    let tree = (!pool.is_empty()).then(|| {
        let pts: Vec<[f32; 8]> = pool.iter().map(|p| p.0).collect();
        ImmutableKdTree::<f32, 8>::new_from_slice(&pts)
    });
    let k = NonZero::new(k.max(1)).expect("k >= 1");
    (0..per * per * per)
        .into_par_iter()
        .map(|i| {
            let b = [i % per, i / per % per, i / (per * per)];
            let o = b.map(|v| v * n);
            let mut r = Vec::with_capacity(n * n * n);
            for z in 0..n {
                for y in 0..n {
                    let row = ((o[2] + z) * f + o[1] + y) * f + o[0];
                    r.extend_from_slice(&v[row..row + n]);
                }
            }
            let count = r.len() as f64;
            let mean_r = r.iter().map(|&x| x as f64).sum::<f64>() / count;
            let rr: f64 = r.iter().map(|&x| (x as f64 - mean_r).powi(2)).sum();
            // The constant map: exact for clamped blocks.
            let qo = q.offset_index(0.0, mean_r as f32);
            let og = q.offset(0.0, qo) as f64;
            let mut best = Fit3 {
                sse: r.iter().map(|&x| (x as f64 - og).powi(2)).sum(),
                map: Map3 {
                    contrast: 0,
                    offset: qo,
                    isometry: 0,
                    domain: 0,
                },
            };
            if rr < 1e-12 {
                return best;
            }
            let (Some(tree), Some(fr)) = (
                &tree,
                octant_feature(n, |p| r[(p[2] * n + p[1]) * n + p[0]]),
            ) else {
                return best;
            };
            let mut d = vec![0.0f32; n * n * n];
            let mut tried = Vec::with_capacity(2 * k.get());
            for query in [fr, fr.map(|x| -x)] {
                for nb in tree.nearest_n::<SquaredEuclidean>(&query, k) {
                    let item = pool[nb.item as usize].1;
                    if tried.contains(&item) {
                        continue;
                    }
                    tried.push(item);
                    if let Some(fit) = domain_fit(h, half, l, item, (&r, mean_r), &mut d)
                        && fit.sse < best.sse
                    {
                        best = fit;
                    }
                }
            }
            best
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_48_isometries_are_distinct_and_match_their_index_form() {
        let n = 4;
        let mut seen = std::collections::HashSet::new();
        for k in 0..CUBE_ISOMETRIES {
            let image: Vec<[usize; 3]> = (0..n * n * n)
                .map(|i| cube_isometry_index(k, [i % n, i / n % n, i / (n * n)], n))
                .collect();
            assert!(seen.insert(image.clone()), "isometry {k} repeats another");
            // A bijection of the block.
            let mut sorted = image.clone();
            sorted.sort();
            sorted.dedup();
            assert_eq!(sorted.len(), n * n * n);
            // The continuous form agrees: voxel q of a range at (8, 4, 12), side 4, reads
            // the domain at (0, 16, 8) (side 8) around the centre of downsampled voxel iso(q).
            let cell = OctCell::new([8, 4, 12], 4, [0, 16, 8], k, 0.5, 0.1);
            for (i, s) in image.iter().enumerate() {
                let qv = [i % n, i / n % n, i / (n * n)];
                let p = [8.5 + qv[0] as f32, 4.5 + qv[1] as f32, 12.5 + qv[2] as f32];
                let want = [
                    0.0 + 2.0 * s[0] as f32 + 1.0,
                    16.0 + 2.0 * s[1] as f32 + 1.0,
                    8.0 + 2.0 * s[2] as f32 + 1.0,
                ];
                let got = cell.phi(p);
                assert!(
                    (0..3).all(|a| (got[a] - want[a]).abs() < 1e-5),
                    "{k} {qv:?}: {got:?} {want:?}"
                );
            }
        }
    }

    /// A smooth field with structure at every scale: a sphere's distance plus ripples.
    fn field(n: usize) -> Vec<f32> {
        (0..n * n * n)
            .map(|i| {
                let p = [i % n, i / n % n, i / (n * n)].map(|v| (v as f32 + 0.5) / n as f32 - 0.5);
                let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                let d = (r - 0.3) * 4.0 + 0.05 * (p[0] * 17.0).sin() * (p[1] * 13.0).cos();
                (0.5 + d).clamp(0.0, 1.0)
            })
            .collect()
    }

    #[test]
    fn stream_round_trip_and_collage_quality() {
        let n = 32;
        let v = field(n);
        let s = VolumeSettings {
            partition: Partition3::Tolerance(0.004),
            ..Default::default()
        };
        let (h, stream, op) = encode_field(&v, n, &s).unwrap();
        assert_eq!(decode_stream(&h, &stream).unwrap(), op.leaves());
        // The ranges are split where the field has structure: fewer maps than the finest grid,
        // more than the coarsest.
        let leaves = op.leaves().len();
        assert!(
            leaves > 8 && leaves < (32 / 4usize).pow(3),
            "{leaves} leaves"
        );
        assert!(op.leaves().iter().any(|l| l.map.contrast != 0));
        // Discrete decoding reproduces the field (the collage theorem at work).
        let (got, _) =
            crate::core::decode::discrete_volume(&op, [n; 3], crate::DiscreteOptions::fixed(20));
        let mse = got
            .iter()
            .zip(&v)
            .map(|(a, b)| ((a - b) as f64).powi(2))
            .sum::<f64>()
            / v.len() as f64;
        let psnr = -10.0 * mse.log10();
        // (A hard field for 32^3: ripples of 12 voxels on a sphere; real distance fields do far
        // better, see the volume tests and bench.)
        assert!(psnr > 30.0, "{psnr} dB");
        // Continuous decoding of voxel centres agrees with the discrete decode on smooth content.
        let pts: Vec<[f32; 3]> = (0..200)
            .map(|i| {
                [(i * 7 % n) as f32, (i * 13 % n) as f32, (i * 29 % n) as f32]
                    .map(|c| (c + 0.5) / n as f32)
            })
            .collect();
        let pv = crate::core::decode::points(&op, &pts, 30, 0.0);
        let mut diff = 0.0f64;
        for (p, r) in pts.iter().zip(&pv) {
            let idx = p.map(|c| (c * n as f32) as usize);
            diff += (r.value - got[(idx[2] * n + idx[1]) * n + idx[0]]).abs() as f64;
            assert!(r.error_bound < 1e-3);
        }
        assert!(
            diff / 200.0 < 0.02,
            "mean |point - discrete| {}",
            diff / 200.0
        );
    }

    #[test]
    fn a_budget_of_maps_is_kept_and_spent_where_it_pays() {
        let n = 32;
        let v = field(n);
        let count = |p| {
            let s = VolumeSettings {
                partition: p,
                ..Default::default()
            };
            let (_, _, op) = encode_field(&v, n, &s).unwrap();
            let (d, _) = crate::core::decode::discrete_volume(
                &op,
                [n; 3],
                crate::DiscreteOptions::fixed(20),
            );
            let mse = d
                .iter()
                .zip(&v)
                .map(|(a, b)| ((a - b) as f64).powi(2))
                .sum::<f64>();
            (op.leaves().len(), mse)
        };
        let (few, mse_few) = count(Partition3::Transforms(120));
        let (more, mse_more) = count(Partition3::Transforms(400));
        // 8 top blocks, each split adds 7: the budget is never exceeded, and is used.
        assert!(few <= 120 && few > 100, "{few}");
        assert!(more <= 400 && more > 380, "{more}");
        assert!(mse_more < mse_few, "{mse_more} {mse_few}");
        // Const range: every range at one size.
        let (all, _) = count(Partition3::ConstRange(0));
        assert_eq!(all, (32 / 4usize).pow(3));
    }

    #[test]
    fn a_corrupt_stream_is_an_error_not_a_panic() {
        let n = 16;
        let (h, stream, _) = encode_field(&field(n), n, &VolumeSettings::default()).unwrap();
        for cut in [0, stream.len() / 2] {
            let _ = decode_stream(&h, &stream[..cut]);
        }
        let mut bad = h.clone();
        bad.frame = 17;
        assert!(decode_stream(&bad, &stream).is_err());
        bad = h.clone();
        bad.quantiser.slope_bits = 4;
        assert!(decode_stream(&bad, &stream).is_err());
        // A tiny file must not declare a lookup map of gigabytes.
        bad = h.clone();
        (bad.frame, bad.min_size, bad.levels, bad.valid) = (1024, 2, 6, 1000.0);
        bad.domain_steps = vec![2; 6];
        let e = decode_stream(&bad, &stream).unwrap_err();
        assert!(
            matches!(&e, FormatError::Header(m) if m.contains("2^24")),
            "{e}"
        );
        for i in 0..stream.len() {
            let mut s = stream.clone();
            s[i] ^= 0x5a;
            if let Ok(leaves) = decode_stream(&h, &s) {
                // Whatever decodes must build an operator or fail cleanly.
                let _ = OctreeOperator::new(&h, leaves);
            }
        }
    }
}
