//! Ctrl-C means stop, always (issue 33): a real SIGINT sent to `hexcal run` on the tiny
//! simulated rig in each phase — while capturing, right after the last capture (while the
//! last pose is processed) and while calibrating — stops the run with exit status 130, a
//! line at once on stderr, the complete poses kept and named, and no calibration written
//! when it came before the calibration finished; the same command then resumes and
//! finishes. A second Ctrl-C exits at once, saying so. `hexcal calibrate` stops too.

#[path = "support/cli.rs"]
mod cli;

use cli::scratch;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStderr, Command, Stdio};
use std::time::{Duration, Instant};

/// A stopped run must exit well within this (the target is a second or two; the bound
/// only tells a stop from a run that ignored the signal and went on).
const ANSWER: Duration = Duration::from_secs(20);

fn rig() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/rigs/sim-tiny.toml")
}

fn spawn(args: &[&std::ffi::OsStr]) -> (Child, BufReader<ChildStderr>) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let err = BufReader::new(child.stderr.take().unwrap());
    (child, err)
}

fn run(out: &Path) -> (Child, BufReader<ChildStderr>) {
    spawn(&[
        "run".as_ref(),
        "--auto".as_ref(),
        "--rig".as_ref(),
        rig().as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ])
}

/// Reads stderr until a line containing `mark`; gives the lines read.
fn until(err: &mut BufReader<ChildStderr>, mark: &str) -> String {
    let mut seen = String::new();
    loop {
        let mut line = String::new();
        let n = err.read_line(&mut line).unwrap();
        assert!(n > 0, "the run ended before {mark:?}:\n{seen}");
        seen.push_str(&line);
        if line.contains(mark) {
            return seen;
        }
    }
}

fn signal(child: &Child, which: &str) {
    let status = Command::new("kill")
        .args([which, &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
}

fn sigint(child: &Child) {
    signal(child, "-INT");
}

/// Waits for the child (at most [`ANSWER`]): its exit status, the rest of stderr and how
/// long it took after the signal.
fn ended(mut child: Child, mut err: BufReader<ChildStderr>) -> (Option<i32>, String, f64) {
    let t = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t.elapsed() > ANSWER {
            let _ = child.kill();
            panic!("no exit {ANSWER:?} after Ctrl-C");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let answer = t.elapsed().as_secs_f64();
    let mut rest = String::new();
    err.read_to_string(&mut rest).unwrap();
    (status.code(), rest, answer)
}

/// Ctrl-C when `mark` is printed: exit 130 with the immediate acknowledgement; gives the
/// rest of stderr.
fn stop_at(out: &Path, mark: &str) -> String {
    let (child, mut err) = run(out);
    until(&mut err, mark);
    sigint(&child);
    let (code, rest, answer) = ended(child, err);
    eprintln!("Ctrl-C at {mark:?}: exit {code:?} {answer:.2} s after the signal");
    assert_eq!(code, Some(130), "Ctrl-C at {mark:?}:\n{rest}");
    assert!(rest.contains("hexcal: stopping (Ctrl-C)"), "{rest}");
    rest
}

#[test]
fn ctrl_c_stops_every_phase_of_a_run_and_the_same_command_resumes() {
    let dir = scratch("ctrl-c");
    let out = dir.join("run");
    let calibration = out.join("calibration/calibration.json");

    // While capturing pose 1: pose 0 (captured, processing) is finished and kept.
    let rest = stop_at(&out, "pose 1 of 5: capturing");
    assert!(
        rest.contains("interrupted: complete poses [0] are kept"),
        "{rest}"
    );

    // Right after the last capture, while the last pose is processed (on a fast machine
    // the processing may just have finished: then the calibration is what stops).
    let rest = stop_at(&out, "pose 4: captured");
    assert!(
        rest.contains("stopped while processing the captured poses: complete poses [0, 1, 2, 3, 4] are kept")
            || rest.contains("stopped while calibrating (nothing of the calibration was written): complete poses [0, 1, 2, 3, 4] are kept"),
        "{rest}"
    );
    assert!(!calibration.exists());

    // While calibrating: every pose kept, nothing of the calibration written.
    let rest = stop_at(&out, "calibrating from");
    assert!(
        rest.contains("stopped while calibrating (nothing of the calibration was written): complete poses [0, 1, 2, 3, 4] are kept"),
        "{rest}"
    );
    assert!(!calibration.exists());

    // The same command resumes: nothing captured again, the calibration written.
    let (child, err) = run(&out);
    let (code, rest, _) = ended(child, err);
    assert_eq!(code, Some(0), "{rest}");
    assert!(
        rest.contains("resuming: poses [0, 1, 2, 3, 4] already complete"),
        "{rest}"
    );
    assert!(!rest.contains("capturing"), "{rest}");
    assert!(calibration.exists());
}

#[test]
fn a_second_ctrl_c_exits_at_once_saying_so_and_calibrate_stops_too() {
    let dir = scratch("ctrl-c-twice");
    let out = dir.join("run");
    let (child, mut err) = run(&out);
    until(&mut err, "calibrating from");
    // Two Ctrl-Cs at once, however fast the first stop: with the run held (SIGSTOP), a
    // SIGINT and a SIGTERM (two of one kind pending would be one) wait to be taken in turn.
    signal(&child, "-STOP");
    signal(&child, "-INT");
    signal(&child, "-TERM");
    signal(&child, "-CONT");
    let (code, rest, _) = ended(child, err);
    assert_eq!(code, Some(130), "{rest}");
    assert!(
        rest.contains("hexcal: stopped at once (second Ctrl-C): every file written is whole"),
        "{rest}"
    );
    assert!(!out.join("calibration/calibration.json").exists());

    // `hexcal calibrate` on the dataset the run left: Ctrl-C while it calibrates.
    let cal = dir.join("cal");
    let (child, mut err) = spawn(&[
        "calibrate".as_ref(),
        out.as_os_str(),
        "--out".as_ref(),
        cal.as_os_str(),
    ]);
    until(&mut err, "calibrating from");
    sigint(&child);
    let (code, rest, answer) = ended(child, err);
    eprintln!("calibrate: exit {code:?} {answer:.2} s after Ctrl-C");
    assert_eq!(code, Some(130), "{rest}");
    assert!(
        rest.contains(
            "stopped (Ctrl-C) before the calibration finished; nothing of it was written"
        ),
        "{rest}"
    );
    assert!(!cal.join("calibration.json").exists());
}
