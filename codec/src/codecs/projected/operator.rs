//! The continuation operator of a decoded grid ([`ProjectedOperator`]; see the parent
//! module for its maths): its records, steps and chains, flattened for kernels.

use std::sync::Arc;

use crate::codecs::projected::header::ProjectedHeader;
use crate::codecs::projected::residual::LazyBounds;
use crate::core::format::FormatError;
use crate::core::operator::{Chain, Operator, Step};

/// The continuation operator of a decoded grid (see the module's documentation). Per cell it
/// keeps g at the cell's nine half-lattice points (g at a sample depends on the cell, through
/// phi, so neighbours do not share them): a step is then one 36-byte record and a bilinear
/// blend over a quarter of the cell, exact at the half-lattice points, where g is the cubic
/// interpolant less rho times the coarser cubic interpolant at phi. Computing the sample
/// corners on the fly instead (five values a cell) took 4.4 times the quadtree's time a point,
/// most of it in the fetch of z at phi; the record takes 40 bytes a sample with z (44 with the
/// residual bound a cell).
#[derive(Clone, Debug)]
pub struct ProjectedOperator {
    pub(super) size: [usize; 2],
    /// Decoded samples, normalised (shared with the windows of a lazily built operator).
    pub(super) z: Arc<[f32]>,
    /// The cells whose records and residual bounds are at hand: all of them for an operator
    /// built whole, none for one built lazily, a request's for a window of one (see
    /// [`records`]).
    pub(super) region: Region,
    /// Per cell of `region`, g at the half-lattice points (a/2, b/2), a, b in 0..3, at
    /// `3 b + a`.
    pub(super) records: Vec<[f32; 9]>,
    pub(super) rho: f32,
    pub(super) interval: (f32, f32),
    /// Per cell of `region`, a bound on |f - S| there, S the bilinear interpolant of the
    /// samples (see [`Self::residual_bounds`]): chains end on S instead of a constant, so they
    /// need the steps that take the bound where they are, not the value range, under the
    /// tolerance.
    pub(super) residual: Vec<f32>,
    /// Of a lazily built operator (and its windows): every cell's residual bound, coded, made
    /// a block of cells at a time on first use (see [`records`](super::records)).
    pub(super) bounds: Option<Arc<LazyBounds>>,
    /// The largest residual bound (of a lazily built operator: unknown, infinite).
    pub(super) residual_max: f32,
    /// The part of the frame unit coordinates map onto (the frame, or for half-resolution
    /// chroma of an odd-sized image, half the luma's extent).
    pub(super) valid: [f32; 2],
}

/// A rectangle of cells.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Region {
    /// Its first cell.
    pub(super) origin: [usize; 2],
    /// Cells along each axis.
    pub(super) size: [usize; 2],
}

impl Region {
    /// The index of cell (i, j) in the region's row-major arrays, if it is inside.
    #[inline(always)]
    pub(super) fn index(&self, i: usize, j: usize) -> Option<usize> {
        // One subtraction and comparison an axis: a cell left of the origin wraps past the size.
        let (x, y) = (
            i.wrapping_sub(self.origin[0]),
            j.wrapping_sub(self.origin[1]),
        );
        (x < self.size[0] && y < self.size[1]).then(|| y * self.size[0] + x)
    }
}

/// The even `c` of a cell along one axis, so that `phi(t) = 2 t - c` maps the cell `[i, i + 1]`
/// onto the even-aligned pair of cells that holds it (or, for the last cell of an even-length
/// axis, the pair just before it).
#[inline(always)]
pub(super) fn block(i: usize, n: usize) -> usize {
    if i % 2 == 1 {
        i + 1
    } else if i + 2 < n {
        i
    } else {
        i + 2
    }
}

/// Catmull-Rom weights at t in [0, 1] for the samples at -1, 0, 1, 2.
pub(super) fn catmull_rom(t: f32) -> [f32; 4] {
    let (t2, t3) = (t * t, t * t * t);
    [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}

/// Largest sum of negative Catmull-Rom weights in 2D (tensor products of 1D weights whose
/// absolute sum is at most 1.25): interpolants overshoot the samples' range by at most this
/// much of it.
pub(super) const OVERSHOOT: f32 = 0.29;

impl ProjectedOperator {
    /// The operator of decoded samples `grid` (source units) under `header`, built whole: a
    /// record and a residual bound a cell (about 44 bytes a sample with the sample).
    pub fn new(header: &ProjectedHeader, grid: &[f64]) -> Result<ProjectedOperator, FormatError> {
        let mut op = ProjectedOperator::samples_only(header, grid)?;
        op.records = op.all_records();
        op.region.size = [op.size[0] - 1, op.size[1] - 1];
        op.residual = op.residual_bounds(&op.records);
        op.residual_max = op.residual.iter().fold(0.0, |m: f32, &r| m.max(r));
        Ok(op)
    }

    /// The operator of decoded samples `grid` under `header`, built lazily: its samples, the
    /// records of the cells a request needs built for it ([`Self::window`]), and a residual
    /// bound a cell coded in a byte, made a block of cells at a time when a request first
    /// reads them (5 bytes a sample in all). The same values as [`Self::new`]'s operator where
    /// chains take the same steps; its residual bounds are rounded up by at most 9%, so a
    /// chain may take a step more to reach a tolerance. What chunks of chunked assets use (see
    /// `crate::codecs::projected::records`).
    pub fn lazy(
        header: &ProjectedHeader,
        grid: Vec<f64>,
    ) -> Result<ProjectedOperator, FormatError> {
        // The grid goes once the samples are made: it is twice their size, and a server builds
        // chunks' operators a core at a time.
        let mut op = ProjectedOperator::samples_only(header, &grid)?;
        drop(grid);
        op.bounds = Some(Arc::new(LazyBounds::new([op.size[0] - 1, op.size[1] - 1])));
        Ok(op)
    }

    /// The samples, rho and the invariant interval; no records yet.
    pub(super) fn samples_only(
        header: &ProjectedHeader,
        grid: &[f64],
    ) -> Result<ProjectedOperator, FormatError> {
        header.validate()?;
        if grid.len() != header.cells() {
            return Err(FormatError::stream(
                "projected grid does not match its header",
            ));
        }
        let size = [header.samples[0] as usize, header.samples[1] as usize];
        let z: Arc<[f32]> = grid
            .iter()
            .map(|&v| ((v - header.value_min) / header.value_span) as f32)
            .collect();
        // Axes of fewer than four samples have no pair of cells to copy from: no details there.
        let rho = if size[0] < 4 || size[1] < 4 {
            0.0
        } else {
            header.roughness
        };
        let (lo, hi) = crate::core::operator::extremes(&z);
        let over = OVERSHOOT * (hi - lo);
        let (clo, chi) = (lo - over, hi + over);
        let interval = crate::core::operator::invariant_interval(
            [(rho, clo - rho * chi, chi - rho * clo)].into_iter(),
        );
        Ok(ProjectedOperator {
            size,
            z,
            region: Region {
                origin: [0, 0],
                size: [0, 0],
            },
            records: Vec::new(),
            rho,
            interval,
            residual: Vec::new(),
            bounds: None,
            residual_max: f32::INFINITY,
            valid: [size[0] as f32, size[1] as f32],
        })
    }

    /// Bytes the operator holds (a cache's weight).
    pub fn resident_bytes(&self) -> u64 {
        let bounds = self.bounds.as_ref().map_or(0, |b| b.bytes());
        (4 * self.z.len() + 36 * self.records.len() + 4 * self.residual.len() + bounds) as u64
    }

    /// Whether the operator was built lazily (see [`Self::lazy`]).
    pub fn is_lazy(&self) -> bool {
        self.bounds.is_some()
    }

    /// Per cell, a bound on |f - S| there, S the bilinear interpolant of the samples. With
    /// r = f - S, `r(p) = d(p) + rho r(phi p)` where `d = g + rho S o phi - S`. On each quarter
    /// cell g is bilinear (the step blends its corners), phi maps the quarter onto one lattice
    /// cell where S is bilinear, and S is bilinear: d is bilinear there and its largest
    /// magnitude D_c over cell c is at the cell's nine half-lattice points, exactly. Then
    /// `R_c = D_c + rho max R_c'` over the 2 x 2 block Q of cells that phi maps c onto. Every
    /// cell of such a block (even-aligned) maps onto the block itself, so `max_Q R <= max_Q D +
    /// rho max_Q R`, that is `max_Q R <= max_Q D / (1 - rho)`, and
    /// `R_c = D_c + rho max_Q D / (1 - rho)`: the limit of iterating the recursion, in closed
    /// form (chains never leave their block, but for the unpaired last cell of an even axis,
    /// which maps onto the pair before it).
    pub(super) fn residual_bounds(&self, records: &[[f32; 9]]) -> Vec<f32> {
        use rayon::prelude::*;
        let [nx, ny] = self.size;
        let cells = (nx - 1) * (ny - 1);
        if self.rho >= 1.0 {
            return vec![f32::INFINITY; cells];
        }
        let d: Vec<f32> = (0..cells)
            .into_par_iter()
            .map(|k| self.excess((k % (nx - 1), k / (nx - 1)), &records[k]))
            .collect();
        (0..cells)
            .into_par_iter()
            .map(|k| self.closed_bound(&d, k % (nx - 1), k / (nx - 1)))
            .collect()
    }

    /// `R_c` of [`Self::residual_bounds`] for cell (i, j), from every cell's D (row-major).
    pub(super) fn closed_bound(&self, d: &[f32], i: usize, j: usize) -> f32 {
        let [nx, ny] = self.size;
        let k = j * (nx - 1) + i;
        // Axes of fewer than four samples have rho 0 (no pair of cells for phi): R = D.
        if self.rho == 0.0 {
            return d[k];
        }
        // The block phi maps the cell onto: cells 2 i - c and 2 i - c + 1 along each axis.
        let (x0, y0) = (2 * i - block(i, nx), 2 * j - block(j, ny));
        let q = y0 * (nx - 1) + x0;
        let most = d[q].max(d[q + 1]).max(d[q + nx - 1]).max(d[q + nx]);
        d[k] + self.rho * most / (1.0 - self.rho)
    }

    /// S, the bilinear interpolant of the samples, at a frame point (clamped as steps are).
    #[inline(always)]
    pub(super) fn bilinear(&self, p: [f32; 2]) -> f32 {
        let (i, u) = self.locate(p[0], self.size[0]);
        let (j, v) = self.locate(p[1], self.size[1]);
        let row = |y: usize| {
            let r = &self.z[y * self.size[0] + i..];
            r[0] + (r[1] - r[0]) * u
        };
        let (top, bottom) = (row(j), row(j + 1));
        top + (bottom - top) * v
    }

    /// The sample at (x, y), clamped into the grid (an axis of two samples has no pair of
    /// cells for phi to land on; its rho is 0, so the clamped value is never weighed).
    pub(super) fn at(&self, x: isize, y: isize) -> f32 {
        let x = x.clamp(0, self.size[0] as isize - 1) as usize;
        let y = y.clamp(0, self.size[1] as isize - 1) as usize;
        self.z[y * self.size[0] + x]
    }

    /// The Catmull-Rom interpolant at sample coordinates (x, y) of the samples on multiples of
    /// `k` (1: all of them; 2: the even lattice), edges replicated.
    pub(super) fn cubic(&self, x: f32, y: f32, k: usize) -> f32 {
        let axis = |t: f32, n: usize| {
            let last = (n - 1) / k;
            let u = (t / k as f32).clamp(0.0, last as f32);
            let c = (u as usize).min(last.saturating_sub(1));
            (c as isize, catmull_rom(u - c as f32), last as isize)
        };
        let (cx, wx, lx) = axis(x, self.size[0]);
        let (cy, wy, ly) = axis(y, self.size[1]);
        let k = k as isize;
        let mut v = 0.0;
        for (b, wb) in wy.iter().enumerate() {
            let row = (cy + b as isize - 1).clamp(0, ly) * k;
            let mut r = 0.0;
            for (a, wa) in wx.iter().enumerate() {
                r += wa * self.at((cx + a as isize - 1).clamp(0, lx) * k, row);
            }
            v += wb * r;
        }
        v
    }

    /// g at sample coordinates (x, y) of cell (i, j): the cubic interpolant of the samples less
    /// rho times the even lattice's at phi.
    pub(super) fn offset_at(&self, i: usize, j: usize, x: f32, y: f32) -> f32 {
        let (cx, cy) = (block(i, self.size[0]), block(j, self.size[1]));
        let (qx, qy) = (2.0 * x - cx as f32, 2.0 * y - cy as f32);
        self.cubic(x, y, 1) - self.rho * self.cubic(qx, qy, 2)
    }

    /// g at half-lattice point (a, b) in {0, 1, 2}^2 of cell (i, j), computed (what the
    /// records hold): at a sample, the sample less rho times the sample at phi (exactly, so
    /// that the continuation passes through the samples); elsewhere [`Self::offset_at`]. The
    /// reference records are tested against, and what a lazily built operator evaluates for a
    /// cell outside its window.
    pub(super) fn half_point(&self, i: usize, j: usize, a: usize, b: usize) -> f32 {
        if a.is_multiple_of(2) && b.is_multiple_of(2) {
            let (x, y) = ((i + a / 2) as isize, (j + b / 2) as isize);
            let (cx, cy) = (
                block(i, self.size[0]) as isize,
                block(j, self.size[1]) as isize,
            );
            return self.at(x, y) - self.rho * self.at(2 * x - cx, 2 * y - cy);
        }
        self.offset_at(i, j, i as f32 + 0.5 * a as f32, j as f32 + 0.5 * b as f32)
    }

    /// The cell of sample coordinate `t` along an axis of `n` samples, and the position in it.
    #[inline(always)]
    pub(super) fn locate(&self, t: f32, n: usize) -> (usize, f32) {
        let t = (t - 0.5).clamp(0.0, (n - 1) as f32);
        // t is in [0, n - 1] here (a NaN clamps to NaN and truncates to some value the min
        // bounds): one instruction, where `as usize` adds fix-ups for what cannot happen.
        let c = (crate::codecs::quadtree::operator::truncate(t).max(0) as usize).min(n - 2);
        (c, t - c as f32)
    }

    /// Whether chains end on S with a residual bound a cell ([`Operator::run_chains`]): unless
    /// the bounds are no tighter than the invariant interval's (or NaN). A lazily built
    /// operator without a window does not know its largest bound: its chains end on S
    /// (whichever end a chain takes, its bound holds), nor do its windows and its lattice, so
    /// that all take the same end.
    pub(super) fn ends_on_samples(&self) -> bool {
        if self.is_lazy() {
            return self.rho < 1.0;
        }
        let (lo, hi) = self.interval;
        !self.residual_max.is_nan() && self.residual_max < 0.5 * (hi - lo)
    }

    /// The residual bound of the cell of frame point `q`.
    #[inline(always)]
    pub(super) fn residual_at(&self, q: [f32; 2]) -> f32 {
        let (i, _) = self.locate(q[0], self.size[0]);
        let (j, _) = self.locate(q[1], self.size[1]);
        self.residual_of(i, j)
    }

    /// The residual bound of cell (i, j): from the region, or outside it the lazily built
    /// operator's (or evaluated).
    #[inline(always)]
    pub(super) fn residual_of(&self, i: usize, j: usize) -> f32 {
        match self.region.index(i, j) {
            Some(k) => self.residual[k],
            None => self.residual_outside(i, j),
        }
    }

    /// [`Self::residual_of`] of a cell outside the region.
    #[cold]
    #[inline(never)]
    pub(super) fn residual_outside(&self, i: usize, j: usize) -> f32 {
        match &self.bounds {
            Some(b) => b.at(&|rect| self.bounds_for(rect).1, i, j),
            // An operator of samples alone (tests): from the records of the cells around it.
            None => self.bounds_for([i, j, i + 1, j + 1]).1[0],
        }
    }

    /// The f32 rounding of a chain's sums a step, a few ulps of the largest value: with a bound
    /// of |acc_s| R the chain's own rounding would no longer hide under it.
    pub(super) fn chain_ulps(&self) -> f32 {
        let (lo, hi) = self.interval;
        2f32.powi(-21) * lo.abs().max(hi.abs()).max(1.0)
    }

    /// Ends a chain that has stopped on S at its point, folded into the callers' seed form
    /// (see [`Operator::run_chains`]).
    #[inline(always)]
    pub(super) fn end_chain(&self, c: &mut Chain<2>) {
        let (lo, hi) = self.interval;
        let (mid, half) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        let bound =
            c.acc_s.abs() * self.residual_at(c.q) + (c.taken + 4) as f32 * self.chain_ulps();
        let folded = bound / half;
        c.acc_g += c.acc_s * self.bilinear(c.q) - folded * mid;
        c.acc_s = folded;
    }

    /// The operator with unit coordinates mapped onto `[0, valid)` of its frame (chroma planes:
    /// the luma's extent halved).
    pub fn with_valid(mut self, valid: [f32; 2]) -> ProjectedOperator {
        self.valid = valid;
        self
    }

    /// The decoded samples, normalised, row-major: the attractor at the sample centres.
    pub fn samples(&self) -> &[f32] {
        &self.z
    }

    /// The detail scaling rho.
    pub fn roughness(&self) -> f32 {
        self.rho
    }

    /// Cells of the operator (each in four quarters).
    pub fn cells(&self) -> usize {
        (self.size[0] - 1) * (self.size[1] - 1)
    }

    /// g at the corners of quarter (qa, qb) of cell (i, j), in the order (0,0), (1,0), (0,1),
    /// (1,1).
    #[inline(always)]
    pub(super) fn quarter(&self, i: usize, j: usize, qa: usize, qb: usize) -> [f32; 4] {
        match self.region.index(i, j) {
            Some(k) => {
                let r = &self.records[k];
                let n = 3 * qb + qa;
                [r[n], r[n + 1], r[n + 3], r[n + 4]]
            }
            None => self.quarter_direct(i, j, qa, qb),
        }
    }

    /// [`Self::quarter`] of a cell outside the region, evaluated (the same bits, slower).
    #[cold]
    #[inline(never)]
    pub(super) fn quarter_direct(&self, i: usize, j: usize, qa: usize, qb: usize) -> [f32; 4] {
        let g = |a: usize, b: usize| self.half_point(i, j, qa + a, qb + b);
        [g(0, 0), g(1, 0), g(0, 1), g(1, 1)]
    }
}

impl Operator<2> for ProjectedOperator {
    fn frame(&self) -> [f32; 2] {
        [self.size[0] as f32, self.size[1] as f32]
    }

    fn valid(&self) -> [f32; 2] {
        self.valid
    }

    /// 1: samples are points, so the discrete decoder samples the previous iterate at phi(p).
    fn expansion(&self) -> u32 {
        1
    }

    /// Samples sit on frame pixel centres k + 0.5.
    #[inline(always)]
    fn step(&self, p: [f32; 2]) -> Step<2> {
        let (i, u) = self.locate(p[0], self.size[0]);
        let (j, v) = self.locate(p[1], self.size[1]);
        let (qa, qb) = (usize::from(u >= 0.5), usize::from(v >= 0.5));
        let (uu, vv) = (2.0 * u - qa as f32, 2.0 * v - qb as f32);
        let g = self.quarter(i, j, qa, qb);
        let (cx, cy) = (block(i, self.size[0]), block(j, self.size[1]));
        let top = g[0] + (g[1] - g[0]) * uu;
        let bottom = g[2] + (g[3] - g[2]) * uu;
        Step {
            offset: top + (bottom - top) * vv,
            contrast: self.rho,
            next: [
                2.0 * (i as f32 + u) - cx as f32 + 0.5,
                2.0 * (j as f32 + v) - cy as f32 + 0.5,
            ],
        }
    }

    fn invariant_interval(&self) -> (f32, f32) {
        self.interval
    }

    /// Chains stop once `|prod s|` times the residual bound of the cell they are in is under
    /// the tolerance, and end on S, the bilinear interpolant, at their last point q, where f
    /// is S plus a residual within that bound. Callers read a chain as `acc_g + acc_s * seed`
    /// within `|acc_s| * half` (the invariant interval's middle and half-width); the tail is
    /// folded into that form, `acc_s` set to the bound over `half`, so their value is
    /// `acc_g + acc_s * S(q)` and their bound `|acc_s| * R(q)` plus the chain's f32 rounding.
    /// A chain is not stepped again after this (every caller finishes it).
    fn run_chains(&self, chains: &mut [Chain<2>], iterations: u32, tolerance: f32) {
        if !self.ends_on_samples() {
            return crate::core::operator::run_chains_stepwise(self, chains, iterations, tolerance);
        }
        let residual = |q: [f32; 2]| self.residual_at(q);
        // Eight chains in lockstep, as `run_chains_stepwise` does: a chain's steps are
        // dependent loads, and independent chains side by side overlap them. The lanes are a
        // copy on the stack: stepping the caller's slice in place ran 2.3 times slower on some
        // of its addresses (the same chains, bit for bit, measured on etopo20: 14.9 against
        // 6.4 ms for 65,536 points), a layout effect a copy removes.
        const LANES: usize = 8;
        let idle = Chain {
            q: [0.0; 2],
            acc_g: 0.0,
            acc_s: 0.0,
            taken: u32::MAX,
        };
        for batch in chains.chunks_mut(LANES) {
            let mut lanes = [idle; LANES];
            lanes[..batch.len()].copy_from_slice(batch);
            loop {
                let mut any = false;
                for c in lanes.iter_mut() {
                    if c.taken >= iterations
                        || !crate::core::operator::active(c.acc_s, residual(c.q), tolerance)
                    {
                        continue;
                    }
                    let st = self.step(c.q);
                    c.taken += 1;
                    c.acc_g += c.acc_s * st.offset;
                    c.acc_s *= st.contrast;
                    c.q = st.next;
                    any = true;
                }
                if !any {
                    break;
                }
            }
            for (c, lane) in batch.iter_mut().zip(&lanes) {
                *c = *lane;
                self.end_chain(c);
            }
        }
    }
}

impl crate::core::pieces::Flatten for ProjectedOperator {
    /// Four pieces per cell, one per quarter (336 bytes a sample as a table; the GPU takes the
    /// lattice of `flat`, 36).
    fn pieces(&self) -> crate::core::pieces::PieceTable {
        use crate::core::pieces::{Piece, PieceTable};
        let q = self.quarters();
        let lx = q.columns.len();
        let pieces = (0..q.offsets.cells())
            .map(|k| {
                let (a, b) = (k % lx, k / lx);
                Piece {
                    origin: [0.5 + 0.5 * a as f32, 0.5 + 0.5 * b as f32],
                    inv_size: [2.0, 2.0],
                    g: q.offsets.of(a, b, lx),
                    s: q.contrast,
                    next_x: q.columns[a],
                    next_y: q.rows[b],
                }
            })
            .collect::<Vec<_>>();
        PieceTable {
            frame: q.frame,
            valid: q.valid,
            lut_origin: q.lut_origin,
            lut_cell: q.lut_cell,
            lut_size: q.lut_size,
            lut: (0..pieces.len() as u32).collect(),
            pieces,
            interval: q.interval,
        }
    }

    /// The quarter cells as a lattice, built directly.
    fn flat(&self) -> crate::core::pieces::Flat {
        crate::core::pieces::Flat::Lattice(self.quarters())
    }
}

impl ProjectedOperator {
    /// The quarter cells (a lattice on the half-sample grid from the first sample centre): a
    /// quarter's offset is the bilinear function through its corners' values, which are its
    /// cell's record (the lattice's offsets in blocks, a block a cell); its map doubles it about
    /// the centre of its block.
    pub(super) fn quarters(&self) -> crate::core::pieces::Lattice {
        let [nx, ny] = self.size;
        let (lx, ly) = (2 * (nx - 1), 2 * (ny - 1));
        let map = |a: usize, n: usize| {
            let x0 = 0.5 * a as f32;
            2.0 * x0 - block(a / 2, n) as f32 + 0.5
        };
        // An operator that holds records for only part of its cells (a chunk's holds none: a
        // request builds those of its own cells) builds them and their bounds for all, on
        // every core, the same bits as `quarter`'s direct evaluation (which took a 1025 x 1080
        // chunk 850 ms).
        let all = self.region.origin == [0, 0] && self.region.size == [nx - 1, ny - 1];
        let whole = if all {
            std::borrow::Cow::Borrowed(self)
        } else {
            std::borrow::Cow::Owned(self.with_region([0, 0, nx - 1, ny - 1]))
        };
        crate::core::pieces::Lattice {
            frame: self.frame(),
            valid: self.valid,
            lut_origin: [0.5; 2],
            lut_cell: [0.5; 2],
            lut_size: [lx as u32, ly as u32],
            contrast: [self.rho, 0.0, 0.0, 0.0],
            offsets: crate::core::pieces::Offsets::Blocks(whole.records.clone()),
            columns: (0..lx).map(|a| [map(a, nx), 1.0, 0.0, 0.0]).collect(),
            rows: (0..ly).map(|b| [map(b, ny), 0.0, 1.0, 0.0]).collect(),
            interval: self.interval,
            ends: whole.ends_on_samples().then(|| crate::core::pieces::Ends {
                size: [nx as u32, ny as u32],
                samples: self.z.to_vec(),
                residual: whole.residual.clone(),
                ulps: self.chain_ulps(),
            }),
        }
    }
}
