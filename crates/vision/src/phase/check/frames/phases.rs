//! Across groups (docs/design.md §6b, eq. 6b.6): a projector's M fringe counts of one
//! direction measure one position, so the wrapped phases of its groups must agree. Per
//! sampled pixel the phases are unwrapped and fused ([`Constellation`]); each group's
//! disagreement e_j, scaled by its noise, is a test with one degree of freedom per pixel, and
//! its mean over the board with C_j's modulation ratio gives the complex factor 1 + w by which
//! the group's fundamental is off. A projector that shows frame s + o's pattern in F of the
//! group's N frames gives w = (F/N)·(e^{iθ_p o} − 1) (the rest averages out over the board),
//! which names the lag.

use super::{Stack, StackFault};
use crate::phase::check::CheckParams;
use crate::phase::Constellation;
use hexcal_core::pattern::{Direction, Sequence};
use std::f64::consts::TAU;

/// Median of χ²₁: a clean group's median scaled disagreement.
const CHI2_1_MEDIAN: f64 = 0.454_936;

/// Extra phase scatter of a group (its median scaled e² − 1) that fails when significant: a
/// scatter that varies from pixel to pixel averages down over a circle like the noise does,
/// so a quarter more variance is harmless; more says the group is not what it should be.
const SCATTER: f64 = 0.25;

/// Pattern offsets tried: up to two frames late or early.
const OFFSETS: [i32; 4] = [-1, 1, -2, 2];

/// One group's disagreement, summed over the pixels.
#[derive(Clone, Debug, Default)]
struct Disagreement {
    /// Σ e/σ², Σ 1/σ² (e in rad).
    sum_e: f64,
    sum_w: f64,
    /// Σ B_j / B̄ and the count.
    sum_ratio: f64,
    count: f64,
    /// Σ of the leverages n_j²B_j²/Σn²B².
    sum_h: f64,
    /// Per pixel e²/(σ²(1 − h)).
    scaled: Vec<f64>,
}

impl Stack<'_> {
    /// Faults of the groups whose phases disagree with their direction's other groups, with
    /// the group each names.
    pub(super) fn phase_consistency(
        &self,
        seq: &Sequence,
        params: &CheckParams,
    ) -> Vec<(usize, StackFault)> {
        let mut faults = Vec::new();
        let n_col = seq.counts(Direction::Columns).len();
        for p in 0..self.model.projectors {
            for (first, dir) in [(0, Direction::Columns), (n_col, Direction::Rows)] {
                let counts = seq.counts(dir);
                let groups: Vec<usize> = (first..first + counts.len()).collect();
                let Some(sums) = self.disagreements(p, &groups, counts) else {
                    continue;
                };
                // One fault per projector and direction: the fusion spreads one group's
                // bias over the others (−δ·n_j·n_k/Σn²), so the worst group is the cause.
                let worst = sums
                    .iter()
                    .enumerate()
                    .filter_map(|(j, d)| {
                        let (score, f) = self.judge_group(p, groups[j], counts.len(), d, params)?;
                        Some((score, groups[j], f))
                    })
                    .max_by(|a, b| a.0.total_cmp(&b.0));
                if let Some((_, g, f)) = worst {
                    faults.push((g, f));
                }
            }
        }
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

    /// Per group of `groups` (one direction's, fringe `counts`), projector p's disagreement
    /// over the interior pixels it lights in every one of them.
    fn disagreements(
        &self,
        p: usize,
        groups: &[usize],
        counts: &[u32],
    ) -> Option<Vec<Disagreement>> {
        let cons = Constellation::shared(counts).ok()?;
        let (np, m) = (self.model.projectors, groups.len());
        let half_spacing = 0.5 * cons.spacing() as f32;
        let phase_var = 2.0 / self.model.steps as f64;
        let mut sums = vec![Disagreement::default(); m];
        let (mut psi, mut weight, mut b) = (vec![0f32; m], vec![0f32; m], vec![0f64; m]);
        for (blk, block) in self.usable() {
            if !block.interior() {
                continue;
            }
            for f in &self.fits[4 * blk..4 * blk + 4] {
                for (j, &g) in groups.iter().enumerate() {
                    let [re, im] = f.fundamentals[g * np + p];
                    b[j] = f64::from(re).hypot(f64::from(im));
                    // C = B·e^{−iφ}: the phase in cycles is arg(C̄)/2π.
                    psi[j] = (f64::from(-im).atan2(f64::from(re)) / TAU).rem_euclid(1.0) as f32;
                    weight[j] = (b[j] * b[j]) as f32;
                }
                if b.iter().any(|&bj| bj < 5.0 * block.var.sqrt()) {
                    continue;
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
                    let e = TAU * ((f64::from(psi[j]) - nj * t + 0.5).rem_euclid(1.0) - 0.5);
                    let var = phase_var * block.var / (b[j] * b[j]);
                    let h = (nj * b[j]).powi(2) / info;
                    let s = &mut sums[j];
                    s.sum_e += e / var;
                    s.sum_w += 1.0 / var;
                    s.sum_ratio += b[j] / mean_b;
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
    /// beyond [`SCATTER`]; with its score (the disagreement in noise units).
    fn judge_group(
        &self,
        p: usize,
        g: usize,
        m: usize,
        d: &Disagreement,
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
        let mut scaled = d.scaled.clone();
        let mid = scaled.len() / 2;
        let median = *scaled.select_nth_unstable_by(mid, f64::total_cmp).1 / CHI2_1_MEDIAN;
        // The sample median's standard error is ≈ 1.6× the mean's (χ²₁).
        let excess = median - 1.0;
        let incoherent = excess > SCATTER && excess > params.z * 1.6 * (2.0 / d.count).sqrt();
        if !(coherent || incoherent) {
            return None;
        }
        let rho = d.sum_ratio / d.count;
        let a = (rho - 1.0) / (1.0 - rho / m as f64);
        // C_j/C_true = (1 + a)·e^{−iδ}.
        let w = [(1.0 + a) * bias.cos() - 1.0, -(1.0 + a) * bias.sin()];
        let score = (excess.max(0.0) + (bias / sigma_phi).powi(2)).sqrt();
        let fault = match coherent.then(|| self.lag(p, w)).flatten() {
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

    /// The lag (frames F of N, offset o) whose w = (F/N)·(e^{iθo} − 1) is nearest the
    /// measured `w`, if within a third of |w|.
    fn lag(&self, p: usize, w: [f64; 2]) -> Option<(usize, i32)> {
        let n = self.model.steps;
        let theta = self.model.theta(p);
        let size = w[0].hypot(w[1]);
        (1..=n)
            .flat_map(|f| OFFSETS.map(|o| (f, o)))
            .map(|(f, o)| {
                let k = f as f64 / n as f64;
                let a = theta * f64::from(o);
                let pred = [k * (a.cos() - 1.0), k * a.sin()];
                ((f, o), (w[0] - pred[0]).hypot(w[1] - pred[1]))
            })
            .min_by(|x, y| x.1.total_cmp(&y.1))
            .filter(|(_, dist)| *dist < size / 3.0)
            .map(|(lag, _)| lag)
    }
}
