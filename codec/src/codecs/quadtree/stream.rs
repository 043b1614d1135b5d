//! The transform stream of one plane: quadtree split flags and each range's map, entropy coded.
//!
//! Encoding and decoding walk the tree with one function (`code`) so that they cannot drift
//! apart. Order: top-level blocks in raster order, children depth first (TL, TR, BL, BR). Blocks
//! wholly outside the frame are skipped; blocks partly outside are split without a flag. A leaf
//! codes its contrast index (context: level), offset index (context: level, constant or not) and,
//! unless the map is constant, its isometry and domain index (context: level).

use serde::{Deserialize, Serialize};

use crate::codecs::quadtree::operator::{QuadtreeOperator, RangeMap};
use crate::codecs::quadtree::search::{Fit, lattice};
use crate::core::entropy::{Bit, BitTree, Decoder, Dir, Encoder, WideIndex};
use crate::core::format::FormatError;
use crate::core::transform::Quantiser;

/// Everything a decoder needs besides the stream: stored in the asset for each plane.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlaneHeader {
    /// Frame (coding grid) size; multiples of `min_size`.
    pub frame: [u32; 2],
    /// Extent of the source in frame units (the unit square maps onto `[0, valid)`).
    pub valid: [f32; 2],
    /// Smallest range side.
    pub min_size: u32,
    /// Number of range sizes: `min_size << l` for `l` in `0..levels`.
    pub levels: u32,
    /// Domain lattice step for each level.
    pub domain_steps: Vec<u32>,
    /// Contrast and offset quantisation.
    pub quantiser: Quantiser,
}

impl PlaneHeader {
    /// Rejects headers no encoder writes (a corrupt or hostile asset).
    pub fn validate(&self) -> Result<(), FormatError> {
        self.quantiser.validate()?;
        let [w, h] = self.frame;
        if self.min_size == 0 || self.levels == 0 || self.levels > 12 {
            return Err(FormatError::header(format!(
                "bad range sizes: min {} levels {}",
                self.min_size, self.levels
            )));
        }
        if (self.min_size as u64) << (self.levels - 1) > 1 << 16 {
            return Err(FormatError::header("largest range side over 65536"));
        }
        if w == 0
            || h == 0
            || w > 1 << 16
            || h > 1 << 16
            || w % self.min_size != 0
            || h % self.min_size != 0
        {
            return Err(FormatError::header(format!(
                "bad frame {w}x{h} for range side {}",
                self.min_size
            )));
        }
        // The encoder pads by less than one smallest range (plus half a sample for odd chroma):
        // anything else would make decoders allocate frames far larger than their output.
        let slack = self.min_size as f32 + 1.0;
        let fits = |v: f32, f: u32| v > 0.0 && v <= f as f32 && v > f as f32 - slack;
        if !(fits(self.valid[0], w) && fits(self.valid[1], h)) {
            return Err(FormatError::header(format!(
                "bad valid extent {:?} in frame {w}x{h}",
                self.valid
            )));
        }
        if self.domain_steps.len() != self.levels as usize || self.domain_steps.contains(&0) {
            return Err(FormatError::header("bad domain steps"));
        }
        Ok(())
    }

    /// Blocks of the largest range size that the frame touches (each codes at least one leaf).
    pub fn top_blocks(&self) -> u64 {
        let n = self.size(self.levels as usize - 1) as u64;
        u64::from(self.frame[0]).div_ceil(n) * u64::from(self.frame[1]).div_ceil(n)
    }

    /// Most leaves a stream of `bytes` bytes can code in this frame: no more than the frame's
    /// smallest blocks, nor than the stream's decisions allow.
    pub fn most_leaves(&self, bytes: usize) -> u64 {
        let cells = (u64::from(self.frame[0]) / u64::from(self.min_size))
            * (u64::from(self.frame[1]) / u64::from(self.min_size));
        let per_leaf = u64::from(self.quantiser.contrast_bits + self.quantiser.offset_bits).max(1);
        cells.min(crate::core::entropy::most_decisions(bytes) / per_leaf)
    }

    /// Memory the decoding operator of this plane takes at most (its cell lookup and its
    /// ranges), from the header and the stream's length alone: what a reader checks against
    /// its budget before decoding.
    pub fn operator_bytes(&self, stream_bytes: usize) -> u64 {
        let cells = (u64::from(self.frame[0]) / u64::from(self.min_size))
            * (u64::from(self.frame[1]) / u64::from(self.min_size));
        // A u32 per lookup cell; a leaf, its range map and its affine cell, about 128 bytes.
        cells * 4 + self.most_leaves(stream_bytes) * 128
    }

    /// Range side of level `l`.
    pub fn size(&self, l: usize) -> usize {
        (self.min_size as usize) << l
    }

    /// Domain lattice (cols, rows) of level `l`.
    pub fn lattice(&self, l: usize) -> (usize, usize) {
        let (n, step) = (self.size(l), self.domain_steps[l] as usize);
        (
            lattice(self.frame[0] as usize, n, step),
            lattice(self.frame[1] as usize, n, step),
        )
    }
}

/// Where a block lies relative to the frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Coverage {
    /// Wholly outside: no data.
    Outside,
    /// Partly inside: always split.
    Partial,
    /// Wholly inside: a range or a split, as coded.
    Inside,
}

/// Coverage of block (bx, by) of side n.
pub fn coverage(frame: [u32; 2], n: usize, bx: usize, by: usize) -> Coverage {
    let (x0, y0) = (bx * n, by * n);
    if x0 >= frame[0] as usize || y0 >= frame[1] as usize {
        Coverage::Outside
    } else if x0 + n <= frame[0] as usize && y0 + n <= frame[1] as usize {
        Coverage::Inside
    } else {
        Coverage::Partial
    }
}

/// A coded range: its block and its quantised map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Leaf {
    /// Level (range side `min_size << level`).
    pub level: usize,
    /// Block column at that level.
    pub bx: usize,
    /// Block row at that level.
    pub by: usize,
    /// The map (sse and weight are not coded and read back as 0).
    pub fit: Fit,
}

struct Models {
    split: Vec<Bit>,
    contrast: Vec<BitTree>,
    offset: Vec<[BitTree; 2]>,
    isometry: Vec<BitTree>,
    /// Slope indices of the planar offset term, x and y (context: level, constant map or not).
    slope: Vec<[[BitTree; 2]; 2]>,
    /// Domain index (high bits through a tree of at most [`DOMAIN_TREE_BITS`]).
    domain: Vec<WideIndex>,
}

/// Largest bit tree for domain indices.
const DOMAIN_TREE_BITS: u32 = 14;

impl Models {
    fn new(h: &PlaneHeader) -> Models {
        let levels = h.levels as usize;
        let bits_for = |count: usize| usize::BITS - count.saturating_sub(1).leading_zeros();
        Models {
            split: vec![Bit::default(); levels],
            contrast: (0..levels)
                .map(|_| BitTree::new(h.quantiser.contrast_bits as u32))
                .collect(),
            offset: (0..levels)
                .map(|_| {
                    let b = h.quantiser.offset_bits as u32;
                    [BitTree::new(b), BitTree::new(b)]
                })
                .collect(),
            isometry: (0..levels).map(|_| BitTree::new(3)).collect(),
            slope: (0..levels)
                .map(|_| {
                    let b = (h.quantiser.slope_bits as u32).max(1);
                    [
                        [BitTree::new(b), BitTree::new(b)],
                        [BitTree::new(b), BitTree::new(b)],
                    ]
                })
                .collect(),
            domain: (0..levels)
                .map(|l| {
                    let (c, r) = h.lattice(l);
                    WideIndex::new(bits_for(c * r), DOMAIN_TREE_BITS)
                })
                .collect(),
        }
    }
}

/// Walks the tree, coding in the direction given. In encoding, `decide(level, bx, by)` says for
/// each inside block: `None` to split, `Some(fit)` for a leaf.
fn code(
    dir: &mut Dir,
    h: &PlaneHeader,
    decide: &dyn Fn(usize, usize, usize) -> Option<Fit>,
) -> Result<Vec<Leaf>, FormatError> {
    let mut m = Models::new(h);
    let top = h.levels as usize - 1;
    let n = h.size(top);
    let (cols, rows) = (
        (h.frame[0] as usize).div_ceil(n),
        (h.frame[1] as usize).div_ceil(n),
    );
    let mut leaves = Vec::new();
    let mut stack = Vec::new();
    let l_s = h.quantiser.contrast_levels();
    for by in 0..rows {
        for bx in 0..cols {
            stack.push((top, bx, by));
            while let Some((l, bx, by)) = stack.pop() {
                let split = match coverage(h.frame, h.size(l), bx, by) {
                    Coverage::Outside => continue,
                    Coverage::Partial => true,
                    Coverage::Inside if l == 0 => false,
                    Coverage::Inside => {
                        let wanted = decide(l, bx, by).is_none();
                        dir.bit(&mut m.split[l], wanted)
                    }
                };
                if split {
                    if l == 0 {
                        return Err(FormatError::stream(
                            "a block at the smallest size lies partly outside the frame",
                        ));
                    }
                    // Pushed in reverse so that TL is coded first.
                    for (cx, cy) in [(1, 1), (0, 1), (1, 0), (0, 0)] {
                        stack.push((l - 1, 2 * bx + cx, 2 * by + cy));
                    }
                    continue;
                }
                let fit = decide(l, bx, by).unwrap_or(Fit {
                    sse: 0.0,
                    weight: 0.0,
                    contrast: 0,
                    offset: 0,
                    isometry: 0,
                    domain: 0,
                    slope: [0; 2],
                    constant_sse: 0.0,
                    constant_offset: 0,
                    constant_slope: [0; 2],
                });
                let (dc, dr) = h.lattice(l);
                let qs = dir.tree(&mut m.contrast[l], (fit.contrast + l_s) as u32) as i32 - l_s;
                if qs.abs() > l_s {
                    return Err(FormatError::stream(format!(
                        "contrast index {qs} out of range"
                    )));
                }
                let qo = dir.tree(&mut m.offset[l][usize::from(qs != 0)], fit.offset);
                let mut slope = [0i32; 2];
                let l_g = h.quantiser.slope_levels();
                if l_g > 0 {
                    for (axis, v) in slope.iter_mut().enumerate() {
                        let t = &mut m.slope[l][usize::from(qs != 0)][axis];
                        *v = dir.tree(t, (fit.slope[axis] + l_g) as u32) as i32 - l_g;
                        if v.abs() > l_g {
                            return Err(FormatError::stream(format!(
                                "slope index {v} out of range"
                            )));
                        }
                    }
                }
                let (mut iso, mut dom) = (0, 0);
                if qs != 0 {
                    if dc * dr == 0 {
                        return Err(FormatError::stream(
                            "a non-constant map at a size with no domains",
                        ));
                    }
                    iso = dir.tree(&mut m.isometry[l], fit.isometry as u32) as u8;
                    dom = dir.wide(&mut m.domain[l], fit.domain);
                    if dom as usize >= dc * dr {
                        return Err(FormatError::stream(format!(
                            "domain index {dom} outside the lattice of {}",
                            dc * dr
                        )));
                    }
                }
                if dir.overrun() {
                    return Err(FormatError::stream("the transform stream is truncated"));
                }
                leaves.push(Leaf {
                    level: l,
                    bx,
                    by,
                    fit: Fit {
                        sse: 0.0,
                        weight: 0.0,
                        contrast: qs,
                        offset: qo,
                        isometry: iso,
                        domain: dom,
                        slope,
                        constant_sse: 0.0,
                        constant_offset: 0,
                        constant_slope: [0; 2],
                    },
                });
            }
        }
    }
    Ok(leaves)
}

/// Codes a plane's partition and maps.
pub fn encode_plane(
    h: &PlaneHeader,
    decide: &dyn Fn(usize, usize, usize) -> Option<Fit>,
) -> Vec<u8> {
    let mut enc = Encoder::new();
    code(&mut Dir::Enc(&mut enc), h, decide).expect("the encoder writes only what it can read");
    enc.finish()
}

/// Reads a plane's partition and maps.
pub fn decode_plane(h: &PlaneHeader, bytes: &[u8]) -> Result<Vec<Leaf>, FormatError> {
    h.validate()?;
    // Every top-level block holds at least one leaf, and a leaf codes its contrast and offset
    // indices: a frame whose leaves the stream cannot hold is refused before the walk.
    let decisions = h.top_blocks() * u64::from(h.quantiser.contrast_bits + h.quantiser.offset_bits);
    if decisions > crate::core::entropy::most_decisions(bytes.len()) {
        return Err(FormatError::stream(format!(
            "a frame of {}x{} needs more than the {} bytes of its stream",
            h.frame[0],
            h.frame[1],
            bytes.len()
        )));
    }
    let mut dec = Decoder::new(bytes);
    let leaves = code(&mut Dir::Dec(&mut dec), h, &|_, _, _| None)?;
    if dec.overrun() {
        return Err(FormatError::stream("the transform stream is truncated"));
    }
    Ok(leaves)
}

/// The decoding operator of a plane's leaves.
pub fn operator(h: &PlaneHeader, leaves: &[Leaf]) -> Result<QuadtreeOperator, FormatError> {
    let q = &h.quantiser;
    let ranges = leaves
        .iter()
        .map(|leaf| {
            let n = h.size(leaf.level);
            let (dc, _) = h.lattice(leaf.level);
            let step = h.domain_steps[leaf.level] as usize;
            let s = q.contrast(leaf.fit.contrast);
            let d = leaf.fit.domain as usize;
            let (dx, dy) = if dc > 0 {
                ((d % dc) * step, (d / dc) * step)
            } else {
                (0, 0)
            };
            RangeMap {
                x: (leaf.bx * n) as u32,
                y: (leaf.by * n) as u32,
                size: n as u32,
                domain_x: dx as u32,
                domain_y: dy as u32,
                isometry: leaf.fit.isometry,
                contrast: s,
                offset: q.offset(s, leaf.fit.offset),
                slope: [q.slope(leaf.fit.slope[0]), q.slope(leaf.fit.slope[1])],
            }
        })
        .collect();
    QuadtreeOperator::new(h.frame, h.valid, h.min_size, ranges)
}
