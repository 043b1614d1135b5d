//! Each cell's residual bound coded in a byte: what a lazily built operator keeps of its
//! bounds (see `records` for why it is built lazily).

/// Every cell's residual bound (see `ProjectedOperator::lazy`) in a byte: code k stands for
/// `largest 2^(-k/8)`, each bound rounded up to the next code (at most 9% over it; bounds
/// under 2^-32 of the largest read as that).
#[derive(Clone, Debug)]
pub(super) struct ResidualCodes {
    /// The bound of each code.
    table: Box<[f32; 256]>,
    /// Row-major, a code a cell.
    codes: Vec<u8>,
}

impl ResidualCodes {
    /// Codes of the `n` bounds `bound(k)`, evaluated twice each (once for the largest) rather
    /// than held: a chunk's operator is built with little besides its samples.
    pub(super) fn new(n: usize, bound: impl Fn(usize) -> f32 + Sync) -> ResidualCodes {
        use rayon::prelude::*;
        let largest = (0..n)
            .into_par_iter()
            .map(&bound)
            .reduce(|| 0.0f32, f32::max);
        let table: Box<[f32; 256]> = Box::new(std::array::from_fn(|k| {
            largest * (-(k as f32) / 8.0).exp2()
        }));
        let codes = (0..n)
            .into_par_iter()
            .map(|i| {
                let r = bound(i);
                let k = (-8.0 * (r / largest).log2()).floor().clamp(0.0, 255.0) as usize;
                // exp2 rounds: step back until the code's bound covers r (a NaN covers nothing
                // and takes code 0, the largest, itself NaN then).
                let mut k = if r.is_nan() { 0 } else { k };
                while k > 0 && table[k] < r {
                    k -= 1;
                }
                k as u8
            })
            .collect();
        ResidualCodes { table, codes }
    }

    /// The bound of cell `k` (row-major).
    #[inline(always)]
    pub(super) fn at(&self, k: usize) -> f32 {
        self.table[usize::from(self.codes[k])]
    }

    /// Bytes held.
    pub(super) fn bytes(&self) -> usize {
        self.codes.len() + 4 * 256
    }

    /// The largest bound.
    pub(super) fn max(&self) -> f32 {
        self.table[0]
    }
}

/// Rows of cells a task of the whole-grid passes takes (records, or their excesses).
pub(super) const BAND: usize = 32;
