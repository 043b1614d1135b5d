//! `fractile.open` and `Asset`: an asset file, object or URL read into NumPy arrays: windows
//! at any resolution (`read`), values at points (`points`), and its georeference in
//! rasterio's terms (`meta`, `profile`).

use std::path::PathBuf;
use std::sync::Arc;

use fractile_codec::chunked::ChunkCache;
use fractile_codec::extract::{Points, Resources};
use fractile_codec::geo::Placement;
use fractile_codec::{AssetLimits, Method};
use fractile_proto::{AssetKind, AssetMeta};
use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{IntoPyArray, PyArrayDyn, PyReadonlyArray1};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::{InputError, raise};

/// What the server answers points with when a request names neither steps nor a tolerance
/// (its default `max_iterations`), so that `Asset.points` gives the server's heights.
const SERVER_ITERATIONS: u32 = 64;

/// An opened asset. Chunked assets are read by range: opening reads the header and the
/// chunk table; each `read` or `points` reads (and keeps decoded, in the process's chunk
/// cache of 512 MiB) the chunks it touches.
#[pyclass(module = "fractile", frozen)]
pub(crate) struct Asset {
    asset: Arc<fractile_codec::Asset>,
    placement: Option<Placement>,
    location: String,
}

/// Opens the asset at `location`: a path, `s3://bucket/key` (credentials and endpoint from
/// the AWS variables, as the server's) or `http(s)://` (any server that answers range
/// requests, such as `fractile serve`'s `/v1/assets/{id}/file`).
#[pyfunction]
pub(crate) fn open(py: Python<'_>, location: &Bound<'_, PyAny>) -> PyResult<Asset> {
    let remote = location
        .extract::<String>()
        .ok()
        .filter(|s| fractile_remote::is_remote(s));
    let (described, path) = match remote {
        Some(url) => (url, None),
        None => {
            let path: PathBuf = location.extract().map_err(|_| {
                PyTypeError::new_err("open() takes a path, an s3:// URL or an http(s):// URL")
            })?;
            (path.display().to_string(), Some(path))
        }
    };
    let opened = py.detach(|| {
        let limits = AssetLimits::default();
        let cache = ChunkCache::shared();
        match &path {
            Some(p) => fractile_codec::Asset::open(p, &limits, cache),
            None => {
                // A missing object is the caller's to fix, as a missing file is; anything
                // else (a store down, a timeout) may succeed later.
                let source = fractile_remote::open(&described).map_err(|e| {
                    if e.kind() == std::io::ErrorKind::NotFound {
                        fractile_codec::Error::input(e.to_string()).caused_by(e)
                    } else {
                        fractile_codec::Error::unavailable(e.to_string()).caused_by(e)
                    }
                })?;
                fractile_codec::Asset::from_source(source, &limits, cache)
            }
        }
    });
    let asset = opened.map_err(raise)?;
    let placement = asset
        .meta
        .georef
        .as_ref()
        .and_then(|g| Placement::of(g, asset.meta.width, asset.meta.height).ok());
    Ok(Asset {
        asset: Arc::new(asset),
        placement,
        location: described,
    })
}

#[pymethods]
impl Asset {
    /// Size, kind, value range, georeference and the encoder's error figures, as a dict.
    #[getter]
    fn meta<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let m = &self.asset.meta;
        let d = PyDict::new(py);
        d.set_item("width", m.width)?;
        d.set_item("height", m.height)?;
        d.set_item("channels", m.channels)?;
        d.set_item("kind", kind_name(m.kind))?;
        d.set_item("codec", self.asset.codec_name())?;
        d.set_item("chunked", self.asset.chunked().is_some())?;
        d.set_item("units", m.units.clone())?;
        d.set_item("value_range", (m.value_min, m.value_max))?;
        d.set_item("nodata", m.nodata)?;
        d.set_item("crs", crs(m))?;
        d.set_item("transform", transform(m))?;
        d.set_item("bounds", bounds(m))?;
        d.set_item("lonlat_bounds", self.placement.as_ref().map(|p| p.bounds()))?;
        let errors = PyDict::new(py);
        errors.set_item("rmse", m.stats.rmse)?;
        errors.set_item("psnr", m.stats.psnr)?;
        errors.set_item("max_error", m.stats.max_error)?;
        errors.set_item("max_contrast", self.asset.max_contrast())?;
        errors.set_item("seed_bound", self.asset.bound_after(0))?;
        d.set_item("errors", errors)?;
        d.set_item("encoder", m.encoder.clone())?;
        d.set_item("location", self.location.clone())?;
        Ok(d)
    }

    /// Keywords for `rasterio.open(path, "w", **asset.profile)`: a float32 GeoTIFF of the
    /// asset's size, channels, CRS and transform (an `affine.Affine` where the package is
    /// installed, as it is with rasterio), NaN as nodata where the source had nodata.
    #[getter]
    fn profile<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let m = &self.asset.meta;
        let d = PyDict::new(py);
        d.set_item("driver", "GTiff")?;
        d.set_item("dtype", "float32")?;
        d.set_item("width", m.width)?;
        d.set_item("height", m.height)?;
        d.set_item("count", m.channels)?;
        d.set_item("crs", crs(m))?;
        let t = match transform(m) {
            Some(t) => match py.import("affine") {
                Ok(affine) => Some(affine.getattr("Affine")?.call1(t)?),
                Err(_) => Some(t.into_pyobject(py)?.into_any()),
            },
            None => None,
        };
        d.set_item("transform", t)?;
        let nodata = (m.nodata.is_some() || self.asset.mask().is_some()).then_some(f64::NAN);
        d.set_item("nodata", nodata)?;
        Ok(d)
    }

    /// The asset as a float32 array: `window` (rasterio's `Window`, or `(col_off, row_off,
    /// width, height)` in source cells, fractions allowed; default all of it) sampled at
    /// `out_shape` (`(rows, cols)`; default the window's size in cells; any size, finer than
    /// the source too), NaN where the source had no data. One channel gives `(rows, cols)`,
    /// colour `(rows, cols, 3)`. `iterations`: exactly this many (default: until converged).
    /// `method`: `"auto"`, `"discrete"` or `"continuous"`. The same decode as `fractile
    /// decode` on the CPU, the GIL released.
    #[pyo3(signature = (window = None, out_shape = None, iterations = None, method = "auto"))]
    fn read<'py>(
        &self,
        py: Python<'py>,
        window: Option<&Bound<'py, PyAny>>,
        out_shape: Option<Vec<usize>>,
        iterations: Option<u32>,
        method: &str,
    ) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let m = &self.asset.meta;
        if matches!(m.kind, AssetKind::Volume | AssetKind::Curve) {
            return Err(InputError::new_err(format!(
                "{} is a {}: read() is for images and height fields",
                self.location,
                kind_name(m.kind)
            )));
        }
        let method = match method {
            "auto" => Method::Auto,
            "discrete" => Method::Discrete,
            "continuous" => Method::Continuous,
            other => {
                return Err(PyValueError::new_err(format!(
                    "method {other:?}: expected \"auto\", \"discrete\" or \"continuous\""
                )));
            }
        };
        let (sw, sh) = (m.width as f64, m.height as f64);
        let cells = match window {
            Some(w) => Some(window_cells(w)?),
            None => None,
        };
        let [c0, r0, cw, rh] = cells.unwrap_or([0.0, 0.0, sw, sh]);
        let inside = c0 >= 0.0 && r0 >= 0.0 && c0 + cw <= sw + 1e-9 && r0 + rh <= sh + 1e-9;
        if !(cw > 0.0 && rh > 0.0 && inside) {
            return Err(PyValueError::new_err(format!(
                "window {:?} must have a positive size and lie inside the {}x{} cells",
                [c0, r0, cw, rh],
                m.width,
                m.height
            )));
        }
        let (height, width) = match out_shape.as_deref() {
            Some([.., rows, cols]) => (*rows, *cols),
            Some(_) => {
                return Err(PyValueError::new_err(
                    "out_shape is (rows, cols) or (bands, rows, cols)",
                ));
            }
            None => ((rh.round() as usize).max(1), (cw.round() as usize).max(1)),
        };
        if width == 0 || height == 0 {
            return Err(PyValueError::new_err(format!(
                "out_shape {height}x{width} must be at least 1x1"
            )));
        }
        if iterations == Some(0) {
            return Err(PyValueError::new_err("iterations must be at least 1"));
        }
        // The size's rule is the codec's, the CLI's too: checked before anything is made. An
        // argument out of range is Python's ValueError.
        self.asset
            .check_read(width, height, &AssetLimits::default())
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let rect = cells.map(|[c0, r0, cw, rh]| {
            [
                (c0 / sw) as f32,
                (r0 / sh) as f32,
                ((c0 + cw) / sw).min(1.0) as f32,
                ((r0 + rh) / sh).min(1.0) as f32,
            ]
        });
        let asset = &self.asset;
        let (mut decoded, _) = py
            .detach(|| asset.raster(rect, width, height, iterations, method))
            .map_err(raise)?;
        let values = if decoded.channels.len() == 1 {
            let plane = decoded.channels.swap_remove(0);
            Array2::from_shape_vec((height, width), plane)
                .map_err(|e| PyValueError::new_err(e.to_string()))?
                .into_dyn()
        } else {
            let n = decoded.channels.len();
            let planes = &decoded.channels;
            Array3::from_shape_fn((height, width, n), |(y, x, c)| planes[c][y * width + x])
                .into_dyn()
        };
        Ok(values.into_pyarray(py))
    }

    /// Values and error bounds at points: `(lon, lat)` for georeferenced assets (any CRS:
    /// the asset's grid is reprojected to), unit coordinates `(x, y)` in [0, 1] otherwise;
    /// scalars or arrays. Returns `(values, bounds)`: values of shape `(n,)` (`(n, 3)` for
    /// colour), NaN outside the asset or on nodata; each bound in value units, on |value -
    /// source| where the asset carries its error map (the default DEM codec does), on the
    /// distance to the fractal's attractor otherwise. The server's answer: 64 steps at most,
    /// each point stopping at the asset's default tolerance, unless `iterations` asks exactly
    /// that many.
    #[pyo3(signature = (lon, lat, iterations = None))]
    fn points<'py>(
        &self,
        py: Python<'py>,
        lon: &Bound<'py, PyAny>,
        lat: &Bound<'py, PyAny>,
        iterations: Option<u32>,
    ) -> PyResult<Sampled<'py>> {
        let m = &self.asset.meta;
        if matches!(m.kind, AssetKind::Volume | AssetKind::Curve) {
            return Err(InputError::new_err(format!(
                "{} is a {}: points() is for images and height fields",
                self.location,
                kind_name(m.kind)
            )));
        }
        let (xs, ys) = (coordinates(lon)?, coordinates(lat)?);
        if xs.len() != ys.len() {
            return Err(PyValueError::new_err(format!(
                "{} longitudes for {} latitudes",
                xs.len(),
                ys.len()
            )));
        }
        if iterations == Some(0) {
            return Err(PyValueError::new_err("iterations must be at least 1"));
        }
        let units: Vec<Option<[f32; 2]>> = xs
            .iter()
            .zip(&ys)
            .map(|(&x, &y)| match &self.placement {
                Some(p) => p.unit(x, y),
                None => ((0.0..=1.0).contains(&x) && (0.0..=1.0).contains(&y))
                    .then_some([x as f32, y as f32]),
            })
            .collect();
        let asset = &self.asset;
        let samples = py
            .detach(|| {
                let (n, tolerance) = match iterations {
                    Some(n) => (n, 0.0),
                    None => (SERVER_ITERATIONS, asset.default_tolerance()),
                };
                let inside: Vec<[f32; 2]> = units.iter().map(|u| u.unwrap_or([0.0; 2])).collect();
                let question = Points {
                    points: &inside,
                    iterations: n,
                    tolerance: Some(tolerance),
                };
                asset.answer(&question, &Resources::CPU)
            })
            .map_err(|e| raise(e.into_error()))?;
        let channels = usize::from(m.channels).max(1);
        let mut values = Vec::with_capacity(samples.len() * channels);
        let mut bounds = Vec::with_capacity(samples.len());
        for (s, u) in samples.iter().zip(&units) {
            if u.is_some() {
                values.extend(s.values.iter().copied());
                bounds.push(s.error_bound + s.source_error.unwrap_or(0.0));
            } else {
                values.extend(std::iter::repeat_n(f32::NAN, channels));
                bounds.push(f32::NAN);
            }
        }
        sampled(py, values, bounds, channels)
    }

    fn __repr__(&self) -> String {
        let m = &self.asset.meta;
        format!(
            "<fractile.Asset {} {}x{} {} ({}{})>",
            self.location,
            m.width,
            m.height,
            kind_name(m.kind),
            self.asset.codec_name(),
            if self.asset.chunked().is_some() {
                ", chunked"
            } else {
                ""
            }
        )
    }
}

/// Values at points and their bounds, as Python gets them.
pub(crate) type Sampled<'py> = (Bound<'py, PyArrayDyn<f32>>, Bound<'py, PyArrayDyn<f32>>);

/// `values` (`channels` a point, point after point) and one bound a point as arrays: values
/// `(n,)`, or `(n, channels)` for colour.
pub(crate) fn sampled<'py>(
    py: Python<'py>,
    values: Vec<f32>,
    bounds: Vec<f32>,
    channels: usize,
) -> PyResult<Sampled<'py>> {
    let n = bounds.len();
    let values = if channels == 1 {
        Array1::from_vec(values).into_dyn()
    } else {
        Array2::from_shape_vec((n, channels), values)
            .map_err(|e| PyValueError::new_err(e.to_string()))?
            .into_dyn()
    };
    Ok((
        values.into_pyarray(py),
        Array1::from_vec(bounds).into_dyn().into_pyarray(py),
    ))
}

/// `(col_off, row_off, width, height)` of a window given as rasterio's `Window` (its
/// attributes), `((row_start, row_stop), (col_start, col_stop))` (rasterio's ranges) or a
/// 4-tuple.
fn window_cells(w: &Bound<'_, PyAny>) -> PyResult<[f64; 4]> {
    if w.hasattr("col_off")? {
        return Ok([
            w.getattr("col_off")?.extract()?,
            w.getattr("row_off")?.extract()?,
            w.getattr("width")?.extract()?,
            w.getattr("height")?.extract()?,
        ]);
    }
    if let Ok(((r0, r1), (c0, c1))) = w.extract::<((f64, f64), (f64, f64))>() {
        return Ok([c0, r0, c1 - c0, r1 - r0]);
    }
    if let Ok(t) = w.extract::<[f64; 4]>() {
        return Ok(t);
    }
    Err(PyTypeError::new_err(
        "window: a rasterio Window, (col_off, row_off, width, height) or ((row_start, row_stop), (col_start, col_stop))",
    ))
}

/// Coordinates from a scalar, a sequence or a NumPy array.
fn coordinates(v: &Bound<'_, PyAny>) -> PyResult<Vec<f64>> {
    if let Ok(a) = v.extract::<PyReadonlyArray1<'_, f64>>() {
        return Ok(a.as_array().to_vec());
    }
    if let Ok(x) = v.extract::<f64>() {
        return Ok(vec![x]);
    }
    v.extract::<Vec<f64>>()
        .map_err(|_| PyTypeError::new_err("coordinates: a number, a sequence or a 1-D array"))
}

fn kind_name(kind: AssetKind) -> &'static str {
    match kind {
        AssetKind::Image => "image",
        AssetKind::HeightField => "height-field",
        AssetKind::Volume => "volume",
        AssetKind::Curve => "curve",
    }
}

/// `EPSG:code` of the asset's CRS, as rasterio takes it.
fn crs(m: &AssetMeta) -> Option<String> {
    m.georef
        .as_ref()
        .and_then(|g| g.epsg)
        .map(|c| format!("EPSG:{c}"))
}

/// The affine transform `(a, b, c, d, e, f)` in rasterio's order: x = a col + b row + c,
/// y = d col + e row + f (north-up: b = d = 0, e < 0).
fn transform(m: &AssetMeta) -> Option<(f64, f64, f64, f64, f64, f64)> {
    m.georef.as_ref().map(|g| {
        (
            g.pixel_size[0],
            0.0,
            g.origin[0],
            0.0,
            g.pixel_size[1],
            g.origin[1],
        )
    })
}

/// `(left, bottom, right, top)` in CRS units, as rasterio's `dataset.bounds`.
fn bounds(m: &AssetMeta) -> Option<(f64, f64, f64, f64)> {
    m.georef.as_ref().map(|g| {
        let right = g.origin[0] + g.pixel_size[0] * m.width as f64;
        let bottom = g.origin[1] + g.pixel_size[1] * m.height as f64;
        (g.origin[0], bottom, right, g.origin[1])
    })
}
