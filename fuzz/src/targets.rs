//! The fuzz targets: each takes arbitrary bytes, runs one of hexcal's readers on them and,
//! when the input is accepted, what hexcal does next with it; it returns a short outcome
//! (`ok` or the kind of refusal) that the campaign uses as feedback. A panic, an abort or
//! an allocation beyond the cap is a bug.

use hexcal::board::{Board, Side};
use hexcal::calib::solve::{calibrate, CalibrateOptions};
use hexcal::dataset::{DatasetInfo, PoseFile, PoseInfo, StackInfo, StackReader};
use hexcal::observations::Correspondences;
use std::path::Path;
use std::sync::OnceLock;

/// One fuzz target.
pub struct Target {
    /// Its name (the corpus folder `fuzz/corpus/NAME`).
    pub name: &'static str,
    /// What it exercises.
    pub about: &'static str,
    /// Whether it reads a file format (the campaign runs ≥ 10⁶ inputs of each).
    pub parser: bool,
    /// Runs one input.
    pub run: fn(&[u8]) -> String,
}

/// Every target.
pub const TARGETS: &[Target] = &[
    Target {
        name: "rig",
        about: "rig file (TOML): parse, check, sequence, dataset description, timing, poses",
        parser: true,
        run: rig,
    },
    Target {
        name: "script",
        about: "a rig file's positioners and capture script (after a fixed rig): parse, check, \
                unroll and plan",
        parser: true,
        run: script,
    },
    Target {
        name: "board",
        about: "board file (TOML): parse, validate, lattice, circles and marker cells",
        parser: true,
        run: board,
    },
    Target {
        name: "scene",
        about: "scene file (TOML): parse, check, board pose",
        parser: true,
        run: scene,
    },
    Target {
        name: "correspondences",
        about: "correspondences file (JSON): parse, check, calibrate (small inputs)",
        parser: true,
        run: correspondences,
    },
    Target {
        name: "views",
        about: "a dataset's views.json: parse, check against a 3-camera, 2-projector dataset",
        parser: true,
        run: views,
    },
    Target {
        name: "stack",
        about: "stack.json: parse, check, frame list against the sequence",
        parser: true,
        run: stack,
    },
    Target {
        name: "dataset",
        about: "dataset.json and pose.json: parse, check",
        parser: true,
        run: dataset,
    },
    Target {
        name: "calibration",
        about: "calibration.json: parse, check, device models",
        parser: true,
        run: calibration,
    },
    Target {
        name: "firmware",
        about: "trigger protocol: frame reader, decoders of both directions, firmware model",
        parser: true,
        run: firmware,
    },
    Target {
        name: "image",
        about: "image files (PNG, TIFF, PNM, JPEG): decode within the limits, then detect",
        parser: true,
        run: image,
    },
    Target {
        name: "console",
        about: "the operator console's HTTP requests (raw bytes to a live console on \
                loopback; TOKEN stands for its access token): parse, route, answer",
        // A network round trip per input (tens a second, not thousands): not held to
        // the file readers' 10⁶-input campaign.
        parser: false,
        run: console,
    },
    Target {
        name: "detect",
        about: "circle detection and grid building on arbitrary small grey images",
        parser: false,
        run: detect,
    },
];

/// The target called `name`.
pub fn find(name: &str) -> Option<&'static Target> {
    TARGETS.iter().find(|t| t.name == name)
}

/// The outcome class of an error message: its text without digits and without what is
/// quoted (values of the input), at most 60 characters.
fn class(message: &str) -> String {
    let mut out = String::new();
    let mut quoted: Option<char> = None;
    for c in message.chars() {
        match quoted {
            Some(q) if c == q => quoted = None,
            Some(_) => {}
            None if c == '"' || c == '`' => quoted = Some(c),
            None if !c.is_ascii_digit() => out.push(c),
            None => {}
        }
        if out.chars().count() >= 60 {
            break;
        }
    }
    out
}

/// `ok`, or the class of the error.
fn outcome<T, E: std::fmt::Display>(r: &Result<T, E>) -> String {
    match r {
        Ok(_) => "ok".into(),
        Err(e) => class(&e.to_string()),
    }
}

fn rig(data: &[u8]) -> String {
    let text = String::from_utf8_lossy(data);
    let rig = match hexcal::rig::file::RigFile::parse(&text, "rig.toml") {
        Ok(r) => r,
        Err(e) => return class(&e.to_string()),
    };
    let _ = hexcal::rig::open::timing(&rig, true);
    for t in rig.cameras.iter().filter_map(|c| c.sim.as_ref()) {
        let _ = hexcal::rig::sim::look_at(&t.pose);
    }
    if let Some(p) = &rig.poses {
        let _ = hexcal::rig::sim::board_poses(p);
    }
    if Board::builtin(&rig.board).is_some() {
        let _ = rig.board();
    }
    let sequence = rig.sequence();
    // A capture script unrolls with its planned times.
    let _ = hexcal::app::script::plan_of(&rig);
    if let Ok(s) = &sequence {
        let info = rig.dataset_info(s);
        if let Err(e) = info.check() {
            panic!("a checked rig gives an invalid dataset.json: {e}");
        }
    }
    outcome(&sequence)
}

/// The rig a `script` input follows: the small simulated rig (seven board poses: a script
/// of more captures needs a sim positioner to move the board).
const SCRIPT_RIG: &str = include_str!("../corpus/rig/small.toml");

fn script(data: &[u8]) -> String {
    let text = format!("{SCRIPT_RIG}\n{}", String::from_utf8_lossy(data));
    let rig = match hexcal::rig::file::RigFile::parse(&text, "rig.toml") {
        Ok(r) => r,
        Err(e) => return class(&e.to_string()),
    };
    let plan = hexcal::app::script::plan_of(&rig);
    if let Ok(Some(plan)) = &plan {
        assert!(
            plan.duration_s.is_finite() && plan.duration_s >= 0.0,
            "a checked script plans {} s",
            plan.duration_s
        );
        for step in &plan.steps {
            let _ = serde_json::to_string(step).expect("a planned step serialises");
        }
    }
    outcome(&plan)
}

fn board(data: &[u8]) -> String {
    let board = Board::from_toml_str(&String::from_utf8_lossy(data));
    if let Ok(b) = &board {
        for side in Side::BOTH {
            let _ = b.circles(side);
            let _ = b.ringed(side);
        }
    }
    outcome(&board)
}

fn scene(data: &[u8]) -> String {
    let scene = hexcal::sim::Scene::parse(&String::from_utf8_lossy(data), "scene.toml");
    if let Ok(s) = &scene {
        let _ = s.pose.cam_from_board();
    }
    outcome(&scene)
}

/// Observations a correspondences input may have for the target to calibrate it (keeps a
/// bundle adjustment short).
const CALIBRATE_AT_MOST: usize = 400;

fn correspondences(data: &[u8]) -> String {
    let c: Correspondences = match serde_json::from_slice(data) {
        Ok(c) => c,
        Err(e) => return class(&e.to_string()),
    };
    if let Err(e) = c.check() {
        return class(&e.to_string());
    }
    let size: usize = c
        .views
        .iter()
        .flat_map(|v| &v.points)
        .map(|p| 1 + p.projectors.len())
        .sum();
    if size > CALIBRATE_AT_MOST {
        return "ok (not calibrated: large)".into();
    }
    let cal = calibrate(
        &Board::hex600(),
        &c.devices,
        c.poses,
        &c.views,
        &CalibrateOptions::default(),
    );
    outcome(&cal)
}

/// The dataset the `views` target checks against: the rig of `fuzz/corpus/rig/small.toml`.
fn small_dataset() -> &'static DatasetInfo {
    static INFO: OnceLock<DatasetInfo> = OnceLock::new();
    INFO.get_or_init(|| {
        let text = include_str!("../corpus/rig/small.toml");
        let rig = hexcal::rig::file::RigFile::parse(text, "small.toml").expect("seed rig");
        rig.dataset_info(&rig.sequence().expect("seed sequence"))
    })
}

fn views(data: &[u8]) -> String {
    let v: hexcal::app::process::PoseViews = match serde_json::from_slice(data) {
        Ok(v) => v,
        Err(e) => return class(&e.to_string()),
    };
    outcome(&v.check(v.pose, small_dataset()).map_err(|e| e.to_string()))
}

fn stack(data: &[u8]) -> String {
    let info: StackInfo = match serde_json::from_slice(data) {
        Ok(i) => i,
        Err(e) => return class(&e.to_string()),
    };
    let reader = StackReader::new(Path::new("stack"), info);
    if let Ok(r) = &reader {
        let _ = r.full_scale();
    }
    outcome(&reader)
}

fn dataset(data: &[u8]) -> String {
    if let Ok(info) = serde_json::from_slice::<DatasetInfo>(data) {
        return outcome(&info.check().map_err(|e| e.to_string()));
    }
    let pose: PoseInfo = match serde_json::from_slice(data) {
        Ok(p) => p,
        Err(e) => return class(&e.to_string()),
    };
    outcome(
        &pose
            .check(pose.pose, small_dataset())
            .map_err(|e| e.to_string()),
    )
}

fn calibration(data: &[u8]) -> String {
    let file = hexcal::report::CalibrationFile::from_json(
        &String::from_utf8_lossy(data),
        "calibration.json",
    );
    if let Ok(f) = &file {
        for d in &f.devices {
            let model = d.model();
            let centre = (f64::from(model.width) / 2.0, f64::from(model.height) / 2.0);
            let _ = model.ray(nalgebra::Point2::new(centre.0, centre.1));
            let _ = hexcal::report::opencv_yaml(d);
        }
    }
    outcome(&file)
}

fn firmware(data: &[u8]) -> String {
    use hexcal_firmware_protocol::{self as proto, ControllerMessage, Request};
    let mut reader = proto::FrameReader::new();
    let mut model = hexcal_simulator::firmware::FirmwareModel::new(Default::default());
    let mut out = Vec::new();
    let mut seen = String::from("frames");
    for (i, &b) in data.iter().enumerate() {
        if let Some(frame) = reader.push(b) {
            let Ok(frame) = frame else {
                seen.push_str(" too-long");
                continue;
            };
            let request = proto::decode_frame::<Request>(frame);
            let message = proto::decode_frame::<ControllerMessage>(frame);
            let _ = proto::decode_hello_request_prefix(frame);
            let _ = proto::decode_hello_reply_prefix(frame);
            if let Ok(r) = &request {
                let again = proto::encode_frame(r).expect("a decoded request encodes");
                let inner = &again[1..again.len() - 1];
                assert_eq!(proto::decode_frame::<Request>(inner).as_ref(), Ok(r));
            }
            seen.push_str(if request.is_ok() || message.is_ok() {
                " message"
            } else {
                " refused"
            });
        }
        // 100 µs per byte, as at 115 200 baud; events as the model's clock passes.
        model.receive(&[b], 100 * i as u64, &mut out);
        model.poll(100 * i as u64, &mut out);
        out.clear();
    }
    seen.truncate(60);
    seen
}

fn image(data: &[u8]) -> String {
    let reader = image::ImageReader::new(std::io::Cursor::new(data));
    let decoded = hexcal::images::decode(reader);
    if let Ok(img) = &decoded {
        let grey = hexcal::images::to_gray(img);
        if grey.width() <= 256 && grey.height() <= 256 {
            detect_grid(&grey);
        }
    }
    outcome(&decoded)
}

/// Detection and grid building on `image`: the number of circles.
fn detect_grid(image: &hexcal::images::FloatImage) -> usize {
    let circles = hexcal::detect::detect(image, &hexcal::detect::DetectParams::default());
    let _ = hexcal::grid::build(
        image,
        &circles,
        &Board::hex600(),
        &hexcal::grid::GridParams::default(),
    );
    circles.len()
}

/// Values a file's float image may hold beyond 8-bit grey levels.
const SPECIAL: [f32; 6] = [
    f32::NAN,
    f32::INFINITY,
    f32::NEG_INFINITY,
    -1e30,
    1e30,
    65535.0,
];

/// Bytes 0–2 give the size (8…64 px a side) and the sample mode (8-bit levels, 16-bit
/// levels, or special float values mixed in), the rest the pixels (repeated).
fn detect(data: &[u8]) -> String {
    let byte = |i: usize| data.get(i).copied().unwrap_or(0);
    let (w, h, mode) = (
        8 + u32::from(byte(0)) % 57,
        8 + u32::from(byte(1)) % 57,
        byte(2) % 3,
    );
    let pixels = if data.len() > 3 {
        &data[3..]
    } else {
        &[0u8][..]
    };
    let image = hexcal::images::FloatImage::from_fn(w, h, |x, y| {
        let i = (y * w + x) as usize;
        let b = pixels[i % pixels.len()];
        image::Luma([match mode {
            0 => f32::from(b),
            1 => f32::from(b) * 257.0,
            _ if b % 17 == 0 => SPECIAL[usize::from(b / 17) % SPECIAL.len()],
            _ => f32::from(b),
        }])
    });
    format!("{} circles", detect_grid(&image).min(9))
}

/// The console the `console` target talks to (one per process), its address and token.
fn live_console() -> &'static (
    std::sync::Mutex<hexcal::app::console::Console>,
    String,
    String,
) {
    static CONSOLE: OnceLock<(
        std::sync::Mutex<hexcal::app::console::Console>,
        String,
        String,
    )> = OnceLock::new();
    CONSOLE.get_or_init(|| {
        let cameras = [("cam0".to_string(), [64, 48])];
        let console = hexcal::app::console::Console::start("127.0.0.1:0", &cameras, false)
            .expect("a console on loopback");
        let url = console.url().to_string();
        let rest = url.strip_prefix("http://").expect("an http URL");
        let (addr, token) = rest.split_once("/?token=").expect("a token in the URL");
        (
            std::sync::Mutex::new(console),
            addr.to_string(),
            token.to_string(),
        )
    })
}

/// One raw HTTP request (every `TOKEN` replaced by the console's token) to the live console;
/// the answer's status line. A console that no longer answers is a failure (its server
/// thread died on an earlier input).
fn console(data: &[u8]) -> String {
    use std::io::{Read, Write};
    let (_, addr, token) = live_console();
    let mut request = Vec::with_capacity(data.len());
    let mut rest = data;
    while let Some(i) = rest.windows(5).position(|w| w == b"TOKEN") {
        request.extend_from_slice(&rest[..i]);
        request.extend_from_slice(token.as_bytes());
        rest = &rest[i + 5..];
    }
    request.extend_from_slice(rest);
    let mut stream = std::net::TcpStream::connect(addr.as_str())
        .unwrap_or_else(|e| panic!("the console stopped answering: {e}"));
    // Loopback answers within milliseconds; a request the server waits on ends here.
    let timeout = Some(std::time::Duration::from_millis(250));
    let _ = stream.set_read_timeout(timeout);
    let _ = stream.set_write_timeout(timeout);
    let _ = stream.write_all(&request);
    let _ = stream.shutdown(std::net::Shutdown::Write);
    // The status line only (an event stream never ends).
    let mut line = Vec::new();
    let mut byte = [0u8; 1];
    while line.len() < 64 && !line.ends_with(b"\r\n") {
        match stream.read(&mut byte) {
            Ok(1) => line.push(byte[0]),
            _ => break,
        }
    }
    let status = String::from_utf8_lossy(&line);
    match status.split_whitespace().nth(1) {
        Some(code) if status.starts_with("HTTP/") => format!("status {code}"),
        _ => "no answer".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_target_has_a_seed_corpus_that_runs() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("corpus");
        for t in TARGETS {
            let dir = root.join(t.name);
            let seeds: Vec<_> = std::fs::read_dir(&dir)
                .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
                .map(|e| e.unwrap().path())
                .collect();
            assert!(!seeds.is_empty(), "{}: no seeds", t.name);
        }
        assert!(find("rig").is_some() && find("nothing").is_none());
    }
}
