//! The codec's kinds of error as Python exceptions: one base, [`FractileError`], and a
//! subclass per kind, so that `except fractile.AssetError` catches a corrupt file and
//! `except fractile.UnavailableError` a store that is down (worth trying again).

use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;

create_exception!(
    fractile,
    FractileError,
    PyException,
    "Every error fractile raises."
);
create_exception!(
    fractile,
    InputError,
    FractileError,
    "The input array or file cannot be encoded (empty, all nodata, a dtype or shape not taken)."
);
create_exception!(
    fractile,
    SettingsError,
    FractileError,
    "The settings are inconsistent (an unknown codec, a rate the codec does not take)."
);
create_exception!(
    fractile,
    AssetError,
    FractileError,
    "An asset is corrupt, truncated, or of an unknown version or codec."
);
create_exception!(
    fractile,
    OutputError,
    FractileError,
    "An output could not be written."
);
create_exception!(
    fractile,
    UnavailableError,
    FractileError,
    "An asset's bytes could not be read now (a store or server down, a file gone): trying again may succeed."
);
create_exception!(
    fractile,
    ClientError,
    FractileError,
    "The fractile server answered with an error or could not be reached; `status` and `code` say which."
);

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("FractileError", py.get_type::<FractileError>())?;
    m.add("InputError", py.get_type::<InputError>())?;
    m.add("SettingsError", py.get_type::<SettingsError>())?;
    m.add("AssetError", py.get_type::<AssetError>())?;
    m.add("OutputError", py.get_type::<OutputError>())?;
    m.add("UnavailableError", py.get_type::<UnavailableError>())?;
    m.add("ClientError", py.get_type::<ClientError>())?;
    Ok(())
}

/// A codec error as the exception of its kind, its message the codec's.
pub(crate) fn raise(e: fractile_codec::Error) -> PyErr {
    use fractile_codec::Error as E;
    let text = e.to_string();
    match e {
        E::Input { .. } => InputError::new_err(text),
        E::Settings { .. } => SettingsError::new_err(text),
        E::Asset { .. } => AssetError::new_err(text),
        E::Output { .. } => OutputError::new_err(text),
        E::Unavailable { .. } => UnavailableError::new_err(text),
        _ => FractileError::new_err(text),
    }
}

/// A client error as [`ClientError`], with the HTTP status and the server's error code as
/// attributes (`None` where the server was not reached).
pub(crate) fn raise_client(py: Python<'_>, e: fractile_client::ClientError) -> PyErr {
    let err = ClientError::new_err(e.to_string());
    let value = err.value(py);
    // Attributes on a fresh exception object cannot fail but for memory.
    let _ = value.setattr("status", e.status());
    let _ = value.setattr("code", e.code().map(str::to_string));
    err
}
