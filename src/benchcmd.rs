//! `hexcal bench …`: the speed benchmarks, each printing its figures.

use anyhow::Context;
use clap::Subcommand;
use std::path::{Path, PathBuf};

#[derive(Subcommand)]
pub enum Bench {
    /// Bundle adjustment of a synthetic rig (6 cameras and 3 projectors: the paper-like rig;
    /// otherwise cameras and projectors on a ring): time, peak memory, σ̂ and the worst
    /// parameter error against the truth.
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
        /// Seed of the rig and its noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Start from Zhang per device and the pose graph (as `hexcal calibrate`), not from
        /// the perturbed truth.
        #[arg(long)]
        real_start: bool,
        /// Instead of one rig, the growth table: 6/3/10, 12/4/20, 20/4/40, 40/4/60 and
        /// 60/4/100 (cameras/projectors/poses), each in its own process, one line each.
        #[arg(long, conflicts_with_all = ["cameras", "projectors", "poses"])]
        table: bool,
    },
    /// Frames per second through the capture engine on a simulated rig (one pose, frames
    /// discarded), with one camera's stack rendering broken down.
    Capture {
        /// The rig file.
        #[arg(long, default_value = "rigs/sim-paper.toml")]
        rig: PathBuf,
    },
    /// A guided operator (each next pose where the console's guidance suggests, placed with
    /// noise) against the rig's fixed schedule: poses until every device's projection
    /// uncertainty is below the rig's threshold, and accuracy against the truth.
    Guide {
        /// The rig file (simulated devices and `[poses]`, the fixed schedule).
        #[arg(long, default_value = "rigs/sim-paper.toml")]
        rig: PathBuf,
        /// Observation noise σ (px).
        #[arg(long, default_value_t = 0.1)]
        sigma: f64,
        /// Most poses of the guided operator.
        #[arg(long, default_value_t = 20)]
        max_poses: usize,
        /// Seed of the noise and the placement errors.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// The console's live preview on a simulated rig: rounds per second and where a
    /// round's time goes (frame grab incl. rendering, reduce, detect, grid, picture).
    Preview {
        /// The rig file.
        #[arg(long, default_value = "rigs/sim-paper.toml")]
        rig: PathBuf,
        /// The board pose (of the rig's `[poses]`) placed.
        #[arg(long, default_value_t = 0)]
        pose: usize,
        /// Rounds timed (after one untimed).
        #[arg(long, default_value_t = 10)]
        rounds: usize,
    },
    /// Step-timing jitter of a rig file's capture script on its simulated devices (the
    /// stage on a pty, waits, timed captures), captures taking no time.
    Script {
        /// The rig file.
        #[arg(long, default_value = "rigs/sim-turntable.toml")]
        rig: PathBuf,
    },
    /// Frames per second through a GigE Vision camera on loopback (the in-process Aravis
    /// fake camera serving known frames, each checked); needs `--features loopback`.
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
    /// Detection on rendered views through each camera pixel format (mono, Bayer raw and
    /// balanced, MJPEG at quality 95 and 85): recall, labelled points, centre error and the
    /// conversion's time per frame.
    ///
    /// With `--rig R` (a simulated rig with projectors): the rig's cameras in each format
    /// through the real capture path, `--poses` poses each: phase error against the
    /// simulator's projector coordinates beside the decoder's predicted σ, detection recall
    /// and centre error, labelled points and projector observations.
    Formats {
        /// Noise draws of each of the two detect-grid scenes.
        #[arg(long, default_value_t = 4)]
        seeds: u64,
        /// A simulated rig file: compare its cameras' formats side by side instead.
        #[arg(long)]
        rig: Option<PathBuf>,
        /// Board poses per format (with `--rig`).
        #[arg(long, default_value_t = 2)]
        poses: usize,
    },
    /// The stack check's false alarms on clean simulated stacks of varied scenes.
    Check {
        /// Stacks to decode.
        #[arg(long, default_value_t = 1000)]
        stacks: usize,
        /// Seed of the scenes.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// The first stack decoded (the scenes before it are drawn, not decoded).
        #[arg(long, default_value_t = 0)]
        from: usize,
    },
    /// The stack check against faults of drawn kinds and sizes: each stack refused with its
    /// cause named, or as accurate as the same stack clean (within 1.5×).
    Faults {
        /// Stacks to decode (each twice: clean and faulty).
        #[arg(long, default_value_t = 300)]
        stacks: usize,
        /// Seed of the scenes and faults.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// The first stack decoded (the ones before it are drawn, not decoded).
        #[arg(long, default_value_t = 0)]
        from: usize,
        /// Print every stack's fault and verdict, not only those used silently or refused
        /// with another cause.
        #[arg(long)]
        every: bool,
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
        /// Timed decodes of the same stack (each with the stack check and without it).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
}

/// The rig sizes of `hexcal bench calib --table` (cameras, projectors, poses).
const TABLE_SIZES: [(usize, usize, usize); 5] = [
    (6, 3, 10),
    (12, 4, 20),
    (20, 4, 40),
    (40, 4, 60),
    (60, 4, 100),
];

/// `hexcal bench calib --table`: every size of [`TABLE_SIZES`] in a child process of this
/// binary (so each peak memory is that size's own), one line per size as it finishes.
fn bench_calib_table(sigma: f64, seed: u64, real_start: bool) -> anyhow::Result<()> {
    let exe = std::env::current_exe().context("locating the hexcal binary")?;
    println!("cameras/projectors/poses: rig; adjustment");
    for (c, p, k) in TABLE_SIZES {
        let mut cmd = std::process::Command::new(&exe);
        cmd.arg("bench").arg("calib");
        for (flag, v) in [("--cameras", c), ("--projectors", p), ("--poses", k)] {
            cmd.arg(flag).arg(v.to_string());
        }
        cmd.arg("--sigma").arg(sigma.to_string());
        cmd.arg("--seed").arg(seed.to_string());
        if real_start {
            cmd.arg("--real-start");
        }
        let out = cmd
            .output()
            .with_context(|| format!("running size {c}/{p}/{k}"))?;
        let text = String::from_utf8_lossy(&out.stdout);
        let lines: Vec<&str> = text.lines().collect();
        match (out.status.success(), lines.as_slice()) {
            (true, [rig, result, ..]) => {
                let rig = rig.trim_start_matches("bundle adjustment: ");
                println!("{c}/{p}/{k}: {rig}\n    {result}");
            }
            _ => println!(
                "{c}/{p}/{k}: failed ({}): {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        }
    }
    Ok(())
}

/// Run one benchmark and print its figures.
pub fn run(what: Bench) -> anyhow::Result<()> {
    match what {
        Bench::Capture { rig } => print!("{}", hexcal::bench::capture::bench_capture(&rig)?),
        Bench::Script { rig } => bench_script(&rig)?,
        Bench::Preview { rig, pose, rounds } => bench_preview(&rig, pose, rounds)?,
        Bench::Guide {
            rig,
            sigma,
            max_poses,
            seed,
        } => bench_guide(&rig, sigma, max_poses, seed)?,
        Bench::Aravis {
            width,
            height,
            bits,
            frames,
        } => println!(
            "{}",
            hexcal::bench::capture::bench_aravis(width, height, bits, frames)?
        ),
        Bench::Window { monitor, slides } => println!(
            "{}",
            hexcal::bench::capture::bench_window(monitor.as_deref(), slides)?
        ),
        Bench::Calib {
            sigma,
            seed,
            real_start,
            table: true,
            ..
        } => bench_calib_table(sigma, seed, real_start)?,
        Bench::Calib {
            cameras,
            projectors,
            poses,
            sigma,
            seed,
            real_start,
            table: false,
        } => print!(
            "{}",
            hexcal::bench::calib::bench_calib(cameras, projectors, poses, sigma, seed, real_start)?
        ),
        Bench::Render { scene, repeat } => {
            let scene = hexcal::app::jobs::scene(scene.as_deref())?;
            println!("{}", hexcal::bench::render::bench_render(&scene, repeat)?);
        }
        Bench::Detect { images, runs } => {
            print!("{}", hexcal::bench::detect::bench_detect(&images, runs)?)
        }
        Bench::Formats { seeds, rig, poses } => match rig {
            Some(rig) => print!(
                "{}",
                hexcal::bench::formats_rig::bench_formats_rig(&rig, poses)?
            ),
            None => print!("{}", hexcal::bench::formats::bench_formats(seeds)?),
        },
        Bench::DetectGrid { runs, out } => {
            use hexcal::bench::detect_grid as bench;
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
        Bench::Check { stacks, seed, from } => {
            let r = hexcal::bench::check::bench_check(stacks, seed, from);
            for line in r.refused.iter().chain(&r.noted).take(20) {
                println!("{line}");
            }
            println!(
                "stack check on {} clean stacks: {} refused, {} with a note; {:.1} s ({:.2} s per stack)",
                r.stacks,
                r.refused.len(),
                r.noted.len(),
                r.seconds,
                r.seconds / r.stacks.max(1) as f64
            );
        }
        Bench::Faults {
            stacks,
            seed,
            from,
            every,
        } => print_faults(stacks, seed, from, every),
        Bench::Decode {
            width,
            height,
            projectors,
            repeats,
        } => {
            let r = hexcal::bench::decode::bench_decode(width, height, projectors, repeats);
            let mib = |b: usize| b as f64 / (1024.0 * 1024.0);
            println!(
                "decode {}×{}, {} frames, P = {projectors}, {} threads (stack rendered in {:.1} s)",
                r.size.0,
                r.size.1,
                r.frames,
                rayon::current_num_threads(),
                r.render_seconds
            );
            let cpu = |s: Option<f64>| s.map_or("n/a".into(), |s| format!("{s:.2} s"));
            for (run, bare) in r.runs.iter().zip(&r.unchecked_runs) {
                println!(
                    "decode {:.3} s wall; CPU {} in frame pushes + {} in finish (without the check: {:.3} s wall; CPU {} + {})",
                    run.wall_seconds,
                    cpu(run.push_cpu_seconds),
                    cpu(run.finish_cpu_seconds),
                    bare.wall_seconds,
                    cpu(bare.push_cpu_seconds),
                    cpu(bare.finish_cpu_seconds)
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
            let (median, cpu_median) = medians(&r.runs);
            let (bare, bare_cpu) = medians(&r.unchecked_runs);
            println!(
                "the check within the decode: {:.3} s wall ({:.1} % of the median decode), CPU {} ({}): the medians with and without it",
                median - bare,
                100.0 * (median - bare) / median,
                cpu_median
                    .zip(bare_cpu)
                    .map_or("n/a".into(), |(c, b)| format!("{:.2} s", c - b)),
                cpu_median
                    .zip(bare_cpu)
                    .map_or("n/a".into(), |(c, b)| format!("{:.1} %", 100.0 * (c - b) / c)),
            );
            println!(
                "stack check {:.3} s wall alone ({:.1} % of the median decode {median:.3} s, which includes it); CPU {} ({} of a decode's median CPU); verdict: {}",
                r.check_seconds,
                100.0 * r.check_seconds / median,
                r.check_cpu_seconds.map_or("n/a".into(), |c| format!("{c:.2} s")),
                r.check_cpu_seconds
                    .zip(cpu_median)
                    .map_or("n/a".into(), |(c, d)| format!("{:.1} %", 100.0 * c / d)),
                match r.verdict.passed() {
                    true => "passed".to_string(),
                    false => r.verdict.summary(),
                }
            );
        }
    }
    Ok(())
}

/// The median wall time of `runs` and their median CPU time (pushes + finish), if measured.
fn medians(runs: &[hexcal::bench::decode::DecodeRun]) -> (f64, Option<f64>) {
    let mut walls: Vec<f64> = runs.iter().map(|run| run.wall_seconds).collect();
    walls.sort_by(f64::total_cmp);
    let mut cpus: Vec<f64> = (runs.iter())
        .filter_map(|run| Some(run.push_cpu_seconds? + run.finish_cpu_seconds?))
        .collect();
    cpus.sort_by(f64::total_cmp);
    (walls[walls.len() / 2], cpus.get(cpus.len() / 2).copied())
}

/// `hexcal bench capture`: one simulated pose through the engine, frames discarded.
/// `hexcal bench preview`: live preview rounds per second and their stages.
fn bench_preview(rig: &Path, pose: usize, rounds: usize) -> anyhow::Result<()> {
    let b = hexcal::bench::preview::bench_preview(rig, pose, rounds, &mut |l| eprintln!("{l}"))?;
    let s = &b.stages;
    println!(
        "rig {}: {} cameras, pose {pose}, {} threads, {} rounds: {:.2} rounds/s",
        rig.display(),
        b.cameras,
        rayon::current_num_threads(),
        b.rounds,
        b.rate_hz
    );
    println!(
        "per round: grab {:.0} ms (wall), tap {:.0} ms (wall); tap CPU over the cameras: reduce {:.0}, detect {:.0}, grid {:.0}, picture {:.0} ms; {} of {} cameras see the board",
        b.grab_ms, b.tap_ms, s.reduce, s.detect, s.grid, s.picture, b.seeing, b.cameras
    );
    Ok(())
}

/// `hexcal bench guide`: guided against fixed, poses to done and accuracy.
fn bench_guide(rig: &Path, sigma: f64, max_poses: usize, seed: u64) -> anyhow::Result<()> {
    let b =
        hexcal::bench::guide::bench_guide(rig, sigma, max_poses, seed, &mut |l| eprintln!("{l}"))?;
    println!(
        "rig {}: threshold {} px, observation noise {} px, guided placement noise {}° / {} mm",
        rig.display(),
        b.threshold,
        b.sigma,
        hexcal::app::guide::operator::PLACEMENT_DEG,
        hexcal::app::guide::operator::PLACEMENT_MM
    );
    for r in &b.runs {
        let trail: Vec<String> = r.worst.iter().map(|(k, w)| format!("{k}:{w:.3}")).collect();
        println!("{:<7} worst px after poses  {}", r.label, trail.join("  "));
    }
    let poses = |k: Option<usize>, r: &hexcal::bench::guide::OperatorRun| {
        k.map_or_else(
            || format!("> {}", r.worst.last().map_or(0, |w| w.0)),
            |k| k.to_string(),
        )
    };
    println!(
        "until done (every device below {} px and covered):",
        b.threshold
    );
    guide_table(&b.runs, &|r| (poses(r.done_at, r), &r.truth));
    println!(
        "until the fixed schedule's uncertainty after all its poses ({:.3} px):",
        b.fixed_final
    );
    guide_table(&b.runs, &|r| (poses(r.matched_at, r), &r.truth_matched));
    Ok(())
}

/// One table of `bench guide`: per operator the poses `at` gives and the accuracy there.
#[allow(clippy::type_complexity)]
fn guide_table(
    runs: &[hexcal::bench::guide::OperatorRun],
    at: &dyn Fn(
        &hexcal::bench::guide::OperatorRun,
    ) -> (String, &Vec<hexcal::app::truth::TruthCheck>),
) {
    println!(
        "{:<7} {:>6} {:>12} {:>12} {:>12} {:>12} {:>10}  worst position",
        "", "poses", "focal err %", "pp err px", "rot err deg", "pos err mm", "s/pose"
    );
    for r in runs {
        let (poses, truth) = at(r);
        let max = |f: &dyn Fn(&hexcal::app::truth::TruthCheck) -> f64| {
            truth.iter().map(f).fold(0.0, f64::max)
        };
        let far = truth
            .iter()
            .max_by(|a, b| a.position_error_mm.total_cmp(&b.position_error_mm))
            .map_or("", |c| c.name.as_str());
        println!(
            "{:<7} {:>6} {:>12.4} {:>12.3} {:>12.4} {:>12.3} {:>10.2}  {far}",
            r.label,
            poses,
            100.0 * max(&|c| c.focal_error),
            max(&|c| c.principal_error),
            max(&|c| c.rotation_error_deg),
            max(&|c| c.position_error_mm),
            r.seconds_per_pose
        );
    }
}

/// `hexcal bench script`: the script's step timing, per kind of step.
fn bench_script(rig_path: &Path) -> anyhow::Result<()> {
    let scratch = std::env::temp_dir().join(format!("hexcal-bench-script-{}", std::process::id()));
    let b = hexcal::bench::script::bench_script(rig_path, &scratch);
    let _ = std::fs::remove_dir_all(&scratch);
    let b = b?;
    println!("{}", b.jitter);
    println!(
        "{:<8} {:>6} {:>14} {:>14} {:>18}",
        "step", "count", "late mean ms", "late max ms", "overrun mean ms"
    );
    for k in &b.kinds {
        println!(
            "{:<8} {:>6} {:>14.3} {:>14.3} {:>18.3}",
            k.kind,
            k.steps,
            1e3 * k.late_mean_s,
            1e3 * k.late_max_s,
            1e3 * k.overrun_mean_s
        );
    }
    Ok(())
}

/// `bench faults`: per kind of fault the stacks refused (with the cause named or not),
/// used accurately, and used although inaccurate (silent), with every silent case (`every`:
/// every case).
fn print_faults(stacks: usize, seed: u64, from: usize, every: bool) {
    use hexcal::bench::faults::{bench_faults, FaultKind};
    let t = std::time::Instant::now();
    let cases = bench_faults(stacks, seed, from);
    for c in cases
        .iter()
        .filter(|c| every || c.silent() || (c.refused && !c.right_cause))
    {
        let what = match (c.silent(), c.refused, c.right_cause) {
            (true, _, _) => "SILENT",
            (_, true, false) => "other cause",
            (_, true, true) => "refused",
            (_, false, _) => "used",
        };
        println!(
            "{what}: {} (ratio {:.2}): {}\n    {}",
            c.label, c.ratio, c.verdict, c.detail
        );
    }
    println!("kind           stacks  refused (named)  used  worst used ratio  silent");
    for kind in FaultKind::ALL {
        let name = kind.name();
        let of: Vec<_> = cases.iter().filter(|c| c.kind == kind).collect();
        let refused = of.iter().filter(|c| c.refused).count();
        let named = of.iter().filter(|c| c.refused && c.right_cause).count();
        let used: Vec<f64> = of.iter().filter(|c| !c.refused).map(|c| c.ratio).collect();
        let worst = used.iter().cloned().fold(0.0, f64::max);
        let silent = of.iter().filter(|c| c.silent()).count();
        println!(
            "{name:<14} {:>6}  {refused:>7} ({named:>3})  {:>4}  {worst:>16.2}  {silent:>6}",
            of.len(),
            used.len()
        );
    }
    println!(
        "{} faulty stacks, {} silent; {:.1} s",
        cases.len(),
        cases.iter().filter(|c| c.silent()).count(),
        t.elapsed().as_secs_f64()
    );
}
