//! Rasters: windows, tiles, regions and meshes' vertices sampled (`Asset::sample_with`),
//! discretely where a pixel covers cells, continuously otherwise, filtered when coarser than
//! the source.

use crate::core::decode::{self, DiscreteOptions, DiscreteReport, Grid, Method};
use crate::geo::{self, Pixels};
use crate::io::asset::Asset;
use crate::render::colour::rgb_bound;
use fractile_proto::ColourModel;
use std::sync::Arc;

use super::filter::{Inside, filter_separable};
use super::*;

impl Asset {
    /// Normalised planes of a `width x height` window `[u0, v0, u1, v1]` decoded elsewhere (the
    /// GPU), kept in the neighbourhood of the data and brought back to source units as
    /// [`Asset::window`] does.
    pub fn window_from_planes(
        &self,
        rect: [f32; 4],
        width: usize,
        height: usize,
        mut planes: Vec<Vec<f32>>,
    ) -> Decoded {
        let [u0, v0, u1, v1] = rect;
        // Pixels no larger than a cell sample the continuation; coarser ones average cells,
        // whose range their centre's neighbourhood need not hold.
        let fine = (u1 - u0).abs() * self.meta.width as f32 <= width as f32
            && (v1 - v0).abs() * self.meta.height as f32 <= height as f32;
        if fine {
            let (xs, ys) = decode::window_axes(rect, width, height);
            for (p, values) in self.planes().iter().zip(planes.iter_mut()) {
                p.operator.limit_grid(&xs, &ys, values);
            }
        }
        let channels = self.to_source(
            planes,
            |i| {
                (
                    u0 + ((i % width) as f32 + 0.5) / width as f32 * (u1 - u0),
                    v0 + ((i / width) as f32 + 0.5) / height as f32 * (v1 - v0),
                )
            },
            None,
        );
        Decoded {
            width,
            height,
            channels,
        }
    }

    /// The asset as a raster of `width x height` over `window` (`None`: all of it), as
    /// `fractile decode` and Python's `Asset.read` make it on the CPU: the whole asset decoded
    /// discretely unless `method` asks the continuous decode, a window by [`Asset::window`]; a
    /// chunked asset's chunks sampled continuously whatever is asked. `iterations`: exactly
    /// this many (`None`: until converged). Returns the method used; a chunk that cannot be
    /// read or decoded is an error (where `window` leaves its pixels NaN).
    pub fn raster(
        &self,
        window: Option<[f32; 4]>,
        width: usize,
        height: usize,
        iterations: Option<u32>,
        method: Method,
    ) -> Result<(Decoded, Method), crate::Error> {
        self.check_read(width, height, &crate::AssetLimits::default())?;
        if self.chunked().is_some() {
            let rect = window.unwrap_or([0.0, 0.0, 1.0, 1.0]);
            let channels = self
                .chunked_window(rect, width, height, iterations, &|_, _, _, _| None)
                .map_err(SampleError::into_error)?;
            let decoded = Decoded {
                width,
                height,
                channels,
            };
            return Ok((decoded, Method::Continuous));
        }
        Ok(match window {
            None if method != Method::Continuous => {
                let opts = iterations.map(DiscreteOptions::fixed).unwrap_or_default();
                (self.decode(width, height, opts).0, Method::Discrete)
            }
            _ => self.window(
                window.unwrap_or([0.0, 0.0, 1.0, 1.0]),
                width,
                height,
                iterations,
                method,
            ),
        })
    }

    /// Refuses a read of `width x height` pixels whose decode would take more than `limits`
    /// lets any decode take, before anything is allocated: the one rule of `fractile decode`
    /// and Python's `read` (a 13 KB asset read at 16384 x 16384 peaked at 9.25 GB). The
    /// estimate is what the peaks measured, 2026-11-28: 36 bytes a pixel (4096 x 4096,
    /// discrete, with the CLI's GeoTIFF) and 64 a row or column of pixels (1 x 2^23,
    /// continuous), each a channel.
    pub fn check_read(
        &self,
        width: usize,
        height: usize,
        limits: &crate::AssetLimits,
    ) -> Result<(), crate::Error> {
        let (w, h) = (width as u64, height as u64);
        let channels = u64::from(self.meta.channels.max(1));
        let cost = w
            .saturating_mul(h)
            .saturating_mul(40)
            .saturating_add(w.saturating_add(h).saturating_mul(64))
            .saturating_mul(channels);
        if cost > limits.max_decode_bytes {
            return Err(crate::Error::input(format!(
                "a read of {width} x {height} pixels would take about {} MiB, over this \
                 reader's limit of {} MiB: ask fewer pixels, or read the asset in windows",
                cost >> 20,
                limits.max_decode_bytes >> 20
            )));
        }
        Ok(())
    }

    /// A chunked asset's window: chunks answer continuously (the overview of the pixels'
    /// size where they are coarser than the source), whatever the method asked; exactly
    /// `iterations` steps, or (`None`) the decoder's default most, each pixel stopping at the
    /// asset's default tolerance.
    fn chunked_window(
        &self,
        rect: [f32; 4],
        width: usize,
        height: usize,
        iterations: Option<u32>,
        continuous: &ChainDevice<'_>,
    ) -> Result<Vec<Vec<f32>>, SampleError> {
        let (xs, ys) = decode::window_axes(rect, width, height);
        let pixels = Pixels {
            sites: geo::Sites::Grid {
                xs: xs.into_iter().map(Some).collect(),
                ys: ys.into_iter().map(Some).collect(),
            },
            footprint: [
                (rect[2] - rect[0]).abs() / width as f32,
                (rect[3] - rect[1]).abs() / height as f32,
            ],
        };
        let n = iterations.unwrap_or(DiscreteOptions::default().max_iterations);
        let tolerance = if iterations.is_some() {
            0.0
        } else {
            self.default_tolerance()
        };
        let resources = Resources {
            device: Some(continuous),
            ..Resources::CPU
        };
        Ok(self.sample_with(&pixels, n, tolerance, &resources)?.0)
    }

    /// A window `[u0, v0, u1, v1]` of the unit square at `width x height`.
    pub fn window(
        &self,
        rect: [f32; 4],
        width: usize,
        height: usize,
        iterations: Option<u32>,
        method: Method,
    ) -> (Decoded, Method) {
        self.window_with(rect, width, height, (iterations, method), &|_, _, _, _| {
            None
        })
    }

    /// [`Asset::window`], a chunked asset's chains offered to `continuous` chunk by chunk (a
    /// GPU). A whole asset's window is decoded here on the CPU: a device makes its grid
    /// itself (`fractile_gpu`'s `Grid::Window`), which the caller asks for directly.
    pub fn window_with(
        &self,
        rect: [f32; 4],
        width: usize,
        height: usize,
        (iterations, method): (Option<u32>, Method),
        continuous: &ChainDevice<'_>,
    ) -> (Decoded, Method) {
        if self.chunked().is_some() {
            // A chunk that cannot be read leaves the window NaN here; `raster` says why.
            let channels = self
                .chunked_window(rect, width, height, iterations, continuous)
                .unwrap_or_else(|_| {
                    vec![vec![f32::NAN; width * height]; self.meta.channels as usize]
                });
            return (
                Decoded {
                    width,
                    height,
                    channels,
                },
                Method::Continuous,
            );
        }
        let mut chosen = method;
        let planes = self
            .planes()
            .iter()
            .map(|p| {
                let (g, m) = decode::window(&p.operator, rect, width, height, iterations, method);
                chosen = m;
                g.values
            })
            .collect();
        (self.window_from_planes(rect, width, height, planes), chosen)
    }

    /// Values at the pixels of a raster (row-major; a pixel outside the asset is answered as
    /// NaN), each standing for `pixels.footprint` (unit coordinates): a tile, a region or a
    /// mesh. Where a pixel covers more than a source cell the asset is decoded discretely at the
    /// pixels' own scale and sampled (a filtered answer, no aliasing); otherwise each point is
    /// decoded continuously ([`crate::io::asset::PlaneOperator::grid`] for separable grids,
    /// [`crate::io::asset::PlaneOperator::points`] for point lists) with at most `iterations`
    /// steps, stopping once its bound is at most `tolerance` (source units; 0: never early).
    /// Returns the channels and the a-priori error bound (source units, largest over the
    /// points). A chunk of a chunked asset that cannot be read leaves NaN and an infinite
    /// bound ([`Asset::sample_with`] says why).
    pub fn sample(&self, pixels: &Pixels, iterations: u32, tolerance: f32) -> (Vec<Vec<f32>>, f32) {
        self.sample_with(pixels, iterations, tolerance, &Resources::CPU)
            .unwrap_or_else(|_| {
                let nan = vec![f32::NAN; pixels.len()];
                (vec![nan; self.meta.channels as usize], f32::INFINITY)
            })
    }

    /// The asset's measured error against its source over the pixels (the largest of its
    /// source-error map over their extent, each pixel's footprint included); `None` for assets
    /// without a map and for pixels wholly outside. For pixels coarser than the source (a
    /// filtered answer) this is the largest point error under them, which bounds the filtered
    /// answer against the source filtered the same way. Fails where a chunk of a chunked
    /// asset under the pixels cannot be read (its map is in the chunk).
    pub fn source_error_over(&self, pixels: &Pixels) -> Result<Option<f32>, crate::Error> {
        if let Some(c) = &self.chunked() {
            return c.source_error_over(&self.meta, pixels);
        }
        Ok(self.source_error_map_over(pixels))
    }

    /// [`Asset::source_error_over`] of an asset that is one operator.
    pub(super) fn source_error_map_over(&self, pixels: &Pixels) -> Option<f32> {
        let map = self.source_error.as_ref()?;
        let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        let mut take = |p: [f32; 2]| {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        };
        match &pixels.sites {
            crate::geo::Sites::Grid { xs, ys } => {
                // A grid's extent: its extreme columns and rows (once there is one of each).
                if ys.iter().any(Option::is_some) {
                    let y = ys.iter().flatten().copied();
                    let (y0, y1) = y.fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), v| {
                        (a.min(v), b.max(v))
                    });
                    for &x in xs.iter().flatten() {
                        take([x, y0]);
                        take([x, y1]);
                    }
                }
            }
            crate::geo::Sites::List { points, .. } => {
                points.iter().flatten().for_each(|&p| take(p))
            }
        }
        if lo[0] > hi[0] {
            return None;
        }
        let [fx, fy] = pixels.footprint.map(|f| f / 2.0);
        Some(map.over([lo[0] - fx, lo[1] - fy, hi[0] + fx, hi[1] + fy]))
    }

    /// Every plane decoded discretely at `width x height` (normalised values) with at most
    /// `iterations` steps, fewer once each is within `tolerance` (normalised; 0: all of them) of
    /// its discrete attractor: what coarse pixels of [`Asset::sample`] are sampled from.
    pub fn discrete_planes(
        &self,
        width: usize,
        height: usize,
        iterations: u32,
        tolerance: f32,
    ) -> Vec<(Grid, DiscreteReport)> {
        if let Some(c) = &self.chunked() {
            // Coarse pixels of a chunked asset are filtered from its top level, one chunk.
            return c.top_discrete_planes(width, height, iterations, tolerance);
        }
        let opts = DiscreteOptions::within(tolerance, iterations);
        self.planes()
            .iter()
            .map(|p| self.discrete(&p.operator, width, height, opts))
            .collect()
    }

    /// [`Asset::sample`], with the continuous chains of each plane offered first to
    /// `resources.device(plane, grid, iterations, tolerance)` (normalised tolerance), which
    /// may answer them elsewhere (a GPU) or return `None` to leave them to the CPU, and the
    /// discrete decodes of coarse pixels kept in `resources.coarse`. Large requests are
    /// decoded in bands of rows or points, looking at `resources.given_up` before each: the
    /// answers are the same (every point is decoded on its own), and a caller that gave up
    /// gets [`Cancelled`] within a band's time.
    pub fn sample_with(
        &self,
        pixels: &Pixels,
        iterations: u32,
        tolerance: f32,
        resources: &Resources<'_>,
    ) -> Result<(Vec<Vec<f32>>, f32), SampleError> {
        if let Some(c) = &self.chunked() {
            return c.sample(&self.meta, pixels, (iterations, tolerance), resources);
        }
        let snapped = self.snap_pixels(pixels);
        let pixels = snapped.as_ref().unwrap_or(pixels);
        let stop = || {
            if resources.asker_gave_up() {
                Err(Cancelled)
            } else {
                Ok(())
            }
        };
        stop()?;
        let footprint = pixels.footprint;
        // Decode the pixels inside the asset, then put them back in place.
        let inside = Inside::of(&pixels.sites);
        let (w, h) = (self.meta.width as f32, self.meta.height as f32);
        let coarse = footprint[0] * w > 1.0 || footprint[1] * h > 1.0;
        let tol = tolerance / self.span().max(f32::MIN_POSITIVE);
        // Largest per-point bound of the continuous path (normalised).
        let mut worst = 0.0f32;
        // A-posteriori bound of the discrete decodes (normalised).
        let mut coarse_bound = f32::INFINITY;
        let planes: Vec<Vec<f32>> = if coarse {
            let (planes, bound) = self.filtered(&inside, footprint, resources, iterations, tol);
            coarse_bound = bound;
            planes
        } else {
            let mut planes = Vec::with_capacity(self.planes().len());
            for k in 0..self.planes().len() {
                let (values, bound) = self
                    .continuous_plane(k, &inside, (iterations, tol), resources)?
                    .into_values();
                worst = worst.max(bound);
                planes.push(values);
            }
            planes
        };
        stop()?;
        let inner = self.to_source(planes, |k| inside.at(k), inside.footprint());
        let channels = inner
            .into_iter()
            .map(|ch| inside.scatter(ch, pixels.len()))
            .collect();
        let bound = if coarse {
            // Against the discrete attractor at the pixels' scale; the a-priori bound holds
            // too, so the smaller of the two.
            let b = coarse_bound * self.span();
            let b = if self.meta.colour == ColourModel::YCbCr {
                rgb_bound(b, b, b)
            } else {
                b
            };
            b.min(self.bound_after(iterations))
        } else {
            let b = worst * self.span();
            if self.meta.colour == ColourModel::YCbCr {
                rgb_bound(b, b, b)
            } else {
                b
            }
        };
        Ok((channels, bound))
    }

    /// Pixels coarser than the source, filtered: a mip level per axis, the source size halved
    /// while its cells stay no larger than a pixel (so cells measure between half a pixel and a
    /// pixel), and a pixel averages 2 x 2 bilinear taps spread over its footprint, which covers
    /// every cell under it: filtered, never aliased. Tiles of one zoom share their grid within
    /// each band of latitude where Mercator keeps a pixel's height within one power of two;
    /// an asset spanning many latitudes has a few grids per zoom (one per band), each decoded
    /// once. One grid for the whole zoom would alias at one end of the band or blur at the
    /// other (by cos(latitude): 11x at 85 degrees). Returns the planes and the discrete
    /// decodes' a-posteriori bound (normalised).
    pub(super) fn filtered(
        &self,
        inside: &Inside,
        footprint: [f32; 2],
        resources: &Resources<'_>,
        iterations: u32,
        tol: f32,
    ) -> (Vec<Vec<f32>>, f32) {
        let level = |fp: f32, n: u32| {
            let cells = (fp * n as f32).max(1.0);
            let halvings = cells.log2().floor().clamp(0.0, 30.0) as u32;
            (n as usize).div_ceil(1 << halvings).max(1)
        };
        let (gw, gh) = (
            level(footprint[0], self.meta.width),
            level(footprint[1], self.meta.height),
        );
        let (qx, qy) = (
            0.25 * footprint[0] * gw as f32,
            0.25 * footprint[1] * gh as f32,
        );
        // At the source's own size, planes that hold their samples are their grids: a tile's
        // pixels are filtered from them in place (no copy a tile, nothing for a cache to keep;
        // a chunk's pixels of one to 1.4 of its cells are all filtered so).
        let native = [self.meta.width as usize, self.meta.height as usize];
        if let Inside::Grid { ix, iy, .. } = inside
            && [gw, gh] == native
        {
            let samples: Option<Vec<&[f32]>> = self
                .planes()
                .iter()
                .map(|p| p.operator.samples().filter(|z| z.len() == gw * gh))
                .collect();
            if let Some(samples) = samples {
                let planes = samples
                    .iter()
                    .map(|z| filter_separable((z, gw, gh), (ix, iy), [qx, qy]))
                    .collect();
                return (planes, 0.0);
            }
        }
        let grids = match resources.coarse {
            Some((kept, key)) => kept.planes((self, key), (gw, gh), (iterations, tol)),
            None => Arc::new(self.discrete_planes(gw, gh, iterations, tol)),
        };
        let bound = grids.iter().map(|(_, r)| r.error_bound).fold(0.0, f32::max);
        let planes = grids
            .iter()
            .map(|(g, _)| {
                if let Inside::Grid { ix, iy, .. } = inside {
                    return filter_separable((&g.values, g.width, g.height), (ix, iy), [qx, qy]);
                }
                (0..inside.len())
                    .map(|k| {
                        let (u, v) = inside.at(k);
                        let (x, y) = (u * gw as f32 - 0.5, v * gh as f32 - 0.5);
                        0.25 * (decode::sample_bilinear(g, x - qx, y - qy)
                            + decode::sample_bilinear(g, x + qx, y - qy)
                            + decode::sample_bilinear(g, x - qx, y + qy)
                            + decode::sample_bilinear(g, x + qx, y + qy))
                    })
                    .collect()
            })
            .collect();
        (planes, bound)
    }

    /// The answer of a grid whose every column and row is a sample centre (a native decode,
    /// after [`Asset::snap_pixels`]) of an operator that knows its samples: the samples
    /// themselves, with a convergence bound of 0, as the discrete decode at the source's size
    /// answers. Why: the continuation passes through every sample, so each chain there only
    /// approaches the sample it starts on, and the chains' steps, their cells' residual bounds
    /// and the neighbourhood clamp cost 70% of a whole read of a chunked DEM (issue 75).
    fn on_samples(
        &self,
        op: &crate::io::asset::PlaneOperator,
        xs: &[f32],
        ys: &[f32],
    ) -> Option<Answer> {
        let (w, h) = (self.meta.width as usize, self.meta.height as usize);
        let z = op.samples().filter(|z| z.len() == w * h)?;
        let centres = |ts: &[f32], n: usize| -> Option<Vec<usize>> {
            ts.iter().map(|&t| super::centre_index(t, n)).collect()
        };
        let (cols, rows) = (centres(xs, w)?, centres(ys, h)?);
        let mut values = Vec::with_capacity(cols.len() * rows.len());
        // A window's columns are consecutive samples: a copy a row.
        let run = super::consecutive(&cols);
        for &j in &rows {
            let row = &z[j * w..(j + 1) * w];
            match &run {
                Some(r) => values.extend_from_slice(&row[r.clone()]),
                None => values.extend(cols.iter().map(|&i| row[i])),
            }
        }
        Some(Answer::Values {
            values,
            error_bound: 0.0,
            iterations: 0,
        })
    }

    /// Plane `k` at the pixels inside the asset by continuous decoding: offered to
    /// `resources.device` first, else on the CPU in bands, looking at `resources.given_up`
    /// before each.
    pub(super) fn continuous_plane(
        &self,
        k: usize,
        inside: &Inside,
        (iterations, tol): (u32, f32),
        resources: &Resources<'_>,
    ) -> Result<Answer, Cancelled> {
        let stop = || {
            if resources.asker_gave_up() {
                Err(Cancelled)
            } else {
                Ok(())
            }
        };
        let p = &self.planes()[k];
        Ok(match inside {
            Inside::Grid { ix, iy, .. } => {
                if let Some(values) = self.on_samples(&p.operator, ix, iy) {
                    return Ok(values);
                }
                let at = Sites::Grid { xs: ix, ys: iy };
                // Where the CPU takes the same steps at every pixel (a subdivision), the
                // device and every band take exactly those, so that all answer alike.
                let (iterations, tol) = match p.operator.grid_steps(ix, iy, iterations, tol) {
                    Some(k) => (k, 0.0),
                    None => (iterations, tol),
                };
                let offered = resources
                    .device
                    .and_then(|d| d(PlaneRef::whole(k, &p.operator), at, iterations, tol));
                let answer = match offered {
                    Some(v) => v,
                    None => {
                        let rows = (BAND_POINTS / ix.len().max(1)).max(1);
                        let mut v = Vec::with_capacity(ix.len() * iy.len());
                        for band in iy.chunks(rows) {
                            stop()?;
                            v.extend(p.operator.grid(ix, band, iterations, tol));
                        }
                        Answer::Points(v)
                    }
                };
                answer.limited(&p.operator, at)
            }
            Inside::List {
                points,
                loose,
                patches,
                ..
            } => match resources
                .device
                .and_then(|d| {
                    d(
                        PlaneRef::whole(k, &p.operator),
                        Sites::List(points),
                        iterations,
                        tol,
                    )
                })
                .map(|a| a.limited(&p.operator, Sites::List(points)))
            {
                Some(v) => v,
                None => {
                    let mut v = Vec::with_capacity(points.len());
                    for band in points[..*loose].chunks(BAND_POINTS) {
                        stop()?;
                        v.extend(p.operator.points(band, iterations, tol));
                    }
                    for (pa, inside) in patches {
                        stop()?;
                        let all = p.operator.patch(&pa.patch, iterations, tol);
                        if inside.iter().all(|&i| i) {
                            v.extend_from_slice(&all);
                            continue;
                        }
                        v.extend(
                            all.into_iter()
                                .zip(inside)
                                .filter(|(_, i)| **i)
                                .map(|(r, _)| r),
                        );
                    }
                    Answer::Points(v).limited(&p.operator, Sites::List(points))
                }
            },
        })
    }
}
