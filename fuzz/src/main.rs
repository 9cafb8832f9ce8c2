//! `hexcal-fuzz`: a seeded mutation fuzzer for hexcal's file readers, the trigger
//! protocol and detection (docs/fuzzing.md). Pure Rust on the stable toolchain: every
//! target runs under `catch_unwind`, with a capped allocator ([`alloc`]) and a time limit
//! per input; inputs that panic, run too long or break the cap are saved under
//! `fuzz/artifacts/TARGET/`. Inputs with an outcome not seen before join the mutation pool
//! (the feedback a coverage-blind fuzzer can have).

mod alloc;
mod mutate;
mod seeds;
mod targets;

use clap::{Parser, Subcommand};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};
use targets::{Target, TARGETS};

#[global_allocator]
static ALLOCATOR: alloc::Capped = alloc::Capped;

/// An input taking more CPU time than this is a failure (a hang, or work out of
/// proportion to its size). CPU time, not wall time: on a loaded machine a descheduled
/// process is not a slow input.
const SLOW: Duration = Duration::from_secs(2);

/// CPU time of this process so far (every thread).
fn cpu_time() -> Duration {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime fills the timespec it is given.
    unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut t) };
    Duration::new(t.tv_sec as u64, t.tv_nsec as u32)
}

/// Most inputs kept in a target's mutation pool.
const MAX_POOL: usize = 4096;

/// Fuzz hexcal's readers (docs/fuzzing.md).
#[derive(Parser)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// List the targets.
    List,
    /// Mutate the targets' corpora: `inputs` per target, or until `seconds` pass.
    Run {
        /// Targets (all when none is named).
        targets: Vec<String>,
        /// Inputs per target.
        #[arg(long, default_value_t = 1_000_000)]
        inputs: u64,
        /// Stop each target after this many seconds.
        #[arg(long)]
        seconds: Option<f64>,
        /// Seed of the mutations.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Run every corpus file (and, with --artifacts, every saved failure) once.
    Replay {
        /// Targets (all when none is named).
        targets: Vec<String>,
        /// Also the saved failures in fuzz/artifacts.
        #[arg(long)]
        artifacts: bool,
    },
    /// CI: replay every corpus, then a seeded run of every target, `seconds` in all.
    Ci {
        /// Time for the seeded runs of all targets together.
        #[arg(long, default_value_t = 40.0)]
        seconds: f64,
        /// Seed of the mutations.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// (Re)write the generated seed files of the corpus (JSON, images, protocol frames).
    Seed,
}

/// The last panic's message and place (the hook keeps it; `catch_unwind` gives no text).
static LAST_PANIC: Mutex<String> = Mutex::new(String::new());

fn fuzz_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The files of a folder, sorted (none when it does not exist).
fn files(dir: &Path) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|d| d.filter_map(|e| e.ok()).map(|e| e.path()).collect())
        .unwrap_or_default();
    out.retain(|p| p.is_file());
    out.sort();
    out
}

/// Why an input failed.
enum Failure {
    /// It panicked (the message).
    Panic(String),
    /// It took this long.
    Slow(Duration),
}

/// Runs `input` on `target`: its outcome, or how it failed. `artifact` is where the
/// allocator saves it if it breaks the cap.
fn run_one(target: &Target, input: &[u8], artifact: &std::ffi::CStr) -> Result<String, Failure> {
    alloc::set_input(input, artifact);
    let t = cpu_time();
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| (target.run)(input)));
    alloc::clear_input();
    let took = cpu_time().saturating_sub(t);
    match result {
        Err(_) => Err(Failure::Panic(
            LAST_PANIC.lock().unwrap_or_else(|e| e.into_inner()).clone(),
        )),
        Ok(_) if took > SLOW => Err(Failure::Slow(took)),
        Ok(outcome) => Ok(outcome),
    }
}

/// The counts of one target's campaign.
#[derive(Default)]
struct Stats {
    inputs: u64,
    outcomes: usize,
    failures: Vec<String>,
    seconds: f64,
}

/// Where the allocator saves an input of `target` that breaks the cap.
fn alloc_artifact(target: &Target) -> std::ffi::CString {
    let dir = fuzz_dir().join("artifacts").join(target.name);
    std::fs::create_dir_all(&dir).expect("the artifacts folder can be created");
    let path = dir.join("alloc-cap");
    std::ffi::CString::new(path.display().to_string()).expect("no NUL in the path")
}

/// Saves a failing input and says what failed.
fn record(target: &Target, input: &[u8], failure: &Failure) -> String {
    let (kind, what) = match failure {
        Failure::Panic(m) => ("panic", m.clone()),
        Failure::Slow(d) => ("slow", format!("took {:.1} s of CPU", d.as_secs_f64())),
    };
    let hash = input.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3)
    });
    let path = fuzz_dir()
        .join("artifacts")
        .join(target.name)
        .join(format!("{kind}-{hash:016x}"));
    let saved =
        std::fs::write(&path, input).map_or_else(|e| e.to_string(), |_| path.display().to_string());
    format!("{}: {kind}: {what} (input: {saved})", target.name)
}

/// Mutates `target`'s corpus for `inputs` inputs or until `until`.
fn campaign(target: &Target, inputs: u64, until: Option<Instant>, seed: u64) -> Stats {
    let artifact = alloc_artifact(target);
    let corpus: Vec<Vec<u8>> = files(&fuzz_dir().join("corpus").join(target.name))
        .iter()
        .filter_map(|p| std::fs::read(p).ok())
        .collect();
    let dict = mutate::dictionary(&corpus);
    let mut pool = corpus.clone();
    let mut seen = HashSet::new();
    let mut stats = Stats::default();
    let start = Instant::now();
    let name_hash = target
        .name
        .bytes()
        .fold(seed, |h, b| h.rotate_left(5) ^ u64::from(b));
    let mut rng = mutate::Rng::new(name_hash);
    for input in &corpus {
        stats.inputs += 1;
        match run_one(target, input, &artifact) {
            Ok(outcome) => {
                seen.insert(outcome);
            }
            Err(f) => stats.failures.push(record(target, input, &f)),
        }
    }
    while stats.inputs < inputs {
        if stats.inputs % 64 == 0 && until.is_some_and(|u| Instant::now() >= u) {
            break;
        }
        let input = mutate::mutate(&pool, &dict, &mut rng);
        stats.inputs += 1;
        match run_one(target, &input, &artifact) {
            Ok(outcome) => {
                if seen.insert(outcome) && pool.len() < MAX_POOL {
                    pool.push(input);
                }
            }
            Err(f) => stats.failures.push(record(target, &input, &f)),
        }
    }
    stats.outcomes = seen.len();
    stats.seconds = start.elapsed().as_secs_f64();
    stats
}

/// Runs every file of `dirs` on `target`: the failures.
fn replay(target: &Target, dirs: &[PathBuf]) -> (usize, Vec<String>) {
    let artifact = alloc_artifact(target);
    let mut failures = Vec::new();
    let mut count = 0;
    for path in dirs.iter().flat_map(|d| files(d)) {
        let input = std::fs::read(&path).unwrap_or_default();
        count += 1;
        if let Err(f) = run_one(target, &input, &artifact) {
            let what = match f {
                Failure::Panic(m) => format!("panic: {m}"),
                Failure::Slow(d) => format!("slow: {:.1} s of CPU", d.as_secs_f64()),
            };
            failures.push(format!("{}: {}: {what}", target.name, path.display()));
        }
    }
    (count, failures)
}

/// The targets named, or all.
fn chosen(names: &[String]) -> Result<Vec<&'static Target>, String> {
    if names.is_empty() {
        return Ok(TARGETS.iter().collect());
    }
    names
        .iter()
        .map(|n| targets::find(n).ok_or_else(|| format!("no target {n:?} (see `list`)")))
        .collect()
}

/// Prints one target's campaign line; its failures go to `failures`.
fn report(target: &Target, stats: Stats, failures: &mut Vec<String>) {
    println!(
        "{}: {} inputs in {:.1} s ({:.0}/s), {} outcomes, {} failures",
        target.name,
        stats.inputs,
        stats.seconds,
        stats.inputs as f64 / stats.seconds.max(1e-9),
        stats.outcomes,
        stats.failures.len()
    );
    failures.extend(stats.failures);
}

/// Runs the command: the failures found.
fn execute(command: Command) -> Result<Vec<String>, String> {
    let corpus = |t: &Target| fuzz_dir().join("corpus").join(t.name);
    let mut failures = Vec::new();
    match command {
        Command::List => {
            for t in TARGETS {
                let kind = if t.parser { "parser" } else { "image" };
                println!("{:<16} {kind:<7} {}", t.name, t.about);
            }
        }
        Command::Seed => seeds::write(&fuzz_dir().join("corpus")).map_err(|e| e.to_string())?,
        Command::Replay { targets, artifacts } => {
            for t in chosen(&targets)? {
                let mut dirs = vec![corpus(t)];
                if artifacts {
                    dirs.push(fuzz_dir().join("artifacts").join(t.name));
                }
                let (n, f) = replay(t, &dirs);
                println!("{}: {n} inputs replayed, {} failures", t.name, f.len());
                failures.extend(f);
            }
        }
        Command::Run {
            targets,
            inputs,
            seconds,
            seed,
        } => {
            for t in chosen(&targets)? {
                let until = seconds.map(|s| Instant::now() + Duration::from_secs_f64(s));
                report(t, campaign(t, inputs, until, seed), &mut failures);
            }
        }
        Command::Ci { seconds, seed } => {
            for t in TARGETS {
                let (n, f) = replay(t, &[corpus(t)]);
                println!(
                    "{}: corpus of {n} inputs replayed, {} failures",
                    t.name,
                    f.len()
                );
                failures.extend(f);
            }
            let each = Duration::from_secs_f64(seconds / TARGETS.len() as f64);
            for t in TARGETS {
                report(
                    t,
                    campaign(t, u64::MAX, Some(Instant::now() + each), seed),
                    &mut failures,
                );
            }
        }
    }
    Ok(failures)
}

fn main() -> std::process::ExitCode {
    std::panic::set_hook(Box::new(|info| {
        *LAST_PANIC.lock().unwrap_or_else(|e| e.into_inner()) = info.to_string().replace('\n', " ");
    }));
    let cli = Cli::parse();
    match execute(cli.command) {
        Ok(failures) if failures.is_empty() => std::process::ExitCode::SUCCESS,
        Ok(failures) => {
            for f in &failures {
                eprintln!("FAILED {f}");
            }
            eprintln!("{} failures", failures.len());
            std::process::ExitCode::FAILURE
        }
        Err(e) => {
            eprintln!("error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}
