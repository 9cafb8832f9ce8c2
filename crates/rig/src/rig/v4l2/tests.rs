//! The V4L2 driver logic against a simulated node: a free-running camera on a virtual clock
//! with a kernel-like buffer queue (frames are lost when every buffer is full), settable
//! formats and controls, and injected faults (lost, corrupted and short buffers, the node
//! vanishing). Format negotiation, control ranges, pixel conversion, stale-frame dropping,
//! frame counters and errors, and a capture through the real engine.

use super::*;
use crate::capture::Session;
use crate::rig::file::RigFile;
use crate::rig::fixture::{tiny, SimDevice};
use crate::rig::{CaptureTiming, RigDevices};
use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};

const NODE: &str = "/dev/video-sim";
const NAME: &str = "usb0";
/// Frame period of the simulated camera.
const PERIOD: Duration = Duration::from_millis(10);

/// Sample (x, y) of frame `seq`: 8-bit luma.
fn luma(x: usize, y: usize, seq: u32) -> u8 {
    (x + 3 * y + 7 * seq as usize) as u8
}

/// Sample (x, y) of frame `seq`: 16-bit word (both bytes vary).
fn word(x: usize, y: usize, seq: u32) -> u16 {
    (x * 257 + y * 31 + seq as usize * 1009) as u16
}

/// The frame a delivered 8-bit image is (7 · 183 ≡ 1 mod 256).
fn sequence_of(pixels: &Pixels) -> u32 {
    match pixels {
        Pixels::Gray8(p) => u32::from(p[0].wrapping_mul(183)),
        Pixels::Gray16(_) => panic!("8-bit expected"),
    }
}

/// Sample (x, y) of frame `seq` of a smooth scene (MJPEG frames: JPEG rings at a wrap).
fn smooth(x: usize, y: usize, seq: u32) -> u8 {
    (60 + x / 2 + y / 3 + seq as usize) as u8
}

/// A Bayer node's scene: [`luma`] constant over each 2×2 cell, so grey-world gains are
/// exact up to rounding.
fn cell_luma(x: usize, y: usize, seq: u32) -> u8 {
    luma(x & !1, y & !1, seq)
}

/// Relative response of the simulated Bayer node's red, green and blue pixels.
const RESPONSE: [f64; 3] = [0.6, 1.0, 0.8];

/// JPEG quality of the simulated node's MJPEG frames.
const MJPEG_QUALITY: u8 = 100;

/// Bytes per row padding the simulated node adds.
const PADDING: u32 = 6;

/// The simulated node's state.
struct Sim {
    formats: Vec<FourCc>,
    /// The largest size the node sets (larger requests are clamped, like real drivers).
    max_size: (u32, u32),
    /// The largest size of each format limited below `max_size` (a webcam's YUYV).
    format_max: HashMap<FourCc, (u32, u32)>,
    format: Option<Format>,
    controls: Vec<ControlInfo>,
    values: HashMap<u32, i64>,
    /// Every control set, in order.
    log: Vec<(u32, i64)>,
    /// Buffers allocated (0: not streaming).
    buffers: u32,
    stamp: StampSource,
    now: Duration,
    /// Frame i starts exposing at `origin + i · PERIOD` and is done one period later.
    origin: Duration,
    next: u32,
    done: VecDeque<u32>,
    held: bool,
    lost: HashSet<u32>,
    flagged: HashSet<u32>,
    short: HashSet<u32>,
    vanish_at: Option<u32>,
    vanished: bool,
}

impl Sim {
    fn done_at(&self, seq: u32) -> Duration {
        self.origin + PERIOD * (seq + 1)
    }

    /// Expose every frame done by now into a free buffer, or lose it.
    fn produce(&mut self) -> io::Result<()> {
        while self.done_at(self.next) <= self.now {
            if self.vanish_at == Some(self.next) {
                self.vanished = true;
            }
            if self.vanished {
                return Err(io::Error::from_raw_os_error(libc::ENODEV));
            }
            let busy = self.done.len() as u32 + u32::from(self.held);
            if !self.lost.contains(&self.next) && busy < self.buffers {
                self.done.push_back(self.next);
            }
            self.next += 1;
        }
        Ok(())
    }

    /// Frame `seq` in the current format.
    fn image(&self, seq: u32) -> Vec<u8> {
        let f = self.format.expect("format set");
        let (w, h, stride) = (f.width as usize, f.height as usize, f.stride as usize);
        if f.fourcc == FourCc::MJPG {
            let grey: Vec<u8> = (0..w * h).map(|i| smooth(i % w, i / w, seq)).collect();
            let mut jpeg = Vec::new();
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, MJPEG_QUALITY)
                .encode(&grey, w as u32, h as u32, image::ExtendedColorType::L8)
                .expect("encodes");
            return jpeg;
        }
        let cfa = pixel_formats()
            .into_iter()
            .find_map(|(c, s)| match s.colour {
                Colour::Bayer(cfa) if c == f.fourcc => Some(cfa),
                _ => None,
            });
        let mut data = vec![0xEE; stride * h];
        if let Some(cfa) = cfa {
            for y in 0..h {
                for x in 0..w {
                    let v = f64::from(cell_luma(x, y, seq)) * RESPONSE[cfa.channel(x, y)];
                    data[y * stride + x] = v.round() as u8;
                }
            }
            return data;
        }
        for y in 0..h {
            let row = &mut data[y * stride..];
            for x in 0..w {
                match f.fourcc {
                    FourCc::GREY => row[x] = luma(x, y, seq),
                    FourCc::YUYV => {
                        row[2 * x] = luma(x, y, seq);
                        // Chroma unlike the luma, so taking it shows.
                        row[2 * x + 1] = 0x80 ^ luma(x + 1, y + 5, seq);
                    }
                    _ => row[2 * x..2 * x + 2].copy_from_slice(&word(x, y, seq).to_le_bytes()),
                }
            }
        }
        data
    }
}

/// A simulated node; clones share it, so a test can steer and inspect it while a camera owns
/// one. `buffer` is the buffer dequeued last.
#[derive(Clone)]
struct SimNode {
    shared: Arc<Mutex<Sim>>,
    buffer: Vec<u8>,
}

/// UVC-like controls: auto exposure (manual or aperture priority), exposure in 100 µs
/// from 0.3 to 204.7 ms, auto priority, gain 0–255.
fn uvc_controls() -> Vec<ControlInfo> {
    vec![
        control(
            CID_EXPOSURE_AUTO,
            "Auto Exposure",
            ControlKind::Menu(vec![1, 3]),
            0,
            3,
        ),
        control(
            CID_EXPOSURE_ABSOLUTE,
            "Exposure Time, Absolute",
            ControlKind::Integer,
            3,
            2047,
        ),
        control(
            CID_EXPOSURE_AUTO_PRIORITY,
            "Exposure, Dynamic Framerate",
            ControlKind::Boolean,
            0,
            1,
        ),
        control(CID_GAIN, "Gain", ControlKind::Integer, 0, 255),
    ]
}

fn control(id: u32, name: &str, kind: ControlKind, min: i64, max: i64) -> ControlInfo {
    ControlInfo {
        id,
        name: name.into(),
        kind,
        min,
        max,
        step: 1,
        read_only: false,
    }
}

impl SimNode {
    fn new(formats: &[FourCc], controls: Vec<ControlInfo>) -> SimNode {
        let sim = Sim {
            formats: formats.to_vec(),
            max_size: (1920, 1200),
            format_max: HashMap::new(),
            format: None,
            controls,
            values: HashMap::from([(CID_EXPOSURE_AUTO, 3)]),
            log: Vec::new(),
            buffers: 0,
            stamp: StampSource::StartOfExposure,
            now: Duration::from_secs(100),
            origin: Duration::ZERO,
            next: 0,
            done: VecDeque::new(),
            held: false,
            lost: HashSet::new(),
            flagged: HashSet::new(),
            short: HashSet::new(),
            vanish_at: None,
            vanished: false,
        };
        SimNode {
            shared: Arc::new(Mutex::new(sim)),
            buffer: Vec::new(),
        }
    }

    fn sim(&self) -> MutexGuard<'_, Sim> {
        self.shared.lock().unwrap()
    }

    /// Let time pass (the capture loop doing something else).
    fn advance(&self, by: Duration) {
        self.sim().now += by;
    }
}

impl V4l2Device for SimNode {
    fn capabilities(&self) -> io::Result<Capabilities> {
        Ok(Capabilities {
            driver: "uvcvideo".into(),
            card: "Sim Cam".into(),
            bus: "usb-sim-1".into(),
            capture: true,
            streaming: true,
        })
    }

    fn formats(&self) -> io::Result<Vec<FourCc>> {
        Ok(self.sim().formats.clone())
    }

    fn set_format(&mut self, format: Format) -> io::Result<Format> {
        let mut s = self.sim();
        if !s.formats.contains(&format.fourcc) {
            return Err(io::Error::from_raw_os_error(libc::EINVAL));
        }
        let bpp = match &format.fourcc.0 {
            b"GREY" | b"BA81" | b"GBRG" | b"GRBG" | b"RGGB" => 1,
            // MJPEG: no rows (bytesperline 0, as uvcvideo sets it).
            b"MJPG" => 0,
            _ => 2,
        };
        let max = s
            .format_max
            .get(&format.fourcc)
            .copied()
            .unwrap_or(s.max_size);
        let width = format.width.min(max.0);
        let height = format.height.min(max.1);
        let set = Format {
            fourcc: format.fourcc,
            width,
            height,
            stride: if bpp == 0 { 0 } else { width * bpp + PADDING },
        };
        s.format = Some(set);
        Ok(set)
    }

    fn controls(&self) -> io::Result<Vec<ControlInfo>> {
        Ok(self.sim().controls.clone())
    }

    fn control(&self, id: u32) -> io::Result<i64> {
        let s = self.sim();
        s.values
            .get(&id)
            .copied()
            .ok_or_else(|| io::Error::from_raw_os_error(libc::EINVAL))
    }

    fn set_control(&mut self, control: &ControlInfo, value: i64) -> io::Result<()> {
        let mut s = self.sim();
        let info = s
            .controls
            .iter()
            .find(|c| c.id == control.id)
            .ok_or_else(|| io::Error::from_raw_os_error(libc::EINVAL))?;
        if !info.allows(value) || info.read_only {
            return Err(io::Error::from_raw_os_error(libc::ERANGE));
        }
        // Like uvcvideo: manual exposure is refused while auto exposure is on.
        if control.id == CID_EXPOSURE_ABSOLUTE
            && !matches!(s.values.get(&CID_EXPOSURE_AUTO), Some(1 | 2) | None)
        {
            return Err(io::Error::from_raw_os_error(libc::EACCES));
        }
        s.values.insert(control.id, value);
        s.log.push((control.id, value));
        Ok(())
    }

    fn start(&mut self, buffers: u32) -> io::Result<()> {
        let mut s = self.sim();
        s.buffers = buffers;
        s.origin = s.now;
        Ok(())
    }

    fn dequeue(&mut self, timeout: Duration) -> io::Result<(&[u8], BufferMeta)> {
        let mut s = self.shared.lock().unwrap();
        if s.buffers == 0 {
            return Err(io::Error::from_raw_os_error(libc::EINVAL));
        }
        s.held = false;
        let deadline = s.now + timeout;
        let seq = loop {
            s.produce()?;
            if let Some(seq) = s.done.pop_front() {
                break seq;
            }
            let next = s.done_at(s.next);
            if next > deadline {
                s.now = deadline;
                return Err(io::Error::new(io::ErrorKind::TimedOut, "VIDIOC_DQBUF"));
            }
            s.now = next;
        };
        s.held = true;
        let image = s.image(seq);
        let start = s.origin + PERIOD * seq;
        let meta = BufferMeta {
            sequence: seq,
            timestamp: match s.stamp {
                StampSource::StartOfExposure => start,
                StampSource::EndOfFrame => start + PERIOD,
            },
            monotonic: true,
            source: s.stamp,
            bytes_used: if s.short.contains(&seq) {
                image.len() as u32 / 2
            } else {
                image.len() as u32
            },
            error: s.flagged.contains(&seq),
            arrival: s.now,
        };
        drop(s);
        self.buffer = image;
        Ok((&self.buffer, meta))
    }

    fn stop(&mut self) -> io::Result<()> {
        let mut s = self.sim();
        s.buffers = 0;
        s.done.clear();
        s.held = false;
        Ok(())
    }

    fn now(&self) -> Duration {
        self.sim().now
    }
}

fn config(width: u32, height: u32, bits: u8) -> CameraConfig {
    CameraConfig {
        width,
        height,
        bits,
        exposure_us: 5_000.0,
        gain_db: 0.0,
        trigger: TriggerSource::Software,
    }
}

fn camera(node: &SimNode) -> V4l2Camera<SimNode> {
    V4l2Camera::new(NAME, NODE, node.clone()).unwrap()
}

/// A camera on a node offering `formats` (UVC controls), configured and streaming.
fn streaming(formats: &[FourCc], config: &CameraConfig) -> (V4l2Camera<SimNode>, SimNode) {
    let node = SimNode::new(formats, uvc_controls());
    let mut cam = camera(&node);
    cam.configure(config).unwrap();
    cam.start().unwrap();
    (cam, node)
}

const WAIT: Duration = Duration::from_secs(1);

/// Trigger and take the frame.
fn take(cam: &mut V4l2Camera<SimNode>) -> Result<CameraFrame, DeviceError> {
    cam.trigger()?;
    cam.next_frame(WAIT)
}

fn gray8(w: usize, h: usize, seq: u32) -> Pixels {
    Pixels::Gray8(
        (0..h)
            .flat_map(|y| (0..w).map(move |x| luma(x, y, seq)))
            .collect(),
    )
}

fn gray16(w: usize, h: usize, seq: u32) -> Pixels {
    Pixels::Gray16(
        (0..h)
            .flat_map(|y| (0..w).map(move |x| word(x, y, seq)))
            .collect(),
    )
}

#[test]
fn grey_is_taken_for_8_bits_and_rows_lose_their_padding() {
    let (mut cam, node) = streaming(&[FourCc::YUYV, FourCc::GREY], &config(64, 48, 8));
    assert_eq!(node.sim().format.unwrap().fourcc, FourCc::GREY);
    let f = take(&mut cam).unwrap();
    assert_eq!((f.width, f.height, f.bits), (64, 48, 8));
    assert_eq!(f.pixels, gray8(64, 48, 0));
}

#[test]
fn only_yuyv_gives_its_luma() {
    let (mut cam, node) = streaming(&[FourCc(*b"MJPG"), FourCc::YUYV], &config(64, 48, 8));
    assert_eq!(node.sim().format.unwrap().fourcc, FourCc::YUYV);
    let f = take(&mut cam).unwrap();
    assert_eq!((f.width, f.height, f.bits), (64, 48, 8));
    assert_eq!(f.pixels, gray8(64, 48, 0));
}

#[test]
fn y16_serves_12_bits_little_endian_and_y12_is_preferred() {
    let (mut cam, node) = streaming(&[FourCc::YUYV, FourCc::Y16], &config(40, 30, 12));
    assert_eq!(node.sim().format.unwrap().fourcc, FourCc::Y16);
    let f = take(&mut cam).unwrap();
    assert_eq!((f.width, f.height, f.bits), (40, 30, 16));
    assert_eq!(f.pixels, gray16(40, 30, 0));

    let (mut cam, node) = streaming(&[FourCc::Y16, FourCc::Y12], &config(40, 30, 12));
    assert_eq!(node.sim().format.unwrap().fourcc, FourCc::Y12);
    assert_eq!(take(&mut cam).unwrap().bits, 12);
}

#[test]
fn no_usable_format_is_refused_naming_camera_request_and_offer() {
    let node = SimNode::new(&[FourCc(*b"H264"), FourCc::Y16], uvc_controls());
    let e = camera(&node).configure(&config(64, 48, 8)).unwrap_err();
    assert!(matches!(&e, DeviceError::Unsupported { setting, .. } if setting == "format"));
    let msg = e.to_string();
    for part in [NAME, NODE, "no format gives 8 bits", "offers H264, Y16"] {
        assert!(msg.contains(part), "{msg:?} lacks {part:?}");
    }
    let node = SimNode::new(&[FourCc::GREY, FourCc::YUYV], uvc_controls());
    let msg = camera(&node)
        .configure(&config(64, 48, 16))
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("no format gives 16 bits") && msg.contains("offers GREY, YUYV"),
        "{msg}"
    );
}

#[test]
fn mjpeg_frames_decode_to_their_luma_and_carry_the_large_sizes() {
    // A webcam: YUYV up to 640×480, MJPEG up to 1920×1200. 1280×720 is MJPEG only.
    let node = SimNode::new(&[FourCc::YUYV, FourCc::MJPG], uvc_controls());
    node.sim().format_max.insert(FourCc::YUYV, (640, 480));
    let mut cam = camera(&node);
    cam.configure(&config(1280, 720, 8)).unwrap();
    assert_eq!(cam.pixel_format().as_deref(), Some("MJPG"));
    cam.start().unwrap();
    let (w, h) = (1280, 720);
    for seq in 0..2 {
        let f = take(&mut cam).unwrap();
        assert_eq!((f.width, f.height, f.bits), (1280, 720, 8));
        let Pixels::Gray8(got) = &f.pixels else {
            panic!("8-bit luma expected")
        };
        // Quality 100 quantises every coefficient by 1: what is left is the rounding of the
        // coefficients and of the integer DCTs, a fraction of a DN, at most 2.
        let err: Vec<f64> = (0..w * h)
            .map(|i| f64::from(got[i]) - f64::from(smooth(i % w, i / w, seq)))
            .collect();
        let worst = err.iter().fold(0.0f64, |m, e| m.max(e.abs()));
        let rms = (err.iter().map(|e| e * e).sum::<f64>() / err.len() as f64).sqrt();
        assert!(
            worst <= 2.0 && rms < 0.7,
            "frame {seq}: worst {worst}, rms {rms}"
        );
    }
    // At 640×480 the uncompressed YUYV wins.
    let mut cam = camera(&node);
    cam.configure(&config(640, 480, 8)).unwrap();
    assert_eq!(cam.pixel_format().as_deref(), Some("YUYV"));
}

#[test]
fn a_cut_mjpeg_frame_is_incomplete_and_worth_a_retry() {
    let (mut cam, node) = streaming(&[FourCc::MJPG], &config(64, 48, 8));
    node.sim().short.insert(0);
    let e = take(&mut cam).unwrap_err();
    assert!(e.retryable(), "{e}");
}

#[test]
fn bayer_buffers_of_each_phase_balance_to_the_neutral_scene() {
    for code in [b"BA81", b"GBRG", b"GRBG", b"RGGB"] {
        let node = SimNode::new(&[FourCc::YUYV, FourCc(*code)], uvc_controls());
        let name = FourCc(*code).to_string();
        let mut cam = camera(&node).with_format(Some(&name));
        cam.configure(&config(64, 48, 8)).unwrap();
        assert_eq!(cam.pixel_format(), Some(name.clone()));
        cam.start().unwrap();
        let f = take(&mut cam).unwrap();
        let Pixels::Gray8(got) = &f.pixels else {
            panic!("8-bit grey expected")
        };
        // Each sample was rounded once through its filter and once through its gain.
        for (i, &v) in got.iter().enumerate() {
            let want = cell_luma(i % 64, i / 64, 0);
            assert!(
                (i16::from(v) - i16::from(want)).abs() <= 1,
                "{name} pixel {i}: {v} for {want}"
            );
        }
    }
    // Unnamed, a Bayer format ranks after YUYV's luma.
    let (cam, _) = streaming(&[FourCc(*b"RGGB"), FourCc::YUYV], &config(64, 48, 8));
    assert_eq!(cam.pixel_format().as_deref(), Some("YUYV"));
    // Named but not offered: refused naming what is.
    let node = SimNode::new(&[FourCc::YUYV], uvc_controls());
    let msg = camera(&node)
        .with_format(Some("RGGB"))
        .configure(&config(64, 48, 8))
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("RGGB not offered") && msg.contains("YUYV"),
        "{msg}"
    );
}

#[test]
fn a_size_the_device_adjusts_is_an_error_naming_both() {
    let node = SimNode::new(&[FourCc::GREY], uvc_controls());
    node.sim().max_size = (1280, 720);
    let msg = camera(&node)
        .configure(&config(1920, 1080, 8))
        .unwrap_err()
        .to_string();
    for part in [NAME, "1920×1080", "1280×720"] {
        assert!(msg.contains(part), "{msg:?} lacks {part:?}");
    }
}

#[test]
fn exposure_is_set_in_100_us_after_manual_mode_and_gain_at_its_minimum() {
    let node = SimNode::new(&[FourCc::GREY], uvc_controls());
    node.sim().values.insert(CID_GAIN, 64);
    let mut cam = camera(&node);
    let c = CameraConfig {
        exposure_us: 33_040.0,
        ..config(64, 48, 8)
    };
    cam.configure(&c).unwrap();
    assert_eq!(
        node.sim().log,
        [
            (CID_EXPOSURE_AUTO, 1),
            (CID_EXPOSURE_AUTO_PRIORITY, 0),
            (CID_EXPOSURE_ABSOLUTE, 330),
            (CID_GAIN, 0),
        ]
    );
    cam.start().unwrap();
    // The exposure set, not the one asked for.
    assert_eq!(take(&mut cam).unwrap().exposure_us, 33_000.0);
}

#[test]
fn exposure_out_of_range_names_the_setting_and_the_range() {
    let node = SimNode::new(&[FourCc::GREY], uvc_controls());
    for exposure_us in [250_000.0, 100.0] {
        let c = CameraConfig {
            exposure_us,
            ..config(64, 48, 8)
        };
        let e = camera(&node).configure(&c).unwrap_err();
        assert!(
            matches!(&e, DeviceError::Unsupported { setting, .. } if setting == "exposure_ms"),
            "{e}"
        );
        let msg = e.to_string();
        assert!(msg.contains("0.3000 ms..=204.7000 ms"), "{msg}");
    }
}

#[test]
fn exposure_in_lines_uses_the_line_time() {
    let mut controls = vec![
        control(CID_EXPOSURE, "Exposure", ControlKind::Integer, 4, 3000),
        control(
            CID_HBLANK,
            "Horizontal Blanking",
            ControlKind::Integer,
            100,
            100,
        ),
        control(
            CID_PIXEL_RATE,
            "Pixel Rate",
            ControlKind::Integer64,
            0,
            i64::MAX,
        ),
    ];
    controls[2].read_only = true;
    let node = SimNode::new(&[FourCc::GREY], controls.clone());
    node.sim()
        .values
        .extend([(CID_HBLANK, 100), (CID_PIXEL_RATE, 100_000_000)]);
    let c = CameraConfig {
        exposure_us: 10_000.0,
        ..config(1900, 1000, 8)
    };
    // Line time (1900 + 100) px / 100 Mpx/s = 20 µs: 500 lines.
    camera(&node).configure(&c).unwrap();
    assert_eq!(node.sim().log, [(CID_EXPOSURE, 500)]);
    let over = CameraConfig {
        exposure_us: 70_000.0,
        ..c
    };
    let msg = camera(&node).configure(&over).unwrap_err().to_string();
    assert!(msg.contains("0.0800 ms..=60.0000 ms"), "{msg}");

    let node = SimNode::new(&[FourCc::GREY], controls[..1].to_vec());
    let msg = camera(&node).configure(&c).unwrap_err().to_string();
    assert!(msg.contains("no HBLANK and PIXEL_RATE"), "{msg}");
    let node = SimNode::new(&[FourCc::GREY], Vec::new());
    let msg = camera(&node).configure(&c).unwrap_err().to_string();
    assert!(
        msg.contains("exposure_ms") && msg.contains("no EXPOSURE"),
        "{msg}"
    );
}

#[test]
fn gain_other_than_0_db_is_refused_naming_the_control_range() {
    let node = SimNode::new(&[FourCc::GREY], uvc_controls());
    let c = CameraConfig {
        gain_db: 6.0,
        ..config(64, 48, 8)
    };
    let e = camera(&node).configure(&c).unwrap_err();
    assert!(matches!(&e, DeviceError::Unsupported { setting, .. } if setting == "gain_db"));
    assert!(
        e.to_string().contains("Gain is in driver units (0..=255)"),
        "{e}"
    );
    let mut controls = uvc_controls();
    controls.retain(|c| c.id != CID_GAIN);
    let node = SimNode::new(&[FourCc::GREY], controls);
    camera(&node).configure(&config(64, 48, 8)).unwrap();
    let msg = camera(&node).configure(&c).unwrap_err().to_string();
    assert!(msg.contains("no gain control"), "{msg}");
}

#[test]
fn a_line_trigger_needs_a_trigger_control_and_counts_by_sequence() {
    let line = CameraConfig {
        trigger: TriggerSource::Line,
        ..config(32, 16, 8)
    };
    // A trigger delay is not a trigger mode.
    let mut controls = uvc_controls();
    controls.push(control(
        0x0099_1002,
        "Trigger Delay",
        ControlKind::Integer,
        0,
        1000,
    ));
    let node = SimNode::new(&[FourCc::GREY], controls);
    let e = camera(&node).configure(&line).unwrap_err();
    assert!(matches!(&e, DeviceError::Unsupported { setting, .. } if setting == "trigger"));
    assert!(e.to_string().contains(NODE), "{e}");

    let mut controls = uvc_controls();
    controls.push(control(
        0x0099_1001,
        "Trigger Mode",
        ControlKind::Boolean,
        0,
        1,
    ));
    let node = SimNode::new(&[FourCc::GREY], controls);
    node.sim().lost.insert(2);
    let mut cam = camera(&node);
    cam.configure(&line).unwrap();
    assert!(node.sim().log.contains(&(0x0099_1001, 1)));
    cam.start().unwrap();
    assert!(matches!(
        cam.trigger(),
        Err(DeviceError::Unsupported { .. })
    ));
    let counters: Vec<u64> = (0..3)
        .map(|_| cam.next_frame(WAIT).unwrap().counter)
        .collect();
    // Frame 2 was lost: the gap shows.
    assert_eq!(counters, [0, 1, 3]);
}

#[test]
fn frames_exposed_before_the_trigger_are_dropped() {
    for stamp in [StampSource::StartOfExposure, StampSource::EndOfFrame] {
        let node = SimNode::new(&[FourCc::GREY], uvc_controls());
        node.sim().stamp = stamp;
        let mut cam = camera(&node);
        cam.configure(&config(32, 16, 8)).unwrap();
        cam.start().unwrap();
        // Frames 0–2 are done and queued, frame 3 is exposing when the trigger comes.
        node.advance(PERIOD * 34 / 10);
        let f = take(&mut cam).unwrap();
        assert_eq!(sequence_of(&f.pixels), 4, "{stamp:?}");
        assert_eq!(f.pixels, gray8(32, 16, 4));
        assert_eq!(
            f.timestamp_ns,
            (node.sim().origin + PERIOD * 4).as_nanos() as u64
                + match stamp {
                    StampSource::StartOfExposure => 0,
                    StampSource::EndOfFrame => PERIOD.as_nanos() as u64,
                }
        );
    }
}

#[test]
fn a_frame_lost_after_the_trigger_is_a_counter_gap_and_one_before_is_not() {
    let (mut cam, node) = streaming(&[FourCc::GREY], &config(32, 16, 8));
    let first = take(&mut cam).unwrap();
    let s0 = sequence_of(&first.pixels);
    node.sim().lost.insert(s0 + 2);
    // Frame s0 + 1 is exposing at the trigger (stale), s0 + 2 is lost, s0 + 3 comes.
    node.advance(PERIOD / 2);
    let f = take(&mut cam).unwrap();
    assert_eq!(sequence_of(&f.pixels), s0 + 3);
    assert_eq!(f.counter, first.counter + 2);
    // Idle for 20 frames: the 4 buffers fill and the kernel loses the rest, all before
    // the trigger.
    node.advance(PERIOD * 20);
    let g = take(&mut cam).unwrap();
    assert!(sequence_of(&g.pixels) > s0 + 20);
    assert_eq!(g.counter, f.counter + 1);
}

#[test]
fn an_error_flag_or_a_short_buffer_is_incomplete_and_the_retry_works() {
    let (mut cam, node) = streaming(&[FourCc::GREY], &config(32, 16, 8));
    node.sim().flagged.insert(0);
    node.sim().short.insert(1);
    for (seq, what) in [(0, "ERROR"), (1, "bytes")] {
        let e = take(&mut cam).unwrap_err();
        assert!(
            matches!(e, DeviceError::Incomplete { .. }) && e.retryable(),
            "{e}"
        );
        let msg = e.to_string();
        assert!(
            msg.contains(NAME) && msg.contains(&format!("buffer {seq} ")) && msg.contains(what),
            "{msg}"
        );
    }
    let f = take(&mut cam).unwrap();
    assert_eq!(f.pixels, gray8(32, 16, 2));
}

#[test]
fn a_vanishing_device_is_gone_naming_the_camera() {
    let (mut cam, node) = streaming(&[FourCc::GREY], &config(32, 16, 8));
    node.sim().vanish_at = Some(2);
    for seq in 0..2 {
        assert_eq!(sequence_of(&take(&mut cam).unwrap().pixels), seq);
    }
    let e = take(&mut cam).unwrap_err();
    assert!(
        matches!(e, DeviceError::Gone { .. }) && !e.retryable(),
        "{e}"
    );
    let msg = e.to_string();
    assert!(msg.contains(NAME) && msg.contains(NODE), "{msg}");
    assert!(matches!(take(&mut cam), Err(DeviceError::Gone { .. })));
}

#[test]
fn no_frame_in_time_is_a_timeout_and_the_trigger_still_holds() {
    let (mut cam, _node) = streaming(&[FourCc::GREY], &config(32, 16, 8));
    cam.trigger().unwrap();
    let e = cam.next_frame(PERIOD / 2).unwrap_err();
    assert!(
        matches!(e, DeviceError::Timeout { .. }) && e.retryable(),
        "{e}"
    );
    assert_eq!(sequence_of(&cam.next_frame(WAIT).unwrap().pixels), 0);
}

#[test]
fn frame_pixels_reads_supported_formats_and_refuses_the_rest() {
    // 2×2 YUYV, stride 6: luma 1 2 / 5 6, chroma and padding must not show.
    let yuyv = [1, 90, 2, 91, 0, 0, 5, 92, 6, 93];
    assert_eq!(
        frame_pixels(FourCc::YUYV, &yuyv, 2, 2, 6),
        Some(Pixels::Gray8(vec![1, 2, 5, 6]))
    );
    let y16 = [0x34, 0x12, 0xff, 0x0f];
    assert_eq!(
        frame_pixels(FourCc::Y12, &y16, 2, 1, 4),
        Some(Pixels::Gray16(vec![0x1234, 0x0fff]))
    );
    assert_eq!(frame_pixels(FourCc::YUYV, &yuyv[..9], 2, 2, 6), None);
    assert_eq!(frame_pixels(FourCc(*b"H264"), &yuyv, 2, 2, 6), None);
    // Not a JPEG: refused, not a frame of garbage.
    assert_eq!(frame_pixels(FourCc::MJPG, &yuyv, 2, 2, 6), None);
}

#[test]
fn describe_names_card_driver_and_formats() {
    let node = SimNode::new(&[FourCc::YUYV, FourCc(*b"MJPG")], Vec::new());
    assert_eq!(
        describe(&node).unwrap(),
        "Sim Cam (uvcvideo, usb-sim-1): YUYV MJPG; hexcal takes for 8 bits YUYV > MJPG \
         (the first that keeps the size)"
    );
}

/// One simulated projector (the engine needs one) and a simulated camera the test replaces.
fn rig() -> RigFile {
    let camera = SimDevice::new("unused", (64, 48), [300.0, 300.0, 31.5, 23.5]);
    tiny()
        .named("v4l2-sim")
        .with("poses.count = 1")
        .without(&["front", "back", "p1"])
        .camera(camera.with("exposure_ms = 5.0"))
        .parse()
        .unwrap()
}

/// One pose through the capture engine with a V4L2 camera on a simulated node that loses
/// frames `lost`: the timeline and, per frame, its counter and the node's sequence number.
fn capture_through_engine(lost: &[u32]) -> (hexcal_core::dataset::Timeline, Vec<(u64, u32)>) {
    let rig = rig();
    let opened = crate::rig::open(&rig).unwrap();
    let node = SimNode::new(&[FourCc::YUYV], uvc_controls());
    node.sim().lost.extend(lost);
    let timing = CaptureTiming {
        settle: Duration::ZERO,
        latency: vec![Duration::ZERO],
        frame_timeout: WAIT,
        retries: 0,
        repeats: 1,
    };
    let devices = RigDevices {
        cameras: vec![Box::new(camera(&node))],
        configs: vec![config(64, 48, 8)],
        projectors: opened.devices.projectors,
        trigger: None,
        timing,
    };
    let mut session = Session::start(devices, &opened.sequence).unwrap();
    let mut frames = Vec::new();
    let timeline = session
        .capture_pose(0, &mut |f| {
            let seq = sequence_of(&f.frame.pixels);
            assert_eq!(f.index, frames.len());
            assert_eq!(f.frame.pixels, gray8(64, 48, seq), "frame {}", f.index);
            frames.push((f.frame.counter, seq));
            Ok(())
        })
        .unwrap();
    session.finish().unwrap();
    assert_eq!(node.sim().buffers, 0, "stopped");
    (timeline, frames)
}

#[test]
fn the_capture_engine_takes_frames_in_order_through_the_driver() {
    let (timeline, frames) = capture_through_engine(&[]);
    assert_eq!(frames.len(), timeline.frames.len());
    assert!(frames.len() > 10);
    assert_eq!(timeline.dropped, 0);
    for (k, w) in frames.windows(2).enumerate() {
        assert_eq!(w[1].0, w[0].0 + 1, "counters at frame {k}");
        assert!(w[1].1 > w[0].1, "sequence at frame {k}");
    }
    // The node loses the frame the engine takes as frame 5: the next one stands in, and
    // the engine sees one frame dropped.
    let (timeline, lossy) = capture_through_engine(&[frames[5].1]);
    assert_eq!(lossy.len(), frames.len());
    assert_eq!(timeline.dropped, 1);
    assert_eq!(lossy[5].0, lossy[4].0 + 2);
    assert_eq!(lossy[5].1, frames[5].1 + 1);
}
