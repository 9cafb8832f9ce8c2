//! Wire protocol between the hexcal host and the camera trigger controller (docs/design.md §12).
//!
//! Takes typed messages ([`Request`] from the host, [`ControllerMessage`] from the
//! controller) and gives the bytes that go on the serial line, and back: postcard encoding,
//! a CRC-32 trailer, COBS framing between `0x00` delimiters. [`FrameReader`] splits a byte
//! stream into frames and resynchronises after garbage. Everything here is `no_std`, without
//! allocation, so the controller firmware links the same crate.
//!
//! The README below is the byte-level specification (its worked examples are checked by the
//! tests against this encoder).
//!
#![doc = include_str!("../README.md")]
#![no_std]
#![warn(missing_docs)]

use core::fmt;

use serde::{de::DeserializeOwned, Deserialize, Serialize};

/// The `heapless` crate, whose `Vec` carries the line list of [`Command::Configure`].
pub use heapless;

/// The protocol version this crate speaks; exchanged in [`Command::Hello`] / [`Reply::Hello`].
pub const PROTOCOL_VERSION: u16 = 1;

/// Most output lines one [`Command::Configure`] can describe.
pub const MAX_LINES: usize = 16;

/// Length of the CRC trailer after the postcard bytes.
pub const CRC_LEN: usize = 4;

/// Longest postcard encoding of any message in either direction: a [`Command::Configure`]
/// with [`MAX_LINES`] lines and every integer at its maximum (3 + 1 + 1 + 16 × 11 bytes).
pub const MAX_MESSAGE_LEN: usize = 181;

/// Longest frame body: postcard bytes plus the CRC trailer.
pub const MAX_BODY_LEN: usize = MAX_MESSAGE_LEN + CRC_LEN;

/// Longest COBS encoding of a body (the bytes between two delimiters).
pub const MAX_COBS_LEN: usize = cobs::max_encoding_length(MAX_BODY_LEN);

/// Longest frame on the wire: leading `0x00`, COBS bytes, trailing `0x00`.
pub const MAX_FRAME_LEN: usize = MAX_COBS_LEN + 2;

/// CRC-32/ISO-HDLC (the zlib/Ethernet CRC): poly 0x04C11DB7 reflected, init and xorout
/// 0xFFFFFFFF; check value 0xCBF43926 for `"123456789"`.
pub const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// One encoded frame, ready to write to the serial line.
pub type Frame = heapless::Vec<u8, MAX_FRAME_LEN>;

/// Host → controller: a command with the sequence number its reply will echo.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq)]
pub struct Request {
    /// Chosen by the host, new for every new request and unchanged when the host resends
    /// the same request after a lost reply.
    pub seq: u16,
    /// What to do.
    pub command: Command,
}

/// What the host asks the controller to do. Every command gets exactly one [`Reply`].
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq)]
pub enum Command {
    /// Open a session: the host's protocol version. Resets the controller (no
    /// configuration, disarmed, heartbeat off, event counter 0). Layout frozen across
    /// versions.
    Hello {
        /// The host's [`PROTOCOL_VERSION`].
        version: u16,
    },
    /// Set the output lines used by following sequences (replaces the previous set).
    Configure {
        /// One entry per line that pulses on every frame.
        lines: heapless::Vec<LineConfig, MAX_LINES>,
    },
    /// Arm a sequence of frames with the current configuration.
    Arm {
        /// Number of frames in the sequence (at least 1).
        frames: u32,
        /// What starts each frame.
        pacing: Pacing,
    },
    /// Fire the next frame ([`Pacing::PerFire`]) or start the sequence
    /// ([`Pacing::Periodic`]).
    Fire,
    /// Abort the armed or running sequence; frames already triggered still complete.
    Disarm,
    /// Send a [`Event::Heartbeat`] every `interval_ms` milliseconds (0: off).
    SetHeartbeat {
        /// Interval in milliseconds; 0 turns heartbeats off.
        interval_ms: u32,
    },
}

/// One output line's pulse, relative to the frame's trigger instant.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub struct LineConfig {
    /// Output line index, below the controller's line count ([`Reply::Hello`]).
    pub line: u8,
    /// Delay from the frame's trigger instant to the rising edge, µs.
    pub delay_us: u32,
    /// High time of the pulse, µs (at least 1).
    pub pulse_us: u32,
}

impl LineConfig {
    /// Time from the frame's trigger instant to this line's falling edge, µs.
    pub fn end_us(&self) -> u64 {
        u64::from(self.delay_us) + u64::from(self.pulse_us)
    }
}

/// What starts the frames of an armed sequence.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pacing {
    /// Each [`Command::Fire`] triggers one frame.
    PerFire,
    /// One [`Command::Fire`] starts the sequence; frame k triggers at start + k·period.
    Periodic {
        /// Frame period, µs; at least the longest line's delay + pulse.
        period_us: u32,
    },
    /// A rising edge on the controller's external start input starts the sequence; frame k
    /// triggers at edge + k·period.
    ExternalStart {
        /// Frame period, µs; at least the longest line's delay + pulse.
        period_us: u32,
    },
}

/// Controller → host.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq)]
pub enum ControllerMessage {
    /// The one reply to the request with sequence number `seq`. Layout of a Hello reply
    /// frozen across versions.
    Reply {
        /// The request's sequence number.
        seq: u16,
        /// The outcome.
        reply: Reply,
    },
    /// Something that happened on the controller, not asked for by one request.
    Event {
        /// Counts events since the last Hello (0, 1, 2, …, wrapping): a gap means an event
        /// was lost.
        counter: u32,
        /// What happened.
        event: Event,
    },
}

/// The outcome of one [`Command`].
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq, Eq)]
pub enum Reply {
    /// Answer to [`Command::Hello`]: the controller's version and size. Sent even when the
    /// versions differ (the controller then refuses every other command with
    /// [`ErrorCode::NoSession`]).
    Hello {
        /// The controller's [`PROTOCOL_VERSION`].
        version: u16,
        /// Number of output lines (valid line indices are `0..lines`).
        lines: u8,
    },
    /// The command was carried out.
    Ok,
    /// Answer to [`Command::Fire`]: the index of the frame it triggered (or of the first
    /// frame of a periodic sequence it started).
    Fired {
        /// Frame index within the armed sequence, from 0.
        frame: u32,
    },
    /// The command was refused; the controller's state is unchanged.
    Error(ErrorCode),
}

/// Why a command was refused.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorCode {
    /// No successful Hello yet (or the last Hello had another version).
    NoSession,
    /// The line does not exist on this controller, or appears twice.
    BadLine {
        /// The offending line index.
        line: u8,
    },
    /// The line's pulse width is 0.
    BadPulse {
        /// The offending line index.
        line: u8,
    },
    /// Arm without a configuration (or with an empty one).
    NotConfigured,
    /// Fire while no sequence is armed (including after the last frame of one).
    NotArmed,
    /// Fire, Configure or Arm while a frame is still pulsing; Fire or Arm while a periodic
    /// sequence runs; Configure while a sequence is armed.
    Busy,
    /// Arm with 0 frames, or a period shorter than the longest delay + pulse.
    BadArm,
    /// Fire in a sequence armed for [`Pacing::ExternalStart`].
    WrongPacing,
}

impl fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ErrorCode::NoSession => write!(f, "no session (Hello missing or version mismatch)"),
            ErrorCode::BadLine { line } => write!(f, "line {line} does not exist or is repeated"),
            ErrorCode::BadPulse { line } => write!(f, "line {line} has a zero pulse width"),
            ErrorCode::NotConfigured => write!(f, "no output lines configured"),
            ErrorCode::NotArmed => write!(f, "no sequence armed"),
            ErrorCode::Busy => write!(f, "busy with the previous frame or a running sequence"),
            ErrorCode::BadArm => write!(f, "zero frames or a period shorter than the pulses"),
            ErrorCode::WrongPacing => write!(f, "Fire in a sequence paced by the external input"),
        }
    }
}

/// Something that happened on the controller.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event {
    /// Every line of a frame has finished its pulse.
    FrameDone(FrameDone),
    /// Periodic sign of life ([`Command::SetHeartbeat`]).
    Heartbeat(Heartbeat),
}

/// A frame's pulses are over.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameDone {
    /// Frame index within the armed sequence, from 0.
    pub frame: u32,
    /// The frame's trigger instant (line pulses start `delay_us` after it), µs on the
    /// controller's monotonic clock.
    pub time_us: u64,
}

/// Periodic sign of life with the controller's state.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub struct Heartbeat {
    /// The controller's monotonic clock, µs.
    pub time_us: u64,
    /// Where the controller's state machine is.
    pub state: ControllerState,
    /// Frames completed in the current (or last) sequence.
    pub frames_done: u32,
}

/// The controller's state machine.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub enum ControllerState {
    /// Session open, no output lines configured.
    Idle,
    /// Lines configured, no sequence armed.
    Configured,
    /// A sequence is armed and waits for Fire or the external start.
    Armed,
    /// A periodic sequence is running.
    Running,
}

/// Why bytes could not be turned into a message (or a message into bytes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameError {
    /// More bytes than [`MAX_COBS_LEN`] before a delimiter (or a message longer than
    /// [`MAX_MESSAGE_LEN`] to encode).
    TooLong,
    /// The bytes between the delimiters are not valid COBS.
    Cobs,
    /// Fewer bytes than one message byte plus the CRC.
    TooShort,
    /// The CRC trailer does not match the postcard bytes.
    Crc {
        /// CRC computed over the received postcard bytes.
        computed: u32,
        /// CRC in the frame's trailer.
        received: u32,
    },
    /// CRC correct, but the bytes are not a message of the expected type.
    Malformed,
    /// A complete message followed by extra bytes before the CRC.
    TrailingBytes,
}

impl fmt::Display for FrameError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FrameError::TooLong => write!(f, "frame longer than {MAX_COBS_LEN} bytes"),
            FrameError::Cobs => write!(f, "invalid COBS encoding"),
            FrameError::TooShort => write!(f, "frame shorter than a message and its CRC"),
            FrameError::Crc { computed, received } => write!(
                f,
                "CRC mismatch: computed {computed:#010x}, frame says {received:#010x}"
            ),
            FrameError::Malformed => write!(f, "CRC correct but not a valid message"),
            FrameError::TrailingBytes => write!(f, "extra bytes after the message"),
        }
    }
}

/// Encodes one message as a complete frame: `0x00`, COBS(postcard ‖ CRC-32 LE), `0x00`.
pub fn encode_frame<T: Serialize>(message: &T) -> Result<Frame, FrameError> {
    let mut body = [0u8; MAX_BODY_LEN];
    let n = postcard::to_slice(message, &mut body[..MAX_MESSAGE_LEN])
        .map_err(|e| match e {
            postcard::Error::SerializeBufferFull => FrameError::TooLong,
            _ => FrameError::Malformed,
        })?
        .len();
    let crc = CRC32.checksum(&body[..n]);
    body[n..n + CRC_LEN].copy_from_slice(&crc.to_le_bytes());
    let mut frame = Frame::new();
    frame
        .resize(MAX_FRAME_LEN, 0)
        .expect("MAX_FRAME_LEN is the capacity");
    let len = cobs::try_encode_including_sentinels(&body[..n + CRC_LEN], &mut frame)
        .map_err(|_| FrameError::TooLong)?;
    frame.truncate(len);
    Ok(frame)
}

/// Decodes the COBS bytes of one frame (between two delimiters, as [`FrameReader`] gives
/// them), checks the CRC and reads exactly one message of type `T`.
pub fn decode_frame<T: DeserializeOwned>(cobs_bytes: &[u8]) -> Result<T, FrameError> {
    let mut body = [0u8; MAX_BODY_LEN];
    let message = verified_message(cobs_bytes, &mut body)?;
    match postcard::take_from_bytes::<T>(message) {
        Ok((value, [])) => Ok(value),
        Ok(_) => Err(FrameError::TrailingBytes),
        Err(_) => Err(FrameError::Malformed),
    }
}

/// The postcard bytes of a frame whose COBS and CRC are valid.
fn verified_message<'a>(
    cobs_bytes: &[u8],
    body: &'a mut [u8; MAX_BODY_LEN],
) -> Result<&'a [u8], FrameError> {
    if cobs_bytes.len() > MAX_COBS_LEN {
        return Err(FrameError::TooLong);
    }
    if cobs_bytes.contains(&0) {
        return Err(FrameError::Cobs);
    }
    let n = cobs::decode(cobs_bytes, body)
        .map_err(|e| match e {
            cobs::DecodeError::TargetBufTooSmall => FrameError::TooLong,
            _ => FrameError::Cobs,
        })?
        .frame_size();
    if n <= CRC_LEN {
        return Err(FrameError::TooShort);
    }
    let (message, trailer) = body[..n].split_at(n - CRC_LEN);
    let received = u32::from_le_bytes([trailer[0], trailer[1], trailer[2], trailer[3]]);
    let computed = CRC32.checksum(message);
    if computed != received {
        return Err(FrameError::Crc { computed, received });
    }
    Ok(message)
}

/// The version-independent start of a Hello request or reply: readable from a peer of any
/// protocol version, because every version keeps this layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HelloPrefix {
    /// Sequence number of the request (echoed by the reply).
    pub seq: u16,
    /// The sender's protocol version.
    pub version: u16,
}

/// Reads the frozen prefix of a Hello request (`seq`, tag 0, `version`), ignoring whatever
/// a newer version appends. `Ok(None)`: a valid frame that is not a Hello request.
pub fn decode_hello_request_prefix(cobs_bytes: &[u8]) -> Result<Option<HelloPrefix>, FrameError> {
    let mut body = [0u8; MAX_BODY_LEN];
    let message = verified_message(cobs_bytes, &mut body)?;
    match postcard::take_from_bytes::<(u16, u32, u16)>(message) {
        Ok(((seq, 0, version), _)) => Ok(Some(HelloPrefix { seq, version })),
        _ => Ok(None),
    }
}

/// Reads the frozen prefix of a Hello reply (tag 0, `seq`, tag 0, `version`), ignoring
/// whatever a newer version appends. `Ok(None)`: a valid frame that is not a Hello reply.
pub fn decode_hello_reply_prefix(cobs_bytes: &[u8]) -> Result<Option<HelloPrefix>, FrameError> {
    let mut body = [0u8; MAX_BODY_LEN];
    let message = verified_message(cobs_bytes, &mut body)?;
    match postcard::take_from_bytes::<(u32, u16, u32, u16)>(message) {
        Ok(((0, seq, 0, version), _)) => Ok(Some(HelloPrefix { seq, version })),
        _ => Ok(None),
    }
}

/// Splits a received byte stream into frames at `0x00` delimiters.
///
/// Empty frames (two delimiters in a row) are skipped. When more than [`MAX_COBS_LEN`] bytes
/// arrive without a delimiter, the reader discards everything up to the next `0x00` and
/// reports [`FrameError::TooLong`] once: this is how it resynchronises after garbage.
#[derive(Debug, Clone)]
pub struct FrameReader {
    buf: [u8; MAX_COBS_LEN],
    len: usize,
    overflowed: bool,
    complete: bool,
}

impl Default for FrameReader {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameReader {
    /// An empty reader.
    pub const fn new() -> Self {
        FrameReader {
            buf: [0; MAX_COBS_LEN],
            len: 0,
            overflowed: false,
            complete: false,
        }
    }

    /// Forgets any partial frame (the next byte starts a new one).
    pub fn clear(&mut self) {
        self.len = 0;
        self.overflowed = false;
        self.complete = false;
    }

    /// Feeds one byte. At a delimiter that ends a non-empty frame, returns its COBS bytes
    /// (for [`decode_frame`]) or [`FrameError::TooLong`] if it overflowed.
    pub fn push(&mut self, byte: u8) -> Option<Result<&[u8], FrameError>> {
        if self.complete {
            self.clear();
        }
        if byte == 0 {
            if self.overflowed {
                self.clear();
                return Some(Err(FrameError::TooLong));
            }
            if self.len == 0 {
                return None;
            }
            self.complete = true;
            return Some(Ok(&self.buf[..self.len]));
        }
        if self.overflowed {
            return None;
        }
        if self.len == MAX_COBS_LEN {
            self.overflowed = true;
            return None;
        }
        self.buf[self.len] = byte;
        self.len += 1;
        None
    }
}

#[cfg(test)]
mod tests;
