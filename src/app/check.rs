//! `hexcal check sync|exposure` and the self-tests a run starts with (docs/design.md §11b).
//!
//! Takes a rig file (and, for a run, its started capture session with the board in view);
//! gives the sync report (latency, dropped and repeated frames, the safe `settle_ms`) and
//! the exposure report (each camera's exposure and gain for the rig's white level, each
//! projector's response through each camera), printed, recorded in the dataset's
//! `self-tests.json` and shown in the report. A failed sync test stops a run before its
//! first stack: every stack would mix two slides.

use super::capture::LoadedRig;
use super::AppError;
use crate::capture::Session;
use crate::check::exposure::{check_exposure, ExposurePlan, ExposureReport};
use crate::check::sync::{check_sync, SyncPlan, SyncReport};
use crate::rig::file::RigFile;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::time::Duration;

/// The dataset file that records every self-test of the runs that wrote it.
pub const SELF_TESTS_FILE: &str = "self-tests.json";

/// Which self-test `hexcal check` runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Which {
    /// Does every camera frame show the slide it was triggered for?
    Sync,
    /// Set each camera's exposure and measure each projector's response.
    Exposure,
}

/// The self-tests done at one moment: by `hexcal check` or before a run's first capture.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SelfTests {
    /// The pose whose capture came next (none for `hexcal check`).
    pub before_pose: Option<usize>,
    /// The sync test, when done.
    pub sync: Option<SyncReport>,
    /// The exposure test, when done.
    pub exposure: Option<ExposureReport>,
}

impl SelfTests {
    /// Whether every test done passed (sync: every frame its own slide; exposure: every
    /// camera reached its white level).
    pub fn passed(&self) -> bool {
        self.sync.as_ref().is_none_or(SyncReport::passed)
            && (self.exposure.iter()).all(|e| e.cameras.iter().all(|c| c.converged))
    }

    /// The problems that matter, one line each (a failed sync test is one).
    pub fn warnings(&self) -> Vec<String> {
        let mut out: Vec<String> = (self.sync.iter())
            .filter(|s| !s.passed())
            .filter_map(|s| s.to_string().lines().last().map(str::to_string))
            .collect();
        out.extend(self.exposure.iter().flat_map(ExposureReport::warnings));
        out
    }
}

impl std::fmt::Display for SelfTests {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if let Some(s) = &self.sync {
            write!(f, "{s}")?;
        }
        if let Some(e) = &self.exposure {
            write!(f, "{e}")?;
        }
        Ok(())
    }
}

/// The sync plan of `rig` (the full test, or the short one a run starts with).
fn sync_plan(rig: &RigFile, session: &Session, short: bool) -> SyncPlan {
    let period = Duration::from_secs_f64(1e-3 * rig.timing.frame_period_ms);
    SyncPlan::new(session.timing(), period, short, None)
}

/// The exposure plan of `rig`: the white level and most gain of its `[checks]` (no gain
/// on a rig with a V4L2 camera: its gain control has no relation to dB), at most a
/// pattern's display time after settling, each frame taken at the run's wait (the session's
/// slowest latency plus settle); `set` says whether exposures are set.
fn exposure_plan(rig: &RigFile, session: &Session, set: bool) -> ExposurePlan {
    let t = &rig.timing;
    let v4l2 = (rig.cameras.iter()).any(|c| c.driver == crate::rig::file::CameraDriver::V4l2);
    let timing = session.timing();
    ExposurePlan {
        white_level: rig.checks.white_level,
        max_exposure_us: 1e3 * (t.frame_period_ms - t.settle_ms),
        max_gain_db: if v4l2 { 0.0 } else { rig.checks.max_gain_db },
        wait: timing.latency.iter().max().copied().unwrap_or_default() + timing.settle,
        set_exposure: set,
    }
}

/// `hexcal check sync|exposure --rig R`: open the rig, put a simulated rig's board at its
/// first pose, run the full test and give its report. `measure_only` keeps the rig file's
/// exposures (the exposure test then only measures the responses).
pub fn check(rig: &LoadedRig, which: Which, measure_only: bool) -> Result<SelfTests, AppError> {
    let opened = crate::rig::open(&rig.file)?;
    if let Some(w) = &opened.world {
        w.place(0);
    }
    let mut session = Session::start(opened.devices, &opened.sequence)?;
    let tested = match which {
        Which::Sync => {
            let plan = sync_plan(&rig.file, &session, false);
            SelfTests {
                before_pose: None,
                sync: Some(check_sync(&mut session, &plan)?),
                exposure: None,
            }
        }
        Which::Exposure => {
            let plan = exposure_plan(&rig.file, &session, !measure_only);
            SelfTests {
                before_pose: None,
                sync: None,
                exposure: Some(check_exposure(&mut session, &plan)?),
            }
        }
    };
    session.finish()?;
    Ok(tested)
}

/// Whether `rig` is simulated throughout (no real camera or projector).
fn simulated(rig: &RigFile) -> bool {
    use crate::rig::file::{CameraDriver, ProjectorDriver};
    rig.cameras.iter().all(|c| c.driver == CameraDriver::Sim)
        && (rig.projectors.iter()).all(|p| p.driver == ProjectorDriver::Sim)
}

/// The self-tests a run starts with, once its board is placed for `pose` (the rig file's
/// `[checks]`: by default on a rig with a real device, not on a simulated one): the short
/// sync test, then the exposure set. Recorded in the dataset folder `dataset`; none when
/// none is due. A failed sync test is an error naming what failed and what to do
/// (`rig_path` names the rig file).
pub fn at_start(
    (rig, rig_path): (&RigFile, &Path),
    session: &mut Session,
    dataset: &Path,
    pose: usize,
) -> Result<Option<SelfTests>, AppError> {
    let sim = simulated(rig);
    let (sync, exposure) = (rig.checks.sync.runs(sim), rig.checks.exposure.runs(sim));
    if rig.projectors.is_empty() || !(sync || exposure) {
        return Ok(None);
    }
    let mut tested = SelfTests {
        before_pose: Some(pose),
        sync: None,
        exposure: None,
    };
    if sync {
        let plan = sync_plan(rig, session, true);
        tested.sync = Some(check_sync(session, &plan)?);
    }
    let synced = tested.sync.as_ref().is_none_or(SyncReport::passed);
    if exposure && synced {
        let plan = exposure_plan(rig, session, true);
        tested.exposure = Some(check_exposure(session, &plan)?);
    }
    record(dataset, &tested)?;
    match tested.sync.as_ref().filter(|s| !s.passed()) {
        Some(s) => Err(AppError::SyncFailed(failed_line(s, rig_path))),
        None => Ok(Some(tested)),
    }
}

/// A failed short sync test in one line: which pairs, and what to do (its waits are too
/// few to measure the settle time: the full test does).
fn failed_line(s: &SyncReport, rig: &Path) -> String {
    let bad: Vec<String> = (s.pairs.iter())
        .filter(|p| !p.dropped.is_empty() || !p.late_at_run.is_empty())
        .map(|p| {
            let what = match p.dropped.is_empty() {
                true => format!("an earlier slide in frames {:?}", p.late_at_run),
                false => format!("no slide at all in frames {:?} (dropped)", p.dropped),
            };
            format!("{} × {} showed {what}", p.camera, p.projector)
        })
        .collect();
    format!(
        "sync FAILED at the run's wait of {:.0} ms: {} — nothing was captured; run `hexcal \
         check sync --rig {}` for the settle_ms to set (or set [checks] sync = \"off\" to \
         capture regardless)",
        s.run_wait_ms,
        bad.join("; "),
        rig.display()
    )
}

/// Append `tested` to the dataset's [`SELF_TESTS_FILE`] (written atomically; earlier
/// records kept).
fn record(dataset: &Path, tested: &SelfTests) -> Result<(), AppError> {
    let path = dataset.join(SELF_TESTS_FILE);
    let mut all = read_records(&path)?;
    all.push(tested.clone());
    let text = serde_json::to_string_pretty(&all).map_err(|source| json(&path, source))?;
    crate::atomic::write(&path, text.as_bytes()).map_err(AppError::io(&path))
}

/// Write `tested` as JSON to `path` (atomically).
pub fn write_json(path: &Path, tested: &SelfTests) -> Result<(), AppError> {
    let text = serde_json::to_string_pretty(tested).map_err(|source| json(path, source))?;
    crate::atomic::write(path, text.as_bytes()).map_err(AppError::io(path))
}

/// The self-tests recorded in a dataset's [`SELF_TESTS_FILE`] at `path` (none when there
/// is no such file).
pub fn read_records(path: &Path) -> Result<Vec<SelfTests>, AppError> {
    match crate::limits::read_text(path) {
        Ok(text) => serde_json::from_str(&text).map_err(|source| json(path, source)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(e) => Err(AppError::io(path)(e)),
    }
}

fn json(path: &Path, source: serde_json::Error) -> AppError {
    AppError::Json {
        path: path.to_path_buf(),
        what: "self-tests record",
        source,
    }
}
