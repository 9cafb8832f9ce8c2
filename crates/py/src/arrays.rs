//! numpy arrays in and out: float arrays of a given width read as views (no copy when the
//! caller's array is already float64), results handed over without copying.

use crate::error::error;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;

/// `obj` as an N × `cols` float64 array: a view of it when it is one already, else
/// `numpy.asarray(obj, dtype=float64)`; `what` names it in the error.
pub fn float_rows<'py>(
    obj: &Bound<'py, PyAny>,
    cols: usize,
    what: &str,
) -> PyResult<PyReadonlyArray2<'py, f64>> {
    let array = match obj.extract::<PyReadonlyArray2<'py, f64>>() {
        Ok(a) => a,
        Err(_) => {
            let numpy = obj.py().import("numpy")?;
            let converted = numpy
                .call_method1("asarray", (obj, "float64"))
                .map_err(|e| error(format!("{what}: not an array of numbers: {e}")))?;
            converted
                .extract::<PyReadonlyArray2<'py, f64>>()
                .map_err(|_| {
                    error(format!(
                        "{what}: expected an N×{cols} array, got {} dimension(s)",
                        converted
                            .getattr("ndim")
                            .and_then(|n| n.extract::<usize>())
                            .unwrap_or(0)
                    ))
                })?
        }
    };
    let shape = array.shape();
    if shape[1] != cols {
        return Err(error(format!(
            "{what}: expected an N×{cols} array, got shape ({}, {})",
            shape[0], shape[1]
        )));
    }
    Ok(array)
}

/// Rows of `cols` values as an N × `cols` numpy array (the buffer is handed over).
pub fn rows_array<'py>(py: Python<'py>, rows: Vec<f64>, cols: usize) -> Bound<'py, PyArray2<f64>> {
    let n = rows.len() / cols;
    Array2::from_shape_vec((n, cols), rows)
        .expect("whole rows")
        .into_pyarray(py)
}

/// The JSON text of a file input: a path (str or `os.PathLike`) is read, a dict or list is
/// serialised with Python's `json`; with the name errors give it (the path, else `what`).
pub fn json_input(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<(String, String)> {
    if obj.is_instance_of::<pyo3::types::PyDict>() || obj.is_instance_of::<pyo3::types::PyList>() {
        let json = obj.py().import("json")?;
        let text = json
            .call_method1("dumps", (obj,))
            .map_err(|e| error(format!("{what}: cannot be written as JSON: {e}")))?
            .extract::<String>()?;
        return Ok((text, what.to_string()));
    }
    let path: std::path::PathBuf = obj.extract().map_err(|_| {
        error(format!(
            "{what}: a dict (the file's JSON layout) or the path of a file"
        ))
    })?;
    let text = hexcal_core::limits::read_text(&path)
        .map_err(|e| error(format!("{}: {e}", path.display())))?;
    Ok((text, path.display().to_string()))
}

/// A correspondences file (README: "A correspondences file") as a dict or a path, parsed and
/// checked as `hexcal calibrate` and `hexcal verify` check it.
pub fn correspondences(
    obj: &Bound<'_, PyAny>,
) -> PyResult<(hexcal_core::observations::Correspondences, String)> {
    let (text, origin) = json_input(obj, "correspondences")?;
    let c: hexcal_core::observations::Correspondences = serde_json::from_str(&text)
        .map_err(|e| error(format!("{origin}: not a correspondences file: {e}")))?;
    c.check().map_err(|e| error(e.in_file(origin.clone())))?;
    Ok((c, origin))
}
