//! Curve codec figures: bytes against float64 and float32 coordinates, Hausdorff distance to
//! the source in metres at each level, encode seconds.
//!
//! `cargo bench -p fractile-codec --bench curve` reads `../shared/data/curve/coastlines-50m.geojson`
//! when present (the 40 longest Natural Earth 1:50m outlines), else `testdata/curve/coast5.geojson`.
//! Environment: `FRACTILE_TOL=0.0089,0.018` (degrees of arc) to change the tolerances of the
//! whole set, `FRACTILE_RING_TOL` those of the five longest rings (default 0.0089 and 0.00899).

use fractile_codec::codecs::curve::{
    self, CurveSettings, METRES_PER_DEGREE, Metric, geojson::Polyline,
};
use std::time::Instant;

/// Hausdorff distances are sampled every 0.0002 degrees (22 m) along segments: exact to 11 m.
const SPACING: f64 = 0.0002;

fn source() -> (String, Vec<Polyline>) {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    for p in [
        root.join("../shared/data/curve/coastlines-50m.geojson"),
        root.join("testdata/curve/coast5.geojson"),
    ] {
        if let Ok(text) = std::fs::read_to_string(&p) {
            return (
                p.display().to_string(),
                curve::geojson::read(&text).expect("GeoJSON"),
            );
        }
    }
    panic!("no curve data found");
}

/// Bytes of the coded payload as an asset stores it (compact header, then the stream).
fn coded_bytes(c: &curve::Curves) -> usize {
    c.payload().len()
}

fn main() {
    let (path, lines) = source();
    let points: usize = lines
        .iter()
        .map(|l| l.points.len() + usize::from(l.closed))
        .sum();
    println!("source: {path}: {} polylines, {points} points", lines.len());
    let tolerances: Vec<f64> = std::env::var("FRACTILE_TOL")
        .ok()
        .map(|v| v.split(',').filter_map(|t| t.parse().ok()).collect())
        .unwrap_or_else(|| vec![0.0, 0.0045, 0.0089, 0.018]);

    println!("\n## All polylines, one asset");
    println!(
        "| tolerance (deg / m) | scheme | bytes | vs float64 | vs float32 | bytes/point | Hausdorff at finest (m) | largest vertex slide (m) | encode (s) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for &tol in &tolerances {
        for fit in [false, true] {
            let t0 = Instant::now();
            let (c, _) = curve::encode(
                &lines,
                &CurveSettings {
                    tolerance: tol,
                    metric: Metric::Sphere,
                    fit,
                    ..Default::default()
                },
            )
            .expect("encode");
            let secs = t0.elapsed().as_secs_f64();
            let bytes = coded_bytes(&c);
            let finest = c.set.at_level(c.set.finest());
            let mut h: f64 = 0.0;
            let mut vertex: f64 = 0.0;
            for ((l, out), rh) in lines.iter().zip(&finest.lines).zip(&c.header.rings) {
                let mut src = l.points.clone();
                if l.closed {
                    src.push(src[0]);
                }
                h = h.max(curve::hausdorff(Metric::Sphere, &src, out, SPACING));
                // A ring around a pole holds its start vertex twice (the coded line's ends):
                // leave one out to pair output and input vertices.
                let mut out = out.clone();
                if out.len() == src.len() + 1 {
                    let s = rh.start.unwrap_or(0) as usize;
                    out.remove(if s == 0 { out.len() - 2 } else { s + 1 });
                }
                for (a, b) in src.iter().zip(&out) {
                    vertex = vertex.max(Metric::Sphere.distance(*a, *b));
                }
            }
            println!(
                "| {tol} / {:.0} | {} | {bytes} | {:.2}:1 | {:.2}:1 | {:.2} | {:.1} | {:.1} | {secs:.2} |",
                tol * METRES_PER_DEGREE,
                if fit { "fitted T, U" } else { "default" },
                (points * 16) as f64 / bytes as f64,
                (points * 8) as f64 / bytes as f64,
                bytes as f64 / points as f64,
                h * METRES_PER_DEGREE,
                vertex * METRES_PER_DEGREE,
            );
        }
    }

    // 0.0089° is 990 m; 0.00899° (999.6 m) is the largest tolerance of this form under 1 km.
    let ring_tolerances: Vec<f64> = std::env::var("FRACTILE_RING_TOL")
        .ok()
        .map(|v| v.split(',').filter_map(|t| t.parse().ok()).collect())
        .unwrap_or_else(|| vec![0.0089, 0.00899]);
    for tol in ring_tolerances {
        println!(
            "\n## The five longest polylines, each its own asset, tolerance {tol}° ({:.0} m), fitted scheme",
            tol * METRES_PER_DEGREE
        );
        let mut order: Vec<usize> = (0..lines.len()).collect();
        order.sort_by_key(|&i| std::cmp::Reverse(lines[i].points.len()));
        println!(
            "| polyline | points | bytes | vs float32 | encode (s) | Hausdorff (m) at finest, -1, -2, -3, -4 levels | bound at finest (m) |"
        );
        println!("|---|---|---|---|---|---|---|");
        for &i in order.iter().take(5) {
            let l = &lines[i];
            let n = l.points.len() + usize::from(l.closed);
            let t0 = Instant::now();
            let (c, _) = curve::encode(
                std::slice::from_ref(l),
                &CurveSettings {
                    tolerance: tol,
                    metric: Metric::Sphere,
                    fit: true,
                    ..Default::default()
                },
            )
            .expect("encode");
            let secs = t0.elapsed().as_secs_f64();
            let bytes = coded_bytes(&c);
            let mut src = l.points.clone();
            if l.closed {
                src.push(src[0]);
            }
            let finest = c.set.finest();
            let per_level: Vec<String> = (0..5)
                .filter(|k| *k <= finest)
                .map(|k| {
                    let out = c.set.at_level(finest - k);
                    format!(
                        "{:.0}",
                        curve::hausdorff(Metric::Sphere, &src, &out.lines[0], SPACING)
                            * METRES_PER_DEGREE
                    )
                })
                .collect();
            println!(
                "| #{i} | {n} | {bytes} | {:.3}:1 | {secs:.2} | {} | {:.0} |",
                (n * 8) as f64 / bytes as f64,
                per_level.join(", "),
                c.set.at_level(finest).error_bound * METRES_PER_DEGREE
            );
        }
    }
}
