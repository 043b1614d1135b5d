//! Quadtree partitions of a plane into ranges.
//!
//! The encoder fits every block of every size once ([`Pyramid`]), in parallel; choosing a
//! partition is then cheap, which is what makes the seed's three modes and rate control fast:
//! * tolerance: split a range while its RMS collage error exceeds the tolerance;
//! * "quad N": split until N ranges, always the range whose split removes the most error
//!   (the seed splits the worst range; splitting where the split *gains* most gives a better
//!   error for the same N, and needs no extra work since children are fitted anyway);
//! * "const range R": one level only.
//!
//! Rate control replays the greedy split order and bisects on its length.

use std::collections::BinaryHeap;

use rayon::prelude::*;

use crate::codecs::quadtree::search::{CodingPlane, DomainPool, Fit, SearchMode, fit_range_each};
use crate::codecs::quadtree::stream::{Coverage, PlaneHeader, coverage};
use crate::core::transform::Quantiser;

/// Fits of every block of every level of one plane.
pub struct Pyramid {
    /// The plane's header (frame, sizes, steps, quantiser).
    pub header: PlaneHeader,
    /// `fits[l][by * cols + bx]`, `None` for blocks not wholly inside the frame.
    pub fits: Vec<Vec<Option<Fit>>>,
    /// Blocks per row at each level.
    pub cols: Vec<usize>,
}

/// Limits of one block: RMS tolerance (normalised) and smallest range side allowed there.
pub type Limits<'a> = &'a (dyn Fn(usize, usize, usize) -> (f32, usize) + Sync);

impl Pyramid {
    /// Fits every inside block of every level (const-range mode has a single level), calling
    /// `progress(1)` per block.
    pub fn build(
        plane: &CodingPlane,
        header: PlaneHeader,
        mode: SearchMode,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Pyramid {
        Self::build_with_domains(plane, &plane.average2(), header, mode, progress)
    }

    /// As [`Pyramid::build`], with domains read from `avg2` ([`CodingPlane::average2`] of
    /// another image of the same frame, such as the attractor of an earlier encode) while
    /// ranges stay the plane's own values.
    pub fn build_with_domains(
        plane: &CodingPlane,
        avg2: &[f32],
        header: PlaneHeader,
        mode: SearchMode,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Pyramid {
        let mut one = Self::build_each(plane, avg2, &[header], mode, progress);
        one.pop().expect("one header, one pyramid")
    }

    /// One pyramid per header, from one search ([`fit_range_each`]): the headers differ only
    /// in their quantisers, which must agree on whether they have slopes. `progress(1)` is
    /// called once per block, not once per header.
    pub fn build_each(
        plane: &CodingPlane,
        avg2: &[f32],
        headers: &[PlaneHeader],
        mode: SearchMode,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Vec<Pyramid> {
        let header = &headers[0];
        let quantisers: Vec<Quantiser> = headers.iter().map(|h| h.quantiser).collect();
        let mut pyramids: Vec<Pyramid> = headers
            .iter()
            .map(|h| Pyramid {
                header: h.clone(),
                fits: Vec::new(),
                cols: Vec::new(),
            })
            .collect();
        for l in 0..header.levels as usize {
            let n = header.size(l);
            let (c, r) = ((plane.width).div_ceil(n), (plane.height).div_ceil(n));
            let pool = DomainPool::new(
                plane,
                avg2,
                n,
                header.domain_steps[l] as usize,
                mode,
                header.quantiser.slope_bits > 0,
            );
            let level: Vec<Option<Vec<Fit>>> = (0..c * r)
                .into_par_iter()
                .map(|i| {
                    let (bx, by) = (i % c, i / c);
                    (coverage(header.frame, n, bx, by) == Coverage::Inside).then(|| {
                        let f = fit_range_each(plane, &pool, bx * n, by * n, &quantisers, mode);
                        progress(1);
                        f
                    })
                })
                .collect();
            for (k, p) in pyramids.iter_mut().enumerate() {
                p.cols.push(c);
                p.fits
                    .push(level.iter().map(|f| f.as_ref().map(|f| f[k])).collect());
            }
        }
        pyramids
    }

    /// Number of inside blocks over all levels (for progress bars).
    pub fn work(header: &PlaneHeader) -> u64 {
        (0..header.levels as usize)
            .map(|l| {
                let n = header.size(l);
                ((header.frame[0] as usize / n) * (header.frame[1] as usize / n)) as u64
            })
            .sum()
    }

    /// The fit of a block.
    pub fn fit(&self, l: usize, bx: usize, by: usize) -> Option<Fit> {
        self.fits[l].get(by * self.cols[l] + bx).copied().flatten()
    }

    fn children_sse(&self, l: usize, bx: usize, by: usize) -> Option<f32> {
        let mut s = 0.0;
        for (cx, cy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            s += self.fit(l - 1, 2 * bx + cx, 2 * by + cy)?.sse;
        }
        Some(s)
    }
}

/// A choice of ranges: `split[l][block]` for inside blocks above the smallest level, and for
/// leaves whether they take the constant map instead of their best map.
#[derive(Clone, Debug)]
pub struct Partition {
    split: Vec<Vec<bool>>,
    constant: Vec<Vec<bool>>,
}

impl Partition {
    fn empty(p: &Pyramid) -> Partition {
        Partition {
            split: p.fits.iter().map(|f| vec![false; f.len()]).collect(),
            constant: p.fits.iter().map(|f| vec![false; f.len()]).collect(),
        }
    }

    /// Whether block (l, bx, by) is split.
    pub fn is_split(&self, p: &Pyramid, l: usize, bx: usize, by: usize) -> bool {
        self.split[l][by * p.cols[l] + bx]
    }

    /// What the stream coder asks: `None` to split, the fit for a leaf.
    pub fn decide(&self, p: &Pyramid, l: usize, bx: usize, by: usize) -> Option<Fit> {
        if l > 0 && self.is_split(p, l, bx, by) {
            return None;
        }
        let f = p.fit(l, bx, by)?;
        Some(if self.constant[l][by * p.cols[l] + bx] {
            f.as_constant()
        } else {
            f
        })
    }

    /// The rate-distortion optimal partition for the Lagrange multiplier `lambda`
    /// (Sullivan-Baker pruning): bottom up, each block keeps the cheapest of its constant map,
    /// its best map, or its four children, in `weight * sse / tol^2 + lambda * bits`. Bits are
    /// estimates (see [`estimated_bits`]); the caller bisects on lambda for an exact rate.
    pub fn by_lagrangian(p: &Pyramid, lambda: f32, weight: f32, limits: Limits) -> Partition {
        let mut part = Partition::empty(p);
        let levels = p.fits.len();
        let mut cost: Vec<Vec<f32>> = p
            .fits
            .iter()
            .map(|f| vec![f32::INFINITY; f.len()])
            .collect();
        for l in 0..levels {
            let n = p.header.size(l);
            let (dc, dr) = p.header.lattice(l);
            let (b_const, b_map) = estimated_bits(dc * dr, l > 0, p.header.quantiser.slope_bits);
            let rows = p.fits[l].len() / p.cols[l];
            for by in 0..rows {
                for bx in 0..p.cols[l] {
                    let i = by * p.cols[l] + bx;
                    let Some(f) = p.fits[l][i] else { continue };
                    let (tol, min) = limits(bx * n, by * n, n);
                    let w = weight / (tol * tol).max(1e-20);
                    let j_map = w * f.sse + lambda * b_map;
                    let j_const = w * f.constant_sse + lambda * b_const;
                    let mut best = j_map.min(j_const);
                    part.constant[l][i] = j_const <= j_map;
                    if l > 0 && n > min {
                        let mut j_split = lambda;
                        for (cx, cy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                            j_split += cost[l - 1][(2 * by + cy) * p.cols[l - 1] + 2 * bx + cx];
                        }
                        if j_split < best {
                            best = j_split;
                            part.split[l][i] = true;
                        }
                    }
                    cost[l][i] = best;
                }
            }
        }
        part
    }

    /// Every range of a single level (const-range mode: the pyramid has one level).
    pub fn whole_level(p: &Pyramid) -> Partition {
        Partition::empty(p)
    }

    /// Splits while the RMS collage error exceeds the block's tolerance.
    pub fn by_tolerance(p: &Pyramid, limits: Limits) -> Partition {
        let mut part = Partition::empty(p);
        let top = p.fits.len() - 1;
        let mut stack: Vec<(usize, usize, usize)> = Vec::new();
        let n_top = p.header.size(top);
        for by in 0..(p.header.frame[1] as usize).div_ceil(n_top) {
            for bx in 0..(p.header.frame[0] as usize).div_ceil(n_top) {
                stack.push((top, bx, by));
            }
        }
        while let Some((l, bx, by)) = stack.pop() {
            let n = p.header.size(l);
            let split = match coverage(p.header.frame, n, bx, by) {
                Coverage::Outside => continue,
                Coverage::Partial => true,
                Coverage::Inside if l == 0 => false,
                Coverage::Inside => {
                    let f = p.fit(l, bx, by).expect("inside blocks are fitted");
                    let (tol, min) = limits(bx * n, by * n, n);
                    n > min && f.weight > 0.0 && f.sse > tol * tol * f.weight
                }
            };
            if split {
                part.split[l][by * p.cols[l] + bx] = true;
                for (cx, cy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    stack.push((l - 1, 2 * bx + cx, 2 * by + cy));
                }
            } else if let Some(f) = p.fit(l, bx, by) {
                // A constant map that already meets the tolerance costs a third of the bits.
                let (tol, _) = limits(bx * n, by * n, n);
                part.constant[l][by * p.cols[l] + bx] = f.constant_sse <= tol * tol * f.weight;
            }
        }
        part
    }
}

/// Estimated bits of a leaf with a constant map and with a full map, at a level with `domains`
/// domains (`flag`: whether a split flag is coded). Measured on camera.png's streams: offsets cost
/// about 6 bits, contrasts 4, isometries 3, domain indices close to log2 of the lattice.
pub fn estimated_bits(domains: usize, flag: bool, slope_bits: u8) -> (f32, f32) {
    let f = if flag { 1.0 } else { 0.0 };
    let d = (domains.max(1) as f32).log2();
    // Slopes cluster near zero; the adaptive coder spends about half their raw bits.
    let g = slope_bits as f32;
    (f + 2.0 + 6.0 + g, f + 4.0 + 6.0 + 3.0 + d + g)
}

/// One split of the greedy order: plane, level, block.
pub type Split = (usize, usize, usize, usize);

#[derive(PartialEq)]
struct Candidate {
    gain: f32,
    split: Split,
}
impl Eq for Candidate {}
impl PartialOrd for Candidate {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Candidate {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.gain
            .total_cmp(&o.gain)
            .then_with(|| o.split.cmp(&self.split))
    }
}

/// The greedy split order over several planes at once: always split the range (of any plane)
/// whose split removes the most weighted error. `weight[plane]` scales a plane's error (chroma
/// counts less); `limits[plane]` scales by the region of interest (gain / tol²) and bounds sizes.
/// Also returns the number of ranges before the first split (forced splits only).
pub fn greedy_order(
    pyramids: &[&Pyramid],
    weight: &[f32],
    limits: &[Limits],
) -> (usize, Vec<Split>) {
    let mut heap = BinaryHeap::new();
    let mut initial = 0usize;
    let push = |heap: &mut BinaryHeap<Candidate>, pi: usize, l: usize, bx: usize, by: usize| {
        let p = pyramids[pi];
        let n = p.header.size(l);
        let (tol, min) = limits[pi](bx * n, by * n, n);
        if l == 0 || n <= min {
            return;
        }
        if let (Some(f), Some(c)) = (p.fit(l, bx, by), p.children_sse(l, bx, by)) {
            let gain = (f.sse - c) * weight[pi] / (tol * tol).max(1e-20);
            heap.push(Candidate {
                gain,
                split: (pi, l, bx, by),
            });
        }
    };
    for (pi, p) in pyramids.iter().enumerate() {
        // Walk the forced splits; the inside blocks they reach are the first ranges.
        let top = p.fits.len() - 1;
        let n_top = p.header.size(top);
        let mut stack = Vec::new();
        for by in 0..(p.header.frame[1] as usize).div_ceil(n_top) {
            for bx in 0..(p.header.frame[0] as usize).div_ceil(n_top) {
                stack.push((top, bx, by));
            }
        }
        while let Some((l, bx, by)) = stack.pop() {
            match coverage(p.header.frame, p.header.size(l), bx, by) {
                Coverage::Outside => {}
                Coverage::Partial => {
                    for (cx, cy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                        stack.push((l - 1, 2 * bx + cx, 2 * by + cy));
                    }
                }
                Coverage::Inside => {
                    initial += 1;
                    push(&mut heap, pi, l, bx, by);
                }
            }
        }
    }
    let mut order = Vec::new();
    while let Some(c) = heap.pop() {
        order.push(c.split);
        let (pi, l, bx, by) = c.split;
        for (cx, cy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            push(&mut heap, pi, l - 1, 2 * bx + cx, 2 * by + cy);
        }
    }
    (initial, order)
}

/// The partitions of each plane after the first `k` splits of a greedy order.
pub fn partitions_after(pyramids: &[&Pyramid], order: &[Split], k: usize) -> Vec<Partition> {
    let mut parts: Vec<Partition> = pyramids.iter().map(|p| Partition::empty(p)).collect();
    for &(pi, l, bx, by) in &order[..k.min(order.len())] {
        parts[pi].split[l][by * pyramids[pi].cols[l] + bx] = true;
    }
    parts
}
