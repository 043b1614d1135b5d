//! Tests of the curve stream: round trips, bounds, the compact header.

use super::*;
use crate::codecs::curve::model::SeamCrossing;
use proptest::prelude::*;

#[test]
fn coverage_finds_the_farthest_point_between_vertices() {
    // Every vertex of `from` lies on `to`; its midpoint (5, 0) is 3/√10 from `to`'s peak.
    let from = [[0.0, 0.0], [10.0, 0.0]];
    let to = [[-1.0, 0.0], [4.0, 0.0], [5.0, 3.0], [6.0, 0.0], [11.0, 0.0]];
    let far = 3.0 / 10f64.sqrt();
    // (A limit touched exactly is refused: halving cannot prove a maximum to zero margin.)
    assert!(covered(Metric::Plane, &from, &to, far + 1e-4));
    assert!(!covered(Metric::Plane, &from, &to, far - 1e-4));
    // The other way round the peak itself is the farthest point: 3 from `from`.
    assert!(!within(Metric::Plane, &from, &to, 3.0 - 1e-4));
    assert!(within(Metric::Plane, &from, &to, 3.0 + 1e-4));
}

#[test]
fn strays_marks_the_points_around_a_decoded_point_off_the_source() {
    let scheme = Scheme::default();
    let fine: Vec<Pt> = (0..64)
        .map(|i| {
            let t = i as f64 / 64.0 * std::f64::consts::TAU;
            [10.0 * t.cos(), 10.0 * t.sin()]
        })
        .collect();
    let src = Prepared {
        closed: true,
        pieces: 2,
        fine: fine.clone(),
        inserted: Vec::new(),
    };
    let ring = Ring::from_fine(&scheme, &fine, true, 2, Vec::new());
    assert!(strays(&scheme, Metric::Plane, 0.01, &ring, &src).is_empty());
    // Push fine point 21 (a finest-level detail) 0.5 outwards.
    let mut moved = fine.clone();
    moved[21] = [moved[21][0] * 1.05, moved[21][1] * 1.05];
    let ring = Ring::from_fine(&scheme, &moved, true, 2, Vec::new());
    let marks = strays(&scheme, Metric::Plane, 0.01, &ring, &src);
    assert!(marks.contains(&20) && marks.contains(&21) && marks.contains(&22));
    assert!(marks.iter().all(|&k| (17..=25).contains(&k)), "{marks:?}");
}

proptest! {
    #[test]
    fn the_coarse_lattice_point_nearest_a_target_is_within_the_tolerance(
        pred in (-170.0..170.0f64, -80.0..80.0f64),
        off in (-0.5..0.5f64, -0.5..0.5f64),
        far in (-20.0..20.0f64, -5.0..5.0f64),
        tol in 0.001..0.05f64,
    ) {
        for metric in [Metric::Plane, Metric::Sphere] {
            let q = Quantiser::new(metric, tol);
            let pred = [pred.0, pred.1];
            // Base points may be a continent from their prediction: the square lattice
            // covers exactly. Detail points are within half a degree: the hexagonal
            // lattice covers exactly in the plane, and within 1% on the sphere, where rows
            // laid out at their own latitude's scale slide against each other.
            let cases = [
                (None, [pred[0] + far.0, pred[1] + far.1], 1e-9),
                (Some(HEXAGONAL_FROM), [pred[0] + off.0, pred[1] + off.1], if metric == Metric::Plane { 1e-9 } else { 0.01 }),
            ];
            for (ctx, target, slack) in cases {
                let lattice = q.lattice(ctx);
                let (b, a) = q.nearest(lattice, pred, target);
                // In the row's plane (its latitude's longitude scale).
                let dist = |b: i64, a: i64| {
                    let p = q.at(lattice, pred, b, a);
                    let sx = metric.x_scale(p[1]);
                    ((p[0] - target[0]) * sx).hypot(p[1] - target[1])
                };
                let d = dist(b, a);
                prop_assert!(d <= tol * (1.0 + slack), "{:?}: {} > {}", ctx, d, tol);
                // And no lattice point of the neighbouring rows and columns is nearer.
                for bb in b - 1..=b + 1 {
                    for aa in a - 1..=a + 1 {
                        prop_assert!(dist(bb, aa) >= d - tol * 1e-3);
                    }
                }
            }
        }
    }

    #[test]
    fn headers_round_trip_with_bounds_rounded_up(
        custom in any::<bool>(),
        sphere in any::<bool>(),
        tol in prop_oneof![Just(0.0), 1e-6..1.0f64],
        rings in proptest::collection::vec((any::<bool>(), 1u32..100_000, 0u8..=24, 0u32..1000,
            proptest::collection::vec((1u32..5000, -3i32..=3), 0..4)), 1..6),
        factor in 1.0..1e6f64,
        stream in proptest::collection::vec(any::<u8>(), 0..8),
    ) {
        let mut scheme = Scheme::default();
        if custom {
            scheme.t[0] = [0.3, 0.8, -0.1];
            scheme.u[1][0] = [0.25, -0.5];
        }
        let tolerance = compact::tolerance_down(tol);
        // Never looser than asked, and at most one f32 step (2^-23) tighter.
        prop_assert!(tolerance <= tol && tolerance >= tol * (1.0 - 2.4e-7));
        let finest_bound = if tol > 0.0 { tolerance * factor } else { factor * 1e-3 };
        let h = CurveHeader {
            scheme,
            metric: if sphere { Metric::Sphere } else { Metric::Plane },
            tolerance,
            rings: rings
                .iter()
                .map(|(closed, pieces, levels, inserted, seam)| {
                    // Ascending indices, non-zero turns (what the encoder writes).
                    let mut at = 0;
                    let seam = seam
                        .iter()
                        .map(|&(gap, t)| {
                            at += gap;
                            SeamCrossing { at, turns: if t == 0 { 1 } else { t } }
                        })
                        .collect();
                    let start = (pieces % 3 == 0).then_some(*inserted);
                    RingHeader { closed: *closed, pieces: *pieces, levels: *levels, inserted: *inserted, seam, start }
                })
                .collect(),
            finest_bound,
        };
        let bytes = compact::write(&h);
        let mut payload = bytes.clone();
        payload.extend_from_slice(&stream);
        let (back, rest) = compact::read(&payload).unwrap();
        // The header delimits itself: what follows is the stream, untouched.
        prop_assert_eq!(rest, &stream[..]);
        prop_assert_eq!(&back.scheme, &h.scheme);
        prop_assert_eq!(back.metric, h.metric);
        prop_assert_eq!(back.tolerance.to_bits(), h.tolerance.to_bits());
        prop_assert_eq!(&back.rings, &h.rings);
        // Still a bound, and at most one 2^(1/256) step (or one f32 ulp) looser.
        prop_assert!(back.finest_bound >= finest_bound && back.finest_bound <= finest_bound * 1.003,
            "{} {}", back.finest_bound, finest_bound);
        // A stored bound is a fixed point: writing it again changes nothing.
        prop_assert_eq!(compact::write(&back), bytes.clone());
        for cut in 0..bytes.len() {
            prop_assert!(compact::read(&bytes[..cut]).is_err());
        }
    }

    #[test]
    fn the_chord_lattice_point_nearest_a_target_is_within_the_tolerance(
        pred in (-170.0..170.0f64, -80.0..80.0f64),
        prev in (-1.0..1.0f64, -1.0..1.0f64),
        next in (-1.0..1.0f64, -1.0..1.0f64),
        off in (-0.2..0.2f64, -0.2..0.2f64),
        tol in 0.001..0.05f64,
    ) {
        let q = Quantiser::new(Metric::Sphere, tol);
        let pred = [pred.0, pred.1];
        let chord = Chord::new(
            &q,
            pred,
            [pred[0] + prev.0, pred[1] + prev.1],
            [pred[0] + next.0, pred[1] + next.1],
        );
        let target = [pred[0] + off.0, pred[1] + off.1];
        let (qn, qt) = chord.nearest(target);
        let p = chord.at(qn, qt);
        // In the lattice's plane (the prediction's): the lattice's covering radius.
        let (dx, dy) = ((p[0] - target[0]) * chord.sx, p[1] - target[1]);
        prop_assert!((dx * dx + dy * dy).sqrt() <= tol * (1.0 + 1e-9));
    }
}
