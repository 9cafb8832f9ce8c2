//! Lens model shared by cameras and projectors (docs/design.md §2): a pinhole with OpenCV's
//! radial-tangential distortion (k1, k2, p1, p2, k3 and the optional rational k4–k6), in
//! OpenCV's parameter order and meaning so exported models drop into OpenCV code.
//!
//! Takes points in the device frame (x right, y down, z forward), or in another frame with a
//! pose `T_device_source`, and gives pixels with (0, 0) at the centre of the top-left pixel,
//! with analytic Jacobians with respect to the point, a left pose increment (ω, τ) and the
//! lens parameters ([`LensParam`] order); the inverse gives rays (Newton undistortion).
//! Equations (D1)–(D4) are listed in `distortion.rs`, (P1)–(P3), (J1)–(J5) and (U1)–(U2) in
//! `projection.rs`. Tests compare against OpenCV's `projectPoints` and `undistortPoints`
//! (vectors in `tests/data/camera/`, made by `make_opencv_vectors.py` there).

mod distortion;
mod params;
mod projection;
#[cfg(test)]
mod tests;

pub use distortion::{CoefficientJacobian, DistortedPoint, Distortion};
pub use params::{LensJacobian, LensParam, LensParams, LensVector, LENS_PARAM_COUNT};
pub use projection::{PoseIncrement, ProjectionJacobians, UndistortedPixel};

use crate::invalid::ValidationError;
use nalgebra::{Point2, Point3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Pinhole intrinsics: focal lengths and principal point in pixels (zero skew).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Intrinsics {
    /// Focal length along x (px).
    pub fx: f64,
    /// Focal length along y (px).
    pub fy: f64,
    /// Principal point x (px).
    pub cx: f64,
    /// Principal point y (px).
    pub cy: f64,
}

/// A camera or projector: image size, intrinsics and distortion.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraModel {
    /// Image width (px).
    pub width: u32,
    /// Image height (px).
    pub height: u32,
    /// Pinhole part.
    pub intrinsics: Intrinsics,
    /// Lens distortion.
    pub distortion: Distortion,
}

impl Intrinsics {
    /// The first problem of intrinsics read from a file: the field and what is wrong; focal
    /// lengths in [[`MIN_FOCAL_PX`](crate::limits::MIN_FOCAL_PX),
    /// [`MAX_FOCAL_PX`](crate::limits::MAX_FOCAL_PX)], the principal point within
    /// [`MAX_PRINCIPAL_POINT_PX`](crate::limits::MAX_PRINCIPAL_POINT_PX).
    pub fn check(&self) -> Result<(), ValidationError> {
        use crate::limits::{MAX_FOCAL_PX, MAX_PRINCIPAL_POINT_PX, MIN_FOCAL_PX};
        for (field, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && (MIN_FOCAL_PX..=MAX_FOCAL_PX).contains(&v)) {
                return Err(ValidationError::new(
                    field,
                    format!(
                        "{} is not a focal length in [{MIN_FOCAL_PX}, {MAX_FOCAL_PX:e}] px",
                        crate::limits::shown(v)
                    ),
                ));
            }
        }
        for (field, v) in [("cx", self.cx), ("cy", self.cy)] {
            crate::limits::within(v, -MAX_PRINCIPAL_POINT_PX, MAX_PRINCIPAL_POINT_PX)
                .map_err(|m| m.at(field))?;
        }
        Ok(())
    }
}

impl Distortion {
    /// The first problem of coefficients read from a file: the coefficient and what is wrong;
    /// every coefficient must be finite and within
    /// [`MAX_DISTORTION`](crate::limits::MAX_DISTORTION).
    pub fn check(&self) -> Result<(), ValidationError> {
        let d = self;
        let named = [
            ("k1", d.k1),
            ("k2", d.k2),
            ("p1", d.p1),
            ("p2", d.p2),
            ("k3", d.k3),
            ("k4", d.k4),
            ("k5", d.k5),
            ("k6", d.k6),
        ];
        let most = crate::limits::MAX_DISTORTION;
        for (field, v) in named {
            crate::limits::within(v, -most, most).map_err(|m| m.at(field))?;
        }
        Ok(())
    }
}

impl CameraModel {
    /// The first problem of a model read from a file: the dotted field and what is wrong. The
    /// image size is within [`crate::limits::image_size`], the intrinsics and distortion as
    /// [`Intrinsics::check`] and [`Distortion::check`] require.
    pub fn check(&self) -> Result<(), ValidationError> {
        crate::limits::image_size(self.width, self.height).map_err(|m| m.at("width"))?;
        self.intrinsics
            .check()
            .map_err(|e| e.map_at(|f| format!("intrinsics.{f}")))?;
        self.distortion
            .check()
            .map_err(|e| e.map_at(|f| format!("distortion.{f}")))
    }

    /// Pixel of a normalised (already distorted) image point.
    pub fn to_pixel(&self, d: Vector2<f64>) -> Point2<f64> {
        let k = &self.intrinsics;
        Point2::new(k.fx * d.x + k.cx, k.fy * d.y + k.cy)
    }

    /// Normalised (distorted) image point of a pixel.
    pub fn from_pixel(&self, p: Point2<f64>) -> Vector2<f64> {
        let k = &self.intrinsics;
        Vector2::new((p.x - k.cx) / k.fx, (p.y - k.cy) / k.fy)
    }

    /// Project a point in the device frame; `None` behind the device (z ≤ 0).
    pub fn project(&self, p: &Point3<f64>) -> Option<Point2<f64>> {
        // Multiplying by 1/z as OpenCV does keeps this bit-identical to
        // `project_with_jacobians`.
        (p.z > 0.0).then(|| {
            let iz = 1.0 / p.z;
            self.to_pixel(self.distortion.distort(Vector2::new(p.x * iz, p.y * iz)))
        })
    }

    /// Undistorted normalised coordinates (x/z, y/z) of the ray through a pixel.
    pub fn undistort(&self, p: Point2<f64>) -> Option<Vector2<f64>> {
        self.distortion.undistort(self.from_pixel(p))
    }

    /// Ray through a pixel in the device frame, with z = 1.
    pub fn ray(&self, p: Point2<f64>) -> Option<Vector3<f64>> {
        self.undistort(p).map(|n| Vector3::new(n.x, n.y, 1.0))
    }

    /// All twelve lens parameters [fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6]
    /// ([`LensParam`] order).
    pub fn lens_vector(&self) -> LensVector {
        let (k, d) = (&self.intrinsics, &self.distortion);
        LensVector::from([
            k.fx, k.fy, k.cx, k.cy, d.k1, d.k2, d.p1, d.p2, d.k3, d.k4, d.k5, d.k6,
        ])
    }

    /// Set all twelve lens parameters from a vector in [`LensParam`] order.
    pub fn set_lens_vector(&mut self, v: &LensVector) {
        self.intrinsics = Intrinsics {
            fx: v[0],
            fy: v[1],
            cx: v[2],
            cy: v[3],
        };
        self.distortion = Distortion {
            k1: v[4],
            k2: v[5],
            p1: v[6],
            p2: v[7],
            k3: v[8],
            k4: v[9],
            k5: v[10],
            k6: v[11],
        };
    }
}
