//! GenICam cameras through Aravis (docs/design.md §11), behind the cargo feature `aravis`.
//!
//! Takes a camera's rig-file name and its address (IP address, serial number or Aravis
//! device id) and gives a [`Camera`]: monochrome, Bayer (every phase) and RGB frames of 8 to
//! 16 bits, packed (PFNC `…p`, GigE Vision `…Packed`) or not, in the grey the stages read
//! ([`hexcal_core::images::to_grey`]; the format the rig file names, else [`choose_format`]), exposure
//! (SFNC `ExposureTime` or `ExposureTimeAbs`), gain (`Gain` in dB, or `GainRaw` at its
//! minimum for 0 dB), trigger mode on with a software or line trigger source, a small
//! buffer pool with GigE Vision packet resend, and incomplete buffers reported as
//! [`DeviceError::Incomplete`] naming Aravis' buffer status. [`list_cameras`] lists the
//! GenICam cameras this machine sees; [`loopback`] runs a real GigE Vision camera on
//! 127.0.0.1 inside the process, for tests and `hexcal bench`.

#[cfg(feature = "loopback")]
pub mod loopback;

#[cfg(feature = "loopback")]
pub use loopback::{bench_loopback, LiveScene, LoopbackBench, LoopbackCamera, LOOPBACK_ADDRESS};

use super::device::{Camera, CameraConfig, DeviceError, TriggerSource};
use aravis::glib::{self, object::Cast};
use aravis::prelude::*;
use aravis::{
    Buffer, BufferPayloadType, BufferStatus, GvStream, GvStreamPacketResend, PixelFormat,
};
use hexcal_core::images::to_grey::{to_grey, BayerBalance, Cfa, Colour, Packing, SampleFormat};
use hexcal_core::images::CameraFrame;
use hexcal_core::Invalid;
use std::ffi::CStr;
use std::os::raw::c_char;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Buffers queued on the stream: enough to absorb a burst while the capture loop copies.
const STREAM_BUFFERS: usize = 4;

/// Aravis' global device list is not thread-safe: opening and listing take this lock.
static DEVICE_LIST: Mutex<()> = Mutex::new(());

/// One GenICam camera this machine sees (for `hexcal devices`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CameraListing {
    /// Aravis device id (opens the camera, like the address).
    pub id: String,
    /// Vendor name.
    pub vendor: String,
    /// Model name.
    pub model: String,
    /// Serial number.
    pub serial: String,
    /// Network address (GigE Vision) or bus address (USB3 Vision).
    pub address: String,
    /// Transport: "GigEVision", "USB3Vision" or "Fake".
    pub protocol: String,
}

/// The GenICam cameras on every enabled Aravis interface (GigE Vision discovery broadcasts
/// on every network interface; USB3 Vision enumerates the bus).
pub fn list_cameras() -> Vec<CameraListing> {
    let _guard = DEVICE_LIST.lock().unwrap_or_else(|e| e.into_inner());
    // SAFETY: the device list is only touched under DEVICE_LIST; every index is below the
    // count just updated, and the strings are copied before the lock is released.
    unsafe {
        aravis_sys::arv_update_device_list();
        (0..aravis_sys::arv_get_n_devices())
            .map(|i| CameraListing {
                id: owned(aravis_sys::arv_get_device_id(i)),
                vendor: owned(aravis_sys::arv_get_device_vendor(i)),
                model: owned(aravis_sys::arv_get_device_model(i)),
                serial: owned(aravis_sys::arv_get_device_serial_nbr(i)),
                address: owned(aravis_sys::arv_get_device_address(i)),
                protocol: owned(aravis_sys::arv_get_device_protocol(i)),
            })
            .collect()
    }
}

/// The pixel formats of the camera `id` and what hexcal takes when the rig file names none
/// (for 8 and 16 bits), for `hexcal devices`; opens the camera.
pub fn describe_formats(id: &str) -> Result<String, DeviceError> {
    let camera = AravisCamera::open(id, id)?;
    let offered: Vec<String> = camera
        .camera
        .dup_available_pixel_formats_as_strings()
        .map_err(|e| camera.error("PixelFormat", e))?
        .iter()
        .map(|o| o.to_string())
        .collect();
    let choice = |bits| choose_format(None, bits, &offered).map_or("none".into(), |c| c.0);
    Ok(format!(
        "formats {}; hexcal takes {} for 8 bits, {} for 16",
        offered.join(" "),
        choice(8),
        choice(16)
    ))
}

/// A C string from Aravis' device list, copied ("" when absent).
///
/// # Safety
/// `s` is null or a valid NUL-terminated string.
unsafe fn owned(s: *const c_char) -> String {
    if s.is_null() {
        String::new()
    } else {
        CStr::from_ptr(s).to_string_lossy().into_owned()
    }
}

/// The GenICam (PFNC) pixel formats the driver reads, by name: Mono8/10/12/16, Mono10p,
/// Mono12p, Mono10Packed, Mono12Packed, the same for Bayer mosaics of each phase
/// (BayerRG8, BayerGB12p, BayerBG10Packed, …), and RGB8 / BGR8 (also as …Packed).
pub fn pixel_formats() -> Vec<(String, SampleFormat)> {
    const DEPTHS: [(&str, Packing, u8); 8] = [
        ("8", Packing::U8, 8),
        ("10", Packing::U16Le, 10),
        ("12", Packing::U16Le, 12),
        ("16", Packing::U16Le, 16),
        ("10p", Packing::LsbStream, 10),
        ("12p", Packing::LsbStream, 12),
        ("10Packed", Packing::GvspPair, 10),
        ("12Packed", Packing::GvspPair, 12),
    ];
    const PHASES: [(&str, Cfa); 4] = [
        ("RG", Cfa::Rggb),
        ("GR", Cfa::Grbg),
        ("GB", Cfa::Gbrg),
        ("BG", Cfa::Bggr),
    ];
    let mut all: Vec<(String, SampleFormat)> = DEPTHS
        .iter()
        .map(|&(d, packing, bits)| (format!("Mono{d}"), SampleFormat::mono(packing, bits)))
        .collect();
    for (p, cfa) in PHASES {
        all.extend(DEPTHS.iter().map(|&(d, packing, bits)| {
            (
                format!("Bayer{p}{d}"),
                SampleFormat::bayer(cfa, packing, bits),
            )
        }));
    }
    for (name, colour) in [
        ("RGB8", Colour::Rgb),
        ("RGB8Packed", Colour::Rgb),
        ("BGR8", Colour::Bgr),
        ("BGR8Packed", Colour::Bgr),
    ] {
        all.push((name.to_string(), SampleFormat::bytes(colour)));
    }
    all
}

/// The pixel format to use among the camera's `offered` ones: `named` (the rig file's
/// `format`) when given, else the best for `bits` by [`SampleFormat::rank`] (ties: the
/// order of [`pixel_formats`]). The reason, naming what is offered, when none fits.
pub fn choose_format(
    named: Option<&str>,
    bits: u8,
    offered: &[String],
) -> Result<(String, SampleFormat), Invalid> {
    let known = pixel_formats();
    let usable = |name: &str| {
        known
            .iter()
            .find(|(n, f)| n == name && f.rank(bits).is_some())
            .cloned()
    };
    let listing = offered.join(", ");
    if let Some(name) = named {
        if !offered.iter().any(|o| o == name) {
            return Err(Invalid(format!(
                "{name} not offered; the camera offers {listing}"
            )));
        }
        return usable(name).ok_or_else(|| match known.iter().find(|(n, _)| n == name) {
            Some((_, f)) => Invalid(format!(
                "{name} gives {} bits, the rig file asks {bits}",
                f.bits
            )),
            None => Invalid(format!(
                "hexcal cannot read {name}; the camera offers {listing}"
            )),
        });
    }
    known
        .iter()
        .filter(|(n, f)| offered.contains(n) && f.rank(bits).is_some())
        .min_by_key(|(_, f)| f.rank(bits))
        .cloned()
        .ok_or_else(|| {
            Invalid(format!(
                "no pixel format gives {bits} bits; the camera offers {listing}"
            ))
        })
}

/// Packet statistics of a running GigE Vision stream.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StreamStatistics {
    /// Buffers completed (successful or not).
    pub completed: u64,
    /// Buffers that failed (lost packets, timeout, size mismatch).
    pub failures: u64,
    /// Frames lost because no buffer was free.
    pub underruns: u64,
    /// GVSP packets the camera sent again on request.
    pub resent_packets: u64,
    /// GVSP packets never received.
    pub missing_packets: u64,
}

/// What `configure` settled on.
#[derive(Clone, Copy, Debug)]
struct Applied {
    width: u32,
    height: u32,
    /// The pixel format code buffers carry.
    code: PixelFormat,
    /// What the samples are.
    format: SampleFormat,
    exposure_us: f64,
    trigger: TriggerSource,
}

/// The camera's 16-bit (or 64-bit) frame ids unwrapped into a counter that only grows.
#[derive(Clone, Copy, Debug, Default)]
struct FrameIds {
    last: Option<(u64, u64)>,
}

impl FrameIds {
    /// GigE Vision's 16-bit block ids run 1..=65535 and skip 0 on wrapping.
    const WRAP: u64 = 0xFFFF;

    /// Counter for raw frame id `id` (one more per frame exposed; a gap is a drop).
    fn counter(&mut self, id: u64) -> u64 {
        let counter = match self.last {
            None => id,
            Some((last_id, last)) if id > last_id => last + (id - last_id),
            Some((last_id, last)) if last_id <= Self::WRAP => last + (id + Self::WRAP - last_id),
            // A 64-bit id going back: the camera restarted its count; keep growing.
            Some((_, last)) => last + 1,
        };
        self.last = Some((id, counter));
        counter
    }
}

/// A GenICam camera opened through Aravis.
pub struct AravisCamera {
    name: String,
    address: String,
    camera: aravis::Camera,
    stream: Option<aravis::Stream>,
    applied: Option<Applied>,
    ids: FrameIds,
    control_lost: Arc<AtomicBool>,
    /// The rig file's `format`, if it names one.
    format_name: Option<String>,
    /// The pixel format chosen at `configure`.
    chosen: Option<String>,
    /// White balance of a Bayer format, held from `start` to `stop`.
    balance: BayerBalance,
}

impl AravisCamera {
    /// Open the camera at `address` (IP address, serial number or Aravis device id) under
    /// the rig file's `name`.
    pub fn open(name: &str, address: &str) -> Result<Self, DeviceError> {
        let camera = {
            let _guard = DEVICE_LIST.lock().unwrap_or_else(|e| e.into_inner());
            aravis::Camera::new(Some(address)).map_err(|e| DeviceError::Failed {
                device: name.to_string(),
                reason: format!("cannot open GenICam camera {address}: {e}"),
            })?
        };
        let control_lost = Arc::new(AtomicBool::new(false));
        if let Some(device) = camera.device() {
            let flag = Arc::clone(&control_lost);
            device.connect_control_lost(move |_| flag.store(true, Ordering::SeqCst));
        }
        Ok(AravisCamera {
            name: name.to_string(),
            address: address.to_string(),
            camera,
            stream: None,
            applied: None,
            ids: FrameIds::default(),
            control_lost,
            format_name: None,
            chosen: None,
            balance: BayerBalance::default(),
        })
    }

    /// Use the pixel format `name` (a PFNC name from [`pixel_formats`]) rather than choosing
    /// one; `None` restores the choice.
    pub fn with_format(mut self, name: Option<&str>) -> Self {
        self.format_name = name.map(str::to_string);
        self
    }

    /// Vendor, model and serial number as the camera reports them.
    pub fn identity(&self) -> Result<(String, String, String), DeviceError> {
        let vendor = self
            .camera
            .vendor_name()
            .map_err(|e| self.error("vendor", e))?;
        let model = self
            .camera
            .model_name()
            .map_err(|e| self.error("model", e))?;
        let serial = self
            .camera
            .device_serial_number()
            .map_err(|e| self.error("serial number", e))?;
        Ok((vendor.into(), model.into(), serial.into()))
    }

    /// Packet statistics of the running stream (zeros when not started).
    pub fn statistics(&self) -> StreamStatistics {
        let Some(stream) = &self.stream else {
            return StreamStatistics::default();
        };
        let (completed, failures, underruns) = stream.statistics();
        let (resent_packets, missing_packets) = stream
            .downcast_ref::<GvStream>()
            .map(|gv| gv.statistics())
            .unwrap_or((0, 0));
        StreamStatistics {
            completed,
            failures,
            underruns,
            resent_packets,
            missing_packets,
        }
    }

    /// A driver failure of `what`: `Gone` when the camera stopped answering.
    fn error(&self, what: &str, e: glib::Error) -> DeviceError {
        use aravis::DeviceError as Arv;
        let silent = e.matches(Arv::Timeout)
            || e.matches(Arv::NotConnected)
            || e.matches(Arv::TransferError);
        if silent || self.control_lost.load(Ordering::SeqCst) {
            DeviceError::Gone {
                device: self.name.clone(),
                reason: format!("{} does not answer ({what}: {e})", self.address),
            }
        } else {
            DeviceError::Failed {
                device: self.name.clone(),
                reason: format!("{what}: {e}"),
            }
        }
    }

    fn unsupported(&self, setting: &str, reason: String) -> DeviceError {
        DeviceError::unsupported(&self.name, setting, reason)
    }

    fn failed(&self, reason: String) -> DeviceError {
        DeviceError::failed(&self.name, reason)
    }

    fn has(&self, feature: &str) -> bool {
        self.camera.is_feature_available(feature).unwrap_or(false)
    }

    /// The first of `names` the camera offers.
    fn first_of<'a>(&self, names: &[&'a str]) -> Option<&'a str> {
        names.iter().copied().find(|f| self.has(f))
    }

    fn entries(&self, feature: &str) -> Result<Vec<String>, DeviceError> {
        let entries = self
            .camera
            .dup_available_enumerations_as_strings(feature)
            .map_err(|e| self.error(feature, e))?;
        Ok(entries.iter().map(|s| s.to_string()).collect())
    }

    fn set_enum(&self, feature: &str, value: &str) -> Result<(), DeviceError> {
        self.camera
            .set_string(feature, value)
            .map_err(|e| self.error(&format!("{feature} = {value}"), e))
    }

    /// Set `feature` to its entry `value` when the camera has both.
    fn set_enum_if_offered(&self, feature: &str, value: &str) -> Result<(), DeviceError> {
        if self.has(feature) && self.entries(feature)?.iter().any(|v| v == value) {
            self.set_enum(feature, value)?;
        }
        Ok(())
    }

    /// Set an integer feature after checking its bounds and increment; refused naming
    /// `setting` when the camera cannot.
    fn set_integer(&self, setting: &str, feature: &str, value: u32) -> Result<(), DeviceError> {
        let cam = &self.camera;
        let (min, max) = cam
            .integer_bounds(feature)
            .map_err(|e| self.error(feature, e))?;
        let inc = cam.integer_increment(feature).unwrap_or(1).max(1);
        let v = i64::from(value);
        if v < min || v > max || (v - min) % inc != 0 {
            return Err(self.unsupported(
                setting,
                format!("{value} not possible ({feature} {min}..={max} in steps of {inc})"),
            ));
        }
        cam.set_integer(feature, v)
            .map_err(|e| self.error(&format!("{feature} = {value}"), e))?;
        let got = cam.integer(feature).map_err(|e| self.error(feature, e))?;
        if got != v {
            return Err(self.unsupported(setting, format!("{feature} = {value} reads back {got}")));
        }
        Ok(())
    }

    /// Set a float feature within its bounds; gives the value the camera settled on.
    fn set_float(&self, setting: &str, feature: &str, value: f64) -> Result<f64, DeviceError> {
        let cam = &self.camera;
        let (min, max) = cam
            .float_bounds(feature)
            .map_err(|e| self.error(feature, e))?;
        if !(min..=max).contains(&value) {
            return Err(self.unsupported(
                setting,
                format!("{value} not possible ({feature} {min}..={max})"),
            ));
        }
        cam.set_float(feature, value)
            .map_err(|e| self.error(&format!("{feature} = {value}"), e))?;
        cam.float(feature).map_err(|e| self.error(feature, e))
    }

    /// Set the pixel format: the one the rig file names, else the best the camera offers for
    /// `bits` ([`SampleFormat::rank`]: monochrome, then Bayer, then RGB); gives its name,
    /// what it is and the pixel format code buffers carry.
    fn set_pixel_format(
        &self,
        bits: u8,
    ) -> Result<(String, SampleFormat, PixelFormat), DeviceError> {
        let offered: Vec<String> = self
            .camera
            .dup_available_pixel_formats_as_strings()
            .map_err(|e| self.error("PixelFormat", e))?
            .iter()
            .map(|o| o.to_string())
            .collect();
        let (name, format) = choose_format(self.format_name.as_deref(), bits, &offered)
            .map_err(|reason| self.unsupported("format", reason.into()))?;
        self.camera
            .set_pixel_format_from_string(&name)
            .map_err(|e| self.error(&format!("PixelFormat = {name}"), e))?;
        let code = self
            .camera
            .pixel_format()
            .map_err(|e| self.error("PixelFormat", e))?;
        Ok((name, format, code))
    }

    /// Exposure through SFNC `ExposureTime` or the older `ExposureTimeAbs` (µs both).
    fn set_exposure(&self, exposure_us: f64) -> Result<f64, DeviceError> {
        self.set_enum_if_offered("ExposureAuto", "Off")?;
        self.set_enum_if_offered("ExposureMode", "Timed")?;
        let feature = self
            .first_of(&["ExposureTime", "ExposureTimeAbs"])
            .ok_or_else(|| {
                self.unsupported(
                    "exposure",
                    "neither ExposureTime nor ExposureTimeAbs offered".into(),
                )
            })?;
        self.set_float("exposure", feature, exposure_us)
    }

    /// Gain in dB through `Gain`; a camera with only `GainRaw` (vendor units) takes 0 dB as
    /// its lowest raw gain and refuses anything else.
    fn set_gain(&self, gain_db: f64) -> Result<(), DeviceError> {
        self.set_enum_if_offered("GainAuto", "Off")?;
        if self.has("Gain") {
            self.set_float("gain_db", "Gain", gain_db)?;
        } else if self.has("GainRaw") {
            if gain_db != 0.0 {
                return Err(self.unsupported(
                    "gain_db",
                    format!("{gain_db} dB: the camera has only GainRaw (vendor units)"),
                ));
            }
            let (min, _) = self
                .camera
                .integer_bounds("GainRaw")
                .map_err(|e| self.error("GainRaw", e))?;
            self.camera
                .set_integer("GainRaw", min)
                .map_err(|e| self.error("GainRaw", e))?;
        } else if gain_db != 0.0 {
            return Err(self.unsupported(
                "gain_db",
                format!("{gain_db} dB: the camera has no gain control"),
            ));
        }
        Ok(())
    }

    /// Frame-start trigger on, from software or the camera's line input (`Line1`, or the
    /// only `Line*` input a camera has).
    fn set_trigger(&self, trigger: TriggerSource) -> Result<(), DeviceError> {
        for feature in ["TriggerMode", "TriggerSource"] {
            if !self.has(feature) {
                return Err(self.unsupported("trigger", format!("no {feature} feature")));
            }
        }
        self.set_enum_if_offered("AcquisitionMode", "Continuous")?;
        self.set_enum_if_offered("TriggerSelector", "FrameStart")?;
        let sources = self.entries("TriggerSource")?;
        let source = match trigger {
            TriggerSource::Software => sources.iter().find(|s| *s == "Software"),
            TriggerSource::Line => {
                let lines: Vec<&String> =
                    sources.iter().filter(|s| s.starts_with("Line")).collect();
                match lines.as_slice() {
                    [only] => Some(*only),
                    _ => lines.into_iter().find(|s| *s == "Line1"),
                }
            }
        }
        .ok_or_else(|| {
            self.unsupported(
                "trigger",
                format!(
                    "no {} trigger source (TriggerSource offers {})",
                    match trigger {
                        TriggerSource::Software => "Software",
                        TriggerSource::Line => "Line1",
                    },
                    sources.join(", ")
                ),
            )
        })?;
        self.set_enum("TriggerMode", "On")?;
        self.set_enum("TriggerSource", source)?;
        self.set_enum_if_offered("TriggerActivation", "RisingEdge")
    }

    /// The frame in a successfully popped buffer, checked against the configuration.
    fn frame(&mut self, buffer: &Buffer, applied: &Applied) -> Result<CameraFrame, DeviceError> {
        let status = buffer.status();
        if status != BufferStatus::Success {
            return Err(DeviceError::Incomplete {
                device: self.name.clone(),
                reason: format!(
                    "buffer status {} (frame id {})",
                    status_name(status),
                    buffer.frame_id()
                ),
            });
        }
        if buffer.payload_type() != BufferPayloadType::Image {
            return Err(self.failed(format!(
                "frame id {}: payload {:?} is not an image",
                buffer.frame_id(),
                buffer.payload_type()
            )));
        }
        let (width, height) = (buffer.image_width(), buffer.image_height());
        let code = buffer.image_pixel_format();
        if (width, height) != (applied.width as i32, applied.height as i32) || code != applied.code
        {
            return Err(self.failed(format!(
                "frame id {}: {width}×{height} format {:#x}, configured {}×{} format {:#x}",
                buffer.frame_id(),
                code.raw(),
                applied.width,
                applied.height,
                applied.code.raw()
            )));
        }
        let data = buffer.image_data();
        let (w, h) = (applied.width as usize, applied.height as usize);
        let row = applied.format.row_bytes(w).unwrap_or(0);
        if data.len() != row * h {
            return Err(DeviceError::Incomplete {
                device: self.name.clone(),
                reason: format!(
                    "SIZE_MISMATCH: frame id {} has {} bytes, {} expected",
                    buffer.frame_id(),
                    data.len(),
                    row * h
                ),
            });
        }
        let pixels = to_grey(&applied.format, &data, w, h, row, &mut self.balance)
            .map_err(|e| self.failed(format!("frame id {}: {e}", buffer.frame_id())))?;
        Ok(CameraFrame {
            width: applied.width,
            height: applied.height,
            bits: applied.format.bits,
            pixels,
            counter: self.ids.counter(buffer.frame_id()),
            timestamp_ns: buffer.timestamp(),
            exposure_us: applied.exposure_us,
        })
    }
}

/// Aravis' name of a buffer status.
fn status_name(status: BufferStatus) -> String {
    match status {
        BufferStatus::Unknown => "UNKNOWN".into(),
        BufferStatus::Success => "SUCCESS".into(),
        BufferStatus::Cleared => "CLEARED".into(),
        BufferStatus::Timeout => "TIMEOUT".into(),
        BufferStatus::MissingPackets => "MISSING_PACKETS".into(),
        BufferStatus::WrongPacketId => "WRONG_PACKET_ID".into(),
        BufferStatus::SizeMismatch => "SIZE_MISMATCH".into(),
        BufferStatus::Filling => "FILLING".into(),
        BufferStatus::Aborted => "ABORTED".into(),
        BufferStatus::PayloadNotSupported => "PAYLOAD_NOT_SUPPORTED".into(),
        other => format!("{other:?}"),
    }
}

impl Camera for AravisCamera {
    fn name(&self) -> &str {
        &self.name
    }

    fn configure(&mut self, config: &CameraConfig) -> Result<(), DeviceError> {
        if self.stream.is_some() {
            return Err(self.failed("configure while acquiring: stop first".into()));
        }
        self.applied = None;
        self.chosen = None;
        let (name, format, code) = self.set_pixel_format(config.bits)?;
        for offset in ["OffsetX", "OffsetY"] {
            if self.has(offset) {
                self.camera
                    .set_integer(offset, 0)
                    .map_err(|e| self.error(offset, e))?;
            }
        }
        self.set_integer("width", "Width", config.width)?;
        self.set_integer("height", "Height", config.height)?;
        let exposure_us = self.set_exposure(config.exposure_us)?;
        self.set_gain(config.gain_db)?;
        self.set_trigger(config.trigger)?;
        self.applied = Some(Applied {
            width: config.width,
            height: config.height,
            code,
            format,
            exposure_us,
            trigger: config.trigger,
        });
        self.chosen = Some(name);
        Ok(())
    }

    fn set_exposure_gain(&mut self, exposure_us: f64, gain_db: f64) -> Result<(), DeviceError> {
        let exposure_us = self.set_exposure(exposure_us)?;
        self.set_gain(gain_db)?;
        if let Some(a) = self.applied.as_mut() {
            a.exposure_us = exposure_us;
        }
        Ok(())
    }

    fn pixel_format(&self) -> Option<String> {
        self.chosen.clone()
    }

    fn balances_colour(&self) -> bool {
        self.applied
            .as_ref()
            .is_some_and(|a| matches!(a.format.colour, Colour::Bayer(_)))
    }

    fn start(&mut self) -> Result<(), DeviceError> {
        if self.applied.is_none() {
            return Err(self.failed("start before configure".into()));
        }
        if self.stream.is_some() {
            return Ok(());
        }
        self.balance = BayerBalance::default();
        let payload = self
            .camera
            .payload()
            .map_err(|e| self.error("payload", e))?;
        let stream = self
            .camera
            .create_stream()
            .map_err(|e| self.error("create stream", e))?;
        if let Some(gv) = stream.downcast_ref::<GvStream>() {
            gv.set_packet_resend(GvStreamPacketResend::Always);
        }
        for _ in 0..STREAM_BUFFERS {
            stream.push_buffer(Buffer::new_allocate(payload as usize));
        }
        self.camera
            .start_acquisition()
            .map_err(|e| self.error("AcquisitionStart", e))?;
        self.stream = Some(stream);
        Ok(())
    }

    fn trigger(&mut self) -> Result<(), DeviceError> {
        DeviceError::check_software_trigger(&self.name, self.applied.as_ref().map(|a| a.trigger))?;
        if self.stream.is_none() {
            return Err(self.failed("trigger before start".into()));
        }
        self.camera
            .software_trigger()
            .map_err(|e| self.error("TriggerSoftware", e))
    }

    fn next_frame(&mut self, timeout: Duration) -> Result<CameraFrame, DeviceError> {
        let (Some(stream), Some(applied)) = (self.stream.clone(), self.applied) else {
            return Err(self.failed("next_frame before start".into()));
        };
        let micros = u64::try_from(timeout.as_micros()).unwrap_or(u64::MAX);
        let Some(buffer) = stream.timeout_pop_buffer(micros) else {
            if self.control_lost.load(Ordering::SeqCst) {
                return Err(DeviceError::Gone {
                    device: self.name.clone(),
                    reason: format!("lost control of {}", self.address),
                });
            }
            return Err(DeviceError::Timeout {
                device: self.name.clone(),
                timeout,
            });
        };
        let frame = self.frame(&buffer, &applied);
        stream.push_buffer(buffer);
        frame
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        let Some(stream) = self.stream.take() else {
            return Ok(());
        };
        let stopped = self
            .camera
            .stop_acquisition()
            .map_err(|e| self.error("AcquisitionStop", e));
        // Dropping the last reference stops the stream's thread and frees its buffers.
        drop(stream);
        stopped
    }
}

impl Drop for AravisCamera {
    fn drop(&mut self) {
        if let Some(stream) = self.stream.take() {
            // Best effort: the camera may be gone already.
            let _ = self.camera.stop_acquisition();
            drop(stream);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn offered(names: &[&str]) -> Vec<String> {
        names.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn the_table_names_every_depth_phase_and_packing_once() {
        let all = pixel_formats();
        assert_eq!(all.len(), 8 + 4 * 8 + 4);
        let mut names: Vec<&str> = all.iter().map(|(n, _)| n.as_str()).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), all.len());
        let find = |name: &str| all.iter().find(|(n, _)| n == name).map(|(_, f)| *f);
        assert_eq!(
            find("BayerGB12p"),
            Some(SampleFormat::bayer(Cfa::Gbrg, Packing::LsbStream, 12))
        );
        assert_eq!(
            find("Mono10Packed"),
            Some(SampleFormat::mono(Packing::GvspPair, 10))
        );
        assert_eq!(
            find("BayerBG16"),
            Some(SampleFormat::bayer(Cfa::Bggr, Packing::U16Le, 16))
        );
        assert_eq!(find("BGR8"), Some(SampleFormat::bytes(Colour::Bgr)));
    }

    #[test]
    fn the_choice_prefers_mono_then_bayer_then_rgb_at_the_bits_asked() {
        let pick = |bits, names: &[&str]| choose_format(None, bits, &offered(names)).map(|c| c.0);
        assert_eq!(pick(8, &["RGB8", "BayerRG8", "Mono8"]).unwrap(), "Mono8");
        assert_eq!(
            pick(8, &["RGB8", "BayerRG8", "Mono16"]).unwrap(),
            "BayerRG8"
        );
        assert_eq!(pick(8, &["RGB8", "Mono16"]).unwrap(), "RGB8");
        assert_eq!(pick(12, &["Mono16", "Mono12p"]).unwrap(), "Mono12p");
        assert_eq!(pick(12, &["Mono16", "BayerRG12p"]).unwrap(), "Mono16");
        let e = pick(12, &["Mono8", "RGB8"]).unwrap_err();
        assert!(e.contains("12 bits") && e.contains("Mono8, RGB8"), "{e}");
    }

    #[test]
    fn a_named_format_must_be_offered_readable_and_of_the_bits_asked() {
        let list = offered(&["Mono8", "BayerRG12p", "YUV422Packed"]);
        assert_eq!(
            choose_format(Some("BayerRG12p"), 12, &list).unwrap().0,
            "BayerRG12p"
        );
        let e = choose_format(Some("BayerGB8"), 8, &list).unwrap_err();
        assert!(e.contains("BayerGB8 not offered"), "{e}");
        let e = choose_format(Some("YUV422Packed"), 8, &list).unwrap_err();
        assert!(e.contains("cannot read YUV422Packed"), "{e}");
        let e = choose_format(Some("BayerRG12p"), 8, &list).unwrap_err();
        assert!(e.contains("gives 12 bits") && e.contains("asks 8"), "{e}");
    }
}
