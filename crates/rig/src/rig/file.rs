//! Rig files (docs/design.md §13): one TOML file describes a rig — board, cameras, projectors,
//! trigger controller, phase-shift sequence, timing and, for simulated devices, their
//! ground truth and the board poses. Unknown keys and impossible values are errors that
//! name the key and its line. The format is documented in `docs/rig-file.md`.

use hexcal_core::board::{Board, BoardError};
use hexcal_core::camera::{Distortion, Intrinsics};
use hexcal_core::dataset::{CameraEntry, DatasetInfo, ProjectorEntry};
use hexcal_core::images::to_grey::Cfa;
use hexcal_core::limits;
use hexcal_core::pattern::{
    ProjectorCode, ProjectorResponse, ProjectorSetup, Sequence, SequenceError,
};
use hexcal_core::tomlspan::{line_of, KeySpans};
use hexcal_core::ValidationError;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

pub mod selftest;
pub mod steps;

/// Camera drivers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraDriver {
    /// Rendered by the simulator.
    Sim,
    /// GenICam camera through Aravis.
    Aravis,
    /// Video4Linux2 device.
    V4l2,
}

/// Projector drivers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ProjectorDriver {
    /// Rendered by the simulator.
    Sim,
    /// A borderless full-screen window on a monitor.
    Window,
}

/// A device's pose in the rig for simulated devices: the device at `eye` looking at
/// `target` (rig frame, mm, y up).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LookAt {
    /// Device centre (mm).
    pub eye: [f64; 3],
    /// A point on the optical axis (mm).
    pub target: [f64; 3],
}

/// Ground truth of a simulated device.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimTruth {
    /// Pinhole intrinsics (px).
    pub intrinsics: Intrinsics,
    /// Lens distortion.
    #[serde(default)]
    pub distortion: Distortion,
    /// Where it is.
    pub pose: LookAt,
}

/// One camera.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// Unique name.
    pub name: String,
    /// Driver.
    pub driver: CameraDriver,
    /// Device address: IP or serial (Aravis), `/dev/videoN` (V4L2); none for `sim`.
    #[serde(default)]
    pub address: Option<String>,
    /// Image width (px).
    pub width: u32,
    /// Image height (px).
    pub height: u32,
    /// Bits per pixel stored: 8, 12 or 16.
    #[serde(default = "default_bits")]
    pub bits: u8,
    /// Exposure time (ms).
    pub exposure_ms: f64,
    /// Analogue gain (dB).
    #[serde(default)]
    pub gain_db: f64,
    /// Trigger-controller output line; none for software trigger.
    #[serde(default)]
    pub trigger_line: Option<u8>,
    /// Pixel format: a GenICam name (`aravis`, e.g. `BayerRG12p`), a fourcc (`v4l2`, e.g.
    /// `MJPG`) or `Mono`, `BayerRG` / `GR` / `GB` / `BG`, `MJPG` (`sim`); none: the driver
    /// chooses (monochrome, then Bayer, then RGB, then MJPEG).
    #[serde(default)]
    pub format: Option<String>,
    /// JPEG quality (1–100) of a `sim` camera with `format = "MJPG"` (default 85).
    #[serde(default)]
    pub jpeg_quality: Option<u8>,
    /// Ground truth (`sim` only).
    #[serde(default)]
    pub sim: Option<SimTruth>,
}

/// What a simulated camera delivers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimFormat {
    /// A monochrome sensor.
    Mono,
    /// A Bayer sensor of this phase, its raw mosaic.
    Bayer(Cfa),
    /// A webcam's Motion JPEG at this quality (1–100), 8 bits.
    Mjpeg(u8),
}

/// The JPEG quality of a simulated MJPEG camera whose rig file gives none.
pub const DEFAULT_JPEG_QUALITY: u8 = 85;

impl CameraSpec {
    /// What this camera delivers if simulated: its `format` and `jpeg_quality`; the reason
    /// (naming the key) when they make no simulated format.
    pub fn sim_format(&self) -> Result<SimFormat, ValidationError> {
        let format = match self.format.as_deref().unwrap_or("Mono") {
            "Mono" => SimFormat::Mono,
            "BayerRG" => SimFormat::Bayer(Cfa::Rggb),
            "BayerGR" => SimFormat::Bayer(Cfa::Grbg),
            "BayerGB" => SimFormat::Bayer(Cfa::Gbrg),
            "BayerBG" => SimFormat::Bayer(Cfa::Bggr),
            "MJPG" => SimFormat::Mjpeg(self.jpeg_quality.unwrap_or(DEFAULT_JPEG_QUALITY)),
            other => {
                return Err(ValidationError::new(
                    "format",
                    format!(
                        "{other:?}: a simulated camera is Mono, BayerRG, BayerGR, BayerGB, \
                         BayerBG or MJPG"
                    ),
                ))
            }
        };
        match (format, self.jpeg_quality) {
            (SimFormat::Mjpeg(q), _) if !(1..=100).contains(&q) => Err(ValidationError::new(
                "jpeg_quality",
                format!("{q}: use 1 to 100"),
            )),
            (SimFormat::Mjpeg(_), _) if self.bits != 8 => Err(ValidationError::new(
                "bits",
                format!("{} bits: MJPEG is 8 bits", self.bits),
            )),
            (SimFormat::Mono | SimFormat::Bayer(_), Some(_)) => Err(ValidationError::new(
                "jpeg_quality",
                "only for format = \"MJPG\"",
            )),
            _ => Ok(format),
        }
    }
}

fn default_bits() -> u8 {
    8
}

/// One projector.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProjectorSpec {
    /// Unique name.
    pub name: String,
    /// Driver.
    pub driver: ProjectorDriver,
    /// Monitor (connector name, e.g. `HDMI-1`) for `window`.
    #[serde(default)]
    pub monitor: Option<String>,
    /// Raster width (px).
    pub width: u32,
    /// Raster height (px).
    pub height: u32,
    /// Time from a frame's present to light on the board (ms).
    #[serde(default)]
    pub latency_ms: f64,
    /// Projector gamma (1 when the rig linearises it).
    #[serde(default = "default_gamma")]
    pub gamma: f64,
    /// Trigger-controller line it signals on, if any.
    #[serde(default)]
    pub trigger_line: Option<u8>,
    /// Ground truth (`sim` only).
    #[serde(default)]
    pub sim: Option<SimTruth>,
    /// How a simulated display misbehaves (`sim` only; docs/rig-file.md, "Self-tests").
    #[serde(default)]
    pub sim_display: Option<selftest::SimDisplay>,
}

fn default_gamma() -> f64 {
    2.2
}

/// The serial trigger controller.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TriggerSpec {
    /// Serial port, e.g. `/dev/ttyACM0`.
    pub port: String,
    /// Pulse width (µs).
    #[serde(default = "default_pulse")]
    pub pulse_us: u32,
}

fn default_pulse() -> u32 {
    100
}

/// The phase-shift sequence (docs/design.md §6).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SequenceSpec {
    /// Fringe counts across the projector, for columns and rows.
    #[serde(default = "default_counts")]
    pub fringe_counts: Vec<u32>,
    /// Phase steps N per fringe count; default 5P (uncorrected gamma) or 2P + 1 (gamma 1).
    #[serde(default)]
    pub steps: Option<u32>,
}

fn default_counts() -> Vec<u32> {
    vec![20, 21, 25]
}

impl Default for SequenceSpec {
    fn default() -> Self {
        SequenceSpec {
            fringe_counts: default_counts(),
            steps: None,
        }
    }
}

/// Timing of the capture.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TimingSpec {
    /// Display time of one pattern (ms): the frame period.
    pub frame_period_ms: f64,
    /// Wait after a pattern is shown before the exposure starts (ms).
    #[serde(default)]
    pub settle_ms: f64,
    /// Pause between board poses (s).
    #[serde(default)]
    pub pose_pause_s: f64,
    /// Repeats of every frame (averaged).
    #[serde(default = "default_repeats")]
    pub repeats: u32,
    /// How many times `run` captures a pose again when a camera's stack fails the stack
    /// check (docs/design.md §6b); then the pose is kept without that camera's stack.
    #[serde(default = "default_stack_retries")]
    pub stack_retries: u32,
}

fn default_repeats() -> u32 {
    1
}

fn default_stack_retries() -> u32 {
    2
}

/// Most recaptures of one pose after a failed stack check.
pub const MAX_STACK_RETRIES: u32 = 10;

/// Board poses of a simulated rig: `count` poses turned about the vertical by up to ±`yaw`
/// degrees, tilted and rolled by up to ±`tilt` degrees, moved by up to ±`shift` mm, seeded.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PosesSpec {
    /// Number of poses.
    pub count: usize,
    /// Largest turn about the vertical (deg).
    pub yaw_deg: f64,
    /// Largest tilt and roll (deg).
    pub tilt_deg: f64,
    /// Largest shift (mm).
    pub shift_mm: f64,
    /// Seed.
    #[serde(default)]
    pub seed: u64,
    /// Poses where the board is not in front of the rig (the operator forgot it): for
    /// testing how a run reports a pose nobody saw.
    #[serde(default)]
    pub absent: Vec<usize>,
    /// Faults the simulator injects into poses' stacks, for testing the stack check.
    #[serde(default)]
    pub faults: Vec<SimFault>,
}

/// A fault the simulated rig shows in one pose's stacks (docs/rig-file.md).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimFault {
    /// The pose.
    pub pose: usize,
    /// How many captures of the pose show it (1: the first; a recapture is clean).
    #[serde(default = "default_fault_attempts")]
    pub attempts: u32,
    /// Every camera's gain multiplied by this (white clips above about 1.1).
    #[serde(default)]
    pub gain: Option<f64>,
    /// A projector one frame late: it shows the previous frame's pattern in these frames
    /// (first, last; within one fringe group).
    #[serde(default)]
    pub lag: Option<LagSpec>,
    /// The view drifts over the sequence: displaced linearly from nothing at the first
    /// frame to this (camera px, x and y) at the last.
    #[serde(default)]
    pub drift_px: Option<[f64; 2]>,
    /// The view jolts: displaced by `px` from frame `frame` on.
    #[serde(default)]
    pub jolt: Option<JoltSpec>,
    /// The room light steps: the ambient light times `factor` from frame `frame` on.
    #[serde(default)]
    pub ambient: Option<AmbientSpec>,
    /// The room light flickers: the ambient light times 1 + amplitude·sin(2π·k/period) at
    /// frame k.
    #[serde(default)]
    pub flicker: Option<FlickerSpec>,
}

/// The view displaced from one frame on (a bumped camera or rig).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JoltSpec {
    /// Displacement (camera px, x and y).
    pub px: [f64; 2],
    /// First frame displaced.
    pub frame: usize,
}

/// The ambient light changed from one frame on (a door opened, a lamp switched).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AmbientSpec {
    /// Factor on the ambient light.
    pub factor: f64,
    /// First frame changed.
    pub frame: usize,
}

/// The ambient light flickering.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlickerSpec {
    /// Relative amplitude (0.1: ±10 %).
    pub amplitude: f64,
    /// Period (frames).
    pub period: f64,
}

/// A projector showing the previous frame's pattern over a run of frames.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LagSpec {
    /// The projector (rig-file order of the simulated projectors).
    pub projector: usize,
    /// First and last frame affected.
    pub frames: [usize; 2],
}

fn default_fault_attempts() -> u32 {
    1
}

/// The console's done rule (`hexcal run --console`, docs/design.md §15).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GuidanceSpec {
    /// A device is done when its projection uncertainty (px, 1σ) stays below this over its
    /// whole image.
    #[serde(default = "default_uncertainty")]
    pub uncertainty_px: f64,
    /// The held-out length error (mm RMS) the rig should meet: the report warns when the
    /// calibration misses it, and not about checks that stay within it.
    #[serde(default = "default_target_mm")]
    pub target_mm: f64,
}

/// Default of [`GuidanceSpec::target_mm`] (mm).
pub const DEFAULT_TARGET_MM: f64 = 0.1;

fn default_target_mm() -> f64 {
    DEFAULT_TARGET_MM
}

/// Default of [`GuidanceSpec::uncertainty_px`] (px).
pub const DEFAULT_UNCERTAINTY_PX: f64 = 1.0;

fn default_uncertainty() -> f64 {
    DEFAULT_UNCERTAINTY_PX
}

impl Default for GuidanceSpec {
    fn default() -> Self {
        GuidanceSpec {
            uncertainty_px: DEFAULT_UNCERTAINTY_PX,
            target_mm: DEFAULT_TARGET_MM,
        }
    }
}

/// A rig file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigFile {
    /// Rig name.
    pub name: String,
    /// Built-in board name or board-file path (relative to the rig file).
    #[serde(default = "default_board")]
    pub board: String,
    /// Cameras.
    #[serde(rename = "camera")]
    pub cameras: Vec<CameraSpec>,
    /// Projectors.
    #[serde(rename = "projector", default)]
    pub projectors: Vec<ProjectorSpec>,
    /// Trigger controller; none for software triggering.
    #[serde(default)]
    pub trigger: Option<TriggerSpec>,
    /// Phase-shift sequence.
    #[serde(default)]
    pub sequence: SequenceSpec,
    /// Timing.
    pub timing: TimingSpec,
    /// Board poses of a simulated rig.
    #[serde(default)]
    pub poses: Option<PosesSpec>,
    /// The operator console's guidance (docs/rig-file.md, "Guidance").
    #[serde(default)]
    pub guidance: GuidanceSpec,
    /// Positioners that move the board (docs/rig-file.md, "Scripts and positioners").
    #[serde(rename = "positioner", default)]
    pub positioners: Vec<steps::PositionerSpec>,
    /// The capture script: steps run in order by `hexcal run`.
    #[serde(default)]
    pub script: Vec<steps::StepSpec>,
    /// When `run` checks sync and sets the exposure (docs/rig-file.md, "Self-tests").
    #[serde(default)]
    pub checks: selftest::ChecksSpec,
    /// The folder of the rig file (board files are relative to it); "." for parsed text.
    #[serde(skip, default = "current_folder")]
    pub base: PathBuf,
}

fn current_folder() -> PathBuf {
    PathBuf::from(".")
}

fn default_board() -> String {
    "hex600".into()
}

/// Why a rig file was refused.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    /// Not readable.
    #[error("cannot read {origin}: {source}")]
    Io {
        /// The file.
        origin: String,
        /// The cause.
        source: std::io::Error,
    },
    /// Not there: the rig files beside where it was looked for.
    #[error(
        "no rig file {origin}{}",
        match others.is_empty() {
            true => String::new(),
            false => format!("; rig files in {}: {}", folder, others.join(", ")),
        }
    )]
    Missing {
        /// The file.
        origin: String,
        /// The folder looked in.
        folder: String,
        /// The `.toml` files there (sorted).
        others: Vec<String>,
    },
    /// Not valid TOML of the format, or an impossible value: the file, the line of the key
    /// when known, the dotted key (e.g. `camera[2].exposure_ms`) and what is wrong.
    #[error(transparent)]
    Invalid(ValidationError),
}

/// [`RigError::Missing`] for `path`: the rig files in its folder (or, when that is not
/// there, in `rigs/`), so that a typo shows the names it meant.
fn missing(path: &Path) -> RigError {
    let parent = path.parent().filter(|p| !p.as_os_str().is_empty());
    let folder = match parent {
        Some(p) if p.is_dir() => p.to_path_buf(),
        _ => Path::new("rigs").to_path_buf(),
    };
    let mut others: Vec<String> = std::fs::read_dir(&folder)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".toml"))
        .collect();
    others.sort();
    others.truncate(40);
    RigError::Missing {
        origin: path.display().to_string(),
        folder: folder.display().to_string(),
        others,
    }
}

impl RigError {
    /// The key the error is about, if any.
    pub fn field(&self) -> Option<&str> {
        match self {
            RigError::Invalid(e) => Some(&e.at),
            RigError::Io { .. } | RigError::Missing { .. } => None,
        }
    }

    /// The line the error is about, if known.
    pub fn line(&self) -> Option<usize> {
        match self {
            RigError::Invalid(e) => e.line,
            RigError::Io { .. } | RigError::Missing { .. } => None,
        }
    }
}

impl RigFile {
    /// Read and check a rig file.
    pub fn load(path: impl AsRef<Path>) -> Result<RigFile, RigError> {
        RigFile::load_with_text(path).map(|(rig, _)| rig)
    }

    /// [`RigFile::load`], also giving the file's text as read (a run copies it into its
    /// dataset without reading the file again).
    pub fn load_with_text(path: impl AsRef<Path>) -> Result<(RigFile, String), RigError> {
        let path = path.as_ref();
        let origin = path.display().to_string();
        let text = hexcal_core::limits::read_text(path).map_err(|source| match source.kind() {
            std::io::ErrorKind::NotFound => missing(path),
            _ => RigError::Io {
                origin: origin.clone(),
                source,
            },
        })?;
        let mut rig = RigFile::parse(&text, &origin)?;
        rig.base = path.parent().unwrap_or(Path::new(".")).to_owned();
        Ok((rig, text))
    }

    /// The board the rig file names: a built-in name or a board file relative to the rig
    /// file's folder.
    pub fn board(&self) -> Result<Board, BoardError> {
        if let Some(b) = Board::builtin(&self.board) {
            return Ok(b);
        }
        Board::load(self.base.join(&self.board))
    }

    /// The phase-shift sequence of a rig file (docs/design.md §6): the default for its projectors
    /// (gamma 1 is linear, others uncorrected) unless `steps` is set; `steps` below 5P means the
    /// projectors' gamma is linearised by hexcal (frequencies 1…P). Fringe counts as given.
    /// A rig without projectors takes one plain frame per camera per pose
    /// ([`Sequence::camera_only`]; `[timing] repeats` makes it a burst, averaged).
    pub fn sequence(&self) -> Result<Sequence, SequenceError> {
        let rig = self;
        if rig.projectors.is_empty() {
            return Ok(Sequence::camera_only());
        }
        let p = rig.projectors.len() as u32;
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
        let default = Sequence::default_for(&setups)?;
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
        Sequence::new(steps, codes, counts.clone(), counts)
    }

    /// The dataset description of this rig under `sequence` (docs/dataset.md).
    pub fn dataset_info(&self, sequence: &Sequence) -> DatasetInfo {
        DatasetInfo {
            format: hexcal_core::dataset::FORMAT.into(),
            version: hexcal_core::dataset::VERSION,
            rig: self.name.clone(),
            board: self.board.clone(),
            sequence: sequence.clone(),
            cameras: self
                .cameras
                .iter()
                .map(|c| CameraEntry {
                    name: c.name.clone(),
                    width: c.width,
                    height: c.height,
                    bits: c.bits,
                    pixel_format: None,
                })
                .collect(),
            projectors: self
                .projectors
                .iter()
                .map(|p| ProjectorEntry {
                    name: p.name.clone(),
                    width: p.width,
                    height: p.height,
                })
                .collect(),
        }
    }

    /// Parse and check rig-file text; errors name `origin`, the key and its line.
    pub fn parse(text: &str, origin: &str) -> Result<RigFile, RigError> {
        let mut keys = KeySpans::default();
        let rig: Result<RigFile, toml_edit::de::Error> =
            toml_edit::ImDocument::parse(text.to_owned())
                .map_err(Into::into)
                .and_then(|doc| {
                    keys = KeySpans::of(doc.as_table());
                    toml_edit::de::from_document(doc)
                });
        let rig = rig.map_err(|e| {
            let span = e.span().filter(|s| Some(s) != keys.root.as_ref());
            let line = span.as_ref().map(|s| line_of(text, s.start));
            let field = span
                .and_then(|s| keys.field_at(&s))
                .unwrap_or_else(|| "(file)".into());
            let message = e.message().trim().replace('\n', ", ");
            RigError::Invalid(
                ValidationError::new(field, message)
                    .in_file(origin)
                    .on_line(line),
            )
        })?;
        rig.check().map_err(|e| {
            let line = keys.line_of(&e.at, text);
            RigError::Invalid(e.in_file(origin).on_line(line))
        })?;
        Ok(rig)
    }

    /// The checks serde cannot make: the dotted key and message of the first violation. Every
    /// number is finite and physically possible, every count and size within
    /// [`hexcal_core::limits`], every name unique and usable as a folder name.
    fn check(&self) -> Result<(), ValidationError> {
        self.check_board_name()?;
        self.check_timing()?;
        if self.cameras.is_empty() {
            return Err(ValidationError::new(
                "camera",
                "a rig needs at least one camera",
            ));
        }
        let devices = self.cameras.len() + self.projectors.len();
        limits::count(devices, limits::MAX_DEVICES, "devices").map_err(|m| m.at("camera"))?;
        let mut names: HashMap<&str, String> = HashMap::new();
        let mut lines: HashMap<u8, String> = HashMap::new();
        for (i, c) in self.cameras.iter().enumerate() {
            let at = |k: &str| format!("camera[{i}].{k}");
            check_device(&mut names, &c.name, at("name"))?;
            self.check_camera(c, &at)?;
            if let Some(l) = c.trigger_line {
                check_line(&mut lines, l, &c.name, at("trigger_line"))?;
            }
        }
        for (i, p) in self.projectors.iter().enumerate() {
            let at = |k: &str| format!("projector[{i}].{k}");
            check_device(&mut names, &p.name, at("name"))?;
            self.check_projector(p, &at)?;
            if let Some(l) = p.trigger_line {
                check_line(&mut lines, l, &p.name, at("trigger_line"))?;
            }
        }
        self.check_trigger(&lines)?;
        self.check_sequence()?;
        self.check_poses()?;
        let u = self.guidance.uncertainty_px;
        if !(u.is_finite() && u > 0.0 && u <= 100.0) {
            return Err(ValidationError::new(
                "guidance.uncertainty_px",
                format!("{u} px is not a projection uncertainty (0 < u ≤ 100 px)"),
            ));
        }
        let t = self.guidance.target_mm;
        if !(t.is_finite() && t > 0.0 && t <= 1000.0) {
            return Err(ValidationError::new(
                "guidance.target_mm",
                format!("{t} mm is not a length error to aim for (0 < t ≤ 1000 mm)"),
            ));
        }
        self.checks.check()?;
        let simulated = self.cameras.iter().any(|c| c.driver == CameraDriver::Sim);
        self.check_script(simulated)
    }

    /// `board`: a built-in board's name or the path of a board file (ending `.toml`); a
    /// name that is neither (a typo of `hex600`) is refused naming the built-in boards.
    fn check_board_name(&self) -> Result<(), ValidationError> {
        let path_like = self.board.ends_with(".toml") || self.board.contains(['/', '\\']);
        if path_like || Board::builtin(&self.board).is_some() {
            return Ok(());
        }
        Err(ValidationError::new(
            "board",
            format!(
                "{} (a board file's path ends in .toml, relative to the rig file)",
                BoardError::Unknown(self.board.clone())
            ),
        ))
    }

    /// `[timing]`: durations finite, positive where they must be, at most an hour.
    fn check_timing(&self) -> Result<(), ValidationError> {
        let t = &self.timing;
        let at = |k: &str| format!("timing.{k}");
        if !(t.frame_period_ms.is_finite()
            && t.frame_period_ms > 0.0
            && t.frame_period_ms <= limits::MAX_DURATION_MS)
        {
            return Err(ValidationError::new(
                at("frame_period_ms"),
                format!(
                    "{} is not a duration in (0, {}] ms",
                    t.frame_period_ms,
                    limits::MAX_DURATION_MS
                ),
            ));
        }
        if !(t.settle_ms.is_finite() && t.settle_ms >= 0.0 && t.settle_ms < t.frame_period_ms) {
            return Err(ValidationError::new(
                at("settle_ms"),
                format!(
                    "must lie in [0, frame_period_ms = {}) ms",
                    t.frame_period_ms
                ),
            ));
        }
        limits::non_negative(t.pose_pause_s, limits::MAX_DURATION_MS / 1e3)
            .map_err(|m| ValidationError::new(at("pose_pause_s"), format!("{m} s")))?;
        if !(1..=limits::MAX_REPEATS).contains(&t.repeats) {
            return Err(ValidationError::new(
                at("repeats"),
                format!("{} repeats: 1 to {}", t.repeats, limits::MAX_REPEATS),
            ));
        }
        if t.stack_retries > MAX_STACK_RETRIES {
            return Err(ValidationError::new(
                at("stack_retries"),
                format!("{}: at most {MAX_STACK_RETRIES}", t.stack_retries),
            ));
        }
        Ok(())
    }

    /// One camera: image size, bits, an exposure that fits the frame, a gain within
    /// ±[`limits::MAX_GAIN_DB`], driver and ground truth.
    fn check_camera(
        &self,
        c: &CameraSpec,
        at: &dyn Fn(&str) -> String,
    ) -> Result<(), ValidationError> {
        let t = &self.timing;
        let window = t.frame_period_ms - t.settle_ms;
        limits::image_size(c.width, c.height).map_err(|m| m.at(at("width")))?;
        if ![8, 12, 16].contains(&c.bits) {
            return Err(ValidationError::new(
                at("bits"),
                format!("{} bits: use 8, 12 or 16", c.bits),
            ));
        }
        if !(c.exposure_ms > 0.0 && c.exposure_ms <= window) {
            return Err(ValidationError::new(
                at("exposure_ms"),
                format!(
                    "{} ms does not fit in a pattern's display time after settling \
                     ({} − {} = {window} ms)",
                    c.exposure_ms, t.frame_period_ms, t.settle_ms
                ),
            ));
        }
        limits::within(c.gain_db, -limits::MAX_GAIN_DB, limits::MAX_GAIN_DB)
            .map_err(|m| m.at(at("gain_db")))?;
        if let Some(f) = &c.format {
            if f.is_empty()
                || f.len() > 32
                || !f.chars().all(|ch| ch.is_ascii_graphic() || ch == ' ')
            {
                return Err(ValidationError::new(
                    at("format"),
                    format!("{f:?} is not a pixel format name"),
                ));
            }
        }
        match c.driver {
            CameraDriver::Sim => {
                c.sim_format().map_err(|e| e.map_at(|key| at(key)))?;
            }
            _ if c.jpeg_quality.is_some() => {
                return Err(ValidationError::new(
                    at("jpeg_quality"),
                    "only for a simulated camera (a real one sets its own)",
                ))
            }
            _ => {}
        }
        check_driver(
            c.driver == CameraDriver::Sim,
            c.sim.is_some(),
            &c.address,
            at,
        )?;
        check_truth(c.sim.as_ref(), at)
    }

    /// One projector: raster size, gamma, latency within the frame, driver and truth.
    fn check_projector(
        &self,
        p: &ProjectorSpec,
        at: &dyn Fn(&str) -> String,
    ) -> Result<(), ValidationError> {
        let period = self.timing.frame_period_ms;
        limits::image_size(p.width, p.height).map_err(|m| m.at(at("width")))?;
        if !(p.gamma > 0.0 && p.gamma < 5.0) {
            return Err(ValidationError::new(
                at("gamma"),
                format!("{} is not a projector gamma", p.gamma),
            ));
        }
        if !(p.latency_ms.is_finite() && p.latency_ms >= 0.0 && p.latency_ms < period) {
            return Err(ValidationError::new(
                at("latency_ms"),
                format!(
                    "{} is not in [0, frame_period_ms = {period}) ms",
                    p.latency_ms
                ),
            ));
        }
        match p.driver {
            ProjectorDriver::Sim if p.sim.is_none() => {
                return Err(ValidationError::new(
                    at("sim"),
                    "a sim projector needs its ground truth",
                ))
            }
            ProjectorDriver::Window if p.monitor.is_none() => {
                return Err(ValidationError::new(
                    at("monitor"),
                    "a window projector needs a monitor",
                ))
            }
            ProjectorDriver::Window if p.sim.is_some() => {
                return Err(ValidationError::new(
                    at("sim"),
                    "only sim projectors have ground truth",
                ))
            }
            _ => {}
        }
        match (&p.sim_display, p.driver) {
            (Some(d), ProjectorDriver::Sim) => d.check(at)?,
            (Some(_), _) => {
                return Err(ValidationError::new(
                    at("sim_display"),
                    "only for a simulated projector",
                ))
            }
            (None, _) => {}
        }
        check_truth(p.sim.as_ref(), at)
    }

    /// `[trigger]`: present when lines are given; a pulse that fits the frame.
    fn check_trigger(&self, lines: &HashMap<u8, String>) -> Result<(), ValidationError> {
        let Some(t) = &self.trigger else {
            if lines.is_empty() {
                return Ok(());
            }
            return Err(ValidationError::new(
                "trigger",
                "trigger lines are given but no trigger controller",
            ));
        };
        let period_us = 1e3 * self.timing.frame_period_ms;
        if t.pulse_us == 0 || f64::from(t.pulse_us) > period_us {
            return Err(ValidationError::new(
                "trigger.pulse_us",
                format!(
                    "{} µs is not in [1, {period_us}] µs (the frame period)",
                    t.pulse_us
                ),
            ));
        }
        Ok(())
    }

    /// `[sequence]`: enough fringe counts, each and the steps within the limits, and a
    /// sequence the projectors can show ([`RigFile::sequence`]).
    fn check_sequence(&self) -> Result<(), ValidationError> {
        let s = &self.sequence;
        if self.projectors.is_empty() && *s != SequenceSpec::default() {
            return Err(ValidationError::new(
                "sequence",
                "a rig without projectors shows no sequence: each pose is one frame per \
                 camera (a burst with [timing] repeats)",
            ));
        }
        if s.fringe_counts.len() < 2 {
            return Err(ValidationError::new(
                "sequence.fringe_counts",
                "temporal unwrapping needs at least two fringe counts",
            ));
        }
        if let Some(&c) = s
            .fringe_counts
            .iter()
            .find(|&&c| c > limits::MAX_IMAGE_SIDE)
        {
            return Err(ValidationError::new(
                "sequence.fringe_counts",
                format!("{c} fringes: at most {}", limits::MAX_IMAGE_SIDE),
            ));
        }
        if let Some(n) = s.steps.filter(|&n| n > limits::MAX_PHASE_STEPS) {
            return Err(ValidationError::new(
                "sequence.steps",
                format!("{n} steps: at most {}", limits::MAX_PHASE_STEPS),
            ));
        }
        self.sequence().map(drop).map_err(|e| {
            let at = match &e {
                SequenceError::Counts { .. } => "sequence.fringe_counts".to_string(),
                SequenceError::Projector { projector, .. } => format!("projector[{projector}]"),
                _ => "sequence.steps".to_string(),
            };
            ValidationError::new(at, e.what())
        })
    }

    /// `[poses]`: present for a simulated rig, a count within the limit, finite ranges,
    /// absent poses among them.
    fn check_poses(&self) -> Result<(), ValidationError> {
        let simulated = self.cameras.iter().any(|c| c.driver == CameraDriver::Sim);
        if simulated && self.poses.is_none() && !self.has_sim_stage() {
            return Err(ValidationError::new(
                "poses",
                "a simulated rig needs board poses (or a sim positioner that moves the board)",
            ));
        }
        let Some(p) = &self.poses else {
            return Ok(());
        };
        if p.count == 0 {
            return Err(ValidationError::new("poses.count", "at least one pose"));
        }
        limits::count(p.count, limits::MAX_POSES, "poses").map_err(|m| m.at("poses.count"))?;
        for (key, v, most) in [
            ("yaw_deg", p.yaw_deg, 180.0),
            ("tilt_deg", p.tilt_deg, 90.0),
            ("shift_mm", p.shift_mm, limits::MAX_DISTANCE_MM),
        ] {
            limits::non_negative(v, most).map_err(|m| m.at(format!("poses.{key}")))?;
        }
        if let Some(k) = p.absent.iter().find(|&&k| k >= p.count) {
            return Err(ValidationError::new(
                "poses.absent",
                format!("pose {k} is out of range (count = {})", p.count),
            ));
        }
        for (i, f) in p.faults.iter().enumerate() {
            check_fault(f, p.count, self.projectors.len())
                .map_err(|m| ValidationError::new(format!("poses.faults[{i}]"), m))?;
        }
        Ok(())
    }
}

/// A simulated fault: its pose and projector in range, a gain between 0 and 100, frames in
/// order.
fn check_fault(f: &SimFault, poses: usize, projectors: usize) -> Result<(), String> {
    if f.pose >= poses {
        return Err(format!("pose {} is out of range (count = {poses})", f.pose));
    }
    if let Some(g) = f.gain {
        if !(g.is_finite() && g > 0.0 && g <= 100.0) {
            return Err(format!("gain {g}: a factor between 0 and 100"));
        }
    }
    let px_ok = |p: [f64; 2]| p.iter().all(|v| v.is_finite() && v.abs() <= 50.0);
    if let Some(d) = f.drift_px.filter(|d| !px_ok(*d)) {
        return Err(format!("drift_px {d:?}: at most 50 px each way"));
    }
    if let Some(j) = f.jolt.filter(|j| !px_ok(j.px)) {
        return Err(format!("jolt.px {:?}: at most 50 px each way", j.px));
    }
    if let Some(a) = f
        .ambient
        .filter(|a| !(a.factor.is_finite() && (0.0..=100.0).contains(&a.factor)))
    {
        return Err(format!(
            "ambient.factor {}: a factor between 0 and 100",
            a.factor
        ));
    }
    if let Some(fl) = f.flicker {
        if !(fl.amplitude.is_finite() && (0.0..=1.0).contains(&fl.amplitude)) {
            return Err(format!(
                "flicker.amplitude {}: between 0 and 1",
                fl.amplitude
            ));
        }
        if !(fl.period.is_finite() && (2.0..=10_000.0).contains(&fl.period)) {
            return Err(format!(
                "flicker.period {}: between 2 and 10000 frames",
                fl.period
            ));
        }
    }
    if let Some(l) = f.lag {
        if l.projector >= projectors {
            return Err(format!("lag.projector {} of {projectors}", l.projector));
        }
        if l.frames[0] > l.frames[1] {
            return Err(format!("lag.frames {:?}: first after last", l.frames));
        }
    }
    Ok(())
}

/// A simulated device's ground truth: intrinsics and distortion as [`Intrinsics::check`]
/// and [`Distortion::check`] require, a finite look-at with the eye off the target.
fn check_truth(
    truth: Option<&SimTruth>,
    at: &dyn Fn(&str) -> String,
) -> Result<(), ValidationError> {
    let Some(t) = truth else {
        return Ok(());
    };
    t.intrinsics
        .check()
        .map_err(|e| e.map_at(|f| at(&format!("sim.intrinsics.{f}"))))?;
    t.distortion
        .check()
        .map_err(|e| e.map_at(|f| at(&format!("sim.distortion.{f}"))))?;
    let far = limits::MAX_DISTANCE_MM;
    for (key, point) in [
        ("sim.pose.eye", t.pose.eye),
        ("sim.pose.target", t.pose.target),
    ] {
        for v in point {
            limits::within(v, -far, far).map_err(|m| m.at(at(key)))?;
        }
    }
    if t.pose.eye == t.pose.target {
        return Err(ValidationError::new(at("sim.pose"), "eye equals target"));
    }
    Ok(())
}

fn check_device<'a>(
    names: &mut HashMap<&'a str, String>,
    name: &'a str,
    field: String,
) -> Result<(), ValidationError> {
    limits::device_name(name).map_err(|m| m.at(field.clone()))?;
    match names.insert(name, field.clone()) {
        Some(first) => Err(ValidationError::new(
            field,
            format!("{name:?} is already the name of {first}"),
        )),
        None => Ok(()),
    }
}

fn check_line(
    lines: &mut HashMap<u8, String>,
    line: u8,
    device: &str,
    field: String,
) -> Result<(), ValidationError> {
    match lines.insert(line, device.to_owned()) {
        Some(other) => Err(ValidationError::new(
            field,
            format!("line {line} is already {other}'s"),
        )),
        None => Ok(()),
    }
}

fn check_driver(
    sim: bool,
    has_truth: bool,
    address: &Option<String>,
    at: &dyn Fn(&str) -> String,
) -> Result<(), ValidationError> {
    match (sim, has_truth, address) {
        (true, false, _) => Err(ValidationError::new(
            at("sim"),
            "a sim camera needs its ground truth",
        )),
        (false, true, _) => Err(ValidationError::new(
            at("sim"),
            "only sim cameras have ground truth",
        )),
        (false, _, None) => Err(ValidationError::new(
            at("address"),
            "a real camera needs an address",
        )),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests;
