//! The script executor on its own (no capture): steps in order with their times, the
//! simulated stage holding the board, faults of a serial positioner through a real pty,
//! Ctrl-C in a move and a wait, prompts, and a resumed script.

use super::*;
use crate::rig::fixture::{SimDevice, SimRig};
use crate::rig::positioner::board_on_stage;
use hexcal_simulator::stage::Axes;
use serialport::SerialPort;
use std::io::{BufRead, BufReader, Write};

/// A one-camera simulated rig with a stage (and a serial positioner on `port`) and `script`.
fn rig(port: &str, script: &str) -> RigFile {
    let positioners = format!(
        r#"[[positioner]]
name = "stage"
driver = "sim"
command = "MOVE {{angle}} {{tilt}}"
sim = {{ speed_deg_s = 400.0, roll_deg = 12.0, centre = [5.0, -3.0, 20.0] }}
[[positioner]]
name = "arm"
driver = "serial"
port = "{port}"
command = "GO {{p}}"
reply = "^DONE"
stop = "HALT"
timeout_s = 0.6
{script}"#
    );
    let camera = SimDevice::new("cam0", (320, 240), [400.0, 400.0, 160.0, 120.0])
        .at([0.0, 0.0, 1200.0])
        .with("exposure_ms = 5.0");
    let projector = SimDevice::new("proj0", (400, 300), [450.0, 450.0, 200.0, 280.0])
        .at([300.0, 100.0, 1200.0]);
    let text = SimRig::new("scripted")
        .table("[timing]\nframe_period_ms = 10.0")
        .table("[poses]\ncount = 8\nyaw_deg = 10.0\ntilt_deg = 10.0\nshift_mm = 0.0")
        .camera(camera)
        .projector(projector)
        .then(&positioners)
        .toml();
    RigFile::parse(&text, "rig.toml").unwrap_or_else(|e| panic!("{e}"))
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hexcal-script-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A device on the master end of a pty pair: answers each command line with `reply(line)`
/// (none: silence) and reports every line it got. Gives the slave's path and the lines.
fn device(
    reply: impl Fn(&str) -> Option<String> + Send + 'static,
) -> (
    String,
    crossbeam_channel::Receiver<String>,
    serialport::TTYPort,
) {
    let (master, slave) = serialport::TTYPort::pair().unwrap();
    let path = slave.name().unwrap();
    let (tx, rx) = crossbeam_channel::unbounded();
    let mut writer = master.try_clone_native().unwrap();
    let mut reader = BufReader::new(master);
    reader
        .get_mut()
        .set_timeout(Duration::from_secs(30))
        .unwrap();
    std::thread::spawn(move || loop {
        let mut line = String::new();
        match reader.read_line(&mut line) {
            Ok(n) if n > 0 => {
                let line = line.trim().to_string();
                if let Some(r) = reply(&line) {
                    let _ = writer.write_all(format!("{r}\r\n").as_bytes());
                }
                if tx.send(line).is_err() {
                    return;
                }
            }
            _ => return,
        }
    });
    // The slave end stays open so the pty lives while the positioner opens it by name.
    (path, rx, slave)
}

fn executor<'a>(
    rig: RigFile,
    out: &Path,
    operator: Receiver<bool>,
    stop: Option<Arc<AtomicBool>>,
    say: &'a mut dyn FnMut(&str),
) -> ScriptRun<'a> {
    let plan = plan_of(&rig).unwrap().unwrap();
    ScriptRun::new(rig, plan, out, operator, stop, say)
}

fn captured(s: &mut ScriptRun, pose: usize) {
    s.event(&Event::PoseCaptured {
        pose,
        seconds: 0.0,
        frames_per_second: 0.0,
    });
}

#[test]
fn steps_run_in_order_and_the_stage_holds_the_simulated_board() {
    let (port, _lines, _keep) = device(|_| Some("DONE".into()));
    let script = r#"[[script]]
move = "stage"
to = { angle = 30, tilt = -10 }
[[script]]
wait = 0.2
[[script]]
capture = "first"
[[script]]
every = 0.3
count = 2
countdown_s = 0.1
[[script]]
move = "arm"
to = { p = 1 }
"#;
    let rig = rig(&port, script);
    let world = SimWorld::new(&rig, rig.board().unwrap()).unwrap();
    let dir = scratch("order");
    let mut said = Vec::new();
    let mut say = |l: &str| said.push(l.to_string());
    let mut s = executor(
        rig.clone(),
        &dir,
        crossbeam_channel::never(),
        None,
        &mut say,
    );
    assert!(s.place(0, Some(&world)).unwrap());
    // The stage's axes place the board.
    let stage = rig.positioners[0].sim.unwrap();
    let held = board_on_stage(
        &stage,
        Axes {
            angle_deg: 30.0,
            tilt_deg: -10.0,
        },
    );
    let board = world.board_at(0).unwrap();
    assert!((board.translation.vector - held.translation.vector).norm() < 1e-9);
    assert!(board.rotation.angle_to(&held.rotation) < 1e-9);
    captured(&mut s, 0);
    assert!(s.place(1, Some(&world)).unwrap());
    captured(&mut s, 1);
    assert!(s.place(2, Some(&world)).unwrap());
    captured(&mut s, 2);
    let records = s.records().to_vec();
    let kinds: Vec<&str> = records.iter().map(|r| r.kind.as_str()).collect();
    assert_eq!(
        kinds,
        ["move", "wait", "capture", "capture", "capture", "move"]
    );
    assert!(records.iter().all(|r| r.end_s.is_some()), "{records:?}");
    // The wait lasted its time; the capture after it was due at its planned end.
    let wait = &records[1];
    assert!(wait.end_s.unwrap() - wait.start_s >= 0.2, "{wait:?}");
    assert!((records[2].due_s - (wait.start_s + 0.2)).abs() < 1e-9);
    // The timed captures: the first after its countdown, the second one period later.
    assert!(records[3].due_s >= records[2].end_s.unwrap() + 0.1 - 1e-9);
    assert!((records[4].due_s - records[3].due_s - 0.3).abs() < 1e-9);
    for r in &records[3..5] {
        assert!(r.start_s >= r.due_s, "{r:?}");
    }
    let j = s.finish().unwrap().unwrap();
    assert!(
        said.iter().any(|l| l.contains("capture in 1 s")),
        "{said:?}"
    );
    assert_eq!(j.steps, 6);
    assert!(j.max_s >= j.rms_s && j.rms_s >= 0.0);
    // script.json: the plan and the session, as written.
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("script.json")).unwrap()).unwrap();
    assert_eq!(file["format"], SCRIPT_FORMAT);
    assert_eq!(file["planned"]["captures"], 3);
    assert_eq!(file["sessions"][0]["steps"].as_array().unwrap().len(), 6);
    assert_eq!(file["sessions"][0]["steps"][2]["pose"], 0);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Run a one-move script against a device answering `reply`; the error.
fn fault(reply: impl Fn(&str) -> Option<String> + Send + 'static) -> String {
    let (port, _lines, _keep) = device(reply);
    let rig = rig(
        &port,
        "[[script]]\nmove = \"arm\"\nto = { p = 3 }\n[[script]]\ncapture = \"x\"\n",
    );
    let dir = scratch("fault");
    let mut say = |_: &str| {};
    let mut s = executor(rig, &dir, crossbeam_channel::never(), None, &mut say);
    let err = s
        .place(0, None)
        .expect_err("the move must fail")
        .to_string();
    // The failed step is on record.
    let text = std::fs::read_to_string(dir.join("script.json")).unwrap();
    assert!(text.contains("failed: "), "{text}");
    let _ = std::fs::remove_dir_all(&dir);
    err
}

#[test]
fn positioner_faults_through_a_pty_name_the_positioner_and_step() {
    let silent = fault(|_| None);
    assert!(
        silent.contains("script[0]") && silent.contains("positioner arm: no reply to \"GO 3\""),
        "{silent}"
    );
    let garbage = fault(|_| Some("\u{1}%%#garbled".into()));
    assert!(
        garbage.contains("script[0]") && garbage.contains("arm: unexpected reply"),
        "{garbage}"
    );
    let faulted = fault(|_| Some("ERR overcurrent on axis 2".into()));
    assert!(
        faulted.contains("script[0]")
            && faulted.contains("arm: fault reported")
            && faulted.contains("overcurrent"),
        "{faulted}"
    );
    // Too slow: the reply comes after the timeout (0.6 s).
    let slow = fault(|_| {
        std::thread::sleep(Duration::from_millis(900));
        Some("DONE".into())
    });
    assert!(
        slow.contains("no reply") && slow.contains("0.6 s"),
        "{slow}"
    );
}

#[test]
fn ctrl_c_in_a_move_sends_the_stop_command_and_stops() {
    let (port, lines, _keep) = device(|_| None);
    let rig = rig(
        &port,
        "[[script]]\nmove = \"arm\"\nto = { p = 3 }\ntimeout_s = 30\n[[script]]\ncapture = \"x\"\n",
    );
    let dir = scratch("stop-move");
    let stop = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&stop);
    std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(200));
        flag.store(true, Ordering::SeqCst);
    });
    let mut say = |_: &str| {};
    let t = Instant::now();
    let mut s = executor(rig, &dir, crossbeam_channel::never(), Some(stop), &mut say);
    assert!(!s.place(0, None).unwrap(), "stopped, not placed");
    assert!(t.elapsed() < Duration::from_secs(5));
    assert_eq!(s.records()[0].outcome, "interrupted");
    let got: Vec<String> = (0..2)
        .map(|_| lines.recv_timeout(Duration::from_secs(3)).unwrap())
        .collect();
    assert_eq!(got, ["GO 3", "HALT"]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn ctrl_c_in_a_wait_stops_it() {
    let (port, _lines, _keep) = device(|_| None);
    let rig = rig(
        &port,
        "[[script]]\nwait = 60\n[[script]]\ncapture = \"x\"\n",
    );
    let dir = scratch("stop-wait");
    let stop = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&stop);
    std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(150));
        flag.store(true, Ordering::SeqCst);
    });
    let mut say = |_: &str| {};
    let t = Instant::now();
    let mut s = executor(rig, &dir, crossbeam_channel::never(), Some(stop), &mut say);
    assert!(!s.place(0, None).unwrap());
    assert!(t.elapsed() < Duration::from_secs(5));
    assert_eq!(s.records()[0].outcome, "interrupted");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn prompts_wait_for_enter_or_their_timeout() {
    let (port, _lines, _keep) = device(|_| None);
    let script = "[[script]]\nprompt = \"turn the board\"\n[[script]]\ncapture = \"x\"\n\
                  [[script]]\nprompt = \"again\"\ntimeout_s = 0.2\n[[script]]\ncapture = \"y\"\n\
                  [[script]]\nprompt = \"last\"\n[[script]]\ncapture = \"z\"\n";
    let rig = rig(&port, script);
    let dir = scratch("prompt");
    let (enter, operator) = crossbeam_channel::unbounded();
    enter.send(true).unwrap();
    let mut said = Vec::new();
    let mut say = |l: &str| said.push(l.to_string());
    let mut s = executor(rig, &dir, operator, None, &mut say);
    assert!(s.place(0, None).unwrap());
    captured(&mut s, 0);
    assert!(s.place(1, None).unwrap());
    captured(&mut s, 1);
    let outcomes: Vec<String> = s.records().iter().map(|r| r.outcome.clone()).collect();
    assert_eq!(outcomes, ["done", "done", "timed out", "done"]);
    // The input ends: a prompt without timeout cannot be answered.
    drop(enter);
    let err = s.place(2, None).expect_err("nobody to answer").to_string();
    assert!(
        err.contains("script[4]") && err.contains("input ended"),
        "{err}"
    );
    drop(s);
    assert!(
        said.iter().any(|l| l.starts_with("turn the board")),
        "{said:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_resumed_script_restores_the_positioners_and_goes_on_after_the_last_pose() {
    let (port, lines, _keep) = device(|_| Some("DONE".into()));
    let script = r#"[[script]]
repeat = 4
vars = { p = { from = 10, step = 1 } }
[[script.steps]]
move = "arm"
to = { p = "{p}" }
[[script.steps]]
capture = "{p}"
"#;
    let rig = rig(&port, script);
    let dir = scratch("resume");
    let mut say = |_: &str| {};
    // Poses 0 and 1 were captured by an earlier run: the script goes on at pose 2.
    let mut s = executor(rig, &dir, crossbeam_channel::never(), None, &mut say);
    assert!(s.place(2, None).unwrap());
    let kinds: Vec<(String, String)> = s
        .records()
        .iter()
        .map(|r| (r.kind.clone(), r.step.clone()))
        .collect();
    assert_eq!(kinds[0].0, "restore");
    assert!(kinds[0].1.contains("round 2 of 4"), "{kinds:?}");
    assert_eq!(kinds[1].0, "move");
    assert_eq!(kinds[2].0, "capture");
    let sent: Vec<String> = (0..2)
        .map(|_| lines.recv_timeout(Duration::from_secs(3)).unwrap())
        .collect();
    assert_eq!(sent, ["GO 11", "GO 12"]);
    assert!(lines.try_recv().is_err(), "GO 10 was never sent");
    // The session starts at the step after pose 1's capture.
    assert_eq!(s.session.from_step, 4);
    drop(s);
    let _ = std::fs::remove_dir_all(&dir);
}
