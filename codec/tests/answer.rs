//! `Asset::answer`, the one call a tile or a region is answered by (issue 76): the same values
//! and bounds as the calls it replaces (the tolerance settled over the pixels, the sample at
//! it, the source error over them), on an asset in one piece and in chunks, with the
//! tolerance settled and asked.

use fractile_codec::encode::chunked::encode_chunked;
use fractile_codec::extract::{CoarseGrids, Request, Resources};
use fractile_codec::geo::{self, Placement};
use fractile_codec::{Asset, Raster, encode_default};

fn testdata(name: &str) -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

#[test]
fn one_answer_is_the_calls_it_replaces() {
    let r = Raster::open(&testdata("jacksboro.tif")).expect("jacksboro");
    let whole = encode_default(&r, 0.8, &|_, _| {}).expect("whole").asset;
    let one = |part: &Raster| encode_default(part, 0.8, &|_, _| {});
    let chunked = encode_chunked(&r, 128, &one, &|_, _| {}).expect("chunked");
    let chunked = Asset::from_bytes(&chunked.bytes).expect("reads");
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
