//! hexcal-py: hexcal from Python (the `hexcal` package; README.md, "Python").
//!
//! Takes what the command line takes — `calibration.json`, correspondences, images, decoded
//! stacks — as Python objects and numpy arrays; gives calibrations whose devices project,
//! unproject and triangulate ([`calibration`], [`triangulate`]), circles and labelled lattice
//! points ([`vision::detect`]), decoded projector maps ([`vision::decode`]) and new
//! calibrations ([`calibrate`]). Every refusal is a `hexcal.Error` (a `ValueError`) with the
//! command line's one-line message; a panic becomes one too ([`error::guard`]).
//!
//! Depends on `hexcal-core`, `hexcal-vision` and `hexcal-calib` only: no driver, no server.
#![warn(missing_docs)]

pub mod arrays;
pub mod calibrate;
pub mod calibration;
pub mod error;
pub mod triangulate;
pub mod vision;

use pyo3::prelude::*;

/// The extension module `hexcal._hexcal`, re-exported by the `hexcal` package.
#[pymodule]
fn _hexcal(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("Error", m.py().get_type::<error::Error>())?;
    m.add_class::<calibration::Device>()?;
    m.add_class::<calibration::Calibration>()?;
    m.add_function(wrap_pyfunction!(calibration::load, m)?)?;
    m.add_function(wrap_pyfunction!(triangulate::triangulate, m)?)?;
    m.add_function(wrap_pyfunction!(triangulate::verify, m)?)?;
    m.add_function(wrap_pyfunction!(vision::detect, m)?)?;
    m.add_function(wrap_pyfunction!(vision::decode, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate::calibrate, m)?)?;
    Ok(())
}
