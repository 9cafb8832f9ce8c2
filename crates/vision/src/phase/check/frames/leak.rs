//! Light changing within a group, seen in its phases (docs/design.md §6b, eq. 6b.8). Light of
//! spatial shape S that changes by δ_s over a group's frames adds S·D to the group's bin,
//! D = (2/N)·Σ_s δ_s·e^{−iθ_p s}, so C = B·e^{−iφ} + S·D and the phase is off by
//! −(S/B)·Im(D·e^{iφ}): in units of its noise σ_φ = √(2/N)·σ_I/B, z = −(S/σ_I)·Im(D·e^{iφ})/√(2/N),
//! independent of B and oscillating with the fringe. The group's scaled disagreement is
//! regressed on each light shape times (sin φ, cos φ), one shape at a time; nuisance
//! regressors take what a lag leaves (a coherent bias and its 2φ ripple, both ∝ B/σ_I), so
//! only the light is tested.
//! This sees a light change in sequences whose model uses every step (N − q < 2), where the
//! per-frame residuals (6b.4) do not exist.

use super::{Block, Stack, StackFault};
use crate::phase::check::CheckParams;
use nalgebra::{DMatrix, DVector, SMatrix, SVector};

/// Light shapes: offset, ambient image, mean image.
const LIGHT: usize = 3;

/// Nuisance regressors: (B/σ_I)·(1, sin 2φ, cos 2φ), what a lag leaves.
const NUISANCE: usize = 3;

/// All regressors: the nuisance, then each light shape times sin φ and cos φ.
const REG: usize = NUISANCE + 2 * LIGHT;

/// A pixel whose scaled disagreement in some group exceeds this is left out: a wrong fringe
/// order (a gross error) is not a light change, and one would outweigh thousands of pixels.
pub(super) const OUTLIER: f64 = 5.0;

/// Normal equations of one group's regression (eq. 6b.8), with the shapes' sums to size the
/// light change.
#[derive(Clone, Debug)]
pub(super) struct Leak {
    ata: SMatrix<f64, REG, REG>,
    atb: SVector<f64, REG>,
    /// Σ of the light shapes (DN) over the pixels, and their count.
    shapes: [f64; LIGHT],
    count: f64,
    /// Σ of the pixels' fusion leverages.
    leverage: f64,
}

impl Default for Leak {
    fn default() -> Self {
        Leak {
            ata: SMatrix::zeros(),
            atb: SVector::zeros(),
            shapes: [0.0; LIGHT],
            count: 0.0,
            leverage: 0.0,
        }
    }
}

impl Leak {
    /// Add a pixel of `block` with modulation `b` (DN), fused phase `phi` (rad) and fusion
    /// leverage `h`, and scaled disagreement `z`.
    pub(super) fn add(&mut self, block: &Block, [b, phi, h]: [f64; 3], z: f64) {
        let (sin, cos) = phi.sin_cos();
        let (sin2, cos2) = (2.0 * sin * cos, 1.0 - 2.0 * sin * sin);
        let sigma = block.var.sqrt();
        let snr = b / sigma;
        let x = SVector::<f64, REG>::from_fn(|i, _| match i {
            0 => snr,
            1 => snr * sin2,
            2 => snr * cos2,
            _ => {
                let k = i - NUISANCE;
                block.shapes[k / 2] / sigma * if k % 2 == 0 { sin } else { cos }
            }
        });
        self.ata += x * x.transpose();
        self.atb += x * z;
        for (sum, shape) in self.shapes.iter_mut().zip(block.shapes) {
            *sum += shape;
        }
        self.count += 1.0;
        self.leverage += h;
    }

    /// Per light shape alone (a room light, an offset, a gain: one cause, one shape), the
    /// sum of squares it explains beyond the nuisance (in units of the scaled disagreements'
    /// variance; χ²₂ in a clean stack) and the complex change D of its light in the group's
    /// bin, for a fusion leverage `leverage` (which leaves √(1 − h) of a group's own bias in
    /// its scaled disagreement). One shape at a time: together they would fit differences
    /// of shapes that no light change makes (a pattern that cancels at the mean level).
    fn fits(&self, steps: usize, leverage: f64) -> [(f64, [f64; 2]); LIGHT] {
        let explain = |rows: &[usize]| {
            let ata = DMatrix::from_fn(rows.len(), rows.len(), |i, j| self.ata[(rows[i], rows[j])]);
            let atb = DVector::from_fn(rows.len(), |i, _| self.atb[rows[i]]);
            let coef = solve(ata, atb.clone());
            (coef.dot(&atb), coef)
        };
        let nuisance: Vec<usize> = (0..NUISANCE).collect();
        let base = explain(&nuisance).0;
        let unit = -(2.0 / steps as f64).sqrt() / (1.0 - leverage).sqrt();
        std::array::from_fn(|k| {
            let i = NUISANCE + 2 * k;
            let rows: Vec<usize> = nuisance.iter().copied().chain([i, i + 1]).collect();
            let (all, coef) = explain(&rows);
            (
                all - base,
                [unit * coef[NUISANCE], unit * coef[NUISANCE + 1]],
            )
        })
    }
}

/// Least squares from normal equations: scaled to unit diagonal, then a pseudo-inverse, so
/// regressors the board cannot tell apart get no coefficient rather than a wild one.
fn solve(ata: DMatrix<f64>, atb: DVector<f64>) -> DVector<f64> {
    let k = atb.len();
    let d = DVector::from_fn(k, |i, _| 1.0 / ata[(i, i)].max(1e-300).sqrt());
    let scaled = DMatrix::from_fn(k, k, |i, j| ata[(i, j)] * d[i] * d[j]);
    let inv = (scaled.pseudo_inverse(1e-9)).unwrap_or_else(|_| DMatrix::zeros(k, k));
    let rhs = atb.component_mul(&d);
    (inv * rhs).component_mul(&d)
}

impl Stack<'_> {
    /// The light change in group g, if its regression `leak` finds one beyond the budget:
    /// one light shape explains more than χ²₂'s quantile at z (the noise scaled by `scale`,
    /// the quietest other group's scatter; the three shapes tried count as three tests) and
    /// a bias, RMS over the pixels, beyond `phase_bias` of the noise (the fusion leaving
    /// 1 − h̄ of it).
    pub(super) fn light_leak(
        &self,
        g: usize,
        leak: &Leak,
        scale: f64,
        params: &CheckParams,
    ) -> Option<StackFault> {
        if leak.count < 100.0 {
            return None;
        }
        let n = self.model.steps;
        let leverage = leak.leverage / leak.count;
        let limit = chi2_2_quantile(params.z) + 2.0 * (LIGHT as f64).ln();
        let (k, explained, change) = (leak.fits(n, leverage).into_iter().enumerate())
            .map(|(k, (explained, change))| (k, explained / scale, change))
            .max_by(|a, b| a.1.total_cmp(&b.1))?;
        let bias = ((explained - 2.0).max(0.0) / leak.count / (1.0 - leverage)).sqrt();
        if explained <= limit || bias <= params.phase_bias {
            return None;
        }
        // The change in the bin at the shape's mean: the frames' RMS change is at least half
        // its size (Cauchy–Schwarz on the N-step sum).
        let mean = leak.shapes.map(|s| s / leak.count);
        let size = 0.5 * mean[k] * change[0].hypot(change[1]);
        Some(StackFault::LightChange {
            first_frame: g * n,
            last_frame: g * n + n - 1,
            percent: 100.0 * size / mean[2].max(f64::MIN_POSITIVE),
        })
    }
}

/// The quantile of χ²₂ exceeded with the probability of a normal beyond z standard
/// deviations: χ²₂'s tail is e^{−x/2}, so x = −2·ln P.
fn chi2_2_quantile(z: f64) -> f64 {
    -2.0 * normal_tail(z).ln()
}

/// P(N(0, 1) > z).
fn normal_tail(z: f64) -> f64 {
    0.5 * libm::erfc(z / std::f64::consts::SQRT_2)
}
