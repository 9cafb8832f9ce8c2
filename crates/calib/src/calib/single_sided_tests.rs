//! A single-sided board (issue 32, item 5): no back-side parameter anywhere, and the same
//! accuracy as the double-sided board's front-only solve on the same data.

use super::bundle::{adjust, Options, Problem};
use super::observability::Unobserved;
use super::solve::{calibrate, CalibrateOptions};
use super::synthetic::{bonferroni_bound, run_rig, worst_deviation, Start, SyntheticRig};
use super::CalibError;
use hexcal_core::board::Side;
use hexcal_core::observations::Frame;

/// Simulated noise (px).
const SIGMA: f64 = 0.1;

/// Every camera on one side, the board turned over in the odd poses: the front-only data of
/// the double-sided board (the even poses, renumbered), and the same observations on its
/// single-sided print.
pub(crate) fn rigs(seed: u64) -> (SyntheticRig, SyntheticRig) {
    let mut double = SyntheticRig::one_sided(3, 0, 8, SIGMA, seed);
    double.observations.retain(|ob| ob.side == Side::Front);
    assert!(double.observations.iter().all(|ob| ob.pose % 2 == 0));
    for ob in &mut double.observations {
        ob.pose /= 2;
    }
    double.boards = double.boards.iter().step_by(2).copied().collect();
    let single = SyntheticRig {
        board: double.board.front_only(),
        ..double.clone()
    };
    (double, single)
}

/// From the same start, the single-sided board's adjustment is the double-sided front-only
/// one without the side transform: no columns for it, no note, no value; every estimate the
/// same, and within the Bonferroni bound of the truth.
#[test]
fn single_sided_board_adjusts_without_side_parameters() {
    let (double, single) = rigs(5);
    let start = |rig: &SyntheticRig| Problem {
        observations: rig.observations.clone(),
        ..rig.perturbed_start(6)
    };
    let o = Options::default();
    let a = adjust(&start(&double), &o).unwrap();
    let b = adjust(&start(&single), &o).unwrap();
    assert_eq!(a.held, [Unobserved::SideTransformOneSideSeen]);
    assert!(a.front_back.is_some() && a.side_index.is_none());
    assert!(b.held.is_empty(), "{:?}", b.held);
    assert!(b.front_back.is_none() && b.side_index.is_none());
    assert_eq!(a.dof, b.dof);
    assert_eq!(a.covariance.len(), b.covariance.len());
    assert!(
        (a.sigma / b.sigma - 1.0).abs() < 1e-9,
        "{} {}",
        a.sigma,
        b.sigma
    );
    for (x, y) in a.devices.iter().zip(&b.devices) {
        let (u, v) = (x.model.lens_vector(), y.model.lens_vector());
        let scale = u.norm();
        let diff = (u - v).norm() / scale;
        assert!(diff < 1e-9, "{}: lens differs by {diff:e}", x.name);
    }
    let devices: Vec<_> = single.devices.iter().collect();
    let boards: Vec<_> = single.boards.iter().collect();
    let nominal = double.board.side_transform(Side::Back);
    let ((z, name), m) = worst_deviation(&b, &devices, &boards, &nominal);
    assert!(
        z <= bonferroni_bound(m),
        "{name} is {z:.2}σ off ({m} parameters)"
    );
    assert!((b.sigma / SIGMA - 1.0).abs() <= 0.02, "σ̂ {}", b.sigma);
}

/// As `hexcal calibrate` runs (Zhang, pose graph, adjustment): the single-sided board
/// passes the grid's accuracy rule as the double-sided front-only data do, with the same
/// σ̂ (its calibration file: `report::tests`).
#[test]
fn single_sided_board_calibrates_as_the_front_only_solve() {
    let (double, single) = rigs(7);
    let a = run_rig(double, Start::Real, 7).unwrap();
    let b = run_rig(single.clone(), Start::Real, 7).unwrap();
    for (what, r) in [("double-sided, front only", &a), ("single-sided", &b)] {
        eprintln!(
            "{what}: σ̂ {:.5} px, worst {:.2}σ ({}), dof {:?}",
            r.posterior_sigma, r.worst_z.0, r.worst_z.1, r.dof
        );
    }
    assert!(a.passes(SIGMA) && b.passes(SIGMA), "{a:?}\n{b:?}");
    assert_eq!(a.held, [Unobserved::SideTransformOneSideSeen]);
    assert!(b.held.is_empty());
    assert_eq!(a.dof, b.dof);
    assert!((a.posterior_sigma / b.posterior_sigma - 1.0).abs() < 1e-6);
}

/// Views or observations on the back of a single-sided board are refused: the view's JSON
/// path for the calibration input, a sentence for the adjustment.
#[test]
fn the_back_of_a_single_sided_board_is_refused() {
    let rig = SyntheticRig::one_sided(1, 0, 6, SIGMA, 3);
    let board = rig.board.front_only();
    let views = rig.views();
    let i = views
        .iter()
        .position(|v| v.frame == Frame::Anchored(Side::Back))
        .expect("the one-sided rig shows the back in odd poses");
    let e = calibrate(
        &board,
        &rig.device_infos(),
        rig.boards.len(),
        &views,
        &CalibrateOptions::default(),
    )
    .unwrap_err();
    assert!(matches!(e, CalibError::Input(_)), "{e}");
    let msg = e.to_string();
    assert!(msg.contains(&format!("views[{i}].frame")), "{msg}");
    assert!(msg.contains("hex600-front is single-sided"), "{msg}");
    let p = Problem {
        board,
        ..rig.perturbed_start(4)
    };
    let e = adjust(&p, &Options::default()).unwrap_err();
    assert!(
        e.to_string().contains("back of a single-sided board"),
        "{e}"
    );
}
