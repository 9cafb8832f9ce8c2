//! The `hexcal` command line.

use clap::{Parser, Subcommand};
use std::path::PathBuf;

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
    /// Measure the speed of a stage (build with --release).
    Bench {
        #[command(subcommand)]
        what: Bench,
    },
}

#[derive(Subcommand)]
enum Bench {
    /// Circle detection on the given images, or on built-in synthetic boards
    /// (1920×1200 and 4096×3000) when none are given.
    Detect {
        /// Images to detect in.
        images: Vec<PathBuf>,
        /// Timed runs per image (after one warm-up run); the median is printed.
        #[arg(long, default_value_t = 7)]
        runs: usize,
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

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Info => {
            let b = hexcal::board::Board::hex600();
            println!("{}: {} circles per side", b.name, b.lattice().len());
        }
        Command::Bench {
            what: Bench::Detect { images, runs },
        } => bench_detect(&images, runs)?,
    }
    Ok(())
}
