use super::*;
use hexcal_firmware_protocol::{heapless, FrameReader, HelloPrefix, MAX_LINES};
use std::os::unix::net::UnixStream;
use std::time::Duration;

fn frame(seq: u16, command: Command) -> Vec<u8> {
    encode_frame(&Request { seq, command }).unwrap().to_vec()
}

/// Sends one request at `now_us`, returns everything the model answers.
fn send_at(
    model: &mut FirmwareModel,
    seq: u16,
    command: Command,
    now_us: u64,
) -> Vec<ControllerMessage> {
    let mut out = Vec::new();
    model.receive(&frame(seq, command), now_us, &mut out);
    out
}

/// The reply to one request (asserting it is the only message).
fn reply(model: &mut FirmwareModel, seq: u16, command: Command, now_us: u64) -> Reply {
    match send_at(model, seq, command, now_us).as_slice() {
        [ControllerMessage::Reply { seq: s, reply }] if *s == seq => reply.clone(),
        other => panic!("expected one reply to seq {seq}, got {other:?}"),
    }
}

fn lines(list: &[(u8, u32, u32)]) -> heapless::Vec<LineConfig, MAX_LINES> {
    list.iter()
        .map(|&(line, delay_us, pulse_us)| LineConfig {
            line,
            delay_us,
            pulse_us,
        })
        .collect()
}

/// A model with a session and two lines: line 0 at once for 100 µs, line 3 after 50 µs for
/// 200 µs (frame length 250 µs).
fn configured() -> FirmwareModel {
    let mut m = FirmwareModel::new(ModelConfig::default());
    assert_eq!(
        reply(&mut m, 0, Command::Hello { version: 1 }, 0),
        Reply::Hello {
            version: 1,
            lines: 8
        }
    );
    let l = lines(&[(0, 0, 100), (3, 50, 200)]);
    assert_eq!(
        reply(&mut m, 1, Command::Configure { lines: l }, 0),
        Reply::Ok
    );
    m
}

fn frame_done(m: &ControllerMessage) -> (u32, FrameDone) {
    match m {
        ControllerMessage::Event {
            counter,
            event: Event::FrameDone(d),
        } => (*counter, *d),
        other => panic!("expected FrameDone, got {other:?}"),
    }
}

#[test]
fn commands_need_a_session_of_the_same_version() {
    let mut m = FirmwareModel::new(ModelConfig::default());
    assert_eq!(
        reply(&mut m, 5, Command::Fire, 0),
        Reply::Error(ErrorCode::NoSession)
    );
    // A host of version 2: the controller still says who it is, then refuses to work.
    assert_eq!(
        reply(&mut m, 6, Command::Hello { version: 2 }, 0),
        Reply::Hello {
            version: 1,
            lines: 8
        }
    );
    assert_eq!(
        reply(&mut m, 7, Command::Configure { lines: lines(&[]) }, 0),
        Reply::Error(ErrorCode::NoSession)
    );
    // A controller configured as version 3 answers a version-1 Hello with 3.
    let mut m3 = FirmwareModel::new(ModelConfig {
        version: 3,
        lines: 4,
    });
    assert_eq!(
        reply(&mut m3, 0, Command::Hello { version: 1 }, 0),
        Reply::Hello {
            version: 3,
            lines: 4
        }
    );
    assert_eq!(
        reply(&mut m3, 1, Command::Disarm, 0),
        Reply::Error(ErrorCode::NoSession)
    );
}

#[test]
fn a_newer_hosts_hello_is_answered_from_its_prefix() {
    // Version-2 Hello with an extra trailing field, framed by hand.
    let mut body = vec![0x09, 0x00, 0x02, 0x2A];
    body.extend_from_slice(
        &hexcal_firmware_protocol::CRC32
            .checksum(&body[..4])
            .to_le_bytes(),
    );
    let mut wire = vec![0u8; 16];
    let n = cobs::encode_including_sentinels(&body, &mut wire);
    let framed = &wire[..n];
    assert_eq!(
        decode_hello_request_prefix(&framed[1..n - 1]),
        Ok(Some(HelloPrefix { seq: 9, version: 2 }))
    );
    let mut m = FirmwareModel::new(ModelConfig::default());
    let mut out = Vec::new();
    m.receive(framed, 0, &mut out);
    assert_eq!(
        out,
        [ControllerMessage::Reply {
            seq: 9,
            reply: Reply::Hello {
                version: 1,
                lines: 8
            }
        }]
    );
}

#[test]
fn refusals_name_the_problem() {
    let mut m = FirmwareModel::new(ModelConfig::default());
    reply(&mut m, 0, Command::Hello { version: 1 }, 0);
    let arm = |frames, pacing| Command::Arm { frames, pacing };
    assert_eq!(
        reply(&mut m, 1, arm(3, Pacing::PerFire), 0),
        Reply::Error(ErrorCode::NotConfigured)
    );
    assert_eq!(
        reply(&mut m, 2, Command::Fire, 0),
        Reply::Error(ErrorCode::NotArmed)
    );
    let bad_line = lines(&[(0, 0, 10), (8, 0, 10)]);
    assert_eq!(
        reply(&mut m, 3, Command::Configure { lines: bad_line }, 0),
        Reply::Error(ErrorCode::BadLine { line: 8 })
    );
    let repeated = lines(&[(2, 0, 10), (2, 5, 10)]);
    assert_eq!(
        reply(&mut m, 4, Command::Configure { lines: repeated }, 0),
        Reply::Error(ErrorCode::BadLine { line: 2 })
    );
    let zero_pulse = lines(&[(1, 0, 0)]);
    assert_eq!(
        reply(&mut m, 5, Command::Configure { lines: zero_pulse }, 0),
        Reply::Error(ErrorCode::BadPulse { line: 1 })
    );
    // Refused commands changed nothing: still idle.
    assert_eq!(m.state(), ControllerState::Idle);

    let mut m = configured();
    assert_eq!(
        reply(&mut m, 2, arm(0, Pacing::PerFire), 0),
        Reply::Error(ErrorCode::BadArm)
    );
    // The frame is 250 µs long: a 249 µs period cannot fit, 250 µs can.
    let p = |period_us| Pacing::Periodic { period_us };
    assert_eq!(
        reply(&mut m, 3, arm(5, p(249)), 0),
        Reply::Error(ErrorCode::BadArm)
    );
    assert_eq!(reply(&mut m, 4, arm(5, p(250)), 0), Reply::Ok);
    assert_eq!(
        reply(&mut m, 5, Command::Configure { lines: lines(&[]) }, 0),
        Reply::Error(ErrorCode::Busy)
    );
    let ext = Pacing::ExternalStart { period_us: 1000 };
    assert_eq!(reply(&mut m, 6, arm(5, ext), 0), Reply::Ok);
    assert_eq!(
        reply(&mut m, 7, Command::Fire, 0),
        Reply::Error(ErrorCode::WrongPacing)
    );
    assert_eq!(reply(&mut m, 8, Command::Disarm, 0), Reply::Ok);
    assert_eq!(m.state(), ControllerState::Configured);
}

#[test]
fn per_fire_frames_report_their_trigger_instant() {
    let mut m = configured();
    let arm = Command::Arm {
        frames: 2,
        pacing: Pacing::PerFire,
    };
    assert_eq!(reply(&mut m, 2, arm, 0), Reply::Ok);
    assert_eq!(m.state(), ControllerState::Armed);
    assert_eq!(
        reply(&mut m, 3, Command::Fire, 1_000),
        Reply::Fired { frame: 0 }
    );
    // Still pulsing 249 µs later: no event, and a second Fire is refused.
    assert_eq!(
        reply(&mut m, 4, Command::Fire, 1_249),
        Reply::Error(ErrorCode::Busy)
    );
    // At 1250 µs line 3 goes low: FrameDone comes before the reply to the next Fire.
    let out = send_at(&mut m, 5, Command::Fire, 1_250);
    assert_eq!(out.len(), 2, "{out:?}");
    assert_eq!(
        frame_done(&out[0]),
        (
            0,
            FrameDone {
                frame: 0,
                time_us: 1_000
            }
        )
    );
    assert_eq!(
        out[1],
        ControllerMessage::Reply {
            seq: 5,
            reply: Reply::Fired { frame: 1 }
        }
    );
    // That was the last frame: the sequence is over.
    assert_eq!(m.state(), ControllerState::Configured);
    let mut out = Vec::new();
    m.poll(1_499, &mut out);
    assert!(out.is_empty());
    assert_eq!(m.next_deadline_us(), Some(1_500));
    m.poll(1_500, &mut out);
    assert_eq!(
        frame_done(&out[0]),
        (
            1,
            FrameDone {
                frame: 1,
                time_us: 1_250
            }
        )
    );
    assert_eq!(
        reply(&mut m, 6, Command::Fire, 2_000),
        Reply::Error(ErrorCode::NotArmed)
    );
    assert_eq!(m.stats().frames_fired, 2);
}

#[test]
fn periodic_frames_follow_the_schedule() {
    let mut m = configured();
    let arm = Command::Arm {
        frames: 4,
        pacing: Pacing::Periodic { period_us: 1_000 },
    };
    assert_eq!(reply(&mut m, 2, arm, 0), Reply::Ok);
    assert_eq!(
        reply(&mut m, 3, Command::Fire, 500),
        Reply::Fired { frame: 0 }
    );
    assert_eq!(m.state(), ControllerState::Running);
    assert_eq!(
        reply(&mut m, 4, Command::Fire, 600),
        Reply::Error(ErrorCode::Busy)
    );
    // The host polls late: all four frames come out at once, with the scheduled instants.
    let mut out = Vec::new();
    m.poll(10_000, &mut out);
    let done: Vec<_> = out.iter().map(frame_done).collect();
    let expected: Vec<_> = (0..4u32)
        .map(|k| {
            (
                k,
                FrameDone {
                    frame: k,
                    time_us: 500 + 1_000 * u64::from(k),
                },
            )
        })
        .collect();
    assert_eq!(done, expected);
    assert_eq!(m.state(), ControllerState::Configured);
    assert_eq!(m.stats().frames_fired, 4);
}

#[test]
fn external_edge_starts_the_sequence() {
    let mut m = configured();
    let arm = Command::Arm {
        frames: 2,
        pacing: Pacing::ExternalStart { period_us: 300 },
    };
    assert_eq!(reply(&mut m, 2, arm, 0), Reply::Ok);
    let mut out = Vec::new();
    m.poll(5_000, &mut out);
    assert!(out.is_empty(), "nothing before the edge");
    m.external_start(7_000, &mut out);
    m.poll(8_000, &mut out);
    let done: Vec<_> = out.iter().map(|e| frame_done(e).1.time_us).collect();
    assert_eq!(done, [7_000, 7_300]);
}

#[test]
fn repeated_request_is_answered_from_the_cache() {
    let mut m = configured();
    let arm = Command::Arm {
        frames: 5,
        pacing: Pacing::PerFire,
    };
    assert_eq!(reply(&mut m, 2, arm, 0), Reply::Ok);
    assert_eq!(
        reply(&mut m, 3, Command::Fire, 100),
        Reply::Fired { frame: 0 }
    );
    // The host lost that reply and resends seq 3 after the frame ended.
    let out = send_at(&mut m, 3, Command::Fire, 1_000);
    assert_eq!(frame_done(&out[0]).1.frame, 0);
    assert_eq!(
        out[1],
        ControllerMessage::Reply {
            seq: 3,
            reply: Reply::Fired { frame: 0 }
        }
    );
    assert_eq!(
        m.stats().frames_fired,
        1,
        "a resent Fire must not fire again"
    );
    assert_eq!(m.stats().replies_replayed, 1);
    // A new seq fires the next frame.
    assert_eq!(
        reply(&mut m, 4, Command::Fire, 2_000),
        Reply::Fired { frame: 1 }
    );
    assert_eq!(m.stats().frames_fired, 2);
}

#[test]
fn bad_frames_are_dropped_without_reply() {
    let mut m = configured();
    let mut out = Vec::new();
    // Corrupt one CRC bit of a valid frame.
    let good = frame(9, Command::Disarm);
    let bad = corrupt_crc(&good);
    m.receive(&bad, 0, &mut out);
    // Garbage, including zeros and an over-long run, then the valid frame.
    let mut garbage = vec![0x11, 0x00, 0x03, 0x99, 0x00];
    garbage.extend(std::iter::repeat_n(0x42, 400));
    m.receive(&garbage, 0, &mut out);
    assert!(out.is_empty(), "{out:?}");
    m.receive(&good, 0, &mut out);
    assert_eq!(
        out,
        [ControllerMessage::Reply {
            seq: 9,
            reply: Reply::Ok
        }]
    );
    let stats = m.stats();
    assert_eq!(stats.crc_errors, 1);
    assert_eq!(
        stats.bad_frames, 3,
        "two short garbage frames and one overflow"
    );
}

#[test]
fn heartbeats_report_the_state() {
    let mut m = configured();
    let beat = Command::SetHeartbeat { interval_ms: 2 };
    assert_eq!(reply(&mut m, 2, beat, 1_000), Reply::Ok);
    let mut out = Vec::new();
    m.poll(7_500, &mut out);
    let beats: Vec<_> = out
        .iter()
        .map(|m| match m {
            ControllerMessage::Event {
                counter,
                event: Event::Heartbeat(h),
            } => (*counter, h.time_us, h.state),
            other => panic!("expected a heartbeat, got {other:?}"),
        })
        .collect();
    let c = ControllerState::Configured;
    assert_eq!(beats, [(0, 3_000, c), (1, 5_000, c), (2, 7_000, c)]);
}

/// Reads frames from `stream` until one decodes (or fails) as a controller message.
fn read_message(stream: &mut UnixStream) -> Result<ControllerMessage, FrameError> {
    let mut reader = FrameReader::new();
    let mut byte = [0u8; 1];
    loop {
        stream.read_exact(&mut byte).unwrap();
        if let Some(frame) = reader.push(byte[0]) {
            return frame.and_then(decode_frame);
        }
    }
}

#[test]
fn thread_serves_a_stream_with_faults() {
    let (mut host, device) = UnixStream::pair().unwrap();
    device
        .set_read_timeout(Some(Duration::from_millis(1)))
        .unwrap();
    host.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let controller = SimulatedController::spawn(device, ModelConfig::default());
    host.write_all(&frame(0, Command::Hello { version: 1 }))
        .unwrap();
    assert!(matches!(
        read_message(&mut host),
        Ok(ControllerMessage::Reply {
            seq: 0,
            reply: Reply::Hello { .. }
        })
    ));
    controller.fault_next_reply(ReplyFault::CorruptCrc);
    host.write_all(&frame(1, Command::Disarm)).unwrap();
    assert!(matches!(
        read_message(&mut host),
        Err(FrameError::Crc { .. })
    ));
    // The resent request gets the cached reply, intact this time.
    host.write_all(&frame(1, Command::Disarm)).unwrap();
    assert_eq!(
        read_message(&mut host),
        Ok(ControllerMessage::Reply {
            seq: 1,
            reply: Reply::Ok
        })
    );
    let stats = controller.stop().unwrap();
    assert_eq!(stats.requests_executed, 2);
    assert_eq!(stats.replies_replayed, 1);
}
