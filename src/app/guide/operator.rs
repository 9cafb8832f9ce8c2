//! A simulated operator who follows the guidance (issue 19: "the simulated board goes where
//! the console suggests, with some placement noise"), shared by `hexcal run --guided` on a
//! simulated rig and `hexcal bench guide`.
//!
//! Takes the simulated world (its devices' truth and its `[poses]` schedule) and each
//! interim calibration's [`Guidance`]; gives the next board pose: for the first
//! [`START_POSES`] (no interim calibration exists before them) a pose placed as the
//! console's first-pose advice asks ([`first_pose`]: every device shows the board live,
//! turned unlike the poses so far), then the board turned to face a device that is not
//! calibrated yet when there is one, else the suggested pose, each placed with
//! [`PLACEMENT_DEG`] / [`PLACEMENT_MM`] of error as a person aiming at it would.

use super::{candidates, sightings, Guidance, MIN_SEEN};
use crate::board::{Board, Side};
use crate::calib::bundle::Device;
use crate::observations::DeviceKind;
use crate::rig::sim::SimWorld;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{rngs::StdRng, SeedableRng};
use rand_distr::{Distribution, Normal};

/// Placement noise of the guided operator: rotation (deg, 1σ about a random axis).
pub const PLACEMENT_DEG: f64 = 3.0;
/// Placement shift noise (mm, 1σ per axis).
pub const PLACEMENT_MM: f64 = 15.0;

/// The calibration poses the first interim calibration needs: the guided operator places
/// these by the first-pose advice ([`first_pose`]), as no interim calibration exists yet.
pub const START_POSES: usize = 3;

/// The simulated rig's truth as calibration devices, poses relative to the first camera
/// (the calibration's reference); and T_ref_rig.
pub fn truth_devices(world: &SimWorld) -> (Vec<Device>, Isometry3<f64>) {
    let ref_rig = world
        .cameras
        .first()
        .map_or_else(Isometry3::identity, |c| c.pose);
    let kinds = world
        .cameras
        .iter()
        .map(|d| (d, DeviceKind::Camera))
        .chain(world.projectors.iter().map(|d| (d, DeviceKind::Projector)));
    let devices = kinds
        .map(|(d, kind)| Device {
            name: d.name.clone(),
            kind,
            model: d.model,
            pose: d.pose * ref_rig.inverse(),
        })
        .collect();
    (devices, ref_rig)
}

/// `pose` as placed by a person aiming at it: turned about a random axis and shifted.
pub fn placed(pose: &Isometry3<f64>, rng: &mut StdRng) -> Isometry3<f64> {
    let n = Normal::new(0.0, 1.0).expect("unit normal");
    let axis = Vector3::new(n.sample(rng), n.sample(rng), n.sample(rng));
    let turn = axis * (PLACEMENT_DEG.to_radians() / 3f64.sqrt());
    let shift = Vector3::new(n.sample(rng), n.sample(rng), n.sample(rng)) * PLACEMENT_MM;
    Isometry3::from_parts(
        Translation3::from(pose.translation.vector + shift),
        UnitQuaternion::from_scaled_axis(turn) * pose.rotation,
    )
}

/// Placements a person makes of a first pose before every device shows it (the live
/// pictures tell them when one does not).
pub const PLACEMENT_TRIES: usize = 5;

/// `pose` placed as in [`placed`] by a person who checks the live pictures: placed again
/// (at most [`PLACEMENT_TRIES`] times in all) while fewer devices show it than at `pose`.
pub fn placed_in_view(
    board: &Board,
    truth: &[Device],
    pose: &Isometry3<f64>,
    rng: &mut StdRng,
) -> Isometry3<f64> {
    let want = devices_showing(board, truth, pose);
    let mut p = placed(pose, rng);
    for _ in 1..PLACEMENT_TRIES {
        if devices_showing(board, truth, &p) >= want {
            break;
        }
        p = placed(pose, rng);
    }
    p
}

/// The board at the schedule's mean position, its front turned to face `device`.
pub fn facing(device: &Device, schedule: &[Isometry3<f64>]) -> Isometry3<f64> {
    let centre = schedule
        .iter()
        .map(|b| b.translation.vector)
        .sum::<Vector3<f64>>()
        / schedule.len().max(1) as f64;
    let eye = device.pose.inverse() * nalgebra::Point3::origin();
    let z = (eye.coords - centre).normalize();
    let r = UnitQuaternion::rotation_between(&Vector3::z(), &z).unwrap_or_else(|| {
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI)
    });
    Isometry3::from_parts(Translation3::from(centre), r)
}

/// How many of `truth` show the board at T_ref_board `pose` with at least [`MIN_SEEN`]
/// points: what the console's live pictures (cameras) and the projectors' light on the
/// board (projectors, in preview they show a flat field) tell a person at the rig.
pub fn devices_showing(board: &Board, truth: &[Device], pose: &Isometry3<f64>) -> usize {
    let seen = sightings(board, truth, &board.side_transform(Side::Back), pose);
    (0..truth.len())
        .filter(|&d| seen.iter().filter(|s| s.device == d).count() >= MIN_SEEN)
        .count()
}

/// Where a person following the console's first-pose advice ([`super::first_pose_advice`])
/// puts pose `placed.len()` (T_ref_board) before any interim calibration exists: of the
/// console's candidates around the poses so far (the schedule's first pose before any),
/// one that the most devices show, turned furthest from every pose so far (for the first
/// pose: the least turned from the schedule's, where a person would start).
pub fn first_pose(
    board: &Board,
    truth: &[Device],
    placed: &[Isometry3<f64>],
    schedule: &[Isometry3<f64>],
) -> Option<Isometry3<f64>> {
    let around = if placed.is_empty() {
        schedule.get(..1)?
    } else {
        placed
    };
    let turn = |c: &Isometry3<f64>| match placed.is_empty() {
        true => -c.rotation.angle_to(&around[0].rotation),
        false => placed
            .iter()
            .map(|p| c.rotation.angle_to(&p.rotation))
            .fold(f64::INFINITY, f64::min),
    };
    candidates(around)
        .into_iter()
        .map(|c| (devices_showing(board, truth, &c), turn(&c), c))
        .max_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)))
        .map(|(_, _, c)| c)
}

/// Where the operator aims next (T_ref_board): told to show the board to a device not
/// calibrated yet, the board turned to face that device (where it stands is known to a
/// person at the rig); else the suggested pose; `None` when the guidance suggests nothing.
pub fn aim(g: &Guidance, truth: &[Device], schedule: &[Isometry3<f64>]) -> Option<Isometry3<f64>> {
    match g.devices.iter().position(|d| d.worst.is_none()) {
        Some(d) => truth.get(d).map(|dev| facing(dev, schedule)),
        None => g.suggestion.as_ref().map(|s| s.pose),
    }
}

/// The guided operator of a simulated run (`hexcal run --guided`).
pub struct SimOperator {
    board: Board,
    truth: Vec<Device>,
    ref_rig: Isometry3<f64>,
    /// The fixed schedule, T_ref_board.
    schedule: Vec<Isometry3<f64>>,
    /// The poses placed so far, T_ref_board.
    placed: Vec<Isometry3<f64>>,
    rng: StdRng,
}

impl SimOperator {
    /// The operator of `world`, its placement noise from `seed`.
    pub fn new(world: &SimWorld, seed: u64) -> SimOperator {
        let (truth, ref_rig) = truth_devices(world);
        let schedule = world.board_poses.iter().map(|b| ref_rig * b).collect();
        SimOperator {
            board: world.board.clone(),
            truth,
            ref_rig,
            schedule,
            placed: Vec::new(),
            rng: StdRng::seed_from_u64(seed),
        }
    }

    /// T_rig_board of pose `k` and what the operator did: for the first [`START_POSES`]
    /// where the first-pose advice leads ([`first_pose`]), after them where `guidance` aims,
    /// each with placement noise; the schedule's pose when there is no guidance to follow.
    /// `None` past the schedule without guidance.
    pub fn next(
        &mut self,
        k: usize,
        guidance: Option<&Guidance>,
    ) -> Option<(Isometry3<f64>, String)> {
        let first = (k < START_POSES)
            .then(|| first_pose(&self.board, &self.truth, &self.placed, &self.schedule))
            .flatten();
        let g = guidance.filter(|_| k >= START_POSES);
        let (ref_board, what) = match (first, g.and_then(|g| aim(g, &self.truth, &self.schedule))) {
            (Some(pose), _) => (
                placed_in_view(&self.board, &self.truth, &pose, &mut self.rng),
                "as the first-pose advice asks: every device shows it, turned unlike before"
                    .to_string(),
            ),
            (None, Some(pose)) => {
                let g = g.expect("aimed by guidance");
                let what = match g.devices.iter().find(|d| d.worst.is_none()) {
                    Some(d) => format!("turned to face {} (not calibrated yet)", d.name),
                    None => g.suggestion.as_ref().map_or_else(String::new, |s| {
                        format!("where the console suggests: {}", s.sentence)
                    }),
                };
                (placed(&pose, &mut self.rng), what)
            }
            (None, None) => (*self.schedule.get(k)?, "the schedule's pose".to_string()),
        };
        self.placed.push(ref_board);
        Some((self.ref_rig.inverse() * ref_board, what))
    }
}
