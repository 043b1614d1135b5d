//! Which source cells held data ([`Mask`]): a bit a cell, range coded with its neighbours as
//! context, and a summary by blocks for fast "all valid" answers.

use crate::Error;
use crate::core::entropy::{Bit, Decoder, Encoder};

/// Which source cells held data (height fields with nodata).
#[derive(Clone, Debug, PartialEq)]
pub struct Mask {
    width: usize,
    height: usize,
    valid: Vec<bool>,
    /// Summed-area table over blocks of `BLOCK x BLOCK` cells of "holds a nodata cell", so
    /// that a tile whose footprint has none skips the per-pixel lookups in O(1) (they were a
    /// tenth of a reprojected tile's time); 4 bytes per block.
    gaps: Vec<u32>,
}

/// Side of a block of [`Mask`]'s summary, in cells.
const BLOCK: usize = 16;

impl Mask {
    /// The mask of a `width x height` grid from its row-major validity.
    pub fn new(width: usize, height: usize, valid: Vec<bool>) -> Mask {
        assert_eq!(valid.len(), width * height, "a validity per cell");
        let (bw, bh) = (width.div_ceil(BLOCK), height.div_ceil(BLOCK));
        let mut gap = vec![0u32; bw * bh];
        for (i, &ok) in valid.iter().enumerate() {
            if !ok {
                gap[(i / width / BLOCK) * bw + (i % width) / BLOCK] = 1;
            }
        }
        let mut gaps = vec![0u32; (bw + 1) * (bh + 1)];
        for by in 0..bh {
            for bx in 0..bw {
                gaps[(by + 1) * (bw + 1) + bx + 1] = gap[by * bw + bx]
                    + gaps[by * (bw + 1) + bx + 1]
                    + gaps[(by + 1) * (bw + 1) + bx]
                    - gaps[by * (bw + 1) + bx];
            }
        }
        Mask {
            width,
            height,
            valid,
            gaps,
        }
    }

    /// Width of the source grid.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height of the source grid.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Row-major validity of the source cells.
    pub fn valid(&self) -> &[bool] {
        &self.valid
    }

    /// The source cell (column, row) under unit point (u, v): monotonic in each coordinate.
    fn cell(&self, u: f32, v: f32) -> (usize, usize) {
        (
            ((u * self.width as f32) as usize).min(self.width - 1),
            ((v * self.height as f32) as usize).min(self.height - 1),
        )
    }

    /// Validity of the source cell under unit point (u, v).
    pub fn at(&self, u: f32, v: f32) -> bool {
        let (x, y) = self.cell(u, v);
        self.valid[y * self.width + x]
    }

    /// Whether every point of the unit box `[u0, u1] x [v0, v1]` is known valid (`at` is true
    /// there: a point maps to a cell between those of the box's corners). Conservative: true
    /// when no nodata cell lies in the blocks of `BLOCK x BLOCK` cells under the box.
    pub fn all_valid(&self, [u0, v0, u1, v1]: [f32; 4]) -> bool {
        let ((x0, y0), (x1, y1)) = (self.cell(u0, v0), self.cell(u1, v1));
        let (bx0, by0, bx1, by1) = (x0 / BLOCK, y0 / BLOCK, x1 / BLOCK + 1, y1 / BLOCK + 1);
        if bx1 <= bx0 || by1 <= by0 {
            return false; // a box given backwards: no claim
        }
        let row = self.width.div_ceil(BLOCK) + 1;
        let at = |bx: usize, by: usize| self.gaps[by * row + bx];
        at(bx1, by1) + at(bx0, by0) == at(bx0, by1) + at(bx1, by0)
    }

    pub(crate) fn encode(&self) -> Vec<u8> {
        // Context: the left and upper neighbours; runs of nodata cost almost nothing.
        let mut enc = Encoder::new();
        let mut ctx = [Bit::default(); 4];
        for y in 0..self.height {
            for x in 0..self.width {
                let c = context(&self.valid, self.width, x, y);
                enc.bit(&mut ctx[c], self.valid[y * self.width + x]);
            }
        }
        enc.finish()
    }

    pub(crate) fn decode(width: usize, height: usize, bytes: &[u8]) -> Result<Mask, Error> {
        // A decision per cell: a mask larger than its stream can hold is refused unallocated.
        if (width as u64) * (height as u64) > crate::core::entropy::most_decisions(bytes.len()) {
            return Err(Error::asset(format!(
                "a nodata mask of {width}x{height} needs more than its {} bytes",
                bytes.len()
            )));
        }
        let mut valid = vec![false; width * height];
        let mut dec = Decoder::new(bytes);
        let mut ctx = [Bit::default(); 4];
        for y in 0..height {
            for x in 0..width {
                let c = context(&valid, width, x, y);
                valid[y * width + x] = dec.bit(&mut ctx[c]);
            }
            if dec.overrun() {
                break;
            }
        }
        if dec.overrun() {
            return Err(Error::asset("the nodata mask is truncated"));
        }
        Ok(Mask::new(width, height, valid))
    }
}

/// The coding context of cell (x, y): validity of its left and upper neighbours.
fn context(valid: &[bool], width: usize, x: usize, y: usize) -> usize {
    let left = x > 0 && valid[y * width + x - 1];
    let up = y > 0 && valid[(y - 1) * width + x];
    usize::from(left) | usize::from(up) << 1
}

/// The validity of a coarse grid of `s x s` cells a cell over a grid of `size` cells: where any
/// of a cell's source cells is valid (a box mean's), or where the one on its lattice, its first,
/// is (`decimated`: a grid of samples taken from the source).
pub(crate) fn coarse_valid(
    valid: &[bool],
    [w, h]: [usize; 2],
    s: usize,
    decimated: bool,
) -> Vec<bool> {
    let (cw, ch) = (w.div_ceil(s), h.div_ceil(s));
    if decimated {
        return (0..cw * ch)
            .map(|c| valid[(c / cw) * s * w + (c % cw) * s])
            .collect();
    }
    let mut out = vec![false; cw * ch];
    for (i, _) in valid.iter().enumerate().filter(|(_, b)| **b) {
        out[(i / w / s) * cw + (i % w) / s] = true;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// The block summary answers what looking at every cell under the box answers.
        #[test]
        fn mask_summary_agrees_with_the_cells(
            w in 1usize..80,
            h in 1usize..80,
            holes in proptest::collection::vec((0usize..80, 0usize..80), 0..4),
            b in (-0.1f32..1.1, -0.1f32..1.1, 0.0f32..0.6, 0.0f32..0.6),
        ) {
            let mut valid = vec![true; w * h];
            for (x, y) in holes {
                valid[(y % h) * w + x % w] = false;
            }
            let m = Mask::new(w, h, valid);
            let bx = [b.0, b.1, b.0 + b.2, b.1 + b.3];
            let ((x0, y0), (x1, y1)) = (m.cell(bx[0], bx[1]), m.cell(bx[2], bx[3]));
            let cells_valid = (y0..=y1).all(|y| (x0..=x1).all(|x| m.valid[y * w + x]));
            // The blocks under the box, cell by cell.
            let (bx0, by0) = (x0 / super::BLOCK * super::BLOCK, y0 / super::BLOCK * super::BLOCK);
            let (bx1, by1) = (((x1 / super::BLOCK + 1) * super::BLOCK).min(w), ((y1 / super::BLOCK + 1) * super::BLOCK).min(h));
            let blocks_valid = (by0..by1).all(|y| (bx0..bx1).all(|x| m.valid[y * w + x]));
            let got = m.all_valid(bx);
            prop_assert_eq!(got, blocks_valid);
            prop_assert!(!got || cells_valid);
            // And every point of the box is then valid.
            if got {
                for k in 0..=16 {
                    let t = k as f32 / 16.0;
                    prop_assert!(m.at(bx[0] + t * b.2, bx[1] + (1.0 - t) * b.3));
                }
            }
        }
    }
}
