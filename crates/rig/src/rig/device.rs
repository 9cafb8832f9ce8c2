//! Device traits (docs/design.md §11): what the capture engine needs from a camera, a projector
//! and a trigger. Every driver (Aravis, V4L2, window, serial controller) and the simulated
//! rig implement them, so one capture loop drives them all.
//!
//! Errors name the device; the engine adds the pose and frame.

use hexcal_core::images::CameraFrame;
use hexcal_core::pattern::Sequence;
use std::time::Duration;

/// Where a camera's exposures start.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TriggerSource {
    /// One software trigger per frame ([`Camera::trigger`]).
    Software,
    /// A pulse on the camera's trigger input (from the trigger controller).
    Line,
}

/// Settings a capture applies to a camera before it starts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraConfig {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Bits per sample (8 for Mono8, more for Mono16-packed formats).
    pub bits: u8,
    /// Exposure time (µs).
    pub exposure_us: f64,
    /// Analogue gain (dB).
    pub gain_db: f64,
    /// Where exposures start.
    pub trigger: TriggerSource,
}

/// A camera.
pub trait Camera: Send {
    /// The device's name (the rig file's).
    fn name(&self) -> &str;
    /// Apply `config`; refused (naming the setting) when the device cannot do it.
    fn configure(&mut self, config: &CameraConfig) -> Result<(), DeviceError>;
    /// Set the exposure (µs) and analogue gain (dB) of the frames that follow, between
    /// captures (after [`Camera::configure`]); refused (naming the setting) when the
    /// device cannot.
    fn set_exposure_gain(&mut self, exposure_us: f64, gain_db: f64) -> Result<(), DeviceError>;
    /// Start acquisition: from now on every trigger gives one frame.
    fn start(&mut self) -> Result<(), DeviceError>;
    /// Expose one frame now (software trigger).
    fn trigger(&mut self) -> Result<(), DeviceError>;
    /// The next frame, waiting at most `timeout`.
    fn next_frame(&mut self, timeout: Duration) -> Result<CameraFrame, DeviceError>;
    /// Stop acquisition.
    fn stop(&mut self) -> Result<(), DeviceError>;
    /// The pixel format `configure` chose, in the driver's own naming (GenICam `BayerRG8`,
    /// V4L2 `MJPG`, …); `None` before `configure` or for a driver with one format.
    fn pixel_format(&self) -> Option<String> {
        None
    }
    /// Whether the configured format is a Bayer mosaic the driver balances by the scene
    /// ([`hexcal_core::images::to_grey::BayerBalance`]): such a camera wants one frame of a white-lit
    /// board before its first stack, so that every frame of the stack is balanced alike.
    fn balances_colour(&self) -> bool {
        false
    }
}

/// What a projector shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Slide {
    /// All black.
    Black,
    /// All white.
    White,
    /// Frame k of the prepared sequence.
    Pattern(usize),
    /// A flat field of intended level L/255, sent as pattern levels are (through the
    /// projector's inverse-gamma table when the sequence linearises it): the self-tests'
    /// frame codes and response levels (docs/design.md §11b).
    Level(u8),
}

/// A projector.
pub trait Projector: Send {
    /// The device's name (the rig file's).
    fn name(&self) -> &str;
    /// Raster size (width, height) in px.
    fn resolution(&self) -> (u32, u32);
    /// Get ready to show `sequence`'s frames as its projector `code` (index into
    /// [`Sequence::projectors`]).
    fn prepare(&mut self, sequence: &Sequence, code: usize) -> Result<(), DeviceError>;
    /// Show `slide` and return once it is on screen.
    fn show(&mut self, slide: Slide) -> Result<(), DeviceError>;
}

/// A hardware trigger: one pulse on every camera line per frame.
pub trait Trigger: Send {
    /// The device's name (its port).
    fn name(&self) -> &str;
    /// Arm a sequence of `frames` frames fired one by one.
    fn arm(&mut self, frames: u32) -> Result<(), DeviceError>;
    /// Fire the next frame; gives the controller's frame index.
    fn fire(&mut self) -> Result<u32, DeviceError>;
    /// Abort the armed sequence.
    fn disarm(&mut self) -> Result<(), DeviceError>;
}

/// Why a device failed.
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    /// No frame arrived in time.
    #[error("{device}: no frame within {timeout:?}")]
    Timeout {
        /// Device name.
        device: String,
        /// How long it waited.
        timeout: Duration,
    },
    /// A frame arrived incomplete (lost packets, wrong size): worth a retry.
    #[error("{device}: incomplete frame: {reason}")]
    Incomplete {
        /// Device name.
        device: String,
        /// What was wrong.
        reason: String,
    },
    /// The device cannot do what was asked.
    #[error("{device}: {setting}: {reason}")]
    Unsupported {
        /// Device name.
        device: String,
        /// The setting (a rig-file key or a feature name).
        setting: String,
        /// Why not.
        reason: String,
    },
    /// The device went away (unplugged, window closed, port gone).
    #[error("{device}: device lost: {reason}")]
    Gone {
        /// Device name.
        device: String,
        /// What happened.
        reason: String,
    },
    /// Any other driver failure.
    #[error("{device}: {reason}")]
    Failed {
        /// Device name.
        device: String,
        /// What happened.
        reason: String,
    },
}

impl DeviceError {
    /// `device` cannot do `setting`, for `reason`.
    pub fn unsupported(device: &str, setting: &str, reason: String) -> Self {
        DeviceError::Unsupported {
            device: device.to_string(),
            setting: setting.to_string(),
            reason,
        }
    }

    /// `device` failed, for `reason`.
    pub fn failed(device: &str, reason: String) -> Self {
        DeviceError::Failed {
            device: device.to_string(),
            reason,
        }
    }

    /// Whether `device`, configured with `trigger` (`None`: not configured yet), takes a
    /// software trigger.
    pub fn check_software_trigger(
        device: &str,
        trigger: Option<TriggerSource>,
    ) -> Result<(), Self> {
        match trigger {
            Some(TriggerSource::Software) => Ok(()),
            Some(_) => Err(Self::unsupported(
                device,
                "trigger",
                "software trigger on a camera configured for its line input".into(),
            )),
            None => Err(Self::failed(device, "trigger before configure".into())),
        }
    }

    /// Whether triggering the frame again may help (a timeout or an incomplete frame).
    pub fn retryable(&self) -> bool {
        matches!(
            self,
            DeviceError::Timeout { .. } | DeviceError::Incomplete { .. }
        )
    }

    /// The device named.
    pub fn device(&self) -> &str {
        match self {
            DeviceError::Timeout { device, .. }
            | DeviceError::Incomplete { device, .. }
            | DeviceError::Unsupported { device, .. }
            | DeviceError::Gone { device, .. }
            | DeviceError::Failed { device, .. } => device,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn software_trigger_needs_a_software_configuration() {
        assert!(DeviceError::check_software_trigger("cam0", Some(TriggerSource::Software)).is_ok());
        let line = DeviceError::check_software_trigger("cam0", Some(TriggerSource::Line));
        assert!(
            matches!(&line, Err(DeviceError::Unsupported { device, setting, .. })
                if device == "cam0" && setting == "trigger"),
            "{line:?}"
        );
        let early = DeviceError::check_software_trigger("cam0", None);
        assert!(
            matches!(&early, Err(DeviceError::Failed { device, reason })
                if device == "cam0" && reason.contains("before configure")),
            "{early:?}"
        );
    }
}
