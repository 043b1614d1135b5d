//! Answers of chunked assets (`io::chunked`): every pixel or point is answered by the chunk
//! that owns it, at the level whose cells match the pixels' size. No math of its own beyond
//! moving unit coordinates between the asset and a chunk: each chunk answers as any asset.
//!
//! The level: pixels of `f` source cells are sampled from level `round(log2 f)`, whose cells
//! are then between 0.7 and 1.4 pixels, continuously (the overview is the filter, so a chunk is
//! never decoded discretely for coarse pixels), unless that level is a view and the pixels
//! span half the raster or more (then the coded level above the views). On the coarsest level, which is one chunk, pixels coarser still are filtered by that
//! chunk as any asset filters them.

use fractile_proto::AssetMeta;
use rayon::prelude::*;

use super::{Answer, ChainDevice, PlaneRef, PointSample, Resources, SampleError, Sites as Chains};
use crate::geo::{Pixels, Sites};
use crate::io::chunked::Chunked;

/// A chunk's answer at its pixels: a plane's values each, and their bound.
type PartAnswer = (Vec<Vec<f32>>, f32);

/// The pixels one chunk answers, in its unit coordinates, and where its answers go.
struct Part {
    /// The chunk's index in its level.
    index: usize,
    /// The pixels, in the chunk's unit coordinates.
    pixels: Pixels,
    /// Where each answer goes.
    back: Back,
}

/// Where a chunk's answers go in the whole request.
enum Back {
    /// Pixel `(cols[i], rows[j])` of the request's grid (`width` columns).
    Grid {
        cols: Vec<usize>,
        rows: Vec<usize>,
        width: usize,
    },
    /// Pixel `to[k]` of the request's list.
    List(Vec<usize>),
}

/// One axis of a level: which chunk owns unit coordinate `t`, and where `t` lies in the
/// cells that chunk codes.
struct Axis {
    /// Source cells on the axis.
    source: f32,
    /// Level cell size in source cells.
    scale: f32,
    /// Chunk side.
    chunk: u32,
    /// Chunks on the axis.
    count: u32,
    /// Level cells a view's samples lie before its cells' centres
    /// ([`crate::io::chunked::ChunkTable::view_shift`]).
    shift: f64,
}

impl Axis {
    /// The owning chunk of `t` and `t` in level cells, in f64: in f32 a position in level
    /// cells carries 2^-24 of the axis (2.4e-4 of a cell at 4,096 cells), and a chunk's
    /// continuation moves by a good part of its detail within that of a sample centre, which
    /// the chunk could then no longer tell it is on (`Asset::snap_to_samples`).
    fn owner(&self, t: f32) -> (u32, f64) {
        let x = f64::from(t) * f64::from(self.source) / f64::from(self.scale);
        let c = ((x / f64::from(self.chunk)).floor().max(0.0) as u32).min(self.count - 1);
        (c, x + self.shift)
    }
}

/// Whether `pixels` span half the unit square or more on both axes (a grid by its pixel count
/// and footprint, wherever it lies; points by their extent).
fn spans_half(pixels: &Pixels) -> bool {
    match &pixels.sites {
        Sites::Grid { xs, ys } => {
            xs.len() as f32 * pixels.footprint[0] >= 0.5
                && ys.len() as f32 * pixels.footprint[1] >= 0.5
        }
        Sites::List { points, .. } => {
            let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
            for [u, v] in points.iter().flatten() {
                (lo[0], hi[0]) = (lo[0].min(*u), hi[0].max(*u));
                (lo[1], hi[1]) = (lo[1].min(*v), hi[1].max(*v));
            }
            hi[0] - lo[0] >= 0.5 && hi[1] - lo[1] >= 0.5
        }
    }
}

impl Chunked {
    /// The level for pixels `cells` source cells wide (the smaller axis).
    fn level_for(&self, cells: f32) -> usize {
        let top = self.table.levels.len() - 1;
        if cells <= 1.0 || !cells.is_finite() {
            return 0;
        }
        ((cells.log2() + 0.5).floor() as usize).min(top)
    }

    /// The axes of `level`.
    /// A view level's chunks are level 0's, each `2^level` times smaller.
    fn axes(&self, meta: &AssetMeta, level: usize) -> [Axis; 2] {
        let t = &self.table;
        let l = &t.levels[level];
        let ((nx, ny), chunk) = if t.is_view(level) {
            (t.grid(meta.width, meta.height), t.chunk >> level)
        } else {
            (t.grid(l.width, l.height), t.chunk)
        };
        let (scale, shift) = ((1u64 << level) as f32, t.view_shift(level));
        [
            Axis {
                source: meta.width as f32,
                scale,
                chunk,
                count: nx,
                shift,
            },
            Axis {
                source: meta.height as f32,
                scale,
                chunk,
                count: ny,
                shift,
            },
        ]
    }

    /// The level the pixels are answered from, and the pixels of each chunk they touch. A view
    /// level never answers pixels that span half the raster or more on both axes: a view reads
    /// its source chunks whole, and such pixels (zoom 0 of a world raster just over the
    /// chunking threshold, 2160 x 1080, read 94% of its file through a view) are answered by
    /// the coded level above the views, its cells then at most 2^(1 + VIEW_DEPTH - l) pixels
    /// (issue 73). The rule is the request's size, not its place, so that the tiles of a zoom
    /// all take the same level (a rule by the bytes of the chunks under each tile answered a
    /// tile across a chunk seam from a coarser level than its neighbours).
    fn split(&self, meta: &AssetMeta, pixels: &Pixels) -> (usize, Vec<Part>) {
        let cells =
            (pixels.footprint[0] * meta.width as f32).min(pixels.footprint[1] * meta.height as f32);
        let mut level = self.level_for(cells);
        if self.table.is_view(level) && spans_half(pixels) {
            level = self.table.views.len() + 1;
        }
        (level, self.split_at(meta, pixels, level))
    }

    /// The pixels of each chunk of `level` they touch.
    fn split_at(&self, meta: &AssetMeta, pixels: &Pixels, level: usize) -> Vec<Part> {
        let top = level + 1 == self.table.levels.len();
        let [ax, ay] = self.axes(meta, level);
        let entries = &self.table.levels[level].chunks;
        // Footprint in level cells; below the top level at most one cell (see the module).
        let fp = |f: f32, axis: &Axis| {
            let f = f * axis.source / axis.scale;
            if top { f } else { f.min(1.0) }
        };
        let (fx, fy) = (fp(pixels.footprint[0], &ax), fp(pixels.footprint[1], &ay));
        let local = |x: f64, lo: u32, hi: u32| ((x - f64::from(lo)) / f64::from(hi - lo)) as f32;
        let mut parts = Vec::new();
        match &pixels.sites {
            Sites::Grid { xs, ys } => {
                let group = |ts: &[Option<f32>], axis: &Axis| {
                    let mut g: Vec<Vec<(usize, f64)>> = vec![Vec::new(); axis.count as usize];
                    for (i, t) in ts.iter().enumerate() {
                        if let Some(t) = t {
                            let (c, x) = axis.owner(*t);
                            g[c as usize].push((i, x));
                        }
                    }
                    g
                };
                let (cols, rows) = (group(xs, &ax), group(ys, &ay));
                for (cy, row) in rows.iter().enumerate().filter(|(_, r)| !r.is_empty()) {
                    for (cx, col) in cols.iter().enumerate().filter(|(_, c)| !c.is_empty()) {
                        let index = cy * ax.count as usize + cx;
                        let [x0, y0, x1, y1] = entries[index].cells;
                        parts.push(Part {
                            index,
                            pixels: Pixels {
                                sites: Sites::Grid {
                                    xs: col.iter().map(|&(_, x)| Some(local(x, x0, x1))).collect(),
                                    ys: row.iter().map(|&(_, y)| Some(local(y, y0, y1))).collect(),
                                },
                                footprint: [fx / (x1 - x0) as f32, fy / (y1 - y0) as f32],
                            },
                            back: Back::Grid {
                                cols: col.iter().map(|&(i, _)| i).collect(),
                                rows: row.iter().map(|&(j, _)| j).collect(),
                                width: xs.len(),
                            },
                        });
                    }
                }
            }
            Sites::List { points, .. } => {
                let mut groups: Vec<Vec<(usize, [f64; 2])>> = vec![Vec::new(); entries.len()];
                for (k, p) in points.iter().enumerate() {
                    if let Some([u, v]) = p {
                        let ((cx, x), (cy, y)) = (ax.owner(*u), ay.owner(*v));
                        groups[(cy * ax.count + cx) as usize].push((k, [x, y]));
                    }
                }
                for (index, group) in groups.into_iter().enumerate() {
                    if group.is_empty() {
                        continue;
                    }
                    let [x0, y0, x1, y1] = entries[index].cells;
                    parts.push(Part {
                        index,
                        pixels: Pixels {
                            sites: Sites::List {
                                width: group.len(),
                                points: group
                                    .iter()
                                    .map(|&(_, [x, y])| Some([local(x, x0, x1), local(y, y0, y1)]))
                                    .collect(),
                                patches: Vec::new(),
                            },
                            footprint: [fx / (x1 - x0) as f32, fy / (y1 - y0) as f32],
                        },
                        back: Back::List(group.into_iter().map(|(k, _)| k).collect()),
                    });
                }
            }
        }
        parts
    }

    /// [`crate::Asset::sample_with`] of a chunked asset: each chunk's pixels decoded by the
    /// chunk, its chains offered to `resources.device` with the chunk named (a device
    /// keeps each chunk's operator resident under its own key). Pixels of chunks with no
    /// valid cell, and pixels outside, are NaN.
    pub(crate) fn sample(
        &self,
        meta: &AssetMeta,
        pixels: &Pixels,
        (iterations, tolerance): (u32, f32),
        resources: &Resources<'_>,
    ) -> Result<(Vec<Vec<f32>>, f32), SampleError> {
        let (level, parts) = self.split(meta, pixels);
        // Chunks side by side (a whole read touches them all; a tile one to four): each is
        // decoded and answered on its own, then its answers put in place.
        let answers: Vec<Option<PartAnswer>> = parts
            .par_iter()
            .map(|part| self.sample_part(level, part, (iterations, tolerance), resources))
            .collect::<Result<_, _>>()?;
        let mut out = vec![vec![f32::NAN; pixels.len()]; meta.channels as usize];
        let mut bound = 0.0f32;
        for (part, answer) in parts.iter().zip(answers) {
            let Some((values, b)) = answer else {
                continue;
            };
            bound = bound.max(b);
            for (plane, v) in out.iter_mut().zip(values) {
                match &part.back {
                    Back::Grid { cols, rows, width } => {
                        let run = super::consecutive(cols);
                        for (j, &row) in rows.iter().enumerate() {
                            let v = &v[j * cols.len()..(j + 1) * cols.len()];
                            let plane = &mut plane[row * width..(row + 1) * width];
                            match &run {
                                Some(r) => plane[r.clone()].copy_from_slice(v),
                                None => {
                                    for (&col, &x) in cols.iter().zip(v) {
                                        plane[col] = x;
                                    }
                                }
                            }
                        }
                    }
                    Back::List(to) => {
                        for (&k, x) in to.iter().zip(v) {
                            plane[k] = x;
                        }
                    }
                }
            }
        }
        Ok((out, bound))
    }

    /// One part of [`Self::sample`]: its chunk's answers at its pixels (`None`: a chunk with
    /// no valid cell).
    fn sample_part(
        &self,
        level: usize,
        part: &Part,
        (iterations, tolerance): (u32, f32),
        resources: &Resources<'_>,
    ) -> Result<Option<PartAnswer>, SampleError> {
        if resources.asker_gave_up() {
            return Err(SampleError::Cancelled);
        }
        let Some(chunk) = self.chunk(level, part.index).map_err(SampleError::Chunk)? else {
            return Ok(None);
        };
        // Only the top level's pixels may be coarser than its cells (see `split`), and its
        // grids are the asset's (`Asset::discrete_planes`): kept under the asset's key where
        // the caller keeps grids (a server's coarse cache), instead of a decode a tile.
        let top = level + 1 == self.table.levels.len();
        let device = resources.device.map(|d| in_chunk(d, (level, part.index)));
        let own = Resources {
            device: device.as_ref().map(|d| d as &ChainDevice<'_>),
            coarse: resources.coarse.filter(|_| top),
            given_up: resources.given_up,
        };
        Ok(Some(chunk.sample_with(
            &part.pixels,
            iterations,
            tolerance,
            &own,
        )?))
    }

    /// [`crate::Asset::discrete_planes`] of a chunked asset: its top level's one chunk's, at
    /// `width x height` (nothing when the chunk cannot be read: the answer that needs it
    /// reports that chunk itself).
    pub(crate) fn top_discrete_planes(
        &self,
        width: usize,
        height: usize,
        iterations: u32,
        tolerance: f32,
    ) -> Vec<(
        crate::core::decode::Grid,
        crate::core::decode::DiscreteReport,
    )> {
        match self.chunk(self.table.levels.len() - 1, 0) {
            Ok(Some(top)) => top.discrete_planes(width, height, iterations, tolerance),
            _ => Vec::new(),
        }
    }

    /// [`crate::Asset::source_error_over`] of a chunked asset: the largest of the chunks'
    /// under the pixels.
    pub(crate) fn source_error_over(
        &self,
        meta: &AssetMeta,
        pixels: &Pixels,
    ) -> Result<Option<f32>, crate::Error> {
        let (level, parts) = self.split(meta, pixels);
        let mut worst: Option<f32> = None;
        for part in parts {
            if let Some(chunk) = self.chunk(level, part.index)?
                && let Some(e) = chunk.source_error_over(&part.pixels)?
            {
                worst = Some(worst.map_or(e, |w| w.max(e)));
            }
        }
        Ok(worst)
    }

    /// [`crate::Asset::points_with`] of a chunked asset: each point by the source level's
    /// chunk that owns it, its chains offered to `continuous` with the chunk named; points of
    /// chunks with no valid cell are NaN.
    pub(crate) fn points(
        &self,
        meta: &AssetMeta,
        pts: &[[f32; 2]],
        (iterations, tolerance): (u32, f32),
        continuous: &ChainDevice<'_>,
    ) -> Result<Vec<PointSample>, crate::Error> {
        let [ax, ay] = self.axes(meta, 0);
        let entries = &self.table.levels[0].chunks;
        let mut groups: Vec<Vec<(usize, [f32; 2])>> = vec![Vec::new(); entries.len()];
        for (k, &[u, v]) in pts.iter().enumerate() {
            let ((cx, x), (cy, y)) = (ax.owner(u), ay.owner(v));
            let [x0, y0, x1, y1] = entries[(cy * ax.count + cx) as usize].cells;
            let local = [
                ((x - f64::from(x0)) / f64::from(x1 - x0)) as f32,
                ((y - f64::from(y0)) / f64::from(y1 - y0)) as f32,
            ];
            groups[(cy * ax.count + cx) as usize].push((k, local));
        }
        let nodata = PointSample {
            values: vec![f32::NAN; meta.channels as usize],
            error_bound: 0.0,
            source_error: None,
            iterations: 0,
        };
        let mut out = vec![nodata; pts.len()];
        for (index, group) in groups.into_iter().enumerate() {
            if group.is_empty() {
                continue;
            }
            let Some(chunk) = self.chunk(0, index)? else {
                continue;
            };
            let local: Vec<[f32; 2]> = group.iter().map(|&(_, p)| p).collect();
            let hook = in_chunk(continuous, (0, index));
            for ((k, _), answer) in group
                .iter()
                .zip(chunk.points_with(&local, iterations, tolerance, &hook))
            {
                out[*k] = answer;
            }
        }
        Ok(out)
    }
}

impl crate::Asset {
    /// The byte ranges `(offset, length)` of the file that an answer at `pixels` reads: the
    /// chunks under them at the level they are answered from (none for whole assets, nor for
    /// chunks with no valid cell). A reader that fetches by range (a browser over HTTP) asks
    /// for these all at once before answering, instead of one round trip a chunk.
    pub fn chunk_ranges(&self, pixels: &Pixels) -> Vec<(u64, u64)> {
        let Some(c) = self.chunked() else {
            return Vec::new();
        };
        let (level, parts) = c.split(&self.meta, pixels);
        let entries = &c.table.levels[level].chunks;
        parts
            .iter()
            .map(|p| &entries[p.index])
            .filter(|e| e.length > 0)
            .map(|e| (e.offset, e.length))
            .collect()
    }

    /// [`Self::chunk_ranges`] of points (unit coordinates), which source chunks answer.
    pub fn point_chunk_ranges(&self, pts: &[[f32; 2]]) -> Vec<(u64, u64)> {
        let Some(c) = self.chunked() else {
            return Vec::new();
        };
        let [ax, ay] = c.axes(&self.meta, 0);
        let entries = &c.table.levels[0].chunks;
        let mut indices: Vec<usize> = pts
            .iter()
            .map(|&[u, v]| (ay.owner(v).0 * ax.count + ax.owner(u).0) as usize)
            .collect();
        indices.sort_unstable();
        indices.dedup();
        indices
            .into_iter()
            .map(|i| &entries[i])
            .filter(|e| e.length > 0)
            .map(|e| (e.offset, e.length))
            .collect()
    }
}

/// `continuous` for the planes of chunk `(level, index)`: a chunk is an asset of its own, and
/// knows not which chunk it is, so its planes are named here on their way to the hook.
fn in_chunk<'a>(
    continuous: &'a ChainDevice<'a>,
    chunk: (usize, usize),
) -> impl Fn(PlaneRef<'_>, Chains<'_>, u32, f32) -> Option<Answer> + Sync + 'a {
    move |plane, sites, n, t| {
        let plane = PlaneRef {
            chunk: Some(chunk),
            ..plane
        };
        continuous(plane, sites, n, t)
    }
}
