//! The guidance loop of a run: the processed poses' views come in as the run makes them;
//! each device's coverage is counted; after each calibration pose (from the third on) an
//! interim calibration runs on a worker thread (never the capture thread) from every view
//! so far, requests that pile up while one runs skipped to the latest; its [`Guidance`] and
//! the done rule give the [`Verdict`], which goes to whoever listens (the console shows it,
//! a guided simulated operator follows it through a [`GuidanceWatch`]).
//!
//! Takes the board, the rig's devices, the threshold and the run's processed poses; gives
//! [`Verdict`]s.

use super::stats::{observations, DeviceStats};
use super::verdict::Verdict;
use super::{guide, Guidance};
use crate::app::calibrate::MIN_CALIBRATION_POSES;
use crate::app::lock;
use crate::app::process::PoseViews;
use crate::board::Board;
use crate::calib::geometric::{calibrate_registering, GeometricParams};
use crate::calib::solve::CalibrateOptions;
use crate::calib::CalibError;
use crate::observations::{CameraView, DeviceInfo};
use crossbeam_channel::{unbounded, Sender};
use std::collections::BTreeSet;
use std::sync::{Arc, Condvar, Mutex};

/// One interim calibration to run.
struct Request {
    board: Board,
    devices: Vec<DeviceInfo>,
    /// Every calibration view so far.
    views: Vec<CameraView>,
    /// Board poses the views' indices refer to.
    poses: usize,
    /// Done threshold (px).
    threshold: f64,
}

/// Who hears each new verdict.
type Listener = Box<dyn Fn(&Verdict) + Send>;

/// What the loop, its worker and its watchers share.
#[derive(Default)]
struct Shared {
    verdict: Mutex<Verdict>,
    /// The pose being placed, and whether the run places poses itself (for the advice).
    placing: Mutex<(Option<usize>, bool)>,
    /// The poses covered by the latest interim calibration asked for, and the latest done.
    interim: Mutex<(usize, usize)>,
    interim_done: Condvar,
    listeners: Mutex<Vec<Listener>>,
}

impl Shared {
    /// Judge the verdict and tell every listener.
    fn publish(&self, verdict: &mut Verdict) {
        let (pose, auto) = *lock(&self.placing);
        verdict.judge(pose, auto);
        for l in lock(&self.listeners).iter() {
            l(verdict);
        }
    }
}

/// The guidance loop of one run.
pub struct Guide {
    shared: Arc<Shared>,
    board: Board,
    devices: Vec<DeviceInfo>,
    /// Every calibration view so far, and the poses they come from.
    views: Vec<CameraView>,
    poses: BTreeSet<usize>,
    worker: Option<Sender<Request>>,
}

impl Guide {
    /// The loop for `devices` (cameras first) of a rig with `board`, done below
    /// `threshold` px; `auto`: the run places poses itself (no first-pose advice).
    pub fn start(board: Board, devices: Vec<DeviceInfo>, threshold: f64, auto: bool) -> Guide {
        let shared = Arc::new(Shared::default());
        *lock(&shared.placing) = (None, auto);
        {
            let mut v = lock(&shared.verdict);
            v.threshold = threshold;
            v.devices = devices.iter().map(DeviceStats::new).collect();
            shared.publish(&mut v);
        }
        let (tx, rx) = unbounded::<Request>();
        let sh = Arc::clone(&shared);
        let spawned = std::thread::Builder::new()
            .name("guide".into())
            .spawn(move || {
                while let Ok(mut r) = rx.recv() {
                    while let Ok(later) = rx.try_recv() {
                        r = later;
                    }
                    finished(&sh, r.poses, interim(&r));
                }
            });
        Guide {
            shared,
            board,
            devices,
            views: Vec::new(),
            poses: BTreeSet::new(),
            worker: spawned.ok().map(|_| tx),
        }
    }

    /// Hear every verdict from now on, starting with the current one (called on the thread
    /// that changed it).
    pub fn listen(&self, listener: impl Fn(&Verdict) + Send + 'static) {
        listener(&lock(&self.shared.verdict));
        lock(&self.shared.listeners).push(Box::new(listener));
    }

    /// A watcher of the interim calibrations, for a guided simulated operator.
    pub fn watch(&self) -> GuidanceWatch {
        GuidanceWatch {
            shared: Arc::clone(&self.shared),
        }
    }

    /// Pose `pose` is being placed.
    pub fn placing(&self, pose: usize) {
        lock(&self.shared.placing).0 = Some(pose);
        self.shared.publish(&mut lock(&self.shared.verdict));
    }

    /// One processed pose: its views counted per device, and, a calibration pose from the
    /// [`MIN_CALIBRATION_POSES`]th on, an interim calibration asked for.
    pub fn processed(&mut self, views: &PoseViews, held_out: bool) {
        let n = self.devices.len();
        let mut per_device = vec![(Vec::new(), Vec::new()); n];
        for view in views.stacks.iter().filter_map(|s| s.view.as_ref()) {
            for (d, (b, p)) in observations(&self.board, view, n).into_iter().enumerate() {
                per_device[d].0.extend(b);
                per_device[d].1.extend(p);
            }
        }
        let mut v = lock(&self.shared.verdict);
        for (d, (b, p)) in v.devices.iter_mut().zip(per_device) {
            d.add(&b, &p, held_out);
        }
        if !held_out {
            let new = views.stacks.iter().filter_map(|s| s.view.clone());
            self.views.extend(new);
            self.poses.insert(views.pose);
            if self.poses.len() >= MIN_CALIBRATION_POSES {
                self.request(&mut v);
            }
        }
        self.shared.publish(&mut v);
    }

    /// Ask the worker for an interim calibration of every view so far.
    fn request(&self, v: &mut Verdict) {
        let Some(worker) = &self.worker else { return };
        let poses = self.poses.last().map_or(0, |p| p + 1);
        v.guiding = true;
        lock(&self.shared.interim).0 = poses;
        let _ = worker.send(Request {
            board: self.board.clone(),
            devices: self.devices.clone(),
            views: self.views.clone(),
            poses,
            threshold: v.threshold,
        });
    }
}

/// One interim calibration and its guidance.
fn interim(r: &Request) -> Result<Guidance, CalibError> {
    let cal = calibrate_registering(
        &r.board,
        &r.devices,
        r.poses,
        &r.views,
        &CalibrateOptions::default(),
        &GeometricParams::default(),
    )?;
    Ok(guide(&cal, &r.devices, r.threshold))
}

/// An interim calibration of `poses` poses finished: its guidance (or why none) into the
/// verdict, and the watchers woken.
fn finished(shared: &Shared, poses: usize, outcome: Result<Guidance, CalibError>) {
    let mut v = lock(&shared.verdict);
    v.guiding = false;
    match outcome {
        Ok(g) => {
            v.guidance = Some(g);
            v.guidance_error = None;
        }
        Err(e) => v.guidance_error = Some(format!("interim calibration: {e}")),
    }
    shared.publish(&mut v);
    drop(v);
    let mut i = lock(&shared.interim);
    i.1 = i.1.max(poses);
    shared.interim_done.notify_all();
}

/// Waits for the guidance loop's interim calibrations (a guided simulated operator follows
/// them).
#[derive(Clone)]
pub struct GuidanceWatch {
    shared: Arc<Shared>,
}

impl GuidanceWatch {
    /// Once every interim calibration asked for so far has finished (or `stopped` says to
    /// give up): the latest guidance, and whether the verdict is done.
    pub fn latest(&self, stopped: &dyn Fn() -> bool) -> (Option<Guidance>, bool) {
        let mut i = lock(&self.shared.interim);
        while i.1 < i.0 && !stopped() {
            i = match self
                .shared
                .interim_done
                .wait_timeout(i, std::time::Duration::from_millis(100))
            {
                Ok((i, _)) => i,
                Err(e) => e.into_inner().0,
            };
        }
        drop(i);
        let v = lock(&self.shared.verdict);
        (v.guidance.clone(), v.done)
    }
}
