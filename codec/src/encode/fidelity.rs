//! Measuring an asset's source-error map ([`SourceError`]) at encode time: the decoded asset
//! against its source on the half-cell lattice (every cell centre, corner and edge midpoint),
//! through the same continuous decoding that answers requests, run to convergence; and, for a
//! projected plane, each cell's proven bound, which holds between the lattice's points too.

use rayon::prelude::*;

use crate::core::fidelity::{BLOCK, SourceError};
use crate::geo::{Pixels, Sites};
use crate::io::asset::{Asset, PlaneOperator};
use crate::io::raster::Raster;

/// Steps at most for a measured point; each stops once within `TOLERANCE` of the span.
const ITERATIONS: u32 = 64;
/// Convergence tolerance of a measured point, as a fraction of the value span (added to the
/// point's error, so the map stays a bound on the attractor's error).
const TOLERANCE: f32 = 1e-5;

/// Lattice rows decoded at a time (a grid of them, on one core).
const BAND: usize = 32;

/// The source-error map of `asset` encoded from `source`, with blocks of [`BLOCK`] cells, or
/// coarser ones where that many would take more than `budget` bytes.
///
/// The half-cell lattice is decoded as separable grids (bands of its rows), which the
/// decoders step by blocks, bit for bit the answers of its points one by one: a point at a
/// time, with a support list each, took about two thirds of a projected encode.
pub(crate) fn measure(asset: &Asset, source: &Raster, budget: usize) -> SourceError {
    let (w, h) = (source.width, source.height);
    let span = (asset.meta.value_max - asset.meta.value_min) as f32;
    let valid = |x: usize, y: usize| source.valid.as_ref().is_none_or(|v| v[y * w + x]);
    let tolerance = TOLERANCE * span.max(f32::MIN_POSITIVE);
    // The half-cell lattice, (q / 2, r / 2) in cells: centres, corners and edge midpoints. A
    // coordinate on a centre has that cell as its support; one on a cell edge the two cells
    // beside it (clamped at the raster's edges, as the bilinear source is), equally weighted.
    let axis = |q: usize, n: usize| -> (usize, usize) {
        if q % 2 == 1 {
            ((q - 1) / 2, (q - 1) / 2)
        } else {
            ((q / 2).saturating_sub(1), (q / 2).min(n - 1))
        }
    };
    let support = |q: usize, r: usize| {
        let ((x0, x1), (y0, y1)) = (axis(q, w), axis(r, h));
        [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
    };
    let xs: Vec<Option<f32>> = (0..=2 * w)
        .map(|q| Some(q as f32 / (2 * w) as f32))
        .collect();
    let footprint = [0.5 / w as f32, 0.5 / h as f32];
    let bands: Vec<usize> = (0..=2 * h).step_by(BAND).collect();
    let lattice: Vec<Vec<f32>> = bands
        .into_par_iter()
        .flat_map_iter(|r0| {
            let r1 = (r0 + BAND).min(2 * h + 1);
            let pixels = Pixels {
                sites: Sites::Grid {
                    xs: xs.clone(),
                    ys: (r0..r1).map(|r| Some(r as f32 / (2 * h) as f32)).collect(),
                },
                footprint,
            };
            let (values, bound) = asset.sample(&pixels, ITERATIONS, tolerance);
            let row = |r: usize| -> Vec<f32> {
                (0..=2 * w)
                    .map(|q| {
                        let cells = support(q, r);
                        if cells.iter().any(|&(x, y)| !valid(x, y)) {
                            return 0.0;
                        }
                        let at = (r - r0) * (2 * w + 1) + q;
                        let mut worst = 0.0f32;
                        for (c, plane) in values.iter().enumerate() {
                            let ch = &source.channels[c];
                            let bilinear =
                                cells.iter().map(|&(x, y)| ch[y * w + x]).sum::<f32>() / 4.0;
                            let e = (plane[at] - bilinear).abs();
                            // NaN where the decode has no data: not an answer to bound.
                            if e.is_finite() {
                                worst = worst.max(e);
                            }
                        }
                        worst + bound
                    })
                    .collect()
            };
            (r0..r1).map(row).collect::<Vec<_>>()
        })
        .collect();
    let cells = proven(asset, source);
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
        // A cell's proven bound counts for the block of each of its four samples: a point in
        // the cell is looked up in the block of one of them.
        if let Some(cells) = &cells {
            for (k, &e) in cells.iter().enumerate() {
                let (x, y) = (k % (w - 1), k / (w - 1));
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    put(x + dx, y + dy, e);
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

/// Per cell between samples, the proven bound of a projected plane's answers there
/// ([`crate::codecs::projected::ProjectedOperator::cell_bounds`]): the lattice's measured errors bound the answers on the
/// lattice only. `None` for other codecs, whose maps stay measured on the lattice (a quadtree's
/// answer between lattice points has no closed form), and for colour (a projected image's
/// planes are luma and chroma, not the source's channels).
fn proven(asset: &Asset, source: &Raster) -> Option<Vec<f32>> {
    let [plane] = asset.planes() else {
        return None;
    };
    let PlaneOperator::Projected(op) = &plane.operator else {
        return None;
    };
    let lo = asset.meta.value_min as f32;
    let span = (asset.meta.value_max - asset.meta.value_min) as f32;
    let cells = op.cell_bounds(&source.channels[0], source.valid.as_deref(), (lo, span));
    (!cells.is_empty() && source.width >= 2 && source.height >= 2).then_some(cells)
}
