//! Terrain-tile meshes: triangles and milliseconds a tile of the greedy Delaunay TIN that
//! `Mesh::adaptive_tile` builds (edges stitched) against the RTIN of `Mesh::adaptive`
//! (unstitched: the easier problem) on the same 65 x 65 windows, both flat (no globe's
//! curvature, which the RTIN does not take).
//!
//! `cargo bench -p fractile-codec --bench terrain_mesh [DEM.tif ...]` (default: the
//! repository's jacksboro and etopo20). Windows: 64 of 65 x 65 source cells along the DEM's
//! diagonals; errors: Cesium's geometric error of the level where a tile spans 64 cells, of
//! the two above and of the two below (coarser and finer errors on the same cells).

use fractile_codec::Raster;
use fractile_codec::mesh::Mesh;
use std::time::Instant;

const N: usize = 65;

fn windows(r: &Raster) -> Vec<Vec<f32>> {
    let mut out = Vec::new();
    for k in 0..64 {
        let t = (k as f64 + 0.5) / 64.0;
        let (x0, y0) = (
            ((r.width - N) as f64 * t) as usize,
            if k % 2 == 0 {
                ((r.height - N) as f64 * t) as usize
            } else {
                ((r.height - N) as f64 * (1.0 - t)) as usize
            },
        );
        out.push(
            (0..N * N)
                .map(|g| r.channels[0][(y0 + g / N) * r.width + x0 + g % N])
                .map(|h| if h.is_finite() { h } else { 0.0 })
                .collect(),
        );
    }
    out
}

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let paths: Vec<std::path::PathBuf> = if args.is_empty() {
        ["jacksboro.tif", "etopo20.tif"]
            .map(|n| root.join("testdata").join(n))
            .to_vec()
    } else {
        args.iter().map(Into::into).collect()
    };
    println!(
        "| DEM | max error (m) | RTIN triangles | TIN triangles | TIN / RTIN | RTIN ms a tile | TIN ms a tile | TIN / RTIN time |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for path in paths {
        let r = Raster::open(&path).expect("a DEM");
        let g = r.georef.as_ref().expect("georeferenced");
        // Cesium's level whose tile spans 64 of the DEM's cells, and its error.
        let level0 = 6_378_137.0 * std::f64::consts::TAU * 0.25 / 130.0;
        let native = (180.0 / (64.0 * g.pixel_size[0])).log2().round();
        let tiles = windows(&r);
        for up in -2..=2 {
            let max_error = (level0 / 2f64.powf(native - f64::from(up))) as f32;
            let (mut counts, mut times) = ([0usize; 2], [0.0f64; 2]);
            for h in &tiles {
                let t0 = Instant::now();
                let rtin = Mesh::adaptive(h, N, [0.0; 2], [1.0; 2], max_error).unwrap();
                times[0] += t0.elapsed().as_secs_f64();
                let t0 = Instant::now();
                let (tin, _) =
                    Mesh::adaptive_tile(h, N, [0.0; 2], [1.0; 2], max_error, 0.0).unwrap();
                times[1] += t0.elapsed().as_secs_f64();
                counts[0] += rtin.triangles.len();
                counts[1] += tin.triangles.len();
            }
            let n = tiles.len() as f64;
            println!(
                "| {} | {max_error:.2} | {:.0} | {:.0} | {:.2} | {:.3} | {:.3} | {:.2} |",
                path.file_name().unwrap().to_string_lossy(),
                counts[0] as f64 / n,
                counts[1] as f64 / n,
                counts[1] as f64 / counts[0] as f64,
                times[0] * 1e3 / n,
                times[1] * 1e3 / n,
                times[1] / times[0]
            );
        }
    }
}
