//! What a tile of a chunked asset costs the CPU that answers it (issue 30's serving bar), with
//! no HTTP in the way: random 256 x 256 windows at pixel footprints from a quarter of a source
//! cell to 32 cells (the zooms of a tile pyramid from the source's + 2 to its - 5), each
//! sampled as the server samples a tile (up to 64 steps, to the tolerance the server settles
//! for the tile: `Asset::tolerance_over`).
//!
//! `cargo bench -p fractile-codec --bench chunk_tiles -- ASSET.fra [TILES] [CACHE_MIB] [TOLERANCE]`
//!
//! TOLERANCE: `tile` (the default: the server's), `asset` (`Asset::default_tolerance`, what
//! tiles converged to before), or a number (value units).
//!
//! Prints, per footprint: the mean time of a tile whose chunks were not decoded yet (the
//! chunk cache starts empty, and `CACHE_MIB`, default 4096, then keeps every chunk), the mean
//! time of the same tiles again (chunks cached), and the mean chain steps a pixel (from the
//! same pixels asked as points, for footprints of a cell or less). Run it with
//! `RAYON_NUM_THREADS=1` for one core's cost, which is what a loaded server pays.

use std::time::Instant;

use fractile_codec::Asset;
use fractile_codec::asset::AssetLimits;
use fractile_codec::chunked::ChunkCache;
use fractile_codec::geo::{Pixels, Sites};

/// A deterministic generator (xorshift), so that runs draw the same tiles.
struct Draw(u64);

impl Draw {
    fn unit(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A 256 x 256 window of pixels `f` source cells wide, at a random place.
fn tile(asset: &Asset, f: f64, draw: &mut Draw) -> Pixels {
    let (w, h) = (f64::from(asset.meta.width), f64::from(asset.meta.height));
    let (sw, sh) = ((256.0 * f / w).min(1.0), (256.0 * f / h).min(1.0));
    let (u0, v0) = (draw.unit() * (1.0 - sw), draw.unit() * (1.0 - sh));
    let axis = |t0: f64, span: f64| -> Vec<Option<f32>> {
        (0..256)
            .map(|i| Some((t0 + (i as f64 + 0.5) / 256.0 * span) as f32))
            .collect()
    };
    Pixels {
        sites: Sites::Grid {
            xs: axis(u0, sw),
            ys: axis(v0, sh),
        },
        footprint: [(sw / 256.0) as f32, (sh / 256.0) as f32],
    }
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let path = std::path::PathBuf::from(
        args.first()
            .expect("ASSET.fra [TILES] [CACHE_MIB] [TOLERANCE]"),
    );
    let tiles: usize = args.get(1).and_then(|t| t.parse().ok()).unwrap_or(20);
    let mib: u64 = args.get(2).and_then(|t| t.parse().ok()).unwrap_or(4096);
    let asset =
        Asset::open(&path, &AssetLimits::default(), ChunkCache::new(mib << 20)).expect("an asset");
    let mode = args.get(3).map_or("tile", String::as_str).to_string();
    let tolerance = |p: &Pixels| match mode.as_str() {
        "tile" => asset.tolerance_over(p).expect("a readable chunk"),
        "asset" => asset.default_tolerance(),
        t => t.parse().expect("tile, asset or a number"),
    };
    println!(
        "{} ({} x {}), tolerance {mode} (the asset's default {:.3}), {} threads, {tiles} tiles a footprint\n",
        path.display(),
        asset.meta.width,
        asset.meta.height,
        asset.default_tolerance(),
        rayon::current_num_threads()
    );
    println!("| cells a pixel | first time ms | again ms | steps a pixel |");
    println!("|---|---|---|---|");
    let mut draw = Draw(0x9e37_79b9_7f4a_7c15);
    for f in [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0] {
        let windows: Vec<Pixels> = (0..tiles).map(|_| tile(&asset, f, &mut draw)).collect();
        let mut times = [0.0f64; 2];
        for time in times.iter_mut() {
            let t = Instant::now();
            for p in &windows {
                std::hint::black_box(asset.sample(p, 64, tolerance(p)));
            }
            *time = t.elapsed().as_secs_f64() * 1e3 / tiles as f64;
        }
        let steps = if f <= 1.0 {
            let (mut sum, mut n) = (0u64, 0u64);
            for p in &windows {
                if let Sites::Grid { xs, ys } = &p.sites {
                    let pts: Vec<[f32; 2]> = ys
                        .iter()
                        .step_by(8)
                        .flat_map(|v| xs.iter().step_by(8).map(move |u| [u.unwrap(), v.unwrap()]))
                        .collect();
                    for s in asset.points(&pts, 64, tolerance(p)) {
                        sum += u64::from(s.iterations);
                        n += 1;
                    }
                }
            }
            format!("{:.2}", sum as f64 / n.max(1) as f64)
        } else {
            "-".into()
        };
        println!("| {f} | {:.1} | {:.2} | {steps} |", times[0], times[1]);
    }
}
