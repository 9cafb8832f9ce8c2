//! Geometric registration on simulated camera-only rigs (`calib::synthetic`): partial views
//! without the centre, relabelled at random, must come back with their true labels and side
//! or be refused; ambiguous or misplaced views are refused.

use super::*;
use crate::calib::synthetic::SyntheticRig;
use nalgebra::{Translation3, Vector2};
use rand::{rngs::StdRng, Rng, SeedableRng};
use std::collections::HashMap;

/// True labels and side of each view made partial, by (camera, pose).
type Expected = HashMap<(usize, usize), (Frame, Vec<Hex>)>;

/// Cut view `v` to the circles beyond a random line 30–100 mm from the centre (so the
/// centre cell is gone) keeping at least 30, relabel them by a random lattice transform and
/// make the view unanchored; gives the true labels and side.
fn make_partial(board: &Board, v: &mut CameraView, rng: &mut StdRng) -> Option<(Frame, Vec<Hex>)> {
    for _ in 0..50 {
        let angle = rng.random_range(0.0..std::f64::consts::TAU);
        let n = Vector2::new(angle.cos(), angle.sin());
        let offset = rng.random_range(30.0..100.0);
        let kept: Vec<ViewPoint> = v
            .points
            .iter()
            .filter(|p| board.position(p.hex).coords.dot(&n) >= offset)
            .cloned()
            .collect();
        if kept.len() < 30 {
            continue;
        }
        let truth = (v.frame, kept.iter().map(|p| p.hex).collect());
        let (k, t) = (
            rng.random_range(0..6),
            Hex::new(rng.random_range(-20..20), rng.random_range(-20..20)),
        );
        v.points = kept;
        for p in &mut v.points {
            p.hex = p.hex.rotate(k) + t;
        }
        v.frame = Frame::Unanchored;
        return Some(truth);
    }
    None
}

/// A camera-only ring rig's views with about `share` of them made partial, keeping every
/// camera at least 4 anchored views and every pose at least 2.
fn camera_only_views(rig: &SyntheticRig, share: f64, seed: u64) -> (Vec<CameraView>, Expected) {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut views = rig.views();
    let mut per_camera: HashMap<usize, usize> = HashMap::new();
    let mut per_pose: HashMap<usize, usize> = HashMap::new();
    for v in &views {
        *per_camera.entry(v.camera).or_default() += 1;
        *per_pose.entry(v.pose).or_default() += 1;
    }
    let mut expected = Expected::new();
    for v in &mut views {
        let (c, k) = (v.camera, v.pose);
        if rng.random::<f64>() >= share || per_camera[&c] <= 4 || per_pose[&k] <= 2 {
            continue;
        }
        if let Some(truth) = make_partial(&rig.board, v, &mut rng) {
            *per_camera.get_mut(&c).expect("counted") -= 1;
            *per_pose.get_mut(&k).expect("counted") -= 1;
            expected.insert((c, k), truth);
        }
    }
    (views, expected)
}

/// Registers the partial views of camera-only rigs: every registered view carries its true
/// labels and side (zero wrong), at least 95 % of the partial views are registered, and
/// the leftovers are reported.
#[test]
fn registers_partial_views_of_camera_only_rigs_by_geometry() {
    let (mut unanchored, mut registered, mut wrong) = (0, 0, 0);
    for seed in 0..3 {
        let rig = SyntheticRig::ring(8, 0, 10, 0.1, 50 + seed);
        let (views, expected) = camera_only_views(&rig, 0.3, 60 + seed);
        let cal = calibrate_registering(
            &rig.board,
            &rig.device_infos(),
            rig.boards.len(),
            &views,
            &CalibrateOptions::default(),
            &GeometricParams::default(),
        )
        .unwrap();
        let reg = &cal.registration;
        assert_eq!(reg.unanchored, expected.len());
        assert_eq!(
            reg.registered.len() + reg.unregistered.len(),
            expected.len()
        );
        assert!(reg.registered.iter().all(|r| r.by == Evidence::Geometry));
        // Check the labels the second calibration used against the truth.
        for r in &reg.registered {
            let (frame, labels) = &expected[&(r.camera, r.pose)];
            let d = cal.device_index.iter().position(|&i| i == r.camera);
            let k = cal.pose_index.iter().position(|&i| i == r.pose);
            let used: Vec<Hex> = cal
                .observations
                .iter()
                .filter(|o| Some(o.device) == d && Some(o.pose) == k)
                .filter(|o| Frame::Anchored(o.side) == *frame)
                .map(|o| o.hex)
                .collect();
            if used.len() != labels.len() || labels.iter().any(|h| !used.contains(h)) {
                wrong += 1;
            }
        }
        for u in &reg.unregistered {
            assert!(expected.contains_key(&(u.camera, u.pose)), "{u:?}");
            eprintln!("rig {seed}: unregistered {u:?}");
        }
        eprintln!(
            "rig {seed}: {} of {} unanchored views registered by geometry",
            reg.registered.len(),
            expected.len()
        );
        unanchored += expected.len();
        registered += reg.registered.len();
    }
    eprintln!("registered {registered} of {unanchored} unanchored views, {wrong} wrong");
    assert_eq!(wrong, 0);
    assert!(unanchored >= 30, "only {unanchored} partial views");
    assert!(
        registered as f64 >= 0.95 * unanchored as f64,
        "registered {registered} of {unanchored}"
    );
}

/// One full view of `rig` (camera `c`, pose `k`) relabelled and unanchored, its truth, and
/// T_device_board.
fn one_view(rig: &SyntheticRig, c: usize, k: usize) -> (CameraView, CameraView, Isometry3<f64>) {
    let truth = rig
        .views()
        .into_iter()
        .find(|v| (v.camera, v.pose) == (c, k))
        .expect("camera sees the pose");
    let mut view = truth.clone();
    view.frame = Frame::Unanchored;
    for p in &mut view.points {
        p.hex = p.hex.rotate(2) + Hex::new(7, -3);
    }
    (view, truth, rig.devices[c].pose * rig.boards[k])
}

#[test]
fn places_a_view_under_a_slightly_wrong_pose_and_refuses_a_misplaced_one() {
    let rig = SyntheticRig::ring(4, 0, 6, 0.1, 7);
    let (view, truth, device_from_board) = one_view(&rig, 1, 2);
    let model = rig.devices[1].model;
    let params = GeometricParams::default();
    // A board pose 0.2 pitch (4 mm) off still gives the true labels.
    for off in [0.0, 4.0] {
        let moved = device_from_board * Translation3::new(off, 0.0, 0.0);
        let placed = place_view(&rig.board, &model, &moved, &view, &params).unwrap();
        assert_eq!(placed.view, truth, "board moved by {off} mm");
        assert_eq!(placed.agreeing, view.points.len());
    }
    // Half a pitch off (10 mm): circles fall between predictions; refused, not guessed.
    let moved = device_from_board * Translation3::new(10.0, 0.0, 0.0);
    let e = place_view(&rig.board, &model, &moved, &view, &params).unwrap_err();
    eprintln!("half a pitch off: {e}");
}

#[test]
fn refuses_a_view_whose_halves_agree_on_different_transforms() {
    let rig = SyntheticRig::ring(4, 0, 6, 0.1, 7);
    let (mut view, _, device_from_board) = one_view(&rig, 0, 1);
    // The second half of the circles shifted by one lattice step (a wrongly joined grid):
    // two transforms with equal support.
    let half = view.points.len() / 2;
    for p in &mut view.points[half..] {
        p.hex = p.hex + Hex::new(1, 0);
    }
    let model = rig.devices[0].model;
    // Even when agreement alone would let it through, the margin refuses it.
    let lenient = GeometricParams {
        min_agreement: 0.3,
        ..GeometricParams::default()
    };
    let e = place_view(&rig.board, &model, &device_from_board, &view, &lenient).unwrap_err();
    assert!(e.starts_with("ambiguous"), "{e}");
    let e = place_view(
        &rig.board,
        &model,
        &device_from_board,
        &view,
        &GeometricParams::default(),
    )
    .unwrap_err();
    assert!(!e.is_empty());
}
