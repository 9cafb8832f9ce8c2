//! The `hexcal` command line.
//!
//! Exit statuses (README "Exit codes"): 0 when every device is calibrated (or the command
//! has nothing to calibrate), 2 when a calibration finished but left a device uncalibrated,
//! 1 when the command failed: refused input or any other error, told in one line.

use anyhow::Context;
use clap::{Parser, Subcommand};
use hexcal::app::AppError;
use hexcal::board::{Board, Side};
use hexcal::calib::solve::CalibrateOptions;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

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
mod cli;

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
        /// The side to draw, as seen looking at it: front or back.
        #[arg(long)]
        side: Side,
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
    },
    /// Speed benchmarks that print figures (built with `--features bench`).
    #[cfg(feature = "bench")]
    Bench {
        #[command(subcommand)]
        what: benchcmd::Bench,
    },
}

fn load_scene(path: Option<&PathBuf>) -> anyhow::Result<hexcal::sim::Scene> {
    Ok(match path {
        Some(p) => hexcal::sim::Scene::load(p)?,
        None => hexcal::sim::Scene::default_scene(),
    })
}

/// `hexcal calibrate`: calibrate a dataset folder or a correspondences file, print the
/// residual table.
fn calibrate(
    input: &Path,
    out: &Path,
    reference: Option<&str>,
    options: CalibrateOptions,
    held_out: usize,
    stereo: &[String],
) -> anyhow::Result<Finished> {
    use hexcal::app::calibrate::{calibrate_dataset, calibrate_file, device_index};
    if input.is_dir() {
        let mut options = options;
        if let Some(name) = reference {
            let data = hexcal::dataset::Dataset::open(input)?;
            let (cameras, projectors) = (&data.info.cameras, &data.info.projectors);
            let names = cameras.iter().map(|c| c.name.as_str());
            let names = names.chain(projectors.iter().map(|p| p.name.as_str()));
            options.bundle.reference = device_index(input, names, name)?;
        }
        let mut printer = cli::printer(cli::Progress::Human);
        let outcome = calibrate_dataset(input, out, held_out, &options, stereo, &mut printer)?;
        cli::summarise(&outcome, cli::Progress::Human);
        return Ok(finished(&outcome.calibration));
    }
    let done = calibrate_file(input, out, reference, options, stereo)?;
    let cal = &done.calibration;
    print!(
        "{}",
        hexcal::report::format_table(&hexcal::calib::diagnostics::residual_table(cal))
    );
    print!("{}", hexcal::report::format_lens_models(cal));
    println!(
        "σ {:.4} px; {} of {} unanchored views registered",
        cal.solution.sigma,
        cal.registration.registered.len(),
        cal.registration.unanchored
    );
    for u in &cal.registration.unregistered {
        let camera = &done.input.devices[u.camera].name;
        println!("unregistered: {camera} pose {}: {}", u.pose, u.reason);
    }
    for e in &cal.excluded {
        println!("not calibrated: {}: {}", e.name, e.reason);
    }
    for (name, px) in done.radtan.iter().filter(|(_, px)| *px > 0.0) {
        println!("camchain.yaml: {name} refitted to radtan, largest deviation {px:.4} px");
    }
    println!("wrote {} files to {}", done.files.len(), out.display());
    cli::report_line(cal, &[], &done.files, 0);
    Ok(finished(cal))
}

/// Whether `cal` calibrated every device.
fn finished(cal: &hexcal::calib::solve::Calibration) -> Finished {
    match cal.excluded.is_empty() {
        true => Finished::Done,
        false => Finished::Uncalibrated(cal.excluded.iter().map(|e| e.name.clone()).collect()),
    }
}

/// `hexcal run`: refuses `--poses` beyond the limit and a `--held-out` that leaves too few
/// poses to calibrate before anything is captured; after the run, the devices its
/// calibration (`OUT/calibration/calibration.json`) lacks.
fn run(
    rig: &Path,
    out: &Path,
    options: &hexcal::app::run::RunOptions,
    how: cli::How,
    progress: cli::Progress,
) -> anyhow::Result<Finished> {
    let file = hexcal::rig::file::RigFile::load(rig)?;
    if !file.script.is_empty() && options.poses.is_some() {
        anyhow::bail!(
            "{}: its script decides the poses: drop --poses",
            rig.display()
        );
    }
    let script = hexcal::app::script::plan_of(&file)?.map(|p| p.captures);
    if let Some(poses) = script
        .or(options.poses)
        .or(file.poses.as_ref().map(|p| p.count))
    {
        check_poses(poses)?;
        hexcal::app::calibrate::check_held_out(poses, options.held_out)?;
    }
    cli::run(rig, out, options, how, progress)?;
    let missing = hexcal::app::calibrate::uncalibrated(out)?;
    Ok(match missing.is_empty() {
        true => Finished::Done,
        false => Finished::Uncalibrated(missing),
    })
}

/// Refuses a `--poses` beyond [`hexcal::limits::MAX_POSES`].
fn check_poses(poses: usize) -> anyhow::Result<()> {
    hexcal::limits::count(poses, hexcal::limits::MAX_POSES, "poses")
        .map_err(|m| anyhow::anyhow!("--poses {m}"))
}

/// `hexcal detect`: every image in turn, the JSON written even when some fail; the failures
/// are reported and make the command fail.
fn detect_command(
    board: &str,
    json: &Path,
    overlay: Option<&Path>,
    images: &[PathBuf],
) -> anyhow::Result<()> {
    use hexcal::app::detect::{process_all, to_json, Settings};
    let board = Board::resolve(board)?;
    if let Some(dir) = overlay {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create overlay directory {}", dir.display()))?;
    }
    let results = process_all(images, &board, &Settings::default(), overlay);
    hexcal::atomic::write(json, to_json(images, &results).as_bytes())
        .with_context(|| format!("cannot write {}", json.display()))?;
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
            let interrupted = matches!(
                e.downcast_ref::<AppError>(),
                Some(AppError::Interrupted { .. })
            );
            ExitCode::from(if interrupted {
                EXIT_INTERRUPTED
            } else {
                EXIT_FAILED
            })
        }
    }
}

/// Run one command.
fn execute(command: Command) -> anyhow::Result<Finished> {
    match command {
        Command::Capture {
            rig,
            out,
            poses,
            auto,
        } => {
            if let Some(p) = poses {
                check_poses(p)?;
            }
            cli::capture(&rig, &out, poses, auto)?
        }
        Command::Decode { stack, out } => cli::decode(&stack, &out)?,
        Command::Devices => cli::devices()?,
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
        } => {
            if dry_run {
                let timeline = hexcal::app::script::timeline(&rig).map_err(anyhow::Error::msg)?;
                print!("{timeline}");
                return Ok(Finished::Done);
            }
            let options = hexcal::app::run::RunOptions {
                poses,
                held_out,
                keep_stacks,
                stop: Some(cli::stop_flag()?),
                stereo,
                ..Default::default()
            };
            let progress = if json {
                cli::Progress::Json
            } else if quiet {
                cli::Progress::Quiet
            } else {
                cli::Progress::Human
            };
            let how = cli::How {
                auto,
                guided,
                console: console.as_deref(),
            };
            return run(&rig, &out, &options, how, progress);
        }
        Command::Calibrate {
            input,
            out,
            reference,
            fix_k3,
            refine_flatness,
            held_out,
            stereo,
        } => {
            let mut options = CalibrateOptions::default();
            options.bundle.fix_k3 = fix_k3;
            options.bundle.refine_flatness = refine_flatness;
            return calibrate(
                &input,
                &out,
                reference.as_deref(),
                options,
                held_out,
                &stereo,
            );
        }
        other => execute_other(other)?,
    }
    Ok(Finished::Done)
}

/// The commands that calibrate nothing and capture nothing.
fn execute_other(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Info => {
            let b = hexcal::board::Board::hex600();
            println!("{}: {} circles per side", b.name, b.lattice().len());
        }
        Command::Board { board, side, out } => {
            if out
                .extension()
                .is_none_or(|e| !e.eq_ignore_ascii_case("svg"))
            {
                anyhow::bail!("{}: only SVG is written (name it *.svg)", out.display());
            }
            let board = Board::resolve(&board)?;
            hexcal::atomic::write(&out, board.svg(side).as_bytes())
                .with_context(|| format!("cannot write {}", out.display()))?;
            println!("{} {side} side written to {}", board.name, out.display());
        }
        Command::Verify { calibration, input } => {
            let checks = hexcal::app::calibrate::verify_input(&input, calibration.as_deref())?;
            print!("{}", hexcal::report::format_verification(&checks));
        }
        Command::Simulate { scene, out, seed } => simulate(scene.as_ref(), &out, seed)?,
        Command::Detect {
            board,
            json,
            overlay,
            images,
        } => detect_command(&board, &json, overlay.as_deref(), &images)?,
        #[cfg(feature = "bench")]
        Command::Bench { what } => benchcmd::run(what)?,
        Command::Capture { .. }
        | Command::Decode { .. }
        | Command::Devices
        | Command::Run { .. }
        | Command::Calibrate { .. } => unreachable!("handled by execute"),
    }
    Ok(())
}

/// `hexcal simulate`: render one view of a scene, write its PNG and ground truth.
fn simulate(scene: Option<&PathBuf>, out: &Path, seed: Option<u64>) -> anyhow::Result<()> {
    let mut scene = load_scene(scene)?;
    scene.seed = seed.unwrap_or(scene.seed);
    let view = hexcal::sim::render(&scene)?;
    let [png, json] = hexcal::sim::write_view(&view, out)?;
    let whole = view.truth.circles.iter().filter(|c| c.whole).count();
    println!(
        "{}: side {}, {} circles imaged ({whole} whole); truth in {}",
        png.display(),
        view.truth.side.map_or("none", |s| s.name()),
        view.truth.circles.len(),
        json.display()
    );
    Ok(())
}
