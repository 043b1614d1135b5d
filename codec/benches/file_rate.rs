//! Issue 52's bars on a chunked DEM: the file's rate against OpenJPEG at the same bytes, the
//! bounded default against JPEG-LS near-lossless at the same max error, and encode times,
//! side by side in one run (release build):
//!
//! `cargo bench -p fractile-codec --bench file_rate -- rates|bounded|bounds|sizes|views [COPIES] [old] [FILE.tif]`
//! (FILE.tif absolute, or from the `codec` folder, where the bench runs)
//!
//! The raster: etopo20 (or FILE.tif) mirrored COPIES x COPIES (odd columns of copies flipped,
//! odd rows upside down; etopo20 x 4 gives 4320 x 2160, over 4096 cells a side, 9.3 Mpx,
//! chunked by default; jacksboro x 12, 4128 x 4356); COPIES 1: the file alone. `rates`: `--codec projected
//! --target-bpp B` at 10:1, 20:1, 40:1 and 80:1 of the int16 bytes (1.6 to 0.2 bpp), and
//! OpenJPEG's `opj_compress -I` at the file's bytes. `bounded`: the default encode (bounded,
//! 0.8 bpp), and JPEG-LS with NEAR at its max error (imagecodecs, through python3). `old`:
//! also the chunked encode before the file's rate (each chunk at the rate, with its own
//! search), as the baseline. The last column of `rates` is level 0 alone against OpenJPEG at
//! level 0's bytes: the gap if the overviews cost nothing (issue 52's one multiresolution).
//! `views`: in rate mode, the share of its source chunk's stream a view of depth 1 and 2
//! decodes (format 7), what a layout with coarse bands apart would save it. `bounds` (issue
//! 73): `--max-error E` at E = 1, 10, 50, 150 in the default chunks and in one piece
//! (`--chunk 0`), their ratio of bytes, SZ3, SPERR and JPEG-LS at the same E on the same cells
//! (python3's imagecodecs), and the largest |decoded - source| of every output as delivered
//! (float32, compared in float64). `sizes` (issue 73): the rate of a chunked file is
//! independent of the raster's size: the raster mirrored 2 x 2 (etopo20: 2160 x 1080, 2.3 Mpx,
//! the tile) and 8 x 8 (8640 x 4320, 37 Mpx, its mosaic), the default encodes of both at 0.6,
//! 0.8 and 1.0 bits a cell, bounded and in rate mode, and the mosaic's PSNR less the tile's at
//! the mosaic's bits a cell (the tile's curve interpolated linearly in bits).

#[path = "support/baselines.rs"]
#[allow(dead_code)]
mod baselines;

#[path = "support/memory.rs"]
mod memory;

#[path = "support/peers.rs"]
mod peers;
use memory::peak_mb;

use std::time::Instant;

use fractile_codec::encode::chunked::{DEFAULT_CHUNK, encode_chunked, encode_chunked_at};
use fractile_codec::encode::rate::FileRate;
use fractile_codec::{Encoded, Raster};

fn raster(copies: usize, file: Option<&str>) -> Raster {
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata");
    let src = match file {
        Some(f) => Raster::open(std::path::Path::new(f)).expect("a DEM"),
        None => Raster::open(&root.join("etopo20.tif")).expect("etopo20"),
    };
    if copies <= 1 {
        return src;
    }
    fractile_codec::mosaic::mirrored(&src, copies, copies).unwrap()
}

/// The file's rate (new) or a rate a chunk (old), rate mode or bounded.
fn encode(r: &Raster, bpp: f64, bounded: bool, old: bool) -> (Encoded, f64) {
    let t = Instant::now();
    let enc = if old {
        let settings = fractile_codec::codecs::projected::ProjectedSettings {
            bounded,
            ..Default::default()
        };
        let one = |part: &Raster| {
            fractile_codec::encode(
                part,
                &fractile_codec::codecs::projected::ProjectedSettings {
                    target_bpp: Some(bpp),
                    ..settings.clone()
                },
                &|_, _| {},
            )
        };
        encode_chunked(r, DEFAULT_CHUNK, &one, &|_, _| {})
    } else {
        let at = |part: &Raster, q, trial| fractile_codec::encode::rate::encode_at(part, q, trial);
        encode_chunked_at(
            r,
            DEFAULT_CHUNK,
            (FileRate { bpp, bounded }, &at),
            &|_, _| {},
        )
    };
    (enc.expect("encode"), t.elapsed().as_secs_f64())
}

/// The overviews' share of a chunked file's bytes.
fn overview_share(enc: &Encoded) -> f64 {
    let Some(c) = enc.asset.chunked() else {
        return 0.0;
    };
    let level = |l: &fractile_codec::chunked::Level| l.chunks.iter().map(|e| e.length).sum::<u64>();
    // A view level's entries are level 0's bytes (format 7): counted once.
    let coded = |&(i, _): &(usize, &fractile_codec::chunked::Level)| !c.table.is_view(i);
    let levels = || c.table.levels.iter().enumerate().filter(coded);
    let all: u64 = levels().map(|(_, l)| level(l)).sum();
    let overviews: u64 = levels().skip(1).map(|(_, l)| level(l)).sum();
    overviews as f64 / all.max(1) as f64
}

/// OpenJPEG's `opj_compress -I` time on `r` at `bpp` (one run, the PNG it reads written first,
/// not timed); NaN without the tool.
fn opj_seconds(r: &Raster, bpp: f64) -> f64 {
    let dir = std::env::temp_dir().join(format!("fractile-opj-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let (png, j2k) = (dir.join("in.png"), dir.join("out.j2k"));
    let (lo, _) = r.value_range();
    let px: Vec<u16> = r.channels[0]
        .iter()
        .map(|&v| (f64::from(v) - lo).round() as u16)
        .collect();
    let img =
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(r.width as u32, r.height as u32, px)
            .expect("a grid");
    img.save(&png).expect("png");
    let t = Instant::now();
    let ok = std::process::Command::new("opj_compress")
        .args(["-I", "-r", &format!("{:.4}", 16.0 / bpp), "-i"])
        .arg(&png)
        .arg("-o")
        .arg(&j2k)
        .output()
        .is_ok_and(|o| o.status.success());
    let secs = t.elapsed().as_secs_f64();
    let _ = std::fs::remove_dir_all(&dir);
    if ok { secs } else { f64::NAN }
}

/// JPEG-LS near-lossless at NEAR = `e` (whole units): its compression ratio against the int16
/// bytes, through python3's imagecodecs.
fn jpegls_ratio(r: &Raster, e: f64) -> Option<f64> {
    let dir = std::env::temp_dir().join(format!("fractile-jls-{}", std::process::id()));
    std::fs::create_dir_all(&dir).ok()?;
    let raw = dir.join("in.raw");
    let (lo, _) = r.value_range();
    let bytes: Vec<u8> = r.channels[0]
        .iter()
        .flat_map(|&v| ((f64::from(v) - lo).round() as u16).to_le_bytes())
        .collect();
    std::fs::write(&raw, &bytes).ok()?;
    let script = format!(
        "import numpy, imagecodecs\na = numpy.fromfile('{}', dtype='<u2').reshape({}, {})\nprint(len(imagecodecs.jpegls_encode(a, level={})))",
        raw.display(),
        r.height,
        r.width,
        e.floor() as i64
    );
    let out = std::process::Command::new("python3")
        .args(["-c", &script])
        .output()
        .ok()?;
    let _ = std::fs::remove_dir_all(&dir);
    let n: f64 = String::from_utf8_lossy(&out.stdout).trim().parse().ok()?;
    Some((r.width * r.height * 2) as f64 / n)
}

/// The `views` table: what share of its source chunk's stream a view of depth 1 and 2 reads
/// (the coarse bands come first), in rate mode at each ratio: what a view would fetch if each
/// chunk's coarse part lay apart (resolution-major), against the whole chunk it fetches now.
fn views(r: &Raster) {
    use fractile_codec::asset::Coding;
    use fractile_codec::codecs::projected::decode_coarse;
    println!(
        "\n| ratio | file bytes | source chunks' streams | a depth-1 view reads | a depth-2 view reads |"
    );
    println!("|---|---|---|---|---|");
    for ratio in [10.0, 20.0, 40.0, 80.0] {
        let (enc, _) = encode(r, 16.0 / ratio, false, false);
        let c = enc.asset.chunked().expect("chunked");
        let (mut all, mut read) = (0usize, [0usize; 2]);
        for i in 0..c.table.levels[0].chunks.len() {
            let Some(chunk) = c.chunk(0, i).expect("a chunk") else {
                continue;
            };
            let Coding::Projected { header, stream } = &chunk.planes()[0].coding else {
                panic!("not projected");
            };
            all += stream.len();
            for (d, n) in read.iter_mut().enumerate() {
                *n += decode_coarse(header, stream, d as u32 + 1)
                    .expect("a view")
                    .2;
            }
        }
        println!(
            "| {ratio}:1 | {} | {all} | {:.1}% | {:.1}% |",
            enc.bytes.len(),
            100.0 * read[0] as f64 / all as f64,
            100.0 * read[1] as f64 / all as f64
        );
    }
}

/// The largest |delivered - source| of `enc` decoded whole at the source's size, as a user
/// receives it (float32, compared in float64), over the valid cells.
fn delivered_error(enc: &Encoded, r: &Raster) -> f64 {
    let (decoded, _) = enc.asset.decode_native();
    decoded.channels[0]
        .iter()
        .zip(&r.channels[0])
        .enumerate()
        .filter(|(i, _)| r.valid.as_ref().is_none_or(|v| v[*i]))
        .map(|(_, (&d, &s))| (f64::from(d) - f64::from(s)).abs())
        .fold(0.0, f64::max)
}

/// The `bounds` table (issue 73): max-error files in chunks and whole, against SZ3, SPERR and
/// JPEG-LS at the same bound.
fn bounds(r: &Raster) {
    use fractile_codec::codecs::projected::ProjectedSettings;
    use fractile_codec::encode::rate::Quality;
    println!(
        "\n| E | chunked | --chunk 0 | chunked / whole bytes | SZ3 | SPERR | JPEG-LS | chunked / best peer | max error delivered: chunked, whole, peers | encode s: chunked, whole |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut versions = String::new();
    for e in [1.0, 10.0, 50.0, 150.0] {
        let at = |part: &Raster, q, trial| fractile_codec::encode::rate::encode_at(part, q, trial);
        let t = Instant::now();
        let chunked = encode_chunked_at(r, DEFAULT_CHUNK, (Quality::Bound(e), &at), &|_, _| {})
            .expect("chunked encode");
        let chunked_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let settings = ProjectedSettings {
            max_error: Some(e),
            ..Default::default()
        };
        let whole = fractile_codec::encode(r, &settings, &|_, _| {}).expect("whole encode");
        let whole_s = t.elapsed().as_secs_f64();
        let (peers, v) = peers::at_bound(r, e).unwrap_or_else(|| ([None, None, None], "-".into()));
        versions = v;
        let cell =
            |p: &Option<peers::Peer>| p.as_ref().map_or("-".into(), |p| format!("{:.2}", p.ratio));
        let best = peers.iter().flatten().map(|p| p.ratio).fold(0.0, f64::max);
        let peer_errors: Vec<String> = peers
            .iter()
            .map(|p| {
                p.as_ref()
                    .map_or("-".into(), |p| format!("{:.3}", p.max_error))
            })
            .collect();
        println!(
            "| {e} | {:.2} | {:.2} | {:.3} | {} | {} | {} | {:.3} | {:.4}, {:.4}, {} | {chunked_s:.1}, {whole_s:.1} |",
            chunked.ratio(),
            whole.ratio(),
            chunked.bytes.len() as f64 / whole.bytes.len() as f64,
            cell(&peers[0]),
            cell(&peers[1]),
            cell(&peers[2]),
            chunked.ratio() / best,
            delivered_error(&chunked, r),
            delivered_error(&whole, r),
            peer_errors.join(", "),
        );
    }
    println!("\nPeers: {versions}");
}

/// The `sizes` table (issue 73): a tile and its 16-fold mosaic, each a default chunked encode
/// at the same rates, bounded and in rate mode.
fn sizes(file: Option<&str>) {
    let (tile, mosaic) = (raster(2, file), raster(8, file));
    println!(
        "tile {} x {}, mosaic {} x {}",
        tile.width, tile.height, mosaic.width, mosaic.height
    );
    println!(
        "\n| mode | aim bpp | tile bpp | tile PSNR dB | mosaic bpp | mosaic PSNR dB | mosaic - tile at the mosaic's bpp, dB |"
    );
    println!("|---|---|---|---|---|---|---|");
    for bounded in [true, false] {
        let aims = [0.6, 0.8, 1.0];
        let points = |r: &Raster| -> Vec<(f64, f64)> {
            aims.iter()
                .map(|&bpp| {
                    let (enc, _) = encode(r, bpp, bounded, false);
                    (enc.bpp(), enc.errors.psnr)
                })
                .collect()
        };
        let (t, m) = (points(&tile), points(&mosaic));
        // The tile's PSNR at `b` bits a cell, linear between its two nearest points.
        let at = |b: f64| {
            let k = (1..t.len()).find(|&k| t[k].0 >= b).unwrap_or(t.len() - 1);
            let ((b0, p0), (b1, p1)) = (t[k - 1], t[k]);
            p0 + (p1 - p0) * (b - b0) / (b1 - b0)
        };
        for ((aim, tp), mp) in aims.iter().zip(&t).zip(&m) {
            println!(
                "| {} | {aim} | {:.3} | {:.2} | {:.3} | {:.2} | {:+.2} |",
                if bounded { "bounded" } else { "rate" },
                tp.0,
                tp.1,
                mp.0,
                mp.1,
                mp.1 - at(mp.0)
            );
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let mode = args.first().map_or("rates", String::as_str).to_string();
    let copies: usize = args.get(1).and_then(|c| c.parse().ok()).unwrap_or(4);
    let old = args.iter().any(|a| a == "old");
    let file = args
        .iter()
        .find(|a| a.ends_with(".tif"))
        .map(String::as_str);
    if mode == "sizes" {
        sizes(file);
        return;
    }
    let r = raster(copies, file);
    let cells = (r.width * r.height) as f64;
    println!(
        "{} x {} ({:.1} Mpx), chunks of {DEFAULT_CHUNK}, {} threads",
        r.width,
        r.height,
        cells / 1e6,
        rayon::current_num_threads()
    );
    if mode == "views" {
        views(&r);
        return;
    }
    if mode == "bounds" {
        bounds(&r);
        return;
    }

    if mode == "bounded" {
        println!(
            "\n| encode | bytes (bpp) | within 0.8 | max error | PSNR dB | ratio | JPEG-LS ratio at that max error | encode s | peak RSS MB |"
        );
        println!("|---|---|---|---|---|---|---|---|---|");
        for old in [false, true].into_iter().filter(|o| !o || old) {
            let (enc, secs) = encode(&r, 0.8, true, old);
            let jls = jpegls_ratio(&r, enc.errors.max_error.ceil());
            println!(
                "| {} | {} ({:.3}) | {} | {:.0} | {:.2} | {:.2}:1 | {} | {:.1} | {:.0} |",
                if old {
                    "a rate a chunk"
                } else {
                    "the file's rate"
                },
                enc.bytes.len(),
                enc.bpp(),
                enc.bpp() <= 0.8,
                enc.errors.max_error,
                enc.errors.psnr,
                enc.ratio(),
                jls.map_or("-".into(), |j| format!("{j:.2}:1")),
                secs,
                peak_mb()
            );
        }
        return;
    }
    println!(
        "\n| ratio | encode | bytes (bpp) | within | PSNR dB | max error | encode s | OpenJPEG PSNR at those bytes | - OpenJPEG | opj s | overviews' bytes | level 0 alone - OpenJPEG at its bytes |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for ratio in [10.0, 20.0, 40.0, 80.0] {
        let bpp = 16.0 / ratio;
        for old in [false, true].into_iter().filter(|o| !o || old) {
            let (enc, secs) = encode(&r, bpp, false, old);
            let got = enc.bpp();
            let j2k = baselines::jpeg2000_at(&r, got);
            let opj = opj_seconds(&r, got);
            // What the overviews cost: level 0's PSNR (the overviews change none of its
            // cells) against OpenJPEG at level 0's bytes alone, as if coarse zooms were free.
            let share = overview_share(&enc);
            let alone = baselines::jpeg2000_at(&r, got * (1.0 - share));
            println!(
                "| {ratio}:1 | {} | {} ({got:.3}) | {} | {:.2} | {:.0} | {secs:.1} | {} | {} | {opj:.1} | {:.1}% | {} |",
                if old {
                    "a rate a chunk"
                } else {
                    "the file's rate"
                },
                enc.bytes.len(),
                got <= bpp,
                enc.errors.psnr,
                enc.errors.max_error,
                j2k.map_or("-".into(), |(b, p)| format!("{p:.2} at {b:.3}")),
                j2k.map_or("-".into(), |(_, p)| format!("{:+.2}", enc.errors.psnr - p)),
                100.0 * share,
                alone.map_or("-".into(), |(_, p)| format!("{:+.2}", enc.errors.psnr - p)),
            );
        }
    }
    println!("\npeak RSS {:.0} MB", peak_mb());
}
