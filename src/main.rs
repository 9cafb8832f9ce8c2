//! The `hexcal` command line.
//!
//! Exit statuses (README "Exit codes"): 0 when every device is calibrated (or the command
//! has nothing to calibrate), 2 when a calibration finished but left a device uncalibrated,
//! 1 when the command failed: refused input or any other error, told in one line.

use clap::{Parser, Subcommand};
use hexcal::app::calibrate::CalibrateOptions;
use hexcal::app::jobs::Side;
use hexcal::app::progress::Event;
use hexcal::app::AppError;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;

// Printing never panics: std's print macros panic when stdout or stderr is a closed pipe
// (`hexcal … | head`), so these replacements, in scope for this file and the modules
// declared after them, drop what cannot be written and the command goes on to its end.

/// `println!` that drops output a closed stdout cannot take.
macro_rules! println {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}

/// `print!` that drops output a closed stdout cannot take.
macro_rules! print {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stdout(), $($arg)*);
    }};
}

/// `eprintln!` that drops output a closed stderr cannot take.
macro_rules! eprintln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($arg)*);
    }};
}

/// `eprint!` that drops output a closed stderr cannot take.
macro_rules! eprint {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stderr(), $($arg)*);
    }};
}

#[cfg(feature = "bench")]
mod benchcmd;

/// Exit status of a command that failed (refused input or any other error).
const EXIT_FAILED: u8 = 1;
/// Exit status of a calibration that finished with some device not calibrated.
const EXIT_UNCALIBRATED: u8 = 2;
/// Exit status of a run stopped by Ctrl-C (128 + SIGINT, as shells report it).
const EXIT_INTERRUPTED: u8 = 130;

/// How a command that did not fail ended.
enum Finished {
    /// Everything asked for was done.
    Done,
    /// A calibration was written without these devices.
    Uncalibrated(Vec<String>),
}

/// Calibrate a structured-light rig of many cameras and projectors.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the built-in board's summary.
    Info,
    /// Write the printable target of one board side: SVG at exact physical size (mm).
    Board {
        /// A built-in board (hex600) or a board file (docs/board-file.md).
        #[arg(long, default_value = "hex600")]
        board: String,
        /// The side to draw, as seen looking at it: front or back (a single-sided board has
        /// the front only, the default for it).
        #[arg(long)]
        side: Option<Side>,
        /// The SVG file to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Render one simulated board view (PNG) with its ground truth (JSON).
    Simulate {
        /// Scene file (TOML); the built-in scene when absent.
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Override the scene's noise seed.
        #[arg(long)]
        seed: Option<u64>,
    },
    /// Calibrate every device from a dataset folder (of `hexcal capture` or `hexcal run`) or
    /// a correspondences file (labelled views with projector pixels, JSON) and write the
    /// calibration, OpenCV and Kalibr files and the residual table.
    Calibrate {
        /// The dataset folder or the correspondences file.
        input: PathBuf,
        /// Dataset poses held out for verification (the last ones).
        #[arg(long, default_value_t = 1)]
        held_out: usize,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Reference device (its frame is the rig's frame); the first device by default.
        #[arg(long)]
        reference: Option<String>,
        /// Hold k3 at zero.
        #[arg(long)]
        fix_k3: bool,
        /// Estimate the board's bend (bowl and two saddles).
        #[arg(long)]
        refine_flatness: bool,
        /// Export the pair FIRST,SECOND as a rectified stereo pair (stereo/FIRST-SECOND.yml);
        /// repeatable.
        #[arg(long, value_name = "FIRST,SECOND")]
        stereo: Vec<String>,
        /// The projection uncertainty you need (px, 1σ): the report warns where a lens
        /// misses it.
        #[arg(long, default_value_t = 1.0)]
        target_px: f64,
        /// The held-out length error you need (mm RMS): the report warns when the
        /// verification misses it, and not about pairs within it.
        #[arg(long, default_value_t = 0.1)]
        target_mm: f64,
    },
    /// Check a calibration on held-out board poses: triangulate them from camera pairs and
    /// camera–projector pairs, report length errors and flatness against the board.
    Verify {
        /// The calibration file (`calibration.json` of `hexcal calibrate`); by default the
        /// one in the folder given.
        #[arg(long)]
        calibration: Option<PathBuf>,
        /// Correspondences of the held-out poses, or a calibration folder or a run's folder
        /// (its held-out.json).
        input: PathBuf,
    },
    /// Self-test a rig through its capture engine: `sync` (does every camera frame show the
    /// slide it was triggered for: latency, dropped and repeated frames, the settle_ms that
    /// is safe) or `exposure` (each camera's exposure and gain for the rig's white level,
    /// each projector's response through each camera). Hold the board in view. Exit 1 when
    /// the test fails.
    Check {
        /// sync or exposure.
        test: hexcal::app::check::Which,
        /// The rig file.
        #[arg(long)]
        rig: PathBuf,
        /// Keep the rig file's exposures: only measure the projectors' responses.
        #[arg(long)]
        measure_only: bool,
        /// Also write the report as JSON to this file.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Send one command to a rig file's positioner as a move sends it, and print every line
    /// sent and received: for setting a positioner up.
    Positioner {
        /// The rig file.
        #[arg(long)]
        rig: PathBuf,
        /// The positioner's name.
        name: String,
        /// The command line to send (as the device takes it, e.g. "G0 X10").
        command: String,
    },
    /// Draw one device's map from a calibration as SVG: `uncertainty` (projection
    /// uncertainty over the image, the region within --target outlined) or `distortion`
    /// (the lens's displacement against a pinhole).
    Show {
        /// uncertainty or distortion.
        map: hexcal::app::show::Map,
        /// The device's name.
        device: String,
        /// A calibration file, or a folder holding one (a calibration folder, a run's).
        #[arg(long, default_value = "hexcal-run")]
        calibration: PathBuf,
        /// The SVG file to write (default: DEVICE-MAP.svg).
        #[arg(long)]
        out: Option<PathBuf>,
        /// The projection uncertainty you need (px), outlined on the uncertainty map.
        #[arg(long, default_value_t = 1.0)]
        target: f64,
    },
    /// Detect the board's circles in images and label them with lattice positions (JSON).
    Detect {
        /// A built-in board (hex600) or a board file (docs/board-file.md).
        #[arg(long, default_value = "hex600")]
        board: String,
        /// The JSON file to write: one object per image, in the order given.
        #[arg(long)]
        json: PathBuf,
        /// Write an overlay PNG per image into this directory.
        #[arg(long)]
        overlay: Option<PathBuf>,
        /// Images: 8- or 16-bit, grey or colour PNG, JPEG or TIFF.
        #[arg(required = true)]
        images: Vec<PathBuf>,
    },
    /// Drive a rig (rig file, docs/rig-file.md) through the phase-shift sequence for each
    /// board pose and write the stacks to a dataset folder (docs/dataset.md); resumes an
    /// interrupted capture.
    Capture {
        /// The rig file.
        #[arg(long)]
        rig: PathBuf,
        /// The dataset folder.
        #[arg(long)]
        out: PathBuf,
        /// Board poses (default: the rig file's [poses] count).
        #[arg(long)]
        poses: Option<usize>,
        /// Do not wait for Enter between poses of a real rig.
        #[arg(long)]
        auto: bool,
    },
    /// One button: capture every board pose of a rig (simulated or real), decoding,
    /// detecting and fitting each pose while the next is captured; then calibrate, verify on
    /// the held-out pose and write the calibration and its report (OUT/calibration). An
    /// interrupted run resumes where it stopped.
    Run {
        /// The rig file.
        #[arg(long)]
        rig: PathBuf,
        /// The dataset folder (views and, with --keep-stacks, every frame).
        #[arg(long, default_value = "hexcal-run")]
        out: PathBuf,
        /// Board poses (default: the rig file's [poses] count).
        #[arg(long)]
        poses: Option<usize>,
        /// Poses held out for verification (the last ones).
        #[arg(long, default_value_t = 1)]
        held_out: usize,
        /// Do not wait for Enter between poses (simulated or scripted poses).
        #[arg(long)]
        auto: bool,
        /// Keep every frame in the dataset (PNG, about 1 GB per pose of the paper rig).
        #[arg(long)]
        keep_stacks: bool,
        /// Print only the final summary.
        #[arg(long, conflicts_with = "json")]
        quiet: bool,
        /// Progress as JSON lines on stdout.
        #[arg(long)]
        json: bool,
        /// Serve the operator console, a web page of live thumbnails, coverage and a
        /// done sign, on ADDR (default 127.0.0.1:8765; port 0 picks a free one).
        #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8765")]
        console: Option<String>,
        /// On a simulated rig, the simulated operator follows the console: after each
        /// interim calibration the board goes where the page suggests (with 3° / 15 mm of
        /// placement error), and the capture ends once the sign reads DONE.
        #[arg(long, requires = "console")]
        guided: bool,
        /// Print the timeline (the script's steps, planned start times, expected duration)
        /// without touching a device.
        #[arg(long)]
        dry_run: bool,
        /// Export the pair FIRST,SECOND as a rectified stereo pair (stereo/FIRST-SECOND.yml);
        /// repeatable.
        #[arg(long, value_name = "FIRST,SECOND")]
        stereo: Vec<String>,
        /// Seconds counted down (on the terminal and, big, on the console's page) after the
        /// board is placed by hand (Enter or Capture) before its capture starts; 0: none.
        #[arg(long, value_name = "SECONDS", default_value_t = hexcal::app::session::COUNTDOWN_S)]
        countdown: f64,
    },
    /// List the cameras, monitors and serial ports this machine has (rig-file addresses).
    Devices,
    /// Decode one camera's stack folder (a dataset's pose-KKK/CAMERA): per projector the
    /// (u, v) maps (32-bit float TIFF), validity, lit and projector-view images, the ambient
    /// image and summary.json.
    Decode {
        /// The stack folder (frames and stack.json).
        stack: PathBuf,
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
        /// Exit 0 even when the stack fails the stack check (its maps are written either way).
        #[arg(long)]
        keep: bool,
        /// A built-in board (hex600) or a board file: also detect the board and write the
        /// stack's circle-centre projector observations (view.json).
        #[arg(long)]
        board: Option<String>,
    },
    /// Speed benchmarks that print figures (built with `--features bench`).
    #[cfg(feature = "bench")]
    Bench {
        #[command(subcommand)]
        what: benchcmd::Bench,
    },
}

/// Keep freed image-sized blocks in the heap instead of returning them to the kernel: a
/// capture allocates and frees frames of megabytes hundreds of times a second, and glibc's
/// default (mmap and munmap for every block above 128 KiB, a dynamic threshold that adapts
/// only up to 32 MiB) spends a third of the time in page faults and TLB shootdowns.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn keep_freed_blocks() {
    // SAFETY: mallopt only changes allocator parameters; called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 30);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 64 << 20);
        // One arena: per-thread arenas would each keep their own freed frames.
        libc::mallopt(libc::M_ARENA_MAX, 1);
    }
}

/// `e` and its causes in one line, each cause once: a library error that already names
/// its cause in its own message (`cannot read F: {source}`) is not followed by it again.
fn one_line(e: &anyhow::Error) -> String {
    let mut line = e.to_string();
    for cause in e.chain().skip(1) {
        let cause = cause.to_string();
        if !line.contains(&cause) {
            line.push_str(": ");
            line.push_str(&cause);
        }
    }
    line
}

fn main() -> ExitCode {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    keep_freed_blocks();
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            // Usage errors are refused input; --help and --version are not errors.
            let failed = e.use_stderr();
            eprint!("{e}");
            return ExitCode::from(if failed { EXIT_FAILED } else { 0 });
        }
    };
    match execute(cli.command) {
        Ok(Finished::Done) => ExitCode::SUCCESS,
        Ok(Finished::Uncalibrated(names)) => {
            eprintln!(
                "not calibrated: {} (exit status {EXIT_UNCALIBRATED})",
                names.join(", ")
            );
            ExitCode::from(EXIT_UNCALIBRATED)
        }
        Err(e) => {
            eprintln!("error: {}", one_line(&e));
            let interrupted = e.downcast_ref::<AppError>().is_some_and(AppError::stopped);
            ExitCode::from(if interrupted {
                EXIT_INTERRUPTED
            } else {
                EXIT_FAILED
            })
        }
    }
}

/// `hexcal detect`: the JSON written even when some images fail; the failures are reported
/// and make the command fail.
fn detect(
    board: &str,
    json: &Path,
    overlay: Option<&Path>,
    images: &[PathBuf],
) -> anyhow::Result<()> {
    let results = hexcal::app::detect::detect_files(board, json, overlay, images)?;
    let mut failed = 0;
    for r in &results {
        match r {
            Ok(rec) => println!(
                "{}: {} circles, {} labelled{}",
                rec.image,
                rec.circles.len(),
                rec.points.len(),
                if rec.points.iter().any(|p| p.anchored) {
                    ", anchored"
                } else {
                    ""
                }
            ),
            Err(e) => {
                eprintln!("error: {e}");
                failed += 1;
            }
        }
    }
    if failed > 0 {
        anyhow::bail!("{failed} of {} images failed", images.len());
    }
    Ok(())
}

/// How `run` and `calibrate DATASET` report progress.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Progress {
    /// Lines for people (frame counters redrawn in place on a terminal).
    Human,
    /// Nothing but errors and the final summary.
    Quiet,
    /// One JSON object per event on stdout.
    Json,
}

/// The event printer of a progress mode.
fn printer(mode: Progress) -> impl FnMut(&Event) {
    use std::io::{IsTerminal, Write};
    let tty = std::io::stderr().is_terminal();
    move |e: &Event| match mode {
        Progress::Json => {
            println!("{}", serde_json::to_string(e).expect("events serialise"));
        }
        Progress::Quiet => {}
        Progress::Human => match e {
            Event::Frames { .. } if !tty => {}
            // Redrawn in place on a terminal, like the frame counter.
            Event::Countdown { seconds, .. } if tty && *seconds > 0 => {
                eprint!("\r{e}   ");
                let _ = std::io::stderr().flush();
            }
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

/// Lines for the operator, on stderr.
fn tell() -> hexcal::app::session::Tell {
    Arc::new(|line: &str| eprintln!("{line}"))
}

/// Peak resident memory of this process (VmHWM of /proc/self/status), where Linux tells it.
fn peak_memory_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// `hexcal run`: the session, its summary and timing printed.
fn run(
    rig: &Path,
    out: &Path,
    options: &hexcal::app::run::RunOptions,
    how: hexcal::app::session::How,
    progress: Progress,
) -> anyhow::Result<Finished> {
    let t = std::time::Instant::now();
    let mut print = printer(progress);
    let mut say = |line: &str| match progress {
        Progress::Json => println!("{}", serde_json::json!({"event": "script", "say": line})),
        _ => eprintln!("{line}"),
    };
    let voice = hexcal::app::session::Voice {
        events: &mut print,
        say: &mut say,
        tell: tell(),
    };
    let ended = hexcal::app::session::run(rig, out, options, how, voice)?;
    if progress != Progress::Json {
        print!("{}", ended.summary);
        if let Some(j) = &ended.jitter {
            println!("{j}");
        }
        match peak_memory_mib() {
            Some(mib) => println!(
                "run took {:.1} s, peak memory {mib:.0} MiB",
                t.elapsed().as_secs_f64()
            ),
            None => println!("run took {:.1} s", t.elapsed().as_secs_f64()),
        }
    }
    Ok(finished(ended.uncalibrated))
}

/// `hexcal capture`: what was captured.
fn capture(rig: &Path, out: &Path, poses: Option<usize>, auto: bool) -> anyhow::Result<()> {
    let done = hexcal::app::session::capture(rig, out, poses, auto, tell())?;
    if let Some(j) = done.jitter {
        println!("{j}");
    }
    if !done.summary.skipped.is_empty() {
        eprintln!(
            "already complete, skipped: poses {:?}",
            done.summary.skipped
        );
    }
    println!(
        "captured {} poses into {}",
        done.summary.captured.len(),
        out.display()
    );
    Ok(())
}

/// Whether every device was calibrated.
fn finished(uncalibrated: Vec<String>) -> Finished {
    match uncalibrated.is_empty() {
        true => Finished::Done,
        false => Finished::Uncalibrated(uncalibrated),
    }
}

/// Run one command.
fn execute(command: Command) -> anyhow::Result<Finished> {
    match command {
        Command::Run {
            rig,
            out,
            poses,
            held_out,
            auto,
            keep_stacks,
            quiet,
            json,
            console,
            guided,
            dry_run,
            stereo,
            countdown,
        } => {
            if dry_run {
                print!("{}", hexcal::app::script::timeline(&rig)?);
                return Ok(Finished::Done);
            }
            let options = hexcal::app::run::RunOptions {
                poses,
                held_out,
                keep_stacks,
                stop: Some(hexcal::app::session::stop_flag()?),
                stereo,
                countdown_s: countdown,
                ..Default::default()
            };
            let progress = match (json, quiet) {
                (true, _) => Progress::Json,
                (_, true) => Progress::Quiet,
                _ => Progress::Human,
            };
            let how = hexcal::app::session::How {
                auto,
                guided,
                console: console.as_deref(),
            };
            run(&rig, &out, &options, how, progress)
        }
        Command::Calibrate {
            input,
            out,
            reference,
            fix_k3,
            refine_flatness,
            held_out,
            stereo,
            target_px,
            target_mm,
        } => {
            let target = hexcal::app::calibrate::target(target_px, target_mm)?;
            let mut options = CalibrateOptions::default();
            options.bundle.stop = hexcal::app::session::stop_on_signals()?;
            options.bundle.fix_k3 = fix_k3;
            options.bundle.refine_flatness = refine_flatness;
            let mut printer = printer(Progress::Human);
            let done = hexcal::app::calibrate::calibrate_input(
                &input,
                &out,
                reference.as_deref(),
                options,
                (held_out, &stereo, target),
                &mut printer,
            )?;
            print!("{}", done.summary);
            Ok(finished(done.uncalibrated))
        }
        other => {
            execute_other(other)?;
            Ok(Finished::Done)
        }
    }
}

/// The commands that calibrate nothing.
fn execute_other(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Info => println!("{}", hexcal::app::jobs::info()),
        Command::Board { board, side, out } => {
            let (name, side) = hexcal::app::jobs::board_svg(&board, side, &out)?;
            println!("{name} {side} side written to {}", out.display());
        }
        Command::Verify { calibration, input } => {
            let table = hexcal::app::calibrate::verification_table(&input, calibration.as_deref())?;
            print!("{table}");
        }
        Command::Check {
            test,
            rig,
            measure_only,
            json,
        } => {
            let rig = hexcal::app::capture::LoadedRig::load(&rig)?;
            let tested = hexcal::app::check::check(&rig, test, measure_only)?;
            print!("{tested}");
            if let Some(path) = json {
                hexcal::app::check::write_json(&path, &tested)?;
                println!("wrote {}", path.display());
            }
            if !tested.passed() {
                anyhow::bail!("{}", tested.warnings().join("; "));
            }
            for w in tested.warnings() {
                eprintln!("warning: {w}");
            }
        }
        Command::Positioner { rig, name, command } => {
            let (lines, ended) = hexcal::app::script::positioner_exchange(&rig, &name, &command)?;
            for line in lines {
                println!("{line}");
            }
            match ended {
                Ok(line) => println!("done: {line}"),
                Err(e) => anyhow::bail!("{e}"),
            }
        }
        Command::Show {
            map,
            device,
            calibration,
            out,
            target,
        } => {
            let out = out.unwrap_or_else(|| PathBuf::from(format!("{device}-{}.svg", map.name())));
            let written = hexcal::app::show::show(map, &calibration, &device, &out, target)?;
            println!("wrote {}", written.display());
        }
        Command::Simulate { scene, out, seed } => {
            println!(
                "{}",
                hexcal::app::jobs::simulate(scene.as_deref(), &out, seed)?
            );
        }
        Command::Detect {
            board,
            json,
            overlay,
            images,
        } => detect(&board, &json, overlay.as_deref(), &images)?,
        Command::Capture {
            rig,
            out,
            poses,
            auto,
        } => capture(&rig, &out, poses, auto)?,
        Command::Decode {
            stack,
            out,
            keep,
            board,
        } => {
            let done = hexcal::app::jobs::decode(&stack, &out, board.as_deref())?;
            print!("{done}");
            println!("wrote {} files to {}", done.files.len(), out.display());
            if !keep && !done.summary.verdict.passed() {
                anyhow::bail!(
                    "{}: the stack failed the stack check; capture it again (--keep accepts it)",
                    stack.display()
                );
            }
        }
        Command::Devices => {
            let (all, notes) = hexcal::app::jobs::devices();
            if all.is_empty() {
                println!("no cameras, monitors or serial ports found");
            }
            for f in &all {
                println!("{:<8} {:<28} {}", f.kind, f.address, f.description);
            }
            for n in notes {
                eprintln!("note: {n}");
            }
        }
        #[cfg(feature = "bench")]
        Command::Bench { what } => benchcmd::run(what)?,
        Command::Run { .. } | Command::Calibrate { .. } => unreachable!("handled by execute"),
    }
    Ok(())
}
