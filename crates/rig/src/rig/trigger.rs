//! Host driver for the serial camera-trigger controller (docs/design.md §11, §12).
//!
//! [`TriggerController`] opens a serial port (or takes any open [`SerialPort`], such as one
//! end of a pty pair with the simulated firmware on the other), checks the protocol version
//! and then configures output lines, arms sequences, fires frames and delivers the
//! controller's `FrameDone` events with their controller timestamps. The wire format is
//! `hexcal-firmware-protocol`'s. Every request is resent with the same sequence number when
//! its reply does not arrive in time (the firmware answers a repeat from its reply cache, so
//! a resent `Fire` never fires twice); garbage on the line costs only itself (the reader
//! resynchronises at the next `0x00`); CRC errors, retries and lost events are counted in
//! [`TriggerStats`]. Errors name the port.

use super::device::DeviceError;
use std::collections::VecDeque;
use std::io::{self, ErrorKind, Read, Write};
use std::time::{Duration, Instant};

use hexcal_firmware_protocol::{
    decode_frame, decode_hello_reply_prefix, encode_frame, heapless, Command, ControllerMessage,
    ErrorCode, Event, FrameDone, FrameError, FrameReader, Heartbeat, LineConfig, Pacing, Reply,
    Request, MAX_LINES, PROTOCOL_VERSION,
};
pub use serialport::SerialPort;

/// How long to wait for a reply and how often to send a request before giving up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TriggerTiming {
    /// Wait for the reply to one transmission of a request.
    pub reply_timeout: Duration,
    /// Transmissions of one request (the first plus the retries), at least 1.
    pub attempts: u32,
}

impl Default for TriggerTiming {
    fn default() -> Self {
        TriggerTiming {
            reply_timeout: Duration::from_millis(200),
            attempts: 3,
        }
    }
}

/// What the controller said about itself in the handshake.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ControllerInfo {
    /// Its protocol version (equal to [`PROTOCOL_VERSION`] once connected).
    pub version: u16,
    /// Number of output lines; valid line indices are `0..lines`.
    pub lines: u8,
}

/// Counters of the link's health since the port was opened.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TriggerStats {
    /// Requests issued (each counted once, however often it was sent).
    pub requests: u64,
    /// Transmissions beyond the first of a request, after a reply timeout.
    pub retries: u64,
    /// Received frames dropped because their CRC did not match.
    pub crc_errors: u64,
    /// Received frames dropped for any other reason (garbage, bad COBS, undecodable).
    pub bad_frames: u64,
    /// Replies ignored because they answered an earlier request (late duplicates).
    pub stale_replies: u64,
    /// Events the controller sent that never arrived (gaps in the event counter).
    pub events_missed: u64,
}

/// Trigger-controller failures; every one names the port.
#[derive(Debug, thiserror::Error)]
pub enum TriggerError {
    /// The serial port could not be opened.
    #[error("trigger controller {port}: cannot open the port: {source}")]
    Open {
        /// The port's path.
        port: String,
        /// What the OS said.
        source: serialport::Error,
    },
    /// Reading from or writing to the port failed.
    #[error("trigger controller {port}: I/O error: {source}")]
    Io {
        /// The port's path.
        port: String,
        /// What the OS said.
        source: io::Error,
    },
    /// The controller speaks another protocol version.
    #[error(
        "trigger controller {port}: protocol version mismatch: hexcal speaks version {host}, \
         the controller firmware speaks version {controller}"
    )]
    VersionMismatch {
        /// The port's path.
        port: String,
        /// This host's [`PROTOCOL_VERSION`].
        host: u16,
        /// The controller's version.
        controller: u16,
    },
    /// No reply to a request after every attempt (the controller was silent, or sent only
    /// frames that failed their CRC or did not decode: `garbled` of them).
    #[error(
        "trigger controller {port}: no reply to {request} after {attempts} attempts \
         ({timeout:?} each; {garbled} garbled frames received meanwhile)"
    )]
    NoReply {
        /// The port's path.
        port: String,
        /// The request's command.
        request: &'static str,
        /// Transmissions made.
        attempts: u32,
        /// Wait per transmission.
        timeout: Duration,
        /// Frames received while waiting that failed their CRC or did not decode.
        garbled: u64,
    },
    /// No event arrived in time.
    #[error("trigger controller {port}: no {what} within {timeout:?}")]
    NoEvent {
        /// The port's path.
        port: String,
        /// The awaited kind of event.
        what: &'static str,
        /// How long the driver waited.
        timeout: Duration,
    },
    /// The controller refused a command.
    #[error("trigger controller {port}: {request} refused: {code}")]
    Refused {
        /// The port's path.
        port: String,
        /// The refused command.
        request: &'static str,
        /// The controller's reason.
        code: ErrorCode,
    },
    /// The controller answered with a reply that does not fit the request.
    #[error("trigger controller {port}: unexpected reply to {request}: {reply:?}")]
    UnexpectedReply {
        /// The port's path.
        port: String,
        /// The request's command.
        request: &'static str,
        /// What came back.
        reply: Reply,
    },
    /// More lines than one Configure can carry.
    #[error("trigger controller {port}: {count} lines configured, at most {max} fit one message")]
    TooManyLines {
        /// The port's path.
        port: String,
        /// Lines asked for.
        count: usize,
        /// [`MAX_LINES`].
        max: usize,
    },
}

impl TriggerError {
    /// This error as the capture-level error of the device `port`: the reason without the
    /// port, which the device error names already.
    pub(crate) fn into_device_error(self, port: &str) -> DeviceError {
        let text = self.to_string();
        let reason = match text.strip_prefix(&format!("trigger controller {port}: ")) {
            Some(rest) => format!("trigger controller: {rest}"),
            None => text,
        };
        DeviceError::Failed {
            device: port.to_string(),
            reason,
        }
    }
}

/// The name of a command, for error messages.
fn command_name(command: &Command) -> &'static str {
    match command {
        Command::Hello { .. } => "Hello",
        Command::Configure { .. } => "Configure",
        Command::Arm { .. } => "Arm",
        Command::Fire => "Fire",
        Command::Disarm => "Disarm",
        Command::SetHeartbeat { .. } => "SetHeartbeat",
    }
}

/// One frame from the controller, as far as it could be understood.
enum Incoming {
    /// A message of this protocol version.
    Message(ControllerMessage),
    /// A Hello reply from a controller of another version that only its frozen prefix
    /// makes readable.
    ForeignHello {
        /// The sequence number it answers.
        seq: u16,
        /// The controller's version.
        version: u16,
    },
}

/// A connected trigger controller.
pub struct TriggerController {
    port: Box<dyn SerialPort>,
    name: String,
    timing: TriggerTiming,
    info: ControllerInfo,
    next_seq: u16,
    reader: FrameReader,
    rx: [u8; 256],
    rx_len: usize,
    rx_pos: usize,
    events: VecDeque<Event>,
    /// The event counter value the next event should carry.
    next_counter: u32,
    last_heartbeat: Option<Heartbeat>,
    stats: TriggerStats,
}

impl std::fmt::Debug for TriggerController {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TriggerController")
            .field("port", &self.name)
            .field("info", &self.info)
            .field("stats", &self.stats)
            .finish_non_exhaustive()
    }
}

impl TriggerController {
    /// Opens the serial port at `path` and performs the handshake. (USB CDC controllers
    /// ignore `baud_rate`; a real UART needs the firmware's rate.)
    pub fn open(path: &str, baud_rate: u32, timing: TriggerTiming) -> Result<Self, TriggerError> {
        let port = serialport::new(path, baud_rate)
            .timeout(timing.reply_timeout)
            .open()
            .map_err(|source| TriggerError::Open {
                port: path.to_string(),
                source,
            })?;
        Self::connect(port, path.to_string(), timing)
    }

    /// Takes an open port (e.g. one end of `serialport::TTYPort::pair()`) and performs the
    /// handshake. Errors name the port by its path, or "unnamed serial port".
    pub fn from_port(
        port: Box<dyn SerialPort>,
        timing: TriggerTiming,
    ) -> Result<Self, TriggerError> {
        let name = port
            .name()
            .unwrap_or_else(|| "unnamed serial port".to_string());
        Self::connect(port, name, timing)
    }

    fn connect(
        port: Box<dyn SerialPort>,
        name: String,
        timing: TriggerTiming,
    ) -> Result<Self, TriggerError> {
        let mut controller = TriggerController {
            port,
            name,
            timing: TriggerTiming {
                attempts: timing.attempts.max(1),
                ..timing
            },
            info: ControllerInfo {
                version: 0,
                lines: 0,
            },
            next_seq: 0,
            reader: FrameReader::new(),
            rx: [0; 256],
            rx_len: 0,
            rx_pos: 0,
            events: VecDeque::new(),
            next_counter: 0,
            last_heartbeat: None,
            stats: TriggerStats::default(),
        };
        let hello = Command::Hello {
            version: PROTOCOL_VERSION,
        };
        match controller.request(hello)? {
            Reply::Hello { version, lines } if version == PROTOCOL_VERSION => {
                controller.info = ControllerInfo { version, lines };
            }
            Reply::Hello { version, .. } => return Err(controller.mismatch(version)),
            reply => {
                return Err(TriggerError::UnexpectedReply {
                    port: controller.name,
                    request: "Hello",
                    reply,
                })
            }
        }
        // Events from before the Hello belong to an earlier session; the controller restarted
        // its event counter at 0.
        controller.events.clear();
        controller.next_counter = 0;
        controller.stats.events_missed = 0;
        controller.last_heartbeat = None;
        Ok(controller)
    }

    /// The port's path (or the name given to an unnamed port).
    pub fn port_name(&self) -> &str {
        &self.name
    }

    /// What the controller reported in the handshake.
    pub fn info(&self) -> ControllerInfo {
        self.info
    }

    /// The link's health counters.
    pub fn stats(&self) -> TriggerStats {
        self.stats
    }

    /// The most recent heartbeat received, if any.
    pub fn last_heartbeat(&self) -> Option<Heartbeat> {
        self.last_heartbeat
    }

    /// Sets the lines that pulse on every frame (replacing the previous set).
    pub fn configure(&mut self, lines: &[LineConfig]) -> Result<(), TriggerError> {
        let lines = heapless::Vec::from_slice(lines).map_err(|_| TriggerError::TooManyLines {
            port: self.name.clone(),
            count: lines.len(),
            max: MAX_LINES,
        })?;
        self.expect_ok(Command::Configure { lines })
    }

    /// Arms a sequence of `frames` frames paced by `pacing`.
    pub fn arm(&mut self, frames: u32, pacing: Pacing) -> Result<(), TriggerError> {
        self.expect_ok(Command::Arm { frames, pacing })
    }

    /// Fires the next frame (or starts a periodic sequence); gives the frame index the
    /// controller assigned.
    pub fn fire(&mut self) -> Result<u32, TriggerError> {
        match self.request(Command::Fire)? {
            Reply::Fired { frame } => Ok(frame),
            reply => Err(self.unexpected("Fire", reply)),
        }
    }

    /// Aborts the armed or running sequence.
    pub fn disarm(&mut self) -> Result<(), TriggerError> {
        self.expect_ok(Command::Disarm)
    }

    /// Asks for a heartbeat event every `interval` (rounded to ms; zero turns them off).
    pub fn set_heartbeat(&mut self, interval: Duration) -> Result<(), TriggerError> {
        let interval_ms = u32::try_from(interval.as_millis()).unwrap_or(u32::MAX);
        self.expect_ok(Command::SetHeartbeat { interval_ms })
    }

    /// The next event from the controller, waiting at most `timeout`.
    pub fn next_event(&mut self, timeout: Duration) -> Result<Event, TriggerError> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(event) = self.events.pop_front() {
                return Ok(event);
            }
            match self.receive(deadline)? {
                Some(Incoming::Message(message)) => self.accept_unsolicited(message),
                Some(Incoming::ForeignHello { .. }) => self.stats.stale_replies += 1,
                None => {
                    return Err(TriggerError::NoEvent {
                        port: self.name.clone(),
                        what: "event",
                        timeout,
                    })
                }
            }
        }
    }

    /// The next `FrameDone` event, waiting at most `timeout` (heartbeats on the way are
    /// recorded in [`TriggerController::last_heartbeat`]). Frames whose event was lost are
    /// skipped and counted in [`TriggerStats::events_missed`]: compare the frame index with
    /// the one expected.
    pub fn wait_frame_done(&mut self, timeout: Duration) -> Result<FrameDone, TriggerError> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.next_event(left) {
                Ok(Event::FrameDone(done)) => return Ok(done),
                Ok(Event::Heartbeat(_)) => {}
                Err(TriggerError::NoEvent { port, .. }) => {
                    return Err(TriggerError::NoEvent {
                        port,
                        what: "FrameDone event",
                        timeout,
                    })
                }
                Err(e) => return Err(e),
            }
        }
    }

    fn expect_ok(&mut self, command: Command) -> Result<(), TriggerError> {
        let name = command_name(&command);
        match self.request(command)? {
            Reply::Ok => Ok(()),
            reply => Err(self.unexpected(name, reply)),
        }
    }

    fn unexpected(&self, request: &'static str, reply: Reply) -> TriggerError {
        TriggerError::UnexpectedReply {
            port: self.name.clone(),
            request,
            reply,
        }
    }

    fn mismatch(&self, controller: u16) -> TriggerError {
        TriggerError::VersionMismatch {
            port: self.name.clone(),
            host: PROTOCOL_VERSION,
            controller,
        }
    }

    /// Sends `command` with a new sequence number and waits for its reply, resending the
    /// identical frame after each reply timeout. A refusal becomes [`TriggerError::Refused`].
    fn request(&mut self, command: Command) -> Result<Reply, TriggerError> {
        let name = command_name(&command);
        let seq = self.next_seq;
        self.next_seq = self.next_seq.wrapping_add(1);
        self.stats.requests += 1;
        let frame = encode_frame(&Request { seq, command })
            .expect("every request fits a frame (the line list is bounded by its type)");
        let garbled_before = self.stats.crc_errors + self.stats.bad_frames;
        for attempt in 0..self.timing.attempts {
            if attempt > 0 {
                self.stats.retries += 1;
            }
            // The port's timeout also bounds the wait for room to write; `receive` may have
            // left it near zero. A TTYPort writes straight to the device: no flush needed
            // (tcdrain could block on a pty).
            self.port
                .set_timeout(self.timing.reply_timeout)
                .map_err(|e| self.io(e.into()))?;
            self.port.write_all(&frame).map_err(|e| self.io(e))?;
            let deadline = Instant::now() + self.timing.reply_timeout;
            while let Some(incoming) = self.receive(deadline)? {
                match incoming {
                    Incoming::Message(ControllerMessage::Reply { seq: s, reply }) if s == seq => {
                        return match reply {
                            Reply::Error(code) => Err(TriggerError::Refused {
                                port: self.name.clone(),
                                request: name,
                                code,
                            }),
                            reply => Ok(reply),
                        };
                    }
                    Incoming::ForeignHello { seq: s, version } if s == seq => {
                        return Err(self.mismatch(version));
                    }
                    Incoming::Message(message) => self.accept_unsolicited(message),
                    Incoming::ForeignHello { .. } => self.stats.stale_replies += 1,
                }
            }
        }
        Err(TriggerError::NoReply {
            port: self.name.clone(),
            request: name,
            attempts: self.timing.attempts,
            timeout: self.timing.reply_timeout,
            garbled: self.stats.crc_errors + self.stats.bad_frames - garbled_before,
        })
    }

    /// Queues an event (checking its counter), or counts a reply to an earlier request.
    fn accept_unsolicited(&mut self, message: ControllerMessage) {
        match message {
            ControllerMessage::Reply { .. } => self.stats.stale_replies += 1,
            ControllerMessage::Event { counter, event } => {
                let gap = counter.wrapping_sub(self.next_counter);
                // A huge "gap" is a counter that went backwards: not a loss.
                if gap < u32::MAX / 2 {
                    self.stats.events_missed += u64::from(gap);
                }
                self.next_counter = counter.wrapping_add(1);
                if let Event::Heartbeat(beat) = event {
                    self.last_heartbeat = Some(beat);
                }
                self.events.push_back(event);
            }
        }
    }

    /// The next frame from the controller that is worth looking at, or `None` at `deadline`.
    /// Dropped frames are counted.
    fn receive(&mut self, deadline: Instant) -> Result<Option<Incoming>, TriggerError> {
        loop {
            while self.rx_pos < self.rx_len {
                let byte = self.rx[self.rx_pos];
                self.rx_pos += 1;
                let Some(frame) = self.reader.push(byte) else {
                    continue;
                };
                let decoded = frame.and_then(|cobs| match decode_frame(cobs) {
                    Ok(message) => Ok(Incoming::Message(message)),
                    Err(FrameError::Malformed | FrameError::TrailingBytes) => {
                        match decode_hello_reply_prefix(cobs) {
                            Ok(Some(h)) => Ok(Incoming::ForeignHello {
                                seq: h.seq,
                                version: h.version,
                            }),
                            _ => Err(FrameError::Malformed),
                        }
                    }
                    Err(e) => Err(e),
                });
                match decoded {
                    Ok(incoming) => return Ok(Some(incoming)),
                    Err(FrameError::Crc { .. }) => self.stats.crc_errors += 1,
                    Err(_) => self.stats.bad_frames += 1,
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            self.port.set_timeout(left).map_err(|e| self.io(e.into()))?;
            match self.port.read(&mut self.rx) {
                Ok(0) => {
                    return Err(self.io(io::Error::new(
                        ErrorKind::UnexpectedEof,
                        "the port was closed",
                    )))
                }
                Ok(n) => {
                    self.rx_len = n;
                    self.rx_pos = 0;
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(self.io(e)),
            }
        }
    }

    fn io(&self, source: io::Error) -> TriggerError {
        TriggerError::Io {
            port: self.name.clone(),
            source,
        }
    }
}

impl super::device::Trigger for TriggerController {
    fn name(&self) -> &str {
        self.port_name()
    }

    fn arm(&mut self, frames: u32) -> Result<(), DeviceError> {
        TriggerController::arm(self, frames, hexcal_firmware_protocol::Pacing::PerFire)
            .map_err(|e| e.into_device_error(self.port_name()))
    }

    fn fire(&mut self) -> Result<u32, DeviceError> {
        TriggerController::fire(self).map_err(|e| e.into_device_error(self.port_name()))
    }

    fn disarm(&mut self) -> Result<(), DeviceError> {
        TriggerController::disarm(self).map_err(|e| e.into_device_error(self.port_name()))
    }
}
