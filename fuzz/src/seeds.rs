//! The generated part of the seed corpus (`hexcal-fuzz seed`): small, valid instances of
//! every JSON file hexcal reads, protocol frames, images. The TOML seeds are copies of the
//! repository's rig, board and scene files (`rigs/`) and `corpus/rig/small.toml`; the
//! script seeds are the positioner and script sections of its scripted rigs.

use hexcal::calib::solve::{calibrate, CalibrateOptions};
use hexcal::calib::synthetic::SyntheticRig;
use hexcal::observations::CameraView;
use hexcal::observations::Correspondences;
use std::io;
use std::path::Path;

/// Points kept per view of the synthetic correspondences (a view needs 12).
const POINTS_PER_VIEW: usize = 13;

/// Writes `value` as compact JSON to `dir/name`.
fn json<T: serde::Serialize>(dir: &Path, name: &str, value: &T) -> io::Result<()> {
    std::fs::create_dir_all(dir)?;
    std::fs::write(
        dir.join(name),
        serde_json::to_vec(value).map_err(io::Error::other)?,
    )
}

/// `views` with at most [`POINTS_PER_VIEW`] points each, those lit by most projectors.
fn trimmed(mut views: Vec<CameraView>) -> Vec<CameraView> {
    for v in &mut views {
        v.points
            .sort_by_key(|p| std::cmp::Reverse(p.projectors.len()));
        v.points.truncate(POINTS_PER_VIEW);
    }
    views
}

/// Writes every generated seed into the corpus folder `corpus`.
pub fn write(corpus: &Path) -> io::Result<()> {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    for (from, to) in [
        ("rigs/sim-paper.toml", "rig/sim-paper.toml"),
        ("rigs/aravis-example.toml", "rig/aravis-example.toml"),
        ("rigs/boards/hex600.toml", "board/hex600.toml"),
        (
            "rigs/scenes/back-wide-angle.toml",
            "scene/back-wide-angle.toml",
        ),
    ] {
        std::fs::create_dir_all(corpus.join(to).parent().expect("a folder"))?;
        std::fs::copy(repo.join(from), corpus.join(to))?;
    }
    std::fs::write(
        corpus.join("scene/default.toml"),
        hexcal::sim::DEFAULT_SCENE,
    )?;
    for (from, to) in [
        ("rigs/sim-turntable.toml", "script/sim-turntable.toml"),
        (
            "rigs/turntable-example.toml",
            "script/turntable-example.toml",
        ),
    ] {
        let text = std::fs::read_to_string(repo.join(from))?;
        std::fs::create_dir_all(corpus.join("script"))?;
        std::fs::write(corpus.join(to), script_section(&text))?;
    }
    console(corpus)?;
    correspondences(corpus)?;
    dataset_files(corpus)?;
    firmware(corpus)?;
    images(corpus)
}

/// Requests a page and a script send to the console (`TOKEN` stands for its token).
fn console(corpus: &Path) -> io::Result<()> {
    let dir = corpus.join("console");
    std::fs::create_dir_all(&dir)?;
    let get = |path: &str| format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
    let post = |path: &str| {
        format!("POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 0\r\n\r\n")
    };
    for (name, request) in [
        ("page", get("/?token=TOKEN")),
        ("state", get("/state?token=TOKEN")),
        ("events", get("/events?token=TOKEN")),
        ("thumb", get("/thumb/0.png?token=TOKEN")),
        ("live", get("/live/0.png?token=TOKEN")),
        ("capture", post("/capture?token=TOKEN")),
        ("finish", post("/finish?token=TOKEN")),
        ("no-token", get("/state")),
        // What the campaign found: tiny_http drains a body it was not asked to read by
        // allocating its declared length (src/app/console/server.rs).
        (
            "huge-body",
            "GET /state?token=TOKEN HTTP/1.1\r\nHost: a\r\nContent-Length: 4294967296\r\n\r\n"
                .to_string(),
        ),
        (
            "chunked",
            "POST /capture?x=1&token=TOKEN HTTP/1.1\r\nHost: a\r\nTransfer-Encoding: \
             chunked\r\n\r\n5\r\nhello\r\n0\r\n\r\n"
                .to_string(),
        ),
    ] {
        std::fs::write(dir.join(format!("{name}.http")), request)?;
    }
    Ok(())
}

/// The positioners and script of a rig file: from its first `[[positioner]]` (or
/// `[[script]]`) to its first device table.
fn script_section(rig: &str) -> &str {
    let start = ["[[positioner]]", "[[script]]"]
        .iter()
        .filter_map(|t| rig.find(t))
        .min()
        .unwrap_or(rig.len());
    let rest = &rig[start..];
    let end = ["[[camera]]", "[[projector]]", "[trigger]"]
        .iter()
        .filter_map(|t| rest.find(t))
        .min()
        .unwrap_or(rest.len());
    &rest[..end]
}

/// A small synthetic correspondences file and the calibration file it gives.
fn correspondences(corpus: &Path) -> io::Result<()> {
    let rig = SyntheticRig::ring(2, 1, 4, 0.1, 3);
    let c = Correspondences {
        board: "hex600".into(),
        devices: rig.device_infos(),
        poses: rig.boards.len(),
        views: trimmed(rig.views()),
    };
    json(&corpus.join("correspondences"), "synthetic.json", &c)?;
    let full = SyntheticRig::ring(2, 1, 4, 0.1, 3);
    let cal = calibrate(
        &full.board,
        &full.device_infos(),
        full.boards.len(),
        &full.views(),
        &CalibrateOptions::default(),
    )
    .map_err(io::Error::other)?;
    let file = hexcal::report::CalibrationFile::new(&cal);
    json(&corpus.join("calibration"), "synthetic.json", &file)
}

/// dataset.json, pose.json, stack.json and views.json of the rig `corpus/rig/small.toml`.
fn dataset_files(corpus: &Path) -> io::Result<()> {
    let text = std::fs::read_to_string(corpus.join("rig/small.toml"))?;
    let rig = hexcal::rig::file::RigFile::parse(&text, "small.toml").map_err(io::Error::other)?;
    let info = rig.dataset_info(&rig.sequence().map_err(io::Error::other)?);
    json(&corpus.join("dataset"), "dataset.json", &info)?;
    let pose = hexcal::dataset::PoseInfo {
        pose: 0,
        cameras: info.cameras.iter().map(|c| c.name.clone()).collect(),
        seconds: 1.5,
        dropped: 0,
        timeline: vec![[0.0, 1.0, 2.0, 0.0], [3.0, 4.0, 5.0, 1.0]],
    };
    json(&corpus.join("dataset"), "pose.json", &pose)?;
    let camera = &info.cameras[0];
    let stack = hexcal::dataset::StackInfo {
        camera: camera.name.clone(),
        width: camera.width,
        height: camera.height,
        bits: camera.bits,
        sequence: info.sequence.clone(),
        frames: (0..info.sequence.frame_count())
            .map(|k| hexcal::dataset::FrameEntry {
                index: k,
                file: format!("frame-{k:03}.png"),
                counter: k as u64,
                timestamp_ns: 1000 * k as u64,
                exposure_us: 10_000.0,
            })
            .collect(),
    };
    json(&corpus.join("stack"), "stack.json", &stack)?;
    // Three cameras, two projectors, one pose: the small rig's device numbering.
    let synthetic = SyntheticRig::ring(3, 2, 1, 0.1, 5);
    let views = trimmed(synthetic.views());
    let stacks = info
        .cameras
        .iter()
        .enumerate()
        .map(|(c, entry)| {
            let view = views.iter().find(|v| v.camera == c).cloned();
            hexcal::app::process::StackResult {
                camera: entry.name.clone(),
                circles: 20,
                points: view.as_ref().map_or(0, |v| v.points.len()),
                anchored: view.is_some(),
                projector_points: vec![POINTS_PER_VIEW; info.projectors.len()],
                error: None,
                view,
                verdict: Some(hexcal::phase::check::StackVerdict::unchecked()),
            }
        })
        .collect();
    let pose_views = hexcal::app::process::PoseViews { pose: 0, stacks };
    json(&corpus.join("views"), "views.json", &pose_views)
}

/// Every request the host sends, framed as on the wire, one after another.
fn firmware(corpus: &Path) -> io::Result<()> {
    use hexcal_firmware_protocol::{encode_frame, Command, LineConfig, Pacing, Request};
    let mut lines = heapless::Vec::new();
    lines
        .push(LineConfig {
            line: 0,
            delay_us: 0,
            pulse_us: 100,
        })
        .map_err(|_| io::Error::other("line"))?;
    let commands = [
        Command::Hello { version: 1 },
        Command::Configure { lines },
        Command::SetHeartbeat { interval_ms: 5 },
        Command::Arm {
            frames: 3,
            pacing: Pacing::Periodic { period_us: 1000 },
        },
        Command::Fire,
        Command::Arm {
            frames: 2,
            pacing: Pacing::PerFire,
        },
        Command::Fire,
        Command::Disarm,
    ];
    let mut bytes = Vec::new();
    for (seq, command) in commands.into_iter().enumerate() {
        let request = Request {
            seq: seq as u16,
            command,
        };
        bytes.extend(encode_frame(&request).map_err(|e| io::Error::other(format!("{e:?}")))?);
    }
    std::fs::create_dir_all(corpus.join("firmware"))?;
    std::fs::write(corpus.join("firmware/session.bin"), bytes)
}

/// A 32×32 grey disc as PNG, 16-bit TIFF and PGM, and as raw `detect` input.
fn images(corpus: &Path) -> io::Result<()> {
    let disc = |x: u32, y: u32| {
        let (dx, dy) = (x as f64 - 15.5, y as f64 - 15.5);
        if dx * dx + dy * dy < 64.0 {
            230u8
        } else {
            25
        }
    };
    let grey = image::GrayImage::from_fn(32, 32, |x, y| image::Luma([disc(x, y)]));
    let deep: image::ImageBuffer<image::Luma<u16>, Vec<u16>> =
        image::ImageBuffer::from_fn(32, 32, |x, y| image::Luma([u16::from(disc(x, y)) * 257]));
    let dir = corpus.join("image");
    std::fs::create_dir_all(&dir)?;
    let save = |r: image::ImageResult<()>| r.map_err(io::Error::other);
    save(grey.save(dir.join("disc.png")))?;
    save(grey.save(dir.join("disc.pgm")))?;
    save(deep.save(dir.join("disc16.tiff")))?;
    let mut raw = vec![24u8, 24, 0];
    raw.extend(grey.as_raw());
    std::fs::create_dir_all(corpus.join("detect"))?;
    std::fs::write(corpus.join("detect/disc.bin"), raw)
}
