//! Discrete decoding (W iterated on a grid of any size, 2D and 3D) and windows answered by
//! whichever of the discrete and continuous decoders is cheaper.

use rayon::prelude::*;

use crate::core::operator::Operator;

use super::continuous::*;

/// A decoded grid (normalised values), row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    /// Width in samples.
    pub width: usize,
    /// Height in samples.
    pub height: usize,
    /// Values, row-major.
    pub values: Vec<f32>,
}

impl Grid {
    /// The grid resampled to `width x height` (no larger) by area means: each new cell the mean
    /// of the cells it covers, each weighed by the part of it covered (the cells are boxes on
    /// the unit square, as pixels are). What a coarser grid of samples is, exactly, without a
    /// decode: the box filter. NaN cells weigh nothing (NaN where all are).
    pub fn area_means(&self, width: usize, height: usize) -> Grid {
        // Per output cell along an axis of n cells onto m: the first cell it covers and the
        // weights of those it covers.
        fn weights(n: usize, m: usize) -> Vec<(usize, Vec<f32>)> {
            let r = n as f64 / m as f64;
            (0..m)
                .map(|i| {
                    let (a, b) = (i as f64 * r, ((i + 1) as f64 * r).min(n as f64));
                    let first = a.floor() as usize;
                    let last = (b.ceil() as usize).clamp(first + 1, n);
                    let w = (first..last)
                        .map(|k| ((b.min(k as f64 + 1.0) - a.max(k as f64)).max(0.0)) as f32)
                        .collect();
                    (first, w)
                })
                .collect()
        }
        let (wx, wy) = (weights(self.width, width), weights(self.height, height));
        // Rows first (sums and weights of finite values), then columns.
        let mut rows = vec![(0.0f32, 0.0f32); width * self.height];
        for (row, out) in self
            .values
            .chunks_exact(self.width)
            .zip(rows.chunks_exact_mut(width))
        {
            for (o, (first, w)) in out.iter_mut().zip(&wx) {
                for (&v, &w) in row[*first..].iter().zip(w) {
                    if v.is_finite() {
                        o.0 += w * v;
                        o.1 += w;
                    }
                }
            }
        }
        let mut values = Vec::with_capacity(width * height);
        for (first, w) in &wy {
            let mut acc = vec![(0.0f32, 0.0f32); width];
            for (k, &w) in w.iter().enumerate() {
                let src = &rows[(first + k) * width..(first + k + 1) * width];
                for (a, &(s, n)) in acc.iter_mut().zip(src) {
                    a.0 += w * s;
                    a.1 += w * n;
                }
            }
            values.extend(
                acc.into_iter()
                    .map(|(s, n)| if n > 0.0 { s / n } else { f32::NAN }),
            );
        }
        Grid {
            width,
            height,
            values,
        }
    }

    /// The grid `fx` x `fy` times coarser: each cell the mean of the finite values of its block
    /// (NaN where there are none, as nodata stays nodata). `None` unless the factors divide the
    /// size. A discrete decode at a coarser size is itself an approximation of the attractor's
    /// cell means; the mean of a finer decode is a closer one, and costs a pass over the grid
    /// instead of a decode.
    pub fn shrink(&self, fx: usize, fy: usize) -> Option<Grid> {
        if fx == 0 || fy == 0 || !self.width.is_multiple_of(fx) || !self.height.is_multiple_of(fy) {
            return None;
        }
        let (w, h) = (self.width / fx, self.height / fy);
        let mut sums = vec![(0.0f32, 0u32); w * h];
        for (y, row) in self.values.chunks_exact(self.width).enumerate() {
            let out = &mut sums[(y / fy) * w..][..w];
            for (x, &v) in row.iter().enumerate() {
                if v.is_finite() {
                    let c = &mut out[x / fx];
                    c.0 += v;
                    c.1 += 1;
                }
            }
        }
        Some(Grid {
            width: w,
            height: h,
            values: sums
                .into_iter()
                .map(|(s, n)| if n > 0 { s / n as f32 } else { f32::NAN })
                .collect(),
        })
    }
}

/// When discrete decoding stops.
#[derive(Clone, Copy, Debug)]
pub struct DiscreteOptions {
    /// Stop when the mean absolute change between two iterates falls under this (normalised;
    /// the seed's criterion is 0.002 of the value range).
    pub min_change: f32,
    /// Never more than this many iterations; exactly this many when `min_change` and
    /// `max_error` are 0.
    pub max_iterations: u32,
    /// Stop once the a-posteriori bound on the distance to the discrete attractor
    /// ([`DiscreteReport::error_bound`]) is at most this (normalised; 0: never on that account).
    pub max_error: f32,
}

impl Default for DiscreteOptions {
    fn default() -> Self {
        DiscreteOptions {
            min_change: 0.002,
            max_iterations: 40,
            max_error: 0.0,
        }
    }
}

impl DiscreteOptions {
    /// Exactly `n` iterations.
    pub fn fixed(n: u32) -> Self {
        DiscreteOptions {
            min_change: 0.0,
            max_iterations: n,
            max_error: 0.0,
        }
    }

    /// At most `n` iterations, fewer once the iterate is provably within `max_error` of the
    /// discrete attractor.
    pub fn within(max_error: f32, n: u32) -> Self {
        DiscreteOptions {
            min_change: 0.0,
            max_iterations: n,
            max_error,
        }
    }
}

/// What discrete decoding did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DiscreteReport {
    /// Iterations run.
    pub iterations: u32,
    /// Mean absolute change of the last iteration (normalised).
    pub last_change: f32,
    /// A-posteriori bound on the largest distance of the result to the discrete attractor at
    /// this size (normalised): `s / (1 - s) * max |f_n - f_(n-1)|` over the whole frame, with s
    /// the largest |contrast| of the discrete operator (averaging and interpolation do not
    /// expand the sup norm, so that operator contracts by s). Usually far below the a-priori
    /// `s^n * max |seed - f|`, since the last change reflects the contrasts actually met.
    pub error_bound: f32,
}

/// Per output pixel: where the operator reads and how it scales what it reads.
pub(super) struct PixelMap {
    offset: f32,
    contrast: f32,
    index: u32,
    fx: f32,
    fy: f32,
}

/// Discrete decoding of the whole source extent at `width x height` (any size: smaller, equal or
/// larger than the source, any ratio).
pub fn discrete<O: Operator<2> + ?Sized>(
    op: &O,
    width: usize,
    height: usize,
    opts: DiscreteOptions,
) -> (Grid, DiscreteReport) {
    let valid = op.valid();
    let frame = op.frame();
    let e = op.expansion().max(1) as usize;
    let sx = width as f32 / valid[0];
    let sy = height as f32 / valid[1];
    // The iteration runs over the whole frame at the output scale (domains may lie in padding).
    let fw = ((frame[0] * sx).ceil() as usize).max(width).max(e);
    let fh = ((frame[1] * sy).ceil() as usize).max(height).max(e);
    let (dw, dh) = (fw - e + 1, fh - e + 1);
    let half = e as f32 * 0.5;
    let maps: Vec<PixelMap> = (0..fw * fh)
        .into_par_iter()
        .map(|i| {
            let (px, py) = ((i % fw) as f32 + 0.5, (i / fw) as f32 + 0.5);
            let st = op.step([px / sx, py / sy]);
            // Top-left of the e x e box centred on phi(p), in output pixels.
            let bx = (st.next[0] * sx - half).clamp(0.0, (dw - 1) as f32);
            let by = (st.next[1] * sy - half).clamp(0.0, (dh - 1) as f32);
            let (ix, iy) = (
                (bx as usize).min(dw.saturating_sub(2)),
                (by as usize).min(dh.saturating_sub(2)),
            );
            PixelMap {
                offset: st.offset,
                contrast: st.contrast,
                index: (iy * dw + ix) as u32,
                fx: if dw > 1 { bx - ix as f32 } else { 0.0 },
                fy: if dh > 1 { by - iy as f32 } else { 0.0 },
            }
        })
        .collect();
    let contraction = maps.iter().fold(0.0f32, |m, p| m.max(p.contrast.abs()));
    let (lo, hi) = op.invariant_interval();
    let mut f = vec![(lo + hi) * 0.5; fw * fh];
    let mut next = vec![0.0f32; fw * fh];
    let mut boxed = vec![0.0f32; dw * dh];
    let norm = 1.0 / (e * e) as f32;
    let mut report = DiscreteReport {
        iterations: 0,
        last_change: f32::INFINITY,
        error_bound: f32::INFINITY,
    };
    let (step_x, step_y) = (usize::from(dw > 1), if dh > 1 { dw } else { 0 });
    while report.iterations < opts.max_iterations {
        // Box average of the iterate over e x e, at every position.
        boxed.par_chunks_mut(dw).enumerate().for_each(|(y, row)| {
            for (x, out) in row.iter_mut().enumerate() {
                let mut acc = 0.0;
                for yy in y..y + e {
                    acc += f[yy * fw + x..yy * fw + x + e].iter().sum::<f32>();
                }
                *out = acc * norm;
            }
        });
        let (change, largest) = next
            .par_chunks_mut(fw)
            .zip(maps.par_chunks(fw))
            .enumerate()
            .map(|(y, (row, mrow))| {
                let (mut ch, mut mx) = (0.0f64, 0.0f32);
                for (x, (out, m)) in row.iter_mut().zip(mrow).enumerate() {
                    let i = m.index as usize;
                    let top = boxed[i] + (boxed[i + step_x] - boxed[i]) * m.fx;
                    let bot =
                        boxed[i + step_y] + (boxed[i + step_y + step_x] - boxed[i + step_y]) * m.fx;
                    let v = m.offset + m.contrast * (top + (bot - top) * m.fy);
                    let d = (v - f[y * fw + x]).abs();
                    if x < width && y < height {
                        ch += d as f64;
                    }
                    mx = mx.max(d);
                    *out = v;
                }
                (ch, mx)
            })
            .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1.max(b.1)));
        std::mem::swap(&mut f, &mut next);
        report.iterations += 1;
        report.last_change = (change / (width * height) as f64) as f32;
        report.error_bound = contraction / (1.0 - contraction) * largest;
        if report.last_change < opts.min_change || report.error_bound <= opts.max_error {
            break;
        }
    }
    let mut values = Vec::with_capacity(width * height);
    for y in 0..height {
        values.extend_from_slice(&f[y * fw..y * fw + width]);
    }
    (
        Grid {
            width,
            height,
            values,
        },
        report,
    )
}

/// How a window is decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Method {
    /// Whichever is cheaper for this window (the default).
    #[default]
    Auto,
    /// Discrete decoding of the whole extent at the window's scale, then sampling the window.
    Discrete,
    /// Continuous decoding of each window pixel centre.
    Continuous,
}

/// The unit coordinates of the pixel centres of a `width x height` window over `rect`
/// (`[u0, v0, u1, v1]`): columns, then rows. Computed in f64 and rounded once; the GPU's windows
/// take the same axes, so both decode the same points.
pub fn window_axes(rect: [f32; 4], width: usize, height: usize) -> (Vec<f32>, Vec<f32>) {
    let axis = |a: f32, b: f32, n: usize| -> Vec<f32> {
        let (a, d) = (f64::from(a), f64::from((b - a).max(1e-9)));
        (0..n)
            .map(|i| (a + (i as f64 + 0.5) / n as f64 * d) as f32)
            .collect()
    };
    (
        axis(rect[0], rect[2], width),
        axis(rect[1], rect[3], height),
    )
}

/// A window `[u0, v0, u1, v1]` of the unit square decoded at `width x height`: value at each
/// pixel centre. `iterations` counts inverse steps (continuous) or iterations (discrete);
/// `None` lets each method use its own stopping rule (point: 12 steps).
pub fn window<O: Operator<2> + ?Sized>(
    op: &O,
    rect: [f32; 4],
    width: usize,
    height: usize,
    iterations: Option<u32>,
    method: Method,
) -> (Grid, Method) {
    let [u0, v0, u1, v1] = rect;
    let (du, dv) = ((u1 - u0).max(1e-9), (v1 - v0).max(1e-9));
    // Full decode at the window's scale costs its pixels times ~10 iterations; point decoding
    // costs the window's pixels times the steps. Discrete needs the whole extent in memory.
    let full_w = (width as f32 / du).ceil() as usize;
    let full_h = (height as f32 / dv).ceil() as usize;
    let full = full_w as f64 * full_h as f64;
    let chosen = match method {
        Method::Auto if full <= 3.0 * (width * height) as f64 && full < 16e6 => Method::Discrete,
        Method::Auto => Method::Continuous,
        m => m,
    };
    let (xs, ys) = window_axes(rect, width, height);
    let centre = |i: usize, j: usize| [xs[i], ys[j]];
    let values = match chosen {
        Method::Discrete => {
            let opts = iterations.map(DiscreteOptions::fixed).unwrap_or_default();
            let (g, _) = discrete(op, full_w.max(1), full_h.max(1), opts);
            (0..width * height)
                .into_par_iter()
                .map(|k| {
                    let [u, v] = centre(k % width, k / width);
                    sample_bilinear(&g, u * g.width as f32 - 0.5, v * g.height as f32 - 0.5)
                })
                .collect()
        }
        _ => {
            let n = iterations.unwrap_or(12);
            let mut values = vec![0.0f32; width * height];
            values
                .par_chunks_mut(width)
                .enumerate()
                .for_each(|(j, row)| {
                    let pts: Vec<[f32; 2]> = (0..width).map(|i| centre(i, j)).collect();
                    for (v, p) in row.iter_mut().zip(points(op, &pts, n, 0.0)) {
                        *v = p.value;
                    }
                });
            values
        }
    };
    (
        Grid {
            width,
            height,
            values,
        },
        chosen,
    )
}

/// Discrete decoding of a 3D operator over the source extent at `dims` samples per axis (x
/// fastest): the 2D [`discrete`] one dimension up. Each iteration averages the previous iterate
/// over boxes of `expansion^3` voxels and reads it trilinearly at phi of each voxel centre.
/// Memory: about 40 bytes a voxel of the frame at the output scale.
pub fn discrete_volume<O: Operator<3> + ?Sized>(
    op: &O,
    dims: [usize; 3],
    opts: DiscreteOptions,
) -> (Vec<f32>, DiscreteReport) {
    let valid = op.valid();
    let frame = op.frame();
    let e = op.expansion().max(1) as usize;
    let scale: [f32; 3] = std::array::from_fn(|a| dims[a] as f32 / valid[a]);
    let fd: [usize; 3] = std::array::from_fn(|a| {
        ((frame[a] * scale[a]).ceil() as usize)
            .max(dims[a])
            .max(e + 1)
    });
    let bd: [usize; 3] = fd.map(|v| v - e + 1);
    let half = e as f32 * 0.5;
    struct VoxelMap {
        offset: f32,
        contrast: f32,
        index: u32,
        frac: [f32; 3],
    }
    let total = fd[0] * fd[1] * fd[2];
    let maps: Vec<VoxelMap> = (0..total)
        .into_par_iter()
        .map(|i| {
            let c = [i % fd[0], i / fd[0] % fd[1], i / (fd[0] * fd[1])];
            let p: [f32; 3] = std::array::from_fn(|a| (c[a] as f32 + 0.5) / scale[a]);
            let st = op.step(p);
            let mut idx = [0usize; 3];
            let mut frac = [0.0f32; 3];
            for a in 0..3 {
                let b = (st.next[a] * scale[a] - half).clamp(0.0, (bd[a] - 1) as f32);
                idx[a] = (b as usize).min(bd[a] - 2);
                frac[a] = b - idx[a] as f32;
            }
            VoxelMap {
                offset: st.offset,
                contrast: st.contrast,
                index: ((idx[2] * bd[1] + idx[1]) * bd[0] + idx[0]) as u32,
                frac,
            }
        })
        .collect();
    let contraction = maps.iter().fold(0.0f32, |m, p| m.max(p.contrast.abs()));
    let (lo, hi) = op.invariant_interval();
    let mut f = vec![(lo + hi) * 0.5; total];
    let mut next = vec![0.0f32; total];
    let mut boxed = vec![0.0f32; bd[0] * bd[1] * bd[2]];
    let norm = 1.0 / (e * e * e) as f32;
    let (sx, sy, sz) = (1, bd[0], bd[0] * bd[1]);
    let mut report = DiscreteReport {
        iterations: 0,
        last_change: f32::INFINITY,
        error_bound: f32::INFINITY,
    };
    let inside = dims[0] * dims[1] * dims[2];
    while report.iterations < opts.max_iterations {
        boxed
            .par_chunks_mut(bd[0] * bd[1])
            .enumerate()
            .for_each(|(z, slab)| {
                for y in 0..bd[1] {
                    for x in 0..bd[0] {
                        let mut acc = 0.0;
                        for zz in z..z + e {
                            for yy in y..y + e {
                                let row = (zz * fd[1] + yy) * fd[0] + x;
                                acc += f[row..row + e].iter().sum::<f32>();
                            }
                        }
                        slab[y * bd[0] + x] = acc * norm;
                    }
                }
            });
        let (change, largest) = next
            .par_chunks_mut(fd[0])
            .zip(maps.par_chunks(fd[0]))
            .enumerate()
            .map(|(row, (out, mrow))| {
                let (y, z) = (row % fd[1], row / fd[1]);
                let (mut ch, mut mx) = (0.0f64, 0.0f32);
                for (x, (o, m)) in out.iter_mut().zip(mrow).enumerate() {
                    let i = m.index as usize;
                    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
                    let [fx, fy, fz] = m.frac;
                    let plane = |k: usize| {
                        lerp(
                            lerp(boxed[k], boxed[k + sx], fx),
                            lerp(boxed[k + sy], boxed[k + sy + sx], fx),
                            fy,
                        )
                    };
                    let v = m.offset + m.contrast * lerp(plane(i), plane(i + sz), fz);
                    let d = (v - f[row * fd[0] + x]).abs();
                    if x < dims[0] && y < dims[1] && z < dims[2] {
                        ch += d as f64;
                    }
                    mx = mx.max(d);
                    *o = v;
                }
                (ch, mx)
            })
            .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1.max(b.1)));
        std::mem::swap(&mut f, &mut next);
        report.iterations += 1;
        report.last_change = (change / inside as f64) as f32;
        report.error_bound = contraction / (1.0 - contraction) * largest;
        if report.last_change < opts.min_change || report.error_bound <= opts.max_error {
            break;
        }
    }
    let mut values = Vec::with_capacity(inside);
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            let row = (z * fd[1] + y) * fd[0];
            values.extend_from_slice(&f[row..row + dims[0]]);
        }
    }
    (values, report)
}

/// The unit coordinates of the samples of a box `[lo, hi]` of the unit cube at `dims` samples
/// per axis: the corners and evenly between them (one sample: the middle). Computed in f64 and
/// rounded once; the GPU's boxes take the same axes, so both decode the same points.
pub fn volume_axes(lo: [f32; 3], hi: [f32; 3], dims: [usize; 3]) -> [Vec<f32>; 3] {
    std::array::from_fn(|a| {
        let (l, h) = (f64::from(lo[a]), f64::from(hi[a]));
        match dims[a] {
            0 => Vec::new(),
            1 => vec![(0.5 * (l + h)) as f32],
            n => (0..n)
                .map(|i| (l + (h - l) * i as f64 / (n - 1) as f64) as f32)
                .collect(),
        }
    })
}

/// Continuous decoding of a box `[lo, hi]` of the unit cube at `dims` samples per axis (x
/// fastest), the samples at the corners and evenly between them (what an isosurface wants:
/// neighbouring boxes share their faces). Returns the values and the largest error bound.
pub fn volume_window<O: Operator<3> + ?Sized>(
    op: &O,
    lo: [f32; 3],
    hi: [f32; 3],
    dims: [usize; 3],
    iterations: u32,
    tolerance: f32,
) -> (Vec<f32>, f32) {
    let [xs, ys, zs] = volume_axes(lo, hi, dims);
    let rows: Vec<(Vec<f32>, f32)> = (0..dims[1] * dims[2])
        .into_par_iter()
        .map(|r| {
            let (y, z) = (ys[r % dims[1]], zs[r / dims[1]]);
            let pts: Vec<[f32; 3]> = xs.iter().map(|&x| [x, y, z]).collect();
            let pv = points(op, &pts, iterations, tolerance);
            let bound = pv.iter().fold(0.0f32, |m, p| m.max(p.error_bound));
            (pv.into_iter().map(|p| p.value).collect(), bound)
        })
        .collect();
    let bound = rows.iter().fold(0.0f32, |m, r| m.max(r.1));
    (rows.into_iter().flat_map(|r| r.0).collect(), bound)
}

/// Bilinear sample of a grid at continuous pixel coordinates (pixel centres at integers), clamped.
pub fn sample_bilinear(g: &Grid, x: f32, y: f32) -> f32 {
    let x = x.clamp(0.0, (g.width - 1) as f32);
    let y = y.clamp(0.0, (g.height - 1) as f32);
    let (x0, y0) = (x as usize, y as usize);
    let (x1, y1) = ((x0 + 1).min(g.width - 1), (y0 + 1).min(g.height - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = |x: usize, y: usize| g.values[y * g.width + x];
    let top = at(x0, y0) + (at(x1, y0) - at(x0, y0)) * fx;
    let bot = at(x0, y1) + (at(x1, y1) - at(x0, y1)) * fx;
    top + (bot - top) * fy
}
