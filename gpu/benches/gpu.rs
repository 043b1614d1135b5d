//! GPU against CPU continuous decoding: points per second for a 4096 x 4096 window and for 1M
//! random points, 10 iterations, on the camera asset (quadtree, 0.48 bpp). The CPU uses every
//! core (rayon over batches of `decode::points`). `cargo bench -p fractile-gpu --bench gpu`
//! (`-- host`: only the host's cost of small dispatches, the tiles' case; `-- volume`: only the
//! 3D box).
//! On Mesa's lavapipe (no GPU) the GPU figures are a software rasteriser's; real ones come from
//! a machine with a GPU.

use std::path::PathBuf;
use std::time::Instant;

use fractile_codec::decode;
use fractile_codec::pieces::Flatten;
use fractile_codec::{QuadtreeSettings, Raster, RateMode, encode};
use fractile_gpu::{Gpu, Grid};
use rayon::prelude::*;

fn main() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata/camera.png");
    let r = Raster::open(&path).expect("testdata");
    let s = QuadtreeSettings {
        rate: RateMode::TargetBpp(0.48),
        ..QuadtreeSettings::default()
    };
    let asset = encode(&r, &s, &|_, _| {}).expect("encode").asset;
    let op = &asset.planes()[0].operator;
    let n = 10;
    // `-- host`: the small dispatches alone (the rest takes minutes on a software adapter).
    // `-- volume`: the 3D box alone.
    if std::env::args().any(|a| a == "volume") {
        println!("| work | backend | seconds | points/s | ratio to CPU |");
        println!("|---|---|---|---|---|");
        volume_box(&Gpu::new(), n);
        return;
    }
    if std::env::args().any(|a| a == "host") {
        let g = Gpu::new().expect("a GPU adapter");
        eprintln!("adapter: {}", g.adapter());
        host_cost(&g, &g.upload_flat(&op.flat()).expect("upload"), n);
        return;
    }
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
    // The CPU's own path for a window, what the server and `fractile decode` take: the grid
    // decoder (blocks of points that step together) on bands of 16 rows, on every core. Its
    // time is the baseline of the values-only readback below, the faster of the two CPU paths.
    let plane = &asset.planes()[0].operator;
    let (xs, ys) = decode::window_axes([0.0, 0.0, 1.0, 1.0], side as usize, side as usize);
    let t = Instant::now();
    let got: usize = ys
        .par_chunks(16)
        .map(|band| plane.grid(&xs, band, n, 0.0).len())
        .sum();
    let grid_cpu = t.elapsed().as_secs_f64();
    println!(
        "| 4096x4096 window, grid decoder | CPU ({} threads) | {grid_cpu:.3} | {:.3e} | |",
        rayon::current_num_threads(),
        got as f64 / grid_cpu
    );
    let gpu = Gpu::new();
    let mut window_cpu = f64::NAN;
    for (label, pts) in [("4096x4096 window", &window), ("1M random points", &random)] {
        let (tc, len) = cpu(pts);
        if label.starts_with("4096") {
            window_cpu = tc;
        }
        println!(
            "| {label} | CPU ({} threads) | {tc:.3} | {:.3e} | 1.00 |",
            rayon::current_num_threads(),
            len as f64 / tc
        );
        match &gpu {
            Ok(g) => {
                let dev = g.upload_flat(&op.flat()).expect("upload");
                // The same work twice, the second timed: a server decodes request after request,
                // and the first one pays the pipeline's warm-up and the staging buffers'
                // first-touch page faults (upload excluded too: assets stay resident).
                let run = || {
                    if label.starts_with("4096") {
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
                    .expect("gpu")
                };
                let t = Instant::now();
                let cold = run().len();
                let t_cold = t.elapsed().as_secs_f64();
                let t = Instant::now();
                let got = run();
                eprintln!("{label}: first run {t_cold:.3} s for {cold} points");
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
    // The same window with the values read back alone and the bounds reduced on the device
    // (issue 32: 4 bytes a point cross instead of 16), against the CPU's time above.
    if let Ok(g) = &gpu {
        let dev = g.upload_flat(&op.flat()).expect("upload");
        let grid = Grid::Window {
            rect: [0.0, 0.0, 1.0, 1.0],
            width: side,
            height: side,
        };
        let _ = g.grid_values(&dev, grid.clone(), n, 0.0).expect("gpu");
        let t = Instant::now();
        let got = g.grid_values(&dev, grid, n, 0.0).expect("gpu");
        let tg = t.elapsed().as_secs_f64();
        println!(
            "| 4096x4096 window, values only | GPU: {} | {tg:.3} | {:.3e} | {:.2} (to the grid decoder: {:.2}) |",
            g.adapter(),
            got.values.len() as f64 / tg,
            window_cpu / tg,
            grid_cpu / tg
        );
    }
    // The device's own time for whole windows (results left on the device), best of five:
    // the targets of issue 6 (4096 x 4096 at 10 steps under 5 ms; 1920 x 1080 in real time).
    if let Ok(g) = &gpu {
        let dev = g.upload_flat(&op.flat()).expect("upload");
        for (w, h) in [(4096u32, 4096u32), (1920, 1080)] {
            let _ = g.kernel_seconds(&dev, w, h, n);
            let best = (0..5)
                .map(|_| g.kernel_seconds(&dev, w, h, n).expect("gpu"))
                .fold(f64::INFINITY, f64::min);
            println!(
                "| {w}x{h} window, device time (no readback) | GPU: {} | {best:.5} | {:.3e} | {:.0} frames/s |",
                g.adapter(),
                (w * h) as f64 / best,
                1.0 / best
            );
        }
    }
    // What a small dispatch costs the host (issue 32: a tile's GPU sample must add well under
    // a millisecond of CPU for tiles to gain): grids of 1 and 256 x 256 points, decoded one
    // after another on one thread and at once on every thread, wall time and the process's CPU
    // time a dispatch. On lavapipe the kernel runs on the CPU too, so only the 1-point row is
    // host cost alone there.
    if let Ok(g) = &gpu {
        let dev = g.upload_flat(&op.flat()).expect("upload");
        host_cost(g, &dev, n);
    }
    volume_box(&gpu, n);
}

/// 3D: a 256^3 box of a volume (IFS3D), continuous decoding at `n` steps, on the CPU and the
/// GPU (each point's bound read back, and the values alone).
fn volume_box(gpu: &Result<Gpu, fractile_gpu::GpuError>, n: u32) {
    let shared = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/mesh/bunny.off");
    let local = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata/mesh/fandisk.off");
    let path = if shared.exists() { shared } else { local };
    let mesh = fractile_codec::mesh::Mesh::read(&path).expect("mesh");
    let s = fractile_codec::encode::volume::MeshSettings {
        grid: 128,
        ..Default::default()
    };
    let vol = fractile_codec::encode::volume::encode_mesh(&mesh, &s, "bench")
        .expect("encode")
        .asset;
    let vop = &vol.volume().expect("volume").operator;
    let dims = [256usize; 3];
    let t = Instant::now();
    let (v, _) = decode::volume_window(vop, [0.0; 3], [1.0; 3], dims, n, 0.0);
    let tc = t.elapsed().as_secs_f64();
    let label = format!(
        "256^3 box of {} (128^3 IFS3D)",
        path.file_name().unwrap().to_string_lossy()
    );
    println!(
        "| {label} | CPU ({} threads) | {tc:.3} | {:.3e} | 1.00 |",
        rayon::current_num_threads(),
        v.len() as f64 / tc
    );
    if let Ok(g) = &gpu {
        let dev = g.upload_volume(vop).expect("upload");
        // As above: the second of two runs.
        let _ = g.volume_grid(&dev, [0.0; 3], [1.0; 3], dims.map(|d| d as u32), n, 0.0);
        let t = Instant::now();
        let got = g
            .volume_grid(&dev, [0.0; 3], [1.0; 3], dims.map(|d| d as u32), n, 0.0)
            .expect("gpu");
        let tg = t.elapsed().as_secs_f64();
        println!(
            "| {label} | GPU: {}, each point's bound read back | {tg:.3} | {:.3e} | {:.2} |",
            g.adapter(),
            got.len() as f64 / tg,
            tc / tg
        );
        // What a mesh asks for: the values, one bound (4 bytes a point read back).
        let _ = g.volume_grid_values(&dev, [0.0; 3], [1.0; 3], dims.map(|d| d as u32), n, 0.0);
        let t = Instant::now();
        let got = g
            .volume_grid_values(&dev, [0.0; 3], [1.0; 3], dims.map(|d| d as u32), n, 0.0)
            .expect("gpu");
        let tg = t.elapsed().as_secs_f64();
        println!(
            "| {label} | GPU: {}, values alone | {tg:.3} | {:.3e} | {:.2} |",
            g.adapter(),
            got.values.len() as f64 / tg,
            tc / tg
        );
    }
}

/// Wall and CPU time of small grid dispatches, on one thread and on every thread at once.
fn host_cost(g: &Gpu, dev: &fractile_gpu::GpuOperator, n: u32) {
    let threads = rayon::current_num_threads();
    println!();
    println!(
        "| small dispatches (values only) | threads | dispatches | wall us each | CPU us each |"
    );
    println!("|---|---|---|---|---|");
    for side in [1usize, 256] {
        let axis: Vec<f32> = (0..side).map(|i| (i as f32 + 0.5) / side as f32).collect();
        let grid = Grid::Separable {
            xs: axis.clone(),
            ys: axis,
        };
        let one = || {
            g.grid_values(dev, grid.clone(), n, 0.0)
                .expect("gpu")
                .values
                .len()
        };
        let _ = one();
        for t in [1, threads] {
            let count = if side == 1 { 4000 } else { 200 } * t;
            let (cpu0, start, r0) = (cpu_seconds(), Instant::now(), g.rounds());
            let got: usize = (0..count)
                .into_par_iter()
                .with_min_len(count / t)
                .map(|_| one())
                .sum();
            let wall = start.elapsed().as_secs_f64();
            let cpu = cpu_seconds().map_or(f64::NAN, |c| c - cpu0.unwrap_or(c));
            assert_eq!(got, count * side * side);
            let r1 = g.rounds();
            println!(
                "| {side} x {side} | {t} | {count} | {:.1} | {:.1} | {:.2} |",
                wall / count as f64 * 1e6,
                cpu / count as f64 * 1e6,
                (r1.1 - r0.1) as f64 / (r1.0 - r0.0).max(1) as f64
            );
        }
    }
}

/// This process's CPU time (user and system, all threads), from /proc; `None` elsewhere.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command's closing parenthesis: utime and stime are the 12th and 13th.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split(' ').collect();
    let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    // USER_HZ is 100 on every Linux this runs on.
    Some(ticks / 100.0)
}
