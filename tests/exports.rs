//! The exports of `hexcal calibrate` loaded in the neighbouring tools' readers: mrcal's own
//! Python (Debian `python3-mrcal`), a COLMAP text-model reader written from COLMAP's
//! documented format, ROS camera_info through YAML and OpenCV, stereo pairs against
//! OpenCV's `stereoRectify`, and the Kalibr camchain as Kalibr's camera-chain reader reads
//! it. Each compares the tool's projections with hexcal's own
//! (`tests/exports/check_exports.py`).

use hexcal::calib::synthetic::SyntheticRig;
use hexcal::observations::Correspondences;
use hexcal::report::CalibrationFile;
use nalgebra::{Point2, Point3};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

#[path = "support/cli.rs"]
mod cli;
use cli::{hexcal, scratch};

/// Debian's interpreter with python3-mrcal, python3-opencv and python3-yaml
/// (scripts/test.sh installs them).
const PYTHON: &str = "/usr/bin/python3";

/// Grid of the Kalibr refit (crates/calib/src/report/export.rs): the reference pixels are its nodes.
const GRID: (usize, usize) = (48, 30);

/// One calibration of the synthetic paper rig (σ = 0.1 px) with the pair cam0,cam1
/// exported, and the reference projections: (output folder, reference JSON).
fn calibrated() -> &'static (PathBuf, PathBuf) {
    static ONCE: OnceLock<(PathBuf, PathBuf)> = OnceLock::new();
    ONCE.get_or_init(|| {
        let dir = scratch("exports");
        let rig = SyntheticRig::paper(8, 0.1, 17);
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
            "--stereo",
            "cam0,cam1",
        ]);
        let stdout = String::from_utf8_lossy(&run.stdout);
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        println!("{stdout}");
        let reference = dir.join("reference.json");
        std::fs::write(&reference, reference_projections(&out)).unwrap();
        (out, reference)
    })
}

/// Per device of `out/calibration.json`: points 1 m along the rays of pixels over the whole
/// image (nodes of [`GRID`], corners included), in the device's and the reference frame,
/// and hexcal's projections of them.
fn reference_projections(out: &Path) -> String {
    let text = std::fs::read_to_string(out.join("calibration.json")).unwrap();
    let file = CalibrationFile::from_json(&text, "calibration.json").unwrap();
    let devices: Vec<serde_json::Value> = file
        .devices
        .iter()
        .map(|d| {
            let m = d.model();
            let pose = d.pose.isometry();
            let (w, h) = (d.width as f64 - 1.0, d.height as f64 - 1.0);
            let (mut dev, mut refp, mut pixels) = (Vec::new(), Vec::new(), Vec::new());
            let cols = (0..GRID.0).step_by(5).chain([GRID.0 - 1]);
            for i in cols {
                for j in (0..GRID.1).step_by(5).chain([GRID.1 - 1]) {
                    let px = Point2::new(
                        w * i as f64 / (GRID.0 - 1) as f64,
                        h * j as f64 / (GRID.1 - 1) as f64,
                    );
                    let Some(ray) = m.ray(px) else { continue };
                    let x = Point3::from(ray * 1000.0);
                    let q = m.project(&x).unwrap();
                    dev.push([x.x, x.y, x.z]);
                    let r = pose.inverse() * x;
                    refp.push([r.x, r.y, r.z]);
                    pixels.push([q.x, q.y]);
                }
            }
            serde_json::json!({
                "name": d.name, "width": d.width, "height": d.height,
                "kind": d.kind,
                "rvec": d.pose.rvec, "tvec": d.pose.tvec,
                "points_dev": dev, "points_ref": refp, "pixels": pixels,
            })
        })
        .collect();
    serde_json::json!({ "devices": devices }).to_string()
}

/// Run the checker for `format`; its figures are printed (`--nocapture` shows them).
fn check(format: &str, extra: &[&str]) {
    let (out, reference) = calibrated();
    let run = Command::new(PYTHON)
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/exports/check_exports.py"))
        .arg(format)
        .arg(out)
        .arg(reference)
        .args(extra)
        .output()
        .expect("/usr/bin/python3 runs (scripts/test.sh installs it)");
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "{format}: {stdout}{}",
        String::from_utf8_lossy(&run.stderr)
    );
    // Every device (or the pair) was checked.
    let lines = stdout.lines().count();
    assert!(lines >= if format == "stereo" { 1 } else { 9 }, "{stdout}");
    println!("{stdout}");
}

#[test]
fn mrcal_loads_every_cameramodel_and_projects_as_hexcal() {
    check("mrcal", &[]);
}

#[test]
fn colmap_text_model_projects_as_hexcal() {
    check("colmap", &[]);
}

#[test]
fn ros_camera_info_loads_and_projects_as_hexcal() {
    check("ros", &[]);
}

#[test]
fn stereo_pair_matches_opencv_stereo_rectify() {
    check("stereo", &["cam0,cam1"]);
}

#[test]
fn kalibr_camchain_has_overlaps_and_an_honest_radtan() {
    check("kalibr", &[]);
}

#[test]
fn stereo_pairs_of_unknown_or_mismatched_devices_are_refused() {
    let (out, _) = calibrated();
    let text = std::fs::read_to_string(out.join("calibration.json")).unwrap();
    let file = CalibrationFile::from_json(&text, "calibration.json").unwrap();
    use hexcal::report::export::stereo_yaml;
    let e = stereo_yaml(&file, "cam0,nope").unwrap_err().to_string();
    assert!(e.contains("nope") && e.contains("--stereo"), "{e}");
    let e = stereo_yaml(&file, "cam0,proj0").unwrap_err().to_string();
    assert!(e.contains("size"), "{e}");
    let e = stereo_yaml(&file, "cam0").unwrap_err().to_string();
    assert!(e.contains("two device names"), "{e}");
}
