//! `hexcal show`: one device's map from a calibration file, as an SVG picture
//! (docs/design.md §8, "Maps"): the projection uncertainty with the region within the
//! user's target outlined, or the lens's displacement field. hexcal's answer to
//! `mrcal-show-projection-uncertainty` and `mrcal-show-distortion-off-pinhole`, which
//! need mrcal's own optimisation inputs that the `.cameramodel` exports cannot hold.
//!
//! Takes a calibration file (or a folder holding one), a device name and what to show;
//! gives the written picture.

use super::AppError;
use crate::report::maps::{distortion_map, distortion_svg, uncertainty_svg, LensWithCovariance};
use crate::report::CalibrationFile;
use std::path::{Path, PathBuf};

/// Which map to show.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Map {
    /// Projection uncertainty (px, 1σ) over the image.
    Uncertainty,
    /// The lens's displacement against a pinhole (px).
    Distortion,
}

impl Map {
    /// Its name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Map::Uncertainty => "uncertainty",
            Map::Distortion => "distortion",
        }
    }
}

/// A map name that is not one.
#[derive(Debug, thiserror::Error)]
#[error("{0:?}: show uncertainty or distortion")]
pub struct UnknownMap(String);

impl std::str::FromStr for Map {
    type Err = UnknownMap;

    fn from_str(s: &str) -> Result<Map, UnknownMap> {
        [Map::Uncertainty, Map::Distortion]
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| UnknownMap(s.to_owned()))
    }
}

/// The calibration file `input` names: the file itself, or `calibration.json` in the folder
/// or in its `calibration` folder (a run's).
fn calibration_path(input: &Path) -> PathBuf {
    if input.is_dir() {
        let own = input.join("calibration.json");
        match own.exists() {
            true => own,
            false => input.join("calibration").join("calibration.json"),
        }
    } else {
        input.to_owned()
    }
}

/// Write `map` of `device` from the calibration `input` to `out` (SVG); `target` is the
/// uncertainty the user needs (px), outlined on the uncertainty map.
pub fn show(
    map: Map,
    input: &Path,
    device: &str,
    out: &Path,
    target: f64,
) -> Result<PathBuf, AppError> {
    if !(target.is_finite() && target > 0.0 && target <= 1e3) {
        return Err(AppError::Input(format!(
            "--target {target}: a projection uncertainty in px, above 0 and at most 1000"
        )));
    }
    let path = calibration_path(input);
    let text = crate::limits::read_text(&path).map_err(AppError::io(&path))?;
    let cal = CalibrationFile::from_json(&text, &path.display().to_string())?;
    let record = cal
        .devices
        .iter()
        .find(|d| d.name == device)
        .ok_or_else(|| {
            let names: Vec<&str> = cal.devices.iter().map(|d| d.name.as_str()).collect();
            AppError::Input(format!(
                "{}: no device {device:?}; it holds {}",
                path.display(),
                names.join(", ")
            ))
        })?;
    let svg = match map {
        Map::Uncertainty => {
            let lens = LensWithCovariance::of_record(record).ok_or_else(|| {
                AppError::Input(format!(
                    "{}: device {device} has no lens covariance (a file of an older hexcal): \
                     calibrate again to map its uncertainty",
                    path.display()
                ))
            })?;
            uncertainty_svg(&lens.uncertainty_map(), device, target)
        }
        Map::Distortion => {
            let (m, vectors) = distortion_map(&record.model());
            distortion_svg(&m, &vectors, device)
        }
    };
    crate::atomic::write(out, svg.as_bytes()).map_err(AppError::io(out))?;
    Ok(out.to_owned())
}
