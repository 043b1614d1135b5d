//! One affine map of a partitioned IFS: the isometry that orients a domain onto its range, and the
//! quantisation of contrast `s` and offset `o`.
//!
//! Offsets are coded in the interval that keeps `o + s*x` inside [0, 1] for every x in [0, 1]:
//! `[max(0, -s), max(0, -s) + 1 - |s|]`. Two gains: the quantiser is finer where |s| is large (where
//! an offset error is amplified by 1/(1-|s|) in the attractor), and [0, 1] is invariant under every
//! operator we write, so the decoders' error bound never needs more than the asset itself.

use super::format::FormatError;
use serde::{Deserialize, Serialize};

/// Number of isometries of the square (the dihedral group D4).
pub(crate) const SQUARE_ISOMETRIES: u8 = 8;

/// Applies isometry `k` (0..8) to a point of the unit square.
///
/// 0 identity, 1 mirror x, 2 mirror y, 3 rotate 180, 4 transpose, 5..7 the transposes of 1..3.
/// The reference the decoders' matrices (`ISOMETRY_MATRICES`) and the index form below are
/// tested against; the decoders use those.
#[cfg(test)]
pub(crate) fn isometry(k: u8, a: f32, b: f32) -> (f32, f32) {
    let (a, b) = if k & 4 != 0 { (b, a) } else { (a, b) };
    let a = if k & 1 != 0 { 1.0 - a } else { a };
    let b = if k & 2 != 0 { 1.0 - b } else { b };
    (a, b)
}

/// The same isometry on the pixel grid of an n x n block: where pixel (i, j) of the range reads
/// in the (downsampled) domain block.
#[inline(always)]
pub(crate) fn isometry_index(k: u8, i: usize, j: usize, n: usize) -> (usize, usize) {
    let (i, j) = if k & 4 != 0 { (j, i) } else { (i, j) };
    let i = if k & 1 != 0 { n - 1 - i } else { i };
    let j = if k & 2 != 0 { n - 1 - j } else { j };
    (i, j)
}

/// `v.round()` (half away from zero, the sign of zero kept), bit for bit, without the call into
/// libm that `f64::round` is on baseline x86-64 (no SSE4.1 `roundsd`): 10% of a projected
/// plane's decode went to that call (issue 75). Below 2^51, adding and taking away 1.5 x 2^52
/// rounds to the nearest integer, ties to even (the sums are exact in between), and a tie goes
/// half a unit away from zero instead; past that, libm's (no prediction gets there).
#[inline(always)]
pub(crate) fn round_half_away(v: f64) -> f64 {
    const SHIFT: f64 = 6_755_399_441_055_744.0;
    if v.abs() < 2_251_799_813_685_248.0 {
        let even = (v + SHIFT) - SHIFT;
        if (v - even).abs() == 0.5 {
            // A tie (rare on predictions: a branch taken seldom costs nothing).
            v + 0.5f64.copysign(v)
        } else {
            even.copysign(v)
        }
    } else {
        v.round()
    }
}

#[cfg(test)]
mod rounding {
    /// [`super::round_half_away`] is `f64::round` on ties, near-ties, both signs, zeros, the
    /// ends of its fast range and beyond, and not finite values.
    #[test]
    fn round_half_away_is_libm_round() {
        let mut cases = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.5,
            -1.5,
            2.5,
            -2.5,
            0.49999999999999994,
        ];
        cases.extend([
            -0.49999999999999994,
            4503599627370495.5,
            -4503599627370495.5,
        ]);
        cases.extend([2251799813685247.5, -2251799813685247.5, 2251799813685248.5]);
        cases.extend([
            1e300,
            -1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            1e-310,
            -1e-310,
        ]);
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        for k in 0..200_000 {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let scale = [1.0, 1e3, 1e6, 1e12, 1e15][k % 5];
            let v = ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * scale;
            cases.extend([v, (v * 2.0).round() / 2.0]);
        }
        for v in cases {
            let (got, want) = (super::round_half_away(v), v.round());
            assert_eq!(got.to_bits(), want.to_bits(), "{v}: {got} against {want}");
        }
        assert!(super::round_half_away(f64::NAN).is_nan());
    }
}

/// How contrast and offset are quantised; stored in each plane header.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quantiser {
    /// Bits of the contrast index (levels -L..=L with L = 2^(bits-1) - 1).
    pub contrast_bits: u8,
    /// Bits of the offset index.
    pub offset_bits: u8,
    /// Largest |s|; below 1 so that every map contracts.
    pub max_contrast: f32,
    /// Bits of each slope index of the planar offset term (0: constant offsets, the seed's
    /// classic codec). A slope is the rise of g across the range, in [-1, 1] of the value range.
    #[serde(default)]
    pub slope_bits: u8,
}

impl Default for Quantiser {
    fn default() -> Self {
        Quantiser {
            contrast_bits: 5,
            offset_bits: 7,
            max_contrast: 0.9,
            slope_bits: 0,
        }
    }
}

impl Quantiser {
    /// Checks the ranges a header may hold (a corrupt asset must not reach the decoder).
    pub fn validate(&self) -> Result<(), FormatError> {
        if !(2..=8).contains(&self.contrast_bits) || !(1..=12).contains(&self.offset_bits) {
            return Err(FormatError::header(format!(
                "quantiser bits out of range: contrast {} (2..=8), offset {} (1..=12)",
                self.contrast_bits, self.offset_bits
            )));
        }
        if self.slope_bits == 1 || self.slope_bits > 12 {
            return Err(FormatError::header(format!(
                "slope bits {} not 0 or in 2..=12",
                self.slope_bits
            )));
        }
        if !(self.max_contrast > 0.0 && self.max_contrast < 1.0) {
            return Err(FormatError::header(format!(
                "max contrast {} is not in (0, 1)",
                self.max_contrast
            )));
        }
        Ok(())
    }

    /// L, the largest contrast index.
    pub fn contrast_levels(&self) -> i32 {
        (1 << (self.contrast_bits - 1)) - 1
    }

    /// Index of the contrast nearest to `s` (clamped to ±max).
    pub fn contrast_index(&self, s: f32) -> i32 {
        let l = self.contrast_levels();
        ((s / self.max_contrast) * l as f32)
            .round()
            .clamp(-l as f32, l as f32) as i32
    }

    /// Contrast of an index.
    pub fn contrast(&self, q: i32) -> f32 {
        q as f32 * self.max_contrast / self.contrast_levels() as f32
    }

    /// Largest offset index.
    pub fn offset_levels(&self) -> u32 {
        (1u32 << self.offset_bits) - 1
    }

    fn offset_interval(s: f32) -> (f32, f32) {
        ((-s).max(0.0), 1.0 - s.abs())
    }

    /// Index of the offset nearest to `o`, given the (quantised) contrast `s`.
    pub fn offset_index(&self, s: f32, o: f32) -> u32 {
        let (lo, width) = Self::offset_interval(s);
        let m = self.offset_levels();
        (((o - lo) / width) * m as f32).round().clamp(0.0, m as f32) as u32
    }

    /// Offset of an index, given the contrast.
    pub fn offset(&self, s: f32, q: u32) -> f32 {
        let (lo, width) = Self::offset_interval(s);
        lo + width * q as f32 / self.offset_levels() as f32
    }

    /// Largest slope index (slopes take indices -S..=S).
    pub fn slope_levels(&self) -> i32 {
        if self.slope_bits < 2 {
            0
        } else {
            (1 << (self.slope_bits - 1)) - 1
        }
    }

    /// Index of the rise nearest to `rise` (the change of g across the range).
    pub fn slope_index(&self, rise: f32) -> i32 {
        let l = self.slope_levels();
        (rise * l as f32).round().clamp(-l as f32, l as f32) as i32
    }

    /// Rise of a slope index.
    pub fn slope(&self, q: i32) -> f32 {
        let l = self.slope_levels();
        if l == 0 { 0.0 } else { q as f32 / l as f32 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn isometries_agree_on_pixel_centres_and_form_a_group() {
        let n = 6;
        for k in 0..SQUARE_ISOMETRIES {
            let mut seen = vec![false; n * n];
            for j in 0..n {
                for i in 0..n {
                    let (a, b) =
                        isometry(k, (i as f32 + 0.5) / n as f32, (j as f32 + 0.5) / n as f32);
                    let (ii, jj) = isometry_index(k, i, j, n);
                    assert!((a * n as f32 - 0.5 - ii as f32).abs() < 1e-5);
                    assert!((b * n as f32 - 0.5 - jj as f32).abs() < 1e-5);
                    seen[jj * n + ii] = true;
                }
            }
            assert!(seen.iter().all(|&s| s), "isometry {k} is not a bijection");
        }
        // The 8 maps are distinct.
        let images: std::collections::HashSet<_> = (0..SQUARE_ISOMETRIES)
            .map(|k| {
                let (a, b) = isometry(k, 0.1, 0.3);
                ((a * 100.0) as i32, (b * 100.0) as i32)
            })
            .collect();
        assert_eq!(images.len(), 8);
    }

    proptest! {
        #[test]
        fn quantised_maps_contract_and_keep_the_unit_interval(
            s in -2.0f32..2.0, o in -2.0f32..3.0, cb in 2u8..8, ob in 1u8..12, smax in 0.05f32..0.99
        ) {
            let q = Quantiser { contrast_bits: cb, offset_bits: ob, max_contrast: smax, slope_bits: 0 };
            let sq = q.contrast(q.contrast_index(s));
            prop_assert!(sq.abs() < 1.0);
            prop_assert!(sq.abs() <= smax + 1e-6);
            let oq = q.offset(sq, q.offset_index(sq, o));
            for x in [0.0f32, 1.0] {
                let y = oq + sq * x;
                prop_assert!((-1e-6..=1.0 + 1e-6).contains(&y), "{} + {} * {} = {}", oq, sq, x, y);
            }
        }
    }
}
