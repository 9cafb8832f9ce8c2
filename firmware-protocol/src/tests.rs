extern crate std;

use super::*;
use proptest::prelude::*;
use std::string::String;
use std::vec::Vec;

fn line(line: u8, delay_us: u32, pulse_us: u32) -> LineConfig {
    LineConfig {
        line,
        delay_us,
        pulse_us,
    }
}

fn lines(list: &[LineConfig]) -> heapless::Vec<LineConfig, MAX_LINES> {
    heapless::Vec::from_slice(list).unwrap()
}

/// The COBS bytes of a frame (between its delimiters), as a `FrameReader` gives them.
fn inner(frame: &[u8]) -> &[u8] {
    assert_eq!(frame.first(), Some(&0));
    assert_eq!(frame.last(), Some(&0));
    &frame[1..frame.len() - 1]
}

fn postcard_bytes<T: Serialize>(value: &T) -> Vec<u8> {
    let mut buf = [0u8; MAX_MESSAGE_LEN];
    postcard::to_slice(value, &mut buf).unwrap().to_vec()
}

/// Frames arbitrary postcard bytes with a correct CRC (for messages this crate cannot build).
fn frame_raw(message: &[u8]) -> Vec<u8> {
    let mut body = message.to_vec();
    body.extend_from_slice(&CRC32.checksum(message).to_le_bytes());
    let mut out = std::vec![0u8; cobs::max_encoding_length(body.len())];
    let n = cobs::encode(&body, &mut out);
    out.truncate(n);
    out
}

fn hex(bytes: &[u8]) -> String {
    bytes
        .iter()
        .map(|b| std::format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

#[test]
fn crc_is_crc32_iso_hdlc() {
    assert_eq!(CRC32.checksum(b"123456789"), 0xCBF4_3926);
}

/// The README's worked examples, in the order they appear there.
enum Example {
    Request(Request),
    Controller(ControllerMessage),
}

#[test]
fn readme_examples_match_the_encoder() {
    let examples = [
        Example::Request(Request {
            seq: 0,
            command: Command::Hello { version: 1 },
        }),
        Example::Controller(ControllerMessage::Reply {
            seq: 0,
            reply: Reply::Hello {
                version: 1,
                lines: 8,
            },
        }),
        Example::Request(Request {
            seq: 1,
            command: Command::Configure {
                lines: lines(&[line(0, 0, 100), line(1, 250, 100)]),
            },
        }),
        Example::Controller(ControllerMessage::Event {
            counter: 5,
            event: Event::FrameDone(FrameDone {
                frame: 2,
                time_us: 1_000_000,
            }),
        }),
    ];
    let readme = include_str!("../README.md");
    let field = |name: &str| -> Vec<String> {
        readme
            .lines()
            .filter_map(|l| l.strip_prefix(name))
            .map(|rest| rest.trim().into())
            .collect()
    };
    let (postcards, crcs, wires) = (field("postcard "), field("crc "), field("wire "));
    assert_eq!(postcards.len(), examples.len(), "postcard lines in README");
    assert_eq!(crcs.len(), examples.len(), "crc lines in README");
    assert_eq!(wires.len(), examples.len(), "wire lines in README");
    for (i, example) in examples.iter().enumerate() {
        let (message, wire) = match example {
            Example::Request(r) => {
                let wire = encode_frame(r).unwrap();
                assert_eq!(&decode_frame::<Request>(inner(&wire)).unwrap(), r);
                (postcard_bytes(r), wire)
            }
            Example::Controller(m) => {
                let wire = encode_frame(m).unwrap();
                assert_eq!(&decode_frame::<ControllerMessage>(inner(&wire)).unwrap(), m);
                (postcard_bytes(m), wire)
            }
        };
        let crc = CRC32.checksum(&message).to_le_bytes();
        assert_eq!(postcards[i], hex(&message), "example {i}: postcard bytes");
        assert_eq!(crcs[i], hex(&crc), "example {i}: CRC");
        assert_eq!(wires[i], hex(&wire), "example {i}: wire bytes");
    }
}

#[test]
fn every_variant_round_trips() {
    let commands = [
        Command::Hello { version: 1 },
        Command::Configure {
            lines: lines(&[line(0, 0, 1), line(15, 1_000, 50_000)]),
        },
        Command::Configure { lines: lines(&[]) },
        Command::Arm {
            frames: 90,
            pacing: Pacing::PerFire,
        },
        Command::Arm {
            frames: 1,
            pacing: Pacing::Periodic { period_us: 33_333 },
        },
        Command::Arm {
            frames: u32::MAX,
            pacing: Pacing::ExternalStart { period_us: 16_667 },
        },
        Command::Fire,
        Command::Disarm,
        Command::SetHeartbeat { interval_ms: 250 },
    ];
    for (i, command) in commands.into_iter().enumerate() {
        let request = Request {
            seq: 1000 + i as u16,
            command,
        };
        let frame = encode_frame(&request).unwrap();
        assert_eq!(decode_frame::<Request>(inner(&frame)), Ok(request));
    }
    let replies = [
        Reply::Hello {
            version: 1,
            lines: 8,
        },
        Reply::Ok,
        Reply::Fired { frame: 7 },
        Reply::Error(ErrorCode::NoSession),
        Reply::Error(ErrorCode::BadLine { line: 9 }),
        Reply::Error(ErrorCode::BadPulse { line: 3 }),
        Reply::Error(ErrorCode::NotConfigured),
        Reply::Error(ErrorCode::NotArmed),
        Reply::Error(ErrorCode::Busy),
        Reply::Error(ErrorCode::BadArm),
        Reply::Error(ErrorCode::WrongPacing),
    ];
    let events = [
        Event::FrameDone(FrameDone {
            frame: 3,
            time_us: 12_345_678,
        }),
        Event::Heartbeat(Heartbeat {
            time_us: u64::MAX,
            state: ControllerState::Idle,
            frames_done: 0,
        }),
        Event::Heartbeat(Heartbeat {
            time_us: 1,
            state: ControllerState::Configured,
            frames_done: 1,
        }),
        Event::Heartbeat(Heartbeat {
            time_us: 2,
            state: ControllerState::Armed,
            frames_done: 2,
        }),
        Event::Heartbeat(Heartbeat {
            time_us: 3,
            state: ControllerState::Running,
            frames_done: 3,
        }),
    ];
    let messages = replies
        .into_iter()
        .enumerate()
        .map(|(i, reply)| ControllerMessage::Reply {
            seq: i as u16,
            reply,
        })
        .chain(
            events
                .into_iter()
                .enumerate()
                .map(|(i, event)| ControllerMessage::Event {
                    counter: i as u32,
                    event,
                }),
        );
    for message in messages {
        let frame = encode_frame(&message).unwrap();
        assert_eq!(
            decode_frame::<ControllerMessage>(inner(&frame)),
            Ok(message)
        );
    }
}

/// The largest message of all: a full Configure with every integer at its maximum.
fn largest_request() -> Request {
    Request {
        seq: u16::MAX,
        command: Command::Configure {
            lines: (0..MAX_LINES)
                .map(|i| line(i as u8, u32::MAX, u32::MAX))
                .collect(),
        },
    }
}

#[test]
fn max_sizes_are_tight() {
    let request = largest_request();
    assert_eq!(postcard_bytes(&request).len(), MAX_MESSAGE_LEN);
    let frame = encode_frame(&request).unwrap();
    assert_eq!(frame.len(), MAX_FRAME_LEN);
    assert_eq!(decode_frame::<Request>(inner(&frame)), Ok(request));
    // The largest controller messages stay well below it.
    let largest_event = ControllerMessage::Event {
        counter: u32::MAX,
        event: Event::Heartbeat(Heartbeat {
            time_us: u64::MAX,
            state: ControllerState::Running,
            frames_done: u32::MAX,
        }),
    };
    assert!(postcard_bytes(&largest_event).len() < MAX_MESSAGE_LEN);
    assert_eq!(MAX_COBS_LEN, MAX_BODY_LEN + 1);
}

#[test]
fn too_many_lines_are_rejected() {
    // A hand-made Configure with MAX_LINES + 1 lines: valid CRC, but more than fits.
    let mut message = std::vec![0x01, 0x01, (MAX_LINES + 1) as u8];
    for i in 0..=MAX_LINES {
        message.extend_from_slice(&[i as u8, 0x00, 0x01]);
    }
    assert_eq!(
        decode_frame::<Request>(&frame_raw(&message)),
        Err(FrameError::Malformed)
    );
}

#[test]
fn oversized_cobs_input_is_rejected() {
    let long = std::vec![0x01u8; MAX_COBS_LEN + 1];
    assert_eq!(decode_frame::<Request>(&long), Err(FrameError::TooLong));
}

#[test]
fn bad_tag_and_trailing_bytes_are_rejected() {
    // Command tag 9 does not exist.
    assert_eq!(
        decode_frame::<Request>(&frame_raw(&[0x01, 0x09])),
        Err(FrameError::Malformed)
    );
    // A Fire request followed by one extra byte.
    assert_eq!(
        decode_frame::<Request>(&frame_raw(&[0x01, 0x03, 0x00])),
        Err(FrameError::TrailingBytes)
    );
    // Only a CRC.
    assert_eq!(
        decode_frame::<Request>(&frame_raw(&[])),
        Err(FrameError::TooShort)
    );
}

#[test]
fn hello_prefix_reads_newer_versions() {
    // A version-2 controller appends a field to its Hello reply; the full decode refuses
    // it, the frozen prefix still gives the version.
    let mut reply = postcard_bytes(&ControllerMessage::Reply {
        seq: 300,
        reply: Reply::Hello {
            version: 2,
            lines: 8,
        },
    });
    reply.push(0x2A);
    let framed = frame_raw(&reply);
    assert_eq!(
        decode_frame::<ControllerMessage>(&framed),
        Err(FrameError::TrailingBytes)
    );
    assert_eq!(
        decode_hello_reply_prefix(&framed),
        Ok(Some(HelloPrefix {
            seq: 300,
            version: 2
        }))
    );
    // Same for a version-2 host's Hello request.
    let mut request = postcard_bytes(&Request {
        seq: 7,
        command: Command::Hello { version: 2 },
    });
    request.extend_from_slice(&[0x01, 0x02]);
    assert_eq!(
        decode_hello_request_prefix(&frame_raw(&request)),
        Ok(Some(HelloPrefix { seq: 7, version: 2 }))
    );
    // Other messages are not Hellos.
    let fire = encode_frame(&Request {
        seq: 7,
        command: Command::Fire,
    })
    .unwrap();
    assert_eq!(decode_hello_request_prefix(inner(&fire)), Ok(None));
    let ok = encode_frame(&ControllerMessage::Reply {
        seq: 7,
        reply: Reply::Ok,
    })
    .unwrap();
    assert_eq!(decode_hello_reply_prefix(inner(&ok)), Ok(None));
}

/// Feeds bytes to a reader and collects what it yields.
fn read_all(reader: &mut FrameReader, bytes: &[u8]) -> Vec<Result<Vec<u8>, FrameError>> {
    bytes
        .iter()
        .filter_map(|&b| reader.push(b).map(|r| r.map(<[u8]>::to_vec)))
        .collect()
}

#[test]
fn reader_resynchronises_after_overflow() {
    let fire = encode_frame(&Request {
        seq: 1,
        command: Command::Fire,
    })
    .unwrap();
    let mut stream = std::vec![0x55u8; 3 * MAX_COBS_LEN];
    stream.extend_from_slice(&fire);
    let mut reader = FrameReader::new();
    let out = read_all(&mut reader, &stream);
    assert_eq!(out.len(), 2);
    assert_eq!(out[0], Err(FrameError::TooLong));
    let cobs = out[1].as_ref().unwrap();
    assert_eq!(
        decode_frame::<Request>(cobs).unwrap().command,
        Command::Fire
    );
}

fn arb_line() -> impl Strategy<Value = LineConfig> {
    (any::<u8>(), any::<u32>(), any::<u32>()).prop_map(|(l, d, p)| line(l, d, p))
}

fn arb_pacing() -> impl Strategy<Value = Pacing> {
    prop_oneof![
        Just(Pacing::PerFire),
        any::<u32>().prop_map(|period_us| Pacing::Periodic { period_us }),
        any::<u32>().prop_map(|period_us| Pacing::ExternalStart { period_us }),
    ]
}

fn arb_request() -> impl Strategy<Value = Request> {
    let command = prop_oneof![
        any::<u16>().prop_map(|version| Command::Hello { version }),
        proptest::collection::vec(arb_line(), 0..=MAX_LINES)
            .prop_map(|l| Command::Configure { lines: lines(&l) }),
        (any::<u32>(), arb_pacing()).prop_map(|(frames, pacing)| Command::Arm { frames, pacing }),
        Just(Command::Fire),
        Just(Command::Disarm),
        any::<u32>().prop_map(|interval_ms| Command::SetHeartbeat { interval_ms }),
    ];
    (any::<u16>(), command).prop_map(|(seq, command)| Request { seq, command })
}

fn arb_error() -> impl Strategy<Value = ErrorCode> {
    prop_oneof![
        Just(ErrorCode::NoSession),
        any::<u8>().prop_map(|line| ErrorCode::BadLine { line }),
        any::<u8>().prop_map(|line| ErrorCode::BadPulse { line }),
        Just(ErrorCode::NotConfigured),
        Just(ErrorCode::NotArmed),
        Just(ErrorCode::Busy),
        Just(ErrorCode::BadArm),
        Just(ErrorCode::WrongPacing),
    ]
}

fn arb_state() -> impl Strategy<Value = ControllerState> {
    prop_oneof![
        Just(ControllerState::Idle),
        Just(ControllerState::Configured),
        Just(ControllerState::Armed),
        Just(ControllerState::Running),
    ]
}

fn arb_controller_message() -> impl Strategy<Value = ControllerMessage> {
    let reply = prop_oneof![
        (any::<u16>(), any::<u8>()).prop_map(|(version, lines)| Reply::Hello { version, lines }),
        Just(Reply::Ok),
        any::<u32>().prop_map(|frame| Reply::Fired { frame }),
        arb_error().prop_map(Reply::Error),
    ];
    let event = prop_oneof![
        (any::<u32>(), any::<u64>())
            .prop_map(|(frame, time_us)| Event::FrameDone(FrameDone { frame, time_us })),
        (any::<u64>(), arb_state(), any::<u32>()).prop_map(|(time_us, state, frames_done)| {
            Event::Heartbeat(Heartbeat {
                time_us,
                state,
                frames_done,
            })
        }),
    ];
    prop_oneof![
        (any::<u16>(), reply).prop_map(|(seq, reply)| ControllerMessage::Reply { seq, reply }),
        (any::<u32>(), event)
            .prop_map(|(counter, event)| ControllerMessage::Event { counter, event }),
    ]
}

proptest! {
    #[test]
    fn requests_round_trip(request in arb_request()) {
        let frame = encode_frame(&request).unwrap();
        prop_assert!(frame.len() <= MAX_FRAME_LEN);
        prop_assert!(!inner(&frame).contains(&0));
        prop_assert_eq!(decode_frame::<Request>(inner(&frame)), Ok(request));
    }

    #[test]
    fn controller_messages_round_trip(message in arb_controller_message()) {
        let frame = encode_frame(&message).unwrap();
        prop_assert!(!inner(&frame).contains(&0));
        prop_assert_eq!(decode_frame::<ControllerMessage>(inner(&frame)), Ok(message));
    }

    #[test]
    fn truncated_frames_are_rejected(request in arb_request(), cut in 0.0f64..1.0) {
        let frame = encode_frame(&request).unwrap();
        let cobs = inner(&frame);
        let keep = (cut * cobs.len() as f64) as usize; // 0 ..= len - 1: a strict prefix
        prop_assert!(decode_frame::<Request>(&cobs[..keep]).is_err());
    }

    #[test]
    fn corrupted_frames_are_rejected(message in arb_controller_message(),
                                     at in 0.0f64..1.0, bit in 0u8..8) {
        // A single flipped bit anywhere in the COBS bytes: invalid COBS, or a body whose
        // CRC-32 no longer matches (CRC-32 detects every error burst up to 32 bits; a flipped
        // code byte moves a zero further, which escapes it with probability 2^-32).
        let frame = encode_frame(&message).unwrap();
        let mut cobs = inner(&frame).to_vec();
        let i = (at * cobs.len() as f64) as usize;
        cobs[i] ^= 1 << bit;
        prop_assert!(decode_frame::<ControllerMessage>(&cobs).is_err());
    }

    #[test]
    fn reader_splits_a_stream_with_garbage(
        messages in proptest::collection::vec(arb_controller_message(), 1..8),
        garbage in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..40), 8),
    ) {
        // Frames with arbitrary garbage between them: every frame comes out intact (the
        // leading delimiter ends the garbage), and the garbage never decodes as a message.
        let mut stream = Vec::new();
        for (m, g) in messages.iter().zip(&garbage) {
            stream.extend_from_slice(g);
            stream.extend_from_slice(&encode_frame(m).unwrap());
        }
        let mut reader = FrameReader::new();
        let decoded: Vec<ControllerMessage> = read_all(&mut reader, &stream)
            .into_iter()
            .filter_map(|f| f.ok().and_then(|c| decode_frame(&c).ok()))
            .collect();
        prop_assert_eq!(decoded, messages);
    }
}
