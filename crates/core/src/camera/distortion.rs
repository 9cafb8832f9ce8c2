//! OpenCV's radial-tangential lens distortion on normalised image points, its derivatives
//! and its inverse.
//!
//! With n = (x, y) = (X/Z, Y/Z) and r² = x² + y²:
//!
//! - (D1) s = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
//! - (D2) x_d = x s + 2 p1 x y + p2 (r² + 2x²),  y_d = y s + p1 (r² + 2y²) + 2 p2 x y
//!
//! (OpenCV's `projectPoints` without thin-prism and tilt terms.) Derivatives, with
//! s' = ds/d(r²) = (a' b − a b') / b², a, b the numerator and denominator of (D1),
//! a' = k1 + 2 k2 r² + 3 k3 r⁴, b' = k4 + 2 k5 r² + 3 k6 r⁴:
//!
//! - (D3) ∂x_d/∂x = s + 2x² s' + 2 p1 y + 6 p2 x,  ∂y_d/∂y = s + 2y² s' + 6 p1 y + 2 p2 x,
//!   ∂x_d/∂y = ∂y_d/∂x = 2xy s' + 2 p1 x + 2 p2 y
//! - (D4) ∂n_d/∂(k1, k2, k3) = n (r², r⁴, r⁶) / b,  ∂n_d/∂(k4, k5, k6) = −n s (r², r⁴, r⁶) / b,
//!   ∂n_d/∂p1 = (2xy, r² + 2y²),  ∂n_d/∂p2 = (r² + 2x², 2xy)
//!
//! Undistortion of n_d: (D5) start n₀ = (n_d − t(n_d)) / s(n_d), t the tangential terms of
//! (D2) (one step of OpenCV's fixed-point iteration); (D6) Newton
//! n ← n − (∂n_d/∂n)⁻¹ (distort(n) − n_d).

use nalgebra::{Matrix2, SMatrix, Vector2};
use serde::{Deserialize, Serialize};

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

/// Derivative of the distorted normalised point with respect to the eight coefficients, in
/// OpenCV's order (k1, k2, p1, p2, k3, k4, k5, k6).
pub type CoefficientJacobian = SMatrix<f64, 2, 8>;

/// A distorted point with its derivatives (what one evaluation of (D1)–(D4) gives).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DistortedPoint {
    /// The distorted normalised point n_d (D2).
    pub point: Vector2<f64>,
    /// ∂n_d/∂n (D3).
    pub d_normalised: Matrix2<f64>,
    /// ∂n_d/∂(k1, k2, p1, p2, k3, k4, k5, k6) (D4).
    pub d_coefficients: CoefficientJacobian,
}

/// Newton iterations [`Distortion::undistort`] allows before it gives up. From its start it
/// took 2–4 (mean 2.0–3.2) on every pixel of the four OpenCV test lenses, k1 = −0.3 included;
/// more are needed only close to where the model folds over.
const MAX_NEWTON_STEPS: usize = 20;

/// Newton stops once a step is below this (normalised units); the quadratic convergence
/// then leaves an error of order (this)², far below rounding.
const NEWTON_STEP_TOLERANCE: f64 = 1e-12;

/// Radial factor s (D1) at r², with 1/b (one division, as OpenCV computes it).
#[inline(always)]
fn radial(d: &Distortion, r2: f64) -> (f64, f64) {
    let a = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3));
    let inv_b = 1.0 / (1.0 + r2 * (d.k4 + r2 * (d.k5 + r2 * d.k6)));
    (a * inv_b, inv_b)
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

    /// Distort a normalised image point (x/z, y/z) (D1, D2).
    #[inline]
    pub fn distort(&self, n: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let (s, _) = radial(self, r2);
        Vector2::new(
            x * s + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * s + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// ∂n_d/∂n, the 2×2 derivative of [`Distortion::distort`] at a normalised point (D3).
    #[inline]
    pub fn jacobian(&self, n: Vector2<f64>) -> Matrix2<f64> {
        self.distort_with_jacobian(n).1
    }

    /// Distorted point and ∂n_d/∂n (D2, D3) in one evaluation.
    #[inline(always)]
    fn distort_with_jacobian(&self, n: Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>, f64) {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let (s, inv_b) = radial(self, r2);
        let da = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3);
        let db = self.k4 + r2 * (2.0 * self.k5 + 3.0 * r2 * self.k6);
        let ds = (da - s * db) * inv_b; // s' = (a' b − a b')/b² = (a' − s b')/b
        let (p1, p2) = (self.p1, self.p2);
        let point = Vector2::new(
            x * s + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * s + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        );
        let off = 2.0 * x * y * ds + 2.0 * p1 * x + 2.0 * p2 * y;
        let jac = Matrix2::new(
            s + 2.0 * x * x * ds + 2.0 * p1 * y + 6.0 * p2 * x,
            off,
            off,
            s + 2.0 * y * y * ds + 6.0 * p1 * y + 2.0 * p2 * x,
        );
        (point, jac, s)
    }

    /// ∂n_d/∂(k1, k2, p1, p2, k3, k4, k5, k6) at a normalised point (D4).
    pub fn coefficient_jacobian(&self, n: Vector2<f64>) -> CoefficientJacobian {
        self.distort_with_jacobians(n).d_coefficients
    }

    /// The distorted point with both its derivatives (D2–D4).
    pub fn distort_with_jacobians(&self, n: Vector2<f64>) -> DistortedPoint {
        let (point, d_normalised, s) = self.distort_with_jacobian(n);
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let (r4, r6) = (r2 * r2, r2 * r2 * r2);
        let inv_b = radial(self, r2).1;
        let (nb, nsb) = (n * inv_b, -n * (s * inv_b));
        let xy2 = 2.0 * x * y;
        let mut d_coefficients = CoefficientJacobian::zeros();
        for (col, v) in [
            nb * r2,
            nb * r4,
            Vector2::new(xy2, r2 + 2.0 * y * y),
            Vector2::new(r2 + 2.0 * x * x, xy2),
            nb * r6,
            nsb * r2,
            nsb * r4,
            nsb * r6,
        ]
        .into_iter()
        .enumerate()
        {
            d_coefficients.set_column(col, &v);
        }
        DistortedPoint {
            point,
            d_normalised,
            d_coefficients,
        }
    }

    /// Whether the lens map is locally one-to-one and orientation-preserving at a normalised
    /// point: det ∂n_d/∂n > 0 and radial factor s > 0 (D1). Beyond the radius where a strong
    /// barrel model folds back this fails, so points there (which OpenCV still projects,
    /// often back into the image as "ghosts") can be recognised.
    pub fn is_invertible_at(&self, n: Vector2<f64>) -> bool {
        let (_, j, s) = self.distort_with_jacobian(n);
        s > 0.0 && j.determinant() > 0.0
    }

    /// Invert [`Distortion::distort`]: the normalised point n with distort(n) = d.
    ///
    /// Starts from one step of OpenCV's fixed-point iteration, n₀ = (d − t(d)) / s(d) (t the
    /// tangential part of D2), then Newton steps with the analytic ∂n_d/∂n (D3); no allocation.
    /// `None` when it does not converge or the solution lies where the model is not
    /// invertible ([`Distortion::is_invertible_at`]), i.e. beyond the fold.
    #[inline]
    pub fn undistort(&self, d: Vector2<f64>) -> Option<Vector2<f64>> {
        let (x, y) = (d.x, d.y);
        let r2 = x * x + y * y;
        let (s0, _) = radial(self, r2);
        let t0 = Vector2::new(
            2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        );
        let mut n = if s0 > 0.0 { (d - t0) / s0 } else { d }; // D5
        let mut previous = f64::INFINITY;
        for _ in 0..MAX_NEWTON_STEPS {
            let (f, j, s) = self.distort_with_jacobian(n);
            let r = f - d;
            let det = j.m11 * j.m22 - j.m12 * j.m21;
            if !det.is_finite() || det == 0.0 {
                return None;
            }
            let step = Vector2::new(j.m22 * r.x - j.m12 * r.y, j.m11 * r.y - j.m21 * r.x) / det;
            n -= step; // D6
            let size = step.x.abs().max(step.y.abs());
            // Quadratic convergence: the error left is ≈ C·size² with C ≈ size/previous², so
            // once two steps are small, size³ ≤ 1e-17·previous² leaves < 1e-17.
            if size <= NEWTON_STEP_TOLERANCE
                || (previous <= 1e-3 && size * size * size <= 1e-17 * previous * previous)
            {
                // The test of `is_invertible_at`, at a point ≤ 1e-7 away from n.
                return (s > 0.0 && det > 0.0).then_some(n);
            }
            previous = size;
        }
        None
    }
}
