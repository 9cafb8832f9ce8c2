//! Exposure for structured light (docs/design.md §11b): each camera's exposure (then gain)
//! for a set white level, and each projector's response through each camera.
//!
//! Takes a started [`Session`] and an [`ExposurePlan`]; gives an [`ExposureReport`]. With
//! every projector white, each camera's exposure is scaled until the brightest board white
//! (the 99th percentile of the pixels the projectors light) sits at the plan's fraction of
//! full scale; past the longest exposure that fits a pattern, gain makes up the rest. The
//! setting is then the session's configured one. Then projector by projector (the others
//! black), a few flat levels are shown, each taken twice: the mean over the lit pixels
//! gives the response (black level, gamma fitted in log–log, clipping), the two takes its
//! noise, from which every threshold derives.

use super::{lit_mask, mean_over, samples, CheckError};
use crate::capture::{ProbeTake, Session};
use crate::rig::Slide;
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// The flat levels of the response measurement.
pub const RESPONSE_LEVELS: [u8; 9] = [0, 32, 64, 96, 128, 160, 192, 224, 255];

/// Where the brightest white may end from the target (fraction of full scale).
const TOLERANCE: f64 = 0.03;
/// Most exposure settings tried per camera.
const MAX_ROUNDS: usize = 8;
/// Levels closer to black than this (DN) are left out of the gamma fit.
const QUANTA_ABOVE_BLACK: f64 = 5.0;
/// The shortest exposure set (µs).
const MIN_EXPOSURE_US: f64 = 10.0;

/// What the exposure check does.
#[derive(Clone, Debug, PartialEq)]
pub struct ExposurePlan {
    /// The brightest board white's target, as a fraction of full scale.
    pub white_level: f64,
    /// The longest exposure (µs): a pattern's display time after settling.
    pub max_exposure_us: f64,
    /// The most gain (dB).
    pub max_gain_db: f64,
    /// Wait after a slide is shown before a frame is taken.
    pub wait: Duration,
    /// Whether to set the exposure (else the configured one is kept and only the response
    /// is measured).
    pub set_exposure: bool,
}

/// One camera's exposure.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraExposure {
    /// The camera.
    pub camera: String,
    /// Exposure set (µs).
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub exposure_us: f64,
    /// Gain set (dB).
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub gain_db: f64,
    /// The brightest board white reached, as a fraction of full scale.
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub white: f64,
    /// Whether it is within tolerance of the target.
    pub converged: bool,
    /// Settings tried.
    pub rounds: usize,
}

/// One projector's response through one camera.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Response {
    /// The camera.
    pub camera: String,
    /// The projector.
    pub projector: String,
    /// Whether the projector lights any of the camera's view (else nothing is measured).
    pub seen: bool,
    /// Intended levels shown.
    pub levels: Vec<u8>,
    /// Mean camera value over the lit pixels at each level (DN).
    pub mean_dn: Vec<f64>,
    /// Noise of one mean (DN, 1σ), from the two takes.
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub sigma_dn: f64,
    /// The level-0 mean as a fraction of the level-255 mean (projector black and ambient).
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub black_ratio: f64,
    /// Gamma fitted to the normalised response (light ∝ level^γ); NaN when not measurable.
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub gamma: f64,
    /// Its 1σ uncertainty from the noise.
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub gamma_sigma: f64,
    /// Fraction of lit pixels at full scale at level 255.
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub saturated: f64,
    /// Whether some level is darker than the one below it beyond the noise.
    pub non_monotone: bool,
    /// Whether the top levels give no more light (the projector or camera clips).
    pub clips: bool,
}

/// The exposure check's result.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExposureReport {
    /// The target white level.
    #[serde(deserialize_with = "super::f64_or_nan")]
    pub white_level: f64,
    /// Per camera, its exposure (as configured when not set).
    pub cameras: Vec<CameraExposure>,
    /// Per camera × projector, camera-major.
    pub responses: Vec<Response>,
}

impl ExposureReport {
    /// One line per problem that matters: a camera short of its white level, a response
    /// that is non-monotone or clips.
    pub fn warnings(&self) -> Vec<String> {
        let mut out = Vec::new();
        for c in self.cameras.iter().filter(|c| !c.converged) {
            out.push(format!(
                "{}: the brightest board white reaches {:.2} of full scale, not {:.2} \
                 (exposure {:.0} µs, gain {:.1} dB)",
                c.camera, c.white, self.white_level, c.exposure_us, c.gain_db
            ));
        }
        for r in self.responses.iter().filter(|r| r.seen) {
            if r.non_monotone {
                out.push(format!(
                    "{} × {}: the response is not monotone (means {:?} DN at levels {:?}): \
                     check the projector's picture settings",
                    r.camera,
                    r.projector,
                    rounded(&r.mean_dn),
                    r.levels
                ));
            }
            if r.clips {
                out.push(format!(
                    "{} × {}: the response clips at the top ({:.1} % of lit pixels at full \
                     scale; levels {:?} give {:?} DN): lower the projector's contrast or the \
                     camera's exposure",
                    r.camera,
                    r.projector,
                    100.0 * r.saturated,
                    &r.levels[r.levels.len() - 2..],
                    rounded(&r.mean_dn[r.mean_dn.len() - 2..])
                ));
            }
        }
        out
    }
}

fn rounded(v: &[f64]) -> Vec<f64> {
    v.iter().map(|x| (10.0 * x).round() / 10.0).collect()
}

/// Set the exposures (when the plan says so) and measure every response.
pub fn check_exposure(
    session: &mut Session,
    plan: &ExposurePlan,
) -> Result<ExposureReport, CheckError> {
    let projectors = session.projector_names();
    if projectors.is_empty() {
        return Err(CheckError::NoProjector);
    }
    let cameras = match plan.set_exposure {
        true => set_exposures(session, plan)?,
        false => {
            let (whites, _) = whites(session, plan, None)?;
            (session.camera_names().into_iter().zip(session.exposures()))
                .zip(whites)
                .map(|((camera, (e, g)), white)| CameraExposure {
                    camera,
                    exposure_us: e,
                    gain_db: g,
                    white,
                    converged: (white - plan.white_level).abs() <= TOLERANCE,
                    rounds: 0,
                })
                .collect()
        }
    };
    let mut responses = vec![Vec::new(); cameras.len()];
    for (p, projector) in projectors.iter().enumerate() {
        for (c, r) in measure_response(session, plan, p, projector)?
            .into_iter()
            .enumerate()
        {
            responses[c].push(r);
        }
    }
    Ok(ExposureReport {
        white_level: plan.white_level,
        cameras,
        responses: responses.into_iter().flatten().collect(),
    })
}

/// Per camera, the pixels any projector lights (from a black and a white frame).
type Masks = Vec<Option<Vec<bool>>>;

/// Per camera, the brightest board white as a fraction of full scale with every projector
/// white, and the masks it was taken over (found from a black and a white frame when not
/// given).
fn whites(
    session: &mut Session,
    plan: &ExposurePlan,
    masks: Option<Masks>,
) -> Result<(Vec<f64>, Masks), CheckError> {
    let n = session.projector_names().len();
    let mut slides = vec![vec![Slide::White; n]];
    if masks.is_none() {
        slides.insert(0, vec![Slide::Black; n]);
    }
    let mut frames: Vec<Vec<(Vec<f32>, f32)>> = Vec::new();
    session.probe(&slides, &[plan.wait], &mut |t: ProbeTake| {
        frames.push(t.frames.iter().map(samples).collect());
        Ok(())
    })?;
    let white = frames.pop().unwrap_or_default();
    let masks = masks.unwrap_or_else(|| {
        let black = frames.pop().unwrap_or_default();
        (black.iter().zip(&white))
            .map(|((b, full), (w, _))| lit_mask(b, w, 0.02 * full))
            .collect()
    });
    let levels = (white.iter().zip(&masks))
        .map(|((v, full), m)| {
            let mut lit: Vec<f32> = match m {
                Some(m) => v
                    .iter()
                    .zip(m)
                    .filter(|(_, &k)| k)
                    .map(|(x, _)| *x)
                    .collect(),
                None => v.clone(),
            };
            let k = ((0.99 * lit.len() as f64) as usize).min(lit.len().saturating_sub(1));
            match lit.is_empty() {
                true => 0.0,
                false => f64::from(*lit.select_nth_unstable_by(k, f32::total_cmp).1 / full),
            }
        })
        .collect();
    Ok((levels, masks))
}

/// Scale each camera's exposure until its brightest white sits at the target; past the
/// longest exposure, gain. The result becomes the session's configured setting.
fn set_exposures(
    session: &mut Session,
    plan: &ExposurePlan,
) -> Result<Vec<CameraExposure>, CheckError> {
    let names = session.camera_names();
    let mut now = session.exposures();
    let mut done = vec![false; names.len()];
    let mut reached = vec![0.0; names.len()];
    let mut rounds = vec![0; names.len()];
    let mut masks = None;
    for _ in 0..MAX_ROUNDS {
        let (white, m) = whites(session, plan, masks.take())?;
        masks = Some(m);
        for c in 0..names.len() {
            if done[c] {
                continue;
            }
            rounds[c] += 1;
            reached[c] = white[c];
            if (white[c] - plan.white_level).abs() <= TOLERANCE {
                done[c] = true;
                continue;
            }
            let scale = match white[c] {
                w if w >= 0.99 => 0.5,
                w => (plan.white_level / w.max(0.01)).min(10.0),
            };
            let next = split(now[c], scale, plan);
            if next == now[c] {
                // At a limit: nothing more to do.
                done[c] = true;
            }
            now[c] = next;
        }
        if done.iter().all(|d| *d) {
            break;
        }
        session.set_exposures(&now.iter().map(|s| Some(*s)).collect::<Vec<_>>())?;
    }
    session.configure_exposures(&now)?;
    Ok((names.into_iter().enumerate())
        .map(|(c, camera)| CameraExposure {
            camera,
            exposure_us: now[c].0,
            gain_db: now[c].1,
            white: reached[c],
            converged: (reached[c] - plan.white_level).abs() <= TOLERANCE,
            rounds: rounds[c],
        })
        .collect())
}

/// The (exposure µs, gain dB) giving `scale` times the signal of `(exposure, gain)`:
/// exposure first up to the plan's longest, then gain up to its most; no gain below 0 dB.
fn split((exposure, gain): (f64, f64), scale: f64, plan: &ExposurePlan) -> (f64, f64) {
    let total = exposure * 10f64.powf(gain / 20.0) * scale;
    let e = total.clamp(MIN_EXPOSURE_US, plan.max_exposure_us);
    let g = (20.0 * (total / e).log10()).clamp(0.0, plan.max_gain_db);
    ((e * 10.0).round() / 10.0, (g * 100.0).round() / 100.0)
}

/// Every camera's samples and full scale of one take.
type Takes = Vec<(Vec<f32>, f32)>;

/// Projector `p`'s response through every camera: each level shown alone, taken twice.
fn measure_response(
    session: &mut Session,
    plan: &ExposurePlan,
    p: usize,
    projector: &str,
) -> Result<Vec<Response>, CheckError> {
    let n = session.projector_names().len();
    let slides: Vec<Vec<Slide>> = (RESPONSE_LEVELS.iter())
        .map(|&l| {
            (0..n)
                .map(|q| {
                    if q == p {
                        Slide::Level(l)
                    } else {
                        Slide::Black
                    }
                })
                .collect()
        })
        .collect();
    // Per level, per take, per camera.
    let mut frames: Vec<Vec<Takes>> = vec![Vec::new(); slides.len()];
    let waits = [plan.wait, plan.wait + Duration::from_millis(1)];
    session.probe(&slides, &waits, &mut |t: ProbeTake| {
        frames[t.slide].push(t.frames.iter().map(samples).collect());
        Ok(())
    })?;
    let last = RESPONSE_LEVELS.len() - 1;
    Ok((session.camera_names().into_iter().enumerate())
        .map(|(c, camera)| {
            let take = |l: usize, t: usize| &frames[l][t][c];
            let full = take(0, 0).1;
            let mask = lit_mask(&take(0, 0).0, &take(last, 0).0, 0.08 * full);
            let values = |l: usize, t: usize| &frames[l][t][c].0;
            response(camera, projector, mask.as_deref(), &values, full)
        })
        .collect())
}

/// The response of one camera × projector from its frames `take(level, take)`.
fn response<'a>(
    camera: String,
    projector: &str,
    mask: Option<&[bool]>,
    take: &dyn Fn(usize, usize) -> &'a Vec<f32>,
    full: f32,
) -> Response {
    let mut r = Response {
        camera,
        projector: projector.to_string(),
        seen: mask.is_some(),
        levels: RESPONSE_LEVELS.to_vec(),
        mean_dn: Vec::new(),
        sigma_dn: f64::NAN,
        black_ratio: f64::NAN,
        gamma: f64::NAN,
        gamma_sigma: f64::NAN,
        saturated: 0.0,
        non_monotone: false,
        clips: false,
    };
    let Some(mask) = mask else {
        return r;
    };
    let count = mask.iter().filter(|&&m| m).count() as f64;
    let levels = RESPONSE_LEVELS.len();
    let mut var = 0.0;
    for l in 0..levels {
        let (a, b) = (take(l, 0), take(l, 1));
        r.mean_dn
            .push(0.5 * (mean_over(a, mask) + mean_over(b, mask)));
        let d: Vec<f32> = a.iter().zip(b).map(|(x, y)| x - y).collect();
        let md = mean_over(&d, mask);
        let sq: Vec<f32> = d
            .iter()
            .map(|x| (f64::from(*x) - md).powi(2) as f32)
            .collect();
        var += mean_over(&sq, mask) / 2.0;
    }
    // Pixel noise averaged over levels; a mean of two takes over `count` pixels.
    let sigma_px = (var / levels as f64).sqrt();
    r.sigma_dn = sigma_px / (2.0 * count).sqrt();
    let m = &r.mean_dn;
    let (black, white) = (m[0], m[levels - 1]);
    r.black_ratio = black / white;
    let top = take(levels - 1, 0);
    let at_full = (top.iter().zip(mask))
        .filter(|(v, &k)| k && **v >= full)
        .count();
    r.saturated = at_full as f64 / count;
    // A difference of two means: √2 σ; beyond 4 of them it is not noise.
    let step = 4.0 * std::f64::consts::SQRT_2 * r.sigma_dn;
    r.non_monotone = m.windows(2).any(|w| w[1] < w[0] - step);
    r.clips = m[levels - 1] - m[levels - 2] <= step || r.saturated > 0.01;
    (r.gamma, r.gamma_sigma) = fit_gamma(m, r.sigma_dn);
    r
}

/// γ of light ∝ (level/255)^γ fitted to the normalised means `m` (first black, last
/// white) in log–log through the origin, weighted by the noise `sigma` of a mean; NaN
/// without two usable levels.
fn fit_gamma(m: &[f64], sigma: f64) -> (f64, f64) {
    let (black, white) = (m[0], m[m.len() - 1]);
    let range = white - black;
    if range <= 0.0 {
        return (f64::NAN, f64::NAN);
    }
    let (mut sxy, mut sxx, mut used) = (0.0, 0.0, 0);
    for (i, &mi) in m.iter().enumerate().take(m.len() - 1).skip(1) {
        let x = (f64::from(RESPONSE_LEVELS[i]) / 255.0).ln();
        let y = (mi - black) / range;
        // Noise of y from the three means it is made of.
        let sy = sigma * (1.0 + y * y + (1.0 - y) * (1.0 - y)).sqrt() / range;
        // Within a few quanta of black a mean carries the rounding's bias, not light.
        if y <= 5.0 * sy || mi - black < QUANTA_ABOVE_BLACK {
            continue;
        }
        let w = (y / sy).powi(2);
        sxy += w * x * y.ln();
        sxx += w * x * x;
        used += 1;
    }
    match used >= 2 {
        true => (sxy / sxx, 1.0 / sxx.sqrt()),
        false => (f64::NAN, f64::NAN),
    }
}

impl std::fmt::Display for ExposureReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "exposure: brightest board white at {:.2} of full scale",
            self.white_level
        )?;
        for c in &self.cameras {
            writeln!(
                f,
                "  {}: exposure {:.0} µs, gain {:.1} dB → white {:.2}{}",
                c.camera,
                c.exposure_us,
                c.gain_db,
                c.white,
                if c.converged {
                    ""
                } else {
                    " (short of target)"
                }
            )?;
        }
        writeln!(f, "response (levels {:?}):", RESPONSE_LEVELS)?;
        for r in &self.responses {
            if !r.seen {
                writeln!(
                    f,
                    "  {} × {}: not lit in this camera's view",
                    r.camera, r.projector
                )?;
                continue;
            }
            writeln!(
                f,
                "  {} × {}: gamma {:.2} ± {:.2}, black {:.1} % of white, {:.1} % saturated{}{}",
                r.camera,
                r.projector,
                r.gamma,
                r.gamma_sigma,
                100.0 * r.black_ratio,
                100.0 * r.saturated,
                if r.non_monotone { ", NOT MONOTONE" } else { "" },
                if r.clips { ", CLIPS" } else { "" }
            )?;
        }
        for w in self.warnings() {
            writeln!(f, "warning: {w}")?;
        }
        Ok(())
    }
}
