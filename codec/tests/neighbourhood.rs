//! Decoded values stay in the neighbourhood of the data (issue 53), on the default DEM codec:
//! a native-size region answers the coded cells (within the encoder's reported max error at
//! every cell), and no sample of a region four times finer than the source leaves the range of
//! its 4 x 4 source neighbourhood by more than that error. Whole and chunked, on etopo20 and
//! jacksboro, and on etopo20 with a pixel size that is not a round number (perturbed by 1e-6,
//! as real GeoTIFFs' often are: 0.08333410511692521 for 1/12 degree), where positions that name
//! a cell centre reach the decoder a rounding off it.

use fractile_codec::encode::chunked::encode_chunked;
use fractile_codec::geo::Placement;
use fractile_codec::{Asset, Encoded, Raster, encode_default};

fn testdata(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// The default encode, whole or in chunks of `chunk` cells.
fn encode(r: &Raster, chunk: Option<u32>) -> Asset {
    let one = |part: &Raster| encode_default(part, 0.8, &|_, _| {});
    let enc: Encoded = match chunk {
        Some(c) => encode_chunked(r, c, &one, &|_, _| {}).expect("chunked encode"),
        None => one(r).expect("encode"),
    };
    Asset::from_bytes(&enc.bytes).expect("reads back")
}

/// The encoder's reported max error and the f32 rounding a decode may add (2^-20 of the value
/// range, as the codec's promise carries).
fn reported(r: &Raster, a: &Asset) -> f32 {
    let (lo, hi) = r.value_range();
    (a.meta.stats.max_error + (hi - lo) * 2f64.powi(-20)) as f32
}

/// Region pixels at `scale` samples a cell over cells `[x0, x1) x [y0, y1)`, through the
/// asset's georeference as a region request builds them (lon/lat of each pixel centre).
fn region(
    r: &Raster,
    a: &Asset,
    cells: [usize; 4],
    scale: usize,
) -> (Vec<f64>, Vec<f64>, Vec<f32>) {
    let g = r.georef.as_ref().expect("a georeferenced DEM");
    let p = Placement::of(g, a.meta.width, a.meta.height).expect("placement");
    let [x0, y0, x1, y1] = cells;
    let s = scale as f64;
    // Pixel centres, in cells from the grid's corner.
    let xs: Vec<f64> = (x0 * scale..x1 * scale)
        .map(|i| (i as f64 + 0.5) / s)
        .collect();
    let ys: Vec<f64> = (y0 * scale..y1 * scale)
        .map(|j| (j as f64 + 0.5) / s)
        .collect();
    let lons: Vec<f64> = xs
        .iter()
        .map(|x| g.origin[0] + x * g.pixel_size[0])
        .collect();
    let lats: Vec<f64> = ys
        .iter()
        .map(|y| g.origin[1] + y * g.pixel_size[1])
        .collect();
    let footprint = p.footprint(
        lons[lons.len() / 2],
        lats[lats.len() / 2],
        g.pixel_size[0] / s,
        -g.pixel_size[1] / s,
    );
    let pixels = p.pixels(&lons, &lats, footprint);
    let (values, _) = a.sample(&pixels, 40, a.default_tolerance());
    let heights = values.into_iter().next().expect("one channel");
    (xs, ys, heights)
}

/// The cells of the highest relief of `r`: a `side`-cell window centred on its highest cell.
fn around_the_peak(r: &Raster, side: usize) -> [usize; 4] {
    let top = (0..r.channels[0].len())
        .filter(|&i| r.is_valid(i))
        .max_by(|&a, &b| r.channels[0][a].total_cmp(&r.channels[0][b]))
        .expect("valid cells");
    let (x, y) = (top % r.width, top / r.width);
    let x0 = x.saturating_sub(side / 2).min(r.width - side);
    let y0 = y.saturating_sub(side / 2).min(r.height - side);
    [x0, y0, x0 + side, y0 + side]
}

/// Checks both bars on `r` coded whole and in chunks.
fn check(r: &Raster, name: &str, chunk: u32, side: usize) {
    for chunked in [None, Some(chunk)] {
        let a = encode(r, chunked);
        assert_eq!(a.chunked().is_some(), chunked.is_some());
        let e = reported(r, &a);
        let what = format!(
            "{name} ({})",
            if chunked.is_some() {
                "chunked"
            } else {
                "whole"
            }
        );
        // A native-size region of the whole grid: every valid cell within the reported error.
        let (w, h) = (r.width, r.height);
        let (_, _, native) = region(r, &a, [0, 0, w, h], 1);
        let mut worst = 0.0f32;
        for (i, v) in native.iter().enumerate() {
            if r.is_valid(i) {
                let err = (v - r.channels[0][i]).abs();
                assert!(err <= e, "{what}: cell {i} decodes {err} off, over {e}");
                worst = worst.max(err);
            }
        }
        assert!(worst > 0.0, "{what}: a lossy encode has errors");
        // A region four times finer around the highest peak, and one at the grid's corner.
        for cells in [around_the_peak(r, side), [0, 0, side, side]] {
            let (xs, ys, fine) = region(r, &a, cells, 4);
            let mut over = 0.0f32;
            for (j, y) in ys.iter().enumerate() {
                for (i, x) in xs.iter().enumerate() {
                    let v = fine[j * xs.len() + i];
                    let (lo, hi) = source_range(r, *x, *y);
                    over = over.max(v - hi).max(lo - v);
                }
            }
            assert!(
                over <= e,
                "{what}: a 4x sample leaves its 4 x 4 source range by {over}, over {e}"
            );
        }
    }
}

/// The source's range over the 4 x 4 cells around position (x, y) in cells (centres at
/// k + 0.5).
fn source_range(r: &Raster, x: f64, y: f64) -> (f32, f32) {
    let cell = |t: f64, n: usize| ((t - 0.5).floor().max(0.0) as usize).min(n - 2);
    let (i, j) = (cell(x, r.width), cell(y, r.height));
    let mut range = (f32::INFINITY, f32::NEG_INFINITY);
    for yy in j.saturating_sub(1)..=(j + 2).min(r.height - 1) {
        for xx in i.saturating_sub(1)..=(i + 2).min(r.width - 1) {
            let k = yy * r.width + xx;
            if r.is_valid(k) {
                let v = r.channels[0][k];
                range = (range.0.min(v), range.1.max(v));
            }
        }
    }
    range
}

#[test]
fn etopo20_decodes_its_cells_and_stays_near_them_at_4x() {
    let r = Raster::open(&testdata("etopo20.tif")).unwrap();
    check(&r, "etopo20", 256, 64);
}

#[test]
fn jacksboro_decodes_its_cells_and_stays_near_them_at_4x() {
    let r = Raster::open(&testdata("jacksboro.tif")).unwrap();
    check(&r, "jacksboro", 128, 64);
}

#[test]
fn a_pixel_size_off_a_round_number_changes_nothing() {
    let mut r = Raster::open(&testdata("etopo20.tif")).unwrap();
    let g = r.georef.as_mut().unwrap();
    g.pixel_size = g.pixel_size.map(|p| p * (1.0 + 1e-6));
    check(&r, "etopo20, pixel size x (1 + 1e-6)", 256, 64);
}

#[test]
fn a_grid_wider_than_f32_resolves_decodes_its_cells() {
    // etopo20 four times side by side, at a quarter of its pixel width (off a round number
    // too): 4,320 cells a row, as a global 5-minute DEM has, where a position in cells in f32
    // carries 2.4e-4 of a cell, half the position quantum of a 1,024-cell chunk. Chunks then
    // decoded cells off their centres, 100-260 m off on such a DEM.
    let one = Raster::open(&testdata("etopo20.tif")).unwrap();
    let mut r = one.clone();
    r.width = 4 * one.width;
    r.channels = vec![
        (0..one.height * r.width)
            .map(|k| one.channels[0][(k / r.width) * one.width + k % r.width % one.width])
            .collect(),
    ];
    let g = r.georef.as_mut().unwrap();
    g.pixel_size[0] *= (1.0 + 1e-6) / 4.0;
    let a = encode(&r, Some(1024));
    let e = reported(&r, &a);
    let (_, _, native) = region(&r, &a, [0, 0, r.width, r.height], 1);
    let off: Vec<usize> = (0..native.len())
        .filter(|&i| (native[i] - r.channels[0][i]).abs() > e)
        .collect();
    assert!(
        off.is_empty(),
        "{} cells decode over {e}: {:?}",
        off.len(),
        &off[..off.len().min(8)]
    );
}
