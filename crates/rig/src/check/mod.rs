//! Self-tests of a rig through the capture engine (docs/design.md §11b).
//!
//! Takes a started capture [`crate::capture::Session`]; gives [`sync`], whether every camera
//! frame shows the slide it was triggered for (latency, dropped and repeated frames, the
//! `settle_ms` that makes the sequence safe), and [`exposure`], each camera's exposure and
//! gain for a set white level and each projector's response through each camera.

pub mod exposure;
pub mod sync;

use crate::capture::CaptureError;
use hexcal_core::images::{CameraFrame, Pixels};

/// Why a self-test could not be done.
#[derive(Debug, thiserror::Error)]
pub enum CheckError {
    /// The capture engine failed.
    #[error("{0}")]
    Capture(#[from] CaptureError),
    /// A projector gave no stable response (its levels never came out in order).
    #[error(
        "projector {projector}: its flat levels never came out brighter level by level \
         within {wait_ms:.0} ms (tried {tries} times)"
    )]
    Unstable {
        /// The projector.
        projector: String,
        /// The longest wait tried (ms).
        wait_ms: f64,
        /// How many times the levels were shown.
        tries: u32,
    },
    /// The rig has no projector (nothing to check).
    #[error("the rig has no projector: there is nothing to check")]
    NoProjector,
}

/// A number as JSON writes it: a value not measured (NaN) is written as `null` and read
/// back as NaN.
fn f64_or_nan<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    use serde::Deserialize;
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// A frame's samples as numbers, and its full scale.
fn samples(f: &CameraFrame) -> (Vec<f32>, f32) {
    let full = ((1u32 << f.bits) - 1) as f32;
    let v = match &f.pixels {
        Pixels::Gray8(p) => p.iter().map(|&x| f32::from(x)).collect(),
        Pixels::Gray16(p) => p.iter().map(|&x| f32::from(x)).collect(),
    };
    (v, full)
}

/// The pixels a projector lights in a camera's view: where its white exceeds its black by
/// more than half the 99th percentile of that difference; none when the difference stays
/// below `min_contrast` (the projector does not reach this camera).
fn lit_mask(black: &[f32], white: &[f32], min_contrast: f32) -> Option<Vec<bool>> {
    let mut diff: Vec<f32> = white.iter().zip(black).map(|(w, b)| w - b).collect();
    let n = diff.len();
    if n == 0 {
        return None;
    }
    let mask_of = |d: &[f32], t: f32| d.iter().map(|&x| x > t).collect::<Vec<bool>>();
    let keep = diff.clone();
    let k = ((0.99 * n as f64) as usize).min(n - 1);
    let (_, p99, _) = diff.select_nth_unstable_by(k, f32::total_cmp);
    let p99 = *p99;
    if p99 < min_contrast {
        return None;
    }
    let mask = mask_of(&keep, 0.5 * p99);
    // At least a few hundred pixels, so that a mean has little noise.
    (mask.iter().filter(|&&m| m).count() >= 200.min(n / 4)).then_some(mask)
}

/// The mean of `v` over `mask`.
fn mean_over(v: &[f32], mask: &[bool]) -> f64 {
    let (sum, count) = v
        .iter()
        .zip(mask)
        .filter(|(_, &m)| m)
        .fold((0.0f64, 0usize), |(s, c), (&x, _)| {
            (s + f64::from(x), c + 1)
        });
    sum / count.max(1) as f64
}

#[cfg(test)]
mod tests;
