//! Tests of chunked encodes: sizes, rates, files written and read back.

use super::*;
use std::sync::Mutex;

fn testdata(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

/// Where a chunk lies: its level (pixel size), corner and size.
fn key(r: &Raster) -> (u64, u64, u64, usize, usize) {
    let g = r.georef.as_ref().expect("georeferenced");
    (
        g.pixel_size[0].to_bits(),
        g.origin[0].to_bits(),
        g.origin[1].to_bits(),
        r.width,
        r.height,
    )
}

/// The cells `[x0, y0, x1, y1)` of a whole raster (its georeference moved to the corner).
fn crop(r: &Raster, [x0, y0, x1, y1]: [u32; 4]) -> Raster {
    let (x0, y0, x1, y1) = (x0 as usize, y0 as usize, x1 as usize, y1 as usize);
    let rows = |p: &[f32]| -> Vec<f32> {
        (y0..y1)
            .flat_map(|y| p[y * r.width + x0..y * r.width + x1].to_vec())
            .collect()
    };
    let valid = r.valid.as_ref().map(|v| {
        (y0..y1)
            .flat_map(|y| v[y * r.width + x0..y * r.width + x1].to_vec())
            .collect::<Vec<bool>>()
    });
    Header::of(r).band(
        [x0, y0],
        x1 - x0,
        r.channels.iter().map(|c| rows(c)).collect(),
        valid.filter(|v| v.contains(&false)),
    )
}

/// The chunks a streaming encode codes, read a band at a time, are the cells a chunk of
/// the raster held whole (and of its overviews, halved whole) holds: nodata cells, odd
/// sizes and the last lone row of a level included.
#[test]
fn streamed_chunks_are_the_whole_rasters_chunks() {
    // 344 x 363 with nodata around the rotated source: levels of 344 x 363, 172 x 182,
    // 86 x 91 in chunks of 64.
    let raster = Raster::open(&testdata("jacksboro-utm.tif")).unwrap();
    let seen = Mutex::new(Vec::new());
    let one = |part: &Raster| {
        seen.lock().unwrap().push(part.clone());
        crate::encode_default(part, 0.8, &|_, _| {})
    };
    let enc = encode_chunked(&raster, 64, &one, &|_, _| {}).unwrap();
    let table = &enc.asset.chunked().unwrap().table;
    let mut level = raster.clone();
    let mut expected = Vec::new();
    for (l, lev) in table.levels.iter().enumerate() {
        if l > 0 {
            level = super::super::pyramid::halve(&level);
        }
        assert_eq!(
            (lev.width as usize, lev.height as usize),
            (level.width, level.height)
        );
        // A view level is read from the source chunks, not coded.
        for e in lev.chunks.iter().filter(|_| !table.is_view(l)) {
            let part = crop(&level, e.cells);
            if part.valid.as_ref().is_none_or(|v| v.contains(&true)) {
                expected.push(part);
            }
        }
    }
    let mut seen = seen.into_inner().unwrap();
    // Aside: the surface that tells whether the codec's overviews may be views (32 x 32,
    // no georeference; this codec's are: two view levels, a coded level above them).
    let probes = seen.iter().filter(|p| p.georef.is_none()).count();
    assert_eq!(probes, 1);
    seen.retain(|p| p.georef.is_some());
    assert_eq!(seen.len(), expected.len());
    assert!(
        table.levels.len() == 4 && table.views.len() == 2 && expected.len() > 30,
        "{}",
        expected.len()
    );
    seen.sort_by_key(key);
    expected.sort_by_key(key);
    for (s, e) in seen.iter().zip(&expected) {
        assert_eq!(key(s), key(e));
        assert_eq!(s.valid, e.valid, "{:?}", key(e));
        for (a, b) in s.channels[0].iter().zip(&e.channels[0]) {
            assert!(
                a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()),
                "{a} {b}"
            );
        }
    }
}
