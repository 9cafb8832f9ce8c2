//! `hexcal bench guide`: a guided operator against a fixed schedule on a simulated rig.
//!
//! Takes a rig file with simulated devices and `[poses]` (its fixed schedule); gives, for
//! the fixed schedule, for an operator who places each pose where the console's first-pose
//! advice and then its guidance ([`crate::app::guide`]) lead (with placement noise), and
//! for an oracle, every device's worst projection uncertainty after each pose, the poses
//! needed until every device is below the rig's threshold with its image covered and
//! until the worst is down to the fixed schedule's after all its poses, and the accuracy
//! against the ground truth at both.
//!
//! The board is observed at the level of calibration input: every circle centre a device
//! would see (cameras: the ellipse centre, §8) plus Gaussian noise, projectors through the
//! camera that sees the circle, both sides by the cameras that face them. Image rendering,
//! decoding and detection are left out (they are what `hexcal run` times), so both
//! operators get the same observation model.

use crate::app::guide::operator::{
    aim, first_pose, placed, placed_in_view, truth_devices, START_POSES,
};
use crate::app::guide::{candidates, guide, predicted_worst, sightings, Guidance, MIN_SEEN};
use crate::app::truth::{check_truth, TruthCheck};
use crate::app::AppError;
use crate::board::{Board, Side};
use crate::calib::bundle::Device;
use crate::calib::circle::ellipse_center;
use crate::calib::diagnostics::coverage;
use crate::calib::geometric::{calibrate_registering, GeometricParams};
use crate::calib::solve::{CalibrateOptions, Calibration};
use crate::calib::zhang::MIN_VIEWS;
use crate::observations::DeviceInfo;
use crate::observations::{CameraView, Frame, ProjectorPixel, ViewPoint};
use crate::rig::file::RigFile;
use crate::rig::sim::SimWorld;
use nalgebra::{Isometry3, Vector2};
use rand::{rngs::StdRng, SeedableRng};
use rand_distr::{Distribution, Normal};
use std::path::Path;

/// A device is covered when at most this fraction of its image cells is empty (the
/// console's 30 % covered rule on the report's cell grid).
const MAX_EMPTY: f64 = 0.7;

/// One operator's run.
#[derive(Clone, Debug)]
pub struct OperatorRun {
    /// "fixed", "guided" or "oracle".
    pub label: &'static str,
    /// After each pose from [`START_POSES`] on: (poses, worst uncertainty over every
    /// device, px; infinite while a device is not calibrated).
    pub worst: Vec<(usize, f64)>,
    /// Poses until done (every device below the threshold and covered), if reached.
    pub done_at: Option<usize>,
    /// Accuracy against the truth at `done_at` (or after the last pose).
    pub truth: Vec<TruthCheck>,
    /// Poses until the worst uncertainty is at most the fixed schedule's after its last
    /// pose (the same uncertainty), if reached.
    pub matched_at: Option<usize>,
    /// Accuracy against the truth at `matched_at` (or after the last pose).
    pub truth_matched: Vec<TruthCheck>,
    /// Seconds of interim calibration and guidance (the oracle: interim calibration only),
    /// per pose (mean).
    pub seconds_per_pose: f64,
}

/// What [`bench_guide`] measured.
#[derive(Clone, Debug)]
pub struct GuideBench {
    /// The threshold (px).
    pub threshold: f64,
    /// Observation noise (px).
    pub sigma: f64,
    /// The fixed schedule's worst uncertainty after its last pose (px): the target of
    /// [`OperatorRun::matched_at`].
    pub fixed_final: f64,
    /// Both operators.
    pub runs: Vec<OperatorRun>,
}

/// The noisy views `truth` gives of the board at T_ref_board `pose` (pose index `k`).
fn observe(
    board: &Board,
    truth: &[Device],
    k: usize,
    pose: &Isometry3<f64>,
    noise: &Normal<f64>,
    rng: &mut StdRng,
) -> Vec<CameraView> {
    let back = board.side_transform(Side::Back);
    let mut n = || Vector2::new(noise.sample(rng), noise.sample(rng));
    let mut views: Vec<CameraView> = Vec::new();
    for s in sightings(board, truth, &back, pose) {
        match s.via {
            None => {
                let dev = &truth[s.device];
                let t = dev.pose * pose * board.side_transform(s.side);
                let Some(e) = ellipse_center(&dev.model, &t, board.position(s.hex), board.radius)
                else {
                    continue;
                };
                let point = ViewPoint {
                    hex: s.hex,
                    image: e + n(),
                    projectors: Vec::new(),
                };
                match views.last_mut() {
                    Some(v) if v.camera == s.device && v.frame == Frame::Anchored(s.side) => {
                        v.points.push(point)
                    }
                    _ => views.push(CameraView {
                        camera: s.device,
                        pose: k,
                        frame: Frame::Anchored(s.side),
                        points: vec![point],
                    }),
                }
            }
            Some(c) => {
                let Some(v) = views.last_mut().filter(|v| v.camera == c) else {
                    continue;
                };
                let Some(p) = v.points.last_mut() else {
                    continue;
                };
                if p.hex == s.hex {
                    p.projectors.push(ProjectorPixel {
                        projector: s.device,
                        pixel: s.pixel + n(),
                    });
                }
            }
        }
    }
    views
}

/// The interim calibration of `views` and its guidance towards `aim` (px: the operator
/// goes on to it past done); done (below `threshold`) also needs every device's image
/// covered.
fn interim(
    board: &Board,
    devices: &[DeviceInfo],
    poses: usize,
    views: &[CameraView],
    (threshold, aim): (f64, f64),
) -> Result<(Calibration, Guidance, bool), AppError> {
    let cal = calibrate_registering(
        board,
        devices,
        poses,
        views,
        &CalibrateOptions::default(),
        &GeometricParams::default(),
    )?;
    let g = guide(&cal, devices, threshold.min(aim));
    let covered = cal.excluded.is_empty() && coverage(&cal).iter().all(|c| c.0 <= MAX_EMPTY);
    let done = covered && worst(&g) <= threshold;
    Ok((cal, g, done))
}

/// The worst uncertainty of `g` (infinite while a device is not calibrated).
fn worst(g: &Guidance) -> f64 {
    g.devices
        .iter()
        .map(|d| d.worst.unwrap_or(f64::INFINITY))
        .fold(0.0, f64::max)
}

/// Everything one operator's loop needs.
struct Setup<'a> {
    board: &'a Board,
    world: &'a SimWorld,
    truth: &'a [Device],
    devices: &'a [DeviceInfo],
    /// The fixed schedule, T_ref_board.
    schedule: &'a [Isometry3<f64>],
    threshold: f64,
    noise: Normal<f64>,
}

/// One operator: the whole schedule (`guided` false), or the first-pose advice for the
/// first [`START_POSES`] and then the guidance's suggestions, until done with the worst
/// uncertainty at most `target` (the same uncertainty as the fixed schedule's) or
/// `max_poses`.
fn operate(
    s: &Setup,
    guided: bool,
    (max_poses, target): (usize, f64),
    seed: u64,
    log: &mut dyn FnMut(&str),
) -> Result<OperatorRun, AppError> {
    let mut rng = StdRng::seed_from_u64(seed);
    let (mut views, mut poses) = (Vec::new(), Vec::new());
    let mut run = OperatorRun::new(if guided { "guided" } else { "fixed" });
    let max = if guided { max_poses } else { s.schedule.len() };
    let mut next = s.schedule[0];
    let mut seconds = 0.0;
    for k in 0..max {
        let pose = match (guided, k < START_POSES) {
            (false, _) => s.schedule[k],
            (true, true) => {
                let first = first_pose(s.board, s.truth, &poses, s.schedule);
                placed_in_view(s.board, s.truth, &first.unwrap_or(s.schedule[k]), &mut rng)
            }
            (true, false) => placed(&next, &mut rng),
        };
        poses.push(pose);
        views.extend(observe(s.board, s.truth, k, &pose, &s.noise, &mut rng));
        if k + 1 < START_POSES {
            continue;
        }
        let t = std::time::Instant::now();
        let (cal, g, done) = interim(s.board, s.devices, k + 1, &views, (s.threshold, target))?;
        seconds += t.elapsed().as_secs_f64();
        log(&format!(
            "{}: {} poses, worst {:.3} px{}",
            run.label,
            k + 1,
            worst(&g),
            g.suggestion
                .as_ref()
                .map_or(String::new(), |s| format!("; next: {}", s.sentence))
        ));
        if run.record(k + 1, &g, done, target, &check_truth(&cal, s.world)) && guided {
            break;
        }
        match aim(&g, s.truth, s.schedule) {
            Some(pose) => next = pose,
            None if guided => break,
            None => {}
        }
    }
    run.seconds_per_pose = seconds / run.worst.len().max(1) as f64;
    Ok(run)
}

impl OperatorRun {
    fn new(label: &'static str) -> OperatorRun {
        OperatorRun {
            label,
            worst: Vec::new(),
            done_at: None,
            truth: Vec::new(),
            matched_at: None,
            truth_matched: Vec::new(),
            seconds_per_pose: 0.0,
        }
    }

    /// Record the interim calibration after `poses` (guidance `g`, `done`, accuracy
    /// `truth`) against the same-uncertainty `target`; whether both marks are reached.
    fn record(
        &mut self,
        poses: usize,
        g: &Guidance,
        done: bool,
        target: f64,
        truth: &[TruthCheck],
    ) -> bool {
        self.worst.push((poses, worst(g)));
        if self.done_at.is_none() {
            self.truth = truth.to_vec();
            self.done_at = done.then_some(poses);
        }
        if self.matched_at.is_none() {
            self.truth_matched = truth.to_vec();
            self.matched_at = (worst(g) <= target).then_some(poses);
        }
        self.done_at.is_some() && self.matched_at.is_some()
    }
}

/// The oracle's weak prior while devices are seen in fewer than [`MIN_VIEWS`] poses (a
/// fraction of each parameter's information): a direction those poses leave free then
/// counts as a large uncertainty rather than none, so a pose that repeats one already
/// chosen ranks low.
const EARLY_RIDGE: f64 = 1e-6;

/// How the oracle ranks a set of poses by their predicted worst uncertainties: first by
/// the poses still missing for devices to be calibrated at all, then (while some are
/// missing: predicted with [`EARLY_RIDGE`], every device seen once counting) by the sum of
/// the logs of the worst uncertainties, else by the worst over every device.
fn rank(predicted: &[Option<f64>], poses_seen: &[usize]) -> (usize, f64) {
    let missing: usize = poses_seen
        .iter()
        .map(|&n| MIN_VIEWS.saturating_sub(n))
        .sum();
    let score = match missing {
        0 => predicted
            .iter()
            .map(|w| w.unwrap_or(f64::INFINITY))
            .fold(0.0, f64::max),
        _ => predicted.iter().flatten().map(|w| w.max(1e-9).ln()).sum(),
    };
    (missing, score)
}

/// Poses (of at least [`MIN_SEEN`] points) in which each of `truth` sees the board at
/// T_ref_board `pose`.
fn seen_by(board: &Board, truth: &[Device], pose: &Isometry3<f64>) -> Vec<usize> {
    let back = board.side_transform(Side::Back);
    let seen = sightings(board, truth, &back, pose);
    (0..truth.len())
        .map(|d| usize::from(seen.iter().filter(|s| s.device == d).count() >= MIN_SEEN))
        .collect()
}

/// The oracle: knowing the rig's truth from the first pose on, each next pose is the
/// candidate (the guidance's candidates around the schedule, and the schedule's own
/// poses) whose predicted uncertainties at the truth rank best ([`rank`]), placed without
/// error; observed and calibrated as the other operators' poses are, until done with the
/// worst uncertainty at most `target` or `max_poses`.
fn oracle(
    s: &Setup,
    (max_poses, target): (usize, f64),
    seed: u64,
    log: &mut dyn FnMut(&str),
) -> Result<OperatorRun, AppError> {
    use rayon::prelude::*;
    let mut rng = StdRng::seed_from_u64(seed);
    // The parameter layout: the calibration of the whole fixed schedule.
    let mut all = Vec::new();
    for (k, pose) in s.schedule.iter().enumerate() {
        all.extend(observe(s.board, s.truth, k, pose, &s.noise, &mut rng));
    }
    let (layout, _, _) = interim(
        s.board,
        s.devices,
        s.schedule.len(),
        &all,
        (s.threshold, s.threshold),
    )?;
    if layout.devices.len() != s.truth.len() {
        return Err(AppError::Input(
            "the oracle needs every device calibrated by the fixed schedule".into(),
        ));
    }
    let truth: Vec<Device> = layout
        .device_index
        .iter()
        .map(|&i| s.truth[i].clone())
        .collect();
    let mut pool = candidates(s.schedule);
    pool.extend_from_slice(s.schedule);
    let sigma = s.noise.std_dev();
    let mut run = OperatorRun::new("oracle");
    let (mut chosen, mut seen, mut views) = (Vec::new(), vec![0usize; truth.len()], Vec::new());
    let mut rng = StdRng::seed_from_u64(seed);
    let mut seconds = 0.0;
    for k in 0..max_poses {
        let best = pool
            .par_iter()
            .map(|c| {
                let mut poses = chosen.clone();
                poses.push(*c);
                let n: Vec<usize> = seen_by(s.board, &truth, c)
                    .iter()
                    .zip(&seen)
                    .map(|(a, b)| a + b)
                    .collect();
                let missing = n.iter().any(|&n| n < MIN_VIEWS);
                let (min, ridge) = if missing {
                    (1, EARLY_RIDGE)
                } else {
                    (MIN_VIEWS, 0.0)
                };
                let w = predicted_worst(&layout, &truth, &poses, sigma, min, ridge);
                let r = rank(&w, &n);
                (*c, n, r)
            })
            .min_by(|a, b| a.2 .0.cmp(&b.2 .0).then(a.2 .1.total_cmp(&b.2 .1)));
        let Some((pose, n, (missing, score))) = best else {
            break;
        };
        log(&format!(
            "oracle: pose {}: predicted {} poses missing, score {score:.3}; seen in {n:?}",
            k + 1,
            missing
        ));
        chosen.push(pose);
        seen = n;
        views.extend(observe(s.board, s.truth, k, &pose, &s.noise, &mut rng));
        if k + 1 < MIN_VIEWS {
            continue;
        }
        let t = std::time::Instant::now();
        let solved = interim(s.board, s.devices, k + 1, &views, (s.threshold, target));
        seconds += t.elapsed().as_secs_f64();
        let (cal, g, done) = match solved {
            Ok(i) => i,
            Err(e) => {
                log(&format!("oracle: {} poses: {e}", k + 1));
                run.worst.push((k + 1, f64::INFINITY));
                continue;
            }
        };
        log(&format!(
            "oracle: {} poses, worst {:.3} px",
            k + 1,
            worst(&g)
        ));
        if run.record(k + 1, &g, done, target, &check_truth(&cal, s.world)) {
            break;
        }
    }
    run.seconds_per_pose = seconds / run.worst.len().max(1) as f64;
    Ok(run)
}

/// The three operators on the rig file at `rig_path`: the fixed schedule to its end, then
/// the guided operator and the oracle until done and at the fixed schedule's final worst
/// uncertainty, or `max_poses`; observation noise `sigma` (px), noise from `seed`; `log`
/// hears each interim calibration.
pub fn bench_guide(
    rig_path: &Path,
    sigma: f64,
    max_poses: usize,
    seed: u64,
    log: &mut dyn FnMut(&str),
) -> Result<GuideBench, AppError> {
    let rig = RigFile::load(rig_path)?;
    let board = Board::resolve(&rig.board)?;
    let world = SimWorld::new(&rig, board.clone()).map_err(|e| AppError::Input(e.to_string()))?;
    if world.cameras.is_empty() || world.board_poses.len() < START_POSES {
        return Err(AppError::Input(format!(
            "{}: needs simulated cameras and at least {START_POSES} [poses]",
            rig_path.display()
        )));
    }
    let (truth, ref_rig) = truth_devices(&world);
    let devices: Vec<DeviceInfo> = truth.iter().map(DeviceInfo::from).collect();
    let schedule: Vec<Isometry3<f64>> = world.board_poses.iter().map(|b| ref_rig * b).collect();
    let setup = Setup {
        board: &board,
        world: &world,
        truth: &truth,
        devices: &devices,
        schedule: &schedule,
        threshold: rig.guidance.uncertainty_px,
        noise: Normal::new(0.0, sigma).map_err(|e| AppError::Input(e.to_string()))?,
    };
    // The fixed schedule runs to its end; its last worst is the others' target.
    let mut fixed = operate(
        &setup,
        false,
        (schedule.len(), f64::NEG_INFINITY),
        seed,
        log,
    )?;
    let fixed_final = fixed.worst.last().map_or(f64::INFINITY, |w| w.1);
    fixed.matched_at = fixed.worst.last().map(|w| w.0);
    let guided = operate(&setup, true, (max_poses, fixed_final), seed, log)?;
    let oracle = oracle(&setup, (max_poses, fixed_final), seed, log)?;
    Ok(GuideBench {
        threshold: setup.threshold,
        sigma,
        fixed_final,
        runs: vec![fixed, guided, oracle],
    })
}
