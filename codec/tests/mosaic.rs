//! Mosaics of GeoTIFFs (issue 30): a real DEM cut into tiles and read back as one raster, and
//! the inputs a mosaic must refuse.

use std::path::{Path, PathBuf};

use fractile_codec::mosaic;
use fractile_codec::raster::{Raster, write_geotiff_f32};
use fractile_proto::Georef;

fn testdata(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// A fresh folder under the system's temporary one.
fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("fractile-mosaic-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Writes the window `[x0, x1) x [y0, y1)` of `r` as a GeoTIFF of its own, georeferenced where
/// it lies (its values with `shift` added, to tell overlapping inputs apart).
fn cut(r: &Raster, [x0, y0, x1, y1]: [usize; 4], shift: f32, path: &Path) {
    let g = r.georef.as_ref().expect("a georeferenced DEM");
    let values: Vec<f32> = (y0..y1)
        .flat_map(|y| (x0..x1).map(move |x| (x, y)))
        .map(|(x, y)| r.channels[0][y * r.width + x] + shift)
        .collect();
    let georef = Georef {
        epsg: g.epsg,
        origin: [
            g.origin[0] + x0 as f64 * g.pixel_size[0],
            g.origin[1] + y0 as f64 * g.pixel_size[1],
        ],
        pixel_size: g.pixel_size,
    };
    write_geotiff_f32(path, x1 - x0, y1 - y0, &values, Some(&georef), None).unwrap();
}

#[test]
fn a_dem_cut_into_tiles_reads_back_as_itself() {
    let src = Raster::open(&testdata("etopo20.tif")).expect("testdata");
    let (w, h) = (src.width, src.height);
    let dir = scratch("tiles");
    // Four tiles that share an edge column and row, as SRTM tiles do, the later ones shifted
    // by 1 m where they overlap the earlier (the first input wins there).
    let (mx, my) = (w / 2, h / 3);
    let windows = [
        [0, 0, mx + 1, my + 1],
        [mx, 0, w, my + 1],
        [0, my, mx + 1, h],
        [mx, my, w, h],
    ];
    for (k, win) in windows.iter().enumerate() {
        cut(&src, *win, k as f32, &dir.join(format!("n{k}.tif")));
    }
    // A folder, in name order, and the same files listed one by one.
    for inputs in [
        vec![dir.clone()],
        (0..4).map(|k| dir.join(format!("n{k}.tif"))).collect(),
    ] {
        let m = mosaic::open(&inputs).expect("a mosaic");
        assert_eq!((m.width, m.height), (w, h));
        assert_eq!(m.georef, src.georef, "the mosaic sits where the DEM does");
        assert!(m.valid.is_none(), "the tiles cover every cell");
        for y in 0..h {
            for x in 0..w {
                // The value of the first tile that covers the cell.
                let first = windows
                    .iter()
                    .position(|&[x0, y0, x1, y1]| (x0..x1).contains(&x) && (y0..y1).contains(&y))
                    .unwrap();
                let want = src.channels[0][y * w + x] + first as f32;
                let got = m.channels[0][y * w + x];
                assert_eq!(got, want, "cell ({x}, {y})");
            }
        }
    }
    // Three of the four: the fourth's cells are nodata, the others as they were.
    let m = mosaic::open(
        &(0..3)
            .map(|k| dir.join(format!("n{k}.tif")))
            .collect::<Vec<_>>(),
    )
    .expect("a mosaic with a hole");
    let valid = m.valid.as_ref().expect("a hole");
    for (y, x) in [(h - 1, w - 1), (my + 1, mx + 1)] {
        assert!(!valid[y * w + x] && m.channels[0][y * w + x].is_nan());
    }
    assert!(valid[0] && valid[(h - 1) * w] && valid[w - 1]);
    std::fs::remove_dir_all(&dir).ok();
}

/// Inputs of another pixel size or alignment (one CRS) are resampled onto the finest input's
/// grid: bilinear between the four cells around each target centre, so every resampled cell
/// is the weighted mean of its input cells, never outside them.
#[test]
fn inputs_off_the_grid_are_resampled_onto_the_finest() {
    let src = Raster::open(&testdata("etopo20.tif")).expect("testdata");
    let g = src.georef.clone().expect("georeferenced");
    let dir = scratch("resampled");
    let a = dir.join("a.tif");
    cut(&src, [0, 0, 40, 30], 0.0, &a);
    // The same cells as a's, placed 50.3 cells east: 0.3 of a cell off a's grid.
    let window: Vec<f32> = (0..30)
        .flat_map(|y| (0..40).map(move |x| (x, y)))
        .map(|(x, y)| src.channels[0][y * src.width + x])
        .collect();
    let shifted = dir.join("shifted.tif");
    let georef = Georef {
        origin: [g.origin[0] + 50.3 * g.pixel_size[0], g.origin[1]],
        ..g.clone()
    };
    write_geotiff_f32(&shifted, 40, 30, &window, Some(&georef), None).unwrap();
    let m = mosaic::open(&[a.clone(), shifted.clone()]).expect("resampled");
    assert_eq!(m.georef.as_ref().unwrap().pixel_size, g.pixel_size);
    assert_eq!(m.georef.as_ref().unwrap().origin, g.origin, "a's grid");
    // Target column 50 + i has its centre at input x = i + 0.2 cells: 0.3 of cell i - 1 and
    // 0.7 of cell i.
    for y in 0..30 {
        for i in 1..40 {
            let (left, right) = (window[y * 40 + i - 1], window[y * 40 + i]);
            let got = m.channels[0][y * m.width + 50 + i];
            let want = 0.3 * f64::from(left) + 0.7 * f64::from(right);
            assert!(
                (f64::from(got) - want).abs() < 1e-3,
                "({i}, {y}): {got} for {want}"
            );
            assert!(got >= left.min(right) - 1e-3 && got <= left.max(right) + 1e-3);
        }
    }
    // A finer input: the mosaic takes its grid, and a's cells are resampled onto it.
    let finer = dir.join("finer.tif");
    let fine = Georef {
        pixel_size: [g.pixel_size[0] / 2.0, g.pixel_size[1] / 2.0],
        origin: [g.origin[0] + 100.0 * g.pixel_size[0], g.origin[1]],
        ..g.clone()
    };
    write_geotiff_f32(&finer, 20, 10, &[1.0f32; 200], Some(&fine), None).unwrap();
    let m = mosaic::open(&[a.clone(), finer]).expect("resampled");
    assert_eq!(m.georef.as_ref().unwrap().pixel_size, fine.pixel_size);
    for y in 2..58 {
        for x in 2..78 {
            let got = m.channels[0][y * m.width + x];
            let near: Vec<f32> = [(x - 1) / 2, x / 2, x.div_ceil(2)]
                .iter()
                .flat_map(|&cx| [(y - 1) / 2, y.div_ceil(2)].map(|cy| window[cy * 40 + cx]))
                .collect();
            let (lo, hi) = near
                .iter()
                .fold((f32::MAX, f32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
            assert!(
                got >= lo - 1e-3 && got <= hi + 1e-3,
                "({x}, {y}): {got} outside {lo}..{hi}"
            );
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn inputs_in_projected_crss_alone_are_refused_by_name() {
    let src = Raster::open(&testdata("etopo20.tif")).expect("testdata");
    let g = src.georef.clone().expect("georeferenced");
    let dir = scratch("refused");
    let a = dir.join("a.tif");
    cut(&src, [0, 0, 40, 30], 0.0, &a);
    let write = |name: &str, georef: Georef| {
        let path = dir.join(name);
        let values = vec![1.0f32; 20 * 10];
        write_geotiff_f32(&path, 20, 10, &values, Some(&georef), None).unwrap();
        path
    };
    let other_crs = write(
        "utm.tif",
        Georef {
            epsg: Some(32616),
            ..g.clone()
        },
    );
    // Another pixel size or alignment is resampled (above), another CRS reprojected onto a
    // longitude/latitude input's grid (cli/tests/bucket_inputs.rs); projected CRSs with no
    // such input are refused by name.
    let utm17 = write(
        "utm17.tif",
        Georef {
            epsg: Some(32617),
            ..g.clone()
        },
    );
    let err = mosaic::open(&[other_crs.clone(), utm17])
        .expect_err("refused")
        .to_string();
    assert!(
        err.contains("projected CRSs") && err.contains("utm.tif") && err.contains("utm17.tif"),
        "{err}"
    );
    // Far apart: a mosaic of mostly nothing, bigger than the encoder takes.
    let far = write(
        "far.tif",
        Georef {
            origin: [g.origin[0] + 40_000.0 * g.pixel_size[0], g.origin[1]],
            ..g.clone()
        },
    );
    let err = mosaic::open(&[a.clone(), far])
        .expect_err("too big")
        .to_string();
    assert!(err.contains("larger than"), "{err}");
    // A folder with no GeoTIFF in it.
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let err = mosaic::open(&[empty]).expect_err("empty").to_string();
    assert!(err.contains("no GeoTIFF"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}
