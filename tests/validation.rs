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
        err.contains("c.json: devices[1].intrinsics.fx: -5 is not a focal length in [1, 1e7] px"),
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
        err.contains("nan.toml [camera] intrinsics.fx: NaN is not a focal length in [1, 1e7] px"),
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

/// A stack.json of `camera` (as `info` describes it) with every frame listed.
fn stack_of(info: &DatasetInfo, camera: usize) -> hexcal::dataset::StackInfo {
    let c = &info.cameras[camera];
    hexcal::dataset::StackInfo {
        camera: c.name.clone(),
        width: c.width,
        height: c.height,
        bits: c.bits,
        sequence: info.sequence.clone(),
        frames: (0..info.sequence.frame_count())
            .map(|k| hexcal::dataset::FrameEntry {
                index: k,
                file: format!("frame-{k:03}.png"),
                counter: k as u64,
                timestamp_ns: 0,
                exposure_us: 10.0,
            })
            .collect(),
    }
}

#[test]
fn a_stack_that_does_not_belong_is_refused_by_name() {
    let (dir, info) = dataset("stack-belongs");
    let folder = dir.join("pose-000/cam0");
    std::fs::create_dir_all(&folder).unwrap();
    let file = folder.join("stack.json");
    let data = Dataset::open(&dir).unwrap();
    let error_of = |stack: &hexcal::dataset::StackInfo| {
        std::fs::write(&file, serde_json::to_string(stack).unwrap()).unwrap();
        data.stack(0, "cam0").unwrap_err().to_string()
    };
    // cam1's stack copied into cam0's folder.
    let err = error_of(&stack_of(&info, 1));
    assert_eq!(
        err,
        format!(
            "{}: camera: the stack of camera \"cam1\" in the folder of camera \"cam0\"",
            file.display()
        )
    );
    let mut deeper = stack_of(&info, 0);
    deeper.bits = 16;
    let err = error_of(&deeper);
    assert!(
        err.starts_with(&format!("{}: width: ", file.display())),
        "{err}"
    );
    assert!(
        err.contains("16 bits; camera \"cam0\" of the dataset is"),
        "{err}"
    );
    let mut other = stack_of(&info, 0);
    let rig = format!("{SMALL_RIG}[sequence]\nfringe_counts = [7, 9]\n");
    let rig = hexcal::rig::file::RigFile::parse(&rig, "small.toml").unwrap();
    other.sequence = rig.sequence().unwrap();
    assert_ne!(other.sequence, info.sequence);
    other.frames.truncate(other.sequence.frame_count());
    let err = error_of(&other);
    assert!(
        err.contains("stack.json: sequence: not the sequence of dataset.json"),
        "{err}"
    );
    std::fs::write(&file, serde_json::to_string(&stack_of(&info, 0)).unwrap()).unwrap();
    assert_eq!(data.stack(0, "cam0").unwrap().info, stack_of(&info, 0));
}

#[test]
fn pose_json_values_are_checked() {
    let (dir, info) = dataset("pose-json");
    let path = dir.join("pose-000/pose.json");
    let frames = info.sequence.frame_count();
    let good = hexcal::dataset::PoseInfo {
        pose: 0,
        cameras: vec!["cam0".into(), "cam1".into(), "cam2".into()],
        seconds: 2.5,
        dropped: 1,
        timeline: vec![[1.0, 2.0, 3.0, 1.0]; frames],
    };
    let data = Dataset::open(&dir).unwrap();
    let read = |p: &hexcal::dataset::PoseInfo| {
        std::fs::write(&path, serde_json::to_string(p).unwrap()).unwrap();
        data.pose(0)
    };
    assert_eq!(read(&good).unwrap(), Some(good.clone()));
    let refused = |edit: &dyn Fn(&mut hexcal::dataset::PoseInfo), says: &str| {
        let mut p = good.clone();
        edit(&mut p);
        let err = read(&p).unwrap_err().to_string();
        assert!(err.starts_with(&path.display().to_string()), "{err}");
        assert!(err.contains(says), "{says:?} missing from: {err}");
    };
    refused(
        &|p| p.cameras[2] = "cam0".into(),
        "cameras[2]: \"cam0\" is already cameras[0]",
    );
    refused(&|p| p.cameras.clear(), "cameras: no camera");
    refused(&|p| p.pose = 3, "pose: 3 in the folder of pose 0");
    refused(
        &|p| p.seconds = 1e308,
        "seconds: 1e308 is not a number in [0, 86400]",
    );
    refused(
        &|p| p.timeline[4][1] = -2.0,
        "timeline[4][1]: -2 is not a number",
    );
    refused(
        &|p| p.timeline[0][3] = 0.5,
        "timeline[0][3]: 0.5 retries is not a whole number",
    );
    refused(
        &|p| p.timeline.push([0.0; 4]),
        &format!("timeline: {} timeline entries", frames + 1),
    );
}

#[test]
fn calibration_json_models_and_poses_are_physically_possible() {
    let good: serde_json::Value = serde_json::from_str(CALIBRATION).unwrap();
    let refuse = |edit: &dyn Fn(&mut serde_json::Value), says: &str| {
        let mut v = good.clone();
        edit(&mut v);
        let err = CalibrationFile::from_json(&v.to_string(), "calibration.json")
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("calibration.json: "), "{err}");
        assert!(err.contains(says), "{says:?} missing from: {err}");
    };
    refuse(
        &|v| v["devices"][0]["pose"]["tvec"][2] = 1e308.into(),
        "devices[0].pose.tvec: a translation of 1e308 mm: at most 1e6 mm",
    );
    refuse(
        &|v| v["devices"][1]["pose"]["rvec"][0] = 40.0.into(),
        "devices[1].pose.rvec: a rotation of 40.1",
    );
    refuse(
        &|v| v["devices"][1]["intrinsics"]["fx"] = 1e-320.into(),
        "devices[1].intrinsics.fx: 1e-320 is not a focal length in [1, 1e7] px",
    );
    refuse(
        &|v| v["devices"][0]["intrinsics"]["cy"] = 1e9.into(),
        "devices[0].intrinsics.cy: 1e9 is not a number in [-655360, 655360]",
    );
    refuse(
        &|v| v["devices"][0]["distortion"]["k1"] = 1e300.into(),
        "devices[0].distortion.k1: ",
    );
    refuse(
        &|v| v["front_back"]["tvec"][0] = (-1e12).into(),
        "front_back.tvec: a translation of 1e12 mm",
    );
}

#[test]
fn rig_values_name_their_file_line_and_range() {
    let refuse = |text: &str, says: &str| {
        let err = hexcal::rig::file::RigFile::parse(text, "rig.toml")
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("rig.toml:"), "{err}");
        assert!(err.contains(says), "{says:?} missing from: {err}");
        err
    };
    let lines = SMALL_RIG.lines().count();
    let err = refuse(
        &format!("{SMALL_RIG}[sequence]\nfringe_counts = [0, 21, 25]\n"),
        &format!(
            "rig.toml:{}: sequence.fringe_counts: Columns fringe counts [0, 21, 25]: a count \
             is zero",
            lines + 2
        ),
    );
    assert_eq!(err.matches("sequence").count(), 1, "{err}");
    let cam0 = "name = \"cam0\"\n";
    refuse(
        &SMALL_RIG.replacen(cam0, &format!("{cam0}gain_db = 1e308\n"), 1),
        "rig.toml:14: camera[0].gain_db: 1e308 is not a number in [-100, 100]",
    );
    refuse(
        &SMALL_RIG.replace("yaw_deg = 30.0", "yaw_deg = 1e308"),
        "rig.toml:7: poses.yaw_deg: 1e308 is not a number in [0, 180]",
    );
    refuse(
        &SMALL_RIG.replace("eye = [0.0, -311.9, 1467.2]", "eye = [0.0, -311.9, 1e300]"),
        "camera[0].sim.pose.eye: 1e300 is not a number in [-1000000, 1000000]",
    );
}

#[test]
fn a_board_file_travels_with_the_files_that_name_it() {
    let dir = scratch("board-in-folder");
    let hex600 = hexcal::board::Board::hex600();
    let named = hexcal::app::calibrate::board_in_folder(&hex600, &dir).unwrap();
    assert_eq!(named, "hex600");
    assert!(
        !dir.join("board.toml").exists(),
        "a built-in board is named"
    );
    let mut own = hex600.clone();
    own.name = "hex600".into();
    own.pitch = 21.0;
    let named = hexcal::app::calibrate::board_in_folder(&own, &dir).unwrap();
    assert_eq!(named, "board.toml");
    let file = dir.join("held-out.json");
    let read = hexcal::board::Board::resolve_in(&named, &file, "board").unwrap();
    assert_eq!(read, own);
}
