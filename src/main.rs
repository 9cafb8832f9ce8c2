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
}

fn load_scene(path: Option<&PathBuf>) -> anyhow::Result<hexcal::sim::Scene> {
    Ok(match path {
        Some(p) => hexcal::sim::Scene::load(p)?,
        None => hexcal::sim::Scene::default_scene(),
    })
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Info => {
            let b = hexcal::board::Board::hex600();
            println!("{}: {} circles per side", b.name, b.lattice().len());
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
        Command::Bench {
            what: Bench::Render { scene, repeat },
        } => {
            let scene = load_scene(scene.as_ref())?;
            println!("{}", hexcal::sim::bench_render(&scene, repeat)?);
        }
    }
    Ok(())
}
