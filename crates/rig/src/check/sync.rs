//! The sync self-test (docs/design.md §11b): does every camera frame show the slide it was
//! triggered for?
//!
//! Takes a started [`Session`] and a [`SyncPlan`]; gives a [`SyncReport`]. Projector by
//! projector (the others black), it first shows [`CODES`] flat levels with a long wait as
//! references, then a frame-coded sequence — frame k a flat level coding k mod 6, each
//! differing from the one before — and after every frame takes each camera's frame at
//! several waits, the run's own wait among them. A camera frame is decoded to the nearest
//! reference level over the pixels the projector lights, so it names the frame it shows:
//! this one, or one that many before. Per camera and projector: the light's latency (ms
//! and frames), frames never shown (dropped), frames later than the rest (repeated), the
//! frames the run's wait would capture too early, and the `settle_ms` that is safe.

use super::{lit_mask, mean_over, samples, CheckError};
use crate::capture::{ProbeTake, Session};
use crate::rig::{CaptureTiming, Slide};
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Code levels shown in the frame-coded sequence: frame k shows level `CODES[k % 6]`.
/// Consecutive frames differ, and the last reference (level 5) differs from frame 0's.
pub const CODES: [usize; 6] = [3, 1, 4, 2, 0, 5];

/// How often references are shown again when they do not come out in order.
const REFERENCE_TRIES: u32 = 5;

/// What the sync test does.
#[derive(Clone, Debug, PartialEq)]
pub struct SyncPlan {
    /// Coded frames per projector.
    pub frames: usize,
    /// Waits after each frame is shown at which every camera takes a frame (ascending;
    /// the run's wait among them).
    pub waits: Vec<Duration>,
    /// The run's wait: the slowest projector's `latency_ms` plus `settle_ms`.
    pub run_wait: Duration,
    /// The slowest projector's `latency_ms`.
    pub latency: Duration,
    /// The rig's pattern period `frame_period_ms`.
    pub frame_period: Duration,
}

impl SyncPlan {
    /// The plan for a rig of `timing` and pattern period `frame_period`: the full test
    /// (12 frames, 10 waits from 0 to `max_wait`) or the short one a run starts with
    /// (6 frames, 3 waits). `max_wait` defaults to the run's wait plus
    /// max(4 frame periods, 100 ms).
    pub fn new(
        timing: &CaptureTiming,
        frame_period: Duration,
        short: bool,
        max_wait: Option<Duration>,
    ) -> SyncPlan {
        let latency = timing.latency.iter().max().copied().unwrap_or_default();
        let run_wait = latency + timing.settle;
        let longest = max_wait
            .unwrap_or_else(|| run_wait + (4 * frame_period).max(Duration::from_millis(100)))
            .max(run_wait);
        let steps: u32 = if short { 2 } else { 9 };
        let mut waits: Vec<Duration> = (0..=steps).map(|i| longest * i / steps).collect();
        waits.push(run_wait);
        waits.sort();
        waits.dedup();
        if short {
            waits.retain(|w| *w == run_wait || *w >= run_wait.max(longest / 2));
        }
        SyncPlan {
            frames: if short { 6 } else { 12 },
            waits,
            run_wait,
            latency,
            frame_period,
        }
    }

    fn longest(&self) -> Duration {
        self.waits.last().copied().unwrap_or_default()
    }
}

/// What one camera saw of one projector.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SyncPair {
    /// The camera.
    pub camera: String,
    /// The projector.
    pub projector: String,
    /// Whether the projector lights any of the camera's view (else nothing below is
    /// measured).
    pub seen: bool,
    /// Median time from show to the slide seen (ms; an upper bound within the wait
    /// resolution).
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub latency_ms: f64,
    /// The latency in the rig's pattern periods (rounded up).
    pub latency_frames: u32,
    /// The latest any frame was first seen (ms; upper bound).
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub worst_ms: f64,
    /// Frames never seen within the longest wait (the display dropped them).
    pub dropped: Vec<usize>,
    /// Frames seen later than the median frame (the display repeated the one before).
    pub repeated: Vec<usize>,
    /// Frames that, at the run's wait, still showed an earlier slide (or a mix).
    pub late_at_run: Vec<usize>,
}

/// The sync test's result.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SyncReport {
    /// Every camera × projector pair, camera-major.
    pub pairs: Vec<SyncPair>,
    /// The waits used (ms).
    pub waits_ms: Vec<f64>,
    /// The run's wait now (ms): latency plus settle.
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub run_wait_ms: f64,
    /// The rig's `settle_ms` now.
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub settle_ms: f64,
    /// The `settle_ms` at which every frame seen is seen at the run's wait.
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub safe_settle_ms: f64,
    /// The rig's pattern period (ms).
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub frame_period_ms: f64,
}

impl SyncReport {
    /// Whether a capture with the rig's timing sees every frame's own slide: nothing
    /// dropped, nothing late at the run's wait.
    pub fn passed(&self) -> bool {
        self.pairs
            .iter()
            .all(|p| p.dropped.is_empty() && p.late_at_run.is_empty())
    }
}

fn ms(d: Duration) -> f64 {
    1e3 * d.as_secs_f64()
}

/// Run the sync test of `plan` on every projector of `session`.
pub fn check_sync(session: &mut Session, plan: &SyncPlan) -> Result<SyncReport, CheckError> {
    let projectors = session.projector_names();
    if projectors.is_empty() {
        return Err(CheckError::NoProjector);
    }
    let cameras = session.camera_names();
    let mut pairs = Vec::new();
    let mut by_projector = Vec::new();
    for (p, name) in projectors.iter().enumerate() {
        let gamma = session.sequence().projectors()[p]
            .response
            .effective_gamma();
        let levels = code_levels(gamma);
        let refs = references(session, p, name, &levels, plan.longest())?;
        let seen = coded(session, p, &levels, &refs, plan)?;
        by_projector.push(seen);
    }
    for (c, camera) in cameras.iter().enumerate() {
        for (p, projector) in projectors.iter().enumerate() {
            pairs.push(analyse(
                camera,
                projector,
                by_projector[p][c].as_ref(),
                plan,
            ));
        }
    }
    let worst = (pairs.iter().filter(|p| p.seen))
        .map(|p| p.worst_ms)
        .fold(0.0, f64::max);
    let settle = ms(plan.run_wait - plan.latency);
    Ok(SyncReport {
        pairs,
        waits_ms: plan.waits.iter().map(|w| ms(*w)).collect(),
        run_wait_ms: ms(plan.run_wait),
        settle_ms: settle,
        safe_settle_ms: (worst - ms(plan.latency)).max(0.0).ceil(),
        frame_period_ms: ms(plan.frame_period),
    })
}

/// The intended levels of the six codes: evenly spaced in light for a projector of
/// effective gamma `gamma`.
fn code_levels(gamma: f64) -> [u8; 6] {
    std::array::from_fn(|i| (255.0 * (i as f64 / 5.0).powf(1.0 / gamma)).round() as u8)
}

/// Slide sets with projector `p` showing `slide` and every other one black.
fn alone(session: &Session, p: usize, slide: Slide) -> Vec<Slide> {
    (0..session.projector_names().len())
        .map(|q| if q == p { slide } else { Slide::Black })
        .collect()
}

/// Per camera: the lit mask and the mean of each code's reference level, or `None` when
/// the projector does not reach the camera.
type References = Vec<Option<(Vec<bool>, [f64; 6])>>;

/// Show the six levels in order with the longest wait and measure them; again when a
/// camera that sees the projector does not see them come out brighter level by level (a
/// slide was dropped).
fn references(
    session: &mut Session,
    p: usize,
    name: &str,
    levels: &[u8; 6],
    wait: Duration,
) -> Result<References, CheckError> {
    let slides: Vec<Vec<Slide>> = (levels.iter())
        .map(|&l| alone(session, p, Slide::Level(l)))
        .collect();
    for _ in 0..REFERENCE_TRIES {
        let mut frames: Vec<Vec<Vec<f32>>> = Vec::new();
        let mut full = 0.0f32;
        session.probe(&slides, &[wait], &mut |t: ProbeTake| {
            let mut per_camera = Vec::new();
            for f in &t.frames {
                let (v, fs) = samples(f);
                full = fs;
                per_camera.push(v);
            }
            frames.push(per_camera);
            Ok(())
        })?;
        let refs: References = (0..frames.first().map_or(0, Vec::len))
            .map(|c| {
                let mask = lit_mask(&frames[0][c], &frames[5][c], 0.05 * full)?;
                let means = std::array::from_fn(|i| mean_over(&frames[i][c], &mask));
                Some((mask, means))
            })
            .collect();
        let ordered = refs.iter().flatten().all(|(_, m)| {
            let step = 0.03 * (m[5] - m[0]);
            m.windows(2).all(|w| w[1] - w[0] > step)
        });
        if ordered {
            return Ok(refs);
        }
    }
    Err(CheckError::Unstable {
        projector: name.to_string(),
        wait_ms: ms(wait),
        tries: REFERENCE_TRIES,
    })
}

/// What one camera saw of the coded frames: per frame, per wait, the time of the take and
/// how many frames behind the slide it showed was (`None`: a mix of two).
type Seen = Vec<Vec<(Duration, Option<usize>)>>;

/// Show the coded frames on projector `p` and decode every camera's takes.
fn coded(
    session: &mut Session,
    p: usize,
    levels: &[u8; 6],
    refs: &References,
    plan: &SyncPlan,
) -> Result<Vec<Option<Seen>>, CheckError> {
    let slides: Vec<Vec<Slide>> = (0..plan.frames)
        .map(|k| alone(session, p, Slide::Level(levels[CODES[k % 6]])))
        .collect();
    let mut seen: Vec<Option<Seen>> = refs
        .iter()
        .map(|r| r.as_ref().map(|_| vec![Vec::new(); plan.frames]))
        .collect();
    session.probe(&slides, &plan.waits, &mut |t: ProbeTake| {
        for (c, f) in t.frames.iter().enumerate() {
            if let (Some((mask, means)), Some(Some(s))) = (&refs[c], seen.get_mut(c)) {
                let m = mean_over(&samples(f).0, mask);
                s[t.slide].push((t.after, behind(t.slide, decode(m, means))));
            }
        }
        Ok(())
    })?;
    Ok(seen)
}

/// The code whose reference mean is nearest `m`; `None` when `m` is nearer the middle
/// between two (a frame exposed across a change).
fn decode(m: f64, means: &[f64; 6]) -> Option<usize> {
    let mut sorted = *means;
    sorted.sort_by(f64::total_cmp);
    let spacing = sorted
        .windows(2)
        .map(|w| w[1] - w[0])
        .fold(f64::MAX, f64::min);
    let (code, d) = (means.iter().enumerate())
        .map(|(i, r)| (i, (m - r).abs()))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    (d < 0.3 * spacing).then_some(code)
}

/// How many frames before frame k the frame of `code` was (the references end on code
/// 5, "frame −1"); `None` for no code or one not among the last six frames.
fn behind(k: usize, code: Option<usize>) -> Option<usize> {
    let code = code?;
    (0..6).find(|&d| match k.checked_sub(d) {
        Some(j) => CODES[j % 6] == code,
        None => d == k + 1 && code == 5,
    })
}

/// One camera × projector pair's figures from what the camera saw.
fn analyse(camera: &str, projector: &str, seen: Option<&Seen>, plan: &SyncPlan) -> SyncPair {
    let mut pair = SyncPair {
        camera: camera.to_string(),
        projector: projector.to_string(),
        seen: seen.is_some(),
        latency_ms: 0.0,
        latency_frames: 0,
        worst_ms: 0.0,
        dropped: Vec::new(),
        repeated: Vec::new(),
        late_at_run: Vec::new(),
    };
    let Some(seen) = seen else {
        return pair;
    };
    let run = plan.waits.iter().position(|w| *w == plan.run_wait);
    // Per frame: the index of the first wait at which its own slide shows.
    let first: Vec<Option<usize>> = (seen.iter())
        .map(|takes| takes.iter().position(|(_, b)| *b == Some(0)))
        .collect();
    let mut on_time: Vec<(usize, f64)> = Vec::new();
    for (k, j) in first.iter().enumerate() {
        match j {
            None => pair.dropped.push(k),
            Some(j) => on_time.push((*j, ms(seen[k][*j].0))),
        }
        if j.is_none_or(|j| run.is_some_and(|r| j > r)) {
            pair.late_at_run.push(k);
        }
    }
    if on_time.is_empty() {
        return pair;
    }
    let mut index: Vec<usize> = on_time.iter().map(|(j, _)| *j).collect();
    index.sort_unstable();
    let typical = index[index.len() / 2];
    let mut times: Vec<f64> = on_time.iter().map(|(_, t)| *t).collect();
    times.sort_by(f64::total_cmp);
    pair.latency_ms = times[times.len() / 2];
    pair.worst_ms = times[times.len() - 1];
    pair.latency_frames = (pair.latency_ms / ms(plan.frame_period)).ceil() as u32;
    pair.repeated = (first.iter().enumerate())
        .filter(|(_, j)| j.is_some_and(|j| j > typical))
        .map(|(k, _)| k)
        .collect();
    pair
}

impl std::fmt::Display for SyncReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (first, last) = (self.waits_ms.first(), self.waits_ms.last());
        writeln!(
            f,
            "sync: waits {:.0}–{:.0} ms after each slide; the run waits {:.0} ms \
             (projector latency_ms + settle_ms {:.0})",
            first.unwrap_or(&0.0),
            last.unwrap_or(&0.0),
            self.run_wait_ms,
            self.settle_ms
        )?;
        for p in &self.pairs {
            write!(f, "  {} × {}: ", p.camera, p.projector)?;
            if !p.seen {
                writeln!(f, "not lit in this camera's view")?;
                continue;
            }
            write!(
                f,
                "latency {:.0} ms ({} frame{} of {:.0} ms), worst {:.0} ms",
                p.latency_ms,
                p.latency_frames,
                if p.latency_frames == 1 { "" } else { "s" },
                self.frame_period_ms,
                p.worst_ms
            )?;
            for (what, frames) in [
                ("dropped", &p.dropped),
                ("repeated", &p.repeated),
                ("early at the run's wait", &p.late_at_run),
            ] {
                if !frames.is_empty() {
                    write!(f, "; {what}: frames {frames:?}")?;
                }
            }
            writeln!(f)?;
        }
        let dropped = self.pairs.iter().any(|p| !p.dropped.is_empty());
        let late = self.pairs.iter().any(|p| !p.late_at_run.is_empty());
        match (dropped, late) {
            (false, false) => writeln!(
                f,
                "sync OK: every frame shows its own slide at the run's wait (safe settle_ms: {:.0}, now {:.0})",
                self.safe_settle_ms, self.settle_ms
            ),
            (_, true) if self.safe_settle_ms > self.settle_ms => writeln!(
                f,
                "sync FAILED: frames would show an earlier slide — set settle_ms = {:.0} \
                 (now {:.0}){}",
                self.safe_settle_ms,
                self.settle_ms,
                if dropped { "; a projector drops frames: check its display mode and cable" } else { "" }
            ),
            _ => writeln!(
                f,
                "sync FAILED: a projector drops frames (no wait shows them): check its display \
                 mode, refresh rate and cable"
            ),
        }
    }
}
