//! The plots of the README: rate-distortion curves (PSNR against bits per pixel) of fractile
//! (the quadtree and projected codecs), JPEG and JPEG 2000 on camera and etopo20, and the throughput comparison of the service.
//! `cargo bench -p fractile-codec --bench plots` encodes each image at a sweep of rates, prints
//! the points as tables and writes `docs/plots/rd-camera.svg`, `docs/plots/rd-etopo20.svg` and
//! `docs/plots/throughput.svg` (from `docs/plots/tiles.csv`, the load test's figures). JPEG 2000
//! needs OpenJPEG's tools on PATH (`apt-get install libopenjp2-tools`); without them its curve
//! is left out and said so.

use std::path::{Path, PathBuf};

use fractile_codec::{QuadtreeSettings, Raster, RateMode, encode};
use plotters::prelude::*;

#[path = "support/baselines.rs"]
mod baselines;
use baselines::{jpeg_at, jpeg2000_at};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// One codec's curve: (bpp, PSNR dB) points in rate order.
struct Curve {
    name: &'static str,
    colour: RGBColor,
    points: Vec<(f64, f64)>,
}

/// The settings `fractile encode` uses for this kind of input at a target rate (for height
/// fields: planar offsets, weighing the quantisers, as the command line does by default).
fn settings(r: &Raster, bpp: f64) -> QuadtreeSettings {
    let s = QuadtreeSettings {
        rate: RateMode::TargetBpp(bpp),
        ..QuadtreeSettings::default()
    };
    if r.sample == fractile_proto::SampleFormat::U8 {
        return s;
    }
    let kind = fractile_proto::AssetKind::HeightField;
    let mut s = s;
    s.quantiser.slope_bits = QuadtreeSettings::default_slope_bits(kind);
    QuadtreeSettings {
        quantiser_choices: QuadtreeSettings::default_quantiser_choices(kind, s.quantiser),
        ..s
    }
}

fn curves(r: &Raster, rates: &[f64], with_jpeg: bool) -> Vec<Curve> {
    use fractile_codec::codecs::projected::ProjectedSettings;
    let mut fractile = Vec::new();
    let mut projected = Vec::new();
    let (mut jpeg, mut j2k) = (Vec::new(), Vec::new());
    for &bpp in rates {
        let enc = encode(r, &settings(r, bpp), &|_, _| {}).expect("encode");
        fractile.push((enc.bpp(), enc.errors.psnr));
        let p = fractile_codec::encode(
            r,
            &ProjectedSettings {
                target_bpp: Some(bpp),
                ..ProjectedSettings::default()
            },
            &|_, _| {},
        )
        .expect("projected");
        projected.push((p.bpp(), p.errors.psnr));
        if with_jpeg {
            jpeg.extend(jpeg_at(r, bpp));
        }
        j2k.extend(jpeg2000_at(r, bpp));
    }
    let mut out = vec![
        Curve {
            name: "fractile (quadtree PIFS)",
            colour: RGBColor(200, 60, 30),
            points: fractile,
        },
        Curve {
            name: "fractile (projected)",
            colour: RGBColor(30, 150, 60),
            points: projected,
        },
    ];
    if with_jpeg {
        out.push(Curve {
            name: "JPEG (image crate, baseline)",
            colour: RGBColor(90, 90, 90),
            points: jpeg,
        });
    }
    if j2k.is_empty() {
        println!("(JPEG 2000 left out: opj_compress is not on PATH)");
    } else {
        out.push(Curve {
            name: "JPEG 2000 (OpenJPEG, 9/7)",
            colour: RGBColor(30, 90, 200),
            points: j2k,
        });
    }
    out
}

fn print_table(title: &str, curves: &[Curve]) {
    println!("\n{title}\n\n| codec | bpp | PSNR dB |\n|---|---|---|");
    for c in curves {
        for (b, p) in &c.points {
            println!("| {} | {b:.3} | {p:.2} |", c.name);
        }
    }
}

fn draw_rd(path: &Path, title: &str, curves: &[Curve]) -> Result<(), Box<dyn std::error::Error>> {
    let all = curves.iter().flat_map(|c| c.points.iter());
    let (mut x1, mut y0, mut y1) = (0.0f64, f64::INFINITY, f64::NEG_INFINITY);
    for (b, p) in all {
        x1 = x1.max(*b);
        y0 = y0.min(*p);
        y1 = y1.max(*p);
    }
    let root = SVGBackend::new(path, (720, 480)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(16)
        .x_label_area_size(40)
        .y_label_area_size(56)
        .build_cartesian_2d(0.0..x1 * 1.05, (y0 - 1.0).floor()..(y1 + 1.0).ceil())?;
    chart
        .configure_mesh()
        .x_desc("bits per pixel")
        .y_desc("PSNR (dB)")
        .draw()?;
    for c in curves {
        let style = ShapeStyle::from(&c.colour).stroke_width(2);
        chart
            .draw_series(LineSeries::new(c.points.iter().copied(), style))?
            .label(c.name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], style));
        chart.draw_series(
            c.points
                .iter()
                .map(|&p| Circle::new(p, 3, ShapeStyle::from(&c.colour).filled())),
        )?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .draw()?;
    root.present()?;
    Ok(())
}

/// A bar chart of the load test's figures, log scale (they span four decades).
fn draw_throughput(csv: &Path, path: &Path) -> Result<(), Box<dyn std::error::Error>> {
    let text = std::fs::read_to_string(csv)?;
    let rows: Vec<(String, String, f64)> = text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (
                f[0].to_string(),
                f[1].to_string(),
                f[2].parse().expect("a number"),
            )
        })
        .collect();
    println!(
        "\nthroughput ({})\n\n| server | work | per second |\n|---|---|---|",
        csv.display()
    );
    for (s, w, v) in &rows {
        println!("| {s} | {w} | {v} |");
    }
    let root = SVGBackend::new(path, (720, 420)).into_drawing_area();
    root.fill(&WHITE)?;
    let n = rows.len() as u32;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Throughput on 2 cores (per second, log scale)",
            ("sans-serif", 20),
        )
        .margin(16)
        .x_label_area_size(30)
        .y_label_area_size(260)
        .build_cartesian_2d((1.0f64..1e7).log_scale(), (0u32..n - 1).into_segmented())?;
    chart
        .configure_mesh()
        .y_labels(rows.len())
        .x_label_formatter(&|v| match *v {
            v if v >= 1e6 => format!("{}M", v / 1e6),
            v if v >= 1e3 => format!("{}k", v / 1e3),
            v => format!("{v}"),
        })
        .y_label_formatter(&|v| match v {
            // The first row on top.
            SegmentValue::CenterOf(i) => rows
                .get((n - 1 - *i) as usize)
                .map(|(s, w, _)| format!("{s}: {w}"))
                .unwrap_or_default(),
            _ => String::new(),
        })
        .x_desc("per second")
        .draw()?;
    chart.draw_series(rows.iter().enumerate().map(|(i, (s, _, v))| {
        let colour = if s == "fractile" {
            RGBColor(200, 60, 30)
        } else {
            RGBColor(90, 90, 90)
        };
        let i = n - 1 - i as u32;
        let mut bar = Rectangle::new(
            [
                (1.0, SegmentValue::Exact(i)),
                (*v, SegmentValue::Exact(i + 1)),
            ],
            colour.filled(),
        );
        bar.set_margin(4, 4, 0, 0);
        bar
    }))?;
    root.present()?;
    Ok(())
}

fn main() {
    let out = root().join("docs/plots");
    std::fs::create_dir_all(&out).expect("docs/plots");
    let camera = Raster::open(&root().join("testdata/camera.png")).expect("camera");
    let rates = [0.15, 0.2, 0.3, 0.4, 0.48, 0.6, 0.8, 1.0];
    let c = curves(&camera, &rates, true);
    print_table("camera 512 x 512", &c);
    draw_rd(
        &out.join("rd-camera.svg"),
        "camera 512 x 512: PSNR against rate",
        &c,
    )
    .expect("rd-camera.svg");
    let etopo = Raster::open(&root().join("testdata/etopo20.tif")).expect("etopo20");
    // 16-bit heights: 48:1 to 8:1.
    let rates = [16.0 / 48.0, 0.5, 16.0 / 24.0, 0.8, 1.0, 16.0 / 12.0, 2.0];
    let e = curves(&etopo, &rates, false);
    print_table("etopo20 (16-bit heights; PSNR over the value range)", &e);
    draw_rd(
        &out.join("rd-etopo20.svg"),
        "etopo20 DEM: PSNR against rate",
        &e,
    )
    .expect("rd-etopo20.svg");
    draw_throughput(&out.join("tiles.csv"), &out.join("throughput.svg")).expect("throughput.svg");
    println!("\nwrote {}", out.display());
}
