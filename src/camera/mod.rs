//! Lens model shared by cameras and projectors (DESIGN.md §2): a pinhole with OpenCV's
//! radial-tangential distortion (k1, k2, p1, p2, k3 and the optional rational k4–k6), in
//! OpenCV's parameter order and meaning so exported models drop into OpenCV code.
//!
//! Takes points in the device frame (x right, y down, z forward) and gives pixels with
//! (0, 0) at the centre of the top-left pixel; the inverse gives rays.

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

/// OpenCV distortion coefficients (k1, k2, p1, p2, k3, k4, k5, k6).
///
/// With k4 = k5 = k6 = 0 this is the 5-parameter model; non-zero k4–k6 switch on the rational
/// denominator (1 + k4 r² + k5 r⁴ + k6 r⁶).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Distortion {
    /// Radial r².
    pub k1: f64,
    /// Radial r⁴.
    pub k2: f64,
    /// Tangential.
    pub p1: f64,
    /// Tangential.
    pub p2: f64,
    /// Radial r⁶.
    pub k3: f64,
    /// Rational denominator r².
    #[serde(default)]
    pub k4: f64,
    /// Rational denominator r⁴.
    #[serde(default)]
    pub k5: f64,
    /// Rational denominator r⁶.
    #[serde(default)]
    pub k6: f64,
}

impl Distortion {
    /// From OpenCV's coefficient vector (4, 5 or 8 entries).
    pub fn from_opencv(c: &[f64]) -> Option<Distortion> {
        let g = |i: usize| c.get(i).copied().unwrap_or(0.0);
        matches!(c.len(), 4 | 5 | 8).then(|| Distortion {
            k1: g(0),
            k2: g(1),
            p1: g(2),
            p2: g(3),
            k3: g(4),
            k4: g(5),
            k5: g(6),
            k6: g(7),
        })
    }

    /// OpenCV's coefficient vector: 5 entries, or 8 when the rational part is used.
    pub fn to_opencv(&self) -> Vec<f64> {
        let mut v = vec![self.k1, self.k2, self.p1, self.p2, self.k3];
        if self.is_rational() {
            v.extend([self.k4, self.k5, self.k6]);
        }
        v
    }

    /// Whether any of k4–k6 is non-zero.
    pub fn is_rational(&self) -> bool {
        self.k4 != 0.0 || self.k5 != 0.0 || self.k6 != 0.0
    }

    /// Distort a normalised image point (x/z, y/z).
    pub fn distort(&self, n: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let r4 = r2 * r2;
        let r6 = r4 * r2;
        let radial = (1.0 + self.k1 * r2 + self.k2 * r4 + self.k3 * r6)
            / (1.0 + self.k4 * r2 + self.k5 * r4 + self.k6 * r6);
        Vector2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Invert [`Distortion::distort`] by fixed-point iteration refined with Newton steps;
    /// `None` when it does not converge (the point lies outside the model's valid region).
    pub fn undistort(&self, d: Vector2<f64>) -> Option<Vector2<f64>> {
        let mut n = d;
        for _ in 0..50 {
            let f = self.distort(n) - d;
            if f.norm() < 1e-14 {
                return Some(n);
            }
            // Newton step with a finite-difference Jacobian of the distortion.
            let h = 1e-7;
            let jx = (self.distort(n + Vector2::new(h, 0.0)) - self.distort(n)) / h;
            let jy = (self.distort(n + Vector2::new(0.0, h)) - self.distort(n)) / h;
            let det = jx.x * jy.y - jy.x * jx.y;
            if det.abs() < 1e-12 {
                return None;
            }
            let step = Vector2::new(
                (jy.y * f.x - jy.x * f.y) / det,
                (-jx.y * f.x + jx.x * f.y) / det,
            );
            n -= step;
        }
        ((self.distort(n) - d).norm() < 1e-9).then_some(n)
    }
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

impl CameraModel {
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
        (p.z > 0.0)
            .then(|| self.to_pixel(self.distortion.distort(Vector2::new(p.x / p.z, p.y / p.z))))
    }

    /// Undistorted normalised coordinates (x/z, y/z) of the ray through a pixel.
    pub fn undistort(&self, p: Point2<f64>) -> Option<Vector2<f64>> {
        self.distortion.undistort(self.from_pixel(p))
    }

    /// Ray through a pixel in the device frame, with z = 1.
    pub fn ray(&self, p: Point2<f64>) -> Option<Vector3<f64>> {
        self.undistort(p).map(|n| Vector3::new(n.x, n.y, 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn undistort_inverts_distort() {
        let d = Distortion {
            k1: -0.3,
            k2: 0.1,
            p1: 0.001,
            p2: -0.002,
            k3: -0.01,
            ..Default::default()
        };
        for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.5, 0.4), (0.6, 0.1)] {
            let n = Vector2::new(x, y);
            let back = d.undistort(d.distort(n)).unwrap();
            assert!((back - n).norm() < 1e-12, "{n:?} -> {back:?}");
        }
    }
}
