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
    use super::super::bundle::{self, DeviceKind, Options};
    use super::super::synthetic::SyntheticRig;
    use crate::board::Side;

    #[test]
    fn paper_rig_reaches_the_noise_floor_from_a_perturbed_start() {
        let sigma = 0.1;
        let rig = SyntheticRig::paper(10, sigma, 7);
        let problem = rig.perturbed_start(8);
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

    /// Errors of every device's first eight lens parameters and pose increment, with their
    /// indices into the solution's covariance.
    fn errors(sol: &bundle::Solution, rig: &SyntheticRig) -> Vec<(usize, f64)> {
        let mut out = Vec::new();
        for (d, (est, truth)) in sol.devices.iter().zip(&rig.devices).enumerate() {
            let (a, b) = (est.model, truth.model);
            let (lens_at, pose_at) = sol.index[d];
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
            out.extend(errs.iter().enumerate().map(|(j, e)| (lens_at + j, *e)));
            if let Some(at) = pose_at {
                // Left increment taking the truth to the estimate: T_est = (exp ω, τ)·T_true.
                let delta = est.pose * truth.pose.inverse();
                let (w, t) = (delta.rotation.scaled_axis(), delta.translation.vector);
                out.extend(
                    [w.x, w.y, w.z, t.x, t.y, t.z]
                        .iter()
                        .enumerate()
                        .map(|(j, e)| (at + j, *e)),
                );
            }
        }
        out
    }

    #[test]
    fn parameter_errors_agree_with_the_covariance() {
        // If Cov(θ) = σ²(JᵀJ)⁻¹ describes the errors e of the p compared parameters, then
        // eᵀ·Cov⁻¹·e / p ~ χ²_p / p (mean 1, sd √(2/p) = 0.13 for p = 120) and the mean
        // squared normalised error (e_i/σ_i)² has mean 1 (its spread is larger: the
        // parameters are correlated, so it is averaged over independent noise draws).
        let sigma = 0.2;
        let (mut maha, mut nmse) = (Vec::new(), Vec::new());
        for seed in 0..3 {
            let rig = SyntheticRig::paper(10, sigma, 100 + seed);
            let sol =
                bundle::adjust(&rig.perturbed_start(200 + seed), &Options::default()).unwrap();
            let e = errors(&sol, &rig);
            let idx: Vec<usize> = e.iter().map(|(i, _)| *i).collect();
            let cov = nalgebra::DMatrix::from_fn(idx.len(), idx.len(), |a, b| {
                sol.covariance[(idx[a], idx[b])]
            });
            let ev = nalgebra::DVector::from_iterator(e.len(), e.iter().map(|(_, v)| *v));
            let m = ev.dot(&cov.clone().cholesky().unwrap().solve(&ev)) / e.len() as f64;
            let z2 = e
                .iter()
                .map(|(i, v)| v * v / sol.covariance[(*i, *i)])
                .sum::<f64>()
                / e.len() as f64;
            maha.push(m);
            nmse.push(z2);
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        eprintln!("Mahalanobis/p per draw {maha:?}, NMSE per draw {nmse:?}");
        assert!((0.7..=1.3).contains(&mean(&maha)), "Mahalanobis/p {maha:?}");
        assert!((0.7..=1.3).contains(&mean(&nmse)), "NMSE {nmse:?}");
    }

    #[test]
    fn facing_cameras_share_one_frame() {
        // Cameras 3–5 see only the back side, cameras 0–2 only the front: their relative
        // poses come out right only through the side transform.
        let rig = SyntheticRig::paper(8, 0.1, 21);
        let sol = bundle::adjust(&rig.perturbed_start(22), &Options::default()).unwrap();
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

mod pipeline {
    use super::super::pipeline::{calibrate, CalibrateOptions};
    use super::super::synthetic::SyntheticRig;
    use super::super::views::Frame;
    use crate::board::Hex;
    use rand::{rngs::StdRng, Rng, SeedableRng};

    #[test]
    fn calibrates_from_views_with_a_fifth_of_them_unanchored() {
        // The paper rig from nothing but labelled views: Zhang, pose graph and adjustment
        // must reach the truth, and views relabelled in an arbitrary lattice frame (as the
        // grid builder leaves a view without its centre) must be registered.
        let sigma = 0.1;
        let rig = SyntheticRig::paper(10, sigma, 31);
        let mut views = rig.views();
        let mut rng = StdRng::seed_from_u64(32);
        let mut scrambled = 0;
        for v in views.iter_mut() {
            // A camera view of the reference camera stays anchored in every pose it has, so
            // that each pose keeps some anchored views under each projector.
            if v.camera != 0 && rng.random_bool(0.2) {
                let (k, t) = (
                    rng.random_range(0..6),
                    Hex::new(rng.random_range(-20..20), rng.random_range(-20..20)),
                );
                for p in &mut v.points {
                    p.hex = p.hex.rotate(k) + t;
                }
                v.frame = Frame::Unanchored;
                scrambled += 1;
            }
        }
        assert!(scrambled > 5);
        let cal = calibrate(
            &rig.board,
            &rig.device_infos(),
            rig.boards.len(),
            &views,
            &CalibrateOptions::default(),
        )
        .unwrap();
        let reg = &cal.registration;
        assert_eq!(reg.unanchored, scrambled);
        assert!(
            reg.registered.len() as f64 >= 0.95 * scrambled as f64,
            "registered {} of {scrambled}: {:?}",
            reg.registered.len(),
            reg.unregistered
        );
        assert!(cal.excluded.is_empty(), "{:?}", cal.excluded);
        assert_eq!(cal.devices.len(), rig.devices.len());
        // The noise floor and the truth: σ per coordinate within 3 %, focal lengths within
        // 6 of their standard deviations.
        assert!(
            (cal.solution.sigma / sigma - 1.0).abs() < 0.03,
            "σ {}",
            cal.solution.sigma
        );
        for (d, (est, truth)) in cal.devices.iter().zip(&rig.devices).enumerate() {
            let e = est.model.intrinsics.fx - truth.model.intrinsics.fx;
            let s = cal.solution.intrinsic_std[d][0];
            assert!(e.abs() < 6.0 * s, "{} fx error {e} std {s}", est.name);
            let dt = (est.pose.translation.vector - truth.pose.translation.vector).norm();
            assert!(dt < 1.0, "{} position error {dt} mm", est.name);
        }
    }
}

mod verification {
    use super::super::pipeline::{calibrate, CalibrateOptions};
    use super::super::synthetic::SyntheticRig;
    use super::super::verify::verify;

    /// Calibrate on poses 0–7 of a 10-pose rig, verify on poses 8 and 9.
    fn held_out(sigma: f64) -> Vec<super::super::verify::PairCheck> {
        let rig = SyntheticRig::paper(10, sigma, 51);
        let views = rig.views();
        let (train, test): (Vec<_>, Vec<_>) = views.into_iter().partition(|v| v.pose < 8);
        let cal = calibrate(
            &rig.board,
            &rig.device_infos(),
            rig.boards.len(),
            &train,
            &CalibrateOptions::default(),
        )
        .unwrap();
        assert_eq!(cal.devices.len(), rig.devices.len());
        let checks = verify(&rig.board, &cal.devices, &test);
        assert!(checks.iter().any(|c| c.second.starts_with("proj")));
        assert!(checks.iter().any(|c| c.second.starts_with("cam")));
        checks
    }

    #[test]
    fn exact_observations_triangulate_to_the_board() {
        // Without noise the calibration is exact, so what remains is the triangulation and
        // its removal of the ellipse-centre bias (0.1–0.3 px here, ~0.1 mm if left in).
        for c in held_out(1e-6) {
            assert!(
                c.length_rms < 1e-3 && c.flatness_rms < 1e-3,
                "{} + {} pose {}: length {} mm, flatness {} mm",
                c.first,
                c.second,
                c.pose,
                c.length_rms,
                c.flatness_rms
            );
        }
    }

    #[test]
    fn held_out_lengths_at_detector_noise() {
        // σ = 0.03 px (the detector's centre error at default noise): a point triangulated
        // from two views 1.5 m away (f = 2400 px, 0.6 mm per px) at ≥ 35° convergence is
        // good to ≈ 0.03·0.6/sin 35° ≈ 0.03 mm in depth, so lengths must be well inside the
        // 0.1 mm acceptance.
        let checks = held_out(0.03);
        let rms =
            (checks.iter().map(|c| c.length_rms.powi(2)).sum::<f64>() / checks.len() as f64).sqrt();
        eprintln!(
            "held-out length RMS over {} pairs: {rms:.4} mm",
            checks.len()
        );
        assert!(rms < 0.1, "{rms} mm");
    }
}

mod flatness {
    use super::super::bundle::{self, Options};
    use super::super::synthetic::SyntheticRig;
    use nalgebra::Vector3;

    #[test]
    fn a_bent_board_is_measured_and_its_residuals_vanish() {
        // A bowl of 1 mm and two small saddles at the board's rim: ignored, they leave
        // residuals of the order of a pixel; refined, the noise floor and the bend within
        // 4 standard deviations.
        let sigma = 0.1;
        let truth = Vector3::new(1.0, 0.3, -0.2);
        let rig = SyntheticRig::paper_bent(10, sigma, 61, truth);
        let start = rig.perturbed_start(62);
        let flat = bundle::adjust(&start, &Options::default()).unwrap();
        let bent = bundle::adjust(
            &start,
            &Options {
                refine_flatness: true,
                ..Options::default()
            },
        )
        .unwrap();
        eprintln!(
            "σ flat model {:.4} px, bent model {:.4} px; bend {:?} ± {:?}",
            flat.sigma, bent.sigma, bent.bend.coefficients, bent.bend_std
        );
        assert!(flat.sigma > 1.5 * sigma, "flat model σ {}", flat.sigma);
        assert!((bent.sigma / sigma - 1.0).abs() < 0.03, "σ {}", bent.sigma);
        for j in 0..3 {
            let e = bent.bend.coefficients[j] - truth[j];
            assert!(
                e.abs() < 4.0 * bent.bend_std[j],
                "coefficient {j}: error {e} mm"
            );
        }
    }
}
