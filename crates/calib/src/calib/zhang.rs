//! Zhang's planar initialisation (docs/design.md §8): normalised DLT homographies per view,
//! closed-form intrinsics with zero skew, poses from homographies, a linear (k1, k2) start.
//!
//! Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000;
//! equation numbers below refer to that paper.

use super::{CalibError, PlanarView};
use hexcal_core::camera::{CameraModel, Distortion, Intrinsics};
use nalgebra::{
    DMatrix, Isometry3, Matrix3, Point2, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3,
    Vector6,
};

/// A plane-to-image homography: image ~ H · (x, y, 1) with (x, y) on the board plane (mm).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Homography(pub Matrix3<f64>);

impl Homography {
    /// Normalised DLT estimate from at least four correspondences (Hartley & Zisserman
    /// Alg. 4.2); `None` when the points are degenerate.
    pub fn estimate(view: &PlanarView) -> Option<Homography> {
        let n = view.points.len();
        if n < 4 {
            return None;
        }
        let tb = normalising_transform(view.points.iter().map(|c| c.board))?;
        let ti = normalising_transform(view.points.iter().map(|c| c.image))?;
        let mut a = DMatrix::<f64>::zeros(2 * n, 9);
        for (i, c) in view.points.iter().enumerate() {
            let p = tb * c.board.to_homogeneous();
            let q = ti * c.image.to_homogeneous();
            let (x, y, w) = (p.x / p.z, p.y / p.z, 1.0);
            let (u, v) = (q.x / q.z, q.y / q.z);
            // Two rows of A·h = 0 per correspondence (H&Z eq. 4.3).
            let r0 = [0.0, 0.0, 0.0, -x, -y, -w, v * x, v * y, v * w];
            let r1 = [x, y, w, 0.0, 0.0, 0.0, -u * x, -u * y, -u * w];
            for j in 0..9 {
                a[(2 * i, j)] = r0[j];
                a[(2 * i + 1, j)] = r1[j];
            }
        }
        let svd = a.try_svd(false, true, f64::EPSILON, MAX_SVD_ITERATIONS)?;
        let vt = svd.v_t?;
        let (k, _) = svd
            .singular_values
            .iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(b.1))?;
        let h = vt.row(k);
        let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
        let h = ti.try_inverse()? * hn * tb;
        let scale = h[(2, 2)];
        (scale.abs() > f64::EPSILON).then(|| Homography(h / scale))
    }

    /// Map a board-plane point into the image.
    pub fn apply(&self, p: Point2<f64>) -> Point2<f64> {
        let q = self.0 * p.to_homogeneous();
        Point2::new(q.x / q.z, q.y / q.z)
    }
}

/// Similarity that moves points to zero mean and mean distance √2 (Hartley normalisation).
fn normalising_transform(
    points: impl Iterator<Item = Point2<f64>> + Clone,
) -> Option<Matrix3<f64>> {
    let n = points.clone().count() as f64;
    let mean = points.clone().fold(Vector2::zeros(), |s, p| s + p.coords) / n;
    let spread = points.map(|p| (p.coords - mean).norm()).sum::<f64>() / n;
    (spread > 0.0).then(|| {
        let s = std::f64::consts::SQRT_2 / spread;
        Matrix3::new(s, 0.0, -s * mean.x, 0.0, s, -s * mean.y, 0.0, 0.0, 1.0)
    })
}

/// The vector v_ij of Zhang's eq. (7) built from columns i and j of H.
fn v_ij(h: &Matrix3<f64>, i: usize, j: usize) -> Vector6<f64> {
    let (hi, hj) = (h.column(i), h.column(j));
    Vector6::new(
        hi[0] * hj[0],
        hi[0] * hj[1] + hi[1] * hj[0],
        hi[1] * hj[1],
        hi[2] * hj[0] + hi[0] * hj[2],
        hi[2] * hj[1] + hi[1] * hj[2],
        hi[2] * hj[2],
    )
}

/// Closed-form intrinsics with zero skew from at least two non-parallel homographies
/// (Zhang §3.1 and Appendix B).
pub fn intrinsics_from_homographies(hs: &[Homography]) -> Result<Intrinsics, CalibError> {
    if hs.len() < 2 {
        return Err(CalibError::TooFewViews {
            needed: 2,
            got: hs.len(),
        });
    }
    // Rows of V·b = 0 (eq. 9), with each H scaled to unit norm for conditioning, plus the
    // zero-skew constraint B12 = 0.
    let mut v = DMatrix::<f64>::zeros(2 * hs.len() + 1, 6);
    for (k, h) in hs.iter().enumerate() {
        let h = h.0 / h.0.norm();
        v.row_mut(2 * k).copy_from(&v_ij(&h, 0, 1).transpose());
        v.row_mut(2 * k + 1)
            .copy_from(&(v_ij(&h, 0, 0) - v_ij(&h, 1, 1)).transpose());
    }
    v[(2 * hs.len(), 1)] = 1.0;
    let svd = v
        .try_svd(false, true, f64::EPSILON, MAX_SVD_ITERATIONS)
        .ok_or(CalibError::Degenerate("intrinsics SVD"))?;
    let vt = svd.v_t.ok_or(CalibError::Degenerate("intrinsics SVD"))?;
    let (k, _) = svd
        .singular_values
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))
        .ok_or(CalibError::Degenerate("intrinsics SVD"))?;
    let b = vt.row(k);
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    // Appendix B closed form.
    let den = b11 * b22 - b12 * b12;
    let cy = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + cy * (b12 * b13 - b11 * b23)) / b11;
    let fx2 = lambda / b11;
    let fy2 = lambda * b11 / den;
    if !(fx2 > 0.0 && fy2 > 0.0) {
        return Err(CalibError::Degenerate(
            "views too close to parallel for closed-form intrinsics",
        ));
    }
    let (fx, fy) = (fx2.sqrt(), fy2.sqrt());
    let cx = -b13 * fx * fx / lambda;
    Ok(Intrinsics { fx, fy, cx, cy })
}

/// Pose T_device_board of one view from its homography and the intrinsics (Zhang §3.1,
/// eq. 14 ff.), with the rotation projected onto SO(3).
pub fn pose_from_homography(h: &Homography, k: &Intrinsics) -> Option<Isometry3<f64>> {
    let kinv = Matrix3::new(k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0).try_inverse()?;
    let m = kinv * h.0;
    let mut lambda = 1.0 / m.column(0).norm();
    // The board lies in front of the device: t_z > 0.
    if m[(2, 2)] * lambda < 0.0 {
        lambda = -lambda;
    }
    let r1 = m.column(0) * lambda;
    let r2 = m.column(1) * lambda;
    let t = m.column(2) * lambda;
    let r3 = r1.cross(&r2);
    let r = Matrix3::from_columns(&[r1, r2, r3]);
    let svd = r.try_svd(true, true, f64::EPSILON, MAX_SVD_ITERATIONS)?;
    let mut rot = svd.u? * svd.v_t?;
    if rot.determinant() < 0.0 {
        rot = -rot;
    }
    Some(Isometry3::from_parts(
        Translation3::from(Vector3::from(t)),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rot)),
    ))
}

/// Linear least-squares (k1, k2) given intrinsics and poses (Zhang §3.3, eq. 13).
pub fn radial_from_views(
    views: &[PlanarView],
    poses: &[Isometry3<f64>],
    k: &Intrinsics,
) -> Distortion {
    let mut ata = nalgebra::Matrix2::<f64>::zeros();
    let mut atb = Vector2::<f64>::zeros();
    for (view, pose) in views.iter().zip(poses) {
        for c in &view.points {
            let p = pose * nalgebra::Point3::new(c.board.x, c.board.y, 0.0);
            if p.z <= 0.0 {
                continue;
            }
            let (x, y) = (p.x / p.z, p.y / p.z);
            let r2 = x * x + y * y;
            let (u, v) = (k.fx * x + k.cx, k.fy * y + k.cy);
            for (d, obs) in [(u - k.cx, c.image.x - u), (v - k.cy, c.image.y - v)] {
                let row = Vector2::new(d * r2, d * r2 * r2);
                ata += row * row.transpose();
                atb += row * obs;
            }
        }
    }
    let k12 = ata.try_inverse().map_or(Vector2::zeros(), |inv| inv * atb);
    Distortion {
        k1: k12.x,
        k2: k12.y,
        ..Default::default()
    }
}

/// Iterations an SVD may take: it converges in tens; data gone non-finite never converge,
/// and the step ends as degenerate instead.
const MAX_SVD_ITERATIONS: usize = 10_000;

/// Views [`initialise`] needs.
pub const MIN_VIEWS: usize = 3;

/// Zhang's initialisation of one device from its planar views: intrinsics, one pose per view
/// (in view order), and a linear radial start. Needs at least [`MIN_VIEWS`] non-parallel
/// views.
pub fn initialise(
    views: &[PlanarView],
    width: u32,
    height: u32,
) -> Result<(CameraModel, Vec<Isometry3<f64>>), CalibError> {
    if views.len() < MIN_VIEWS {
        return Err(CalibError::TooFewViews {
            needed: MIN_VIEWS,
            got: views.len(),
        });
    }
    let hs: Vec<Homography> = views
        .iter()
        .map(|v| Homography::estimate(v).ok_or(CalibError::Degenerate("homography")))
        .collect::<Result<_, _>>()?;
    let intrinsics = intrinsics_from_homographies(&hs)?;
    let poses: Vec<Isometry3<f64>> = hs
        .iter()
        .map(|h| pose_from_homography(h, &intrinsics).ok_or(CalibError::Degenerate("pose")))
        .collect::<Result<_, _>>()?;
    let pinhole = CameraModel {
        width,
        height,
        intrinsics,
        distortion: Distortion::default(),
    };
    // The linear radial step (eq. 13) is poorly conditioned when the closed-form intrinsics
    // have absorbed distortion: keep it only when it lowers the reprojection error.
    let radial = CameraModel {
        distortion: radial_from_views(views, &poses, &intrinsics),
        ..pinhole
    };
    let model =
        if rms_reprojection(&radial, views, &poses) < rms_reprojection(&pinhole, views, &poses) {
            radial
        } else {
            pinhole
        };
    Ok((model, poses))
}

/// RMS reprojection error (px, per coordinate) of planar views under a model and poses.
pub fn rms_reprojection(
    model: &CameraModel,
    views: &[PlanarView],
    poses: &[Isometry3<f64>],
) -> f64 {
    let (mut sq, mut n) = (0.0, 0usize);
    for (view, pose) in views.iter().zip(poses) {
        for c in &view.points {
            let p = pose * nalgebra::Point3::new(c.board.x, c.board.y, 0.0);
            match model.project(&p) {
                Some(q) => sq += (q - c.image).norm_squared(),
                None => sq += f64::INFINITY,
            }
            n += 2;
        }
    }
    (sq / n.max(1) as f64).sqrt()
}
