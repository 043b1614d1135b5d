//! Bytes and encode time of terrain-RGB tiles by precision and container (PNG at each deflate
//! effort, lossless WebP), on the default
//! DEM encode (0.8 bits a cell) of a real DEM, over a walk of zooms 10 to 16 (eight tiles a
//! zoom along the asset's diagonal). Prints a table.
//!
//! `cargo bench -p fractile --bench tile_png [-- DEM.tif|ASSET.fra ...]` (default:
//! testdata/jacksboro.tif; an asset file is benched as it is, whatever its codec and rate).
//! `FRACTILE_BENCH_ZOOMS=0-3` walks other zooms (zooms inside a coarse DEM's source, whose
//! tiles carry more detail than deep zooms' do).

use std::sync::Arc;
use std::time::Instant;

use axum::body::Body;
use axum::http::Request;
use fractile_codec::{Raster, encode_default};
use fractile_server::AppState;
use fractile_server::Store;
use fractile_server::encoding::{
    Container, Deflate, HeightEncoding, Rounding, TileFormat, encode_tile, relief,
};
use http_body_util::BodyExt;
use tower::ServiceExt;

/// A decoded tile: heights and the bound the server gives them at full precision.
struct Decoded {
    zoom: u8,
    heights: Vec<f32>,
    error_bound: f32,
}

async fn f32_tile(state: &Arc<AppState>, z: u8, x: u32, y: u32) -> Option<Decoded> {
    let uri = format!("/v1/assets/dem/tiles/{z}/{x}/{y}.f32");
    let req = Request::get(&uri).body(Body::empty()).unwrap();
    let resp = fractile_server::app(state.clone())
        .oneshot(req)
        .await
        .unwrap();
    if !resp.status().is_success() {
        return None;
    }
    let error_bound = resp
        .headers()
        .get("x-error-bound")?
        .to_str()
        .ok()?
        .parse()
        .ok()?;
    let body = resp.into_body().collect().await.unwrap().to_bytes();
    let heights = body
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    Some(Decoded {
        zoom: z,
        heights,
        error_bound,
    })
}

/// The asset of `path`: a `.fra` file as it is (any codec, any rate), else the default encode
/// of a DEM.
fn asset_bytes(path: &std::path::Path) -> Vec<u8> {
    if path.extension().is_some_and(|e| e == "fra") {
        return std::fs::read(path).expect("an asset file");
    }
    let src = Raster::open(path).expect("a DEM");
    encode_default(
        &src,
        fractile_codec::encode::DEFAULT_HEIGHT_FIELD_BPP,
        &|_, _| {},
    )
    .expect("an encode")
    .bytes
}

/// The zooms walked: `FRACTILE_BENCH_ZOOMS` (`A-B`), else 10 to 16.
fn zooms() -> std::ops::RangeInclusive<u8> {
    std::env::var("FRACTILE_BENCH_ZOOMS")
        .ok()
        .and_then(|z| {
            let (a, b) = z.split_once('-')?;
            Some(a.parse().ok()?..=b.parse().ok()?)
        })
        .unwrap_or(10..=16)
}

fn bench_dem(path: &std::path::Path) {
    let bytes = asset_bytes(path);
    let dir = std::env::temp_dir().join(format!("fractile-tile-png-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("dem.fra"), &bytes).unwrap();
    let (store, _) = Store::open(&dir).unwrap();
    let state = Arc::new(AppState::new(store, "http://bench".into()));
    let stored = state.store.get("dem").unwrap();
    let place = stored.placement.clone().expect("a georeferenced DEM");
    let [w, s, e, n] = place.bounds();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let mut tiles = Vec::new();
    for z in zooms() {
        for k in 0..8 {
            let t = (k as f64 + 0.5) / 8.0;
            let (x, y) = fractile_codec::geo::lonlat_tile(z, w + t * (e - w), n - t * (n - s));
            if let Some(d) = rt.block_on(f32_tile(&state, z, x, y)) {
                tiles.push(d);
            }
        }
    }
    let name = path.file_name().unwrap().to_string_lossy();
    println!(
        "\n{name}: {} tiles over zooms {:?}, mean X-Error-Bound {:.1} m",
        tiles.len(),
        zooms(),
        tiles.iter().map(|t| t.error_bound as f64).sum::<f64>() / tiles.len() as f64
    );
    println!("| precision | container | mean bytes | vs full, fast | encode ms a tile |");
    println!("|---|---|---|---|---|");
    let format = TileFormat::Heights(HeightEncoding::TerrainRgb);
    let mut baseline = None;
    for bound in [false, true] {
        for deflate in [
            Container::Png(Deflate::Fast),
            Container::Png(Deflate::Level(1)),
            Container::Png(Deflate::Level(3)),
            Container::Png(Deflate::Level(4)),
            Container::Png(Deflate::Level(5)),
            Container::Png(Deflate::Level(6)),
            Container::Png(Deflate::Level(9)),
            Container::WebP,
        ] {
            let (mut bytes, start) = (0usize, Instant::now());
            let reps = 3;
            for _ in 0..reps {
                bytes = 0;
                for t in &tiles {
                    let rounding = if bound {
                        Rounding::for_tile(
                            HeightEncoding::TerrainRgb,
                            t.error_bound,
                            relief(&t.heights, 256),
                            stored.asset.meta.stats.rmse as f32,
                        )
                    } else {
                        Rounding::default()
                    };
                    let channels = [t.heights.clone()];
                    let (_, body) = encode_tile(
                        &stored.asset.meta,
                        &channels,
                        256,
                        format,
                        None,
                        (rounding, deflate),
                    );
                    bytes += body.len();
                }
            }
            let ms = start.elapsed().as_secs_f64() * 1e3 / (reps * tiles.len()) as f64;
            let mean = bytes as f64 / tiles.len() as f64;
            let base = *baseline.get_or_insert(mean);
            println!(
                "| {} | {deflate:?} | {mean:.0} | {:.2} | {ms:.2} |",
                if bound { "bound" } else { "full" },
                mean / base
            );
        }
    }
    // Row filters at the server's default (rounded to the bound, zlib 6): the served tiles'
    // pixels encoded again with each filter (packed heights take Up, see `encoding`).
    println!("\n| row filter (rounded, zlib 6) | mean bytes | vs adaptive | encode ms a tile |");
    println!("|---|---|---|---|");
    let pixels: Vec<image::RgbImage> = tiles
        .iter()
        .map(|t| {
            let rounding = Rounding::for_tile(
                HeightEncoding::TerrainRgb,
                t.error_bound,
                relief(&t.heights, 256),
                stored.asset.meta.stats.rmse as f32,
            );
            let (_, body) = encode_tile(
                &stored.asset.meta,
                std::slice::from_ref(&t.heights),
                256,
                format,
                None,
                (rounding, Container::Png(Deflate::for_tile(rounding))),
            );
            image::load_from_memory(&body).expect("a PNG").to_rgb8()
        })
        .collect();
    let mut adaptive = None;
    for (name, rows) in [
        ("adaptive", image::codecs::png::FilterType::Adaptive),
        ("Up", image::codecs::png::FilterType::Up),
        ("Paeth", image::codecs::png::FilterType::Paeth),
    ] {
        use image::ImageEncoder;
        let (mut bytes, start, reps) = (0usize, Instant::now(), 3);
        for _ in 0..reps {
            bytes = 0;
            for p in &pixels {
                let mut out = Vec::new();
                image::codecs::png::PngEncoder::new_with_quality(
                    &mut out,
                    image::codecs::png::CompressionType::Level(6),
                    rows,
                )
                .write_image(p, 256, 256, image::ExtendedColorType::Rgb8)
                .expect("a PNG");
                bytes += out.len();
            }
        }
        let ms = start.elapsed().as_secs_f64() * 1e3 / (reps * pixels.len()) as f64;
        let mean = bytes as f64 / pixels.len() as f64;
        let base = *adaptive.get_or_insert(mean);
        println!("| {name} | {mean:.0} | {:.3} | {ms:.2} |", mean / base);
    }
    // Where the bytes are: by zoom, at the server's default (rounded to the bound, zlib 6).
    println!("\n| zoom | mean X-Error-Bound m | rounding step m | mean bytes |");
    println!("|---|---|---|---|");
    for z in zooms() {
        let at: Vec<&Decoded> = tiles.iter().filter(|t| t.zoom == z).collect();
        if at.is_empty() {
            continue;
        }
        let (mut bytes, mut bound, mut step) = (0usize, 0.0f64, 0.0f64);
        for t in &at {
            let rounding = Rounding::for_tile(
                HeightEncoding::TerrainRgb,
                t.error_bound,
                relief(&t.heights, 256),
                stored.asset.meta.stats.rmse as f32,
            );
            let (_, body) = encode_tile(
                &stored.asset.meta,
                std::slice::from_ref(&t.heights),
                256,
                format,
                None,
                (rounding, Container::Png(Deflate::for_tile(rounding))),
            );
            bytes += body.len();
            bound += f64::from(t.error_bound);
            step += 0.1 * f64::from(1u32 << rounding.shift);
        }
        let n = at.len() as f64;
        println!(
            "| {z} | {:.1} | {:.1} | {:.0} |",
            bound / n,
            step / n,
            bytes as f64 / n
        );
    }
    let cell_degrees = (e - w) / stored.asset.meta.width as f64;
    what_smoother_tiles_cost(&tiles, cell_degrees, &stored.asset.meta);
    std::fs::remove_dir_all(&dir).ok();
}

/// The tile's heights at the lattice of `spacing` pixels (about a source cell): bilinear
/// between the lattice's samples (`blocks` false: every detail finer than the source's cells
/// removed, the smoothest tile the source justifies) or each lattice cell at its first sample
/// (`blocks` true: nearest resampling, what TiTiler serves past the source's resolution).
fn on_lattice(h: &[f32], spacing: usize, blocks: bool) -> Vec<f32> {
    let side = 256;
    let node = |k: usize| (k * spacing).min(side - 1);
    (0..side * side)
        .map(|i| {
            let (x, y) = (i % side, i / side);
            let (cx, cy) = (x / spacing, y / spacing);
            if blocks {
                return h[node(cy) * side + node(cx)];
            }
            let fx = (x - node(cx)) as f32 / (node(cx + 1) - node(cx)).max(1) as f32;
            let fy = (y - node(cy)) as f32 / (node(cy + 1) - node(cy)).max(1) as f32;
            let at = |a: usize, b: usize| h[node(b) * side + node(a)];
            let top = at(cx, cy) * (1.0 - fx) + at(cx + 1, cy) * fx;
            let bottom = at(cx, cy + 1) * (1.0 - fx) + at(cx + 1, cy + 1) * fx;
            top * (1.0 - fy) + bottom * fy
        })
        .collect()
}

/// Issue 77's question: what rounding away the detail past the source's resolution would save.
/// For each zoom, the served tile's bytes against the same tile with every detail finer than
/// the source's cells removed (bilinear between samples a source cell apart, rounded by the
/// same rule; no stairs, since the rule still keeps 256 levels over the relief) and against
/// the source's cells as blocks (nearest resampling: TiTiler's tiles, stairs by construction).
/// PNG at the server's deflate, then image's lossless WebP.
fn what_smoother_tiles_cost(
    tiles: &[Decoded],
    cell_degrees: f64,
    meta: &fractile_proto::AssetMeta,
) {
    println!(
        "\n| zoom | source cell, pixels | served | detail past the source removed | at full precision | the source's cells as blocks | the same three, WebP |"
    );
    println!("|---|---|---|---|---|---|---|");
    let format = TileFormat::Heights(HeightEncoding::TerrainRgb);
    let encode = |h: &[f32], t: &Decoded, container: Option<Container>, full: bool| {
        let rounding = match full {
            true => Rounding::default(),
            false => Rounding::for_tile(
                HeightEncoding::TerrainRgb,
                t.error_bound,
                relief(h, 256),
                meta.stats.rmse as f32,
            ),
        };
        let container = container.unwrap_or(Container::Png(Deflate::for_tile(rounding)));
        let (_, body) = encode_tile(
            meta,
            &[h.to_vec()],
            256,
            format,
            None,
            (rounding, container),
        );
        body.len()
    };
    let mut total = [0f64; 7];
    let zs: Vec<u8> = zooms().collect();
    for &z in &zs {
        let at: Vec<&Decoded> = tiles.iter().filter(|t| t.zoom == z).collect();
        if at.is_empty() {
            continue;
        }
        let cell = cell_degrees / (360.0 / f64::from(1u32 << z) / 256.0);
        let spacing = if cell >= 2.0 {
            1usize << cell.log2().floor() as u32
        } else {
            1
        };
        let mut row = [0f64; 7];
        for t in &at {
            let smooth = on_lattice(&t.heights, spacing, false);
            let blocks = on_lattice(&t.heights, spacing, true);
            let webp = Some(Container::WebP);
            let sizes = [
                encode(&t.heights, t, None, false),
                encode(&smooth, t, None, false),
                encode(&smooth, t, None, true),
                encode(&blocks, t, None, false),
                encode(&t.heights, t, webp, false),
                encode(&smooth, t, webp, false),
                encode(&blocks, t, webp, false),
            ];
            for (r, s) in row.iter_mut().zip(sizes) {
                *r += s as f64 / at.len() as f64;
            }
        }
        for (a, r) in total.iter_mut().zip(row) {
            *a += r / zs.len() as f64;
        }
        println!(
            "| {z} | {cell:.1} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0}, {:.0}, {:.0} |",
            row[0], row[1], row[2], row[3], row[4], row[5], row[6]
        );
    }
    println!(
        "| mean | | {:.0} | {:.0} | {:.0} | {:.0} | {:.0}, {:.0}, {:.0} |",
        total[0], total[1], total[2], total[3], total[4], total[5], total[6]
    );
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let paths: Vec<std::path::PathBuf> = if args.is_empty() {
        vec![std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../testdata/jacksboro.tif")]
    } else {
        args.iter().map(Into::into).collect()
    };
    for p in paths {
        bench_dem(&p);
    }
}
