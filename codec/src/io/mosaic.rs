//! Mosaics: many GeoTIFFs that tile an area (SRTM and Copernicus DEMs come as 1-degree
//! tiles) read as one raster, by bands of rows ([`Mosaic`]) or whole ([`open`]).
//!
//! The inputs must share a CRS. Those on the grid of the finest input (the same pixel size,
//! origins a whole number of pixels apart) are read as they are; the others (another pixel
//! size, or an origin off by a fraction of a cell) are resampled onto it ([`Resampled`]:
//! bilinear, or the area average where coarser), never silently shifted. Inputs in another
//! CRS get an error that names them (reprojection is not done yet). Cells no input covers are
//! nodata. Where inputs overlap (SRTM tiles
//! share their edge rows and columns), the first input in the order given that has data there
//! wins; a folder's files are taken in name order.

use std::path::{Path, PathBuf};

use fractile_proto::{Georef, SampleFormat};

use crate::Error;
use crate::io::raster::Raster;
use crate::io::resample::{Reprojected, Resampled};
use crate::io::rows::{GeoTiff, Header, InMemory, Rows, cut_at, is_tiff};

/// A part's rows of a band: its column on the mosaic, its first row, its cells.
type PartBand = (usize, usize, Raster);

/// Parts of a mosaic read at once for a band: reads by range wait on the network far more
/// than on a core.
const READERS: usize = 16;

/// How far (in pixels) two origins may be from a whole number of pixels apart, or two pixel
/// sizes apart relative to their size, and still count as one grid: far above the rounding of
/// coordinates a GeoTIFF stores in f64, far below any real misalignment.
const SAME_GRID: f64 = 1e-6;

// The widest and tallest mosaics: with the rows they bound (their resampled inputs too).
pub use crate::io::rows::{MAX_HEIGHT, MAX_WIDTH};

/// The rasters a list of paths names: each file as given, each folder's `.tif` / `.tiff` files
/// in name order.
pub fn input_files(paths: &[PathBuf]) -> Result<Vec<PathBuf>, Error> {
    let mut files = Vec::new();
    for p in paths {
        if p.is_dir() {
            let mut in_dir: Vec<PathBuf> = std::fs::read_dir(p)
                .map_err(|e| {
                    Error::input(format!("{}: {e}", p.display()))
                        .at(p)
                        .caused_by(e)
                })?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| {
                    f.is_file()
                        && f.extension().and_then(|e| e.to_str()).is_some_and(|e| {
                            e.eq_ignore_ascii_case("tif") || e.eq_ignore_ascii_case("tiff")
                        })
                })
                .collect();
            if in_dir.is_empty() {
                return Err(Error::input(format!(
                    "{}: a folder with no GeoTIFF (.tif, .tiff) in it",
                    p.display()
                )));
            }
            in_dir.sort();
            files.extend(in_dir);
        } else {
            files.push(p.clone());
        }
    }
    Ok(files)
}

/// Reads `paths` (see [`input_files`]) as one raster: the one file itself, or the mosaic of
/// several, whole (a chunked encode reads them by bands instead: [`open_rows`]).
pub fn open(paths: &[PathBuf]) -> Result<Raster, Error> {
    open_rows(paths)?.read_all()
}

/// The raster `paths` name (see [`input_files`]) as bands of rows: one GeoTIFF
/// read by its strips or tiles, a mosaic of several read band by band from each, any other
/// file (PNG, JPEG) decoded whole.
pub fn open_rows(paths: &[PathBuf]) -> Result<Box<dyn Rows>, Error> {
    let files = input_files(paths)?;
    match files.as_slice() {
        [one] if is_tiff(one) => Ok(Box::new(GeoTiff::open(one)?)),
        [one] => Ok(Box::new(InMemory::owned(Raster::open(one)?))),
        _ => Ok(Box::new(Mosaic::open(&files)?)),
    }
}

/// A mosaic of GeoTIFFs read by bands of rows: each band gathered from the inputs it crosses,
/// each read by its own strips or tiles.
pub struct Mosaic {
    header: Header,
    /// Each input (on the mosaic's grid, or resampled onto it) and its column and row on it.
    parts: Vec<([usize; 2], Box<dyn Rows>)>,
    /// How many inputs were resampled onto the mosaic's grid.
    resampled: usize,
}

impl Mosaic {
    /// Reads the headers of `files` (GeoTIFFs on one grid) and places them.
    pub fn open(files: &[PathBuf]) -> Result<Mosaic, Error> {
        let mut parts = Vec::with_capacity(files.len());
        for f in files {
            if !is_tiff(f) {
                return Err(Error::input(format!(
                    "{}: a mosaic's inputs are GeoTIFFs (.tif, .tiff)",
                    f.display()
                )));
            }
            parts.push(GeoTiff::open(f)?);
        }
        Mosaic::of(parts)
    }

    /// The mosaic of GeoTIFFs already opened (local or read by range), placed on one grid:
    /// theirs, or where they differ in pixel size or alignment (one CRS), the finest input's
    /// (the first of the finest), the others resampled onto it ([`crate::mosaic::Resampled`]).
    pub fn of(parts: Vec<GeoTiff>) -> Result<Mosaic, Error> {
        Mosaic::on(parts, None)
    }

    /// [`Mosaic::of`] on the grid `grid` names (its input's name and georeference) when given:
    /// every input not on it resampled or reprojected onto it.
    pub fn on(parts: Vec<GeoTiff>, grid: Option<(PathBuf, Georef)>) -> Result<Mosaic, Error> {
        let names: Vec<PathBuf> = parts.iter().map(|p| p.source().name().into()).collect();
        let target = match grid {
            Some(g) => Some(g),
            None => finest(&names, &parts)?,
        };
        let mut resampled = 0;
        let mut boxed: Vec<Box<dyn Rows>> = Vec::with_capacity(parts.len());
        for (name, part) in names.iter().zip(parts) {
            let (Some((first, t)), Some(g)) = (&target, part.header().georef.clone()) else {
                boxed.push(Box::new(part));
                continue;
            };
            let at = |e: Error| {
                let p = name.display();
                Error::input(format!("{p}: {e}")).at(name)
            };
            if g.epsg != t.epsg {
                boxed.push(Box::new(Reprojected::new(Box::new(part), t).map_err(at)?));
                resampled += 1;
            } else if offset((first.as_path(), t), (name.as_path(), &g)).is_err() {
                boxed.push(Box::new(Resampled::new(Box::new(part), t).map_err(at)?));
                resampled += 1;
            } else {
                boxed.push(Box::new(part));
            }
        }
        let headers: Vec<(&Path, &Header)> = names
            .iter()
            .zip(&boxed)
            .map(|(f, p)| (f.as_path(), p.header()))
            .collect();
        let (mut header, at) = place(&headers)?;
        if resampled > 0 {
            // Said in the asset (its encoder line, shown by `fractile info` and the server):
            // what a reader may hold the cells to.
            header.lineage = Some(format!(
                "{resampled} of {} inputs resampled onto this grid (bilinear, or the area \
                 average where a cell is coarser; reprojected where of another CRS): each such \
                 cell a weighted mean of input cells, between the least and the greatest of them",
                names.len()
            ));
        }
        Ok(Mosaic {
            header,
            parts: at.into_iter().zip(boxed).collect(),
            resampled,
        })
    }

    /// How many inputs were resampled onto the mosaic's grid (bilinear, or averaged where
    /// coarser): each resampled cell lies between the input cells it is made from.
    pub fn resampled(&self) -> usize {
        self.resampled
    }
}

impl Rows for Mosaic {
    fn header(&self) -> &Header {
        &self.header
    }

    fn read(&mut self, y0: usize, y1: usize) -> Result<Raster, Error> {
        let w = self.header.width;
        let y1 = y1.min(self.header.height);
        let n = w * y1.saturating_sub(y0);
        let mut values = vec![f32::NAN; n];
        let mut valid = vec![false; n];
        // The parts the band crosses, read side by side (a part read by range waits on the
        // network, a local one on inflate), then laid down in order: the first input with
        // data at a cell keeps it.
        let crossing: Vec<&mut ([usize; 2], Box<dyn Rows>)> = self
            .parts
            .iter_mut()
            .filter(|(at, part)| y0.max(at[1]) < y1.min(at[1] + part.header().height))
            .collect();
        let per = crossing.len().div_ceil(READERS).max(1);
        let mut crossing = crossing;
        let bands: Vec<Result<Vec<PartBand>, Error>> = std::thread::scope(|s| {
            let workers: Vec<_> = crossing
                .chunks_mut(per)
                .map(|some| {
                    s.spawn(move || {
                        some.iter_mut()
                            .map(|([ox, oy], part)| {
                                let to = y1.min(*oy + part.header().height);
                                let from = y0.max(*oy);
                                Ok((*ox, from, part.read(from - *oy, to - *oy)?))
                            })
                            .collect()
                    })
                })
                .collect();
            workers
                .into_iter()
                .map(|w| {
                    w.join()
                        .unwrap_or_else(|_| Err(Error::input("a reader of the mosaic panicked")))
                })
                .collect()
        });
        for (ox, from, band) in bands
            .into_iter()
            .collect::<Result<Vec<_>, _>>()?
            .into_iter()
            .flatten()
        {
            let pw = band.width;
            let to = from + band.height;
            for y in from..to {
                for x in 0..pw {
                    let (i, k) = ((y - from) * pw + x, (y - y0) * w + ox + x);
                    // The first input with data here keeps the cell.
                    if valid[k] || !band.is_valid(i) {
                        continue;
                    }
                    valid[k] = true;
                    values[k] = band.channels[0][i];
                }
            }
        }
        let valid = valid.contains(&false).then_some(valid);
        Ok(self.header.band([0, y0], w, vec![values], valid))
    }
}

/// The grid a mosaic of `parts` is made on, with its input's name for messages: the
/// georeference of the input with the smallest cells (the first of them); where the inputs
/// are in more than one CRS, of the longitude/latitude inputs only (the others are
/// reprojected onto it: cells in degrees and in metres do not compare, and a lon/lat grid is
/// what global collections share). `None` without georeferences.
fn finest(names: &[PathBuf], parts: &[GeoTiff]) -> Result<Option<(PathBuf, Georef)>, Error> {
    let placed: Vec<(&PathBuf, Georef)> = names
        .iter()
        .zip(parts)
        .filter_map(|(n, p)| Some((n, p.header().georef.clone()?)))
        .collect();
    let one_crs = placed.windows(2).all(|w| w[0].1.epsg == w[1].1.epsg);
    let lonlat = |g: &Georef| {
        g.epsg
            .is_none_or(|c| crate::geo::epsg_is_geographic(c) == Some(true))
    };
    let candidates: Vec<&(&PathBuf, Georef)> = placed
        .iter()
        .filter(|(_, g)| one_crs || lonlat(g))
        .collect();
    if candidates.is_empty() && !placed.is_empty() {
        return Err(Error::input(format!(
            "{} is in {} and {} in {}: inputs in several projected CRSs need one on a \
             longitude/latitude grid, which the others are reprojected onto",
            placed[0].0.display(),
            crs_name(placed[0].1.epsg),
            placed[placed.len() - 1].0.display(),
            crs_name(placed[placed.len() - 1].1.epsg)
        )));
    }
    Ok(candidates
        .into_iter()
        .min_by(|a, b| {
            let area = |g: &Georef| (g.pixel_size[0] * g.pixel_size[1]).abs();
            area(&a.1).total_cmp(&area(&b.1))
        })
        .map(|(n, g)| ((*n).clone(), g.clone())))
}

/// Where a part lies on the first part's grid: its column and row offsets.
fn offset(first: (&Path, &Georef), part: (&Path, &Georef)) -> Result<[i64; 2], Error> {
    let ((f, g0), (p, g)) = (first, part);
    if g.epsg != g0.epsg {
        return Err(Error::input(format!(
            "{} is in {} and {} in {}: a mosaic's inputs share one CRS (reproject them first)",
            p.display(),
            crs_name(g.epsg),
            f.display(),
            crs_name(g0.epsg)
        )));
    }
    for k in 0..2 {
        // A NaN (a zero or non-finite pixel size) is refused too.
        let apart = ((g.pixel_size[k] - g0.pixel_size[k]) / g0.pixel_size[k]).abs();
        if apart.is_nan() || apart > SAME_GRID {
            return Err(Error::input(format!(
                "{} has pixels of {:?} and {} of {:?}: a mosaic's inputs share one resolution (resample them first)",
                p.display(),
                g.pixel_size,
                f.display(),
                g0.pixel_size
            )));
        }
    }
    let mut at = [0i64; 2];
    for (k, at) in at.iter_mut().enumerate() {
        let cells = (g.origin[k] - g0.origin[k]) / g0.pixel_size[k];
        let off = (cells - cells.round()).abs();
        if off.is_nan() || off > SAME_GRID {
            return Err(Error::input(format!(
                "{} is {:.3} pixels off the grid of {} (not a whole number): a mosaic's inputs share one grid",
                p.display(),
                cells - cells.round(),
                f.display()
            )));
        }
        *at = cells.round() as i64;
    }
    Ok(at)
}

fn crs_name(epsg: Option<u32>) -> String {
    epsg.map_or_else(|| "an unnamed CRS".into(), |c| format!("EPSG:{c}"))
}

/// The header of the mosaic of `parts` (each with the path it came from, for errors) and
/// where each lies on it: the union of their extents on their shared grid (see the module's
/// documentation).
fn place(parts: &[(&Path, &Header)]) -> Result<(Header, Vec<[usize; 2]>), Error> {
    let Some(&(first_path, first)) = parts.first() else {
        return Err(Error::input("a mosaic of no rasters"));
    };
    let georef = |(p, r): (&Path, &Header)| {
        r.georef.clone().ok_or_else(|| {
            Error::input(format!(
                "{} has no georeference: a mosaic places its inputs by theirs",
                p.display()
            ))
        })
    };
    let g0 = georef(parts[0])?;
    let mut placed = Vec::with_capacity(parts.len());
    for &(p, r) in parts {
        if r.kind != first.kind || r.channels != first.channels {
            return Err(Error::input(format!(
                "{} and {} hold different kinds of data (a height field and an image, or different channels)",
                p.display(),
                first_path.display()
            )));
        }
        let g = georef((p, r))?;
        placed.push((offset((first_path, &g0), (p, &g))?, r));
    }
    let lo = |k: usize| placed.iter().map(|(at, _)| at[k]).min().unwrap_or(0);
    let size = |r: &Header| [r.width as i64, r.height as i64];
    let hi = |k: usize| {
        placed
            .iter()
            .map(|(at, r)| at[k] + size(r)[k])
            .max()
            .unwrap_or(0)
    };
    let (x0, y0) = (lo(0), lo(1));
    let (w, h) = ((hi(0) - x0) as usize, (hi(1) - y0) as usize);
    if w > MAX_WIDTH || h > MAX_HEIGHT {
        return Err(Error::input(format!(
            "the mosaic of these inputs is {w}x{h}, larger than the {MAX_WIDTH} samples wide and {MAX_HEIGHT} high this version encodes (are they of one area?)"
        )));
    }
    let same = |f: &dyn Fn(&Header) -> bool| parts.iter().all(|(_, r)| f(r));
    let header = Header {
        width: w,
        height: h,
        channels: first.channels,
        kind: first.kind,
        sample: if same(&|r| r.sample == first.sample) {
            first.sample
        } else {
            SampleFormat::F32
        },
        units: if same(&|r| r.units == first.units) {
            first.units.clone()
        } else {
            None
        },
        nodata: first.nodata,
        georef: Some(cut_at(&g0, [x0 as f64, y0 as f64])),
        lineage: None,
    };
    let at = placed
        .iter()
        .map(|(at, _)| [(at[0] - x0) as usize, (at[1] - y0) as usize])
        .collect();
    Ok((header, at))
}

/// `nx x ny` copies of `src` side by side, odd columns of copies flipped left-right and odd
/// rows upside down, so that copies meet without a step: large real rasters for tests and
/// benches (issue 30: never synthetic noise). Single-channel; no georeference (the caller
/// places it).
pub fn mirrored(src: &Raster, nx: usize, ny: usize) -> Result<Raster, Error> {
    let (w, h) = (src.width, src.height);
    let (mw, mh) = (nx * w, ny * h);
    let mut values = vec![0f32; mw * mh];
    for y in 0..mh {
        let (cy, sy) = (y / h, y % h);
        let sy = if cy % 2 == 1 { h - 1 - sy } else { sy };
        for x in 0..mw {
            let (cx, sx) = (x / w, x % w);
            let sx = if cx % 2 == 1 { w - 1 - sx } else { sx };
            values[y * mw + x] = src.channels[0][sy * w + sx];
        }
    }
    let mut r = Raster::from_values(mw, mh, values, src.kind)?;
    r.sample = src.sample;
    r.units = src.units.clone();
    Ok(r)
}
