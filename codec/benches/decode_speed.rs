//! Issue 75's bars on a chunked DEM: a whole-raster decode against OpenJPEG's at the same
//! bytes, one core each, and the bounded default's encode against `opj_compress`, side by side
//! in one run (release build):
//!
//! `cargo bench -p fractile-codec --bench decode_speed -- [COPIES] [FILE.tif]`
//! (FILE.tif absolute, or from the `codec` folder, where the bench runs);
//! `-- ASSET.fra`: only the whole reads of that file, best of 7 on one thread (for profiling).
//!
//! The raster: etopo20 (or FILE.tif) mirrored COPIES x COPIES (default 4: 4320 x 2160, 9.3 Mpx,
//! chunked by default). Encoded twice: the bounded default (0.8 bpp, the pyramid) and rate mode
//! at 0.8 bpp (lifted), each written to a file, then read back whole as `fractile decode` and
//! Python's `Asset.read` read it (`Asset::open` with a fresh chunk cache, `Asset::raster`), best
//! of 3, on a pool of one thread and on every core. OpenJPEG: the raster as a 16-bit PNG,
//! `opj_compress -r` at our file's bytes (the JPEG 2000 file's size printed beside), then
//! `opj_decompress -threads 1` to a raw file, best of 3 process wall times (its own "decode
//! time" printed too). The ratios: ours on one thread over OpenJPEG's process on one, and over
//! its own decode time (without reading and writing its files: the stricter).

#[path = "support/memory.rs"]
mod memory;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use fractile_codec::chunked::ChunkCache;
use fractile_codec::encode::chunked::{DEFAULT_CHUNK, encode_chunked_at};
use fractile_codec::encode::rate::FileRate;
use fractile_codec::{Asset, AssetLimits, Encoded, Method, Raster};

fn raster(copies: usize, file: Option<&str>) -> Raster {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata");
    let src = match file {
        Some(f) => Raster::open(Path::new(f)).expect("a DEM"),
        None => Raster::open(&root.join("etopo20.tif")).expect("etopo20"),
    };
    if copies <= 1 {
        return src;
    }
    fractile_codec::mosaic::mirrored(&src, copies, copies).expect("a mirrored raster")
}

fn encode(r: &Raster, bounded: bool) -> (Encoded, f64) {
    let t = Instant::now();
    let at = |part: &Raster, q, trial| fractile_codec::encode::rate::encode_at(part, q, trial);
    let file = FileRate { bpp: 0.8, bounded };
    let enc = encode_chunked_at(r, DEFAULT_CHUNK, (file, &at), &|_, _| {}).expect("encode");
    (enc, t.elapsed().as_secs_f64())
}

/// The best of 3 whole reads of the file at `path` (seconds), on `pool`; and the PSNR of the
/// last against the source.
fn read_seconds(path: &Path, r: &Raster, pool: &rayon::ThreadPool) -> (f64, f64) {
    let mut best = f64::INFINITY;
    let mut psnr = f64::NAN;
    for _ in 0..3 {
        let t = Instant::now();
        let decoded = pool.install(|| {
            let a =
                Asset::open(path, &AssetLimits::default(), ChunkCache::new(1 << 30)).expect("open");
            a.raster(None, r.width, r.height, None, Method::Auto)
                .expect("read")
                .0
        });
        best = best.min(t.elapsed().as_secs_f64());
        let (lo, hi) = r.value_range();
        let peak = hi - lo;
        let mut se = 0.0;
        for (d, s) in decoded.channels[0].iter().zip(&r.channels[0]) {
            se += (f64::from(*d) - f64::from(*s)).powi(2);
        }
        let mse = se / r.channels[0].len() as f64;
        psnr = 10.0 * (peak * peak / mse).log10();
    }
    (best, psnr)
}

/// OpenJPEG's figures at our file's bytes.
struct OpenJpeg {
    /// `opj_compress` seconds.
    compress: f64,
    /// The JPEG 2000 file's bytes.
    bytes: u64,
    /// The best of 3 `opj_decompress -threads 1` process seconds.
    decompress: f64,
    /// Its own decode time, ms.
    decode_ms: f64,
}

/// OpenJPEG at `bytes` (`None` without the tools).
fn openjpeg(r: &Raster, bytes: usize, dir: &Path) -> Option<OpenJpeg> {
    let (png, j2k, raw) = (dir.join("in.png"), dir.join("out.j2k"), dir.join("out.raw"));
    let (lo, _) = r.value_range();
    let px: Vec<u16> = r.channels[0]
        .iter()
        .map(|&v| (f64::from(v) - lo).round() as u16)
        .collect();
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(r.width as u32, r.height as u32, px)?
        .save(&png)
        .ok()?;
    let ratio = (r.width * r.height * 2) as f64 / bytes as f64;
    let t = Instant::now();
    let made = Command::new("opj_compress")
        .args(["-r", &format!("{ratio:.4}"), "-i"])
        .arg(&png)
        .arg("-o")
        .arg(&j2k)
        .output()
        .ok()?;
    let compress = t.elapsed().as_secs_f64();
    if !made.status.success() {
        return None;
    }
    let (mut best, mut own) = (f64::INFINITY, f64::NAN);
    for _ in 0..3 {
        let t = Instant::now();
        let out = Command::new("opj_decompress")
            .args(["-threads", "1", "-i"])
            .arg(&j2k)
            .arg("-o")
            .arg(&raw)
            .output()
            .ok()?;
        best = best.min(t.elapsed().as_secs_f64());
        own = String::from_utf8_lossy(&out.stdout)
            .lines()
            .find_map(|l| l.strip_prefix("decode time: "))
            .and_then(|v| v.trim_end_matches(" ms").trim().parse().ok())
            .unwrap_or(f64::NAN);
    }
    Some(OpenJpeg {
        compress,
        bytes: std::fs::metadata(&j2k).ok()?.len(),
        decompress: best,
        decode_ms: own,
    })
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a pool");
    if let Some(asset) = args.iter().find(|a| a.ends_with(".fra")) {
        let path = Path::new(asset);
        let a = Asset::read(path).expect("an asset");
        let (w, h) = (a.meta.width as usize, a.meta.height as usize);
        let best = (0..7)
            .map(|_| {
                let t = Instant::now();
                one.install(|| {
                    let a = Asset::open(path, &AssetLimits::default(), ChunkCache::new(1 << 30))
                        .expect("open");
                    a.raster(None, w, h, None, Method::Auto).expect("read");
                });
                t.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min);
        println!("{asset}: {w} x {h}, whole read on one thread, best of 7: {best:.3} s");
        return;
    }
    let copies: usize = args.iter().find_map(|a| a.parse().ok()).unwrap_or(4);
    let file = args
        .iter()
        .find(|a| a.ends_with(".tif"))
        .map(String::as_str);
    let r = raster(copies, file);
    let cores = rayon::current_num_threads();
    println!(
        "{} x {} ({:.1} Mpx), chunks of {DEFAULT_CHUNK}, {cores} cores",
        r.width,
        r.height,
        (r.width * r.height) as f64 / 1e6
    );
    let dir = std::env::temp_dir().join(format!("fractile-decode-speed-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("a temporary folder");
    let all = rayon::ThreadPoolBuilder::new()
        .num_threads(cores)
        .build()
        .expect("a pool");
    println!(
        "\n| mode | bytes (bpp) | PSNR dB | read s, 1 thread | read s, {cores} threads | JPEG 2000 bytes | opj_decompress s (its decode ms) | 1 thread / opj process | 1 thread / opj decode | encode s | opj_compress s | encode / opj_compress |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for bounded in [true, false] {
        let (enc, encode_s) = encode(&r, bounded);
        let path = dir.join("asset.fra");
        std::fs::write(&path, &enc.bytes).expect("write");
        let (single, psnr) = read_seconds(&path, &r, &one);
        let (many, _) = read_seconds(&path, &r, &all);
        let opj = openjpeg(&r, enc.bytes.len(), &dir);
        let cell = |f: &dyn Fn(&OpenJpeg) -> String| opj.as_ref().map_or("-".into(), f);
        println!(
            "| {} | {} ({:.3}) | {psnr:.2} | {single:.3} | {many:.3} | {} | {} | {} | {} | {encode_s:.1} | {} | {} |",
            if bounded {
                "bounded default"
            } else {
                "rate 0.8 bpp"
            },
            enc.bytes.len(),
            enc.bpp(),
            cell(&|o| o.bytes.to_string()),
            cell(&|o| format!("{:.3} ({:.0})", o.decompress, o.decode_ms)),
            cell(&|o| format!("{:.2}x", single / o.decompress)),
            cell(&|o| format!("{:.2}x", single * 1e3 / o.decode_ms)),
            cell(&|o| format!("{:.2}", o.compress)),
            cell(&|o| format!("{:.1}x", encode_s / o.compress)),
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    println!("\npeak RSS {:.0} MB", memory::peak_mb());
}
