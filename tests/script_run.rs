//! Capture scripts through the binary (issue 18): a tiny simulated rig whose board sits on
//! the simulated stage (a firmware model on a real pty) runs unattended to a calibration
//! that matches its ground truth; `--dry-run` prints the timeline and touches nothing; a
//! stage that faults, stays silent or replies garbage stops the run naming the step and the
//! positioner, keeping every pose captured, and the same command then resumes the script
//! after the last pose captured; Ctrl-C during a move stops the run (exit 130); the
//! operator console shows a prompt and its button answers it.

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
        .take_while(|l| !l.starts_with("image:"))
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

/// Mean grey level of one stored frame.
fn mean_level(frame: &Path) -> f64 {
    let img = image::open(frame).unwrap().to_luma8();
    img.pixels().map(|p| f64::from(p.0[0])).sum::<f64>() / f64::from(img.width() * img.height())
}

#[test]
fn capture_runs_the_script_and_a_step_sets_its_own_exposure() {
    let dir = scratch("script-capture");
    // The held-out capture (pose 5) at 2 ms instead of cam0's own 4 ms, then pose 6 with
    // the board where it was: cam0's frames half as bright, cam1's alike.
    let text_in = tiny().replace(
        "capture = \"held out\"\n",
        "capture = \"held out\"\nexposure_us = 2000\ncameras = [\"cam0\"]\n\
         [[script]]\ncapture = \"again\"\n",
    );
    let rig = write(&dir, "rig.toml", &text_in);
    let dry = run(&rig, &dir.join("none"), &["--dry-run"]);
    let stdout = text(&dry.stdout);
    assert!(dry.status.success(), "{stdout}");
    assert!(
        stdout.contains("capture pose 5 \"held out\", exposure 2000 µs (cam0)"),
        "{stdout}"
    );
    let out = dir.join("data");
    let done = Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(["capture", "--rig"])
        .arg(&rig)
        .arg("--out")
        .arg(&out)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let (stdout, stderr) = (text(&done.stdout), text(&done.stderr));
    assert!(done.status.success(), "{stdout}\n{stderr}");
    // The script ran: it prompted, moved the stage, captured all seven poses and timed
    // every step into script.json.
    assert!(stderr.contains("Mount the board"), "{stderr}");
    assert!(stdout.contains("captured 7 poses"), "{stdout}");
    assert!(stdout.contains("jitter"), "{stdout}");
    let record = script_json(&out);
    let steps = record["sessions"][0]["steps"].as_array().unwrap();
    // Prompt (its timeout passes with no operator), 5 × (move, capture), move, wait, two
    // captures, move.
    assert_eq!(steps.len(), 16, "{record}");
    assert!(
        steps[1..].iter().all(|s| s["outcome"] == "done"),
        "{record}"
    );
    let exposure = |pose: usize, cam: &str| {
        let path = out.join(format!("pose-{pose:03}/{cam}/stack.json"));
        let stack: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        stack["frames"][0]["exposure_us"].as_f64().unwrap()
    };
    assert_eq!(exposure(5, "cam0"), 2000.0);
    assert_eq!(exposure(5, "cam1"), 4000.0);
    // Restored after.
    assert_eq!(exposure(6, "cam0"), 4000.0);
    for (cam, ratio) in [("cam0", 0.5), ("cam1", 1.0)] {
        // Mean level over a few frames. Halving an integer level rounds half of them up by
        // 0.5 DN, so the halved mean lies within 0.5 DN of half the other; the shot and
        // read noise of a mean over 4 × 400 000 pixels moves it by ≈ 0.01 DN.
        let mean = |pose: usize| {
            (0..4)
                .map(|k| mean_level(&out.join(format!("pose-{pose:03}/{cam}/frame-{k:03}.png"))))
                .sum::<f64>()
                / 4.0
        };
        let (dim, own) = (mean(5), mean(6));
        eprintln!("{cam}: pose 5 {dim:.3} DN, pose 6 {own:.3} DN (expected ×{ratio})");
        assert!((dim - ratio * own).abs() <= 0.5, "{cam}: {dim} vs {own}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_serial_positioner_on_a_pty_moves_and_its_fault_stops_the_capture() {
    use serialport::SerialPort;
    use std::io::{BufRead, BufReader, Write};
    // A robot arm on the far end of a pty pair: "GO n" lines ending CR LF, "DONE" after
    // each of the first two moves, then a fault.
    let (mut master, slave) = serialport::TTYPort::pair().unwrap();
    master.set_timeout(Duration::from_millis(50)).unwrap();
    // hexcal opens the slave end itself (exclusively): this end is closed, and the master's
    // reads fail until hexcal has it open.
    let port = slave.name().unwrap();
    drop(slave);
    let arm = std::thread::spawn(move || {
        let mut heard = Vec::new();
        let mut reader = BufReader::new(master.try_clone_native().unwrap());
        let mut line = String::new();
        let deadline = Instant::now() + Duration::from_secs(120);
        while heard.len() < 3 && Instant::now() < deadline {
            if !reader.read_line(&mut line).is_ok_and(|n| n > 0) || !line.ends_with('\n') {
                std::thread::sleep(Duration::from_millis(10));
                continue;
            }
            heard.push(line.clone());
            let reply = match heard.len() {
                3 => "FAULT gripper open\r\n",
                _ => "DONE\r\n",
            };
            master.write_all(reply.as_bytes()).unwrap();
            line.clear();
        }
        heard
    });
    let dir = scratch("script-serial");
    let head = tiny();
    let devices = &head[head.find("[[camera]]").unwrap()..];
    let rig_text = format!(
        "name = \"serial-arm\"\n[timing]\nframe_period_ms = 5.0\npose_pause_s = 0.1\n\
         [poses]\ncount = 3\nyaw_deg = 20.0\ntilt_deg = 10.0\nshift_mm = 0.0\n\
         [[positioner]]\nname = \"arm\"\ndriver = \"serial\"\nport = \"{port}\"\n\
         line_ending = \"crlf\"\ncommand = \"GO {{preset}}\"\nreply = \"^DONE\"\n\
         fault = \"^FAULT\"\ntimeout_s = 5.0\nmove_s = 0.5\n\
         [[script]]\nrepeat = 3\nvars = {{ p = {{ from = 0, step = 1 }} }}\n\
         steps = [{{ move = \"arm\", to = {{ preset = \"{{p}}\" }} }}, {{ capture = \"preset {{p}}\" }}]\n\
         {devices}"
    );
    let rig = write(&dir, "rig.toml", &rig_text);
    let out = dir.join("data");
    let failed = Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(["capture", "--rig"])
        .arg(&rig)
        .arg("--out")
        .arg(&out)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let stderr = text(&failed.stderr);
    assert_eq!(failed.status.code(), Some(1), "{stderr}");
    let error: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(error.len(), 1, "{stderr}");
    assert!(
        error[0].contains("script[0].steps[0] (round 3 of 3): positioner arm: fault reported")
            && error[0].contains("\"FAULT gripper open\""),
        "{stderr}"
    );
    assert_eq!(
        arm.join().unwrap(),
        ["GO 0\r\n", "GO 1\r\n", "GO 2\r\n"],
        "the arm heard its commands, CR LF ended"
    );
    // The two poses captured before the fault are complete.
    for k in 0..2 {
        assert!(
            out.join(format!("pose-{k:03}/pose.json")).exists(),
            "pose {k}"
        );
    }
    assert!(!out.join("pose-002/pose.json").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// One HTTP request to the console at `addr`: the status line and the body.
fn http(addr: &str, request: &str) -> (String, String) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "{request} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut all = Vec::new();
    let _ = s.read_to_end(&mut all);
    let all = text(&all);
    let (head, body) = all.split_once("\r\n\r\n").unwrap_or((&all, ""));
    (
        head.lines().next().unwrap_or("").to_string(),
        body.to_string(),
    )
}

#[test]
fn the_console_shows_a_prompt_and_its_button_answers_it() {
    use std::io::{BufRead, BufReader};
    let dir = scratch("script-console-prompt");
    // The prompt waits for the operator (no timeout) and stdin is closed: only the
    // console's button can answer it (without it the run stops: "the input ended").
    let prompt = "prompt = \"Mount the board\"\n";
    let rig_text = tiny().replace(&format!("{prompt}timeout_s = 0.2\n"), prompt);
    assert!(
        rig_text.contains(&format!("{prompt}[[script]]")),
        "{rig_text}"
    );
    let rig = write(&dir, "prompt.toml", &rig_text);
    let out = dir.join("out");
    let mut child = Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(["run", "--console", "127.0.0.1:0", "--rig"])
        .arg(&rig)
        .arg("--out")
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    let (addr, token) = loop {
        let line = lines.next().expect("the console's address").unwrap();
        if let Some(url) = line.strip_prefix("console: http://") {
            let url = url.split(' ').next().unwrap();
            let (addr, token) = url.split_once("/?token=").expect("the access token");
            break (addr.to_string(), token.to_string());
        }
    };
    let rest = std::thread::spawn(move || lines.map_while(Result::ok).collect::<Vec<_>>());
    // The page's state shows the prompt while the script waits for it.
    let t = Instant::now();
    loop {
        let (_, body) = http(&addr, &format!("GET /state?token={token}"));
        if body.contains("\"prompt\":\"Mount the board\"") {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "no prompt: {body}");
        std::thread::sleep(Duration::from_millis(100));
    }
    // Without the token the button is refused; with it, taken.
    let (status, _) = http(&addr, "POST /capture");
    assert!(status.contains(" 403 "), "{status}");
    let (status, body) = http(&addr, &format!("POST /capture?token={token}"));
    assert!(status.contains(" 200 "), "{status}: {body}");
    let status = child.wait().unwrap();
    let stderr = rest.join().unwrap().join("\n");
    assert!(status.success(), "{stderr}");
    let record = script_json(&out);
    let prompt = &record["sessions"][0]["steps"][0];
    assert_eq!(prompt["kind"], "prompt", "{prompt}");
    assert_eq!(prompt["outcome"], "done", "{prompt}");
    let _ = std::fs::remove_dir_all(&dir);
}
