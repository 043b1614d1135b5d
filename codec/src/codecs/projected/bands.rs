//! How the lifted multiresolution's coefficients are coded ([`super::lifting`]): the coarsest
//! grid by MED prediction, then the bands of every level from the coarsest, each coefficient
//! quantised with its band's step and range coded in a context of its band's orientation and
//! depth, its coded neighbours, its sibling bands at the same place and its parent (as EBCOT and
//! SPIHT use them).
//!
//! Two codes ([`Code`]): [`Code::Plain`], format 9's and before (LZMA's one-rate contexts of 11
//! bits, each sign in its magnitude's context), and [`Code::Contextual`] (format 10): two-rate
//! contexts of 15 bits (`entropy::TwoRateBit`), and each sign in a context of its band and its
//! west and north neighbours' signs. Why: at 0.2-0.5 bits a pixel most coefficients are zero,
//! and a one-rate context's zero flag costs at least 0.022 bits, a tenth of the budget at 0.2
//! bpp; the two-rate code gained 0.25-0.9 dB at the same bytes on the repository's and held-out
//! images (docs/benchmarks.md, issue 77's third session). Tried and left out, each between
//! -0.07 and +0.04 dB: the nonzero indices dequantised to their measured centroids (an offset
//! per band and class coded after each level), finer neighbour buckets, a fourth depth, the
//! parent in the neighbours' sum; the pyramid's rates (4, 7) were the best of seven pairs or
//! within 0.01 dB of it.

use crate::core::entropy::{Bit, Decoder, Encoder, Model, TwoRateBit};
use crate::core::lattice::{IntCoder, med};

use super::kernel::{Kernel, gains};
use super::pyramid::{Order, causal_neighbours};

/// Neighbour and parent buckets of a coefficient's context; three depths (finest, next, the
/// rest) and three orientations.
const NEIGHBOUR_BUCKETS: usize = 6;
const PARENT_BUCKETS: usize = 4;
const DEPTHS: usize = 3;
const BAND_CONTEXTS: usize = 3 * DEPTHS * NEIGHBOUR_BUCKETS * PARENT_BUCKETS;
/// Contexts of the coarsest grid (MED residuals by local relief).
const COARSE_CONTEXTS: usize = 4;

/// Which of a band's axes hold details: HL (x), LH (y), HH (both).
const BANDS: [[bool; 2]; 3] = [[true, false], [false, true], [true, true]];

/// How a stream codes its coefficients.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Code {
    /// Formats up to 9.
    Plain,
    /// Format 10.
    Contextual,
}

// Here rather than in `pyramid`, which this module builds on.
impl Order {
    /// How a lifted plane's coefficients are coded (the pyramid's orders name none).
    pub fn code(self) -> Code {
        if self.two_rate() {
            Code::Contextual
        } else {
            Code::Plain
        }
    }
}

/// The sides of the walk over the coefficients: the encoder quantises and codes, the decoder
/// reads; both return the quantised index of the coefficient at `at`.
pub(super) trait Indices<M> {
    /// `prediction`: the coarsest grid's MED prediction of the index (its residual is coded,
    /// the index rounded plainly); `None` for a band's detail (rate-distortion choice).
    fn index(
        &mut self,
        at: usize,
        step: f64,
        prediction: Option<i32>,
        coder: &mut IntCoder<M>,
    ) -> i32;

    /// A band's detail at `at` of step `step`: its magnitude in `coder`, its sign apart in
    /// `sign`.
    fn detail(&mut self, at: (usize, f64), coder: &mut IntCoder<M>, sign: &mut M) -> i32;
}

/// Context of the coarsest grid from the spread of its causal neighbours (quantised units).
fn coarse_context(a: i32, b: i32, c: i32) -> usize {
    match (a - b).unsigned_abs().max((a - c).unsigned_abs()) {
        0..=1 => 0,
        2..=4 => 1,
        5..=16 => 2,
        _ => 3,
    }
}

/// Bucket of a coefficient's coded neighbourhood (`2 (|W| + |N|) + |NW| + |NE|`, plus half the
/// siblings').
fn neighbour_bucket(near: u32) -> usize {
    match near {
        0 => 0,
        1..=2 => 1,
        3..=4 => 2,
        5..=8 => 3,
        9..=16 => 4,
        _ => 5,
    }
}

/// Bucket of a coefficient's parent's |index|.
fn parent_bucket(parent: u32) -> usize {
    match parent {
        0 => 0,
        1 => 1,
        2..=3 => 2,
        _ => 3,
    }
}

/// The context of a sign from its west and north neighbours' signs in the band.
fn sign_context(west: i32, north: i32) -> usize {
    (3 * (west.signum() + 1) + (north.signum() + 1)) as usize
}

/// One walk over the coefficients, coarsest first, filling `g` with the dequantised
/// coefficients: the coarse grid, then the bands of every level down to `depth + 1` (0: all of
/// them; a reader of the coarse band at `depth` stops there, the stream's rest unread).
pub(super) fn walk(
    (size, levels, depth): ([usize; 2], u32, u32),
    code: Code,
    steps: &Steps,
    g: &mut [f64],
    side: &mut (impl Indices<Bit> + Indices<TwoRateBit>),
) {
    match code {
        Code::Plain => walk_with::<Bit>((size, levels, depth), code, steps, g, side),
        Code::Contextual => walk_with::<TwoRateBit>((size, levels, depth), code, steps, g, side),
    }
}

fn walk_with<M: Model + Default + Copy>(
    (size, levels, depth): ([usize; 2], u32, u32),
    code: Code,
    steps: &Steps,
    g: &mut [f64],
    side: &mut dyn Indices<M>,
) {
    let [w, h] = size;
    let mut coarse: Vec<IntCoder<M>> = (0..COARSE_CONTEXTS).map(|_| IntCoder::fresh()).collect();
    let mut bands: Vec<IntCoder<M>> = (0..BAND_CONTEXTS).map(|_| IntCoder::fresh()).collect();
    let mut signs = [[M::default(); 9]; 3];
    let mut q = vec![0i32; w * h];
    let top = 1usize << levels;
    for y in (0..h).step_by(top) {
        for x in (0..w).step_by(top) {
            let i = y * w + x;
            let (a, b, c) = causal_neighbours(&q, w, (x, y), top);
            let coder = &mut coarse[coarse_context(a, b, c)];
            q[i] = side.index(i, steps.coarse, Some(med(a, b, c)), coder);
            g[i] = f64::from(q[i]) * steps.coarse;
        }
    }
    for j in (depth + 1..=levels).rev() {
        let s = 1usize << (j - 1);
        let stride = 2 * s;
        let depth = (j as usize - 1).min(DEPTHS - 1);
        let signed = |q: &[i32], x: isize, y: isize| -> i32 {
            if x < 0 || y < 0 || x >= w as isize || y >= h as isize {
                0
            } else {
                q[y as usize * w + x as usize]
            }
        };
        let magnitude = |q: &[i32], x: isize, y: isize| signed(q, x, y).unsigned_abs();
        for (band, axes) in BANDS.iter().enumerate() {
            let step = steps.band[j as usize - 1][band];
            let (x0, y0) = (usize::from(axes[0]) * s, usize::from(axes[1]) * s);
            for y in (y0..h).step_by(stride) {
                for x in (x0..w).step_by(stride) {
                    let i = y * w + x;
                    let (xi, yi, st) = (x as isize, y as isize, stride as isize);
                    // Every neighbour below lies within stride + s of (x, y) (above it, or
                    // beside it, or a stride below): away from the edges, read unchecked.
                    let reach = stride + s;
                    let inside = x >= reach && y >= reach && x + reach < w && y + stride < h;
                    let magnitude = |q: &[i32], x: isize, y: isize| -> u32 {
                        if inside {
                            q[y as usize * w + x as usize].unsigned_abs()
                        } else {
                            magnitude(q, x, y)
                        }
                    };
                    // The west and north neighbours, signed: their signs are the sign's context.
                    let (west, north) = if inside {
                        (q[i - stride], q[i - stride * w])
                    } else {
                        (signed(&q, xi - st, yi), signed(&q, xi, yi - st))
                    };
                    let near = 2 * (west.unsigned_abs() + north.unsigned_abs())
                        + magnitude(&q, xi - st, yi - st)
                        + magnitude(&q, xi + st, yi - st);
                    // The sibling bands already coded at this level, at the same place and
                    // around it (all of a sibling band is known, ahead of this row too).
                    let si = s as isize;
                    let around = |cx: isize, cy: isize| {
                        2 * magnitude(&q, cx, cy)
                            + magnitude(&q, cx - st, cy)
                            + magnitude(&q, cx + st, cy)
                            + magnitude(&q, cx, cy - st)
                            + magnitude(&q, cx, cy + st)
                    };
                    let sib = match band {
                        0 => 0,
                        1 => around(xi + si, yi - si),
                        _ => (around(xi, yi - si) + around(xi - si, yi)) / 2,
                    };
                    let near = near + sib / 2;
                    // The parent: the same band one level coarser, over the same place.
                    let parent = if j < levels {
                        let px = 2 * x0 + (x / stride / 2) * 2 * stride;
                        let py = 2 * y0 + (y / stride / 2) * 2 * stride;
                        magnitude(&q, px as isize, py as isize)
                    } else {
                        0
                    };
                    let context = ((band * DEPTHS + depth) * NEIGHBOUR_BUCKETS
                        + neighbour_bucket(near))
                        * PARENT_BUCKETS
                        + parent_bucket(parent);
                    let coder = &mut bands[context];
                    q[i] = match code {
                        Code::Plain => side.index(i, step, None, coder),
                        Code::Contextual => {
                            let sign = &mut signs[band][sign_context(west, north)];
                            side.detail((i, step), coder, sign)
                        }
                    };
                    g[i] = f64::from(q[i]) * step;
                }
            }
        }
    }
}

/// The quantiser steps of a transform: the coarsest grid's and, per level (finest first), each
/// band's (HL, LH, HH).
pub(super) struct Steps {
    coarse: f64,
    band: Vec<[f64; 3]>,
}

impl Steps {
    pub(super) fn new((step, levels, kernel): (f64, u32, Kernel), weights: &[i32]) -> Steps {
        if levels == 0 {
            return Steps {
                coarse: step,
                band: Vec::new(),
            };
        }
        let (gx, gy) = (
            gains(kernel, weights, 0, levels),
            gains(kernel, weights, 1, levels),
        );
        let at = |g: f64| step / g.sqrt();
        let band = (0..levels as usize)
            .map(|j| {
                [
                    at(gx[j].1 * gy[j].0),
                    at(gx[j].0 * gy[j].1),
                    at(gx[j].1 * gy[j].1),
                ]
            })
            .collect();
        let top = levels as usize - 1;
        Steps {
            coarse: at(gx[top].0 * gy[top].0),
            band,
        }
    }
}

/// The encoder's side: each band index is rounded, then moved one step nearer zero where that
/// saves more bits (at `lambda` a bit, in squared steps) than it costs in squared error, as the
/// pyramid's quantiser does.
pub(super) struct Quantiser<'a> {
    pub(super) coefficients: &'a [f64],
    pub(super) lambda: f64,
    pub(super) encoder: &'a mut Encoder,
}

impl<M: Model + Default + Copy> Indices<M> for Quantiser<'_> {
    fn index(
        &mut self,
        at: usize,
        step: f64,
        prediction: Option<i32>,
        coder: &mut IntCoder<M>,
    ) -> i32 {
        let r = self.coefficients[at] / step;
        let limit = f64::from(i32::MAX / 4);
        let q = r.round().clamp(-limit, limit) as i32;
        if let Some(p) = prediction {
            coder.put(self.encoder, q - p);
            return q;
        }
        let mut q = q;
        if self.lambda > 0.0 && q != 0 {
            let nearer = q - q.signum();
            let cost = |q: i32| (r - f64::from(q)).powi(2) + self.lambda * coder.cost(q, 0);
            if cost(nearer) < cost(q) {
                q = nearer;
            }
        }
        coder.put(self.encoder, q);
        q
    }

    fn detail(&mut self, (at, step): (usize, f64), coder: &mut IntCoder<M>, sign: &mut M) -> i32 {
        let r = self.coefficients[at] / step;
        let a = r.abs();
        let mut m = a.round().min(f64::from(i32::MAX / 4)) as i32;
        if self.lambda > 0.0 && m != 0 {
            // As `index`, the sign's bits counted where the magnitude is not zero.
            let bits = |m: i32| coder.cost(m, 0) + if m != 0 { sign.cost(r < 0.0) } else { 0.0 };
            let cost = |m: i32| (a - f64::from(m)).powi(2) + self.lambda * bits(m);
            if cost(m - 1) < cost(m) {
                m -= 1;
            }
        }
        coder.put(self.encoder, m);
        if m != 0 {
            self.encoder.bit(sign, r < 0.0);
        }
        if r < 0.0 { -m } else { m }
    }
}

/// The decoder's side.
pub(super) struct Reader<'a, 'b> {
    pub(super) decoder: &'a mut Decoder<'b>,
}

impl<M: Model + Default + Copy> Indices<M> for Reader<'_, '_> {
    fn index(
        &mut self,
        _at: usize,
        _step: f64,
        prediction: Option<i32>,
        coder: &mut IntCoder<M>,
    ) -> i32 {
        let v = coder.get(self.decoder);
        v.saturating_add(prediction.unwrap_or(0))
    }

    fn detail(&mut self, _: (usize, f64), coder: &mut IntCoder<M>, sign: &mut M) -> i32 {
        // A magnitude is never coded negative; a corrupt stream's is read as zero.
        let m = coder.get(self.decoder).max(0);
        if m != 0 && self.decoder.bit(sign) {
            -m
        } else {
            m
        }
    }
}
