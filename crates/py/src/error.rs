//! The package's one exception and the guard that turns panics into it.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

pyo3::create_exception!(
    hexcal,
    Error,
    PyValueError,
    "A refused input or a failed step, with the hexcal command line's one-line message."
);

/// A [`Error`] with `message`.
pub fn error(message: impl std::fmt::Display) -> PyErr {
    Error::new_err(message.to_string())
}

/// Runs `f`; a panic inside becomes an [`Error`] ("internal error: …") instead of ending
/// the interpreter's call with pyo3's `PanicException`.
pub fn guard<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or_else(|payload| {
        let what = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "a panic without message".into());
        Err(error(format!("internal error: {what}")))
    })
}
