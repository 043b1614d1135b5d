//! `fractile.encode` and `fractile.encode_file`: NumPy arrays and raster files into asset
//! files, with the command line's defaults: no codec named, a height field is coded by the
//! projected IFS under a bounded rate of 0.8 bits a cell (every cell within the bound it
//! answers) and an image by the same codec under a rate of 0.75 bits a pixel; over twice the chunk size (1024) on a side,
//! in chunks sharing one rate. The policy is `fractile encode`'s (cli/src/encoding/args.rs)
//! for the few keywords Python takes; the codec's calls are the same ones.

use std::path::PathBuf;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use fractile_codec::encode::{Options, Plan, Written};
use fractile_codec::raster::MAX_MAGNITUDE;
use fractile_codec::rows::{InMemory, Rows};
use fractile_codec::{CodecSettings, Raster};
use fractile_proto::{AssetKind, Georef, SampleFormat};
use numpy::{PyReadonlyArray2, PyReadonlyArray3};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::{SettingsError, raise};

/// What the keywords ask, checked.
struct Request {
    kind: AssetKind,
    codec: String,
    target_bpp: Option<f64>,
    max_error: Option<f64>,
    chunk: Option<u32>,
}

impl Request {
    fn new(
        kind: AssetKind,
        codec: Option<&str>,
        target_bpp: Option<f64>,
        max_error: Option<f64>,
        chunk: Option<u32>,
    ) -> PyResult<Request> {
        // The default, as `fractile encode`'s: the projected codec. Any codec of the
        // registry by its name.
        let codec = codec.unwrap_or(fractile_codec::codecs::projected::CODEC_NAME);
        if target_bpp.is_some() && max_error.is_some() {
            return Err(SettingsError::new_err(
                "settings: give target_bpp or max_error, not both",
            ));
        }
        if target_bpp.is_some_and(|v| !(v.is_finite() && v > 0.0)) {
            return Err(PyValueError::new_err(
                "target_bpp must be a positive number",
            ));
        }
        // 0 is lossless, for integer samples (the codec says so of continuous ones), as
        // `fractile encode --max-error 0`.
        if max_error.is_some_and(|v| !(v.is_finite() && v >= 0.0)) {
            return Err(PyValueError::new_err("max_error must be a number >= 0"));
        }
        let req = Request {
            kind,
            codec: codec.to_string(),
            target_bpp,
            max_error,
            chunk,
        };
        // An unknown name, or a keyword the codec does not read, is refused before any work.
        CodecSettings::named(&req.codec, &req.options(), kind).map_err(raise)?;
        Ok(req)
    }

    /// The codec's options (`None`: the codec's default rate); a codec reading `bounded`
    /// codes a height field's rate bounded (every cell within the bound it reports), as the
    /// height-field default does; an image's rate buys the best PSNR, as `fractile encode`'s.
    fn options(&self) -> Options {
        let takes = CodecSettings::takes(&self.codec).unwrap_or_default();
        Options {
            target_bpp: self.target_bpp,
            max_error: self.max_error,
            bounded: self.kind == AssetKind::HeightField
                && self.max_error.is_none()
                && takes.contains(&"bounded"),
            ..Options::default()
        }
    }
}

/// Calls `progress(done, total)` on the Python callable at most every 0.2 s (and at the
/// end), from whichever thread the encoder reports on; its first exception is kept and
/// raised when the encode is over.
struct Progress {
    callback: Option<Py<PyAny>>,
    last: Mutex<Option<Instant>>,
    failed: Mutex<Option<PyErr>>,
}

impl Progress {
    fn new(callback: Option<Py<PyAny>>) -> Progress {
        Progress {
            callback,
            last: Mutex::new(None),
            failed: Mutex::new(None),
        }
    }

    fn report(&self, done: u64, total: u64) {
        let Some(cb) = &self.callback else { return };
        {
            let mut last = self.last.lock().unwrap_or_else(|e| e.into_inner());
            let due = last.is_none_or(|t| t.elapsed() >= Duration::from_millis(200));
            if !due && done < total {
                return;
            }
            *last = Some(Instant::now());
        }
        Python::attach(|py| {
            if let Err(e) = cb.call1(py, (done, total)) {
                let mut failed = self.failed.lock().unwrap_or_else(|e| e.into_inner());
                failed.get_or_insert(e);
            }
        });
    }

    fn finish(self) -> PyResult<()> {
        match self.failed.into_inner().unwrap_or_else(|e| e.into_inner()) {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}

/// Codes `rows` into `path` as `req` asks: whole, or in chunks where the raster is over twice
/// a chunk on a side (or `chunk` says so).
fn code(
    rows: &mut dyn Rows,
    req: &Request,
    path: &std::path::Path,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> PyResult<Written> {
    let chunk = match req.chunk {
        Some(c) if c != 0 && c < 64 => {
            return Err(PyValueError::new_err(
                "chunk must be 0 (whole) or at least 64",
            ));
        }
        other => other,
    };
    // The plan of `fractile encode`: whole, or in chunks sharing one quality where the codec
    // offers one (the max error asked for, or the one that fits the file's rate), each at its
    // share of the rate otherwise.
    let plan = Plan::new(&req.codec, &req.options(), chunk, rows.header()).map_err(raise)?;
    if plan.chunk().is_none() {
        let raster = rows.read_all().map_err(raise)?;
        let enc = fractile_codec::encode(&raster, plan.settings(), progress).map_err(raise)?;
        return enc.write(path).map_err(raise);
    }
    plan.encode_chunks(rows, path, progress).map_err(raise)
}

/// What an encode reports, as a dict.
fn report<'py>(py: Python<'py>, w: &Written) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("codec", w.asset.codec_name())?;
    d.set_item("bytes", w.length)?;
    d.set_item("source_bytes", w.asset.meta.source_bytes())?;
    d.set_item("ratio", w.ratio())?;
    d.set_item("bpp", w.bpp())?;
    d.set_item("psnr", w.errors.psnr)?;
    d.set_item("rmse", w.errors.rmse)?;
    d.set_item("max_error", w.errors.max_error)?;
    d.set_item("seconds", w.seconds)?;
    d.set_item("chunked", w.asset.chunked().is_some())?;
    Ok(d)
}

/// Encodes a NumPy array into the asset file `path` and returns what the encoder measured
/// (bytes, ratio, PSNR, RMSE, max error). See `fractile.pyi` for the keywords.
#[pyfunction]
#[pyo3(signature = (array, path, *, transform = None, crs = None, nodata = None,
    target_bpp = None, max_error = None, codec = None, chunk = None, progress = None))]
#[expect(clippy::too_many_arguments, reason = "Python's keywords")]
pub(crate) fn encode<'py>(
    py: Python<'py>,
    array: &Bound<'py, PyAny>,
    path: PathBuf,
    transform: Option<&Bound<'py, PyAny>>,
    crs: Option<&Bound<'py, PyAny>>,
    nodata: Option<f64>,
    target_bpp: Option<f64>,
    max_error: Option<f64>,
    codec: Option<&str>,
    chunk: Option<u32>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let mut raster = raster_of(array, nodata)?;
    raster.georef = georef(transform, crs)?;
    let req = Request::new(raster.kind, codec, target_bpp, max_error, chunk)?;
    let progress = Progress::new(progress);
    let written = py.detach(|| {
        let mut rows = InMemory::owned(raster);
        code(&mut rows, &req, &path, &|d, t| progress.report(d, t))
    })?;
    progress.finish()?;
    report(py, &written)
}

/// Encodes a raster file (GeoTIFF, 16-bit PNG, PNG or JPEG) of any size into the asset file
/// `path`, read a band of rows at a time when it is coded in chunks; its georeference and
/// nodata are the file's.
#[pyfunction]
#[pyo3(signature = (source, path, *, target_bpp = None, max_error = None, codec = None,
    chunk = None, progress = None))]
#[expect(clippy::too_many_arguments, reason = "Python's keywords")]
pub(crate) fn encode_file<'py>(
    py: Python<'py>,
    source: PathBuf,
    path: PathBuf,
    target_bpp: Option<f64>,
    max_error: Option<f64>,
    codec: Option<&str>,
    chunk: Option<u32>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let mut rows = py
        .detach(|| fractile_codec::mosaic::open_rows(std::slice::from_ref(&source)))
        .map_err(raise)?;
    let req = Request::new(rows.header().kind, codec, target_bpp, max_error, chunk)?;
    let progress = Progress::new(progress);
    let written = py.detach(|| code(rows.as_mut(), &req, &path, &|d, t| progress.report(d, t)))?;
    progress.finish()?;
    report(py, &written)
}

/// The raster of a 2-D array (a height field: int16, uint16, float32 or float64; uint8: a
/// grey image) or of a `(rows, cols, 3)` uint8 array (a colour image). NaN and `nodata`
/// cells are nodata.
fn raster_of(array: &Bound<'_, PyAny>, nodata: Option<f64>) -> PyResult<Raster> {
    fn plane<T: numpy::Element + Copy>(
        a: &Bound<'_, PyAny>,
        f: impl Fn(T) -> f32,
    ) -> Option<(usize, usize, Vec<f32>)> {
        let a = a.extract::<PyReadonlyArray2<'_, T>>().ok()?;
        let view = a.as_array();
        let (h, w) = view.dim();
        Some((w, h, view.iter().map(|&v| f(v)).collect()))
    }
    let height_field = plane::<i16>(array, f32::from)
        .map(|p| (p, SampleFormat::I16))
        .or_else(|| plane::<u16>(array, f32::from).map(|p| (p, SampleFormat::U16)))
        .or_else(|| plane::<f32>(array, |v| v).map(|p| (p, SampleFormat::F32)))
        .or_else(|| {
            // float64 is coded as float32: a value beyond float32 would become infinity, and
            // so nodata, silently; it is refused with the codec's own message instead.
            plane::<f64>(array, |v| {
                if v.is_finite() && v.abs() > MAX_MAGNITUDE {
                    f32::copysign(f32::MAX, v as f32)
                } else {
                    v as f32
                }
            })
            .map(|p| (p, SampleFormat::F32))
        });
    let (kind, sample, width, height, channels) = if let Some(((w, h, v), s)) = height_field {
        (AssetKind::HeightField, s, w, h, vec![v])
    } else if let Some((w, h, v)) = plane::<u8>(array, f32::from) {
        (AssetKind::Image, SampleFormat::U8, w, h, vec![v])
    } else if let Ok(a) = array.extract::<PyReadonlyArray3<'_, u8>>() {
        let view = a.as_array();
        let (h, w, n) = view.dim();
        if n != 3 {
            return Err(PyValueError::new_err(format!(
                "a colour image is (rows, cols, 3) uint8; this one has {n} channels"
            )));
        }
        let channels = (0..3)
            .map(|c| {
                view.index_axis(numpy::ndarray::Axis(2), c)
                    .iter()
                    .map(|&v| f32::from(v))
                    .collect()
            })
            .collect();
        (AssetKind::Image, SampleFormat::U8, w, h, channels)
    } else {
        return Err(PyTypeError::new_err(
            "encode() takes a 2-D int16, uint16, float32 or float64 array (a height field), a 2-D uint8 array (grey) or a (rows, cols, 3) uint8 array (colour)",
        ));
    };
    if channels.len() > 1 && nodata.is_some() {
        return Err(PyValueError::new_err(
            "nodata is for height fields and grey images; colour images have no nodata",
        ));
    }
    // Units stay unknown: an array does not say (a GeoTIFF's reader does not guess either).
    Raster::from_channels(width, height, channels, kind, sample, nodata).map_err(raise)
}

/// The georeference of rasterio's `transform` (an `affine.Affine` or its first six numbers
/// `a, b, c, d, e, f`, north-up: `b = d = 0`) and `crs` (an EPSG code, `"EPSG:4326"`, or a
/// rasterio `CRS`).
fn georef(
    transform: Option<&Bound<'_, PyAny>>,
    crs: Option<&Bound<'_, PyAny>>,
) -> PyResult<Option<Georef>> {
    let Some(t) = transform else {
        if crs.is_some() {
            return Err(PyValueError::new_err("crs needs a transform too"));
        }
        return Ok(None);
    };
    let numbers: Vec<f64> = t
        .try_iter()?
        .map(|v| v?.extract::<f64>())
        .collect::<PyResult<_>>()
        .map_err(|_| PyTypeError::new_err("transform: an affine.Affine or (a, b, c, d, e, f)"))?;
    let [a, b, c, d, e, f] = match numbers.as_slice() {
        [a, b, c, d, e, f] | [a, b, c, d, e, f, ..] => [*a, *b, *c, *d, *e, *f],
        _ => {
            return Err(PyTypeError::new_err(
                "transform: an affine.Affine or (a, b, c, d, e, f)",
            ));
        }
    };
    if b != 0.0 || d != 0.0 || !(a > 0.0 && e < 0.0) {
        return Err(PyValueError::new_err(
            "transform: only north-up grids (b = d = 0, a > 0, e < 0) are encoded",
        ));
    }
    let epsg = match crs {
        None => None,
        Some(c) => Some(epsg_of(c)?),
    };
    Ok(Some(Georef {
        epsg,
        origin: [c, f],
        pixel_size: [a, e],
    }))
}

fn epsg_of(crs: &Bound<'_, PyAny>) -> PyResult<u32> {
    if let Ok(code) = crs.extract::<u32>() {
        return Ok(code);
    }
    if crs.hasattr("to_epsg")? {
        if let Some(code) = crs.call_method0("to_epsg")?.extract::<Option<u32>>()? {
            return Ok(code);
        }
        return Err(PyValueError::new_err("crs: this CRS has no EPSG code"));
    }
    let text: String = crs
        .extract()
        .map_err(|_| PyTypeError::new_err("crs: an EPSG code, \"EPSG:n\" or a rasterio CRS"))?;
    text.trim()
        .to_ascii_uppercase()
        .strip_prefix("EPSG:")
        .and_then(|n| n.parse().ok())
        .ok_or_else(|| PyValueError::new_err(format!("crs {text:?}: expected \"EPSG:n\"")))
}
