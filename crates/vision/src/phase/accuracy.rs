//! Decoded maps against a synthetic scene's ground truth (`sim::fringe`), for the decoder's
//! tests and benchmark.

use super::maps::DecodedStack;
use hexcal_core::pattern::Sequence;
use hexcal_sim::fringe::Truth;

/// Accuracy of one projector's decoded maps against the ground truth.
#[derive(Clone, Copy, Debug)]
pub struct ProjectorAccuracy {
    /// Valid pixels.
    pub valid: usize,
    /// Valid interior pixels compared.
    pub compared: usize,
    /// RMS error of u (projector px).
    pub rms_u: f64,
    /// RMS error of v (projector px).
    pub rms_v: f64,
    /// The decoder's predicted σ_u (projector px).
    pub predicted_u: f64,
    /// The decoder's predicted σ_v (projector px).
    pub predicted_v: f64,
    /// Compared pixels off by more than max(6σ, 1 px) in u or v, σ from the true modulation.
    pub gross: usize,
}

/// Compare decoded maps with the truth on valid interior pixels.
pub fn accuracy(decoded: &DecodedStack, truth: &Truth, seq: &Sequence) -> Vec<ProjectorAccuracy> {
    decoded
        .projectors
        .iter()
        .enumerate()
        .map(|(p, maps)| {
            let sigma = truth.sigma_uv(seq, p);
            let (mut cnt, mut su, mut sv, mut gross) = (0usize, 0f64, 0f64, 0usize);
            for (i, &ok) in maps.valid.as_slice().iter().enumerate() {
                if !ok || !truth.interior[i] {
                    continue;
                }
                let eu = f64::from(maps.u.as_raw()[i]) - truth.u[p][i];
                let ev = f64::from(maps.v.as_raw()[i]) - truth.v[p][i];
                cnt += 1;
                su += eu * eu;
                sv += ev * ev;
                let (s_u, s_v) = sigma(i);
                if eu.abs() > (6.0 * s_u).max(1.0) || ev.abs() > (6.0 * s_v).max(1.0) {
                    gross += 1;
                }
            }
            let c = cnt.max(1) as f64;
            ProjectorAccuracy {
                valid: maps.noise.valid_pixels,
                compared: cnt,
                rms_u: (su / c).sqrt(),
                rms_v: (sv / c).sqrt(),
                predicted_u: maps.noise.sigma_u,
                predicted_v: maps.noise.sigma_v,
                gross,
            }
        })
        .collect()
}
