//! The `hexcal` command line.

use clap::{Parser, Subcommand};

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
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Info => {
            let b = hexcal::board::Board::hex600();
            println!("{}: {} circles per side", b.name, b.lattice().len());
        }
    }
    Ok(())
}
