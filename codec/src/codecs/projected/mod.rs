//! The projected IFS with details on height fields (`projected`): the model of seed 001 (Guérin,
//! Tosan et al.) on a grid. A coarse grid of control points, subdivision masks fitted to the
//! data level by level (the fractal part), and details at every level (the wavelet part), coded
//! the way near-lossless image coders code residuals ([`pyramid`]).
//!
//! Two modes:
//! - **max error** (`--max-error E`): every decoded sample is within E of its source (in source
//!   units), because each detail is quantised in closed loop with a step of 2E (an odd multiple
//!   of the quantum for integer data). The measured ratio is reported beside LERC and JPEG-LS
//!   near-lossless, which make the same promise.
//! - **rate** (`--target-bpp`): the step is found by bisection, and the levels are lifted
//!   ([`lifting`]): each coarse grid holds local means, not samples, which is what approximates
//!   the surface best at a given rate (the pyramid is coded too, and kept where it codes
//!   better: at high rates on images with large flat areas).
//!
//! Past the finest level the surface is continued by a partitioned affine operator of the
//! form every decoder of fractile evaluates ([`ProjectedOperator`]): in each cell between four
//! decoded samples, `f = B1 + rho (f o phi - B2 o phi)`, where B1 interpolates the samples
//! bilinearly, phi maps the cell onto the even-aligned 2 x 2 block of cells that holds it (scale
//! 2), and B2 interpolates the block's corners. At the samples themselves phi lands on samples
//! of the even lattice, where `f - B2` is zero, so the surface passes through every decoded
//! sample; between them it carries the details of the next coarser octave scaled by rho, and
//! so on down every octave: the roughness of the source continues self-similarly. rho is
//! fitted per asset as the ratio of the finest two octaves' detail amplitudes.

pub mod encode;
pub mod grid;
pub mod lifting;
mod neighbourhood;
pub mod plane;
pub mod pyramid;
pub mod records;
mod residual;
pub mod subdivision;

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::core::entropy::{Decoder, Encoder};
use crate::core::operator::{Chain, Operator, Step};

/// What a reader needs to decode a plane's stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProjectedHeader {
    /// Source width and height in samples.
    pub samples: [u32; 2],
    /// Refinement levels: the control grid has a sample every `2^levels`.
    pub levels: u8,
    /// Quantiser step of the finest level, source units.
    pub step: f64,
    /// Step growth per coarser level (1 in max-error mode).
    pub growth: f64,
    /// The source's quantum (0 for continuous values).
    pub quantum: f64,
    /// Lowest value of the coding range (source units): decoded samples are normalised by it.
    pub value_min: f64,
    /// Width of the coding range.
    pub value_span: f64,
    /// The detail scaling of the continuation past the finest level, in [0, 0.95].
    pub roughness: f32,
    /// The bound the encoder promised (source units); 0 with a quantum is lossless, 0 without
    /// one is rate mode (no promise, see [`ProjectedHeader::promise`]).
    pub max_error: f64,
    /// The multiresolution: the pyramid's order of each level's passes (the encoder keeps the
    /// one that codes smaller), or a lifted kernel (rate mode).
    pub order: pyramid::Order,
}

impl ProjectedHeader {
    /// Rejects headers no encoder writes.
    pub fn validate(&self) -> Result<(), String> {
        let [w, h] = self.samples;
        if !(2..=1 << 16).contains(&w) || !(2..=1 << 16).contains(&h) {
            return Err(format!("bad projected sample grid {w}x{h}"));
        }
        if self.levels > 12 {
            return Err(format!("bad projected level count {}", self.levels));
        }
        let finite = [
            self.step,
            self.growth,
            self.quantum,
            self.value_min,
            self.value_span,
        ];
        if finite.iter().any(|v| !v.is_finite()) || self.step <= 0.0 {
            return Err("bad projected quantiser".into());
        }
        if !(0.5..=4.0).contains(&self.growth) || self.quantum < 0.0 || self.value_span <= 0.0 {
            return Err("bad projected step growth, quantum or value range".into());
        }
        if !(0.0..=0.95).contains(&self.roughness) {
            return Err(format!("bad projected roughness {}", self.roughness));
        }
        if self.order.lifting().is_some() && (self.max_error != 0.0 || self.quantum != 0.0) {
            return Err("a lifted projected plane makes no per-sample promise".into());
        }
        Ok(())
    }

    fn layout(&self) -> pyramid::Layout {
        pyramid::Layout {
            size: [self.samples[0] as usize, self.samples[1] as usize],
            levels: u32::from(self.levels),
            step: self.step,
            growth: self.growth,
            quantum: self.quantum,
            order: self.order,
        }
    }

    /// The encoder's promise at every valid sample, source units: `max_error` in max-error mode
    /// (which sets a quantum, or a positive bound on continuous data); none under rate control.
    /// Decoded values are f32 fractions of the value range, and a continuous decode sums a
    /// chain of them, so the promise carries their rounding: 2^-20 of the range (0.015 m on
    /// etopo20; the encoder checks its samples with 2^-22, the chain measured up to 4 times
    /// that).
    pub fn promise(&self) -> Option<f64> {
        (self.max_error > 0.0 || self.quantum > 0.0)
            .then_some(self.max_error + self.value_span * 2f64.powi(-20))
    }

    /// Samples in all.
    pub fn cells(&self) -> usize {
        self.samples[0] as usize * self.samples[1] as usize
    }
}

/// The codec's name (`fractile encode --codec projected`).
pub const CODEC_NAME: &str = "projected";

pub use pyramid::levels_for;

/// Codes a grid (source units, invalid cells filled) under `header` with a dead zone (the
/// pyramid's) and a rate-distortion weight (rate mode only); returns the stream and the decoded
/// samples.
pub fn encode_grid(
    header: &ProjectedHeader,
    source: &[f64],
    valid: Option<&[bool]>,
    (dead_zone, lambda): (f64, f64),
) -> (Vec<u8>, Vec<f64>) {
    // A promise per sample leaves no room for rate-distortion choices.
    let lambda = if header.max_error == 0.0 && header.quantum == 0.0 {
        lambda
    } else {
        0.0
    };
    let layout = header.layout();
    if let Some(kernel) = layout.order.lifting() {
        return lifting::encode(&lifted_plane(&layout, kernel), source, lambda);
    }
    let mut g = vec![0.0; header.cells()];
    let mut q = pyramid::Quantiser {
        source,
        valid,
        dead_zone,
        lambda,
        encoder: Encoder::new(),
        coders: pyramid::Coders::new(),
    };
    let target = |i: usize| valid.is_none_or(|v| v[i]).then(|| source[i]);
    pyramid::walk(&layout, &mut g, &mut q, Some(&target));
    (q.encoder.finish(), g)
}

/// A lifted plane's parameters from its layout (its dead zone and step growth are the pyramid's
/// alone: band steps follow from the synthesis gains).
fn lifted_plane(layout: &pyramid::Layout, kernel: lifting::Kernel) -> lifting::Plane {
    lifting::Plane {
        size: layout.size,
        levels: layout.levels,
        step: layout.step,
        kernel,
        ends: lifting::Ends::Mirror,
    }
}

/// Decodes a plane's samples (source units).
pub fn decode_grid(header: &ProjectedHeader, stream: &[u8]) -> Result<Vec<f64>, String> {
    header.validate()?;
    // Every sample costs at least one decision: refuse a header that claims more than the stream
    // can hold before allocating for it.
    let most = crate::core::entropy::most_decisions(stream.len());
    if header.cells() as u64 > most {
        return Err(format!(
            "a projected stream of {} bytes cannot hold {} samples",
            stream.len(),
            header.cells()
        ));
    }
    let layout = header.layout();
    let mut decoder = Decoder::new(stream);
    let g = if let Some(kernel) = layout.order.lifting() {
        lifting::decode(&lifted_plane(&layout, kernel), &mut decoder)
    } else {
        let mut g = vec![0.0; header.cells()];
        let mut r = pyramid::Reader {
            decoder,
            coders: pyramid::Coders::new(),
        };
        pyramid::walk(&layout, &mut g, &mut r, None);
        decoder = r.decoder;
        g
    };
    if decoder.overrun() || g.iter().any(|v| !v.is_finite()) {
        return Err("projected stream truncated or corrupt".into());
    }
    Ok(g)
}

/// The coarse view at `depth` of a coded plane: its multiresolution's samples on multiples of
/// `2^depth`, decoded from the coarse part of its stream alone, in source units, with the
/// header of a plane of that grid (no promise: see below). What a chunked file's derived levels
/// are (`io::chunked`, format 7): the overview of `2^depth` cells a side that no longer needs
/// coding beside the source.
///
/// A lifted plane's coarse samples are the analysis low-pass at that depth (local means of
/// about `2^depth` cells, divided here by the kernel's gain); the pyramid's are decoded samples
/// of the source's own lattice (closed loop, so each within the plane's promise of its source
/// cell). Either stands for the cells around it, not for one cell, so the view's header makes
/// no per-sample promise: its error is measured against the source's box means at encode time.
///
/// Also returns the bytes of the stream it read: the prefix a reader of that depth needs
/// (bands are coded coarsest first).
pub fn decode_coarse(
    header: &ProjectedHeader,
    stream: &[u8],
    depth: u32,
) -> Result<(ProjectedHeader, Vec<f64>, usize), String> {
    header.validate()?;
    if depth == 0 || depth > 12 {
        return Err(format!("no coarse view at depth {depth}"));
    }
    // A plane of fewer levels (a thin chunk) is read whole below its coarsest level, and its
    // samples on multiples of 2^depth taken.
    let read = depth.min(u32::from(header.levels));
    let most = crate::core::entropy::most_decisions(stream.len());
    if (header.cells() >> (2 * depth.min(u32::from(header.levels)))) as u64 > most {
        return Err("projected stream too short for its grid".into());
    }
    let layout = header.layout();
    let mut decoder = Decoder::new(stream);
    let (g, gain) = if let Some(kernel) = layout.order.lifting() {
        let plane = lifted_plane(&layout, kernel);
        let g = lifting::decode_to(&plane, &mut decoder, read);
        (g, lifting::dc_gain(kernel).powi(2 * read as i32))
    } else {
        let mut g = vec![0.0; header.cells()];
        let mut r = pyramid::Reader {
            decoder,
            coders: pyramid::Coders::new(),
        };
        pyramid::walk_to(&layout, &mut g, &mut r, None, read);
        decoder = r.decoder;
        (g, 1.0)
    };
    let [w, h] = layout.size;
    let s = 1usize << depth;
    let (cw, ch) = (w.div_ceil(s), h.div_ceil(s));
    let mut coarse = Vec::with_capacity(cw * ch);
    for y in (0..h).step_by(s) {
        coarse.extend((0..w).step_by(s).map(|x| g[y * w + x] / gain));
    }
    if decoder.overrun() || coarse.iter().any(|v| !v.is_finite()) {
        return Err("projected stream truncated or corrupt".into());
    }
    let view = ProjectedHeader {
        samples: [cw as u32, ch as u32],
        levels: header.levels - read as u8,
        max_error: 0.0,
        quantum: 0.0,
        ..header.clone()
    };
    view.validate()?;
    Ok((view, coarse, decoder.consumed()))
}

/// The roughness of the continuation: how much the details of one octave shrink into the next
/// finer one, measured on the decoded grid as the ratio of the RMS residuals of cubic
/// (Catmull-Rom) midpoint prediction at spacings 1 and 2 (`2^-H` for a surface of Hurst
/// exponent H; the smooth part of the surface, which shrinks by 1/4 an octave, is what the
/// cubic predicts and so leaves out), within [0, 0.9].
pub fn fit_roughness(g: &[f64], w: usize, h: usize) -> f32 {
    let rms = |k: usize| {
        let (mut sum, mut n) = (0.0, 0usize);
        let mid = |a: f64, b: f64, c: f64, d: f64| (9.0 * (b + c) - a - d) / 16.0;
        for y in 0..h {
            for x in (3 * k..w.saturating_sub(3 * k)).step_by(2 * k) {
                let i = y * w + x;
                let d = g[i] - mid(g[i - 3 * k], g[i - k], g[i + k], g[i + 3 * k]);
                sum += d * d;
                n += 1;
            }
        }
        for y in (3 * k..h.saturating_sub(3 * k)).step_by(2 * k) {
            for x in 0..w {
                let i = y * w + x;
                let r = |o: usize| g[i - o * w];
                let s = |o: usize| g[i + o * w];
                let d = g[i] - mid(r(3 * k), r(k), s(k), s(3 * k));
                sum += d * d;
                n += 1;
            }
        }
        (sum / n.max(1) as f64).sqrt()
    };
    let (fine, coarse) = (rms(1), rms(2));
    // A surface the cubic predicts to rounding (a plane, a cubic) has no roughness to continue.
    let scale = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if coarse > 1e-9 * scale {
        (fine / coarse).clamp(0.0, 0.9) as f32
    } else {
        0.0
    }
}

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
    size: [usize; 2],
    /// Decoded samples, normalised (shared with the windows of a lazily built operator).
    z: Arc<[f32]>,
    /// The cells whose records and residual bounds are at hand: all of them for an operator
    /// built whole, none for one built lazily, a request's for a window of one (see
    /// [`records`]).
    region: Region,
    /// Per cell of `region`, g at the half-lattice points (a/2, b/2), a, b in 0..3, at
    /// `3 b + a`.
    records: Vec<[f32; 9]>,
    rho: f32,
    interval: (f32, f32),
    /// Per cell of `region`, a bound on |f - S| there, S the bilinear interpolant of the
    /// samples (see [`Self::residual_bounds`]): chains end on S instead of a constant, so they
    /// need the steps that take the bound where they are, not the value range, under the
    /// tolerance.
    residual: Vec<f32>,
    /// Of a lazily built operator: every cell's residual bound, coded in a byte.
    coded: Option<Arc<residual::ResidualCodes>>,
    /// The largest residual bound.
    residual_max: f32,
    /// The part of the frame unit coordinates map onto (the frame, or for half-resolution
    /// chroma of an odd-sized image, half the luma's extent).
    valid: [f32; 2],
}

/// A rectangle of cells.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Region {
    /// Its first cell.
    origin: [usize; 2],
    /// Cells along each axis.
    size: [usize; 2],
}

impl Region {
    /// The index of cell (i, j) in the region's row-major arrays, if it is inside.
    #[inline(always)]
    fn index(&self, i: usize, j: usize) -> Option<usize> {
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
fn block(i: usize, n: usize) -> usize {
    if i % 2 == 1 {
        i + 1
    } else if i + 2 < n {
        i
    } else {
        i + 2
    }
}

/// Catmull-Rom weights at t in [0, 1] for the samples at -1, 0, 1, 2.
fn catmull_rom(t: f32) -> [f32; 4] {
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
const OVERSHOOT: f32 = 0.29;

impl ProjectedOperator {
    /// The operator of decoded samples `grid` (source units) under `header`, built whole: a
    /// record and a residual bound a cell (about 44 bytes a sample with the sample).
    pub fn new(header: &ProjectedHeader, grid: &[f64]) -> Result<ProjectedOperator, String> {
        let mut op = ProjectedOperator::samples_only(header, grid)?;
        op.records = op.all_records();
        op.region.size = [op.size[0] - 1, op.size[1] - 1];
        op.residual = op.residual_bounds();
        op.residual_max = op.residual.iter().fold(0.0, |m: f32, &r| m.max(r));
        Ok(op)
    }

    /// The operator of decoded samples `grid` under `header`, built lazily: its samples and a
    /// residual bound a cell coded in a byte (5 bytes a sample), the records of the cells a
    /// request needs built for it ([`Self::window`]). The same values as [`Self::new`]'s
    /// operator where chains take the same steps; its residual bounds are rounded up by at
    /// most 9%, so a chain may take a step more to reach a tolerance. What chunks of chunked
    /// assets use (see [`records`]).
    pub fn lazy(header: &ProjectedHeader, grid: Vec<f64>) -> Result<ProjectedOperator, String> {
        // The grid goes once the samples are made: it is twice their size, and a server builds
        // chunks' operators a core at a time.
        let mut op = ProjectedOperator::samples_only(header, &grid)?;
        drop(grid);
        let coded = op.residual_codes();
        op.residual_max = coded.max();
        op.coded = Some(Arc::new(coded));
        Ok(op)
    }

    /// The samples, rho and the invariant interval; no records yet.
    fn samples_only(header: &ProjectedHeader, grid: &[f64]) -> Result<ProjectedOperator, String> {
        header.validate()?;
        if grid.len() != header.cells() {
            return Err("projected grid does not match its header".into());
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
        let (lo, hi) = z
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
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
            coded: None,
            residual_max: f32::INFINITY,
            valid: [size[0] as f32, size[1] as f32],
        })
    }

    /// Bytes the operator holds (a cache's weight).
    pub fn resident_bytes(&self) -> u64 {
        let coded = self.coded.as_ref().map_or(0, |c| c.bytes());
        (4 * self.z.len() + 36 * self.records.len() + 4 * self.residual.len() + coded) as u64
    }

    /// Whether the operator was built lazily (see [`Self::lazy`]).
    pub fn is_lazy(&self) -> bool {
        self.coded.is_some()
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
    fn residual_bounds(&self) -> Vec<f32> {
        use rayon::prelude::*;
        let [nx, ny] = self.size;
        let cells = (nx - 1) * (ny - 1);
        if self.rho >= 1.0 {
            return vec![f32::INFINITY; cells];
        }
        let d: Vec<f32> = (0..cells)
            .into_par_iter()
            .map(|k| self.excess((k % (nx - 1), k / (nx - 1)), &self.records[k]))
            .collect();
        (0..cells)
            .into_par_iter()
            .map(|k| self.closed_bound(&d, k % (nx - 1), k / (nx - 1)))
            .collect()
    }

    /// `R_c` of [`Self::residual_bounds`] for cell (i, j), from every cell's D (row-major).
    fn closed_bound(&self, d: &[f32], i: usize, j: usize) -> f32 {
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
    fn bilinear(&self, p: [f32; 2]) -> f32 {
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
    fn at(&self, x: isize, y: isize) -> f32 {
        let x = x.clamp(0, self.size[0] as isize - 1) as usize;
        let y = y.clamp(0, self.size[1] as isize - 1) as usize;
        self.z[y * self.size[0] + x]
    }

    /// The Catmull-Rom interpolant at sample coordinates (x, y) of the samples on multiples of
    /// `k` (1: all of them; 2: the even lattice), edges replicated.
    fn cubic(&self, x: f32, y: f32, k: usize) -> f32 {
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
    fn offset_at(&self, i: usize, j: usize, x: f32, y: f32) -> f32 {
        let (cx, cy) = (block(i, self.size[0]), block(j, self.size[1]));
        let (qx, qy) = (2.0 * x - cx as f32, 2.0 * y - cy as f32);
        self.cubic(x, y, 1) - self.rho * self.cubic(qx, qy, 2)
    }

    /// g at half-lattice point (a, b) in {0, 1, 2}^2 of cell (i, j), computed (what the
    /// records hold): at a sample, the sample less rho times the sample at phi (exactly, so
    /// that the continuation passes through the samples); elsewhere [`Self::offset_at`]. The
    /// reference records are tested against, and what a lazily built operator evaluates for a
    /// cell outside its window.
    fn half_point(&self, i: usize, j: usize, a: usize, b: usize) -> f32 {
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
    fn locate(&self, t: f32, n: usize) -> (usize, f32) {
        let t = (t - 0.5).clamp(0.0, (n - 1) as f32);
        // t is in [0, n - 1] here (a NaN clamps to NaN and truncates to some value the min
        // bounds): one instruction, where `as usize` adds fix-ups for what cannot happen.
        let c = (crate::codecs::quadtree::operator::truncate(t).max(0) as usize).min(n - 2);
        (c, t - c as f32)
    }

    /// Whether chains end on S with a residual bound a cell ([`Operator::run_chains`]): unless
    /// the bounds are no tighter than the invariant interval's (or NaN).
    fn ends_on_samples(&self) -> bool {
        let (lo, hi) = self.interval;
        !self.residual_max.is_nan() && self.residual_max < 0.5 * (hi - lo)
    }

    /// The residual bound of the cell of frame point `q`.
    #[inline(always)]
    fn residual_at(&self, q: [f32; 2]) -> f32 {
        let (i, _) = self.locate(q[0], self.size[0]);
        let (j, _) = self.locate(q[1], self.size[1]);
        self.residual_of(i, j)
    }

    /// The residual bound of cell (i, j): from the region, or outside it its coded one.
    #[inline(always)]
    fn residual_of(&self, i: usize, j: usize) -> f32 {
        match self.region.index(i, j) {
            Some(k) => self.residual[k],
            None => self
                .coded
                .as_ref()
                .map_or(f32::INFINITY, |c| c.at(j * (self.size[0] - 1) + i)),
        }
    }

    /// The f32 rounding of a chain's sums a step, a few ulps of the largest value: with a bound
    /// of |acc_s| R the chain's own rounding would no longer hide under it.
    fn chain_ulps(&self) -> f32 {
        let (lo, hi) = self.interval;
        2f32.powi(-21) * lo.abs().max(hi.abs()).max(1.0)
    }

    /// Ends a chain that has stopped on S at its point, folded into the callers' seed form
    /// (see [`Operator::run_chains`]).
    #[inline(always)]
    fn end_chain(&self, c: &mut Chain<2>) {
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
    fn quarter(&self, i: usize, j: usize, qa: usize, qb: usize) -> [f32; 4] {
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
    fn quarter_direct(&self, i: usize, j: usize, qa: usize, qb: usize) -> [f32; 4] {
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
    fn quarters(&self) -> crate::core::pieces::Lattice {
        let [nx, ny] = self.size;
        let (lx, ly) = (2 * (nx - 1), 2 * (ny - 1));
        let map = |a: usize, n: usize| {
            let x0 = 0.5 * a as f32;
            2.0 * x0 - block(a / 2, n) as f32 + 0.5
        };
        let whole = self.region.origin == [0, 0] && self.region.size == [nx - 1, ny - 1];
        let records = if whole {
            self.records.clone()
        } else {
            // An operator that holds records for only part of its cells (a chunk's holds
            // none: a request builds those of its own cells) builds them from the half
            // lattices, a band of cell rows at a time on every core, the same bits as
            // `quarter`'s direct evaluation (which took a 1025 x 1080 chunk 850 ms).
            use rayon::prelude::*;
            let mut all = vec![[0.0f32; 9]; (nx - 1) * (ny - 1)];
            all.par_chunks_mut(residual::BAND * (nx - 1))
                .enumerate()
                .for_each(|(band, out)| {
                    let j0 = band * residual::BAND;
                    let j1 = (j0 + residual::BAND).min(ny - 1);
                    self.records_into([0, j0, nx - 1, j1], out);
                });
            all
        };
        crate::core::pieces::Lattice {
            frame: self.frame(),
            valid: self.valid,
            lut_origin: [0.5; 2],
            lut_cell: [0.5; 2],
            lut_size: [lx as u32, ly as u32],
            contrast: [self.rho, 0.0, 0.0, 0.0],
            offsets: crate::core::pieces::Offsets::Blocks(records),
            columns: (0..lx).map(|a| [map(a, nx), 1.0, 0.0, 0.0]).collect(),
            rows: (0..ly).map(|b| [map(b, ny), 0.0, 1.0, 0.0]).collect(),
            interval: self.interval,
            ends: self.ends_on_samples().then(|| crate::core::pieces::Ends {
                size: [nx as u32, ny as u32],
                samples: self.z.to_vec(),
                residual: (0..(nx - 1) * (ny - 1))
                    .map(|k| self.residual_of(k % (nx - 1), k / (nx - 1)))
                    .collect(),
                ulps: self.chain_ulps(),
            }),
        }
    }
}

/// Settings of the projected encoder.
#[derive(Clone, Debug, PartialEq)]
pub struct ProjectedSettings {
    /// The bound on |decoded - source| at every valid sample, source units (max-error mode).
    pub max_error: Option<f64>,
    /// Rate mode with the interpolating pyramid's closed loop alone, not also the lifted
    /// levels (to measure one against the other: 0.6-1.2 dB worse at 40:1 and 80:1 on DEMs).
    pub pyramid: bool,
    /// Step growth per coarser level in rate mode, with the pyramid.
    pub growth: f64,
    /// Dead zone in rate mode with the pyramid, as a fraction of a step.
    pub dead_zone: f64,
    /// Rate mode: the weight of a bit against squared error in steps^2 when a detail may move
    /// one step towards zero.
    pub lambda: f64,
    /// Under a target rate: the smallest max error whose file fits, every cell within it (the
    /// max-error quantiser, no dead zone), instead of the best PSNR. Costs 1.8 dB at 0.8 bpp
    /// on etopo20 and jacksboro, and gives a bound that holds at every cell.
    pub bounded: bool,
    /// Rate mode at this step and design, no rate control of its own: the chunks of a file
    /// whose rate is the file's ([`crate::encode::rate`]) share one step found for them all.
    pub at_step: Option<AtStep>,
    /// A trial coding whose file is not kept (a rate search's): no source-error map is
    /// measured (the map took most of an encode), the file has none.
    pub trial: bool,
    /// A size: the file at most this many bits a source cell (with `bounded`, or alone:
    /// the best PSNR that fits); `None` with `max_error`.
    pub target_bpp: Option<f64>,
}

/// A step (source units) and the multiresolution that codes at it: a lifted kernel
/// ([`pyramid::Order::Lifted`], [`pyramid::Order::Lifted97`]) or `None`, the pyramid (its order chosen).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AtStep {
    /// The quantiser's step, source units.
    pub step: f64,
    /// The multiresolution.
    pub design: Option<pyramid::Order>,
}

impl Default for ProjectedSettings {
    fn default() -> Self {
        // Measured on etopo20 and jacksboro at 0.2 and 0.8 bpp (docs/benchmarks.md). The
        // pyramid: coarse levels finer (0.65-0.75 a level) gain 1.5 dB at 0.8 bpp and 3 dB at
        // 0.2 bpp on etopo20 over one step for all, since a coarse sample predicts many finer
        // ones; a dead zone of 0.15 step beats none and 0.35 by 0.1-0.6 dB. Both: the
        // rate-distortion choice at lambda 0.1 adds 0.1-0.3 dB (0.05, 0.15, 0.2, 0.25, 0.3 and
        // 0.5 tried; on the lifted levels too).
        ProjectedSettings {
            max_error: None,
            pyramid: false,
            growth: 0.7,
            dead_zone: 0.15,
            lambda: 0.1,
            bounded: false,
            at_step: None,
            trial: false,
            target_bpp: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::decode;

    /// A small rough grid: a smooth slope plus a hashed roughness.
    pub(super) fn grid(w: usize, h: usize) -> Vec<f64> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let noise = (i as u32).wrapping_mul(2_654_435_761) as f64 / u32::MAX as f64;
                3.0 * x + 2.0 * y + 10.0 * noise
            })
            .collect()
    }

    pub(super) fn header(w: usize, h: usize, g: &[f64]) -> ProjectedHeader {
        let (lo, hi) = g
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        ProjectedHeader {
            samples: [w as u32, h as u32],
            levels: levels_for(w, h),
            step: 1.0,
            growth: 1.0,
            quantum: 0.0,
            value_min: lo,
            value_span: hi - lo,
            roughness: fit_roughness(g, w, h),
            max_error: 0.5,
            order: pyramid::Order::Quincunx,
        }
    }

    /// The lanes of `run_chains` answer as one chain at a time does, bit for bit: each stepped
    /// by `step` while it has steps left and its cell's residual bound times its contrast
    /// product is over the tolerance, then ended on S.
    #[test]
    fn chains_in_lanes_answer_as_one_at_a_time() {
        use crate::core::decode::{position_quantum, to_frame};
        use crate::core::operator::active;
        let (w, h) = (41, 29);
        let g = grid(w, h);
        let op = ProjectedOperator::new(&header(w, h, &g), &g).expect("operator");
        assert!(op.ends_on_samples());
        let (lo, hi) = op.invariant_interval();
        let (seed, half) = ((lo + hi) * 0.5, (hi - lo) * 0.5);
        let quantum = position_quantum(&op.frame());
        // 1,003 points (a last batch of three), some past the frame's edges.
        let pts: Vec<[f32; 2]> = (0..1003)
            .map(|k| {
                let t = k as f32;
                [
                    (t * 0.618_034).fract() * 1.1 - 0.05,
                    (t * 0.414_214).fract(),
                ]
            })
            .collect();
        for (iterations, tol) in [(3, 0.0), (40, 1e-3), (40, 2e-2), (0, 0.0)] {
            let lanes = decode::points(&op, &pts, iterations, tol);
            for (k, p) in pts.iter().enumerate() {
                let mut c = Chain::start([
                    to_frame(p[0], op.valid()[0], quantum),
                    to_frame(p[1], op.valid()[1], quantum),
                ]);
                while c.taken < iterations && active(c.acc_s, op.residual_at(c.q), tol) {
                    let st = op.step(c.q);
                    c.taken += 1;
                    c.acc_g += c.acc_s * st.offset;
                    c.acc_s *= st.contrast;
                    c.q = st.next;
                }
                op.end_chain(&mut c);
                assert_eq!(
                    lanes[k],
                    c.finish(seed, half),
                    "point {k}, {iterations} steps"
                );
            }
        }
    }

    /// The records built from the half lattices are the bits the direct tensor-product
    /// evaluation gives, on rough and smooth grids of odd and even sizes and the smallest axes.
    /// (Unit tests read no files: the layout rule keeps `codecs` from importing `io`.)
    #[test]
    fn records_from_half_lattices_are_the_direct_evaluations_bit_for_bit() {
        let smooth = |w: usize, h: usize| -> Vec<f64> {
            (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f64, (i / w) as f64);
                    1234.5 * (0.3 * x).sin() * (0.21 * y).cos() - 17.25 * x
                })
                .collect()
        };
        let mut cases: Vec<(usize, usize, Vec<f64>)> = [(61, 40), (64, 33), (5, 4), (4, 7), (2, 3)]
            .iter()
            .flat_map(|&(w, h)| [(w, h, grid(w, h)), (w, h, smooth(w, h))])
            .collect();
        cases.push((17, 12, grid(17, 12)));
        for (w, h, g) in cases {
            // A roughness of its own, so that the even lattice's term is weighed everywhere.
            let hd = ProjectedHeader {
                roughness: 0.6,
                ..header(w, h, &g)
            };
            let op = ProjectedOperator::new(&hd, &g).expect("operator");
            assert!(op.rho > 0.0 || w < 4 || h < 4);
            for (k, rec) in op.records.iter().enumerate() {
                let (i, j) = (k % (w - 1), k / (w - 1));
                for (n, &v) in rec.iter().enumerate() {
                    let direct = op.half_point(i, j, n % 3, n / 3);
                    assert_eq!(
                        v.to_bits(),
                        direct.to_bits(),
                        "{w}x{h} cell ({i}, {j}) point {n}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_continuation_passes_through_every_sample_and_its_pieces_agree() {
        for (w, h) in [(17, 12), (16, 9), (4, 4), (2, 5)] {
            let g = grid(w, h);
            let hd = header(w, h, &g);
            let op = ProjectedOperator::new(&hd, &g).expect("operator");
            let pts: Vec<[f32; 2]> = (0..w * h)
                .map(|i| {
                    [
                        ((i % w) as f32 + 0.5) / w as f32,
                        ((i / w) as f32 + 0.5) / h as f32,
                    ]
                })
                .collect();
            for (k, pv) in decode::points(&op, &pts, 400, 0.0).iter().enumerate() {
                let want = op.samples()[k];
                assert!(
                    (pv.value - want).abs() < 1e-4,
                    "{w}x{h} sample {k}: {} against {want}",
                    pv.value
                );
            }
            // The GPU's flattening steps as `step` does, seeded by a constant.
            crate::core::pieces::tests::agree(&Stepwise(&op), "projected");
            // And goes to a device as a lattice: the quarter cells' offsets (16 bytes each
            // against a piece's 80 and its lookup entry's 4), a map a column and a row.
            let table = crate::core::pieces::Flatten::pieces(&op);
            let lattice = table.lattice().expect("the quarter cells are a lattice");
            // Built directly, the same lattice, with where chains end: the samples and each
            // cell's residual bound, when chains end on them.
            let crate::core::pieces::Flat::Lattice(direct) =
                crate::core::pieces::Flatten::flat(&op)
            else {
                panic!("the projected codec flattens to a lattice");
            };
            let ends = direct.ends.clone();
            let direct = crate::core::pieces::Lattice {
                ends: None,
                ..direct
            };
            let [lx, ly] = table.lut_size.map(|n| n as usize);
            // Its offsets in blocks, a cell's record shared by its four quarters, are the
            // table's coefficients cell by cell.
            use crate::core::pieces::Offsets;
            let Offsets::Blocks(blocks) = &direct.offsets else {
                panic!("the quarter cells' offsets go in blocks");
            };
            assert_eq!(blocks.len() * 4, lx * ly);
            let cells = (0..lx * ly)
                .map(|k| direct.offsets.of(k % lx, k / lx, lx))
                .collect();
            assert_eq!(
                crate::core::pieces::Lattice {
                    offsets: Offsets::Cells(cells),
                    ..direct.clone()
                },
                lattice
            );
            assert_eq!(ends.is_some(), op.ends_on_samples());
            if let Some(e) = ends {
                assert_eq!(e.samples.as_slice(), op.samples());
                assert_eq!(e.residual.len(), (w - 1) * (h - 1));
                assert_eq!(e.residual[w], op.residual_of(w % (w - 1), w / (w - 1)));
            }
            // And from an operator holding no records (a chunk's), which builds them all for
            // its lattice by bands rather than holding them: the same lattice.
            let lean = ProjectedOperator::samples_only(&hd, &g).expect("operator");
            let crate::core::pieces::Flat::Lattice(lean) =
                crate::core::pieces::Flatten::flat(&lean)
            else {
                panic!("the projected codec flattens to a lattice");
            };
            assert_eq!(crate::core::pieces::Lattice { ends: None, ..lean }, direct);
            assert_eq!((direct.columns.len(), direct.rows.len()), (lx, ly));
            assert_eq!(table.device_bytes(), 84 * lx * ly);
            assert_eq!(lattice.device_bytes(), 16 * (lx * ly + lx + ly));
            assert_eq!(
                direct.device_bytes(),
                (9 * lx * ly).next_multiple_of(16) + 16 * (lx + ly)
            );
            // Chains that end on the bilinear interpolant against chains from a constant seed:
            // within the sum of their bounds, with the tolerance reached in fewer steps.
            let probe: Vec<[f32; 2]> = (0..997)
                .map(|i| {
                    [
                        (i as f32 * 0.618_034).fract(),
                        (i as f32 * 0.414_214).fract(),
                    ]
                })
                .collect();
            let ended = decode::points(&op, &probe, 400, 1e-3);
            let seeded = decode::points(&Stepwise(&op), &probe, 400, 1e-3);
            let (mut fewer, mut steps) = (0u32, 0u32);
            for (a, b) in ended.iter().zip(&seeded) {
                assert!(
                    (a.value - b.value).abs() <= a.error_bound + b.error_bound,
                    "{w}x{h}: {} within {} against {} within {}",
                    a.value,
                    a.error_bound,
                    b.value,
                    b.error_bound
                );
                fewer += a.iterations;
                steps += b.iterations;
            }
            assert!(
                fewer < steps || op.roughness() == 0.0,
                "{w}x{h}: {fewer} steps against {steps}"
            );
        }
    }

    /// The operator stepped as every other codec's is (the default `run_chains`, a constant
    /// seed): what the flattening for the GPU reproduces.
    struct Stepwise<'a>(&'a ProjectedOperator);

    impl Operator<2> for Stepwise<'_> {
        fn frame(&self) -> [f32; 2] {
            self.0.frame()
        }
        fn valid(&self) -> [f32; 2] {
            self.0.valid()
        }
        fn expansion(&self) -> u32 {
            self.0.expansion()
        }
        fn step(&self, p: [f32; 2]) -> Step<2> {
            self.0.step(p)
        }
        fn invariant_interval(&self) -> (f32, f32) {
            self.0.invariant_interval()
        }
    }

    impl crate::core::pieces::Flatten for Stepwise<'_> {
        fn pieces(&self) -> crate::core::pieces::PieceTable {
            self.0.pieces()
        }
    }

    #[test]
    fn a_grid_codes_within_half_a_step_and_decodes_as_coded() {
        let (w, h) = (37, 29);
        let g = grid(w, h);
        for order in [pyramid::Order::Separable, pyramid::Order::Quincunx] {
            let hd = ProjectedHeader {
                order,
                ..header(w, h, &g)
            };
            let (stream, coded) = encode_grid(&hd, &g, None, (0.0, 0.0));
            let decoded = decode_grid(&hd, &stream).expect("decode");
            assert_eq!(
                coded, decoded,
                "{order:?}: the decoder walks as the encoder did"
            );
            for (a, b) in decoded.iter().zip(&g) {
                assert!((a - b).abs() <= 0.5 + 1e-9, "{order:?}: {a} for {b}");
            }
        }
    }

    /// A coarse view: the pyramid's samples on multiples of 2^depth, bit for bit the full
    /// decode's there; a lifted plane's, the low-pass of the decoded grid at that depth (in
    /// source units: a plane's view of a plane is that plane), and close to the source's own
    /// low-pass at a fine step.
    #[test]
    fn coarse_views_are_the_coarse_samples_of_the_multiresolution() {
        let (w, h) = (45, 38);
        let g = grid(w, h);
        for depth in 1..=3u32 {
            let s = 1usize << depth;
            let (cw, ch) = (w.div_ceil(s), h.div_ceil(s));
            let hd = header(w, h, &g);
            let (stream, _) = encode_grid(&hd, &g, None, (0.0, 0.0));
            let full = decode_grid(&hd, &stream).unwrap();
            let (view, coarse, read) = decode_coarse(&hd, &stream, depth).unwrap();
            // The bytes it says it read are all it needs.
            let (_, again, _) = decode_coarse(&hd, &stream[..read], depth).unwrap();
            assert_eq!(
                again,
                coarse,
                "pyramid {depth}: {read} of {} bytes",
                stream.len()
            );
            assert_eq!(view.samples, [cw as u32, ch as u32]);
            assert_eq!(
                view.promise(),
                None,
                "a view stands for cells, not one cell"
            );
            for (k, v) in coarse.iter().enumerate() {
                assert_eq!(*v, full[(k / cw) * s * w + (k % cw) * s], "pyramid {depth}");
            }
            let plane: Vec<f64> = (0..w * h)
                .map(|i| 100.0 + 3.0 * (i % w) as f64 - 2.0 * (i / w) as f64)
                .collect();
            for (order, kernel) in [
                (pyramid::Order::Lifted, lifting::Kernel::Fitted),
                (pyramid::Order::Lifted97, lifting::Kernel::Cdf97),
            ] {
                for (source, step) in [(&plane, 0.01), (&g, 0.01)] {
                    let hd = ProjectedHeader {
                        order,
                        max_error: 0.0,
                        step,
                        ..header(w, h, source)
                    };
                    let (stream, _) = encode_grid(&hd, source, None, (0.0, 0.0));
                    let (_, coarse, read) = decode_coarse(&hd, &stream, depth).unwrap();
                    let (_, again, _) = decode_coarse(&hd, &stream[..read], depth).unwrap();
                    assert_eq!(
                        again, coarse,
                        "{kernel:?} {depth}: a prefix of {read} bytes"
                    );
                    let lp = lifting::analysis(&lifted_plane(&hd.layout(), kernel), source, depth);
                    // Past the plane's levels (2 here), its coarsest samples are taken.
                    let read = depth.min(u32::from(hd.levels));
                    let gain = lifting::dc_gain(kernel).powi(2 * read as i32);
                    for (k, v) in coarse.iter().enumerate() {
                        let (x, y) = ((k % cw) * s, (k / cw) * s);
                        let want = lp[y * w + x] / gain;
                        assert!(
                            (v - want).abs() < 0.05,
                            "{kernel:?} {depth}: {v} for {want}"
                        );
                        if std::ptr::eq(source, &plane) {
                            // Away from the mirrored ends a low-pass of a plane is the plane.
                            let inside = x >= 8 && y >= 8 && x + 8 < w && y + 8 < h;
                            let at = source[y * w + x];
                            assert!(!inside || (v - at).abs() < 0.05, "{kernel:?}: {v} for {at}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn roughness_is_none_on_a_cubic_and_high_on_noise() {
        let (w, h) = (64, 64);
        // A cubic's midpoint residual is zero: no roughness at all.
        let cubic: Vec<f64> = (0..w * h)
            .map(|i| ((i % w) as f64).powi(3) * 1e-3 + (i / w) as f64)
            .collect();
        assert!(fit_roughness(&cubic, w, h) < 0.05);
        // White noise has the same residual at every spacing: the most rho allows.
        assert!(fit_roughness(&grid(w, h), w, h) > 0.7);
    }
}
