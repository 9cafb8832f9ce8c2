//! The console's interim calibrations: after each processed pose, a worker thread (never the
//! capture thread) calibrates from every view so far and turns the result into
//! [`Guidance`] for the page. Requests that pile up while one runs are skipped to the latest.
//!
//! Takes the views of the processed calibration poses; gives [`Guidance`] through a callback.

use crate::app::guide::{guide, Guidance};
use crate::board::Board;
use crate::calib::geometric::{calibrate_registering, GeometricParams};
use crate::calib::solve::CalibrateOptions;
use crate::observations::CameraView;
use crate::observations::DeviceInfo;
use crossbeam_channel::{unbounded, Sender};
use std::thread::JoinHandle;

/// One interim calibration to run.
pub struct Request {
    /// The board.
    pub board: Board,
    /// The rig's devices (cameras first).
    pub devices: Vec<DeviceInfo>,
    /// Every calibration view so far.
    pub views: Vec<CameraView>,
    /// Board poses the views' indices refer to.
    pub poses: usize,
    /// Done threshold (px).
    pub threshold: f64,
}

/// What an interim calibration gave: guidance, or why there is none yet.
pub type Outcome = Result<Guidance, String>;

/// The worker thread and its queue.
pub struct Worker {
    tx: Option<Sender<Request>>,
    thread: Option<JoinHandle<()>>,
}

impl Worker {
    /// Start the worker; `done` receives each outcome with its request's `poses` (on the
    /// worker's thread).
    pub fn start(done: impl Fn(usize, Outcome) + Send + 'static) -> Worker {
        let (tx, rx) = unbounded::<Request>();
        let thread = std::thread::Builder::new()
            .name("console-guide".into())
            .spawn(move || {
                while let Ok(mut r) = rx.recv() {
                    while let Ok(later) = rx.try_recv() {
                        r = later;
                    }
                    done(r.poses, run(&r));
                }
            })
            .ok();
        Worker {
            tx: Some(tx),
            thread,
        }
    }

    /// Ask for an interim calibration (dropped when the worker is gone).
    pub fn request(&self, r: Request) {
        if let Some(tx) = &self.tx {
            let _ = tx.send(r);
        }
    }
}

impl Drop for Worker {
    /// Stop taking requests; the calibration under way finishes on its own (it is not
    /// waited for: the run must not wait on its console).
    fn drop(&mut self) {
        self.tx.take();
        self.thread.take();
    }
}

/// One interim calibration and its guidance.
fn run(r: &Request) -> Outcome {
    let cal = calibrate_registering(
        &r.board,
        &r.devices,
        r.poses,
        &r.views,
        &CalibrateOptions::default(),
        &GeometricParams::default(),
    )
    .map_err(|e| format!("interim calibration: {e}"))?;
    Ok(guide(&cal, &r.devices, r.threshold))
}
