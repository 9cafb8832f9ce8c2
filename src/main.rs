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
    }
    Ok(())
}
