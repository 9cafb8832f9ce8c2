//! One-button calibration (`hexcal run`): the stages streamed in one process.
//!
//! Takes a rig file (or a dataset on disk); gives a calibration, its verification on
//! held-out poses and the report files. While pose k+1 is captured, pose k's stacks finish
//! decoding and go through detection, grid building and the projector fits, each camera in
//! its own thread fed frame by frame over a bounded crossbeam channel (stacks are never held
//! whole). Every pose's views land in the dataset (`pose-KKK/views.json`, then `pose.json`)
//! before the pose counts as done, so an interrupted run keeps every finished pose and a
//! resumed run or `hexcal calibrate DATASET` completes it.

use super::calibrate::{devices_of, finish, Collected};
use super::capture::{prepare, LoadedRig, PlaceBoard, Prepared};
use super::process::{
    process_stored, refusal, stack_worker, PoseViews, StackJob, StackResult, Turns,
};
use super::progress::{Event, Outcome};
use super::truth::{check_truth, format_truth};
use super::AppError;
use crate::board::Board;
use crate::calib::solve::CalibrateOptions;
use crate::calib::CalibError;
use crate::capture::Session;
use crate::dataset::{Dataset, Leftover, PoseInfo, Timeline};
use crate::images::CameraFrame;
use crate::pattern::Sequence;
use crate::phase::check::{StackNote, StackVerdict};
use crate::rig::OpenedRig;
use crate::stop::Stop;
use crossbeam_channel::{bounded, unbounded, Receiver, Sender};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;

/// Settings of [`run`].
#[derive(Clone, Debug, Default)]
pub struct RunOptions {
    /// Board poses to capture (default: the rig file's `[poses] count`).
    pub poses: Option<usize>,
    /// Poses held out for verification (the last ones).
    pub held_out: usize,
    /// Write every frame to the dataset as well (PNG; gigabytes per pose).
    pub keep_stacks: bool,
    /// Set (e.g. by Ctrl-C) to stop capturing: the pose being captured is dropped, every
    /// pose already captured is finished, and the run ends with [`AppError::Interrupted`].
    pub stop: Option<Arc<AtomicBool>>,
    /// Device pairs ("first,second") to export as rectified stereo pairs.
    pub stereo: Vec<String>,
    /// Sees every captured frame (the operator console's thumbnails).
    pub frame_tap: Option<FrameTap>,
    /// Finish processing each pose before the board is placed for the next, so a watcher
    /// (the operator console) shows what it gave first.
    pub settle_each_pose: bool,
    /// The poses captured with their own exposure or gain (a capture script's), set before
    /// each and undone after.
    pub exposures: crate::rig::script::PoseExposures,
    /// Sees live preview frames while the board is placed (the operator console's live
    /// thumbnails): the projectors show a flat field and every camera takes one frame after
    /// another until the placement ends; none of them is written to the dataset.
    pub preview: Option<PreviewTap>,
    /// Sees every processed pose's views as the run makes them (the guidance loop and the
    /// console), before [`Event::PoseProcessed`] tells of it.
    pub views_tap: Option<ViewsTap>,
    /// Seconds counted down after each placement before its capture starts (set for an
    /// operator placing the board by hand; 0: none): the run waits the longer of this and
    /// the rig file's `pose_pause_s`, telling every whole second left ([`Event::Countdown`]).
    pub countdown_s: f64,
}

/// What a [`ViewsTap`] calls: a processed pose's views, and whether the pose is held out.
pub type ViewsFn = dyn Fn(&PoseViews, bool) + Send + Sync;

/// Called with every processed pose (resumed ones too), on the run's thread.
#[derive(Clone)]
pub struct ViewsTap(pub Arc<ViewsFn>);

impl std::fmt::Debug for ViewsTap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ViewsTap")
    }
}

/// What a [`PreviewTap`] calls: one round of preview frames (camera order), or why the
/// preview stopped.
pub type PreviewFn = dyn Fn(Result<&[CameraFrame], &str>) + Send + Sync;

/// Called with every round of preview frames, on the preview thread; the next round waits
/// for it.
#[derive(Clone)]
pub struct PreviewTap(pub Arc<PreviewFn>);

impl std::fmt::Debug for PreviewTap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("PreviewTap")
    }
}

/// Preview rounds start at most this often (10 a second), leaving the processor to the
/// interim calibration when the rig renders and detects faster.
pub const PREVIEW_PERIOD: std::time::Duration = std::time::Duration::from_millis(100);

/// What a [`FrameTap`] calls: pose index and frame.
pub type TapFn = dyn Fn(usize, &crate::dataset::StackFrame) + Send + Sync;

/// Called with every captured frame and its pose, on the capture thread (keep it quick).
#[derive(Clone)]
pub struct FrameTap(pub Arc<TapFn>);

impl std::fmt::Debug for FrameTap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FrameTap")
    }
}

impl RunOptions {
    fn stopped(&self) -> bool {
        self.stop.as_ref().is_some_and(|s| s.load(Ordering::SeqCst))
    }

    /// Wait `seconds` after pose `k` is placed (the board settles, the operator steps back)
    /// before its capture, telling `events` every whole second left ([`Event::Countdown`];
    /// the last, 0, as the wait ends and the capture starts); `false` when stopped meanwhile.
    fn pause(&self, seconds: f64, k: usize, events: &mut dyn FnMut(&Event)) -> bool {
        let until = std::time::Instant::now() + std::time::Duration::from_secs_f64(seconds);
        let mut told = None;
        while !self.stopped() {
            let left = until.saturating_duration_since(std::time::Instant::now());
            let whole = left.as_secs_f64().ceil() as u64;
            if seconds > 0.0 && told != Some(whole) {
                events(&Event::Countdown {
                    pose: k,
                    seconds: whole,
                });
                told = Some(whole);
            }
            if left.is_zero() {
                return true;
            }
            std::thread::sleep(left.min(std::time::Duration::from_millis(20)));
        }
        false
    }
}
/// Per-device coverage as poses come in.
struct Coverage {
    names: Vec<String>,
    poses_seen: Vec<usize>,
    cameras: usize,
}

impl Coverage {
    fn add(&mut self, views: &PoseViews, held_out: bool) -> Event {
        let mut points = vec![0usize; self.names.len()];
        for (c, s) in views.stacks.iter().enumerate() {
            points[c] = s.points;
            for (p, n) in s.projector_points.iter().enumerate() {
                points[self.cameras + p] += n;
            }
        }
        if !held_out {
            for (seen, &n) in self.poses_seen.iter_mut().zip(&points) {
                *seen += usize::from(n > 0);
            }
        }
        Event::PoseProcessed {
            pose: views.pose,
            points: self.names.iter().cloned().zip(points).collect(),
            need_views: self
                .names
                .iter()
                .zip(&self.poses_seen)
                .filter(|(_, &n)| n < 3)
                .map(|(d, _)| d.clone())
                .collect(),
            held_out,
        }
    }
}

/// A camera's stack that failed the stack check, as `refused.json` records it.
#[derive(Clone, Debug, serde::Serialize)]
struct RefusedStack {
    camera: String,
    verdict: StackVerdict,
}

/// Places the board again for a pose whose capture was refused (`Ok(false)`: the capture
/// ends instead).
type Replace<'a> = dyn FnMut(&mut Session) -> Result<bool, AppError> + 'a;

/// One capture of a pose: its timeline, its stack threads, its record and the stacks whose
/// check failed.
struct Attempt {
    timeline: Timeline,
    workers: Vec<JoinHandle<StackResult>>,
    info: PoseInfo,
    refused: Vec<RefusedStack>,
}

/// What the background processing of one pose sends back.
struct Processed {
    views: PoseViews,
    info: PoseInfo,
}

/// `hexcal run`: capture every pose of `rig` into the dataset `out`
/// (resuming one that is there), process each pose while the next is captured, calibrate,
/// verify on the held-out poses and write the outputs to `out/calibration`. `place(k, world)`
/// puts the board at pose k (the simulated world's, or the operator's) and may stop the
/// capture (`Ok(false)`); `events` hears the progress.
pub fn run(
    rig: &LoadedRig,
    out: &Path,
    options: &RunOptions,
    place: &mut PlaceBoard,
    events: &mut dyn FnMut(&Event),
) -> Result<Outcome, AppError> {
    super::calibrate::check_stereo(
        &options.stereo,
        &super::calibrate::devices_of_rig(&rig.file),
    )?;
    let rig_path = rig.path.clone();
    let Prepared {
        rig,
        opened,
        data,
        lock: _lock,
    } = prepare(rig, out)?;
    let poses = options
        .poses
        .or(rig.poses.as_ref().map(|p| p.count))
        .ok_or_else(|| {
            AppError::Input("say how many poses (the rig file has no [poses] table)".into())
        })?;
    let held_from = poses.saturating_sub(options.held_out);
    let devices = devices_of(&data.info);
    let world = opened.world.clone();
    let mut stream = Stream::new(data, &opened, poses, held_from, events);
    stream.views_tap = options.views_tap.clone();
    stream.retries = rig.timing.stack_retries;
    stream.self_tests = Some((rig.clone(), rig_path));
    stream.resume()?;
    let mut session = Session::start(opened.devices, &opened.sequence)?;
    stream.data.record_formats(&session.pixel_formats())?;
    let captured = capture_todo(
        &mut stream,
        &mut session,
        place,
        world.as_deref(),
        options,
        poses,
        rig.timing.pose_pause_s,
    );
    stream.drain()?;
    session.finish()?;
    if let Some(e) = captured.failed {
        return Err(e);
    }
    if let Some(place_again) = captured.interrupted {
        let kept = stream.data.completed()?;
        (stream.events)(&Event::Interrupted {
            kept: kept.clone(),
            place_again: Some(place_again),
        });
        return Err(AppError::Interrupted { kept, place_again });
    }
    let Stream {
        all,
        warnings,
        events,
        data,
        ..
    } = stream;
    let collected = Collected {
        board: &opened.board,
        devices: &devices,
        all: &all,
        held_from,
        stereo: &options.stereo,
        target: crate::calib::diagnostics::Target {
            uncertainty_px: rig.guidance.uncertainty_px,
            length_mm: rig.guidance.target_mm,
        },
        self_tests: super::check::read_records(&data.root().join(super::check::SELF_TESTS_FILE))?,
    };
    let dir = out.join("calibration");
    let stopped = |during: &'static str| -> Result<AppError, AppError> {
        Ok(AppError::Stopped {
            during,
            kept: data.completed()?,
        })
    };
    if options.stopped() {
        // Ctrl-C after the last capture: the poses in processing were finished above.
        return Err(stopped("processing the captured poses")?);
    }
    let mut calibrate = CalibrateOptions::default();
    calibrate.bundle.stop = options.stop.clone().map(Stop::on).unwrap_or_default();
    let mut outcome = match finish(collected, &dir, &calibrate, &warnings, events) {
        Err(AppError::Calibration(CalibError::Stopped)) => {
            return Err(stopped(
                "calibrating (nothing of the calibration was written)",
            )?)
        }
        done => done?,
    };
    outcome.timelines = captured.timelines;
    if let Some(w) = &world {
        outcome.truth = check_truth(&outcome.calibration, w);
        let path = dir.join("truth.txt");
        crate::atomic::write(&path, format_truth(&outcome.truth).as_bytes())
            .map_err(AppError::io(&path))?;
        outcome.files.push(path);
    }
    Ok(outcome)
}

/// How the capture of the poses still to do ended.
#[derive(Default)]
struct Captured {
    /// Each captured pose's timeline.
    timelines: Vec<(usize, Timeline)>,
    /// The pose the capture stopped at (Ctrl-C).
    interrupted: Option<usize>,
    /// An error, told once every pose already captured is finished.
    failed: Option<AppError>,
}

/// Place and capture every pose of `poses` not yet in the dataset, each left to settle for
/// `pause` seconds (or the operator's longer countdown) after it is placed; stops at Ctrl-C,
/// a refused placement or an error.
fn capture_todo(
    stream: &mut Stream<'_>,
    session: &mut Session,
    place: &mut PlaceBoard,
    world: Option<&crate::rig::sim::SimWorld>,
    options: &RunOptions,
    poses: usize,
    pause: f64,
) -> Captured {
    let mut c = Captured::default();
    let todo: Vec<usize> = (0..poses).filter(|&k| stream.all[k].is_none()).collect();
    for k in todo {
        if options.settle_each_pose {
            if let Err(e) = stream.drain() {
                c.failed = Some(e);
                break;
            }
        }
        (stream.events)(&Event::PoseStarted { pose: k, of: poses });
        let wait = pause.max(options.countdown_s);
        let placed = match previewing(session, options.preview.as_ref(), || place(k, world)) {
            Ok(placed) => placed && options.pause(wait, k, &mut *stream.events),
            Err(e) => {
                c.failed = Some(e);
                break;
            }
        };
        if options.stopped() || !placed || options.stopped() {
            c.interrupted = options.stopped().then_some(k);
            break;
        }
        if let Err(e) = stream.self_test(session, k) {
            c.failed = Some(e);
            break;
        }
        // A refused capture is taken again once the board is placed again (the operator's
        // Enter or the console's Capture again; at once when the run places it itself).
        let mut again = |s: &mut Session| -> Result<bool, AppError> {
            let placed = previewing(s, options.preview.as_ref(), || place(k, world))?;
            Ok(placed && !options.stopped())
        };
        let captured = super::capture::exposed(session, options.exposures.get(&k), |s| {
            stream.capture_pose(s, k, options, (&mut again, wait))
        });
        match captured {
            Ok(Some(timeline)) => c.timelines.push((k, timeline)),
            Ok(None) => {
                c.interrupted = options.stopped().then_some(k);
                break;
            }
            Err(_) if options.stopped() => {
                c.interrupted = Some(k);
                break;
            }
            Err(e) => {
                c.failed = Some(e);
                break;
            }
        }
    }
    c
}

/// `place()`, with a live preview on its own thread meanwhile when `tap` is given: preview
/// rounds one after another (at most one per [`PREVIEW_PERIOD`]) handed to the tap, stopped
/// and joined before this returns, so no preview frame is taken once a capture may start.
fn previewing<T>(session: &mut Session, tap: Option<&PreviewTap>, place: impl FnOnce() -> T) -> T {
    let Some(tap) = tap else {
        return place();
    };
    let quit = AtomicBool::new(false);
    std::thread::scope(|scope| {
        let preview = std::thread::Builder::new()
            .name("preview".into())
            .spawn_scoped(scope, || preview_rounds(session, &*tap.0, &quit));
        let placed = place();
        quit.store(true, Ordering::SeqCst);
        match preview {
            Ok(thread) => {
                let _ = thread.join();
            }
            Err(e) => (tap.0)(Err(&format!("no preview thread: {e}"))),
        }
        placed
    })
}

/// Preview rounds until `quit`; a failed round ends the preview (the capture that follows
/// meets the device's failure itself).
fn preview_rounds(session: &mut Session, tap: &PreviewFn, quit: &AtomicBool) {
    use std::time::{Duration, Instant};
    while !quit.load(Ordering::SeqCst) {
        let started = Instant::now();
        match session.preview() {
            Ok(frames) => tap(Ok(&frames)),
            Err(e) => {
                tap(Err(&e.to_string()));
                return;
            }
        }
        while !quit.load(Ordering::SeqCst) {
            let left = PREVIEW_PERIOD.saturating_sub(started.elapsed());
            if left.is_zero() {
                break;
            }
            std::thread::sleep(left.min(Duration::from_millis(10)));
        }
    }
}

/// One pose's decoding threads: the frame senders (camera order), the threads, and a
/// receiver that disconnects once every thread has made its compact stack (or failed).
type StackWorkers = (
    Vec<Sender<CameraFrame>>,
    Vec<JoinHandle<StackResult>>,
    Receiver<(usize, StackVerdict)>,
);

/// A run between poses: the dataset, every pose's views so far, and the one pose whose
/// stacks are still being processed while the next is captured.
struct Stream<'e> {
    data: Dataset,
    board: Board,
    sequence: Sequence,
    held_from: usize,
    coverage: Coverage,
    all: Vec<Option<PoseViews>>,
    warnings: Vec<String>,
    events: &'e mut dyn FnMut(&Event),
    views_tap: Option<ViewsTap>,
    /// Recaptures of a pose whose stack fails the stack check.
    retries: u32,
    /// The rig whose self-tests (its `[checks]`) are due before the first capture.
    self_tests: Option<(crate::rig::file::RigFile, std::path::PathBuf)>,
    done_tx: Sender<Result<Processed, AppError>>,
    done_rx: Receiver<Result<Processed, AppError>>,
    in_flight: Option<JoinHandle<()>>,
}

impl<'e> Stream<'e> {
    /// The rig's self-tests when they are still due (before pose `k`, the first captured):
    /// told as an event (recorded in the dataset, whence the report takes them).
    fn self_test(&mut self, session: &mut Session, k: usize) -> Result<(), AppError> {
        let Some((rig, path)) = self.self_tests.take() else {
            return Ok(());
        };
        if let Some(t) = super::check::at_start((&rig, &path), session, self.data.root(), k)? {
            (self.events)(&Event::SelfTested {
                pose: k,
                report: t.to_string(),
            });
        }
        Ok(())
    }

    /// A processed pose to the views tap, then told as an event.
    fn processed(&mut self, views: &PoseViews, held_out: bool) {
        if let Some(tap) = &self.views_tap {
            (tap.0)(views, held_out);
        }
        (self.events)(&self.coverage.add(views, held_out));
    }

    fn new(
        data: Dataset,
        opened: &OpenedRig,
        poses: usize,
        held_from: usize,
        events: &'e mut dyn FnMut(&Event),
    ) -> Stream<'e> {
        let devices = devices_of(&data.info);
        let coverage = Coverage {
            names: devices.iter().map(|d| d.name.clone()).collect(),
            poses_seen: vec![0; devices.len()],
            cameras: data.info.cameras.len(),
        };
        let (done_tx, done_rx) = unbounded();
        Stream {
            data,
            board: opened.board.clone(),
            sequence: opened.sequence.clone(),
            held_from,
            coverage,
            all: vec![None; poses],
            warnings: Vec::new(),
            events,
            views_tap: None,
            retries: 0,
            self_tests: None,
            done_tx,
            done_rx,
            in_flight: None,
        }
    }

    /// The incomplete poses left by an interrupted run.
    fn recover(&mut self) -> Result<(), AppError> {
        let done = self.data.completed()?;
        for k in (0..self.all.len()).filter(|k| !done.contains(k)) {
            match self.data.leftover(k)? {
                Leftover::Nothing => {}
                Leftover::Processed(info) => self.data.complete(&info)?,
                Leftover::Stacks(info) => {
                    let views = process_stored(&self.data, &self.board, k);
                    self.data.write_pose_file(k, "views.json", &views)?;
                    self.data.complete(&info)?;
                    (self.events)(&Event::Recovered { pose: k });
                }
                Leftover::Unsaved { kept } => (self.events)(&Event::NotSaved {
                    pose: k,
                    kept: kept.map(|p| p.display().to_string()),
                }),
            }
        }
        Ok(())
    }

    fn cameras(&self) -> usize {
        self.data.info.cameras.len()
    }

    /// Take in the views of every pose already complete in the dataset; finish the poses an
    /// interrupted run captured but did not complete (their stacks or views on disk); move
    /// aside what is left of the others, to be captured again.
    fn resume(&mut self) -> Result<(), AppError> {
        self.data.remove_stale_temporaries()?;
        self.recover()?;
        let done = self.data.completed()?;
        let mut resumed = Vec::new();
        let poses = self.all.len();
        for &k in done.iter().filter(|&&k| k < poses) {
            let views = self.data.read_pose_file::<PoseViews>(k, "views.json")?;
            if let Some(v) = views {
                self.processed(&v, k >= self.held_from);
                self.all[k] = Some(v);
                resumed.push(k);
            }
        }
        if !resumed.is_empty() {
            (self.events)(&Event::Resumed { poses: resumed });
        }
        Ok(())
    }

    /// Capture pose `k` and hand it over to processing while the next is captured; a pose
    /// with a stack that fails the stack check is set aside (`pose-KKK.refused-N`) and,
    /// once `again` has placed the board again and `wait` seconds are counted down,
    /// captured again, up to `[timing] stack_retries` times, then kept without that stack.
    /// `None`: the capture ended while the board was to be placed again.
    fn capture_pose(
        &mut self,
        session: &mut Session,
        k: usize,
        options: &RunOptions,
        (again, wait): (&mut Replace<'_>, f64),
    ) -> Result<Option<Timeline>, AppError> {
        let mut attempt = 1;
        loop {
            let Attempt {
                timeline,
                workers,
                info,
                refused,
            } = self.capture_once(session, k, options)?;
            if refused.is_empty() || attempt > self.retries {
                self.hand_over(k, workers, info)?;
                return Ok(Some(timeline));
            }
            attempt += 1;
            for w in workers {
                w.join().map_err(|_| AppError::Thread("a stack thread"))?;
            }
            for r in &refused {
                (self.events)(&Event::StackRefused {
                    pose: k,
                    camera: r.camera.clone(),
                    reason: refusal(&r.verdict),
                    attempt,
                    of: self.retries + 1,
                });
            }
            self.data.refuse(k, &refused)?;
            if !again(session)? || !options.pause(wait, k, &mut *self.events) {
                return Ok(None);
            }
        }
    }

    /// Capture pose `k` once, every frame going to its camera's decoding thread (and to
    /// disk with `keep_stacks`); gives the timeline, the stack threads, the pose's record
    /// and the stacks whose check failed.
    fn capture_once(
        &mut self,
        session: &mut Session,
        k: usize,
        options: &RunOptions,
    ) -> Result<Attempt, AppError> {
        // A camera-only pose is one frame per camera: always kept (docs/dataset.md).
        let keep_stacks = options.keep_stacks || self.sequence.is_camera_only();
        let (senders, workers, decoded) = self.spawn_stack_workers(k)?;
        let (cameras, frames) = (self.cameras(), self.sequence.frame_count());
        let mut writer = self.data.pose_writer(k)?;
        let mut last = 0;
        let events = &mut *self.events;
        let timeline = session.capture_pose(k, &mut |f| {
            if options.stopped() {
                return Err("interrupted".into());
            }
            if keep_stacks {
                writer.write(&f)?;
            }
            if let Some(tap) = &options.frame_tap {
                (tap.0)(k, &f);
            }
            if f.camera == cameras - 1 && (f.index + 1) * 10 / frames > last {
                last = (f.index + 1) * 10 / frames;
                events(&Event::Frames {
                    pose: k,
                    done: f.index + 1,
                    of: frames,
                });
            }
            senders[f.camera]
                .send(f.frame)
                .map_err(|_| "its decoding thread ended".into())
        })?;
        drop(senders);
        let info = writer.finish(&timeline)?;
        self.data.mark_captured(&info)?;
        (self.events)(&Event::PoseCaptured {
            pose: k,
            seconds: timeline.total.as_secs_f64(),
            frames_per_second: timeline.frames_per_second(cameras),
        });
        // The next pose's decoders start filling only once this pose's are compact: the
        // capture of pose k + 1 overlaps the processing of pose k, not its decoding.
        let verdicts: Vec<(usize, StackVerdict)> = decoded.iter().collect();
        for (c, verdict) in &verdicts {
            for note in &verdict.notes {
                if matches!(note, StackNote::Repaired { .. }) {
                    (self.events)(&Event::StackRepaired {
                        pose: k,
                        camera: self.data.info.cameras[*c].name.clone(),
                        what: note.describe(),
                    });
                }
            }
        }
        let refused = verdicts
            .into_iter()
            .filter(|(_, v)| !v.passed())
            .map(|(c, verdict)| RefusedStack {
                camera: self.data.info.cameras[c].name.clone(),
                verdict,
            })
            .collect();
        Ok(Attempt {
            timeline,
            workers,
            info,
            refused,
        })
    }

    /// One decoding thread per camera for pose `k`, fed frame by frame.
    fn spawn_stack_workers(&self, k: usize) -> Result<StackWorkers, AppError> {
        let mut senders = Vec::new();
        let mut workers = Vec::new();
        let turns = std::sync::Arc::new(Turns::default());
        let (decoded_tx, decoded_rx) = bounded(0);
        for (c, entry) in self.data.info.cameras.iter().enumerate() {
            let (tx, rx) = bounded(2);
            senders.push(tx);
            let job = StackJob {
                sequence: self.sequence.clone(),
                entry: entry.clone(),
                board: self.board.clone(),
                camera: c,
                pose: k,
                first_projector: self.cameras(),
                turns: std::sync::Arc::clone(&turns),
                decoded: decoded_tx.clone(),
            };
            let worker = std::thread::Builder::new()
                .name(format!("stack {}", entry.name))
                .spawn(move || stack_worker(rx, job))
                .map_err(AppError::Spawn)?;
            workers.push(worker);
        }
        Ok((senders, workers, decoded_rx))
    }

    /// Pose `k`'s stack threads finish in a thread of their own; at most one pose is in
    /// processing while the next is captured (memory stays bounded).
    fn hand_over(
        &mut self,
        k: usize,
        workers: Vec<JoinHandle<StackResult>>,
        info: PoseInfo,
    ) -> Result<(), AppError> {
        if let Some(h) = self.in_flight.take() {
            h.join()
                .map_err(|_| AppError::Thread("a processing thread"))?;
        }
        while let Ok(p) = self.done_rx.try_recv() {
            self.handle(p)?;
        }
        let tx = self.done_tx.clone();
        let thread = std::thread::Builder::new()
            .name(format!("pose {k}"))
            .spawn(move || {
                let stacks: Result<Vec<StackResult>, AppError> = workers
                    .into_iter()
                    .map(|w| w.join().map_err(|_| AppError::Thread("a stack thread")))
                    .collect();
                let _ = tx.send(stacks.map(|stacks| Processed {
                    views: PoseViews { pose: k, stacks },
                    info,
                }));
            })
            .map_err(AppError::Spawn)?;
        self.in_flight = Some(thread);
        Ok(())
    }

    /// Wait for the pose still in processing and take in every processed pose.
    fn drain(&mut self) -> Result<(), AppError> {
        if let Some(h) = self.in_flight.take() {
            h.join()
                .map_err(|_| AppError::Thread("a processing thread"))?;
        }
        while let Ok(p) = self.done_rx.try_recv() {
            self.handle(p)?;
        }
        Ok(())
    }

    /// A processed pose: its failures reported, its views written (then the pose marked
    /// complete) and kept.
    fn handle(&mut self, p: Result<Processed, AppError>) -> Result<(), AppError> {
        let p = p?;
        let k = p.views.pose;
        for s in &p.views.stacks {
            if let Some(reason) = &s.error {
                self.warnings
                    .push(format!("pose {k}, camera {}: {reason}", s.camera));
                (self.events)(&Event::StackFailed {
                    pose: k,
                    camera: s.camera.clone(),
                    reason: reason.clone(),
                });
            }
        }
        self.processed(&p.views, k >= self.held_from);
        if p.views.stacks.iter().all(|s| s.view.is_none()) {
            let reason = "no camera found the board".to_string();
            self.warnings.push(format!("pose {k}: {reason}"));
            (self.events)(&Event::PoseSkipped { pose: k, reason });
        }
        self.data
            .write_pose_file(k, "views.json", &p.views)
            .and_then(|()| self.data.complete(&p.info))?;
        self.all[k] = Some(p.views);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    #[test]
    fn the_pose_pause_counts_down_and_ctrl_c_cuts_it_short() {
        let stop = Arc::new(AtomicBool::new(false));
        let options = RunOptions {
            stop: Some(Arc::clone(&stop)),
            ..RunOptions::default()
        };
        let t = Instant::now();
        let mut told = Vec::new();
        let mut events = |e: &Event| {
            if let Event::Countdown { pose: 4, seconds } = e {
                told.push((*seconds, t.elapsed()));
            }
        };
        assert!(options.pause(1.15, 4, &mut events));
        let waited = t.elapsed();
        assert!(waited >= Duration::from_millis(1150), "{waited:?}");
        // Each whole second left, told as it is reached; 0 as the wait ends.
        let seconds: Vec<u64> = told.iter().map(|(s, _)| *s).collect();
        assert_eq!(seconds, [2, 1, 0], "{told:?}");
        for ((s, at), want) in told.iter().zip([0.0, 0.15, 1.15]) {
            let at = at.as_secs_f64();
            assert!(
                at >= want && at < want + 0.3,
                "{s} s told at {at} s: {told:?}"
            );
        }
        // No wait, no countdown.
        let mut none = 0;
        assert!(options.pause(0.0, 1, &mut |_| none += 1));
        assert_eq!(none, 0);
        let flag = Arc::clone(&stop);
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(50));
            flag.store(true, Ordering::SeqCst);
        });
        let t = Instant::now();
        assert!(!options.pause(600.0, 0, &mut |_| {}));
        assert!(t.elapsed() < Duration::from_secs(60));
    }
}
