//! Triangulation of pixel pairs of two calibrated devices (camera–camera or
//! camera–projector) as `hexcal verify` does it — the midpoint of the shortest segment
//! between the two rays — with each point's covariance propagated from the calibration's
//! uncertainty; and `hexcal verify` itself on held-out poses.

use crate::arrays::{correspondences, float_rows, rows_array};
use crate::calibration::{Calibration, Device};
use crate::error::{error, guard};
use hexcal_calib::calib::bundle::Device as Posed;
use hexcal_calib::calib::verify::{midpoint, ray, verify as verify_pairs};
use hexcal_core::board::Board;
use hexcal_core::camera::{LensParam, PoseIncrement};
use nalgebra::{DMatrix, Matrix3, Point2, Point3, Vector3};
use numpy::ndarray::Array3;
use numpy::{IntoPyArray, PyArray2, PyArray3};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The triangulated point of one pixel pair, if both rays exist and are not parallel.
fn point(a: &Posed, pa: Point2<f64>, b: &Posed, pb: Point2<f64>) -> Option<Point3<f64>> {
    midpoint(ray(a, pa)?, ray(b, pb)?)
}

/// One device's uncertain quantities: its free lens parameters (full covariance), a left
/// pose increment (independent σ per component: the file holds no more) and the pixel.
struct Uncertain {
    device: Posed,
    free: Vec<LensParam>,
    lens: DMatrix<f64>,
    pose_std: [f64; 6],
}

impl Uncertain {
    fn new(d: &Device) -> PyResult<Uncertain> {
        let (free, lens) = d.lens_covariance_matrix()?;
        Ok(Uncertain {
            device: d.posed(),
            free,
            lens,
            pose_std: d.record().pose_std,
        })
    }

    /// Parameters: free lens parameters, then ω, τ, then the pixel's x, y.
    fn count(&self) -> usize {
        self.free.len() + 8
    }

    /// Standard deviation of parameter k (a scale for its finite-difference step).
    fn std(&self, k: usize, pixel_sigma: f64) -> f64 {
        let n = self.free.len();
        match k {
            k if k < n => self.lens[(k, k)].max(0.0).sqrt(),
            k if k < n + 6 => self.pose_std[k - n],
            _ => pixel_sigma,
        }
    }

    /// Covariance of parameters k and l.
    fn cov(&self, k: usize, l: usize, pixel_sigma: f64) -> f64 {
        let n = self.free.len();
        match (k < n, l < n) {
            (true, true) => self.lens[(k, l)],
            (false, false) if k == l => self.std(k, pixel_sigma).powi(2),
            _ => 0.0,
        }
    }

    /// The device and pixel with parameter k moved by h.
    fn moved(&self, pixel: Point2<f64>, k: usize, h: f64) -> (Posed, Point2<f64>) {
        let n = self.free.len();
        let mut device = self.device.clone();
        let mut pixel = pixel;
        if k < n {
            let mut v = device.model.lens_vector();
            v[self.free[k].index()] += h;
            device.model.set_lens_vector(&v);
        } else if k < n + 6 {
            let mut step = [0.0; 6];
            step[k - n] = h;
            let inc = PoseIncrement {
                rotation: Vector3::new(step[0], step[1], step[2]),
                translation: Vector3::new(step[3], step[4], step[5]),
            };
            device.pose = inc.apply(&device.pose);
        } else {
            pixel[k - n - 6] += h;
        }
        (device, pixel)
    }
}

/// Covariance (mm²) of the point triangulated from `pa` and `pb`: first-order propagation,
/// central differences with steps of 1 % of each parameter's σ.
fn covariance(
    a: &Uncertain,
    pa: Point2<f64>,
    b: &Uncertain,
    pb: Point2<f64>,
    pixel_sigma: f64,
) -> Option<Matrix3<f64>> {
    // Jacobian columns of the point with respect to each device's parameters.
    let columns = |u: &Uncertain, first: bool| -> Option<Vec<Vector3<f64>>> {
        (0..u.count())
            .map(|k| {
                let h = 0.01 * u.std(k, pixel_sigma);
                if h == 0.0 {
                    return Some(Vector3::zeros());
                }
                let at = |h: f64| {
                    if first {
                        let (d, p) = u.moved(pa, k, h);
                        point(&d, p, &b.device, pb)
                    } else {
                        let (d, p) = u.moved(pb, k, h);
                        point(&a.device, pa, &d, p)
                    }
                };
                Some((at(h)? - at(-h)?) / (2.0 * h))
            })
            .collect()
    };
    let mut c = Matrix3::zeros();
    for (u, j) in [(a, columns(a, true)?), (b, columns(b, false)?)] {
        for (k, jk) in j.iter().enumerate() {
            for (l, jl) in j.iter().enumerate() {
                let s = u.cov(k, l, pixel_sigma);
                if s != 0.0 {
                    c += jk * jl.transpose() * s;
                }
            }
        }
    }
    Some(c)
}

/// Triangulates pixel pairs: `pixels_first` (N × 2) of device `first` with `pixels_second`
/// (N × 2) of device `second` (a camera with a camera or a projector; for a projector its
/// decoded (u, v)). Each point (N × 3, reference frame, mm) is the midpoint of the shortest
/// segment between the two rays, as `hexcal verify` computes it; NaN where a ray does not
/// exist or the rays are parallel. No ellipse-centre de-biasing: that needs the board's
/// pose, which `verify` fits on a held-out pose.
///
/// With `pixel_sigma` (px, the 1σ noise of each pixel coordinate, may be 0) it returns
/// (points, covariance N × 3 × 3, mm²): the lens covariances of both devices, their pose σ
/// and the pixel noise propagated to first order. The file holds no correlations between
/// devices (nor within a pose), so those are taken as zero.
#[pyfunction]
#[pyo3(signature = (calibration, first, second, pixels_first, pixels_second, pixel_sigma = None))]
pub fn triangulate<'py>(
    py: Python<'py>,
    calibration: &Calibration,
    first: &str,
    second: &str,
    pixels_first: &Bound<'py, PyAny>,
    pixels_second: &Bound<'py, PyAny>,
    pixel_sigma: Option<f64>,
) -> PyResult<Bound<'py, PyAny>> {
    guard(|| {
        let da = calibration.device(py, first)?;
        let db = calibration.device(py, second)?;
        let (da, db) = (da.get(), db.get());
        let pa = float_rows(pixels_first, 2, "pixels_first")?;
        let pb = float_rows(pixels_second, 2, "pixels_second")?;
        let (pa, pb) = (pa.as_array(), pb.as_array());
        if pa.nrows() != pb.nrows() {
            return Err(error(format!(
                "pixels_first has {} rows, pixels_second {}: one pixel pair per row",
                pa.nrows(),
                pb.nrows()
            )));
        }
        let pairs: Vec<(Point2<f64>, Point2<f64>)> = pa
            .rows()
            .into_iter()
            .zip(pb.rows())
            .map(|(a, b)| (Point2::new(a[0], a[1]), Point2::new(b[0], b[1])))
            .collect();
        let (a, b) = (da.posed(), db.posed());
        let mut points = Vec::with_capacity(3 * pairs.len());
        for &(p, q) in &pairs {
            match point(&a, p, &b, q) {
                Some(x) => points.extend(x.iter().copied()),
                None => points.extend([f64::NAN; 3]),
            }
        }
        let points: Bound<'py, PyArray2<f64>> = rows_array(py, points, 3);
        let Some(sigma) = pixel_sigma else {
            return Ok(points.into_any());
        };
        if !(sigma.is_finite() && sigma >= 0.0) {
            return Err(error(format!("pixel_sigma {sigma}: a finite σ ≥ 0 (px)")));
        }
        let (ua, ub) = (Uncertain::new(da)?, Uncertain::new(db)?);
        let mut cov = Vec::with_capacity(9 * pairs.len());
        for &(p, q) in &pairs {
            match covariance(&ua, p, &ub, q, sigma) {
                Some(c) => cov.extend(c.transpose().iter().copied()),
                None => cov.extend([f64::NAN; 9]),
            }
        }
        let cov: Bound<'py, PyArray3<f64>> = Array3::from_shape_vec((pairs.len(), 3, 3), cov)
            .expect("3 × 3 per point")
            .into_pyarray(py);
        Ok((points, cov).into_pyobject(py)?.into_any())
    })
}

/// `hexcal verify --calibration … HELD_OUT`: the held-out poses of a correspondences file
/// (a path, e.g. a run's `calibration/held-out.json`, or a dict of its layout) triangulated
/// from every camera–camera and camera–projector pair that shares ten circles, with each
/// camera's ellipse-centre bias removed. One dict per pair and pose: "first", "second",
/// "pose", "points", "length_rms", "length_max", "flatness_rms" (mm).
#[pyfunction]
pub fn verify<'py>(
    py: Python<'py>,
    calibration: &Calibration,
    held_out: &Bound<'py, PyAny>,
) -> PyResult<Vec<Bound<'py, PyDict>>> {
    guard(|| {
        let (c, origin) = correspondences(held_out)?;
        let devices = c
            .devices
            .iter()
            .map(|d| {
                calibration
                    .file()
                    .devices
                    .iter()
                    .find(|r| r.name == d.name)
                    .map(|r| Posed {
                        name: r.name.clone(),
                        kind: r.kind,
                        model: r.model(),
                        pose: r.pose.isometry(),
                    })
                    .ok_or_else(|| {
                        error(format!(
                            "{origin}: device {:?} is not in the calibration",
                            d.name
                        ))
                    })
            })
            .collect::<PyResult<Vec<_>>>()?;
        let board =
            Board::resolve_in(&c.board, std::path::Path::new(&origin), "board").map_err(error)?;
        let verification = py.detach(|| verify_pairs(&board, &devices, &c.views));
        let checks = verification.checks;
        if checks.is_empty() {
            let why = match verification.skipped.first() {
                None => "no device pair shares ten circles of a pose".to_string(),
                Some(first) => format!("no device pair gives figures ({first})"),
            };
            return Err(error(format!("{origin}: {why}")));
        }
        checks
            .iter()
            .map(|k| {
                let d = PyDict::new(py);
                d.set_item("first", &k.first)?;
                d.set_item("second", &k.second)?;
                d.set_item("pose", k.pose)?;
                d.set_item("points", k.points)?;
                d.set_item("length_rms", k.length_rms)?;
                d.set_item("length_max", k.length_max)?;
                d.set_item("flatness_rms", k.flatness_rms)?;
                Ok(d)
            })
            .collect()
    })
}
