//! Grids of values on a lattice of nodes, as the lattice codecs (fractal interpolation
//! surfaces, psa2d) and the projected codec's pyramid code them: an adaptive integer code on the
//! range coder, MED prediction over a grid, the lattice's frame and cells, and the normalised
//! source grid the fits read.

use super::format::FormatError;
use crate::core::entropy::{Bit, Decoder, Encoder, Model};

/// Adaptive Elias-gamma-like code of a signed integer on the binary range coder: a zero flag, a
/// sign, the magnitude's bit length in unary, then its lower bits. Each unary position and each
/// mantissa position has its own context, so the code learns the residuals' distribution.
pub(crate) struct IntCoder<M = Bit> {
    zero: M,
    sign: [M; 3],
    unary: [M; 32],
    mantissa: [M; 32],
}

impl IntCoder {
    pub(crate) fn new() -> IntCoder {
        IntCoder::fresh()
    }
}

impl<M: Model + Default + Copy> IntCoder<M> {
    /// A coder whose contexts have learnt nothing.
    pub(crate) fn fresh() -> IntCoder<M> {
        IntCoder {
            zero: M::default(),
            sign: [M::default(); 3],
            unary: [M::default(); 32],
            mantissa: [M::default(); 32],
        }
    }

    pub(crate) fn put(&mut self, enc: &mut Encoder, v: i32) {
        self.put_signed(enc, v, 0)
    }

    /// [`IntCoder::put`] with the sign in context `sign` (0 to 2; `put` codes it in 0).
    pub(crate) fn put_signed(&mut self, enc: &mut Encoder, v: i32, sign: usize) {
        enc.bit(&mut self.zero, v == 0);
        if v == 0 {
            return;
        }
        enc.bit(&mut self.sign[sign], v < 0);
        let m = v.unsigned_abs();
        let len = 32 - m.leading_zeros(); // 1..=32; the top bit is implied
        for k in 1..len {
            enc.bit(&mut self.unary[k as usize], true);
        }
        if len < 32 {
            enc.bit(&mut self.unary[len as usize], false);
        }
        for k in (0..len - 1).rev() {
            enc.bit(&mut self.mantissa[k as usize], m >> k & 1 == 1);
        }
    }

    /// What [`IntCoder::put_signed`] of `v` in sign context `sign` would cost now, in bits
    /// (for rate-distortion choices).
    pub(crate) fn cost(&self, v: i32, sign: usize) -> f64 {
        let mut bits = self.zero.cost(v == 0);
        if v == 0 {
            return bits;
        }
        bits += self.sign[sign].cost(v < 0);
        let m = v.unsigned_abs();
        let len = 32 - m.leading_zeros();
        for k in 1..len {
            bits += self.unary[k as usize].cost(true);
        }
        if len < 32 {
            bits += self.unary[len as usize].cost(false);
        }
        for k in (0..len - 1).rev() {
            bits += self.mantissa[k as usize].cost(m >> k & 1 == 1);
        }
        bits
    }

    pub(crate) fn get(&mut self, dec: &mut Decoder) -> i32 {
        self.get_signed(dec, 0)
    }

    /// Reads what [`IntCoder::put_signed`] wrote.
    pub(crate) fn get_signed(&mut self, dec: &mut Decoder, sign: usize) -> i32 {
        if dec.bit(&mut self.zero) {
            return 0;
        }
        let negative = dec.bit(&mut self.sign[sign]);
        let mut len = 1u32;
        while len < 32 && dec.bit(&mut self.unary[len as usize]) {
            len += 1;
        }
        let mut m = 1u32;
        for k in (0..len - 1).rev() {
            m = m << 1 | u32::from(dec.bit(&mut self.mantissa[k as usize]));
        }
        let m = m.min(i32::MAX as u32) as i32;
        if negative { -m } else { m }
    }
}

/// LOCO-I's median edge detector: the prediction of a node from its left, upper and upper-left
/// neighbours (the best simple predictor for terrain-like grids). Integer heights here, decoded
/// samples in the projected codec's control grid.
pub(crate) fn med<T>(a: T, b: T, c: T) -> T
where
    T: Copy + PartialOrd + std::ops::Add<Output = T> + std::ops::Sub<Output = T>,
{
    let (lo, hi) = if a < b { (a, b) } else { (b, a) };
    if c >= hi {
        lo
    } else if c <= lo {
        hi
    } else {
        a + b - c
    }
}

pub(crate) fn predict(v: &[i32], nx: usize, i: usize, j: usize) -> i32 {
    match (i, j) {
        (0, 0) => 0,
        (_, 0) => v[i - 1],
        (0, _) => v[(j - 1) * nx],
        _ => med(
            v[j * nx + i - 1],
            v[(j - 1) * nx + i],
            v[(j - 1) * nx + i - 1],
        ),
    }
}

/// Codes a row-major grid of integers by MED prediction, with its own adaptive contexts.
pub(crate) fn put_grid(enc: &mut Encoder, values: &[i32], nx: usize) {
    let mut c = IntCoder::new();
    for j in 0..values.len() / nx.max(1) {
        for i in 0..nx {
            c.put(enc, values[j * nx + i] - predict(values, nx, i, j));
        }
    }
}

/// Reads an `nx x ny` grid written by [`put_grid`]; a value outside `range` is an error naming
/// `what` (a corrupt stream must not build an operator).
pub(crate) fn get_grid(
    dec: &mut Decoder,
    [nx, ny]: [usize; 2],
    range: std::ops::RangeInclusive<i64>,
    what: &str,
) -> Result<Vec<i32>, FormatError> {
    // A value codes at least one decision: a grid larger than the stream can hold is refused
    // before it is allocated, and a short stream stops at the row where it ran out.
    if (nx as u64) * (ny as u64) > crate::core::entropy::most_decisions(dec.stream_len()) {
        return Err(FormatError::stream(format!(
            "a grid of {nx}x{ny} {what}s needs more than its stream's {} bytes",
            dec.stream_len()
        )));
    }
    let mut c = IntCoder::new();
    let mut values = vec![0i32; nx * ny];
    for j in 0..ny {
        for i in 0..nx {
            let v = predict(&values, nx, i, j) as i64 + c.get(dec) as i64;
            if !range.contains(&v) {
                return Err(FormatError::stream(format!("{what} {v} out of range")));
            }
            values[j * nx + i] = v as i32;
        }
        if dec.overrun() {
            return Err(FormatError::stream(format!(
                "the stream ends inside the {what}s"
            )));
        }
    }
    Ok(values)
}

/// Largest height index a step allows (values are normalised to 0..1).
pub(crate) fn top_index(height_step: f32) -> i64 {
    (1.0 / height_step).ceil() as i64 + 1
}

/// Frame of a lattice of `n` vertices `spacing` samples apart.
pub(crate) fn lattice_frame(n: [usize; 2], spacing: f32) -> [f32; 2] {
    [
        (n[0] - 1) as f32 * spacing + 1.0,
        (n[1] - 1) as f32 * spacing + 1.0,
    ]
}

/// The cell of a lattice holding sample point `t` (clamped into the lattice) and the local
/// coordinates in it.
pub(crate) fn lattice_locate(n: [usize; 2], spacing: f32, t: [f32; 2]) -> (usize, usize, f32, f32) {
    let cell = |t: f32, n: usize| -> (usize, f32) {
        let t = t.clamp(0.0, (n - 1) as f32 * spacing) / spacing;
        let c = (t as usize).min(n - 2);
        (c, t - c as f32)
    };
    let (ci, u) = cell(t[0], n[0]);
    let (cj, v) = cell(t[1], n[1]);
    (ci, cj, u, v)
}

/// A normalised source grid (values in 0..1, nodata already filled).
pub(crate) struct Source<'a> {
    /// Width in samples.
    pub width: usize,
    /// Height in samples.
    pub height: usize,
    /// Row-major values.
    pub values: &'a [f32],
}

impl Source<'_> {
    pub(crate) fn at(&self, x: usize, y: usize) -> f32 {
        self.values[y.min(self.height - 1) * self.width + x.min(self.width - 1)]
    }

    /// Bilinear value at a real sample position (edge-extended).
    pub(crate) fn bilinear(&self, x: f32, y: f32) -> f32 {
        let x = x.clamp(0.0, (self.width - 1) as f32);
        let y = y.clamp(0.0, (self.height - 1) as f32);
        let (x0, y0) = (x as usize, y as usize);
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let top = self.at(x0, y0) * (1.0 - fx) + self.at(x0 + 1, y0) * fx;
        let bottom = self.at(x0, y0 + 1) * (1.0 - fx) + self.at(x0 + 1, y0 + 1) * fx;
        top * (1.0 - fy) + bottom * fy
    }
}

/// RMS error of plain bilinear interpolation between nodes `spacing` apart (normalised units):
/// what the surface must improve on, and the scale the node heights need no finer step than.
pub(crate) fn interpolation_rmse(source: &Source, spacing: u32) -> f32 {
    let k = spacing.max(1) as usize;
    let (mut sum, mut n) = (0.0f64, 0usize);
    for y in 0..source.height {
        for x in 0..source.width {
            let (cx, cy) = (x / k * k, y / k * k);
            let (u, v) = ((x - cx) as f32 / k as f32, (y - cy) as f32 / k as f32);
            let b = source.at(cx, cy) * (1.0 - u) * (1.0 - v)
                + source.at(cx + k, cy) * u * (1.0 - v)
                + source.at(cx, cy + k) * (1.0 - u) * v
                + source.at(cx + k, cy + k) * u * v;
            let d = (b - source.at(x, y)) as f64;
            sum += d * d;
            n += 1;
        }
    }
    (sum / n.max(1) as f64).sqrt() as f32
}
