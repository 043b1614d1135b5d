//! RGB <-> YCbCr (ITU-R BT.601, full range, as JPEG), so colour images code luma at full
//! resolution and chroma at half resolution and a lower rate (the seed's advice).

/// Converts RGB planes to Y, Cb, Cr planes; `peak` is 255 (8-bit) or 65535 (16-bit).
pub(crate) fn rgb_to_ycbcr(rgb: &[Vec<f32>], peak: f32) -> [Vec<f32>; 3] {
    let mid = (peak + 1.0) / 2.0;
    let n = rgb[0].len();
    let (mut y, mut cb, mut cr) = (
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
    );
    for ((&r, &g), &b) in rgb[0].iter().zip(&rgb[1]).zip(&rgb[2]) {
        y.push(0.299 * r + 0.587 * g + 0.114 * b);
        cb.push((mid - 0.168_736 * r - 0.331_264 * g + 0.5 * b).clamp(0.0, peak));
        cr.push((mid + 0.5 * r - 0.418_688 * g - 0.081_312 * b).clamp(0.0, peak));
    }
    [y, cb, cr]
}

/// Converts one Y, Cb, Cr sample to RGB.
#[inline]
pub(crate) fn ycbcr_to_rgb(y: f32, cb: f32, cr: f32, peak: f32) -> [f32; 3] {
    let mid = (peak + 1.0) / 2.0;
    let (cb, cr) = (cb - mid, cr - mid);
    [
        y + 1.402 * cr,
        y - 0.344_136 * cb - 0.714_136 * cr,
        y + 1.772 * cb,
    ]
}

/// Largest RGB error that Y, Cb, Cr errors of at most `by`, `bc` can cause.
pub(crate) fn rgb_bound(by: f32, bcb: f32, bcr: f32) -> f32 {
    (by + 1.402 * bcr)
        .max(by + 0.344_136 * bcb + 0.714_136 * bcr)
        .max(by + 1.772 * bcb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_within_rounding() {
        let rgb = vec![
            vec![0.0, 255.0, 12.0, 200.0],
            vec![0.0, 255.0, 250.0, 30.0],
            vec![0.0, 255.0, 99.0, 180.0],
        ];
        let [y, cb, cr] = rgb_to_ycbcr(&rgb, 255.0);
        for i in 0..4 {
            let back = ycbcr_to_rgb(y[i], cb[i], cr[i], 255.0);
            for c in 0..3 {
                assert!((back[c] - rgb[c][i]).abs() < 0.05, "{i} {c}: {back:?}");
            }
        }
    }
}
