//! The residual bounds of a lazily built operator: coded in a byte a cell, and made a block of
//! cells at a time, the first time a request reads the block (see `records` for why the
//! operator is built lazily).
//!
//! Why blocks made on first use: making every cell's bound when a chunk is decoded was 45% of
//! the first tile that reads the chunk (a browser reading a chunk for one tile pays it whole),
//! and making them for each request instead took warm tiles 1.5 to 2.3 times as long (a
//! server's tiles are mostly warm). Blocks pay each bound once, for the cells that are read.

use std::sync::{LazyLock, OnceLock};

/// What makes a block's bounds: the exact bounds of the cells `[i0, i1) x [j0, j1)`,
/// row-major (the operator's; this module knows nothing else of it).
pub(super) type Make<'a> = &'a (dyn Fn([usize; 4]) -> Vec<f32> + Sync);

/// Cells along each side of a block.
const SIDE: usize = 64;

/// `2^(-k/8)`: code k of a block stands for its largest bound times this.
static SCALE: LazyLock<[f32; 256]> =
    LazyLock::new(|| std::array::from_fn(|k| (-(k as f32) / 8.0).exp2()));

/// Every cell's residual bound of a lazily built operator, in blocks made on first use.
#[derive(Debug)]
pub(super) struct LazyBounds {
    /// Cells along each axis.
    cells: [usize; 2],
    /// Blocks along x.
    across: usize,
    /// Row-major, a slot a block.
    blocks: Box<[OnceLock<Block>]>,
}

/// A block's bounds: code k of a cell stands for `largest 2^(-k/8)`, each bound rounded up to
/// the next code (at most 9% over it; bounds under 2^-32 of the largest read as that).
#[derive(Debug)]
struct Block {
    largest: f32,
    /// Row-major over the block's cells.
    codes: Box<[u8]>,
}

impl LazyBounds {
    /// The empty blocks over `cells` cells.
    pub(super) fn new(cells: [usize; 2]) -> LazyBounds {
        let across = cells[0].div_ceil(SIDE);
        let n = across * cells[1].div_ceil(SIDE);
        LazyBounds {
            cells,
            across,
            blocks: (0..n).map(|_| OnceLock::new()).collect(),
        }
    }

    /// Bytes the bounds hold once every block is made (a cache weighs the operator by them
    /// from the start).
    pub(super) fn bytes(&self) -> usize {
        self.cells[0] * self.cells[1] + 8 * self.blocks.len()
    }

    /// The cells of block `b`: `[i0, j0, i1, j1)`.
    fn rect(&self, b: usize) -> [usize; 4] {
        let (bx, by) = (b % self.across, b / self.across);
        let (i0, j0) = (bx * SIDE, by * SIDE);
        [
            i0,
            j0,
            (i0 + SIDE).min(self.cells[0]),
            (j0 + SIDE).min(self.cells[1]),
        ]
    }

    /// Block `b`, made now if it is not yet.
    fn block(&self, make: Make<'_>, b: usize) -> &Block {
        self.blocks[b].get_or_init(|| {
            let bounds = make(self.rect(b));
            // Infinite bounds (no contraction) take code 0, infinite too.
            let largest = bounds.iter().fold(0.0f32, |m, &r| m.max(r));
            let codes = bounds
                .iter()
                .map(|&r| {
                    let k = (-8.0 * (r / largest).log2()).floor().clamp(0.0, 255.0) as usize;
                    // exp2 rounds: step back until the code's bound covers r (a NaN covers
                    // nothing and takes code 0, the largest, itself NaN then).
                    let mut k = if r.is_nan() { 0 } else { k };
                    while k > 0 && largest * SCALE[k] < r {
                        k -= 1;
                    }
                    k as u8
                })
                .collect();
            Block { largest, codes }
        })
    }

    /// The bound of cell (i, j).
    #[inline]
    pub(super) fn at(&self, make: Make<'_>, i: usize, j: usize) -> f32 {
        let b = (j / SIDE) * self.across + i / SIDE;
        let block = self.block(make, b);
        let [i0, j0, i1, _] = self.rect(b);
        block.largest * SCALE[usize::from(block.codes[(j - j0) * (i1 - i0) + i - i0])]
    }

    /// The bounds of the cells `[i0, i1) x [j0, j1)`, row-major, the blocks they lie in made
    /// first (on every core).
    pub(super) fn rect_bounds(&self, make: Make<'_>, [i0, j0, i1, j1]: [usize; 4]) -> Vec<f32> {
        use rayon::prelude::*;
        let (bx0, by0, bx1, by1) = (i0 / SIDE, j0 / SIDE, (i1 - 1) / SIDE, (j1 - 1) / SIDE);
        (by0..=by1)
            .flat_map(|by| (bx0..=bx1).map(move |bx| by * self.across + bx))
            .collect::<Vec<_>>()
            .into_par_iter()
            .for_each(|b| {
                self.block(make, b);
            });
        // Row by row, a run of cells a block.
        let mut out = Vec::with_capacity((i1 - i0) * (j1 - j0));
        for j in j0..j1 {
            let mut i = i0;
            while i < i1 {
                let b = (j / SIDE) * self.across + i / SIDE;
                let block = self.block(make, b);
                let [b0, c0, b1, _] = self.rect(b);
                let row = &block.codes[(j - c0) * (b1 - b0)..][..b1 - b0];
                let end = b1.min(i1);
                out.extend(
                    row[i - b0..end - b0]
                        .iter()
                        .map(|&k| block.largest * SCALE[usize::from(k)]),
                );
                i = end;
            }
        }
        out
    }
}
