//! The self-tests through the capture engine on the tiny simulated rig (two cameras facing
//! each other across the board, projector p0 lighting the front and p1 the back), against
//! the simulated displays' faults and truths.

use super::exposure::{check_exposure, ExposurePlan};
use super::sync::{check_sync, SyncPlan};
use crate::capture::Session;
use crate::rig::fixture::{tiny, SimRig};
use std::time::Duration;

/// A started session on `rig`, its board at pose 0; and the rig's pattern period.
fn session(rig: SimRig) -> (Session, Duration) {
    let rig = rig.parse().unwrap();
    let opened = crate::rig::open(&rig).unwrap();
    opened.world.as_ref().unwrap().place(0);
    let s = Session::start(opened.devices, &opened.sequence).unwrap();
    (
        s,
        Duration::from_secs_f64(1e-3 * rig.timing.frame_period_ms),
    )
}

#[test]
fn sync_names_lag_repeats_and_drops_per_camera_and_projector() {
    let lag = 27.0;
    let refresh_ms = 1e3 / 60.0;
    let rig = tiny()
        .edit("p0", |p| {
            p.with(&format!(
                "sim_display = {{ lag_ms = {lag}, repeat_every = 5, refresh_hz = 60.0 }}"
            ))
        })
        .edit("p1", |p| p.with("sim_display = { drop_every = 9 }"));
    let (mut s, period) = session(rig);
    let plan = SyncPlan::new(s.timing(), period, false, Some(Duration::from_millis(100)));
    let report = check_sync(&mut s, &plan).unwrap();
    s.finish().unwrap();
    println!("{report}");
    let pair = |c: &str, p: &str| {
        (report.pairs.iter())
            .find(|x| x.camera == c && x.projector == p)
            .unwrap()
    };
    // Each camera sees only the projector on its side.
    assert!(!pair("front", "p1").seen && !pair("back", "p0").seen);
    // p0: the light comes `lag` late, within one wait step (11.1 ms); 12 frames, every 5th
    // show one refresh later still; none dropped.
    let step = 100.0 / 9.0;
    let p0 = pair("front", "p0");
    assert!(p0.seen);
    assert!(
        p0.latency_ms >= lag && p0.latency_ms <= lag + step + 5.0,
        "{p0:?}"
    );
    assert_eq!(p0.latency_frames, (p0.latency_ms / 20.0).ceil() as u32);
    assert!(p0.dropped.is_empty(), "{p0:?}");
    assert!((2..=3).contains(&p0.repeated.len()), "{p0:?}");
    assert!(p0.worst_ms >= lag + refresh_ms, "{p0:?}");
    // The run waits 0 ms: every p0 frame would show the one before.
    assert_eq!(p0.late_at_run, (0..12).collect::<Vec<_>>());
    // p1: no lag, no repeat; one or two of its 12 coded frames dropped (every 9th show).
    let p1 = pair("back", "p1");
    assert!(p1.seen && p1.repeated.is_empty(), "{p1:?}");
    assert!((1..=2).contains(&p1.dropped.len()), "{p1:?}");
    assert!(p1.latency_ms < step, "{p1:?}");
    assert_eq!(p1.late_at_run, p1.dropped);
    // Safe: the latest light seen (a repeat), to the whole millisecond.
    assert!(!report.passed());
    assert!(report.safe_settle_ms >= lag + refresh_ms, "{report:?}");
    assert!(report.safe_settle_ms <= p0.worst_ms + 1.0, "{report:?}");
    let text = report.to_string();
    assert!(text.contains("front × p0: latency"), "{text}");
    assert!(text.contains("sync FAILED"), "{text}");
}

#[test]
fn short_sync_passes_a_lag_the_settle_time_covers() {
    let rig = tiny()
        .with("timing.settle_ms = 8.0")
        .edit("p0", |p| p.with("sim_display = { lag_ms = 5.0 }"));
    let (mut s, period) = session(rig);
    let plan = SyncPlan::new(s.timing(), period, true, None);
    assert!(plan.waits.contains(&Duration::from_millis(8)));
    let report = check_sync(&mut s, &plan).unwrap();
    s.finish().unwrap();
    println!("{report}");
    assert!(report.passed(), "{report}");
    let p0 = (report.pairs.iter())
        .find(|x| x.camera == "front" && x.projector == "p0")
        .unwrap();
    assert!(p0.latency_ms >= 5.0 && p0.latency_ms < 20.0, "{p0:?}");
    assert!(p0.dropped.is_empty() && p0.late_at_run.is_empty());
    assert!(report.to_string().contains("sync OK"));
}

#[test]
fn exposure_converges_and_recovers_gamma_and_a_clipping_projector_is_warned() {
    // p0 uncorrected gamma 2.2 (the rig's default); p1's light stops growing above level 200.
    let rig = tiny().edit("p1", |p| p.with("sim_display = { clip_level = 200 }"));
    let (mut s, period) = session(rig);
    let plan = |white_level, max_exposure_us| ExposurePlan {
        white_level,
        max_exposure_us,
        max_gain_db: 24.0,
        wait: Duration::ZERO,
        set_exposure: true,
    };
    assert_eq!(period, Duration::from_millis(20));
    // Half scale by exposure alone.
    let half = check_exposure(&mut s, &plan(0.5, 20_000.0)).unwrap();
    println!("{half}");
    for c in &half.cameras {
        assert!(c.converged && (c.white - 0.5).abs() <= 0.03, "{c:?}");
        assert!(c.exposure_us <= 20_000.0 && c.gain_db == 0.0, "{c:?}");
    }
    assert_eq!(s.exposures()[0], (half.cameras[0].exposure_us, 0.0));
    // Gamma from the response at this exposure, within 4σ of its noise. (With gain added
    // below, γ is 0.005 low — 6σ: the simulated camera scales an already rounded frame, and
    // rounding twice moves the level means by up to ±0.09 DN against their 0.02 DN noise;
    // design §11b.)
    let g = (half.responses.iter())
        .find(|x| x.projector == "p0" && x.seen)
        .unwrap();
    assert!(g.gamma_sigma > 0.0 && g.gamma_sigma < 0.05, "{g:?}");
    assert!((g.gamma - 2.2).abs() <= 4.0 * g.gamma_sigma, "{g:?}");
    // 0.8 with at most 4 ms of exposure: the rest is gain.
    let report = check_exposure(&mut s, &plan(0.8, 4_000.0)).unwrap();
    s.finish().unwrap();
    println!("{report}");
    for c in &report.cameras {
        assert!(c.converged && (c.white - 0.8).abs() <= 0.03, "{c:?}");
        assert!(c.exposure_us == 4_000.0 && c.gain_db > 0.0, "{c:?}");
    }
    let r = |c: &str, p: &str| {
        (report.responses.iter())
            .find(|x| x.camera == c && x.projector == p)
            .unwrap()
    };
    assert!(!r("front", "p1").seen && !r("back", "p0").seen);
    let p0 = r("front", "p0");
    assert!(!p0.clips && !p0.non_monotone, "{p0:?}");
    let p1 = r("back", "p1");
    assert!(p1.clips, "{p1:?}");
    let warnings = report.warnings();
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(
        warnings[0].starts_with("back × p1: the response clips"),
        "{warnings:?}"
    );
}
