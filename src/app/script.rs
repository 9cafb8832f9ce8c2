//! Capture scripts under `hexcal run` (docs/rig-file.md, "Scripts and positioners").
//!
//! Takes a rig file's script unrolled ([`Plan`]), the dataset folder, the operator's Enter
//! presses and the stop flag; gives the board placement [`super::run::run`] asks for before
//! each pose: the steps before that capture executed in order — waits, prompts, positioner
//! moves, the ticks of timed captures with their countdown — and every step's planned,
//! due and actual times, written to `DATASET/script.json` after each step. A resumed run
//! starts after the last pose captured, the positioners first brought back to where the
//! skipped steps left them. [`timeline`] is `--dry-run`: the plan, no device touched.

use super::progress::Event;
use super::AppError;
use crate::rig::file::RigFile;
use crate::rig::positioner::{Positioner, PositionerError};
use crate::rig::script::{Action, Plan, PlannedStep};
use crate::rig::sim::SimWorld;
use crossbeam_channel::{Receiver, RecvTimeoutError};
use regex::Regex;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

/// Why a script step failed.
#[derive(Debug, thiserror::Error)]
pub enum ScriptError {
    /// A positioner failed in a step.
    #[error("{step}: {source}")]
    Positioner {
        /// The step, as the rig file names it.
        step: String,
        /// What the positioner did.
        source: PositionerError,
    },
    /// A prompt without timeout, and the operator's input ended.
    #[error("{step}: the prompt waits for Enter, but the input ended")]
    NoOperator {
        /// The step.
        step: String,
    },
    /// The rig file's script cannot be planned: the dotted key and why.
    #[error(transparent)]
    Plan(crate::invalid::ValidationError),
    /// The run asked for a pose the script does not capture.
    #[error("the script captures {captures} poses; pose {pose} is not among them")]
    NoSuchPose {
        /// The pose asked for.
        pose: usize,
        /// Captures in the script.
        captures: usize,
    },
}

impl From<ScriptError> for AppError {
    fn from(e: ScriptError) -> AppError {
        AppError::Script(e)
    }
}

/// One step as it ran.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepRecord {
    /// The step, as the rig file names it (with its repeat round).
    pub step: String,
    /// `capture`, `wait`, `prompt`, `move`, or `restore` (a move repeated on resuming).
    pub kind: String,
    /// The pose, for a capture.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose: Option<usize>,
    /// Planned start after the script (or its resumption) began (s).
    pub planned_start_s: f64,
    /// Planned duration (s).
    pub planned_s: f64,
    /// When it was due (s): the previous step's end, a wait's end as planned, or a timed
    /// capture's tick.
    pub due_s: f64,
    /// When it started (s).
    pub start_s: f64,
    /// When it ended (s), once it did.
    #[serde(default)]
    pub end_s: Option<f64>,
    /// `done`, `timed out`, `interrupted`, or the error.
    pub outcome: String,
}

impl StepRecord {
    /// Start minus due (s).
    pub fn jitter_s(&self) -> f64 {
        self.start_s - self.due_s
    }
}

/// One run of the script (a resumed run adds one).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScriptSession {
    /// Wall-clock start (s since 1970).
    pub started_unix_s: f64,
    /// The first step run (index into the plan).
    pub from_step: usize,
    /// The steps as they ran.
    pub steps: Vec<StepRecord>,
}

/// `script.json`: the plan and every session's steps.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct ScriptFile {
    format: String,
    planned: serde_json::Value,
    sessions: Vec<ScriptSession>,
}

const SCRIPT_FORMAT: &str = "hexcal-script-1";

/// Step timing of a session.
#[derive(Clone, Debug, PartialEq)]
pub struct Jitter {
    /// Steps run.
    pub steps: usize,
    /// Time the steps took (s).
    pub seconds: f64,
    /// Their planned time (s).
    pub planned_s: f64,
    /// Mean, RMS and largest |start − due| (s).
    pub mean_s: f64,
    /// RMS.
    pub rms_s: f64,
    /// Largest.
    pub max_s: f64,
    /// The step with the largest.
    pub worst: String,
}

impl std::fmt::Display for Jitter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "script: {} steps in {:.1} s (planned {:.1} s); start jitter mean {:.2} ms, RMS \
             {:.2} ms, max {:.2} ms ({})",
            self.steps,
            self.seconds,
            self.planned_s,
            1e3 * self.mean_s,
            1e3 * self.rms_s,
            1e3 * self.max_s,
            self.worst
        )
    }
}

/// The step timing of `records` (start minus due of each step).
pub fn jitter(records: &[StepRecord]) -> Option<Jitter> {
    let first = records.first()?;
    let late: Vec<f64> = records.iter().map(|r| r.jitter_s().abs()).collect();
    let n = late.len() as f64;
    let (worst, max) = records
        .iter()
        .zip(&late)
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(r, &l)| (r.step.clone(), l))?;
    let end = records
        .iter()
        .filter_map(|r| r.end_s)
        .fold(first.start_s, f64::max);
    Some(Jitter {
        steps: records.len(),
        seconds: end - first.start_s,
        planned_s: records.iter().map(|r| r.planned_s).sum(),
        mean_s: late.iter().sum::<f64>() / n,
        rms_s: (late.iter().map(|l| l * l).sum::<f64>() / n).sqrt(),
        max_s: max,
        worst,
    })
}

/// How a step ended.
enum Ended {
    Done,
    TimedOut,
    Stopped,
}

/// A script being run: the plan, the positioners, the clock and the records.
pub struct ScriptRun<'a> {
    plan: Plan,
    rig: RigFile,
    file: PathBuf,
    positioners: BTreeMap<String, Positioner>,
    started: Option<Instant>,
    /// Next step to run.
    cursor: usize,
    /// When the next step is due (s on the script clock).
    due: f64,
    /// Tick 0 of each `every` block (s on the script clock).
    anchors: BTreeMap<usize, f64>,
    session: ScriptSession,
    earlier: Vec<ScriptSession>,
    operator: Receiver<bool>,
    stop: Option<Arc<AtomicBool>>,
    say: &'a mut dyn FnMut(&str),
    /// Hears a prompt's text when it starts and `None` when it ends (the operator console
    /// shows it and lets its button answer).
    asking: Option<Asking<'a>>,
    /// A failure of the steps after the last capture (they run while poses are processed).
    failure: Option<AppError>,
}

/// Hears a prompt's text when it starts and `None` when it ends.
pub type Asking<'a> = Box<dyn FnMut(Option<&str>) + 'a>;

/// The seconds one pose's capture is planned to take: its frames, repeated, and the pause.
pub fn capture_seconds(rig: &RigFile) -> Result<f64, AppError> {
    let sequence = rig
        .sequence()
        .map_err(|e| AppError::Input(format!("sequence: {e}")))?;
    let t = &rig.timing;
    Ok(
        sequence.frame_count() as f64 * f64::from(t.repeats) * t.frame_period_ms / 1e3
            + t.pose_pause_s,
    )
}

/// The rig file's script unrolled and planned, if it has one.
pub fn plan_of(rig: &RigFile) -> Result<Option<Plan>, AppError> {
    rig.script_plan(capture_seconds(rig)?)
        .map_err(|e| ScriptError::Plan(e).into())
}

impl<'a> ScriptRun<'a> {
    /// Run `rig`'s script (`plan`) for the dataset folder `out`: `operator` gives one `true`
    /// per Enter (`false` when input ends), `stop` is the Ctrl-C flag, `say` hears what the
    /// operator is told.
    pub fn new(
        rig: RigFile,
        plan: Plan,
        out: &Path,
        operator: Receiver<bool>,
        stop: Option<Arc<AtomicBool>>,
        say: &'a mut dyn FnMut(&str),
    ) -> ScriptRun<'a> {
        ScriptRun {
            plan,
            rig,
            file: out.join("script.json"),
            positioners: BTreeMap::new(),
            started: None,
            cursor: 0,
            due: 0.0,
            anchors: BTreeMap::new(),
            session: ScriptSession {
                started_unix_s: 0.0,
                from_step: 0,
                steps: Vec::new(),
            },
            earlier: Vec::new(),
            operator,
            stop,
            say,
            asking: None,
            failure: None,
        }
    }

    /// `asking` hears each prompt's text when it starts and `None` when it ends.
    pub fn with_prompts_to(mut self, asking: Asking<'a>) -> Self {
        self.asking = Some(asking);
        self
    }

    /// The steps of this session so far.
    pub fn records(&self) -> &[StepRecord] {
        &self.session.steps
    }

    /// Run the steps before pose `k`'s capture and start it: `Ok(false)` when stopped.
    pub fn place(&mut self, k: usize, world: Option<&SimWorld>) -> Result<bool, AppError> {
        let target = self.capture_step(k)?;
        let resume_from = match k {
            0 => 0,
            _ => self.capture_step(k - 1)? + 1,
        };
        if self.started.is_none() {
            self.begin(world, resume_from)?;
        }
        if self.cursor < resume_from {
            if !self.restore(resume_from)? {
                return Ok(false);
            }
            self.cursor = resume_from;
        }
        while self.cursor < target {
            if !self.run_step(self.cursor)? {
                return Ok(false);
            }
            self.cursor += 1;
        }
        if !self.start_capture(target)? {
            return Ok(false);
        }
        if let Some(w) = world {
            w.place(k);
        }
        self.cursor = target + 1;
        Ok(true)
    }

    /// Hear the run's progress: a capture's end; after the last capture, the steps left.
    pub fn event(&mut self, e: &Event) {
        if let Event::PoseCaptured { pose, .. } = e {
            self.captured(*pose);
        }
    }

    /// Pose `pose` is captured: its record closes; after the last capture, the steps left
    /// run.
    pub fn captured(&mut self, pose: usize) {
        let now = self.now();
        if let Some(r) = self
            .session
            .steps
            .iter_mut()
            .rev()
            .find(|r| r.pose == Some(pose) && r.end_s.is_none())
        {
            r.end_s = Some(now);
            r.outcome = "done".into();
            self.due = now;
        }
        let last = self.plan.captures.checked_sub(1);
        if Some(pose) == last && self.failure.is_none() {
            while self.cursor < self.plan.steps.len() {
                match self.run_step(self.cursor) {
                    Ok(true) => self.cursor += 1,
                    Ok(false) => break,
                    Err(e) => {
                        self.failure = Some(e);
                        break;
                    }
                }
            }
        }
        if let Err(e) = self.save() {
            self.failure.get_or_insert(e);
        }
    }

    /// The end of the run: a failure of the steps after the last capture, and the timing.
    pub fn finish(mut self) -> Result<Option<Jitter>, AppError> {
        if let Some(e) = self.failure.take() {
            return Err(e);
        }
        self.save()?;
        Ok(jitter(&self.session.steps))
    }

    /// Index of pose `k`'s capture in the plan.
    fn capture_step(&self, k: usize) -> Result<usize, AppError> {
        self.plan
            .steps
            .iter()
            .position(|s| matches!(s.action, Action::Capture { pose, .. } if pose == k))
            .ok_or_else(|| {
                ScriptError::NoSuchPose {
                    pose: k,
                    captures: self.plan.captures,
                }
                .into()
            })
    }

    /// Open every positioner (a simulated stage then holds the board), start the clock,
    /// read the sessions of earlier runs.
    fn begin(&mut self, world: Option<&SimWorld>, from: usize) -> Result<(), AppError> {
        for p in &self.rig.positioners {
            let opened = Positioner::open(p, world).map_err(|source| ScriptError::Positioner {
                step: format!("positioner {}", p.name),
                source,
            })?;
            self.positioners.insert(p.name.clone(), opened);
        }
        if self.file.exists() {
            let text = crate::limits::read_text(&self.file).map_err(AppError::io(&self.file))?;
            let earlier: ScriptFile =
                serde_json::from_str(&text).map_err(|source| AppError::Json {
                    path: self.file.clone(),
                    what: "script record",
                    source,
                })?;
            self.earlier = earlier.sessions;
        }
        self.started = Some(Instant::now());
        self.session.from_step = from;
        self.session.started_unix_s = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        Ok(())
    }

    fn now(&self) -> f64 {
        self.started.map_or(0.0, |s| s.elapsed().as_secs_f64())
    }

    fn stopped(&self) -> bool {
        self.stop.as_ref().is_some_and(|s| s.load(Ordering::SeqCst))
    }

    /// Planned start of step `i` after this session's first step.
    fn planned_start(&self, i: usize) -> f64 {
        let origin = self
            .plan
            .steps
            .get(self.session.from_step)
            .map_or(0.0, |s| s.planned_start_s);
        self.plan.steps[i].planned_start_s - origin
    }

    /// Open a record of step `i` (kind `kind`) starting now.
    fn open_record(&mut self, i: usize, kind: &str) -> usize {
        let s = &self.plan.steps[i];
        let pose = match s.action {
            Action::Capture { pose, .. } => Some(pose),
            _ => None,
        };
        let record = StepRecord {
            step: s.step.clone(),
            kind: kind.into(),
            pose,
            planned_start_s: self.planned_start(i),
            planned_s: s.planned_s,
            due_s: self.due,
            start_s: self.now(),
            end_s: None,
            outcome: String::new(),
        };
        self.session.steps.push(record);
        self.session.steps.len() - 1
    }

    fn close_record(&mut self, r: usize, outcome: &str) -> Result<(), AppError> {
        let now = self.now();
        let record = &mut self.session.steps[r];
        record.end_s = Some(now);
        record.outcome = outcome.into();
        if self.due < now {
            self.due = now;
        }
        self.save()
    }

    /// Run step `i` (not a capture: those start in [`Self::start_capture`]).
    fn run_step(&mut self, i: usize) -> Result<bool, AppError> {
        let step: PlannedStep = self.plan.steps[i].clone();
        let kind = match &step.action {
            Action::Capture { .. } => return self.start_capture(i),
            Action::Wait { .. } => "wait",
            Action::Prompt { .. } => "prompt",
            Action::Move { .. } => "move",
        };
        let r = self.open_record(i, kind);
        self.save()?;
        let ended = match &step.action {
            Action::Wait { seconds } => {
                let until = self.session.steps[r].start_s + seconds;
                let ended = self.sleep_until(until);
                // The next step is due when the wait should have ended.
                self.session.steps[r].end_s = Some(self.now());
                self.due = until;
                ended
            }
            Action::Prompt { text, timeout_s } => self.prompt(&step.step, text, *timeout_s),
            Action::Move { .. } => self.move_step(&step),
            Action::Capture { .. } => unreachable!("returned above"),
        };
        let ended = match ended {
            Ok(e) => e,
            Err(e) => {
                self.close_record(r, &format!("failed: {e}"))?;
                return Err(e);
            }
        };
        let (outcome, go_on) = match ended {
            Ended::Done => ("done", true),
            Ended::TimedOut => ("timed out", true),
            Ended::Stopped => ("interrupted", false),
        };
        let wait_due = self.due;
        self.close_record(r, outcome)?;
        if kind == "wait" {
            self.due = wait_due;
        }
        Ok(go_on)
    }

    /// Sleep until `until` on the script clock, waking for Ctrl-C.
    fn sleep_until(&self, until: f64) -> Result<Ended, AppError> {
        loop {
            if self.stopped() {
                return Ok(Ended::Stopped);
            }
            let left = until - self.now();
            if left <= 0.0 {
                return Ok(Ended::Done);
            }
            std::thread::sleep(Duration::from_secs_f64(left.min(0.02)));
        }
    }

    /// Show `text` (the console too) and wait for the operator's answer or the timeout.
    fn prompt(&mut self, step: &str, text: &str, timeout: Option<f64>) -> Result<Ended, AppError> {
        let tail = match timeout {
            Some(t) => format!(" (Enter, or going on in {t} s)"),
            None => " (press Enter)".into(),
        };
        (self.say)(&format!("{text}{tail}"));
        if let Some(asking) = self.asking.as_mut() {
            asking(Some(text));
        }
        let ended = self.await_operator(step, timeout);
        if let Some(asking) = self.asking.as_mut() {
            asking(None);
        }
        ended
    }

    /// Wait for the operator's answer (Enter typed ahead counts) or the timeout.
    fn await_operator(&mut self, step: &str, timeout: Option<f64>) -> Result<Ended, AppError> {
        let until = timeout.map(|t| self.now() + t);
        let mut input_ended = false;
        loop {
            if self.stopped() {
                return Ok(Ended::Stopped);
            }
            if until.is_some_and(|u| self.now() >= u) {
                return Ok(Ended::TimedOut);
            }
            if input_ended {
                match until {
                    Some(_) => std::thread::sleep(Duration::from_millis(20)),
                    None => {
                        let step = step.to_string();
                        return Err(ScriptError::NoOperator { step }.into());
                    }
                }
                continue;
            }
            match self.operator.recv_timeout(Duration::from_millis(20)) {
                Ok(true) => return Ok(Ended::Done),
                Ok(false) | Err(RecvTimeoutError::Disconnected) => input_ended = true,
                Err(RecvTimeoutError::Timeout) => {}
            }
        }
    }

    fn move_step(&mut self, step: &PlannedStep) -> Result<Ended, AppError> {
        let Action::Move {
            positioner,
            command,
            expect,
            timeout_s,
            ..
        } = &step.action
        else {
            unreachable!("a move step")
        };
        let failed = |source| ScriptError::Positioner {
            step: step.step.clone(),
            source,
        };
        let expect = Regex::new(expect).map_err(|e| {
            failed(PositionerError::Pattern {
                name: positioner.clone(),
                pattern: expect.clone(),
                message: e.to_string(),
            })
        })?;
        let stop = self.stop.clone();
        let stopped = move || stop.as_ref().is_some_and(|s| s.load(Ordering::SeqCst));
        let p = self
            .positioners
            .get_mut(positioner)
            .ok_or_else(|| AppError::Input(format!("{}: no positioner {positioner}", step.step)))?;
        let timeout = Duration::from_secs_f64(*timeout_s);
        match p.command(command, &expect, timeout, &stopped) {
            Ok(_) => Ok(Ended::Done),
            Err(PositionerError::Interrupted { .. }) => Ok(Ended::Stopped),
            Err(e) => Err(failed(e).into()),
        }
    }

    /// Resuming at step `from`: each positioner's last move among the skipped steps, again.
    fn restore(&mut self, from: usize) -> Result<bool, AppError> {
        let mut last: BTreeMap<String, usize> = BTreeMap::new();
        for (i, s) in self.plan.steps[..from].iter().enumerate() {
            if let Action::Move { positioner, .. } = &s.action {
                last.insert(positioner.clone(), i);
            }
        }
        (self.say)(&format!(
            "resuming the script at {} (steps before it were run by an earlier run)",
            self.plan.steps[from].step
        ));
        for i in last.into_values() {
            let r = self.open_record(i, "restore");
            let step = self.plan.steps[i].clone();
            match self.move_step(&step) {
                Ok(Ended::Stopped) => {
                    self.close_record(r, "interrupted")?;
                    return Ok(false);
                }
                Ok(_) => self.close_record(r, "done")?,
                Err(e) => {
                    self.close_record(r, &format!("failed: {e}"))?;
                    return Err(e);
                }
            }
        }
        Ok(true)
    }

    /// Start the capture of step `i`: a timed capture first waits for its tick, counting
    /// down; then its record opens (it closes when the run reports the pose captured).
    fn start_capture(&mut self, i: usize) -> Result<bool, AppError> {
        let Action::Capture {
            pose, label, tick, ..
        } = self.plan.steps[i].action.clone()
        else {
            unreachable!("a capture step")
        };
        if let Some(t) = tick {
            let now = self.now();
            let anchor = *self.anchors.entry(t.group).or_insert_with(|| {
                // The block starts one countdown from now (from this tick, when resumed).
                now + t.countdown_s - f64::from(t.index) * t.period_s
            });
            let at = anchor + f64::from(t.index) * t.period_s;
            self.due = at;
            if !self.countdown(at, t.countdown_s, pose)? {
                return Ok(false);
            }
        }
        let r = self.open_record(i, "capture");
        self.session.steps[r].outcome = "capturing".into();
        let name = if label.is_empty() {
            String::new()
        } else {
            format!(" ({label})")
        };
        (self.say)(&format!("capturing pose {pose}{name}"));
        self.save()?;
        Ok(true)
    }

    /// Wait for `at`, telling the operator the seconds left in the last `countdown_s`.
    fn countdown(&mut self, at: f64, countdown_s: f64, pose: usize) -> Result<bool, AppError> {
        let mut told = None;
        loop {
            let left = at - self.now();
            if left <= 0.0 {
                return Ok(true);
            }
            if self.stopped() {
                return Ok(false);
            }
            let whole = left.ceil() as u64;
            if left <= countdown_s && told != Some(whole) {
                told = Some(whole);
                (self.say)(&format!(
                    "pose {pose}: hold the board still, capture in {whole} s"
                ));
            }
            std::thread::sleep(Duration::from_secs_f64(left.min(0.01)));
        }
    }

    /// Write `script.json`: the plan, the earlier sessions and this one.
    fn save(&self) -> Result<(), AppError> {
        let planned = serde_json::to_value(&self.plan).map_err(|source| AppError::Json {
            path: self.file.clone(),
            what: "script record",
            source,
        })?;
        let mut sessions = self.earlier.clone();
        sessions.push(self.session.clone());
        let file = ScriptFile {
            format: SCRIPT_FORMAT.into(),
            planned,
            sessions,
        };
        let text = serde_json::to_string_pretty(&file).map_err(|source| AppError::Json {
            path: self.file.clone(),
            what: "script record",
            source,
        })?;
        crate::atomic::write(&self.file, text.as_bytes()).map_err(AppError::io(&self.file))
    }
}

/// `hexcal run --dry-run`: the timeline of the rig file at `rig_path` — each step with its
/// planned start and duration, and the expected total — without touching a device.
pub fn timeline(rig_path: &Path) -> Result<String, AppError> {
    let rig = RigFile::load(rig_path)?;
    let capture_s = capture_seconds(&rig)?;
    let mut out = String::new();
    let Some(plan) = plan_of(&rig)? else {
        let poses = rig.poses.as_ref().map_or(0, |p| p.count);
        return Ok(format!(
            "{}: no script: {poses} poses, each placed by the operator (Enter) or the \
             simulator, {capture_s:.2} s of capture each; expected at least {:.1} s\n",
            rig_path.display(),
            poses as f64 * capture_s
        ));
    };
    out += &format!(
        "{}: {} steps, {} captures, expected {:.1} s ({capture_s:.2} s per capture); no \
         device touched\n",
        rig_path.display(),
        plan.steps.len(),
        plan.captures,
        plan.duration_s
    );
    out += &format!(
        "{:>10} {:>9}  {:<44} {}\n",
        "start s", "dur s", "step", "does"
    );
    for s in &plan.steps {
        out += &format!(
            "{:>10.3} {:>9.3}  {:<44} {}\n",
            s.planned_start_s,
            s.planned_s,
            s.step,
            describe(&s.action)
        );
    }
    if plan.steps.iter().any(|s| {
        matches!(
            s.action,
            Action::Prompt {
                timeout_s: None,
                ..
            }
        )
    }) {
        out += "prompts without a timeout wait for the operator: planned at 0 s\n";
    }
    Ok(out)
}

fn describe(a: &Action) -> String {
    match a {
        Action::Capture {
            pose,
            label,
            tick,
            exposure,
        } => {
            let timed = tick.map_or(String::new(), |t| {
                format!(", tick {} every {} s", t.index, t.period_s)
            });
            let set = exposure
                .as_ref()
                .map_or(String::new(), |e| format!(", {}", e.describe()));
            format!("capture pose {pose} {label:?}{timed}{set}")
        }
        Action::Wait { seconds } => format!("wait {seconds} s"),
        Action::Prompt { text, timeout_s } => match timeout_s {
            Some(t) => format!("prompt {text:?} (up to {t} s)"),
            None => format!("prompt {text:?}"),
        },
        Action::Move {
            positioner,
            command,
            ..
        } => format!("move {positioner}: {command:?}"),
    }
}

#[cfg(test)]
mod tests;

/// `hexcal positioner`: send `command` to the rig file's positioner `name` as a move sends
/// it (echo, acknowledgement, completion line or polling, as the rig file says) and give
/// every line sent and received, then how it ended — for a person setting a positioner up.
pub fn positioner_exchange(
    rig_path: &Path,
    name: &str,
    command: &str,
) -> Result<(Vec<String>, Result<String, PositionerError>), AppError> {
    let rig = RigFile::load(rig_path)?;
    let spec = rig.positioner(name).ok_or_else(|| {
        let names: Vec<&str> = rig.positioners.iter().map(|p| p.name.as_str()).collect();
        AppError::Input(format!(
            "{}: no positioner {name:?}; its positioners: {}",
            rig_path.display(),
            if names.is_empty() {
                "none".to_string()
            } else {
                names.join(", ")
            }
        ))
    })?;
    let mut p = Positioner::open(spec, None).map_err(|source| ScriptError::Positioner {
        step: format!("positioner {name}"),
        source,
    })?;
    let expect = Regex::new(&spec.reply).map_err(|e| AppError::Input(e.to_string()))?;
    let timeout = Duration::from_secs_f64(spec.timeout_s);
    let ended = p.command(command, &expect, timeout, &|| false);
    Ok((p.transcript().to_vec(), ended))
}
