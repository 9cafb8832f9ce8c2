//! Capture scripts through the binary (issue 18): a tiny simulated rig whose board sits on
//! the simulated stage (a firmware model on a real pty) runs unattended to a calibration
//! that matches its ground truth; `--dry-run` prints the timeline and touches nothing; a
//! stage that faults, stays silent or replies garbage stops the run naming the step and the
//! positioner, keeping every pose captured, and the same command then resumes the script
//! after the last pose captured; Ctrl-C during a move stops the run (exit 130).

#[path = "support/cli.rs"]
mod cli;

use cli::scratch;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn tiny() -> String {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/rigs/sim-tiny-turntable.toml");
    std::fs::read_to_string(path).unwrap()
}

/// `text` as `name` in `dir`.
fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

fn run(rig: &Path, out: &Path, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(["run", "--rig"])
        .arg(rig)
        .arg("--out")
        .arg(out)
        .args(extra)
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn script_json(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("script.json")).unwrap()).unwrap()
}

#[test]
fn a_scripted_rig_runs_unattended_to_its_ground_truth() {
    let dir = scratch("script-run");
    let rig = write(&dir, "rig.toml", &tiny());
    let out = dir.join("data");
    let t = Instant::now();
    let done = run(&rig, &out, &[]);
    let (stdout, stderr) = (text(&done.stdout), text(&done.stderr));
    assert!(done.status.success(), "{stdout}\n{stderr}");
    eprintln!("scripted run took {:.1} s", t.elapsed().as_secs_f64());
    // The script told the operator, moved the stage and captured each pose in turn.
    assert!(stderr.contains("Mount the board"), "{stderr}");
    assert!(stderr.contains("capturing pose 5 (held out)"), "{stderr}");
    // Every device against the truth of the simulated rig: the board was where the stage's
    // axes put it (a board elsewhere than rendered would not calibrate to the truth).
    let truth = std::fs::read_to_string(out.join("calibration/truth.txt")).unwrap();
    let rows: Vec<Vec<f64>> = truth
        .lines()
        .skip(1)
        .map(|l| {
            l.split_whitespace()
                .skip(1)
                .map(|v| v.parse().unwrap())
                .collect()
        })
        .collect();
    assert_eq!(rows.len(), 3, "{truth}");
    for r in &rows {
        // Focal error ≤ 0.1 % (run_sim.rs's bound), rotation ≤ 0.05°, position ≤ 1 mm.
        assert!(r[0] <= 0.1 && r[2] <= 0.05 && r[3] <= 1.0, "{truth}");
    }
    // script.json: one session, every step timed; the summary prints the jitter.
    let record = script_json(&out);
    let steps = record["sessions"][0]["steps"].as_array().unwrap();
    assert_eq!(record["planned"]["captures"], 6);
    assert_eq!(
        steps.len(),
        record["planned"]["steps"].as_array().unwrap().len()
    );
    assert!(steps.iter().all(|s| s["end_s"].is_number()), "{steps:?}");
    let captures = steps.iter().filter(|s| s["kind"] == "capture").count();
    assert_eq!(captures, 6);
    assert!(stdout.contains("script: 15 steps in"), "{stdout}");
    assert!(stdout.contains("start jitter mean"), "{stdout}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn dry_run_prints_the_timeline_and_touches_no_device() {
    let dir = scratch("script-dry");
    // A serial positioner on a port that does not exist: a dry run never opens it.
    let text_in = tiny().replace(
        "driver = \"sim\"\ncommand",
        "driver = \"serial\"\nport = \"/dev/ttyNOPE9\"\nmove_s = 1.5\ncommand",
    );
    let text_in = text_in.replace(
        "sim = { offset = [30.0, 20.0, 0.0], roll_deg = 10.0, speed_deg_s = 200.0 }\n",
        "",
    );
    // Without a simulated stage the simulated rig needs a board pose per capture.
    let poses = "[poses]\ncount = 6\nyaw_deg = 20.0\ntilt_deg = 10.0\nshift_mm = 0.0\n";
    let rig = write(&dir, "rig.toml", &format!("{text_in}{poses}"));
    let out = dir.join("data");
    let done = run(&rig, &out, &["--dry-run"]);
    let stdout = text(&done.stdout);
    assert!(done.status.success(), "{stdout}\n{}", text(&done.stderr));
    assert!(!out.exists(), "a dry run writes no dataset");
    // 15 steps: prompt, 5 × (move, capture), move, wait, capture, move. A capture is its
    // frames at 5 ms plus the 0.1 s pause; a move 1.5 s; the prompt its 0.2 s.
    let frames = hexcal::rig::file::RigFile::load(&rig)
        .unwrap()
        .sequence()
        .unwrap()
        .frame_count();
    let capture = frames as f64 * 0.005 + 0.1;
    assert!(stdout.contains("15 steps, 6 captures"), "{stdout}");
    let expected = 0.2 + 7.0 * 1.5 + 6.0 * capture + 0.1;
    assert!(
        stdout.contains(&format!(
            "expected {expected:.1} s ({capture:.2} s per capture)"
        )),
        "{stdout}"
    );
    let third = format!("{:.3}", 0.2 + 2.0 * (1.5 + capture));
    let lines: Vec<&str> = stdout.lines().collect();
    assert!(
        lines
            .iter()
            .any(|l| l.contains("script[1].steps[0] (round 3 of 5)")
                && l.contains("\"MOVE 25 -15\"")
                && l.trim_start().starts_with(&third)),
        "{stdout}"
    );
    assert!(
        lines
            .iter()
            .any(|l| l.contains("capture pose 5 \"held out\"")),
        "{stdout}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_faulty_stage_stops_the_run_and_the_same_command_resumes_after_the_last_pose() {
    let dir = scratch("script-fault");
    let stage = "sim = { offset = [30.0, 20.0, 0.0], roll_deg = 10.0, speed_deg_s = 200.0 }";
    let faulty = tiny().replace(
        stage,
        &stage.replace(" }", ", fault = { kind = \"error\", after_moves = 3 } }"),
    );
    let rig = write(&dir, "rig.toml", &faulty);
    let out = dir.join("data");
    let failed = run(&rig, &out, &[]);
    let stderr = text(&failed.stderr);
    assert_eq!(failed.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("script[1].steps[0] (round 4 of 5): positioner stage: fault reported")
            && stderr.contains("ERR motor stalled"),
        "{stderr}"
    );
    // Poses 0–2 were captured and finished before the fault.
    for k in 0..3 {
        assert!(
            out.join(format!("pose-{k:03}/pose.json")).exists(),
            "pose {k}"
        );
    }
    assert!(!out.join("pose-003/pose.json").exists());
    // The stage is mended: the same command resumes after pose 2.
    write(&dir, "rig.toml", &tiny());
    let resumed = run(&rig, &out, &["--json"]);
    let stdout = text(&resumed.stdout);
    assert!(
        resumed.status.success(),
        "{stdout}\n{}",
        text(&resumed.stderr)
    );
    let events: Vec<serde_json::Value> = stdout
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    let reused = events.iter().find(|e| e["event"] == "resumed").unwrap();
    assert_eq!(reused["poses"], serde_json::json!([0, 1, 2]));
    let started: Vec<u64> = events
        .iter()
        .filter(|e| e["event"] == "pose_started")
        .map(|e| e["pose"].as_u64().unwrap())
        .collect();
    assert_eq!(started, [3, 4, 5]);
    let record = script_json(&out);
    let sessions = record["sessions"].as_array().unwrap();
    assert_eq!(sessions.len(), 2);
    // The first session ends with the failed move; the second starts after pose 2's
    // capture (step 7), the stage first sent back to pose 2's angle and tilt.
    let first = sessions[0]["steps"].as_array().unwrap();
    assert!(first.last().unwrap()["outcome"]
        .as_str()
        .unwrap()
        .starts_with("failed: "));
    assert_eq!(sessions[1]["from_step"], 7);
    let second = sessions[1]["steps"].as_array().unwrap();
    assert_eq!(second[0]["kind"], "restore");
    assert!(second[0]["step"].as_str().unwrap().contains("round 3 of 5"));
    assert!(stdout.contains("\"finished\""), "{stdout}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_silent_or_garbling_stage_is_named_in_one_line() {
    let dir = scratch("script-silent");
    let stage = "sim = { offset = [30.0, 20.0, 0.0], roll_deg = 10.0, speed_deg_s = 200.0 }";
    for (kind, says) in [
        (
            "silent",
            "positioner stage: no reply to \"MOVE -25 -15\" within 0.5 s",
        ),
        ("garbage", "positioner stage: unexpected reply"),
    ] {
        let rig_text = tiny()
            .replace("timeout_s = 5.0", "timeout_s = 0.5")
            .replace(
                stage,
                &stage.replace(" }", &format!(", fault = {{ kind = \"{kind}\" }} }}")),
            );
        let rig = write(&dir, &format!("{kind}.toml"), &rig_text);
        let failed = run(&rig, &dir.join(kind), &[]);
        let stderr = text(&failed.stderr);
        assert_eq!(failed.status.code(), Some(1), "{stderr}");
        let error: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
        assert_eq!(error.len(), 1, "{stderr}");
        assert!(
            error[0].contains("script[1].steps[0] (round 1 of 5)") && error[0].contains(says),
            "{kind}: {stderr}"
        );
        assert_eq!(error[0].matches("positioner stage").count(), 1, "{stderr}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn ctrl_c_during_a_move_stops_the_run() {
    let dir = scratch("script-sigint");
    // The first move takes 25 s at 1°/s.
    let slow = tiny()
        .replace("speed_deg_s = 200.0", "speed_deg_s = 1.0")
        .replace("timeout_s = 5.0", "timeout_s = 60.0");
    let rig = write(&dir, "rig.toml", &slow);
    let out = dir.join("data");
    let mut child = Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(["run", "--rig"])
        .arg(&rig)
        .arg("--out")
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Wait until the move is under way (its record is written when it starts).
    let deadline = Instant::now() + Duration::from_secs(120);
    while !std::fs::read_to_string(out.join("script.json")).is_ok_and(|t| t.contains("\"move\"")) {
        assert!(Instant::now() < deadline, "the move never started");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(300));
    let sent = Instant::now();
    Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    let status = child.wait().unwrap();
    let mut stderr = String::new();
    use std::io::Read;
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut stderr)
        .unwrap();
    assert_eq!(status.code(), Some(130), "{stderr}");
    assert!(
        sent.elapsed() < Duration::from_secs(10),
        "the move was not cut short"
    );
    assert!(
        stderr.contains("interrupted") && stderr.contains("pose 0"),
        "{stderr}"
    );
    let record = script_json(&out);
    let steps = record["sessions"][0]["steps"].as_array().unwrap();
    assert_eq!(steps.last().unwrap()["outcome"], "interrupted");
    let _ = std::fs::remove_dir_all(&dir);
}
