//! Opening a rig file's devices for a capture.
//!
//! Takes a [`RigFile`]; gives its board, sequence, timing and one boxed device per camera and
//! projector from the driver the file names (`sim` always; `aravis`, `v4l2` and `window`
//! when hexcal was built with that cargo feature), and the serial trigger controller when
//! the file has one.

use super::device::{Camera, CameraConfig, DeviceError, Projector, Trigger, TriggerSource};
use super::file::{CameraDriver, ProjectorDriver, RigFile};
use super::sim::{SimRigError, SimWorld, WiredTrigger};
use super::trigger::{TriggerController, TriggerError, TriggerTiming};
use hexcal_core::board::{Board, BoardError};
use hexcal_core::pattern::{Sequence, SequenceError};
use std::sync::Arc;
use std::time::Duration;

/// The `[trigger] port` of a simulated controller: the simulator's firmware model on an
/// in-process pty pair, wired to the simulated cameras.
pub const SIMULATED_PORT: &str = "sim";

/// Why a rig could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// The board file.
    #[error("board: {0}")]
    Board(#[from] BoardError),
    /// The phase-shift sequence the projectors ask for (its message says "sequence: ").
    #[error("{0}")]
    Sequence(#[from] SequenceError),
    /// The simulated devices.
    #[error("{0}")]
    Sim(#[from] SimRigError),
    /// A device's driver.
    #[error("{0}")]
    Device(#[from] DeviceError),
    /// A projector's driver (its error names the projector).
    #[error("projector {0}")]
    Projector(DeviceError),
    /// The trigger controller.
    #[error("trigger: {0}")]
    Trigger(#[from] TriggerError),
    /// A device the rig file cannot open as written.
    #[error("{device}: {reason}")]
    Spec {
        /// The device (as the rig file names it).
        device: String,
        /// What is missing.
        reason: String,
    },
}

/// Timing of a capture.
#[derive(Clone, Debug, PartialEq)]
pub struct CaptureTiming {
    /// Wait after the slowest projector presented a pattern, before triggering.
    pub settle: Duration,
    /// Each projector's latency from presented to light on the board.
    pub latency: Vec<Duration>,
    /// How long to wait for a camera's frame.
    pub frame_timeout: Duration,
    /// Extra triggers of a frame that timed out or arrived incomplete.
    pub retries: u32,
    /// Frames taken and averaged per pattern.
    pub repeats: u32,
}

/// A rig's devices, ready for a capture session (`capture::Session::start`).
pub struct RigDevices {
    /// Cameras, in rig-file order.
    pub cameras: Vec<Box<dyn Camera>>,
    /// Their settings.
    pub configs: Vec<CameraConfig>,
    /// Projectors, in rig-file order (projector i shows code i).
    pub projectors: Vec<Box<dyn Projector>>,
    /// The hardware trigger, if any.
    pub trigger: Option<Box<dyn Trigger>>,
    /// Timing.
    pub timing: CaptureTiming,
}

/// An opened rig: its board, its sequence, its devices and, when it has simulated devices,
/// the simulated world (to place its board poses).
pub struct OpenedRig {
    /// The board.
    pub board: Board,
    /// The sequence.
    pub sequence: Sequence,
    /// The devices.
    pub devices: RigDevices,
    /// The simulated world, if any device is simulated.
    pub world: Option<Arc<SimWorld>>,
}

/// Open every device of `rig`: its board, sequence, devices and timing.
pub fn open(rig: &RigFile) -> Result<OpenedRig, OpenError> {
    let board = rig.board()?;
    let sequence = rig.sequence()?;
    let simulated = rig.cameras.iter().any(|c| c.driver == CameraDriver::Sim)
        || rig
            .projectors
            .iter()
            .any(|p| p.driver == ProjectorDriver::Sim);
    let world = match simulated {
        true => Some(Arc::new(SimWorld::new(rig, board.clone())?)),
        false => None,
    };
    let (sim_cameras, sim_projectors) = world.as_ref().map(|w| w.devices()).unwrap_or_default();
    let (cameras, configs) = open_cameras(rig, sim_cameras)?;
    let devices = RigDevices {
        cameras,
        configs,
        projectors: open_projectors(rig, sim_projectors)?,
        trigger: open_trigger(rig, world.as_ref())?,
        timing: timing(rig, world.is_some()),
    };
    Ok(OpenedRig {
        board,
        sequence,
        devices,
        world,
    })
}

/// Cameras and their settings, in rig-file order.
type OpenedCameras = (Vec<Box<dyn Camera>>, Vec<CameraConfig>);

/// The cameras of `rig` and their settings; simulated ones come from `simulated`, in order.
fn open_cameras(
    rig: &RigFile,
    simulated: Vec<super::sim::SimCamera>,
) -> Result<OpenedCameras, OpenError> {
    let mut simulated = simulated.into_iter();
    let mut cameras: Vec<Box<dyn Camera>> = Vec::new();
    let mut configs = Vec::new();
    for c in &rig.cameras {
        cameras.push(match c.driver {
            CameraDriver::Sim => Box::new(simulated.next().ok_or_else(|| OpenError::Spec {
                device: c.name.clone(),
                reason: "no simulated camera for it".into(),
            })?),
            driver => open_camera(driver, &c.name, c.address.as_deref(), c.format.as_deref())?,
        });
        configs.push(CameraConfig {
            width: c.width,
            height: c.height,
            bits: c.bits,
            exposure_us: 1e3 * c.exposure_ms,
            gain_db: c.gain_db,
            trigger: match rig.trigger {
                Some(_) => TriggerSource::Line,
                None => TriggerSource::Software,
            },
        });
    }
    Ok((cameras, configs))
}

/// The projectors of `rig`; simulated ones come from `simulated`, in order.
fn open_projectors(
    rig: &RigFile,
    simulated: Vec<super::sim::SimProjector>,
) -> Result<Vec<Box<dyn Projector>>, OpenError> {
    let mut simulated = simulated.into_iter();
    let mut projectors: Vec<Box<dyn Projector>> = Vec::new();
    for p in &rig.projectors {
        projectors.push(match p.driver {
            ProjectorDriver::Sim => Box::new(simulated.next().ok_or_else(|| OpenError::Spec {
                device: p.name.clone(),
                reason: "no simulated projector for it".into(),
            })?),
            ProjectorDriver::Window => {
                open_window(&p.name, p.monitor.as_deref(), p.width, p.height)?
            }
        });
    }
    Ok(projectors)
}

/// The trigger controller of `rig`'s `[trigger]`, its lines configured: the simulator's
/// firmware model on a pty wired to the simulated cameras for port "sim".
fn open_trigger(
    rig: &RigFile,
    world: Option<&Arc<SimWorld>>,
) -> Result<Option<Box<dyn Trigger>>, OpenError> {
    let Some(t) = &rig.trigger else {
        return Ok(None);
    };
    let lines: Vec<_> = rig
        .cameras
        .iter()
        .filter_map(|c| c.trigger_line)
        .map(|line| hexcal_firmware_protocol::LineConfig {
            line,
            delay_us: 0,
            pulse_us: t.pulse_us,
        })
        .collect();
    if t.port != SIMULATED_PORT {
        let mut c = TriggerController::open(&t.port, 115_200, TriggerTiming::default())?;
        c.configure(&lines)?;
        return Ok(Some(Box::new(c)));
    }
    let world = world.cloned().ok_or_else(|| OpenError::Spec {
        device: "trigger".into(),
        reason: "port \"sim\" needs simulated cameras".into(),
    })?;
    let mut w = WiredTrigger::simulated(world, Duration::from_secs(2))?;
    w.controller().configure(&lines)?;
    Ok(Some(Box::new(w)))
}

/// The capture timing of `rig` (a checked rig file: every duration finite, at most an
/// hour); simulated cameras render while the others wait, so their frame timeout allows
/// for it.
pub fn timing(rig: &RigFile, simulated: bool) -> CaptureTiming {
    let frame = Duration::from_secs_f64(1e-3 * rig.timing.frame_period_ms);
    CaptureTiming {
        settle: Duration::from_secs_f64(1e-3 * rig.timing.settle_ms),
        latency: rig
            .projectors
            .iter()
            .map(|p| Duration::from_secs_f64(1e-3 * p.latency_ms))
            .collect(),
        frame_timeout: (10 * frame).max(Duration::from_secs(if simulated { 30 } else { 2 })),
        retries: 2,
        repeats: rig.timing.repeats,
    }
}

fn open_camera(
    driver: CameraDriver,
    name: &str,
    address: Option<&str>,
    format: Option<&str>,
) -> Result<Box<dyn Camera>, OpenError> {
    let needs_address = || OpenError::Spec {
        device: name.to_string(),
        reason: "address is required".into(),
    };
    #[cfg(feature = "aravis")]
    if driver == CameraDriver::Aravis {
        let address = address.ok_or_else(needs_address)?;
        let camera = super::aravis::AravisCamera::open(name, address)?.with_format(format);
        return Ok(Box::new(camera));
    }
    #[cfg(feature = "v4l2")]
    if driver == CameraDriver::V4l2 {
        let address = address.ok_or_else(needs_address)?;
        let camera = super::v4l2::V4l2Camera::open(name, address)?.with_format(format);
        return Ok(Box::new(camera));
    }
    let _ = (address, format, needs_address);
    let feature = match driver {
        CameraDriver::Aravis => "aravis",
        CameraDriver::V4l2 => "v4l2",
        CameraDriver::Sim => unreachable!("simulated cameras come from the world"),
    };
    Err(OpenError::Spec {
        device: name.to_string(),
        reason: format!("driver {feature} is not built in; rebuild with `--features {feature}`"),
    })
}

#[cfg(feature = "window")]
fn open_window(
    name: &str,
    monitor: Option<&str>,
    width: u32,
    height: u32,
) -> Result<Box<dyn Projector>, OpenError> {
    let monitor = monitor.ok_or_else(|| OpenError::Spec {
        device: format!("projector {name}"),
        reason: "monitor is required".into(),
    })?;
    let projector = super::window::WindowProjector::open(name, monitor, width, height)
        .map_err(OpenError::Projector)?;
    Ok(Box::new(projector))
}

#[cfg(not(feature = "window"))]
fn open_window(
    name: &str,
    _monitor: Option<&str>,
    _width: u32,
    _height: u32,
) -> Result<Box<dyn Projector>, OpenError> {
    Err(OpenError::Spec {
        device: format!("projector {name}"),
        reason: "driver window is not built in; rebuild with `--features window`".into(),
    })
}
