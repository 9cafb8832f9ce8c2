//! Projection of points given in another frame, with the Jacobians a bundle adjustment needs,
//! and the pose-increment convention.
//!
//! Poses are `T_device_source` (maps points in the source frame, e.g. a board, into the device
//! frame). With X in the source frame:
//!
//! - (P1) X_d = R X + t
//! - (P2) n = (X_d / Z_d, Y_d / Z_d), then n_d = distort(n) (D1, D2 in `distortion`)
//! - (P3) pixel = (fx x_d + cx, fy y_d + cy)
//!
//! A pose increment δ = (ω, τ) acts on the left: T ← (exp(ω), τ)·T, i.e. X_d ← exp(ω) X_d + τ,
//! with exp the axis-angle (Rodrigues) map. Jacobians, F = diag(fx, fy):
//!
//! - (J1) ∂n/∂X_d = [[1/Z_d, 0, −x/Z_d], [0, 1/Z_d, −y/Z_d]]
//! - (J2) ∂pixel/∂X_d = F · ∂n_d/∂n · ∂n/∂X_d
//! - (J3) ∂pixel/∂X = ∂pixel/∂X_d · R
//! - (J4) ∂pixel/∂(ω, τ) = ∂pixel/∂X_d · [−[X_d]× | I]   (at δ = 0)
//! - (J5) ∂pixel/∂(fx, fy, cx, cy) = [[x_d, 0, 1, 0], [0, y_d, 0, 1]],
//!   ∂pixel/∂(k1 … k6) = F · ∂n_d/∂k
//!
//! Undistortion of a pixel p solves distort(n) = m with m = F⁻¹(p − c); implicit
//! differentiation gives
//!
//! - (U1) ∂n/∂p = (∂n_d/∂n)⁻¹ F⁻¹
//! - (U2) ∂n/∂(fx, fy, cx, cy) = −(∂n_d/∂n)⁻¹ [[m_x/fx, 0, 1/fx, 0], [0, m_y/fy, 0, 1/fy]],
//!   ∂n/∂k = −(∂n_d/∂n)⁻¹ ∂n_d/∂k

use super::{CameraModel, LensJacobian};
use nalgebra::{
    Isometry3, Matrix2, Matrix2x3, Matrix2x6, Matrix3, Point2, Point3, Translation3,
    UnitQuaternion, Vector2, Vector3, Vector6,
};

/// A left increment of a pose: T ← (exp(ω), τ)·T, so a device-frame point moves as
/// X_d ← exp(ω)·X_d + τ. As a 6-vector it is (ω, τ), rotation first.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PoseIncrement {
    /// ω: axis-angle rotation (rad), about the target frame's origin.
    pub rotation: Vector3<f64>,
    /// τ: translation in the target frame (same unit as the pose).
    pub translation: Vector3<f64>,
}

impl PoseIncrement {
    /// From the solver's 6-vector (ω, τ).
    pub fn from_vector(v: &Vector6<f64>) -> PoseIncrement {
        PoseIncrement {
            rotation: v.fixed_rows::<3>(0).into_owned(),
            translation: v.fixed_rows::<3>(3).into_owned(),
        }
    }

    /// As the solver's 6-vector (ω, τ).
    pub fn to_vector(&self) -> Vector6<f64> {
        let (w, t) = (&self.rotation, &self.translation);
        Vector6::new(w.x, w.y, w.z, t.x, t.y, t.z)
    }

    /// The incremented pose (exp(ω), τ)·T.
    pub fn apply(&self, t: &Isometry3<f64>) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(self.translation),
            UnitQuaternion::from_scaled_axis(self.rotation),
        ) * t
    }
}

/// A projected point with its derivatives (J3–J5).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectionJacobians {
    /// The pixel (P3).
    pub pixel: Point2<f64>,
    /// ∂pixel/∂X, X in the source frame (J3).
    pub d_point: Matrix2x3<f64>,
    /// ∂pixel/∂(ω, τ) of a left pose increment (J4).
    pub d_pose: Matrix2x6<f64>,
    /// ∂pixel/∂(lens parameters), columns in `LensParam` order (J5).
    pub d_lens: LensJacobian,
}

/// The undistorted normalised point of a pixel with its derivatives (U1, U2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UndistortedPixel {
    /// n = (x/z, y/z) of the ray through the pixel.
    pub normalised: Vector2<f64>,
    /// ∂n/∂pixel (U1).
    pub d_pixel: Matrix2<f64>,
    /// ∂n/∂(lens parameters), columns in `LensParam` order (U2).
    pub d_lens: LensJacobian,
}

/// [v]×, the cross-product matrix.
fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

impl CameraModel {
    /// Project a point given in a source frame, with `t_device_source` (P1–P3); `None`
    /// behind the device.
    pub fn project_from(
        &self,
        t_device_source: &Isometry3<f64>,
        x: &Point3<f64>,
    ) -> Option<Point2<f64>> {
        self.project(&(t_device_source * x))
    }

    /// Project a point given in a source frame with its Jacobians with respect to the point,
    /// a left increment of `t_device_source` and the lens parameters (J1–J5); `None` behind
    /// the device. For a point in the device frame pass the identity pose.
    pub fn project_with_jacobians(
        &self,
        t_device_source: &Isometry3<f64>,
        x: &Point3<f64>,
    ) -> Option<ProjectionJacobians> {
        let xd = t_device_source * x; // P1
        if xd.z <= 0.0 {
            return None;
        }
        let iz = 1.0 / xd.z;
        let n = Vector2::new(xd.x * iz, xd.y * iz); // P2
        let dist = self.distortion.distort_with_jacobians(n);
        let k = &self.intrinsics;
        let md = dist.point;
        let pixel = Point2::new(k.fx * md.x + k.cx, k.fy * md.y + k.cy); // P3
        let dn_dxd = Matrix2x3::new(iz, 0.0, -n.x * iz, 0.0, iz, -n.y * iz); // J1
        let f = Matrix2::new(k.fx, 0.0, 0.0, k.fy);
        let d_device = f * dist.d_normalised * dn_dxd; // J2
        let d_point = d_device * t_device_source.rotation.to_rotation_matrix().matrix(); // J3
        let mut d_pose = Matrix2x6::zeros(); // J4
        d_pose
            .fixed_columns_mut::<3>(0)
            .copy_from(&(-d_device * skew(&xd.coords)));
        d_pose.fixed_columns_mut::<3>(3).copy_from(&d_device);
        let mut d_lens = LensJacobian::zeros(); // J5
        d_lens[(0, 0)] = md.x;
        d_lens[(1, 1)] = md.y;
        d_lens[(0, 2)] = 1.0;
        d_lens[(1, 3)] = 1.0;
        d_lens
            .fixed_columns_mut::<8>(4)
            .copy_from(&(f * dist.d_coefficients));
        Some(ProjectionJacobians {
            pixel,
            d_point,
            d_pose,
            d_lens,
        })
    }

    /// Undistorted normalised point of a pixel with its derivatives with respect to the pixel
    /// and the lens parameters (U1, U2); `None` where [`CameraModel::undistort`] fails.
    pub fn undistort_with_jacobians(&self, p: Point2<f64>) -> Option<UndistortedPixel> {
        let m = self.from_pixel(p);
        let n = self.distortion.undistort(m)?;
        let dist = self.distortion.distort_with_jacobians(n);
        let jinv = dist.d_normalised.try_inverse()?;
        let k = &self.intrinsics;
        let d_pixel = jinv * Matrix2::new(1.0 / k.fx, 0.0, 0.0, 1.0 / k.fy); // U1
        let mut dm = LensJacobian::zeros(); // ∂(distort(n) − m)/∂lens at fixed n
        dm[(0, 0)] = m.x / k.fx;
        dm[(1, 1)] = m.y / k.fy;
        dm[(0, 2)] = 1.0 / k.fx;
        dm[(1, 3)] = 1.0 / k.fy;
        dm.fixed_columns_mut::<8>(4).copy_from(&dist.d_coefficients);
        Some(UndistortedPixel {
            normalised: n,
            d_pixel,
            d_lens: -jinv * dm, // U2
        })
    }
}
