//! The `hexcal` command line.

use anyhow::Context;
use clap::{Parser, Subcommand};
use hexcal::board::{Board, Side};
use std::path::{Path, PathBuf};

mod cli;

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
    },
    /// Check a calibration on held-out board poses: triangulate them from camera pairs and
    /// camera–projector pairs, report length errors and flatness against the board.
    Verify {
        /// The calibration file (`calibration.json` of `hexcal calibrate`).
        #[arg(long)]
        calibration: PathBuf,
        /// Correspondences of the held-out poses.
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
    /// Speed benchmarks that print figures.
    Bench {
        #[command(subcommand)]
        what: Bench,
    },
}

#[derive(Subcommand)]
enum Bench {
    /// Bundle adjustment of a synthetic rig from a perturbed start (6 cameras and 3
    /// projectors: the paper-like rig; otherwise cameras and projectors on a ring).
    Calib {
        /// Cameras.
        #[arg(long, default_value_t = 6)]
        cameras: usize,
        /// Projectors.
        #[arg(long, default_value_t = 3)]
        projectors: usize,
        /// Board poses.
        #[arg(long, default_value_t = 10)]
        poses: usize,
        /// Observation noise σ (px).
        #[arg(long, default_value_t = 0.1)]
        sigma: f64,
    },
    /// Frames per second through the capture engine on a simulated rig (one pose, frames
    /// discarded), with one camera's stack rendering broken down.
    Capture {
        /// The rig file.
        #[arg(long, default_value = "rigs/sim-paper.toml")]
        rig: PathBuf,
    },
    /// Frames per second through a GigE Vision camera on loopback (the in-process Aravis
    /// fake camera serving known frames, each checked); needs `--features aravis`.
    Aravis {
        /// Frame width.
        #[arg(long, default_value_t = 1920)]
        width: u32,
        /// Frame height.
        #[arg(long, default_value_t = 1200)]
        height: u32,
        /// Bits per sample (8 or 16).
        #[arg(long, default_value_t = 8)]
        bits: u8,
        /// Frames.
        #[arg(long, default_value_t = 100)]
        frames: usize,
    },
    /// Time from a window projector's `show` to the slide drawn by the X server (pattern
    /// slides at the monitor's size on `$DISPLAY`); needs `--features window`.
    Window {
        /// Monitor (the first one when absent; `hexcal devices` lists them).
        #[arg(long)]
        monitor: Option<String>,
        /// Slides.
        #[arg(long, default_value_t = 100)]
        slides: usize,
    },
    /// Render the built-in 1920×1200 scene (or --scene): ray grid, geometry, one frame.
    Render {
        /// Scene file (TOML); the built-in scene when absent.
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Repetitions (the median is printed).
        #[arg(long, default_value_t = 5)]
        repeat: usize,
    },
    /// Circle detection on the given images, or on built-in synthetic boards
    /// (1920×1200 and 4096×3000) when none are given.
    Detect {
        /// Images to detect in.
        images: Vec<PathBuf>,
        /// Timed runs per image (after one warm-up run); the median is printed.
        #[arg(long, default_value_t = 7)]
        runs: usize,
    },
    /// Detection + grid building on rendered 1920×1200 and 4096×3000 board views, with
    /// recall and centre error against the truth.
    DetectGrid {
        /// Timed runs per image (after one warm-up run); medians are printed.
        #[arg(long, default_value_t = 7)]
        runs: usize,
        /// Keep the views, their truth and the figures here (else a temporary directory,
        /// removed afterwards); OpenCV's SimpleBlobDetector runs on them
        /// (scripts/bench_opencv_blobs.py) when /usr/bin/python3 has cv2.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Decode one camera's default phase-shift stack (synthetic scene, gamma 2.2).
    Decode {
        /// Camera width (px).
        #[arg(long, default_value_t = 1920)]
        width: u32,
        /// Camera height (px).
        #[arg(long, default_value_t = 1200)]
        height: u32,
        /// Number of projectors.
        #[arg(long, default_value_t = 3)]
        projectors: usize,
        /// Timed decodes of the same stack.
        #[arg(long, default_value_t = 3)]
        repeats: usize,
    },
}

/// `hexcal bench detect`: per image, the median and fastest time of `detect` and the
/// throughput.
fn bench_detect(images: &[PathBuf], runs: usize) -> anyhow::Result<()> {
    use {
        hexcal::detect::{detect, synth, DetectParams},
        hexcal::images::GrayImage,
    };
    let inputs: Vec<(String, GrayImage)> = if images.is_empty() {
        vec![
            (
                "synthetic board, r=10 px, tilt 40°".into(),
                synth::lattice_image(1920, 1200, 10.0, 40.0, 1),
            ),
            (
                "synthetic board, r=4 px, frontal".into(),
                synth::lattice_image(1920, 1200, 4.0, 0.0, 2),
            ),
            (
                "synthetic board, r=24 px, tilt 40°".into(),
                synth::lattice_image(4096, 3000, 24.0, 40.0, 3),
            ),
            (
                "synthetic board, r=10 px, frontal".into(),
                synth::lattice_image(4096, 3000, 10.0, 0.0, 4),
            ),
        ]
    } else {
        images
            .iter()
            .map(|p| Ok((p.display().to_string(), hexcal::images::load_gray(p)?)))
            .collect::<anyhow::Result<_>>()?
    };
    let params = DetectParams::default();
    println!("threads: {}", rayon::current_num_threads());
    println!(
        "{:>11} {:>6} {:>8} {:>10} {:>10} {:>8}  image",
        "size", "MP", "circles", "median ms", "min ms", "MP/s"
    );
    for (name, img) in &inputs {
        let n = detect(img, &params).len();
        let mut ms: Vec<f64> = (0..runs.max(1))
            .map(|_| {
                let t = std::time::Instant::now();
                std::hint::black_box(detect(img, &params));
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        ms.sort_by(f64::total_cmp);
        let mp = img.width() as f64 * img.height() as f64 / 1e6;
        let med = ms[ms.len() / 2];
        println!(
            "{:>11} {:>6.2} {:>8} {:>10.1} {:>10.1} {:>8.1}  {name}",
            format!("{}x{}", img.width(), img.height()),
            mp,
            n,
            med,
            ms[0],
            mp / (med / 1e3)
        );
    }
    Ok(())
}

fn load_scene(path: Option<&PathBuf>) -> anyhow::Result<hexcal::sim::Scene> {
    Ok(match path {
        Some(p) => hexcal::sim::Scene::load(p)?,
        None => hexcal::sim::Scene::default_scene(),
    })
}

/// `hexcal calibrate`: read, calibrate, write, print the residual table.
fn calibrate(
    input: &Path,
    out: &Path,
    reference: Option<&str>,
    fix_k3: bool,
    refine_flatness: bool,
    held_out: usize,
) -> anyhow::Result<()> {
    use hexcal::calib::pipeline::{calibrate, CalibrateOptions, Correspondences};
    if input.is_dir() {
        let mut options = CalibrateOptions::default();
        options.bundle.fix_k3 = fix_k3;
        options.bundle.refine_flatness = refine_flatness;
        if let Some(name) = reference {
            let data = hexcal::dataset::Dataset::open(input)?;
            options.bundle.reference = data
                .info
                .cameras
                .iter()
                .map(|c| &c.name)
                .chain(data.info.projectors.iter().map(|p| &p.name))
                .position(|d| d == name)
                .with_context(|| format!("{}: no device named {name:?}", input.display()))?;
        }
        let outcome = hexcal::pipeline::calibrate_dataset(
            input,
            out,
            held_out,
            &options,
            &mut cli::printer(cli::Progress::Human),
        )
        .map_err(anyhow::Error::msg)?;
        cli::summarise(&outcome, cli::Progress::Human);
        return Ok(());
    }
    let text = std::fs::read_to_string(input)
        .with_context(|| format!("cannot read {}", input.display()))?;
    let c: Correspondences = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a correspondences file", input.display()))?;
    let board = Board::resolve(&c.board)?;
    let mut options = CalibrateOptions::default();
    options.bundle.fix_k3 = fix_k3;
    options.bundle.refine_flatness = refine_flatness;
    if let Some(name) = reference {
        options.bundle.reference = c
            .devices
            .iter()
            .position(|d| d.name == name)
            .with_context(|| format!("{}: no device named {name:?}", input.display()))?;
    }
    let cal = calibrate(&board, &c.devices, c.poses, &c.views, &options)?;
    let mut written = hexcal::report::write_outputs(&cal, out)?;
    let html = out.join("report.html");
    hexcal::report::html::write_html(
        &hexcal::report::html::ReportInput {
            calibration: &cal,
            verification: &[],
            title: &format!("hexcal calibration of {}", input.display()),
            warnings: Vec::new(),
        },
        &html,
    )?;
    written.push(html);
    print!(
        "{}",
        hexcal::report::format_table(&hexcal::report::residual_table(&cal))
    );
    println!(
        "σ {:.4} px; {} of {} unanchored views registered",
        cal.solution.sigma,
        cal.registration.registered.len(),
        cal.registration.unanchored
    );
    for u in &cal.registration.unregistered {
        println!(
            "unregistered: {} pose {}: {}",
            c.devices[u.camera].name, u.pose, u.reason
        );
    }
    for e in &cal.excluded {
        println!("not calibrated: {}: {}", e.name, e.reason);
    }
    println!("wrote {} files to {}", written.len(), out.display());
    Ok(())
}

/// `hexcal verify`: triangulate held-out poses and print the length and flatness table.
fn verify(calibration: &Path, input: &Path) -> anyhow::Result<()> {
    use hexcal::calib::bundle::Device;
    use hexcal::calib::pipeline::Correspondences;
    let text = std::fs::read_to_string(calibration)
        .with_context(|| format!("cannot read {}", calibration.display()))?;
    let cal =
        hexcal::report::CalibrationFile::from_json(&text, &calibration.display().to_string())?;
    let text = std::fs::read_to_string(input)
        .with_context(|| format!("cannot read {}", input.display()))?;
    let c: Correspondences = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a correspondences file", input.display()))?;
    let devices = c
        .devices
        .iter()
        .map(|d| {
            let r = cal
                .devices
                .iter()
                .find(|r| r.name == d.name)
                .with_context(|| {
                    format!(
                        "{}: device {:?} is not in {}",
                        input.display(),
                        d.name,
                        calibration.display()
                    )
                })?;
            Ok(Device {
                name: r.name.clone(),
                kind: r.kind,
                model: r.model(),
                pose: r.pose.isometry(),
            })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let board = Board::resolve(&c.board)?;
    let checks = hexcal::calib::verify::verify(&board, &devices, &c.views);
    anyhow::ensure!(
        !checks.is_empty(),
        "{}: no device pair shares ten circles of a pose",
        input.display()
    );
    print!("{}", hexcal::report::format_verification(&checks));
    Ok(())
}

/// `hexcal detect`: every image in turn, the JSON written even when some fail; the failures
/// are reported and make the command fail.
fn detect_command(
    board: &str,
    json: &Path,
    overlay: Option<&Path>,
    images: &[PathBuf],
) -> anyhow::Result<()> {
    use hexcal::detection::{process_all, to_json, Settings};
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

fn main() -> anyhow::Result<()> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    keep_freed_blocks();
    let cli = Cli::parse();
    match cli.command {
        Command::Capture {
            rig,
            out,
            poses,
            auto,
        } => cli::capture(&rig, &out, poses, auto)?,
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
        } => cli::run(
            &rig,
            &out,
            &hexcal::pipeline::RunOptions {
                poses,
                held_out,
                keep_stacks,
            },
            auto,
            if json {
                cli::Progress::Json
            } else if quiet {
                cli::Progress::Quiet
            } else {
                cli::Progress::Human
            },
        )?,
        Command::Bench {
            what: Bench::Capture { rig },
        } => cli::bench_capture(&rig)?,
        Command::Bench {
            what:
                Bench::Aravis {
                    width,
                    height,
                    bits,
                    frames,
                },
        } => cli::bench_aravis(width, height, bits, frames)?,
        Command::Bench {
            what: Bench::Window { monitor, slides },
        } => cli::bench_window(monitor.as_deref(), slides)?,
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
        Command::Calibrate {
            input,
            out,
            reference,
            fix_k3,
            refine_flatness,
            held_out,
        } => calibrate(
            &input,
            &out,
            reference.as_deref(),
            fix_k3,
            refine_flatness,
            held_out,
        )?,
        Command::Verify { calibration, input } => verify(&calibration, &input)?,
        Command::Simulate { scene, out, seed } => {
            let mut scene = load_scene(scene.as_ref())?;
            scene.seed = seed.unwrap_or(scene.seed);
            let view = hexcal::sim::render(&scene)?;
            let [png, json] = hexcal::sim::write_view(&view, &out)?;
            let whole = view.truth.circles.iter().filter(|c| c.whole).count();
            println!(
                "{}: side {}, {} circles imaged ({whole} whole); truth in {}",
                png.display(),
                view.truth.side.map_or("none", |s| s.name()),
                view.truth.circles.len(),
                json.display()
            );
        }
        Command::Detect {
            board,
            json,
            overlay,
            images,
        } => detect_command(&board, &json, overlay.as_deref(), &images)?,
        Command::Bench {
            what:
                Bench::Calib {
                    cameras,
                    projectors,
                    poses,
                    sigma,
                },
        } => {
            let b = hexcal::calib::synthetic::bench_adjust(cameras, projectors, poses, sigma)?;
            println!(
                "bundle adjustment: {} devices, {} poses, {} observations, n = {}, p = {}, {} threads",
                b.devices,
                b.poses,
                b.observations,
                b.dof.0,
                b.dof.1,
                rayon::current_num_threads()
            );
            println!(
                "{:.3} s, {} LM iterations; posterior σ {:.4} px (simulated {sigma}), worst focal error {:.4} %",
                b.seconds,
                b.iterations,
                b.posterior_sigma,
                100.0 * b.worst_focal_error
            );
        }
        Command::Bench {
            what: Bench::Render { scene, repeat },
        } => {
            let scene = load_scene(scene.as_ref())?;
            println!("{}", hexcal::sim::bench_render(&scene, repeat)?);
        }
        Command::Bench {
            what: Bench::Detect { images, runs },
        } => bench_detect(&images, runs)?,
        Command::Bench {
            what: Bench::DetectGrid { runs, out },
        } => {
            use hexcal::detection::bench;
            // The views go to --out, else to a temporary directory, for OpenCV's run.
            let dir = out.clone().unwrap_or_else(|| {
                std::env::temp_dir().join(format!("hexcal-bench-{}", std::process::id()))
            });
            std::fs::create_dir_all(&dir)?;
            let report = bench::bench_detect_grid(&bench::scenes(), runs, Some(&dir));
            let side_by_side = report
                .is_ok()
                .then(|| bench::opencv_side_by_side(&dir, runs));
            if out.is_none() {
                std::fs::remove_dir_all(&dir)?;
            }
            print!("{}", report?);
            match side_by_side {
                Some(Ok(table)) => {
                    print!("\nOpenCV SimpleBlobDetector on the same views:\n{table}")
                }
                Some(Err(why)) => println!("\nOpenCV SimpleBlobDetector not run: {why}"),
                None => {}
            }
        }
        Command::Bench {
            what:
                Bench::Decode {
                    width,
                    height,
                    projectors,
                    repeats,
                },
        } => {
            let r = hexcal::phase::synthetic::bench_decode(width, height, projectors, repeats);
            let mib = |b: usize| b as f64 / (1024.0 * 1024.0);
            println!(
                "decode {}×{}, {} frames, P = {projectors}, {} threads (stack rendered in {:.1} s)",
                r.size.0,
                r.size.1,
                r.frames,
                rayon::current_num_threads(),
                r.render_seconds
            );
            for run in &r.runs {
                let cpu = |s: Option<f64>| s.map_or("n/a".into(), |s| format!("{s:.2} s"));
                println!(
                    "decode {:.3} s wall; CPU {} in frame pushes + {} in finish",
                    run.wall_seconds,
                    cpu(run.push_cpu_seconds),
                    cpu(run.finish_cpu_seconds)
                );
            }
            println!(
                "load average: {}",
                std::fs::read_to_string("/proc/loadavg")
                    .unwrap_or_default()
                    .trim()
            );
            println!(
                "decoder buffers {:.0} MiB, decoded maps {:.0} MiB, peak RSS growth {}",
                mib(r.decoder_bytes),
                mib(r.output_bytes),
                r.peak_growth_bytes
                    .map_or("n/a".into(), |b| format!("{:.0} MiB", mib(b)))
            );
            for (p, a) in r.accuracy.iter().enumerate() {
                println!(
                    "projector {p}: valid {} (compared {}), rms u {:.3} v {:.3} px, predicted σ_u {:.3} σ_v {:.3}, gross {}",
                    a.valid, a.compared, a.rms_u, a.rms_v, a.predicted_u, a.predicted_v, a.gross
                );
            }
        }
    }
    Ok(())
}
