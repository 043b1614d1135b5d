//! Issue 7's measurements: the fractal interpolation surface codecs against the quadtree IFS at
//! matched ratios on three real DEMs, and the zoom beyond the source (power-spectrum slopes).
//! Release build: `cargo bench -p fractile-codec --bench fis`.

use std::path::PathBuf;
use std::time::Instant;

use fractile_codec::codecs::fis::{FisSettings, Scaling, codec_name};
use fractile_codec::codecs::psa::{Domains, PsaSettings, Tiling};
use fractile_codec::{Encoded, QuadtreeSettings, Raster, RateMode, encode};
use rustfft::FftPlanner;
use rustfft::num_complex::Complex;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

fn row(dem: &str, codec: &str, e: &Encoded) {
    let t = Instant::now();
    let reps = 3;
    for _ in 0..reps {
        std::hint::black_box(e.asset.decode_native());
    }
    let decode_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
    let setting = e
        .asset
        .meta
        .encoder
        .split_whitespace()
        .find(|t| t.starts_with("spacing="))
        .unwrap_or("")
        .to_string();
    println!(
        "| {dem} | {codec} {setting} | {} | {:.1}:1 | {:.2} | {:.1} | {:.2} | {:.0} |",
        e.bytes.len(),
        e.ratio(),
        e.errors.psnr,
        e.errors.max_error,
        e.seconds,
        decode_ms
    );
}

/// Radially averaged power spectrum of a Hann-windowed grid, in bins of frequency (cycles per
/// sample, 0..0.5), and the least-squares slope of log power against log frequency over `band`.
fn spectrum_slope(v: &[f32], w: usize, h: usize, band: (f64, f64)) -> f64 {
    let mean = v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
    let hann =
        |i: usize, n: usize| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * i as f64 / n as f64).cos();
    let mut buf: Vec<Complex<f64>> = (0..w * h)
        .map(|k| {
            let (x, y) = (k % w, k / w);
            Complex::new((v[k] as f64 - mean) * hann(x, w) * hann(y, h), 0.0)
        })
        .collect();
    let mut planner = FftPlanner::new();
    let (fw, fh) = (planner.plan_fft_forward(w), planner.plan_fft_forward(h));
    for r in buf.chunks_mut(w) {
        fw.process(r);
    }
    let mut col = vec![Complex::new(0.0, 0.0); h];
    for x in 0..w {
        for y in 0..h {
            col[y] = buf[y * w + x];
        }
        fh.process(&mut col);
        for y in 0..h {
            buf[y * w + x] = col[y];
        }
    }
    let bins = 64;
    let (mut power, mut count) = (vec![0.0f64; bins], vec![0usize; bins]);
    for y in 0..h {
        for x in 0..w {
            let fx = if x <= w / 2 {
                x as f64
            } else {
                x as f64 - w as f64
            } / w as f64;
            let fy = if y <= h / 2 {
                y as f64
            } else {
                y as f64 - h as f64
            } / h as f64;
            let f = (fx * fx + fy * fy).sqrt();
            if f > 0.0 && f < 0.5 {
                let b = (f / 0.5 * bins as f64) as usize;
                power[b] += buf[y * w + x].norm_sqr();
                count[b] += 1;
            }
        }
    }
    let pts: Vec<(f64, f64)> = (0..bins)
        .filter(|&b| count[b] > 0)
        .map(|b| {
            (
                (b as f64 + 0.5) / bins as f64 * 0.5,
                power[b] / count[b] as f64,
            )
        })
        .filter(|&(f, p)| f >= band.0 && f <= band.1 && p > 0.0)
        .map(|(f, p)| (f.ln(), p.ln()))
        .collect();
    let n = pts.len() as f64;
    let (sx, sy) = pts.iter().fold((0.0, 0.0), |(a, b), p| (a + p.0, b + p.1));
    let (mx, my) = (sx / n, sy / n);
    let (num, den) = pts.iter().fold((0.0, 0.0), |(a, b), p| {
        (a + (p.0 - mx) * (p.1 - my), b + (p.0 - mx) * (p.0 - mx))
    });
    num / den
}

/// The quadtree settings `fractile encode --target-bpp` uses for this kind of data.
fn quadtree(r: &Raster, bpp: f64) -> QuadtreeSettings {
    let mut s = QuadtreeSettings {
        rate: RateMode::TargetBpp(bpp),
        ..QuadtreeSettings::default()
    };
    s.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(r.kind);
    s
}

fn main() {
    let filter = std::env::args().skip(1).find(|a| !a.starts_with('-'));
    let want = |s: &str| filter.as_deref().is_none_or(|f| s.contains(f));
    let codecs = [Scaling::PerNode, Scaling::PerCell, Scaling::Global];
    if want("table") {
        println!(
            "## Fractal interpolation surfaces against the quadtree IFS (PSNR peak = range)\n"
        );
        println!("| DEM | codec | bytes | ratio | PSNR dB | max error | encode s | decode ms |");
        println!("|---|---|---|---|---|---|---|---|");
        for file in [
            "jacksboro.tif",
            "etopo20.tif",
            "topobathy.tif",
            "camera.png",
        ] {
            let r = Raster::open(&data(file)).expect("testdata");
            let name = file.split('.').next().unwrap_or(file);
            let image = r.kind == fractile_proto::AssetKind::Image;
            for ratio in [16.0, 32.0, 64.0] {
                let bpp = (r.sample.bytes() * 8) as f64 / ratio;
                for (tiling, domains) in [
                    (Tiling::Rectangular, Domains::Overlapping),
                    (Tiling::Rectangular, Domains::Touching),
                    (Tiling::Triangular, Domains::Overlapping),
                ] {
                    let s = PsaSettings {
                        tiling,
                        domains,
                        ..PsaSettings::default()
                    };
                    let label = format!(
                        "{} {}",
                        fractile_codec::codecs::psa::codec_name(tiling),
                        format!("{domains:?}").to_lowercase()
                    );
                    match fractile_codec::encode(
                        &r,
                        &PsaSettings {
                            target_bpp: Some(bpp),
                            ..s.clone()
                        },
                        &|_, _| {},
                    ) {
                        Ok(e) => row(name, &label, &e),
                        Err(e) => println!("| {name} | {label} | - | {ratio}:1 | {e} | | | |"),
                    }
                }
                for s in codecs {
                    if image {
                        continue;
                    }
                    match fractile_codec::encode(
                        &r,
                        &FisSettings {
                            scaling: s,
                            target_bpp: Some(bpp),
                            ..FisSettings::default()
                        },
                        &|_, _| {},
                    ) {
                        Ok(e) => row(name, codec_name(s), &e),
                        Err(e) => {
                            println!("| {name} | {} | - | {ratio}:1 | {e} | | | |", codec_name(s))
                        }
                    }
                }
                let q = quadtree(&r, bpp);
                let e = encode(&r, &q, &|_, _| {}).expect("quadtree");
                row(name, "quadtree-pifs", &e);
            }
        }
    }
    if want("zoom") {
        // The zoom beyond the source: 4x on jacksboro, spectra against the source's and bicubic's.
        let r = Raster::open(&data("jacksboro.tif")).expect("testdata");
        let (w, h) = (r.width, r.height);
        let lo = r.channels[0].iter().cloned().fold(f32::INFINITY, f32::min);
        let hi = r.channels[0]
            .iter()
            .cloned()
            .fold(f32::NEG_INFINITY, f32::max);
        println!("\n## Zoom beyond the source: jacksboro at 4x, power-spectrum slopes\n");
        println!(
            "Slope of log power against log frequency (cycles per output sample); the source's"
        );
        println!(
            "band is 0.02..0.5 of its own samples, which is 0.005..0.125 at 4x; 0.125..0.5 is"
        );
        println!("detail no source sample holds.\n");
        println!("| surface | slope, source band | slope, beyond the source |");
        println!("|---|---|---|");
        println!(
            "| source ({w}x{h}) | {:.2} | - |",
            spectrum_slope(&r.channels[0], w, h, (0.02, 0.5))
        );
        let (bw, bh) = (4 * w, 4 * h);
        let img = image::ImageBuffer::<image::Luma<f32>, Vec<f32>>::from_raw(
            w as u32,
            h as u32,
            // image's f32 filters clamp to 0..1: resize normalised heights.
            r.channels[0].iter().map(|v| (v - lo) / (hi - lo)).collect(),
        )
        .expect("grid");
        let up = image::imageops::resize(
            &img,
            bw as u32,
            bh as u32,
            image::imageops::FilterType::CatmullRom,
        )
        .into_raw();
        let slopes = |v: &[f32]| {
            (
                spectrum_slope(v, bw, bh, (0.005, 0.125)),
                spectrum_slope(v, bw, bh, (0.125, 0.5)),
            )
        };
        let (a, b) = slopes(&up);
        println!("| bicubic (Catmull-Rom) 4x | {a:.2} | {b:.2} |");
        for (label, enc) in [
            (
                "fis-bilinear, spacing 4",
                fractile_codec::encode(
                    &r,
                    &FisSettings {
                        spacing: 4,
                        ..FisSettings::default()
                    },
                    &|_, _| {},
                )
                .expect("fis"),
            ),
            (
                "fis-rect, spacing 4",
                fractile_codec::encode(
                    &r,
                    &FisSettings {
                        scaling: Scaling::PerCell,
                        spacing: 4,
                        ..FisSettings::default()
                    },
                    &|_, _| {},
                )
                .expect("fis"),
            ),
            (
                "quadtree-pifs 0.8 bpp",
                encode(&r, &quadtree(&r, 0.8), &|_, _| {}).expect("quadtree"),
            ),
        ] {
            let (d, _) = enc.asset.window(
                [0.0, 0.0, 1.0, 1.0],
                bw,
                bh,
                Some(40),
                fractile_codec::Method::Continuous,
            );
            let (a, b) = slopes(&d.channels[0]);
            println!(
                "| {label} ({:.1}:1), continuous 4x | {a:.2} | {b:.2} |",
                enc.ratio()
            );
        }
    }
}
