//! The lifted multiresolution of the projected codec, for rate mode: the levels of the
//! interpolating pyramid ([`super::pyramid`]) with an update step after each prediction, so that
//! each level's coarse samples are local means of the finer ones rather than a subset of them.
//!
//! Why a second multiresolution: the pyramid quantises in closed loop, which bounds every
//! sample (max-error mode) but keeps the coarse grids as point samples. At low rates most
//! details are quantised to zero, and the surface is then the subdivision of sub-sampled
//! (aliased) control points; against JPEG 2000 at the same bytes it lost 0.6-1.9 dB at 40:1
//! and 80:1 on the DEMs. A coarse grid of local means approximates the surface better at a
//! given rate (the wavelet coders' energy compaction), at the price of the per-sample bound:
//! quantisation errors spread through the synthesis, so this is rate mode's alone.
//!
//! One level is separable and in place on the pyramid's lattice (spacing s = 2^l, the level's
//! samples on multiples of s): along every row of the level the odd samples are predicted from
//! the even ones and replaced by their detail, then the even ones are updated from the
//! details; then the same along every column. What stays on multiples of 2s is the next level.
//! Two kernels ([`Kernel`]), the encoder keeps the one that codes the plane better:
//! - [`Kernel::Fitted`], the projected IFS's own: the four-point subdivision mask
//!   `m12 + a (m12 - m03)` with `a` fitted per level and axis by least squares (`a = 1/8` is
//!   Dubuc-Deslauriers), then the (4, 4) update `(9 (d-1 + d+1) - (d-3 + d+3)) / 32`;
//! - [`Kernel::Cdf97`], the four lifting steps of the CDF 9/7 wavelet (JPEG 2000's lossy one),
//!   whose smoother synthesis measured 0.1-0.25 dB better on photographs, and the same on DEMs.
//!
//! Either is a subdivision scheme: with every detail zero, the synthesis refines the coarse
//! grid towards the scheme's limit surface. Edges mirror each line about its end samples
//! (whole-sample symmetry keeps parity, so a mirrored neighbour of an odd sample is odd).
//! Decoding runs the steps backwards, each exactly inverted.
//!
//! Coefficients are quantised (rate-distortion choice against one step nearer zero, no dead
//! zone: measured, a dead zone of 0.15-0.35 step lost 0.1-0.6 dB once that choice is made) with
//! a step per band of `step / sqrt(gain)`, the gain being the energy of the band's synthesis
//! function on the finest grid (measured from the kernel and its weights), so that one step
//! spreads the squared error evenly over the bands. They are range coded band by band from the
//! coarsest, each in a context of its band's orientation and depth, its coded neighbours, its
//! sibling bands at the same place and its parent (as EBCOT and SPIHT use them): `bands.rs`.

use crate::core::entropy::{Decoder, Encoder};
use crate::core::lattice::IntCoder;

pub use super::bands::Code;
use super::bands::{Quantiser, Reader, Steps, walk};
use super::kernel::*;

/// What both sides need to know of a plane.
#[derive(Clone, Copy, Debug)]
pub struct Plane {
    /// Samples along x and y.
    pub size: [usize; 2],
    /// Levels of the transform.
    pub levels: u32,
    /// The quantiser step (source units) that the bands' steps are scaled from.
    pub step: f64,
    /// The lifting steps.
    pub kernel: Kernel,
    /// How lines continue past their ends (files of format 6 and before: mirrored).
    pub ends: Ends,
    /// How the coefficients are coded.
    pub code: Code,
}

/// The forward transform of `grid` to depth `depth` (at most `plane.levels`), in place on the
/// grid's lattice: the coarse samples on multiples of `2^depth`, details elsewhere. What a
/// reader of a coarse band needs to compare against (benches, tests).
pub fn analysis(plane: &Plane, grid: &[f64], depth: u32) -> Vec<f64> {
    let mut g = grid.to_vec();
    forward(
        &mut g,
        plane.size,
        depth.min(plane.levels),
        (plane.kernel, plane.ends),
    );
    g
}

/// Codes a grid (source units) with the lifted multiresolution and a rate-distortion weight
/// `lambda`; returns the stream and the decoded samples.
pub fn encode(plane: &Plane, source: &[f64], lambda: f64) -> (Vec<u8>, Vec<f64>) {
    let mut coefficients = source.to_vec();
    let weights = forward(
        &mut coefficients,
        plane.size,
        plane.levels,
        (plane.kernel, plane.ends),
    );
    let mut encoder = Encoder::new();
    if plane.kernel == Kernel::Fitted {
        let mut weight_coder = IntCoder::new();
        for &v in &weights {
            weight_coder.put(&mut encoder, v);
        }
    }
    let steps = Steps::new((plane.step, plane.levels, plane.kernel), &weights);
    let mut g = vec![0.0; source.len()];
    let mut quantiser = Quantiser {
        coefficients: &coefficients,
        lambda,
        encoder: &mut encoder,
    };
    walk(
        (plane.size, plane.levels, 0),
        plane.code,
        &steps,
        &mut g,
        &mut quantiser,
    );
    inverse(
        &mut g,
        (plane.size, plane.levels, 0),
        (plane.kernel, plane.ends),
        &weights,
    );
    (encoder.finish(), g)
}

/// Decodes what [`encode`] coded.
pub fn decode(plane: &Plane, decoder: &mut Decoder<'_>) -> Vec<f64> {
    decode_to(plane, decoder, 0)
}

/// The coarse band at `depth` (at most `plane.levels`) of what [`encode`] coded, decoded
/// from the stream's coarse part alone, in place on the grid's lattice (the band's samples on
/// multiples of `2^depth`, the rest of `g` meaningless) and in the band's own units (the
/// source's times [`dc_gain`] to the power `2 depth`).
pub fn decode_to(plane: &Plane, decoder: &mut Decoder<'_>, depth: u32) -> Vec<f64> {
    let depth = depth.min(plane.levels);
    let mut weights = vec![0; 2 * plane.levels as usize];
    if plane.kernel == Kernel::Fitted {
        let mut weight_coder = IntCoder::new();
        for w in &mut weights {
            *w = weight_coder
                .get(decoder)
                .clamp(WEIGHT_RANGE.0, WEIGHT_RANGE.1);
        }
    }
    let steps = Steps::new((plane.step, plane.levels, plane.kernel), &weights);
    let mut g = vec![0.0; plane.size[0] * plane.size[1]];
    walk(
        (plane.size, plane.levels, depth),
        plane.code,
        &steps,
        &mut g,
        &mut Reader { decoder },
    );
    inverse(
        &mut g,
        (plane.size, plane.levels, depth),
        (plane.kernel, plane.ends),
        &weights,
    );
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    fn surface(w: usize, h: usize) -> Vec<f64> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                (x * 0.11).sin() * 40.0 + (y * 0.07).cos() * 25.0 + (x * y * 0.0005).sin() * 3.0
            })
            .collect()
    }

    #[test]
    fn the_transform_inverts_exactly_on_any_grid_size() {
        for kernel in [Kernel::Fitted, Kernel::Cdf97] {
            for (w, h) in [(37, 29), (64, 64), (17, 100), (2, 9)] {
                let source = surface(w, h);
                let mut g = source.clone();
                let levels = super::super::pyramid::levels_for(w, h).into();
                let weights = forward(&mut g, [w, h], levels, (kernel, Ends::Mirror));
                if levels > 0 {
                    assert_ne!(g, source, "{w}x{h}: the transform changed nothing");
                }
                inverse(
                    &mut g,
                    ([w, h], levels, 0),
                    (kernel, Ends::Mirror),
                    &weights,
                );
                let worst = g
                    .iter()
                    .zip(&source)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                assert!(worst < 1e-9, "{kernel:?} {w}x{h}: off by {worst}");
            }
        }
    }

    /// Point-symmetric ends invert exactly too, and two grids that share a column (the right
    /// edge of one, the left edge of the other, as chunks of format 7 will) get the same
    /// coarse samples along it at every depth, which mirrored ends do not.
    #[test]
    fn point_symmetric_ends_give_neighbours_the_same_coarse_edge() {
        let (w, h) = (65, 33);
        let whole = surface(2 * w - 1, h);
        let part = |x0: usize| -> Vec<f64> {
            (0..h)
                .flat_map(|y| (x0..x0 + w).map(move |x| (y, x)))
                .map(|(y, x)| whole[y * (2 * w - 1) + x])
                .collect()
        };
        let (left, right) = (part(0), part(w - 1));
        for ends in [Ends::PointSymmetric, Ends::Mirror] {
            let plane = Plane {
                size: [w, h],
                levels: 3,
                step: 1.0,
                kernel: Kernel::Cdf97,
                ends,
                code: Code::Plain,
            };
            let mut g = left.clone();
            let weights = forward(&mut g, [w, h], 3, (Kernel::Cdf97, ends));
            inverse(&mut g, ([w, h], 3, 0), (Kernel::Cdf97, ends), &weights);
            let worst = g.iter().zip(&left).map(|(a, b)| (a - b).abs());
            assert!(worst.fold(0.0, f64::max) < 1e-9, "{ends:?} inverts");
            for depth in 1..=3u32 {
                let (a, b) = (
                    analysis(&plane, &left, depth),
                    analysis(&plane, &right, depth),
                );
                let seam = (0..h)
                    .step_by(1 << depth)
                    .map(|y| (a[y * w + w - 1] - b[y * w]).abs())
                    .fold(0.0, f64::max);
                match ends {
                    Ends::PointSymmetric => assert!(seam < 1e-9, "depth {depth}: {seam}"),
                    Ends::Mirror => assert!(seam > 1.0, "depth {depth}: mirrored ends agree?"),
                }
            }
        }
    }

    #[test]
    fn details_of_a_smooth_grid_are_small_and_coarse_samples_are_local_means() {
        let (w, h) = (96, 80);
        let source = surface(w, h);
        let levels = u32::from(super::super::pyramid::levels_for(w, h));
        for kernel in [Kernel::Fitted, Kernel::Cdf97] {
            let mut g = source.clone();
            forward(&mut g, [w, h], levels, (kernel, Ends::Mirror));
            // The finest HH details of a smooth surface are far below its relief.
            let hh = (1..h)
                .step_by(2)
                .flat_map(|y| (1..w).step_by(2).map(move |x| y * w + x))
                .map(|i| g[i].abs())
                .fold(0.0, f64::max);
            assert!(hh < 1.0, "{kernel:?}: finest HH up to {hh}");
        }
        // A checkerboard of +-50 on the surface: sub-sampling would keep +50 on every coarse
        // sample (they all sit on even x and y), local means cancel it.
        let board: Vec<f64> = source
            .iter()
            .enumerate()
            .map(|(i, v)| {
                v + if (i % w + i / w) % 2 == 0 {
                    50.0
                } else {
                    -50.0
                }
            })
            .collect();
        let mut g = board.clone();
        forward(&mut g, [w, h], 1, (Kernel::Fitted, Ends::Mirror));
        let worst = (0..h)
            .step_by(2)
            .flat_map(|y| (0..w).step_by(2).map(move |x| y * w + x))
            .map(|i| (g[i] - source[i]).abs())
            .fold(0.0, f64::max);
        assert!(worst < 5.0, "a coarse sample {worst} from the surface");
    }

    #[test]
    fn a_grid_decodes_as_coded_and_the_error_follows_the_step() {
        let (w, h) = (96, 80);
        let source = surface(w, h);
        let levels = u32::from(super::super::pyramid::levels_for(w, h));
        for kernel in [Kernel::Fitted, Kernel::Cdf97] {
            let mut last = 0.0;
            for step in [0.05, 0.5, 5.0] {
                let plane = Plane {
                    size: [w, h],
                    levels,
                    step,
                    kernel,
                    ends: Ends::Mirror,
                    code: Code::Plain,
                };
                let (stream, coded) = encode(&plane, &source, 0.1);
                let decoded = decode(&plane, &mut Decoder::new(&stream));
                assert_eq!(coded, decoded, "the decoder decodes what the encoder coded");
                let mse = coded
                    .iter()
                    .zip(&source)
                    .map(|(a, b)| (a - b).powi(2))
                    .sum::<f64>()
                    / source.len() as f64;
                // Uniform quantisation of step q leaves about q^2 / 12 of squared error.
                assert!(mse < step * step / 4.0, "{kernel:?} step {step}: mse {mse}");
                assert!(
                    mse > last,
                    "{kernel:?}: a coarser step made a smaller error"
                );
                last = mse;
            }
        }
    }

    mod two_rate {
        use super::super::*;
        use crate::codecs::projected::pyramid::levels_for;
        use crate::io::raster::Raster;

        fn testdata(name: &str) -> Vec<f64> {
            let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../testdata")
                .join(name);
            let r = Raster::open(&path).unwrap();
            r.channels[0].iter().map(|&v| f64::from(v)).collect()
        }

        /// On a photograph and a DEM at 0.1-0.4 and 0.6-2 bits a sample (format 9's streams at steps
        /// of 1/8 and 1/64 of their range), the two-rate code at the finest step that fits format
        /// 9's bytes has a smaller error (measured 0.22-0.72 dB at the coarse step, 0.14-0.45 at the
        /// fine one); and every stream
        /// decodes to the samples its encoder reconstructed.
        #[test]
        fn two_rate_contexts_code_real_planes_better_in_the_same_bytes() {
            for (name, size) in [("camera.png", [512, 512]), ("jacksboro.tif", [403, 344])] {
                let source = testdata(name);
                let (lo, hi) = source
                    .iter()
                    .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
                for kernel in [Kernel::Cdf97, Kernel::Fitted] {
                    for fraction in [8.0, 64.0] {
                        let code_at = |code, step| {
                            let plane = Plane {
                                size,
                                levels: u32::from(levels_for(size[0], size[1])),
                                step,
                                kernel,
                                ends: Ends::Mirror,
                                code,
                            };
                            let (stream, samples) = encode(&plane, &source, 0.1);
                            let decoded = decode(&plane, &mut Decoder::new(&stream));
                            assert_eq!(samples, decoded, "{name} {kernel:?} {code:?}");
                            let squared: f64 = samples
                                .iter()
                                .zip(&source)
                                .map(|(a, b)| (a - b).powi(2))
                                .sum();
                            (stream.len(), squared)
                        };
                        let plain = code_at(Code::Plain, (hi - lo) / fraction);
                        // Bisection on the step's logarithm for the finest that fits.
                        let (mut fine, mut coarse) = (
                            ((hi - lo) / fraction / 4.0).ln(),
                            ((hi - lo) / fraction).ln(),
                        );
                        let mut kept = code_at(Code::Contextual, coarse.exp());
                        for _ in 0..14 {
                            let mid = 0.5 * (fine + coarse);
                            let tried = code_at(Code::Contextual, mid.exp());
                            if tried.0 <= plain.0 {
                                (coarse, kept) = (mid, tried);
                            } else {
                                fine = mid;
                            }
                        }
                        assert!(kept.0 <= plain.0);
                        let gain = 10.0 * (plain.1 / kept.1).log10();
                        let least = if fraction < 10.0 { 0.15 } else { 0.08 };
                        assert!(
                            gain > least,
                            "{name} {kernel:?} 1/{fraction} ({} bytes): {gain:.3} dB",
                            plain.0
                        );
                    }
                }
            }
        }
    }
}
