//! The curve codec on real coastlines (testdata/curve/coast5.geojson, Natural Earth 1:50m):
//! exact reconstruction, the tolerance and level bounds against measured Hausdorff distances,
//! levels past the source, the file format's refusals, and the three deformations.

use fractile_codec::asset::Asset;
use fractile_codec::codecs::curve::geojson::Polyline;
use fractile_codec::codecs::curve::{self, CurveSettings, Metric, Pt};
use fractile_proto::Deformation;

fn coast() -> Vec<Polyline> {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../testdata/curve/coast5.geojson");
    curve::geojson::read(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn closed(l: &Polyline) -> Vec<Pt> {
    let mut p = l.points.clone();
    if l.closed {
        p.push(p[0]);
    }
    p
}

fn encode(lines: &[Polyline], tolerance: f64, fit: bool) -> Asset {
    let s = CurveSettings {
        tolerance,
        metric: Metric::Sphere,
        fit,
        ..Default::default()
    };
    let enc = fractile_codec::encode::curve::encode_asset(lines, &s, "coast5").unwrap();
    // What is served is what a reader of the file gets.
    let read = Asset::from_bytes(&enc.bytes).unwrap();
    assert_eq!(read.curves().unwrap().set, enc.asset.curves().unwrap().set);
    read
}

#[test]
fn tolerance_zero_reconstructs_every_input_vertex() {
    let lines = coast();
    for fit in [false, true] {
        let a = encode(&lines, 0.0, fit);
        let set = &a.curves().unwrap().set;
        let out = set.at_level(set.finest());
        assert_eq!(out.lines.len(), lines.len());
        for (l, o) in lines.iter().zip(&out.lines) {
            let src = closed(l);
            assert_eq!(o.len(), src.len());
            for (p, q) in src.iter().zip(o) {
                assert!(
                    (p[0] - q[0]).abs() < 1e-9 && (p[1] - q[1]).abs() < 1e-9,
                    "{p:?} {q:?}"
                );
            }
        }
    }
}

#[test]
fn every_level_within_its_bound_and_the_finest_within_the_tolerance() {
    let lines = coast();
    let tol = 0.009;
    let a = encode(&lines, tol, true);
    let c = a.curves().unwrap();
    let set = &c.set;
    let finest = set.finest();
    for level in 0..=finest + 2 {
        let out = set.at_level(level);
        let mut worst: f64 = 0.0;
        for (l, o) in lines.iter().zip(&out.lines) {
            // Sampled every tol/64 along segments: a point may slide along the coast, so the
            // largest distance need not be at a vertex.
            worst = worst.max(curve::hausdorff(Metric::Sphere, &closed(l), o, tol / 64.0));
        }
        assert!(
            worst <= out.error_bound * (1.0 + 1e-9),
            "level {level}: Hausdorff {worst} over the bound {}",
            out.error_bound
        );
        if level == finest {
            // Bounds are stored as f32 rounded up: within a few f32 ulps of the tolerance.
            assert!(out.error_bound <= tol * (1.0 + 1e-6), "{}", out.error_bound);
            // One output vertex per input vertex, each near the coast (it may slide along it).
            for (l, o) in lines.iter().zip(&out.lines) {
                assert_eq!(o.len(), closed(l).len());
            }
        }
        if level < finest {
            // A coarse level is a real simplification: far fewer points, larger error.
            let pts: usize = out.lines.iter().map(Vec::len).sum();
            let all: usize = lines.iter().map(|l| l.points.len()).sum();
            assert!(pts < all);
            assert!(out.error_bound > tol);
        }
    }
    // Lossy coding pays: at ~1 km the five coastlines code to well under float32's size.
    let f32_bytes = 8 * a.meta.width as usize;
    assert!(
        a.to_bytes().len() * 4 < f32_bytes,
        "{} bytes",
        a.to_bytes().len()
    );
}

#[test]
fn levels_past_the_source_keep_its_points_and_add_detail() {
    let lines = coast();
    let a = encode(&lines, 0.009, true);
    let set = &a.curves().unwrap().set;
    let l = set.finest();
    for ring in &set.rings {
        let own = set.ring_level(ring, l);
        let at = ring.polygon(&set.scheme, own);
        let deeper = ring.polygon(&set.scheme, own + 2);
        assert_eq!(
            deeper.len() - usize::from(!ring.closed),
            4 * (at.len() - usize::from(!ring.closed))
        );
        for (i, p) in at.iter().enumerate() {
            assert_eq!(deeper[4 * i], *p, "interpolating: source-level points stay");
        }
    }
    // The deepest level a request can name is the deepest, not level 0 wrapped round (whose
    // points and bound it answered): refused for its size instead.
    for ring in &set.rings {
        assert!(set.ring_level(ring, usize::MAX) > usize::MAX / 2);
    }
    assert!(set.points_at(usize::MAX) > set.points_at(l + 20));
}

#[test]
fn corrupt_truncated_and_unknown_files_are_refused() {
    let a = encode(&coast()[..1], 0.01, false);
    let bytes = a.to_bytes();
    for cut in [10, bytes.len() / 2, bytes.len() - 1] {
        assert!(Asset::from_bytes(&bytes[..cut]).is_err());
    }
    let mut flipped = bytes.clone();
    let mid = flipped.len() / 2;
    flipped[mid] ^= 0x40;
    assert!(Asset::from_bytes(&flipped).is_err());
    let mut codec = bytes.clone();
    codec[11] = 9;
    let err = Asset::from_bytes(&codec).unwrap_err().to_string();
    assert!(
        err.contains("unknown codec 9") || err.contains("checksum"),
        "{err}"
    );
}

/// Sets an asset file's version byte and its CRC to match.
fn restamp(bytes: &mut [u8], version: u8) {
    bytes[8] = version;
    let body = bytes.len() - 4;
    let crc = crc32fast::hash(&bytes[..body]).to_le_bytes();
    bytes[body..].copy_from_slice(&crc);
}

#[test]
fn older_curve_assets_are_refused_by_name() {
    // Format versions 2 and 3 changed the curve coding: an older curve file must not decode
    // to garbage, even with a valid checksum.
    // Version 9 numbers files that are not chunked after 5, with 5's layout (its change, and
    // 10's, were the projected codec's coding): the same bytes as version 5 are one.
    let v9 = encode(&coast()[..1], 0.01, false).to_bytes();
    assert_eq!(u16::from_le_bytes([v9[8], v9[9]]), 10);
    let mut v5 = v9.clone();
    restamp(&mut v5, 5);
    assert_eq!(
        Asset::from_bytes(&v5).unwrap().curves().unwrap().set,
        Asset::from_bytes(&v9).unwrap().curves().unwrap().set
    );
    // Version 5 added a source-error map after the payload (for rasters; a curve's is empty):
    // without its length field, the same bytes are a version-4 file.
    let body = v5.len() - 8;
    assert_eq!(v5[body..body + 4], [0; 4]);
    let mut current = v5.clone();
    current.drain(body..body + 4);
    restamp(&mut current, 4);
    assert_eq!(
        Asset::from_bytes(&current).unwrap().curves().unwrap().set,
        Asset::from_bytes(&v5).unwrap().curves().unwrap().set
    );
    // Version 4 only added antimeridian crossings: a version-3 curve asset (none) still reads.
    let mut v3 = current.clone();
    restamp(&mut v3, 3);
    assert_eq!(
        Asset::from_bytes(&v3).unwrap().curves().unwrap().set,
        Asset::from_bytes(&current).unwrap().curves().unwrap().set
    );
    for version in [1u8, 2] {
        let mut bytes = current.clone();
        restamp(&mut bytes, version);
        let err = Asset::from_bytes(&bytes).unwrap_err().to_string();
        assert!(
            err.contains(&format!("curve asset of format version {version}")),
            "{err}"
        );
    }
}

#[test]
fn bad_polylines_get_clear_errors() {
    let s = CurveSettings::default();
    let two = [Polyline {
        points: vec![[0.0, 0.0], [1.0, 1.0]],
        closed: true,
    }];
    let e = curve::encode(&two, &s).unwrap_err().to_string();
    assert!(e.contains("at least 3"), "{e}");
    let nan = [Polyline {
        points: vec![[0.0, 0.0], [f64::NAN, 1.0], [2.0, 0.0]],
        closed: false,
    }];
    assert!(
        curve::encode(&nan, &s)
            .unwrap_err()
            .to_string()
            .contains("not finite")
    );
    let neg = CurveSettings {
        tolerance: -1.0,
        ..Default::default()
    };
    assert!(curve::encode(&coast(), &neg).is_err());
}

#[test]
fn a_similarity_of_the_control_points_moves_the_whole_curve() {
    let lines = coast();
    let a = encode(&lines, 0.0, true);
    let set = &a.curves().unwrap().set;
    // Rotate ring 0's control points by 90° about (0, 50), scale by 1.5, translate.
    let f = |p: Pt| [-(p[1] - 50.0) * 1.5 + 3.0, p[0] * 1.5 + 50.0 - 2.0];
    let points: Vec<Pt> = set.rings[0].base.iter().map(|&p| f(p)).collect();
    let d = curve::deform::apply(set, &[Deformation::Control { ring: 0, points }]).unwrap();
    let before = set.at_level(set.finest());
    let after = d.at_level(d.finest());
    for (p, q) in before.lines[0].iter().zip(&after.lines[0]) {
        let t = f(*p);
        assert!(
            (t[0] - q[0]).abs() < 1e-9 && (t[1] - q[1]).abs() < 1e-9,
            "{t:?} vs {q:?}"
        );
    }
    assert_eq!(before.lines[1], after.lines[1], "other rings untouched");
}

#[test]
fn detail_edits_touch_only_the_finer_levels() {
    let lines = coast();
    let a = encode(&lines, 0.0, false);
    let set = &a.curves().unwrap().set;
    let finest = set.finest();
    let same = curve::deform::apply(
        set,
        &[Deformation::Details {
            from_level: 0,
            scale: 1.0,
            rotate_degrees: 0.0,
            ring: None,
        }],
    )
    .unwrap();
    assert_eq!(same.at_level(finest).lines, set.at_level(finest).lines);
    let smooth = curve::deform::apply(
        set,
        &[Deformation::Details {
            from_level: finest - 1,
            scale: 0.0,
            rotate_degrees: 0.0,
            ring: None,
        }],
    )
    .unwrap();
    let r = &set.rings[0];
    let own = set.ring_level(r, finest);
    let (a0, b0) = (
        r.polygon(&set.scheme, own),
        smooth.rings[0].polygon(&smooth.scheme, own),
    );
    let mut moved = 0;
    for i in 0..a0.len() {
        if i % 2 == 0 {
            assert_eq!(a0[i], b0[i], "points of coarser levels stay");
        } else if a0[i] != b0[i] {
            moved += 1;
        }
    }
    assert!(
        moved > a0.len() / 4,
        "the finest details were removed ({moved} moved)"
    );
}

#[test]
fn a_local_edit_moves_the_point_and_its_neighbours_only() {
    let lines = coast();
    let a = encode(&lines, 0.0, false);
    let set = &a.curves().unwrap().set;
    let level = set.finest() - 3;
    let before = set.at_level(level).lines[0].clone();
    let to = [before[5][0] + 0.5, before[5][1] + 0.25];
    let d = curve::deform::apply(
        set,
        &[Deformation::Local {
            ring: 0,
            level,
            index: 5,
            to,
            radius: 2,
        }],
    )
    .unwrap();
    let after = d.at_level(level).lines[0].clone();
    assert!((after[5][0] - to[0]).abs() < 1e-9 && (after[5][1] - to[1]).abs() < 1e-9);
    for (i, (p, q)) in before.iter().zip(&after).enumerate() {
        let k = i.abs_diff(5);
        if k > 2 {
            assert!(
                (p[0] - q[0]).abs() < 1e-9 && (p[1] - q[1]).abs() < 1e-9,
                "point {i} moved"
            );
        } else if k > 0 {
            let w = curve::deform::falloff(k, 2);
            assert!(((q[0] - p[0]) - 0.5 * w).abs() < 1e-9, "falloff at {k}");
        }
    }
    // The finer levels follow: the finest curve changed near the edit and nowhere far from it.
    let (fb, fa) = (set.at_level(set.finest()), d.at_level(d.finest()));
    let changed = fb.lines[0]
        .iter()
        .zip(&fa.lines[0])
        .filter(|(p, q)| (p[0] - q[0]).abs() > 1e-9 || (p[1] - q[1]).abs() > 1e-9)
        .count();
    assert!(changed > 0 && changed < fb.lines[0].len() / 2, "{changed}");
    assert!(
        curve::deform::apply(
            set,
            &[Deformation::Local {
                ring: 0,
                level: 99,
                index: 0,
                to,
                radius: 0
            }]
        )
        .is_err()
    );
}

fn antarctica() -> Vec<Polyline> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../testdata/curve/antarctica.geojson");
    curve::geojson::read(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// A coastline moved in longitude by `by` degrees, wrapped into [-180, 180].
fn moved(l: &Polyline, by: f64) -> Polyline {
    let mut m = l.clone();
    for p in &mut m.points {
        p[0] += by;
        if p[0] > 180.0 {
            p[0] -= 360.0;
        }
    }
    m
}

/// Asserts what a user of a coastline across the antimeridian relies on: every level within
/// its bound against the source as drawn (longitude and latitude, no wrapping), the finest
/// within the tolerance, longitudes within [-180, 180], every input vertex kept in order
/// with the jump around the world where the source has it. Returns the payload bytes.
fn check_across_the_antimeridian(l: &Polyline, tol: f64) -> usize {
    let a = encode(std::slice::from_ref(l), tol, false);
    let c = a.curves().unwrap();
    let src = closed(l);
    let set = &c.set;
    // Sampled every tol/4 along segments (the jumps around the world are long).
    let f = set.finest();
    for level in [0, f / 2, f - 1, f, f + 1] {
        let out = set.at_level(level);
        let o = &out.lines[0];
        assert!(
            o.iter().all(|p| (-180.0..=180.0).contains(&p[0])),
            "level {level}"
        );
        let h = curve::hausdorff(Metric::Sphere, &src, o, tol / 4.0);
        assert!(
            h <= out.error_bound * (1.0 + 1e-9),
            "level {level}: {h} over {}",
            out.error_bound
        );
    }
    let mut out = set.at_level(set.finest()).lines.swap_remove(0);
    let h = curve::hausdorff(Metric::Sphere, &src, &out, tol / 4.0);
    assert!(h <= tol * 1.001, "finest: Hausdorff {h} over {tol}");
    // Closed exactly, from the input's first vertex.
    assert_eq!(out.first(), out.last());
    assert!(Metric::Sphere.distance(out[0], src[0]) <= tol * 1.001);
    let winds = c.header.rings[0].closed != l.closed;
    if winds {
        // Around the pole: coded as an open line from a start vertex to the same vertex one
        // turn on, so the output holds that vertex twice, both within the tolerance of it.
        assert_eq!(out.len(), src.len() + 1);
        let start = c.header.rings[0]
            .start
            .expect("a winding ring stores its start") as usize;
        let (a, b) = if start == 0 {
            (out.len() - 2, out.len() - 1)
        } else {
            (start, start + 1)
        };
        let hop = Metric::Sphere.distance(out[a], out[b]);
        assert!(hop <= 2.0 * tol * 1.001, "hop of {hop} at vertex {start}");
        out.remove(if start == 0 { a } else { b });
    }
    assert_eq!(out.len(), src.len());
    for (i, (p, q)) in src.iter().zip(&out).enumerate().skip(1) {
        let jumps = |a: Pt, b: Pt| (a[0] - b[0]).abs() > 180.0;
        assert_eq!(jumps(src[i - 1], *p), jumps(out[i - 1], *q), "vertex {i}");
    }
    c.payload().len()
}

#[test]
fn rings_across_the_antimeridian_code_as_one_curve_and_keep_their_side() {
    let tol = 0.009;
    // Antarctica winds around the pole: in longitude and latitude it is no closed loop.
    let ant = &antarctica()[0];
    let bytes = check_across_the_antimeridian(ant, tol);
    // A real coast moved onto the antimeridian (Great Britain's west coast then wiggles across
    // it 14 times) codes about as small as where it was.
    let coast = &coast()[0];
    let here = check_across_the_antimeridian(coast, tol);
    let centre = coast.points.iter().map(|p| p[0]).sum::<f64>() / coast.points.len() as f64;
    let across = moved(coast, 180.0 - centre);
    let crossings = across
        .points
        .windows(2)
        .filter(|w| (w[0][0] - w[1][0]).abs() > 180.0)
        .count();
    assert!(crossings >= 2, "the moved coast crosses the antimeridian");
    let there = check_across_the_antimeridian(&across, tol);
    // Started between two crossings, the ring also crosses where it closes.
    let first = across
        .points
        .windows(2)
        .position(|w| (w[0][0] - w[1][0]).abs() > 180.0)
        .unwrap();
    let mut started = across.clone();
    started.points.rotate_left(first + 1);
    check_across_the_antimeridian(&started, tol);
    // Each crossing costs a byte of header and holds two points to their vertices.
    assert!(
        (there as f64) < here as f64 * 1.01 + 2.0 * crossings as f64,
        "{there} bytes across the antimeridian ({crossings} crossings) against {here} away from it"
    );
    // Antarctica at 1 km: better than 7.8:1 against float32 (it was 7.85:1 with the jump).
    let points = ant.points.len() + 1;
    assert!(points as f64 * 8.0 / bytes as f64 > 7.88, "{bytes} bytes");
}

#[test]
fn the_start_kept_codes_no_larger_than_the_inputs_own() {
    // One ring under the default scheme: each candidate start is coded exactly as the asset
    // will be, so the search can only help; the output still starts at the input's first
    // vertex and stays within the tolerance.
    let ant = &antarctica()[0];
    let tol = 0.009;
    let bytes = |starts: usize| {
        let s = CurveSettings {
            tolerance: tol,
            fit: false,
            starts,
            ..Default::default()
        };
        curve::encode(std::slice::from_ref(ant), &s).unwrap().0
    };
    let (own, searched) = (bytes(1), bytes(16));
    assert!(searched.payload().len() <= own.payload().len());
    let out = searched
        .set
        .at_level(searched.set.finest())
        .lines
        .swap_remove(0);
    let src = closed(ant);
    assert!(Metric::Sphere.distance(out[0], src[0]) <= tol * 1.001);
    assert!(curve::hausdorff(Metric::Sphere, &src, &out, tol / 4.0) <= tol * 1.001);
}
