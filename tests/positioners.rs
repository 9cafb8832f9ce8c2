//! Positioners as labs have them (issue 34): the rig-file templates for a GRBL-style and a
//! Zaber-style controller, each driven through `hexcal positioner` against a fake that
//! speaks its protocol on a pty pair (`serialport::TTYPort::pair()`; the binary opens the
//! slave end by its /dev/pts path as it would a USB adapter): a move acknowledged at once
//! and polled until idle, a fault the device reports, and a device that never gets idle
//! (the timeout).

#[path = "support/cli.rs"]
mod cli;

use cli::scratch;
use serialport::{SerialPort, TTYPort};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// What a fake answers to one line: the lines to send back.
type Answer = Box<dyn FnMut(&str) -> Vec<String> + Send>;

/// A fake device on the master end of a pty pair answering each line with `answer`; gives
/// the slave's path (kept open) and a flag that ends the fake.
fn fake(mut answer: Answer) -> (String, TTYPort, Arc<AtomicBool>) {
    let (mut master, slave) = TTYPort::pair().expect("a pty pair");
    master.set_timeout(Duration::from_millis(20)).unwrap();
    let path = slave.name().expect("the slave's path");
    let done = Arc::new(AtomicBool::new(false));
    let end = Arc::clone(&done);
    std::thread::spawn(move || {
        let mut pending = Vec::new();
        let mut buf = [0u8; 256];
        while !end.load(Ordering::SeqCst) {
            if let Ok(n) = master.read(&mut buf) {
                pending.extend_from_slice(&buf[..n]);
            }
            while let Some(i) = pending.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = pending.drain(..=i).collect();
                let line = String::from_utf8_lossy(&line).trim().to_string();
                for reply in answer(&line) {
                    let _ = master.write_all(format!("{reply}\r\n").as_bytes());
                }
            }
        }
    });
    (path, slave, done)
}

/// The template `rigs/NAME` with the positioner on `port` and moves timing out after
/// `timeout_s`, written into `dir`.
fn template(dir: &Path, name: &str, port: &str, timeout_s: f64) -> PathBuf {
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("rigs")
            .join(name),
    )
    .unwrap()
    .replacen("port = \"/dev/ttyUSB0\"", &format!("port = {port:?}"), 1)
    .replacen("timeout_s = 30.0", &format!("timeout_s = {timeout_s}"), 1);
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

/// `hexcal positioner --rig RIG table COMMAND`: exit status, stdout, stderr.
fn exchange(rig: &Path, command: &str) -> (Option<i32>, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_hexcal"))
        .args(["positioner", "--rig"])
        .arg(rig)
        .args(["table", command])
        .output()
        .unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// A GRBL-style controller: "ok" for a motion command in range, "error:15" (travel
/// exceeded) beyond ±180; status "<Run|…>" for `busy` queries after a move, then
/// "<Idle|…>"; `stuck`: always running.
fn grbl(busy: usize, stuck: bool) -> Answer {
    let mut left: usize = 0;
    Box::new(move |line| {
        if line == "?" {
            return match left {
                0 if !stuck => vec!["<Idle|MPos:0.000,0.000,0.000|FS:0,0>".into()],
                _ => {
                    left = left.saturating_sub(1);
                    vec!["<Run|MPos:1.000,0.000,0.000|FS:500,0>".into()]
                }
            };
        }
        let x: f64 = line
            .split_whitespace()
            .find_map(|w| w.strip_prefix('X'))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0.0);
        if x.abs() > 180.0 {
            return vec!["error:15".into()];
        }
        left = busy;
        vec!["ok".into()]
    })
}

/// A Zaber-style device 1: every command answered at once, "RJ" for a position beyond
/// ±3 600 000 microsteps; status "BUSY" for `busy` polls after a move, then "IDLE".
fn zaber(busy: usize, stuck: bool) -> Answer {
    let mut left: usize = 0;
    Box::new(move |line| {
        if line == "/1" {
            let state = if left > 0 || stuck { "BUSY" } else { "IDLE" };
            left = left.saturating_sub(1);
            return vec![format!("@01 0 OK {state} -- 0")];
        }
        let steps: f64 = line
            .rsplit(' ')
            .next()
            .and_then(|v| v.parse().ok())
            .unwrap_or(0.0);
        if steps.abs() > 3_600_000.0 {
            return vec!["@01 0 RJ IDLE BADDATA 0".into()];
        }
        left = busy;
        vec!["@01 0 OK BUSY WR 0".into()]
    })
}

#[test]
fn a_grbl_style_controller_is_acknowledged_polled_faulted_and_timed_out() {
    let dir = scratch("positioner-grbl");
    let (port, _slave, done) = fake(grbl(3, false));
    let rig = template(&dir, "grbl-positioner-example.toml", &port, 5.0);
    let (code, out, err) = exchange(&rig, "G0 X30 Y-20");
    assert_eq!(code, Some(0), "{out}{err}");
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines[0], "> G0 X30 Y-20", "{out}");
    assert_eq!(lines[1], "< ok", "{out}");
    assert_eq!(
        lines.iter().filter(|l| l.starts_with("< <Run|")).count(),
        3,
        "{out}"
    );
    assert!(
        out.ends_with("done: <Idle|MPos:0.000,0.000,0.000|FS:0,0>\n"),
        "{out}"
    );

    let (code, out, err) = exchange(&rig, "G0 X400 Y0");
    assert_eq!(code, Some(1), "{out}{err}");
    assert!(
        err.contains("fault reported to \"G0 X400 Y0\": \"error:15\""),
        "{err}"
    );
    done.store(true, Ordering::SeqCst);

    // A controller that echoes every line: the echoes are skipped.
    let mut inner = grbl(1, false);
    let (port, _slave, done) = fake(Box::new(move |line| {
        let mut all = vec![line.to_string()];
        all.extend(inner(line));
        all
    }));
    let rig = template(&dir, "grbl-positioner-example.toml", &port, 5.0);
    let text = std::fs::read_to_string(&rig).unwrap();
    std::fs::write(&rig, text.replacen("ack = ", "echo = true\nack = ", 1)).unwrap();
    let (code, out, err) = exchange(&rig, "G0 X5 Y5");
    assert_eq!(code, Some(0), "{out}{err}");
    assert!(out.starts_with("> G0 X5 Y5\n< G0 X5 Y5\n< ok\n"), "{out}");
    done.store(true, Ordering::SeqCst);

    let (port, _slave, done) = fake(grbl(0, true));
    let rig = template(&dir, "grbl-positioner-example.toml", &port, 0.5);
    let (code, out, err) = exchange(&rig, "G0 X10 Y0");
    assert_eq!(code, Some(1), "{out}{err}");
    assert!(
        err.contains("no reply to \"G0 X10 Y0\" within 0.5 s"),
        "{err}"
    );
    assert!(out.contains("< <Run|"), "polled while it ran: {out}");
    done.store(true, Ordering::SeqCst);
}

#[test]
fn a_zaber_style_device_is_acknowledged_polled_faulted_and_timed_out() {
    let dir = scratch("positioner-zaber");
    let (port, _slave, done) = fake(zaber(2, false));
    let rig = template(&dir, "zaber-positioner-example.toml", &port, 5.0);
    let (code, out, err) = exchange(&rig, "/1 move abs 350000");
    assert_eq!(code, Some(0), "{out}{err}");
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(
        &lines[..4],
        [
            "> /1 move abs 350000",
            "< @01 0 OK BUSY WR 0",
            "> /1",
            "< @01 0 OK BUSY -- 0"
        ],
        "{out}"
    );
    assert!(out.ends_with("done: @01 0 OK IDLE -- 0\n"), "{out}");

    let (code, _, err) = exchange(&rig, "/1 move abs 99999999");
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("\"@01 0 RJ IDLE BADDATA 0\""), "{err}");
    done.store(true, Ordering::SeqCst);

    let (port, _slave, done) = fake(zaber(0, true));
    let rig = template(&dir, "zaber-positioner-example.toml", &port, 0.5);
    let (code, _, err) = exchange(&rig, "/1 move abs 10");
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("within 0.5 s"), "{err}");
    done.store(true, Ordering::SeqCst);
}

/// The templates' scripts fill their commands as the devices take them: the Zaber stage's
/// degrees turned into microsteps by `steps_per_unit`.
#[test]
fn the_templates_plan_their_moves_in_the_devices_units() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("rigs");
    let run = |name: &str| {
        let out = Command::new(env!("CARGO_BIN_EXE_hexcal"))
            .args(["run", "--dry-run", "--rig"])
            .arg(root.join(name))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    let zaber = run("zaber-positioner-example.toml");
    assert!(
        zaber.contains("move table: \"/1 move abs -350000\""),
        "{zaber}"
    );
    let grbl = run("grbl-positioner-example.toml");
    assert!(grbl.contains("move table: \"G0 X-30 Y-20\""), "{grbl}");
}
