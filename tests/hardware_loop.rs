//! The whole hardware path in one process (docs/design.md §11, issue 6): the real capture engine
//! drives a GigE Vision camera (Aravis, opened by address, on the in-process loopback camera
//! that serves the simulator's rendered stack of the rig's board pose), the serial trigger
//! controller (the host driver on one end of a pty pair, the firmware model on the other; the
//! line pulse of the camera's line reaches the loopback camera's trigger input) and a
//! projector (with `--features window` the window projector on a private Xvfb, whose screen
//! is captured at every trigger of the first pose; otherwise the simulated projector), and
//! writes a dataset. The stacks then decode to the renderer's (u, v) within the decoder's
//! predicted noise, the frames' counters and timestamps run in order, and at every trigger
//! the projector showed pattern k while the camera was about to expose frame k.
//!
//! Fault: a controller that starts answering garbage mid-sequence stops the capture with an
//! error naming the port, pose and frame; the pose written before reads back intact.
#![cfg(feature = "loopback")]

use hexcal::dataset::{CameraEntry, Dataset, DatasetInfo, ProjectorEntry, StackReader};
use hexcal::pattern::Sequence;
use hexcal::phase::files::{decode_dir, DecodeSummary};
use hexcal::rig::aravis::{AravisCamera, LoopbackCamera, LOOPBACK_ADDRESS};
use hexcal::rig::file::RigFile;
use hexcal::rig::fixture::{SimDevice, SimRig};
use hexcal::rig::sim::SimWorld;
use hexcal::rig::trigger::{TriggerController, TriggerTiming};
use hexcal::sim::stack::StackRenderer;
use hexcal_firmware_protocol::LineConfig;
use hexcal_simulator::firmware::{ModelConfig, SimulatedController};
use serialport::{SerialPort, TTYPort};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use {
    hexcal::capture::{CaptureError, Session},
    hexcal::dataset::Timeline,
    hexcal::rig::{CaptureTiming, RigDevices},
};
use {
    hexcal::images::Pixels,
    hexcal::rig::{Camera, CameraConfig, DeviceError, Projector, Slide, Trigger, TriggerSource},
};

/// One loopback camera at a time: it listens on 127.0.0.1's GVCP port.
static LOOPBACK: Mutex<()> = Mutex::new(());

fn exclusive() -> MutexGuard<'static, ()> {
    LOOPBACK.lock().unwrap_or_else(|e| e.into_inner())
}

/// Camera and projector (and screen) size.
const W: u32 = 640;
const H: u32 = 400;
/// The camera's trigger line on the controller.
const LINE: u8 = 0;
const WAIT: Duration = Duration::from_secs(2);

/// The rig's ground truth: the camera and projector models and poses the simulator renders
/// the camera's view from (one linear projector: the default 18-frame sequence).
fn rig() -> RigFile {
    let camera = SimDevice::new("cam", (W, H), [1500.0, 1500.0, 319.5, 199.5]);
    let projector =
        SimDevice::new("proj", (W, H), [800.0, 800.0, 320.0, 360.0]).at([300.0, 50.0, 1300.0]);
    SimRig::new("hardware-loop")
        .table("[timing]\nframe_period_ms = 20.0")
        .table("[poses]\ncount = 2\nyaw_deg = 15.0\ntilt_deg = 8.0\nshift_mm = 20.0\nseed = 11")
        .camera(camera.with("exposure_ms = 5.0"))
        .projector(projector.with("gamma = 1.0"))
        .parse()
        .unwrap()
}

/// The simulated world, its sequence, and per pose the renderer and the frames it gives.
struct Truth {
    sequence: Sequence,
    renderers: Vec<StackRenderer>,
    frames: Vec<Vec<Pixels>>,
}

fn truth(poses: usize) -> Truth {
    let rig = rig();
    let world = SimWorld::new(&rig, rig.board().unwrap()).unwrap();
    let sequence = rig.sequence().unwrap();
    let renderers: Vec<StackRenderer> = (0..poses)
        .map(|p| world.stack_renderer(0, p, &sequence).unwrap())
        .collect();
    let frames = renderers
        .iter()
        .map(|r| {
            (0..sequence.frame_count())
                .map(|k| Pixels::Gray8(r.frame(k).data.iter().map(|&v| v as u8).collect()))
                .collect()
        })
        .collect();
    Truth {
        sequence,
        renderers,
        frames,
    }
}

/// The firmware end of the pty; while `garbage` is set, every byte the firmware sends but
/// the frame delimiters (0) is replaced by noise (a controller answering garbage).
struct Garbling {
    port: TTYPort,
    garbage: Arc<AtomicBool>,
    state: u64,
}

impl Read for Garbling {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        self.port.read(buf)
    }
}

impl Write for Garbling {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        if !self.garbage.load(Ordering::SeqCst) {
            return self.port.write(buf);
        }
        let noise: Vec<u8> = buf
            .iter()
            .map(|&b| {
                if b == 0 {
                    // Frames stay delimited, so the driver sees garbled frames.
                    return 0;
                }
                // xorshift64
                self.state ^= self.state << 13;
                self.state ^= self.state >> 7;
                self.state ^= self.state << 17;
                (self.state >> 24) as u8 | 1
            })
            .collect();
        self.port.write_all(&noise)?;
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.port.flush()
    }
}

/// What the wiring saw at one line pulse, just before the camera got it.
#[derive(Clone, Debug, PartialEq)]
struct Pulse {
    /// The controller's frame index (restarts at every arm).
    frame: u32,
    /// What the projector showed.
    slide: Slide,
    /// Frames the loopback camera had served.
    served: usize,
    /// Screen pixels that differ from the pattern of this frame (window projector only).
    screen_mismatches: Option<usize>,
}

/// Looks at the rig at a pulse (the projector's slide, the screen) for the record.
type Probe = Box<dyn FnMut(u32) -> Pulse + Send>;

/// The trigger controller with its camera line wired to the loopback camera's line input:
/// a frame's pulse reaches the camera when the controller reports it done.
struct Wired {
    controller: TriggerController,
    _firmware: SimulatedController,
    camera: Arc<Mutex<LoopbackCamera>>,
    probe: Probe,
    pulses: Arc<Mutex<Vec<Pulse>>>,
}

impl Wired {
    /// The firmware model on a pty pair (its output garbled while `garbage` is set), the
    /// host driver on the other end, line [`LINE`] configured.
    fn new(
        camera: Arc<Mutex<LoopbackCamera>>,
        garbage: Arc<AtomicBool>,
        probe: Probe,
    ) -> (Wired, Arc<Mutex<Vec<Pulse>>>) {
        let (mut master, slave) = TTYPort::pair().expect("a pty pair");
        master.set_timeout(Duration::from_millis(1)).unwrap();
        let firmware = SimulatedController::spawn(
            Garbling {
                port: master,
                garbage,
                state: 0x9E37_79B9_7F4A_7C15,
            },
            ModelConfig::default(),
        );
        let mut controller =
            TriggerController::from_port(Box::new(slave), TriggerTiming::default()).unwrap();
        controller
            .configure(&[LineConfig {
                line: LINE,
                delay_us: 0,
                pulse_us: 100,
            }])
            .unwrap();
        let pulses = Arc::new(Mutex::new(Vec::new()));
        let wired = Wired {
            controller,
            _firmware: firmware,
            camera,
            probe,
            pulses: Arc::clone(&pulses),
        };
        (wired, pulses)
    }
}

impl Trigger for Wired {
    fn name(&self) -> &str {
        self.controller.port_name()
    }

    fn arm(&mut self, frames: u32) -> Result<(), DeviceError> {
        Trigger::arm(&mut self.controller, frames)
    }

    fn fire(&mut self) -> Result<u32, DeviceError> {
        let frame = Trigger::fire(&mut self.controller)?;
        let port = self.controller.port_name().to_string();
        let done = self
            .controller
            .wait_frame_done(WAIT)
            .map_err(|e| DeviceError::Failed {
                device: port.clone(),
                reason: e.to_string(),
            })?;
        if done.frame != frame {
            return Err(DeviceError::Failed {
                device: port,
                reason: format!("frame {} done after firing frame {frame}", done.frame),
            });
        }
        let pulse = (self.probe)(frame);
        self.pulses.lock().unwrap().push(pulse);
        self.camera.lock().unwrap().pulse_line(WAIT)?;
        Ok(frame)
    }

    fn disarm(&mut self) -> Result<(), DeviceError> {
        Trigger::disarm(&mut self.controller)
    }
}

/// A projector whose current slide can be watched.
struct Watched {
    inner: Box<dyn Projector>,
    slide: Arc<Mutex<Slide>>,
}

impl Projector for Watched {
    fn name(&self) -> &str {
        self.inner.name()
    }

    fn resolution(&self) -> (u32, u32) {
        self.inner.resolution()
    }

    fn prepare(&mut self, sequence: &Sequence, code: usize) -> Result<(), DeviceError> {
        self.inner.prepare(sequence, code)
    }

    fn show(&mut self, slide: Slide) -> Result<(), DeviceError> {
        self.inner.show(slide)?;
        *self.slide.lock().unwrap() = slide;
        Ok(())
    }
}

/// The simulated projector of the truth rig.
fn simulated_projector() -> Box<dyn Projector> {
    let rig = rig();
    let world = Arc::new(SimWorld::new(&rig, rig.board().unwrap()).unwrap());
    let (_, mut projectors) = world.devices();
    Box::new(projectors.remove(0))
}

/// The rig's devices started in a session over a fresh dataset.
struct Loop {
    session: Session,
    /// The trigger controller's port (the pty's slave path).
    port: String,
    loopback: Arc<Mutex<LoopbackCamera>>,
    pulses: Arc<Mutex<Vec<Pulse>>>,
    data: Dataset,
}

/// Serve `frames` (every pose's in turn) on the loopback camera; wire the controller to it;
/// start a session with `projector`, whose slide `probe` reads at every pulse.
fn start(
    truth: &Truth,
    out: &Path,
    projector: Box<dyn Projector>,
    garbage: Arc<AtomicBool>,
    mut look: impl FnMut(u32, Slide, usize) -> Pulse + Send + 'static,
) -> Loop {
    let served: Vec<Pixels> = truth.frames.iter().flatten().cloned().collect();
    let loopback = Arc::new(Mutex::new(
        LoopbackCamera::start("HEXLOOP", served).expect("loopback camera starts"),
    ));
    let camera = AravisCamera::open("cam", LOOPBACK_ADDRESS).expect("opens by address");
    let slide = Arc::new(Mutex::new(Slide::Black));
    let watched = Watched {
        inner: projector,
        slide: Arc::clone(&slide),
    };
    let camera_side = Arc::clone(&loopback);
    let probe: Probe = Box::new(move |frame| {
        let shown = *slide.lock().unwrap();
        let served = camera_side.lock().unwrap().served();
        look(frame, shown, served)
    });
    let (wired, pulses) = Wired::new(Arc::clone(&loopback), garbage, probe);
    let port = wired.controller.port_name().to_string();
    let config = CameraConfig {
        width: W,
        height: H,
        bits: 8,
        exposure_us: 5000.0,
        gain_db: 0.0,
        trigger: TriggerSource::Line,
    };
    let timing = CaptureTiming {
        settle: Duration::from_millis(2),
        latency: vec![Duration::ZERO],
        frame_timeout: WAIT,
        retries: 2,
        repeats: 1,
    };
    let session = Session::start(
        RigDevices {
            cameras: vec![Box::new(camera) as Box<dyn Camera>],
            configs: vec![config],
            projectors: vec![Box::new(watched) as Box<dyn Projector>],
            trigger: Some(Box::new(wired)),
            timing,
        },
        &truth.sequence,
    )
    .expect("session starts");
    let info = DatasetInfo {
        format: hexcal::dataset::FORMAT.into(),
        version: hexcal::dataset::VERSION,
        rig: "hardware-loop".into(),
        board: "hex600".into(),
        sequence: truth.sequence.clone(),
        cameras: vec![CameraEntry {
            name: "cam".into(),
            width: W,
            height: H,
            bits: 8,
            pixel_format: None,
        }],
        projectors: vec![ProjectorEntry {
            name: "proj".into(),
            width: W,
            height: H,
        }],
    };
    let data = Dataset::create_or_resume(out, info).unwrap();
    Loop {
        session,
        port,
        loopback,
        pulses,
        data,
    }
}

impl Loop {
    /// Capture pose `pose` into the dataset (complete only when every frame arrived).
    fn capture(&mut self, pose: usize) -> Result<Timeline, CaptureError> {
        let mut writer = self.data.pose_writer(pose).unwrap();
        let timeline = self
            .session
            .capture_pose(pose, &mut |f| Ok(writer.write(&f)?))?;
        self.data
            .complete(&writer.finish(&timeline).unwrap())
            .unwrap();
        Ok(timeline)
    }
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("hexcal-hwloop-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// Every frame of `pose` in the dataset is, sample for sample, the frame served.
fn assert_reads_back(data: &Dataset, pose: usize, served: &[Pixels]) {
    let stack = StackReader::open(&data.stack_dir(pose, "cam")).unwrap();
    for (k, expect) in served.iter().enumerate() {
        let Pixels::Gray8(expect) = expect else {
            unreachable!("8-bit frames served")
        };
        let got: Vec<u8> = stack.frame(k).unwrap().iter().map(|&v| v as u8).collect();
        assert!(
            &got == expect,
            "pose {pose}, frame {k} differs from the frame served"
        );
    }
}

/// Decode pose `pose`'s stack folder and compare its (u, v) on valid interior pixels with
/// the renderer's truth (interior: uniform albedo within ±3 px, where the PSF does not mix
/// the phases of differently bright neighbours, which is optics, not decoding).
///
/// Per pixel the decoder's noise model predicts σ_φ = √(2/N)·σ_I(A)/B (docs/design.md §6) and
/// σ_u = W·σ_φ/(2π·√Σn²) (σ_v likewise). An error beyond 6 of those is gross (a wrong fringe
/// order): none where σ_φ ≤ 0.10 rad (§6: ≈ 5·10⁻⁷ per pixel there); among the noisier
/// valid pixels (validity B ≥ 5σ_I allows σ_φ 0.16 with N = 3) no more than a rate of
/// 5·10⁻³ per pixel gives with probability 0.999 (§6: 10⁻³ at σ_φ = 0.15, rising about
/// fivefold per 0.01 rad). The others' RMS is within 1.2 × the decoder's predicted σ_u, σ_v
/// of the run.
fn assert_decodes_to_truth(data: &Dataset, pose: usize, truth: &StackRenderer) {
    let decoded = decode_dir(&data.stack_dir(pose, "cam")).expect("the stack decodes");
    let summary = DecodeSummary::new(&decoded);
    let maps = &decoded.projectors[0];
    let noise = summary.projectors[0].noise;
    let sequence = &data.info.sequence;
    let steps = f64::from(sequence.steps());
    let norm = |d| {
        let sum: u32 = sequence.counts(d).iter().map(|n| n * n).sum();
        2.0 * std::f64::consts::PI * f64::from(sum).sqrt()
    };
    let (norm_u, norm_v) = (
        norm(hexcal::pattern::Direction::Columns),
        norm(hexcal::pattern::Direction::Rows),
    );
    let t = truth.truth(0);
    let w = W as usize;
    let (mut su, mut sv, mut n) = (0.0, 0.0, 0usize);
    let (mut noisy, mut gross_noisy) = (0usize, 0usize);
    for (i, &ok) in maps.valid.as_slice().iter().enumerate() {
        if !(ok && t.lit(i) && truth.uniform_albedo(i, 3)) {
            continue;
        }
        let b = f64::from(maps.modulation.as_raw()[i]);
        let level = f64::from(decoded.ambient.as_raw()[i]) + b;
        let sigma_phi = (2.0 / steps).sqrt() * decoded.noise.sigma(level) / b;
        let (sigma_u, sigma_v) = (
            f64::from(W) * sigma_phi / norm_u,
            f64::from(H) * sigma_phi / norm_v,
        );
        let eu = f64::from(maps.u.as_raw()[i] - t.u(i));
        let ev = f64::from(maps.v.as_raw()[i] - t.v(i));
        let gross = eu.abs() > 6.0 * sigma_u || ev.abs() > 6.0 * sigma_v;
        if sigma_phi > 0.10 {
            noisy += 1;
            if gross {
                gross_noisy += 1;
                eprintln!(
                    "pose {pose}, pixel ({}, {}): gross error ({eu:.2}, {ev:.2}) px at \
                     B {b:.1} DN, σ_φ {sigma_phi:.3} rad",
                    i % w,
                    i / w
                );
                continue;
            }
        }
        assert!(
            !gross,
            "pose {pose}, pixel ({}, {}): error ({eu:.3}, {ev:.3}) px beyond 6 × predicted \
             ({sigma_u:.3}, {sigma_v:.3}) at σ_φ {sigma_phi:.3} rad",
            i % w,
            i / w
        );
        su += eu * eu;
        sv += ev * ev;
        n += 1;
    }
    let (rms_u, rms_v) = ((su / n as f64).sqrt(), (sv / n as f64).sqrt());
    eprintln!(
        "pose {pose}: {n} interior pixels decoded ({:.1} % of all valid): u RMS {rms_u:.3} px \
         (predicted σ_u {:.3}), v RMS {rms_v:.3} px (σ_v {:.3}); {gross_noisy} gross of \
         {noisy} at σ_φ > 0.10 rad",
        100.0 * summary.projectors[0].valid_fraction,
        noise.sigma_u,
        noise.sigma_v
    );
    assert!(n > 1000, "pose {pose}: only {n} interior pixels decoded");
    let allowed = poisson_quantile(5e-3 * noisy as f64, 1e-3);
    assert!(
        gross_noisy <= allowed,
        "pose {pose}: {gross_noisy} gross errors in {noisy} noisy pixels (at most {allowed})"
    );
    assert!(
        rms_u <= 1.2 * noise.sigma_u && rms_v <= 1.2 * noise.sigma_v,
        "pose {pose}: RMS ({rms_u}, {rms_v}) beyond 1.2 × predicted ({}, {})",
        noise.sigma_u,
        noise.sigma_v
    );
}

/// The smallest k with P(X > k) < `tail` for X ~ Poisson(`mean`).
fn poisson_quantile(mean: f64, tail: f64) -> usize {
    let (mut k, mut term) = (0, (-mean).exp());
    let mut cdf = term;
    while 1.0 - cdf >= tail {
        k += 1;
        term *= mean / k as f64;
        cdf += term;
    }
    k
}

/// Counters consecutive and timestamps increasing over the stacks of `poses`, in order.
fn assert_frames_in_order(data: &Dataset, poses: usize) {
    let mut last: Option<(u64, u64)> = None;
    for pose in 0..poses {
        let stack = StackReader::open(&data.stack_dir(pose, "cam")).unwrap();
        for f in &stack.info.frames {
            assert!((f.exposure_us - 5000.0).abs() < 1.0, "{f:?}");
            if let Some((counter, time)) = last {
                assert_eq!(f.counter, counter + 1, "pose {pose}, frame {}", f.index);
                assert!(f.timestamp_ns > time, "pose {pose}, frame {}", f.index);
            }
            last = Some((f.counter, f.timestamp_ns));
        }
    }
}

const LOOP_TEST: &str = "two_poses_through_gige_vision_a_pty_controller_and_a_projector_decode";

#[test]
fn two_poses_through_gige_vision_a_pty_controller_and_a_projector_decode() {
    let _one = exclusive();
    on_display(LOOP_TEST, || {
        const POSES: usize = 2;
        let truth = truth(POSES);
        let n = truth.sequence.frame_count();
        let out = scratch("loop");
        let (projector, mut screen) = projector(&truth.sequence);
        let mut rig = start(
            &truth,
            &out,
            projector,
            Arc::new(AtomicBool::new(false)),
            move |frame, slide, served| Pulse {
                frame,
                slide,
                served,
                screen_mismatches: screen(served, frame),
            },
        );
        let mut timelines = Vec::new();
        for pose in 0..POSES {
            let t = rig.capture(pose).expect("pose captured");
            eprintln!("pose {pose}: {}", t.summary(1));
            timelines.push(t);
        }
        eprintln!("timeline of pose 0 (ms: shown, triggered, collected):");
        for f in &timelines[0].frames {
            eprintln!(
                "  frame {:2}: {:7.2} {:7.2} {:7.2}",
                f.index,
                1e3 * f.shown.as_secs_f64(),
                1e3 * f.triggered.as_secs_f64(),
                1e3 * f.collected.as_secs_f64()
            );
        }
        rig.session.finish().expect("session ends cleanly");
        for t in &timelines {
            assert_eq!(t.frames.len(), n);
            assert_eq!(t.dropped, 0);
            assert!(t.frames.iter().all(|f| f.retries == 0), "{t:?}");
        }
        // Lockstep, seen at every pulse: the projector showed pattern k (on screen, pixel
        // for pixel, with the window projector) and the camera was about to serve frame k
        // of that pose.
        let pulses = rig.pulses.lock().unwrap().clone();
        assert_eq!(pulses.len(), POSES * n);
        for (i, p) in pulses.iter().enumerate() {
            let k = i % n;
            assert_eq!(
                (p.frame as usize, p.slide, p.served),
                (k, Slide::Pattern(k), i),
                "pulse {i}"
            );
            assert!(
                p.screen_mismatches.is_none_or(|bad| bad == 0),
                "pulse {i}: {p:?}"
            );
        }
        #[cfg(feature = "window")]
        assert!(
            pulses
                .iter()
                .filter(|p| p.screen_mismatches.is_some())
                .count()
                == n,
            "the screen was captured at every pulse of pose 0"
        );
        let loopback = rig.loopback.lock().unwrap();
        assert_eq!((loopback.served(), loopback.mismatches()), (POSES * n, 0));
        drop(loopback);
        assert_eq!(
            rig.data.completed().unwrap(),
            (0..POSES).collect::<Vec<_>>()
        );
        assert_frames_in_order(&rig.data, POSES);
        for pose in 0..POSES {
            assert_reads_back(&rig.data, pose, &truth.frames[pose]);
            assert_decodes_to_truth(&rig.data, pose, &truth.renderers[pose]);
        }
        let _ = std::fs::remove_dir_all(&out);
    });
}

#[test]
fn a_controller_answering_garbage_names_port_pose_and_frame_and_keeps_earlier_poses() {
    let _one = exclusive();
    let truth = truth(2);
    let n = truth.sequence.frame_count();
    let out = scratch("garbage");
    let garbage = Arc::new(AtomicBool::new(false));
    // From frame 5 of pose 1 on, the controller's replies are noise.
    let switch = Arc::clone(&garbage);
    let mut rig = start(
        &truth,
        &out,
        simulated_projector(),
        Arc::clone(&garbage),
        move |frame, slide, served| {
            if served == n + 5 {
                switch.store(true, Ordering::SeqCst);
            }
            Pulse {
                frame,
                slide,
                served,
                screen_mismatches: None,
            }
        },
    );
    let port = rig.port.clone();
    rig.capture(0).expect("pose 0 before the fault");
    let err = rig.capture(1).expect_err("garbage from the controller");
    let text = err.to_string();
    eprintln!("{text}");
    assert!(
        matches!(
            &err,
            CaptureError::Frame { pose: 1, frame: 6, source } if source.device() == port
        ),
        "{text}"
    );
    assert!(
        text.starts_with(&format!("pose 1, frame 6: {port}: trigger controller: "))
            && text.contains("no reply to Fire after 3 attempts")
            && !text.contains("; 0 garbled"),
        "{text}"
    );
    garbage.store(false, Ordering::SeqCst);
    drop(rig.session);
    // Pose 0 is complete and reads back as served; pose 1 is not complete.
    let data = Dataset::open(&out).unwrap();
    assert_eq!(data.completed().unwrap(), vec![0]);
    assert!(data.pose(1).unwrap().is_none());
    assert_reads_back(&data, 0, &truth.frames[0]);
    let _ = std::fs::remove_dir_all(&out);
}

/// Screen pixels that differ from the pattern of frame k, at a pulse (`served` frames served
/// before it, controller frame k); `None` where the screen is not looked at.
type ScreenCheck = Box<dyn FnMut(usize, u32) -> Option<usize> + Send>;

/// Run `body` as it is: the simulated projector needs no display.
#[cfg(not(feature = "window"))]
fn on_display(_name: &str, body: impl FnOnce()) {
    body();
}

/// The simulated projector; no screen to look at.
#[cfg(not(feature = "window"))]
fn projector(_: &Sequence) -> (Box<dyn Projector>, ScreenCheck) {
    (simulated_projector(), Box::new(|_, _| None))
}

/// Set in the child process that runs a test on its own Xvfb: that display.
#[cfg(feature = "window")]
const CHILD_DISPLAY: &str = "HEXCAL_HWLOOP_DISPLAY";

#[cfg(feature = "window")]
#[path = "support/xvfb.rs"]
mod xvfb;

/// Run test `name` in a child process of this binary with `DISPLAY` on a private Xvfb (one
/// winit event loop per process, on the display it was started with); in the child, `body`.
#[cfg(feature = "window")]
fn on_display(name: &str, body: impl FnOnce()) {
    if std::env::var_os(CHILD_DISPLAY).is_some() {
        body();
        return;
    }
    let x = xvfb::Xvfb::start(W, H);
    let out = std::process::Command::new(std::env::current_exe().unwrap())
        .args([name, "--exact", "--nocapture", "--test-threads=1"])
        .env("DISPLAY", &x.display)
        .env(CHILD_DISPLAY, &x.display)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{text}");
    assert!(out.status.success(), "{name} on Xvfb {} failed", x.display);
    assert!(text.contains("1 passed"), "{name} did not run in the child");
}

/// The screen as grey levels; a pixel that is not grey counts as level 256.
#[cfg(feature = "window")]
fn screen_levels() -> Vec<u16> {
    let (width, height, px) = xvfb::screenshot(&std::env::var(CHILD_DISPLAY).unwrap());
    assert_eq!((width, height), (W, H), "screen size");
    px.iter()
        .map(|&p| {
            let [r, g, b] = [p >> 16, (p >> 8) & 0xff, p & 0xff];
            if r == g && g == b {
                r as u16
            } else {
                256
            }
        })
        .collect()
}

/// The window projector, full screen on the private Xvfb; the screen is compared with the
/// pattern at every pulse of the first pose.
#[cfg(feature = "window")]
fn projector(sequence: &Sequence) -> (Box<dyn Projector>, ScreenCheck) {
    let p = hexcal::rig::window::WindowProjector::open("proj", "screen", W, H)
        .expect("window projector on Xvfb");
    let sequence = sequence.clone();
    let n = sequence.frame_count();
    let check = move |served: usize, frame: u32| {
        (served < n).then(|| {
            let expect = sequence.pattern_image(0, frame as usize);
            screen_levels()
                .iter()
                .zip(expect.as_raw())
                .filter(|(&s, &e)| s != u16::from(e))
                .count()
        })
    };
    (Box::new(p), Box::new(check))
}
