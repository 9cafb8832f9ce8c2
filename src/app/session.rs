//! One `hexcal run` or `hexcal capture` as an operator drives it: the rig file read once and
//! checked against the command line, the board placed pose after pose (by the simulated
//! world, the operator's Enter, the console's Capture button, a guided simulated operator
//! or the rig file's capture script), and the operator console wired to the run.
//!
//! Takes the command's settings and where to tell things ([`Voice`]); gives the run's
//! [`Outcome`] with its summary, or what a capture stored.

use super::capture::{capture_dataset, CaptureOptions, CaptureSummary, LoadedRig, Note};
use super::console::Console;
use super::guide::interim::{GuidanceWatch, Guide};
use super::guide::operator::SimOperator;
use super::progress::{Event, Outcome};
use super::run::{RunOptions, ViewsTap};
use super::script::{plan_of, Asking, Jitter, ScriptRun};
use super::AppError;
use crate::app::lock;
use crate::rig::file::CameraDriver;
use crate::rig::script::{Action, Plan};
use crate::rig::sim::SimWorld;
use crossbeam_channel::{Receiver, RecvTimeoutError};
use std::cell::RefCell;
use std::io::BufRead;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Lines for the operator (prompts, the console's address, a guided operator's moves),
/// callable from any thread.
pub type Tell = Arc<dyn Fn(&str) + Send + Sync>;

/// Where a session tells what happens.
pub struct Voice<'a> {
    /// Every progress event (the console hears them too).
    pub events: &'a mut dyn FnMut(&Event),
    /// A capture script's spoken lines.
    pub say: &'a mut dyn FnMut(&str),
    /// Lines for the operator.
    pub tell: Tell,
}

/// A flag that Ctrl-C (or SIGTERM) sets: the run stops capturing, finishes every pose
/// already captured and ends, or stops its calibration within an iteration; each signal is
/// answered at once on stderr. A second one exits at once (code 130), saying so; every
/// file written so far is whole, since every write is atomic.
pub fn stop_flag() -> Result<Arc<AtomicBool>, AppError> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [SIGINT, SIGTERM] {
        let flag = Arc::clone(&stop);
        let handler = move || {
            let again = flag.swap(true, Ordering::SeqCst);
            say_raw(if again { SECOND_STOP } else { FIRST_STOP });
            if again {
                signal_hook::low_level::exit(130);
            }
        };
        // SAFETY: the handler only swaps an atomic flag, write(2)s a static message and
        // _exit(2)s: all async-signal-safe, no allocation, no lock.
        unsafe { signal_hook::low_level::register(signal, handler) }.map_err(AppError::Signals)?;
    }
    Ok(stop)
}

/// [`stop_flag`] as the stages poll it (`hexcal calibrate`'s adjustment).
pub fn stop_on_signals() -> Result<crate::stop::Stop, AppError> {
    Ok(crate::stop::Stop::on(stop_flag()?))
}

/// Told on the first Ctrl-C.
const FIRST_STOP: &[u8] = b"\nhexcal: stopping (Ctrl-C): finishing what is captured, then \
    saying what is kept; Ctrl-C again to stop at once\n";

/// Told on the second Ctrl-C, just before the exit.
const SECOND_STOP: &[u8] = b"\nhexcal: stopped at once (second Ctrl-C): every file written \
    is whole; run the same command to resume\n";

/// `message` on stderr from a signal handler (write(2), no lock, no allocation).
fn say_raw(message: &[u8]) {
    // SAFETY: a valid buffer of its own length; write(2) is async-signal-safe. A short
    // or failed write only shortens the message.
    unsafe {
        libc::write(2, message.as_ptr().cast(), message.len());
    }
}

/// The operator's lines (`true` per line, `false` at the end of input), read in a thread of
/// their own so that a wait for Enter still sees Ctrl-C.
fn operator_lines() -> Receiver<bool> {
    let (tx, rx) = crossbeam_channel::bounded(1);
    std::thread::spawn(move || loop {
        let mut line = String::new();
        let more = std::io::stdin()
            .lock()
            .read_line(&mut line)
            .is_ok_and(|n| n > 0);
        if tx.send(more).is_err() || !more {
            break;
        }
    });
    rx
}

/// How `hexcal run` is driven.
#[derive(Clone, Copy, Debug, Default)]
pub struct How<'a> {
    /// Poses are placed without waiting for Enter.
    pub auto: bool,
    /// The simulated operator follows the console's guidance.
    pub guided: bool,
    /// The console's address.
    pub console: Option<&'a str>,
}

/// A simulated operator following the console (`--guided`): the console's guidance, the
/// operator once the world is known, and the seed of its placement noise.
type Guided = (GuidanceWatch, Option<SimOperator>, u64);

/// Puts the simulated board at pose k: the `[poses]` pose, or, `guided`, where the
/// console's latest guidance (waited for) aims; `Ok(false)` once the console says done.
fn place_sim(
    w: &SimWorld,
    k: usize,
    guided: Option<&mut Guided>,
    stop: Option<&Arc<AtomicBool>>,
    tell: &Tell,
) -> Result<bool, AppError> {
    let Some((watch, operator, seed)) = guided else {
        if k >= w.board_poses.len() {
            return Err(AppError::Input(format!(
                "the simulated rig has {} board poses ([poses] count)",
                w.board_poses.len()
            )));
        }
        w.place(k);
        return Ok(true);
    };
    let (guidance, done) = watch.latest(&|| stop.is_some_and(|s| s.load(Ordering::SeqCst)));
    if done {
        tell(&format!(
            "guided: every device is done after {k} poses; no more poses"
        ));
        return Ok(false);
    }
    let operator = operator.get_or_insert_with(|| SimOperator::new(w, *seed));
    match operator.next(k, guidance.as_ref()) {
        Some((board, what)) => {
            tell(&format!("guided: pose {k}: {what}"));
            w.place_at(k, board);
            Ok(true)
        }
        None => Err(AppError::Input(format!(
            "pose {k}: no guidance to follow and the simulated rig has {} board poses",
            w.board_poses.len()
        ))),
    }
}

/// Puts the board at pose k: a simulated world's pose when the rig is simulated (`guided`:
/// where the console's guidance aims); then, unless `auto` (or a simulated world placed it
/// and `sim_places` says that is enough), waits for the operator's Enter or a press of the
/// console's capture `button` (end of input, or `stop` set, ends the capture). A press of
/// the console's `finish` button ends the capture at the next placement, or while waiting.
fn placer(
    (auto, sim_places): (bool, bool),
    stop: Option<Arc<AtomicBool>>,
    (button, finish): (Option<Receiver<()>>, Option<Receiver<()>>),
    mut guided: Option<Guided>,
    tell: Tell,
) -> impl FnMut(usize, Option<&SimWorld>) -> Result<bool, AppError> {
    let mut lines = None;
    let finished = move |tell: &Tell| {
        let pressed = finish.as_ref().is_some_and(|f| f.try_recv().is_ok());
        if pressed {
            tell("finish: the console's Finish ends the capture; calibrating now");
        }
        pressed
    };
    move |k, world| {
        if finished(&tell) {
            return Ok(false);
        }
        if let Some(w) = world {
            if !place_sim(w, k, guided.as_mut(), stop.as_ref(), &tell)? {
                return Ok(false);
            }
        }
        if auto || (sim_places && world.is_some()) {
            return Ok(true);
        }
        tell(&format!(
            "pose {k}: place the board, then press Enter (end of input stops; the console's \
             Finish calibrates now)"
        ));
        let lines = lines.get_or_insert_with(operator_lines);
        // A press from before this pose waited is stale.
        while button.as_ref().is_some_and(|b| b.try_recv().is_ok()) {}
        loop {
            match lines.recv_timeout(Duration::from_millis(100)) {
                Ok(more) => return Ok(more),
                Err(RecvTimeoutError::Disconnected) => return Ok(false),
                Err(RecvTimeoutError::Timeout) => {
                    if stop.as_ref().is_some_and(|s| s.load(Ordering::SeqCst)) || finished(&tell) {
                        return Ok(false);
                    }
                    if button.as_ref().is_some_and(|b| b.try_recv().is_ok()) {
                        return Ok(true);
                    }
                }
            }
        }
    }
}

/// The operator's answers to a script's prompts: Enter, read only when the script prompts
/// (an unattended script leaves stdin alone), and, with the console open, its `button`; the
/// end of stdin then leaves the button to answer.
fn script_operator(plan: &Plan, button: Option<Receiver<()>>) -> Receiver<bool> {
    let prompts = plan
        .steps
        .iter()
        .any(|s| matches!(s.action, Action::Prompt { .. }));
    let lines = match prompts {
        true => operator_lines(),
        false => return crossbeam_channel::never(),
    };
    let Some(button) = button else {
        return lines;
    };
    let (tx, rx) = crossbeam_channel::bounded(1);
    std::thread::spawn(move || {
        // Enter (or the end of stdin: `None`) until stdin ends, then the button alone.
        let mut lines = Some(lines);
        loop {
            let press = match lines.clone() {
                Some(l) => crossbeam_channel::select! {
                    recv(l) -> line => match line {
                        Ok(true) => Ok(()),
                        _ => {
                            lines = None;
                            continue;
                        }
                    },
                    recv(button) -> press => press,
                },
                None => button.recv(),
            };
            if press.is_err() || tx.send(true).is_err() {
                return;
            }
        }
    });
    rx
}

/// What `hexcal capture` stored.
#[derive(Debug)]
pub struct Captured {
    /// The poses captured now and those already there.
    pub summary: CaptureSummary,
    /// A capture script's step timing.
    pub jitter: Option<Jitter>,
}

/// `hexcal capture`: drive the rig for `poses` poses, or through its capture script, into
/// the dataset `out`; `tell` hears each pose's note and the operator's prompts.
pub fn capture(
    rig: &Path,
    out: &Path,
    poses: Option<usize>,
    auto: bool,
    tell: Tell,
) -> Result<Captured, AppError> {
    let rig = LoadedRig::load(rig)?;
    if let Some(p) = poses {
        check_poses(p)?;
    }
    let Some(plan) = plan_of(&rig.file)? else {
        let poses = poses
            .or(rig.file.poses.as_ref().map(|p| p.count))
            .ok_or_else(|| {
                AppError::Input(
                    "say how many poses with --poses (the rig file has no [poses] table)".into(),
                )
            })?;
        let options = CaptureOptions {
            poses,
            ..Default::default()
        };
        let mut place = placer((auto, true), None, (None, None), None, Arc::clone(&tell));
        let mut log = |note: Note| tell(&note.to_string());
        let summary = capture_dataset(&rig, out, &options, &mut place, &mut log)?;
        return Ok(Captured {
            summary,
            jitter: None,
        });
    };
    if poses.is_some() {
        return Err(scripted_poses(&rig));
    }
    let options = CaptureOptions {
        poses: plan.captures,
        exposures: plan.exposures(&rig.file),
    };
    let operator = script_operator(&plan, None);
    let mut say = |line: &str| tell(line);
    let file = rig.file.clone();
    let script = RefCell::new(ScriptRun::new(file, plan, out, operator, None, &mut say));
    let mut place = |k, world: Option<&SimWorld>| script.borrow_mut().place(k, world);
    let mut log = |note: Note| {
        if let Note::Captured { pose, .. } = note {
            script.borrow_mut().captured(pose);
        }
        tell(&note.to_string());
    };
    let summary = capture_dataset(&rig, out, &options, &mut place, &mut log);
    let jitter = script.into_inner().finish();
    Ok(Captured {
        summary: summary?,
        jitter: jitter?,
    })
}

/// Refuses `--poses` beyond [`crate::limits::MAX_POSES`].
fn check_poses(poses: usize) -> Result<(), AppError> {
    crate::limits::count(poses, crate::limits::MAX_POSES, "poses")
        .map_err(|m| AppError::Input(format!("--poses {m}")))
}

/// The refusal of `--poses` for a rig whose script decides them.
fn scripted_poses(rig: &LoadedRig) -> AppError {
    AppError::Input(format!(
        "{}: its script decides the poses: drop --poses",
        rig.path.display()
    ))
}

/// How a run ended.
#[derive(Debug)]
pub struct Ended {
    /// The calibration and everything written.
    pub outcome: Outcome,
    /// Its printed summary ([`super::summary::of_run`]).
    pub summary: String,
    /// A capture script's step timing.
    pub jitter: Option<Jitter>,
    /// The rig's devices the calibration lacks.
    pub uncalibrated: Vec<String>,
}

/// `hexcal run`: the one-button calibration of the rig file `rig` into `out`, with the
/// operator console on `how.console`'s address if given. Refuses `--poses` beyond the limit
/// and a `--held-out` that leaves too few poses to calibrate before anything is captured.
pub fn run(
    rig: &Path,
    out: &Path,
    options: &RunOptions,
    how: How,
    voice: Voice,
) -> Result<Ended, AppError> {
    let rig = LoadedRig::load(rig)?;
    let plan = plan_of(&rig.file)?;
    check_run(&rig, plan.as_ref(), options)?;
    let mut options = options.clone();
    if how.auto || plan.is_some() {
        // Nobody places the board by hand: no countdown (the rig's pose_pause_s still holds).
        options.countdown_s = 0.0;
    }
    let mut console = how
        .console
        .map(|addr| Console::start(addr, &camera_panels(&rig.file), how.auto))
        .transpose()?;
    let guide = match &console {
        Some(c) => Some(watch_run(&rig, c, how, &mut options, &voice.tell)?),
        None => None,
    };
    let button = console.as_ref().map(Console::captures);
    let finish = console.as_ref().map(Console::finishes);
    let prompts = console.as_ref().map(Console::prompts);
    let guided = guided(&rig, how, guide.as_ref())?;
    let Voice {
        events: print,
        say,
        tell,
    } = voice;
    let mut events = |e: &Event| {
        if let (Event::PoseStarted { pose, .. }, Some(g)) = (e, &guide) {
            lock(g).placing(*pose);
        }
        if let Some(c) = console.as_mut() {
            c.event(e);
        }
        print(e);
    };
    let ran = match plan {
        Some(plan) => {
            let hooks = (button, prompts.map(|p| Box::new(p) as Asking));
            run_script(&rig, plan, out, &options, &mut events, say, hooks)
        }
        None => {
            let stop = options.stop.clone();
            let mut place = placer((how.auto, false), stop, (button, finish), guided, tell);
            super::run::run(&rig, out, &options, &mut place, &mut events).map(|o| (o, None))
        }
    };
    let ended = ran.and_then(|(outcome, jitter)| {
        Ok(Ended {
            summary: super::summary::of_run(&outcome),
            uncalibrated: super::calibrate::uncalibrated(out)?,
            outcome,
            jitter,
        })
    });
    if let Some(c) = console.as_mut() {
        match &ended {
            Ok(e) => c.ended(Ok(&e.uncalibrated)),
            Err(e) => c.ended(Err(&e.to_string())),
        }
    }
    ended
}

/// Each camera's name and image size: the console's panels.
pub fn camera_panels(rig: &crate::rig::file::RigFile) -> Vec<(String, [u32; 2])> {
    let cameras = rig.cameras.iter();
    cameras
        .map(|c| (c.name.clone(), [c.width, c.height]))
        .collect()
}

/// The run watched by the console (`c`): its frames make the thumbnails, its live preview
/// (while the operator places the board, without a script) the live pictures, its processed
/// poses the overlays and, through the guidance loop (started here), the verdict the page
/// shows. Gives the guidance loop.
fn watch_run(
    rig: &LoadedRig,
    c: &Console,
    how: How,
    options: &mut RunOptions,
    tell: &Tell,
) -> Result<Arc<Mutex<Guide>>, AppError> {
    tell(&format!("console: {} (open it in a browser)", c.url()));
    options.frame_tap = Some(c.frame_tap());
    options.settle_each_pose = true;
    let board = rig.file.board()?;
    if !how.auto && rig.file.script.is_empty() {
        options.preview = Some(c.preview_tap(board.clone()));
    }
    let devices = super::calibrate::devices_of_rig(&rig.file);
    let threshold = rig.file.guidance.uncertainty_px;
    let guide = Guide::start(board, devices, threshold, how.auto);
    guide.listen(c.verdicts());
    let guide = Arc::new(Mutex::new(guide));
    let (g, overlays) = (Arc::clone(&guide), c.overlays());
    options.views_tap = Some(ViewsTap(Arc::new(move |views, held_out| {
        overlays(views);
        lock(&g).processed(views, held_out);
    })));
    Ok(guide)
}

/// The longest countdown before a capture (s).
pub const MAX_COUNTDOWN_S: f64 = 60.0;

/// The countdown before each capture of a board placed by hand, unless told otherwise (s).
pub const COUNTDOWN_S: f64 = 3.0;

/// The command line's poses checked against the rig file: a script decides its own; the
/// count within the limit, and enough left after `--held-out` to calibrate; the countdown
/// within 0 to [`MAX_COUNTDOWN_S`].
fn check_run(rig: &LoadedRig, plan: Option<&Plan>, options: &RunOptions) -> Result<(), AppError> {
    if plan.is_some() && options.poses.is_some() {
        return Err(scripted_poses(rig));
    }
    if !(0.0..=MAX_COUNTDOWN_S).contains(&options.countdown_s) {
        return Err(AppError::Input(format!(
            "--countdown {}: give 0 to {MAX_COUNTDOWN_S} seconds",
            options.countdown_s
        )));
    }
    let poses =
        plan.map(|p| p.captures)
            .or(options.poses)
            .or(rig.file.poses.as_ref().map(|p| p.count));
    if let Some(poses) = poses {
        check_poses(poses)?;
        super::calibrate::check_held_out(poses, options.held_out)?;
    }
    Ok(())
}

/// The guided simulated operator, when `how` asks for one (a simulated rig with a
/// `[poses]` table and no script, with the console open).
fn guided(
    rig: &LoadedRig,
    how: How,
    guide: Option<&Arc<Mutex<Guide>>>,
) -> Result<Option<Guided>, AppError> {
    let simulated = rig
        .file
        .cameras
        .iter()
        .all(|c| c.driver == CameraDriver::Sim);
    if how.guided && (!simulated || !rig.file.script.is_empty() || rig.file.poses.is_none()) {
        return Err(AppError::Input(format!(
            "{}: --guided needs a simulated rig (every camera `sim`) with a [poses] table and \
             no script",
            rig.path.display()
        )));
    }
    let seed = rig.file.poses.as_ref().map_or(1, |p| p.seed);
    Ok(match (guide, how.guided) {
        (Some(g), true) => Some((lock(g).watch(), None, seed)),
        _ => None,
    })
}

/// A run of `rig`'s capture script (`plan`) into `out`: the script places every pose and
/// sets the exposure of the captures that ask for their own; the operator's Enter, or the
/// console's `button`, answers its prompts, which the console's `prompts` shows.
fn run_script(
    rig: &LoadedRig,
    plan: Plan,
    out: &Path,
    options: &RunOptions,
    show: &mut dyn FnMut(&Event),
    say: &mut dyn FnMut(&str),
    (button, prompts): (Option<Receiver<()>>, Option<Asking<'static>>),
) -> Result<(Outcome, Option<Jitter>), AppError> {
    let operator = script_operator(&plan, button);
    let options = RunOptions {
        poses: Some(plan.captures),
        exposures: plan.exposures(&rig.file),
        ..options.clone()
    };
    let file = rig.file.clone();
    let mut script = ScriptRun::new(file, plan, out, operator, options.stop.clone(), say);
    if let Some(prompts) = prompts {
        script = script.with_prompts_to(prompts);
    }
    let script = RefCell::new(script);
    let mut events = |e: &Event| {
        script.borrow_mut().event(e);
        show(e);
    };
    let mut place = |k, world: Option<&SimWorld>| script.borrow_mut().place(k, world);
    let outcome = super::run::run(rig, out, &options, &mut place, &mut events);
    let jitter = script.into_inner().finish();
    Ok((outcome?, jitter?))
}
