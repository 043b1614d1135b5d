//! The right-triangulated irregular network's pieces (Evans et al., as Martini builds it):
//! its triangles by index on a 2^k + 1 grid, their errors, and the chords of a tile's edges.

use crate::Error;

/// The inputs of an adaptive mesh: `2^k + 1` heights a side and a finite `max_error >= 0`.
pub(super) fn check_rtin(heights: &[f32], n: usize, max_error: f32) -> Result<(), Error> {
    if n < 2 || !(n - 1).is_power_of_two() || heights.len() != n * n {
        return Err(Error::input(format!(
            "an adaptive mesh needs 2^k + 1 heights a side, got {n} ({} heights)",
            heights.len()
        )));
    }
    if !(max_error.is_finite() && max_error >= 0.0) {
        return Err(Error::input(format!(
            "max_error must be a finite number >= 0, got {max_error}"
        )));
    }
    Ok(())
}

/// The vertices an edge of `samples` keeps on its own (Douglas-Peucker: split at the sample
/// farthest from the chord while one leaves it by more than `max_error`; the ends always) and
/// the edge's heights with every other sample moved onto its chord. The farthest sample, not
/// the middle: an edge carries no dyadic constraint (the greedy TIN takes vertices anywhere),
/// and the farthest split keeps 1.5-2x fewer vertices on small tiles. Nodata is off every chord
/// and splits there first, down to single cells.
pub(super) fn edge_chords(samples: &[f32], max_error: f32) -> (Vec<bool>, Vec<f32>) {
    let last = samples.len() - 1;
    let mut kept = vec![false; samples.len()];
    let mut chords = samples.to_vec();
    (kept[0], kept[last]) = (true, true);
    let mut stack = vec![(0, last)];
    while let Some((a, b)) = stack.pop() {
        let (ha, hb) = (f64::from(samples[a]), f64::from(samples[b]));
        let chord = |k: usize| (ha * (b - k) as f64 + hb * (k - a) as f64) / (b - a) as f64;
        // The first farthest sample (NaN: nodata, infinitely far); both tiles on the edge
        // walk it in the same order and pick the same one.
        let mut far = (a, f64::from(max_error));
        for (k, &h) in samples.iter().enumerate().take(b).skip(a + 1) {
            let d = (f64::from(h) - chord(k)).abs();
            let d = if d.is_nan() { f64::INFINITY } else { d };
            if d > far.1 {
                far = (k, d);
            }
        }
        if far.0 != a {
            kept[far.0] = true;
            stack.extend([(a, far.0), (far.0, b)]);
        } else {
            for (k, c) in chords.iter_mut().enumerate().take(b).skip(a + 1) {
                *c = chord(k) as f32;
            }
        }
    }
    (kept, chords)
}

/// Corners `[ax, ay, bx, by, cx, cy]` (a, b: the long edge; c: the right angle) of triangle
/// `id` of the RTIN over a `tile x tile` grid, numbered as a binary heap: 2 and 3 are the two
/// halves of the square, and triangle k splits into 2k and 2k + 1 (Martini's numbering).
pub(super) fn rtin_triangle(mut id: usize, tile: usize) -> [usize; 6] {
    let [mut ax, mut ay, mut bx, mut by, mut cx, mut cy] = if id & 1 == 1 {
        [0, 0, tile, tile, tile, 0]
    } else {
        [tile, tile, 0, 0, 0, tile]
    };
    while {
        id >>= 1;
        id > 1
    } {
        let (mx, my) = ((ax + bx) / 2, (ay + by) / 2);
        if id & 1 == 1 {
            (bx, by, ax, ay) = (ax, ay, cx, cy);
        } else {
            (ax, ay, bx, by) = (bx, by, cx, cy);
        }
        (cx, cy) = (mx, my);
    }
    [ax, ay, bx, by, cx, cy]
}

/// The largest vertical distance between the plane through a triangle's corners and the
/// heights of the grid points it covers (infinite where one is nodata).
pub(super) fn rtin_error(heights: &[f32], n: usize, [ax, ay, bx, by, cx, cy]: [usize; 6]) -> f32 {
    let h = |x: usize, y: usize| heights[y * n + x] as f64;
    let (ha, hb, hc) = (h(ax, ay), h(bx, by), h(cx, cy));
    if !(ha.is_finite() && hb.is_finite() && hc.is_finite()) {
        return f32::INFINITY;
    }
    let [ax, ay, bx, by, cx, cy] = [ax, ay, bx, by, cx, cy].map(|v| v as i64);
    let det = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax);
    let sign = det.signum();
    // Each barycentric numerator is linear in x along a row, `alpha x + beta(y)`; the points
    // inside have all three of det's sign, an interval of x per row found exactly in integers
    // (scanning only it measured 2x faster than testing every point of the bounding box).
    let floor_div = |a: i64, b: i64| {
        let q = a / b;
        if a % b != 0 && ((a < 0) != (b < 0)) {
            q - 1
        } else {
            q
        }
    };
    let mut worst = 0.0f64;
    for y in ay.min(by).min(cy)..=ay.max(by).max(cy) {
        let (ab, bb) = (cy - ay, -ax * (cy - ay) - (y - ay) * (cx - ax));
        let (ac, bc) = (-(by - ay), (bx - ax) * (y - ay) + (by - ay) * ax);
        let (aa, ba) = (-(ab + ac), det - bb - bc);
        let (mut lo, mut hi) = (ax.min(bx).min(cx), ax.max(bx).max(cx));
        for (alpha, beta) in [(ab, bb), (ac, bc), (aa, ba)] {
            // sign * (alpha x + beta) >= 0, i.e. a x >= b.
            let (a, b) = (sign * alpha, -sign * beta);
            match a.cmp(&0) {
                std::cmp::Ordering::Greater => lo = lo.max(-floor_div(-b, a)),
                std::cmp::Ordering::Less => hi = hi.min(floor_div(b, a)),
                std::cmp::Ordering::Equal if b > 0 => hi = lo - 1,
                std::cmp::Ordering::Equal => {}
            }
        }
        for x in lo..=hi {
            let nb = (x - ax) * (cy - ay) - (y - ay) * (cx - ax);
            let nc = (bx - ax) * (y - ay) - (by - ay) * (x - ax);
            let z = ha + (nb as f64 * (hb - ha) + nc as f64 * (hc - ha)) / det as f64;
            let d = (h(x as usize, y as usize) - z).abs();
            if !d.is_finite() {
                return f32::INFINITY;
            }
            worst = worst.max(d);
        }
    }
    // Rounded up, so that the f32 comparison never lets a triangle slip over the bound.
    let w = worst as f32;
    if (w as f64) < worst { w.next_up() } else { w }
}
