//! `hexcal bench faults`: the stack check against faults of drawn kinds and sizes
//! (docs/design.md §6b). Each stack is rendered twice from one scene and one noise draw,
//! clean and with its fault, and both are decoded; a faulty stack must end refused with its
//! cause named, or accurate: the error of its patch means (16 × 16 px, about a circle's
//! pixels, so a bias counts as it does at a circle centre) at most 1.5× the clean stack's.

use super::check::draw;
use crate::phase::check::StackFault;
use crate::phase::{DecodedStack, Decoder, FrameRef};
use crate::sim::fringe::{Disturbance, Renderer, Truth};
use hexcal_vision::stats::median;
use rand::{Rng, SeedableRng};
use std::f64::consts::TAU;

/// A faulty stack's error may be this many times the clean stack's.
const ACCURATE: f64 = 1.5;

/// Patch side (px) and the valid interior pixels a patch needs.
const PATCH: usize = 16;
const PATCH_PIXELS: usize = 64;

/// The kinds of fault drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FaultKind {
    /// A projector shows another frame's pattern in some frames of a group.
    Lag,
    /// The board drifts over the sequence.
    Drift,
    /// The board jolts at a frame.
    Jolt,
    /// The room light flickers.
    Flicker,
    /// The room light steps at a frame.
    AmbientStep,
    /// A camera gain that may clip.
    Gain,
}

impl FaultKind {
    /// Every kind, in the order they are drawn and listed.
    pub const ALL: [FaultKind; 6] = [
        FaultKind::Lag,
        FaultKind::Drift,
        FaultKind::Jolt,
        FaultKind::Flicker,
        FaultKind::AmbientStep,
        FaultKind::Gain,
    ];

    /// Its name in the bench's table.
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::Lag => "lag",
            FaultKind::Drift => "drift",
            FaultKind::Jolt => "jolt",
            FaultKind::Flicker => "flicker",
            FaultKind::AmbientStep => "ambient step",
            FaultKind::Gain => "gain",
        }
    }
}

/// One faulty stack's outcome.
#[derive(Clone, Debug)]
pub struct FaultCase {
    /// The fault's kind.
    pub kind: FaultKind,
    /// The scene and the fault with its size.
    pub label: String,
    /// Whether the check refused the stack.
    pub refused: bool,
    /// Whether a refusal names a cause of the fault's kind.
    pub right_cause: bool,
    /// Worst patch-mean error ratio to the clean stack over projectors and directions.
    pub ratio: f64,
    /// The verdict's faults and notes.
    pub verdict: String,
    /// Per projector and direction, the patch-mean error RMS (faulty/clean) and valid pixels.
    pub detail: String,
}

impl FaultCase {
    /// Used although its error is beyond 1.5× the clean stack's.
    pub fn silent(&self) -> bool {
        !self.refused && self.ratio > ACCURATE
    }
}

/// Decode `stacks` stacks of scenes and faults drawn from `seed`, from stack `from` on (the
/// ones before drawn, not decoded: one stack can be looked at again alone).
pub fn bench_faults(stacks: usize, seed: u64, from: usize) -> Vec<FaultCase> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    (0..from + stacks)
        .filter_map(|i| {
            let (scene, seq, label) = draw(&mut rng, i as u64);
            let kind = FaultKind::ALL[rng.random_range(0..FaultKind::ALL.len())];
            let (fault, what) = fault(&mut rng, kind, &seq, scene.projectors.len());
            if i < from {
                return None;
            }
            let mut renderer = Renderer::new(&scene, &seq);
            let size = (scene.width, scene.height);
            let none = |_| Disturbance::none(seq.projectors().len());
            let clean = decode(&mut renderer, &seq, size, none);
            let faulty = decode(&mut renderer, &seq, size, &fault);
            let truth = renderer.truth();
            let (ratio, detail) = worst_ratio(&faulty, &clean, &truth, scene.width as usize);
            let v = &faulty.verdict;
            let notes: Vec<String> = v.notes.iter().map(|n| n.describe()).collect();
            Some(FaultCase {
                kind,
                label: format!("{label}; {what}"),
                refused: !v.passed(),
                right_cause: v.faults.iter().any(|f| names(kind, f)),
                ratio,
                verdict: format!("[{}] [{}]", v.summary(), notes.join("; ")),
                detail,
            })
        })
        .collect()
}

/// Whether `f` names a fault of kind `kind`.
fn names(kind: FaultKind, f: &StackFault) -> bool {
    use StackFault::*;
    match kind {
        FaultKind::Lag => matches!(
            f,
            WrongPattern { .. }
                | LagInGroups { .. }
                | FringesInMean { .. }
                | PhaseDisagreement { .. }
                | Unwrapping { .. }
                | Disturbed { .. }
        ),
        FaultKind::Drift | FaultKind::Jolt => matches!(f, Motion { .. } | Jolt { .. }),
        FaultKind::Flicker | FaultKind::AmbientStep => {
            matches!(f, LightChange { .. } | Disturbed { .. })
        }
        FaultKind::Gain => matches!(f, Clipped { .. }),
    }
}

/// A fault of kind `kind` as a per-frame disturbance, with words for it.
fn fault(
    rng: &mut impl Rng,
    kind: FaultKind,
    seq: &crate::pattern::Sequence,
    np: usize,
) -> (Box<dyn Fn(usize) -> Disturbance>, String) {
    let (n, count) = (seq.steps() as usize, seq.frame_count());
    let log_uniform = |rng: &mut dyn rand::RngCore, lo: f64, hi: f64| {
        (lo.ln() + rng.random::<f64>() * (hi / lo).ln()).exp()
    };
    let none = move || Disturbance::none(np);
    match kind {
        FaultKind::Lag => {
            let (p, g) = (rng.random_range(0..np), rng.random_range(0..seq.groups()));
            let frames = rng.random_range(1..=n);
            let first = g * n + rng.random_range(0..=n - frames);
            let offset = [-2i64, -1, 1, 2][rng.random_range(0..4)];
            let f = move |k: usize| {
                let mut d = none();
                if (first..first + frames).contains(&k) {
                    d.shown[p] = Some((k as i64 + offset).clamp(0, count as i64 - 1) as usize);
                }
                d
            };
            let what = format!(
                "projector {p} shows frame k{offset:+} in frames {first}–{}",
                first + frames - 1
            );
            (Box::new(f), what)
        }
        FaultKind::Drift | FaultKind::Jolt => {
            let px = log_uniform(rng, 0.01, 0.5);
            let a = rng.random::<f64>() * TAU;
            let at = rng.random_range(1..count);
            let drift = kind == FaultKind::Drift;
            let f = move |k: usize| {
                let s = match drift {
                    true => px * k as f64 / (count - 1) as f64,
                    false => px * f64::from(u8::from(k >= at)),
                };
                Disturbance {
                    shift: [s * a.cos(), s * a.sin()],
                    ..none()
                }
            };
            let what = match drift {
                true => format!("drift {px:.3} px over the sequence"),
                false => format!("jolt {px:.3} px at frame {at}"),
            };
            (Box::new(f), what)
        }
        FaultKind::Flicker => {
            let amp = log_uniform(rng, 0.005, 0.2);
            let period = rng.random_range(4..=12) as f64;
            let phase = rng.random::<f64>() * TAU;
            let f = move |k: usize| Disturbance {
                ambient: 1.0 + amp * (TAU * k as f64 / period + phase).sin(),
                ..none()
            };
            (
                Box::new(f),
                format!(
                    "ambient flicker ±{:.1} %, period {period} frames",
                    100.0 * amp
                ),
            )
        }
        FaultKind::AmbientStep => {
            let size = log_uniform(rng, 0.02, 0.5) * [-0.6, 1.0][rng.random_range(0..2)];
            let at = rng.random_range(1..count);
            let f = move |k: usize| Disturbance {
                ambient: if k >= at { 1.0 + size } else { 1.0 },
                ..none()
            };
            (
                Box::new(f),
                format!("ambient {:+.1} % from frame {at}", 100.0 * size),
            )
        }
        FaultKind::Gain => {
            let gain = rng.random_range(1.0..2.2);
            let f = move |_: usize| Disturbance { gain, ..none() };
            (Box::new(f), format!("camera gain ×{gain:.2}"))
        }
    }
}

/// Decode the stack `renderer` gives with frame k disturbed as `fault(k)` says.
fn decode(
    renderer: &mut Renderer,
    seq: &crate::pattern::Sequence,
    (w, h): (u32, u32),
    fault: impl Fn(usize) -> Disturbance,
) -> DecodedStack {
    let mut decoder = Decoder::<u8>::new(seq, "bench", w, h, 255.0).expect("a valid frame format");
    for k in 0..seq.frame_count() {
        let frame = renderer.frame_with(k, &fault(k));
        decoder
            .push_frame(k, FrameRef::from(&frame))
            .expect("frames match the sequence");
    }
    decoder.finish().expect("complete stack")
}

/// The worst over projectors and directions of the faulty stack's patch-mean error RMS over
/// the clean stack's, over the patches both decode; each projector's and direction's RMS
/// (faulty/clean) and valid pixels.
fn worst_ratio(
    faulty: &DecodedStack,
    clean: &DecodedStack,
    truth: &Truth,
    width: usize,
) -> (f64, String) {
    let mut worst: f64 = 0.0;
    let mut detail = Vec::new();
    for p in 0..clean.projectors.len() {
        for dir in 0..2 {
            let errors = |d: &DecodedStack| patch_errors(d, truth, p, dir, width);
            let (a, b) = (errors(faulty), errors(clean));
            let (mut sa, mut sb, mut m) = (0.0, 0.0, 0usize);
            for (ea, eb) in a.iter().zip(&b) {
                if let (Some(ea), Some(eb)) = (ea, eb) {
                    (sa, sb, m) = (sa + ea * ea, sb + eb * eb, m + 1);
                }
            }
            if m > 0 && sb > 0.0 {
                worst = worst.max((sa / sb).sqrt());
            }
            let valid = |d: &DecodedStack| {
                d.projectors[p]
                    .valid
                    .as_slice()
                    .iter()
                    .filter(|&&v| v)
                    .count()
            };
            let gross = |d: &DecodedStack| gross_errors(d, truth, p, dir);
            detail.push(format!(
                "p{p} {}: {:.3}/{:.3} px over {m} patches, valid {}/{}, off by > 5 px {}/{}",
                ["u", "v"][dir],
                (sa / m.max(1) as f64).sqrt(),
                (sb / m.max(1) as f64).sqrt(),
                valid(faulty),
                valid(clean),
                gross(faulty),
                gross(clean)
            ));
        }
    }
    (worst, detail.join("; "))
}

/// Valid interior pixels of projector p whose u (`dir` 0) or v is off by more than 5 px (gross: 10σ at the validity floor of N = 3).
fn gross_errors(d: &DecodedStack, truth: &Truth, p: usize, dir: usize) -> usize {
    let maps = &d.projectors[p];
    let (got, want) = match dir {
        0 => (maps.u.as_raw(), &truth.u[p]),
        _ => (maps.v.as_raw(), &truth.v[p]),
    };
    (maps.valid.as_slice().iter().enumerate())
        .filter(|&(i, &ok)| ok && truth.interior[i] && (f64::from(got[i]) - want[i]).abs() > 5.0)
        .count()
}

/// Per 16 × 16 patch, the mean error of projector p's u (`dir` 0) or v over its valid
/// interior pixels, where it has enough of them; as the circle-centre fit does (docs/design.md
/// §7), a pixel grossly off the patch's others (beyond 6 robust standard deviations and
/// 1 px) is left out.
fn patch_errors(
    d: &DecodedStack,
    truth: &Truth,
    p: usize,
    dir: usize,
    w: usize,
) -> Vec<Option<f64>> {
    let maps = &d.projectors[p];
    let (got, want) = match dir {
        0 => (maps.u.as_raw(), &truth.u[p]),
        _ => (maps.v.as_raw(), &truth.v[p]),
    };
    let h = got.len() / w;
    let (pw, ph) = (w / PATCH, h / PATCH);
    let mut errors = vec![Vec::new(); pw * ph];
    for (i, &ok) in maps.valid.as_slice().iter().enumerate() {
        let (x, y) = (i % w / PATCH, i / w / PATCH);
        if ok && truth.interior[i] && x < pw && y < ph {
            errors[y * pw + x].push(f64::from(got[i]) - want[i]);
        }
    }
    errors
        .into_iter()
        .map(|mut e| (e.len() >= PATCH_PIXELS).then(|| robust_mean(&mut e)))
        .collect()
}

/// The mean of `e` without the values beyond 6 robust standard deviations (and 1 px) of its
/// median (reorders it).
fn robust_mean(e: &mut [f64]) -> f64 {
    let m = median(e);
    let mut dev: Vec<f64> = e.iter().map(|v| (v - m).abs()).collect();
    let limit = (6.0 * median(&mut dev) / 0.6745).max(1.0);
    let kept: Vec<f64> = e
        .iter()
        .copied()
        .filter(|v| (v - m).abs() <= limit)
        .collect();
    kept.iter().sum::<f64>() / kept.len() as f64
}
