//! The `[[positioner]]` and `[[script]]` tables of a rig file as written (docs/rig-file.md,
//! "Scripts and positioners"): positioner drivers and their settings, script steps and
//! stepping variables. Checked and unrolled by [`crate::rig::script`].

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Positioner drivers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PositionerDriver {
    /// A device on a serial line speaking a text protocol.
    Serial,
    /// The simulator's turntable and tilt stage on an in-process pty; it moves the
    /// simulated board.
    Sim,
}

/// How command lines to a positioner end.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LineEnding {
    /// `\n`.
    #[default]
    Lf,
    /// `\r\n`.
    Crlf,
    /// `\r`.
    Cr,
}

impl LineEnding {
    /// The bytes that end a line.
    pub fn text(self) -> &'static str {
        match self {
            LineEnding::Lf => "\n",
            LineEnding::Crlf => "\r\n",
            LineEnding::Cr => "\r",
        }
    }
}

/// A fault the simulated stage shows, for testing how a run reports it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SimFaultKind {
    /// Replies nothing.
    Silent,
    /// Replies line noise.
    Garbage,
    /// Replies `ERR motor stalled`.
    Error,
}

/// `sim.fault` of a simulated stage: what goes wrong after how many moves.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimFaultSpec {
    /// The fault.
    pub kind: SimFaultKind,
    /// Moves completed before it starts.
    #[serde(default)]
    pub after_moves: u32,
}

/// The simulated stage: a turntable (axis `angle`, about the rig's vertical) carrying a tilt
/// axis (`tilt`, about the table's horizontal), the board mounted on it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimStageSpec {
    /// Where the stage's axes cross, in the rig frame (mm).
    #[serde(default)]
    pub centre: [f64; 3],
    /// Where the board's centre is on the mount, from the axes' crossing (mm, board frame):
    /// an off-axis board sweeps across the views as the table turns.
    #[serde(default)]
    pub offset: [f64; 3],
    /// How the board is turned in its own plane on the mount (deg).
    #[serde(default)]
    pub roll_deg: f64,
    /// Axis speed (deg/s).
    #[serde(default = "default_speed")]
    pub speed_deg_s: f64,
    /// Largest tilt either way (deg).
    #[serde(default = "default_tilt_limit")]
    pub tilt_limit_deg: f64,
    /// A fault to show (testing).
    #[serde(default)]
    pub fault: Option<SimFaultSpec>,
}

fn default_speed() -> f64 {
    90.0
}

fn default_tilt_limit() -> f64 {
    60.0
}

/// A positioner: a device that moves the board on command.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PositionerSpec {
    /// Unique name (steps name it).
    pub name: String,
    /// Driver.
    pub driver: PositionerDriver,
    /// Serial port (`serial` only).
    #[serde(default)]
    pub port: Option<String>,
    /// Baud rate.
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Line ending of commands.
    #[serde(default)]
    pub line_ending: LineEnding,
    /// Command template: `{name}` is replaced by the move step's `to.name`.
    pub command: String,
    /// Pattern (regular expression) of the reply that says the move is done.
    #[serde(default = "default_reply")]
    pub reply: String,
    /// Pattern of a reply that reports a fault.
    #[serde(default = "default_fault")]
    pub fault: String,
    /// Command sent when a move is interrupted (Ctrl-C), if the device has one.
    #[serde(default)]
    pub stop: Option<String>,
    /// Longest wait for a move's reply (s).
    #[serde(default = "default_timeout")]
    pub timeout_s: f64,
    /// Expected duration of a move, for the planned timeline (s); a `sim` stage's moves are
    /// planned from its speed.
    #[serde(default)]
    pub move_s: f64,
    /// The simulated stage (`sim` only).
    #[serde(default)]
    pub sim: Option<SimStageSpec>,
    /// The device echoes each line it is sent: that line is skipped.
    #[serde(default)]
    pub echo: bool,
    /// Pattern of the line that acknowledges a command at once; the move is then done at
    /// the `reply` line, or when the `poll` finds the device idle.
    #[serde(default)]
    pub ack: Option<String>,
    /// Poll the device's state until it is idle, instead of waiting for a `reply` line.
    #[serde(default)]
    pub poll: Option<PollSpec>,
    /// Serial framing: data bits (7 or 8).
    #[serde(default = "default_data_bits")]
    pub data_bits: u8,
    /// Serial framing: parity.
    #[serde(default)]
    pub parity: Parity,
    /// Serial framing: stop bits (1 or 2).
    #[serde(default = "default_stop_bits")]
    pub stop_bits: u8,
    /// Serial flow control.
    #[serde(default)]
    pub flow_control: FlowControl,
    /// Device steps per unit of the numbers move steps give (degrees, mm): each is
    /// multiplied by it and rounded to a whole step before it fills the command.
    #[serde(default)]
    pub steps_per_unit: Option<f64>,
}

/// How a positioner is polled until its move is done.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PollSpec {
    /// The status query sent (e.g. `?` for GRBL, `/1` for a Zaber device).
    pub query: String,
    /// Pattern of a status line that says the device is idle (the move done).
    pub idle: String,
    /// Time between queries (s).
    #[serde(default = "default_poll_period")]
    pub period_s: f64,
}

/// Serial parity.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Parity {
    /// None.
    #[default]
    None,
    /// Odd.
    Odd,
    /// Even.
    Even,
}

/// Serial flow control.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FlowControl {
    /// None.
    #[default]
    None,
    /// XON/XOFF.
    Software,
    /// RTS/CTS.
    Hardware,
}

fn default_data_bits() -> u8 {
    8
}

fn default_stop_bits() -> u8 {
    1
}

fn default_poll_period() -> f64 {
    0.1
}

fn default_baud() -> u32 {
    115_200
}

fn default_reply() -> String {
    "^OK".into()
}

fn default_fault() -> String {
    "^(ERR|FAULT)".into()
}

fn default_timeout() -> f64 {
    30.0
}

/// A value a move step gives a command template: a number, or text that may use the
/// script's variables (`"{angle}"`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum ValueSpec {
    /// A number.
    Number(f64),
    /// Text, variables substituted.
    Text(String),
}

/// A `repeat` block's stepping variable: `from + i·step` in round i, or `values[i]` (cycled).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VarSpec {
    /// Value in round 0.
    #[serde(default)]
    pub from: Option<f64>,
    /// Added every round.
    #[serde(default)]
    pub step: Option<f64>,
    /// The values, round by round (cycled).
    #[serde(default)]
    pub values: Option<Vec<f64>>,
}

/// One `[[script]]` step as written: exactly one of `capture`, `wait`, `prompt`, `move`,
/// `repeat`, `every`, with the keys that step takes.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepSpec {
    /// Capture one pose; the text labels it (variables substituted).
    #[serde(default)]
    pub capture: Option<String>,
    /// Wait this many seconds.
    #[serde(default)]
    pub wait: Option<f64>,
    /// Show this text and wait for the operator (Enter), or `timeout_s`.
    #[serde(default)]
    pub prompt: Option<String>,
    /// Move this positioner.
    #[serde(default, rename = "move")]
    pub move_to: Option<String>,
    /// `move`: the template's values.
    #[serde(default)]
    pub to: Option<BTreeMap<String, ValueSpec>>,
    /// `move`: pattern of the reply that says done (default: the positioner's `reply`).
    #[serde(default)]
    pub expect: Option<String>,
    /// `move`, `prompt`: longest wait (s).
    #[serde(default)]
    pub timeout_s: Option<f64>,
    /// Repeat `steps` this many times.
    #[serde(default)]
    pub repeat: Option<u32>,
    /// `repeat`: stepping variables.
    #[serde(default)]
    pub vars: Option<BTreeMap<String, VarSpec>>,
    /// `repeat`: the block.
    #[serde(default)]
    pub steps: Option<Vec<StepSpec>>,
    /// Capture every this many seconds (hand-held board), `count` times.
    #[serde(default)]
    pub every: Option<f64>,
    /// `every`: captures.
    #[serde(default)]
    pub count: Option<u32>,
    /// `every`: countdown before each capture (s, default 3).
    #[serde(default)]
    pub countdown_s: Option<f64>,
    /// `every`: label of each capture (`{i}` is its number in the block).
    #[serde(default)]
    pub label: Option<String>,
    /// `capture`, `every`: exposure of these captures (µs) instead of the cameras' own.
    #[serde(default)]
    pub exposure_us: Option<f64>,
    /// `capture`, `every`: gain of these captures (dB) instead of the cameras' own.
    #[serde(default)]
    pub gain_db: Option<f64>,
    /// `capture`, `every`: the cameras `exposure_us` and `gain_db` apply to (default all).
    #[serde(default)]
    pub cameras: Option<Vec<String>>,
}
