//! Calibration from correspondences (`hexcal calibrate CORRESPONDENCES.json`): the same
//! parser, checks, registration and bundle adjustment, giving a [`Calibration`] instead of
//! files.

use crate::arrays::correspondences;
use crate::calibration::Calibration;
use crate::error::{error, guard};
use hexcal_calib::calib::geometric::{calibrate_registering, GeometricParams};
use hexcal_calib::calib::solve::CalibrateOptions;
use hexcal_calib::report::CalibrationFile;
use hexcal_core::board::Board;
use pyo3::prelude::*;

/// Calibrates every device from correspondences — a dict of the correspondences file's
/// layout (README, "A correspondences file") or the path of such a file — as
/// `hexcal calibrate CORRESPONDENCES.json` does: unanchored views registered, Zhang per
/// device, pose graph, one bundle adjustment, distortion terms the data cannot determine
/// fixed. `reference` names the gauge device (default: the first), `fix_k3` and
/// `refine_flatness` as the command's flags. Devices left out are in the result's
/// `excluded`; writes no file (`Calibration.save` writes `calibration.json`).
#[pyfunction]
#[pyo3(signature = (correspondences, reference = None, fix_k3 = false, refine_flatness = false))]
pub fn calibrate(
    py: Python<'_>,
    correspondences: &Bound<'_, PyAny>,
    reference: Option<&str>,
    fix_k3: bool,
    refine_flatness: bool,
) -> PyResult<Calibration> {
    guard(|| {
        let (c, origin) = self::correspondences(correspondences)?;
        let board =
            Board::resolve_in(&c.board, std::path::Path::new(&origin), "board").map_err(error)?;
        let mut options = CalibrateOptions::default();
        options.bundle.fix_k3 = fix_k3;
        options.bundle.refine_flatness = refine_flatness;
        if let Some(name) = reference {
            options.bundle.reference = c
                .devices
                .iter()
                .position(|d| d.name == name)
                .ok_or_else(|| error(format!("{origin}: no device named {name:?}")))?;
        }
        let cal = py
            .detach(|| {
                calibrate_registering(
                    &board,
                    &c.devices,
                    c.poses,
                    &c.views,
                    &options,
                    &GeometricParams::default(),
                )
            })
            .map_err(|e| error(format!("calibration: {e}")))?;
        let excluded = cal
            .excluded
            .iter()
            .map(|e| (e.name.clone(), e.reason.clone()))
            .collect();
        Calibration::new(py, CalibrationFile::new(&cal), excluded)
    })
}
