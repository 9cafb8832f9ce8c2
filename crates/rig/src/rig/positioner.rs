//! Positioners: devices that move the board on command over a serial line with a text
//! protocol (turntables, pan-tilt stages, robot arms), for capture scripts.
//!
//! Takes a [`PositionerSpec`]; gives a [`Positioner`] that sends one command line and waits
//! for the reply the step expects, telling a fault reply, a garbage reply, silence and an
//! interrupt apart, each error naming the positioner and the command. A `sim` positioner is
//! the simulator's turntable-and-tilt stage (`hexcal_simulator::stage`) on an in-process
//! pty pair, driven through the same serial code; mounted on a [`SimWorld`], the stage's
//! axes place the simulated board.

use super::script::{
    FlowControl, Parity, PositionerDriver, PositionerSpec, SimFaultKind, SimStageSpec,
};
use super::sim::SimWorld;
use hexcal_simulator::stage::{Axes, SimulatedStage, StageConfig, StageFault};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use regex::Regex;
use serialport::SerialPort;
use std::io::{ErrorKind, Read, Write};
use std::time::{Duration, Instant};

/// Why a positioner failed.
#[derive(Debug, thiserror::Error)]
pub enum PositionerError {
    /// The port could not be opened.
    #[error("positioner {name}: cannot open {port}: {source}")]
    Open {
        /// Positioner.
        name: String,
        /// Port.
        port: String,
        /// Why.
        source: serialport::Error,
    },
    /// Reading or writing the line failed.
    #[error("positioner {name}: {source}")]
    Io {
        /// Positioner.
        name: String,
        /// Why.
        source: std::io::Error,
    },
    /// A reply pattern does not compile.
    #[error("positioner {name}: pattern {pattern:?}: {message}")]
    Pattern {
        /// Positioner.
        name: String,
        /// The pattern.
        pattern: String,
        /// Why.
        message: String,
    },
    /// No reply in time.
    #[error("positioner {name}: no reply to {command:?} within {timeout_s} s")]
    NoReply {
        /// Positioner.
        name: String,
        /// The command.
        command: String,
        /// The timeout (s).
        timeout_s: f64,
    },
    /// A reply that is neither the expected one nor a fault.
    #[error("positioner {name}: unexpected reply {line:?} to {command:?} (expected /{expect}/)")]
    Garbage {
        /// Positioner.
        name: String,
        /// The command.
        command: String,
        /// What came back.
        line: String,
        /// The pattern expected.
        expect: String,
    },
    /// The device reported a fault.
    #[error("positioner {name}: fault reported to {command:?}: {line:?}")]
    Fault {
        /// Positioner.
        name: String,
        /// The command.
        command: String,
        /// The device's line.
        line: String,
    },
    /// Stopped (Ctrl-C) while waiting for the reply.
    #[error("positioner {name}: interrupted while waiting for {command:?}")]
    Interrupted {
        /// Positioner.
        name: String,
        /// The command.
        command: String,
    },
}

/// What a reply line means.
enum Reply {
    /// Read on (an echo, the acknowledgement, a busy status).
    Next,
    /// The move is done.
    Done,
    /// A fault line.
    Fault(String),
    /// A line that is not what was expected (the line, the pattern expected).
    Garbage(String, String),
    /// No line within the timeout.
    Silent(Duration),
    /// Stopped.
    Interrupted,
}

/// Longest reply line kept (bytes); a device that sends more without a line end is garbage.
const MAX_LINE: usize = 4096;

/// How a device says a command was taken and a move is done (docs/rig-file.md, "Scripts
/// and positioners"): an echo to skip, an acknowledgement at once, then a completion line
/// or a status polled until idle.
struct Protocol {
    echo: bool,
    ack: Option<Regex>,
    /// The status query, the idle pattern, the period.
    poll: Option<(String, Regex, Duration)>,
}

/// An open positioner.
pub struct Positioner {
    name: String,
    port: Box<dyn SerialPort>,
    ending: &'static str,
    fault: Regex,
    stop: Option<String>,
    protocol: Protocol,
    pending: Vec<u8>,
    /// Every line sent (`> …`) and received (`< …`), for `hexcal positioner`.
    transcript: Vec<String>,
    /// The simulated stage serving the other end of the pty, for `sim`.
    stage: Option<SimulatedStage>,
}

/// A pattern of `spec`, compiled; an error naming the positioner.
fn pattern(name: &str, text: &str) -> Result<Regex, PositionerError> {
    Regex::new(text).map_err(|e| PositionerError::Pattern {
        name: name.to_string(),
        pattern: text.to_string(),
        message: e.to_string(),
    })
}

/// The serial framing of `spec` on a port builder.
fn framed(spec: &PositionerSpec, path: &str) -> serialport::SerialPortBuilder {
    use serialport::{DataBits, FlowControl as Flow, Parity as P, StopBits};
    serialport::new(path, spec.baud)
        .timeout(Duration::from_millis(20))
        .data_bits(match spec.data_bits {
            7 => DataBits::Seven,
            _ => DataBits::Eight,
        })
        .parity(match spec.parity {
            Parity::None => P::None,
            Parity::Odd => P::Odd,
            Parity::Even => P::Even,
        })
        .stop_bits(match spec.stop_bits {
            2 => StopBits::Two,
            _ => StopBits::One,
        })
        .flow_control(match spec.flow_control {
            FlowControl::None => Flow::None,
            FlowControl::Software => Flow::Software,
            FlowControl::Hardware => Flow::Hardware,
        })
}

impl Positioner {
    /// Open the positioner of `spec`: its serial port, or for `sim` the simulated stage on a
    /// pty pair, mounted on `world` when there is one (the stage then holds the board).
    pub fn open(spec: &PositionerSpec, world: Option<&SimWorld>) -> Result<Self, PositionerError> {
        let name = spec.name.clone();
        let fault = pattern(&name, &spec.fault)?;
        let protocol = Protocol {
            echo: spec.echo,
            ack: spec.ack.as_deref().map(|a| pattern(&name, a)).transpose()?,
            poll: match &spec.poll {
                Some(q) => Some((
                    q.query.clone(),
                    pattern(&name, &q.idle)?,
                    Duration::from_secs_f64(q.period_s),
                )),
                None => None,
            },
        };
        let open_error = |port: &str| {
            let (name, port) = (name.clone(), port.to_string());
            move |source| PositionerError::Open { name, port, source }
        };
        let (port, stage): (Box<dyn SerialPort>, _) = match (spec.driver, &spec.port) {
            (PositionerDriver::Serial, Some(path)) => {
                let port = framed(spec, path).open().map_err(open_error(path))?;
                (port, None)
            }
            _ => {
                let (mut master, mut slave) =
                    serialport::TTYPort::pair().map_err(open_error("a pty pair"))?;
                master
                    .set_timeout(Duration::from_millis(1))
                    .map_err(open_error("a pty pair"))?;
                slave
                    .set_timeout(Duration::from_millis(20))
                    .map_err(open_error("a pty pair"))?;
                let stage_spec = spec.sim.unwrap_or(SimStageSpec {
                    centre: [0.0; 3],
                    offset: [0.0; 3],
                    roll_deg: 0.0,
                    speed_deg_s: 90.0,
                    tilt_limit_deg: 60.0,
                    fault: None,
                });
                let stage = SimulatedStage::spawn(master, stage_config(&stage_spec));
                if let Some(w) = world {
                    let handle = stage.handle();
                    w.mount(Box::new(move || {
                        board_on_stage(&stage_spec, handle.position())
                    }));
                }
                (Box::new(slave) as Box<dyn SerialPort>, Some(stage))
            }
        };
        Ok(Positioner {
            name,
            port,
            ending: spec.line_ending.text(),
            fault,
            stop: spec.stop.clone(),
            protocol,
            pending: Vec::new(),
            transcript: Vec::new(),
            stage,
        })
    }

    /// Every line sent (`> …`) and received (`< …`) so far.
    pub fn transcript(&self) -> &[String] {
        &self.transcript
    }

    /// Its name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Where a simulated stage's axes are now (deg), for `sim` positioners.
    pub fn stage_axes(&self) -> Option<Axes> {
        self.stage.as_ref().map(|s| s.handle().position())
    }

    /// Send `command` and wait up to `timeout` for the move to be done: its echo skipped,
    /// its acknowledgement taken, then a line matching `expect` or, polling, a status line
    /// matching the idle pattern (other status lines are "busy"). A line matching the
    /// fault pattern, any other line, silence, and `stopped()` turning true (then the
    /// positioner's stop command is sent) are errors naming the positioner and command.
    pub fn command(
        &mut self,
        command: &str,
        expect: &Regex,
        timeout: Duration,
        stopped: &dyn Fn() -> bool,
    ) -> Result<String, PositionerError> {
        self.drain_input()?;
        self.write_line(command)?;
        let deadline = Instant::now() + timeout;
        let mut acked = self.protocol.ack.is_none();
        let mut next_poll = Instant::now();
        loop {
            if stopped() {
                if let Some(stop) = self.stop.clone() {
                    self.write_line(&stop)?;
                }
                return Err(self.error(command, Reply::Interrupted));
            }
            if let Some((query, _, period)) = self.protocol.poll.clone() {
                if acked && Instant::now() >= next_poll {
                    self.write_line(&query)?;
                    next_poll = Instant::now() + period;
                }
            }
            if let Some(line) = self.read_line()? {
                match self.judge(command, &line, expect, &mut acked) {
                    Reply::Next => continue,
                    Reply::Done => return Ok(line),
                    other => return Err(self.error(command, other)),
                }
            }
            if Instant::now() >= deadline {
                return Err(self.error(command, Reply::Silent(timeout)));
            }
        }
    }

    /// What `line` means in answer to `command`.
    fn judge(&self, command: &str, line: &str, expect: &Regex, acked: &mut bool) -> Reply {
        let p = &self.protocol;
        let query = p.poll.as_ref().map(|q| q.0.trim());
        if p.echo && (line == command.trim() || Some(line) == query) {
            return Reply::Next;
        }
        if self.fault.is_match(line) {
            return Reply::Fault(line.to_string());
        }
        if !*acked {
            return match p.ack.as_ref().is_some_and(|a| a.is_match(line)) {
                true => {
                    *acked = true;
                    Reply::Next
                }
                false => Reply::Garbage(
                    line.to_string(),
                    p.ack.as_ref().map_or("", |a| a.as_str()).to_string(),
                ),
            };
        }
        match &p.poll {
            Some((_, idle, _)) if idle.is_match(line) => Reply::Done,
            // Busy, or a status line of another kind: poll on.
            Some(_) => Reply::Next,
            None if expect.is_match(line) => Reply::Done,
            None => Reply::Garbage(line.to_string(), expect.as_str().to_string()),
        }
    }

    /// The error of a command's `reply`.
    fn error(&self, command: &str, reply: Reply) -> PositionerError {
        let (name, command) = (self.name.clone(), command.to_string());
        match reply {
            Reply::Fault(line) => PositionerError::Fault {
                name,
                command,
                line,
            },
            Reply::Garbage(line, expect) => PositionerError::Garbage {
                name,
                command,
                line,
                expect,
            },
            Reply::Silent(t) => PositionerError::NoReply {
                name,
                command,
                timeout_s: t.as_secs_f64(),
            },
            Reply::Interrupted | Reply::Next | Reply::Done => {
                PositionerError::Interrupted { name, command }
            }
        }
    }

    fn io(&self, source: std::io::Error) -> PositionerError {
        PositionerError::Io {
            name: self.name.clone(),
            source,
        }
    }

    fn write_line(&mut self, line: &str) -> Result<(), PositionerError> {
        self.transcript.push(format!("> {line}"));
        let bytes = format!("{line}{}", self.ending);
        self.port
            .write_all(bytes.as_bytes())
            .and_then(|()| self.port.flush())
            .map_err(|e| self.io(e))
    }

    /// Forget replies that came before this command (a late reply to an earlier one).
    fn drain_input(&mut self) -> Result<(), PositionerError> {
        self.pending.clear();
        let waiting = self.port.bytes_to_read().unwrap_or(0);
        if waiting > 0 {
            let mut junk = vec![0u8; waiting as usize];
            let _ = self.port.read(&mut junk);
        }
        Ok(())
    }

    /// One complete non-empty line, if one arrives within the port's read timeout.
    fn read_line(&mut self) -> Result<Option<String>, PositionerError> {
        loop {
            if let Some(end) = self.pending.iter().position(|&b| b == b'\n' || b == b'\r') {
                let line: Vec<u8> = self.pending.drain(..=end).collect();
                let text = String::from_utf8_lossy(&line).trim().to_string();
                if text.is_empty() {
                    continue;
                }
                self.transcript.push(format!("< {text}"));
                return Ok(Some(text));
            }
            if self.pending.len() > MAX_LINE {
                let text = String::from_utf8_lossy(&self.pending[..64]).into_owned();
                self.pending.clear();
                return Ok(Some(text));
            }
            let mut buf = [0u8; 256];
            match self.port.read(&mut buf) {
                Ok(0) => return Ok(None),
                Ok(n) => self.pending.extend_from_slice(&buf[..n]),
                Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => {
                    return Ok(None)
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => return Ok(None),
                Err(e) => return Err(self.io(e)),
            }
        }
    }
}

fn stage_config(s: &SimStageSpec) -> StageConfig {
    StageConfig {
        speed_deg_s: s.speed_deg_s,
        tilt_limit_deg: s.tilt_limit_deg,
        fault: s.fault.map(|f| {
            let kind = match f.kind {
                SimFaultKind::Silent => StageFault::Silent,
                SimFaultKind::Garbage => StageFault::Garbage,
                SimFaultKind::Error => StageFault::Error,
            };
            (kind, f.after_moves)
        }),
    }
}

/// T_rig_board of a board on the simulated stage: the turntable turns about the rig's
/// vertical (y) through `centre`, the tilt axis (the table's x) rides on it, and the board
/// is mounted turned by `roll_deg` in its own plane with its centre at `offset` from the
/// axes' crossing.
pub fn board_on_stage(s: &SimStageSpec, axes: Axes) -> Isometry3<f64> {
    let rot = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), axes.angle_deg.to_radians())
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), axes.tilt_deg.to_radians())
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), s.roll_deg.to_radians());
    let stage = Isometry3::from_parts(Translation3::from(Vector3::from(s.centre)), rot);
    stage * Translation3::from(Vector3::from(s.offset))
}
