//! GPU against CPU continuous decoding: points per second for a 4096 x 4096 window and for 1M
//! random points, 10 iterations, on the camera asset (quadtree, 0.48 bpp). The CPU uses every
//! core (rayon over batches of `decode::points`). `cargo bench -p fractile-gpu --bench gpu`.
//! On Mesa's lavapipe (no GPU) the GPU figures are a software rasteriser's; real ones come from
//! a machine with a GPU.

use std::path::PathBuf;
use std::time::Instant;

use fractile_codec::decode;
use fractile_codec::pieces::Flatten;
use fractile_codec::{EncodeSettings, Raster, RateMode, encode};
use fractile_gpu::{Gpu, Grid};
use rayon::prelude::*;

fn main() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata/camera.png");
    let r = Raster::open(&path).expect("testdata");
    let s = EncodeSettings {
        rate: RateMode::TargetBpp(0.48),
        ..EncodeSettings::default()
    };
    let asset = encode(&r, &s, &|_, _| {}).expect("encode").asset;
    let op = &asset.planes[0].operator;
    let n = 10;
    let side = 4096u32;
    let window: Vec<[f32; 2]> = (0..side * side)
        .map(|k| {
            let (i, j) = ((k % side) as f32 + 0.5, (k / side) as f32 + 0.5);
            [i / side as f32, j / side as f32]
        })
        .collect();
    let random: Vec<[f32; 2]> = (0..1_000_000u32)
        .map(|i| {
            let h = i.wrapping_mul(2_654_435_761);
            let k = i.wrapping_mul(40_503) ^ (h >> 11);
            [h as f32 / u32::MAX as f32, k as f32 / u32::MAX as f32]
        })
        .collect();
    let cpu = |pts: &[[f32; 2]]| {
        let t = Instant::now();
        let v: Vec<_> = pts
            .par_chunks(4096)
            .flat_map_iter(|c| decode::points(op, c, n, 0.0))
            .collect();
        (t.elapsed().as_secs_f64(), v.len())
    };
    println!("| work | backend | seconds | points/s | ratio to CPU |");
    println!("|---|---|---|---|---|");
    let gpu = Gpu::new();
    for (label, pts) in [("4096x4096 window", &window), ("1M random points", &random)] {
        let (tc, len) = cpu(pts);
        println!(
            "| {label} | CPU ({} threads) | {tc:.3} | {:.3e} | 1.00 |",
            rayon::current_num_threads(),
            len as f64 / tc
        );
        match &gpu {
            Ok(g) => {
                let dev = g.upload(&op.pieces()).expect("upload");
                // Once to warm the pipeline, then timed (upload excluded: assets stay resident).
                let _ = g.points(&dev, &pts[..1024], n, 0.0);
                let t = Instant::now();
                let got = if label.starts_with("4096") {
                    g.grid(
                        &dev,
                        Grid::Window {
                            rect: [0.0, 0.0, 1.0, 1.0],
                            width: side,
                            height: side,
                        },
                        n,
                        0.0,
                    )
                } else {
                    g.points(&dev, pts, n, 0.0)
                }
                .expect("gpu");
                let tg = t.elapsed().as_secs_f64();
                println!(
                    "| {label} | GPU: {} | {tg:.3} | {:.3e} | {:.2} |",
                    g.adapter(),
                    got.len() as f64 / tg,
                    tc / tg
                );
            }
            Err(e) => println!("| {label} | GPU | - | {e} | - |"),
        }
    }
}
