//! Mosaics: many georeferenced rasters that tile an area (SRTM and Copernicus DEMs come as
//! 1-degree tiles) read as one [`Raster`], which then encodes as any raster does.
//!
//! The inputs must share a grid: the same CRS, the same pixel size, and origins a whole number
//! of pixels apart. Reprojection and resampling are out of scope: inputs that would need them
//! get an error that says which input differs and how, rather than a mosaic that is silently
//! shifted or stretched. Cells no input covers are nodata. Where inputs overlap (SRTM tiles
//! share their edge rows and columns), the first input in the order given that has data there
//! wins; a folder's files are taken in name order.

use std::path::{Path, PathBuf};

use fractile_proto::{Georef, SampleFormat};

use crate::Error;
use crate::io::raster::Raster;

/// How far (in pixels) two origins may be from a whole number of pixels apart, or two pixel
/// sizes apart relative to their size, and still count as one grid: far above the rounding of
/// coordinates a GeoTIFF stores in f64, far below any real misalignment.
const SAME_GRID: f64 = 1e-6;

/// The largest mosaic in cells: inputs far apart would otherwise ask for a grid of mostly
/// nodata bigger than memory. The same side limit as a single raster has.
const MAX_SIDE: usize = 1 << 15;

/// The rasters a list of paths names: each file as given, each folder's `.tif` / `.tiff` files
/// in name order.
pub fn input_files(paths: &[PathBuf]) -> Result<Vec<PathBuf>, Error> {
    let mut files = Vec::new();
    for p in paths {
        if p.is_dir() {
            let mut in_dir: Vec<PathBuf> = std::fs::read_dir(p)
                .map_err(|e| Error::Input(format!("{}: {e}", p.display())))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| {
                    f.is_file()
                        && f.extension().and_then(|e| e.to_str()).is_some_and(|e| {
                            e.eq_ignore_ascii_case("tif") || e.eq_ignore_ascii_case("tiff")
                        })
                })
                .collect();
            if in_dir.is_empty() {
                return Err(Error::Input(format!(
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
/// several.
pub fn open(paths: &[PathBuf]) -> Result<Raster, Error> {
    let files = input_files(paths)?;
    if let [one] = files.as_slice() {
        return Raster::open(one);
    }
    let parts = files
        .iter()
        .map(|f| Raster::open(f).map(|r| (f.as_path(), r)))
        .collect::<Result<Vec<_>, _>>()?;
    mosaic(&parts)
}

/// Where a part lies on the first part's grid: its column and row offsets.
fn offset(first: (&Path, &Georef), part: (&Path, &Georef)) -> Result<[i64; 2], Error> {
    let ((f, g0), (p, g)) = (first, part);
    if g.epsg != g0.epsg {
        return Err(Error::Input(format!(
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
            return Err(Error::Input(format!(
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
            return Err(Error::Input(format!(
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

/// The mosaic of `parts` (each with the path it came from, for errors): one raster over the
/// union of their extents on their shared grid (see the module's documentation).
pub fn mosaic(parts: &[(&Path, Raster)]) -> Result<Raster, Error> {
    let Some((first_path, first)) = parts.first() else {
        return Err(Error::Input("a mosaic of no rasters".into()));
    };
    let georef = |(p, r): &(&Path, Raster)| {
        r.georef.clone().ok_or_else(|| {
            Error::Input(format!(
                "{} has no georeference: a mosaic places its inputs by theirs",
                p.display()
            ))
        })
    };
    let g0 = georef(&parts[0])?;
    let mut placed = Vec::with_capacity(parts.len());
    for part in parts {
        let (p, r) = part;
        if r.kind != first.kind || r.channels.len() != first.channels.len() {
            return Err(Error::Input(format!(
                "{} and {} hold different kinds of data (a height field and an image, or different channels)",
                p.display(),
                first_path.display()
            )));
        }
        let g = georef(part)?;
        placed.push((offset((first_path, &g0), (p, &g))?, r));
    }
    let lo = |k: usize| placed.iter().map(|(at, _)| at[k]).min().unwrap_or(0);
    let size = |r: &Raster| [r.width as i64, r.height as i64];
    let hi = |k: usize| {
        placed
            .iter()
            .map(|(at, r)| at[k] + size(r)[k])
            .max()
            .unwrap_or(0)
    };
    let (x0, y0) = (lo(0), lo(1));
    let (w, h) = ((hi(0) - x0) as usize, (hi(1) - y0) as usize);
    if w > MAX_SIDE || h > MAX_SIDE {
        return Err(Error::Input(format!(
            "the mosaic of these inputs is {w}x{h}, larger than the {MAX_SIDE} samples a side this version encodes (are they of one area?)"
        )));
    }
    let mut channels = vec![vec![f32::NAN; w * h]; first.channels.len()];
    let mut valid = vec![false; w * h];
    for (at, r) in &placed {
        let (ox, oy) = ((at[0] - x0) as usize, (at[1] - y0) as usize);
        for y in 0..r.height {
            for x in 0..r.width {
                let (i, k) = (y * r.width + x, (oy + y) * w + ox + x);
                // The first input with data here keeps the cell.
                if valid[k] || !r.is_valid(i) {
                    continue;
                }
                valid[k] = true;
                for (out, ch) in channels.iter_mut().zip(&r.channels) {
                    out[k] = ch[i];
                }
            }
        }
    }
    let same = |f: &dyn Fn(&Raster) -> bool| parts.iter().all(|(_, r)| f(r));
    let sample = if same(&|r| r.sample == first.sample) {
        first.sample
    } else {
        SampleFormat::F32
    };
    let mosaic = Raster {
        width: w,
        height: h,
        channels,
        valid: (!valid.iter().all(|&v| v)).then_some(valid),
        kind: first.kind,
        sample,
        units: if same(&|r| r.units == first.units) {
            first.units.clone()
        } else {
            None
        },
        nodata: first.nodata,
        georef: Some(Georef {
            epsg: g0.epsg,
            origin: [
                g0.origin[0] + x0 as f64 * g0.pixel_size[0],
                g0.origin[1] + y0 as f64 * g0.pixel_size[1],
            ],
            pixel_size: g0.pixel_size,
        }),
    };
    Ok(mosaic)
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
