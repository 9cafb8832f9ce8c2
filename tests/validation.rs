//! Every reader refuses what the issue-16 classes of bad input put in its file — an index out
//! of range, a value that is not finite, a count beyond a limit, a duplicate name, a path out
//! of its folder — with one line naming the file, the JSON path or line, and the limit
//! (docs/limits.md). Through the library: `tests/refusals.rs` runs the binary.

use hexcal::app::process::PoseViews;
use hexcal::dataset::{Dataset, DatasetInfo};
use hexcal::report::CalibrationFile;
use std::path::Path;

#[path = "support/cli.rs"]
mod cli;
use cli::{hexcal, scratch};

const SMALL_RIG: &str = include_str!("../fuzz/corpus/rig/small.toml");
const VIEWS: &str = include_str!("../fuzz/corpus/views/views.json");
const CALIBRATION: &str = include_str!("../fuzz/corpus/calibration/synthetic.json");

/// A dataset folder of the small rig with pose 0 complete; its description.
fn dataset(name: &str) -> (std::path::PathBuf, DatasetInfo) {
    let dir = scratch(name);
    let rig = hexcal::rig::file::RigFile::parse(SMALL_RIG, "small.toml").unwrap();
    let info = rig.dataset_info(&rig.sequence().unwrap());
    Dataset::create_or_resume(&dir, info.clone()).unwrap();
    std::fs::create_dir_all(dir.join("pose-000")).unwrap();
    std::fs::write(dir.join("pose-000/pose.json"), "{}").unwrap();
    (dir, info)
}

/// The error of reading `views` as pose 0's views.json of a fresh dataset.
fn views_error(views: &serde_json::Value) -> String {
    let (dir, _) = dataset("views-json");
    let path = dir.join("pose-000/views.json");
    std::fs::write(&path, views.to_string()).unwrap();
    let data = Dataset::open(&dir).unwrap();
    let err = data
        .read_pose_file::<PoseViews>(0, "views.json")
        .unwrap_err()
        .to_string();
    assert!(err.starts_with(&path.display().to_string()), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    err
}

#[test]
fn views_json_indices_are_checked() {
    let good: serde_json::Value = serde_json::from_str(VIEWS).unwrap();
    let (dir, _) = dataset("views-json-good");
    std::fs::write(dir.join("pose-000/views.json"), VIEWS).unwrap();
    let data = Dataset::open(&dir).unwrap();
    assert!(data
        .read_pose_file::<PoseViews>(0, "views.json")
        .unwrap()
        .is_some());

    // The first point lit by a projector.
    let (c, p) = (0..3)
        .find_map(|c| {
            let points = good["stacks"][c]["view"]["points"].as_array()?;
            let p = points
                .iter()
                .position(|p| p["projectors"].as_array().is_some_and(|a| !a.is_empty()))?;
            Some((c, p))
        })
        .unwrap();
    let mut v = good.clone();
    v["stacks"][c]["view"]["points"][p]["projectors"][0]["projector"] = 9.into();
    let err = views_error(&v);
    let at = format!("stacks[{c}].view.points[{p}].projectors[0].projector");
    assert!(
        err.contains(&format!("{at}: device 9 is not one of the 2 projectors")),
        "{err}"
    );
    let mut v = good.clone();
    v["stacks"][1]["view"]["camera"] = 0.into();
    let err = views_error(&v);
    assert!(
        err.contains("stacks[1].view.camera: camera 0 in the result of camera 1"),
        "{err}"
    );
    let mut v = good.clone();
    v["pose"] = 3.into();
    assert!(views_error(&v).contains("pose: 3 in the folder of pose 0"));
    let mut v = good;
    v["stacks"][2]["view"]["points"][1]["hex"]["q"] = 2_000_000_000.into();
    let err = views_error(&v);
    assert!(
        err.contains("stacks[2].view.points[1].hex: (2000000000, "),
        "{err}"
    );
}

#[test]
fn dataset_json_names_and_pose_folders_are_checked() {
    let (dir, info) = dataset("dataset-json");
    let mut bad = info.clone();
    bad.projectors[1].name = "cam2".into();
    std::fs::write(
        dir.join("dataset.json"),
        serde_json::to_string(&bad).unwrap(),
    )
    .unwrap();
    let err = Dataset::open(&dir).unwrap_err().to_string();
    assert!(
        err.contains(
            "dataset.json: projectors[1].name: \"cam2\" is already the name of cameras[2]"
        ),
        "{err}"
    );
    let mut bad = info.clone();
    bad.cameras[0].name = "../../elsewhere".into();
    std::fs::write(
        dir.join("dataset.json"),
        serde_json::to_string(&bad).unwrap(),
    )
    .unwrap();
    let err = Dataset::open(&dir).unwrap_err().to_string();
    assert!(
        err.contains("cameras[0].name: \"../../elsewhere\" cannot name a folder"),
        "{err}"
    );
    std::fs::write(
        dir.join("dataset.json"),
        serde_json::to_string(&info).unwrap(),
    )
    .unwrap();
    std::fs::create_dir_all(dir.join("pose-99999999999999999999")).unwrap();
    let err = Dataset::open(&dir)
        .unwrap()
        .completed()
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("pose 99999999999999999999: at most 10000 poses"),
        "{err}"
    );
}

#[test]
fn calibration_json_values_are_checked() {
    let good: serde_json::Value = serde_json::from_str(CALIBRATION).unwrap();
    assert!(CalibrationFile::from_json(CALIBRATION, "c.json").is_ok());
    let refuse = |v: &serde_json::Value| {
        CalibrationFile::from_json(&v.to_string(), "c.json")
            .unwrap_err()
            .to_string()
    };
    let mut v = good.clone();
    v["devices"][1]["intrinsics"]["fx"] = (-5.0).into();
    let err = refuse(&v);
    assert!(
        err.contains("c.json: devices[1].intrinsics.fx: -5 is not a positive focal length"),
        "{err}"
    );
    let mut v = good.clone();
    v["devices"][0]["height"] = 2_147_483_648u64.into();
    assert!(refuse(&v).contains("devices[0].width: "), "{}", refuse(&v));
    let mut v = good;
    v["reference"] = "nobody".into();
    assert!(refuse(&v).contains("reference: \"nobody\" is none of the devices"));
}

#[test]
fn scene_and_board_values_are_checked() {
    let dir = scratch("scene-nan");
    let scene = hexcal::sim::DEFAULT_SCENE.replace("fx = 1600.0", "fx = nan");
    let path = dir.join("nan.toml");
    std::fs::write(&path, scene).unwrap();
    let run = hexcal(&[
        "simulate",
        "--scene",
        path.to_str().unwrap(),
        "--out",
        dir.join("o").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{err}");
    assert!(
        err.contains("nan.toml [camera] intrinsics.fx: NaN is not a positive focal length"),
        "{err}"
    );
    assert!(!dir.join("o").exists());

    let hex600 = include_str!("../rigs/boards/hex600.toml");
    let wide = hex600
        .replace("half_width = 290.0", "half_width = 29000000.0")
        .replace("size = [600.0, 500.0]", "size = [60000000.0, 500.0]");
    let err = hexcal::board::Board::from_toml_str(&wide)
        .unwrap_err()
        .to_string();
    assert!(err.contains("field `half_width`: about "), "{err}");
    assert!(
        err.contains(" circles per side (pitch 20 mm): at most 100000"),
        "{err}"
    );
}

#[test]
fn images_beyond_the_limits_are_refused_before_decoding() {
    // A PGM header claiming 70000 × 10 px, with no pixels behind it.
    let dir = scratch("image-huge");
    let path = dir.join("huge.pgm");
    std::fs::write(&path, "P5\n70000 10\n255\n").unwrap();
    let err = hexcal::images::load_gray(&path).unwrap_err().to_string();
    assert!(err.contains("huge.pgm"), "{err}");
    // 40000 × 40000 passes the side limit, not the pixel count.
    std::fs::write(&path, "P5\n40000 40000\n255\n").unwrap();
    let err = hexcal::images::load_gray(&path).unwrap_err().to_string();
    assert!(
        err.contains("40000×40000 px: at most 268435456 (2²⁸) pixels"),
        "{err}"
    );
}

#[test]
fn sequences_and_decoders_stay_within_their_limits() {
    let rig = SMALL_RIG.replace("[poses]", "[sequence]\nsteps = 100000\n[poses]");
    let err = hexcal::rig::file::RigFile::parse(&rig, "r.toml")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("sequence.steps: 100000 steps: at most 1000"),
        "{err}"
    );
    let rig = hexcal::rig::file::RigFile::parse(SMALL_RIG, "r.toml").unwrap();
    let seq = rig.sequence().unwrap();
    let err = hexcal::phase::Decoder::<u16>::new(&seq, "cam0", 65_536, 4096, 255.0)
        .err()
        .unwrap()
        .to_string();
    assert!(
        err.contains("at most 8589934592 (limits::MAX_DECODER_BYTES)"),
        "{err}"
    );
    assert!(Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("docs/limits.md")
        .exists());
}
