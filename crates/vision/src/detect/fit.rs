//! Direct least-squares ellipse fitting (Fitzgibbon, Pilu & Fisher 1999, in the numerically
//! stable form of Halíř & Flusser 1998) and conic ↔ ellipse conversion.

use super::Ellipse;
use nalgebra::{Matrix3, Point2, Vector2, Vector3};

/// A conic A x² + B xy + C y² + D x + E y + F = 0.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Conic {
    /// Coefficients (A, B, C, D, E, F).
    pub(crate) c: [f64; 6],
}

impl Conic {
    /// Value of the conic polynomial at p.
    #[inline]
    pub(crate) fn value(&self, p: Point2<f64>) -> f64 {
        let [a, b, c, d, e, f] = self.c;
        a * p.x * p.x + b * p.x * p.y + c * p.y * p.y + d * p.x + e * p.y + f
    }

    /// Sampson (first-order geometric) distance of p from the conic (px).
    #[inline]
    pub(crate) fn sampson_distance(&self, p: Point2<f64>) -> f64 {
        let [a, b, c, d, e, _] = self.c;
        let g = Vector2::new(2.0 * a * p.x + b * p.y + d, b * p.x + 2.0 * c * p.y + e);
        self.value(p).abs() / g.norm().max(1e-300)
    }

    /// The ellipse this conic describes, if it is a real ellipse.
    pub(crate) fn to_ellipse(self) -> Option<Ellipse> {
        let [a, b, c, d, e, f] = self.c;
        let det = 4.0 * a * c - b * b;
        if det.abs() < 1e-300 {
            return None;
        }
        // Centre: ∇ = 0, i.e. [2A B; B 2C]·x = −[D; E].
        let x0 = (b * e - 2.0 * c * d) / det;
        let y0 = (b * d - 2.0 * a * e) / det;
        let f0 = f + 0.5 * (d * x0 + e * y0);
        // (p − x0)ᵀ Q (p − x0) = −f0 with Q = [A B/2; B/2 C].
        let (tr, df) = (a + c, ((a - c) * (a - c) + b * b).sqrt());
        let (q1, q2) = (0.5 * (tr - df), 0.5 * (tr + df));
        let (s1, s2) = (-f0 / q1, -f0 / q2);
        if !(s1 > 0.0 && s2 > 0.0 && s1.is_finite() && s2.is_finite()) {
            return None;
        }
        // The major axis is the eigenvector of the smaller eigenvalue (larger −f0/q).
        let (major, minor, q_major) = if s1 >= s2 { (s1, s2, q1) } else { (s2, s1, q2) };
        // Eigenvector of Q for q_major: (B/2, q − A) or (q − C, B/2).
        let (vx, vy) =
            if (q_major - a).abs() + (b * 0.5).abs() > (q_major - c).abs() + (b * 0.5).abs() {
                (0.5 * b, q_major - a)
            } else {
                (q_major - c, 0.5 * b)
            };
        let angle = if vx == 0.0 && vy == 0.0 {
            0.0
        } else {
            vy.atan2(vx)
        };
        Some(Ellipse {
            center: Point2::new(x0, y0),
            a: major.sqrt(),
            b: minor.sqrt(),
            angle,
        })
    }

    /// The conic of an ellipse.
    pub(crate) fn from_ellipse(e: &Ellipse) -> Conic {
        let (s, c) = e.angle.sin_cos();
        let (ia, ib) = (1.0 / (e.a * e.a), 1.0 / (e.b * e.b));
        let qa = c * c * ia + s * s * ib;
        let qb = 2.0 * c * s * (ia - ib);
        let qc = s * s * ia + c * c * ib;
        let (x0, y0) = (e.center.x, e.center.y);
        Conic {
            c: [
                qa,
                qb,
                qc,
                -2.0 * qa * x0 - qb * y0,
                -qb * x0 - 2.0 * qc * y0,
                qa * x0 * x0 + qb * x0 * y0 + qc * y0 * y0 - 1.0,
            ],
        }
    }
}

/// Iterations the eigenvalue solver of [`fit_ellipse`] may take (it converges in tens).
const MAX_SCHUR_ITERATIONS: usize = 10_000;

/// Fitzgibbon's direct ellipse fit (Halíř–Flusser form) to ≥ 6 points; coordinates are
/// centred and scaled first for conditioning. `None` when no ellipse fits.
pub(crate) fn fit_ellipse(points: &[Point2<f64>]) -> Option<Conic> {
    let n = points.len();
    if n < 6 {
        return None;
    }
    let mean = points.iter().fold(Vector2::zeros(), |s, p| s + p.coords) / n as f64;
    let spread = (points
        .iter()
        .map(|p| (p.coords - mean).norm_squared())
        .sum::<f64>()
        / n as f64)
        .sqrt();
    // Not finite (a NaN pixel of a float image) or all points equal: no ellipse.
    if !(spread.is_finite() && spread > 0.0) {
        return None;
    }
    let k = 1.0 / spread;
    // Scatter blocks: D1 = [x², xy, y²], D2 = [x, y, 1].
    let (mut s1, mut s2, mut s3) = (
        Matrix3::<f64>::zeros(),
        Matrix3::<f64>::zeros(),
        Matrix3::<f64>::zeros(),
    );
    for p in points {
        let (x, y) = ((p.x - mean.x) * k, (p.y - mean.y) * k);
        let d1 = Vector3::new(x * x, x * y, y * y);
        let d2 = Vector3::new(x, y, 1.0);
        s1 += d1 * d1.transpose();
        s2 += d1 * d2.transpose();
        s3 += d2 * d2.transpose();
    }
    // T = −S3⁻¹ S2ᵀ; reduced scatter M = S1 + S2 T; M' = C1⁻¹ M (Halíř–Flusser Eq. 29).
    let t = -s3.try_inverse()? * s2.transpose();
    let m = s1 + s2 * t;
    let mp = Matrix3::from_rows(&[(m.row(2) * 0.5), (-m.row(1)), (m.row(0) * 0.5)]);
    // Bounded iterations: a Schur decomposition that does not converge ends, unfitted.
    let eig = nalgebra::linalg::Schur::try_new(mp, f64::EPSILON, MAX_SCHUR_ITERATIONS)?
        .complex_eigenvalues();
    let mut best: Option<(f64, Vector3<f64>)> = None;
    for l in eig.iter() {
        if l.im.abs() > 1e-9 * (1.0 + l.re.abs()) {
            continue;
        }
        let Some(v) = null_vector(&(mp - Matrix3::identity() * l.re)) else {
            continue;
        };
        let cond = 4.0 * v[0] * v[2] - v[1] * v[1];
        if cond > 0.0 && best.is_none_or(|(b, _)| cond / v.norm_squared() > b) {
            best = Some((cond / v.norm_squared(), v));
        }
    }
    let a1 = best?.1;
    let a2 = t * a1;
    // Back from normalised coordinates u = k (p − m).
    let [a, b, c] = [a1[0], a1[1], a1[2]];
    let [d, e, f] = [a2[0], a2[1], a2[2]];
    let (mx, my) = (mean.x, mean.y);
    let (a, b, c, d, e) = (a * k * k, b * k * k, c * k * k, d * k, e * k);
    Some(Conic {
        c: [
            a,
            b,
            c,
            d - 2.0 * a * mx - b * my,
            e - b * mx - 2.0 * c * my,
            a * mx * mx + b * mx * my + c * my * my - d * mx - e * my + f,
        ],
    })
}

/// A unit vector v with M v ≈ 0 for a rank-2 3×3 M: the largest cross product of two rows.
fn null_vector(m: &Matrix3<f64>) -> Option<Vector3<f64>> {
    let r = [
        m.row(0).transpose(),
        m.row(1).transpose(),
        m.row(2).transpose(),
    ];
    let cands = [r[0].cross(&r[1]), r[0].cross(&r[2]), r[1].cross(&r[2])];
    let v = cands
        .into_iter()
        .max_by(|a, b| a.norm_squared().total_cmp(&b.norm_squared()))?;
    let n = v.norm();
    (n > 0.0).then(|| v / n)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points_on(e: &Ellipse, n: usize) -> Vec<Point2<f64>> {
        let (s, c) = e.angle.sin_cos();
        (0..n)
            .map(|i| {
                let t = 2.0 * std::f64::consts::PI * i as f64 / n as f64 + 0.1;
                let (u, v) = (e.a * t.cos(), e.b * t.sin());
                Point2::new(e.center.x + c * u - s * v, e.center.y + s * u + c * v)
            })
            .collect()
    }

    #[test]
    fn fits_exact_points_exactly() {
        for e in [
            Ellipse {
                center: Point2::new(812.3, 91.7),
                a: 12.0,
                b: 3.1,
                angle: 0.7,
            },
            Ellipse {
                center: Point2::new(3.3, 2000.1),
                a: 40.0,
                b: 39.0,
                angle: -2.0,
            },
            Ellipse {
                center: Point2::new(0.0, 0.0),
                a: 4.0,
                b: 4.0,
                angle: 0.0,
            },
        ] {
            let conic = fit_ellipse(&points_on(&e, 30)).expect("fit");
            let got = conic.to_ellipse().expect("ellipse");
            assert!((got.center - e.center).norm() < 1e-7, "{got:?} vs {e:?}");
            assert!((got.a - e.a).abs() < 1e-7 && (got.b - e.b).abs() < 1e-7);
            if e.a - e.b > 1e-3 {
                let da = (got.angle - e.angle).rem_euclid(std::f64::consts::PI);
                assert!(da.min(std::f64::consts::PI - da) < 1e-7);
            }
            // Conversion round trip and distances of points on the curve.
            let back = Conic::from_ellipse(&got).to_ellipse().unwrap();
            assert!((back.center - got.center).norm() < 1e-9 && (back.a - got.a).abs() < 1e-9);
            assert!(points_on(&e, 7)
                .iter()
                .all(|&p| conic.sampson_distance(p) < 1e-7));
        }
    }

    #[test]
    fn sampson_distance_is_the_radial_gap_on_a_circle() {
        let e = Ellipse {
            center: Point2::new(5.0, -2.0),
            a: 10.0,
            b: 10.0,
            angle: 0.0,
        };
        let c = Conic::from_ellipse(&e);
        // For a circle Q = (r² − R²)/R², |∇Q| = 2r/R²: Sampson = (r² − R²)/(2r) ≈ r − R.
        let d = c.sampson_distance(Point2::new(15.1, -2.0));
        assert!((d - (10.1f64 * 10.1 - 100.0) / 20.2).abs() < 1e-12);
        assert!(fit_ellipse(&[Point2::new(0.0, 0.0); 8]).is_none());
    }
}
