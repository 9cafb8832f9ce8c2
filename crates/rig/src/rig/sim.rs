//! The simulated rig: cameras and projectors of a rig file's `sim` devices, implementing the
//! same device traits as the real drivers, so the capture engine runs unchanged on them.
//!
//! Takes a [`RigFile`] (devices with ground truth, board poses) and gives boxed
//! [`Camera`]s and [`Projector`]s sharing one [`SimWorld`]: the board pose the "operator"
//! placed and what every projector shows. A triggered camera renders frame k of its stack
//! ([`StackRenderer`], geometry once per pose) when every projector shows pattern k; in a
//! rig without projectors, its plain frame of the board lit by the room.
//! Faults can be injected per camera (stop delivering, drop frames) for the engine's tests.

use super::device::{Camera, CameraConfig, DeviceError, Projector, Slide};
use super::file::selftest::SimDisplay;
use super::file::{LookAt, PosesSpec, ProjectorDriver, RigFile, SimFormat, SimTruth};
use hexcal_core::board::Board;
use hexcal_core::camera::CameraModel;
use hexcal_core::images::to_grey::{jpeg_luma, to_pixels, BayerBalance, Cfa};
use hexcal_core::images::{CameraFrame, Pixels};
use hexcal_core::pattern::Sequence;
use hexcal_sim::stack::{FrameChange, StackProjector, StackRenderer};
use hexcal_sim::{Imaging, PoseSpec, Scene, SimError};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{rngs::StdRng, Rng, SeedableRng};
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Why a simulated rig could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum SimRigError {
    /// A simulated device without its `sim` truth.
    #[error("{0}: a sim device needs sim.intrinsics and sim.pose")]
    NoTruth(String),
    /// A device's `sim.pose` is impossible.
    #[error("{device}: sim.pose: {source}")]
    Pose {
        /// The device.
        device: String,
        /// Why.
        source: SimError,
    },
    /// No `[poses]` table.
    #[error("a simulated rig needs a [poses] table")]
    NoPoses,
    /// No pty pair for the simulated trigger controller.
    #[error("trigger: no pty pair: {0}")]
    Pty(serialport::Error),
    /// The host driver could not talk to the simulated controller.
    #[error("trigger: {0}")]
    Controller(#[from] super::trigger::TriggerError),
}

/// Ambient light on white (DN) and the level every projector together adds up to on white
/// (docs/design.md §9 default stack conditions); a rig without projectors is lit to the
/// white level by the room.
const AMBIENT_DN: f64 = 40.0;
const WHITE_DN: f64 = 235.0;

/// A simulated device's truth: model and T_device_rig.
#[derive(Clone, Debug)]
pub struct SimDevice {
    /// Name (the rig file's).
    pub name: String,
    /// Lens model and image size.
    pub model: CameraModel,
    /// T_device_rig.
    pub pose: Isometry3<f64>,
}

/// What the simulated projectors show and where the board is.
#[derive(Clone, Debug)]
struct State {
    pose: usize,
    /// What each projector's light on the board shows now.
    slides: Vec<Slide>,
    sequence: Option<Sequence>,
    /// Per projector, slides shown but not yet on the board (a display with
    /// [`SimDisplay`] lag), with the time each appears, in order.
    queued: Vec<VecDeque<(Instant, Slide)>>,
    /// Per projector, the slides shown so far (counts its drops and repeats).
    shows: Vec<u64>,
}

impl State {
    /// Move the queued slides due by `now` onto the board.
    fn advance(&mut self, now: Instant) {
        for (slide, queue) in self.slides.iter_mut().zip(&mut self.queued) {
            while queue.front().is_some_and(|(t, _)| *t <= now) {
                if let Some((_, s)) = queue.pop_front() {
                    *slide = s;
                }
            }
        }
    }
}

/// The shared world of a simulated rig: ground truth and current state.
#[derive(Debug)]
pub struct SimWorld {
    /// The board.
    pub board: Board,
    /// Simulated cameras.
    pub cameras: Vec<SimDevice>,
    /// Simulated projectors.
    pub projectors: Vec<SimDevice>,
    /// Board poses T_rig_board.
    pub board_poses: Vec<Isometry3<f64>>,
    /// What each simulated camera delivers, in the order of `cameras`.
    pub formats: Vec<SimFormat>,
    /// Faults injected into poses' stacks.
    pub faults: Vec<super::file::SimFault>,
    /// Each simulated projector's display faults, if any.
    displays: Vec<Option<SimDisplay>>,
    imaging: Imaging,
    state: Mutex<State>,
    /// Trigger pulses on the cameras' lines so far (see [`WiredTrigger`]).
    pulses: std::sync::atomic::AtomicU64,
    /// Where a simulated positioner holds the board, when one does.
    mount: MountSlot,
    /// Poses placed elsewhere than `board_poses` says (a guided operator's), T_rig_board.
    moved: Mutex<std::collections::BTreeMap<usize, Isometry3<f64>>>,
    /// Taken while a camera builds its stack renderer: one at a time (the geometry pass and
    /// a projector's whole-image truth are transient per-pixel buffers; each build runs on
    /// all cores).
    building: Mutex<()>,
}

/// The slot of a [`BoardMount`] (Debug shows whether something holds the board).
#[derive(Default)]
struct MountSlot(Mutex<Option<BoardMount>>);

impl std::fmt::Debug for MountSlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let held = self.0.lock().map(|m| m.is_some()).unwrap_or(false);
        write!(f, "{}", if held { "mounted" } else { "free" })
    }
}

/// Where the board is now (T_rig_board), read from whatever holds it (a simulated stage).
pub type BoardMount = Box<dyn Fn() -> Isometry3<f64> + Send + Sync>;

/// T_device_rig of a device at `eye` looking at `target` (rig y up, image y down).
pub fn look_at(l: &LookAt) -> Result<Isometry3<f64>, SimError> {
    PoseSpec {
        eye: Some(l.eye),
        target: Some(l.target),
        ..PoseSpec::default()
    }
    .cam_from_board()
}

/// The board poses T_rig_board of a `[poses]` table: turned about the vertical evenly over
/// ±yaw, tilted and rolled at random within ±tilt, shifted within ±shift (seeded).
pub fn board_poses(spec: &PosesSpec) -> Vec<Isometry3<f64>> {
    let mut rng = StdRng::seed_from_u64(spec.seed);
    (0..spec.count)
        .map(|k| {
            let f = if spec.count > 1 {
                k as f64 / (spec.count - 1) as f64
            } else {
                0.5
            };
            let yaw = (spec.yaw_deg * (2.0 * f - 1.0)).to_radians();
            let mut r = || rng.random_range(-1.0..=1.0);
            let (tilt, roll) = (
                (spec.tilt_deg * r()).to_radians(),
                (spec.tilt_deg * r()).to_radians(),
            );
            let mut shift = Vector3::new(r(), r(), r()) * spec.shift_mm;
            if spec.absent.contains(&k) {
                // Far behind every device: nothing sees it.
                shift.y += 1e5;
            }
            let rot = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw)
                * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), tilt)
                * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll);
            Isometry3::from_parts(Translation3::from(shift), rot)
        })
        .collect()
}

fn device(
    name: &str,
    truth: Option<&SimTruth>,
    width: u32,
    height: u32,
) -> Result<SimDevice, SimRigError> {
    let t = truth.ok_or_else(|| SimRigError::NoTruth(name.to_string()))?;
    Ok(SimDevice {
        name: name.to_string(),
        model: CameraModel {
            width,
            height,
            intrinsics: t.intrinsics,
            distortion: t.distortion,
        },
        pose: look_at(&t.pose).map_err(|source| SimRigError::Pose {
            device: name.to_string(),
            source,
        })?,
    })
}

impl SimWorld {
    /// The world of `rig`'s simulated devices on `board` (devices of other drivers are left
    /// out); fails naming the device whose truth is missing or the missing `[poses]`.
    pub fn new(rig: &RigFile, board: Board) -> Result<SimWorld, SimRigError> {
        use super::file::CameraDriver;
        let cameras = rig
            .cameras
            .iter()
            .filter(|c| c.driver == CameraDriver::Sim)
            .map(|c| device(&c.name, c.sim.as_ref(), c.width, c.height))
            .collect::<Result<Vec<_>, _>>()?;
        let formats = rig
            .cameras
            .iter()
            .filter(|c| c.driver == CameraDriver::Sim)
            .map(|c| c.sim_format().unwrap_or(SimFormat::Mono))
            .collect();
        let projectors = rig
            .projectors
            .iter()
            .filter(|p| p.driver == ProjectorDriver::Sim)
            .map(|p| device(&p.name, p.sim.as_ref(), p.width, p.height))
            .collect::<Result<Vec<_>, _>>()?;
        let poses = match &rig.poses {
            Some(p) => board_poses(p),
            None if rig.has_sim_stage() => Vec::new(),
            None => return Err(SimRigError::NoPoses),
        };
        Ok(SimWorld {
            board,
            faults: rig
                .poses
                .as_ref()
                .map_or_else(Vec::new, |p| p.faults.clone()),
            board_poses: poses,
            state: Mutex::new(State {
                pose: 0,
                slides: vec![Slide::Black; projectors.len()],
                sequence: None,
                queued: vec![VecDeque::new(); projectors.len()],
                shows: vec![0; projectors.len()],
            }),
            displays: rig
                .projectors
                .iter()
                .filter(|p| p.driver == ProjectorDriver::Sim)
                .map(|p| p.sim_display)
                .collect(),
            cameras,
            formats,
            projectors,
            imaging: Imaging::default(),
            pulses: std::sync::atomic::AtomicU64::new(0),
            mount: MountSlot::default(),
            moved: Mutex::new(Default::default()),
            building: Mutex::new(()),
        })
    }

    /// From now on the board is where `mount` says (a simulated positioner holds it),
    /// whatever pose is placed.
    pub fn mount(&self, mount: BoardMount) {
        *self.mount.0.lock().unwrap_or_else(|e| e.into_inner()) = Some(mount);
    }

    /// T_rig_board at pose `pose`: where the mount holds it, else where it was placed
    /// ([`SimWorld::place_at`]), else the `[poses]` pose.
    pub fn board_at(&self, pose: usize) -> Option<Isometry3<f64>> {
        match &*self.mount.0.lock().unwrap_or_else(|e| e.into_inner()) {
            Some(m) => Some(m()),
            None => {
                let moved = self.moved.lock().unwrap_or_else(|e| e.into_inner());
                moved.get(&pose).or(self.board_poses.get(pose)).copied()
            }
        }
    }

    /// Place the board at pose `pose` (what the operator does between poses).
    pub fn place(&self, pose: usize) {
        self.lock().pose = pose;
    }

    /// Place the board for pose `pose` at `board` (T_rig_board) instead of the `[poses]`
    /// pose: where a guided operator puts it.
    pub fn place_at(&self, pose: usize, board: Isometry3<f64>) {
        self.moved
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(pose, board);
        self.place(pose);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panicking device thread cannot leave the state half-written: every write is
        // one assignment.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// What is on the board now: the state with every displayed slide due by now.
    fn on_board(&self) -> State {
        let mut state = self.lock();
        state.advance(Instant::now());
        state.clone()
    }

    /// Projector `p` is told to show `slide`: on the board at once, or as its display's
    /// faults say (late by its lag, a repeat one refresh later still, a drop never).
    fn show(&self, p: usize, slide: Slide) {
        let now = Instant::now();
        let mut state = self.lock();
        state.advance(now);
        state.shows[p] += 1;
        let n = state.shows[p];
        let Some(d) = self.displays.get(p).copied().flatten() else {
            state.queued[p].clear();
            state.slides[p] = slide;
            return;
        };
        let every = |k: Option<u32>| k.is_some_and(|k| n % u64::from(k) == 0);
        if every(d.drop_every) {
            return;
        }
        let mut due = now + Duration::from_secs_f64(1e-3 * d.lag_ms);
        if every(d.repeat_every) {
            due += d.refresh();
        }
        // A display shows its frames in order.
        if let Some((last, _)) = state.queued[p].back() {
            due = due.max(*last);
        }
        state.queued[p].push_back((due, slide));
        state.advance(now);
    }

    /// The simulated cameras and projectors of this world, as devices.
    pub fn devices(self: &Arc<Self>) -> (Vec<SimCamera>, Vec<SimProjector>) {
        let cams = (0..self.cameras.len())
            .map(|index| SimCamera {
                world: Arc::clone(self),
                index,
                renderer: None,
                pending: VecDeque::new(),
                counter: 0,
                exposure_us: 0.0,
                gain_db: 0.0,
                configured: (0.0, 0.0),
                started: false,
                line: false,
                pulses_seen: 0,
                faults: Faults::default(),
                balance: BayerBalance::default(),
                attempts: Default::default(),
            })
            .collect();
        let projs = (0..self.projectors.len())
            .map(|index| SimProjector {
                world: Arc::clone(self),
                index,
            })
            .collect();
        (cams, projs)
    }

    /// The stack renderer of camera `c` at board pose `pose` under `sequence` (what a
    /// triggered camera renders from).
    pub fn stack_renderer(
        &self,
        c: usize,
        pose: usize,
        sequence: &Sequence,
    ) -> Result<StackRenderer, SimError> {
        let board = self.board_at(pose).ok_or_else(|| {
            SimError::Scene(format!(
                "pose {pose}: the simulated rig has {} board poses and nothing holds the board",
                self.board_poses.len()
            ))
        })?;
        self.stack_renderer_at(c, pose, board, sequence)
    }

    /// The scene camera `c` sees with the board at `board` (T_rig_board) for pose `pose`
    /// (its noise seed): what its stacks are rendered from, and its ground truth.
    pub fn scene_at(&self, c: usize, pose: usize, board: Isometry3<f64>) -> Scene {
        let cam = &self.cameras[c];
        let cam_from_board = cam.pose * board;
        let r = cam_from_board.rotation.scaled_axis();
        let t = cam_from_board.translation.vector;
        Scene {
            name: format!("{}-pose{pose}", cam.name),
            seed: 1000 * pose as u64 + c as u64,
            camera: cam.model,
            pose: PoseSpec {
                rvec: Some([r.x, r.y, r.z]),
                tvec: Some([t.x, t.y, t.z]),
                ..PoseSpec::default()
            },
            imaging: self.imaging,
            board: self.board.clone(),
        }
    }

    /// The stack renderer of camera `c` with the board at `board` (T_rig_board) for pose
    /// `pose` (its noise seed).
    pub fn stack_renderer_at(
        &self,
        c: usize,
        pose: usize,
        board: Isometry3<f64>,
        sequence: &Sequence,
    ) -> Result<StackRenderer, SimError> {
        let scene = self.scene_at(c, pose, board);
        let gain = (WHITE_DN - AMBIENT_DN) / self.projectors.len().max(1) as f64;
        // Without projectors the room light is what lights the board, up to the white level.
        let ambient = match self.projectors.is_empty() {
            true => WHITE_DN,
            false => AMBIENT_DN,
        };
        let projectors: Vec<StackProjector> = self
            .projectors
            .iter()
            .map(|p| StackProjector {
                model: p.model,
                proj_from_board: p.pose * board,
                gain_dn: gain,
            })
            .collect();
        StackRenderer::new(&scene, &projectors, ambient, sequence)
    }
}

/// What a simulated camera renders.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Showing {
    /// Frame k of the sequence (or of a camera-only rig's plain frames), each projector
    /// showing its pattern of the list (k, or an earlier one of a late display).
    Pattern(usize, Vec<usize>),
    /// Every projector white (`true`) or black.
    Flat(bool),
    /// Each projector a flat level of its own.
    Levels(Vec<u8>),
}

/// Faults a simulated camera can be told to show.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Faults {
    /// Stop delivering after this many frames (as if unplugged).
    pub stop_after: Option<u64>,
    /// Lose every frame whose counter is a multiple of this (exposed, never delivered).
    pub drop_every: Option<u64>,
}

/// A simulated camera.
pub struct SimCamera {
    world: Arc<SimWorld>,
    index: usize,
    renderer: Option<(usize, Isometry3<f64>, StackRenderer)>,
    pending: VecDeque<CameraFrame>,
    counter: u64,
    exposure_us: f64,
    gain_db: f64,
    /// The exposure (µs) and gain (dB) of the last [`Camera::configure`]: the rendered
    /// images' own brightness; other settings scale it.
    configured: (f64, f64),
    started: bool,
    /// Exposures start on line pulses rather than software triggers.
    line: bool,
    /// Line pulses already exposed.
    pulses_seen: u64,
    faults: Faults,
    /// White balance of a Bayer camera, held from `start` to `stop` as the drivers do.
    balance: BayerBalance,
    /// Per pose, the captures of its sequence begun so far (for [`SimWorld::faults`]).
    attempts: std::collections::BTreeMap<usize, u32>,
}

impl SimCamera {
    /// Inject `faults`.
    pub fn set_faults(&mut self, faults: Faults) {
        self.faults = faults;
    }

    fn failed(&self, reason: impl Into<String>) -> DeviceError {
        DeviceError::Failed {
            device: self.name().to_string(),
            reason: reason.into(),
        }
    }
}

impl Camera for SimCamera {
    fn name(&self) -> &str {
        &self.world.cameras[self.index].name
    }

    fn configure(&mut self, config: &CameraConfig) -> Result<(), DeviceError> {
        let m = &self.world.cameras[self.index].model;
        if (config.width, config.height) != (m.width, m.height) {
            return Err(DeviceError::Unsupported {
                device: self.name().to_string(),
                setting: "width, height".into(),
                reason: format!(
                    "{}×{} asked, the simulated sensor is {}×{}",
                    config.width, config.height, m.width, m.height
                ),
            });
        }
        if config.bits != self.world.imaging.bits {
            return Err(DeviceError::Unsupported {
                device: self.name().to_string(),
                setting: "bits".into(),
                reason: format!(
                    "{} asked, the simulated sensor gives {}",
                    config.bits, self.world.imaging.bits
                ),
            });
        }
        self.exposure_us = config.exposure_us;
        self.gain_db = config.gain_db;
        self.configured = (config.exposure_us, config.gain_db);
        self.line = config.trigger == super::device::TriggerSource::Line;
        Ok(())
    }

    fn set_exposure_gain(&mut self, exposure_us: f64, gain_db: f64) -> Result<(), DeviceError> {
        if !(exposure_us.is_finite() && exposure_us > 0.0 && gain_db.is_finite()) {
            return Err(DeviceError::unsupported(
                self.name(),
                "exposure_us, gain_db",
                format!("{exposure_us} µs, {gain_db} dB"),
            ));
        }
        self.exposure_us = exposure_us;
        self.gain_db = gain_db;
        Ok(())
    }

    fn pixel_format(&self) -> Option<String> {
        Some(match self.world.formats[self.index] {
            SimFormat::Mono => format!("Mono{}", self.world.imaging.bits),
            SimFormat::Bayer(cfa) => format!("Bayer{}{}", cfa_name(cfa), self.world.imaging.bits),
            SimFormat::Mjpeg(q) => format!("MJPG (quality {q})"),
        })
    }

    fn balances_colour(&self) -> bool {
        matches!(self.world.formats[self.index], SimFormat::Bayer(_))
    }

    fn start(&mut self) -> Result<(), DeviceError> {
        self.started = true;
        self.balance = BayerBalance::default();
        self.pending.clear();
        self.pulses_seen = self.world.pulses.load(std::sync::atomic::Ordering::SeqCst);
        Ok(())
    }

    fn trigger(&mut self) -> Result<(), DeviceError> {
        if self.line {
            return Err(DeviceError::Unsupported {
                device: self.name().to_string(),
                setting: "trigger".into(),
                reason: "software trigger on a line-triggered camera".into(),
            });
        }
        self.expose()
    }

    fn next_frame(&mut self, timeout: Duration) -> Result<CameraFrame, DeviceError> {
        if self.line {
            // Expose once per pulse that arrived on the line, waiting for one if none has.
            let deadline = std::time::Instant::now() + timeout;
            loop {
                let pulses = self.world.pulses.load(std::sync::atomic::Ordering::SeqCst);
                while self.pulses_seen < pulses {
                    self.pulses_seen += 1;
                    self.expose()?;
                }
                if !self.pending.is_empty() || std::time::Instant::now() >= deadline {
                    break;
                }
                std::thread::sleep(Duration::from_micros(200));
            }
        }
        match self.pending.pop_front() {
            Some(f) => Ok(f),
            None => {
                if !self.line {
                    std::thread::sleep(timeout);
                }
                Err(DeviceError::Timeout {
                    device: self.name().to_string(),
                    timeout,
                })
            }
        }
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        self.started = false;
        self.renderer = None;
        Ok(())
    }
}

impl SimCamera {
    /// Scale a rendered frame (at the configured exposure and gain) to the exposure and
    /// gain set now: signal ∝ exposure · 10^(gain/20), clipped at full scale. (The noise
    /// scales with it, as if amplified after the sensor.)
    fn brighten(&self, data: &mut [u16], bits: u8) {
        let (exposure, gain) = self.configured;
        if (self.exposure_us, self.gain_db) == (exposure, gain) || exposure <= 0.0 {
            return;
        }
        let scale = self.exposure_us / exposure * 10f64.powf((self.gain_db - gain) / 20.0);
        let full = f64::from((1u32 << bits) - 1);
        for v in data {
            *v = (f64::from(*v) * scale).round().min(full) as u16;
        }
    }

    /// What to render and the sequence the projectors were prepared with: pattern k of
    /// every projector, or a flat field (every projector white, or every one black: a
    /// preview between poses); in a rig without projectors, the plain frame (indexed by the
    /// camera's counter, so the frames of a burst have noise of their own).
    fn showing(&self, state: &State) -> Result<(Showing, Sequence), DeviceError> {
        if self.world.projectors.is_empty() {
            return Ok((
                Showing::Pattern(self.counter as usize, Vec::new()),
                Sequence::camera_only(),
            ));
        }
        let all = |slide: Slide| state.slides.iter().all(|s| *s == slide);
        let patterns: Option<Vec<usize>> = (state.slides.iter())
            .map(|s| match s {
                Slide::Pattern(k) => Some(*k),
                _ => None,
            })
            .collect();
        let levels: Option<Vec<u8>> = (state.slides.iter())
            .map(|s| match s {
                Slide::Black => Some(0),
                Slide::White => Some(255),
                Slide::Level(l) => Some(*l),
                Slide::Pattern(_) => None,
            })
            .collect();
        let what = match (patterns, levels) {
            (Some(shown), _) => Showing::Pattern(shown.iter().copied().max().unwrap_or(0), shown),
            _ if all(Slide::White) => Showing::Flat(true),
            _ if all(Slide::Black) => Showing::Flat(false),
            (_, Some(levels)) => Showing::Levels(levels),
            _ => {
                return Err(self.failed(format!(
                    "the simulator renders patterns of every projector or flat fields of \
                     every projector, not a mix; projectors show {:?}",
                    state.slides
                )))
            }
        };
        let sequence = state
            .sequence
            .clone()
            .ok_or_else(|| self.failed("projectors not prepared"))?;
        Ok((what, sequence))
    }

    /// Expose one frame of what the projectors show now.
    fn expose(&mut self) -> Result<(), DeviceError> {
        if !self.started {
            return Err(self.failed("triggered before start"));
        }
        if self.faults.stop_after.is_some_and(|n| self.counter >= n) {
            return Ok(());
        }
        let state = self.world.on_board();
        let (what, sequence) = self.showing(&state)?;
        let board = self.world.board_at(state.pose).ok_or_else(|| {
            self.failed(format!(
                "pose {}: no board pose (the rig has {})",
                state.pose,
                self.world.board_poses.len()
            ))
        })?;
        if self
            .renderer
            .as_ref()
            .is_none_or(|(p, b, _)| *p != state.pose || *b != board)
        {
            self.renderer = None;
            let built = {
                let _turn = self
                    .world
                    .building
                    .lock()
                    .unwrap_or_else(|e| e.into_inner());
                self.world
                    .stack_renderer_at(self.index, state.pose, board, &sequence)
            };
            let mut r = built.map_err(|e| self.failed(e.to_string()))?;
            if let SimFormat::Bayer(cfa) = self.world.formats[self.index] {
                r.set_cfa(Some(cfa_response(cfa)));
            }
            for (p, d) in self.world.displays.iter().enumerate() {
                if let Some(level) = d.and_then(|d| d.clip_level) {
                    r.clip_light(p, level);
                }
            }
            self.renderer = Some((state.pose, board, r));
        }
        let Some((_, _, renderer)) = &self.renderer else {
            unreachable!("set above")
        };
        if matches!(&what, Showing::Pattern(0, _)) {
            *self.attempts.entry(state.pose).or_default() += 1;
        }
        let attempt = self.attempts.get(&state.pose).copied().unwrap_or(0);
        let faults: Vec<&super::file::SimFault> = (self.world.faults.iter())
            .filter(|f| f.pose == state.pose && attempt <= f.attempts)
            .collect();
        let mut frame = match what {
            Showing::Pattern(k, shown) => {
                let change = changed(k, &faults, sequence.frame_count());
                renderer.frame_changed(k, &lagged(k, shown, &faults), &change)
            }
            Showing::Flat(white) => renderer.flat_frame(white, self.counter),
            Showing::Levels(levels) => renderer.levels_frame(&levels, self.counter),
        };
        self.brighten(&mut frame.data, frame.bits);
        if let Some(gain) = faults.iter().find_map(|f| f.gain) {
            let full = f64::from((1u32 << frame.bits) - 1);
            for v in &mut frame.data {
                *v = (f64::from(*v) * gain).round().min(full) as u16;
            }
        }
        let counter = self.counter;
        self.counter += 1;
        if self.faults.drop_every.is_some_and(|n| counter % n == n - 1) {
            return Ok(());
        }
        let pixels = self.deliver(
            frame.data,
            frame.size.width as usize,
            frame.size.height as usize,
            frame.bits,
        )?;
        self.pending.push_back(CameraFrame {
            width: frame.size.width,
            height: frame.size.height,
            bits: frame.bits,
            pixels,
            counter,
            timestamp_ns: counter * 1_000_000,
            exposure_us: self.exposure_us,
        });
        Ok(())
    }
}

impl SimCamera {
    /// A rendered frame as the camera's format delivers it, turned grey as the drivers do
    /// (docs/design.md §11): a Bayer mosaic balanced, a JPEG coded at its quality and
    /// decoded to its luma.
    fn deliver(
        &mut self,
        mut data: Vec<u16>,
        width: usize,
        height: usize,
        bits: u8,
    ) -> Result<Pixels, DeviceError> {
        match self.world.formats[self.index] {
            SimFormat::Mono => Ok(to_pixels(data, bits)),
            SimFormat::Bayer(cfa) => {
                self.balance.apply(&mut data, width, cfa, bits);
                Ok(to_pixels(data, bits))
            }
            SimFormat::Mjpeg(quality) => {
                let bytes: Vec<u8> = data.iter().map(|&v| v.min(255) as u8).collect();
                let mut jpeg = Vec::new();
                image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, quality)
                    .encode(
                        &bytes,
                        width as u32,
                        height as u32,
                        image::ExtendedColorType::L8,
                    )
                    .map_err(|e| self.failed(format!("JPEG encoder: {e}")))?;
                let luma =
                    jpeg_luma(&jpeg, width, height).map_err(|e| self.failed(e.to_string()))?;
                Ok(Pixels::Gray8(luma))
            }
        }
    }
}

/// The pattern each projector shows in frame k under `faults`: the previous frame's for a
/// lagged projector in its frames, else what its display shows (`shown`).
fn lagged(k: usize, mut shown: Vec<usize>, faults: &[&super::file::SimFault]) -> Vec<usize> {
    for lag in faults.iter().filter_map(|f| f.lag) {
        if (lag.frames[0]..=lag.frames[1]).contains(&k) && k > 0 {
            if let Some(p) = shown.get_mut(lag.projector) {
                *p = k - 1;
            }
        }
    }
    shown
}

/// How frame k of a sequence of `frames` differs under `faults` (drift, jolt, ambient
/// step and flicker).
fn changed(k: usize, faults: &[&super::file::SimFault], frames: usize) -> FrameChange {
    let mut c = FrameChange::default();
    let mut ambient = 1.0;
    for f in faults {
        if let Some([dx, dy]) = f.drift_px {
            let t = k as f64 / frames.saturating_sub(1).max(1) as f64;
            c.shift = [c.shift[0] + t * dx, c.shift[1] + t * dy];
        }
        if let Some(j) = f.jolt.filter(|j| k >= j.frame) {
            c.shift = [c.shift[0] + j.px[0], c.shift[1] + j.px[1]];
        }
        if let Some(a) = f.ambient.filter(|a| k >= a.frame) {
            ambient *= a.factor;
        }
        if let Some(fl) = f.flicker {
            ambient *= 1.0 + fl.amplitude * (std::f64::consts::TAU * k as f64 / fl.period).sin();
        }
    }
    c.ambient = ambient as f32;
    c
}

/// The relative response to the simulator's white light of a Bayer sensor's red, green
/// and blue pixels (a typical colour CMOS sensor: green the most sensitive).
pub const CFA_RESPONSE: [f32; 3] = [0.60, 1.0, 0.80];

/// The response of the four pixels of a 2×2 cell of `cfa` ([`CFA_RESPONSE`]), row by row.
fn cfa_response(cfa: Cfa) -> [f32; 4] {
    [(0, 0), (1, 0), (0, 1), (1, 1)].map(|(x, y)| CFA_RESPONSE[cfa.channel(x, y)])
}

/// GenICam's two letters of a CFA phase (`RG` for RGGB).
fn cfa_name(cfa: Cfa) -> &'static str {
    match cfa {
        Cfa::Rggb => "RG",
        Cfa::Grbg => "GR",
        Cfa::Gbrg => "GB",
        Cfa::Bggr => "BG",
    }
}

/// The trigger controller (the real host driver, talking to real or simulated firmware)
/// wired to a simulated rig's camera lines: a frame's pulse reaches the cameras when the
/// controller reports it done (its `FrameDone` event, with the controller's timestamp).
pub struct WiredTrigger {
    controller: super::trigger::TriggerController,
    world: Arc<SimWorld>,
    next: u32,
    timeout: Duration,
    /// The simulated firmware serving the controller's port, when it is simulated too.
    firmware: Option<hexcal_simulator::firmware::SimulatedController>,
}

impl WiredTrigger {
    /// Wire `controller`'s lines to `world`'s cameras; `timeout` bounds the wait for each
    /// frame's `FrameDone`.
    pub fn new(
        controller: super::trigger::TriggerController,
        world: Arc<SimWorld>,
        timeout: Duration,
    ) -> WiredTrigger {
        WiredTrigger {
            controller,
            world,
            next: 0,
            timeout,
            firmware: None,
        }
    }

    /// A controller whose firmware is the simulator's model on an in-process pty pair.
    pub fn simulated(world: Arc<SimWorld>, timeout: Duration) -> Result<WiredTrigger, SimRigError> {
        use hexcal_simulator::firmware::{ModelConfig, SimulatedController};
        use serialport::SerialPort;
        let (mut master, slave) = serialport::TTYPort::pair().map_err(SimRigError::Pty)?;
        // The firmware's read timeout is its timer resolution.
        master
            .set_timeout(Duration::from_millis(1))
            .map_err(SimRigError::Pty)?;
        let firmware = SimulatedController::spawn(master, ModelConfig::default());
        let controller = super::trigger::TriggerController::from_port(
            Box::new(slave),
            super::trigger::TriggerTiming::default(),
        )?;
        Ok(WiredTrigger {
            firmware: Some(firmware),
            ..WiredTrigger::new(controller, world, timeout)
        })
    }

    /// The controller, to configure its lines.
    pub fn controller(&mut self) -> &mut super::trigger::TriggerController {
        &mut self.controller
    }

    /// Frames the simulated firmware fired, if it is simulated.
    pub fn firmware_frames(&self) -> Option<u64> {
        self.firmware.as_ref().map(|f| f.stats().frames_fired)
    }

    /// The host driver's counters (requests, retries, CRC errors, lost events).
    pub fn stats(&self) -> super::trigger::TriggerStats {
        self.controller.stats()
    }

    fn error(&self, e: super::trigger::TriggerError) -> DeviceError {
        e.into_device_error(self.controller.port_name())
    }
}

impl super::device::Trigger for WiredTrigger {
    fn name(&self) -> &str {
        self.controller.port_name()
    }

    fn arm(&mut self, frames: u32) -> Result<(), DeviceError> {
        self.next = 0;
        super::device::Trigger::arm(&mut self.controller, frames)
    }

    fn fire(&mut self) -> Result<u32, DeviceError> {
        let frame = super::device::Trigger::fire(&mut self.controller)?;
        let done = self
            .controller
            .wait_frame_done(self.timeout)
            .map_err(|e| self.error(e))?;
        if done.frame != frame || frame != self.next {
            return Err(DeviceError::Failed {
                device: self.controller.port_name().to_string(),
                reason: format!(
                    "frame {} reported done after firing frame {frame} (expected {})",
                    done.frame, self.next
                ),
            });
        }
        self.next += 1;
        self.world
            .pulses
            .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        Ok(frame)
    }

    fn disarm(&mut self) -> Result<(), DeviceError> {
        super::device::Trigger::disarm(&mut self.controller)
    }
}

/// A simulated projector.
pub struct SimProjector {
    world: Arc<SimWorld>,
    index: usize,
}

impl Projector for SimProjector {
    fn name(&self) -> &str {
        &self.world.projectors[self.index].name
    }

    fn resolution(&self) -> (u32, u32) {
        let m = &self.world.projectors[self.index].model;
        (m.width, m.height)
    }

    fn prepare(&mut self, sequence: &Sequence, code: usize) -> Result<(), DeviceError> {
        if code != self.index || code >= sequence.projectors().len() {
            return Err(DeviceError::Unsupported {
                device: self.name().to_string(),
                setting: "sequence".into(),
                reason: format!(
                    "simulated projector {} cannot show code {code} of {}",
                    self.index,
                    sequence.projectors().len()
                ),
            });
        }
        self.world.lock().sequence = Some(sequence.clone());
        Ok(())
    }

    fn show(&mut self, slide: Slide) -> Result<(), DeviceError> {
        self.world.show(self.index, slide);
        Ok(())
    }
}
