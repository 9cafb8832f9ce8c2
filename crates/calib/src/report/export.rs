//! Exports for neighbouring tools (docs/design.md §8 "Exports"): an mrcal `.cameramodel`
//! per device, a COLMAP text model (cameras, images = the rig's poses), a ROS
//! `camera_info` YAML per device, OpenCV `stereoRectify`-style YAMLs for named pairs and a
//! Kalibr camchain with `cam_overlaps` and the radtan refit that replaces k3.
//!
//! Takes a [`CalibrationFile`] (and, for overlaps, the observations of a [`Calibration`]);
//! gives text. Lengths in mm, pixels with (0, 0) at the centre of the top-left pixel unless
//! a format says otherwise (COLMAP: at its corner). Projectors are exported as the inverse
//! cameras they are (docs/design.md §2), marked as projectors in comments or fields where
//! the format has room.

use super::{opencv_distortion, opencv_matrix, CalibrationFile, DeviceRecord};
use crate::calib::solve::Calibration;
use hexcal_core::camera::{CameraModel, Distortion, Intrinsics};
use hexcal_core::observations::DeviceKind;
use nalgebra::{
    Isometry3, Matrix3, Matrix3x4, Matrix4, Point2, Rotation3, SMatrix, SVector, Vector2, Vector3,
};
use std::collections::BTreeMap;
use std::fmt::Write as _;

/// Why a stereo pair cannot be exported.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// A named device is not in the calibration.
    #[error("--stereo {pair}: no calibrated device named {name:?}")]
    UnknownDevice {
        /// The pair as given.
        pair: String,
        /// The missing name.
        name: String,
    },
    /// The pair cannot be rectified together.
    #[error("--stereo {pair}: {reason}")]
    Pair {
        /// The pair as given.
        pair: String,
        /// Why not.
        reason: String,
    },
}

fn kind_word(k: DeviceKind) -> &'static str {
    match k {
        DeviceKind::Camera => "camera",
        DeviceKind::Projector => "projector",
    }
}

fn list(values: &[f64]) -> String {
    let v: Vec<String> = values.iter().map(|x| format!("{x:?}")).collect();
    v.join(", ")
}

fn row_major(m: &[f64], rows: usize, cols: usize, column_major: bool) -> Vec<f64> {
    (0..rows)
        .flat_map(|i| (0..cols).map(move |j| (i, j)))
        .map(|(i, j)| {
            if column_major {
                m[j * rows + i]
            } else {
                m[i * cols + j]
            }
        })
        .collect()
}

/// mrcal's `.cameramodel` of one device: `LENSMODEL_OPENCV5` (or `OPENCV8` with the
/// rational terms; both are OpenCV's equations, so mrcal projects exactly as hexcal does),
/// intrinsics [fx, fy, cx, cy, k…], `extrinsics` = rt_cam_ref (Rodrigues vector, then
/// translation in mm: mrcal's convention, the same as T_device_ref) and `imagersize`.
/// With `region`, the model's `valid_intrinsics_region` (a closed polygon, px).
pub fn mrcal_cameramodel(d: &DeviceRecord, region: Option<&[[f64; 2]]>) -> String {
    let k = &d.intrinsics;
    let (lensmodel, dist) = match d.distortion.is_rational() {
        true => ("LENSMODEL_OPENCV8", opencv_distortion(&d.distortion)),
        false => ("LENSMODEL_OPENCV5", opencv_distortion(&d.distortion)),
    };
    let mut intrinsics = vec![k.fx, k.fy, k.cx, k.cy];
    intrinsics.extend(dist);
    let mut s = format!(
        "# mrcal camera model written by hexcal: {} ({}); extrinsics are rt_{}_ref with \
         translations in mm.\n",
        d.name,
        kind_word(d.kind),
        d.name
    );
    if d.kind == DeviceKind::Projector {
        s += "# A projector is an inverse camera: its imager is the projected raster, a \
              pixel's ray is the light it casts.\n";
    }
    let extrinsics = [d.pose.rvec, d.pose.tvec].concat();
    let _ = write!(
        s,
        "{{\n    'lensmodel': '{lensmodel}',\n    'intrinsics': [ {} ],\n    'extrinsics': [ {} ],\n    \
         'imagersize': [ {}, {} ],\n",
        list(&intrinsics),
        list(&extrinsics),
        d.width,
        d.height
    );
    if let Some(r) = region.filter(|r| !r.is_empty()) {
        let points: Vec<String> = r
            .iter()
            .chain(&r[..1])
            .map(|p| format!("[ {:?}, {:?} ]", p[0], p[1]))
            .collect();
        let _ = writeln!(
            s,
            "    # where the projection uncertainty is below {} px (docs/design.md §8)\n    \
             'valid_intrinsics_region': [ {} ],",
            crate::calib::diagnostics::VALID_UNCERTAINTY,
            points.join(", ")
        );
    }
    s += "}\n";
    s
}

/// A COLMAP text model (`cameras.txt`, `images.txt`, `points3D.txt`): one camera and one
/// image per device, the image's pose T_device_ref (the reference device's frame is
/// COLMAP's world, mm). Models FULL_OPENCV, or OPENCV when k3 and the rational terms are
/// zero; principal points shifted by +0.5 px, as COLMAP's pixel (0, 0) is the corner of
/// the top-left pixel.
pub fn colmap_model(file: &CalibrationFile) -> [(&'static str, String); 3] {
    let n = file.devices.len();
    let mut cameras = format!(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, \
         PARAMS[]\n# Number of cameras: {n}\n# Written by hexcal; principal points in COLMAP's \
         convention (pixel (0, 0) is the top-left pixel's corner).\n"
    );
    let mut images = format!(
        "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, \
         TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n# Number of images: \
         {n}, mean observations per image: 0\n# One image per device, posed in the reference \
         device's frame ({}), translations in mm.\n",
        file.reference
    );
    for d in file
        .devices
        .iter()
        .filter(|d| d.kind == DeviceKind::Projector)
    {
        let _ = writeln!(
            images,
            "# {} is a projector (an inverse camera: its image is the projected raster).",
            d.name
        );
    }
    for (i, d) in file.devices.iter().enumerate() {
        let (k, dist) = (&d.intrinsics, &d.distortion);
        let mut params = vec![
            k.fx,
            k.fy,
            k.cx + 0.5,
            k.cy + 0.5,
            dist.k1,
            dist.k2,
            dist.p1,
        ];
        params.push(dist.p2);
        let model = if dist.k3 == 0.0 && !dist.is_rational() {
            "OPENCV"
        } else {
            params.extend([dist.k3, dist.k4, dist.k5, dist.k6]);
            "FULL_OPENCV"
        };
        let p: Vec<String> = params.iter().map(|x| format!("{x:?}")).collect();
        let id = i + 1;
        let _ = writeln!(
            cameras,
            "{id} {model} {} {} {}",
            d.width,
            d.height,
            p.join(" ")
        );
        let t = d.pose.isometry();
        let q = t.rotation.quaternion();
        let v = t.translation.vector;
        let _ = writeln!(
            images,
            "{id} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {id} {}\n",
            q.w, q.i, q.j, q.k, v.x, v.y, v.z, d.name
        );
    }
    let points =
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, \
                  B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n# Number of points: 0, mean \
                  track length: 0\n"
            .to_string();
    [
        ("cameras.txt", cameras),
        ("images.txt", images),
        ("points3D.txt", points),
    ]
}

fn ros_matrix(s: &mut String, name: &str, rows: usize, cols: usize, data: &[f64]) {
    let _ = writeln!(
        s,
        "{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{}]",
        list(data)
    );
}

/// A ROS `camera_info` YAML (camera_calibration_parsers' format) of one device:
/// `plumb_bob` (or `rational_polynomial`) distortion, identity rectification and the
/// monocular projection matrix P = [K | 0]. Its pose relative to the rig is not part of
/// camera_info (see `calibration.json` or the stereo files).
pub fn ros_camera_info(d: &DeviceRecord) -> String {
    let k = &d.intrinsics;
    let mut s = format!(
        "# ROS camera_info of {} ({}) written by hexcal.\n",
        d.name,
        kind_word(d.kind)
    );
    if d.kind == DeviceKind::Projector {
        s += "# A projector is an inverse camera: its image is the projected raster.\n";
    }
    let _ = writeln!(s, "image_width: {}\nimage_height: {}", d.width, d.height);
    let _ = writeln!(s, "camera_name: {}", d.name);
    let km = [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0];
    ros_matrix(&mut s, "camera_matrix", 3, 3, &km);
    let dist = opencv_distortion(&d.distortion);
    let model = match d.distortion.is_rational() {
        true => "rational_polynomial",
        false => "plumb_bob",
    };
    let _ = writeln!(s, "distortion_model: {model}");
    ros_matrix(&mut s, "distortion_coefficients", 1, dist.len(), &dist);
    let eye = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
    ros_matrix(&mut s, "rectification_matrix", 3, 3, &eye);
    let p = [
        k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
    ];
    ros_matrix(&mut s, "projection_matrix", 3, 4, &p);
    s
}

/// A rectified stereo pair as OpenCV's `stereoRectify` defines it (CALIB_ZERO_DISPARITY,
/// alpha = −1): X_second = R·X_first + T (mm), rectifying rotations R1, R2, projections
/// P1, P2 and the disparity-to-depth matrix Q.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoRectification {
    /// Rotation first → second.
    pub r: Matrix3<f64>,
    /// Translation first → second (mm).
    pub t: Vector3<f64>,
    /// Rectifying rotation of the first device.
    pub r1: Matrix3<f64>,
    /// Rectifying rotation of the second device.
    pub r2: Matrix3<f64>,
    /// Projection of the first rectified device.
    pub p1: Matrix3x4<f64>,
    /// Projection of the second rectified device.
    pub p2: Matrix3x4<f64>,
    /// Disparity-to-depth matrix.
    pub q: Matrix4<f64>,
}

/// Mean over the four image corners of their rays turned by `rot` and projected with focal
/// length `fc` and principal point 0 (how stereoRectify centres each rectified image).
fn corner_mean(m: &CameraModel, rot: &Matrix3<f64>, fc: f64) -> Option<Vector2<f64>> {
    let (w, h) = (m.width as f64 - 1.0, m.height as f64 - 1.0);
    let mut sum = Vector2::zeros();
    for (x, y) in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
        let p = rot * m.ray(Point2::new(x, y))?;
        sum += Vector2::new(fc * p.x / p.z, fc * p.y / p.z);
    }
    Some(sum / 4.0)
}

/// Rectify the pair (`first`, `second`) as OpenCV's stereoRectify does: each device turned
/// by half the relative rotation, then both so the baseline lies along x (or y when it is
/// mostly vertical); a common focal length (the mean fy, or fx for vertical pairs) and a
/// common principal point (the mean of the two that centre each image's corners).
pub fn stereo_rectify(a: &DeviceRecord, b: &DeviceRecord) -> Option<StereoRectification> {
    let rel = b.pose.isometry() * a.pose.isometry().inverse();
    let r = *rel.rotation.to_rotation_matrix().matrix();
    let t = rel.translation.vector;
    let half = rel.rotation.scaled_axis() * -0.5;
    let r_r = *Rotation3::new(half).matrix();
    let th = r_r * t;
    let idx = if th.x.abs() > th.y.abs() { 0 } else { 1 };
    let mut uu = Vector3::zeros();
    uu[idx] = if th[idx] > 0.0 { 1.0 } else { -1.0 };
    let mut ww = th.cross(&uu);
    let nw = ww.norm();
    if nw > 0.0 {
        ww *= (th[idx].abs() / th.norm()).acos() / nw;
    }
    let w_r = *Rotation3::new(ww).matrix();
    let (r1, r2) = (w_r * r_r.transpose(), w_r * r_r);
    let tr = r2 * t;
    let f = |d: &DeviceRecord| {
        if idx == 0 {
            d.intrinsics.fy
        } else {
            d.intrinsics.fx
        }
    };
    let fc = (f(a) + f(b)) * 0.5;
    let centre = |d: &DeviceRecord, rot: &Matrix3<f64>| -> Option<Vector2<f64>> {
        let size = Vector2::new(d.width as f64 - 1.0, d.height as f64 - 1.0);
        Some(size / 2.0 - corner_mean(&d.model(), rot, fc)?)
    };
    let cc = (centre(a, &r1)? + centre(b, &r2)?) / 2.0;
    let mut p1 = Matrix3x4::zeros();
    p1[(0, 0)] = fc;
    p1[(1, 1)] = fc;
    p1[(0, 2)] = cc.x;
    p1[(1, 2)] = cc.y;
    p1[(2, 2)] = 1.0;
    let mut p2 = p1;
    p2[(idx, 3)] = tr[idx] * fc;
    #[rustfmt::skip]
    let q = Matrix4::new(
        1.0, 0.0, 0.0, -cc.x,
        0.0, 1.0, 0.0, -cc.y,
        0.0, 0.0, 0.0, fc,
        0.0, 0.0, -1.0 / tr[idx], 0.0,
    );
    Some(StereoRectification {
        r,
        t,
        r1,
        r2,
        p1,
        p2,
        q,
    })
}

/// The OpenCV FileStorage YAML of a stereo pair named "first,second" (both devices'
/// K and distortion, image size, R, T, R1, R2, P1, P2, Q; mm). The two must have the same
/// raster size (stereoRectify takes one).
pub fn stereo_yaml(file: &CalibrationFile, pair: &str) -> Result<String, ExportError> {
    let err = |reason: &str| ExportError::Pair {
        pair: pair.into(),
        reason: reason.into(),
    };
    let (first, second) = pair
        .split_once(',')
        .ok_or_else(|| err("expected two device names, e.g. cam0,cam1"))?;
    let find = |name: &str| {
        file.devices
            .iter()
            .find(|d| d.name == name.trim())
            .ok_or_else(|| ExportError::UnknownDevice {
                pair: pair.into(),
                name: name.trim().into(),
            })
    };
    let (a, b) = (find(first)?, find(second)?);
    if a.name == b.name {
        return Err(err("a device cannot pair with itself"));
    }
    if (a.width, a.height) != (b.width, b.height) {
        return Err(err(
            "the two rasters differ in size; stereoRectify needs one size",
        ));
    }
    let s = stereo_rectify(a, b)
        .ok_or_else(|| err("an image corner lies beyond the lens model's fold"))?;
    let mut y = format!(
        "%YAML:1.0\n---\nfirst: \"{}\"\nfirst_kind: {}\nsecond: \"{}\"\nsecond_kind: {}\n",
        a.name,
        kind_word(a.kind),
        b.name,
        kind_word(b.kind)
    );
    let _ = writeln!(y, "image_width: {}\nimage_height: {}", a.width, a.height);
    for (name, d) in [("1", a), ("2", b)] {
        let k = &d.intrinsics;
        let km = [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0];
        opencv_matrix(&mut y, &format!("K{name}"), 3, 3, &km);
        let dist = opencv_distortion(&d.distortion);
        opencv_matrix(&mut y, &format!("D{name}"), 1, dist.len(), &dist);
    }
    let m = |v: &[f64], r, c| row_major(v, r, c, true);
    opencv_matrix(&mut y, "R", 3, 3, &m(s.r.as_slice(), 3, 3));
    opencv_matrix(&mut y, "T", 3, 1, s.t.as_slice());
    opencv_matrix(&mut y, "R1", 3, 3, &m(s.r1.as_slice(), 3, 3));
    opencv_matrix(&mut y, "R2", 3, 3, &m(s.r2.as_slice(), 3, 3));
    opencv_matrix(&mut y, "P1", 3, 4, &m(s.p1.as_slice(), 3, 4));
    opencv_matrix(&mut y, "P2", 3, 4, &m(s.p2.as_slice(), 3, 4));
    opencv_matrix(&mut y, "Q", 4, 4, &m(s.q.as_slice(), 4, 4));
    Ok(y)
}

/// Circles two devices must share to count as overlapping (as verification needs).
pub const OVERLAP_POINTS: usize = 10;

/// Per device (in calibration order), the other devices that observed at least
/// [`OVERLAP_POINTS`] of the same circles (same board pose, side and lattice position):
/// Kalibr's `cam_overlaps`.
pub fn overlaps(cal: &Calibration) -> Vec<Vec<usize>> {
    let mut seen: BTreeMap<_, Vec<usize>> = BTreeMap::new();
    for o in &cal.observations {
        seen.entry((o.pose, o.side, o.hex.q, o.hex.r))
            .or_default()
            .push(o.device);
    }
    let n = cal.devices.len();
    let mut shared = vec![vec![0usize; n]; n];
    for devices in seen.values_mut() {
        devices.sort_unstable();
        devices.dedup();
        for &i in devices.iter() {
            for &j in devices.iter().filter(|&&j| j != i) {
                shared[i][j] += 1;
            }
        }
    }
    shared
        .iter()
        .map(|row| (0..n).filter(|&j| row[j] >= OVERLAP_POINTS).collect())
        .collect()
}

/// Grid of the radtan refit: columns and rows of pixels, corners included.
const FIT_GRID: (usize, usize) = (48, 30);

/// Pinhole-radtan (fx, fy, cx, cy, k1, k2, p1, p2) refitted to a device's full model over
/// its whole image, and the largest pixel deviation between the two on the fit grid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RadtanFit {
    /// The refitted model (k3 and the rational terms zero).
    pub model: CameraModel,
    /// Largest |π_radtan(ray) − pixel| over the grid (px).
    pub max_deviation: f64,
}

fn radtan_model(m: &CameraModel, p: &SVector<f64, 8>) -> CameraModel {
    CameraModel {
        intrinsics: Intrinsics {
            fx: p[0],
            fy: p[1],
            cx: p[2],
            cy: p[3],
        },
        distortion: Distortion {
            k1: p[4],
            k2: p[5],
            p1: p[6],
            p2: p[7],
            ..Default::default()
        },
        ..*m
    }
}

/// Refit radtan to `m`: the rays of a grid of pixels over the whole image (those the model
/// can invert) must project to the same pixels; Gauss–Newton from `m` without k3.
pub fn radtan_fit(m: &CameraModel) -> RadtanFit {
    let (nx, ny) = FIT_GRID;
    let (w, h) = (m.width as f64 - 1.0, m.height as f64 - 1.0);
    let samples: Vec<(Vector2<f64>, Point2<f64>)> = (0..ny)
        .flat_map(|j| (0..nx).map(move |i| (i, j)))
        .map(|(i, j)| {
            Point2::new(
                w * i as f64 / (nx - 1) as f64,
                h * j as f64 / (ny - 1) as f64,
            )
        })
        .filter_map(|p| Some((m.undistort(p)?, p)))
        .collect();
    let (k, d) = (&m.intrinsics, &m.distortion);
    let mut theta = SVector::<f64, 8>::from([k.fx, k.fy, k.cx, k.cy, d.k1, d.k2, d.p1, d.p2]);
    let deviation = |theta: &SVector<f64, 8>| {
        let fit = radtan_model(m, theta);
        samples
            .iter()
            .map(|(n, p)| (fit.to_pixel(fit.distortion.distort(*n)) - p).norm())
            .fold(0.0, f64::max)
    };
    if d.k3 != 0.0 || d.is_rational() {
        for _ in 0..20 {
            let fit = radtan_model(m, &theta);
            let (mut jtj, mut jtr) = (SMatrix::<f64, 8, 8>::zeros(), SVector::<f64, 8>::zeros());
            for (n, p) in &samples {
                let nd = fit.distortion.distort(*n);
                let r = fit.to_pixel(nd) - p;
                let dc = fit.distortion.coefficient_jacobian(*n);
                let mut j = SMatrix::<f64, 2, 8>::zeros();
                j[(0, 0)] = nd.x;
                j[(1, 1)] = nd.y;
                j[(0, 2)] = 1.0;
                j[(1, 3)] = 1.0;
                for c in 0..4 {
                    j[(0, 4 + c)] = theta[0] * dc[(0, c)];
                    j[(1, 4 + c)] = theta[1] * dc[(1, c)];
                }
                jtj += j.transpose() * j;
                jtr += j.transpose() * r;
            }
            match jtj.cholesky() {
                Some(c) => theta -= c.solve(&jtr),
                None => break,
            }
        }
    }
    RadtanFit {
        model: radtan_model(m, &theta),
        max_deviation: deviation(&theta),
    }
}

/// A Kalibr camchain: one `camN` per device in order, pinhole-radtan, `cam_overlaps` (from
/// [`overlaps`]) and `T_cn_cnm1` relative to the previous device (metres, as Kalibr uses).
/// A device with k3 or rational terms gets the [`radtan_fit`] over its whole image, its
/// largest deviation from the full model stated in a comment; projectors are listed as
/// cameras and marked in a comment (Kalibr has no projector model). Returns the text and
/// each device's fit.
pub fn kalibr_camchain(
    file: &CalibrationFile,
    overlaps: &[Vec<usize>],
) -> (String, Vec<RadtanFit>) {
    let mut s = String::from("# Kalibr camchain written by hexcal; translations in metres.\n");
    let mut previous: Option<Isometry3<f64>> = None;
    let mut fits = Vec::new();
    for (i, d) in file.devices.iter().enumerate() {
        let fit = radtan_fit(&d.model());
        let (k, dist) = (&fit.model.intrinsics, &fit.model.distortion);
        let _ = writeln!(s, "cam{i}:");
        if d.kind == DeviceKind::Projector {
            let _ = writeln!(
                s,
                "  # {} is a projector: its \"image\" is the projected raster",
                d.name
            );
        }
        if d.distortion != fit.model.distortion {
            let _ = writeln!(
                s,
                "  # radtan refit of {} over its whole image (k3 {:?} k4 {:?} k5 {:?} k6 {:?} \
                 have no place in radtan): largest deviation {:.4} px",
                d.name,
                d.distortion.k3,
                d.distortion.k4,
                d.distortion.k5,
                d.distortion.k6,
                fit.max_deviation
            );
        }
        let ov: Vec<String> = overlaps
            .get(i)
            .into_iter()
            .flatten()
            .map(|j| j.to_string())
            .collect();
        let _ = writeln!(s, "  cam_overlaps: [{}]", ov.join(", "));
        let _ = writeln!(s, "  camera_model: pinhole");
        let _ = writeln!(
            s,
            "  distortion_coeffs: [{}]",
            list(&[dist.k1, dist.k2, dist.p1, dist.p2])
        );
        let _ = writeln!(s, "  distortion_model: radtan");
        let _ = writeln!(s, "  intrinsics: [{}]", list(&[k.fx, k.fy, k.cx, k.cy]));
        let _ = writeln!(s, "  resolution: [{}, {}]", d.width, d.height);
        let _ = writeln!(s, "  rostopic: /{}/image_raw", d.name);
        let pose = d.pose.isometry();
        if let Some(prev) = previous {
            // T_cn_cnm1 = T_n_ref · T_ref_(n−1).
            let m = (pose * prev.inverse()).to_homogeneous();
            let _ = writeln!(s, "  T_cn_cnm1:");
            for r in 0..4 {
                let scale = |c: usize| if c == 3 && r < 3 { 1e-3 } else { 1.0 };
                let row: Vec<f64> = (0..4).map(|c| m[(r, c)] * scale(c)).collect();
                let _ = writeln!(s, "  - [{}]", list(&row));
            }
        }
        previous = Some(pose);
        fits.push(fit);
    }
    (s, fits)
}
