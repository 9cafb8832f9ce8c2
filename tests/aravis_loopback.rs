//! The Aravis driver through the real GigE Vision protocol: a fake camera on 127.0.0.1 in
//! this process serves frames we give it (rendered board views, synthetic patterns), the
//! driver opens it by address, configures it, triggers it in software and must hand back
//! exactly those frames in order — or say clearly, naming the device, why it cannot. A
//! loopback camera that sees a live scene (the projector's slide, at the exposure the driver
//! set through GenICam) lets the exposure check run through the driver end to end.
#![cfg(feature = "loopback")]

use hexcal::capture::Session;
use hexcal::check::exposure::{check_exposure, ExposurePlan};
use hexcal::pattern::{ProjectorResponse, ProjectorSetup, Sequence};
use hexcal::rig::aravis::loopback::synthetic_frame;
use hexcal::rig::aravis::{
    list_cameras, AravisCamera, LiveScene, LoopbackCamera, LOOPBACK_ADDRESS,
};
use hexcal::rig::{CaptureTiming, Projector, RigDevices, Slide};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use {
    hexcal::images::{CameraFrame, Pixels},
    hexcal::rig::{Camera, CameraConfig, DeviceError, TriggerSource},
};

/// One loopback camera at a time: it listens on 127.0.0.1's GVCP port.
static LOOPBACK: Mutex<()> = Mutex::new(());

fn exclusive() -> MutexGuard<'static, ()> {
    LOOPBACK.lock().unwrap_or_else(|e| e.into_inner())
}

const TIMEOUT: Duration = Duration::from_secs(2);

fn config(width: u32, height: u32, bits: u8) -> CameraConfig {
    CameraConfig {
        width,
        height,
        bits,
        exposure_us: 5000.0,
        gain_db: 0.0,
        trigger: TriggerSource::Software,
    }
}

/// Serve `frames`, open the camera by address as `name`, configure and start it.
fn loopback(
    name: &str,
    frames: Vec<Pixels>,
    config: &CameraConfig,
) -> (LoopbackCamera, AravisCamera) {
    let fake = LoopbackCamera::start("HEXTEST", frames).expect("loopback camera starts");
    let mut camera = AravisCamera::open(name, LOOPBACK_ADDRESS).expect("opens by address");
    camera.configure(config).expect("configures");
    camera.start().expect("starts");
    (fake, camera)
}

fn shot(camera: &mut AravisCamera) -> Result<CameraFrame, DeviceError> {
    camera.trigger()?;
    camera.next_frame(TIMEOUT)
}

/// The default scene's rendered board view as 8-bit samples, with frame `k`'s number in a
/// 16×16 block at the top left so every frame differs.
fn board_frames(n: usize) -> (u32, u32, Vec<Pixels>) {
    let scene = hexcal::sim::Scene::default_scene();
    let view = hexcal::sim::render(&scene).expect("default scene renders");
    let (w, h) = (view.frame.size.width, view.frame.size.height);
    let shift = view.frame.bits.saturating_sub(8);
    let board: Vec<u8> = view
        .frame
        .data
        .iter()
        .map(|&v| (v >> shift) as u8)
        .collect();
    let frames = (0..n)
        .map(|k| {
            let mut p = board.clone();
            for y in 0..16 {
                for x in 0..16 {
                    p[y * w as usize + x] = (k * 37 + 11) as u8;
                }
            }
            Pixels::Gray8(p)
        })
        .collect();
    (w, h, frames)
}

#[test]
fn rendered_boards_arrive_in_order_pixel_for_pixel() {
    let _one = exclusive();
    const DISTINCT: usize = 5;
    // The fake camera's 16-bit frame ids start at 65401: 150 frames cross the wrap.
    const FRAMES: usize = 150;
    let (w, h, served) = board_frames(DISTINCT);
    let (fake, mut camera) = loopback("cam-board", served.clone(), &config(w, h, 8));
    let mut counters = Vec::new();
    for _ in 0..FRAMES {
        let frame = shot(&mut camera).expect("frame arrives");
        assert_eq!((frame.width, frame.height, frame.bits), (w, h, 8));
        assert!(
            (frame.exposure_us - 5000.0).abs() < 1.0,
            "{}",
            frame.exposure_us
        );
        let k = counters.len();
        assert!(
            frame.pixels == served[k % DISTINCT],
            "frame {k} (counter {}) is not the board view served",
            frame.counter
        );
        counters.push(frame.counter);
    }
    for pair in counters.windows(2) {
        assert_eq!(pair[1], pair[0] + 1, "counters {counters:?}");
    }
    camera.stop().expect("stops");
    assert_eq!(fake.served(), FRAMES);
    assert_eq!(fake.mismatches(), 0);
}

#[test]
fn mono16_frames_and_restart() {
    let _one = exclusive();
    let (w, h) = (640, 480);
    let served: Vec<Pixels> = (0..3).map(|k| synthetic_frame(w, h, 16, k)).collect();
    let (fake, mut camera) = loopback("cam-16", served.clone(), &config(w, h, 16));
    let mut last = None;
    for round in 0..2 {
        for _ in 0..6 {
            let frame = shot(&mut camera).expect("frame arrives");
            assert_eq!(frame.bits, 16);
            let k = fake.served() - 1;
            assert!(frame.pixels == served[k % 3], "frame {k} differs");
            if let Some(last) = last {
                assert_eq!(frame.counter, last + 1);
            }
            last = Some(frame.counter);
        }
        camera.stop().expect("stops");
        if round == 0 {
            camera.start().expect("starts again");
        }
    }
    assert_eq!(fake.mismatches(), 0);
}

/// Response of the red, green and blue pixels of the served Bayer mosaics.
const RESPONSE: [f64; 3] = [0.6, 1.0, 0.8];

#[test]
fn bayer_mosaics_of_every_phase_arrive_balanced_to_the_board_view() {
    use hexcal::images::to_grey::Cfa;
    let _one = exclusive();
    let (w, h, views) = board_frames(1);
    let Pixels::Gray8(view) = &views[0] else {
        unreachable!("8-bit views")
    };
    // The board view constant over each 2×2 cell, so grey-world gains are exact up to
    // rounding.
    let cell = |i: usize| view[((i / w as usize) & !1) * w as usize + ((i % w as usize) & !1)];
    for (name, cfa) in [
        ("BayerRG8", Cfa::Rggb),
        ("BayerGR8", Cfa::Grbg),
        ("BayerGB8", Cfa::Gbrg),
        ("BayerBG8", Cfa::Bggr),
    ] {
        let mosaic: Vec<u8> = (0..view.len())
            .map(|i| {
                let r = RESPONSE[cfa.channel(i % w as usize, i / w as usize)];
                (f64::from(cell(i)) * r).round() as u8
            })
            .collect();
        let fake = LoopbackCamera::start("HEXTEST", vec![Pixels::Gray8(mosaic)]).unwrap();
        let mut camera = AravisCamera::open("cam-bayer", LOOPBACK_ADDRESS)
            .unwrap()
            .with_format(Some(name));
        camera.configure(&config(w, h, 8)).expect("configures");
        assert_eq!(camera.pixel_format().as_deref(), Some(name));
        camera.start().expect("starts");
        for _ in 0..2 {
            let frame = shot(&mut camera).expect("frame arrives");
            let Pixels::Gray8(got) = &frame.pixels else {
                panic!("8-bit grey expected")
            };
            // Rounded once through the filter, once through the gain: within 1 DN.
            let worst = (0..got.len())
                .map(|i| (i16::from(got[i]) - i16::from(cell(i))).abs())
                .max();
            assert!(worst <= Some(1), "{name}: worst {worst:?}");
        }
        camera.stop().expect("stops");
        assert_eq!(fake.mismatches(), 0);
    }
    // Unnamed, the monochrome format the fake camera also offers is chosen.
    let fake = LoopbackCamera::start("HEXTEST", views).unwrap();
    let mut camera = AravisCamera::open("cam-auto", LOOPBACK_ADDRESS).unwrap();
    camera.configure(&config(w, h, 8)).expect("configures");
    assert_eq!(camera.pixel_format().as_deref(), Some("Mono8"));
    // A format the camera does not offer is refused naming what it offers.
    let mut camera = AravisCamera::open("cam-named", LOOPBACK_ADDRESS)
        .unwrap()
        .with_format(Some("BayerRG12p"));
    let msg = camera.configure(&config(w, h, 12)).unwrap_err().to_string();
    assert!(
        msg.contains("BayerRG12p not offered") && msg.contains("BayerRG8"),
        "{msg}"
    );
    drop(fake);
}

#[test]
fn impossible_settings_are_refused_naming_device_and_setting() {
    let _one = exclusive();
    let fake = LoopbackCamera::start("HEXTEST", vec![synthetic_frame(64, 64, 8, 0)]).unwrap();
    let mut camera = AravisCamera::open("cam-refuse", LOOPBACK_ADDRESS).unwrap();
    let (vendor, model, serial) = camera.identity().unwrap();
    assert_eq!(
        (vendor.as_str(), serial.as_str()),
        ("Aravis", "HEXTEST"),
        "{model}"
    );
    let cases = [
        (
            CameraConfig {
                width: 9000,
                ..config(64, 64, 8)
            },
            "width",
        ),
        (
            CameraConfig {
                bits: 9,
                ..config(64, 64, 8)
            },
            "bits",
        ),
        (
            CameraConfig {
                gain_db: 6.0,
                ..config(64, 64, 8)
            },
            "gain_db",
        ),
        (
            CameraConfig {
                exposure_us: 1e9,
                ..config(64, 64, 8)
            },
            "exposure",
        ),
    ];
    for (cfg, setting) in cases {
        match camera.configure(&cfg) {
            Err(e @ DeviceError::Unsupported { .. }) => {
                let text = e.to_string();
                assert!(text.starts_with("cam-refuse: "), "{text}");
                assert!(text.contains(setting), "{text}");
            }
            other => panic!("{setting}: {other:?}"),
        }
    }
    // Line trigger: the camera's single line input; no software trigger then.
    let line = CameraConfig {
        trigger: TriggerSource::Line,
        ..config(64, 64, 8)
    };
    camera.configure(&line).unwrap();
    camera.start().unwrap();
    let e = camera.trigger().unwrap_err();
    assert!(matches!(e, DeviceError::Unsupported { .. }), "{e}");
    assert!(matches!(
        camera.next_frame(Duration::from_millis(200)),
        Err(DeviceError::Timeout { .. })
    ));
    camera.stop().unwrap();
    drop(fake);
}

#[test]
fn lost_packets_give_incomplete_frames_never_wrong_ones() {
    let _one = exclusive();
    let (w, h) = (320, 240);
    let served: Vec<Pixels> = (0..4).map(|k| synthetic_frame(w, h, 8, k)).collect();
    let (fake, mut camera) = loopback("cam-lossy", served.clone(), &config(w, h, 8));
    let good = shot(&mut camera).expect("loss-free frame");
    let first = good.counter;
    fake.set_packet_loss(0.02);
    let (mut ok, mut incomplete) = (0, 0);
    for _ in 0..40 {
        match shot(&mut camera) {
            Ok(frame) => {
                let k = (frame.counter - first) as usize;
                assert!(frame.pixels == served[k % 4], "frame {k} silently wrong");
                ok += 1;
            }
            Err(e) => {
                assert!(e.retryable(), "{e}");
                assert_eq!(e.device(), "cam-lossy");
                if let DeviceError::Incomplete { reason, .. } = &e {
                    assert!(
                        [
                            "MISSING_PACKETS",
                            "TIMEOUT",
                            "SIZE_MISMATCH",
                            "WRONG_PACKET_ID"
                        ]
                        .iter()
                        .any(|s| reason.contains(s)),
                        "{e}"
                    );
                }
                incomplete += 1;
            }
        }
    }
    let stats = camera.statistics();
    eprintln!("2 % GVSP loss: {ok} complete, {incomplete} incomplete of 40; {stats:?}");
    assert!(incomplete > 0, "2 % packet loss never showed");
    assert!(stats.missing_packets > 0 || stats.failures > 0, "{stats:?}");
    // Loss gone: frames are whole again (after any late buffer of the lossy run).
    fake.set_packet_loss(0.0);
    let mut whole = 0;
    for _ in 0..10 {
        if let Ok(frame) = shot(&mut camera) {
            let k = (frame.counter - first) as usize;
            assert!(frame.pixels == served[k % 4]);
            whole += 1;
        }
    }
    assert!(whole >= 8, "{whole} of 10 whole after the loss stopped");
    camera.stop().unwrap();
}

#[test]
fn camera_gone_mid_sequence_is_an_error_naming_it() {
    let _one = exclusive();
    let served = vec![synthetic_frame(128, 96, 8, 0)];
    let (fake, mut camera) = loopback("cam-unplugged", served, &config(128, 96, 8));
    for _ in 0..3 {
        shot(&mut camera).expect("frame before the fault");
    }
    camera.trigger().expect("trigger before the fault");
    // The camera goes away before it served the triggered frame (it polls for triggers).
    drop(fake);
    let timeout = Duration::from_millis(500);
    let t0 = Instant::now();
    let waited = camera.next_frame(timeout);
    let took = t0.elapsed();
    // Dropping the fake raced with its serving the frame: then one more frame is fine.
    let e = match waited {
        Ok(_) => camera.next_frame(timeout).expect_err("no second frame"),
        Err(e) => e,
    };
    assert!(matches!(e, DeviceError::Timeout { .. }), "{e}");
    assert_eq!(e.device(), "cam-unplugged");
    assert!(took < timeout + Duration::from_millis(300), "{took:?}");
    // Retrying the frame: the trigger finds nobody (Aravis' GVCP budget: 5 × 500 ms).
    let t0 = Instant::now();
    let e = camera
        .trigger()
        .expect_err("trigger to a camera that is gone");
    let took = t0.elapsed();
    eprintln!("after the camera went away: {e} ({took:?})");
    assert!(matches!(e, DeviceError::Gone { .. }), "{e}");
    assert!(
        e.to_string().starts_with("cam-unplugged: device lost: "),
        "{e}"
    );
    assert!(took < Duration::from_secs(4), "{took:?}");
    drop(camera);
}

#[test]
fn no_camera_at_the_address_is_an_error_naming_it() {
    let _one = exclusive();
    let t0 = Instant::now();
    let e = AravisCamera::open("cam-absent", LOOPBACK_ADDRESS)
        .err()
        .expect("nothing listens there");
    eprintln!("{e} ({:?})", t0.elapsed());
    assert!(
        e.to_string()
            .starts_with("cam-absent: cannot open GenICam camera 127.0.0.1"),
        "{e}"
    );
}

#[test]
fn lists_cameras_and_opens_one_by_device_id() {
    let _one = exclusive();
    hexcal::rig::aravis::loopback::enable_fake_interface();
    let cameras = list_cameras();
    let fake = cameras
        .iter()
        .find(|c| c.protocol == "Fake" || c.model == "Fake")
        .unwrap_or_else(|| panic!("no fake camera in {cameras:?}"));
    assert_eq!(fake.vendor, "Aravis");
    let mut camera = AravisCamera::open("cam-fake", &fake.id).expect("opens by device id");
    camera.configure(&config(256, 128, 8)).unwrap();
    camera.start().unwrap();
    let a = shot(&mut camera).unwrap();
    let b = shot(&mut camera).unwrap();
    assert_eq!((b.width, b.height), (256, 128));
    assert_eq!(b.counter, a.counter + 1);
    camera.stop().unwrap();
}

/// A projector that only says what it shows (the loopback scene reads it).
struct Shown(Arc<Mutex<Slide>>);

impl Projector for Shown {
    fn name(&self) -> &str {
        "proj"
    }

    fn resolution(&self) -> (u32, u32) {
        (1920, 1080)
    }

    fn prepare(&mut self, _: &Sequence, _: usize) -> Result<(), DeviceError> {
        Ok(())
    }

    fn show(&mut self, slide: Slide) -> Result<(), DeviceError> {
        *self.0.lock().unwrap() = slide;
        Ok(())
    }
}

/// Light at 5000 µs (DN): the room everywhere, and the projector's full white on the board
/// (the middle of the view), whose light goes as level^γ.
const AMBIENT_DN: f64 = 4.0;
const PROJECTOR_DN: f64 = 120.0;
const GAMMA: f64 = 2.2;

/// The board as the camera sees it under `slide` at `exposure_us`, with 1 DN of read noise
/// (frame `k`'s own draw).
fn seen(slide: Slide, exposure_us: f64, k: u64) -> Pixels {
    let light = match slide {
        Slide::Black => 0.0,
        Slide::White => 1.0,
        Slide::Level(l) => (f64::from(l) / 255.0).powf(GAMMA),
        Slide::Pattern(_) => 0.5,
    };
    let mut state = k.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    let (w, h) = (64usize, 48usize);
    let samples = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let board = (16..48).contains(&x) && (12..36).contains(&y);
            let dn = (AMBIENT_DN + PROJECTOR_DN * light * f64::from(u8::from(board))) * exposure_us
                / 5000.0;
            // Four uniforms: σ = 1 DN.
            let noise = (0..4).map(|_| uniform()).sum::<f64>() * 3f64.sqrt();
            (dn + noise).round().clamp(0.0, 255.0) as u8
        })
        .collect();
    Pixels::Gray8(samples)
}

#[test]
fn the_exposure_check_sets_an_aravis_cameras_exposure_through_genicam() {
    let _one = exclusive();
    let slide = Arc::new(Mutex::new(Slide::Black));
    let shown = Arc::clone(&slide);
    let frames = AtomicU64::new(0);
    let scene: LiveScene = Box::new(move |exposure_us| {
        let k = frames.fetch_add(1, Ordering::SeqCst);
        seen(*shown.lock().unwrap(), exposure_us, k)
    });
    let _fake = LoopbackCamera::start_scene("HEXTEST", scene).unwrap();
    let camera = AravisCamera::open("cam", LOOPBACK_ADDRESS).unwrap();
    let setup = ProjectorSetup {
        width: 1920,
        height: 1080,
        response: ProjectorResponse::Gamma { gamma: GAMMA },
    };
    let sequence = Sequence::default_for(&[setup]).unwrap();
    let mut session = Session::start(
        RigDevices {
            cameras: vec![Box::new(camera) as Box<dyn Camera>],
            configs: vec![config(64, 48, 8)],
            projectors: vec![Box::new(Shown(slide)) as Box<dyn Projector>],
            trigger: None,
            timing: CaptureTiming {
                settle: Duration::from_millis(2),
                latency: vec![Duration::ZERO],
                frame_timeout: TIMEOUT,
                retries: 2,
                repeats: 1,
            },
        },
        &sequence,
    )
    .unwrap();
    let plan = ExposurePlan {
        white_level: 0.8,
        max_exposure_us: 20_000.0,
        max_gain_db: 0.0,
        wait: Duration::from_millis(5),
        set_exposure: true,
    };
    let report = check_exposure(&mut session, &plan).unwrap();
    eprintln!("{report:?}");
    assert!(report.warnings().is_empty(), "{:?}", report.warnings());
    // The white the check reached was read from frames taken at the exposure it set through
    // ExposureTime: the board's brightest white (124 DN and its noise's 99th percentile at
    // 5000 µs) at 0.8 of 255 needs about 204/126.3 of 5000 µs.
    let cam = &report.cameras[0];
    assert!(cam.converged && (cam.white - 0.8).abs() <= 0.03, "{cam:?}");
    let expected = 5000.0 * 0.8 * 255.0 / (AMBIENT_DN + PROJECTOR_DN + 2.3);
    assert!((cam.exposure_us / expected - 1.0).abs() < 0.04, "{cam:?}");
    assert_eq!(session.exposures(), vec![(cam.exposure_us, 0.0)]);
    let r = &report.responses[0];
    assert!(r.seen && !r.non_monotone && !r.clips, "{r:?}");
    assert!(
        (r.gamma - GAMMA).abs() < 4.0 * r.gamma_sigma,
        "γ {} ± {}",
        r.gamma,
        r.gamma_sigma
    );
}
