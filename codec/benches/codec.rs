//! Codec bench: prints a table per test image and setting (bpp, ratio, PSNR, encode s, decode
//! ms, and JPEG and JPEG 2000 at the same rate beside it), then decoder speeds. Release build:
//! `cargo bench -p fractile-codec --bench codec`. Uses `testdata/` and, when present,
//! `../shared/data` (etopo20); `PROJECTED_EXTRA=a.tif:b.png` adds held-out rasters to the
//! projected codec's table.

use std::path::{Path, PathBuf};
use std::time::Instant;

use fractile_codec::codecs::quadtree::{DEFAULT_SPEED, SPEEDS};
use fractile_codec::decode::{self, DiscreteOptions};
use fractile_codec::metrics;
use fractile_codec::operator;
use fractile_codec::operator::Operator;
use fractile_codec::{QuadtreeSettings, Raster, RateMode, SearchMode, encode};

#[path = "support/baselines.rs"]
mod baselines;
use baselines::{jpeg_at, jpeg2000_at};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn quiet(_: u64, _: u64) {}

/// The median wall time of `reps` runs of `f`, in ms: the machine is shared (wrk, rayon's
/// spinning workers after an all-core decode), and the median is what a run without such
/// interference takes.
fn median_ms(reps: usize, mut f: impl FnMut()) -> f64 {
    let mut times: Vec<f64> = (0..reps)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

fn row(name: &str, setting: &str, r: &Raster, s: &QuadtreeSettings, jpeg_bpp: bool) {
    let enc = encode(r, s, &quiet).expect("encode");
    let t = Instant::now();
    let (_d, rep) = enc.asset.decode_native();
    let dec_ms = t.elapsed().as_secs_f64() * 1e3;
    let jpeg = if jpeg_bpp {
        jpeg_at(r, enc.bpp())
    } else {
        None
    };
    let j2k = jpeg2000_at(r, enc.bpp());
    let beside = |f: Option<(f64, f64)>| {
        f.map(|(b, p)| format!("{p:.2} dB at {b:.3} bpp"))
            .unwrap_or_else(|| "-".into())
    };
    println!(
        "| {name} | {setting} | {} | {:.3} | {:.2}:1 | {:.2} | {:.2} | {:.1} ({} it) | {} | {} |",
        enc.bytes.len(),
        enc.bpp(),
        enc.ratio(),
        enc.errors.psnr,
        enc.seconds,
        dec_ms,
        rep.iterations,
        beside(jpeg),
        beside(j2k)
    );
}

fn main() {
    let filter = std::env::args().nth(1).filter(|a| !a.starts_with('-'));
    let want = |n: &str| filter.as_deref().is_none_or(|f| n.contains(f));
    println!(
        "## Rate and quality (release, {} threads)\n",
        rayon::current_num_threads()
    );
    println!(
        "| image | setting | bytes | bpp | ratio | PSNR dB | encode s | decode ms | JPEG same bpp | JPEG 2000 same bpp |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let camera = Raster::open(&root().join("testdata/camera.png")).expect("camera");
    let bpp = |b| QuadtreeSettings {
        rate: RateMode::TargetBpp(b),
        ..QuadtreeSettings::default()
    };
    // Height fields with a planar offset term at the default 6-bit offsets and slopes, and as
    // the CLI encodes them by default: also weighing 5, 7 and 8 bits and keeping the best.
    let dem = |b| {
        let mut s = bpp(b);
        s.quantiser.slope_bits =
            QuadtreeSettings::default_slope_bits(fractile_proto::AssetKind::HeightField);
        s
    };
    let dem_weighed = |b| {
        let s = dem(b);
        QuadtreeSettings {
            quantiser_choices: QuadtreeSettings::default_quantiser_choices(
                fractile_proto::AssetKind::HeightField,
                s.quantiser,
            ),
            ..s
        }
    };
    if want("camera") {
        for b in [0.48, 0.20] {
            row(
                "camera 512",
                &format!("target {b} bpp"),
                &camera,
                &bpp(b),
                true,
            );
            let s = QuadtreeSettings {
                search: SearchMode::Classified,
                ..bpp(b)
            };
            row(
                "camera 512",
                &format!("target {b} bpp, classified"),
                &camera,
                &s,
                true,
            );
        }
    }
    if want("astronaut") {
        let a = Raster::open(&root().join("testdata/astronaut.png")).expect("astronaut");
        row("astronaut 512 RGB", "target 0.5 bpp", &a, &bpp(0.5), true);
    }
    if want("jacksboro") {
        let j = Raster::open(&root().join("testdata/jacksboro.tif")).expect("jacksboro");
        row("jacksboro", "ratio 20:1 (0.8 bpp)", &j, &bpp(0.8), false);
        row(
            "jacksboro",
            "ratio 20:1, planar offsets",
            &j,
            &dem(0.8),
            false,
        );
        row(
            "jacksboro",
            "ratio 20:1, planar, weighed quantisers",
            &j,
            &dem_weighed(0.8),
            false,
        );
    }
    let etopo_path = root().join("testdata/etopo20.tif");
    if want("etopo") && Path::new(&etopo_path).exists() {
        let e = Raster::open(&etopo_path).expect("etopo20");
        row("etopo20", "ratio 20:1 (0.8 bpp)", &e, &bpp(0.8), false);
        row(
            "etopo20",
            "ratio 20:1, planar offsets",
            &e,
            &dem(0.8),
            false,
        );
        row(
            "etopo20",
            "ratio 20:1, planar, weighed quantisers",
            &e,
            &dem_weighed(0.8),
            false,
        );
    }

    if want("speed") {
        // The speed presets (`--speed`), each image at each preset, in one run: quality against
        // encode time, the default's row beside the others.
        println!("\n## Speed presets\n");
        println!(
            "| image | rate | speed | domain step, candidates, attractor passes | bpp | PSNR dB | encode s |"
        );
        println!("|---|---|---|---|---|---|---|");
        let mut cases: Vec<(&str, &Raster, f64, bool)> = vec![
            ("camera 512", &camera, 0.2, false),
            ("camera 512", &camera, 0.48, false),
        ];
        let etopo = Path::new(&etopo_path)
            .exists()
            .then(|| Raster::open(&etopo_path).expect("etopo20"));
        if let Some(e) = &etopo {
            cases.push(("etopo20", e, 0.8, true));
        }
        for (name, r, b, height) in cases {
            for speed in 0..SPEEDS.len() as u8 {
                let mut s = QuadtreeSettings {
                    rate: RateMode::TargetBpp(b),
                    ..QuadtreeSettings::at_speed(speed).expect("preset")
                };
                // One quantiser (no `quantiser_choices`): the presets are compared on the
                // search alone.
                if height {
                    s.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(
                        fractile_proto::AssetKind::HeightField,
                    );
                }
                let enc = encode(r, &s, &quiet).expect("encode");
                let p = SPEEDS[speed as usize];
                println!(
                    "| {name} | {b} bpp | {speed}{} | {}, {}, {} | {:.3} | {:.2} | {:.2} |",
                    if speed == DEFAULT_SPEED {
                        " (default)"
                    } else {
                        ""
                    },
                    p.domain_step,
                    p.candidates,
                    p.attractor_passes,
                    enc.bpp(),
                    enc.errors.psnr,
                    enc.seconds
                );
            }
        }
    }

    if want("decode") {
        println!("\n## Decoders (camera at 0.48 bpp)\n");
        let enc = encode(&camera, &bpp(0.48), &quiet).expect("encode");
        let op = &enc.asset.planes()[0].operator;
        let reps = 10;
        let disc = median_ms(reps, || {
            std::hint::black_box(decode::discrete(op, 512, 512, DiscreteOptions::default()));
        });
        // Continuous: 256 x 256 points x 10 steps on one core (no rayon).
        let pts: Vec<[f32; 2]> = (0..256 * 256)
            .map(|k| {
                [
                    ((k % 256) as f32 + 0.5) / 256.0,
                    ((k / 256) as f32 + 0.5) / 256.0,
                ]
            })
            .collect();
        let reps = 30;
        let single = median_ms(reps, || {
            let mut acc = 0.0f32;
            for p in &pts {
                acc += op.point(*p, 10).value;
            }
            std::hint::black_box(acc);
        });
        let cont = median_ms(reps, || {
            std::hint::black_box(op.points(&pts, 10, 0.0));
        });
        // The same chains stepped through `Operator::step` (the layout every codec has),
        // against the quadtree's own layout for the loop that `points` uses.
        let fractile_codec::asset::PlaneOperator::Quadtree(quadtree) = op else {
            unreachable!("images are coded as quadtrees")
        };
        let valid = op.valid();
        let stepwise = median_ms(reps, || {
            let mut chains: Vec<operator::Chain<2>> = pts
                .iter()
                .map(|p| operator::Chain {
                    q: [
                        decode::to_frame(p[0], valid[0], decode::position_quantum(&op.frame())),
                        decode::to_frame(p[1], valid[1], decode::position_quantum(&op.frame())),
                    ],
                    acc_g: 0.0,
                    acc_s: 1.0,
                    taken: 0,
                })
                .collect();
            operator::run_chains_stepwise(quadtree, &mut chains, 10, 0.0);
            std::hint::black_box(chains);
        });
        // The same pixel centres as the separable grid they are (how tiles and regions decode).
        let axis: Vec<f32> = (0..256).map(|k| (k as f32 + 0.5) / 256.0).collect();
        let cont_grid = median_ms(reps, || {
            std::hint::black_box(op.grid(&axis, &axis, 10, 0.0));
        });
        // Discrete vs continuous at pixel centres: the measured difference of averaging and sampling.
        let (grid, _) = decode::discrete(op, 512, 512, DiscreteOptions::fixed(40));
        let mut diff = 0.0f64;
        for k in 0..512 * 512 {
            let p = decode::point(
                op,
                [
                    ((k % 512) as f32 + 0.5) / 512.0,
                    ((k / 512) as f32 + 0.5) / 512.0,
                ],
                40,
            );
            diff += (p.value - grid.values[k]).abs() as f64;
        }
        let cont_psnr = {
            let vals: Vec<f32> = (0..512 * 512)
                .map(|k| {
                    255.0
                        * decode::point(
                            op,
                            [
                                ((k % 512) as f32 + 0.5) / 512.0,
                                ((k / 512) as f32 + 0.5) / 512.0,
                            ],
                            40,
                        )
                        .value
                })
                .collect();
            metrics::compare(&camera.channels, &[vals], None, 255.0).psnr
        };
        println!("| decoder | figure |");
        println!("|---|---|");
        println!("| discrete 512x512, to convergence (all cores) | {disc:.1} ms |");
        println!(
            "| continuous 256x256 points x 10 steps, one point at a time (one core) | {single:.2} ms |"
        );
        println!(
            "| continuous 256x256 points x 10 steps, batched, stepped through `Operator::step` (one core) | {stepwise:.2} ms ({:.1}x) |",
            single / stepwise
        );
        println!(
            "| continuous 256x256 points x 10 steps, batched, the quadtree's own layout (one core) | {cont:.2} ms ({:.1}x; {:.2}x the stepwise) |",
            single / cont,
            stepwise / cont
        );
        println!(
            "| continuous 256x256 points x 10 steps, the pixel centres as a grid (one core) | {cont_grid:.2} ms ({:.1}x) |",
            single / cont_grid
        );
        // Separable grids (what tiles and regions decode): 256 x 256 pixel centres over windows
        // of the source from its full width to 1/64 of it, to the 0.002 tolerance, point by
        // point and block by block (the same answers, checked here too).
        for div in [2u32, 8, 32, 64] {
            let side = 1.0 / div as f32;
            let (u0, v0) = (0.37 - side / 2.0, 0.41 - side / 2.0);
            let xs: Vec<f32> = (0..256)
                .map(|i| u0 + side * (i as f32 + 0.5) / 256.0)
                .collect();
            let ys: Vec<f32> = (0..256)
                .map(|j| v0 + side * (j as f32 + 0.5) / 256.0)
                .collect();
            let grid_pts: Vec<[f32; 2]> = ys
                .iter()
                .flat_map(|&y| xs.iter().map(move |&x| [x, y]))
                .collect();
            let by_point = median_ms(reps, || {
                std::hint::black_box(op.points(&grid_pts, 30, 0.002));
            });
            let by_grid = median_ms(reps, || {
                std::hint::black_box(op.grid(&xs, &ys, 30, 0.002));
            });
            assert_eq!(
                op.grid(&xs, &ys, 30, 0.002),
                op.points(&grid_pts, 30, 0.002)
            );
            println!(
                "| 256x256 grid over {} source pixels wide, bound 0.002: point by point / block by block (one core) | {by_point:.2} / {by_grid:.2} ms ({:.1}x) |",
                512 / div,
                by_point / by_grid
            );
            // The same window turned by 2 degrees (a tile over a UTM grid: the meridian
            // convergence) as a bilinear patch: point by point and patch decoding.
            let (c, s) = (2f64.to_radians().cos(), 2f64.to_radians().sin());
            let step = side as f64 / 256.0;
            let patch = decode::Patch {
                origin: [u0 as f64 + 0.5 * step, v0 as f64 + 0.5 * step],
                a: [step * c, step * s],
                b: [-step * s, step * c],
                c: [0.0, 0.0],
                width: 256,
                height: 256,
            };
            let patch_pts: Vec<[f32; 2]> = (0..256)
                .flat_map(|j| (0..256).map(move |i| patch.at(i, j).map(|t| t as f32)))
                .collect();
            let by_point = median_ms(reps, || {
                std::hint::black_box(op.points(&patch_pts, 30, 0.002));
            });
            let by_patch = median_ms(reps, || {
                std::hint::black_box(op.patch(&patch, 30, 0.002));
            });
            println!(
                "| the same turned 2 degrees, as a patch: point by point / patch (one core) | {by_point:.2} / {by_patch:.2} ms ({:.1}x) |",
                by_point / by_patch
            );
        }
        println!(
            "| mean abs(discrete - continuous) at pixel centres | {:.2} grey levels |",
            diff / (512.0 * 512.0) * 255.0
        );
        println!(
            "| PSNR discrete / continuous (40 steps) vs source | {:.2} / {:.2} dB |",
            enc.errors.psnr, cont_psnr
        );
    }
    if want("projected") {
        projected(&root(), &camera, &dem_weighed);
    }
    if want("projected") || want("points") {
        projected_points(&root(), &dem_weighed);
    }
    if want("scale") {
        scale(&root(), &dem_weighed);
    }
}

/// Issue 30's scaling: the default DEM encode (0.8 bpp, as the CLI encodes DEMs) of mosaics of
/// k x k mirrored copies of etopo20 (a real DEM; mirrors keep it continuous across the seams),
/// time a megapixel against one copy's, and PSNR.
fn scale(root: &Path, dem: &dyn Fn(f64) -> QuadtreeSettings) {
    let e = Raster::open(&root.join("testdata/etopo20.tif")).expect("testdata");
    println!(
        "\n## Encode time against raster size (mirrored etopo20, 0.8 bpp, {} threads)\n",
        rayon::current_num_threads()
    );
    println!("| copies | size | Mpx | encode s | s a Mpx | against one copy | PSNR dB |");
    println!("|---|---|---|---|---|---|---|");
    let mut base = None;
    for k in [1usize, 2, 4] {
        let (w, h) = (e.width * k, e.height * k);
        let values: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let mirror = |t: usize, n: usize| {
                    if (t / n).is_multiple_of(2) {
                        t % n
                    } else {
                        n - 1 - t % n
                    }
                };
                e.channels[0][mirror(y, e.height) * e.width + mirror(x, e.width)]
            })
            .collect();
        let r = Raster::from_values(w, h, values, fractile_proto::AssetKind::HeightField)
            .expect("a mosaic");
        let enc = encode(&r, &dem(0.8), &quiet).expect("encode");
        let mpx = (w * h) as f64 / 1e6;
        let per = enc.seconds / mpx;
        let first = *base.get_or_insert(per);
        println!(
            "| {k} x {k} | {w} x {h} | {mpx:.2} | {:.1} | {per:.2} | {:.2}x | {:.2} |",
            enc.seconds,
            per / first,
            enc.errors.psnr
        );
    }
}

/// Issue 29's tables: the projected codec beside the quadtree and JPEG 2000 at the same bytes
/// on both DEMs and on camera, its max-error ratios, and point decoding beside the quadtree's.
fn projected(root: &Path, camera: &Raster, quadtree: &dyn Fn(f64) -> QuadtreeSettings) {
    use fractile_codec::codecs::projected::ProjectedSettings;
    let rate = ProjectedSettings::default();
    let pyramid = ProjectedSettings {
        pyramid: true,
        ..ProjectedSettings::default()
    };
    println!("\n## projected against the quadtree and JPEG 2000 at the same bytes\n");
    println!(
        "| image | ratio | projected (kernel) | projected, pyramid | quadtree-pifs | JPEG 2000 | \
         projected - JPEG 2000 |"
    );
    println!("|---|---|---|---|---|---|---|");
    let dems: Vec<(&str, Raster)> = ["jacksboro.tif", "etopo20.tif"]
        .iter()
        .map(|n| {
            (
                *n,
                Raster::open(&root.join("testdata").join(n)).expect("testdata"),
            )
        })
        .collect();
    let dem_rows = |name: &str, r: &Raster| {
        for ratio in [10.0, 20.0, 40.0, 80.0] {
            let bpp = 16.0 / ratio;
            let p = fractile_codec::encode(
                r,
                &ProjectedSettings {
                    target_bpp: Some(bpp),
                    ..rate.clone()
                },
                &|_, _| {},
            )
            .expect("projected");
            let pp = fractile_codec::encode(
                r,
                &ProjectedSettings {
                    target_bpp: Some(bpp),
                    ..pyramid.clone()
                },
                &|_, _| {},
            )
            .expect("projected");
            let q = encode(r, &quadtree(bpp), &quiet).expect("quadtree");
            let j = jpeg2000_at(r, p.bpp());
            println!(
                "| {name} | {ratio}:1 | {:.2} dB at {:.3} bpp ({}) | {:.2} dB at {:.3} bpp | \
                 {:.2} dB at {:.3} bpp | {} | {} |",
                p.errors.psnr,
                p.bpp(),
                kernel(&p.asset),
                pp.errors.psnr,
                pp.bpp(),
                q.errors.psnr,
                q.bpp(),
                j.map_or("-".into(), |(b, d)| format!("{d:.2} dB at {b:.3} bpp")),
                j.map_or("-".into(), |(_, d)| format!("{:+.2} dB", p.errors.psnr - d)),
            );
        }
    };
    let image_rows = |label: &str, image: &Raster| {
        for bpp in [0.25, 0.5, 1.0, 2.0] {
            let p = fractile_codec::encode(
                image,
                &ProjectedSettings {
                    target_bpp: Some(bpp),
                    ..rate.clone()
                },
                &|_, _| {},
            )
            .expect("projected");
            let pp = fractile_codec::encode(
                image,
                &ProjectedSettings {
                    target_bpp: Some(bpp),
                    ..pyramid.clone()
                },
                &|_, _| {},
            )
            .expect("projected");
            let j = jpeg2000_at(image, p.bpp());
            let jp = jpeg_at(image, p.bpp());
            println!(
                "| {label} | {bpp} bpp | {:.2} dB at {:.3} bpp ({}) | {:.2} dB | JPEG {} | {} | {} |",
                p.errors.psnr,
                p.bpp(),
                kernel(&p.asset),
                pp.errors.psnr,
                jp.map_or("-".into(), |(b, d)| format!("{d:.2} dB at {b:.3} bpp")),
                j.map_or("-".into(), |(b, d)| format!("{d:.2} dB at {b:.3} bpp")),
                j.map_or("-".into(), |(_, d)| format!("{:+.2} dB", p.errors.psnr - d)),
            );
        }
    };
    for (name, r) in &dems {
        dem_rows(name, r);
    }
    let astronaut = Raster::open(&root.join("testdata/astronaut.png")).expect("astronaut");
    image_rows("camera 512", camera);
    image_rows("astronaut 512 RGB", &astronaut);
    // Held-out data (not in the repository): `PROJECTED_EXTRA=a.tif:b.png`, 8-bit rasters as
    // images, the others as DEMs.
    for path in std::env::var("PROJECTED_EXTRA")
        .unwrap_or_default()
        .split(':')
    {
        if path.is_empty() {
            continue;
        }
        let r = Raster::open(Path::new(path)).expect("a PROJECTED_EXTRA raster");
        let name = Path::new(path)
            .file_name()
            .map_or(path.into(), |n| n.to_string_lossy());
        if r.sample == fractile_proto::SampleFormat::U8 {
            image_rows(&name, &r);
        } else {
            dem_rows(&name, &r);
        }
    }
    println!("\n## projected --max-error: ratio against JPEG-LS near-lossless at the same bound\n");
    println!("JPEG-LS figures as issue 29 quotes them (NEAR = E); ours measured here.\n");
    println!("| DEM | E | ratio | worst error | PSNR dB | encode s | JPEG-LS |");
    println!("|---|---|---|---|---|---|---|");
    for (name, r) in &dems {
        for e in [0.0, 1.0, 10.0] {
            let s = ProjectedSettings {
                max_error: Some(e),
                ..ProjectedSettings::default()
            };
            let p = fractile_codec::encode(r, &s, &|_, _| {}).expect("projected");
            let anchor = match (*name, e) {
                ("etopo20.tif", 10.0) => "4.45:1",
                ("jacksboro.tif", 10.0) => "10.6:1",
                _ => "-",
            };
            println!(
                "| {name} | {e} | {:.2}:1 | {:.4} | {:.2} | {:.2} | {anchor} |",
                p.ratio(),
                p.errors.max_error,
                p.errors.psnr,
                p.seconds
            );
        }
    }
}

/// The multiresolution a projected asset's first plane was coded with.
fn kernel(asset: &fractile_codec::asset::Asset) -> String {
    match &asset.planes()[0].coding {
        fractile_codec::asset::Coding::Projected { header, .. } => {
            format!("{:?}", header.order)
        }
        _ => "-".into(),
    }
}

/// Point decoding of projected assets beside the quadtree's, both at 20:1 on etopo20: 256 x
/// 256 points, batched, one core; ten steps each, and to the server's default tolerance (half
/// a metre), where projected chains end on the bilinear interpolant and stop sooner.
fn projected_points(root: &Path, quadtree: &dyn Fn(f64) -> QuadtreeSettings) {
    use fractile_codec::codecs::projected::ProjectedSettings;
    let e = Raster::open(&root.join("testdata/etopo20.tif")).expect("testdata");
    let bounded = ProjectedSettings {
        bounded: true,
        ..Default::default()
    };
    let p = fractile_codec::encode(
        &e,
        &ProjectedSettings {
            target_bpp: Some(0.8),
            ..ProjectedSettings::default()
        },
        &|_, _| {},
    )
    .expect("projected");
    let b = fractile_codec::encode(
        &e,
        &ProjectedSettings {
            target_bpp: Some(0.8),
            ..bounded.clone()
        },
        &|_, _| {},
    )
    .expect("projected");
    let q = encode(&e, &quadtree(0.8), &quiet).expect("quadtree");
    let pts: Vec<[f32; 2]> = (0..256 * 256)
        .map(|k| {
            [
                ((k % 256) as f32 * 0.37 + 0.5) / 256.0 % 1.0,
                ((k / 256) as f32 * 0.61 + 0.5) / 256.0 % 1.0,
            ]
        })
        .collect();
    let time = |a: &fractile_codec::Asset, steps: u32, tolerance_m: f64| {
        let op = &a.planes()[0].operator;
        let tolerance = (tolerance_m / (a.meta.value_max - a.meta.value_min)) as f32;
        let mut n = 0u32;
        let ms = median_ms(15, || {
            let v = op.points(&pts, steps, tolerance);
            n = v.iter().map(|p| p.iterations).sum();
            std::hint::black_box(v);
        });
        (ms, f64::from(n) / pts.len() as f64)
    };
    println!("\n## Point decoding, etopo20 at 20:1 (256 x 256 points, batched, one core)\n");
    println!("| codec | steps | ms | mean steps | against the quadtree |");
    println!("|---|---|---|---|---|");
    for (steps, tol, label) in [(10, 0.0, "10"), (64, 0.5, "to 0.5 m")] {
        let (tq, nq) = time(&q.asset, steps, tol);
        println!("| quadtree-pifs | {label} | {tq:.2} | {nq:.1} | 1.00x |");
        for (name, a) in [("projected", &p.asset), ("projected --bounded", &b.asset)] {
            let (t, n) = time(a, steps, tol);
            println!(
                "| {name} | {label} | {t:.2} | {n:.1} | {:.2}x the time |",
                t / tq
            );
        }
    }
    residual_slack(&b.asset);
    // Tiles and regions are separable grids: 256 x 256 pixel centres over a window `zoom`
    // times finer than the source, to 0.5 m, decoded as a grid (blocks of points step
    // together) and as the same points one chain each, in the same run.
    println!("\n## Grid decoding, etopo20 at 20:1 (256 x 256 pixels to 0.5 m, one core)\n");
    println!(
        "| codec | pixels a source cell | grid ms | points ms | grid against points | against the quadtree's grid |"
    );
    println!("|---|---|---|---|---|---|");
    let [w, h] = [e.width as f32, e.height as f32];
    for zoom in [1.0f32, 4.0, 16.0, 32.0] {
        // A window of 256 / zoom cells a side, off the lattice's dyadic points.
        let (x0, y0) = (0.3 * w + 0.37, 0.4 * h + 0.21);
        let axis = |o: f32, n: f32| -> Vec<f32> {
            (0..256)
                .map(|k| (o + (k as f32 + 0.5) / zoom) / n)
                .collect()
        };
        let (xs, ys) = (axis(x0, w), axis(y0, h));
        let pts: Vec<[f32; 2]> = ys
            .iter()
            .flat_map(|&y| xs.iter().map(move |&x| [x, y]))
            .collect();
        let time = |a: &fractile_codec::Asset| {
            let op = &a.planes()[0].operator;
            let tolerance = (0.5 / (a.meta.value_max - a.meta.value_min)) as f32;
            let g = median_ms(15, || {
                std::hint::black_box(op.grid(&xs, &ys, 64, tolerance));
            });
            let p = median_ms(15, || {
                std::hint::black_box(op.points(&pts, 64, tolerance));
            });
            (g, p)
        };
        let (gq, pq) = time(&q.asset);
        println!(
            "| quadtree-pifs | {} | {gq:.2} | {pq:.2} | {:.2}x the time | 1.00x |",
            zoom * zoom,
            gq / pq
        );
        let (g, p) = time(&b.asset);
        println!(
            "| projected --bounded | {} | {g:.2} | {p:.2} | {:.2}x the time | {:.2}x the time |",
            zoom * zoom,
            g / p,
            g / gq
        );
    }
}

/// Where the projected points' steps go: per cell, the residual bound R a chain ends on (the
/// bound of a chain of no steps: S with `|f - S| <= R`) against the largest |f - S| found at
/// 16 x 16 points of the cell (f: 60 steps, tolerance 0), on 2,000 cells drawn at random. A
/// chain takes ln(R / tolerance) / ln(1 / rho) steps; a bound as tight as the true maximum
/// would save ln(R / max) / ln(1 / rho) of them, the most any tighter bound can.
fn residual_slack(a: &fractile_codec::Asset) {
    let op = match &a.planes()[0].operator {
        fractile_codec::asset::PlaneOperator::Projected(op) => op,
        _ => return,
    };
    let span = (a.meta.value_max - a.meta.value_min) as f32;
    let [w, h] = [a.meta.width as usize, a.meta.height as usize];
    let rho = f64::from(op.roughness());
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut draw = |n: usize| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state % n as u64) as usize
    };
    let (mut bounds, mut maxima, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..2000 {
        let (i, j) = (draw(w - 1), draw(h - 1));
        let pts: Vec<[f32; 2]> = (0..256)
            .map(|k| {
                let (a, b) = ((k % 16) as f32 + 0.5, (k / 16) as f32 + 0.5);
                [
                    (i as f32 + 0.5 + a / 16.0) / w as f32,
                    (j as f32 + 0.5 + b / 16.0) / h as f32,
                ]
            })
            .collect();
        let s = op.points(&pts, 0, 0.0);
        let f = op.points(&pts, 60, 0.0);
        let most = s
            .iter()
            .zip(&f)
            .map(|(s, f)| (f.value - s.value).abs())
            .fold(0.0f32, f32::max);
        let r = s.iter().map(|p| p.error_bound).fold(0.0f32, f32::max);
        bounds.push(f64::from(r * span));
        maxima.push(f64::from(most * span));
        ratios.push(f64::from(r / most.max(1e-9)));
    }
    let quantiles = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        [v[v.len() / 10], v[v.len() / 2], v[9 * v.len() / 10]]
    };
    let (r, m, q) = (
        quantiles(&mut bounds),
        quantiles(&mut maxima),
        quantiles(&mut ratios),
    );
    println!(
        "\n## The residual bound against the largest |f - S| a cell, etopo20 --bounded at 20:1 (rho {rho:.3}; 2,000 cells)\n"
    );
    println!(
        "| quantile | R (m) | largest \\|f - S\\| found (m) | R over it | steps a tight bound saves |"
    );
    println!("|---|---|---|---|---|");
    for (k, name) in ["10%", "median", "90%"].iter().enumerate() {
        println!(
            "| {name} | {:.1} | {:.1} | {:.2} | {:.2} |",
            r[k],
            m[k],
            q[k],
            q[k].ln() / (1.0 / rho).ln()
        );
    }
}
