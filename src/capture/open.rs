//! Opening a rig file's devices for a capture.
//!
//! Takes a [`RigFile`]; gives its board, sequence, timing and one boxed device per camera and
//! projector from the driver the file names (`sim` always; `aravis`, `v4l2` and `window`
//! when hexcal was built with that cargo feature), and the serial trigger controller when
//! the file has one.

use super::CaptureTiming;
use crate::board::Board;
use crate::pattern::{ProjectorCode, ProjectorResponse, ProjectorSetup, Sequence};
use crate::rig::file::{CameraDriver, ProjectorDriver, RigFile};
use crate::rig::sim::{SimWorld, WiredTrigger};
use crate::rig::trigger::{TriggerController, TriggerTiming};
use crate::rig::{Camera, CameraConfig, Projector, Trigger, TriggerSource};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

/// The `[trigger] port` of a simulated controller: the simulator's firmware model on an
/// in-process pty pair, wired to the simulated cameras.
pub const SIMULATED_PORT: &str = "sim";

/// A rig's devices, ready for [`super::Session::start`].
pub struct OpenedRig {
    /// The board.
    pub board: Board,
    /// Cameras, in rig-file order.
    pub cameras: Vec<Box<dyn Camera>>,
    /// Their settings.
    pub configs: Vec<CameraConfig>,
    /// Projectors, in rig-file order (projector i shows code i).
    pub projectors: Vec<Box<dyn Projector>>,
    /// The hardware trigger, if any.
    pub trigger: Option<Box<dyn Trigger>>,
    /// The sequence.
    pub sequence: Sequence,
    /// Timing.
    pub timing: CaptureTiming,
    /// The simulated world when the rig has simulated devices (to place its board poses).
    pub world: Option<Arc<SimWorld>>,
}

/// The board a rig file names: a built-in name or a board file relative to `base`.
pub fn board(rig: &RigFile, base: &Path) -> Result<Board, String> {
    if let Some(b) = Board::builtin(&rig.board) {
        return Ok(b);
    }
    Board::load(base.join(&rig.board)).map_err(|e| format!("board: {e}"))
}

/// The phase-shift sequence of a rig file (docs/design.md §6): the default for its projectors
/// (gamma 1 is linear, others uncorrected) unless `steps` is set; `steps` below 5P means the
/// projectors' gamma is linearised by hexcal (frequencies 1…P). Fringe counts as given.
pub fn sequence(rig: &RigFile) -> Result<Sequence, String> {
    let p = rig.projectors.len() as u32;
    let err = |e: crate::pattern::SequenceError| format!("sequence: {e}");
    let linearised = rig.sequence.steps.is_some_and(|n| n < 5 * p);
    let setups: Vec<ProjectorSetup> = rig
        .projectors
        .iter()
        .map(|s| ProjectorSetup {
            width: s.width,
            height: s.height,
            response: if s.gamma == 1.0 {
                ProjectorResponse::Linear
            } else if linearised {
                ProjectorResponse::Linearised { gamma: s.gamma }
            } else {
                ProjectorResponse::Gamma { gamma: s.gamma }
            },
        })
        .collect();
    let default = Sequence::default_for(&setups).map_err(err)?;
    let counts = rig.sequence.fringe_counts.clone();
    let steps = rig.sequence.steps.unwrap_or(default.steps());
    let codes: Vec<ProjectorCode> = if steps == default.steps() {
        default.projectors().to_vec()
    } else {
        // Frequencies ±1 (mod 5) when harmonics must stay apart, else 1…P.
        let harmonics = setups.iter().any(|s| s.response.has_harmonics());
        setups
            .iter()
            .enumerate()
            .map(|(i, s)| ProjectorCode {
                width: s.width,
                height: s.height,
                frequency: if harmonics {
                    5 * (i as u32 / 2) + if i % 2 == 0 { 1 } else { 4 }
                } else {
                    i as u32 + 1
                },
                response: s.response,
            })
            .collect()
    };
    Sequence::new(steps, codes, counts.clone(), counts).map_err(err)
}

/// Open every device of `rig` (its file in folder `base`).
pub fn open(rig: &RigFile, base: &Path) -> Result<OpenedRig, String> {
    let board = board(rig, base)?;
    let sequence = sequence(rig)?;
    let world = if rig.cameras.iter().any(|c| c.driver == CameraDriver::Sim)
        || rig
            .projectors
            .iter()
            .any(|p| p.driver == ProjectorDriver::Sim)
    {
        Some(Arc::new(SimWorld::new(rig, board.clone())?))
    } else {
        None
    };
    let (mut sim_cams, mut sim_projs) = match &world {
        Some(w) => {
            let (c, p) = w.devices();
            (c.into_iter(), p.into_iter())
        }
        None => (Vec::new().into_iter(), Vec::new().into_iter()),
    };
    let mut cameras: Vec<Box<dyn Camera>> = Vec::new();
    let mut configs = Vec::new();
    for c in &rig.cameras {
        let cam: Box<dyn Camera> = match c.driver {
            CameraDriver::Sim => Box::new(sim_cams.next().ok_or("simulated cameras")?),
            driver => open_camera(driver, &c.name, c.address.as_deref())?,
        };
        cameras.push(cam);
        configs.push(CameraConfig {
            width: c.width,
            height: c.height,
            bits: c.bits,
            exposure_us: 1e3 * c.exposure_ms,
            gain_db: c.gain_db,
            trigger: if rig.trigger.is_some() {
                TriggerSource::Line
            } else {
                TriggerSource::Software
            },
        });
    }
    let mut projectors: Vec<Box<dyn Projector>> = Vec::new();
    for p in &rig.projectors {
        projectors.push(match p.driver {
            ProjectorDriver::Sim => Box::new(sim_projs.next().ok_or("simulated projectors")?),
            ProjectorDriver::Window => {
                open_window(&p.name, p.monitor.as_deref(), p.width, p.height)?
            }
        });
    }
    let trigger: Option<Box<dyn Trigger>> = match &rig.trigger {
        Some(t) => {
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
            if t.port == SIMULATED_PORT {
                // The simulator's firmware model on a pty, its lines wired to the
                // simulated cameras.
                let world = world
                    .clone()
                    .ok_or("trigger: port \"sim\" needs simulated cameras")?;
                let mut w = WiredTrigger::simulated(world, Duration::from_secs(2))?;
                w.controller()
                    .configure(&lines)
                    .map_err(|e| e.to_string())?;
                Some(Box::new(w))
            } else {
                let mut c = TriggerController::open(&t.port, 115_200, TriggerTiming::default())
                    .map_err(|e| e.to_string())?;
                c.configure(&lines).map_err(|e| e.to_string())?;
                Some(Box::new(c))
            }
        }
        None => None,
    };
    let frame = Duration::from_secs_f64(1e-3 * rig.timing.frame_period_ms);
    let timing = CaptureTiming {
        settle: Duration::from_secs_f64(1e-3 * rig.timing.settle_ms),
        latency: rig
            .projectors
            .iter()
            .map(|p| Duration::from_secs_f64(1e-3 * p.latency_ms))
            .collect(),
        // Simulated cameras render while the others wait: allow for it.
        frame_timeout: (10 * frame).max(Duration::from_secs(if world.is_some() { 30 } else { 2 })),
        retries: 2,
        repeats: rig.timing.repeats,
    };
    Ok(OpenedRig {
        board,
        cameras,
        configs,
        projectors,
        trigger,
        sequence,
        timing,
        world,
    })
}

fn open_camera(
    driver: CameraDriver,
    name: &str,
    address: Option<&str>,
) -> Result<Box<dyn Camera>, String> {
    #[cfg(feature = "aravis")]
    if driver == CameraDriver::Aravis {
        let address = address.ok_or_else(|| format!("camera {name}: address is required"))?;
        return crate::rig::aravis::AravisCamera::open(name, address)
            .map(|c| Box::new(c) as Box<dyn Camera>)
            .map_err(|e| e.to_string());
    }
    #[cfg(feature = "v4l2")]
    if driver == CameraDriver::V4l2 {
        let address = address.ok_or_else(|| format!("camera {name}: address is required"))?;
        return crate::rig::v4l2::V4l2Camera::open(name, address)
            .map(|c| Box::new(c) as Box<dyn Camera>)
            .map_err(|e| e.to_string());
    }
    let _ = address;
    let feature = match driver {
        CameraDriver::Aravis => "aravis",
        CameraDriver::V4l2 => "v4l2",
        CameraDriver::Sim => unreachable!("simulated cameras come from the world"),
    };
    Err(format!(
        "camera {name}: driver {feature} is not built in; rebuild with `--features {feature}`"
    ))
}

#[cfg(feature = "window")]
fn open_window(
    name: &str,
    monitor: Option<&str>,
    width: u32,
    height: u32,
) -> Result<Box<dyn Projector>, String> {
    let monitor = monitor.ok_or_else(|| format!("projector {name}: monitor is required"))?;
    crate::rig::window::WindowProjector::open(name, monitor, width, height)
        .map(|p| Box::new(p) as Box<dyn Projector>)
        .map_err(|e| format!("projector {e}"))
}

#[cfg(not(feature = "window"))]
fn open_window(
    name: &str,
    _monitor: Option<&str>,
    _width: u32,
    _height: u32,
) -> Result<Box<dyn Projector>, String> {
    Err(format!(
        "projector {name}: driver window is not built in; rebuild with `--features window`"
    ))
}
