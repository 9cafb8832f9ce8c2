use super::*;
use crate::calib::diagnostics::projection_uncertainty;
use crate::calib::solve::{calibrate, CalibrateOptions};
use crate::calib::synthetic::SyntheticRig;
use crate::calib::zhang::MIN_VIEWS;

/// The paper-like rig's calibration from its views of the poses below `poses`.
fn calibration(rig: &SyntheticRig, poses: usize) -> Calibration {
    let views: Vec<_> = rig.views().into_iter().filter(|v| v.pose < poses).collect();
    calibrate(
        &rig.board,
        &rig.device_infos(),
        poses,
        &views,
        &CalibrateOptions::default(),
    )
    .unwrap()
}

/// The worst uncertainty over every device's image of `cal`.
fn worst_of(cal: &Calibration) -> f64 {
    let g = guide(cal, &device_infos(cal), 1e9);
    g.devices
        .iter()
        .map(|d| d.worst.unwrap())
        .fold(0.0, f64::max)
}

/// The worst uncertainty over every device's image predicted for `cal` with board pose
/// `pose` added to its normal equations `info0` (the device block's information).
fn predicted_worst(
    cal: &Calibration,
    block: &Block,
    info0: &DMatrix<f64>,
    pose: &Isometry3<f64>,
) -> f64 {
    let sol = &cal.solution;
    let fb = back_frame(cal);
    let seen = sightings(&cal.board, &cal.devices, &fb, pose);
    assert!(seen.len() > 1000, "{} sightings", seen.len());
    let h = information(block, &cal.devices, &fb, &cal.board, pose, &seen, sol.sigma);
    let after = (info0 + h).cholesky().unwrap().inverse();
    let distance = working_distances(&cal.devices, &sol.boards);
    (0..cal.devices.len())
        .map(|d| block.worst(&cal.devices, &after, d, distance[d]).unwrap().0)
        .fold(0.0, f64::max)
}

fn device_infos(cal: &Calibration) -> Vec<DeviceInfo> {
    cal.devices.iter().map(DeviceInfo::from).collect()
}

#[test]
fn uncertainty_is_the_diagnostics_one_and_prediction_matches_a_resolve() {
    let rig = SyntheticRig::paper(5, 0.1, 3);
    let cal = calibration(&rig, 4);
    let block = Block::of(&cal);
    let cov = cal.solution.covariance.block(&block.state);
    // With its pose held (the pose block zeroed), a device's rig uncertainty at any depth is
    // the report's lens-only projection uncertainty; with it, the pose adds what it adds.
    let mut posed = 0;
    for d in 0..cal.devices.len() {
        let dev = &cal.devices[d];
        let free = &block.lens[d].1;
        let full = block.device_cov(&cov, d);
        let mut held = full.clone();
        held.view_mut((free.len(), 0), (full.nrows() - free.len(), full.ncols()))
            .fill(0.0);
        held.view_mut((0, free.len()), (full.nrows(), full.ncols() - free.len()))
            .fill(0.0);
        let has_pose = block.pose[d].is_some();
        posed += usize::from(has_pose);
        for p in [Point2::new(10.0, 10.0), Point2::new(960.0, 500.0)] {
            let theirs = projection_uncertainty(&cal, d, p).unwrap();
            for depth in [0.5, 2.0] {
                let mine = rig_uncertainty(dev, free, has_pose, &held, depth, p).unwrap();
                assert!((mine / theirs - 1.0).abs() < 1e-9, "{mine} vs {theirs}");
            }
            let with_pose = rig_uncertainty(dev, free, has_pose, &full, 1.0, p).unwrap();
            assert!(with_pose.is_finite() && (with_pose != theirs) == has_pose);
        }
    }
    assert_eq!(posed, cal.devices.len() - 1, "one reference device");
    // Adding pose 4's information to the normal equations predicts the covariance of the
    // re-solve with pose 4: the worst uncertainty within 15 % (σ̂ of the re-solve differs
    // by ~1 %, the linearisation point by the estimate's error).
    let info0 = cov.clone().cholesky().unwrap().inverse();
    let predicted = predicted_worst(&cal, &block, &info0, &rig.boards[4]);
    let before = worst_of(&cal);
    let actual = worst_of(&calibration(&rig, 5));
    assert!(predicted < before, "{predicted} ≥ {before}");
    assert!(
        (predicted / actual - 1.0).abs() < 0.15,
        "predicted {predicted}, re-solved {actual}, before {before}"
    );
}

#[test]
fn the_suggestion_lowers_the_worst_uncertainty_more_than_the_next_fixed_pose() {
    let rig = SyntheticRig::paper(5, 0.1, 5);
    let cal = calibration(&rig, 4);
    let infos = device_infos(&cal);
    let g = guide(&cal, &infos, 1e-6);
    assert!(!g.done);
    let s = g.suggestion.expect("a suggestion");
    assert!(
        s.sentence.starts_with(&format!("for {}:", s.target)),
        "{}",
        s.sentence
    );
    assert!(s.outlines.iter().any(|o| o.is_some()));
    // The picture: a camera that sees the pose, the tilt from facing it, one short line.
    let p = s.picture.as_ref().expect("a picture of the pose");
    assert!(s.outlines[p.camera].is_some(), "{p:?}");
    let d = cal
        .device_index
        .iter()
        .position(|&i| i == p.camera)
        .unwrap();
    let cam = &cal.devices[d];
    assert_eq!(cam.kind, DeviceKind::Camera);
    let (_, tilt) = picture::facing(cam, &s.pose);
    assert!(
        (p.tilt_deg - tilt).abs() <= picture::STEP_DEG / 2.0,
        "{p:?}, {tilt}"
    );
    let words = p.line.split_whitespace().count();
    assert!(
        words <= picture::MAX_WORDS && p.line.contains(&cam.name),
        "{p:?}"
    );
    if let Some(t) = &p.turn {
        let norm = t.toward[0].hypot(t.toward[1]);
        assert!(
            (norm - 1.0).abs() < 1e-9 && t.deg >= picture::STEP_DEG,
            "{p:?}"
        );
    }
    // The fixed schedule's next pose, predicted the same way, does no better.
    let block = Block::of(&cal);
    let cov = cal.solution.covariance.block(&block.state);
    let info0 = cov.cholesky().unwrap().inverse();
    let fixed = predicted_worst(&cal, &block, &info0, &rig.boards[4]);
    assert!(
        s.predicted <= fixed,
        "suggested {} vs fixed {fixed}",
        s.predicted
    );
    // Done once the threshold is above every device's worst.
    let g = guide(&cal, &infos, 1e3);
    assert!(g.done && g.suggestion.is_none());
}

#[test]
fn hull_keeps_the_outer_points() {
    let pts: Vec<Point2<f64>> = [
        (0.0, 0.0),
        (2.0, 0.0),
        (1.0, 1.0),
        (2.0, 2.0),
        (0.0, 2.0),
        (1.0, 0.5),
    ]
    .iter()
    .map(|&(x, y)| Point2::new(x, y))
    .collect();
    let h = hull(&pts);
    assert_eq!(h.len(), 4);
    for c in [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)] {
        assert!(h.contains(&Point2::new(c.0, c.1)));
    }
}

#[test]
fn the_rig_file_threshold_is_read_and_checked() {
    let text = include_str!("../../../rigs/sim-paper.toml");
    let rig = crate::rig::file::RigFile::parse(text, "sim-paper.toml").unwrap();
    assert_eq!(
        rig.guidance.uncertainty_px,
        crate::rig::file::DEFAULT_UNCERTAINTY_PX
    );
    let set = format!("{text}\n[guidance]\nuncertainty_px = 0.4\n");
    let rig = crate::rig::file::RigFile::parse(&set, "sim-paper.toml").unwrap();
    assert_eq!(rig.guidance.uncertainty_px, 0.4);
    for bad in ["-1.0", "0.0", "nan", "1e9"] {
        let text = format!("{text}\n[guidance]\nuncertainty_px = {bad}\n");
        let e = crate::rig::file::RigFile::parse(&text, "sim-paper.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("guidance.uncertainty_px"), "{bad}: {e}");
    }
}

#[test]
fn predictions_from_scratch_need_enough_poses_and_fall_with_more() {
    // Predicted from the calibration's own board poses at its estimate with its σ̂: every
    // device gets a finite worst uncertainty. (Agreement with the solve's own covariance
    // is the next test's: here the solve also has views steeper than `sightings` allows.)
    let rig = SyntheticRig::paper(5, 0.1, 3);
    let cal = calibration(&rig, 5);
    let sol = &cal.solution;
    let predicted =
        super::predicted_worst(&cal, &cal.devices, &sol.boards, sol.sigma, MIN_VIEWS, 0.0);
    assert!(predicted.iter().all(|p| p.is_some_and(f64::is_finite)));
    // Fewer poses than asked for: nothing is predicted.
    let none = super::predicted_worst(&cal, &cal.devices, &sol.boards, sol.sigma, 6, 0.0);
    assert!(none.iter().all(Option::is_none));
    // Three of the poses predict more uncertainty than all five, every device counted
    // (devices left out are held, which would lower the others' uncertainty).
    let three = super::predicted_worst(&cal, &cal.devices, &sol.boards[..3], sol.sigma, 1, 0.0);
    let five = super::predicted_worst(&cal, &cal.devices, &sol.boards, sol.sigma, 1, 0.0);
    for (t, f) in three.iter().zip(&five) {
        assert!(t.unwrap() > f.unwrap(), "{t:?} vs {f:?}");
    }
}

#[test]
fn first_pose_advice_names_the_devices_left_out_until_the_first_calibration() {
    let seen = [("cam0", 2), ("cam1", 1), ("proj0", 2)];
    let first = first_pose_advice(0, 3, &[("cam0", 0)]).unwrap();
    assert!(first.contains("1 of 3") && first.contains("every camera shows it"));
    assert!(!first.contains("turned"), "{first}");
    let third = first_pose_advice(2, 3, &seen).unwrap();
    assert!(
        third.contains("3 of 3") && third.contains("turned as far"),
        "{third}"
    );
    assert!(
        third.ends_with("not seen in every pose so far: cam1 (1 of 2)."),
        "{third}"
    );
    // From the pose that completes the first calibration's set on, the guidance speaks.
    assert_eq!(first_pose_advice(3, 3, &seen), None);
}

#[test]
fn the_first_poses_show_the_board_to_every_device_each_turned_from_the_others() {
    let text = include_str!("../../../rigs/sim-paper.toml");
    let rig = crate::rig::file::RigFile::parse(text, "sim-paper.toml").unwrap();
    let world = crate::rig::sim::SimWorld::new(&rig, rig.board().unwrap()).unwrap();
    let (truth, ref_rig) = operator::truth_devices(&world);
    let schedule: Vec<Isometry3<f64>> = world.board_poses.iter().map(|b| ref_rig * b).collect();
    let board = &world.board;
    let mut placed: Vec<Isometry3<f64>> = Vec::new();
    for k in 0..operator::START_POSES {
        let pose = operator::first_pose(board, &truth, &placed, &schedule).unwrap();
        assert_eq!(
            operator::devices_showing(board, &truth, &pose),
            truth.len(),
            "pose {k}"
        );
        // Turned from every earlier pose by more than the candidates' 20° step: a
        // different orientation for Zhang's method in every device.
        for p in &placed {
            let turn = pose.rotation.angle_to(&p.rotation).to_degrees();
            assert!(turn > 20.0, "pose {k}: {turn}° from an earlier pose");
        }
        placed.push(pose);
    }
}

#[test]
fn prediction_from_scratch_matches_the_solve_with_the_same_observations() {
    // The synthetic rig observes a side from any angle it faces a device; `sightings` only
    // within MAX_VIEW_ANGLE_DEG. With the rig's observations cut to that rule, the solve's
    // own covariance and the from-scratch prediction at its estimate (same board poses, σ̂)
    // see the same Jacobians, so they must agree to the linearisation's precision.
    let mut rig = SyntheticRig::paper(5, 0.1, 3);
    let cos = MAX_VIEW_ANGLE_DEG.to_radians().cos();
    let (devices, boards, board) = (rig.devices.clone(), rig.boards.clone(), rig.board.clone());
    let within = |d: usize, pose: usize, side: Side| {
        let t = devices[d].pose * boards[pose] * board.side_transform(side);
        let eye = (t.inverse() * Point3::origin()).coords;
        eye.z > cos * eye.norm()
    };
    let before = rig.observations.len();
    rig.observations.retain(|o| {
        within(o.device, o.pose, o.side) && o.via.is_none_or(|v| within(v.camera, o.pose, o.side))
    });
    eprintln!(
        "{} of {before} observations within the view angle",
        rig.observations.len()
    );
    let cal = calibration(&rig, 5);
    let sol = &cal.solution;
    let solved = guide(&cal, &device_infos(&cal), 1e9);
    let predicted =
        super::predicted_worst(&cal, &cal.devices, &sol.boards, sol.sigma, MIN_VIEWS, 0.0);
    for (s, p) in solved.devices.iter().zip(&predicted) {
        let (name, s, p) = (&s.name, s.worst.unwrap(), p.unwrap());
        eprintln!("{name}: solve {s:.4} px, predicted {p:.4} px");
        assert!((p / s - 1.0).abs() < 0.05, "solve {s} px, predicted {p} px");
    }
}
