//! Rasters read by bands of rows (issue 30): a GeoTIFF read strip by strip or tile by tile
//! holds what the file holds, whatever the bands asked, and a chunked encode streamed from a
//! file to disk writes what the same encode of the raster in memory writes.

use fractile_codec::encode::chunked::{encode_chunked, encode_chunked_file};
use fractile_codec::rows::{GeoTiff, Rows};
use fractile_codec::{Encoded, Raster, encode_default};

fn testdata(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// `rows` read in bands of `n` rows, joined.
fn by_bands(rows: &mut dyn Rows, n: usize) -> Raster {
    let h = rows.header().height;
    let mut joined = rows.read(0, n.min(h)).unwrap();
    let mut valid = joined
        .valid
        .take()
        .unwrap_or_else(|| vec![true; joined.width * joined.height]);
    let mut y = n.min(h);
    while y < h {
        let band = rows.read(y, (y + n).min(h)).unwrap();
        assert_eq!(band.height, (y + n).min(h) - y);
        joined.channels[0].extend_from_slice(&band.channels[0]);
        match &band.valid {
            Some(v) => valid.extend_from_slice(v),
            None => valid.resize(valid.len() + band.width * band.height, true),
        }
        // Each band is georeferenced at its own top row.
        let (g, g0) = (band.georef.unwrap(), joined.georef.as_ref().unwrap());
        assert_eq!(g.origin[1], g0.origin[1] + y as f64 * g0.pixel_size[1]);
        y += n;
    }
    joined.height = h;
    joined.valid = valid.contains(&false).then_some(valid);
    joined
}

fn same_cells(a: &Raster, b: &Raster, what: &str) {
    assert_eq!((a.width, a.height), (b.width, b.height), "{what}");
    assert_eq!(a.valid, b.valid, "{what}: validity");
    for (i, (x, y)) in a.channels[0].iter().zip(&b.channels[0]).enumerate() {
        assert!(
            x.to_bits() == y.to_bits() || !a.is_valid(i),
            "{what}: cell {i}: {x} against {y}"
        );
    }
}

#[test]
fn a_geotiff_reads_the_same_by_strips_tiles_and_bands() {
    // jacksboro.tif has strips of 10 rows; jacksboro-tiled.tif is the same grid in 64 x 64
    // tiles (edge tiles padded: 403 x 344 is no multiple of 64).
    let strips = GeoTiff::open(&testdata("jacksboro.tif")).unwrap();
    let tiles = GeoTiff::open(&testdata("jacksboro-tiled.tif")).unwrap();
    assert_eq!(strips.header(), tiles.header());
    let whole = Raster::open(&testdata("jacksboro.tif")).unwrap();
    // Figures of the file read by tifffile 2025 (numpy), independent of this reader.
    let at = |x: usize, y: usize| whole.channels[0][y * whole.width + x];
    assert_eq!((whole.width, whole.height), (403, 344));
    let sum: f64 = whole.channels[0].iter().map(|&v| f64::from(v)).sum();
    assert_eq!(sum, 73_617_913.0);
    assert_eq!(
        [at(0, 0), at(402, 343), at(200, 100), at(64, 200)],
        [483.0, 272.0, 522.0, 568.0]
    );
    for n in [1, 7, 10, 64, 100, 344, 1000] {
        for name in ["jacksboro.tif", "jacksboro-tiled.tif"] {
            let mut rows = GeoTiff::open(&testdata(name)).unwrap();
            same_cells(
                &by_bands(&mut rows, n),
                &whole,
                &format!("{name} in bands of {n}"),
            );
        }
    }
    // Strips of 3 and 11 rows, float samples, and nodata cells: bands against the whole.
    for name in ["etopo20.tif", "jacksboro-utm.tif", "topobathy.tif"] {
        let whole = Raster::open(&testdata(name)).unwrap();
        for n in [5, 128] {
            let mut rows = GeoTiff::open(&testdata(name)).unwrap();
            same_cells(
                &by_bands(&mut rows, n),
                &whole,
                &format!("{name} in bands of {n}"),
            );
        }
    }
    let utm = Raster::open(&testdata("jacksboro-utm.tif")).unwrap();
    assert!(
        utm.valid.as_ref().is_some_and(|v| v.contains(&false)),
        "nodata read as nodata"
    );
}

fn one(part: &Raster) -> Result<Encoded, fractile_codec::Error> {
    encode_default(part, 0.8, &|_, _| {})
}

#[test]
fn a_chunked_encode_streamed_from_a_file_writes_what_the_encode_in_memory_does() {
    let dir = std::env::temp_dir().join(format!("fractile-rows-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // Nodata outside the rotated source, and an odd height (363): overviews of odd sizes.
    let name = "jacksboro-utm.tif";
    let raster = Raster::open(&testdata(name)).unwrap();
    let in_memory = encode_chunked(&raster, 64, &one, &|_, _| {}).unwrap();
    let out = dir.join("streamed.fra");
    let mut rows = GeoTiff::open(&testdata(name)).unwrap();
    let written = encode_chunked_file(&mut rows, 64, &one, &|_, _| {}, &out).unwrap();
    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(written.length, bytes.len() as u64);
    assert_eq!(bytes.len(), in_memory.bytes.len());
    // Chunk files and the file's metadata hold no encode time: the same bytes.
    assert!(
        bytes == in_memory.bytes,
        "a streamed encode wrote other bytes"
    );
    let table = &written.asset.chunked().unwrap().table;
    assert!(table.levels.len() >= 3, "overviews");
    assert_eq!(written.errors.rmse, in_memory.errors.rmse);
    // Nothing but the output is left beside it (the spilled chunks were in an unnamed file).
    let left: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left, vec![std::ffi::OsString::from("streamed.fra")]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A GeoTIFF placed by what its catalog says (`GeoTiff::declared`, a STAC item's grid) reads
/// what the file holds once its header agrees; a catalog that says another grid is an error
/// naming both, at the first read.
#[test]
fn a_declared_geotiff_is_checked_against_its_header_when_read() {
    use fractile_codec::rows::TiffSource;
    let path = testdata("jacksboro-tiled.tif");
    let mut opened = GeoTiff::open(&path).unwrap();
    let header = opened.header().clone();
    let source = TiffSource::File(path.clone());
    let mut declared = GeoTiff::declared(source.clone(), header.clone());
    let whole = opened.read(0, header.height).unwrap();
    same_cells(&by_bands(&mut declared, 37), &whole, "declared");
    let wrong = |edit: &dyn Fn(&mut fractile_codec::rows::Header)| {
        let mut h = header.clone();
        edit(&mut h);
        let mut d = GeoTiff::declared(source.clone(), h);
        d.read(0, 8).expect_err("a wrong catalog read").to_string()
    };
    let err = wrong(&|h| h.width -= 1);
    let (said, held) = (
        format!("its catalog says {}x", header.width - 1),
        format!("the file holds {}x", header.width),
    );
    assert!(err.contains(&said) && err.contains(&held), "{err}");
    let err = wrong(&|h| h.georef.as_mut().unwrap().origin[0] += 1e-3);
    assert!(err.contains("its catalog says"), "{err}");
    let err = wrong(&|h| h.nodata = Some(-9999.0));
    assert!(err.contains("nodata Some(-9999.0)"), "{err}");
}
