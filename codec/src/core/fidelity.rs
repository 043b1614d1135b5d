//! The source-error map: for each block of source cells, the largest error of the decoded
//! asset against the data that was encoded, measured at encode time and stored with the asset
//! (format version 5), so that every answer can bound its distance to the source and not only
//! to the fractal's attractor.
//!
//! An answer's `error_bound` is then the map's bound where the answer lies plus the
//! convergence bound of its iterations (`|answer - source| <= |answer - attractor| +
//! |attractor - source|`). Between source cells the source is taken as the bilinear
//! interpolation of its cell centres. The map is measured on the half-cell lattice (every cell
//! centre, corner and edge midpoint) with the asset's own continuous decoding, run to
//! convergence; a measured point's error counts for the block of each cell of its bilinear
//! support. On that lattice the bound holds; between its points the attractor can leave the
//! bilinear source further (measured: etopo20 tiles at 1.23x their bound, topobathy's at
//! 1.31x), so a projected plane's map also takes each cell's proven bound, which holds
//! everywhere in the cell (see `encode::fidelity`; other codecs keep the lattice's measure).
//! The bounds are loose, a block's largest error being far over a typical cell's
//! (mean bound 9x the mean error on jacksboro, 19x on etopo20): see docs/benchmarks.md.
//!
//! Bounds are stored as 8-bit codes on a logarithmic scale of the value span (steps of 2^(1/8),
//! about 9%), always rounded up so that a stored bound is never below the measured one, and
//! coded with the project's adaptive binary range coder (a few bits a block).

use super::format::FormatError;
use crate::core::entropy::{BitTree, Decoder, Encoder};

/// Source cells a side of a block (a power of two; 16: a bound per 256 cells, a few bits each,
/// about 1% of a DEM coded at 0.8 bits per cell).
pub(crate) const BLOCK: usize = 16;

/// The smallest non-zero code stands for `span x 2^-24`; code `k` for `span x 2^((k-1)/8 - 24)`
/// up to 254 (about 200 times the span); 255 for an unbounded error.
const SMALLEST: i32 = -24;

/// The map's share of a file: the encoder coarsens its blocks (from [`BLOCK`] cells a side,
/// doubling) until the map takes at most this fraction of the operator's bytes, and rate
/// control sets that much aside under a target size. (Measured at 0.8 bits a cell, about 5 bits
/// a block of 16 x 16: 2.3% of jacksboro's file; at 0.2 bits a cell, 16 x 16 blocks would take
/// 10% of camera's.)
pub(crate) const SHARE: f64 = 0.02;

/// The bytes set aside for the map in a file of `bytes` (at least a few, for tiny files).
pub(crate) fn reserve(bytes: usize) -> usize {
    ((bytes as f64 * SHARE) as usize).max(16)
}

/// Each block's bound on |decoded - source|, in source units.
#[derive(Clone, Debug, PartialEq)]
pub struct SourceError {
    width: usize,
    height: usize,
    block: usize,
    span: f32,
    codes: Vec<u8>,
    bounds: Vec<f32>,
}

/// The bound that code `k` stands for, for a value span `span`.
fn bound_of(k: u8, span: f32) -> f32 {
    if k == 0 {
        return 0.0;
    }
    // Beyond the scale (200 times the span): no bound.
    if k == 255 {
        return f32::INFINITY;
    }
    let exact =
        f64::from(reference(span)) * ((f64::from(k) - 1.0) / 8.0 + f64::from(SMALLEST)).exp2();
    let b = exact as f32;
    if f64::from(b) < exact { b.next_up() } else { b }
}

/// The unit of the scale: the span, or 1 for a constant source.
fn reference(span: f32) -> f32 {
    if span.is_finite() && span > 0.0 {
        span
    } else {
        1.0
    }
}

/// The smallest code whose bound is at least `e` (255, no bound, for anything beyond the
/// scale).
fn code_of(e: f32, span: f32) -> u8 {
    if e == 0.0 {
        return 0;
    }
    // NaN and negative errors are not errors the scale can hold: the largest code.
    if e.is_nan() || e < 0.0 {
        return 255;
    }
    let k = ((f64::from(e) / f64::from(reference(span))).log2() - f64::from(SMALLEST)) * 8.0 + 1.0;
    let mut k = k.floor().clamp(1.0, 255.0) as u8;
    while k < 255 && bound_of(k, span) < e {
        k += 1;
    }
    k
}

impl SourceError {
    /// A map of `width x height` cells from each block's measured error (blocks of `block`
    /// cells a side, row-major), rounded up to the stored scale.
    pub fn from_block_errors(
        width: usize,
        height: usize,
        block: usize,
        errors: &[f32],
        span: f32,
    ) -> SourceError {
        assert_eq!(errors.len(), width.div_ceil(block) * height.div_ceil(block));
        let codes: Vec<u8> = errors.iter().map(|&e| code_of(e, span)).collect();
        SourceError::from_codes(width, height, block, codes, span)
    }

    fn from_codes(width: usize, height: usize, block: usize, codes: Vec<u8>, span: f32) -> Self {
        let bounds = codes.iter().map(|&k| bound_of(k, span)).collect();
        SourceError {
            width,
            height,
            block,
            span,
            codes,
            bounds,
        }
    }

    /// Cells a side of a block.
    pub fn block(&self) -> usize {
        self.block
    }

    /// The largest bound over source cells `x0..=x1`, `y0..=y1` (clamped to the raster).
    pub fn over_cells(&self, [x0, y0, x1, y1]: [i64; 4]) -> f32 {
        let clamp = |v: i64, n: usize| v.clamp(0, n as i64 - 1) as usize / self.block;
        let (bx0, bx1) = (clamp(x0, self.width), clamp(x1, self.width));
        let (by0, by1) = (clamp(y0, self.height), clamp(y1, self.height));
        let cols = self.width.div_ceil(self.block);
        let mut worst = 0.0f32;
        for by in by0..=by1 {
            for bx in bx0..=bx1 {
                worst = worst.max(self.bounds[by * cols + bx]);
            }
        }
        worst
    }

    /// The bound at unit point (u, v) (0..1 across the raster, v down): the largest over the
    /// blocks of the cells of its bilinear support.
    pub fn at(&self, u: f32, v: f32) -> f32 {
        self.over([u, v, u, v])
    }

    /// The largest bound over the unit rectangle `[u0, v0, u1, v1]`, with the bilinear support
    /// of its edges.
    pub fn over(&self, [u0, v0, u1, v1]: [f32; 4]) -> f32 {
        // Cell centres sit at (i + 0.5) / width: a point's support is the centres around it.
        let cell = |t: f32, n: usize| (f64::from(t) * n as f64 - 0.5).floor() as i64;
        self.over_cells([
            cell(u0, self.width),
            cell(v0, self.height),
            cell(u1, self.width) + 1,
            cell(v1, self.height) + 1,
        ])
    }

    /// The largest bound of the whole map.
    pub fn largest(&self) -> f32 {
        self.bounds.iter().copied().fold(0.0, f32::max)
    }

    /// The smallest positive bound of the map (blocks of nodata measure 0 and are left out),
    /// or `None` when no block has one.
    pub fn smallest(&self) -> Option<f32> {
        self.bounds
            .iter()
            .copied()
            .filter(|&b| b > 0.0)
            .reduce(f32::min)
    }

    /// The mean of the blocks' bounds.
    pub fn mean(&self) -> f32 {
        (self.bounds.iter().map(|&b| f64::from(b)).sum::<f64>() / self.bounds.len().max(1) as f64)
            as f32
    }

    /// The stored bytes: the block size (u16) and the codes, range coded with the smaller of
    /// the west and north codes as context (neighbouring blocks have similar errors).
    pub fn encode(&self) -> Vec<u8> {
        let mut out = (self.block as u16).to_le_bytes().to_vec();
        let cols = self.width.div_ceil(self.block);
        let mut trees: Vec<BitTree> = (0..8).map(|_| BitTree::new(8)).collect();
        let mut enc = Encoder::new();
        for (i, &k) in self.codes.iter().enumerate() {
            enc.tree(&mut trees[context(&self.codes, i, cols)], u32::from(k));
        }
        out.extend(enc.finish());
        out
    }

    /// Reads what [`SourceError::encode`] wrote for a `width x height` raster whose values span
    /// `span`.
    pub fn decode(
        bytes: &[u8],
        width: usize,
        height: usize,
        span: f32,
    ) -> Result<Self, FormatError> {
        let block = match bytes {
            [a, b, ..] => usize::from(u16::from_le_bytes([*a, *b])),
            _ => return Err(FormatError::stream("the source-error map is truncated")),
        };
        if !block.is_power_of_two() || block > 4096 {
            return Err(FormatError::stream(format!(
                "bad source-error block size {block}"
            )));
        }
        let cols = width.div_ceil(block);
        let n = cols * height.div_ceil(block);
        let mut trees: Vec<BitTree> = (0..8).map(|_| BitTree::new(8)).collect();
        let mut dec = Decoder::new(&bytes[2..]);
        let mut codes = Vec::with_capacity(n);
        for i in 0..n {
            let c = context(&codes, i, cols);
            codes.push(dec.tree(&mut trees[c]) as u8);
            if dec.overrun() {
                return Err(FormatError::stream("the source-error map is truncated"));
            }
        }
        Ok(SourceError::from_codes(width, height, block, codes, span))
    }
}

/// The coding context of block `i`: the smaller of its west and north neighbours' codes, in 8
/// bands.
fn context(codes: &[u8], i: usize, cols: usize) -> usize {
    let west = (!i.is_multiple_of(cols)).then(|| codes[i - 1]);
    let north = (i >= cols).then(|| codes[i - cols]);
    let k = match (west, north) {
        (Some(a), Some(b)) => a.min(b),
        (Some(a), None) | (None, Some(a)) => a,
        (None, None) => 128,
    };
    usize::from(k / 32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_round_up_and_stay_within_a_step() {
        for span in [1.0f32, 255.0, 15_256.0, 0.0] {
            for e in [0.0f32, 1e-9, 0.003, 0.5, 1.0, 7.3, 326.0, 4000.0, f32::NAN] {
                let b = bound_of(code_of(e, span), span);
                assert!(b >= e || (e.is_nan() && b == f32::INFINITY), "{e} -> {b}");
                if b == f32::INFINITY {
                    assert!(e.is_nan() || e > 200.0 * reference(span), "{e} ({span})");
                    continue;
                }
                // Within one step of 2^(1/8) above, unless below the scale's smallest.
                let floor = reference(span) * 2f32.powi(SMALLEST);
                assert!(b <= (e * 1.0905).max(floor * 1.0001), "{e} -> {b} ({span})");
            }
        }
    }

    #[test]
    fn maps_survive_their_coding_and_refuse_truncation() {
        let (w, h) = (100usize, 37usize);
        let n = w.div_ceil(BLOCK) * h.div_ceil(BLOCK);
        let errors: Vec<f32> = (0..n).map(|i| ((i * 37 % 11) as f32 + 0.5) * 3.1).collect();
        let map = SourceError::from_block_errors(w, h, BLOCK, &errors, 2000.0);
        let bytes = map.encode();
        let back = SourceError::decode(&bytes, w, h, 2000.0).unwrap();
        assert_eq!(back, map);
        assert!(SourceError::decode(&bytes[..1], w, h, 2000.0).is_err());
        // A block's bound covers the cells of that block and the support of points near it.
        let cols = w.div_ceil(BLOCK);
        assert_eq!(map.over_cells([17, 3, 17, 3]), map.bounds[1]);
        assert!(map.at(17.5 / w as f32, 3.5 / h as f32) >= map.bounds[1]);
        assert_eq!(map.over_cells([0, 0, 99, 36]), map.largest());
        assert!(map.bounds[cols] >= errors[cols]);
    }
}
