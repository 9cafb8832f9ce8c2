//! A real GigE Vision camera on 127.0.0.1 inside this process (Aravis' `GvFakeCamera`),
//! serving frames we give it through the real protocol (GVCP control, GVSP stream, packet
//! resend), and the loopback benchmark.
//!
//! Takes the frames to serve (8-bit samples for Mono8 or a Bayer…8 mosaic, 16-bit for
//! Mono16; one per trigger, in turn) and gives a camera
//! the driver opens at [`LOOPBACK_ADDRESS`]; its packet loss can be raised to test resend
//! and incomplete frames. One loopback camera at a time per machine (it listens on the
//! GVCP port of 127.0.0.1).

use super::AravisCamera;
use crate::rig::device::{Camera, CameraConfig, DeviceError, TriggerSource};
use aravis::glib::translate::ToGlibPtr;
use aravis::GvFakeCamera;
use hexcal_core::images::Pixels;
use std::fmt;
use std::os::raw::c_void;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// The address the loopback camera answers on.
pub const LOOPBACK_ADDRESS: &str = "127.0.0.1";

/// How often the fake camera looks for a software trigger (its default is 25 Hz).
const TRIGGER_POLL_HZ: f64 = 2000.0;

/// A scene a loopback camera sees: the frame it takes at an exposure (µs), called on the fake
/// camera's stream thread at each frame.
pub type LiveScene = Box<dyn Fn(f64) -> Pixels + Send + Sync>;

/// What a loopback camera serves.
enum Served {
    /// Frame k of the stream is `frames[k % len]`.
    Frames(Vec<Pixels>),
    /// Each frame rendered when it is taken, at the exposure the camera is set to then.
    Scene(LiveScene),
}

/// The frames a loopback camera serves, shared with the fake camera's stream thread.
struct FrameSource {
    served: Served,
    next: AtomicUsize,
    mismatches: AtomicUsize,
}

/// A GigE Vision camera on 127.0.0.1 serving the frames it was given, one per trigger.
pub struct LoopbackCamera {
    fake: GvFakeCamera,
    source: *mut FrameSource,
}

// SAFETY: `source` is owned by this value and only read (atomics, immutable frames) by the
// fake camera's thread; `GvFakeCamera` is Send.
unsafe impl Send for LoopbackCamera {}

impl LoopbackCamera {
    /// Start a camera with serial number `serial` serving `frames` in turn (frame k of the
    /// stream is `frames[k % len]`). The driver's configuration must match the frames'
    /// size and sample type (Mono8 or BayerRG8 / GR8 / GB8 / BG8 for `Gray8`, Mono16 for
    /// `Gray16`); a frame that does
    /// not is sent as zeros and counted in [`mismatches`](Self::mismatches).
    pub fn start(serial: &str, frames: Vec<Pixels>) -> Result<Self, DeviceError> {
        if frames.is_empty() {
            return Err(DeviceError::Failed {
                device: format!("loopback camera {serial}"),
                reason: "no frames to serve".into(),
            });
        }
        Self::serve(serial, Served::Frames(frames))
    }

    /// Start a camera that sees `scene`: each frame is what the scene gives at the exposure
    /// (µs) the driver has set through GenICam's `ExposureTime` when the frame is taken (the
    /// sensor end of the driver's exposure control). Sizes as for [`Self::start`].
    pub fn start_scene(serial: &str, scene: LiveScene) -> Result<Self, DeviceError> {
        Self::serve(serial, Served::Scene(scene))
    }

    fn serve(serial: &str, served: Served) -> Result<Self, DeviceError> {
        let error = |reason: String| DeviceError::Failed {
            device: format!("loopback camera {serial}"),
            reason,
        };
        let fake = GvFakeCamera::new(Some(LOOPBACK_ADDRESS), Some(serial));
        if !fake.is_running() {
            return Err(error(format!(
                "cannot listen on {LOOPBACK_ADDRESS} (another GigE Vision camera there?)"
            )));
        }
        let camera = fake
            .fake_camera()
            .ok_or_else(|| error("no fake camera inside".into()))?;
        camera.set_trigger_frequency(TRIGGER_POLL_HZ);
        let source = Box::into_raw(Box::new(FrameSource {
            served,
            next: AtomicUsize::new(0),
            mismatches: AtomicUsize::new(0),
        }));
        // SAFETY: `source` lives until `drop`, which removes the callback first.
        unsafe {
            aravis_sys::arv_fake_camera_set_fill_pattern(
                camera.to_glib_none().0,
                Some(fill),
                source.cast(),
            );
        }
        Ok(LoopbackCamera { fake, source })
    }

    /// Drop this fraction (0–1) of the GVSP packets it sends.
    pub fn set_packet_loss(&self, ratio: f64) {
        self.fake.set_gvsp_lost_ratio(ratio);
    }

    /// A rising edge on the camera's trigger input line: with TriggerMode On and its line
    /// source (`Line0`, what the driver selects for a line-triggered camera) the camera
    /// exposes one frame. The fake camera has no line input of its own, so the edge is
    /// delivered through its software-trigger register, switching the source to Software
    /// until the camera took the trigger (within `timeout`). Refused, naming the registers,
    /// when the camera is not waiting for a line trigger or does not take it.
    pub fn pulse_line(&self, timeout: Duration) -> Result<(), DeviceError> {
        use aravis_sys::{
            ARV_FAKE_CAMERA_REGISTER_TRIGGER_MODE as MODE,
            ARV_FAKE_CAMERA_REGISTER_TRIGGER_SOFTWARE as SOFTWARE,
            ARV_FAKE_CAMERA_REGISTER_TRIGGER_SOURCE as SOURCE,
        };
        const LINE0: u32 = 0;
        const SOFTWARE_SOURCE: u32 = 1;
        let error = |reason: String| DeviceError::Failed {
            device: "loopback camera line input".into(),
            reason,
        };
        let camera = self
            .fake
            .fake_camera()
            .ok_or_else(|| error("no fake camera inside".into()))?;
        let raw = camera.to_glib_none().0;
        // SAFETY: `raw` is a live fake camera (held by `camera`); its registers are plain
        // memory words, read and written whole.
        let read = |address: i32| unsafe {
            let mut value = 0u32;
            aravis_sys::arv_fake_camera_read_register(raw, address as u32, &mut value);
            value
        };
        // SAFETY: as above.
        let write = |address: i32, value: u32| unsafe {
            aravis_sys::arv_fake_camera_write_register(raw, address as u32, value);
        };
        let (mode, source) = (read(MODE), read(SOURCE));
        if mode != 1 || source != LINE0 {
            return Err(error(format!(
                "the camera is not waiting for a line trigger (TriggerMode {mode}, \
                 TriggerSource {source}; Line0 is 0)"
            )));
        }
        write(SOURCE, SOFTWARE_SOURCE);
        write(SOFTWARE, 1);
        let deadline = Instant::now() + timeout;
        // The camera clears the register when it takes the trigger.
        while read(SOFTWARE) != 0 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_micros(100));
        }
        let taken = read(SOFTWARE) == 0;
        write(SOFTWARE, 0);
        write(SOURCE, LINE0);
        if taken {
            Ok(())
        } else {
            Err(error(format!(
                "the camera did not take the pulse within {timeout:?} (acquisition stopped?)"
            )))
        }
    }

    /// Frames served so far.
    pub fn served(&self) -> usize {
        self.source().next.load(Ordering::SeqCst)
    }

    /// Frames that did not match the driver's configuration (sent as zeros).
    pub fn mismatches(&self) -> usize {
        self.source().mismatches.load(Ordering::SeqCst)
    }

    fn source(&self) -> &FrameSource {
        // SAFETY: owned by self, freed only in drop.
        unsafe { &*self.source }
    }
}

impl Drop for LoopbackCamera {
    fn drop(&mut self) {
        // SAFETY: resetting the callback takes the fake camera's fill lock, so once it
        // returns no fill is running with `source`, which is then freed exactly once.
        unsafe {
            if let Some(camera) = self.fake.fake_camera() {
                aravis_sys::arv_fake_camera_set_fill_pattern(
                    camera.to_glib_none().0,
                    None,
                    std::ptr::null_mut(),
                );
            }
            drop(Box::from_raw(self.source));
        }
    }
}

/// The fake camera's fill callback: copies the next frame into the buffer.
unsafe extern "C" fn fill(
    buffer: *mut aravis_sys::ArvBuffer,
    data: *mut c_void,
    exposure_us: u32,
    _gain: u32,
    format: aravis_sys::ArvPixelFormat,
) {
    let source = &*(data as *const FrameSource);
    let k = source.next.fetch_add(1, Ordering::SeqCst);
    let taken;
    let frame = match &source.served {
        Served::Frames(frames) => &frames[k % frames.len()],
        Served::Scene(scene) => {
            taken = scene(f64::from(exposure_us));
            &taken
        }
    };
    let width = aravis_sys::arv_buffer_get_image_width(buffer).max(0) as usize;
    let height = aravis_sys::arv_buffer_get_image_height(buffer).max(0) as usize;
    let mut received = 0usize;
    let out = aravis_sys::arv_buffer_get_data(buffer, &mut received).cast::<u8>();
    let samples = width * height;
    // The fake camera checked that the buffer holds width × height samples of `format`:
    // one byte each for the 8-bit formats (Mono8, Bayer…8), two for Mono16.
    let bytes_per_sample = ((format >> 16) & 0xFF) as usize / 8;
    let bytes: Vec<u8> = match (bytes_per_sample, frame) {
        (1, Pixels::Gray8(p)) if p.len() == samples => p.clone(),
        (2, Pixels::Gray16(p)) if p.len() == samples => {
            p.iter().flat_map(|v| v.to_le_bytes()).collect()
        }
        _ => {
            source.mismatches.fetch_add(1, Ordering::SeqCst);
            vec![0; samples * bytes_per_sample]
        }
    };
    if !out.is_null() {
        std::ptr::copy_nonoverlapping(bytes.as_ptr(), out, bytes.len());
    }
}

/// Frames per second through the loopback camera.
#[derive(Clone, Debug)]
pub struct LoopbackBench {
    /// Frame width (px).
    pub width: u32,
    /// Frame height (px).
    pub height: u32,
    /// Bits per sample (8 → Mono8, otherwise Mono16).
    pub bits: u8,
    /// Frames timed.
    pub frames: usize,
    /// Wall time for them (s).
    pub seconds: f64,
    /// Frames per second (trigger, transfer, check, one at a time).
    pub fps: f64,
    /// Image data rate (MB/s).
    pub megabytes_per_s: f64,
    /// GVSP packets resent on request.
    pub resent_packets: u64,
}

impl fmt::Display for LoopbackBench {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "aravis loopback {}×{} {}-bit: {} frames in {:.3} s = {:.1} frames/s ({:.1} MB/s), {} packets resent",
            self.width,
            self.height,
            self.bits,
            self.frames,
            self.seconds,
            self.fps,
            self.megabytes_per_s,
            self.resent_packets
        )
    }
}

/// Turn on Aravis' in-process "Fake" interface (no network), so that device discovery lists
/// its fake camera beside the real ones.
pub fn enable_fake_interface() {
    // SAFETY: a NUL-terminated interface name; Aravis copies what it needs.
    unsafe { aravis_sys::arv_enable_interface(c"Fake".as_ptr()) };
}

/// Distinct synthetic frame `k` (a diagonal ramp shifted by `k`, `k` in the first sample).
pub fn synthetic_frame(width: u32, height: u32, bits: u8, k: usize) -> Pixels {
    let (w, h) = (width as usize, height as usize);
    let ramp = |i: usize| (i % w) * 3 + (i / w) * 5 + k * 17;
    if bits == 8 {
        let mut p: Vec<u8> = (0..w * h).map(|i| ramp(i) as u8).collect();
        if let Some(first) = p.first_mut() {
            *first = k as u8;
        }
        Pixels::Gray8(p)
    } else {
        let max = (1usize << bits.min(16)) - 1;
        let mut p: Vec<u16> = (0..w * h).map(|i| ((ramp(i) * 13) & max) as u16).collect();
        if let Some(first) = p.first_mut() {
            *first = (k & max) as u16;
        }
        Pixels::Gray16(p)
    }
}

/// Time `frames` software-triggered frames of `width` × `height` (8 bits: Mono8, else
/// Mono16) through a loopback camera, one at a time as the capture loop takes them, each
/// checked sample for sample against what was served.
pub fn bench_loopback(
    width: u32,
    height: u32,
    bits: u8,
    frames: usize,
) -> Result<LoopbackBench, DeviceError> {
    const DISTINCT: usize = 4;
    const WARM_UP: usize = 3;
    let served: Vec<Pixels> = (0..DISTINCT)
        .map(|k| synthetic_frame(width, height, bits, k))
        .collect();
    let loopback = LoopbackCamera::start("HEXBENCH", served.clone())?;
    let mut camera = AravisCamera::open("loopback", LOOPBACK_ADDRESS)?;
    camera.configure(&CameraConfig {
        width,
        height,
        bits: if bits == 8 { 8 } else { 16 },
        exposure_us: 1000.0,
        gain_db: 0.0,
        trigger: TriggerSource::Software,
    })?;
    camera.start()?;
    let timeout = Duration::from_secs(2);
    let mut first = None;
    let mut start = Instant::now();
    for i in 0..WARM_UP + frames {
        if i == WARM_UP {
            start = Instant::now();
        }
        camera.trigger()?;
        let frame = camera.next_frame(timeout)?;
        let first = *first.get_or_insert(frame.counter);
        let k = (frame.counter - first) as usize;
        if frame.pixels != served[k % DISTINCT] {
            return Err(DeviceError::Failed {
                device: "loopback".into(),
                reason: format!("frame {} differs from the frame served", frame.counter),
            });
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    let resent_packets = camera.statistics().resent_packets;
    camera.stop()?;
    drop(camera);
    drop(loopback);
    let bytes = f64::from(width) * f64::from(height) * if bits == 8 { 1.0 } else { 2.0 };
    Ok(LoopbackBench {
        width,
        height,
        bits,
        frames,
        seconds,
        fps: frames as f64 / seconds,
        megabytes_per_s: frames as f64 * bytes / seconds / 1e6,
        resent_packets,
    })
}
