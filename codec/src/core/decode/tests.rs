//! Tests of the decoders on a toy operator, without a codec.

use super::*;
use crate::core::operator::{Operator, Step, invariant_interval};

/// Area means: whole blocks where the sizes divide, weighed parts where they do not (each
/// new cell's mean of the box it covers, on a grid that is x + 10 y, whose box means are
/// the box centre's value), and NaN cells left out.
#[test]
fn area_means_are_the_means_of_the_boxes_covered() {
    let plane = |w: usize, h: usize| Grid {
        width: w,
        height: h,
        values: (0..w * h)
            .map(|k| (k % w) as f32 + 10.0 * (k / w) as f32)
            .collect(),
    };
    // The grid is separable and linear in the cell index, so a box's mean is the mean
    // index covered along x plus ten times along y, each cell weighed by its overlap.
    let mean_index = |i: usize, n: usize, m: usize| {
        let (a, b) = (
            i as f64 * n as f64 / m as f64,
            (i + 1) as f64 * n as f64 / m as f64,
        );
        let (mut sum, mut weight) = (0.0, 0.0);
        for k in 0..n {
            let o = (b.min(k as f64 + 1.0) - a.max(k as f64)).max(0.0);
            sum += o * k as f64;
            weight += o;
        }
        sum / weight
    };
    for (w, h, nw, nh) in [(8, 6, 4, 3), (7, 5, 3, 2), (9, 9, 4, 4), (5, 3, 5, 1)] {
        let got = plane(w, h).area_means(nw, nh);
        for (k, v) in got.values.iter().enumerate() {
            let want = (mean_index(k % nw, w, nw) + 10.0 * mean_index(k / nw, h, nh)) as f32;
            if w % nw == 0 && h % nh == 0 {
                // Whole blocks: the block's centre.
                let (fx, fy) = ((w / nw) as f32, (h / nh) as f32);
                let (i, j) = ((k % nw) as f32, (k / nw) as f32);
                let centre = (i + 0.5) * fx - 0.5 + 10.0 * ((j + 0.5) * fy - 0.5);
                assert!((want - centre).abs() < 1e-4);
            }
            assert!(
                (v - want).abs() < 1e-4,
                "{w}x{h} -> {nw}x{nh} at {k}: {v} {want}"
            );
        }
    }
    let mut g = plane(4, 2);
    g.values[0] = f32::NAN;
    g.values[2] = f32::NAN;
    g.values[3] = f32::NAN;
    g.values[7] = f32::NAN;
    let got = g.area_means(2, 1);
    // Left box: 1, 10 and 11 remain; right box: 12 alone.
    assert_eq!(got.values[0], (1.0 + 10.0 + 11.0) / 3.0);
    assert_eq!(got.values[1], 12.0);
    let none = Grid {
        width: 2,
        height: 1,
        values: vec![f32::NAN; 2],
    };
    assert!(none.area_means(1, 1).values[0].is_nan());
}

#[test]
fn volume_axes_hold_the_corners_and_even_steps_between() {
    let [xs, ys, zs] = volume_axes([0.1, 0.25, 0.3], [0.7, 0.75, 0.3], [7, 5, 1]);
    assert_eq!((xs[0], xs[6]), (0.1, 0.7));
    assert_eq!(ys, [0.25, 0.375, 0.5, 0.625, 0.75]);
    // One sample: the middle of the span.
    assert_eq!(zs, [0.3]);
    // Evenly spaced to f32 rounding: 0.1 + k * 0.1 for k = 0..6.
    for (k, x) in xs.iter().enumerate() {
        assert!((x - (0.1 + 0.1 * k as f32)).abs() <= 1e-7, "{k}: {x}");
    }
}

#[test]
fn shrink_averages_blocks_and_keeps_nodata() {
    // 4 x 2 -> 2 x 1: blocks {1, 2, 5, 6} and {3, NaN, 7, NaN}.
    let g = Grid {
        width: 4,
        height: 2,
        values: vec![1.0, 2.0, 3.0, f32::NAN, 5.0, 6.0, 7.0, f32::NAN],
    };
    let c = g.shrink(2, 2).unwrap();
    assert_eq!((c.width, c.height), (2, 1));
    assert_eq!(c.values, vec![3.5, 5.0]);
    // Rows only, and a block of nodata alone.
    let r = Grid {
        width: 1,
        height: 4,
        values: vec![f32::NAN, f32::NAN, 2.0, 4.0],
    }
    .shrink(1, 2)
    .unwrap();
    assert!(r.values[0].is_nan() && r.values[1] == 3.0);
    assert!(g.shrink(3, 1).is_none() && g.shrink(0, 1).is_none());
}

/// Four cells of 4 on an 8x8 frame, each mapping its quadrant onto the whole frame (a flip
/// for some), with constant contrast and offset: decoders are tested on the operator form
/// alone, without a codec.
struct Toy;

/// (contrast, offset, flip x, flip y) of the cells, row-major.
const CELLS: [(f32, f32, bool, bool); 4] = [
    (0.5, 0.1, false, false),
    (-0.5, 0.7, true, false),
    (0.25, 0.3, true, true),
    (0.0, 0.9, false, false),
];

impl Operator<2> for Toy {
    fn frame(&self) -> [f32; 2] {
        [8.0, 8.0]
    }
    fn valid(&self) -> [f32; 2] {
        [8.0, 8.0]
    }
    fn expansion(&self) -> u32 {
        2
    }
    fn step(&self, p: [f32; 2]) -> Step<2> {
        let p = p.map(|t| t.clamp(0.0, 8.0));
        let (cx, cy) = (usize::from(p[0] >= 4.0), usize::from(p[1] >= 4.0));
        let (contrast, offset, fx, fy) = CELLS[cy * 2 + cx];
        let local = |t: f32, c: usize, flip: bool| {
            let u = ((t - 4.0 * c as f32) / 4.0).clamp(0.0, 1.0);
            8.0 * if flip { 1.0 - u } else { u }
        };
        Step {
            offset,
            contrast,
            next: [local(p[0], cx, fx), local(p[1], cy, fy)],
        }
    }
    fn invariant_interval(&self) -> (f32, f32) {
        invariant_interval(CELLS.iter().map(|&(s, o, _, _)| (s, o, o)))
    }
}

fn toy() -> Toy {
    Toy
}

#[test]
fn point_values_satisfy_the_fixed_point_equation() {
    // f(p) = o + s f(phi(p)) must hold for the decoded values, up to the bounds.
    let op = toy();
    for &(u, v) in &[(0.1f32, 0.2f32), (0.7, 0.1), (0.3, 0.9), (0.55, 0.45)] {
        let a = point(&op, [u, v], 40);
        let st = op.step([u * 8.0, v * 8.0]);
        let b = point(&op, [st.next[0] / 8.0, st.next[1] / 8.0], 40);
        let rhs = st.offset + st.contrast * b.value;
        assert!(
            (a.value - rhs).abs() <= a.error_bound + b.error_bound + 1e-5,
            "{a:?} vs {rhs}"
        );
    }
}

#[test]
fn bound_holds_and_shrinks() {
    let op = toy();
    let mut last = f32::INFINITY;
    for n in 1..20 {
        let r = point(&op, [0.2, 0.3], n);
        let reference = point(&op, [0.2, 0.3], 200);
        assert!((r.value - reference.value).abs() <= r.error_bound + 1e-6);
        assert!(r.error_bound <= last);
        last = r.error_bound;
    }
}

#[test]
fn constant_map_is_exact_in_one_step() {
    let r = point(&toy(), [0.9, 0.9], 10);
    assert_eq!(r.iterations, 1);
    assert_eq!(r.error_bound, 0.0);
    assert!((r.value - 0.9).abs() < 1e-6);
}

#[test]
fn discrete_decoding_at_any_size_converges_to_the_same_picture() {
    let op = toy();
    let (a, ra) = discrete(&op, 8, 8, DiscreteOptions::fixed(60));
    assert!(ra.last_change < 1e-5);
    // Each output pixel must satisfy the discrete fixed-point equation exactly at size 8.
    let (b, _) = discrete(&op, 32, 32, DiscreteOptions::fixed(60));
    let (c, _) = discrete(&op, 5, 13, DiscreteOptions::fixed(60));
    // Means over quadrants agree across sizes (same attractor, other sampling).
    let mean = |g: &Grid| g.values.iter().sum::<f32>() / g.values.len() as f32;
    assert!(
        (mean(&a) - mean(&b)).abs() < 0.02,
        "{} {}",
        mean(&a),
        mean(&b)
    );
    assert!(
        (mean(&a) - mean(&c)).abs() < 0.05,
        "{} {}",
        mean(&a),
        mean(&c)
    );
    // The constant range decodes to its offset everywhere.
    assert!((b.values[31 * 32 + 31] - 0.9).abs() < 1e-6);
}

#[test]
fn batched_points_equal_single_points() {
    let op = toy();
    let pts: Vec<[f32; 2]> = (0..37)
        .map(|i| [(i as f32 * 0.37) % 1.0, (i as f32 * 0.61) % 1.0])
        .collect();
    let batch = points(&op, &pts, 15, 0.0);
    for (p, b) in pts.iter().zip(&batch) {
        let single = point(&op, *p, 15);
        assert!(
            (single.value - b.value).abs() < 1e-6 && single.iterations == b.iterations,
            "{single:?} {b:?}"
        );
    }
}
