//! Chunked assets (format version 6) on a real DEM: every cell within the bound its answer
//! carries, no seam between chunks beyond their own errors, coarse pixels answered from the
//! overview of their size, and corrupt or empty chunks answered by name without losing the
//! rest.

use fractile_codec::chunked::is_chunked;
use fractile_codec::encode::chunked::encode_chunked;
use fractile_codec::extract::{Resources, SampleError};
use fractile_codec::geo::{Pixels, Sites};
use fractile_codec::{Asset, Encoded, Raster, encode_default};

fn testdata(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name)
}

const CHUNK: u32 = 256;

fn chunked(r: &Raster) -> Encoded {
    let one = |part: &Raster| encode_default(part, 0.8, &|_, _| {});
    encode_chunked(r, CHUNK, &one, &|_, _| {}).expect("chunked encode")
}

/// What f32 rounding may add to a bound (a few units in the last place of the value range).
fn rounding(r: &Raster) -> f32 {
    let (lo, hi) = r.value_range();
    ((hi - lo) * 2f64.powi(-20)) as f32
}

fn file_of(enc: &Encoded, name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("fractile-chunked-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, &enc.bytes).unwrap();
    path
}

#[test]
fn every_cell_of_a_chunked_dem_is_within_its_bound_and_chunks_meet_within_their_errors() {
    let r = Raster::open(&testdata("etopo20.tif")).unwrap();
    let (w, h) = (r.width, r.height);
    let enc = chunked(&r);
    assert!(is_chunked(&enc.bytes));
    // Read by range from a file, as a server does.
    let asset = Asset::read(&file_of(&enc, "etopo20.fra")).unwrap();
    let table = &asset.chunked().expect("chunked").table;
    assert!(
        table.levels[0].chunks.len() >= 6,
        "{:?}",
        table.levels[0].chunks.len()
    );
    assert!(table.levels.len() >= 2, "overviews");
    // Every cell centre.
    let pts: Vec<[f32; 2]> = (0..h)
        .flat_map(|y| {
            (0..w).map(move |x| [(x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32])
        })
        .collect();
    let answers = asset
        .try_points_with(&pts, 40, 0.0, &|_, _, _, _| None)
        .unwrap();
    let slack = rounding(&r);
    let mut worst = 0.0f32;
    for (i, a) in answers.iter().enumerate() {
        let bound = a.error_bound + a.source_error.expect("each chunk has a map") + slack;
        let err = (a.values[0] - r.channels[0][i]).abs();
        assert!(err <= bound, "cell {i}: error {err} over its bound {bound}");
        worst = worst.max(err);
    }
    assert!(worst > 0.0, "a lossy rate has errors");
    // A native read (`fractile decode`, Python's `read`) answers every cell by its chunk's
    // sample, the attractor there: within each chain's bound of its point's answer, and
    // within the cell's source error of the source.
    let (read, _) = asset
        .raster(None, w, h, None, fractile_codec::Method::Auto)
        .unwrap();
    for (i, a) in answers.iter().enumerate() {
        let v = read.channels[0][i];
        let chain = (v - a.values[0]).abs();
        assert!(
            chain <= a.error_bound + slack,
            "cell {i}: {chain} from its chain"
        );
        let err = (v - r.channels[0][i]).abs();
        assert!(
            err <= a.source_error.unwrap() + slack,
            "cell {i}: error {err}"
        );
    }
    // Seams: just either side of every chunk edge, the two chunks' answers differ by at most
    // the sum of their bounds (each is within its bound of the bilinear source, which is
    // continuous).
    let eps = 1e-3;
    let mut seams = 0;
    for k in 1..(w as u32 / CHUNK) {
        let x = (k * CHUNK) as f32;
        for y in (0..h).step_by(7) {
            let v = (y as f32 + 0.5) / h as f32;
            let pair = [[(x - eps) / w as f32, v], [(x + eps) / w as f32, v]];
            let a = asset
                .try_points_with(&pair, 40, 0.0, &|_, _, _, _| None)
                .unwrap();
            let bound: f32 = a
                .iter()
                .map(|p| p.error_bound + p.source_error.unwrap())
                .sum();
            let step = (a[0].values[0] - a[1].values[0]).abs();
            assert!(
                step <= bound + 2.0 * slack,
                "seam at x {x}, row {y}: {step} > {bound}"
            );
            seams += 1;
        }
    }
    assert!(seams > 100);
    // The file's bytes back, whole.
    assert_eq!(asset.to_bytes(), enc.bytes);
}

#[test]
fn coarse_pixels_are_answered_from_the_overview_of_their_size() {
    let r = Raster::open(&testdata("etopo20.tif")).unwrap();
    let (w, h) = (r.width, r.height);
    let asset = Asset::from_bytes(&chunked(&r).bytes).unwrap();
    let centres = |n: usize| (0..n).map(|i| Some((i as f32 + 0.5) / n as f32)).collect();
    let table = &asset.chunked().unwrap().table;
    let levels = table.levels.len();
    assert_eq!(
        (levels, table.views.len()),
        (4, 2),
        "1080 x 540 in chunks of 256: 540 x 270 and 270 x 135 views, a coded 135 x 68 above"
    );
    // Pixels of b x b source cells (the cells of level log2(b): 1 and 2, views; 3, the top):
    // over the whole raster for the coded level; over the first chunk's cells for a view,
    // which never answers pixels that span half the raster on both axes.
    for level in 1..levels {
        let b = 1usize << level;
        let view = table.is_view(level);
        let (pw, ph) = if view {
            (CHUNK as usize / b, CHUNK as usize / b)
        } else {
            (w / b, h / b)
        };
        // A view's sample k is the source cell b k, decoded: pixels centred there. A coded
        // level's cell is the mean of its b x b block: pixels centred on the blocks.
        let at = |n: usize, k: usize| {
            let centre = if view { b * k } else { b * k + b / 2 };
            (centre as f32 + if view { 0.5 } else { 0.0 }) / n as f32
        };
        let pixels = Pixels {
            sites: Sites::Grid {
                xs: (0..pw).map(|i| Some(at(w, i))).collect(),
                ys: (0..ph).map(|j| Some(at(h, j))).collect(),
            },
            footprint: [b as f32 / w as f32, b as f32 / h as f32],
        };
        let (values, bound) = asset.sample(&pixels, 40, 0.0);
        assert!(bound.is_finite());
        // A view stands for the source cells on its lattice, decoded within the source
        // chunks' bound; a coded level for the block means, rounded to the source's integers at
        // each halving (half a metre each), coded within each of its chunks' bound.
        let mut worst = 0.0f32;
        for j in 0..ph {
            for i in 0..pw {
                let stands_for = if view {
                    f64::from(r.channels[0][b * j * w + b * i])
                } else {
                    (0..b)
                        .flat_map(|dy| (0..b).map(move |dx| (b * i + dx, b * j + dy)))
                        .map(|(x, y)| r.channels[0][y * w + x] as f64)
                        .sum::<f64>()
                        / (b * b) as f64
                };
                worst = worst.max((values[0][j * pw + i] - stands_for as f32).abs());
            }
        }
        let chunks = asset.chunked().unwrap();
        let coded = if view { 0 } else { level };
        let promise = (0..chunks.table.levels[coded].chunks.len())
            .filter_map(|i| chunks.chunk(coded, i).unwrap())
            .map(|c| c.planes()[0].promise().expect("bounded") + c.bound_after(40))
            .fold(0.0f32, f32::max);
        let slack = if view {
            0.0
        } else {
            0.5 * level as f32 + rounding(&r)
        };
        assert!(
            worst <= promise + slack,
            "level {level}: {worst} > {promise}"
        );
    }
    // And a sample whose pixels are coarser than the whole asset still answers (the top
    // level, filtered by its one chunk).
    let tiny = Pixels {
        sites: Sites::Grid {
            xs: centres(4),
            ys: centres(2),
        },
        footprint: [0.25, 0.5],
    };
    let (v, _) = asset.sample(&tiny, 40, 0.0);
    assert!(v[0].iter().all(|x| x.is_finite()));
}

#[test]
fn a_corrupt_chunk_is_refused_by_name_and_the_other_chunks_still_answer() {
    let r = Raster::open(&testdata("etopo20.tif")).unwrap();
    let enc = chunked(&r);
    let table = Asset::from_bytes(&enc.bytes)
        .unwrap()
        .chunked()
        .unwrap()
        .table
        .clone();
    let last = table.levels[0].chunks.last().unwrap().clone();
    let mut bytes = enc.bytes.clone();
    bytes[(last.offset + last.length / 2) as usize] ^= 0x40;
    let asset = Asset::read(&file_of(&Encoded { bytes, ..enc }, "corrupt.fra")).unwrap();
    let hook = |_: fractile_codec::extract::PlaneRef<'_>,
                _: fractile_codec::extract::Sites<'_>,
                _,
                _| None;
    let first = asset
        .try_points_with(&[[0.01, 0.01]], 20, 0.0, &hook)
        .unwrap();
    assert!(first[0].values[0].is_finite());
    let err = asset
        .try_points_with(&[[0.99, 0.99]], 20, 0.0, &hook)
        .unwrap_err();
    assert!(err.to_string().contains("checksum"), "{err}");
    let pixels = Pixels {
        sites: Sites::List {
            width: 1,
            points: vec![Some([0.99, 0.99])],
            patches: Vec::new(),
        },
        footprint: [1e-4, 1e-4],
    };
    assert!(matches!(
        asset.sample_with(&pixels, 20, 0.0, &Resources::CPU),
        Err(SampleError::Chunk(_))
    ));
    // A corrupt header is refused when the file opens.
    let enc = chunked(&r);
    let mut bytes = enc.bytes.clone();
    bytes[40] ^= 1;
    let err = Asset::from_bytes(&bytes).unwrap_err().to_string();
    assert!(
        err.contains("checksum") || err.contains("metadata"),
        "{err}"
    );
}

#[test]
fn chunks_without_data_answer_nodata_and_the_rest_answer_values() {
    let mut r = Raster::open(&testdata("etopo20.tif")).unwrap();
    let w = r.width;
    // The north-west chunk and its overlap: no data.
    let mut valid = vec![true; r.width * r.height];
    for y in 0..(CHUNK as usize + 8) {
        for x in 0..(CHUNK as usize + 8) {
            valid[y * w + x] = false;
            r.channels[0][y * w + x] = f32::NAN;
        }
    }
    r.valid = Some(valid);
    let enc = chunked(&r);
    let asset = Asset::from_bytes(&enc.bytes).unwrap();
    assert_eq!(asset.chunked().unwrap().table.levels[0].chunks[0].length, 0);
    let (u, v) = (10.0 / w as f32, 10.0 / r.height as f32);
    let p = asset.points(&[[u, v], [0.9, 0.9]], 20, 0.0);
    assert!(p[0].values[0].is_nan(), "{:?}", p[0]);
    assert!(p[1].values[0].is_finite());
}

/// Prefetching fills a cache with every chunk when they fit, coarsest level first, and stops
/// before its budget when they do not; a corrupt chunk is skipped (its requests report it).
#[test]
fn prefetch_decodes_chunks_coarsest_first_within_its_budget() {
    use fractile_codec::chunked::ChunkCache;
    let r = Raster::open(&testdata("etopo20.tif")).unwrap();
    let enc = chunked(&r);
    let path = file_of(&enc, "prefetch.fra");
    let limits = fractile_codec::AssetLimits::default();
    let open = |mib: u64| {
        let cache = ChunkCache::new(mib << 20);
        let a = Asset::open(&path, &limits, cache.clone()).unwrap();
        (a, cache)
    };
    let (asset, cache) = open(256);
    let c = asset.chunked().unwrap();
    let all: usize = c.table.levels.iter().map(|l| l.chunks.len()).sum();
    assert!(all > 4, "{all} chunks");
    assert_eq!(cache.weighted_bytes(), 0);
    let (n, bytes) = c.prefetch(cache.capacity());
    assert_eq!(n, all);
    assert_eq!(bytes, cache.weighted_bytes());
    // A budget of a byte: the first chunk only, the top level's (built whole: 44 bytes a cell,
    // where the finer levels' hold about 5).
    let (asset, cache) = open(256);
    let c = asset.chunked().unwrap();
    let (n, top) = c.prefetch(1);
    let l = c.table.levels.last().unwrap();
    assert_eq!(n, 1);
    assert!(
        top > 30 * u64::from(l.width) * u64::from(l.height),
        "{top} bytes"
    );
    // Twice that: the next level's chunks while they fit, not all of them.
    let (n, _) = c.prefetch(2 * top);
    let held = cache.weighted_bytes();
    assert!(n > 1 && n < all, "{n} of {all}");
    assert!(
        held <= 2 * top + held / n as u64 + top,
        "{held} over {}",
        2 * top
    );
    // A corrupt chunk: the others are cached, and it is not, nor its views (its bytes).
    let views = c.table.views.len();
    assert_eq!(views, 2);
    let last = c.table.levels[0].chunks.last().unwrap().clone();
    let mut bytes = enc.bytes.clone();
    bytes[(last.offset + last.length / 2) as usize] ^= 0x40;
    let path = file_of(&Encoded { bytes, ..enc }, "prefetch-corrupt.fra");
    let cache = ChunkCache::new(256 << 20);
    let asset = Asset::open(&path, &limits, cache.clone()).unwrap();
    let (n, _) = asset.chunked().unwrap().prefetch(cache.capacity());
    assert_eq!(n, all - 1 - views);
}

/// A table is checked against its layout before anything is decoded: a view level
/// whose cells are not its source chunks', a map missing, more view levels than the file may
/// have, or views without the overlap that puts chunks on their lattice, are each refused by
/// name (a reader would otherwise place or decode a view from the wrong chunk).
#[test]
fn a_table_whose_views_do_not_match_the_layout_is_refused() {
    use fractile_codec::chunked::{ChunkTable, header};
    let r = Raster::open(&testdata("jacksboro.tif")).unwrap();
    let one = |part: &Raster| encode_default(part, 0.8, &|_, _| {});
    let bytes = encode_chunked(&r, 128, &one, &|_, _| {}).unwrap().bytes;
    let asset = Asset::from_bytes(&bytes).unwrap();
    let table = asset.chunked().unwrap().table.clone();
    assert_eq!((table.views.len(), table.levels.len()), (2, 4));
    // The same file with its header written again from a changed table (header() sets the
    // offsets, a view level's to level 0's, as an encoder does).
    let with = |change: &dyn Fn(&mut ChunkTable)| {
        let mut t = table.clone();
        change(&mut t);
        let mut t2 = table.clone();
        let old_len = header(&asset.meta, &mut t2).len();
        let mut out = header(&asset.meta, &mut t);
        out.extend_from_slice(&bytes[old_len..]);
        Asset::from_bytes(&out)
            .map(|_| ())
            .map_err(|e| e.to_string())
    };
    assert_eq!(with(&|_| {}), Ok(()), "the file as written");
    let err = with(&|t| t.levels[1].chunks[4].cells[0] += 1).unwrap_err();
    assert!(
        err.contains("chunk 4 of level 1 claims other cells"),
        "{err}"
    );
    let err = with(&|t| {
        t.views[0].maps.pop();
    })
    .unwrap_err();
    assert!(err.contains("not a map a chunk"), "{err}");
    let err = with(&|t| t.views.push(t.views[0].clone())).unwrap_err();
    assert!(err.contains("3 view levels of 4 levels"), "{err}");
    let err = with(&|t| t.overlap = 1).unwrap_err();
    assert!(err.contains("overlap of 1"), "{err}");
}

/// A file with views assembled again from its chunks' files is the same bytes: a view level's
/// files are level 0's, not written twice (they were, and the file was refused on upload).
#[test]
fn a_file_with_views_assembles_to_its_own_bytes() {
    let r = Raster::open(&testdata("etopo20.tif")).unwrap();
    let enc = chunked(&r);
    let asset = Asset::from_bytes(&enc.bytes).unwrap();
    let c = asset.chunked().unwrap();
    assert_eq!(c.table.views.len(), 2);
    let files: Vec<Vec<Vec<u8>>> = fractile_codec::chunked::chunk_files(&c.table, &enc.bytes);
    let again = fractile_codec::chunked::assemble(&asset.meta, c.table.clone(), &files);
    assert!(
        again == enc.bytes,
        "{} bytes against {}",
        again.len(),
        enc.bytes.len()
    );
}
