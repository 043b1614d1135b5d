//! How far a height tile's heights may be rounded (`precision=bound`): what its error bound
//! justifies and what its relief needs to shade without stairs.

use fractile_proto::query::HeightEncoding;

/// What part of a tile's error bound its heights may be rounded by (`precision=bound`): the
/// step is the largest power-of-two multiple of the encoding's unit not over this fraction of
/// the bound. A half keeps the rounding (at most half a step) under a quarter of the bound, so
/// the bound a tile reports grows by at most 25%, and the rounding's RMS (step / sqrt 12, at
/// most 0.14 of the bound) adds about 6% to the RMS of errors that average 0.4 of the bound
/// (the default DEM encode's bounds are 2.5-2.7 times its actual errors). A quarter, the first
/// choice, left the default encode's tiles at 1.9x TiTiler's bytes against 1.37x at a half,
/// on jacksboro at zooms 10-16 (docs/benchmarks.md).
pub const ROUNDING_FRACTION: f32 = 0.5;

/// Levels over a tile's relief that `precision=bound` keeps at least, unless a coarser step is
/// below both the data's own error and the heights' change between neighbours (see
/// [`Rounding::for_tile`]). Why: a bound is the worst case over everything a tile covers, and
/// on rough DEMs it reaches kilometres (issue 56: steps of 410-820 m on a global DEM left 8-30
/// heights a tile at zooms 5-7, a hillshade of stairs). 256 levels leave at least 256 distinct
/// steps over the relief whatever the power of two falls on (512 kept jacksboro's tiles at
/// zooms 10-16 at 36 KB, 256 at 30 KB, the bound alone at 12 KB: docs/benchmarks.md).
pub const RELIEF_LEVELS: f32 = 256.0;

/// What a tile's heights hold for its rounding: their relief (highest less lowest) and the
/// mean change between horizontal neighbours, over the heights that are numbers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Relief {
    /// Highest less lowest height (NaN for a tile without heights).
    pub span: f32,
    /// Mean |height - its left neighbour's| (NaN without a pair).
    pub gradient: f32,
}

/// The [`Relief`] of a tile's heights, rows of `side`.
pub fn relief(heights: &[f32], side: usize) -> Relief {
    let (lo, hi) = heights
        .iter()
        .filter(|h| h.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &h| {
            (a.min(h), b.max(h))
        });
    let (mut sum, mut pairs) = (0.0f64, 0usize);
    for row in heights.chunks(side.max(1)) {
        for w in row.windows(2) {
            let d = (w[1] - w[0]).abs();
            if d.is_finite() {
                sum += f64::from(d);
                pairs += 1;
            }
        }
    }
    Relief {
        span: if lo <= hi { hi - lo } else { f32::NAN },
        gradient: if pairs > 0 {
            (sum / pairs as f64) as f32
        } else {
            f32::NAN
        },
    }
}

/// How a height tile is rounded: heights go to multiples of `2^shift` units of the encoding.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Rounding {
    /// log2 of the step in the encoding's units (0: its own unit, `precision=full`).
    pub shift: u32,
    /// The most a height moves by the rounding beyond the encoding's own unit, in metres (half
    /// a step; 0 at shift 0): what the tile's bounds grow by.
    pub error: f32,
}

impl Rounding {
    /// The coarsest rounding that a tile whose error bound is `bound` justifies (see
    /// [`ROUNDING_FRACTION`]) and that keeps its heights' shading: a step of at most the
    /// relief over [`RELIEF_LEVELS`], or, where that is finer, of at most twice the asset's
    /// RMSE against its source `rmse` (a step the data's own error already blurs) and half
    /// the mean change between neighbours (so that neighbours still differ: no flat stairs in
    /// a hillshade). None for `Gray16` (its unit is the asset's range over 65535, not a height
    /// step map clients know) or a bound that is not a positive number.
    pub fn for_tile(e: HeightEncoding, bound: f32, relief: Relief, rmse: f32) -> Rounding {
        let unit = match e {
            HeightEncoding::TerrainRgb => 0.1,
            HeightEncoding::Terrarium => 1.0 / 256.0,
            HeightEncoding::Gray16 => return Rounding::default(),
        };
        let mut steps = bound * ROUNDING_FRACTION / unit;
        // A relief that is not a number (a tile of nodata) leaves the bound's step; an RMSE
        // or a gradient that is not (unknown, no pairs) leaves the relief's.
        if relief.span >= 0.0 {
            let coarser = (2.0 * rmse).min(0.5 * relief.gradient);
            steps = steps.min((relief.span / RELIEF_LEVELS).max(coarser) / unit);
        }
        if steps.is_nan() || steps < 2.0 {
            return Rounding::default();
        }
        // At most 2^20 units (terrain-RGB: 105 km; Terrarium: 4 km), far above any bound.
        let shift = (steps.log2().floor() as u32).min(20);
        Rounding {
            shift,
            error: unit * (1u32 << shift) as f32 / 2.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_takes_the_largest_power_of_two_step_under_half_the_bound() {
        // 100 m: half is 50 m, 500 units of 0.1 m; 256 units (25.6 m) is the largest power of
        // two under it. Terrarium: 50 m is 12,800 units of 1/256 m; 8192 (32 m).
        let r = Rounding::for_tile(
            HeightEncoding::TerrainRgb,
            100.0,
            Relief {
                span: f32::NAN,
                gradient: f32::NAN,
            },
            f32::NAN,
        );
        assert_eq!(r.shift, 8);
        assert!((r.error - 12.8).abs() < 1e-5);
        let t = Rounding::for_tile(
            HeightEncoding::Terrarium,
            100.0,
            Relief {
                span: f32::NAN,
                gradient: f32::NAN,
            },
            f32::NAN,
        );
        assert_eq!(t.shift, 13);
        assert!((t.error - 16.0).abs() < 1e-5);
        // Under two units of the encoding, and where no bound is known: full precision.
        for b in [0.3, 0.0, f32::NAN, -3.0] {
            assert_eq!(
                Rounding::for_tile(
                    HeightEncoding::TerrainRgb,
                    b,
                    Relief {
                        span: f32::NAN,
                        gradient: f32::NAN
                    },
                    f32::NAN
                ),
                Rounding::default()
            );
        }
        assert_eq!(
            Rounding::for_tile(
                HeightEncoding::Gray16,
                100.0,
                Relief {
                    span: f32::NAN,
                    gradient: f32::NAN
                },
                f32::NAN
            ),
            Rounding::default()
        );
    }

    #[test]
    fn a_tiles_relief_keeps_its_shading_whatever_its_bound() {
        let flat = |span, gradient| Relief { span, gradient };
        // A 1 km bound over 2,000 m of relief, neighbours 1 m apart, RMSE 50 m: half the bound
        // (5,000 units of 0.1 m) would leave 4 steps; the relief over 256 levels is 78 units,
        // so 64 (6.4 m): 312 steps.
        let r = Rounding::for_tile(HeightEncoding::TerrainRgb, 1000.0, flat(2000.0, 1.0), 50.0);
        assert_eq!(r.shift, 6);
        // Neighbours 100 m apart: half of it (50 m) and twice the RMSE (100 m) allow 500
        // units, so 256 (25.6 m).
        let r = Rounding::for_tile(
            HeightEncoding::TerrainRgb,
            1000.0,
            flat(2000.0, 100.0),
            50.0,
        );
        assert_eq!(r.shift, 8);
        // ... but not past twice the RMSE: 5 m allow 100 units, so 64 (6.4 m, the relief's).
        let r = Rounding::for_tile(HeightEncoding::TerrainRgb, 1000.0, flat(2000.0, 100.0), 2.5);
        assert_eq!(r.shift, 6);
        // A flat tile keeps full precision whatever the bound.
        for span in [20.0, 0.0] {
            assert_eq!(
                Rounding::for_tile(HeightEncoding::TerrainRgb, 1000.0, flat(span, 0.0), 50.0),
                Rounding::default()
            );
        }
        // The bound's step where it is the finer one; an unknown relief leaves it.
        let nan = flat(f32::NAN, f32::NAN);
        assert_eq!(
            Rounding::for_tile(HeightEncoding::TerrainRgb, 100.0, flat(1e6, 1e4), 1e4),
            Rounding::for_tile(HeightEncoding::TerrainRgb, 100.0, nan, f32::NAN)
        );
        let r = relief(&[0.0, 3.0, f32::NAN, -2.0, 1.0, 1.0], 3);
        assert_eq!(r.span, 5.0);
        // Pairs (0, 3) and (-2, 1), (1, 1): the pair with a NaN is not one.
        assert!((r.gradient - 2.0).abs() < 1e-6);
        assert!(relief(&[f32::NAN], 1).span.is_nan());
    }
}
