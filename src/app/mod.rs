//! The application layer: the jobs a user runs, each orchestrating the stages below.
//!
//! - [`run`]: one button — capture every pose, stream each through decode, detection, grid
//!   and projector fits while the next is captured, calibrate, verify, write the outputs;
//! - [`capture`]: a rig's poses into a dataset folder;
//! - [`calibrate`]: a dataset folder or a correspondences file to a calibration;
//! - [`detect`]: circles and labelled lattice points of image files, with overlays;
//! - [`console`]: the operator console of `run --console` (a local web page), with
//!   [`guide`]: per-device projection uncertainty, the done rule and the next pose;
//! - [`script`]: a rig file's capture script (positioner moves, waits, prompts, timed
//!   captures) driving `run`, with its timeline and step timing;
//! - [`session`]: a run or capture as the operator drives it — the rig file read once, the
//!   board placed (Enter, the console's button, a guided simulated operator, a script), the
//!   console wired to the run; [`summary`]: the printed summary of a calibration;
//! - [`jobs`]: the small jobs (board, info, simulate, decode, devices);
//! - [`process`]: one camera's stack through the stages; [`truth`]: a calibration against a
//!   simulated rig's ground truth.

pub mod calibrate;
pub mod capture;
pub mod check;
pub mod console;
pub mod detect;
pub mod guide;
pub mod jobs;
pub mod process;
pub mod progress;
pub mod run;
pub mod script;
pub mod session;
pub mod show;
pub mod summary;
pub mod truth;

use std::path::PathBuf;

/// Why a job failed: the stage's own error, or the file it could not use.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    /// The rig file.
    #[error("{0}")]
    Rig(#[from] crate::rig::file::RigError),
    /// Opening the rig's devices.
    #[error("{0}")]
    Open(#[from] crate::rig::OpenError),
    /// The dataset folder.
    #[error("{0}")]
    Dataset(#[from] crate::dataset::DatasetError),
    /// The capture.
    #[error("{0}")]
    Capture(#[from] crate::capture::CaptureError),
    /// A board file.
    #[error("{0}")]
    Board(#[from] crate::board::BoardError),
    /// The calibration.
    #[error("calibration: {0}")]
    Calibration(#[from] crate::calib::CalibError),
    /// Writing the outputs.
    #[error("{0}")]
    Report(#[from] crate::report::ReportError),
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A JSON file is not what it should be.
    #[error("{path}: not a {what}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// What it should be.
        what: &'static str,
        /// The parser's message (with line and column).
        source: serde_json::Error,
    },
    /// The input cannot give what the job needs (the message names the file or setting).
    #[error("{0}")]
    Input(String),
    /// A value of an input file is wrong: the file, the value's JSON path and what is wrong.
    #[error(transparent)]
    Invalid(crate::invalid::ValidationError),
    /// Ctrl-C: the capture stopped after finishing every pose already captured.
    #[error(
        "interrupted: complete poses {kept:?} are kept; pose {place_again} was not finished: \
         place the board again and run the same command to resume"
    )]
    Interrupted {
        /// Complete poses in the dataset.
        kept: Vec<usize>,
        /// The pose to place again.
        place_again: usize,
    },
    /// Ctrl-C after the capture: the run stopped while processing or calibrating, keeping
    /// every complete pose.
    #[error(
        "stopped while {during}: complete poses {kept:?} are kept; run the same command to \
         resume (the poses still missing are captured, then everything is calibrated)"
    )]
    Stopped {
        /// What the run was doing.
        during: &'static str,
        /// Complete poses in the dataset.
        kept: Vec<usize>,
    },
    /// A capture script's step (told in one line: not a source of this error).
    #[error("script: {0}")]
    Script(script::ScriptError),
    /// A worker thread could not be started.
    #[error("cannot start a thread: {0}")]
    Spawn(std::io::Error),
    /// The output folder is another job's.
    #[error("{0}")]
    Lock(#[from] crate::lock::LockError),
    /// Ctrl-C and SIGTERM could not be taken over.
    #[error("cannot handle Ctrl-C: {0}")]
    Signals(std::io::Error),
    /// The operator console.
    #[error("{0}")]
    Console(#[from] console::ConsoleError),
    /// The scene file of a simulated view.
    #[error("{0}")]
    Sim(#[from] crate::sim::SimError),
    /// Decoding a stack folder.
    #[error("{0}")]
    Decode(#[from] crate::phase::files::DecodeFilesError),
    /// A self-test could not be done.
    #[error("self-test: {0}")]
    Check(#[from] crate::check::CheckError),
    /// The sync test a run starts with failed (the line says what to set).
    #[error("{0}")]
    SyncFailed(String),
    /// A worker thread ended without its result.
    #[error("{0} panicked")]
    Thread(&'static str),
}

impl AppError {
    /// Whether the job ended because Ctrl-C (or SIGTERM) stopped it.
    pub fn stopped(&self) -> bool {
        matches!(
            self,
            AppError::Interrupted { .. }
                | AppError::Stopped { .. }
                | AppError::Calibration(crate::calib::CalibError::Stopped)
        )
    }

    /// An I/O error on `path`.
    pub fn io(path: &std::path::Path) -> impl FnOnce(std::io::Error) -> AppError + '_ {
        move |source| AppError::Io {
            path: path.to_owned(),
            source,
        }
    }
}

/// A mutex that a panicked holder leaves usable: the data the app's threads share (the
/// console's page, the guidance loop's verdict) stays consistent field by field, and the run
/// must go on.
pub(crate) fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}
