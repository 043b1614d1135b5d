//! `fractile.Client`: the Rust client's typed calls to a fractile server (`fractile serve`),
//! answers as NumPy arrays and dicts. Each call blocks, with the GIL released, on a small
//! runtime the client keeps.

use std::path::PathBuf;

use fractile_client::{
    PointsEncoding, PointsRequest, RegionFormat, RegionRequest, TileAddress, TileEncoding,
    TileRequest,
};
use numpy::ndarray::{Array2, Array3};
use numpy::{IntoPyArray, PyArrayDyn};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyBytes;

use crate::asset::{Sampled, sampled};
use crate::errors::{FractileError, raise_client};

/// A client of a fractile server.
#[pyclass(module = "fractile", frozen)]
pub(crate) struct Client {
    client: fractile_client::Client,
    runtime: tokio::runtime::Runtime,
}

/// A tile or region as answered: its values and the server's bounds.
#[pyclass(module = "fractile", frozen, get_all)]
pub(crate) struct Answer {
    /// Values: `(rows, cols)` of heights (NaN on nodata), or `(rows, cols, channels)` of
    /// 8-bit intensities for visual tiles.
    values: Py<PyArrayDyn<f32>>,
    /// How far the answer is from the fractal's attractor (`X-Convergence-Bound`).
    convergence_bound: f32,
    /// The bound against the source data (`X-Error-Bound`), `None` for assets without a
    /// source-error map.
    error_bound: Option<f32>,
    /// The body as sent (PNG, float32 or GeoTIFF bytes).
    body: Py<PyBytes>,
}

#[pymethods]
impl Answer {
    fn __repr__(&self) -> String {
        format!(
            "<fractile.Answer convergence_bound={} error_bound={:?}>",
            self.convergence_bound, self.error_bound
        )
    }
}

impl Client {
    fn block<T: Send>(
        &self,
        py: Python<'_>,
        call: impl std::future::Future<Output = Result<T, fractile_client::ClientError>> + Send,
    ) -> PyResult<T> {
        py.detach(|| self.runtime.block_on(call))
            .map_err(|e| raise_client(py, e))
    }
}

/// A JSON-serialisable answer as Python objects (dicts, lists, numbers).
fn to_python<'py>(py: Python<'py>, v: &impl serde::Serialize) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(v).map_err(|e| FractileError::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

fn array<'py>(
    py: Python<'py>,
    values: Vec<f32>,
    (rows, cols, channels): (usize, usize, usize),
) -> PyResult<Py<PyArrayDyn<f32>>> {
    let a = if channels == 1 {
        Array2::from_shape_vec((rows, cols), values).map(|a| a.into_dyn())
    } else {
        Array3::from_shape_vec((rows, cols, channels), values).map(|a| a.into_dyn())
    }
    .map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py).unbind())
}

#[pymethods]
impl Client {
    /// A client of the server at `url` (`http://127.0.0.1:8080`); `token` is sent with
    /// uploads and deletes.
    #[new]
    #[pyo3(signature = (url, token = None))]
    fn new(py: Python<'_>, url: &str, token: Option<String>) -> PyResult<Client> {
        let client = fractile_client::Client::new(url)
            .map_err(|e| raise_client(py, e))?
            .with_token(token);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("fractile-client")
            .enable_all()
            .build()
            .map_err(|e| FractileError::new_err(e.to_string()))?;
        Ok(Client { client, runtime })
    }

    /// The server's base URL.
    #[getter]
    fn url(&self) -> &str {
        self.client.base()
    }

    /// Every asset the server holds: a list of summaries (dicts).
    fn assets<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let got = self.block(py, self.client.assets())?;
        to_python(py, &got)
    }

    /// One asset's summary (size, bounds, value range, codec, error figures).
    fn asset<'py>(&self, py: Python<'py>, id: &str) -> PyResult<Bound<'py, PyAny>> {
        let got = self.block(py, self.client.asset(id))?;
        to_python(py, &got)
    }

    /// Uploads the asset file at `path` as `id`; returns its summary.
    fn upload<'py>(&self, py: Python<'py>, id: &str, path: PathBuf) -> PyResult<Bound<'py, PyAny>> {
        let bytes = std::fs::read(&path)
            .map_err(|e| FractileError::new_err(format!("{}: {e}", path.display())))?;
        let got = self.block(py, self.client.upload(id, bytes))?;
        to_python(py, &got.summary)
    }

    /// Deletes the asset `id`.
    fn delete(&self, py: Python<'_>, id: &str) -> PyResult<()> {
        self.block(py, self.client.delete(id))
    }

    /// Tile `z/x/y` of `id`: `encoding` `"f32"` (heights, the default), `"terrarium"`,
    /// `"terrain-rgb"`, `"gray16"` or `"png"` (visual); `tile_size` 256 or 512;
    /// `iterations` exactly, or `tolerance` (value units) per pixel; neither: the server's
    /// default.
    #[pyo3(signature = (id, z, x, y, *, encoding = "f32", tile_size = 256, iterations = None,
        tolerance = None))]
    #[expect(clippy::too_many_arguments, reason = "Python's keywords")]
    fn tile(
        &self,
        py: Python<'_>,
        id: &str,
        z: u8,
        x: u32,
        y: u32,
        encoding: &str,
        tile_size: u32,
        iterations: Option<u32>,
        tolerance: Option<f32>,
    ) -> PyResult<Answer> {
        let encoding = TileEncoding::parse(encoding).ok_or_else(|| {
            PyValueError::new_err(format!(
                "encoding {encoding:?}: f32, terrarium, terrain-rgb, gray16 or png"
            ))
        })?;
        let req = TileRequest {
            iterations,
            tolerance,
            tile_size,
            ..TileRequest::new(TileAddress { z, x, y }, encoding)
        };
        let t = self.block(py, self.client.tile(id, &req))?;
        let (size, channels) = (t.size as usize, t.channels.max(1) as usize);
        Ok(Answer {
            values: array(py, t.values, (size, size, channels))?,
            convergence_bound: t.convergence_bound,
            error_bound: t.error_bound,
            body: PyBytes::new(py, &t.body).unbind(),
        })
    }

    /// The values of `id` on a `width x height` grid of pixel centres over `bbox`
    /// (`[west, south, east, north]`: lon/lat, or unit coordinates for assets without a
    /// georeference), as float32.
    #[pyo3(signature = (id, bbox, width, height, *, iterations = None, tolerance = None))]
    #[expect(clippy::too_many_arguments, reason = "Python's keywords")]
    fn region(
        &self,
        py: Python<'_>,
        id: &str,
        bbox: [f64; 4],
        width: u32,
        height: u32,
        iterations: Option<u32>,
        tolerance: Option<f32>,
    ) -> PyResult<Answer> {
        let req = RegionRequest {
            bbox,
            width,
            height,
            iterations,
            tolerance,
            format: RegionFormat::F32,
        };
        let r = self.block(py, self.client.region(id, &req))?;
        let planes = r.values.unwrap_or_default();
        let channels = planes.len().max(1);
        let (w, h) = (width as usize, height as usize);
        let values: Vec<f32> = if channels == 1 {
            planes.into_iter().next().unwrap_or_default()
        } else {
            (0..w * h)
                .flat_map(|i| planes.iter().map(move |p| p[i]))
                .collect()
        };
        Ok(Answer {
            values: array(py, values, (h, w, channels))?,
            convergence_bound: r.convergence_bound,
            error_bound: r.error_bound,
            body: PyBytes::new(py, &r.body).unbind(),
        })
    }

    /// Values and bounds at points, as `Asset.points` gives them: `(values, bounds)`, NaN
    /// outside the asset; each bound against the source where the asset has an error map,
    /// against the attractor otherwise. One request (the server's points batch).
    #[pyo3(signature = (id, lon, lat, iterations = None))]
    fn points<'py>(
        &self,
        py: Python<'py>,
        id: &str,
        lon: Vec<f64>,
        lat: Vec<f64>,
        iterations: Option<u32>,
    ) -> PyResult<Sampled<'py>> {
        if lon.len() != lat.len() {
            return Err(PyValueError::new_err(format!(
                "{} longitudes for {} latitudes",
                lon.len(),
                lat.len()
            )));
        }
        let req = PointsRequest {
            points: lon.iter().zip(&lat).map(|(&x, &y)| [x, y]).collect(),
            iterations,
            tolerance: None,
        };
        let got = self.block(py, self.client.points(id, &req, PointsEncoding::Binary))?;
        let channels = got
            .results
            .iter()
            .find_map(|r| r.values.as_ref().map(Vec::len))
            .unwrap_or(1)
            .max(1);
        let mut values = Vec::with_capacity(got.results.len() * channels);
        let mut bounds = Vec::with_capacity(got.results.len());
        for r in &got.results {
            match &r.values {
                Some(v) => values.extend(v.iter().map(|x| x.unwrap_or(f32::NAN))),
                None => values.extend(std::iter::repeat_n(f32::NAN, channels)),
            }
            bounds.push(r.error_bound.or(r.convergence_bound).unwrap_or(f32::NAN));
        }
        sampled(py, values, bounds, channels)
    }

    /// The URL of `id`'s asset file, which `fractile.open` reads by range.
    fn file_url(&self, id: &str) -> String {
        format!("{}/v1/assets/{id}/file", self.client.base())
    }

    fn __repr__(&self) -> String {
        format!("<fractile.Client {}>", self.client.base())
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        // A runtime dropped where another runs (an asyncio loop does not count) would panic;
        // shut it down without waiting.
        let rt = std::mem::replace(
            &mut self.runtime,
            match tokio::runtime::Builder::new_current_thread().build() {
                Ok(rt) => rt,
                Err(_) => return,
            },
        );
        rt.shutdown_background();
    }
}
