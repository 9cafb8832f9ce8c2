//! A calibration read from `calibration.json` (or made by [`crate::calibrate`]) and its
//! devices: lens model, pose, covariance, projection and unprojection of numpy arrays.
//!
//! Units as in the file: millimetres and pixels, pixel (0, 0) at the centre of the top-left
//! pixel, poses `T_device_ref` (X_device = R·X_ref + T).

use crate::arrays::{float_rows, rows_array};
use crate::error::{error, guard};
use hexcal_calib::calib::bundle::Device as Posed;
use hexcal_calib::calib::diagnostics::lens_uncertainty;
use hexcal_calib::calib::verify::ray;
use hexcal_calib::report::{opencv_yaml, CalibrationFile, DeviceRecord};
use hexcal_core::camera::{CameraModel, LensParam};
use hexcal_core::observations::DeviceKind;
use nalgebra::{DMatrix, Isometry3, Matrix4, Point2, Point3};
use numpy::ndarray::{Array1, Array2};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyKeyError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::PathBuf;

/// One calibrated camera or projector (a projector is the inverse camera it is: its image
/// is the projected raster).
#[pyclass(frozen, module = "hexcal")]
pub struct Device {
    record: DeviceRecord,
}

/// A 4 × 4 homogeneous matrix as a numpy array.
fn matrix4<'py>(py: Python<'py>, m: &Matrix4<f64>) -> Bound<'py, PyArray2<f64>> {
    Array2::from_shape_fn((4, 4), |(i, j)| m[(i, j)]).into_pyarray(py)
}

impl Device {
    /// The device's lens model.
    pub fn model(&self) -> CameraModel {
        self.record.model()
    }

    /// T_device_ref.
    pub fn isometry(&self) -> Isometry3<f64> {
        self.record.pose.isometry()
    }

    /// The record as the calibration's posed device (name, kind, model, pose).
    pub fn posed(&self) -> Posed {
        Posed {
            name: self.record.name.clone(),
            kind: self.record.kind,
            model: self.model(),
            pose: self.isometry(),
        }
    }

    /// The record of the file.
    pub fn record(&self) -> &DeviceRecord {
        &self.record
    }

    /// The covariance of the free lens parameters and which they are; an error naming the
    /// device when the file holds none (files of older builds).
    pub fn lens_covariance_matrix(&self) -> PyResult<(Vec<LensParam>, DMatrix<f64>)> {
        let r = &self.record;
        if r.lens_params.is_empty() {
            return Err(error(format!(
                "device {}: calibration.json holds no lens covariance (written by an older \
                 hexcal): no uncertainty",
                r.name
            )));
        }
        let free = r
            .lens_params
            .iter()
            .map(|n| {
                *LensParam::ALL
                    .iter()
                    .find(|p| p.name() == n)
                    .expect("checked when read")
            })
            .collect();
        let n = r.lens_params.len();
        Ok((free, DMatrix::from_fn(n, n, |i, j| r.lens_covariance[i][j])))
    }
}

#[pymethods]
impl Device {
    /// Device name.
    #[getter]
    fn name(&self) -> &str {
        &self.record.name
    }

    /// "camera" or "projector".
    #[getter]
    fn kind(&self) -> &'static str {
        match self.record.kind {
            DeviceKind::Camera => "camera",
            DeviceKind::Projector => "projector",
        }
    }

    /// Image (raster) width (px).
    #[getter]
    fn width(&self) -> u32 {
        self.record.width
    }

    /// Image (raster) height (px).
    #[getter]
    fn height(&self) -> u32 {
        self.record.height
    }

    /// Pinhole intrinsics: {"fx", "fy", "cx", "cy"} (px).
    #[getter]
    fn intrinsics<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let k = &self.record.intrinsics;
        let d = PyDict::new(py);
        for (name, v) in [("fx", k.fx), ("fy", k.fy), ("cx", k.cx), ("cy", k.cy)] {
            d.set_item(name, v)?;
        }
        Ok(d)
    }

    /// OpenCV distortion coefficients: {"k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"}.
    #[getter]
    fn distortion<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let k = &self.record.distortion;
        let d = PyDict::new(py);
        let named = [
            ("k1", k.k1),
            ("k2", k.k2),
            ("p1", k.p1),
            ("p2", k.p2),
            ("k3", k.k3),
            ("k4", k.k4),
            ("k5", k.k5),
            ("k6", k.k6),
        ];
        for (name, v) in named {
            d.set_item(name, v)?;
        }
        Ok(d)
    }

    /// OpenCV's camera matrix K (3 × 3).
    #[getter]
    fn camera_matrix<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let k = &self.record.intrinsics;
        let m = [[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]];
        Array2::from_shape_fn((3, 3), |(i, j)| m[i][j]).into_pyarray(py)
    }

    /// OpenCV's distortion vector: (k1, k2, p1, p2, k3), or 8 values with the rational
    /// k4–k6 (as in the OpenCV export).
    #[getter]
    fn dist_coeffs<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.record.distortion.to_opencv())
    }

    /// T_device_ref as a 4 × 4 matrix: X_device = R·X_ref + T (mm).
    #[getter]
    fn pose<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        matrix4(py, &self.isometry().to_homogeneous())
    }

    /// Rotation of the pose as a Rodrigues vector (rad), as OpenCV's `rvec`.
    #[getter]
    fn rvec<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.record.pose.rvec.to_vec())
    }

    /// Translation of the pose (mm), as OpenCV's `tvec`.
    #[getter]
    fn tvec<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.record.pose.tvec.to_vec())
    }

    /// Names of the estimated lens parameters ("fx", …), the rows of `lens_covariance`.
    #[getter]
    fn lens_params(&self) -> Vec<String> {
        self.record.lens_params.clone()
    }

    /// Standard deviations of the estimated lens parameters, in `lens_params` order.
    #[getter]
    fn lens_std<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.record.lens_std.clone())
    }

    /// Covariance of the estimated lens parameters (`lens_params` × `lens_params`), or None
    /// in a file of an older build that holds none.
    #[getter]
    fn lens_covariance<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<f64>>> {
        self.lens_covariance_matrix()
            .ok()
            .map(|(_, c)| Array2::from_shape_fn(c.shape(), |(i, j)| c[(i, j)]).into_pyarray(py))
    }

    /// Standard deviations of a left increment of the pose: (ω rad, τ mm), zero for the
    /// reference device. (The file holds no cross-covariances between devices.)
    #[getter]
    fn pose_std<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.record.pose_std.to_vec())
    }

    /// Every distortion term: [{"term", "estimated", "estimate", "std", "reason"}].
    #[getter]
    fn lens_model<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let list = PyList::empty(py);
        for t in &self.record.lens_model {
            let d = PyDict::new(py);
            d.set_item("term", &t.term)?;
            d.set_item("estimated", t.estimated)?;
            d.set_item("estimate", t.estimate)?;
            d.set_item("std", t.std)?;
            d.set_item("reason", &t.reason)?;
            list.append(d)?;
        }
        Ok(list)
    }

    /// Pixels (N × 2) of points (N × 3, mm) given in the reference frame, or in the device's
    /// own frame with `frame="device"`; NaN for a point behind the device (z ≤ 0 in its
    /// frame). Equal to `cv2.projectPoints` with the OpenCV export's K, distortion, R, T.
    #[pyo3(signature = (points, frame = "reference"))]
    fn project<'py>(
        &self,
        py: Python<'py>,
        points: &Bound<'py, PyAny>,
        frame: &str,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        guard(|| {
            let pose = match frame {
                "reference" => self.isometry(),
                "device" => Isometry3::identity(),
                other => {
                    return Err(error(format!(
                        "frame {other:?}: \"reference\" or \"device\""
                    )))
                }
            };
            let pts = float_rows(points, 3, "points")?;
            let model = self.model();
            let mut out = Vec::with_capacity(pts.shape()[0] * 2);
            for row in pts.as_array().rows() {
                let x = Point3::new(row[0], row[1], row[2]);
                match model.project_from(&pose, &x) {
                    Some(p) => out.extend([p.x, p.y]),
                    None => out.extend([f64::NAN; 2]),
                }
            }
            Ok(rows_array(py, out, 2))
        })
    }

    /// Unit rays (N × 3) through pixels (N × 2) in the device's own frame (x right, y down,
    /// z forward); NaN where the lens model cannot be inverted. `rays` gives them in the
    /// reference frame.
    fn unproject<'py>(
        &self,
        py: Python<'py>,
        pixels: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        guard(|| {
            let px = float_rows(pixels, 2, "pixels")?;
            let model = self.model();
            let mut out = Vec::with_capacity(px.shape()[0] * 3);
            for row in px.as_array().rows() {
                match model.ray(Point2::new(row[0], row[1])) {
                    Some(d) => out.extend(d.normalize().iter().copied()),
                    None => out.extend([f64::NAN; 3]),
                }
            }
            Ok(rows_array(py, out, 3))
        })
    }

    /// The rays through pixels (N × 2) in the reference frame: (origins N × 3, the device's
    /// centre in mm; unit directions N × 3), as `hexcal verify` triangulates them; NaN where
    /// the lens model cannot be inverted.
    #[allow(clippy::type_complexity)]
    fn rays<'py>(
        &self,
        py: Python<'py>,
        pixels: &Bound<'py, PyAny>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray2<f64>>)> {
        guard(|| {
            let px = float_rows(pixels, 2, "pixels")?;
            let device = self.posed();
            let n = px.shape()[0];
            let (mut origins, mut directions) =
                (Vec::with_capacity(3 * n), Vec::with_capacity(3 * n));
            for row in px.as_array().rows() {
                match ray(&device, Point2::new(row[0], row[1])) {
                    Some((o, d)) => {
                        origins.extend(o.iter().copied());
                        directions.extend(d.iter().copied());
                    }
                    None => {
                        origins.extend([f64::NAN; 3]);
                        directions.extend([f64::NAN; 3]);
                    }
                }
            }
            Ok((rows_array(py, origins, 3), rows_array(py, directions, 3)))
        })
    }

    /// Projection uncertainty (px, 1σ along the worst direction) at pixels (N × 2): the lens
    /// covariance of the file propagated to the pixel of the ray through each (the pose held),
    /// as the report's valid-intrinsics region uses it (docs/design.md §8); NaN where the
    /// lens model cannot be inverted. Raises `hexcal.Error` for a file without covariance.
    fn projection_uncertainty<'py>(
        &self,
        py: Python<'py>,
        pixels: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        guard(|| {
            let px = float_rows(pixels, 2, "pixels")?;
            let (free, cov) = self.lens_covariance_matrix()?;
            let model = self.model();
            let out: Array1<f64> = px
                .as_array()
                .rows()
                .into_iter()
                .map(|row| {
                    lens_uncertainty(&model, &free, &cov, Point2::new(row[0], row[1]))
                        .unwrap_or(f64::NAN)
                })
                .collect();
            Ok(out.into_pyarray(py))
        })
    }

    /// The device's OpenCV FileStorage YAML, as `calibration/opencv/NAME.yml` holds it
    /// (`camera_matrix`, `distortion_coefficients`, `R`, `T`, image size).
    fn opencv_yaml(&self) -> String {
        opencv_yaml(&self.record)
    }

    fn __repr__(&self) -> String {
        let r = &self.record;
        format!(
            "<hexcal.Device {} ({}, {}×{})>",
            r.name,
            self.kind(),
            r.width,
            r.height
        )
    }
}

/// Every calibrated device's model and pose in the reference device's frame, indexed by
/// name (`cal["cam0"]`).
#[pyclass(frozen, module = "hexcal")]
pub struct Calibration {
    file: CalibrationFile,
    devices: Vec<Py<Device>>,
    excluded: Vec<(String, String)>,
}

impl Calibration {
    /// The Python object of a calibration file; `excluded` the devices left out and why.
    pub fn new(
        py: Python<'_>,
        file: CalibrationFile,
        excluded: Vec<(String, String)>,
    ) -> PyResult<Calibration> {
        let devices = file
            .devices
            .iter()
            .map(|r| Py::new(py, Device { record: r.clone() }))
            .collect::<PyResult<_>>()?;
        Ok(Calibration {
            file,
            devices,
            excluded,
        })
    }

    /// The file.
    pub fn file(&self) -> &CalibrationFile {
        &self.file
    }

    /// The device called `name`, or a `KeyError` naming the devices there are.
    pub fn device<'py>(&self, py: Python<'py>, name: &str) -> PyResult<Bound<'py, Device>> {
        self.file
            .devices
            .iter()
            .position(|d| d.name == name)
            .map(|i| self.devices[i].bind(py).clone())
            .ok_or_else(|| {
                let names: Vec<&str> = self.file.devices.iter().map(|d| d.name.as_str()).collect();
                PyKeyError::new_err(format!(
                    "no calibrated device named {name:?} (devices: {})",
                    names.join(", ")
                ))
            })
    }
}

#[pymethods]
impl Calibration {
    /// The device called `name`; `KeyError` if there is none.
    fn __getitem__<'py>(&self, py: Python<'py>, name: &str) -> PyResult<Bound<'py, Device>> {
        self.device(py, name)
    }

    /// Whether a device is called `name`.
    fn __contains__(&self, name: &str) -> bool {
        self.file.devices.iter().any(|d| d.name == name)
    }

    /// Number of calibrated devices.
    fn __len__(&self) -> usize {
        self.devices.len()
    }

    /// The calibrated devices, in the file's order.
    #[getter]
    fn devices(&self, py: Python<'_>) -> Vec<Py<Device>> {
        self.devices.iter().map(|d| d.clone_ref(py)).collect()
    }

    /// Device names, in the file's order.
    #[getter]
    fn names(&self) -> Vec<String> {
        self.file.devices.iter().map(|d| d.name.clone()).collect()
    }

    /// Name of the reference device (its frame is the reference frame, its pose the
    /// identity).
    #[getter]
    fn reference(&self) -> &str {
        &self.file.reference
    }

    /// Board name (or board file) the calibration used.
    #[getter]
    fn board(&self) -> &str {
        &self.file.board
    }

    /// Posterior σ per residual coordinate (px).
    #[getter]
    fn sigma(&self) -> f64 {
        self.file.sigma
    }

    /// T_board_back, the refined back side's frame in the board's (4 × 4, mm); None for a
    /// single-sided board, which has no back.
    #[getter]
    fn front_back<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<f64>>> {
        self.file
            .front_back
            .as_ref()
            .map(|fb| matrix4(py, &fb.isometry().to_homogeneous()))
    }

    /// Devices the calibration left out, as (name, reason); empty for a loaded file (which
    /// lists only calibrated devices).
    #[getter]
    fn excluded(&self) -> Vec<(String, String)> {
        self.excluded.clone()
    }

    /// The calibration as `calibration.json` text.
    fn to_json(&self) -> String {
        self.file.to_json()
    }

    /// Writes `calibration.json` text to `path` (atomically: a reader never sees half).
    fn save(&self, path: PathBuf) -> PyResult<()> {
        hexcal_core::atomic::write(&path, self.file.to_json().as_bytes())
            .map_err(|e| error(format!("cannot write {}: {e}", path.display())))
    }

    fn __repr__(&self) -> String {
        format!(
            "<hexcal.Calibration of {} devices, reference {}>",
            self.devices.len(),
            self.file.reference
        )
    }
}

/// Reads a `calibration.json` (of `hexcal run` or `hexcal calibrate`), checked as the
/// command line checks it; a bad file raises `hexcal.Error` naming the file and the value.
#[pyfunction]
pub fn load(py: Python<'_>, path: PathBuf) -> PyResult<Calibration> {
    guard(|| {
        let text = hexcal_core::limits::read_text(&path)
            .map_err(|e| error(format!("{}: {e}", path.display())))?;
        let file = CalibrationFile::from_json(&text, &path.display().to_string()).map_err(error)?;
        Calibration::new(py, file, Vec::new())
    })
}
