//! The trigger-controller driver against the simulated firmware over a real pty pair
//! (`serialport::TTYPort::pair()`): the driver on the slave end (a /dev/pts/N path, as a
//! real USB CDC device would be), the firmware model on the master end.

use std::time::Duration;

use hexcal::rig::trigger::{ControllerInfo, TriggerController, TriggerError, TriggerTiming};
use hexcal_firmware_protocol::{ControllerState, ErrorCode, Event, LineConfig, Pacing};
use hexcal_simulator::firmware::{ModelConfig, ReplyFault, SimulatedController};
use rand::{rngs::StdRng, Rng, SeedableRng};
use serialport::{SerialPort, TTYPort};

/// Short enough that the fault tests stay quick, long enough that a loaded 2-core machine
/// does not make a healthy reply late (replies take well under a millisecond here).
const TIMING: TriggerTiming = TriggerTiming {
    reply_timeout: Duration::from_millis(200),
    attempts: 3,
};

/// Generous wait for events that are due within a millisecond.
const EVENT_WAIT: Duration = Duration::from_secs(2);

/// A pty pair with the firmware model serving the master end.
fn pty_with_firmware(config: ModelConfig) -> (TTYPort, SimulatedController) {
    let (mut master, slave) = TTYPort::pair().expect("a pty pair");
    // The firmware's read timeout is its timer resolution.
    master
        .set_timeout(Duration::from_millis(1))
        .expect("setting the firmware end's timeout");
    (slave, SimulatedController::spawn(master, config))
}

fn connect(timing: TriggerTiming) -> (TriggerController, SimulatedController) {
    let (slave, firmware) = pty_with_firmware(ModelConfig::default());
    let controller = TriggerController::from_port(Box::new(slave), timing).expect("handshake");
    (controller, firmware)
}

fn two_lines() -> [LineConfig; 2] {
    [
        LineConfig {
            line: 0,
            delay_us: 0,
            pulse_us: 100,
        },
        LineConfig {
            line: 1,
            delay_us: 50,
            pulse_us: 100,
        },
    ]
}

#[test]
fn handshake_over_a_port_opened_by_path() {
    let (slave, firmware) = pty_with_firmware(ModelConfig::default());
    let path = slave.name().expect("a pty slave has a path");
    assert!(path.starts_with("/dev/"), "{path}");
    let controller = TriggerController::open(&path, 115_200, TIMING).expect("handshake");
    drop(slave); // the port opened by path keeps the pty alive
    assert_eq!(controller.port_name(), path);
    assert_eq!(
        controller.info(),
        ControllerInfo {
            version: 1,
            lines: 8
        }
    );
    assert_eq!(controller.stats().retries, 0);
    assert_eq!(firmware.stats().requests_executed, 1);
}

#[test]
fn opening_a_missing_port_names_it() {
    let err = TriggerController::open("/dev/hexcal-no-such-port", 115_200, TIMING).unwrap_err();
    assert!(matches!(err, TriggerError::Open { .. }), "{err:?}");
    assert!(
        err.to_string().contains("/dev/hexcal-no-such-port"),
        "{err}"
    );
}

#[test]
fn version_mismatch_names_port_and_both_versions() {
    let (slave, _firmware) = pty_with_firmware(ModelConfig {
        version: 2,
        lines: 8,
    });
    let path = slave.name().unwrap();
    let err = TriggerController::from_port(Box::new(slave), TIMING).unwrap_err();
    match &err {
        TriggerError::VersionMismatch {
            port,
            host,
            controller,
        } => {
            assert_eq!(port, &path);
            assert_eq!((*host, *controller), (1, 2));
        }
        other => panic!("expected a version mismatch, got {other:?}"),
    }
    let text = err.to_string();
    assert!(
        text.contains(&path) && text.contains("version 1") && text.contains("version 2"),
        "{text}"
    );
}

#[test]
fn configure_arm_fire_gives_ordered_events() {
    let (mut controller, firmware) = connect(TIMING);
    controller.configure(&two_lines()).unwrap();
    const N: u32 = 20;
    controller.arm(N, Pacing::PerFire).unwrap();
    let mut previous: Option<u64> = None;
    for k in 0..N {
        assert_eq!(controller.fire().unwrap(), k);
        let done = controller.wait_frame_done(EVENT_WAIT).unwrap();
        assert_eq!(done.frame, k);
        if let Some(t) = previous {
            // Frame k cannot trigger before frame k-1's pulses (150 µs) are over.
            assert!(
                done.time_us >= t + 150,
                "frame {k} at {} after {t}",
                done.time_us
            );
        }
        previous = Some(done.time_us);
    }
    // The sequence is over: one more Fire is refused by the firmware.
    let err = controller.fire().unwrap_err();
    assert!(
        matches!(
            err,
            TriggerError::Refused {
                code: ErrorCode::NotArmed,
                ..
            }
        ),
        "{err:?}"
    );
    let stats = controller.stats();
    assert_eq!(
        (stats.events_missed, stats.crc_errors, stats.bad_frames),
        (0, 0, 0)
    );
    assert_eq!(firmware.stats().frames_fired, u64::from(N));
}

#[test]
fn periodic_sequence_keeps_the_period() {
    let (mut controller, firmware) = connect(TIMING);
    controller.configure(&two_lines()).unwrap();
    const PERIOD_US: u32 = 2_000;
    controller
        .arm(
            6,
            Pacing::Periodic {
                period_us: PERIOD_US,
            },
        )
        .unwrap();
    assert_eq!(controller.fire().unwrap(), 0);
    let done: Vec<_> = (0..6)
        .map(|_| controller.wait_frame_done(EVENT_WAIT).unwrap())
        .collect();
    let frames: Vec<u32> = done.iter().map(|d| d.frame).collect();
    assert_eq!(frames, [0, 1, 2, 3, 4, 5]);
    // The controller's clock stamps the scheduled trigger instants: exactly one period apart.
    for pair in done.windows(2) {
        assert_eq!(pair[1].time_us - pair[0].time_us, u64::from(PERIOD_US));
    }
    assert_eq!(firmware.stats().frames_fired, 6);
}

#[test]
fn external_start_triggers_the_sequence() {
    let (mut controller, firmware) = connect(TIMING);
    controller.configure(&two_lines()).unwrap();
    controller
        .arm(3, Pacing::ExternalStart { period_us: 1_000 })
        .unwrap();
    let err = controller.fire().unwrap_err();
    assert!(
        matches!(
            err,
            TriggerError::Refused {
                code: ErrorCode::WrongPacing,
                ..
            }
        ),
        "{err:?}"
    );
    // No edge yet: nothing happens.
    assert!(controller
        .wait_frame_done(Duration::from_millis(50))
        .is_err());
    firmware.external_start();
    let frames: Vec<u32> = (0..3)
        .map(|_| controller.wait_frame_done(EVENT_WAIT).unwrap().frame)
        .collect();
    assert_eq!(frames, [0, 1, 2]);
}

#[test]
fn refusals_name_port_and_reason() {
    let (mut controller, _firmware) = connect(TIMING);
    let port = controller.port_name().to_string();
    let err = controller.fire().unwrap_err();
    assert!(err.to_string().contains(&port), "{err}");
    assert!(
        matches!(
            err,
            TriggerError::Refused {
                request: "Fire",
                code: ErrorCode::NotArmed,
                ..
            }
        ),
        "{err:?}"
    );
    let bad = [LineConfig {
        line: 9,
        delay_us: 0,
        pulse_us: 10,
    }];
    let err = controller.configure(&bad).unwrap_err();
    assert!(
        matches!(
            err,
            TriggerError::Refused {
                code: ErrorCode::BadLine { line: 9 },
                ..
            }
        ),
        "{err:?}"
    );
    assert!(err.to_string().contains("line 9"), "{err}");
    let too_many: Vec<_> = (0..17)
        .map(|line| LineConfig {
            line,
            delay_us: 0,
            pulse_us: 10,
        })
        .collect();
    let err = controller.configure(&too_many).unwrap_err();
    assert!(
        matches!(err, TriggerError::TooManyLines { count: 17, .. }),
        "{err:?}"
    );
}

#[test]
fn corrupted_reply_is_retried() {
    let (mut controller, firmware) = connect(TIMING);
    controller.configure(&two_lines()).unwrap();
    controller.arm(2, Pacing::PerFire).unwrap();
    firmware.fault_next_reply(ReplyFault::CorruptCrc);
    assert_eq!(controller.fire().unwrap(), 0);
    assert_eq!(controller.wait_frame_done(EVENT_WAIT).unwrap().frame, 0);
    let stats = controller.stats();
    assert_eq!(stats.crc_errors, 1);
    assert!(stats.retries >= 1, "{stats:?}");
    let fw = firmware.stats();
    assert!(fw.replies_replayed >= 1, "{fw:?}");
    assert_eq!(fw.frames_fired, 1, "the resent Fire must not fire again");
}

#[test]
fn garbage_between_frames_costs_no_reply() {
    // A long timeout: any retry here would mean a reply was lost to the garbage, not that
    // the machine was slow.
    let timing = TriggerTiming {
        reply_timeout: Duration::from_secs(2),
        attempts: 2,
    };
    let (mut controller, firmware) = connect(timing);
    let mut rng = StdRng::seed_from_u64(6);
    // Before each reply: random bytes (zeros included), a burst longer than any frame,
    // and a truncated copy of a real frame's start.
    firmware.fault_next_reply(ReplyFault::Garbage(
        (0..60).map(|_| rng.random::<u8>()).collect(),
    ));
    firmware.fault_next_reply(ReplyFault::Garbage(vec![0x5A; 700]));
    firmware.fault_next_reply(ReplyFault::Garbage(vec![0x00, 0x03, 0x01, 0x05, 0x09]));
    controller.configure(&two_lines()).unwrap();
    controller.arm(1, Pacing::PerFire).unwrap();
    assert_eq!(controller.fire().unwrap(), 0);
    assert_eq!(controller.wait_frame_done(EVENT_WAIT).unwrap().frame, 0);
    let stats = controller.stats();
    assert_eq!(stats.retries, 0, "{stats:?}");
    assert!(stats.bad_frames + stats.crc_errors >= 3, "{stats:?}");
    assert_eq!(firmware.stats().frames_fired, 1);
}

#[test]
fn lost_reply_is_retried_without_double_fire() {
    let (mut controller, firmware) = connect(TIMING);
    controller.configure(&two_lines()).unwrap();
    controller.arm(3, Pacing::PerFire).unwrap();
    firmware.fault_next_reply(ReplyFault::Drop);
    assert_eq!(controller.fire().unwrap(), 0);
    assert!(controller.stats().retries >= 1);
    assert_eq!(controller.wait_frame_done(EVENT_WAIT).unwrap().frame, 0);
    assert_eq!(controller.fire().unwrap(), 1);
    assert_eq!(controller.wait_frame_done(EVENT_WAIT).unwrap().frame, 1);
    // Exactly one event per frame: nothing else arrives.
    assert!(controller.next_event(Duration::from_millis(50)).is_err());
    let fw = firmware.stats();
    assert_eq!(fw.frames_fired, 2, "{fw:?}");
    assert!(fw.replies_replayed >= 1, "{fw:?}");
}

#[test]
fn silent_controller_times_out_naming_the_port() {
    let timing = TriggerTiming {
        reply_timeout: Duration::from_millis(100),
        attempts: 3,
    };
    let (mut controller, firmware) = connect(timing);
    let port = controller.port_name().to_string();
    firmware.set_silent(true);
    let err = controller.disarm().unwrap_err();
    match &err {
        TriggerError::NoReply {
            port: p,
            request,
            attempts,
            garbled,
            ..
        } => {
            assert_eq!(p, &port);
            // Silence, not garbage.
            assert_eq!((*request, *attempts, *garbled), ("Disarm", 3, 0));
        }
        other => panic!("expected NoReply, got {other:?}"),
    }
    assert!(err.to_string().contains(&port), "{err}");
    assert_eq!(controller.stats().retries, 2);
    // Back to life: the link recovers with the next request.
    firmware.set_silent(false);
    controller.disarm().unwrap();
}

#[test]
fn lost_events_are_counted() {
    let (mut controller, firmware) = connect(TIMING);
    controller.configure(&two_lines()).unwrap();
    controller.arm(2, Pacing::PerFire).unwrap();
    firmware.drop_next_events(1);
    assert_eq!(controller.fire().unwrap(), 0);
    // Frame 0's event is lost; after frame 1's pulses the next event is frame 1's.
    std::thread::sleep(Duration::from_millis(5));
    assert_eq!(controller.fire().unwrap(), 1);
    assert_eq!(controller.wait_frame_done(EVENT_WAIT).unwrap().frame, 1);
    assert_eq!(controller.stats().events_missed, 1);
}

#[test]
fn heartbeats_arrive_in_order() {
    let (mut controller, _firmware) = connect(TIMING);
    controller.configure(&two_lines()).unwrap();
    controller.set_heartbeat(Duration::from_millis(5)).unwrap();
    let mut times = Vec::new();
    for _ in 0..3 {
        match controller.next_event(EVENT_WAIT).unwrap() {
            Event::Heartbeat(beat) => {
                assert_eq!(beat.state, ControllerState::Configured);
                times.push(beat.time_us);
            }
            other => panic!("expected a heartbeat, got {other:?}"),
        }
    }
    assert!(times.windows(2).all(|w| w[1] - w[0] == 5_000), "{times:?}");
    assert_eq!(
        controller.last_heartbeat().map(|b| b.time_us),
        times.last().copied()
    );
    controller.set_heartbeat(Duration::ZERO).unwrap();
}
