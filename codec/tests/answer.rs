//! `Asset::answer`, the one call a tile or a region is answered by (issue 76): the same values
//! and bounds as the calls it replaces (the tolerance settled over the pixels, the sample at
//! it, the source error over them), on an asset in one piece and in chunks, with the
//! tolerance settled and asked; and points through the same call, as `Asset::points` answers
//! them.

use fractile_codec::encode::chunked::encode_chunked;
use fractile_codec::extract::{CoarseGrids, Points, Request, Resources};
use fractile_codec::geo::{self, Placement};
use fractile_codec::{Asset, Raster, encode_default};

fn testdata(name: &str) -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// jacksboro, and its default encode in one piece and in chunks of 128 cells.
fn jacksboro_whole_and_chunked() -> (Raster, Asset, Asset) {
    let r = Raster::open(&testdata("jacksboro.tif")).expect("jacksboro");
    let whole = encode_default(&r, 0.8, &|_, _| {}).expect("whole").asset;
    let one = |part: &Raster| encode_default(part, 0.8, &|_, _| {});
    let chunked = encode_chunked(&r, 128, &one, &|_, _| {}).expect("chunked");
    let chunked = Asset::from_bytes(&chunked.bytes).expect("reads");
    (r, whole, chunked)
}

#[test]
fn one_answer_is_the_calls_it_replaces() {
    let (r, whole, chunked) = jacksboro_whole_and_chunked();
    assert!(chunked.chunked().is_some());
    let g = r.georef.as_ref().expect("a georeferenced DEM");
    // The answers keep their coarse grids; the calls they replace decode their own.
    let kept = CoarseGrids::new(64 << 20);
    let mut compared = 0;
    for (key, asset) in [&whole, &chunked].into_iter().enumerate() {
        let place = Placement::of(g, asset.meta.width, asset.meta.height).expect("placement");
        let [west, south, east, north] = place.bounds();
        let (lon, lat) = (0.3 * west + 0.7 * east, 0.6 * south + 0.4 * north);
        for z in [9u8, 12, 14, 17] {
            let (x, y) = geo::lonlat_tile(z, lon, lat);
            let pixels = geo::tile_pixels(Some(&place), z, x, y, 64, 1);
            for asked in [None, Some(0.5f32)] {
                let request = Request {
                    pixels: &pixels,
                    iterations: 64,
                    tolerance: asked,
                };
                let resources = Resources {
                    coarse: Some((&kept, key as u64)),
                    ..Resources::CPU
                };
                let answer = asset.answer(&request, &resources).expect("answers");
                let tolerance = match asked {
                    Some(t) => t,
                    None => asset.tolerance_over(&pixels).expect("tolerance"),
                };
                let (channels, convergence) = asset
                    .sample_with(&pixels, 64, tolerance, &Resources::CPU)
                    .expect("samples");
                let source = asset.source_error_over(&pixels).expect("source error");
                assert_eq!(
                    answer.tolerance.to_bits(),
                    tolerance.to_bits(),
                    "z{z} {asked:?}"
                );
                assert_eq!(answer.convergence.to_bits(), convergence.to_bits());
                assert_eq!(answer.source, source);
                assert!(answer.source.is_some(), "a map over the tile");
                let same = answer.channels[0]
                    .iter()
                    .zip(&channels[0])
                    .all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(same, "z{z} {asked:?}: other values");
                assert!(answer.channels[0].iter().any(|v| v.is_finite()));
                compared += 1;
            }
        }
    }
    assert_eq!(compared, 16);
    // The coarse zoom's grids went through the kept ones (the same bits as decoded).
    let counts = kept.counts();
    assert!(counts.misses >= 1 && !kept.is_empty(), "{counts:?}");
}

/// Points through the one call: each the value, bound, source error and steps `Asset::points`
/// gives at the tolerance asked, or at the asset's default where none is, whole and chunked.
#[test]
fn points_are_answered_by_the_same_call() {
    let (_, whole, chunked) = jacksboro_whole_and_chunked();
    // Sample centres, cell corners and points between, across the chunks' seams.
    let pts: Vec<[f32; 2]> = (0..97)
        .map(|k| {
            let t = k as f32 / 96.0;
            [0.03 + 0.94 * t, 0.9 - 0.8 * (t * 7.0).fract()]
        })
        .collect();
    for asset in [&whole, &chunked] {
        for asked in [None, Some(0.25f32), Some(0.0)] {
            let question = Points {
                points: &pts,
                iterations: 40,
                tolerance: asked,
            };
            let answer = asset.answer(&question, &Resources::CPU).expect("answers");
            let tolerance = asked.unwrap_or_else(|| asset.default_tolerance());
            let expected = asset.points(&pts, 40, tolerance);
            assert_eq!(answer.len(), pts.len());
            for (a, e) in answer.iter().zip(&expected) {
                assert_eq!(a.values[0].to_bits(), e.values[0].to_bits(), "{asked:?}");
                assert_eq!(a.error_bound.to_bits(), e.error_bound.to_bits());
                assert_eq!(a.source_error, e.source_error);
                assert_eq!(a.iterations, e.iterations);
            }
            assert!(answer.iter().all(|a| a.values[0].is_finite()));
        }
    }
}
