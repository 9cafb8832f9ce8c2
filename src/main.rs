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
    /// Speed benchmarks that print figures.
    #[command(subcommand)]
    Bench(Bench),
}

#[derive(Subcommand)]
enum Bench {
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

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Info => {
            let b = hexcal::board::Board::hex600();
            println!("{}: {} circles per side", b.name, b.lattice().len());
        }
        Command::Bench(Bench::Decode {
            width,
            height,
            projectors,
            repeats,
        }) => {
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
