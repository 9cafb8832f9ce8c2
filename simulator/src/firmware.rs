//! A model of the trigger-controller firmware (docs/design.md §12), speaking
//! `hexcal-firmware-protocol` on any byte stream.
//!
//! [`FirmwareModel`] is the controller's state machine: bytes and the controller clock in,
//! [`ControllerMessage`]s out (session, configure → arm → fire or periodic pacing →
//! `FrameDone` events carrying each frame's trigger instant, errors, heartbeats, and the
//! reply cache that makes a repeated request idempotent). [`SimulatedController`] runs it
//! on a thread serving one end of a pty (or any `Read + Write` stream) and injects faults
//! for tests: corrupted CRCs, garbage bytes, dropped replies and events, a hung controller.
//! A wrong protocol version is a [`ModelConfig`] setting.

use std::collections::VecDeque;
use std::io::{self, ErrorKind, Read, Write};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Instant;

use hexcal_firmware_protocol::{
    decode_frame, decode_hello_request_prefix, encode_frame, Command, ControllerMessage,
    ControllerState, ErrorCode, Event, FrameDone, FrameError, FrameReader, Heartbeat, LineConfig,
    Pacing, Reply, Request, MAX_BODY_LEN, PROTOCOL_VERSION,
};

/// What the simulated controller is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ModelConfig {
    /// Protocol version it reports in its Hello reply (set it to another value than
    /// [`PROTOCOL_VERSION`] to simulate a mismatched firmware).
    pub version: u16,
    /// Number of output lines.
    pub lines: u8,
}

impl Default for ModelConfig {
    fn default() -> Self {
        ModelConfig {
            version: PROTOCOL_VERSION,
            lines: 8,
        }
    }
}

/// Counters of what the firmware saw and did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ModelStats {
    /// Requests executed (repeats answered from the reply cache not included).
    pub requests_executed: u64,
    /// Repeated requests answered with the cached reply, without executing them again.
    pub replies_replayed: u64,
    /// Frames triggered (each pulses every configured line once).
    pub frames_fired: u64,
    /// Received frames dropped for a CRC mismatch.
    pub crc_errors: u64,
    /// Received frames dropped for any other reason (COBS, length, undecodable).
    pub bad_frames: u64,
}

/// A sequence armed by [`Command::Arm`].
#[derive(Debug, Clone, Copy)]
struct Sequence {
    frames: u32,
    pacing: Pacing,
    /// Index of the next frame to trigger.
    next_frame: u32,
    /// Trigger instant of frame 0 once a periodic sequence has started, µs.
    start_us: Option<u64>,
}

impl Sequence {
    fn period_us(&self) -> Option<u64> {
        match self.pacing {
            Pacing::PerFire => None,
            Pacing::Periodic { period_us } | Pacing::ExternalStart { period_us } => {
                Some(u64::from(period_us))
            }
        }
    }

    /// Trigger instant of the next frame of a running periodic sequence.
    fn next_trigger_us(&self) -> Option<u64> {
        Some(self.start_us? + u64::from(self.next_frame) * self.period_us()?)
    }
}

/// A triggered frame whose pulses are not all over yet.
#[derive(Debug, Clone, Copy)]
struct InFlight {
    done: FrameDone,
    /// When the last line goes low, µs.
    end_us: u64,
}

/// The controller's state machine; time is the controller's monotonic clock in µs, given by
/// the caller.
#[derive(Debug, Clone)]
pub struct FirmwareModel {
    config: ModelConfig,
    reader: FrameReader,
    /// A Hello with our version has been received.
    session: bool,
    lines: Vec<LineConfig>,
    sequence: Option<Sequence>,
    in_flight: VecDeque<InFlight>,
    frames_done: u32,
    /// Heartbeat interval and next due time, µs.
    heartbeat: Option<(u64, u64)>,
    event_counter: u32,
    /// The last executed request and the reply it got (the replay cache).
    last: Option<(Request, ControllerMessage)>,
    stats: ModelStats,
}

impl FirmwareModel {
    /// A controller just powered on (no session yet).
    pub fn new(config: ModelConfig) -> Self {
        FirmwareModel {
            config,
            reader: FrameReader::new(),
            session: false,
            lines: Vec::new(),
            sequence: None,
            in_flight: VecDeque::new(),
            frames_done: 0,
            heartbeat: None,
            event_counter: 0,
            last: None,
            stats: ModelStats::default(),
        }
    }

    /// What it saw and did so far.
    pub fn stats(&self) -> ModelStats {
        self.stats
    }

    /// The state a heartbeat reports.
    pub fn state(&self) -> ControllerState {
        match self.sequence {
            Some(s) if s.start_us.is_some() => ControllerState::Running,
            Some(_) => ControllerState::Armed,
            None if self.lines.is_empty() => ControllerState::Idle,
            None => ControllerState::Configured,
        }
    }

    /// Takes bytes received at `now_us`: appends to `out` the events due by then and one
    /// reply per complete, valid request frame, in the order they are to be sent.
    pub fn receive(&mut self, bytes: &[u8], now_us: u64, out: &mut Vec<ControllerMessage>) {
        self.poll(now_us, out);
        for &byte in bytes {
            let Some(frame) = self.reader.push(byte) else {
                continue;
            };
            let request = frame.and_then(|cobs| match decode_frame::<Request>(cobs) {
                // A Hello from a peer of another version may not decode in full: answer it
                // from its frozen prefix.
                Err(FrameError::TrailingBytes | FrameError::Malformed) => {
                    match decode_hello_request_prefix(cobs) {
                        Ok(Some(hello)) => Ok(Request {
                            seq: hello.seq,
                            command: Command::Hello {
                                version: hello.version,
                            },
                        }),
                        _ => Err(FrameError::Malformed),
                    }
                }
                other => other,
            });
            match request {
                Ok(request) => out.push(self.answer(request, now_us)),
                Err(FrameError::Crc { .. }) => self.stats.crc_errors += 1,
                Err(_) => self.stats.bad_frames += 1,
            }
        }
    }

    /// A rising edge on the external start input at `now_us`: starts a sequence armed with
    /// [`Pacing::ExternalStart`] (ignored otherwise, as the hardware would).
    pub fn external_start(&mut self, now_us: u64, out: &mut Vec<ControllerMessage>) {
        self.poll(now_us, out);
        if let Some(s) = &mut self.sequence {
            if matches!(s.pacing, Pacing::ExternalStart { .. }) && s.start_us.is_none() {
                s.start_us = Some(now_us);
                self.poll(now_us, out);
            }
        }
    }

    /// Advances the clock to `now_us`: triggers the periodic frames due by then and appends
    /// the events due by then to `out`, in time order.
    pub fn poll(&mut self, now_us: u64, out: &mut Vec<ControllerMessage>) {
        loop {
            let trigger = self
                .sequence
                .and_then(|s| s.next_trigger_us())
                .filter(|&t| t <= now_us);
            let frame_end = self
                .in_flight
                .front()
                .map(|f| f.end_us)
                .filter(|&t| t <= now_us);
            let beat = self.heartbeat.map(|(_, due)| due).filter(|&t| t <= now_us);
            // The earliest due action first; frame ends before triggers at the same instant
            // (a period equal to the pulse length is allowed).
            let earliest = [frame_end, trigger, beat].into_iter().flatten().min();
            let Some(t) = earliest else {
                return;
            };
            if frame_end == Some(t) {
                let frame = self.in_flight.pop_front().expect("front exists");
                self.frames_done += 1;
                self.emit(Event::FrameDone(frame.done), out);
            } else if trigger == Some(t) {
                self.trigger(t);
            } else {
                let (interval, due) = self.heartbeat.expect("heartbeat due");
                self.heartbeat = Some((interval, due + interval));
                let beat = Heartbeat {
                    time_us: due,
                    state: self.state(),
                    frames_done: self.frames_done,
                };
                self.emit(Event::Heartbeat(beat), out);
            }
        }
    }

    /// The next instant at which [`FirmwareModel::poll`] has something to do.
    pub fn next_deadline_us(&self) -> Option<u64> {
        let trigger = self.sequence.and_then(|s| s.next_trigger_us());
        let frame_end = self.in_flight.front().map(|f| f.end_us);
        let beat = self.heartbeat.map(|(_, due)| due);
        [trigger, frame_end, beat].into_iter().flatten().min()
    }

    fn emit(&mut self, event: Event, out: &mut Vec<ControllerMessage>) {
        out.push(ControllerMessage::Event {
            counter: self.event_counter,
            event,
        });
        self.event_counter = self.event_counter.wrapping_add(1);
    }

    /// Longest delay + pulse over the configured lines, µs.
    fn frame_length_us(&self) -> u64 {
        self.lines.iter().map(LineConfig::end_us).max().unwrap_or(0)
    }

    /// Triggers the next frame of the armed sequence at `t_us`.
    fn trigger(&mut self, t_us: u64) {
        let length = self.frame_length_us();
        let Some(s) = &mut self.sequence else {
            return;
        };
        let frame = s.next_frame;
        s.next_frame += 1;
        if s.next_frame == s.frames {
            self.sequence = None;
        }
        self.stats.frames_fired += 1;
        self.in_flight.push_back(InFlight {
            done: FrameDone {
                frame,
                time_us: t_us,
            },
            end_us: t_us + length,
        });
    }

    /// The reply to one decoded request: from the cache if it repeats the last one.
    fn answer(&mut self, request: Request, now_us: u64) -> ControllerMessage {
        if let Some((last, reply)) = &self.last {
            if *last == request && !matches!(request.command, Command::Hello { .. }) {
                self.stats.replies_replayed += 1;
                return reply.clone();
            }
        }
        self.stats.requests_executed += 1;
        let reply = ControllerMessage::Reply {
            seq: request.seq,
            reply: self.execute(&request.command, now_us),
        };
        self.last = match request.command {
            Command::Hello { .. } => None,
            _ => Some((request, reply.clone())),
        };
        reply
    }

    fn execute(&mut self, command: &Command, now_us: u64) -> Reply {
        if let Command::Hello { version } = command {
            *self = FirmwareModel {
                session: *version == self.config.version,
                reader: self.reader.clone(),
                stats: self.stats,
                ..FirmwareModel::new(self.config)
            };
            return Reply::Hello {
                version: self.config.version,
                lines: self.config.lines,
            };
        }
        if !self.session {
            return Reply::Error(ErrorCode::NoSession);
        }
        let pulsing = !self.in_flight.is_empty();
        let result = match *command {
            Command::Hello { .. } => unreachable!("handled above"),
            Command::Configure { ref lines } => self.configure(lines, pulsing),
            Command::Arm { frames, pacing } => self.arm(frames, pacing, pulsing),
            Command::Fire => return self.fire(now_us, pulsing),
            Command::Disarm => {
                self.sequence = None;
                Ok(())
            }
            Command::SetHeartbeat { interval_ms } => {
                let interval = u64::from(interval_ms) * 1000;
                self.heartbeat = (interval > 0).then_some((interval, now_us + interval));
                Ok(())
            }
        };
        match result {
            Ok(()) => Reply::Ok,
            Err(code) => Reply::Error(code),
        }
    }

    fn configure(&mut self, lines: &[LineConfig], pulsing: bool) -> Result<(), ErrorCode> {
        if pulsing || self.sequence.is_some() {
            return Err(ErrorCode::Busy);
        }
        for (i, l) in lines.iter().enumerate() {
            if l.line >= self.config.lines || lines[..i].iter().any(|o| o.line == l.line) {
                return Err(ErrorCode::BadLine { line: l.line });
            }
            if l.pulse_us == 0 {
                return Err(ErrorCode::BadPulse { line: l.line });
            }
        }
        self.lines = lines.to_vec();
        Ok(())
    }

    fn arm(&mut self, frames: u32, pacing: Pacing, pulsing: bool) -> Result<(), ErrorCode> {
        if pulsing || self.sequence.is_some_and(|s| s.start_us.is_some()) {
            return Err(ErrorCode::Busy);
        }
        if self.lines.is_empty() {
            return Err(ErrorCode::NotConfigured);
        }
        let sequence = Sequence {
            frames,
            pacing,
            next_frame: 0,
            start_us: None,
        };
        if frames == 0
            || sequence
                .period_us()
                .is_some_and(|p| p < self.frame_length_us())
        {
            return Err(ErrorCode::BadArm);
        }
        self.sequence = Some(sequence);
        self.frames_done = 0;
        Ok(())
    }

    fn fire(&mut self, now_us: u64, pulsing: bool) -> Reply {
        let Some(s) = &mut self.sequence else {
            return Reply::Error(ErrorCode::NotArmed);
        };
        if matches!(s.pacing, Pacing::ExternalStart { .. }) {
            return Reply::Error(ErrorCode::WrongPacing);
        }
        if pulsing || s.start_us.is_some() {
            return Reply::Error(ErrorCode::Busy);
        }
        let frame = s.next_frame;
        if matches!(s.pacing, Pacing::Periodic { .. }) {
            // Frame 0 triggers now; `poll` triggers the rest on schedule.
            s.start_us = Some(now_us);
        }
        self.trigger(now_us);
        Reply::Fired { frame }
    }
}

/// A fault applied to one reply the simulated controller sends.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ReplyFault {
    /// Send the reply with one bit of its CRC trailer flipped.
    CorruptCrc,
    /// Execute the request but send no reply.
    Drop,
    /// Send these bytes right before the reply's frame.
    Garbage(Vec<u8>),
}

/// Faults waiting to be applied.
#[derive(Debug, Default)]
struct Faults {
    replies: VecDeque<ReplyFault>,
    drop_events: u32,
    silent: bool,
}

/// State shared between the controller thread and its handle.
#[derive(Debug, Default)]
struct Shared {
    faults: Mutex<Faults>,
    stats: Mutex<ModelStats>,
    external_edges: AtomicU32,
    stop: AtomicBool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic on the other thread leaves the data as consistent as it was: keep using it.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A [`FirmwareModel`] on its own thread, serving one end of a byte stream.
#[derive(Debug)]
pub struct SimulatedController {
    shared: Arc<Shared>,
    thread: Option<JoinHandle<io::Result<()>>>,
}

impl SimulatedController {
    /// Starts the controller on `stream` (e.g. the master end of a
    /// `serialport::TTYPort::pair()`). The stream's reads must return within a few
    /// milliseconds when no byte arrives (an `io::ErrorKind::TimedOut` or `WouldBlock`
    /// error): that is the resolution of the controller's timers. The thread ends at
    /// [`SimulatedController::stop`], on end of stream or when the other end hangs up.
    pub fn spawn<S: Read + Write + Send + 'static>(stream: S, config: ModelConfig) -> Self {
        let shared = Arc::new(Shared::default());
        let thread_shared = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("sim-trigger-firmware".into())
            .spawn(move || serve(stream, FirmwareModel::new(config), &thread_shared))
            .expect("spawning the firmware thread");
        SimulatedController {
            shared,
            thread: Some(thread),
        }
    }

    /// Queues a fault for the next reply not yet faulted (faults apply in order, one per
    /// reply).
    pub fn fault_next_reply(&self, fault: ReplyFault) {
        lock(&self.shared.faults).replies.push_back(fault);
    }

    /// Drops the next `n` events instead of sending them.
    pub fn drop_next_events(&self, n: u32) {
        lock(&self.shared.faults).drop_events += n;
    }

    /// A hung controller: while silent it swallows every byte and neither executes nor
    /// sends anything.
    pub fn set_silent(&self, silent: bool) {
        lock(&self.shared.faults).silent = silent;
    }

    /// A rising edge on the external start input.
    pub fn external_start(&self) {
        self.shared.external_edges.fetch_add(1, Ordering::SeqCst);
    }

    /// Counters so far (updated before each batch of messages is sent, so a message the host
    /// has received is already counted).
    pub fn stats(&self) -> ModelStats {
        *lock(&self.shared.stats)
    }

    /// Stops the thread; gives its final counters, or the I/O error that ended it.
    pub fn stop(mut self) -> io::Result<ModelStats> {
        self.join()?;
        Ok(self.stats())
    }

    fn join(&mut self) -> io::Result<()> {
        self.shared.stop.store(true, Ordering::SeqCst);
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(result)) => result,
            Some(Err(_)) => Err(io::Error::other("the firmware thread panicked")),
            None => Ok(()),
        }
    }
}

impl Drop for SimulatedController {
    fn drop(&mut self) {
        // Errors were the test's to see through `stop`; a dropped handle just ends the thread.
        let _ = self.join();
    }
}

/// The controller thread: read, run the model, write with faults applied.
fn serve<S: Read + Write>(
    mut stream: S,
    mut model: FirmwareModel,
    shared: &Shared,
) -> io::Result<()> {
    let origin = Instant::now();
    let mut buf = [0u8; 256];
    let mut out = Vec::new();
    while !shared.stop.load(Ordering::SeqCst) {
        let n = match stream.read(&mut buf) {
            Ok(0) => return Ok(()),
            Ok(n) => n,
            Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => 0,
            Err(e) if e.kind() == ErrorKind::Interrupted => continue,
            Err(e) if e.kind() == ErrorKind::BrokenPipe => return Ok(()),
            Err(e) => return Err(e),
        };
        if lock(&shared.faults).silent {
            continue;
        }
        let now_us = origin.elapsed().as_micros() as u64;
        for _ in 0..shared.external_edges.swap(0, Ordering::SeqCst) {
            model.external_start(now_us, &mut out);
        }
        model.receive(&buf[..n], now_us, &mut out);
        *lock(&shared.stats) = model.stats();
        if !out.is_empty() {
            for message in out.drain(..) {
                send(&mut stream, &message, shared)?;
            }
            stream.flush()?;
        }
    }
    Ok(())
}

fn send<W: Write>(stream: &mut W, message: &ControllerMessage, shared: &Shared) -> io::Result<()> {
    let mut frame = encode_frame(message)
        .map_err(|e| io::Error::other(format!("encoding {message:?}: {e}")))?
        .to_vec();
    let mut faults = lock(&shared.faults);
    match message {
        ControllerMessage::Event { .. } if faults.drop_events > 0 => {
            faults.drop_events -= 1;
            return Ok(());
        }
        ControllerMessage::Event { .. } => {}
        ControllerMessage::Reply { .. } => match faults.replies.pop_front() {
            None => {}
            Some(ReplyFault::Drop) => return Ok(()),
            Some(ReplyFault::CorruptCrc) => frame = corrupt_crc(&frame),
            Some(ReplyFault::Garbage(bytes)) => stream.write_all(&bytes)?,
        },
    }
    drop(faults);
    stream.write_all(&frame)
}

/// The same frame with the lowest bit of its CRC trailer's last byte flipped.
fn corrupt_crc(frame: &[u8]) -> Vec<u8> {
    let mut body = [0u8; MAX_BODY_LEN];
    let n = cobs::decode(&frame[1..frame.len() - 1], &mut body)
        .expect("our own frames are valid COBS")
        .frame_size();
    body[n - 1] ^= 1;
    let mut out = vec![0u8; cobs::max_encoding_length(n) + 2];
    let len = cobs::encode_including_sentinels(&body[..n], &mut out);
    out.truncate(len);
    out
}

#[cfg(test)]
mod tests;
