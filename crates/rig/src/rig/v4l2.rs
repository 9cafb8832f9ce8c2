//! Video4Linux2 cameras (docs/design.md §11), behind the cargo feature `v4l2`.
//!
//! Takes a camera's rig-file name and its device node (`/dev/videoN`) and gives a
//! [`Camera`]. Two layers: [`V4l2Device`] is the handful of device operations the driver
//! needs (capabilities, formats, controls, an mmap stream), implemented on the `v4l` crate
//! by [`node::Node`]; [`V4l2Camera`] is the driver logic, generic over that trait:
//!
//! - **Format.** The rig file's `format` (a fourcc) if it names one; else the best the node
//!   offers for the rig file's `bits` ([`candidates`]): monochrome (`GREY`, `Y10` / `Y12`,
//!   else `Y16`), then `YUYV` keeping its luma, then Bayer (`BA81` … `RG16`), then `RGB3` /
//!   `BGR3`, then `MJPG`, skipping a format the node sets at another size (UVC webcams
//!   often give their large sizes in MJPEG only). Every buffer becomes grey through
//!   [`hexcal_core::images::to_grey`] (little-endian words as [`Pixels::Gray16`] with the
//!   format's bits; Bayer balanced; RGB and MJPEG as luma). Nothing fitting is refused
//!   naming the camera, the request and what the device offers; a size no format keeps is
//!   an error naming both sizes.
//! - **Exposure.** `V4L2_CID_EXPOSURE_AUTO` set to manual (or shutter priority) first, and
//!   `V4L2_CID_EXPOSURE_AUTO_PRIORITY` off so the frame rate stays put; then
//!   `V4L2_CID_EXPOSURE_ABSOLUTE` in 100 µs units, or — for raw sensor drivers —
//!   `V4L2_CID_EXPOSURE` in lines, converted with the line time `(width + HBLANK) /
//!   PIXEL_RATE` when the node offers both. Out of range is refused naming the range in ms.
//! - **Gain.** `V4L2_CID_GAIN` (else `V4L2_CID_ANALOGUE_GAIN`) is in driver units with no
//!   general relation to dB, so the one mapping made is 0 dB = the control's minimum; other
//!   gains are refused naming the control and its range. Auto gain is switched off.
//! - **Trigger.** UVC / V4L2 cameras free-run. A software trigger means "the next frame
//!   whose exposure starts at or after this call": buffers exposed earlier are dequeued and
//!   dropped. The start of exposure is the buffer timestamp when the driver stamps the start
//!   of exposure (`TSTAMP_SRC_SOE`, as `uvcvideo` does), else the end-of-frame stamp less the
//!   exposure and one frame interval (measured between buffers; none before the second),
//!   which errs on the side of waiting one frame more. A timestamp on another clock than
//!   `CLOCK_MONOTONIC` (rare) is replaced by the time of dequeuing, which cannot tell a
//!   buffer done before the trigger from one done after: the capture engine drains every
//!   ready buffer before it triggers, which covers it. [`TriggerSource::Line`] needs a
//!   boolean (or 0–1 integer) device control whose name contains "trigger" (vendor
//!   drivers' "Trigger Mode"), set to 1; it is refused otherwise (V4L2 has no standard
//!   trigger control).
//! - **Frame counter.** Line-triggered: the buffer sequence number, unwrapped. Software:
//!   one more per triggered frame delivered, plus the frames the kernel lost (sequence gaps)
//!   whose exposure started after the trigger, so a gap is a frame the engine missed, and the
//!   stale frames dropped on purpose are not. A frame taken with no trigger pending (the
//!   engine's drain) repeats the last counter: it is stale by definition.
//! - **Errors.** A buffer flagged `ERROR` or with fewer bytes than the format needs is
//!   [`DeviceError::Incomplete`]; a node that vanished (`ENODEV`, `ENXIO`, or `EIO` from a
//!   queue the kernel put in its error state) is [`DeviceError::Gone`] naming the camera and
//!   node; no buffer in time is [`DeviceError::Timeout`].
//!
//! [`describe`] gives a node's card, driver and formats for `hexcal devices`;
//! [`frame_pixels`] converts one buffer.

pub mod node;
#[cfg(test)]
mod tests;

pub use node::Node;

use super::device::{Camera, CameraConfig, DeviceError, TriggerSource};
use hexcal_core::images::to_grey::{to_grey, BayerBalance, Cfa, Colour, Packing, SampleFormat};
use hexcal_core::images::{CameraFrame, Pixels};
use hexcal_core::Invalid;
use std::fmt;
use std::io;
use std::time::Duration;

/// Buffers in the mmap stream: enough to absorb a burst while the capture loop copies.
pub const STREAM_BUFFERS: u32 = 4;

/// `V4L2_CID_EXPOSURE` (user class; driver units, lines for raw sensors).
pub const CID_EXPOSURE: u32 = 0x0098_0911;
/// `V4L2_CID_AUTOGAIN`.
pub const CID_AUTOGAIN: u32 = 0x0098_0912;
/// `V4L2_CID_GAIN` (driver units).
pub const CID_GAIN: u32 = 0x0098_0913;
/// `V4L2_CID_EXPOSURE_AUTO` (menu: 0 auto, 1 manual, 2 shutter priority, 3 aperture
/// priority).
pub const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
/// `V4L2_CID_EXPOSURE_ABSOLUTE` (100 µs units).
pub const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
/// `V4L2_CID_EXPOSURE_AUTO_PRIORITY` (may the camera lower its frame rate for exposure).
pub const CID_EXPOSURE_AUTO_PRIORITY: u32 = 0x009a_0903;
/// `V4L2_CID_HBLANK` (pixels).
pub const CID_HBLANK: u32 = 0x009e_0902;
/// `V4L2_CID_ANALOGUE_GAIN` (driver units).
pub const CID_ANALOGUE_GAIN: u32 = 0x009e_0903;
/// `V4L2_CID_PIXEL_RATE` (pixels per second).
pub const CID_PIXEL_RATE: u32 = 0x009f_0902;

const EXPOSURE_MANUAL: i64 = 1;
const EXPOSURE_SHUTTER_PRIORITY: i64 = 2;

/// A V4L2 pixel format code (fourcc), e.g. `GREY`.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct FourCc(pub [u8; 4]);

impl FourCc {
    /// 8-bit greyscale.
    pub const GREY: FourCc = FourCc(*b"GREY");
    /// 10-bit greyscale in 16-bit little-endian words.
    pub const Y10: FourCc = FourCc(*b"Y10 ");
    /// 12-bit greyscale in 16-bit little-endian words.
    pub const Y12: FourCc = FourCc(*b"Y12 ");
    /// 16-bit greyscale, little-endian.
    pub const Y16: FourCc = FourCc(*b"Y16 ");
    /// YUV 4:2:2 interleaved Y0 U Y1 V.
    pub const YUYV: FourCc = FourCc(*b"YUYV");
    /// Motion JPEG: one JPEG per frame.
    pub const MJPG: FourCc = FourCc(*b"MJPG");
}

impl fmt::Display for FourCc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s: String = self
            .0
            .iter()
            .map(|&b| if b.is_ascii_graphic() { b as char } else { '?' })
            .collect();
        f.write_str(s.trim_end_matches('?'))
    }
}

impl fmt::Debug for FourCc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "FourCc({self})")
    }
}

/// What a node says it is (`VIDIOC_QUERYCAP`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Capabilities {
    /// Kernel driver, e.g. `uvcvideo`.
    pub driver: String,
    /// Device name, e.g. the camera's model.
    pub card: String,
    /// Bus address.
    pub bus: String,
    /// Whether the node captures video (single-planar).
    pub capture: bool,
    /// Whether it streams (mmap I/O).
    pub streaming: bool,
}

/// An image format (`VIDIOC_S_FMT` request or answer).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Format {
    /// Pixel format.
    pub fourcc: FourCc,
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Bytes per row, padding included (`bytesperline`; 0 in a request: the device's
    /// choice).
    pub stride: u32,
}

/// The value type of a control.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ControlKind {
    /// Integer in `min..=max` in steps of `step`.
    Integer,
    /// 64-bit integer (read-only rates, for instance).
    Integer64,
    /// 0 or 1.
    Boolean,
    /// Menu: the indices the device offers.
    Menu(Vec<i64>),
    /// Any other type (buttons, strings, compound): never set by the driver.
    Other,
}

/// One control a node offers (`VIDIOC_QUERY_EXT_CTRL`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ControlInfo {
    /// Control id (`V4L2_CID_*`).
    pub id: u32,
    /// Name as the driver gives it.
    pub name: String,
    /// Value type.
    pub kind: ControlKind,
    /// Minimum.
    pub min: i64,
    /// Maximum.
    pub max: i64,
    /// Step (≥ 1).
    pub step: u64,
    /// Read-only (or disabled).
    pub read_only: bool,
}

impl ControlInfo {
    /// Whether `value` is within the range and on a step.
    pub fn allows(&self, value: i64) -> bool {
        match &self.kind {
            ControlKind::Menu(items) => items.contains(&value),
            _ => {
                let step = self.step.max(1) as i128;
                (self.min..=self.max).contains(&value)
                    && (i128::from(value) - i128::from(self.min)) % step == 0
            }
        }
    }
}

/// Where a buffer's timestamp was taken.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StampSource {
    /// Start of exposure (`V4L2_BUF_FLAG_TSTAMP_SRC_SOE`).
    StartOfExposure,
    /// End of frame (`V4L2_BUF_FLAG_TSTAMP_SRC_EOF`, the default).
    EndOfFrame,
}

/// A dequeued buffer's metadata (`struct v4l2_buffer`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BufferMeta {
    /// Sequence number: one more per frame the device produced (a gap: frames lost).
    pub sequence: u32,
    /// Timestamp.
    pub timestamp: Duration,
    /// Whether the timestamp is on `CLOCK_MONOTONIC` (else it is not comparable with
    /// [`V4l2Device::now`]).
    pub monotonic: bool,
    /// Where the timestamp was taken.
    pub source: StampSource,
    /// Bytes of image data.
    pub bytes_used: u32,
    /// The driver flagged the data as corrupted (`V4L2_BUF_FLAG_ERROR`).
    pub error: bool,
    /// When it was dequeued ([`V4l2Device::now`]).
    pub arrival: Duration,
}

/// The device operations the driver needs: [`Node`] does them on a real `/dev/video*`
/// through the `v4l` crate; tests use a simulated node. Errors are the kernel's (`ENODEV`
/// when the device vanished, [`io::ErrorKind::TimedOut`] when no buffer came in time).
pub trait V4l2Device: Send {
    /// What the node is.
    fn capabilities(&self) -> io::Result<Capabilities>;
    /// Capture pixel formats the node offers.
    fn formats(&self) -> io::Result<Vec<FourCc>>;
    /// Ask for `format`; gives what the device set (it may adjust size and stride).
    fn set_format(&mut self, format: Format) -> io::Result<Format>;
    /// The node's controls.
    fn controls(&self) -> io::Result<Vec<ControlInfo>>;
    /// Current value of control `id`.
    fn control(&self, id: u32) -> io::Result<i64>;
    /// Set `control` to `value`.
    fn set_control(&mut self, control: &ControlInfo, value: i64) -> io::Result<()>;
    /// Allocate `buffers` mmap buffers, queue them and start streaming.
    fn start(&mut self, buffers: u32) -> io::Result<()>;
    /// Give back the buffer dequeued last (if any) and dequeue the next one, waiting at most
    /// `timeout`; the data stays valid until the next call.
    fn dequeue(&mut self, timeout: Duration) -> io::Result<(&[u8], BufferMeta)>;
    /// Stop streaming and free the buffers.
    fn stop(&mut self) -> io::Result<()>;
    /// Now, on the clock of monotonic buffer timestamps (`CLOCK_MONOTONIC`).
    fn now(&self) -> Duration;
}

/// The pixel formats the driver reads, by fourcc: `GREY`, `Y10`, `Y12`, `Y16` (16-bit
/// little-endian words), `YUYV` (its luma); Bayer `BA81` `GBRG` `GRBG` `RGGB` (8 bits),
/// `BG10` `GB10` `BA10` `RG10`, `BG12` `GB12` `BA12` `RG12`, `BYR2` `GB16` `GR16` `RG16`
/// (16-bit words); `RGB3`, `BGR3` (24-bit RGB / BGR); `MJPG` (its luma).
pub fn pixel_formats() -> Vec<(FourCc, SampleFormat)> {
    use Packing::{U16Le, U8};
    let mono = |code: &[u8; 4], packing, bits| (FourCc(*code), SampleFormat::mono(packing, bits));
    let bayer = |code: &[u8; 4], cfa, packing, bits| {
        (FourCc(*code), SampleFormat::bayer(cfa, packing, bits))
    };
    vec![
        mono(b"GREY", U8, 8),
        mono(b"Y10 ", U16Le, 10),
        mono(b"Y12 ", U16Le, 12),
        mono(b"Y16 ", U16Le, 16),
        (FourCc::YUYV, SampleFormat::bytes(Colour::YuyvLuma)),
        bayer(b"BA81", Cfa::Bggr, U8, 8),
        bayer(b"GBRG", Cfa::Gbrg, U8, 8),
        bayer(b"GRBG", Cfa::Grbg, U8, 8),
        bayer(b"RGGB", Cfa::Rggb, U8, 8),
        bayer(b"BG10", Cfa::Bggr, U16Le, 10),
        bayer(b"GB10", Cfa::Gbrg, U16Le, 10),
        bayer(b"BA10", Cfa::Grbg, U16Le, 10),
        bayer(b"RG10", Cfa::Rggb, U16Le, 10),
        bayer(b"BG12", Cfa::Bggr, U16Le, 12),
        bayer(b"GB12", Cfa::Gbrg, U16Le, 12),
        bayer(b"BA12", Cfa::Grbg, U16Le, 12),
        bayer(b"RG12", Cfa::Rggb, U16Le, 12),
        bayer(b"BYR2", Cfa::Bggr, U16Le, 16),
        bayer(b"GB16", Cfa::Gbrg, U16Le, 16),
        bayer(b"GR16", Cfa::Grbg, U16Le, 16),
        bayer(b"RG16", Cfa::Rggb, U16Le, 16),
        (FourCc(*b"RGB3"), SampleFormat::bytes(Colour::Rgb)),
        (FourCc(*b"BGR3"), SampleFormat::bytes(Colour::Bgr)),
        (FourCc::MJPG, SampleFormat::bytes(Colour::Jpeg)),
    ]
}

/// The formats to try for `bits`, best first: the rig file's `named` one alone, else every
/// offered format that gives `bits`, by [`SampleFormat::rank`]. The reason, naming the node
/// (`node`) and what it offers, when none fits.
pub fn candidates(
    named: Option<&str>,
    bits: u8,
    offered: &[FourCc],
    node: &str,
) -> Result<Vec<(FourCc, SampleFormat)>, Invalid> {
    let listing = offered
        .iter()
        .map(|f| f.to_string())
        .collect::<Vec<_>>()
        .join(", ");
    let known = pixel_formats();
    if let Some(name) = named {
        let Some(&(code, format)) = known.iter().find(|(c, _)| c.to_string() == name.trim()) else {
            return Err(Invalid(format!(
                "hexcal cannot read {name}; {node} offers {listing}"
            )));
        };
        if !offered.contains(&code) {
            return Err(Invalid(format!(
                "{name} not offered; {node} offers {listing}"
            )));
        }
        if format.rank(bits).is_none() {
            return Err(Invalid(format!(
                "{name} gives {} bits, the rig file asks {bits}",
                format.bits
            )));
        }
        return Ok(vec![(code, format)]);
    }
    let mut usable: Vec<_> = known
        .into_iter()
        .filter(|(c, f)| offered.contains(c) && f.rank(bits).is_some())
        .collect();
    usable.sort_by_key(|(_, f)| f.rank(bits));
    if usable.is_empty() {
        return Err(Invalid(format!(
            "no format gives {bits} bits; {node} offers {listing}"
        )));
    }
    Ok(usable)
}

/// Pixels of one frame of a format the driver reads ([`pixel_formats`]) from `data` with
/// `stride` bytes per row (a JPEG: the whole coded frame); `None` for another format or a
/// buffer that does not hold the frame. A Bayer mosaic is balanced by its own grey world.
pub fn frame_pixels(
    fourcc: FourCc,
    data: &[u8],
    width: usize,
    height: usize,
    stride: usize,
) -> Option<Pixels> {
    let (_, format) = pixel_formats().into_iter().find(|(c, _)| *c == fourcc)?;
    to_grey(
        &format,
        data,
        width,
        height,
        stride,
        &mut BayerBalance::default(),
    )
    .ok()
}

/// What `configure` settled on.
#[derive(Clone, Copy, Debug)]
struct Applied {
    format: Format,
    samples: SampleFormat,
    exposure_us: f64,
    trigger: TriggerSource,
}

impl Applied {
    /// Bytes a complete frame occupies (a JPEG: at least one).
    fn frame_bytes(&self) -> usize {
        let f = &self.format;
        match self.samples.row_bytes(f.width as usize) {
            Some(row) => (f.height as usize).saturating_sub(1) * f.stride as usize + row,
            None => 1,
        }
    }
}

/// The last buffer dequeued: its sequence number, timestamp and estimated start of
/// exposure.
#[derive(Clone, Copy, Debug)]
struct Seen {
    sequence: u32,
    stamp: Duration,
    start: Duration,
}

/// State of a running stream.
#[derive(Clone, Copy, Debug, Default)]
struct Stream {
    /// Software trigger waiting for its frame: when it was called (device clock).
    pending: Option<Duration>,
    /// Last buffer dequeued.
    last: Option<Seen>,
    /// Frame interval measured from consecutive buffers.
    interval: Option<Duration>,
    /// Counter of the last frame delivered.
    counter: Option<u64>,
}

/// A V4L2 camera: the driver logic over a [`V4l2Device`] ([`Node`] for a real one).
pub struct V4l2Camera<D: V4l2Device = Node> {
    name: String,
    address: String,
    device: D,
    applied: Option<Applied>,
    stream: Option<Stream>,
    /// The rig file's `format` (a fourcc), if it names one.
    format_name: Option<String>,
    /// White balance of a Bayer format, held from `start` to `stop`.
    balance: BayerBalance,
}

impl V4l2Camera<Node> {
    /// Open the device node `address` (`/dev/videoN`) under the rig file's `name`.
    pub fn open(name: &str, address: &str) -> Result<Self, DeviceError> {
        let node = Node::open(address).map_err(|e| DeviceError::Failed {
            device: name.to_string(),
            reason: format!("cannot open {address}: {e}"),
        })?;
        V4l2Camera::new(name, address, node)
    }
}

impl<D: V4l2Device> V4l2Camera<D> {
    /// The camera `name` on `device` (found at `address`); refused unless the node captures
    /// video by streaming.
    pub fn new(name: &str, address: &str, device: D) -> Result<Self, DeviceError> {
        let cam = V4l2Camera {
            name: name.to_string(),
            address: address.to_string(),
            device,
            applied: None,
            stream: None,
            format_name: None,
            balance: BayerBalance::default(),
        };
        let caps = cam
            .device
            .capabilities()
            .map_err(|e| cam.io_error("VIDIOC_QUERYCAP", e))?;
        if !caps.capture || !caps.streaming {
            return Err(cam.failed(format!(
                "{} ({}, {}) is not a streaming video capture node",
                cam.address, caps.card, caps.driver
            )));
        }
        Ok(cam)
    }

    /// Use the pixel format `fourcc` (from [`pixel_formats`]) rather than choosing one;
    /// `None` restores the choice.
    pub fn with_format(mut self, fourcc: Option<&str>) -> Self {
        self.format_name = fourcc.map(str::to_string);
        self
    }

    /// A kernel error while doing `what`: `Gone` when the node vanished, else `Failed`.
    fn io_error(&self, what: &str, e: io::Error) -> DeviceError {
        match e.raw_os_error() {
            Some(libc::ENODEV | libc::ENXIO) => DeviceError::Gone {
                device: self.name.clone(),
                reason: format!("{} vanished ({what}: {e})", self.address),
            },
            Some(libc::EIO) => DeviceError::Gone {
                device: self.name.clone(),
                reason: format!(
                    "{} stream in its error state, unplugged? ({what}: {e})",
                    self.address
                ),
            },
            _ => DeviceError::Failed {
                device: self.name.clone(),
                reason: format!("{what}: {e}"),
            },
        }
    }

    fn unsupported(&self, setting: &str, reason: String) -> DeviceError {
        DeviceError::unsupported(&self.name, setting, reason)
    }

    fn failed(&self, reason: String) -> DeviceError {
        DeviceError::failed(&self.name, reason)
    }

    /// Choose and set the pixel format for `bits` at `width`×`height`: the rig file's, else
    /// the first of [`candidates`] the device sets at that size.
    fn set_format(
        &mut self,
        width: u32,
        height: u32,
        bits: u8,
    ) -> Result<(Format, SampleFormat), DeviceError> {
        let offered = self
            .device
            .formats()
            .map_err(|e| self.io_error("VIDIOC_ENUM_FMT", e))?;
        let wanted = candidates(self.format_name.as_deref(), bits, &offered, &self.address)
            .map_err(|reason| self.unsupported("format", reason.into()))?;
        let mut refused = None;
        for (fourcc, samples) in wanted {
            match self.try_format(fourcc, samples, width, height)? {
                Ok(format) => return Ok((format, samples)),
                Err(e) => {
                    refused.get_or_insert(e);
                }
            }
        }
        Err(refused.unwrap_or_else(|| self.failed("no format to try".into())))
    }

    /// Set `fourcc` at `width`×`height`: the format set, or (inside) why the device would
    /// not keep that size.
    fn try_format(
        &mut self,
        fourcc: FourCc,
        samples: SampleFormat,
        width: u32,
        height: u32,
    ) -> Result<Result<Format, DeviceError>, DeviceError> {
        let asked = Format {
            fourcc,
            width,
            height,
            stride: 0,
        };
        let set = self
            .device
            .set_format(asked)
            .map_err(|e| self.io_error(&format!("VIDIOC_S_FMT {fourcc} {width}×{height}"), e))?;
        if (set.width, set.height) != (width, height) {
            return Ok(Err(self.unsupported(
                "width, height",
                format!(
                    "the rig file asks {width}×{height}; {} set {}×{} for {fourcc}",
                    self.address, set.width, set.height
                ),
            )));
        }
        if set.fourcc != fourcc {
            return Err(self.failed(format!("asked for {fourcc}, the device set {}", set.fourcc)));
        }
        let min_stride = samples.row_bytes(width as usize).unwrap_or(0) as u32;
        Ok(Ok(Format {
            stride: set.stride.max(min_stride),
            ..set
        }))
    }

    /// The value of control `id` (called `what`).
    fn read(&self, id: u32, what: &str) -> Result<i64, DeviceError> {
        self.device.control(id).map_err(|e| self.io_error(what, e))
    }

    /// Set `control` to `value` after checking its range; refused naming `setting`.
    fn set_checked(
        &mut self,
        setting: &str,
        control: &ControlInfo,
        value: i64,
        unit: impl Fn(i64) -> String,
    ) -> Result<(), DeviceError> {
        if control.read_only {
            return Err(self.unsupported(setting, format!("{} is read-only", control.name)));
        }
        if !control.allows(value) {
            return Err(self.unsupported(
                setting,
                format!(
                    "{} not possible ({} {}..={} in steps of {})",
                    unit(value),
                    control.name,
                    unit(control.min),
                    unit(control.max),
                    unit(control.step as i64)
                ),
            ));
        }
        self.device
            .set_control(control, value)
            .map_err(|e| self.io_error(&format!("{} = {value}", control.name), e))
    }

    /// Manual exposure of `exposure_us`; gives the exposure set (µs).
    fn set_exposure(
        &mut self,
        controls: &[ControlInfo],
        exposure_us: f64,
        width: u32,
    ) -> Result<f64, DeviceError> {
        let find = |id: u32| controls.iter().find(|c| c.id == id);
        if let Some(auto) = find(CID_EXPOSURE_AUTO) {
            let mode = [EXPOSURE_MANUAL, EXPOSURE_SHUTTER_PRIORITY]
                .into_iter()
                .find(|&m| auto.allows(m))
                .ok_or_else(|| {
                    self.unsupported(
                        "exposure_ms",
                        format!("{} offers no manual mode", auto.name),
                    )
                })?;
            self.set_checked("exposure_ms", auto, mode, |v| v.to_string())?;
        }
        if let Some(priority) = find(CID_EXPOSURE_AUTO_PRIORITY) {
            if priority.allows(0) && !priority.read_only {
                self.set_checked("exposure_ms", priority, 0, |v| v.to_string())?;
            }
        }
        let ms = |us: f64| format!("{:.4} ms", us / 1e3);
        if let Some(absolute) = find(CID_EXPOSURE_ABSOLUTE) {
            let units = (exposure_us / 100.0).round() as i64;
            self.set_checked("exposure_ms", absolute, units, |u| ms(100.0 * u as f64))?;
            let got = self.read(CID_EXPOSURE_ABSOLUTE, &absolute.name)?;
            return Ok(100.0 * got as f64);
        }
        if let Some(lines) = find(CID_EXPOSURE) {
            let (Some(_), Some(_)) = (find(CID_HBLANK), find(CID_PIXEL_RATE)) else {
                return Err(self.unsupported(
                    "exposure_ms",
                    format!(
                        "{} is in driver units and the node has no HBLANK and PIXEL_RATE \
                         to convert them",
                        lines.name
                    ),
                ));
            };
            let hblank = self.read(CID_HBLANK, "HBLANK")?;
            let rate = self.read(CID_PIXEL_RATE, "PIXEL_RATE")?;
            if rate <= 0 {
                return Err(self.failed(format!("PIXEL_RATE reads {rate}")));
            }
            let line_us = 1e6 * (i64::from(width) + hblank) as f64 / rate as f64;
            let value = (exposure_us / line_us).round() as i64;
            self.set_checked("exposure_ms", lines, value, |l| ms(l as f64 * line_us))?;
            let got = self.read(CID_EXPOSURE, &lines.name)?;
            return Ok(got as f64 * line_us);
        }
        Err(self.unsupported(
            "exposure_ms",
            "no EXPOSURE_ABSOLUTE or EXPOSURE control".into(),
        ))
    }

    /// Gain: auto off, 0 dB = the gain control's minimum (the only mapping V4L2's driver
    /// units allow in general).
    fn set_gain(&mut self, controls: &[ControlInfo], gain_db: f64) -> Result<(), DeviceError> {
        let find = |id: u32| controls.iter().find(|c| c.id == id);
        if let Some(auto) = find(CID_AUTOGAIN) {
            if !auto.read_only {
                self.set_checked("gain_db", auto, 0, |v| v.to_string())?;
            }
        }
        match find(CID_GAIN).or_else(|| find(CID_ANALOGUE_GAIN)) {
            Some(gain) if gain_db == 0.0 => {
                let min = gain.min;
                self.set_checked("gain_db", gain, min, |v| v.to_string())
            }
            Some(gain) => Err(self.unsupported(
                "gain_db",
                format!(
                    "{gain_db} dB: {} is in driver units ({}..={}); only 0 dB (its minimum) \
                     is mapped",
                    gain.name, gain.min, gain.max
                ),
            )),
            None if gain_db == 0.0 => Ok(()),
            None => Err(self.unsupported(
                "gain_db",
                format!("{gain_db} dB: the device has no gain control"),
            )),
        }
    }

    /// Free-run for software triggers; the trigger control on for line triggers.
    fn set_trigger(
        &mut self,
        controls: &[ControlInfo],
        trigger: TriggerSource,
    ) -> Result<(), DeviceError> {
        let control = controls.iter().find(|c| {
            c.name.to_ascii_lowercase().contains("trigger")
                && !c.read_only
                && match c.kind {
                    ControlKind::Boolean => true,
                    ControlKind::Integer => (c.min, c.max) == (0, 1),
                    _ => false,
                }
        });
        match (trigger, control) {
            (TriggerSource::Software, Some(c)) => {
                let c = c.clone();
                self.set_checked("trigger", &c, 0, |v| v.to_string())
            }
            (TriggerSource::Software, None) => Ok(()),
            (TriggerSource::Line, Some(c)) => {
                let c = c.clone();
                self.set_checked("trigger", &c, 1, |v| v.to_string())
            }
            (TriggerSource::Line, None) => Err(self.unsupported(
                "trigger",
                format!(
                    "a line trigger needs a trigger control (on/off); {} free-runs",
                    self.address
                ),
            )),
        }
    }

    /// Estimated start of exposure of a buffer (exposure time `exposure_us`).
    fn exposure_start(meta: &BufferMeta, exposure_us: f64, stream: &Stream) -> Duration {
        let before_end = Duration::from_secs_f64(1e-6 * exposure_us.max(0.0))
            + stream.interval.unwrap_or_default();
        match (meta.monotonic, meta.source) {
            (true, StampSource::StartOfExposure) => meta.timestamp,
            (true, StampSource::EndOfFrame) => meta.timestamp.saturating_sub(before_end),
            // A timestamp on another clock: when it arrived is all that is known.
            (false, _) => meta.arrival.saturating_sub(before_end),
        }
    }

    /// Frames the kernel lost between `last` and `seen` whose exposure started at or after
    /// `trigger` (their starts interpolated between the two).
    fn lost_after(last: Option<Seen>, seen: Seen, trigger: Duration) -> u64 {
        let Some(last) = last else { return 0 };
        let gap = u64::from(seen.sequence.wrapping_sub(last.sequence));
        if gap < 2 {
            return 0;
        }
        let span = seen.start.saturating_sub(last.start).as_nanos() as f64;
        (1..gap)
            .filter(|&j| {
                let start = last.start.as_nanos() as f64 + span * j as f64 / gap as f64;
                start >= trigger.as_nanos() as f64
            })
            .count() as u64
    }
}

impl<D: V4l2Device> Camera for V4l2Camera<D> {
    fn name(&self) -> &str {
        &self.name
    }

    fn configure(&mut self, config: &CameraConfig) -> Result<(), DeviceError> {
        if self.stream.is_some() {
            return Err(self.failed("configure while streaming: stop first".into()));
        }
        self.applied = None;
        let (format, samples) = self.set_format(config.width, config.height, config.bits)?;
        let controls = self
            .device
            .controls()
            .map_err(|e| self.io_error("VIDIOC_QUERY_EXT_CTRL", e))?;
        let exposure_us = self.set_exposure(&controls, config.exposure_us, format.width)?;
        self.set_gain(&controls, config.gain_db)?;
        self.set_trigger(&controls, config.trigger)?;
        self.applied = Some(Applied {
            format,
            samples,
            exposure_us,
            trigger: config.trigger,
        });
        Ok(())
    }

    fn set_exposure_gain(&mut self, exposure_us: f64, gain_db: f64) -> Result<(), DeviceError> {
        let Some(applied) = self.applied else {
            return Err(self.failed("exposure set before configure".into()));
        };
        let controls = self
            .device
            .controls()
            .map_err(|e| self.io_error("VIDIOC_QUERY_EXT_CTRL", e))?;
        let exposure_us = self.set_exposure(&controls, exposure_us, applied.format.width)?;
        self.set_gain(&controls, gain_db)?;
        if let Some(a) = self.applied.as_mut() {
            a.exposure_us = exposure_us;
        }
        Ok(())
    }

    fn pixel_format(&self) -> Option<String> {
        self.applied.map(|a| a.format.fourcc.to_string())
    }

    fn balances_colour(&self) -> bool {
        self.applied
            .is_some_and(|a| matches!(a.samples.colour, Colour::Bayer(_)))
    }

    fn start(&mut self) -> Result<(), DeviceError> {
        if self.applied.is_none() {
            return Err(self.failed("start before configure".into()));
        }
        if self.stream.is_some() {
            return Ok(());
        }
        self.device
            .start(STREAM_BUFFERS)
            .map_err(|e| self.io_error("VIDIOC_STREAMON", e))?;
        self.balance = BayerBalance::default();
        self.stream = Some(Stream::default());
        Ok(())
    }

    fn trigger(&mut self) -> Result<(), DeviceError> {
        DeviceError::check_software_trigger(&self.name, self.applied.as_ref().map(|a| a.trigger))?;
        let now = self.device.now();
        let Some(stream) = self.stream.as_mut() else {
            return Err(self.failed("trigger before start".into()));
        };
        stream.pending = Some(now);
        Ok(())
    }

    fn next_frame(&mut self, timeout: Duration) -> Result<CameraFrame, DeviceError> {
        let (Some(mut stream), Some(applied)) = (self.stream, self.applied) else {
            return Err(self.failed("next_frame before start".into()));
        };
        let begun = self.device.now();
        let result = loop {
            let waited = self.device.now().saturating_sub(begun);
            let left = timeout.saturating_sub(waited);
            let (data, meta) = match self.device.dequeue(left) {
                Ok(got) => got,
                Err(e) if e.kind() == io::ErrorKind::TimedOut => {
                    break Err(DeviceError::Timeout {
                        device: self.name.clone(),
                        timeout,
                    })
                }
                Err(e) => break Err(self.io_error("VIDIOC_DQBUF", e)),
            };
            if let Some(last) = stream.last {
                let gap = meta.sequence.wrapping_sub(last.sequence);
                if let (true, true, Some(dt)) = (
                    meta.monotonic,
                    gap > 0,
                    meta.timestamp.checked_sub(last.stamp),
                ) {
                    stream.interval = Some(dt / gap);
                }
            }
            let seen = Seen {
                sequence: meta.sequence,
                stamp: meta.timestamp,
                start: Self::exposure_start(&meta, applied.exposure_us, &stream),
            };
            let counter = match (applied.trigger, stream.pending) {
                (TriggerSource::Line, _) => match (stream.counter, stream.last) {
                    (Some(c), Some(l)) => c + u64::from(meta.sequence.wrapping_sub(l.sequence)),
                    _ => u64::from(meta.sequence),
                },
                (TriggerSource::Software, Some(trigger)) => {
                    if seen.start < trigger {
                        // Exposed before the trigger: stale, drop it.
                        stream.last = Some(seen);
                        continue;
                    }
                    stream.pending = None;
                    let lost = Self::lost_after(stream.last, seen, trigger);
                    stream.counter.map_or(lost, |c| c + 1 + lost)
                }
                // Free-running with no trigger pending: not a frame of the triggered series.
                (TriggerSource::Software, None) => stream.counter.unwrap_or(0),
            };
            stream.last = Some(seen);
            stream.counter = Some(counter);
            if meta.error {
                break Err(DeviceError::Incomplete {
                    device: self.name.clone(),
                    reason: format!("buffer {} flagged ERROR by the driver", meta.sequence),
                });
            }
            let need = applied.frame_bytes();
            if (meta.bytes_used as usize) < need || data.len() < need {
                break Err(DeviceError::Incomplete {
                    device: self.name.clone(),
                    reason: format!(
                        "buffer {} has {} bytes, {need} expected",
                        meta.sequence, meta.bytes_used
                    ),
                });
            }
            let f = applied.format;
            let used = (meta.bytes_used as usize).min(data.len());
            let pixels = match to_grey(
                &applied.samples,
                &data[..used],
                f.width as usize,
                f.height as usize,
                f.stride as usize,
                &mut self.balance,
            ) {
                Ok(p) => p,
                Err(e) => {
                    break Err(DeviceError::Incomplete {
                        device: self.name.clone(),
                        reason: format!("buffer {} ({}): {e}", meta.sequence, f.fourcc),
                    })
                }
            };
            break Ok(CameraFrame {
                width: f.width,
                height: f.height,
                bits: applied.samples.bits,
                pixels,
                counter,
                timestamp_ns: u64::try_from(meta.timestamp.as_nanos()).unwrap_or(u64::MAX),
                exposure_us: applied.exposure_us,
            });
        };
        self.stream = Some(stream);
        result
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        if self.stream.take().is_none() {
            return Ok(());
        }
        self.device
            .stop()
            .map_err(|e| self.io_error("VIDIOC_STREAMOFF", e))
    }
}

impl<D: V4l2Device> Drop for V4l2Camera<D> {
    fn drop(&mut self) {
        if self.stream.take().is_some() {
            // Best effort: the device may be gone already.
            let _ = self.device.stop();
        }
    }
}

/// A node's card, driver, bus and capture formats, and the order in which the driver tries
/// them for 8 bits, for `hexcal devices`.
pub fn describe<D: V4l2Device>(device: &D) -> io::Result<String> {
    let caps = device.capabilities()?;
    if !caps.capture {
        return Ok(format!("{} ({}): no video capture", caps.card, caps.driver));
    }
    let offered = device.formats()?;
    let formats: Vec<String> = offered.iter().map(|f| f.to_string()).collect();
    let order = |bits| match candidates(None, bits, &offered, "the node") {
        Ok(c) => c
            .iter()
            .map(|(f, _)| f.to_string())
            .collect::<Vec<_>>()
            .join(" > "),
        Err(_) => "none".into(),
    };
    Ok(format!(
        "{} ({}, {}): {}; hexcal takes for 8 bits {} (the first that keeps the size)",
        caps.card,
        caps.driver,
        caps.bus,
        formats.join(" "),
        order(8)
    ))
}
