use super::*;
use crate::rig::file::RigError;
use crate::rig::fixture::{SimDevice, SimRig};

/// A small simulated rig (one camera) with a stage, a serial positioner and `script`.
fn rig_text(script: &str) -> String {
    let camera = SimDevice::new("cam0", (640, 480), [800.0, 800.0, 320.0, 240.0])
        .at([0.0, 0.0, 1200.0])
        .with("exposure_ms = 5.0");
    let projector = SimDevice::new("proj0", (800, 600), [900.0, 900.0, 400.0, 560.0])
        .at([300.0, 100.0, 1200.0]);
    SimRig::new("scripted")
        .table("[timing]\nframe_period_ms = 10.0\npose_pause_s = 0.5")
        .camera(camera)
        .projector(projector)
        .then(POSITIONERS)
        .then(script)
        .toml()
}

/// The rig's positioners: a simulated stage and a serial arm.
const POSITIONERS: &str = r#"[[positioner]]
name = "stage"
driver = "sim"
command = "MOVE {angle} {tilt}"
sim.speed_deg_s = 10.0
[[positioner]]
name = "arm"
driver = "serial"
port = "/dev/ttyUSB0"
line_ending = "crlf"
command = "GO {preset}"
reply = "^DONE"
move_s = 2.0
"#;

/// The refusal of `script`, which must name `line` (1-based, counted in the script text)
/// and a key starting with `field`.
fn refused(script: &str, line_in_script: usize, field: &str) -> RigError {
    let text = rig_text(script);
    let offset = text.find(script).unwrap();
    let line = text[..offset].matches('\n').count() + line_in_script;
    let err = RigFile::parse(&text, "rig.toml").expect_err("must be refused");
    assert_eq!(err.line(), Some(line), "{err}");
    assert!(
        err.field().is_some_and(|f| f.starts_with(field)),
        "{err} (expected {field})"
    );
    assert!(
        err.to_string()
            .starts_with(&format!("rig.toml:{line}: {field}")),
        "{err}"
    );
    err
}

const TURNTABLE: &str = r#"[[script]]
prompt = "Mount the board"
timeout_s = 5
[[script]]
repeat = 3
vars = { angle = { from = -30, step = 30 }, tilt = { values = [20, -20] } }
[[script.steps]]
move = "stage"
to = { angle = "{angle}", tilt = "{tilt}" }
[[script.steps]]
wait = 0.25
[[script.steps]]
capture = "angle {angle}, tilt {tilt}"
[[script]]
move = "arm"
to = { preset = "home" }
timeout_s = 9
[[script]]
every = 4.0
count = 2
countdown_s = 2
label = "hand {i}"
"#;

#[test]
fn a_script_unrolls_with_its_variables_and_planned_times() {
    let rig = RigFile::parse(&rig_text(TURNTABLE), "rig.toml").unwrap();
    // Capture time 1.5 s: the plan adds it per capture.
    let plan = rig.script_plan(1.5).unwrap().unwrap();
    assert_eq!(plan.captures, 5);
    let kinds: Vec<String> = plan
        .steps
        .iter()
        .map(|s| match &s.action {
            Action::Capture { pose, label, .. } => format!("c{pose}:{label}"),
            Action::Wait { seconds } => format!("w{seconds}"),
            Action::Prompt { .. } => "p".into(),
            Action::Move { command, .. } => format!("m:{command}"),
        })
        .collect();
    assert_eq!(
        kinds,
        [
            "p",
            "m:MOVE -30 20",
            "w0.25",
            "c0:angle -30, tilt 20",
            "m:MOVE 0 -20",
            "w0.25",
            "c1:angle 0, tilt -20",
            "m:MOVE 30 20",
            "w0.25",
            "c2:angle 30, tilt 20",
            "m:GO home",
            "c3:hand 0",
            "c4:hand 1",
        ]
    );
    // Planned: prompt 5 s (its timeout); stage moves at 10°/s: 30° (3 s), 40° (4 s), 40°.
    let planned: Vec<f64> = plan.steps.iter().map(|s| s.planned_s).collect();
    let expect = [
        5.0, 3.0, 0.25, 1.5, 4.0, 0.25, 1.5, 4.0, 0.25, 1.5, 2.0, 4.0, 4.0,
    ];
    for (i, (p, e)) in planned.iter().zip(expect).enumerate() {
        assert!((p - e).abs() < 1e-12, "step {i}: {p} s, expected {e}");
    }
    let mut clock = 0.0;
    for s in &plan.steps {
        assert!((s.planned_start_s - clock).abs() < 1e-9, "{}", s.step);
        clock += s.planned_s;
    }
    assert!((plan.duration_s - clock).abs() < 1e-9);
    assert_eq!(plan.steps[4].step, "script[1].steps[0] (round 2 of 3)");
    let Action::Move {
        timeout_s, expect, ..
    } = &plan.steps[10].action
    else {
        panic!("a move")
    };
    assert_eq!((*timeout_s, expect.as_str()), (9.0, "^DONE"));
}

#[test]
fn a_rig_without_script_has_no_plan() {
    let text = rig_text("[poses]\ncount = 2\nyaw_deg = 0.0\ntilt_deg = 0.0\nshift_mm = 0.0\n");
    let rig = RigFile::parse(&text, "rig.toml").unwrap();
    assert!(rig.script_plan(1.0).unwrap().is_none());
}

#[test]
fn step_errors_name_the_key_and_line() {
    // No kind, two kinds, a key of another kind.
    refused("[[script]]\ntimeout_s = 3\n", 1, "script[0]");
    let err = refused("[[script]]\nwait = 1\ncapture = \"x\"\n", 1, "script[0]");
    assert!(err.to_string().contains("capture, wait"), "{err}");
    let err = refused(
        "[[script]]\ncapture = \"x\"\n[[script]]\nwait = 1\nlabel = \"y\"\n",
        5,
        "script[1].label",
    );
    assert!(err.to_string().contains("every"), "{err}");
    // Unknown keys are refused by the parser, on their line.
    refused(
        "[[script]]\ncapture = \"x\"\nexposure = 3\n",
        3,
        "script[0]",
    );
    // Impossible values.
    refused(
        "[[script]]\ncapture = \"x\"\n[[script]]\nwait = -1\n",
        4,
        "script[1].wait",
    );
    refused(
        "[[script]]\ncapture = \"x\"\n[[script]]\nprompt = \"p\"\ntimeout_s = 0\n",
        5,
        "script[1].timeout_s",
    );
    let err = refused(
        "[[script]]\ncapture = \"at {angle}\"\n",
        2,
        "script[0].capture",
    );
    assert!(err.to_string().contains("{angle} is not defined"), "{err}");
    refused("[[script]]\nwait = 1\n", 1, "script");
}

#[test]
fn move_errors_name_the_positioner_key_and_line() {
    let err = refused(
        "[[script]]\nmove = \"table\"\ncapture = \"x\"\n",
        1,
        "script[0]",
    );
    assert!(err.to_string().contains("one kind"), "{err}");
    let err = refused(
        "[[script]]\nmove = \"table\"\n[[script]]\ncapture = \"x\"\n",
        2,
        "script[0].move",
    );
    assert!(
        err.to_string().contains("no positioner is named \"table\""),
        "{err}"
    );
    let err = refused(
        "[[script]]\nmove = \"stage\"\nto = { angle = 3 }\n[[script]]\ncapture = \"x\"\n",
        3,
        "script[0].to",
    );
    assert!(err.to_string().contains("{tilt} is not defined"), "{err}");
    let err = refused(
        "[[script]]\nmove = \"arm\"\nto = { preset = 1, speed = 2 }\n[[script]]\ncapture = \"x\"\n",
        3,
        "script[0].to",
    );
    assert!(err.to_string().contains("no {speed}"), "{err}");
    let err = refused(
        "[[script]]\nmove = \"arm\"\nto = { preset = 1 }\nexpect = \"(\"\n[[script]]\ncapture = \"x\"\n",
        4,
        "script[0].expect",
    );
    assert!(err.to_string().contains("regular expression"), "{err}");
}

#[test]
fn repeat_and_every_errors_name_the_key_and_line() {
    let nested = "[[script]]\nrepeat = 2\nvars = { a = { from = 1 } }\n[[script.steps]]\ncapture = \"{a}\"\n[[script.steps]]\nwait = \"soon\"\n";
    refused(nested, 7, "script[0].steps[1]");
    let err = refused(
        "[[script]]\nrepeat = 2\nvars = { a = { step = 1 } }\n[[script.steps]]\ncapture = \"{a}\"\n",
        3,
        "script[0].vars",
    );
    assert!(err.to_string().contains("from"), "{err}");
    refused(
        "[[script]]\nrepeat = 0\nsteps = [{ capture = \"x\" }]\n",
        2,
        "script[0].repeat",
    );
    // A missing key: the line of its step.
    refused("[[script]]\nrepeat = 2\n", 1, "script[0].steps");
    refused("[[script]]\nevery = 2.0\n", 1, "script[0].count");
    refused(
        "[[script]]\nevery = 2.0\ncount = 3\ncountdown_s = 5\n",
        4,
        "script[0].countdown_s",
    );
    let err = refused(
        "[[script]]\nrepeat = 100000\nsteps = [{ capture = \"x\" }]\n",
        1,
        "script",
    );
    assert!(err.to_string().contains("at most"), "{err}");
}

#[test]
fn positioner_errors_name_the_key_and_line() {
    let base = rig_text("[[script]]\ncapture = \"x\"\n");
    let cases = [
        ("port = \"/dev/ttyUSB0\"\n", "", "positioner[1].port"),
        (
            "reply = \"^DONE\"\n",
            "reply = \"^DONE(\"\n",
            "positioner[1].reply",
        ),
        (
            "move_s = 2.0\n",
            "move_s = 2.0\ntimeout_s = -1\n",
            "positioner[1].timeout_s",
        ),
        (
            "command = \"GO {preset}\"\n",
            "command = \"GO {preset\"\n",
            "positioner[1].command",
        ),
        (
            "sim.speed_deg_s = 10.0\n",
            "sim.speed_deg_s = 0.0\n",
            "positioner[0].sim.speed_deg_s",
        ),
        (
            "name = \"arm\"\n",
            "name = \"stage\"\n",
            "positioner[1].name",
        ),
        (
            "driver = \"serial\"\n",
            "driver = \"robot\"\n",
            "positioner[1].driver",
        ),
    ];
    for (old, new, field) in cases {
        assert_eq!(base.matches(old).count(), 1, "{old}");
        let text = base.replacen(old, new, 1);
        let err = RigFile::parse(&text, "rig.toml").expect_err(field);
        assert!(
            err.field().is_some_and(|f| f.starts_with(field)),
            "{err} ({field})"
        );
        assert!(err.line().is_some(), "{err}");
    }
}

#[test]
fn a_simulated_rig_without_stage_needs_a_pose_per_capture() {
    let text = rig_text("[poses]\ncount = 1\nyaw_deg = 0.0\ntilt_deg = 0.0\nshift_mm = 0.0\n[[script]]\nrepeat = 2\nsteps = [{ capture = \"x\" }]\n")
        .replace("driver = \"sim\"\ncommand = \"MOVE", "driver = \"serial\"\nport = \"/dev/null\"\ncommand = \"MOVE")
        .replace("sim.speed_deg_s = 10.0\n", "");
    let err = RigFile::parse(&text, "rig.toml").expect_err("one pose for two captures");
    assert_eq!(err.field(), Some("poses.count"), "{err}");
}

#[test]
fn templates_fill_and_numbers_print_plainly() {
    let mut v = |n: &str| (n == "a").then(|| "7".to_string());
    assert_eq!(fill("X{a}Y{{z}}", &mut v).unwrap(), "X7Y{z}");
    assert!(fill("X{b}", &mut v)
        .unwrap_err()
        .contains("{b} is not defined"));
    assert!(fill("X{a", &mut v).is_err());
    assert!(fill("X}", &mut v).is_err());
    assert_eq!(
        placeholders("MOVE {angle} {tilt}").unwrap(),
        ["angle", "tilt"]
    );
    assert_eq!(format_number(45.0), "45");
    assert_eq!(format_number(-7.5), "-7.5");
    assert_eq!(format_number(1.0 / 3.0), "0.333333");
}

#[test]
fn shipped_scripted_rigs_load_and_unroll() {
    let rigs = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("rigs");
    let sim = RigFile::load(rigs.join("sim-turntable.toml")).unwrap_or_else(|e| panic!("{e}"));
    assert!(sim.poses.is_none() && sim.has_sim_stage());
    let plan = sim.script_plan(1.0).unwrap().unwrap();
    assert_eq!(plan.captures, 10);
    let example =
        RigFile::load(rigs.join("turntable-example.toml")).unwrap_or_else(|e| panic!("{e}"));
    let plan = example.script_plan(1.0).unwrap().unwrap();
    // 3 tilts × 4 angles on the stage, 4 hand-held, 1 held out.
    assert_eq!(plan.captures, 17);
}

#[test]
fn a_capture_sets_its_own_exposure_and_gain() {
    let script = "[[script]]\ncapture = \"plain\"\n[[script]]\ncapture = \"dim\"\n\
                  exposure_us = 2500\n[[script]]\nevery = 2.0\ncount = 2\ngain_db = 6\n\
                  cameras = [\"cam0\"]\n";
    let rig = RigFile::parse(&rig_text(script), "rig.toml").unwrap();
    let plan = rig.script_plan(1.0).unwrap().unwrap();
    let exposures = plan.exposures(&rig);
    // Pose 0 keeps the camera's own; pose 1 its own gain with 2.5 ms; poses 2 and 3 (the
    // every block) its own 5 ms with 6 dB.
    assert_eq!(exposures.len(), 3, "{exposures:?}");
    assert!(!exposures.contains_key(&0));
    assert_eq!(exposures[&1], [Some((2500.0, 0.0))]);
    assert_eq!(exposures[&2], [Some((5000.0, 6.0))]);
    assert_eq!(exposures[&3], exposures[&2]);
}

#[test]
fn exposure_errors_name_the_key_and_line() {
    // 10 ms frames, no settle: 10 000 µs at most.
    let err = refused(
        "[[script]]\ncapture = \"x\"\nexposure_us = 12000\n",
        3,
        "script[0].exposure_us",
    );
    assert!(err.to_string().contains("10000 µs"), "{err}");
    refused(
        "[[script]]\ncapture = \"x\"\nexposure_us = 0\n",
        3,
        "script[0].exposure_us",
    );
    refused(
        "[[script]]\ncapture = \"x\"\ngain_db = nan\n",
        3,
        "script[0].gain_db",
    );
    let err = refused(
        "[[script]]\ncapture = \"x\"\ngain_db = 3\ncameras = [\"cam9\"]\n",
        4,
        "script[0].cameras",
    );
    assert!(err.to_string().contains("\"cam9\""), "{err}");
    refused(
        "[[script]]\ncapture = \"x\"\ngain_db = 3\ncameras = [\"cam0\", \"cam0\"]\n",
        4,
        "script[0].cameras",
    );
    refused(
        "[[script]]\ncapture = \"x\"\ncameras = [\"cam0\"]\n",
        3,
        "script[0].cameras",
    );
    // A key of captures on another kind of step.
    let err = refused(
        "[[script]]\ncapture = \"x\"\n[[script]]\nwait = 1\nexposure_us = 100\n",
        5,
        "script[1].exposure_us",
    );
    assert!(err.to_string().contains("capture, every"), "{err}");
}
