//! The `hexcal` command line.

use anyhow::Context;
use clap::{Parser, Subcommand};
use hexcal::board::{Board, Side};
use std::path::{Path, PathBuf};

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
    /// Speed benchmarks that print figures.
    Bench {
        #[command(subcommand)]
        what: Bench,
    },
}

#[derive(Subcommand)]
enum Bench {
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
        /// Write the views, their truth and the figures here (for
        /// scripts/bench_opencv_blobs.py).
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
    use hexcal::detect::{detect, synth, DetectParams, GrayImage};
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
            .map(|p| Ok((p.display().to_string(), hexcal::imageio::load_gray(p)?)))
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

/// Write `bytes` to `path` through a temporary file beside it and a rename, so that `path`
/// holds either the old or the whole new content.
fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let name = path.file_name().context("output path has no file name")?;
    let tmp = path.with_file_name(format!(
        ".{}.tmp{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    std::fs::write(&tmp, bytes)
        .and_then(|()| std::fs::rename(&tmp, path))
        .inspect_err(|_| {
            let _ = std::fs::remove_file(&tmp);
        })
        .with_context(|| format!("cannot write {}", path.display()))
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
    write_atomic(json, to_json(images, &results).as_bytes())?;
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

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
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
            write_atomic(&out, board.svg(side).as_bytes())?;
            println!("{} {side} side written to {}", board.name, out.display());
        }
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
            let scenes = hexcal::detection::bench::scenes();
            let report =
                hexcal::detection::bench::bench_detect_grid(&scenes, runs, out.as_deref())?;
            print!("{report}");
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
