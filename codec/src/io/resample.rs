//! An input on another grid of the same CRS (another pixel size, or an origin off the grid by
//! a fraction of a cell) read on the mosaic's grid (issue 78): heights bilinear between the
//! four input cells around a target cell's centre where the target is as fine as the input or
//! finer, the area-weighted average of the input cells a target cell covers where it is
//! coarser (as GDAL's `bilinear` and `average` resamplings do). Nodata cells take no weight
//! (the others' are renormalised); a target cell none reaches is nodata. Separable: each axis
//! has its taps, computed once.
//!
//! Every resampled value is a weighted mean of input cells, so it lies between the least and
//! the greatest of the cells it is made from: that is the bound it keeps against the inputs.

use fractile_proto::{Georef, SampleFormat};

use crate::Error;
use crate::io::raster::Raster;
use crate::io::rows::{Header, Rows, cut_at};

/// The input cells one target cell is made of along one axis: the first index and a weight
/// for it and each next one.
#[derive(Clone, Debug, PartialEq)]
struct Taps {
    first: usize,
    weights: Vec<f64>,
}

/// The taps of `count` target cells from `start` (target cell index of the first) along an
/// axis where the input's first edge is at `edge` in target cells and each input cell is
/// `ratio` target cells wide, the input `cells` long: bilinear when `ratio >= 1` (the target
/// as fine or finer), area average otherwise. `None` for a cell the input does not reach.
fn taps(start: i64, count: usize, edge: f64, ratio: f64, cells: usize) -> Vec<Option<Taps>> {
    let n = cells as f64;
    (0..count)
        .map(|k| {
            let centre = (start + k as i64) as f64 + 0.5;
            // In input cells, edges at integers.
            let u = (centre - edge) / ratio;
            if ratio >= 1.0 - 1e-9 {
                if !(0.0..=n).contains(&u) {
                    return None;
                }
                let s = (u - 0.5).clamp(0.0, n - 1.0);
                let k0 = s.floor();
                let f = s - k0;
                let k0 = k0 as usize;
                Some(match f > 1e-12 && k0 + 1 < cells {
                    true => Taps {
                        first: k0,
                        weights: vec![1.0 - f, f],
                    },
                    false => Taps {
                        first: k0,
                        weights: vec![1.0],
                    },
                })
            } else {
                let half = 0.5 / ratio;
                let (lo, hi) = ((u - half).max(0.0), (u + half).min(n));
                if hi <= lo {
                    return None;
                }
                let first = lo.floor() as usize;
                let last = (hi.ceil() as usize).min(cells);
                let weights = (first..last)
                    .map(|p| (hi.min(p as f64 + 1.0) - lo.max(p as f64)).max(0.0))
                    .collect();
                Some(Taps { first, weights })
            }
        })
        .collect()
}

/// An error where `count` target cells along axis `a` (0 across, 1 down) are more than a
/// mosaic takes ([`crate::mosaic::MAX_WIDTH`], [`crate::mosaic::MAX_HEIGHT`]).
fn too_large(count: usize, a: usize) -> Result<(), Error> {
    use crate::io::rows::{MAX_HEIGHT, MAX_WIDTH};
    let most = if a == 0 { MAX_WIDTH } else { MAX_HEIGHT };
    match count <= most {
        true => Ok(()),
        false => Err(Error::input(format!(
            "{count} cells {} on the target grid, more than the {most} a mosaic takes (is the \
             target grid far finer than the input?)",
            if a == 0 { "across" } else { "down" }
        ))),
    }
}

/// The weighted mean of the valid input cells `row` x `col` of `band` (whose first row is
/// input row `r0`): nodata cells take no weight; `None` where none is valid.
fn weighted(band: &Raster, r0: usize, row: &Taps, col: &Taps) -> Option<f32> {
    let (mut sum, mut weight) = (0.0f64, 0.0f64);
    for (dr, wr) in row.weights.iter().enumerate() {
        for (dc, wc) in col.weights.iter().enumerate() {
            let at = (row.first + dr - r0) * band.width + col.first + dc;
            if band.is_valid(at) {
                sum += wr * wc * f64::from(band.channels[0][at]);
                weight += wr * wc;
            }
        }
    }
    (weight > 1e-12).then(|| (sum / weight) as f32)
}

/// An input read on another grid of its CRS: the window of target cells whose centres lie
/// on it.
pub struct Resampled {
    inner: Box<dyn Rows>,
    header: Header,
    cols: Vec<Option<Taps>>,
    rows: Vec<Option<Taps>>,
}

impl Resampled {
    /// `inner` on the grid of `target` (the same CRS: the caller checks): its window there.
    pub fn new(inner: Box<dyn Rows>, target: &Georef) -> Result<Resampled, Error> {
        let h = inner.header().clone();
        let Some(g) = h.georef.clone() else {
            return Err(Error::input(
                "a raster with no georeference cannot be resampled",
            ));
        };
        let axis = |a: usize, cells: usize| {
            // The input's first edge and its cell, in target cells.
            let edge = (g.origin[a] - target.origin[a]) / target.pixel_size[a];
            let ratio = g.pixel_size[a] / target.pixel_size[a];
            if !(edge.is_finite() && ratio.is_finite() && ratio > 0.0) {
                return Err(Error::input(format!(
                    "pixels of {:?} against {:?}: axes that run opposite ways are not resampled",
                    g.pixel_size, target.pixel_size
                )));
            }
            let far = edge + ratio * cells as f64;
            let start = (edge - 0.5).ceil() as i64;
            let end = (far - 0.5).floor() as i64;
            let count = (end - start + 1).max(0) as usize;
            // Checked before the taps are made: a grid far finer than the input's.
            too_large(count, a)?;
            Ok((start, taps(start, count, edge, ratio, cells)))
        };
        let (x0, cols) = axis(0, h.width)?;
        let (y0, rows) = axis(1, h.height)?;
        let header = Header {
            width: cols.len(),
            height: rows.len(),
            // Weighted means are not integers.
            sample: SampleFormat::F32,
            georef: Some(Georef {
                epsg: g.epsg,
                ..cut_at(target, [x0 as f64, y0 as f64])
            }),
            ..h
        };
        Ok(Resampled {
            inner,
            header,
            cols,
            rows,
        })
    }
}

impl Rows for Resampled {
    fn header(&self) -> &Header {
        &self.header
    }

    fn read(&mut self, y0: usize, y1: usize) -> Result<Raster, Error> {
        let (w, y1) = (self.header.width, y1.min(self.header.height));
        let span = |t: &Taps| (t.first, t.first + t.weights.len());
        let needed = self.rows[y0..y1].iter().flatten().map(span);
        let (r0, r1) = needed.fold((usize::MAX, 0), |(a, b), (s, e)| (a.min(s), b.max(e)));
        let n = w * y1.saturating_sub(y0);
        let (mut values, mut valid) = (vec![f32::NAN; n], vec![false; n]);
        if r0 < r1 {
            let band = self.inner.read(r0, r1)?;
            for (j, row) in self.rows[y0..y1].iter().enumerate() {
                let Some(row) = row else { continue };
                for (i, col) in self.cols.iter().enumerate() {
                    let Some(col) = col else { continue };
                    if let Some(v) = weighted(&band, r0, row, col) {
                        values[j * w + i] = v;
                        valid[j * w + i] = true;
                    }
                }
            }
        }
        let valid = valid.contains(&false).then_some(valid);
        Ok(self.header.band([0, y0], w, vec![values], valid))
    }
}

/// An input in another CRS (UTM, Web Mercator, a national grid: any the placement knows) read
/// on a longitude/latitude grid (issue 78): each target cell's centre taken to the input's
/// CRS (proj4rs) and its height bilinear between the four input cells around it, or, where a
/// target cell covers more than an input cell each way, the average of the input cells its
/// footprint's box covers. Nodata as in [`Resampled`]; every value a weighted mean of input
/// cells, as there.
pub struct Reprojected {
    inner: Box<dyn Rows>,
    header: Header,
    input: crate::geo::Placement,
    target: Georef,
    size: [usize; 2],
}

impl Reprojected {
    /// `inner` on the longitude/latitude grid `target`: its window there (the cells whose
    /// centres lie in the input's longitude/latitude box).
    pub fn new(inner: Box<dyn Rows>, target: &Georef) -> Result<Reprojected, Error> {
        let h = inner.header().clone();
        let Some(g) = h.georef.clone() else {
            return Err(Error::input(
                "a raster with no georeference cannot be reprojected",
            ));
        };
        let input = crate::geo::Placement::of(&g, h.width as u32, h.height as u32)
            .map_err(|e| Error::input(format!("its CRS cannot be placed: {e}")))?;
        let [w, s, e, n] = input.bounds();
        let (px, py) = (target.pixel_size[0], target.pixel_size[1]);
        if !(px > 0.0 && py < 0.0) {
            return Err(Error::input("a target grid that is not north-up"));
        }
        let x0 = ((w - target.origin[0]) / px - 0.5).ceil() as i64;
        let x1 = ((e - target.origin[0]) / px - 0.5).floor() as i64;
        let y0 = ((n - target.origin[1]) / py - 0.5).ceil() as i64;
        let y1 = ((s - target.origin[1]) / py - 0.5).floor() as i64;
        let (width, height) = ((x1 - x0 + 1).max(0) as usize, (y1 - y0 + 1).max(0) as usize);
        too_large(width, 0)?;
        too_large(height, 1)?;
        let window = Georef {
            epsg: target.epsg,
            origin: [
                target.origin[0] + x0 as f64 * px,
                target.origin[1] + y0 as f64 * py,
            ],
            pixel_size: target.pixel_size,
        };
        let header = Header {
            width,
            height,
            sample: SampleFormat::F32,
            georef: Some(window.clone()),
            ..h.clone()
        };
        Ok(Reprojected {
            inner,
            header,
            input,
            target: window,
            size: [h.width, h.height],
        })
    }

    /// Input cell coordinates (edges at integers) of (lon, lat).
    fn at(&self, lon: f64, lat: f64) -> Option<[f64; 2]> {
        let [u, v] = self.input.unit_f64(lon, lat)?;
        Some([u * self.size[0] as f64, v * self.size[1] as f64])
    }
}

impl Rows for Reprojected {
    fn header(&self) -> &Header {
        &self.header
    }

    fn read(&mut self, y0: usize, y1: usize) -> Result<Raster, Error> {
        let (w, y1) = (self.header.width, y1.min(self.header.height));
        let (px, py) = (self.target.pixel_size[0], self.target.pixel_size[1]);
        let [iw, ih] = self.size;
        // Each target cell's box in input cells: its centre's position and, from its corners,
        // how many input cells it spans each way.
        let mut boxes: Vec<Option<([f64; 2], [f64; 2])>> = Vec::with_capacity(w * (y1 - y0));
        for j in y0..y1 {
            let lat = self.target.origin[1] + (j as f64 + 0.5) * py;
            for i in 0..w {
                let lon = self.target.origin[0] + (i as f64 + 0.5) * px;
                let corners = [(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)]
                    .map(|(a, b)| self.at(lon + a * px, lat + b * py));
                let (Some(c), [Some(a), Some(b), Some(d), Some(e)]) = (self.at(lon, lat), corners)
                else {
                    boxes.push(None);
                    continue;
                };
                let span = |k: usize| {
                    let v = [a[k], b[k], d[k], e[k]];
                    v.iter().fold(f64::MIN, |m, &x| m.max(x))
                        - v.iter().fold(f64::MAX, |m, &x| m.min(x))
                };
                boxes.push(Some((c, [span(0), span(1)])));
            }
        }
        let axis = |centre: f64, span: f64, cells: usize| -> Option<Taps> {
            match span > 1.0 {
                false => taps(0, 1, -centre + 0.5, 1.0, cells).pop().flatten(),
                true => taps(0, 1, 0.5 - centre / span, 1.0 / span, cells)
                    .pop()
                    .flatten(),
            }
        };
        let cells: Vec<Option<(Taps, Taps)>> = boxes
            .iter()
            .map(|b| {
                let ([cx, cy], [sx, sy]) = (*b)?;
                Some((axis(cx, sx, iw)?, axis(cy, sy, ih)?))
            })
            .collect();
        let (r0, r1) = cells
            .iter()
            .flatten()
            .fold((usize::MAX, 0), |(a, b), (_, r)| {
                (a.min(r.first), b.max(r.first + r.weights.len()))
            });
        let n = w * (y1 - y0);
        let (mut values, mut valid) = (vec![f32::NAN; n], vec![false; n]);
        if r0 < r1 {
            let band = self.inner.read(r0, r1)?;
            for (k, taps) in cells.iter().enumerate() {
                let Some((col, row)) = taps else { continue };
                if let Some(v) = weighted(&band, r0, row, col) {
                    values[k] = v;
                    valid[k] = true;
                }
            }
        }
        let valid = valid.contains(&false).then_some(valid);
        Ok(self.header.band([0, y0], w, vec![values], valid))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn taps_are_bilinear_finer_and_area_weighted_coarser() {
        // The same grid: each target cell is its input cell.
        let same = taps(0, 4, 0.0, 1.0, 4);
        for (k, t) in same.iter().enumerate() {
            assert_eq!(
                t.as_ref().unwrap(),
                &Taps {
                    first: k,
                    weights: vec![1.0]
                }
            );
        }
        // Half a cell off: halfway between two input cells.
        let off = taps(0, 3, -0.5, 1.0, 4);
        assert_eq!(
            off[1].as_ref().unwrap(),
            &Taps {
                first: 1,
                weights: vec![0.5, 0.5]
            }
        );
        // Twice as coarse: two input cells a target cell, equal weights.
        let coarse = taps(0, 2, 0.0, 0.5, 4);
        assert_eq!(
            coarse[1].as_ref().unwrap(),
            &Taps {
                first: 2,
                weights: vec![1.0, 1.0]
            }
        );
        // Past the input: nothing.
        assert!(taps(10, 1, 0.0, 1.0, 4)[0].is_none());
    }

    /// A target grid so fine that the input would span more cells than a mosaic takes is
    /// refused before its taps are made.
    #[test]
    fn a_target_grid_far_finer_than_the_input_is_refused() {
        let mut r =
            Raster::from_values(4, 4, vec![1.0; 16], fractile_proto::AssetKind::HeightField)
                .unwrap();
        let g = Georef {
            epsg: Some(4326),
            origin: [0.0, 1.0],
            pixel_size: [0.25, -0.25],
        };
        r.georef = Some(g.clone());
        let fine = Georef {
            pixel_size: [1e-6, -1e-6],
            ..g
        };
        let inner = Box::new(crate::io::rows::InMemory::owned(r));
        let err = Resampled::new(inner, &fine)
            .err()
            .expect("refused")
            .to_string();
        assert!(err.contains("more than"), "{err}");
    }
}
