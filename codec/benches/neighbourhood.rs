//! The projected continuation kept in its 4 x 4 neighbourhood (issue 53): what it changes and
//! what it costs, on the default DEM encode of the test DEMs (or any GeoTIFF given).
//!
//! `cargo bench -p fractile-codec --bench neighbourhood -- [DEM.tif ...]`
//!
//! Prints, per DEM, a 4x decode of the whole grid, raw (the chains' answers, what tiles served
//! before the clamp) and clamped (what they serve now): the samples more than 100 m (or 10% of
//! the value range, if less) over the highest of their 3 x 3 source cells, the largest excess
//! over their 4 x 4 source cells, and the RMSE against the source's bilinear interpolant. Then
//! the clamp's cost beside a tile's: random 256 x 256 windows at 1/16, 1/4 and 1 cell a pixel,
//! sampled as a tile is (`Asset::sample`), and the clamp alone on the same pixels.

use std::time::Instant;

use fractile_codec::geo::{Pixels, Sites};
use fractile_codec::{Asset, Raster, encode_default};

fn testdata(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// The source's value at position (x, y) in cells (centres at k + 0.5), bilinear, and its
/// ranges over the 3 x 3 and 4 x 4 cells around it.
fn source_at(r: &Raster, x: f64, y: f64) -> (f64, (f32, f32), (f32, f32)) {
    let (w, h) = (r.width, r.height);
    let (fx, fy) = (
        (x - 0.5).clamp(0.0, (w - 1) as f64),
        (y - 0.5).clamp(0.0, (h - 1) as f64),
    );
    let (i, j) = ((fx as usize).min(w - 2), (fy as usize).min(h - 2));
    let (u, v) = (fx - i as f64, fy - j as f64);
    let at = |x: usize, y: usize| f64::from(r.channels[0][y * w + x]);
    let bilinear = (1.0 - v) * ((1.0 - u) * at(i, j) + u * at(i + 1, j))
        + v * ((1.0 - u) * at(i, j + 1) + u * at(i + 1, j + 1));
    let range = |x0: usize, x1: usize, y0: usize, y1: usize| {
        let mut m = (f32::INFINITY, f32::NEG_INFINITY);
        for yy in y0..=y1.min(h - 1) {
            for xx in x0..=x1.min(w - 1) {
                let s = r.channels[0][yy * w + xx];
                m = (m.0.min(s), m.1.max(s));
            }
        }
        m
    };
    let (cx, cy) = ((x as usize).min(w - 1), (y as usize).min(h - 1));
    let three = range(cx.saturating_sub(1), cx + 1, cy.saturating_sub(1), cy + 1);
    let four = range(i.saturating_sub(1), i + 2, j.saturating_sub(1), j + 2);
    (bilinear, three, four)
}

/// Uniform draws in [0, 1) from `seed` (xorshift: the same draws every run).
fn draw(mut seed: u64) -> impl FnMut() -> f64 {
    move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn main() {
    let mut files: Vec<std::path::PathBuf> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .map(Into::into)
        .collect();
    if files.is_empty() {
        files = vec![testdata("etopo20.tif"), testdata("jacksboro.tif")];
    }
    println!(
        "| DEM | 4x decode | samples over their 3 x 3 cells by the margin | largest excess over the 4 x 4 cells | RMSE against the bilinear source |"
    );
    println!("|---|---|---|---|---|");
    let mut assets = Vec::new();
    for f in &files {
        let r = Raster::open(f).expect("a raster");
        let enc = encode_default(&r, 0.8, &|_, _| {}).expect("encodes");
        let a = Asset::from_bytes(&enc.bytes).expect("reads back");
        let (lo, hi) = r.value_range();
        let margin = (100.0f64).min(0.1 * (hi - lo)) as f32;
        let (w, h) = (4 * r.width, 4 * r.height);
        let axis = |n: usize| {
            (0..n)
                .map(|i| (i as f32 + 0.5) / n as f32)
                .collect::<Vec<_>>()
        };
        let (xs, ys) = (axis(w), axis(h));
        let op = &a.planes()[0].operator;
        let raw: Vec<f32> = op
            .grid(&xs, &ys, 40, 0.0)
            .into_iter()
            .map(|p| p.value)
            .collect();
        let mut clamped = raw.clone();
        op.limit_grid(&xs, &ys, &mut clamped);
        let name = f.file_name().unwrap().to_string_lossy().to_string();
        for (what, values) in [("raw", &raw), ("clamped", &clamped)] {
            let (mut over, mut worst, mut sq, mut n) = (0usize, 0.0f32, 0.0f64, 0usize);
            for (k, v) in values.iter().enumerate() {
                let (x, y) = ((k % w) as f64 / 4.0 + 0.125, (k / w) as f64 / 4.0 + 0.125);
                let value =
                    a.meta.value_min as f32 + v * (a.meta.value_max - a.meta.value_min) as f32;
                let (b, three, four) = source_at(&r, x, y);
                over += usize::from(value > three.1 + margin);
                worst = worst.max(value - four.1).max(four.0 - value);
                sq += (f64::from(value) - b).powi(2);
                n += 1;
            }
            println!(
                "| {name} | {what} | {:.2}% (margin {margin:.0}) | {worst:.1} | {:.2} |",
                100.0 * over as f64 / n as f64,
                (sq / n as f64).sqrt()
            );
        }
        assets.push((name, a));
    }
    println!("\n| DEM | 65,536 random points ms | the clamp alone ms | share |");
    println!("|---|---|---|---|");
    let mut next = draw(0x2545_f491_4f6c_dd1d);
    let mut next = move || next() as f32;
    for (name, a) in &assets {
        let pts: Vec<[f32; 2]> = (0..65_536).map(|_| [next(), next()]).collect();
        let t = Instant::now();
        let answers = a.points(&pts, 40, a.default_tolerance());
        let all = t.elapsed().as_secs_f64() * 1e3;
        // The normalised answers, clamped again (the fastest of five runs).
        let (lo, span) = (a.meta.value_min, a.meta.value_max - a.meta.value_min);
        let raw: Vec<f32> = answers
            .iter()
            .map(|s| ((f64::from(s.values[0]) - lo) / span) as f32)
            .collect();
        let clamp = (0..5)
            .map(|_| {
                let mut values = raw.clone();
                let t = Instant::now();
                a.planes()[0].operator.limit_points(&pts, &mut values);
                std::hint::black_box(&values);
                t.elapsed().as_secs_f64() * 1e3
            })
            .fold(f64::INFINITY, f64::min);
        println!(
            "| {name} | {all:.2} | {clamp:.3} | {:.1}% |",
            100.0 * clamp / all
        );
    }
    println!("\n| DEM | cells a pixel | tile ms | the clamp alone ms | share |");
    println!("|---|---|---|---|---|");
    let mut unit = draw(0x9e37_79b9_7f4a_7c15);
    for (name, a) in &assets {
        let (w, h) = (f64::from(a.meta.width), f64::from(a.meta.height));
        for f in [0.0625, 0.25, 1.0] {
            let (mut tile, mut clamp) = (0.0f64, 0.0f64);
            let tiles = 20;
            for _ in 0..tiles {
                let (sw, sh) = ((256.0 * f / w).min(1.0), (256.0 * f / h).min(1.0));
                let (u0, v0) = (unit() * (1.0 - sw), unit() * (1.0 - sh));
                let axis = |t0: f64, span: f64| -> Vec<f32> {
                    (0..256)
                        .map(|i| (t0 + (i as f64 + 0.5) / 256.0 * span) as f32)
                        .collect()
                };
                let (xs, ys) = (axis(u0, sw), axis(v0, sh));
                let pixels = Pixels {
                    sites: Sites::Grid {
                        xs: xs.iter().copied().map(Some).collect(),
                        ys: ys.iter().copied().map(Some).collect(),
                    },
                    footprint: [(sw / 256.0) as f32, (sh / 256.0) as f32],
                };
                let t = Instant::now();
                let tolerance = a.tolerance_over(&pixels).expect("a whole asset");
                std::hint::black_box(a.sample(&pixels, 64, tolerance));
                tile += t.elapsed().as_secs_f64();
                let mut values = vec![0.5f32; xs.len() * ys.len()];
                let t = Instant::now();
                a.planes()[0].operator.limit_grid(&xs, &ys, &mut values);
                std::hint::black_box(&values);
                clamp += t.elapsed().as_secs_f64();
            }
            let (tile, clamp) = (1e3 * tile / tiles as f64, 1e3 * clamp / tiles as f64);
            println!(
                "| {name} | {f} | {tile:.2} | {clamp:.3} | {:.1}% |",
                100.0 * clamp / tile
            );
        }
    }
}
