//! The reader by range against the codec reading the whole file: the same heights for tiles at
//! zooms inside and past the source, only the chunks a tile reads fetched, and a call that
//! lacks bytes names them. On a chunked file of `testdata/golden` (jacksboro in chunks with
//! coarse views, UTM: a projected placement).

use fractile_codec::Asset;
use fractile_codec::geo::{Placement, tile_pixels};
use fractile_wasm::reader::{ITERATIONS, ReadError, Reader};

fn golden() -> Vec<u8> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../testdata/golden/v7-chunked-views-jacksboro.fra"
    );
    std::fs::read(path).expect("golden chunked file")
}

/// Runs `call` as the browser's worker does: fetch what it lacks, hand it over, ask again.
fn fetching<T>(
    r: &Reader,
    bytes: &[u8],
    mut call: impl FnMut(&Reader) -> Result<T, ReadError>,
) -> T {
    for _ in 0..64 {
        match call(r) {
            Ok(t) => return t,
            Err(ReadError::Missing(o, l)) => {
                let (o, l) = (o as usize, l as usize);
                assert!(o + l <= bytes.len(), "asked for bytes past the end");
                r.add(o as u64, bytes[o..o + l].to_vec());
            }
            Err(ReadError::Failed(m)) => panic!("{m}"),
        }
    }
    panic!("still lacking bytes after 64 fetches")
}

/// The tiles over the asset at zooms from two under its native one to three past it.
fn tiles(r: &Reader) -> Vec<(u8, u32, u32)> {
    let ([w, s, e, n], native) = r.map_frame(256).unwrap();
    let (lon, lat) = (0.5 * (w + e), 0.5 * (s + n));
    (native.saturating_sub(2)..=native + 3)
        .map(|z| {
            let (x, y) = fractile_codec::geo::lonlat_tile(z, lon, lat);
            (z, x, y)
        })
        .collect()
}

#[test]
fn tiles_read_by_range_are_the_whole_files_answers() {
    let bytes = golden();
    let mut r = Reader::new(bytes.len() as u64, 64 << 20);
    let meta = loop {
        match r.open() {
            Ok(m) => break m.clone(),
            Err(ReadError::Missing(o, l)) => {
                r.add(o, bytes[o as usize..(o + l) as usize].to_vec());
            }
            Err(ReadError::Failed(m)) => panic!("{m}"),
        }
    };
    let whole = Asset::from_bytes(&bytes).unwrap();
    assert_eq!(meta, whole.meta);
    assert!(whole.chunked().is_some(), "the golden file is chunked");
    let g = whole.meta.georef.as_ref().unwrap();
    let placement = Placement::of(g, whole.meta.width, whole.meta.height).unwrap();
    let tiles = tiles(&r);
    assert_eq!(tiles.len(), 6);
    let mut with_data = 0;
    for (z, x, y) in tiles {
        let ours = fetching(&r, &bytes, |r| r.tile((z, x, y), 256)).heights;
        // The server's extraction: the same calls on the whole file.
        let pixels = tile_pixels(Some(&placement), z, x, y, 256, 0);
        let tolerance = whole.tolerance_over(&pixels).unwrap();
        let (theirs, _) = whole.sample(&pixels, ITERATIONS, tolerance);
        assert_eq!(ours.len(), theirs[0].len());
        for (i, (a, b)) in ours.iter().zip(&theirs[0]).enumerate() {
            assert!(
                a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()),
                "{z}/{x}/{y} pixel {i}: {a} != {b}"
            );
        }
        with_data += usize::from(ours.iter().any(|v| v.is_finite()));
    }
    assert_eq!(with_data, 6, "every tile lies on the asset");
}

/// etopo20 (1,080 x 540 cells, the world) in chunks of 128: 45 chunks at the source level.
fn etopo_in_chunks() -> Vec<u8> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../testdata/etopo20.tif");
    let r = fractile_codec::Raster::open(std::path::Path::new(path)).unwrap();
    let one = |part: &fractile_codec::Raster| fractile_codec::encode_default(part, 0.8, &|_, _| {});
    fractile_codec::encode::chunked::encode_chunked(&r, 128, &one, &|_, _| {})
        .unwrap()
        .bytes
}

#[test]
fn a_tile_fetches_only_the_chunks_it_reads_and_names_them_first() {
    let bytes = etopo_in_chunks();
    let mut r = Reader::new(bytes.len() as u64, 64 << 20);
    // Nothing held: opening asks for the first bytes, no more than the opening's.
    match r.open() {
        Err(ReadError::Missing(0, l)) => assert!(l <= fractile_wasm::reader::OPENING_BYTES),
        other => panic!("{:?}", other.map(|m| m.width)),
    }
    let opened = loop {
        match r.open() {
            Ok(_) => break r.held_bytes(),
            Err(ReadError::Missing(o, l)) => r.add(o, bytes[o as usize..(o + l) as usize].to_vec()),
            Err(ReadError::Failed(m)) => panic!("{m}"),
        }
    };
    let deepest = *tiles(&r).last().unwrap();
    // Not fetched yet: the tile names the chunks it reads, and asking for it fails on one.
    let wanted = r.tile_ranges(deepest, 256).unwrap();
    assert!(!wanted.is_empty(), "a deep tile reads some chunk");
    assert!(matches!(r.tile(deepest, 256), Err(ReadError::Missing(..))));
    for &(o, l) in &wanted {
        r.add(o, bytes[o as usize..(o + l) as usize].to_vec());
    }
    // Named beforehand, those chunks are all it needs.
    let t = r.tile(deepest, 256).expect("the named chunks suffice");
    assert!(t.heights.iter().any(|v| v.is_finite()));
    let fetched = r.held_bytes() - opened;
    assert!(
        fetched < bytes.len() as u64 / 8,
        "{fetched} of {} bytes fetched for one tile (opening took {opened} more)",
        bytes.len()
    );
    assert!(
        r.tile_ranges(deepest, 256).unwrap().is_empty(),
        "all held now"
    );
}

/// A zoom-0 tile of a chunked DEM reads at most an eighth of its file (issue 73). etopo20
/// mirrored to 2160 x 1080, the world, in chunks of 256: zoom 0's pixels are 4 to 8.4 cells,
/// whose level (2) is a view of the source chunks, which it would read whole (94% of the file,
/// measured); the coded level above the views (270 x 135, one chunk) answers instead.
#[test]
fn a_zoom_zero_tile_reads_an_eighth_of_the_file_at_most() {
    use fractile_codec::encode::chunked::encode_chunked_at;
    use fractile_codec::encode::rate::FileRate;
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../testdata/etopo20.tif");
    let src = fractile_codec::Raster::open(std::path::Path::new(path)).unwrap();
    let mut r = fractile_codec::mosaic::mirrored(&src, 2, 2).unwrap();
    r.georef = Some(fractile_proto::Georef {
        epsg: Some(4326),
        origin: [-180.0, 90.0],
        pixel_size: [360.0 / r.width as f64, -180.0 / r.height as f64],
    });
    let rate = FileRate {
        bpp: 0.8,
        bounded: true,
    };
    let at = fractile_codec::encode::rate::encode_at;
    let bytes = encode_chunked_at(&r, 256, (rate, &at), &|_, _| {})
        .unwrap()
        .bytes;
    let asset = Asset::from_bytes(&bytes).unwrap();
    let table = &asset.chunked().unwrap().table;
    assert_eq!((table.levels.len(), table.views.len()), (4, 2));
    let mut reader = Reader::new(bytes.len() as u64, 64 << 20);
    let opened = loop {
        match reader.open() {
            Ok(_) => break reader.held_bytes(),
            Err(ReadError::Missing(o, l)) => {
                reader.add(o, bytes[o as usize..(o + l) as usize].to_vec())
            }
            Err(ReadError::Failed(m)) => panic!("{m}"),
        }
    };
    let t = fetching(&reader, &bytes, |r| r.tile((0, 0, 0), 256));
    assert!(t.heights.iter().filter(|v| v.is_finite()).count() > 256 * 100);
    let read = reader.held_bytes() - opened;
    assert!(
        read > 0 && read <= bytes.len() as u64 / 8,
        "zoom 0 read {read} of {} bytes (opening {opened})",
        bytes.len()
    );
}
