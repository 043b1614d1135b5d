//! Heights packed into the pixels of a `raster-dem` tile as MapLibre and Mapbox read them
//! (terrain-RGB, Terrarium), and read back: the one copy of these formulas. The server packs
//! the tiles it answers, the browser's decoder (`wasm/`) packs the tiles it decodes (so both
//! paths give a map the same bytes), the client and the tests unpack.

use crate::query::HeightEncoding;

/// The height drawn where there is no data: 0 clamped into the asset's value range, so that a
/// map never sees a -10000 m hole or a spike (the camera would jump).
pub fn fill_height(value_min: f64, value_max: f64) -> f32 {
    0.0f32.clamp(value_min as f32, value_max as f32)
}

/// `x.round() as u32` for `x >= 0` without the libm call that `round` is on baseline x86-64
/// (3% of an uncached tile's time): truncating `x + 0.5` is the same below 2^23 (where adding
/// 0.5 is exact from x = 1 up; under 1 only x = 0.5 - 2^-25 differs, a height of -9999.95 m in
/// terrain-RGB), and from 2^23 up x is already an integer.
fn round_non_negative(x: f32) -> u32 {
    if x < 8_388_608.0 {
        (x + 0.5) as u32
    } else {
        x as u32
    }
}

/// Heights as RGB pixels (3 bytes each, row-major) in `encoding`, non-finite heights as
/// `fill`, rounded to multiples of `2^shift` units of the encoding (0: its full precision).
/// `None` for an encoding that is not packed into RGB (`gray16`).
pub fn pack_rgb(
    heights: &[f32],
    encoding: HeightEncoding,
    fill: f32,
    shift: u32,
) -> Option<Vec<u8>> {
    let height = |v: f32| if v.is_finite() { v } else { fill };
    // One loop per encoding into a sized buffer (a `flat_map(..).collect()` with the
    // match inside measured 7-15% of an uncached tile's time).
    let mut px = vec![0u8; heights.len() * 3];
    let cells = px.chunks_exact_mut(3).zip(heights);
    match encoding {
        HeightEncoding::TerrainRgb => {
            let scale = 10.0 / (1u32 << shift) as f32;
            for (p, &v) in cells {
                let x = ((height(v) + 10000.0) * scale).max(0.0);
                let c = (round_non_negative(x) << shift).min(0xFF_FFFF);
                p.copy_from_slice(&[(c >> 16) as u8, (c >> 8) as u8, c as u8]);
            }
        }
        HeightEncoding::Terrarium if shift > 0 => {
            // In 1/256 m units, rounded to the nearest multiple of the step (the full-precision
            // arm below truncates the fraction, as Terrarium's own tiles do).
            let scale = 256.0 / (1u32 << shift) as f32;
            for (p, &v) in cells {
                let x = ((height(v) + 32768.0) * scale).max(0.0);
                let c = (round_non_negative(x) << shift).min(0xFF_FFFF);
                p.copy_from_slice(&[(c >> 16) as u8, (c >> 8) as u8, c as u8]);
            }
        }
        HeightEncoding::Terrarium => {
            for (p, &v) in cells {
                let c = (height(v) + 32768.0).clamp(0.0, 65535.996);
                // Truncation is floor for c >= 0 (and not a libm call).
                let i = c as u32;
                p.copy_from_slice(&[
                    (i >> 8) as u8,
                    (i & 0xFF) as u8,
                    ((c - i as f32) * 256.0) as u8,
                ]);
            }
        }
        HeightEncoding::Gray16 => return None,
    }
    Some(px)
}

/// The height of one RGB pixel in `encoding` (`gray16` is no RGB encoding: NaN).
pub fn unpack_rgb(p: [u8; 3], encoding: HeightEncoding) -> f32 {
    let [r, g, b] = p.map(f64::from);
    match encoding {
        HeightEncoding::TerrainRgb => (-10000.0 + (r * 65536.0 + g * 256.0 + b) * 0.1) as f32,
        HeightEncoding::Terrarium => (r * 256.0 + g + b / 256.0 - 32768.0) as f32,
        HeightEncoding::Gray16 => f32::NAN,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values worked by hand from the formulas MapLibre documents: 1234.5 m is terrain-RGB
    /// code 112345 = (1, 182, 217) and Terrarium 34002.5 = (132, 210, 128).
    #[test]
    fn packs_the_documented_pixels_and_reads_them_back() {
        let t = pack_rgb(&[1234.5], HeightEncoding::TerrainRgb, 0.0, 0).unwrap();
        assert_eq!(t, vec![1, 182, 217]);
        let m = pack_rgb(&[1234.5], HeightEncoding::Terrarium, 0.0, 0).unwrap();
        assert_eq!(m, vec![132, 210, 128]);
        assert!((unpack_rgb([1, 182, 217], HeightEncoding::TerrainRgb) - 1234.5).abs() < 1e-3);
        assert_eq!(
            unpack_rgb([132, 210, 128], HeightEncoding::Terrarium),
            1234.5
        );
        // Nodata is the fill height; gray16 is not packed into RGB.
        let f = pack_rgb(&[f32::NAN], HeightEncoding::TerrainRgb, 12.0, 0).unwrap();
        assert!((unpack_rgb([f[0], f[1], f[2]], HeightEncoding::TerrainRgb) - 12.0).abs() < 0.06);
        assert!(pack_rgb(&[1.0], HeightEncoding::Gray16, 0.0, 0).is_none());
        assert_eq!(fill_height(100.0, 200.0), 100.0);
    }
}
