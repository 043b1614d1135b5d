//! Images by default (issue 77): what `fractile encode` writes for an image, zoomed past its
//! pixels, stays smooth: no blocks along the quadtree's ranges or the source's pixels.

use fractile_codec::asset::Asset;
use fractile_codec::raster::Raster;
use fractile_codec::{Method, QuadtreeSettings, RateMode, encode, encode_default};

fn testdata(name: &str) -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// Zoom of the window read past the source's pixels.
const ZOOM: usize = 8;
/// Output pixels a period of the structure blocks follow: a 4-pixel range (the quadtree's
/// smallest, and a multiple of every coarser one's side) at `ZOOM`, so that range and pixel
/// edges fall on its phases 0 and multiples of `ZOOM`.
const PERIOD: usize = 4 * ZOOM;

/// How much the steps between horizontal neighbours jump at one phase of [`PERIOD`]: the
/// largest ratio of a phase's mean |step| to the larger of its two neighbouring phases'. A
/// continuous surface's steps change gradually from phase to phase (a bilinear one's are
/// equal across a cell, and a step across a sample is between its two cells' slopes): at most
/// about 1. A block edge puts a jump on one phase that its neighbours do not have.
fn blockiness(v: &[f32], w: usize) -> f64 {
    let mut sum = [0f64; PERIOD];
    let mut count = [0usize; PERIOD];
    for row in v.chunks(w) {
        for (x, pair) in row.windows(2).enumerate() {
            // The step between x and x + 1 crosses an edge at x + 1's phase 0.
            let phase = (x + 1) % PERIOD;
            sum[phase] += f64::from((pair[1] - pair[0]).abs());
            count[phase] += 1;
        }
    }
    let means: Vec<f64> = sum.iter().zip(count).map(|(s, n)| s / n as f64).collect();
    (0..PERIOD)
        .map(|p| {
            let around = means[(p + PERIOD - 1) % PERIOD].max(means[(p + 1) % PERIOD]);
            means[p] / around
        })
        .fold(0.0, f64::max)
}

/// A 64 x 64-pixel window at the image's centre, on pixel edges, read at 8x its pixels by the
/// continuous decoder: the luma-like mean of its channels.
fn zoomed(asset: &Asset, r: &Raster) -> (Vec<f32>, usize) {
    let (x0, y0) = (r.width / 2 - 32, r.height / 2 - 32);
    let rect = [
        x0 as f32 / r.width as f32,
        y0 as f32 / r.height as f32,
        (x0 + 64) as f32 / r.width as f32,
        (y0 + 64) as f32 / r.height as f32,
    ];
    let side = 64 * ZOOM;
    let (d, _) = asset
        .raster(Some(rect), side, side, None, Method::Continuous)
        .expect("a zoomed read");
    let n = d.channels.len() as f32;
    let mean = (0..side * side)
        .map(|i| d.channels.iter().map(|c| c[i]).sum::<f32>() / n)
        .collect();
    (mean, side)
}

#[test]
fn an_images_default_encode_zoomed_past_its_pixels_has_no_blocks() {
    for name in ["camera.png", "astronaut.png"] {
        let r = Raster::open(&testdata(name)).unwrap();
        let ours = encode_default(&r, 0.5, &|_, _| {}).unwrap();
        let mut settings = QuadtreeSettings {
            rate: RateMode::TargetBpp(0.5),
            ..QuadtreeSettings::default()
        };
        settings.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(r.kind);
        settings.quantiser_choices =
            QuadtreeSettings::default_quantiser_choices(r.kind, settings.quantiser);
        let quadtree = encode(&r, &settings, &|_, _| {}).unwrap();
        let asset = Asset::from_bytes(&ours.bytes).unwrap();
        assert_eq!(asset.codec_name(), "projected", "{name}");
        let (v, w) = zoomed(&asset, &r);
        let smooth = blockiness(&v, w);
        let (v, w) = zoomed(&Asset::from_bytes(&quadtree.bytes).unwrap(), &r);
        let blocks = blockiness(&v, w);
        println!("{name}: blockiness {smooth:.2} by default, {blocks:.2} on the quadtree");
        // The measure sees the quadtree's blocks (so that it can fail), and the default has
        // none. (Continuing the image's roughness through the operator's 2 x 2 blocks, as
        // height fields do, measured 1.6 on camera: a lattice of small squares.)
        assert!(blocks > 3.0, "{name}: the quadtree's blockiness {blocks}");
        assert!(smooth < 1.15, "{name}: the default's blockiness {smooth}");
    }
}
