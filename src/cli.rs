//! The capture-side commands: `capture`, `decode` and `run` (with its console and capture script).

mod script;

use anyhow::Context;
use crossbeam_channel::{Receiver, RecvTimeoutError};
use hexcal::app::AppError;
use hexcal::rig::sim::SimWorld;
use std::io::BufRead;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// A flag that Ctrl-C (or SIGTERM) sets: the run stops capturing, finishes every pose
/// already captured and ends. A second one exits at once (code 130); every file written so
/// far is whole, since every write is atomic.
pub fn stop_flag() -> anyhow::Result<Arc<AtomicBool>> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [SIGINT, SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(signal, 130, Arc::clone(&stop))?;
        signal_hook::flag::register(signal, Arc::clone(&stop))?;
    }
    Ok(stop)
}

/// The operator's lines (`true` per line, `false` at the end of input), read in a thread of
/// their own so that a wait for Enter still sees Ctrl-C.
pub fn operator_lines() -> Receiver<bool> {
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
type Guided = (
    hexcal::app::console::GuidanceWatch,
    Option<SimOperator>,
    u64,
);

use hexcal::app::guide::operator::SimOperator;

/// Puts the simulated board at pose k: the `[poses]` pose, or, `guided`, where the
/// console's latest guidance (waited for) aims; `Ok(false)` once the console says done.
fn place_sim(
    w: &SimWorld,
    k: usize,
    guided: Option<&mut Guided>,
    stop: Option<&Arc<AtomicBool>>,
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
        eprintln!("guided: every device is done after {k} poses; no more poses");
        return Ok(false);
    }
    let operator = operator.get_or_insert_with(|| SimOperator::new(w, *seed));
    match operator.next(k, guidance.as_ref()) {
        Some((board, what)) => {
            eprintln!("guided: pose {k}: {what}");
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
/// console's capture `button` (end of input, or `stop` set, ends the capture).
fn placer(
    (auto, sim_places): (bool, bool),
    stop: Option<Arc<AtomicBool>>,
    button: Option<Receiver<()>>,
    mut guided: Option<Guided>,
) -> impl FnMut(usize, Option<&SimWorld>) -> Result<bool, AppError> {
    let mut lines = None;
    move |k, world| {
        if let Some(w) = world {
            if !place_sim(w, k, guided.as_mut(), stop.as_ref())? {
                return Ok(false);
            }
        }
        if auto || (sim_places && world.is_some()) {
            return Ok(true);
        }
        eprintln!("pose {k}: place the board, then press Enter (end of input stops)");
        let lines = lines.get_or_insert_with(operator_lines);
        // A press from before this pose waited is stale.
        while button.as_ref().is_some_and(|b| b.try_recv().is_ok()) {}
        loop {
            match lines.recv_timeout(Duration::from_millis(100)) {
                Ok(more) => return Ok(more),
                Err(RecvTimeoutError::Disconnected) => return Ok(false),
                Err(RecvTimeoutError::Timeout) => {
                    if stop.as_ref().is_some_and(|s| s.load(Ordering::SeqCst)) {
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

/// `hexcal capture`: drive the rig for `poses` poses, or through its capture script, into the
/// dataset `out`.
pub fn capture(rig: &Path, out: &Path, poses: Option<usize>, auto: bool) -> anyhow::Result<()> {
    let file = hexcal::rig::file::RigFile::load(rig)?;
    let (summary, jitter) = match hexcal::app::script::plan_of(&file)? {
        Some(_) if poses.is_some() => anyhow::bail!(
            "{}: its script decides the poses: drop --poses",
            rig.display()
        ),
        Some(plan) => script::capture(file, plan, (rig, out))?,
        None => {
            let poses = poses
                .or(file.poses.map(|p| p.count))
                .context("say how many poses with --poses (the rig file has no [poses] table)")?;
            let options = hexcal::app::capture::CaptureOptions {
                poses,
                ..Default::default()
            };
            let mut place = placer((auto, true), None, None, None);
            let mut log = |note| eprintln!("{note}");
            let summary =
                hexcal::app::capture::capture_dataset(rig, out, &options, &mut place, &mut log)
                    .map_err(anyhow::Error::msg)?;
            (summary, None)
        }
    };
    if let Some(j) = jitter {
        println!("{j}");
    }
    if !summary.skipped.is_empty() {
        eprintln!("already complete, skipped: poses {:?}", summary.skipped);
    }
    println!(
        "captured {} poses into {}",
        summary.captured.len(),
        out.display()
    );
    Ok(())
}

/// `hexcal decode`: one camera's stack folder to maps, images and a summary.
pub fn decode(stack: &Path, out: &Path) -> anyhow::Result<()> {
    let t = std::time::Instant::now();
    let (files, summary) = hexcal::phase::files::decode_to_files(stack, out)?;
    println!(
        "camera {}: {}×{}, decoded in {:.2} s; noise σ_I² = {:.2} + {:.3}·I",
        summary.camera,
        summary.width,
        summary.height,
        t.elapsed().as_secs_f64(),
        summary.noise.offset,
        summary.noise.slope
    );
    for p in &summary.projectors {
        println!(
            "projector {}: valid {:.1} %, B {:.1} DN, σ_I {:.2} DN, predicted σ_φ {:.4} rad, \
             σ_u {:.3} px, σ_v {:.3} px",
            p.projector,
            100.0 * p.valid_fraction,
            p.noise.modulation,
            p.noise.sigma_i,
            p.noise.sigma_phi,
            p.noise.sigma_u,
            p.noise.sigma_v
        );
    }
    println!("wrote {} files to {}", files.len(), out.display());
    Ok(())
}

/// How `run` and `calibrate DATASET` report progress.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Progress {
    /// Lines for people (frame counters redrawn in place on a terminal).
    Human,
    /// Nothing but errors and the final summary.
    Quiet,
    /// One JSON object per event on stdout.
    Json,
}

/// The event printer of a progress mode.
pub fn printer(mode: Progress) -> impl FnMut(&hexcal::app::progress::Event) {
    use hexcal::app::progress::Event;
    use std::io::{IsTerminal, Write};
    let tty = std::io::stderr().is_terminal();
    move |e: &Event| match mode {
        Progress::Json => {
            println!("{}", serde_json::to_string(e).expect("events serialise"));
        }
        Progress::Quiet => {}
        Progress::Human => match e {
            Event::Frames { .. } if !tty => {}
            Event::Frames { pose, done, of } => {
                let filled = 30 * done / (*of).max(1);
                eprint!(
                    "\rpose {pose} [{}{}] {done}/{of} frames   ",
                    "#".repeat(filled),
                    " ".repeat(30 - filled)
                );
                let _ = std::io::stderr().flush();
            }
            _ if tty => eprintln!("\r{e}   "),
            _ => eprintln!("{e}"),
        },
    }
}

/// `hexcal run`: the one-button calibration, with the operator console on `console`'s
/// address if given.
pub fn run(
    rig: &Path,
    out: &Path,
    options: &hexcal::app::run::RunOptions,
    how: How,
    progress: Progress,
) -> anyhow::Result<()> {
    use hexcal::app::console::Console;
    let How {
        auto,
        guided,
        console,
    } = how;
    let mut console = console
        .map(|addr| Console::start(addr, out, auto))
        .transpose()?;
    let mut options = options.clone();
    if let Some(c) = &console {
        eprintln!("console: {} (open it in a browser)", c.url());
        options.frame_tap = Some(c.frame_tap());
        options.settle_each_pose = true;
    }
    let button = console.as_ref().map(Console::captures);
    let prompts = console.as_ref().map(Console::prompts);
    let t = std::time::Instant::now();
    let file = hexcal::rig::file::RigFile::load(rig)?;
    let simulated = file
        .cameras
        .iter()
        .all(|c| c.driver == hexcal::rig::file::CameraDriver::Sim);
    if guided && (!simulated || !file.script.is_empty() || file.poses.is_none()) {
        anyhow::bail!(
            "{}: --guided needs a simulated rig (every camera `sim`) with a [poses] table and \
             no script",
            rig.display()
        );
    }
    let seed = file.poses.as_ref().map_or(1, |p| p.seed);
    if let Some(c) = console.as_mut() {
        c.set_threshold(file.guidance.uncertainty_px);
    }
    // While the operator places the board (no script: it times its own steps), the page
    // shows what each camera sees.
    if let (Some(c), false, true) = (&console, auto, file.script.is_empty()) {
        let board = hexcal::board::Board::resolve(&file.board)?;
        options.preview = Some(c.preview_tap(board));
    }
    let guided = match (&console, guided) {
        (Some(c), true) => Some((c.guidance_watch(), None, seed)),
        _ => None,
    };
    let mut show = |e: &hexcal::app::progress::Event| {
        if let Some(c) = console.as_mut() {
            c.event(e);
        }
    };
    let (outcome, jitter) = match hexcal::app::script::plan_of(&file)? {
        Some(plan) => {
            let hooks = script::ConsoleHooks {
                button,
                prompts: prompts.map(|p| Box::new(p) as hexcal::app::script::Asking),
            };
            script::run(
                file,
                plan,
                (rig, out),
                &options,
                progress,
                (&mut show, hooks),
            )?
        }
        None => {
            let stop = options.stop.clone();
            let mut place = placer((auto, false), stop, button, guided);
            let mut print = printer(progress);
            let mut events = |e: &hexcal::app::progress::Event| {
                show(e);
                print(e);
            };
            let outcome = hexcal::app::run::run(rig, out, &options, &mut place, &mut events)?;
            (outcome, None)
        }
    };
    summarise(&outcome, progress);
    if let (Some(j), true) = (jitter, progress != Progress::Json) {
        println!("{j}");
    }
    if progress != Progress::Json {
        match peak_memory_mib() {
            Some(mib) => println!(
                "run took {:.1} s, peak memory {mib:.0} MiB",
                t.elapsed().as_secs_f64()
            ),
            None => println!("run took {:.1} s", t.elapsed().as_secs_f64()),
        }
    }
    Ok(())
}

/// Peak resident memory of this process (VmHWM of /proc/self/status), where Linux tells it.
fn peak_memory_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// The residual table, verification and warnings of a finished run.
pub fn summarise(outcome: &hexcal::app::progress::Outcome, progress: Progress) {
    if progress == Progress::Json {
        return;
    }
    let cal = &outcome.calibration;
    print!(
        "{}",
        hexcal::report::format_table(&hexcal::calib::diagnostics::residual_table(cal))
    );
    print!("{}", hexcal::report::format_lens_models(cal));
    for e in &cal.excluded {
        println!("not calibrated: {}: {}", e.name, e.reason);
    }
    let reg = &cal.registration;
    if reg.unanchored > 0 {
        println!(
            "{} of {} unanchored views registered",
            reg.registered.len(),
            reg.unanchored
        );
    }
    for u in &reg.unregistered {
        let camera = &outcome.devices[u.camera].name;
        println!("unregistered: {camera} pose {}: {}", u.pose, u.reason);
    }
    if !outcome.verification.is_empty() {
        print!(
            "{}",
            hexcal::report::format_verification(&outcome.verification)
        );
    }
    for a in &outcome.agreement {
        println!(
            "{}: cameras agree on its pixels to {:.4} px RMS per camera ({} camera pairs × circles)",
            outcome.devices[a.projector].name, a.rms, a.pairs
        );
    }
    if !outcome.truth.is_empty() {
        println!("against the simulated rig's ground truth:");
        print!("{}", hexcal::app::truth::format_truth(&outcome.truth));
    }
    for w in &outcome.warnings {
        println!("warning: {w}");
    }
    println!("wrote {} files", outcome.files.len());
    report_line(
        cal,
        &outcome.verification,
        &outcome.files,
        outcome.warnings.len(),
    );
}

/// "report: PATH (N warnings)" when `files` hold the HTML report; `extra` counts the
/// caller's warnings the page also shows.
pub fn report_line(
    cal: &hexcal::calib::solve::Calibration,
    verification: &[hexcal::calib::verify::PairCheck],
    files: &[std::path::PathBuf],
    extra: usize,
) {
    use hexcal::calib::diagnostics::{residual_table, verification_warnings, warnings};
    let Some(page) = files.iter().find(|f| f.ends_with("report.html")) else {
        return;
    };
    let n = warnings(cal, &residual_table(cal)).len()
        + verification_warnings(verification, |n| hexcal::report::html::is_projector(cal, n)).len()
        + extra;
    println!(
        "report: {} ({n} warning{})",
        page.display(),
        if n == 1 { "" } else { "s" }
    );
}

/// `hexcal devices`: what this machine has, as rig-file addresses.
pub fn devices() -> anyhow::Result<()> {
    use hexcal::rig::discover::{serial_ports, video_nodes, Found};
    let mut all: Vec<Found> = Vec::new();
    let mut notes = Vec::new();
    match serial_ports() {
        Ok(p) => all.extend(p),
        Err(e) => notes.push(e.to_string()),
    }
    all.extend(video_nodes());
    extra_devices(&mut all, &mut notes);
    if all.is_empty() {
        println!("no cameras, monitors or serial ports found");
    }
    for f in &all {
        println!("{:<8} {:<28} {}", f.kind, f.address, f.description);
    }
    for n in notes {
        eprintln!("note: {n}");
    }
    Ok(())
}

/// Devices of the drivers built in (cargo features).
fn extra_devices(all: &mut Vec<hexcal::rig::discover::Found>, notes: &mut Vec<String>) {
    #[cfg(feature = "aravis")]
    all.extend(hexcal::rig::aravis::list_cameras().into_iter().map(|c| {
        let formats = hexcal::rig::aravis::describe_formats(&c.id)
            .unwrap_or_else(|e| format!("formats unknown: {e}"));
        hexcal::rig::discover::Found {
            kind: "aravis",
            description: format!(
                "{} {} #{} ({}): {formats}",
                c.vendor, c.model, c.serial, c.protocol
            ),
            address: if c.address.is_empty() {
                c.id
            } else {
                c.address
            },
        }
    }));
    #[cfg(not(feature = "aravis"))]
    notes.push("GenICam cameras are listed by builds with --features aravis".into());
    #[cfg(feature = "window")]
    match hexcal::rig::window::monitors() {
        Ok(m) => all.extend(m.into_iter().map(|m| hexcal::rig::discover::Found {
            kind: "monitor",
            description: format!("{}×{} at {},{}", m.width, m.height, m.x, m.y),
            address: m.name,
        })),
        Err(e) => notes.push(format!("monitors: {e}")),
    }
    #[cfg(not(feature = "window"))]
    notes.push("monitors are listed by builds with --features window".into());
    let _ = (&all, &notes);
}
