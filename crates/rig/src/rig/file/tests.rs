use super::*;

fn shipped(name: &str) -> String {
    std::fs::read_to_string(
        Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
            .join("rigs")
            .join(name),
    )
    .unwrap()
}

#[test]
fn shipped_rig_files_load() {
    let paper = RigFile::load(
        Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("rigs/sim-paper.toml"),
    )
    .unwrap();
    assert_eq!((paper.cameras.len(), paper.projectors.len()), (6, 3));
    assert_eq!(paper.poses.unwrap().count, 10);
    // Cameras 0–2 and 3–5 face each other across the board.
    for i in 0..3 {
        let (a, b) = (
            paper.cameras[i].sim.unwrap().pose.eye,
            paper.cameras[i + 3].sim.unwrap().pose.eye,
        );
        assert!(a[2] > 0.0 && b[2] < 0.0, "cam{i} and cam{}", i + 3);
    }
    for name in ["aravis-example.toml", "v4l2-example.toml"] {
        RigFile::parse(&shipped(name), name).unwrap_or_else(|e| panic!("{e}"));
    }
}

/// Parse `text` with `old` replaced by `new` once: the error, which must name the line
/// where `marker` (a line of `new`) is written.
fn refused(text: &str, old: &str, new: &str, marker: &str) -> RigError {
    assert_eq!(text.matches(old).count(), 1, "{old:?} must occur once");
    let at = text.find(old).unwrap() + new.find(marker).unwrap();
    let text = text.replacen(old, new, 1);
    let err = RigFile::parse(&text, "rig.toml").expect_err("must be refused");
    let line = text[..at].matches('\n').count() + 1;
    assert_eq!(err.line(), Some(line), "{err}");
    assert!(
        err.to_string().starts_with(&format!("rig.toml:{line}: ")),
        "{err}"
    );
    err
}

#[test]
fn errors_name_the_key_and_its_line() {
    let paper = shipped("sim-paper.toml");
    let err = refused(
        &paper,
        "name = \"cam2\"\n",
        "name = \"cam2\"\nshutter = 3\n",
        "shutter",
    );
    assert!(err.to_string().contains("shutter"), "{err}");
    assert!(err.field().unwrap().starts_with("camera[2]"), "{err}");

    let err = refused(
        &paper,
        "name = \"cam4\"\ndriver = \"sim\"\nwidth = 1920\nheight = 1200\nexposure_ms = 30.0",
        "name = \"cam4\"\ndriver = \"sim\"\nwidth = 1920\nheight = 1200\nexposure_ms = 45.0",
        "exposure_ms",
    );
    assert_eq!(err.field(), Some("camera[4].exposure_ms"), "{err}");
    assert!(err.to_string().contains("display time"), "{err}");

    let err = refused(&paper, "name = \"cam5\"", "name = \"cam1\"", "name");
    assert_eq!(err.field(), Some("camera[5].name"), "{err}");

    let err = refused(
        &paper,
        "name = \"proj1\"\ndriver = \"sim\"\nwidth = 1920\nheight = 1080\ngamma = 2.2",
        "name = \"proj1\"\ndriver = \"sim\"\nwidth = 1920\nheight = 1080\ngamma = 0.0",
        "gamma",
    );
    assert_eq!(err.field(), Some("projector[1].gamma"), "{err}");

    let err = refused(&paper, "count = 10", "count = 0", "count");
    assert_eq!(err.field(), Some("poses.count"), "{err}");
}

#[test]
fn two_devices_on_one_trigger_line_are_refused() {
    let lab = shipped("aravis-example.toml");
    let err = refused(&lab, "trigger_line = 1", "trigger_line = 0", "trigger_line");
    assert_eq!(err.field(), Some("camera[1].trigger_line"), "{err}");
    assert!(err.to_string().contains("already left's"), "{err}");
}

#[test]
fn a_real_camera_needs_an_address() {
    // A missing key is reported at its table's header.
    let text = shipped("v4l2-example.toml").replacen("address = \"/dev/video0\"\n", "", 1);
    let err = RigFile::parse(&text, "desk.toml").unwrap_err();
    assert_eq!(err.field(), Some("camera[0].address"), "{err}");
    let header = text[..text.find("[[camera]]").unwrap()]
        .matches('\n')
        .count()
        + 1;
    assert_eq!(err.line(), Some(header), "{err}");
}

#[test]
fn a_rig_without_projectors_takes_one_plain_frame_per_pose() {
    let text = shipped("sim-cameras.toml");
    let rig = RigFile::parse(&text, "sim-cameras.toml").unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((rig.cameras.len(), rig.projectors.len()), (8, 0));
    let sequence = rig.sequence().unwrap();
    assert!(sequence.is_camera_only());
    assert_eq!(sequence.frame_count(), 1);
    // A sequence table has nothing to describe there.
    let err = refused(
        &text,
        "[poses]\n",
        "[sequence]\nfringe_counts = [20, 21]\n[poses]\n",
        "[sequence]",
    );
    assert_eq!(err.field(), Some("sequence"), "{err}");
}

#[test]
fn colour_and_webcam_rigs_name_their_simulated_formats() {
    let bayer = RigFile::parse(&shipped("sim-bayer.toml"), "sim-bayer.toml")
        .unwrap_or_else(|e| panic!("{e}"));
    let formats: Vec<SimFormat> = bayer
        .cameras
        .iter()
        .map(|c| c.sim_format().unwrap())
        .collect();
    assert_eq!(
        formats[..4],
        Cfa::ALL.map(SimFormat::Bayer),
        "the four phases in turn"
    );
    let mjpeg = RigFile::parse(&shipped("sim-mjpeg.toml"), "sim-mjpeg.toml")
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(mjpeg
        .cameras
        .iter()
        .all(|c| c.sim_format() == Ok(SimFormat::Mjpeg(85))));
    let paper = RigFile::parse(&shipped("sim-paper.toml"), "sim-paper.toml").unwrap();
    assert_eq!(paper.cameras[0].sim_format(), Ok(SimFormat::Mono));
}

#[test]
fn impossible_simulated_formats_are_refused_at_their_line() {
    let bayer = shipped("sim-bayer.toml");
    let err = refused(
        &bayer,
        "name = \"cam1\"\ndriver = \"sim\"\nformat = \"BayerGR\"",
        "name = \"cam1\"\ndriver = \"sim\"\nformat = \"Bayer\"",
        "format",
    );
    assert_eq!(err.field(), Some("camera[1].format"), "{err}");
    let err = refused(
        &bayer,
        "name = \"cam2\"\ndriver = \"sim\"\nformat = \"BayerGB\"",
        "name = \"cam2\"\ndriver = \"sim\"\nformat = \"BayerGB\"\njpeg_quality = 90",
        "jpeg_quality",
    );
    assert_eq!(err.field(), Some("camera[2].jpeg_quality"), "{err}");
    let mjpeg = shipped("sim-mjpeg.toml");
    let err = refused(
        &mjpeg,
        "name = \"cam3\"\ndriver = \"sim\"\nformat = \"MJPG\"\njpeg_quality = 85",
        "name = \"cam3\"\ndriver = \"sim\"\nformat = \"MJPG\"\njpeg_quality = 0",
        "jpeg_quality",
    );
    assert_eq!(err.field(), Some("camera[3].jpeg_quality"), "{err}");
    let err = refused(
        &mjpeg,
        "name = \"cam4\"\ndriver = \"sim\"\nformat = \"MJPG\"\njpeg_quality = 85",
        "name = \"cam4\"\ndriver = \"sim\"\nformat = \"MJPG\"\njpeg_quality = 85\nbits = 12",
        "bits",
    );
    assert!(err.to_string().contains("MJPEG is 8 bits"), "{err}");
}
