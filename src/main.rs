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
        Command::Bench {
            what: Bench::Render { scene, repeat },
        } => {
            let scene = load_scene(scene.as_ref())?;
            println!("{}", hexcal::sim::bench_render(&scene, repeat)?);
        }
    }
    Ok(())
}
