//! A chunked file's rate is the file's (issue 52): the whole file, overviews and table
//! included, is within `--target-bpp`; one step for every chunk codes it better than a rate a
//! chunk; the bounded default has one bound, held by every cell of every chunk.

use std::path::Path;

use fractile_codec::encode::chunked::{chunk_bpp, encode_chunked, encode_chunked_at, quality_for};
use fractile_codec::encode::rate::encode_at;
use fractile_codec::encode::rate::{AIM, FileRate, Quality};
use fractile_codec::rows::InMemory;
use fractile_codec::{Encoded, Raster};

fn testdata(name: &str) -> Raster {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata")
        .join(name);
    Raster::open(&p).unwrap()
}

fn at_rate(r: &Raster, chunk: u32, rate: FileRate) -> Encoded {
    let at = |part: &Raster, q, trial| encode_at(part, q, trial);
    encode_chunked_at(r, chunk, (rate, &at), &|_, _| {}).unwrap()
}

fn budget(r: &Raster, bpp: f64) -> usize {
    (bpp * (r.width * r.height) as f64 / 8.0).floor() as usize
}

/// Rate mode on etopo20 in chunks of 256 (8 chunks of the source, 3 of overviews): every file
/// within its rate, and better than each chunk coded at the rate (the ceiling kept the same
/// way, [`chunk_bpp`]) by the one step's spending of bits where they lower the error most.
#[test]
fn the_files_rate_is_a_ceiling_and_one_step_beats_a_rate_a_chunk() {
    let r = testdata("etopo20.tif");
    for bpp in [0.4, 1.6] {
        let ours = at_rate(
            &r,
            256,
            FileRate {
                bpp,
                bounded: false,
            },
        );
        assert!(
            ours.bytes.len() <= budget(&r, bpp),
            "{} bytes over {}",
            ours.bytes.len(),
            budget(&r, bpp)
        );
        assert!(ours.bytes.len() as f64 > 0.9 * budget(&r, bpp) as f64);
        let per_chunk = chunk_bpp(r.width, r.height, 256, bpp);
        let settings = fractile_codec::codecs::projected::ProjectedSettings {
            target_bpp: Some(per_chunk),
            ..Default::default()
        };
        let one = |part: &Raster| fractile_codec::encode(part, &settings, &|_, _| {});
        let theirs = encode_chunked(&r, 256, &one, &|_, _| {}).unwrap();
        assert!(theirs.bytes.len() <= budget(&r, bpp));
        assert!(
            ours.errors.psnr > theirs.errors.psnr + 0.1,
            "{bpp} bpp: one step {:.2} dB, a rate a chunk {:.2} dB",
            ours.errors.psnr,
            theirs.errors.psnr
        );
    }
}

/// The bounded default: within its rate, and every valid cell of every chunk within the one
/// bound the search found, on a DEM with nodata around a rotated source.
#[test]
fn a_bounded_file_has_one_bound_held_everywhere() {
    for (name, chunk) in [("etopo20.tif", 256), ("jacksboro-utm.tif", 64)] {
        let r = testdata(name);
        let rate = FileRate {
            bpp: 3.0,
            bounded: true,
        };
        let enc = at_rate(&r, chunk, rate);
        assert!(enc.bytes.len() <= budget(&r, 3.0), "{name}");
        let at = |part: &Raster, q, trial| encode_at(part, q, trial);
        let (q, _) = quality_for(&mut InMemory::new(&r), chunk, (rate, &at), AIM).unwrap();
        let Quality::Bound(e) = q else {
            panic!("{q:?}")
        };
        assert!(e >= 1.0, "{name}: {e}");
        // The file's bound, as its source level's chunks name it: the sample's, or coarser
        // when the whole file came out over the rate and was coded again.
        let line = &enc.asset.meta.encoder;
        let file_bound: f64 = line
            .split_whitespace()
            .find_map(|w| w.strip_prefix("max_error="))
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("{line}"));
        assert!(
            file_bound >= e && file_bound <= 2.0 * e,
            "{name}: {file_bound} {e}"
        );
        assert!(
            enc.errors.max_error <= file_bound + 1e-3,
            "{name}: {} over the bound {file_bound}",
            enc.errors.max_error
        );
        // The bound is the finest that fits: most chunks reach it, so the worst cell does.
        assert!(enc.errors.max_error >= 0.5 * e, "{name}");
    }
}

/// Rate mode (lifted chunks, format 8): the first two overviews are views of the source chunks,
/// the coarse bands of their own multiresolution, with no bytes of their own, and a coded
/// level lies above them; coarse pixels are
/// answered from it within its measured maps, and it stands for the box means as well as a
/// coded overview at twice the step would (its RMSE against them within twice the source
/// level's against the source).
#[test]
fn a_rate_files_first_overviews_are_views_of_its_source_chunks() {
    use fractile_codec::geo::{Pixels, Sites};
    let r = testdata("etopo20.tif");
    let enc = at_rate(
        &r,
        256,
        FileRate {
            bpp: 0.8,
            bounded: false,
        },
    );
    let chunks = enc.asset.chunked().expect("chunked");
    let t = &chunks.table;
    assert_eq!((t.levels.len(), t.views.len()), (4, 2));
    assert!(t.is_view(1) && t.is_view(2) && !t.is_view(3));
    for l in [1, 2] {
        for (v, s) in t.levels[l].chunks.iter().zip(&t.levels[0].chunks) {
            assert_eq!((v.offset, v.length), (s.offset, s.length));
        }
    }
    // The file is its header, level 0's chunks and level 3's: nothing of levels 1 and 2.
    let coded: u64 = [0, 3]
        .iter()
        .flat_map(|&l| &t.levels[l].chunks)
        .map(|e| e.length)
        .sum();
    let first = t.levels[0].chunks.iter().map(|e| e.offset).min().unwrap();
    assert_eq!(first + coded, enc.bytes.len() as u64);
    let (w, h) = (r.width, r.height);
    // Level-1 pixels over the first source chunk's cells (a view never answers pixels that
    // span half the raster on both axes).
    let (pw, ph) = (128, 128);
    let centres = |n: usize, of: usize| {
        (0..n)
            .map(|i| Some((2 * i + 1) as f32 / of as f32))
            .collect()
    };
    let pixels = Pixels {
        sites: Sites::Grid {
            xs: centres(pw, w),
            ys: centres(ph, h),
        },
        footprint: [2.0 / w as f32, 2.0 / h as f32],
    };
    let (values, bound) = enc.asset.sample(&pixels, 40, 0.0);
    let mut sq = 0.0f64;
    for j in 0..ph {
        for i in 0..pw {
            let mean = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .iter()
                .map(|(dx, dy)| f64::from(r.channels[0][(2 * j + dy) * w + 2 * i + dx]))
                .sum::<f64>()
                / 4.0;
            let e = f64::from(values[0][j * pw + i]) - mean;
            sq += e * e;
        }
    }
    let rmse = (sq / (pw * ph) as f64).sqrt();
    assert!(bound.is_finite());
    // A low-pass is no box mean (see `encode::chunked::view_maps`), but close to one: 161 m
    // RMS where the source level is 76 m from the source (measured); placed a quarter cell
    // off (on its box cell's centre), 189 m; scaled by the kernel's gain, kilometres.
    assert!(
        rmse <= 2.3 * enc.errors.rmse,
        "the view is {rmse} from the box means, the source level {} from the source",
        enc.errors.rmse
    );
}
