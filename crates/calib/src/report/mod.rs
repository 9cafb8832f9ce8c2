//! What a calibration gives its users: hexcal's own calibration file, an OpenCV FileStorage
//! YAML per device, the exports for neighbouring tools ([`export`]: mrcal, COLMAP, ROS,
//! stereo pairs, Kalibr), and the per-device residual table of the paper's Table I
//! (docs/design.md §8).
//!
//! Takes a [`Calibration`]; gives serialisable values and text. Units: millimetres and
//! pixels; poses are `T_device_ref` (a point in the reference device's frame mapped into
//! the device's frame), rotations as Rodrigues vectors (rad).

pub mod export;
pub mod html;
pub mod maps;

use crate::calib::diagnostics::{lens_covariance, valid_region, ResidualRow, VALID_UNCERTAINTY};
use crate::calib::lens_model::TermChoice;
use crate::calib::solve::Calibration;
use hexcal_core::board::Sides;
use hexcal_core::camera::{CameraModel, Distortion, Intrinsics};
use hexcal_core::observations::DeviceKind;
use hexcal_core::{Invalid, ValidationError};
use nalgebra::{Isometry3, Matrix3, Vector3};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Version of [`CalibrationFile`]'s format.
pub const FORMAT_VERSION: u32 = 1;

/// A rigid transform in a file: Rodrigues vector (rad) and translation (mm).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseRecord {
    /// Rotation vector (axis × angle, rad).
    pub rvec: [f64; 3],
    /// Translation (mm).
    pub tvec: [f64; 3],
}

impl PoseRecord {
    /// The record of an isometry.
    pub fn from_isometry(t: &Isometry3<f64>) -> PoseRecord {
        let r = t.rotation.scaled_axis();
        let v = t.translation.vector;
        PoseRecord {
            rvec: [r.x, r.y, r.z],
            tvec: [v.x, v.y, v.z],
        }
    }

    /// The isometry of a record.
    pub fn isometry(&self) -> Isometry3<f64> {
        Isometry3::new(Vector3::from(self.tvec), Vector3::from(self.rvec))
    }
}

/// One calibrated device in a [`CalibrationFile`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeviceRecord {
    /// Device name.
    pub name: String,
    /// Camera or projector.
    pub kind: DeviceKind,
    /// Image (raster) width (px).
    pub width: u32,
    /// Image (raster) height (px).
    pub height: u32,
    /// Pinhole intrinsics (px).
    pub intrinsics: Intrinsics,
    /// OpenCV distortion coefficients.
    pub distortion: Distortion,
    /// T_device_ref.
    pub pose: PoseRecord,
    /// Standard deviations of the lens parameters, in the solver's order of the free
    /// parameters ([`hexcal_core::camera::LensParam`] order).
    pub lens_std: Vec<f64>,
    /// Standard deviations of the pose increment (ω rad, τ mm); zero for the reference.
    pub pose_std: [f64; 6],
    /// Names of the free lens parameters ("fx", …, "k3"), the rows and columns of
    /// `lens_covariance` (empty in files of older builds).
    #[serde(default)]
    pub lens_params: Vec<String>,
    /// Covariance of the free lens parameters (px², docs/design.md (33)), row by row.
    #[serde(default)]
    pub lens_covariance: Vec<Vec<f64>>,
    /// Every distortion term: estimated or fixed, and why (docs/design.md §8, "Lens model";
    /// empty in files of older builds).
    #[serde(default)]
    pub lens_model: Vec<TermRecord>,
}

/// One distortion term of a device in a [`CalibrationFile`]: whether the data determine
/// it, the evidence, and the reason in words.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TermRecord {
    /// The term ("k1", …).
    pub term: String,
    /// Whether it was estimated (otherwise held: at zero when the data could not determine
    /// it).
    pub estimated: bool,
    /// Its estimate: the final value when estimated, the rejected estimate when fixed.
    pub estimate: f64,
    /// Standard deviation of that estimate.
    pub std: f64,
    /// Why, in words.
    pub reason: String,
}

impl TermRecord {
    fn new(t: &TermChoice) -> TermRecord {
        TermRecord {
            term: t.param.name().to_string(),
            estimated: t.estimated,
            estimate: t.estimate,
            std: t.std,
            reason: t.reason(),
        }
    }
}

/// Per device, one line: the distortion terms it estimates, those fixed, and the evidence
/// for each term the data tested.
pub fn format_lens_models(cal: &Calibration) -> String {
    let mut s = String::new();
    for (dev, choice) in cal.devices.iter().zip(&cal.lens) {
        let tested: Vec<String> = choice
            .terms
            .iter()
            .filter(|t| t.tested)
            .map(TermChoice::reason)
            .collect();
        let _ = writeln!(
            s,
            "lens model {}: {}{}",
            dev.name,
            choice.summary(),
            if tested.is_empty() {
                String::new()
            } else {
                format!(" ({})", tested.join("; "))
            }
        );
    }
    s
}

impl DeviceRecord {
    /// The device's lens model.
    pub fn model(&self) -> CameraModel {
        CameraModel {
            width: self.width,
            height: self.height,
            intrinsics: self.intrinsics,
            distortion: self.distortion,
        }
    }
}

/// hexcal's calibration file (JSON): every device's model and pose in one frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationFile {
    /// Format version ([`FORMAT_VERSION`]).
    pub version: u32,
    /// Units of lengths and image coordinates.
    pub units: Units,
    /// Board name.
    pub board: String,
    /// Printed sides of the board: written `1` for a single-sided board, absent (2) else.
    #[serde(default, skip_serializing_if = "Sides::is_two")]
    pub board_sides: Sides,
    /// Refined T_board_back (the back side's frame in the board frame); absent for a
    /// single-sided board, which has no back.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub front_back: Option<PoseRecord>,
    /// Board bend (mm): displacement along the board's z at distance `bend_scale` from the
    /// centre for the bowl (x² + y²), saddle (x² − y²) and saddle (2xy) shapes; zero unless
    /// refined.
    pub bend: [f64; 3],
    /// Standard deviations of `bend` (mm).
    pub bend_std: [f64; 3],
    /// L of the bend shapes (mm).
    pub bend_scale: f64,
    /// Name of the reference device (pose identity).
    pub reference: String,
    /// Calibrated devices.
    pub devices: Vec<DeviceRecord>,
    /// Posterior σ per residual coordinate (px).
    pub sigma: f64,
}

/// The units a file uses.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Units {
    /// Length unit of translations.
    pub length: String,
    /// Unit of image coordinates; pixel (0, 0) is the centre of the top-left pixel.
    pub image: String,
}

/// Why a calibration file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// Not readable or not valid JSON of the format.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// A value of the file is wrong: the file, the value's JSON path and what is wrong.
    #[error(transparent)]
    Invalid(ValidationError),
    /// A file could not be written.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The cause.
        source: std::io::Error,
    },
    /// An export asked for cannot be made.
    #[error(transparent)]
    Export(#[from] export::ExportError),
    /// A version this build does not read.
    #[error("{path}: format version {found}, this hexcal reads version {FORMAT_VERSION}")]
    Version {
        /// The file.
        path: String,
        /// Version found.
        found: u32,
    },
}

impl CalibrationFile {
    /// The file of a calibration.
    pub fn new(cal: &Calibration) -> CalibrationFile {
        let sol = &cal.solution;
        let reference = cal.reference;
        CalibrationFile {
            version: FORMAT_VERSION,
            units: Units {
                length: "mm".into(),
                image: "px".into(),
            },
            board: cal.board.name.clone(),
            board_sides: cal.board.sides,
            front_back: sol.front_back.as_ref().map(PoseRecord::from_isometry),
            bend: sol.bend.coefficients.into(),
            bend_std: sol.bend_std,
            bend_scale: sol.bend.scale,
            reference: cal.devices[reference].name.clone(),
            devices: cal
                .devices
                .iter()
                .enumerate()
                .map(|(i, d)| DeviceRecord {
                    name: d.name.clone(),
                    kind: d.kind,
                    width: d.model.width,
                    height: d.model.height,
                    intrinsics: d.model.intrinsics,
                    distortion: d.model.distortion,
                    pose: PoseRecord::from_isometry(&d.pose),
                    lens_std: sol.intrinsic_std[i].clone(),
                    pose_std: sol.pose_std[i],
                    lens_params: lens_covariance(cal, i)
                        .0
                        .iter()
                        .map(|p| p.name().to_string())
                        .collect(),
                    lens_covariance: {
                        let c = lens_covariance(cal, i).1;
                        c.row_iter().map(|r| r.iter().copied().collect()).collect()
                    },
                    lens_model: cal.lens[i].terms.iter().map(TermRecord::new).collect(),
                })
                .collect(),
            sigma: sol.sigma,
        }
    }

    /// Parse a file's text; errors name `path`.
    pub fn from_json(text: &str, path: &str) -> Result<CalibrationFile, ReportError> {
        #[derive(Deserialize)]
        struct Versioned {
            version: u32,
        }
        let parse = |e: serde_json::Error| ReportError::Parse {
            path: path.into(),
            message: e.to_string(),
        };
        let v: Versioned = serde_json::from_str(text).map_err(parse)?;
        if v.version != FORMAT_VERSION {
            return Err(ReportError::Version {
                path: path.into(),
                found: v.version,
            });
        }
        let file: CalibrationFile = serde_json::from_str(text).map_err(parse)?;
        file.check()
            .map_err(|e| ReportError::Invalid(e.in_file(path)))?;
        Ok(file)
    }

    /// The first problem of a calibration file: the JSON path and what is wrong. Devices within
    /// [`hexcal_core::limits::MAX_DEVICES`] with unique names, models as
    /// [`CameraModel::check`] requires, poses as [`hexcal_core::limits::rigid`] requires,
    /// finite figures, and a reference among them.
    pub fn check(&self) -> Result<(), ValidationError> {
        use hexcal_core::limits;
        limits::count(self.devices.len(), limits::MAX_DEVICES, "devices")
            .map_err(|m| m.at("devices"))?;
        let mut names = std::collections::BTreeMap::new();
        for (i, d) in self.devices.iter().enumerate() {
            let at = |k: &str| format!("devices[{i}].{k}");
            limits::device_name(&d.name).map_err(|m| m.at(at("name")))?;
            if let Some(first) = names.insert(d.name.as_str(), i) {
                return Err(ValidationError::new(
                    at("name"),
                    format!("{:?} is already the name of devices[{first}]", d.name),
                ));
            }
            d.model().check().map_err(|e| e.map_at(at))?;
            limits::rigid(&d.pose.rvec, &d.pose.tvec).map_err(|e| e.within(at("pose")))?;
            limits::count(
                d.lens_std.len(),
                hexcal_core::camera::LENS_PARAM_COUNT,
                "values",
            )
            .map_err(|m| m.at(at("lens_std")))?;
            check_covariance(d).map_err(|e| e.map_at(|k| at(k)))?;
            check_lens_model(d).map_err(|m| m.at(at("lens_model")))?;
        }
        if !self.devices.iter().any(|d| d.name == self.reference) {
            return Err(ValidationError::new(
                "reference",
                format!("{:?} is none of the devices", self.reference),
            ));
        }
        check_front_back(self)?;
        limits::finite(&self.bend).map_err(|m| m.at("bend"))?;
        limits::finite(&[self.bend_scale, self.sigma]).map_err(|m| m.at("sigma"))
    }

    /// Pretty JSON text.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("plain data serialises")
    }
}

/// `front_back` finite for a double-sided board, absent for a single-sided one.
fn check_front_back(f: &CalibrationFile) -> Result<(), ValidationError> {
    match (&f.front_back, f.board_sides) {
        (Some(fb), Sides::Two) => {
            hexcal_core::limits::rigid(&fb.rvec, &fb.tvec).map_err(|e| e.within("front_back"))
        }
        (None, Sides::One) => Ok(()),
        (Some(_), Sides::One) => Err(ValidationError::new(
            "front_back",
            "a single-sided board (board_sides 1) has no back side transform",
        )),
        (None, Sides::Two) => Err(ValidationError::new(
            "front_back",
            "missing: a double-sided board's calibration has the back side transform",
        )),
    }
}

/// The first problem of a record's lens-model terms: at most one per lens parameter, each
/// named as one, with finite figures.
fn check_lens_model(d: &DeviceRecord) -> Result<(), Invalid> {
    hexcal_core::limits::count(
        d.lens_model.len(),
        hexcal_core::camera::LENS_PARAM_COUNT,
        "terms",
    )?;
    for t in &d.lens_model {
        if !hexcal_core::camera::LensParam::ALL
            .iter()
            .any(|p| p.name() == t.term)
        {
            return Err(Invalid(format!("{:?} is no lens parameter", t.term)));
        }
        hexcal_core::limits::finite(&[t.estimate, t.std])?;
    }
    Ok(())
}

/// The first problem of a record's labelled covariance: names of lens parameters, as many
/// as `lens_std` holds (or none), a square finite matrix of that size.
fn check_covariance(d: &DeviceRecord) -> Result<(), ValidationError> {
    let n = d.lens_params.len();
    if n == 0 && d.lens_covariance.is_empty() {
        return Ok(());
    }
    if n != d.lens_std.len() {
        return Err(ValidationError::new(
            "lens_params",
            format!("{n} names for {} standard deviations", d.lens_std.len()),
        ));
    }
    let names: Vec<&str> = hexcal_core::camera::LensParam::ALL
        .iter()
        .map(|p| p.name())
        .collect();
    if let Some(bad) = d.lens_params.iter().find(|p| !names.contains(&p.as_str())) {
        return Err(ValidationError::new(
            "lens_params",
            format!("{bad:?} is no lens parameter"),
        ));
    }
    if d.lens_covariance.len() != n || d.lens_covariance.iter().any(|r| r.len() != n) {
        return Err(ValidationError::new(
            "lens_covariance",
            format!("not a {n} × {n} matrix"),
        ));
    }
    for row in &d.lens_covariance {
        hexcal_core::limits::finite(row).map_err(|m| m.at("lens_covariance"))?;
    }
    Ok(())
}

/// The distortion vector OpenCV uses: 5 coefficients, or 8 with the rational terms.
fn opencv_distortion(d: &Distortion) -> Vec<f64> {
    let mut v = vec![d.k1, d.k2, d.p1, d.p2, d.k3];
    if d.is_rational() {
        v.extend([d.k4, d.k5, d.k6]);
    }
    v
}

fn opencv_matrix(out: &mut String, name: &str, rows: usize, cols: usize, data: &[f64]) {
    let values: Vec<String> = data.iter().map(|x| format!("{x:.17e}")).collect();
    let _ = write!(
        out,
        "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]\n",
        values.join(", ")
    );
}

/// OpenCV FileStorage YAML of one device (readable by `cv2.FileStorage`): `camera_matrix`,
/// `distortion_coefficients`, `image_width`, `image_height`, and `R`, `T` of T_device_ref
/// (X_device = R·X_ref + T, mm).
pub fn opencv_yaml(d: &DeviceRecord) -> String {
    let k = &d.intrinsics;
    let mut s = String::from("%YAML:1.0\n---\n");
    let _ = writeln!(s, "name: \"{}\"", d.name);
    let _ = writeln!(
        s,
        "kind: {}",
        match d.kind {
            DeviceKind::Camera => "camera",
            DeviceKind::Projector => "projector",
        }
    );
    let _ = writeln!(s, "image_width: {}", d.width);
    let _ = writeln!(s, "image_height: {}", d.height);
    opencv_matrix(
        &mut s,
        "camera_matrix",
        3,
        3,
        &[k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
    );
    let dist = opencv_distortion(&d.distortion);
    opencv_matrix(&mut s, "distortion_coefficients", 1, dist.len(), &dist);
    let t = d.pose.isometry();
    let r: Matrix3<f64> = *t.rotation.to_rotation_matrix().matrix();
    let rows: Vec<f64> = (0..3)
        .flat_map(|i| (0..3).map(move |j| r[(i, j)]))
        .collect();
    opencv_matrix(&mut s, "R", 3, 3, &rows);
    opencv_matrix(&mut s, "T", 3, 1, t.translation.vector.as_slice());
    s
}

/// The table as aligned text.
pub fn format_table(rows: &[ResidualRow]) -> String {
    let mut s = format!(
        "{:<12} {:<9} {:>8} {:>8} {:>17} {:>9}\n",
        "device", "kind", "points", "outliers", "mean ± std (px)", "RMS (px)"
    );
    for r in rows {
        let kind = match r.kind {
            DeviceKind::Camera => "camera",
            DeviceKind::Projector => "projector",
        };
        let _ = writeln!(
            s,
            "{:<12} {:<9} {:>8} {:>8} {:>8.4} ± {:<6.4} {:>9.4}",
            r.name, kind, r.points, r.outliers, r.mean, r.std, r.rms
        );
    }
    s
}

/// Write every output of a calibration into `dir`, each file atomically:
/// `calibration.json`, `opencv/NAME.yml`, `mrcal/NAME.cameramodel` and `ros/NAME.yaml` per
/// device, `colmap/{cameras,images,points3D}.txt`, `camchain.yaml` (Kalibr),
/// `stereo/FIRST-SECOND.yml` per pair of `stereo` ("first,second"), and `residuals.txt` and
/// `residuals.json` from `rows` (the calibration's
/// [`Diagnosis`](crate::calib::diagnostics::Diagnosis)). Returns the paths written and, per
/// device, the Kalibr radtan refit's largest deviation (px). Pairs are checked before
/// anything is written.
pub fn write_outputs(
    cal: &Calibration,
    rows: &[ResidualRow],
    dir: &Path,
    stereo: &[String],
) -> Result<Written, ReportError> {
    let io = |path: &Path| {
        let path = path.display().to_string();
        move |source| ReportError::Io { path, source }
    };
    let file = CalibrationFile::new(cal);
    let pairs = stereo
        .iter()
        .map(|p| {
            let name = p.replace(',', "-").replace(' ', "");
            Ok((
                dir.join("stereo").join(format!("{name}.yml")),
                export::stereo_yaml(&file, p)?,
            ))
        })
        .collect::<Result<Vec<_>, export::ExportError>>()?;
    for sub in ["opencv", "mrcal", "ros", "colmap", "stereo"] {
        let d = dir.join(sub);
        if sub != "stereo" || !pairs.is_empty() {
            std::fs::create_dir_all(&d).map_err(io(&d))?;
        }
    }
    let (camchain, fits) = export::kalibr_camchain(&file, &export::overlaps(cal));
    let mut outputs = vec![
        (dir.join("calibration.json"), file.to_json()),
        (dir.join("camchain.yaml"), camchain),
        (dir.join("residuals.txt"), format_table(rows)),
        (
            dir.join("residuals.json"),
            serde_json::to_string_pretty(rows).expect("plain data serialises"),
        ),
    ];
    for (i, d) in file.devices.iter().enumerate() {
        let at = |sub: &str, ext: &str| dir.join(sub).join(format!("{}.{ext}", d.name));
        outputs.push((at("opencv", "yml"), opencv_yaml(d)));
        let region = valid_region(cal, i, VALID_UNCERTAINTY);
        let model = export::mrcal_cameramodel(d, region.as_deref());
        outputs.push((at("mrcal", "cameramodel"), model));
        outputs.push((at("ros", "yaml"), export::ros_camera_info(d)));
    }
    for (name, text) in export::colmap_model(&file) {
        outputs.push((dir.join("colmap").join(name), text));
    }
    outputs.extend(pairs);
    for (path, text) in &outputs {
        hexcal_core::atomic::write(path, text.as_bytes()).map_err(io(path))?;
    }
    Ok(Written {
        files: outputs.into_iter().map(|(p, _)| p).collect(),
        radtan: file
            .devices
            .iter()
            .zip(&fits)
            .map(|(d, f)| (d.name.clone(), f.max_deviation))
            .collect(),
    })
}

/// What [`write_outputs`] wrote.
#[derive(Clone, Debug)]
pub struct Written {
    /// Paths written.
    pub files: Vec<PathBuf>,
    /// Per device, the Kalibr radtan refit's largest deviation from the full model (px).
    pub radtan: Vec<(String, f64)>,
}

/// The held-out verification as a table: per device pair and pose, points, length error
/// RMS and maximum, flatness; then the RMS over all pairs.
pub fn format_verification(checks: &[crate::calib::verify::PairCheck]) -> String {
    let mut s = format!(
        "{:<10} {:<10} {:>5} {:>7} {:>14} {:>14} {:>14} {:>14}\n",
        "first",
        "second",
        "pose",
        "points",
        "length RMS mm",
        "from noise mm",
        "length max mm",
        "flatness mm"
    );
    for k in checks {
        let noise = match k.predicted_rms {
            Some(p) => format!("{p:.4}"),
            None => "-".into(),
        };
        s += &format!(
            "{:<10} {:<10} {:>5} {:>7} {:>14.4} {:>14} {:>14.4} {:>14.4}\n",
            k.first, k.second, k.pose, k.points, k.length_rms, noise, k.length_max, k.flatness_rms
        );
    }
    match verification_rms(checks) {
        Some(rms) => {
            s += &format!(
                "length error RMS over {} pairs: {rms:.4} mm\n",
                checks.len()
            )
        }
        None => s += "no device pair shares ten circles of a held-out pose\n",
    }
    s
}

pub use crate::calib::verify::verification_rms;

#[cfg(test)]
mod tests {
    use super::CalibrationFile;
    use crate::calib::single_sided_tests::rigs;
    use crate::calib::solve::{calibrate, CalibrateOptions};
    use hexcal_core::board::Sides;

    /// A single-sided board's calibration file says it is single-sided and has no side
    /// transform; one written into it is refused by its path.
    #[test]
    fn a_single_sided_boards_file_has_no_side_transform() {
        let (_, single) = rigs(7);
        let cal = calibrate(
            &single.board,
            &single.device_infos(),
            single.boards.len(),
            &single.views(),
            &CalibrateOptions::default(),
        )
        .unwrap();
        assert!(cal.solution.front_back.is_none() && cal.solution.held.is_empty());
        let file = CalibrationFile::new(&cal);
        let json = file.to_json();
        assert!(json.contains("\"board_sides\": 1"), "{json}");
        assert!(!json.contains("front_back"), "{json}");
        let back = CalibrationFile::from_json(&json, "c.json").unwrap();
        assert_eq!((back.board_sides, back.front_back), (Sides::One, None));
        // A side transform written into a single-sided board's file is refused by its path.
        let forged = json.replacen(
            "\"board_sides\": 1,",
            "\"board_sides\": 1, \"front_back\": {\"rvec\": [0, 3.1, 0], \"tvec\": [0, 0, -10]},",
            1,
        );
        let e = CalibrationFile::from_json(&forged, "c.json").unwrap_err();
        assert!(e.to_string().contains("front_back"), "{e}");
        assert!(e.to_string().contains("single-sided"), "{e}");
    }
}
