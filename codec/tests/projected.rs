//! The projected codec on real DEMs: its promise (the max-error bound at every cell, lossless at
//! 0 on integer data), against the anchors the issue names (JPEG-LS near-lossless at the same
//! bound), what a corrupt stream gets, and its continuation past the source (the 4x zoom test:
//! PSNR against bicubic, and the power of the finest octave against the real finer DEM's).

use fractile_codec::Method;
use fractile_codec::asset::{Asset, Coding};
use fractile_codec::codecs::projected::{ProjectedHeader, ProjectedSettings};
use fractile_codec::raster::Raster;
use fractile_proto::AssetKind;

fn testdata(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// JPEG-LS near-lossless ratios at a bound of 10 m (CharLS through imagecodecs, NEAR=10, as
/// quoted in issue 29): the bar at the same bound.
const JPEG_LS_AT_10: [(&str, f64); 2] = [("etopo20.tif", 4.45), ("jacksboro.tif", 10.6)];

/// What f32 rounding may add to a bound: decoded values are f32 fractions of the asset's value
/// range, so one unit in their last place (2^-23 of the range: 1.8 mm on etopo20).
fn rounding(r: &Raster) -> f64 {
    let (lo, hi) = r.value_range();
    (hi - lo) * 2f64.powi(-23)
}

#[test]
fn max_error_holds_at_every_cell_of_real_dems_read_back_from_their_bytes() {
    for name in ["etopo20.tif", "jacksboro.tif", "topobathy.tif"] {
        let r = Raster::open(&testdata(name)).expect("testdata");
        for e in [0.0, 1.0, 10.0, 37.5] {
            let s = ProjectedSettings {
                max_error: Some(e),
                ..Default::default()
            };
            let enc = fractile_codec::encode(&r, &s, &|_, _| {}).expect("encode");
            let asset = Asset::from_bytes(&enc.bytes).expect("read back");
            assert_eq!(asset.codec_name(), "projected");
            let (d, _) = asset.decode_native();
            let slack = rounding(&r);
            let mut over = 0;
            let mut worst = 0.0f64;
            for (i, (&src, &dec)) in r.channels[0].iter().zip(&d.channels[0]).enumerate() {
                if r.valid.as_ref().is_some_and(|v| !v[i]) {
                    continue;
                }
                let err = f64::from((dec - src).abs());
                worst = worst.max(err);
                if err > e + slack {
                    over += 1;
                }
            }
            println!(
                "{name} E={e}: {:.2}:1, worst {worst:.4}, PSNR {:.2} dB",
                enc.ratio(),
                enc.errors.psnr
            );
            assert_eq!(
                over, 0,
                "{name} E={e}: {over} cells over the bound (worst {worst})"
            );
            // A bound that is not used is a wasted one: the worst error reaches it (to the
            // quantum of integer data).
            assert!(worst >= e.floor() - 1e-3, "{name} E={e}: worst {worst}");
        }
    }
}

#[test]
fn max_error_10_codes_smaller_than_jpeg_ls_near_lossless() {
    for (name, jpeg_ls) in JPEG_LS_AT_10 {
        let r = Raster::open(&testdata(name)).expect("testdata");
        let s = ProjectedSettings {
            max_error: Some(10.0),
            ..Default::default()
        };
        let enc = fractile_codec::encode(&r, &s, &|_, _| {}).expect("encode");
        println!("{name}: {:.2}:1 against JPEG-LS {jpeg_ls}:1", enc.ratio());
        assert!(
            enc.ratio() >= jpeg_ls,
            "{name}: {:.3}:1 under JPEG-LS's {jpeg_ls}:1",
            enc.ratio()
        );
    }
}

#[test]
fn a_corrupt_or_truncated_stream_is_an_error() {
    let r = Raster::open(&testdata("jacksboro.tif")).expect("testdata");
    let bounded = ProjectedSettings {
        max_error: Some(2.0),
        ..Default::default()
    };
    // The pyramid (max error) and the lifted levels (rate).
    for (settings, bpp) in [(bounded, None), (ProjectedSettings::default(), Some(0.8))] {
        let enc = fractile_codec::encode(
            &r,
            &ProjectedSettings {
                target_bpp: bpp,
                ..settings.clone()
            },
            &|_, _| {},
        )
        .expect("encode");
        let Coding::Projected { header, stream } = &enc.asset.planes()[0].coding else {
            panic!("a projected plane");
        };
        let meta = enc.asset.meta.clone();
        let part =
            |h: ProjectedHeader, s: Vec<u8>| Asset::from_coded(meta.clone(), vec![(h, s)], None);
        assert!(part(header.clone(), stream.clone()).is_ok());
        for cut in [0, 10, stream.len() / 2] {
            let e = part(header.clone(), stream[..cut].to_vec()).expect_err("truncated");
            assert!(
                e.to_string().contains("projected"),
                "{:?}: {e}",
                header.order
            );
        }
        let mut bad = header.clone();
        bad.levels = 40;
        assert!(part(bad, stream.clone()).is_err());
        let mut bad = header.clone();
        bad.roughness = 1.5;
        assert!(part(bad, stream.clone()).is_err());
        if header.order.lifting().is_some() {
            // A lifted plane promises nothing per sample: a header that says it does is not
            // one an encoder wrote.
            let mut bad = header.clone();
            bad.quantum = 1.0;
            assert!(part(bad, stream.clone()).is_err());
        }
    }
}

/// Power of the finest octave of a grid's spectrum: the part of its 2D power spectrum with a
/// frequency over a quarter cycle a sample along x or y. The grid is mean-removed and Hann
/// windowed first: the FFT sees it as periodic, and the jump between opposite edges would
/// otherwise leak into every frequency (on etopo20 it was half the finest octave's power).
fn finest_octave_power(v: &[f32], w: usize, h: usize) -> f64 {
    use rustfft::{FftPlanner, num_complex::Complex};
    let mean = v.iter().map(|&x| f64::from(x)).sum::<f64>() / v.len() as f64;
    let hann = |i: usize, n: usize| {
        0.5 - 0.5 * (2.0 * std::f64::consts::PI * (i as f64 + 0.5) / n as f64).cos()
    };
    let mut a: Vec<Complex<f64>> = v
        .iter()
        .enumerate()
        .map(|(i, &x)| {
            let k = hann(i % w, w) * hann(i / w, h);
            Complex::new((f64::from(x) - mean) * k, 0.0)
        })
        .collect();
    let mut planner = FftPlanner::new();
    let (fw, fh) = (planner.plan_fft_forward(w), planner.plan_fft_forward(h));
    for row in a.chunks_exact_mut(w) {
        fw.process(row);
    }
    let mut col = vec![Complex::new(0.0, 0.0); h];
    let mut total = 0.0;
    for x in 0..w {
        for y in 0..h {
            col[y] = a[y * w + x];
        }
        fh.process(&mut col);
        let fx = x.min(w - x) as f64 / w as f64;
        for (y, c) in col.iter().enumerate() {
            let fy = y.min(h - y) as f64 / h as f64;
            if fx > 0.25 || fy > 0.25 {
                total += c.norm_sqr();
            }
        }
    }
    total
}

/// The 4x zoom test of issue 29: a copy of a DEM 4x coarser (block means) is encoded, decoded at
/// 4x by continuous extraction, and compared with the real DEM.
struct Zoom {
    psnr: f64,
    bicubic_psnr: f64,
    octave: f64,
    bicubic_octave: f64,
}

fn zoom(name: &str) -> Zoom {
    let r = Raster::open(&testdata(name)).expect("testdata");
    let (cw, ch) = (r.width / 4, r.height / 4);
    let (w, h) = (4 * cw, 4 * ch);
    let fine: Vec<f32> = (0..w * h)
        .map(|i| r.channels[0][(i / w) * r.width + i % w])
        .collect();
    let coarse: Vec<f32> = (0..cw * ch)
        .map(|i| {
            let (x, y) = (i % cw, i / cw);
            let mut s = 0.0f64;
            for k in 0..16 {
                s += f64::from(fine[(4 * y + k / 4) * w + 4 * x + k % 4]);
            }
            (s / 16.0) as f32
        })
        .collect();
    let c = Raster::from_values(cw, ch, coarse.clone(), AssetKind::HeightField).expect("coarse");
    let s = ProjectedSettings {
        max_error: Some(0.5),
        ..Default::default()
    };
    let enc = fractile_codec::encode(&c, &s, &|_, _| {}).expect("encode");
    let (d, _) = enc
        .asset
        .window([0.0, 0.0, 1.0, 1.0], w, h, Some(40), Method::Continuous);
    let (lo, hi) = fine
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let img = image::ImageBuffer::<image::Luma<f32>, Vec<f32>>::from_raw(
        cw as u32,
        ch as u32,
        // image's f32 filters clamp to 0..1: resize normalised heights.
        coarse.iter().map(|v| (v - lo) / (hi - lo)).collect(),
    )
    .expect("grid");
    let bicubic: Vec<f32> = image::imageops::resize(
        &img,
        w as u32,
        h as u32,
        image::imageops::FilterType::CatmullRom,
    )
    .into_raw()
    .into_iter()
    .map(|v| lo + v * (hi - lo))
    .collect();
    let psnr = |v: &[f32]| {
        let mse = v
            .iter()
            .zip(&fine)
            .map(|(a, b)| f64::from(a - b).powi(2))
            .sum::<f64>()
            / v.len() as f64;
        10.0 * (f64::from(hi - lo).powi(2) / mse).log10()
    };
    let real = finest_octave_power(&fine, w, h);
    Zoom {
        psnr: psnr(&d.channels[0]),
        bicubic_psnr: psnr(&bicubic),
        octave: finest_octave_power(&d.channels[0], w, h) / real,
        bicubic_octave: finest_octave_power(&bicubic, w, h) / real,
    }
}

/// Measured, not all of issue 29's bar: the continuation keeps a tenth or more of the real
/// finest octave where bicubic keeps almost none, within a few dB of bicubic's PSNR. Both halves
/// of the bar at once (half the power within 0.5 dB) are out of reach of a linear self-similar
/// continuation: its details are not correlated with the real ones, so each unit of their power
/// is a unit of error (the sweep of rho is in docs/benchmarks.md).
#[test]
fn zoom_past_the_source_continues_the_roughness() {
    for name in ["etopo20.tif", "jacksboro.tif"] {
        let z = zoom(name);
        println!(
            "{name} 4x: PSNR {:.2} dB (bicubic {:.2}), finest-octave power {:.1}% of the real DEM's (bicubic {:.2}%)",
            z.psnr,
            z.bicubic_psnr,
            100.0 * z.octave,
            100.0 * z.bicubic_octave
        );
        assert!(
            z.bicubic_octave < 0.01,
            "{name}: bicubic keeps {}",
            z.bicubic_octave
        );
        assert!(
            z.octave > 10.0 * z.bicubic_octave && z.octave < 2.0,
            "{name}: finest octave {:.4} of the real DEM's",
            z.octave
        );
        assert!(
            z.psnr >= z.bicubic_psnr - 3.0,
            "{name}: {:.2} dB against bicubic's {:.2}",
            z.psnr,
            z.bicubic_psnr
        );
    }
}

#[test]
fn rate_control_fits_its_target_and_reaches_jpeg_2000_on_etopo20() {
    // Issue 29's bar: JPEG 2000 (OpenJPEG) gives 47.2 dB on etopo20 at 20:1 (0.8 bpp); the
    // quadtree 43.2 dB.
    let r = Raster::open(&testdata("etopo20.tif")).expect("testdata");
    let enc = fractile_codec::encode(
        &r,
        &ProjectedSettings {
            target_bpp: Some(0.8),
            ..ProjectedSettings::default()
        },
        &|_, _| {},
    )
    .expect("encode");
    println!(
        "etopo20 at 0.8 bpp: {:.3} bpp, {:.2} dB",
        enc.bpp(),
        enc.errors.psnr
    );
    assert!(enc.bpp() <= 0.8, "{} bpp", enc.bpp());
    // A file more than 1% under its rate is coded again with the slack.
    assert!(
        enc.bpp() >= 0.99 * 0.8,
        "rate control left {} bpp unused",
        0.8 - enc.bpp()
    );
    assert!(enc.errors.psnr >= 47.2, "{:.2} dB", enc.errors.psnr);
}

#[test]
fn lifted_levels_beat_the_closed_loop_pyramid_at_low_rates() {
    // At 80:1 most details are zero: the pyramid then subdivides sub-sampled control points,
    // the lifted levels local means (measured 1.0-1.2 dB apart on both DEMs with one-rate
    // contexts; format 9's two-rate contexts, which code the pyramid's many zeros for less,
    // brought jacksboro to 0.49 dB apart).
    for name in ["jacksboro.tif", "etopo20.tif"] {
        let r = Raster::open(&testdata(name)).expect("testdata");
        let lifted = fractile_codec::encode(
            &r,
            &ProjectedSettings {
                target_bpp: Some(0.2),
                ..ProjectedSettings::default()
            },
            &|_, _| {},
        )
        .expect("lifted");
        let pyramid = ProjectedSettings {
            pyramid: true,
            ..Default::default()
        };
        let pyramid = fractile_codec::encode(
            &r,
            &ProjectedSettings {
                target_bpp: Some(0.2),
                ..pyramid.clone()
            },
            &|_, _| {},
        )
        .expect("pyramid");
        println!(
            "{name} at 0.2 bpp: lifted {:.2} dB at {:.3} bpp, pyramid {:.2} dB at {:.3} bpp",
            lifted.errors.psnr,
            lifted.bpp(),
            pyramid.errors.psnr,
            pyramid.bpp()
        );
        assert!(lifted.bpp() <= 0.2 && pyramid.bpp() <= 0.2);
        // The allowance for the rest of the file (12% of a small one) is given back to the
        // streams where it was not needed.
        assert!(lifted.bpp() >= 0.99 * 0.2, "{name}: {} bpp", lifted.bpp());
        assert!(
            lifted.errors.psnr >= pyramid.errors.psnr + 0.3,
            "{name}: lifted {:.2} dB, pyramid {:.2} dB",
            lifted.errors.psnr,
            pyramid.errors.psnr
        );
    }
}

/// Issue 34's bar on projected assets: at 10,000 random cell centres, every answer within its
/// `error_bound` (the source-error map, or the encoder's promise at a sample centre, plus
/// convergence), and under `--max-error` or a bounded rate (the DEM default) the mean bound
/// within 4x of the mean error.
#[test]
fn error_bounds_hold_and_are_tight_at_random_cell_centres() {
    for name in ["jacksboro.tif", "etopo20.tif", "topobathy.tif"] {
        let src = Raster::open(&testdata(name)).expect("testdata");
        for (label, settings, bpp) in [
            (
                "--max-error 10",
                ProjectedSettings {
                    max_error: Some(10.0),
                    ..Default::default()
                },
                None,
            ),
            ("--target-bpp 0.8", ProjectedSettings::default(), Some(0.8)),
            (
                "--target-bpp 0.8 --bounded",
                ProjectedSettings {
                    bounded: true,
                    ..Default::default()
                },
                Some(0.8),
            ),
        ] {
            let enc = fractile_codec::encode(
                &src,
                &ProjectedSettings {
                    target_bpp: bpp,
                    ..settings.clone()
                },
                &|_, _| {},
            )
            .expect("encode");
            let asset = Asset::from_bytes(&enc.bytes).expect("read back");
            let (w, h) = (src.width, src.height);
            let mut state = 34u64;
            let mut next = |n: usize| {
                state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
                let mut z = state;
                z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                ((z ^ (z >> 31)) % n as u64) as usize
            };
            let cells: Vec<(usize, usize)> = (0..10_000).map(|_| (next(w), next(h))).collect();
            let pts: Vec<[f32; 2]> = cells
                .iter()
                .map(|&(x, y)| [(x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32])
                .collect();
            // As the server answers a request that names neither steps nor a tolerance: its
            // step limit, at the asset's default tolerance (an eighth of the smallest source
            // error here), which each chain's convergence bound must then be within
            let tolerance = asset.default_tolerance();
            let smallest = asset.source_error.as_ref().and_then(|m| m.smallest());
            // (or of the promise at sample centres, where that is smaller)
            let promise = asset.planes()[0].promise().unwrap_or(f32::INFINITY);
            assert_eq!(
                tolerance,
                (0.5f32).max(smallest.expect("a map").min(promise) / 8.0),
                "{name} {label}"
            );
            let answers = asset.points(&pts, 64, tolerance);
            let (mut actual, mut bound) = (0.0f64, 0.0f64);
            for (&(x, y), a) in cells.iter().zip(&answers) {
                let error = (a.values[0] - src.channels[0][y * w + x]).abs();
                // Within the f32 rounding floor that chains add to their bounds: a few ulps of
                // the range a step (`ProjectedOperator::run_chains`), at most 64 steps.
                let span = (asset.meta.value_max - asset.meta.value_min) as f32;
                let floor = (64 + 4) as f32 * 2f32.powi(-21) * 1.5 * span;
                assert!(
                    a.error_bound <= tolerance + floor,
                    "{name} {label}: converged to {}, tolerance {tolerance}",
                    a.error_bound
                );
                let b = a.source_error.expect("a map") + a.error_bound;
                assert!(
                    error <= b,
                    "{name} {label} ({x}, {y}): off by {error}, bound {b}"
                );
                actual += f64::from(error);
                bound += f64::from(b);
            }
            let ratio = bound / actual;
            println!(
                "{name} {label}: mean error {:.2}, mean bound {:.2} ({ratio:.2}x), default tolerance {tolerance:.2}",
                actual / cells.len() as f64,
                bound / cells.len() as f64
            );
            // The promise makes the bound at sample centres; under rate control the map alone
            // bounds them, with the heavier tail of a dead-zone quantiser (reported).
            if settings.max_error.is_some() || settings.bounded {
                assert!(ratio <= 4.0, "{name} {label}: bound {ratio:.2}x the error");
            }
            if settings.bounded {
                // This is what a height field gets when no codec is named (the same coded
                // planes; the files differ in the encode time they record).
                let default = fractile_codec::encode_default(&src, 0.8, &|_, _| {})
                    .expect("the default encode");
                let read = Asset::from_bytes(&default.bytes).expect("read back");
                assert_eq!(read.codec_name(), "projected", "{name}");
                assert_eq!(default.bytes.len(), enc.bytes.len(), "{name}");
                assert_eq!(
                    read.planes()[0].promise(),
                    asset.planes()[0].promise(),
                    "{name}"
                );
                // The rate is kept, and the bound found is the one the asset keeps.
                assert!(enc.bpp() <= 0.8, "{name} {label}: {} bpp", enc.bpp());
                let promise = asset.planes()[0]
                    .promise()
                    .expect("a bounded encode promises");
                assert!(
                    enc.errors.max_error <= f64::from(promise),
                    "{name} {label}: max error {} over the promise {promise}",
                    enc.errors.max_error
                );
            }
        }
    }
}

#[test]
fn colour_images_code_as_luma_and_chroma_at_the_resolution_that_codes_better() {
    let r = Raster::open(&testdata("astronaut.png")).expect("testdata");
    // JPEG at these rates gives 27.7 and 36.99 dB on it (the codec bench at 0.5 and 2 bpp; it
    // cannot reach 0.25), JPEG 2000 28.65 and 40.70; a broken chroma path is far under.
    for (bpp, chroma, floor) in [(0.25, 256, 27.0), (2.0, 512, 40.0)] {
        let enc = fractile_codec::encode(
            &r,
            &ProjectedSettings {
                target_bpp: Some(bpp),
                ..ProjectedSettings::default()
            },
            &|_, _| {},
        )
        .expect("encode");
        let asset = Asset::from_bytes(&enc.bytes).expect("read back");
        assert_eq!(asset.planes().len(), 3);
        let Coding::Projected { header, .. } = &asset.planes()[1].coding else {
            panic!("projected chroma");
        };
        // Half-resolution chroma codes better at low rates, full resolution at high ones
        // (both are tried).
        assert_eq!(header.samples, [chroma, chroma], "chroma at {bpp} bpp");
        println!(
            "astronaut at {bpp} bpp: {:.3} bpp, {:.2} dB",
            enc.bpp(),
            enc.errors.psnr
        );
        assert!(
            enc.bpp() <= bpp && enc.bpp() > 0.9 * bpp,
            "{} bpp",
            enc.bpp()
        );
        assert!(
            enc.errors.psnr > floor,
            "{:.2} dB at {bpp} bpp",
            enc.errors.psnr
        );
    }
    let settings = ProjectedSettings {
        max_error: Some(2.0),
        ..Default::default()
    };
    assert!(
        fractile_codec::encode(&r, &settings, &|_, _| {}).is_err(),
        "a bound on colour is refused"
    );
}
