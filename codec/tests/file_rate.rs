//! A chunked file's rate is the file's (issue 52): the whole file, overviews and table
//! included, is within `--target-bpp`; one step for every chunk codes it better than a rate a
//! chunk; the bounded default has one bound, held by every cell of every chunk.

use std::path::Path;

use fractile_codec::encode::chunked::{chunk_bpp, encode_chunked, encode_chunked_at, quality_for};
use fractile_codec::encode::projected::{encode_at, encode_projected};
use fractile_codec::encode::rate::{AIM, FileRate, Quality};
use fractile_codec::io::rows::InMemory;
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
        let settings = Default::default();
        let one = |part: &Raster| encode_projected(part, &settings, Some(per_chunk));
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
