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
