//! Chunked against single-operator encodes of one large real DEM (issue 30): time, peak memory,
//! bytes and PSNR, and the seams (RMSE of windows straddling chunk edges against windows inside
//! chunks). One encode a run, so that the peak resident memory is that encode's:
//!
//! `cargo bench -p fractile-codec --bench chunked -- single|CHUNK [COPIES]`
//!
//! and writes the mosaic as GeoTIFFs for the command line (`fractile encode DIR`), a 2 x 2
//! block of copies a file, on one global grid:
//!
//! `cargo bench -p fractile-codec --bench chunked -- tiffs DIR [COPIES]` (8: 16 files of
//! 2160 x 1080, 37 Mpx in all)
//!
//! The raster: etopo20 mirrored COPIES x COPIES (odd columns of copies flipped left-right, odd
//! rows upside down; 4 gives 4320 x 2160, 9.3 Mpx), encoded by the default DEM encode
//! (projected, bounded, 0.8 bits a cell) whole or in chunks of CHUNK.

#[path = "support/memory.rs"]
mod memory;
use memory::peak_mb;

use std::time::Instant;

use fractile_codec::encode::chunked::encode_chunked;
use fractile_codec::geo::{Pixels, Sites};
use fractile_codec::{Asset, Raster, encode_default};

fn mosaic(copies: usize) -> Raster {
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata");
    let src = Raster::open(&root.join("etopo20.tif")).expect("etopo20");
    fractile_codec::mosaic::mirrored(&src, copies, copies).unwrap()
}

/// `r` as GeoTIFFs of 2 x 2 etopo20 copies each (float32), placed on one global grid.
fn write_tiffs(dir: &std::path::Path, r: &Raster) {
    std::fs::create_dir_all(dir).unwrap();
    let (tw, th) = (2160, 1080);
    let pixel = [360.0 / r.width as f64, -180.0 / r.height as f64];
    for ty in 0..r.height / th {
        for tx in 0..r.width / tw {
            let values: Vec<f32> = (0..th)
                .flat_map(|y| {
                    let row = (ty * th + y) * r.width + tx * tw;
                    r.channels[0][row..row + tw].iter().copied()
                })
                .collect();
            let georef = fractile_proto::Georef {
                epsg: Some(4326),
                origin: [
                    -180.0 + (tx * tw) as f64 * pixel[0],
                    90.0 + (ty * th) as f64 * pixel[1],
                ],
                pixel_size: pixel,
            };
            let path = dir.join(format!("part-{ty}-{tx}.tif"));
            fractile_codec::raster::write_geotiff_f32(&path, tw, th, &values, Some(&georef), None)
                .unwrap();
        }
    }
    println!(
        "{} x {} in {} GeoTIFFs under {}",
        r.width,
        r.height,
        (r.width / tw) * (r.height / th),
        dir.display()
    );
}

/// RMSE against the source of a `side x side` window of cell centres at (x0, y0).
fn window_rmse(asset: &Asset, r: &Raster, (x0, y0): (usize, usize), side: usize) -> f64 {
    let (w, h) = (r.width, r.height);
    let pixels = Pixels {
        sites: Sites::Grid {
            xs: (x0..x0 + side)
                .map(|x| Some((x as f32 + 0.5) / w as f32))
                .collect(),
            ys: (y0..y0 + side)
                .map(|y| Some((y as f32 + 0.5) / h as f32))
                .collect(),
        },
        footprint: [1.0 / w as f32, 1.0 / h as f32],
    };
    let (v, _) = asset.sample(&pixels, 40, asset.default_tolerance());
    let mut sq = 0.0;
    for j in 0..side {
        for i in 0..side {
            let d = f64::from(v[0][j * side + i] - r.channels[0][(y0 + j) * w + x0 + i]);
            sq += d * d;
        }
    }
    (sq / (side * side) as f64).sqrt()
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let mode = args.first().map_or("1024", String::as_str).to_string();
    let copies: usize = args.get(1).and_then(|c| c.parse().ok()).unwrap_or(4);
    if mode == "tiffs" {
        let dir = std::path::PathBuf::from(args.get(1).expect("tiffs DIR [COPIES]"));
        let copies: usize = args.get(2).and_then(|c| c.parse().ok()).unwrap_or(8);
        return write_tiffs(&dir, &mosaic(copies));
    }
    let r = mosaic(copies);
    let cells = (r.width * r.height) as f64;
    let before = peak_mb();
    let t = Instant::now();
    let one = |part: &Raster| encode_default(part, 0.8, &|_, _| {});
    let enc = if mode == "single" {
        one(&r).expect("encode")
    } else {
        let chunk: u32 = mode.parse().expect("single or a chunk side");
        encode_chunked(&r, chunk, &one, &|_, _| {}).expect("encode")
    };
    let secs = t.elapsed().as_secs_f64();
    println!(
        "\n{} x {} ({:.1} Mpx), {mode}: {:.1} s ({:.2} us a cell), peak RSS {:.0} MB (raster alone {:.0} MB), {} bytes ({:.3} bpp), PSNR {:.2} dB, max error {:.0}",
        r.width,
        r.height,
        cells / 1e6,
        secs,
        secs / cells * 1e6,
        peak_mb(),
        before,
        enc.bytes.len(),
        enc.bpp(),
        enc.errors.psnr,
        enc.errors.max_error
    );
    // Seams: 64 x 64 windows centred on chunk corners and edges, against windows centred
    // inside chunks (the same count), at native resolution.
    if let Some(c) = enc.asset.chunked() {
        let side = 64;
        let chunk = c.table.chunk as usize;
        let (nx, ny) = c.table.grid(r.width as u32, r.height as u32);
        let (mut across, mut inside) = (Vec::new(), Vec::new());
        for cy in 0..ny as usize {
            for cx in 0..nx as usize {
                let (x, y) = (cx * chunk, cy * chunk);
                if cx > 0 {
                    across.push(window_rmse(
                        &enc.asset,
                        &r,
                        (x - side / 2, y + chunk / 2),
                        side,
                    ));
                }
                if cy > 0 {
                    across.push(window_rmse(
                        &enc.asset,
                        &r,
                        (x + chunk / 2, y - side / 2),
                        side,
                    ));
                }
                let (ix, iy) = (x + chunk / 2 - side / 2, y + chunk / 2 - side / 2);
                if ix + side <= r.width && iy + side <= r.height {
                    inside.push(window_rmse(&enc.asset, &r, (ix, iy), side));
                    inside.push(window_rmse(
                        &enc.asset,
                        &r,
                        (ix + side, iy + side / 2),
                        side,
                    ));
                }
            }
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        println!(
            "seams: {} windows across chunk edges, RMSE {:.2}; {} inside chunks, RMSE {:.2}; ratio {:.3}",
            across.len(),
            mean(&across),
            inside.len(),
            mean(&inside),
            mean(&across) / mean(&inside)
        );
    }
}
