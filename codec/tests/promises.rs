//! A bound holds in what a user receives (issue 73): for every test DEM, in chunks and in one
//! piece, under `--max-error E` and the bounded default, every valid cell of every output that
//! lands on the source's cells is within the file's bound, computed in float64 from the
//! float32 values delivered: the whole decode (`fractile decode`'s GeoTIFF, Python's `read`),
//! a window of it, the pixels of a region on the source's grid (the server's `.f32` regions)
//! and the points at cell centres (`/points`), each as those callers make them. The
//! float32 roundings of a value once took `--max-error 1` to 1.0029.

use fractile_codec::codecs::projected::ProjectedSettings;
use fractile_codec::encode::chunked::encode_chunked_at;
use fractile_codec::encode::rate::encode_at;
use fractile_codec::encode::rate::{FileRate, Quality};
use fractile_codec::geo::{Pixels, Sites};
use fractile_codec::{Asset, Encoded, Method, Raster};

fn testdata(name: &str) -> Raster {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name);
    Raster::open(&path).expect("a test DEM")
}

/// The largest |delivered - source| over the valid cells of a window `[x0, y0, x1, y1)` of
/// `r`, whose values `out` are row-major over the window.
fn worst(r: &Raster, [x0, y0, x1, y1]: [usize; 4], out: &[f32]) -> f64 {
    let w = x1 - x0;
    let mut worst = 0.0f64;
    for y in y0..y1 {
        for x in x0..x1 {
            let i = y * r.width + x;
            if r.valid.as_ref().is_some_and(|v| !v[i]) {
                continue;
            }
            let d = f64::from(out[(y - y0) * w + x - x0]);
            assert!(d.is_finite(), "cell ({x}, {y}) delivered {d}");
            worst = worst.max((d - f64::from(r.channels[0][i])).abs());
        }
    }
    worst
}

/// Every output of `enc` (coded from `r`) within `bound`, the bound it says.
fn every_output_within(name: &str, r: &Raster, enc: &Encoded, bound: f64) {
    let asset = Asset::from_bytes(&enc.bytes).expect("the file opens");
    let (w, h) = (r.width, r.height);
    let all = [0, 0, w, h];
    let (decoded, _) = asset.decode_native();
    let e = worst(r, all, &decoded.channels[0]);
    assert!(
        e <= bound,
        "{name}: the whole decode is {e} from the source, over {bound}"
    );
    let (raster, _) = asset
        .raster(None, w, h, None, Method::Auto)
        .expect("a whole read");
    let e = worst(r, all, &raster.channels[0]);
    assert!(
        e <= bound,
        "{name}: the read is {e} from the source, over {bound}"
    );
    // A window on cell edges, read at the source's resolution.
    let win = [w / 5, h / 3, w / 5 + w / 2, h / 3 + h / 2];
    let unit = |v: usize, n: usize| v as f32 / n as f32;
    let rect = [
        unit(win[0], w),
        unit(win[1], h),
        unit(win[2], w),
        unit(win[3], h),
    ];
    let (part, _) = asset
        .raster(
            Some(rect),
            win[2] - win[0],
            win[3] - win[1],
            None,
            Method::Auto,
        )
        .expect("a window");
    let e = worst(r, win, &part.channels[0]);
    assert!(
        e <= bound,
        "{name}: a window is {e} from the source, over {bound}"
    );
    // A region's pixels on the source's cells, as the server samples them.
    let centre = |i: usize, n: usize| Some((i as f32 + 0.5) / n as f32);
    let pixels = Pixels {
        sites: Sites::Grid {
            xs: (0..w).map(|i| centre(i, w)).collect(),
            ys: (0..h).map(|j| centre(j, h)).collect(),
        },
        footprint: [1.0 / w as f32, 1.0 / h as f32],
    };
    let tolerance = asset.tolerance_over(&pixels).expect("a tolerance");
    let (values, _) = asset.sample(&pixels, 40, tolerance);
    let e = worst(r, all, &values[0]);
    assert!(
        e <= bound,
        "{name}: a region is {e} from the source, over {bound}"
    );
    // Points at every 7th cell centre.
    let cells: Vec<(usize, usize)> = (0..h)
        .step_by(7)
        .flat_map(|y| (0..w).step_by(7).map(move |x| (x, y)))
        .collect();
    let pts: Vec<[f32; 2]> = cells
        .iter()
        .map(|&(x, y)| [(x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32])
        .collect();
    for (p, &(x, y)) in asset.points(&pts, 40, 0.0).iter().zip(&cells) {
        let i = y * w + x;
        if r.valid.as_ref().is_some_and(|v| !v[i]) {
            continue;
        }
        let e = (f64::from(p.values[0]) - f64::from(r.channels[0][i])).abs();
        assert!(
            e <= bound,
            "{name}: the point ({x}, {y}) is {e} away, over {bound}"
        );
    }
}

/// `--max-error E` in one piece and in chunks (of 128 here, so that the small test DEMs have
/// chunks, views and a coded level above them), on an integer DEM, a float one with fractions,
/// and one with nodata.
#[test]
fn every_output_of_a_max_error_file_is_within_its_bound() {
    let mut fractional = testdata("topobathy.tif");
    for (i, v) in fractional.channels[0].iter_mut().enumerate() {
        *v += 0.37 * (i as f32).sin();
    }
    let mut holes = testdata("jacksboro.tif");
    let (w, h) = (holes.width, holes.height);
    holes.valid = Some((0..w * h).map(|i| (i % w + i / w) % 11 != 3).collect());
    let dems = [
        ("etopo20", testdata("etopo20.tif")),
        ("jacksboro with nodata", holes),
        ("topobathy with fractions", fractional),
    ];
    for (name, r) in &dems {
        for e in [0.5, 1.0, 10.0, 150.0] {
            let whole = fractile_codec::encode(
                r,
                &ProjectedSettings {
                    max_error: Some(e),
                    ..Default::default()
                },
                &|_, _| {},
            )
            .unwrap();
            every_output_within(&format!("{name} whole at {e}"), r, &whole, e);
            if r.width >= 256 {
                let chunked =
                    encode_chunked_at(r, 128, (Quality::Bound(e), &encode_at), &|_, _| {}).unwrap();
                every_output_within(&format!("{name} in chunks at {e}"), r, &chunked, e);
            }
        }
    }
}

/// The bounded default keeps the bound it reports, in one piece and in chunks.
#[test]
fn every_output_of_a_bounded_file_is_within_the_bound_it_reports() {
    let r = testdata("etopo20.tif");
    let rate = FileRate {
        bpp: 0.8,
        bounded: true,
    };
    let chunked = encode_chunked_at(&r, 128, (rate, &encode_at), &|_, _| {}).unwrap();
    let reported = chunked.asset.meta.stats.max_error;
    assert!(reported > 0.0 && reported == reported.round(), "{reported}");
    every_output_within("etopo20 bounded in chunks", &r, &chunked, reported);
    let whole = fractile_codec::encode_default(&r, 0.8, &|_, _| {}).unwrap();
    every_output_within(
        "etopo20 bounded",
        &r,
        &whole,
        whole.asset.meta.stats.max_error,
    );
}
