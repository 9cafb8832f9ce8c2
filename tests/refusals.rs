//! No input crashes hexcal (issue 16): one input per class of bad input — an index out of
//! range, a value that is not finite, a count beyond a limit, a duplicate name, a frame path
//! outside its folder — is refused through the real binary with exit status 1 and one line
//! naming the file, the line or JSON path, and what is wrong; a calibration that leaves a
//! device out exits 2 naming it; a closed stdout or stderr never makes it panic (101).

use hexcal::calib::synthetic::SyntheticRig;
use hexcal::observations::Correspondences;
use std::os::fd::{FromRawFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

#[path = "support/cli.rs"]
mod cli;
use cli::{hexcal, scratch};

/// The rig of `fuzz/corpus/rig/small.toml` (three simulated cameras, two projectors).
const SMALL_RIG: &str = include_str!("../fuzz/corpus/rig/small.toml");

/// stderr of a run that must fail with status 1 in one line starting `error: ` and
/// containing every one of `parts`.
fn refused(run: &Output, parts: &[&str]) -> String {
    let err = String::from_utf8_lossy(&run.stderr).into_owned();
    assert_eq!(run.status.code(), Some(1), "{err}");
    assert_eq!(err.lines().count(), 1, "one line: {err}");
    assert!(err.starts_with("error: "), "{err}");
    for p in parts {
        assert!(err.contains(p), "{p:?} missing from: {err}");
    }
    err
}

/// `text` written to `dir/name`.
fn file(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

/// `SMALL_RIG` with `old` replaced by `new` (as many lines), and the 1-based line of the
/// last line of `new`.
fn rig_with(old: &str, new: &str) -> (String, usize) {
    assert_eq!(SMALL_RIG.matches(old).count(), 1, "{old}");
    let at = SMALL_RIG.find(old).unwrap() + old.rfind('\n').map_or(0, |i| i + 1);
    (
        SMALL_RIG.replacen(old, new, 1),
        SMALL_RIG[..at].matches('\n').count() + 1,
    )
}

/// A small exactly solvable correspondences file: 2 cameras, 2 projectors, 5 poses.
fn correspondences() -> Correspondences {
    let rig = SyntheticRig::ring(2, 2, 5, 0.05, 11);
    Correspondences {
        board: "hex600".into(),
        devices: rig.device_infos(),
        poses: rig.boards.len(),
        views: rig.views(),
    }
}

fn calibrate(dir: &Path, c: &Correspondences) -> Output {
    let input = file(dir, "corr.json", &serde_json::to_string(c).unwrap());
    hexcal(&[
        "calibrate",
        input.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
    ])
}

#[test]
fn out_of_range_indices_are_refused() {
    let dir = scratch("refuse-index");
    let mut c = correspondences();
    c.views[3].camera = 7;
    let err = refused(
        &calibrate(&dir, &c),
        &["corr.json: views[3].camera: device 7 is out of range (4 devices)"],
    );
    assert!(!dir.join("out").exists(), "{err}");
    let mut c = correspondences();
    c.views[0].pose = 5;
    refused(
        &calibrate(&dir, &c),
        &["views[0].pose: pose 5 is out of range (5 poses)"],
    );
    let mut c = correspondences();
    let (v, p) = (c.views.iter().enumerate())
        .find_map(|(v, view)| {
            Some((
                v,
                view.points.iter().position(|p| !p.projectors.is_empty())?,
            ))
        })
        .unwrap();
    c.views[v].points[p].projectors[0].projector = 0;
    let at = format!("views[{v}].points[{p}].projectors[0].projector: device 0 (");
    refused(&calibrate(&dir, &c), &[&at, ") is a camera"]);
}

#[test]
fn non_finite_values_are_refused() {
    let dir = scratch("refuse-nan");
    let (text, line) = rig_with("frame_period_ms = 20.0", "frame_period_ms = nan");
    let rig = file(&dir, "nan.toml", &text);
    let out = dir.join("data");
    let run = hexcal(&[
        "capture",
        "--rig",
        rig.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    refused(
        &run,
        &[&format!(
            "nan.toml:{line}: timing.frame_period_ms: NaN is not a duration"
        )],
    );
    assert!(!out.exists());
    let (text, line) = rig_with("fx = 1500.0", "fx = nan");
    let rig = file(&dir, "fx.toml", &text);
    let run = hexcal(&[
        "capture",
        "--rig",
        rig.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    refused(
        &run,
        &[&format!(
            "fx.toml:{line}: projector[0].sim.intrinsics.fx: NaN is not a focal length in [1, 1e7] px"
        )],
    );
    let mut c = correspondences();
    c.views[2].points[0].image.x = f64::INFINITY;
    // JSON has no infinity: serde writes null, which is no number.
    refused(&calibrate(&dir, &c), &["corr.json", "line 1"]);
}

#[test]
fn huge_counts_are_refused_naming_the_limit() {
    let dir = scratch("refuse-huge");
    let out = dir.join("data");
    for (old, new, says) in [
        (
            "count = 7",
            "count = 4000000000",
            "poses.count: 4000000000 poses: at most 10000",
        ),
        (
            "\"cam0\"\ndriver = \"sim\"\nwidth = 960",
            "\"cam0\"\ndriver = \"sim\"\nwidth = 4294967295",
            "camera[0].width: 4294967295×600 px: width and height at most 65536",
        ),
    ] {
        let (text, line) = rig_with(old, new);
        let rig = file(&dir, "huge.toml", &text);
        let run = hexcal(&[
            "capture",
            "--rig",
            rig.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        refused(&run, &[&format!("huge.toml:{line}: {says}")]);
    }
    let rig = file(&dir, "small.toml", SMALL_RIG);
    let run = hexcal(&[
        "run",
        "--rig",
        rig.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--poses",
        "99999999",
    ]);
    refused(&run, &["--poses 99999999 poses: at most 10000"]);
    let board = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/rigs/boards/hex600.toml"
    ))
    .unwrap()
    .replace("pitch = 20.0", "pitch = 0.001")
    .replace("radius = 6.0", "radius = 0.0001");
    let board = file(&dir, "tiny.toml", &board);
    let run = hexcal(&[
        "board",
        "--board",
        board.to_str().unwrap(),
        "--side",
        "front",
        "--out",
        dir.join("b.svg").to_str().unwrap(),
    ]);
    refused(
        &run,
        &[
            "tiny.toml, line",
            "field `pitch`",
            "below the smallest pitch, 1 mm",
        ],
    );
    let mut c = correspondences();
    c.poses = 1 << 40;
    refused(
        &calibrate(&dir, &c),
        &["corr.json: poses: 1099511627776 poses: at most 10000"],
    );
    assert!(!out.exists());
}

#[test]
fn duplicate_names_are_refused() {
    let dir = scratch("refuse-dup");
    let mut c = correspondences();
    c.devices[1].name = c.devices[0].name.clone();
    let name = c.devices[0].name.clone();
    refused(
        &calibrate(&dir, &c),
        &[&format!(
            "corr.json: devices[1].name: {name:?} is already the name of devices[0]"
        )],
    );
    assert!(!dir.join("out").exists());
}

#[test]
fn frame_paths_outside_their_folder_are_refused() {
    let dir = scratch("refuse-path");
    let stack = dir.join("cam0");
    std::fs::create_dir_all(&stack).unwrap();
    let rig = hexcal::rig::file::RigFile::parse(SMALL_RIG, "small.toml").unwrap();
    let info = rig.dataset_info(&rig.sequence().unwrap());
    for bad in ["../secret.png", "/etc/passwd", ""] {
        let s = hexcal::dataset::StackInfo {
            camera: "cam0".into(),
            width: 960,
            height: 600,
            bits: 8,
            sequence: info.sequence.clone(),
            frames: (0..info.sequence.frame_count())
                .map(|k| hexcal::dataset::FrameEntry {
                    index: k,
                    file: if k == 4 {
                        bad.into()
                    } else {
                        format!("frame-{k:03}.png")
                    },
                    counter: 0,
                    timestamp_ns: 0,
                    exposure_us: 1.0,
                })
                .collect(),
        };
        file(&stack, "stack.json", &serde_json::to_string(&s).unwrap());
        let run = hexcal(&[
            "decode",
            stack.to_str().unwrap(),
            "--out",
            dir.join("out").to_str().unwrap(),
        ]);
        refused(
            &run,
            &[
                "cam0/stack.json: frames[4].file: ",
                "is not a file inside the stack folder",
            ],
        );
    }
}

#[test]
fn a_device_left_uncalibrated_exits_2_naming_it() {
    let dir = scratch("exit-uncalibrated");
    let mut c = correspondences();
    let last = c.devices.len() - 1;
    for v in &mut c.views {
        for p in &mut v.points {
            p.projectors.retain(|q| q.projector != last);
        }
    }
    let run = calibrate(&dir, &c);
    let (out, err) = (
        String::from_utf8_lossy(&run.stdout),
        String::from_utf8_lossy(&run.stderr),
    );
    assert_eq!(run.status.code(), Some(2), "{out}{err}");
    let name = &c.devices[last].name;
    assert!(
        out.contains(&format!(
            "not calibrated: {name}: 0 usable views, at least 3 needed"
        )),
        "{out}"
    );
    assert!(err.contains(&format!("not calibrated: {name}")), "{err}");
    assert!(dir.join("out/calibration.json").exists());
    // Every device calibrated: 0.
    assert_eq!(calibrate(&dir, &correspondences()).status.code(), Some(0));
    // The reference device lacking views stops the calibration, naming it and its views.
    let mut c = correspondences();
    c.views.retain(|v| v.camera != 0 || v.pose < 2);
    let reference = c.devices[0].name.clone();
    refused(
        &calibrate(&dir, &c),
        &[&format!("the reference device {reference} cannot be calibrated: 2 usable views, at least 3 needed")],
    );
}

#[test]
fn held_out_leaving_too_few_poses_is_refused_before_capture() {
    let dir = scratch("refuse-held-out");
    let rig = file(&dir, "small.toml", SMALL_RIG);
    let out = dir.join("run");
    let run = hexcal(&[
        "run",
        "--rig",
        rig.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--auto",
        "--held-out",
        "5",
    ]);
    refused(
        &run,
        &["--held-out 5 leaves 2 calibration poses of 7: at least 3 needed"],
    );
    assert!(!out.exists(), "nothing captured");
}

#[test]
fn a_missing_rig_file_is_named_with_its_cause_once() {
    let dir = scratch("refuse-missing-rig");
    let rig = dir.join("absent.toml");
    let out = dir.join("run");
    for cmd in [&["run", "--auto"][..], &["capture"][..]] {
        let mut args = cmd.to_vec();
        args.extend([
            "--rig",
            rig.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        let err = refused(&hexcal(&args), &["no rig file", "absent.toml"]);
        assert_eq!(err.matches("no rig file").count(), 1, "{err}");
        assert_eq!(err.matches("absent.toml").count(), 1, "{err}");
    }
    assert!(!out.exists(), "nothing written");
}

/// A pipe whose reading end is closed: writing to it fails with EPIPE.
fn closed_pipe() -> Stdio {
    let mut fds = [0; 2];
    // SAFETY: pipe(2) fills two new descriptors; each is owned exactly once below.
    unsafe {
        assert_eq!(libc::pipe(fds.as_mut_ptr()), 0);
        drop(OwnedFd::from_raw_fd(fds[0]));
        Stdio::from(OwnedFd::from_raw_fd(fds[1]))
    }
}

#[test]
fn closed_pipes_never_panic() {
    let dir = scratch("closed-pipe");
    let input = file(
        &dir,
        "corr.json",
        &serde_json::to_string(&correspondences()).unwrap(),
    );
    let bad = file(&dir, "bad.json", "{");
    let out = dir.join("out");
    let hexcal = |args: &[&str], stdout: Stdio, stderr: Stdio| {
        Command::new(env!("CARGO_BIN_EXE_hexcal"))
            .args(args)
            .stdout(stdout)
            .stderr(stderr)
            .status()
            .unwrap()
            .code()
    };
    let good = [
        "calibrate",
        input.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    assert_eq!(hexcal(&good, closed_pipe(), Stdio::null()), Some(0));
    assert_eq!(hexcal(&good, closed_pipe(), closed_pipe()), Some(0));
    assert!(out.join("calibration.json").exists(), "the work is done");
    assert_eq!(hexcal(&["info"], closed_pipe(), closed_pipe()), Some(0));
    let failing = [
        "calibrate",
        bad.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    assert_eq!(hexcal(&failing, Stdio::null(), closed_pipe()), Some(1));
    assert_eq!(hexcal(&["--help"], closed_pipe(), closed_pipe()), Some(0));
    assert_eq!(
        hexcal(&["no-such-command"], closed_pipe(), closed_pipe()),
        Some(1)
    );
}

#[test]
fn names_that_become_paths_stay_in_their_folder() {
    let dir = scratch("refuse-traversal");
    let out = dir.join("deep/out");
    // A scene's name is the output files' name.
    for bad in ["../../escaped", "/tmp/hexcal-escaped"] {
        let scene =
            hexcal::sim::DEFAULT_SCENE.replace("name = \"view\"", &format!("name = {bad:?}"));
        assert_ne!(scene, hexcal::sim::DEFAULT_SCENE);
        let path = file(&dir, "scene.toml", &scene);
        let run = hexcal(&[
            "simulate",
            "--scene",
            path.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        refused(
            &run,
            &[
                "scene.toml name: ",
                &format!("{bad:?} is not a plain file name"),
            ],
        );
        assert!(!dir.join("escaped.png").exists() && !out.exists());
    }
    assert!(!Path::new("/tmp/hexcal-escaped.png").exists());
    // A board named by a correspondences file, a dataset or a held-out file is a built-in
    // board or a file inside that file's folder: a valid board file one folder up is not.
    let inner = dir.join("inner");
    std::fs::create_dir_all(&inner).unwrap();
    file(
        &dir,
        "board.toml",
        &hexcal::board::Board::hex600().to_toml(),
    );
    let outside = dir.join("board.toml");
    for bad in ["../board.toml", outside.to_str().unwrap()] {
        let mut c = correspondences();
        c.board = bad.into();
        refused(
            &calibrate(&inner, &c),
            &[
                "corr.json: board: ",
                &format!("{bad:?} is not a path inside"),
            ],
        );
        assert!(!inner.join("out").exists());
    }
    let mut c = correspondences();
    c.board = "hex601".into();
    refused(
        &calibrate(&inner, &c),
        &[&format!(
            "corr.json: board: \"hex601\" is neither a built-in board (hex600) nor a board file \
             in {}",
            inner.display()
        )],
    );
    let rig = hexcal::rig::file::RigFile::parse(SMALL_RIG, "small.toml").unwrap();
    let mut info = rig.dataset_info(&rig.sequence().unwrap());
    info.board = "../board.toml".into();
    hexcal::dataset::Dataset::create_or_resume(&inner.join("data"), info).unwrap();
    let run = hexcal(&[
        "calibrate",
        inner.join("data").to_str().unwrap(),
        "--out",
        inner.join("cal").to_str().unwrap(),
    ]);
    refused(
        &run,
        &["data/dataset.json: board: \"../board.toml\" is not a path inside"],
    );
}

#[test]
fn a_frame_linked_out_of_its_stack_is_refused() {
    let dir = scratch("refuse-symlink");
    let stack = dir.join("cam0");
    std::fs::create_dir_all(&stack).unwrap();
    let rig = hexcal::rig::file::RigFile::parse(SMALL_RIG, "small.toml").unwrap();
    let info = rig.dataset_info(&rig.sequence().unwrap());
    let n = info.sequence.frame_count();
    let s = hexcal::dataset::StackInfo {
        camera: "cam0".into(),
        width: 960,
        height: 600,
        bits: 8,
        sequence: info.sequence.clone(),
        frames: (0..n)
            .map(|k| hexcal::dataset::FrameEntry {
                index: k,
                file: format!("frame-{k:03}.png"),
                counter: k as u64,
                timestamp_ns: 0,
                exposure_us: 1.0,
            })
            .collect(),
    };
    file(&stack, "stack.json", &serde_json::to_string(&s).unwrap());
    // A readable 960 × 600 PNG outside the stack folder, linked in as frame 0.
    let secret = dir.join("secret.png");
    image::GrayImage::new(960, 600).save(&secret).unwrap();
    let link = stack.join("frame-000.png");
    std::os::unix::fs::symlink(&secret, &link).unwrap();
    let run = hexcal(&[
        "decode",
        stack.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
    ]);
    refused(
        &run,
        &[
            "camera cam0, frame 0 (",
            &format!("{} leads out of {}", link.display(), stack.display()),
        ],
    );
}

/// `hexcal verify --calibration CAL INPUT`.
fn verify(calibration: &Path, input: &Path) -> Output {
    hexcal(&[
        "verify",
        "--calibration",
        calibration.to_str().unwrap(),
        input.to_str().unwrap(),
    ])
}

#[test]
fn verify_refuses_nonsense_and_skips_degenerate_pairs() {
    let dir = scratch("refuse-verify");
    let c = correspondences();
    let run = calibrate(&dir, &c);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let input = dir.join("corr.json");
    let good: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("out/calibration.json")).unwrap())
            .unwrap();
    let with = |name: &str, edit: &dyn Fn(&mut serde_json::Value)| {
        let mut v = good.clone();
        edit(&mut v);
        file(&dir, name, &v.to_string())
    };
    let sound = verify(&dir.join("out/calibration.json"), &input);
    let table = String::from_utf8_lossy(&sound.stdout).into_owned();
    assert!(sound.status.success(), "{table}");
    let rows = |t: &str, first: &str, second: &str| {
        t.lines()
            .filter(|l| l.split_whitespace().take(2).eq([first, second]))
            .count()
    };
    let pairs = rows(&table, "cam0", "proj0");
    assert!(pairs > 0, "{table}");
    // proj0 placed at cam0's pose: no baseline; skipped with a note, never reported.
    let index = |name: &str| {
        let devices = good["devices"].as_array().unwrap();
        devices.iter().position(|d| d["name"] == name).unwrap()
    };
    let (cam0, proj0) = (index("cam0"), index("proj0"));
    let coaxial = with("coaxial.json", &|v| {
        v["devices"][proj0]["pose"] = v["devices"][cam0]["pose"].clone();
    });
    let run = verify(&coaxial, &input);
    let text = String::from_utf8_lossy(&run.stdout).into_owned();
    assert!(run.status.success(), "{text}");
    assert_eq!(rows(&text, "cam0", "proj0"), 0, "{text}");
    let notes = text
        .lines()
        .filter(|l| l.starts_with("note: cam0–proj0 at pose "))
        .filter(|l| l.contains("no baseline to triangulate over"))
        .count();
    assert_eq!(notes, pairs, "{text}");
    assert!(!text.contains("NaN"), "{text}");
    // Every device at one place: nothing left to report.
    let one_place = with("one-place.json", &|v| {
        for d in v["devices"].as_array_mut().unwrap() {
            d["pose"] = serde_json::json!({"rvec": [0.0, 0.0, 0.0], "tvec": [0.0, 0.0, 0.0]});
        }
    });
    refused(
        &verify(&one_place, &input),
        &["corr.json: no device pair gives figures", "no baseline"],
    );
    // Values no calibration has: refused naming the calibration file and the value.
    let far = with("far.json", &|v| {
        v["devices"][0]["pose"]["tvec"][0] = 1e308.into()
    });
    refused(
        &verify(&far, &input),
        &["far.json: devices[0].pose.tvec: a translation of 1e308 mm"],
    );
    let tiny = with("tiny.json", &|v| {
        v["devices"][proj0]["intrinsics"]["fx"] = 1e-320.into()
    });
    refused(
        &verify(&tiny, &input),
        &[&format!(
            "tiny.json: devices[{proj0}].intrinsics.fx: 1e-320 is not a focal length"
        )],
    );
}

/// First contact (issue 34): an empty folder given to `calibrate` says what it should hold;
/// a rig file that is not there lists the rig files beside it; a `--stereo` pair naming a
/// device the rig does not have is refused before anything is captured, with the names.
#[test]
fn first_contact_mistakes_say_what_was_meant() {
    let dir = scratch("first-contact");
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let out = dir.join("out");
    let run = hexcal(&[
        "calibrate",
        empty.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    refused(
        &run,
        &[
            "not a hexcal dataset (no dataset.json)",
            "pose-KKK",
            "correspondences file",
        ],
    );

    let rigs = dir.join("rigs");
    std::fs::create_dir_all(&rigs).unwrap();
    file(&rigs, "small.toml", SMALL_RIG);
    let typo = rigs.join("smal.toml");
    let run = hexcal(&["run", "--rig", typo.to_str().unwrap(), "--auto"]);
    refused(
        &run,
        &["no rig file", "smal.toml; rig files in", "small.toml"],
    );

    let rig = file(&dir, "rig.toml", SMALL_RIG);
    let data = dir.join("data");
    let run = hexcal(&[
        "run",
        "--rig",
        rig.to_str().unwrap(),
        "--auto",
        "--out",
        data.to_str().unwrap(),
        "--stereo",
        "cam0,cam9",
    ]);
    refused(
        &run,
        &["--stereo cam0,cam9: no device \"cam9\"; the devices are cam0"],
    );
    assert!(!data.exists(), "nothing written before the refusal");
}

/// A board typo in a rig file names its line and the built-in boards.
#[test]
fn a_board_typo_in_a_rig_file_names_its_line_and_the_built_in_boards() {
    let dir = scratch("board-typo");
    let (text, line) = rig_with("board = \"hex600\"", "board = \"hex60\"");
    let rig = file(&dir, "rig.toml", &text);
    let run = hexcal(&["run", "--rig", rig.to_str().unwrap(), "--dry-run"]);
    refused(
        &run,
        &[
            &format!("rig.toml:{line}: board: "),
            "\"hex60\"",
            "built-in board (hex600)",
        ],
    );
}
