//! Across groups (docs/design.md §6b, eq. 6b.6): a projector's M fringe counts of one
//! direction measure one position, so the wrapped phases of its groups must agree. Per
//! sampled pixel the phases are unwrapped and fused ([`Constellation`]); each group's
//! disagreement e_j, scaled by its noise, is a test with one degree of freedom per pixel, and
//! its mean over the board with C_j's modulation ratio gives the complex factor 1 + w by which
//! the group's fundamental is off. A projector that shows frame s + o's pattern in F of the
//! group's N frames gives w = (F/N)·(e^{iθ_p o} − 1) (the rest averages out over the board),
//! which names the lag.

use super::{Stack, StackFault};
use crate::phase::check::fit::median;
use crate::phase::check::repair::kept_groups;
use crate::phase::check::CheckParams;
use crate::phase::decode::phase_cycles;
use crate::phase::Constellation;
use hexcal_core::pattern::{Direction, Sequence};
use rayon::prelude::*;
use std::f64::consts::TAU;

/// Median of χ²₁: a clean group's median scaled disagreement.
const CHI2_1_MEDIAN: f64 = 0.454_936;

/// Extra phase scatter of a group (its median scaled e² over that of the direction's quietest
/// other group, or over χ²₁'s if that is lower, − 1) that fails when significant: a scatter
/// that varies from pixel to pixel averages down over a circle like the noise does, so a
/// quarter more variance is harmless; more says the group is not what it should be.
const SCATTER: f64 = 0.25;

/// Modulation (σ_I units) every group of a pixel needs for its phases to be tested.
const MIN_SNR: f64 = 6.0;

/// Pattern offsets tried: up to two frames late or early.
const OFFSETS: [i32; 4] = [-1, 1, -2, 2];

/// One group's disagreement, summed over the pixels.
#[derive(Clone, Debug, Default)]
struct Disagreement {
    /// Σ e/σ², Σ 1/σ² (e in rad).
    sum_e: f64,
    sum_w: f64,
    /// Σ of C_j/C_pred = (B_j/B̄)·e^{−ie} (re, im): its mean is 1 + w, the oscillating
    /// part averaging out linearly; and the count.
    sum_ratio: [f64; 2],
    count: f64,
    /// Σ of the leverages n_j²B_j²/Σn²B².
    sum_h: f64,
    /// Per pixel e²/(σ²(1 − h)).
    scaled: Vec<f64>,
}

impl Disagreement {
    /// The median of the scaled disagreements over that of χ²₁: 1 for a clean group whose
    /// noise model is right (reorders them).
    fn median(&mut self) -> f64 {
        match self.scaled.is_empty() {
            true => 1.0,
            false => median(&mut self.scaled) / CHI2_1_MEDIAN,
        }
    }
}

impl Stack<'_> {
    /// Faults of the groups whose phases disagree with their direction's other groups, with
    /// the group each names.
    pub(super) fn phase_consistency(
        &self,
        seq: &Sequence,
        params: &CheckParams,
    ) -> Vec<(usize, StackFault)> {
        let n_col = seq.counts(Direction::Columns).len();
        let tasks: Vec<(usize, usize, Direction)> = (0..self.model.projectors)
            .flat_map(|p| [(p, 0, Direction::Columns), (p, n_col, Direction::Rows)])
            .collect();
        // Each projector and direction on its own core.
        let mut faults: Vec<(usize, StackFault)> = tasks
            .into_par_iter()
            .filter_map(|(p, first, dir)| {
                let counts = seq.counts(dir);
                let groups: Vec<usize> = (first..first + counts.len()).collect();
                self.worst_group(p, &groups, counts, params)
            })
            .collect();
        // A lag leaks into the other projectors' bins of its group (its frames' change is not
        // one frequency): their disagreement there is its consequence.
        let lagged: Vec<usize> = faults
            .iter()
            .filter(|(_, f)| matches!(f, StackFault::WrongPattern { .. }))
            .map(|(g, _)| *g)
            .collect();
        faults.retain(|(g, f)| {
            !(matches!(f, StackFault::PhaseDisagreement { .. }) && lagged.contains(g))
        });
        faults
    }

    /// Whether, with the groups in `left_out` (a bit each) left out, every projector's
    /// kept groups agree: a repair's check that the lag was placed in the right group.
    pub(super) fn kept_groups_agree(
        &self,
        seq: &Sequence,
        params: &CheckParams,
        left_out: u32,
    ) -> bool {
        let n_col = seq.counts(Direction::Columns).len();
        (0..self.model.projectors).all(|p| {
            [(0, Direction::Columns), (n_col, Direction::Rows)]
                .into_iter()
                .all(|(first, dir)| {
                    let kept = kept_groups(seq, dir, first, left_out);
                    if kept.len() == seq.counts(dir).len() {
                        return true;
                    }
                    let (groups, counts): (Vec<usize>, Vec<u32>) = kept.into_iter().unzip();
                    self.worst_group(p, &groups, &counts, params).is_none()
                })
        })
    }

    /// Projector p's worst group of `groups` (one direction's, fringe `counts`) whose phases
    /// disagree with the others, with its fault. One fault per projector and direction: the
    /// fusion spreads one group's bias over the others (−δ·n_j·n_k/Σn²), so the worst group
    /// is the cause.
    pub(super) fn worst_group(
        &self,
        p: usize,
        groups: &[usize],
        counts: &[u32],
        params: &CheckParams,
    ) -> Option<(usize, StackFault)> {
        let mut sums = self.disagreements(p, groups, counts)?;
        let medians: Vec<f64> = sums.iter_mut().map(Disagreement::median).collect();
        sums.iter()
            .enumerate()
            .filter_map(|(j, d)| {
                // The scatter of the direction's quietest other group: a noise model a
                // little off shifts every group's alike.
                let reference = (medians.iter().enumerate())
                    .filter(|&(k, _)| k != j)
                    .map(|(_, &m)| m)
                    .fold(f64::INFINITY, f64::min)
                    .max(1.0);
                let scatter = [medians[j], reference];
                let (score, f) =
                    self.judge_group(p, groups[j], counts.len(), d, scatter, params)?;
                Some((score, groups[j], f))
            })
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, g, f)| (g, f))
    }

    /// Per group of `groups` (one direction's, fringe `counts`), projector p's disagreement
    /// over the interior pixels it lights in every one of them.
    fn disagreements(
        &self,
        p: usize,
        groups: &[usize],
        counts: &[u32],
    ) -> Option<Vec<Disagreement>> {
        let cons = Constellation::shared(counts).ok()?;
        let m = groups.len();
        let half_spacing = 0.5 * cons.spacing() as f32;
        let phase_var = 2.0 / self.model.steps as f64;
        let mut sums = vec![Disagreement::default(); m];
        for s in &mut sums {
            s.scaled.reserve(self.fits.len());
        }
        let (mut psi, mut weight, mut b) = (vec![0f32; m], vec![0f32; m], vec![0f64; m]);
        for (blk, block) in self.usable() {
            if !block.interior() {
                continue;
            }
            for f in (4 * blk..4 * blk + 4).map(|i| self.fits.pixel(i)) {
                for (j, &g) in groups.iter().enumerate() {
                    let [re, im] = f.fundamental(g, p);
                    // |C|² = B² + 4σ_I²/N on average: B without the noise's share.
                    let c2 = f64::from(re).powi(2) + f64::from(im).powi(2);
                    b[j] = (c2 - 2.0 * phase_var * block.var).max(0.0).sqrt();
                    weight[j] = (b[j] * b[j]) as f32;
                }
                // Phases of B ≥ 6σ_I are Gaussian to the test's precision (σ_φ ≤ 0.09 rad
                // for N = 7; lower, the noise's own B biases the measured spread).
                if b.iter().any(|&bj| bj < MIN_SNR * block.var.sqrt()) {
                    continue;
                }
                for (j, &g) in groups.iter().enumerate() {
                    // C = B·e^{−iφ}: the phase in cycles is arg(C̄)/2π, as the decoder takes
                    // it (≤ 2·10⁻⁶ cycles off atan2).
                    let [re, im] = f.fundamental(g, p);
                    psi[j] = phase_cycles(-im, re);
                }
                let un = cons.unwrap(&psi, &weight);
                if un.distance >= half_spacing {
                    continue;
                }
                let t = f64::from(un.position);
                let mean_b = b.iter().sum::<f64>() / m as f64;
                let info: f64 = (0..m).map(|j| (f64::from(counts[j]) * b[j]).powi(2)).sum();
                for j in 0..m {
                    let nj = f64::from(counts[j]);
                    let e = TAU * centred(f64::from(psi[j]) - nj * t);
                    let var = phase_var * block.var / (b[j] * b[j]);
                    let h = (nj * b[j]).powi(2) / info;
                    let s = &mut sums[j];
                    s.sum_e += e / var;
                    s.sum_w += 1.0 / var;
                    let (sin, cos) = (e as f32).sin_cos();
                    s.sum_ratio[0] += b[j] / mean_b * f64::from(cos);
                    s.sum_ratio[1] -= b[j] / mean_b * f64::from(sin);
                    s.sum_h += h;
                    s.count += 1.0;
                    s.scaled.push(e * e / (var * (1.0 - h)));
                }
            }
        }
        Some(sums)
    }

    /// The fault of projector p's group g (one of `m` in its direction), if its phases
    /// disagree: coherently beyond the budget (named as a lag when one fits), or incoherently
    /// beyond [`SCATTER`] (`scatter`: its median scaled disagreement and the reference's);
    /// with its score (the disagreement in noise units).
    fn judge_group(
        &self,
        p: usize,
        g: usize,
        m: usize,
        d: &Disagreement,
        [median, reference]: [f64; 2],
        params: &CheckParams,
    ) -> Option<(f64, StackFault)> {
        if d.count < 100.0 {
            return None;
        }
        let n = self.model.steps;
        let frames = [g * n, g * n + n - 1];
        let leverage = d.sum_h / d.count;
        let mean_e = d.sum_e / d.sum_w;
        let se = 1.0 / d.sum_w.sqrt();
        // The per-pixel phase noise, RMS: the unit of the budget.
        let sigma_phi = (d.count / d.sum_w).sqrt();
        let bias = mean_e / (1.0 - leverage);
        let coherent = mean_e.abs() > params.z * se && bias.abs() > params.phase_bias * sigma_phi;
        // The sample median's standard error is ≈ 1.6× the mean's (χ²₁).
        let excess = median / reference - 1.0;
        let incoherent = excess > SCATTER && excess > params.z * 1.6 * (2.0 / d.count).sqrt();
        if !(coherent || incoherent) {
            return None;
        }
        // The mean of C_j/C_pred; its angle is −(1 − h)·δ (the fusion holds the group), its
        // size (1 + a)/(1 + a/M) (B̄ holds B_j): C_j/C_true = (1 + a)·e^{−iδ}.
        let [re, im] = d.sum_ratio.map(|v| v / d.count);
        let rho = re.hypot(im);
        let a = (rho - 1.0) / (1.0 - rho / m as f64);
        let delta = -im.atan2(re) / (1.0 - leverage);

        let score = (excess.max(0.0) + (bias / sigma_phi).powi(2)).sqrt();
        let fault = match coherent.then(|| self.lag(p, delta, a)).flatten() {
            Some((count, offset)) => StackFault::WrongPattern {
                projector: p,
                group: g,
                frames,
                count,
                offset,
            },
            None => StackFault::PhaseDisagreement {
                projector: p,
                group: g,
                frames,
                sigma: score,
            },
        };
        Some((score, fault))
    }

    /// The lag (frames F of N, offset o) whose group phase bias δ = −arg(1 + (F/N)·(e^{iθo} − 1))
    /// is nearest the measured `delta`, within a third of it, and whose modulation change
    /// |1 + …| − 1 is within 0.15 or half of itself of the measured `a` (a quarter weight in
    /// the choice: the patterns' harmonics, leaking through the F-frame window, change the
    /// modulation more than the phase). A lag always lowers the modulation
    /// (|1 + k·(e^{iθo} − 1)| < 1 for 0 < k ≤ 1); another projector's lag leaking into this
    /// one's bins biases its phase as much but leaves its modulation unchanged or higher.
    fn lag(&self, p: usize, delta: f64, a: f64) -> Option<(usize, i32)> {
        let n = self.model.steps;
        let theta = self.model.theta(p);
        (1..=n)
            .flat_map(|f| OFFSETS.map(|o| (f, o)))
            .map(|(f, o)| {
                let k = f as f64 / n as f64;
                let (re, im) = (
                    1.0 + k * ((theta * f64::from(o)).cos() - 1.0),
                    k * (theta * f64::from(o)).sin(),
                );
                let (d_pred, a_pred) = (-im.atan2(re), re.hypot(im) - 1.0);
                let fits = (delta - d_pred).abs() < delta.abs() / 3.0
                    && a < 0.0
                    && (a - a_pred).abs() < f64::max(0.15, 0.5 * a_pred.abs());
                let score = (delta - d_pred).abs() + 0.25 * (a - a_pred).abs();
                ((f, o), fits, score)
            })
            .filter(|(_, fits, _)| *fits)
            .min_by(|x, y| x.2.total_cmp(&y.2))
            .map(|(lag, _, _)| lag)
    }
}

/// x minus its nearest integer, in [−½, ½) (x within ±2⁶² of 0; no libm call).
fn centred(x: f64) -> f64 {
    let y = x + 0.5;
    let whole = y as i64 as f64;
    let floor = if whole > y { whole - 1.0 } else { whole };
    y - floor - 0.5
}
