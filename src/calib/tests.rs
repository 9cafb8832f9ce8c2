use super::zhang::{self, Homography};
use super::{PlanarView, PlaneCorrespondence};
use crate::board::{Board, Side};
use crate::camera::{CameraModel, Distortion, Intrinsics};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{rngs::StdRng, Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

fn truth() -> CameraModel {
    CameraModel {
        width: 1920,
        height: 1200,
        intrinsics: Intrinsics {
            fx: 1800.0,
            fy: 1795.0,
            cx: 970.0,
            cy: 590.0,
        },
        distortion: Distortion {
            k1: -0.12,
            k2: 0.05,
            ..Default::default()
        },
    }
}

/// Board poses tilted 15–40° about varied axes, 1.2–1.8 m away.
fn poses(rng: &mut StdRng, n: usize) -> Vec<Isometry3<f64>> {
    (0..n)
        .map(|_| {
            let axis = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                0.2,
            );
            let angle = rng.random_range(15f64..40.0).to_radians();
            let flip = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
            Isometry3::from_parts(
                Translation3::new(
                    rng.random_range(-60.0..60.0),
                    rng.random_range(-40.0..40.0),
                    rng.random_range(1200.0..1800.0),
                ),
                UnitQuaternion::from_scaled_axis(axis.normalize() * angle) * flip,
            )
        })
        .collect()
}

fn observe(cam: &CameraModel, pose: &Isometry3<f64>, sigma: f64, rng: &mut StdRng) -> PlanarView {
    let board = Board::hex600();
    let noise = Normal::new(0.0, sigma.max(1e-300)).unwrap();
    let points = board
        .circles(Side::Front)
        .iter()
        .filter_map(|c| {
            let p = cam.project(&(pose * Point3::new(c.center_2d.x, c.center_2d.y, 0.0)))?;
            let inside = p.x >= 0.0
                && p.y >= 0.0
                && p.x < f64::from(cam.width)
                && p.y < f64::from(cam.height);
            inside.then(|| PlaneCorrespondence {
                board: c.center_2d,
                image: p + nalgebra::Vector2::new(noise.sample(rng), noise.sample(rng)),
            })
        })
        .collect();
    PlanarView { points }
}

#[test]
fn homography_is_exact_without_distortion() {
    let mut cam = truth();
    cam.distortion = Distortion::default();
    let mut rng = StdRng::seed_from_u64(1);
    let pose = poses(&mut rng, 1)[0];
    let view = observe(&cam, &pose, 0.0, &mut rng);
    let h = Homography::estimate(&view).unwrap();
    for c in &view.points {
        assert!((h.apply(c.board) - c.image).norm() < 1e-8);
    }
}

#[test]
fn zhang_recovers_pinhole_exactly_without_noise() {
    let mut cam = truth();
    cam.distortion = Distortion::default();
    let mut rng = StdRng::seed_from_u64(2);
    let ps = poses(&mut rng, 5);
    let views: Vec<_> = ps.iter().map(|p| observe(&cam, p, 0.0, &mut rng)).collect();
    let (est, est_poses) = zhang::initialise(&views, cam.width, cam.height).unwrap();
    let (k, t) = (est.intrinsics, cam.intrinsics);
    assert!((k.fx - t.fx).abs() < 1e-6 * t.fx, "{k:?}");
    assert!((k.fy - t.fy).abs() < 1e-6 * t.fy, "{k:?}");
    assert!(
        (k.cx - t.cx).abs() < 1e-4 && (k.cy - t.cy).abs() < 1e-4,
        "{k:?}"
    );
    assert!(est.distortion.k1.abs() < 1e-9 && est.distortion.k2.abs() < 1e-9);
    for (e, p) in est_poses.iter().zip(&ps) {
        assert!((e.translation.vector - p.translation.vector).norm() < 1e-5);
        assert!(e.rotation.angle_to(&p.rotation) < 1e-8);
    }
}

#[test]
fn zhang_start_is_close_with_distortion_and_noise() {
    // With k1 = −0.12 the closed form is biased (it ignores distortion); a start within a few
    // per cent is what the bundle adjustment needs.
    let cam = truth();
    let mut rng = StdRng::seed_from_u64(3);
    let ps = poses(&mut rng, 8);
    let views: Vec<_> = ps.iter().map(|p| observe(&cam, p, 0.3, &mut rng)).collect();
    let (est, est_poses) = zhang::initialise(&views, cam.width, cam.height).unwrap();
    let (k, t) = (est.intrinsics, cam.intrinsics);
    assert!((k.fx / t.fx - 1.0).abs() < 0.05, "{k:?}");
    assert!((k.fy / t.fy - 1.0).abs() < 0.05, "{k:?}");
    let pinhole = CameraModel {
        distortion: Distortion::default(),
        ..est
    };
    assert!(
        zhang::rms_reprojection(&est, &views, &est_poses)
            <= zhang::rms_reprojection(&pinhole, &views, &est_poses)
    );
}

mod bundle_adjustment {
    use super::super::bundle::{self, ellipse_bias, DeviceKind, Options, Problem};
    use super::super::synthetic::{ellipse_center, SyntheticRig};
    use crate::board::Side;
    use crate::camera::{CameraModel, Distortion, Intrinsics};
    use nalgebra::{Isometry3, Point2, Translation3, UnitQuaternion, Vector3};
    use rand::{rngs::StdRng, Rng, SeedableRng};

    #[test]
    fn closed_form_bias_matches_fitted_rim_on_a_pinhole() {
        let model = CameraModel {
            width: 1920,
            height: 1200,
            intrinsics: Intrinsics {
                fx: 2000.0,
                fy: 2000.0,
                cx: 960.0,
                cy: 600.0,
            },
            distortion: Distortion::default(),
        };
        let pose = Isometry3::from_parts(
            Translation3::new(-80.0, 50.0, 900.0),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.7, 0.4, 0.1)),
        );
        for c in [
            Point2::new(0.0, 0.0),
            Point2::new(200.0, -150.0),
            Point2::new(-280.0, 220.0),
        ] {
            let bias = ellipse_bias(&pose, c, 6.0).unwrap();
            let p = pose * nalgebra::Point3::new(c.x, c.y, 0.0);
            let n = nalgebra::Vector2::new(p.x / p.z, p.y / p.z) + bias;
            let predicted = model.to_pixel(n);
            let fitted = ellipse_center(&model, &pose, c, 6.0).unwrap();
            // Both are exact for a pinhole; the fit of 64 exact rim points is good to 1e-8 px.
            assert!(
                (predicted - fitted).norm() < 1e-6,
                "{predicted} vs {fitted}"
            );
            // And the bias is not negligible at this tilt.
            assert!((bias * 2000.0).norm() > 0.01);
        }
    }

    fn perturbed(rig: &SyntheticRig, seed: u64) -> Problem {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut devices = rig.devices.clone();
        let mut turn = |rng: &mut StdRng| {
            let axis = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            UnitQuaternion::from_scaled_axis(axis * 5f64.to_radians())
        };
        for (i, d) in devices.iter_mut().enumerate() {
            d.model.intrinsics.fx *= 1.0 + rng.random_range(-0.05..0.05);
            d.model.intrinsics.fy = d.model.intrinsics.fx;
            d.model.distortion = Distortion::default();
            if i != 0 {
                d.pose = Isometry3::from_parts(
                    Translation3::from(d.pose.translation.vector + Vector3::new(30.0, -20.0, 40.0)),
                    turn(&mut rng) * d.pose.rotation,
                );
            }
        }
        let boards = rig
            .boards
            .iter()
            .map(|b| Isometry3::from_parts(b.translation, turn(&mut rng) * b.rotation))
            .collect();
        Problem {
            board: rig.board.clone(),
            devices,
            boards,
            observations: rig.observations.clone(),
        }
    }

    #[test]
    fn paper_rig_reaches_the_noise_floor_from_a_perturbed_start() {
        let sigma = 0.1;
        let rig = SyntheticRig::paper(10, sigma, 7);
        let problem = perturbed(&rig, 8);
        let sol = bundle::adjust(&problem, &Options::default()).unwrap();
        let (n, p) = sol.dof;
        // RMS per coordinate of the inliers → σ·√(1 − p/n) (DESIGN.md §8); a 4σ trim of 2D
        // Gaussian norms removes 3e-4 of them and lowers the RMS by < 0.5 %.
        let (sq, cnt) = sol
            .residuals
            .iter()
            .filter(|r| !r.outlier)
            .fold((0.0, 0usize), |(s, c), r| {
                (s + r.error.norm_squared(), c + 2)
            });
        let rms = (sq / cnt as f64).sqrt();
        let expect = sigma * (1.0 - p as f64 / n as f64).sqrt();
        assert_eq!(cnt, n);
        assert!(
            (rms / expect - 1.0).abs() < 0.03,
            "rms {rms} vs {expect} (n {n}, p {p})"
        );
        // Every device recovered: focal within 6σ of its standard deviation (and well under 0.1 %).
        for (d, (est, truth)) in sol.devices.iter().zip(&rig.devices).enumerate() {
            let e = est.model.intrinsics.fx - truth.model.intrinsics.fx;
            let s = sol.intrinsic_std[d][0];
            assert!(
                e.abs() < 6.0 * s && e.abs() < 1e-3 * truth.model.intrinsics.fx,
                "{} fx error {e} std {s}",
                est.name
            );
        }
        assert!(sol.devices.iter().any(|d| d.kind == DeviceKind::Projector));
    }

    #[test]
    fn parameter_errors_agree_with_the_covariance() {
        // Mean squared normalised error over every intrinsic and device-pose parameter of a
        // converged solve must be ≈ 1 (0.7–1.3) if Cov(θ) = σ²(JᵀJ)⁻¹ describes the errors.
        let sigma = 0.2;
        let rig = SyntheticRig::paper(10, sigma, 11);
        let mut problem = perturbed(&rig, 12);
        problem
            .devices
            .iter_mut()
            .for_each(|d| d.model.distortion.k3 = 0.0);
        let sol = bundle::adjust(
            &problem,
            &Options {
                refine_side_transform: false,
                ..Options::default()
            },
        )
        .unwrap();
        let mut z2 = Vec::new();
        for (d, (est, truth)) in sol.devices.iter().zip(&rig.devices).enumerate() {
            let (a, b) = (est.model, truth.model);
            let errs = [
                a.intrinsics.fx - b.intrinsics.fx,
                a.intrinsics.fy - b.intrinsics.fy,
                a.intrinsics.cx - b.intrinsics.cx,
                a.intrinsics.cy - b.intrinsics.cy,
                a.distortion.k1 - b.distortion.k1,
                a.distortion.k2 - b.distortion.k2,
                a.distortion.p1 - b.distortion.p1,
                a.distortion.p2 - b.distortion.p2,
            ];
            for (e, s) in errs.iter().zip(&sol.intrinsic_std[d]) {
                z2.push((e / s).powi(2));
            }
            if d != 0 {
                // Left increment taking the truth to the estimate: (ω, τ) with
                // T_est = (exp ω, τ)·T_true.
                let delta = est.pose * truth.pose.inverse();
                let w = delta.rotation.scaled_axis();
                let t = delta.translation.vector;
                for (e, s) in [w.x, w.y, w.z, t.x, t.y, t.z].iter().zip(&sol.pose_std[d]) {
                    z2.push((e / s).powi(2));
                }
            }
        }
        let mse = z2.iter().sum::<f64>() / z2.len() as f64;
        assert!(
            (0.7..=1.3).contains(&mse),
            "normalised MSE {mse} over {} parameters",
            z2.len()
        );
    }

    #[test]
    fn facing_cameras_share_one_frame() {
        // Cameras 3–5 see only the back side, cameras 0–2 only the front: their relative
        // poses come out right only through the side transform.
        let rig = SyntheticRig::paper(8, 0.1, 21);
        let sol = bundle::adjust(&perturbed(&rig, 22), &Options::default()).unwrap();
        for d in 3..6 {
            let (e, t) = (sol.devices[d].pose, rig.devices[d].pose);
            assert!(
                (e.translation.vector - t.translation.vector).norm() < 1.0,
                "{}",
                sol.devices[d].name
            );
            assert!(e.rotation.angle_to(&t.rotation) < 1e-3);
        }
        let fb = rig.board.side_transform(Side::Back);
        assert!((sol.front_back.translation.vector - fb.translation.vector).norm() < 0.5);
    }
}
