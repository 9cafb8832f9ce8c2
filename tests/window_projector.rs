//! The window projector under Xvfb (docs/design.md §11): slides on screen pixel for pixel, errors
//! naming the projector, a window destroyed or killed from outside, the X server gone, a
//! capture whose projector window is killed mid-sequence, and the sync self-test through the
//! capture engine with a camera that sees the screen.
//!
//! winit opens one X display per process, so every test runs in a child process of this
//! test binary with its own Xvfb (DISPLAY set for the child only). Needs `Xvfb`, `xwd`
//! (x11-apps) and `xdotool`.
#![cfg(feature = "window")]

use hexcal::capture::{CaptureError, Session};
use hexcal::dataset::{CameraEntry, Dataset, DatasetInfo, ProjectorEntry, StackReader};
use hexcal::pattern::{ProjectorResponse, ProjectorSetup, Sequence};
use hexcal::rig::file::RigFile;
use hexcal::rig::fixture::{tiny, SimDevice, SimRig};
use hexcal::rig::window::WindowProjector;
use hexcal::rig::{CaptureTiming, RigDevices};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use {
    hexcal::images::Pixels,
    hexcal::rig::{Camera, DeviceError, Projector, Slide},
};

#[path = "support/xvfb.rs"]
mod xvfb;
use xvfb::Xvfb;

/// Set in a child process: the X display its test runs on.
const CHILD_DISPLAY: &str = "HEXCAL_WINDOW_TEST_DISPLAY";
/// Set in a child process: the pid of its Xvfb.
const CHILD_XVFB: &str = "HEXCAL_WINDOW_TEST_XVFB";

/// Run test `name`'s `body` in a child process of this binary on its own Xvfb of
/// `width` × `height`; in that child, just run `body`.
fn isolated(name: &str, (width, height): (u32, u32), body: impl FnOnce()) {
    if std::env::var_os(CHILD_DISPLAY).is_some() {
        body();
        return;
    }
    let x = Xvfb::start(width, height);
    let out = Command::new(std::env::current_exe().unwrap())
        .args([name, "--exact", "--nocapture", "--test-threads=1"])
        .env("DISPLAY", &x.display)
        .env(CHILD_DISPLAY, &x.display)
        .env(CHILD_XVFB, x.pid().to_string())
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "child test {name} failed:\n{text}");
    // The child really ran this one test.
    assert!(text.contains("1 passed"), "child test {name}:\n{text}");
}

fn display() -> String {
    std::env::var(CHILD_DISPLAY).unwrap()
}

/// Pixels of the screen that differ from `expect` (grey levels), and the first of them.
fn mismatches(expect: &[u8]) -> (usize, Option<(usize, u32, u8)>) {
    let (_, _, px) = xvfb::screenshot(&display());
    assert_eq!(px.len(), expect.len());
    let mut first = None;
    let n = px
        .iter()
        .zip(expect)
        .enumerate()
        .filter(|(_, (&p, &e))| p != u32::from(e) * 0x0001_0101)
        .inspect(|&(i, (&p, &e))| {
            first.get_or_insert((i, p, e));
        })
        .count();
    (n, first)
}

fn sequence(width: u32, height: u32, response: ProjectorResponse) -> Sequence {
    Sequence::default_for(&[ProjectorSetup {
        width,
        height,
        response,
    }])
    .unwrap()
}

/// The projector's X window id (its title is "hexcal projector NAME").
fn window_id(name: &str) -> String {
    let out = Command::new("xdotool")
        .args(["search", "--name", &format!("^hexcal projector {name}$")])
        .env("DISPLAY", display())
        .output()
        .expect("xdotool");
    let ids = String::from_utf8_lossy(&out.stdout).trim().to_string();
    assert_eq!(ids.lines().count(), 1, "one window named {name}: {ids:?}");
    ids
}

/// Run `xdotool ACTION ID` and wait until the server no longer has the window.
fn xdotool_on_window(action: &str, id: &str) {
    let ok = Command::new("xdotool")
        .args([action, id])
        .env("DISPLAY", display())
        .status()
        .unwrap()
        .success();
    assert!(ok, "xdotool {action} {id}");
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let exists = Command::new("xwininfo")
            .args(["-id", id, "-display", &display()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .unwrap()
            .success();
        if !exists {
            return;
        }
        assert!(Instant::now() < deadline, "window {id} still there");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn assert_gone(r: Result<(), DeviceError>, name: &str, why: &str) {
    match r {
        Err(e @ DeviceError::Gone { .. }) => {
            assert_eq!(e.device(), name);
            assert!(e.to_string().contains(why), "{e}");
        }
        other => panic!("expected {name} gone ({why}), got {other:?}"),
    }
}

#[test]
fn slides_on_screen_match_the_patterns_pixel_for_pixel() {
    isolated(
        "slides_on_screen_match_the_patterns_pixel_for_pixel",
        (1280, 800),
        || {
            // Uncorrected gamma (levels as computed) and linearised (through the inverse
            // gamma table): the window must show exactly the levels `pattern_image` gives.
            for response in [
                ProjectorResponse::Gamma { gamma: 2.2 },
                ProjectorResponse::Linearised { gamma: 2.2 },
            ] {
                let seq = sequence(1280, 800, response);
                let mut p = WindowProjector::open("front", "screen", 1280, 800).unwrap();
                assert_eq!(p.resolution(), (1280, 800));
                p.prepare(&seq, 0).unwrap();
                let n = seq.frame_count();
                let slides = [
                    Slide::White,
                    Slide::Pattern(0),
                    Slide::Pattern(1),
                    Slide::Black,
                    Slide::Pattern(n / 2 + 3),
                    Slide::Pattern(n - 1),
                    Slide::Level(128),
                ];
                for slide in slides {
                    p.show(slide).unwrap();
                    let expect = match slide {
                        Slide::Black => vec![0; 1280 * 800],
                        Slide::White => vec![255; 1280 * 800],
                        Slide::Pattern(k) => seq.pattern_image(0, k).into_raw(),
                        // A flat level goes through the inverse-gamma table as patterns do.
                        Slide::Level(l) => vec![
                            match response {
                                ProjectorResponse::Linearised { gamma } => {
                                    hexcal::pattern::inverse_gamma_lut(gamma)[usize::from(l)]
                                }
                                _ => l,
                            };
                            1280 * 800
                        ],
                    };
                    let (bad, first) = mismatches(&expect);
                    assert_eq!(
                        bad, 0,
                        "{response:?} {slide:?}: first (index, screen, grey) {first:?}"
                    );
                }
                // The last pattern is not what an earlier one looked like: the comparison
                // can tell slides apart.
                let (bad, _) = mismatches(&seq.pattern_image(0, 0).into_raw());
                assert!(bad > 1000, "pattern {} looks like pattern 0", n - 1);
                // A pattern beyond the sequence is refused, naming the projector.
                let e = p.show(Slide::Pattern(n)).unwrap_err();
                assert!(e.to_string().starts_with("front: sequence:"), "{e}");
                drop(p);
                // Dropping the projector removed its window: the last slide is gone.
                let (bad, _) = mismatches(&seq.pattern_image(0, n - 1).into_raw());
                assert!(bad > 1000, "window still shown after drop");
            }
        },
    );
}

#[test]
fn a_missing_monitor_or_a_wrong_size_names_the_projector() {
    isolated(
        "a_missing_monitor_or_a_wrong_size_names_the_projector",
        (1280, 800),
        || {
            let e = WindowProjector::open("left", "HDMI-9", 1280, 800)
                .err()
                .unwrap();
            assert_eq!(
                e.to_string(),
                format!(
                    "left: monitor: no monitor \"HDMI-9\" on X display {}; monitors: screen \
                     (1280×800 at 0,0)",
                    display()
                )
            );
            let e = WindowProjector::open("left", "screen", 1920, 1080)
                .err()
                .unwrap();
            assert_eq!(
                e.to_string(),
                "left: width, height: the projector is 1920×1080 but monitor screen is 1280×800"
            );
            // Through a rig file: the capture's device opening names it too.
            let side = rig(Some((1920, 1080))).edit("p1", |p| SimDevice {
                name: "side".into(),
                ..p
            });
            let rig = RigFile::parse(&side.toml(), "wrong.toml").unwrap();
            let e = hexcal::rig::open(&rig).err().unwrap();
            assert_eq!(
                e.to_string(),
                "projector side: width, height: the projector is 1920×1080 but monitor screen \
                 is 1280×800"
            );
            // A sequence code of another size is refused by prepare.
            let mut p = WindowProjector::open("left", "screen", 1280, 800).unwrap();
            let e = p
                .prepare(&sequence(1920, 1080, ProjectorResponse::Linear), 0)
                .unwrap_err();
            assert!(
                e.to_string()
                    .starts_with("left: sequence: code 0 is 1920×1080"),
                "{e}"
            );
        },
    );
}

#[test]
fn a_window_destroyed_by_another_client_is_gone() {
    isolated(
        "a_window_destroyed_by_another_client_is_gone",
        (640, 480),
        || {
            let mut p = WindowProjector::open("front", "screen", 640, 480).unwrap();
            p.show(Slide::White).unwrap();
            xdotool_on_window("windowclose", &window_id("front"));
            assert_gone(p.show(Slide::Black), "front", "destroyed");
            assert_gone(p.show(Slide::White), "front", "destroyed");
        },
    );
}

#[test]
fn a_killed_window_client_is_gone() {
    isolated("a_killed_window_client_is_gone", (640, 480), || {
        let mut p = WindowProjector::open("front", "screen", 640, 480).unwrap();
        p.show(Slide::White).unwrap();
        // XKillClient: the server closes this process's X connection.
        xdotool_on_window("windowkill", &window_id("front"));
        assert_gone(p.show(Slide::Black), "front", "X connection closed");
        assert_gone(p.show(Slide::White), "front", "X connection closed");
        // No new window on a lost display, and the error says why.
        let e = WindowProjector::open("back", "screen", 640, 480)
            .err()
            .unwrap();
        // Whether the display thread or winit notices the closed connection first, the
        // error names it.
        let e = e.to_string();
        assert!(
            e.starts_with("back")
                && (e.contains("X connection closed") || e.contains("X11 connection error")),
            "{e}"
        );
    });
}

#[test]
fn a_vanished_x_server_is_gone() {
    isolated("a_vanished_x_server_is_gone", (640, 480), || {
        let mut p = WindowProjector::open("front", "screen", 640, 480).unwrap();
        p.show(Slide::White).unwrap();
        let pid = std::env::var(CHILD_XVFB).unwrap();
        assert!(Command::new("kill").arg(&pid).status().unwrap().success());
        let socket = format!("/tmp/.X11-unix/X{}", &display()[1..]);
        let deadline = Instant::now() + Duration::from_secs(10);
        while Path::new(&socket).exists() {
            assert!(Instant::now() < deadline, "Xvfb still running");
            std::thread::sleep(Duration::from_millis(20));
        }
        assert_gone(p.show(Slide::Black), "front", "X connection closed");
    });
}

fn signal_xvfb(signal: &str) {
    let pid = std::env::var(CHILD_XVFB).unwrap();
    assert!(Command::new("kill")
        .args([signal, &pid])
        .status()
        .unwrap()
        .success());
}

#[test]
fn show_returns_once_the_server_has_drawn_the_slide() {
    isolated(
        "show_returns_once_the_server_has_drawn_the_slide",
        (640, 480),
        || {
            let mut p = WindowProjector::open("front", "screen", 640, 480).unwrap();
            p.show(Slide::White).unwrap();
            // While the server is stopped nothing can be drawn: show must wait for it.
            signal_xvfb("-STOP");
            std::thread::scope(|scope| {
                let shown = scope.spawn(|| p.show(Slide::Black));
                std::thread::sleep(Duration::from_millis(300));
                let waited = !shown.is_finished();
                signal_xvfb("-CONT");
                let r = shown.join().unwrap();
                assert!(
                    waited,
                    "show returned while the X server was stopped: {r:?}"
                );
                r.unwrap();
            });
            assert_eq!(mismatches(&[0; 640 * 480]).0, 0);
            // A server that stays stopped: show gives up, naming the projector.
            signal_xvfb("-STOP");
            let e = p.show(Slide::White).unwrap_err();
            signal_xvfb("-CONT");
            assert!(
                matches!(&e, DeviceError::Failed { device, reason }
                    if device == "front" && reason.ends_with("no answer within 5s")),
                "{e}"
            );
            // Running again, it shows the next slide.
            p.show(Slide::White).unwrap();
            assert_eq!(mismatches(&[255; 640 * 480]).0, 0);
        },
    );
}

/// The tiny rig in two poses (two simulated cameras facing each other across the board, p0
/// simulated), its p1 a window of `size` on monitor `screen`, or simulated when none.
fn rig(p1_window: Option<(u32, u32)>) -> SimRig {
    let rig = tiny().named("tiny-window").with("poses.count = 2");
    match p1_window {
        Some(size) => rig.edit("p1", |p| {
            p.sized(size).driver("window").with("monitor = \"screen\"")
        }),
        None => rig,
    }
}

/// Projector p1 of the capture: the simulated projector lights the simulated board, the
/// window shows the same slide on the X display.
struct Mirrored {
    sim: Box<dyn Projector>,
    window: WindowProjector,
}

impl Projector for Mirrored {
    fn name(&self) -> &str {
        self.window.name()
    }
    fn resolution(&self) -> (u32, u32) {
        self.window.resolution()
    }
    fn prepare(&mut self, sequence: &Sequence, code: usize) -> Result<(), DeviceError> {
        self.window.prepare(sequence, code)?;
        self.sim.prepare(sequence, code)
    }
    fn show(&mut self, slide: Slide) -> Result<(), DeviceError> {
        self.window.show(slide)?;
        self.sim.show(slide)
    }
}

#[test]
fn a_capture_whose_projector_window_is_killed_keeps_the_poses_written() {
    isolated(
        "a_capture_whose_projector_window_is_killed_keeps_the_poses_written",
        (320, 200),
        || {
            // The simulated world needs every projector's truth: simulate p1 there and
            // drive its window beside it.
            let rig = rig(None).parse().unwrap();
            let opened = hexcal::rig::open(&rig).unwrap();
            let world = opened.world.clone().unwrap();
            let seq = opened.sequence.clone();
            let (cams, mut projs) = world.devices();
            let p1 = Mirrored {
                sim: Box::new(projs.pop().unwrap()),
                window: WindowProjector::open("p1", "screen", 320, 200).unwrap(),
            };
            let cameras: Vec<Box<dyn Camera>> =
                cams.into_iter().map(|c| Box::new(c) as _).collect();
            let projectors: Vec<Box<dyn Projector>> =
                vec![Box::new(projs.pop().unwrap()), Box::new(p1)];
            let timing = CaptureTiming {
                frame_timeout: Duration::from_millis(500),
                settle: Duration::ZERO,
                ..opened.devices.timing
            };
            let devices = RigDevices {
                cameras,
                configs: opened.devices.configs,
                projectors,
                trigger: None,
                timing,
            };
            let mut s = Session::start(devices, &seq).unwrap();
            let dir =
                std::env::temp_dir().join(format!("hexcal-window-capture-{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&dir);
            let data = Dataset::create_or_resume(&dir, info(&seq)).unwrap();

            // Pose 0 completes with the window showing every pattern.
            world.place(0);
            let mut w = data.pose_writer(0).unwrap();
            let mut front = Vec::new();
            let t = s
                .capture_pose(0, &mut |f| {
                    if f.camera == 0 {
                        front.push(pixels(&f.frame.pixels));
                    }
                    Ok(w.write(&f)?)
                })
                .unwrap();
            data.complete(&w.finish(&t).unwrap()).unwrap();
            assert_eq!(front.len(), seq.frame_count());

            // Pose 1: the window's client is killed once frame 5 is stored.
            world.place(1);
            let mut w = data.pose_writer(1).unwrap();
            let id = window_id("p1");
            let err = s
                .capture_pose(1, &mut |f| {
                    w.write(&f).map_err(|e| e.to_string())?;
                    if f.index == 5 && f.camera == 1 {
                        xdotool_on_window("windowkill", &id);
                    }
                    Ok(())
                })
                .unwrap_err();
            let text = err.to_string();
            match &err {
                CaptureError::Frame {
                    pose: 1,
                    frame: 6,
                    source: e @ DeviceError::Gone { .. },
                } => assert_eq!(e.device(), "p1", "{text}"),
                _ => panic!("expected p1 gone at pose 1, frame 6: {text}"),
            }
            assert!(
                text.starts_with("pose 1, frame 6: p1: device lost: the X connection closed"),
                "{text}"
            );
            drop(s);

            // The completed pose is intact: pose 0 only, its frames bit for bit.
            let again = Dataset::create_or_resume(&dir, info(&seq)).unwrap();
            assert_eq!(again.completed().unwrap(), vec![0]);
            let stack = StackReader::open(&again.stack_dir(0, "front")).unwrap();
            for (k, expect) in front.iter().enumerate() {
                let got: Vec<u16> = stack.frame(k).unwrap();
                assert_eq!(&got, expect, "pose 0, frame {k}");
            }
            let _ = std::fs::remove_dir_all(&dir);
        },
    );
}

fn pixels(p: &Pixels) -> Vec<u16> {
    match p {
        Pixels::Gray8(v) => v.iter().map(|&x| u16::from(x)).collect(),
        Pixels::Gray16(v) => v.clone(),
    }
}

fn info(seq: &Sequence) -> DatasetInfo {
    DatasetInfo {
        format: hexcal::dataset::FORMAT.into(),
        version: hexcal::dataset::VERSION,
        rig: "tiny-window".into(),
        board: "hex600".into(),
        sequence: seq.clone(),
        cameras: ["front", "back"]
            .map(|name| CameraEntry {
                name: name.into(),
                width: 320,
                height: 240,
                bits: 8,
                pixel_format: None,
            })
            .to_vec(),
        projectors: ["p0", "p1"]
            .map(|name| ProjectorEntry {
                name: name.into(),
                width: 320,
                height: 200,
            })
            .to_vec(),
    }
}

/// A camera that sees the X screen: each trigger takes a screenshot (`xwd`) as an 8-bit grey
/// frame, so what it sees is what the window projector has drawn at that moment.
struct ScreenCamera {
    frames: std::collections::VecDeque<hexcal::images::CameraFrame>,
    counter: u64,
}

impl Camera for ScreenCamera {
    fn name(&self) -> &str {
        "screen"
    }
    fn configure(&mut self, _: &hexcal::rig::CameraConfig) -> Result<(), DeviceError> {
        Ok(())
    }
    fn set_exposure_gain(&mut self, _: f64, _: f64) -> Result<(), DeviceError> {
        Ok(())
    }
    fn start(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }
    fn trigger(&mut self) -> Result<(), DeviceError> {
        let (width, height, px) = xvfb::screenshot(&display());
        self.counter += 1;
        self.frames.push_back(hexcal::images::CameraFrame {
            width,
            height,
            bits: 8,
            pixels: Pixels::Gray8(px.iter().map(|&p| (p & 0xff) as u8).collect()),
            counter: self.counter,
            timestamp_ns: self.counter * 1_000_000,
            exposure_us: 1000.0,
        });
        Ok(())
    }
    fn next_frame(&mut self, _: Duration) -> Result<hexcal::images::CameraFrame, DeviceError> {
        self.frames.pop_front().ok_or_else(|| DeviceError::Failed {
            device: "screen".into(),
            reason: "no frame".into(),
        })
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }
}

#[test]
fn sync_through_the_window_projector_sees_every_slide_at_once() {
    // docs/design.md §11b: the sync test through the capture engine, the window projector
    // full screen on Xvfb and a camera that sees the screen. Its `show` returns once the
    // server has drawn the slide, so with no settle time every coded frame is seen at the
    // first wait (0 ms after show returned): nothing dropped, repeated or early.
    isolated(
        "sync_through_the_window_projector_sees_every_slide_at_once",
        (320, 200),
        || {
            use hexcal::check::sync::{check_sync, SyncPlan};
            let projector = WindowProjector::open("p", "screen", 320, 200).unwrap();
            let timing = CaptureTiming {
                settle: Duration::ZERO,
                latency: vec![Duration::ZERO],
                frame_timeout: Duration::from_secs(2),
                retries: 0,
                repeats: 1,
            };
            let devices = RigDevices {
                cameras: vec![Box::new(ScreenCamera {
                    frames: Default::default(),
                    counter: 0,
                })],
                configs: vec![hexcal::rig::CameraConfig {
                    width: 320,
                    height: 200,
                    bits: 8,
                    exposure_us: 1000.0,
                    gain_db: 0.0,
                    trigger: hexcal::rig::TriggerSource::Software,
                }],
                projectors: vec![Box::new(projector)],
                trigger: None,
                timing,
            };
            let seq = sequence(320, 200, ProjectorResponse::Linear);
            let mut s = Session::start(devices, &seq).unwrap();
            let period = Duration::from_millis(50);
            let plan = SyncPlan::new(s.timing(), period, false, Some(Duration::from_millis(90)));
            let report = check_sync(&mut s, &plan).unwrap();
            s.finish().unwrap();
            println!("{report}");
            let p = &report.pairs[0];
            assert!(p.seen, "{report}");
            // Seen at the first wait (0 ms, as timed: well under the next wait, 10 ms).
            assert!(p.latency_ms < 5.0, "{report}");
            assert!(p.dropped.is_empty() && p.repeated.is_empty(), "{report}");
            assert!(p.late_at_run.is_empty(), "{report}");
            assert!(report.passed() && report.safe_settle_ms <= 1.0, "{report}");
        },
    );
}
