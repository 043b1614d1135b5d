//! A polyline prepared for coding ([`prepare`]): longitudes unwrapped, and its points ordered
//! by the level at which the scheme's subdivision inserts them.

use crate::codecs::curve::distance::Pt;
use crate::codecs::curve::model::*;

/// Points the encoder needs: the fine polygon of an input polyline, with the number of base
/// pieces and the indices of inserted points.
#[derive(Clone, Debug, PartialEq)]
pub struct Prepared {
    /// Closed ring or open polyline.
    pub closed: bool,
    /// Base pieces `K`.
    pub pieces: usize,
    /// `K·2^(L+1)` (+1 open) points: the input vertices in order, with points inserted on the
    /// input's own segments.
    pub fine: Vec<Pt>,
    /// Indices of the inserted points in `fine`, ascending.
    pub inserted: Vec<u32>,
}

/// Most levels a ring may have (2^25 points per base piece is far beyond any polyline).
pub const MAX_LEVELS: usize = 24;

/// Cuts a polyline into base pieces and inserts points on its longest segments until the
/// count fits `K·2^(L+1)`. Input vertices are never moved or dropped. `points` of a ring need
/// not repeat the first point at the end (a repeated one is removed).
pub fn prepare(points: &[Pt], closed: bool) -> Result<Prepared, crate::Error> {
    if let Some(p) = points
        .iter()
        .find(|p| !p[0].is_finite() || !p[1].is_finite())
    {
        return Err(crate::Error::input(format!(
            "a vertex is not finite: {p:?}"
        )));
    }
    let mut pts = points.to_vec();
    if closed && pts.len() > 1 && pts.first() == pts.last() {
        pts.pop();
    }
    let min = if closed { 3 } else { 2 };
    if pts.len() < min {
        return Err(crate::Error::input(format!(
            "a {} needs at least {min} vertices, this one has {}",
            if closed { "ring" } else { "polyline" },
            pts.len()
        )));
    }
    // Segments to fill: n for a ring, n - 1 for an open polyline. Pick the levels L and pieces K
    // with K·2^(L+1) >= segments that cost least: an inserted point costs about one coded
    // point (~1 byte), a base piece about two coarsely coded points (~8 bytes).
    let segments = if closed { pts.len() } else { pts.len() - 1 };
    let mut best = (f64::INFINITY, 0, 1);
    for levels in 0..=MAX_LEVELS {
        let per = 2usize << levels;
        let pieces = segments.div_ceil(per).max(if closed { 2 } else { 1 });
        let inserted = pieces * per - segments;
        let cost = inserted as f64 + 8.0 * pieces as f64;
        if cost < best.0 {
            best = (cost, levels, pieces);
        }
        if per > segments {
            break;
        }
    }
    let (_, levels, pieces) = best;
    let extra = pieces * (2 << levels) - segments;
    // Split the longest segments: each input segment s gets k_s extra points, evenly spaced
    // on it, chosen greedily by the length of its sub-segments (a heap of segments).
    let seg_len = |i: usize| {
        let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
    };
    let mut splits = vec![0usize; segments];
    let mut heap: std::collections::BinaryHeap<(OrdF64, usize)> =
        (0..segments).map(|i| (OrdF64(seg_len(i)), i)).collect();
    for _ in 0..extra {
        let (_, i) = heap.pop().expect("segments is non-empty");
        splits[i] += 1;
        heap.push((OrdF64(seg_len(i) / (splits[i] + 1) as f64), i));
    }
    let mut fine = Vec::with_capacity(pieces * (2 << levels) + 1);
    let mut inserted = Vec::with_capacity(extra);
    for (i, &k) in splits.iter().enumerate() {
        let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
        fine.push(a);
        for j in 1..=k {
            let t = j as f64 / (k + 1) as f64;
            inserted.push(fine.len() as u32);
            fine.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
        }
    }
    if !closed {
        fine.push(*pts.last().expect("non-empty"));
    }
    Ok(Prepared {
        closed,
        pieces,
        fine,
        inserted,
    })
}

/// The seam of input vertex indices as fine indices of `p` (inserted points shift them).
pub(super) fn seam_to_fine(seam: &[SeamCrossing], p: &Prepared) -> Vec<SeamCrossing> {
    seam.iter()
        .map(|c| SeamCrossing {
            at: fine_index(&p.inserted, c.at as usize) as u32,
            turns: c.turns,
        })
        .collect()
}

/// Total order on lengths for the heap (lengths are finite: vertices were checked).
#[derive(Clone, Copy)]
struct OrdF64(f64);
impl PartialEq for OrdF64 {
    fn eq(&self, o: &Self) -> bool {
        self.cmp(o).is_eq()
    }
}
impl Eq for OrdF64 {}
impl PartialOrd for OrdF64 {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for OrdF64 {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&o.0)
    }
}
