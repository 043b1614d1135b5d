//! Error measures between a source and a decoded grid, over valid cells only.

use serde::Serialize;

/// Errors of a decoded grid against its source.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Errors {
    /// Root mean square error.
    pub rmse: f64,
    /// Mean absolute error.
    pub mae: f64,
    /// Largest absolute error.
    pub max_error: f64,
    /// PSNR in dB for the given peak (infinite when identical).
    pub psnr: f64,
    /// Samples compared.
    pub samples: u64,
}

/// Compares channel planes sample by sample where `valid` (if any) holds; NaNs in either side are
/// skipped as nodata.
pub fn compare(
    source: &[Vec<f32>],
    decoded: &[Vec<f32>],
    valid: Option<&[bool]>,
    peak: f64,
) -> Errors {
    let (mut se, mut ae, mut max, mut n) = (0.0f64, 0.0f64, 0.0f64, 0u64);
    for (s, d) in source.iter().zip(decoded) {
        for (i, (&a, &b)) in s.iter().zip(d).enumerate() {
            if valid.is_some_and(|v| !v[i]) || !a.is_finite() || !b.is_finite() {
                continue;
            }
            let e = (a as f64 - b as f64).abs();
            se += e * e;
            ae += e;
            max = max.max(e);
            n += 1;
        }
    }
    let n_f = n.max(1) as f64;
    let rmse = (se / n_f).sqrt();
    Errors {
        rmse,
        mae: ae / n_f,
        max_error: max,
        psnr: if rmse > 0.0 {
            20.0 * (peak / rmse).log10()
        } else {
            f64::INFINITY
        },
        samples: n,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_of_a_known_error() {
        // Every sample off by 1 on peak 255: 20 log10(255) = 48.13 dB.
        let a = vec![vec![10.0f32; 100]];
        let b = vec![vec![11.0f32; 100]];
        let e = compare(&a, &b, None, 255.0);
        assert!((e.psnr - 48.1308).abs() < 1e-3);
        assert_eq!(e.max_error, 1.0);
        // Masked samples do not count.
        let mut c = b.clone();
        c[0][3] = 200.0;
        let mut valid = vec![true; 100];
        valid[3] = false;
        assert_eq!(compare(&a, &c, Some(&valid), 255.0).max_error, 1.0);
    }
}
