//! Nothing captured is ever lost (issue 16): `hexcal run --keep-stacks` on a tiny simulated
//! rig is killed 20 times — SIGINT and SIGKILL in turn, at times spread over a pose's capture
//! and processing — and resumed each time. Every frame, stack description and views file on
//! disk at a kill is found byte for byte after the last resume (where it was, or in the
//! `pose-KKK.interrupted-N` folder a partial pose is moved to); no temporary file is left;
//! the final calibration is the uninterrupted run's, byte for byte.

#[path = "support/cli.rs"]
mod cli;

use cli::scratch;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const KILLS: usize = 20;

fn rig() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/rigs/sim-tiny.toml")
}

fn run(out: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_hexcal"));
    c.args(["run", "--auto", "--keep-stacks", "--quiet", "--rig"])
        .arg(rig())
        .arg("--out")
        .arg(out)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    c
}

/// Every file under `dir` (relative path → content).
fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut all = BTreeMap::new();
    let mut dirs = vec![dir.to_owned()];
    while let Some(d) = dirs.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                dirs.push(p);
            } else if let Ok(bytes) = std::fs::read(&p) {
                all.insert(p.strip_prefix(dir).unwrap().to_owned(), bytes);
            }
        }
    }
    all
}

/// The captured files a kill must not lose: frames, stack descriptions, views.
fn captured(path: &Path) -> bool {
    let name = path.file_name().unwrap().to_string_lossy();
    !name.starts_with('.')
        && (name.starts_with("frame-") || name == "stack.json" || name == "views.json")
}

/// Where `path` (in pose folder `pose-KKK/…`) may be after a resume: in place, or in one of
/// the folders a partial pose was moved to.
fn places(path: &Path, after: &BTreeMap<PathBuf, Vec<u8>>) -> Vec<PathBuf> {
    let mut parts = path.iter();
    let pose = parts.next().unwrap().to_string_lossy().into_owned();
    let rest: PathBuf = parts.collect();
    let aside = after.keys().filter_map(|p| {
        let top = p.iter().next()?.to_string_lossy().into_owned();
        top.starts_with(&format!("{pose}.interrupted-"))
            .then(|| Path::new(&top).join(&rest))
    });
    std::iter::once(path.to_owned()).chain(aside).collect()
}

fn wait(child: &mut std::process::Child) -> (Option<i32>, String) {
    let status = child.wait().unwrap();
    let mut err = String::new();
    use std::io::Read;
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    (status.code(), err)
}

#[test]
fn killed_runs_lose_nothing_and_resume_to_the_same_calibration() {
    let dir = scratch("kill-resume");
    let reference = dir.join("reference");
    let t0 = Instant::now();
    let (code, err) = wait(&mut run(&reference).spawn().unwrap());
    assert_eq!(code, Some(0), "{err}");
    let whole = t0.elapsed().as_secs_f64();

    let out = dir.join("killed");
    let mut snapshots = Vec::new();
    for i in 0..KILLS {
        // Kill times spread over [5 %, 45 %] of a whole run (5 poses and the calibration):
        // before, during and after a pose's capture and processing.
        let at = whole * (0.05 + 0.4 * ((i * 7) % KILLS) as f64 / KILLS as f64);
        let mut child = run(&out).spawn().unwrap();
        std::thread::sleep(Duration::from_secs_f64(at));
        let signal = if i % 2 == 0 { "-INT" } else { "-KILL" };
        Command::new("kill")
            .args([signal, &child.id().to_string()])
            .status()
            .unwrap();
        let (code, err) = wait(&mut child);
        match signal {
            // Ctrl-C: stopped (130) having kept what was captured (during the capture, or
            // after it while processing or calibrating), or it came too late to stop
            // anything (the run finished).
            "-INT" => assert!(
                code == Some(130) && (err.contains("interrupted") || err.contains("stopped while"))
                    || code == Some(0),
                "kill {i} (SIGINT at {at:.1} s): exit {code:?}: {err}"
            ),
            _ => assert!(code.is_none() || code == Some(0), "kill {i}: {code:?}"),
        }
        snapshots.push(files(&out));
    }
    let (code, err) = wait(&mut run(&out).spawn().unwrap());
    assert_eq!(code, Some(0), "final resume: {err}");

    let after = files(&out);
    for (i, snapshot) in snapshots.iter().enumerate() {
        for (path, bytes) in snapshot.iter().filter(|(p, _)| captured(p)) {
            let kept = places(path, &after)
                .iter()
                .any(|p| after.get(p) == Some(bytes));
            assert!(
                kept,
                "after kill {i}: {} was lost or changed",
                path.display()
            );
        }
    }
    let temporaries: Vec<_> = after
        .keys()
        .filter(|p| p.file_name().unwrap().to_string_lossy().contains(".tmp"))
        .collect();
    assert!(temporaries.is_empty(), "left behind: {temporaries:?}");
    let calibration = Path::new("calibration/calibration.json");
    assert!(
        after.get(calibration) == files(&reference).get(calibration),
        "the resumed calibration differs from the uninterrupted run's"
    );
    let frames = after.keys().filter(|p| captured(p)).count();
    eprintln!("{KILLS} kills over a {whole:.1} s run; {frames} captured files checked");
    let _ = std::fs::remove_dir_all(&dir);
}
