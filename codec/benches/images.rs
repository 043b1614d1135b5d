//! Issue 77's image bars: what `fractile encode` writes for an image by default, against
//! JPEG 2000 (OpenJPEG) and AVIF (libavif through imagecodecs) at the same bytes, and against
//! the quadtree PIFS (the default before). Prints a table.
//!
//! `cargo bench -p fractile-codec --bench images [-- IMAGE.png ...]` (default: the
//! repository's camera and astronaut; other 8-bit images are held-out data). AVIF needs a
//! Python with imagecodecs: `FRACTILE_PYTHON=/tmp/tt/bin/python` (tools/avif_at.py).

use std::path::{Path, PathBuf};
use std::time::Instant;

use fractile_codec::{QuadtreeSettings, Raster, RateMode, encode, encode_default};

#[path = "support/baselines.rs"]
#[allow(dead_code)]
mod baselines;
use baselines::{avif_at, jpeg2000_at};

/// The rates of the bars, and camera's 0.2 bits a pixel.
const RATES: [f64; 4] = [0.2, 0.25, 0.5, 1.0];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn main() {
    let args: Vec<PathBuf> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .map(PathBuf::from)
        .collect();
    let images = if args.is_empty() {
        vec![
            root().join("testdata/camera.png"),
            root().join("testdata/astronaut.png"),
        ]
    } else {
        args
    };
    println!(
        "| image | rate | default (projected) | encode s | quadtree-pifs | JPEG 2000 | AVIF | \
         default - JPEG 2000 | default - AVIF |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for path in &images {
        let r = Raster::open(path).expect("an image");
        let name = Path::new(path).file_name().unwrap().to_string_lossy();
        for bpp in RATES {
            let start = Instant::now();
            let ours = encode_default(&r, bpp, &|_, _| {}).expect("the default encode");
            let seconds = start.elapsed().as_secs_f64();
            let mut quadtree = QuadtreeSettings {
                rate: RateMode::TargetBpp(bpp),
                ..QuadtreeSettings::default()
            };
            quadtree.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(r.kind);
            quadtree.quantiser_choices =
                QuadtreeSettings::default_quantiser_choices(r.kind, quadtree.quantiser);
            let old = encode(&r, &quadtree, &|_, _| {}).expect("the quadtree");
            let got = ours.bpp();
            let j2k = jpeg2000_at(&r, got);
            let avif = avif_at(&root(), &r, got);
            let at = |p: Option<(f64, f64)>| {
                p.map_or("-".into(), |(b, d)| format!("{d:.2} dB at {b:.3} bpp"))
            };
            let gap = |p: Option<(f64, f64)>| {
                p.map_or("-".into(), |(_, d)| {
                    format!("{:+.2} dB", ours.errors.psnr - d)
                })
            };
            println!(
                "| {name} | {bpp} bpp | {:.2} dB at {got:.3} bpp | {seconds:.2} | {:.2} dB at {:.3} bpp | {} | {} | {} | {} |",
                ours.errors.psnr,
                old.errors.psnr,
                old.bpp(),
                at(j2k),
                at(avif),
                gap(j2k),
                gap(avif),
            );
        }
    }
}
