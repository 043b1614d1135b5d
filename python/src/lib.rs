//! `fractile` for Python: assets written from and read into NumPy arrays, with rasterio's
//! georeference. A thin layer over the codec's calls, the same ones `fractile encode` and
//! `fractile decode` make, so that Python answers equal the command line's and the server's.
//! Decoding runs with the GIL released, on the codec's own rayon threads.
//!
//! The module's Python face is written in `fractile.pyi` beside this crate (types and
//! docstrings); `docs/python.md` is its guide.

use pyo3::prelude::*;

mod asset;
mod client;
mod encoding;
mod errors;

/// The module `fractile`.
#[pymodule]
fn fractile(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(encoding::encode, m)?)?;
    m.add_function(wrap_pyfunction!(encoding::encode_file, m)?)?;
    m.add_function(wrap_pyfunction!(asset::open, m)?)?;
    m.add_class::<asset::Asset>()?;
    m.add_class::<client::Client>()?;
    m.add_class::<client::Answer>()?;
    errors::register(m)?;
    Ok(())
}
