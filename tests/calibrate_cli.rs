//! `hexcal calibrate` end to end on exact synthetic correspondences of the paper-like rig:
//! the calibration file recovers the truth, OpenCV's own FileStorage reads the per-device
//! YAML with the same numbers, the Kalibr camchain is valid YAML with one entry per device,
//! and bad input names the file.

use hexcal::calib::synthetic::SyntheticRig;
use hexcal::observations::Correspondences;
use hexcal::report::CalibrationFile;
use std::path::Path;
use std::process::Command;

#[path = "support/cli.rs"]
mod cli;
use cli::{hexcal, scratch};

/// Debian's interpreter, which `apt-get install python3-opencv python3-yaml` (scripts/test.sh)
/// equips; a `python3` earlier on PATH (pyenv, a venv) may lack both.
const PYTHON: &str = "/usr/bin/python3";

fn python(script: &str, args: &[&Path]) -> String {
    let out = Command::new(PYTHON)
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("/usr/bin/python3 runs (scripts/test.sh installs it)");
    assert!(
        out.status.success(),
        "python: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn calibrate_writes_files_that_opencv_and_yaml_read() {
    let dir = scratch("calibrate-cli");
    let sigma = 0.1;
    let rig = SyntheticRig::paper(9, sigma, 41);
    // Poses 0–6 calibrate, 7–8 are held out for `hexcal verify`.
    let (train, test): (Vec<_>, Vec<_>) = rig.views().into_iter().partition(|v| v.pose < 7);
    let write = |name: &str, views| {
        let c = Correspondences {
            board: "hex600".into(),
            devices: rig.device_infos(),
            poses: rig.boards.len(),
            views,
        };
        let path = dir.join(name);
        std::fs::write(&path, serde_json::to_string(&c).unwrap()).unwrap();
        path
    };
    let input = write("correspondences.json", train);
    let held_out = write("held-out.json", test);
    let out = dir.join("out");
    let run = hexcal(&[
        "calibrate",
        input.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    // The table has a row per device.
    for d in &rig.devices {
        assert!(stdout.contains(&d.name), "{stdout}");
    }

    let text = std::fs::read_to_string(out.join("calibration.json")).unwrap();
    let file = CalibrationFile::from_json(&text, "calibration.json").unwrap();
    assert_eq!(file.devices.len(), rig.devices.len());
    for (est, truth) in file.devices.iter().zip(&rig.devices) {
        // Focal lengths to 0.1 % (their σ is ~0.01 % at this noise).
        let e = est.intrinsics.fx / truth.model.intrinsics.fx - 1.0;
        assert!(e.abs() < 1e-3, "{} fx error {e}", est.name);
        let dt = (est.pose.isometry().translation.vector - truth.pose.translation.vector).norm();
        assert!(dt < 1.0, "{} position error {dt} mm", est.name);
    }

    // Every device's lens covariance is in the file, labelled, and agrees with its σ.
    for d in &file.devices {
        assert_eq!(
            d.lens_params[..5],
            ["fx", "fy", "cx", "cy", "k1"],
            "{}",
            d.name
        );
        for (i, s) in d.lens_std.iter().enumerate() {
            let c = d.lens_covariance[i][i].sqrt();
            assert!((c - s).abs() <= 1e-9 * s, "{} {}: {c} vs {s}", d.name, i);
        }
    }
    let mut bad: serde_json::Value = serde_json::from_str(&text).unwrap();
    bad["devices"][1]["lens_covariance"][0] = serde_json::json!([1.0]);
    let e = CalibrationFile::from_json(&bad.to_string(), "c.json").unwrap_err();
    assert!(e.to_string().contains("devices[1].lens_covariance"), "{e}");

    // OpenCV reads what we wrote, value for value.
    let cam = &file.devices[1];
    let yml = out.join("opencv").join(format!("{}.yml", cam.name));
    let read = python(
        "import sys, cv2\n\
         fs = cv2.FileStorage(sys.argv[1], cv2.FILE_STORAGE_READ)\n\
         k = fs.getNode('camera_matrix').mat(); d = fs.getNode('distortion_coefficients').mat()\n\
         r = fs.getNode('R').mat(); t = fs.getNode('T').mat()\n\
         w = int(fs.getNode('image_width').real()); h = int(fs.getNode('image_height').real())\n\
         print(k[0,0], k[1,1], k[0,2], k[1,2], d[0,0], d[0,1], r.shape, t[0,0], t[1,0], t[2,0], w, h)\n",
        &[&yml],
    );
    let f: Vec<&str> = read.split_whitespace().collect();
    let num = |i: usize| f[i].parse::<f64>().unwrap();
    assert!((num(0) - cam.intrinsics.fx).abs() < 1e-9 * cam.intrinsics.fx);
    assert!((num(1) - cam.intrinsics.fy).abs() < 1e-9 * cam.intrinsics.fy);
    assert!((num(2) - cam.intrinsics.cx).abs() < 1e-9);
    assert!((num(4) - cam.distortion.k1).abs() < 1e-12);
    let t = cam.pose.isometry().translation.vector;
    // "(3, 3)" is printed as two fields.
    assert!(
        (num(8) - t.x).abs() < 1e-9 && (num(10) - t.z).abs() < 1e-9,
        "{read}"
    );
    assert_eq!((f[11], f[12]), ("1920", "1200"));

    // The camchain is YAML with one camN per device and a 4×4 T_cn_cnm1 after the first.
    let chain = python(
        "import sys, yaml\n\
         c = yaml.safe_load(open(sys.argv[1]))\n\
         print(len(c), len(c['cam1']['T_cn_cnm1']), c['cam0']['resolution'])\n",
        &[&out.join("camchain.yaml")],
    );
    assert!(
        chain.starts_with(&format!("{} 4 [1920, 1200]", rig.devices.len())),
        "{chain}"
    );
    assert!(out.join("residuals.txt").exists() && out.join("residuals.json").exists());

    // Held-out lengths: σ = 0.1 px is ≈ 0.06 mm per view at 1.5 m; 0.2 mm bounds a pair's RMS.
    let run = hexcal(&[
        "verify",
        "--calibration",
        out.join("calibration.json").to_str().unwrap(),
        held_out.to_str().unwrap(),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let stdout = String::from_utf8_lossy(&run.stdout);
    let last = stdout.lines().last().unwrap();
    let rms: f64 = last
        .split_whitespace()
        .rev()
        .nth(1)
        .unwrap()
        .parse()
        .unwrap();
    assert!(rms < 0.2, "{stdout}");
    assert!(
        stdout.contains("proj0") && stdout.contains("cam1"),
        "{stdout}"
    );

    // `hexcal show`: the maps of a device as SVG; a device that is not there is named
    // with those that are.
    for map in ["uncertainty", "distortion"] {
        let svg = dir.join(format!("proj0-{map}.svg"));
        let run = hexcal(&[
            "show",
            map,
            "proj0",
            "--calibration",
            out.to_str().unwrap(),
            "--out",
            svg.to_str().unwrap(),
        ]);
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(
            text.starts_with("<svg") && text.contains("proj0: "),
            "{text}"
        );
    }
    let run = hexcal(&[
        "show",
        "uncertainty",
        "cam9",
        "--calibration",
        out.to_str().unwrap(),
    ]);
    assert_eq!(run.status.code(), Some(1));
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(err.contains("no device \"cam9\"; it holds cam0"), "{err}");
}

#[test]
fn bad_input_names_the_file() {
    let dir = scratch("calibrate-bad");
    let input = dir.join("broken.json");
    std::fs::write(&input, "{\"board\": \"hex600\", \"devices\": [").unwrap();
    let run = hexcal(&[
        "calibrate",
        input.to_str().unwrap(),
        "--out",
        dir.join("out").to_str().unwrap(),
    ]);
    assert!(!run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(err.contains("broken.json"), "{err}");
    assert!(!dir.join("out").exists());
}

/// Issue 32: one camera seeing the board's front in some poses and its back in others
/// calibrates (it failed with singular normal equations), and the summary says in one line
/// that the front→back transform was held.
#[test]
fn one_camera_turning_the_board_over_calibrates_and_says_what_was_held() {
    let dir = scratch("calibrate-one-camera");
    let rig = SyntheticRig::one_sided(1, 0, 11, 0.1, 5);
    let c = Correspondences {
        board: "hex600".into(),
        devices: rig.device_infos(),
        poses: rig.boards.len(),
        views: rig.views(),
    };
    let input = dir.join("correspondences.json");
    std::fs::write(&input, serde_json::to_string(&c).unwrap()).unwrap();
    let out = dir.join("out");
    let run = hexcal(&[
        "calibrate",
        input.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let held: Vec<&str> = stdout.lines().filter(|l| l.starts_with("held: ")).collect();
    assert_eq!(held.len(), 1, "{stdout}");
    assert!(
        held[0].contains("front→back transform not observed: no pose is seen from both sides"),
        "{stdout}"
    );
}
