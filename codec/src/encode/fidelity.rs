//! Measuring an asset's source-error map ([`SourceError`]) at encode time: the decoded asset
//! against its source on the half-cell lattice (every cell centre, corner and edge midpoint),
//! through the same continuous decoding that answers requests, run to convergence.

use rayon::prelude::*;

use crate::core::fidelity::{BLOCK, SourceError};
use crate::io::asset::Asset;
use crate::io::raster::Raster;

/// Steps at most for a measured point; each stops once within `TOLERANCE` of the span.
const ITERATIONS: u32 = 64;
/// Convergence tolerance of a measured point, as a fraction of the value span (added to the
/// point's error, so the map stays a bound on the attractor's error).
const TOLERANCE: f32 = 1e-5;

/// A point measured: its unit coordinates and the source cells of its bilinear support.
type Measured = ([f32; 2], Vec<(usize, usize)>);

/// The source-error map of `asset` encoded from `source`, with blocks of [`BLOCK`] cells, or
/// coarser ones where that many would take more than `budget` bytes.
pub fn measure(asset: &Asset, source: &Raster, budget: usize) -> SourceError {
    let (w, h) = (source.width, source.height);
    let span = (asset.meta.value_max - asset.meta.value_min) as f32;
    let valid = |x: usize, y: usize| source.valid.as_ref().is_none_or(|v| v[y * w + x]);
    let tolerance = TOLERANCE * span.max(f32::MIN_POSITIVE);
    // Rows of centres (j + 0.5) and of corners (j = 0..=h), in parallel by row.
    let error_row = |points: Vec<Measured>| -> Vec<f32> {
        let pts: Vec<[f32; 2]> = points.iter().map(|p| p.0).collect();
        let samples = asset.points(&pts, ITERATIONS, tolerance);
        points
            .iter()
            .zip(samples)
            .map(|((_, support), s)| {
                if support.iter().any(|&(x, y)| !valid(x, y)) {
                    return 0.0;
                }
                let mut worst = 0.0f32;
                for (c, &v) in s.values.iter().enumerate() {
                    let ch = &source.channels[c];
                    let bilinear = support.iter().map(|&(x, y)| ch[y * w + x]).sum::<f32>()
                        / support.len() as f32;
                    let e = (v - bilinear).abs();
                    // NaN where the decode has no data: not an answer to bound.
                    if e.is_finite() {
                        worst = worst.max(e);
                    }
                }
                worst + s.error_bound
            })
            .collect()
    };
    // The half-cell lattice, (q / 2, r / 2) in cells: centres, corners and edge midpoints. A
    // coordinate on a centre has that cell as its support; one on a cell edge the two cells
    // beside it (clamped at the raster's edges, as the bilinear source is), equally weighted.
    let axis = |q: usize, n: usize| -> Vec<usize> {
        if q % 2 == 1 {
            vec![(q - 1) / 2]
        } else {
            vec![(q / 2).saturating_sub(1), (q / 2).min(n - 1)]
        }
    };
    let support = |q: usize, r: usize| -> Vec<(usize, usize)> {
        let xs = axis(q, w);
        axis(r, h)
            .into_iter()
            .flat_map(|y| xs.iter().map(move |&x| (x, y)))
            .collect()
    };
    let lattice: Vec<Vec<f32>> = (0..=2 * h)
        .into_par_iter()
        .map(|r| {
            error_row(
                (0..=2 * w)
                    .map(|q| {
                        let u = [q as f32 / (2 * w) as f32, r as f32 / (2 * h) as f32];
                        (u, support(q, r))
                    })
                    .collect(),
            )
        })
        .collect();
    let mut block = BLOCK;
    loop {
        let cols = w.div_ceil(block);
        let mut errors = vec![0.0f32; cols * h.div_ceil(block)];
        let mut put = |x: usize, y: usize, e: f32| {
            let b = &mut errors[(y / block) * cols + x / block];
            *b = b.max(e);
        };
        for (r, row) in lattice.iter().enumerate() {
            for (q, &e) in row.iter().enumerate() {
                for (x, y) in support(q, r) {
                    put(x, y, e);
                }
            }
        }
        let map = SourceError::from_block_errors(w, h, block, &errors, span);
        if map.encode().len() <= budget || block >= 4096 {
            return map;
        }
        block *= 2;
    }
}
