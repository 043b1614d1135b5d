//! The domains a range is searched among ([`DomainPool`]): the coding plane they are cut
//! from, their normalised features (DCT coefficients of a reduced block, Fisher's quadrant
//! classes) and the k-d trees of the nearest-neighbour search, one a tile on large planes.

use kiddo::ImmutableKdTree;

use crate::core::transform::{SQUARE_ISOMETRIES, isometry_index};

/// The grid the encoder fits: normalised values in [0, 1] over a padded frame, with a weight per
/// sample (1 for source data, 0 for padding and nodata, which then never count in the error).
#[derive(Clone, Debug)]
pub struct CodingPlane {
    /// Frame width.
    pub width: usize,
    /// Frame height.
    pub height: usize,
    /// Values, row-major; padding and nodata cells are filled with plausible values because
    /// domains read them.
    pub values: Vec<f32>,
    /// 1.0 where the error counts, 0.0 elsewhere.
    pub weights: Vec<f32>,
    /// Extent of the source in frame units.
    pub valid: [f32; 2],
}

impl CodingPlane {
    /// Mean of 2x2 blocks at every position: `avg2[y * (w-1) + x]` averages
    /// `values[x..x+2, y..y+2]`. A domain block of side 2n read at half resolution is
    /// `avg2[dx + 2i, dy + 2j]`.
    pub fn average2(&self) -> Vec<f32> {
        let (w, h) = (self.width, self.height);
        if w < 2 || h < 2 {
            return Vec::new();
        }
        let mut out = Vec::with_capacity((w - 1) * (h - 1));
        for y in 0..h - 1 {
            let (a, b) = (
                &self.values[y * w..(y + 1) * w],
                &self.values[(y + 1) * w..(y + 2) * w],
            );
            for x in 0..w - 1 {
                out.push(0.25 * (a[x] + a[x + 1] + b[x] + b[x + 1]));
            }
        }
        out
    }
}

/// How domains are searched.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SearchMode {
    /// Every domain and isometry.
    Full,
    /// Fisher's quadrant-brightness classes.
    Classified,
    /// Saupe's nearest-neighbour search, scoring this many candidates for r̂ and as many for -r̂.
    Nearest(usize),
}

impl Default for SearchMode {
    fn default() -> Self {
        SearchMode::Nearest(32)
    }
}

pub(super) const FEATURES: usize = 16;
/// Dimensions indexed by the k-d tree: the lowest-frequency AC coefficients of the orthonormal 4x4
/// DCT of the normalised block. The DCT is orthonormal, so distances in this subspace never exceed
/// the full distance (a lower bound that keeps the true nearest among the candidates often), and
/// k-d trees prune well in 8 dimensions where in 16 they degrade to a linear scan (measured:
/// 420 µs a query on 129k points at 16 dims).
pub(super) const INDEXED: usize = 8;
/// (u, v) frequencies of the indexed coefficients, lowest first.
pub(super) const ZIGZAG: [(usize, usize); INDEXED] = [
    (1, 0),
    (0, 1),
    (0, 2),
    (1, 1),
    (2, 0),
    (3, 0),
    (2, 1),
    (1, 2),
];

pub(super) fn dct_features(f: &[f32; FEATURES]) -> [f32; INDEXED] {
    // Orthonormal DCT-II basis for N = 4, computed once.
    static BASIS: std::sync::LazyLock<[[f32; 4]; 4]> = std::sync::LazyLock::new(|| {
        let mut b = [[0.0f32; 4]; 4];
        for (k, row) in b.iter_mut().enumerate() {
            let c = if k == 0 {
                0.5
            } else {
                std::f32::consts::FRAC_1_SQRT_2
            };
            for (n, v) in row.iter_mut().enumerate() {
                *v = c * ((std::f32::consts::PI * (2 * n + 1) as f32 * k as f32) / 8.0).cos();
            }
        }
        b
    });
    let basis = |k: usize, n: usize| BASIS[k][n];
    let mut out = [0.0f32; INDEXED];
    for (o, &(u, v)) in out.iter_mut().zip(&ZIGZAG) {
        let mut acc = 0.0;
        for j in 0..4 {
            for i in 0..4 {
                acc += f[j * 4 + i] * basis(u, i) * basis(v, j);
            }
        }
        *o = acc;
    }
    out
}

/// A domain index and an isometry.
pub(super) type DomainOrientation = (u32, u8);

/// A k-d tree over the oriented domains of one tile, and what each of its points stands for.
pub(super) type LocalTree = (ImmutableKdTree<f32, INDEXED>, Vec<DomainOrientation>);

/// Side of a tile of the nearest-neighbour search, in frame samples: a range is searched among
/// the domains whose corner lies in its own tile. Planes up to 1.5 tiles a side keep one tree
/// (every domain a candidate, as before tiles); larger ones are cut into tiles of this side
/// (a remainder under half a tile joins its neighbour), so that the tree a query walks stops
/// growing with the raster: one tree over all of a 2.3 Mpx raster took 56% of its encode in
/// the query against 46% at 0.58 Mpx, and its time a pixel grew 1.5x a 4x (measured on
/// mirrored copies of etopo20; docs/benchmarks.md). Local search is the usual compromise of
/// fractal coders: most good domains of a range are near it.
pub(crate) const TILE: usize = 1024;

/// Tiles along an axis of `frame` samples: 1 up to 1.5 [`TILE`], else one a [`TILE`] with the
/// remainder in the last.
pub(super) fn tiles_along(frame: usize) -> usize {
    if frame * 2 <= 3 * TILE {
        1
    } else {
        (frame + TILE / 2) / TILE
    }
}

/// All domains of one range size: the lattice, the blocks at half resolution, their sums, and the
/// index the chosen search needs.
pub struct DomainPool {
    /// Range side n (domains have side 2n).
    pub size: usize,
    /// Lattice step in frame samples.
    pub step: usize,
    /// Domains per row.
    pub cols: usize,
    /// Domain rows.
    pub rows: usize,
    pub(super) blocks: Vec<f32>,
    pub(super) sums: Vec<f32>,
    pub(super) sums2: Vec<f32>,
    /// Sums of d * X and d * Y (centred pixel coordinates), for the planar offset term.
    pub(super) sums_xy: Vec<[f32; 2]>,
    pub(super) plane: bool,
    pub(super) perms: Vec<Vec<u32>>,
    /// The nearest-neighbour index, one k-d tree a tile of the plane (see [`TILE`]).
    pub(super) trees: Vec<Option<LocalTree>>,
    /// Domain-position tiles a row and their side, in frame samples.
    pub(super) tiles: (usize, usize),
    pub(super) classes: Option<Vec<Vec<(u32, u8)>>>,
}

/// Domain lattice size along one axis for frame side `frame`, range side `n`, step `step`.
pub fn lattice(frame: usize, n: usize, step: usize) -> usize {
    if frame >= 2 * n {
        (frame - 2 * n) / step.max(1) + 1
    } else {
        0
    }
}

impl DomainPool {
    /// Builds the pool of domains of side `2n` on a lattice of `step` over the plane.
    pub fn new(
        plane: &CodingPlane,
        avg2: &[f32],
        n: usize,
        step: usize,
        mode: SearchMode,
        planar: bool,
    ) -> DomainPool {
        let cols = lattice(plane.width, n, step);
        let rows = lattice(plane.height, n, step);
        let count = cols * rows;
        let aw = plane.width.saturating_sub(1);
        let mut blocks = Vec::with_capacity(count * n * n);
        let (mut sums, mut sums2) = (Vec::with_capacity(count), Vec::with_capacity(count));
        let mut sums_xy = Vec::with_capacity(count);
        let c = (n as f32 - 1.0) * 0.5;
        for d in 0..count {
            let (dx, dy) = ((d % cols) * step, (d / cols) * step);
            let (mut s, mut s2, mut sx, mut sy) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
            for j in 0..n {
                for i in 0..n {
                    let v = avg2[(dy + 2 * j) * aw + dx + 2 * i];
                    blocks.push(v);
                    s += v;
                    s2 += v * v;
                    sx += v * (i as f32 - c);
                    sy += v * (j as f32 - c);
                }
            }
            sums.push(s);
            sums2.push(s2);
            sums_xy.push([sx, sy]);
        }
        let perms = (0..SQUARE_ISOMETRIES)
            .map(|k| {
                let mut p = vec![0u32; n * n];
                for j in 0..n {
                    for i in 0..n {
                        let (ii, jj) = isometry_index(k, i, j, n);
                        p[j * n + i] = (jj * n + ii) as u32;
                    }
                }
                p
            })
            .collect();
        let mut pool = DomainPool {
            size: n,
            step,
            cols,
            rows,
            blocks,
            sums,
            sums2,
            sums_xy,
            plane: planar,
            perms,
            trees: Vec::new(),
            tiles: (1, usize::MAX),
            classes: None,
        };
        match mode {
            SearchMode::Nearest(_) if count > 0 => pool.build_tree([plane.width, plane.height]),
            SearchMode::Classified if count > 0 && n >= 2 => pool.build_classes(),
            _ => {}
        }
        pool
    }

    /// Number of domains.
    pub fn count(&self) -> usize {
        self.cols * self.rows
    }

    /// Top-left corner of domain `d` in frame samples.
    pub fn position(&self, d: usize) -> (usize, usize) {
        ((d % self.cols) * self.step, (d / self.cols) * self.step)
    }

    pub(super) fn block(&self, d: usize) -> &[f32] {
        let nn = self.size * self.size;
        &self.blocks[d * nn..(d + 1) * nn]
    }

    /// The tile of the search that the frame point (x, y) lies in (clamped into the tiles).
    pub(super) fn tile_of(&self, x: usize, y: usize) -> usize {
        let (cols, side) = self.tiles;
        let rows = self.trees.len() / cols.max(1);
        (y / side).min(rows - 1) * cols + (x / side).min(cols - 1)
    }

    /// The k-d tree of the tile of frame point (x, y) (the one tree of a small plane).
    pub(super) fn tree_at(&self, x: usize, y: usize) -> Option<&LocalTree> {
        if self.trees.is_empty() {
            return None;
        }
        self.trees[self.tile_of(x, y)].as_ref()
    }

    pub(super) fn build_tree(&mut self, frame: [usize; 2]) {
        let [tx, ty] = frame.map(tiles_along);
        // One side for both axes: a plane under 1.5 tiles on both keeps one tree.
        let side = if tx * ty == 1 { usize::MAX } else { TILE };
        self.tiles = (tx, side);
        self.trees = (0..tx * ty).map(|_| None).collect();
        let mut points = vec![Vec::new(); tx * ty];
        let mut items = vec![Vec::new(); tx * ty];
        for d in 0..self.count() {
            let (px, py) = self.position(d);
            let t = self.tile_of(px, py);
            let (points, items) = (&mut points[t], &mut items[t]);
            let base = reduce(self.block(d), self.size);
            if normalise(base, self.plane).is_none() {
                continue;
            }
            for k in 0..SQUARE_ISOMETRIES {
                let mut f = [0.0f32; FEATURES];
                for j in 0..4 {
                    for i in 0..4 {
                        let (ii, jj) = isometry_index(k, i, j, 4);
                        f[j * 4 + i] = base[jj * 4 + ii];
                    }
                }
                // An isometry keeps the norm, but not the f32 rounding of the residual's sum: a
                // block at the flatness threshold can pass in one orientation and fail in
                // another. Such a block has nothing for a range to match; skip it.
                let Some(f) = normalise(f, self.plane) else {
                    continue;
                };
                // A jitter far below any meaningful difference breaks exact ties between blocks
                // (padding repeats edges), which k-d trees split badly.
                let mut f = dct_features(&f);
                let h = (d as u32)
                    .wrapping_mul(2_654_435_761)
                    .wrapping_add(k as u32 * 40_503);
                f[(h >> 29) as usize] += (h & 0xFFFF) as f32 * 1e-12;
                points.push(f);
                items.push((d as u32, k));
            }
        }
        for (t, (points, items)) in points.into_iter().zip(items).enumerate() {
            if !points.is_empty() {
                self.trees[t] = Some((ImmutableKdTree::new_from_slice(&points), items));
            }
        }
    }

    pub(super) fn build_classes(&mut self) {
        let mut classes = vec![Vec::new(); 24];
        for d in 0..self.count() {
            let q = quadrant_means(self.block(d), self.size);
            for k in 0..SQUARE_ISOMETRIES {
                // Quadrant (qi, qj) of the oriented domain reads quadrant iso(qi, qj) of the block.
                let mut m = [0.0f32; 4];
                for (qj, qi) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let (ii, jj) = isometry_index(k, qi, qj, 2);
                    m[qj * 2 + qi] = q[jj * 2 + ii];
                }
                classes[order_class(&m)].push((d as u32, k));
            }
        }
        self.classes = Some(classes);
    }
}

/// Reduces an n x n block to 4 x 4 (box average for n >= 4, replication for n < 4).
pub(super) fn reduce(block: &[f32], n: usize) -> [f32; FEATURES] {
    let mut f = [0.0f32; FEATURES];
    if n >= 4 {
        let b = n / 4;
        for j in 0..n {
            for i in 0..n {
                f[(j / b).min(3) * 4 + (i / b).min(3)] += block[j * n + i];
            }
        }
    } else {
        for j in 0..4 {
            for i in 0..4 {
                f[j * 4 + i] = block[(j * n / 4) * n + i * n / 4];
            }
        }
    }
    f
}

/// Zero mean (and, with `plane`, no planar part), unit norm; `None` for blocks with nothing
/// left (only a constant map fits them).
pub(super) fn normalise(mut f: [f32; FEATURES], plane: bool) -> Option<[f32; FEATURES]> {
    let mean = f.iter().sum::<f32>() / FEATURES as f32;
    let (mut gx, mut gy) = (0.0f32, 0.0f32);
    if plane {
        // Centred 4x4 coordinates: X = i - 1.5, and the sum of X^2 is 20.
        for j in 0..4 {
            for i in 0..4 {
                gx += f[j * 4 + i] * (i as f32 - 1.5) / 20.0;
                gy += f[j * 4 + i] * (j as f32 - 1.5) / 20.0;
            }
        }
    }
    let mut norm = 0.0;
    for (k, v) in f.iter_mut().enumerate() {
        *v -= mean + gx * ((k % 4) as f32 - 1.5) + gy * ((k / 4) as f32 - 1.5);
        norm += *v * *v;
    }
    if norm < 1e-12 {
        return None;
    }
    let inv = 1.0 / norm.sqrt();
    f.iter_mut().for_each(|v| *v *= inv);
    Some(f)
}

pub(super) fn quadrant_means(block: &[f32], n: usize) -> [f32; 4] {
    let h = n / 2;
    let mut q = [0.0f32; 4];
    for j in 0..n {
        for i in 0..n {
            q[(j / h).min(1) * 2 + (i / h).min(1)] += block[j * n + i];
        }
    }
    q
}

/// Index (0..24) of the permutation that sorts four quadrant means, brightest first.
pub(super) fn order_class(m: &[f32; 4]) -> usize {
    let mut idx = [0usize, 1, 2, 3];
    idx.sort_by(|&a, &b| m[b].total_cmp(&m[a]).then(a.cmp(&b)));
    // Lehmer code of the permutation.
    let mut code = 0;
    for i in 0..4 {
        let smaller = (i + 1..4).filter(|&j| idx[j] < idx[i]).count();
        code = code * (4 - i) + smaller;
    }
    code
}

pub(super) fn reversed_class(m: &[f32; 4]) -> usize {
    order_class(&[-m[0], -m[1], -m[2], -m[3]])
}
