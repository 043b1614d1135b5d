//! IFS3D: the partitioned IFS on a 3D grid (seed, sec. 3.3), for signed distance fields.
//!
//! The same operator form as in 2D, one dimension up: octree ranges of side `min_size << l`,
//! domains twice that side on a lattice, all 48 isometries of the cube, constant contrast and
//! offset per range (least squares, quantised with the 2D [`Quantiser`]). Ranges whose block is
//! constant (wholly clamped inside or outside the band) are constant maps found without a search
//! and coded in a bit or two. The decoders of [`crate::core::decode`] run it unchanged: [`OctreeOperator`]
//! is an [`Operator<3>`].
//!
//! * [`OctreeOperator`]: the decoding form (a cell-index map at the smallest range size, one
//!   affine cell per range).
//! * [`crate::codecs::ifs3d::fit::encode_field`]: the encoder: fits of every block at every size (Saupe's nearest-neighbour
//!   search on 2x2x2 octant features, the 48 orientations of every domain in one k-d tree),
//!   then a partition by collage tolerance or by a budget of maps, then the stream.
//! * `code`: one walk for the stream, shared by encoder and decoder, as in [`crate::codecs::quadtree::stream`].

use serde::{Deserialize, Serialize};

use crate::core::entropy::{Bit, BitTree, Decoder, Dir, WideIndex};
use crate::core::format::FormatError;
use crate::core::operator::{Operator, Step, invariant_interval};
use crate::core::transform::Quantiser;

/// Number of isometries of the cube (the full octahedral group, reflections included).
pub const CUBE_ISOMETRIES: u8 = 48;

const PERMUTATIONS: [[usize; 3]; 6] = [
    [0, 1, 2],
    [0, 2, 1],
    [1, 0, 2],
    [1, 2, 0],
    [2, 0, 1],
    [2, 1, 0],
];

/// Isometry `k` (0..48) as (permutation, mirrors): local coordinate `a'_i` of the domain is
/// `a_{perm[i]}` of the range, mirrored (`1 - a`) where `mirror[i]`. 0 is the identity.
pub fn cube_isometry(k: u8) -> ([usize; 3], [bool; 3]) {
    let k = (k % CUBE_ISOMETRIES) as usize;
    (PERMUTATIONS[k / 8], [k & 1 != 0, k & 2 != 0, k & 4 != 0])
}

/// Where voxel `q` of an `n^3` range block reads in the (downsampled) domain block under
/// isometry `k`: the discrete form of [`cube_isometry`].
#[inline(always)]
pub fn cube_isometry_index(k: u8, q: [usize; 3], n: usize) -> [usize; 3] {
    let (perm, mirror) = cube_isometry(k);
    std::array::from_fn(|a| {
        let v = q[perm[a]];
        if mirror[a] { n - 1 - v } else { v }
    })
}

/// Everything a decoder needs besides the stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OctreeHeader {
    /// Side of the cubic frame (coding grid); a multiple of the largest range side.
    pub frame: u32,
    /// Extent of the source in frame units (the unit cube maps onto `[0, valid)^3`).
    pub valid: f32,
    /// Smallest range side.
    pub min_size: u32,
    /// Number of range sizes: `min_size << l` for `l` in `0..levels`.
    pub levels: u32,
    /// Domain lattice step for each level.
    pub domain_steps: Vec<u32>,
    /// Contrast and offset quantisation (slopes unused in 3D: `slope_bits` must be 0).
    pub quantiser: Quantiser,
}

impl OctreeHeader {
    /// Rejects headers no encoder writes (a corrupt or hostile asset).
    pub fn validate(&self) -> Result<(), FormatError> {
        self.quantiser.validate()?;
        if self.quantiser.slope_bits != 0 {
            return Err(FormatError::header(
                "IFS3D has constant offsets: slope bits must be 0",
            ));
        }
        if self.min_size < 2 || self.levels == 0 || self.levels > 6 {
            return Err(FormatError::header(format!(
                "bad range sizes: min {} levels {}",
                self.min_size, self.levels
            )));
        }
        let top = (self.min_size as u64) << (self.levels - 1);
        if self.frame == 0 || self.frame > 1024 || !(self.frame as u64).is_multiple_of(top) {
            return Err(FormatError::header(format!(
                "frame {} is not a multiple of the largest range side {top} (or over 1024)",
                self.frame
            )));
        }
        // The cell-index map has (frame / min_size)^3 entries: a hostile header must not make a
        // reader allocate gigabytes (2^24 entries is 64 MiB: a 1024 frame with 4-voxel ranges).
        if (self.frame as u64 / self.min_size as u64).pow(3) > 1 << 24 {
            return Err(FormatError::header(format!(
                "frame {} with ranges of {} needs over 2^24 lookup cells",
                self.frame, self.min_size
            )));
        }
        if !(self.valid > 0.0
            && self.valid <= self.frame as f32
            && self.valid > self.frame as f32 - top as f32)
        {
            return Err(FormatError::header(format!(
                "bad valid extent {} in frame {}",
                self.valid, self.frame
            )));
        }
        if self.domain_steps.len() != self.levels as usize
            || self.domain_steps.iter().any(|&s| s == 0 || s % 2 != 0)
        {
            return Err(FormatError::header(
                "bad domain steps (each even and positive)",
            ));
        }
        Ok(())
    }

    /// Range side of level `l`.
    pub fn size(&self, l: usize) -> usize {
        (self.min_size as usize) << l
    }

    /// Domain positions per axis at level `l` (0 when the frame is too small for a domain).
    pub fn lattice(&self, l: usize) -> usize {
        let (f, d, step) = (
            self.frame as usize,
            2 * self.size(l),
            self.domain_steps[l] as usize,
        );
        if f < d { 0 } else { (f - d) / step + 1 }
    }

    /// Corner of domain `d` at level `l`, in frame voxels.
    pub fn domain_corner(&self, l: usize, d: u32) -> [u32; 3] {
        let c = self.lattice(l).max(1) as u32;
        let step = self.domain_steps[l];
        [d % c * step, d / c % c * step, d / (c * c) * step]
    }
}

/// A range's quantised map, as coded.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Map3 {
    /// Contrast index.
    pub contrast: i32,
    /// Offset index.
    pub offset: u32,
    /// Isometry, 0..48 (0 when the contrast is 0).
    pub isometry: u8,
    /// Domain index on the level's lattice (0 when the contrast is 0).
    pub domain: u32,
}

/// A coded range: its block and map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Leaf3 {
    /// Level (range side `min_size << level`).
    pub level: usize,
    /// Block coordinates at that level.
    pub block: [usize; 3],
    /// The map.
    pub map: Map3,
}

/// One range's map in the form the decoders evaluate: `phi_a(p) = ±2 p[perm[a]] + c[a]`,
/// `g(p) = offset`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OctCell {
    /// Constants of phi.
    pub c: [f32; 3],
    /// Coefficients of phi (±2, the domain's scale with the isometry's mirror).
    pub coef: [f32; 3],
    /// Which coordinate of p each phi_a reads.
    pub perm: [u8; 3],
    /// Contrast s.
    pub contrast: f32,
    /// Offset g.
    pub offset: f32,
}

impl OctCell {
    /// The cell of range `origin`, side `n`, mapped from the domain at `domain` (side 2n).
    pub fn new(
        origin: [u32; 3],
        n: u32,
        domain: [u32; 3],
        isometry: u8,
        contrast: f32,
        offset: f32,
    ) -> OctCell {
        let (perm, mirror) = cube_isometry(isometry);
        let (n, r) = (n as f32, origin.map(|v| v as f32));
        let mut cell = OctCell {
            c: [0.0; 3],
            coef: [2.0; 3],
            perm: perm.map(|p| p as u8),
            contrast,
            offset,
        };
        for a in 0..3 {
            let (d, rp) = (domain[a] as f32, r[perm[a]]);
            if mirror[a] {
                cell.coef[a] = -2.0;
                cell.c[a] = d + 2.0 * n + 2.0 * rp;
            } else {
                cell.c[a] = d - 2.0 * rp;
            }
        }
        cell
    }

    /// phi at p.
    #[inline(always)]
    pub fn phi(&self, p: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|a| self.coef[a] * p[self.perm[a] as usize] + self.c[a])
    }
}

/// An octree partitioned IFS on a cubic 3D frame.
#[derive(Clone, Debug)]
pub struct OctreeOperator {
    header: OctreeHeader,
    cell: u32,
    inv_cell: f32,
    side: usize,
    lut: Vec<u32>,
    cells: Vec<OctCell>,
    leaves: Vec<Leaf3>,
    interval: (f32, f32),
}

impl OctreeOperator {
    /// Builds the operator of coded leaves; fails unless they tile the frame.
    pub fn new(header: &OctreeHeader, leaves: Vec<Leaf3>) -> Result<OctreeOperator, FormatError> {
        header.validate()?;
        let q = header.quantiser;
        let cell = header.min_size;
        let side = (header.frame / cell) as usize;
        let mut lut = vec![u32::MAX; side * side * side];
        let mut cells = Vec::with_capacity(leaves.len());
        for (i, leaf) in leaves.iter().enumerate() {
            let n = header.size(leaf.level) as u32;
            let origin = leaf.block.map(|b| b as u32 * n);
            if origin.iter().any(|&o| o + n > header.frame) {
                return Err(FormatError::stream(format!(
                    "range {i} lies outside the frame"
                )));
            }
            let s = q.contrast(leaf.map.contrast);
            let o = q.offset(s, leaf.map.offset);
            let domain = header.domain_corner(leaf.level, leaf.map.domain);
            cells.push(OctCell::new(origin, n, domain, leaf.map.isometry, s, o));
            let (c0, k) = (origin.map(|v| (v / cell) as usize), (n / cell) as usize);
            for z in c0[2]..c0[2] + k {
                for y in c0[1]..c0[1] + k {
                    for slot in
                        &mut lut[(z * side + y) * side + c0[0]..(z * side + y) * side + c0[0] + k]
                    {
                        if *slot != u32::MAX {
                            return Err(FormatError::stream(format!(
                                "range {i} overlaps another range"
                            )));
                        }
                        *slot = i as u32;
                    }
                }
            }
        }
        if lut.contains(&u32::MAX) {
            return Err(FormatError::stream(
                "the ranges leave part of the frame uncovered",
            ));
        }
        let interval = invariant_interval(cells.iter().map(|c| (c.contrast, c.offset, c.offset)));
        Ok(OctreeOperator {
            header: header.clone(),
            cell,
            inv_cell: 1.0 / cell as f32,
            side,
            lut,
            cells,
            leaves,
            interval,
        })
    }

    /// The header it was built from.
    pub fn header(&self) -> &OctreeHeader {
        &self.header
    }

    /// The coded ranges, in stream order.
    pub fn leaves(&self) -> &[Leaf3] {
        &self.leaves
    }

    /// The ranges' maps in affine form, in the order of [`Self::leaves`].
    pub fn cells(&self) -> &[OctCell] {
        &self.cells
    }

    /// The cell-index map at the smallest range size (x fastest, `frame / cell` per side).
    pub fn lookup(&self) -> (&[u32], u32) {
        (&self.lut, self.cell)
    }

    /// Largest |s|.
    pub fn max_contrast(&self) -> f32 {
        self.cells.iter().fold(0.0, |m, c| m.max(c.contrast.abs()))
    }

    #[inline(always)]
    fn range_at(&self, p: [f32; 3]) -> usize {
        let i = p.map(|v| ((v * self.inv_cell) as usize).min(self.side - 1));
        self.lut[(i[2] * self.side + i[1]) * self.side + i[0]] as usize
    }
}

impl Operator<3> for OctreeOperator {
    fn frame(&self) -> [f32; 3] {
        [self.header.frame as f32; 3]
    }

    fn valid(&self) -> [f32; 3] {
        [self.header.valid; 3]
    }

    fn expansion(&self) -> u32 {
        2
    }

    #[inline(always)]
    fn step(&self, p: [f32; 3]) -> Step<3> {
        let c = &self.cells[self.range_at(p)];
        Step {
            offset: c.offset,
            contrast: c.contrast,
            next: c.phi(p),
        }
    }

    fn invariant_interval(&self) -> (f32, f32) {
        self.interval
    }
}

// ---------------------------------------------------------------------------------------------
// The stream.

struct Models {
    split: Vec<Bit>,
    /// Contrast index, context: level.
    contrast: Vec<BitTree>,
    /// Offset index, context: level, constant map or not.
    offset: Vec<[BitTree; 2]>,
    isometry: Vec<BitTree>,
    /// Domain index.
    domain: Vec<WideIndex>,
}

const DOMAIN_TREE_BITS: u32 = 12;

impl Models {
    fn new(h: &OctreeHeader) -> Models {
        let levels = h.levels as usize;
        let bits_for = |count: usize| usize::BITS - count.saturating_sub(1).leading_zeros();
        let ob = h.quantiser.offset_bits as u32;
        Models {
            split: vec![Bit::default(); levels],
            contrast: (0..levels)
                .map(|_| BitTree::new(h.quantiser.contrast_bits as u32))
                .collect(),
            offset: (0..levels)
                .map(|_| [BitTree::new(ob), BitTree::new(ob)])
                .collect(),
            isometry: (0..levels).map(|_| BitTree::new(6)).collect(),
            domain: (0..levels)
                .map(|l| WideIndex::new(bits_for(h.lattice(l).pow(3)), DOMAIN_TREE_BITS))
                .collect(),
        }
    }
}

/// Walks the octree in both directions: top-level blocks in z, y, x order, children depth first
/// (x fastest). `decide(level, block)` says, when encoding, `None` to split or the leaf's map.
pub(crate) fn code(
    dir: &mut Dir,
    h: &OctreeHeader,
    decide: &dyn Fn(usize, [usize; 3]) -> Option<Map3>,
) -> Result<Vec<Leaf3>, FormatError> {
    let mut m = Models::new(h);
    let top = h.levels as usize - 1;
    let blocks = h.frame as usize / h.size(top);
    let l_s = h.quantiser.contrast_levels();
    let mut leaves = Vec::new();
    let mut stack = Vec::new();
    for bz in 0..blocks {
        for by in 0..blocks {
            for bx in 0..blocks {
                stack.push((top, [bx, by, bz]));
                while let Some((l, b)) = stack.pop() {
                    if l > 0 {
                        let wanted = decide(l, b).is_none();
                        if dir.bit(&mut m.split[l], wanted) {
                            for c in (0..8).rev() {
                                stack.push((
                                    l - 1,
                                    [
                                        2 * b[0] + (c & 1),
                                        2 * b[1] + (c >> 1 & 1),
                                        2 * b[2] + (c >> 2),
                                    ],
                                ));
                            }
                            continue;
                        }
                    }
                    let map = decide(l, b).unwrap_or_default();
                    let qs = dir.tree(&mut m.contrast[l], (map.contrast + l_s) as u32) as i32 - l_s;
                    if qs.abs() > l_s {
                        return Err(FormatError::stream(format!(
                            "contrast index {qs} out of range"
                        )));
                    }
                    let qo = dir.tree(&mut m.offset[l][usize::from(qs != 0)], map.offset);
                    let (mut iso, mut dom) = (0u8, 0u32);
                    if qs != 0 {
                        let count = h.lattice(l).pow(3);
                        if count == 0 {
                            return Err(FormatError::stream(
                                "a non-constant map at a size with no domains",
                            ));
                        }
                        iso = dir.tree(&mut m.isometry[l], map.isometry as u32) as u8;
                        if iso >= CUBE_ISOMETRIES {
                            return Err(FormatError::stream(format!(
                                "isometry {iso} out of range"
                            )));
                        }
                        dom = dir.wide(&mut m.domain[l], map.domain);
                        if dom as usize >= count {
                            return Err(FormatError::stream(format!(
                                "domain index {dom} outside the lattice of {count}"
                            )));
                        }
                    }
                    if dir.overrun() {
                        return Err(FormatError::stream("the transform stream is truncated"));
                    }
                    leaves.push(Leaf3 {
                        level: l,
                        block: b,
                        map: Map3 {
                            contrast: qs,
                            offset: qo,
                            isometry: iso,
                            domain: dom,
                        },
                    });
                }
            }
        }
    }
    Ok(leaves)
}

/// Decodes a stream into its leaves (errors for anything no encoder writes).
pub fn decode_stream(h: &OctreeHeader, bytes: &[u8]) -> Result<Vec<Leaf3>, FormatError> {
    h.validate()?;
    let mut dec = Decoder::new(bytes);
    let leaves = code(&mut Dir::Dec(&mut dec), h, &|_, _| None)?;
    if dec.overrun() {
        return Err(FormatError::stream("the transform stream is truncated"));
    }
    Ok(leaves)
}

// ---------------------------------------------------------------------------------------------
// The encoder.
