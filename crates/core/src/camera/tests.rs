//! Camera model tests: analytic Jacobians against central finite differences, projection and
//! undistortion against OpenCV reference vectors, conventions and serde.

use super::*;
use nalgebra::{Isometry3, Matrix2, SMatrix, Translation3, UnitQuaternion, Vector2, Vector6};
use serde::Deserialize;

/// 5-coefficient model with strong barrel distortion (k1 = −0.3), as in OpenCV vectors'
/// "strong_barrel".
fn strong_barrel() -> CameraModel {
    CameraModel {
        width: 1280,
        height: 1024,
        intrinsics: Intrinsics {
            fx: 900.0,
            fy: 899.0,
            cx: 641.2,
            cy: 509.6,
        },
        distortion: Distortion::from_opencv(&[-0.3, 0.1, 0.001, -0.002, -0.01]).unwrap(),
    }
}

/// 8-coefficient rational model, as in OpenCV vectors' "rational8".
fn rational8() -> CameraModel {
    CameraModel {
        width: 2448,
        height: 2048,
        intrinsics: Intrinsics {
            fx: 2400.0,
            fy: 2395.0,
            cx: 1230.4,
            cy: 1019.8,
        },
        distortion: Distortion::from_opencv(&[0.8, -0.2, 0.0004, -0.0006, 0.05, 0.95, 0.1, 0.02])
            .unwrap(),
    }
}

/// A board-to-device pose about 1.5 m away, rotated about all three axes.
fn board_pose() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(60.0, -40.0, 1500.0),
        UnitQuaternion::from_scaled_axis(Vector3::new(0.3, -0.5, 0.2)),
    )
}

/// Pixels on a 5×5 grid through the image corners (0, 0) … (w−1, h−1).
fn grid_pixels(m: &CameraModel, nu: usize, nv: usize) -> Vec<Point2<f64>> {
    let (w, h) = (m.width as f64 - 1.0, m.height as f64 - 1.0);
    (0..nv)
        .flat_map(|j| {
            (0..nu).map(move |i| {
                Point2::new(
                    w * i as f64 / (nu - 1) as f64,
                    h * j as f64 / (nv - 1) as f64,
                )
            })
        })
        .collect()
}

/// Source-frame points that `t_device_source` puts on the rays of a 5×5 pixel grid through
/// the image corners, at depths 500–3000 mm.
fn points_across_image(m: &CameraModel, t_device_source: &Isometry3<f64>) -> Vec<Point3<f64>> {
    grid_pixels(m, 5, 5)
        .into_iter()
        .enumerate()
        .map(|(i, p)| {
            let depth = 500.0 + 2500.0 * ((i * 7) % 25) as f64 / 24.0;
            let xd = Point3::from(m.ray(p).expect("grid pixel undistorts") * depth);
            t_device_source.inverse_transform_point(&xd)
        })
        .collect()
}

/// Central differences, column i = (g(i, +h_i) − g(i, −h_i)) / 2h_i.
fn central_differences<const C: usize>(
    h: [f64; C],
    g: impl Fn(usize, f64) -> Vector2<f64>,
) -> SMatrix<f64, 2, C> {
    let mut j = SMatrix::<f64, 2, C>::zeros();
    for (i, &hi) in h.iter().enumerate() {
        j.set_column(i, &((g(i, hi) - g(i, -hi)) / (2.0 * hi)));
    }
    j
}

/// Per column: |analytic − fd| ≤ abs + rel·max|analytic column|.
fn assert_columns_close<const C: usize>(
    what: &str,
    analytic: &SMatrix<f64, 2, C>,
    fd: &SMatrix<f64, 2, C>,
    abs: f64,
    rel: f64,
) {
    for c in 0..C {
        let scale = analytic.column(c).amax();
        let err = (analytic.column(c) - fd.column(c)).amax();
        assert!(
            err <= abs + rel * scale,
            "{what}, column {c}: analytic {:?} vs finite differences {:?} (error {err:e})",
            analytic.column(c),
            fd.column(c)
        );
    }
}

#[test]
fn distortion_jacobians_match_finite_differences() {
    // n and n_d are O(1); with h = 1e-6 the rounding error of a central difference is
    // ≈ 1e-16/1e-6 = 1e-10 and the truncation h²/6·|n_d'''| ≈ 1e-12·O(10): 1e-8 leaves
    // a margin of 100 while a wrong term (an O(0.01–1) change) fails.
    for m in [strong_barrel(), rational8()] {
        let d = m.distortion;
        for p in grid_pixels(&m, 7, 6) {
            let n = m.undistort(p).unwrap();
            let fd = central_differences([1e-6; 2], |i, h| {
                let mut nh = n;
                nh[i] += h;
                d.distort(nh)
            });
            assert_columns_close("∂n_d/∂n", &d.jacobian(n), &fd, 1e-8, 1e-8);
            let fd = central_differences([1e-6; 8], |i, h| {
                let mut c = [d.k1, d.k2, d.p1, d.p2, d.k3, d.k4, d.k5, d.k6];
                c[i] += h;
                Distortion::from_opencv(&c).unwrap().distort(n)
            });
            assert_columns_close("∂n_d/∂k", &d.coefficient_jacobian(n), &fd, 1e-8, 1e-8);
            let both = d.distort_with_jacobians(n);
            assert_eq!(both.point, d.distort(n));
        }
    }
}

#[test]
fn projection_jacobians_match_finite_differences() {
    // Pixels are ≤ 3000 px, so a central difference carries a rounding error ≈ 3000·2e-16/h:
    // 6e-10 px/mm for h = 1e-3 mm (point, τ, fx…cy in px) and 6e-7 for h = 1e-6 (ω in rad,
    // distortion coefficients). Truncation (h²/6·|g'''|) is below 1e-9 in all of them (the
    // pixel is linear in fx…cy, k1–k3, p1, p2 and τ). Tolerance 1e-5 absolute + 1e-7 of the
    // column: a wrong derivative misses by O(column) ≥ 1e-3 px per unit at the corners.
    for m in [strong_barrel(), rational8()] {
        let t = board_pose();
        for x in points_across_image(&m, &t) {
            let pj = m.project_with_jacobians(&t, &x).expect("in front");
            assert_eq!(pj.pixel, m.project_from(&t, &x).unwrap());
            let fd = central_differences([1e-3; 3], |i, h| {
                let mut xh = x;
                xh[i] += h;
                m.project_from(&t, &xh).unwrap().coords
            });
            assert_columns_close("∂pixel/∂X", &pj.d_point, &fd, 1e-5, 1e-7);
            let fd = central_differences([1e-6, 1e-6, 1e-6, 1e-3, 1e-3, 1e-3], |i, h| {
                let mut v = Vector6::zeros();
                v[i] = h;
                let th = PoseIncrement::from_vector(&v).apply(&t);
                m.project_from(&th, &x).unwrap().coords
            });
            assert_columns_close("∂pixel/∂(ω, τ)", &pj.d_pose, &fd, 1e-5, 1e-7);
            let fd = central_differences(
                [
                    1e-3, 1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6,
                ],
                |i, h| {
                    let mut mh = m;
                    let mut v = m.lens_vector();
                    v[i] += h;
                    mh.set_lens_vector(&v);
                    mh.project_from(&t, &x).unwrap().coords
                },
            );
            assert_columns_close("∂pixel/∂lens", &pj.d_lens, &fd, 1e-5, 1e-7);
        }
    }
}

#[test]
fn undistortion_jacobians_match_finite_differences() {
    // n is O(1) and Newton leaves it at rounding level (≈ 2e-16), so a central difference
    // errs by ≈ 2e-16/h: 2e-13 per px for h = 1e-3 px (against ∂n/∂pixel ≈ 1/f ≈ 1e-3) and
    // 2e-10 for h = 1e-6 (coefficients, against columns up to O(1)). Tolerance 1e-9
    // absolute + 1e-7 relative.
    for m in [strong_barrel(), rational8()] {
        for p in grid_pixels(&m, 7, 6) {
            let u = m.undistort_with_jacobians(p).expect("undistorts");
            assert_eq!(Some(u.normalised), m.undistort(p));
            let fd = central_differences([1e-3; 2], |i, h| {
                let mut ph = p;
                ph[i] += h;
                m.undistort(ph).unwrap()
            });
            assert_columns_close("∂n/∂pixel", &u.d_pixel, &fd, 1e-9, 1e-7);
            let fd = central_differences(
                [
                    1e-3, 1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6,
                ],
                |i, h| {
                    let mut mh = m;
                    let mut v = m.lens_vector();
                    v[i] += h;
                    mh.set_lens_vector(&v);
                    mh.undistort(p).unwrap()
                },
            );
            assert_columns_close("∂n/∂lens", &u.d_lens, &fd, 1e-9, 1e-7);
        }
    }
}

/// Test vectors written by tests/data/camera/make_opencv_vectors.py.
#[derive(Deserialize)]
struct OpenCvVectors {
    opencv_version: String,
    cameras: Vec<OpenCvCamera>,
}

#[derive(Deserialize)]
struct OpenCvCamera {
    name: String,
    width: u32,
    height: u32,
    #[serde(rename = "K")]
    k: [[f64; 3]; 3],
    dist: Vec<f64>,
    views: Vec<OpenCvView>,
    undistort: OpenCvUndistort,
}

#[derive(Deserialize)]
struct OpenCvView {
    rvec: [f64; 3],
    tvec: [f64; 3],
    points: Vec<[f64; 3]>,
    pixels: Vec<[f64; 2]>,
    jacobians: Vec<OpenCvJacobian>,
}

/// projectPoints' Jacobian rows (u, v) for one point.
#[derive(Deserialize)]
struct OpenCvJacobian {
    d_tvec: [[f64; 3]; 2],
    d_intrinsics: [[f64; 4]; 2],
    d_dist: [Vec<f64>; 2],
}

#[derive(Deserialize)]
struct OpenCvUndistort {
    pixels: Vec<[f64; 2]>,
    normalised: Vec<[f64; 2]>,
}

fn opencv_vectors() -> OpenCvVectors {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/data/camera/opencv_vectors.json"
    );
    let text = std::fs::read_to_string(path).expect("read OpenCV test vectors");
    serde_json::from_str(&text).expect("parse OpenCV test vectors")
}

impl OpenCvCamera {
    fn model(&self) -> CameraModel {
        assert_eq!([self.k[0][1], self.k[1][0]], [0.0, 0.0], "zero skew");
        CameraModel {
            width: self.width,
            height: self.height,
            intrinsics: Intrinsics {
                fx: self.k[0][0],
                fy: self.k[1][1],
                cx: self.k[0][2],
                cy: self.k[1][2],
            },
            distortion: Distortion::from_opencv(&self.dist).unwrap(),
        }
    }
}

#[test]
fn projection_matches_opencv_project_points() {
    // Both sides compute the same formulas in double precision: rounding differences are
    // ≈ 1e-16 relative, i.e. ≈ 1e-12 px on ~2000 px. 1e-9 px (the brief's target) leaves
    // three orders of margin and still fails any real model difference.
    let v = opencv_vectors();
    let mut worst = 0.0f64;
    let mut worst_jacobian = 0.0f64;
    for cam in &v.cameras {
        let m = cam.model();
        assert_eq!(m.distortion.to_opencv(), cam.dist, "{}", cam.name);
        for view in &cam.views {
            let t = Isometry3::new(Vector3::from(view.tvec), Vector3::from(view.rvec));
            for (x, px) in view.points.iter().zip(&view.pixels) {
                let x = Point3::from(*x);
                let p = m.project_from(&t, &x).expect("in front");
                let err = (p - Point2::from(*px)).norm();
                assert!(err < 1e-9, "{}: {p} vs OpenCV {px:?}", cam.name);
                worst = worst.max(err);
            }
            // The analytic Jacobians against OpenCV's own: τ of a left increment is tvec's
            // derivative; fx, fy, cx, cy and the coefficients are the same parameters. Relative
            // agreement 1e-9 (both analytic, double precision).
            for (x, jac) in view.points.iter().zip(&view.jacobians) {
                let pj = m.project_with_jacobians(&t, &Point3::from(*x)).unwrap();
                for r in 0..2 {
                    let ours = (3..6).map(|c| pj.d_pose[(r, c)]);
                    let ours = ours.chain((0..4 + cam.dist.len()).map(|c| pj.d_lens[(r, c)]));
                    let theirs = jac.d_tvec[r].iter().chain(&jac.d_intrinsics[r]);
                    for (a, &b) in ours.zip(theirs.chain(&jac.d_dist[r])) {
                        let err = (a - b).abs() / b.abs().max(1.0);
                        assert!(err < 1e-9, "{}: Jacobian {a} vs OpenCV {b}", cam.name);
                        worst_jacobian = worst_jacobian.max(err);
                    }
                }
            }
        }
    }
    println!(
        "OpenCV {}: projection max |Δ| = {worst:.1e} px, Jacobian max relative Δ = {worst_jacobian:.1e}",
        v.opencv_version
    );
}

#[test]
fn undistortion_matches_opencv_undistort_points() {
    // OpenCV iterated until its re-projection error was < 1e-12 px (checked by the script),
    // i.e. its n is within ≈ 1e-12·|∂n/∂pixel| ≈ 1e-12/f·2 of the root even where the strong
    // barrel lens compresses 2:1; ours is at rounding level. Compared in pixels (f·|Δn|):
    // 1e-9 px.
    let v = opencv_vectors();
    let mut worst = 0.0f64;
    for cam in &v.cameras {
        let m = cam.model();
        for (px, n_cv) in cam.undistort.pixels.iter().zip(&cam.undistort.normalised) {
            let n = m.undistort(Point2::from(*px)).expect("undistorts");
            let d = n - Vector2::from(*n_cv);
            let err = (d.x * m.intrinsics.fx).hypot(d.y * m.intrinsics.fy);
            assert!(err < 1e-9, "{}: {px:?}: {n} vs OpenCV {n_cv:?}", cam.name);
            worst = worst.max(err);
        }
    }
    println!("undistortion vs OpenCV: max f·|Δn| = {worst:.1e} px");
}

#[test]
fn undistortion_round_trips_over_whole_images() {
    // Newton stops at steps ≤ 1e-12 with quadratic convergence, so the root is at rounding
    // level: distort(undistort(m)) reproduces m within a few 1e-16, i.e. ≪ 1e-10 px.
    let v = opencv_vectors();
    let mut worst = 0.0f64;
    for m in v.cameras.iter().map(OpenCvCamera::model) {
        for p in grid_pixels(&m, 97, 81) {
            let n = m.undistort(p).expect("every pixel of the image undistorts");
            let back = m.to_pixel(m.distortion.distort(n));
            worst = worst.max((back - p).norm());
            let ray = m.ray(p).unwrap();
            assert_eq!((ray.x, ray.y, ray.z), (n.x, n.y, 1.0));
            let again = m.distortion.undistort(m.distortion.distort(n)).unwrap();
            assert!((again - n).norm() < 1e-13, "{n} -> {again}");
        }
    }
    assert!(worst < 1e-10, "round trip off by {worst:e} px");
    println!("undistort round trip: max {worst:.1e} px");
}

#[test]
fn behind_the_device_gives_none() {
    let m = strong_barrel();
    let t = board_pose();
    for z in [0.0, -1e-9, -5.0] {
        let xd = Point3::new(10.0, -20.0, z);
        assert_eq!(m.project(&xd), None);
        let x = t.inverse_transform_point(&xd);
        assert_eq!(m.project_from(&t, &x), None);
        assert!(m.project_with_jacobians(&t, &x).is_none());
    }
    assert!(m.project(&Point3::new(10.0, -20.0, 1e-6)).is_some());
}

#[test]
fn undistortion_refuses_points_beyond_the_fold() {
    // k1 = −0.3 alone: r_d = r − 0.3 r³ rises to its maximum 0.7027 at r = 1/√0.9 = 1.054
    // (eq. D3 radial entry 1 − 0.9 r² = 0) and folds back; s = 1 − 0.3 r² < 0 beyond 1.826.
    let d = Distortion {
        k1: -0.3,
        ..Default::default()
    };
    assert!(d.is_invertible_at(Vector2::new(1.0, 0.0)));
    assert!(!d.is_invertible_at(Vector2::new(0.0, 1.2)));
    assert!(!d.is_invertible_at(Vector2::new(2.0, 0.0)));
    let inside = Vector2::new(0.6, 0.5); // r = 0.78
    let n = d.undistort(d.distort(inside)).unwrap();
    assert!((n - inside).norm() < 1e-14);
    // r_d = 0.8 has no root with r < 1.054; the only real root is the mirrored r ≈ −2.1
    // (where s < 0), which must not be returned.
    assert_eq!(d.undistort(Vector2::new(0.8, 0.0)), None);
    assert_eq!(d.undistort(Vector2::new(0.0, -0.75)), None);
    // A ghost: this point, 1.2 beyond the fold, is projected back inside; it is not the
    // inverse of its own image.
    let ghost = Vector2::new(1.5, 0.0);
    let n = d.undistort(d.distort(ghost)).unwrap();
    assert!((n - ghost).norm() > 0.1, "{n}");
}

#[test]
fn pose_increment_acts_on_the_left() {
    let t = board_pose();
    let inc = PoseIncrement {
        rotation: Vector3::new(0.01, -0.02, 0.03),
        translation: Vector3::new(1.0, 2.0, -3.0),
    };
    assert_eq!(PoseIncrement::from_vector(&inc.to_vector()), inc);
    let x = Point3::new(100.0, -50.0, 7.0);
    let expected = UnitQuaternion::from_scaled_axis(inc.rotation) * (t * x) + inc.translation;
    assert!((inc.apply(&t) * x - expected).norm() < 1e-9);
    assert_eq!(PoseIncrement::default().apply(&t), t);
}

#[test]
fn lens_params_select_and_order() {
    let m = rational8();
    let v = m.lens_vector();
    for p in LensParam::ALL {
        let mut mm = m;
        let mut vv = v;
        vv[p.index()] += 1.0;
        mm.set_lens_vector(&vv);
        assert_ne!(mm, m, "{p}");
        assert_eq!(mm.lens_vector(), vv);
    }
    assert_eq!(
        v.as_slice(),
        &[2400.0, 2395.0, 1230.4, 1019.8, 0.8, -0.2, 0.0004, -0.0006, 0.05, 0.95, 0.1, 0.02]
    );
    assert_eq!(LensParams::standard().len(), 9);
    assert_eq!(LensParams::rational().len(), 12);
    assert_eq!(LensParams::for_model(&m), LensParams::rational());
    assert_eq!(
        LensParams::for_model(&strong_barrel()),
        LensParams::standard()
    );
    let mask = LensParams::standard().fix(LensParam::K3).fix(LensParam::Cy);
    assert_eq!(mask.len(), 7);
    assert!(!mask.is_free(LensParam::K3) && mask.free(LensParam::K3).is_free(LensParam::K3));
    let names: Vec<&str> = mask.iter().map(LensParam::name).collect();
    assert_eq!(names, ["fx", "fy", "cx", "k1", "k2", "p1", "p2"]);
    let mut compact = [0.0; 7];
    mask.gather(&m, &mut compact);
    assert_eq!(
        compact,
        [2400.0, 2395.0, 1230.4, 0.8, -0.2, 0.0004, -0.0006]
    );
    let mut mm = m;
    mask.scatter(&mut mm, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
    let expected = [
        1.0, 2.0, 3.0, 1019.8, 4.0, 5.0, 6.0, 7.0, 0.05, 0.95, 0.1, 0.02,
    ];
    assert_eq!(mm.lens_vector().as_slice(), &expected);
    assert!(LensParams::rational()
        .iter()
        .map(LensParam::index)
        .eq(0..12));
    assert_eq!(serde_json::to_string(&LensParam::K3).unwrap(), "\"k3\"");
}

#[test]
fn opencv_coefficient_vectors() {
    let d = Distortion::from_opencv(&[-0.3, 0.1, 0.001, -0.002]).unwrap();
    assert_eq!(d.to_opencv(), [-0.3, 0.1, 0.001, -0.002, 0.0]);
    let c8 = [0.8, -0.2, 0.0004, -0.0006, 0.05, 0.95, 0.1, 0.02];
    assert_eq!(Distortion::from_opencv(&c8).unwrap().to_opencv(), c8);
    assert_eq!(Distortion::from_opencv(&c8[..6]), None);
}

#[test]
fn camera_model_serde_round_trip() {
    for m in [strong_barrel(), rational8()] {
        let json = serde_json::to_string(&m).unwrap();
        let back: CameraModel = serde_json::from_str(&json).unwrap();
        // serde_json's default float parser may miss the last bit (its `float_roundtrip`
        // feature is off in this workspace): allow 1 ulp per value.
        let (a, b) = (m.lens_vector(), back.lens_vector());
        assert!((a - b)
            .iter()
            .zip(a.iter())
            .all(|(d, x)| d.abs() <= x.abs() * f64::EPSILON));
        assert_eq!((back.width, back.height), (m.width, m.height));
        // TOML (rig files) parses floats exactly.
        let toml_text = toml::to_string(&m).unwrap();
        assert_eq!(toml::from_str::<CameraModel>(&toml_text).unwrap(), m);
    }
    // The 5-coefficient form may omit k4–k6; unknown keys are errors.
    let five = r#"{"width": 640, "height": 480,
        "intrinsics": {"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5},
        "distortion": {"k1": -0.1, "k2": 0.01, "p1": 0.0, "p2": 0.0, "k3": 0.0}}"#;
    let m: CameraModel = serde_json::from_str(five).unwrap();
    assert!(!m.distortion.is_rational());
    assert!(serde_json::from_str::<CameraModel>(&five.replace("\"k3\"", "\"k7\"")).is_err());
}

#[test]
fn jacobian_of_distortion_is_identity_without_distortion() {
    let d = Distortion::default();
    let n = Vector2::new(0.3, -0.7);
    assert_eq!(d.distort(n), n);
    assert_eq!(d.jacobian(n), Matrix2::identity());
    assert_eq!(d.undistort(n), Some(n));
}
