//! Across groups (docs/design.md §6b, eq. 6b.6): a projector's M fringe counts of one
//! direction measure one position, so the wrapped phases of its groups must agree. Per
//! sampled pixel the phases are unwrapped and fused ([`Constellation`]); each group's
//! disagreement e_j, scaled by its noise, is a test with one degree of freedom per pixel, and
//! its mean over the board with C_j's modulation ratio gives the complex factor 1 + w by which
//! the group's fundamental is off. A projector that shows frame s + o's pattern in F of the
//! group's N frames gives w = (F/N)·(e^{iθ_p o} − 1) (the rest averages out over the board),
//! which names the lag. Light that changes within a group adds its shape times one complex
//! number to the group's bins, which biases the phase by (shape/B)·sin(φ + α): that pattern
//! of the disagreement over the board names the light change (eq. 6b.8).

use super::leak::{Leak, OUTLIER};
use super::{Stack, StackFault};
use crate::phase::check::repair::kept_groups;
use crate::phase::check::CheckParams;
use crate::phase::decode::phase_cycles;
use crate::phase::Constellation;
use crate::stats::{chi2_tail, median};
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

/// Modulation (σ_I units) every group of a pixel needs for its phases' bias and scatter to be
/// tested.
pub(super) const MIN_SNR: f64 = 6.0;

/// Modulation (σ_I units) every group of a pixel needs for the light and unwrapping tests:
/// the decoder's validity floor.
const MIN_LINEAR: f64 = 5.0;

/// Fraction of the tested pixels beyond the expected that may fail to unwrap: the loss that
/// stops being incidental, as for clipping.
const UNWRAP_LOSS: f64 = 0.02;

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
    /// The light-leak regression.
    leak: Leak,
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

/// A projector's and direction's pixels that fail to unwrap (their phases match no order
/// tuple), against what the noise makes fail.
#[derive(Clone, Copy, Debug, Default)]
struct Unwrapping {
    /// Dimensions of the constellation's space: M − 1 for M counts.
    dims: usize,
    tried: f64,
    failed: f64,
    /// Σ over the pixels of the probability that noise alone puts them beyond half the
    /// constellation spacing r: P(χ²_{M−1} > r²/σ²) (σ² the mean of the groups' phase
    /// variances). With M = 2 every point lies within r of a constellation point, so this
    /// is the loss to wrong fringe orders, which no distance shows.
    expected: f64,
    /// Σ over the pixels of 1/(1 − that probability), each at most [`MAX_INFLATION`]: how
    /// much the loss inflates the variance of a mean over pixels, pixel by pixel (the loss
    /// gathers where the modulation is low: the harmonic mean of the keep probabilities,
    /// not their mean, sets the noise of a circle).
    inflation: f64,
}

/// Largest variance inflation one pixel's loss counts with (its pixel almost surely lost).
const MAX_INFLATION: f64 = 100.0;

impl Unwrapping {
    /// Count a pixel (`failed` or not) with half spacing `r` and mean phase variance `var`
    /// (rad²).
    fn add(&mut self, failed: bool, r: f32, var: f64) {
        self.tried += 1.0;
        self.failed += f64::from(u8::from(failed));
        let lost = chi2_tail(self.dims, f64::from(r).powi(2) / var);
        self.expected += lost;
        self.inflation += (1.0 / (1.0 - lost)).min(MAX_INFLATION);
    }

    /// The fraction beyond the expected that failed, if significant at z and beyond
    /// [`UNWRAP_LOSS`].
    fn excess(&self, z: f64) -> Option<f64> {
        let extra = self.failed - self.expected;
        let significant = extra > z * (self.expected + 1.0).sqrt();
        (significant && extra > UNWRAP_LOSS * self.tried).then(|| extra / self.tried)
    }

    /// The share of the information in the tested pixels that the pixels that unwrap to
    /// the right fringe orders keep: the fraction of them that did not fail or, where less,
    /// the harmonic mean of the probabilities that noise leaves them (1 when none was
    /// tested).
    fn kept_share(&self) -> f64 {
        match self.tried > 0.0 {
            true => (1.0 - self.failed / self.tried).min(self.tried / self.inflation),
            false => 1.0,
        }
    }
}

/// What the phase tests find for one projector and direction.
struct Findings {
    /// The worst group whose phases disagree, with its fault.
    worst: Option<(usize, StackFault)>,
    /// The groups whose disagreement has the pattern of a light change.
    leaks: Vec<(usize, StackFault)>,
    /// The direction's phases fail to unwrap at more pixels than the noise explains.
    unwrapping: Option<StackFault>,
    /// The share of the tested pixels' information that unwraps ([`Unwrapping`]).
    kept_share: f64,
}

impl Stack<'_> {
    /// Faults of the groups whose phases disagree with their direction's other groups (a
    /// lag, light changing within the group, phases that match no fringe orders), with the
    /// group each names.
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
        let findings: Vec<Findings> = tasks
            .into_par_iter()
            .filter_map(|(p, first, dir)| {
                let counts = seq.counts(dir);
                let groups: Vec<usize> = (first..first + counts.len()).collect();
                self.group_findings(p, &groups, counts, params)
            })
            .collect();
        let mut faults = Vec::new();
        let mut leaks = Vec::new();
        for f in findings {
            faults.extend(f.worst);
            faults.extend(f.unwrapping.map(|u| (unwrapping_group(&u), u)));
            leaks.extend(f.leaks);
        }
        // A lag leaks into the other projectors' bins of its group (its frames' change is not
        // one frequency): their disagreement there is its consequence.
        let lagged: Vec<usize> = faults
            .iter()
            .filter(|(_, f)| matches!(f, StackFault::WrongPattern { .. }))
            .map(|(g, _)| *g)
            .collect();
        let unwrapped: Vec<usize> = faults
            .iter()
            .filter(|(_, f)| matches!(f, StackFault::Unwrapping { .. }))
            .map(|(g, _)| *g)
            .collect();
        // One light change per group (the largest any projector sees); it explains the
        // group's phase disagreement.
        let mut light: Vec<(usize, StackFault)> = Vec::new();
        for (g, f) in leaks {
            // A lag biases its projector's fused positions, and through them the other
            // groups of its direction: their patterns are the lag's (a repair checks them
            // again with the lagged group left out). Positions that do not unwrap leave no
            // pattern to read.
            let same_direction = |&l: &usize| (l < n_col) == (g < n_col);
            if lagged.iter().any(same_direction) || unwrapped.iter().any(same_direction) {
                continue;
            }
            match light.iter_mut().find(|(h, _)| *h == g) {
                Some(kept) if percent(&kept.1) >= percent(&f) => {}
                Some(kept) => kept.1 = f,
                None => light.push((g, f)),
            }
        }
        faults.retain(|(g, f)| {
            !(matches!(f, StackFault::PhaseDisagreement { .. })
                && (lagged.contains(g) || light.iter().any(|(h, _)| h == g)))
        });
        faults.extend(light);
        faults
    }

    /// Whether a repair that leaves out the groups in `left_out` (a bit each) holds: every
    /// projector's kept groups agree (the lag was placed in the right group), and the
    /// positions they give are at most `params.repair_cost` times noisier than the full
    /// stack's (eq. 6b.10: the kept counts' share of the information and the share of the
    /// pixels their own constellation still unwraps).
    pub(super) fn repair_holds(&self, seq: &Sequence, params: &CheckParams, left_out: u32) -> bool {
        let n_col = seq.counts(Direction::Columns).len();
        (0..self.model.projectors).all(|p| {
            [(0, Direction::Columns), (n_col, Direction::Rows)]
                .into_iter()
                .all(|(first, dir)| {
                    let kept = kept_groups(seq, dir, first, left_out);
                    if kept.len() == seq.counts(dir).len() {
                        return true;
                    }
                    let left: Vec<(usize, u32)> = (kept_groups(seq, dir, first, 0).into_iter())
                        .filter(|g| !kept.contains(g))
                        .collect();
                    let share = self.kept_information(p, &kept, &left);
                    let (groups, counts): (Vec<usize>, Vec<u32>) = kept.into_iter().unzip();
                    self.group_findings(p, &groups, &counts, params)
                        .is_none_or(|f| {
                            let cost = (1.0 / (share * f.kept_share)).sqrt(); // (6b.10)
                            f.worst.is_none()
                                && f.unwrapping.is_none()
                                && f.leaks.is_empty()
                                && cost <= params.repair_cost
                        })
                })
        })
    }

    /// The share of projector p's position information over the interior pixels that the
    /// `kept` groups of a direction keep, of those groups and the `left` ones (group,
    /// fringe count): Σ_kept n²B² over that plus Σ_left n²·B̄²_kept (a left-out group's own B
    /// is the fault's: a lag lowers it in its projector and leaks into the others').
    fn kept_information(&self, p: usize, kept: &[(usize, u32)], left: &[(usize, u32)]) -> f64 {
        let n2 = |gs: &[(usize, u32)]| gs.iter().map(|&(_, n)| f64::from(n).powi(2)).sum::<f64>();
        let n2_left = n2(left);
        let (mut kept_info, mut left_info) = (0.0, 0.0);
        for (blk, block) in self.usable().filter(|(_, b)| b.interior()) {
            for f in (4 * blk..4 * blk + 4).map(|i| self.fits.pixel(i)) {
                let mut b2_sum = 0.0;
                for &(g, n) in kept {
                    let b2 = block.modulation_sq(f, g, p, self.model.steps);
                    kept_info += f64::from(n).powi(2) * b2;
                    b2_sum += b2;
                }
                left_info += n2_left * b2_sum / kept.len() as f64;
            }
        }
        kept_info / (kept_info + left_info).max(f64::MIN_POSITIVE)
    }

    /// What the phase tests find for projector p's `groups` (one direction's, fringe
    /// `counts`). One phase fault per projector and direction: the fusion spreads one
    /// group's bias over the others (−δ·n_j·n_k/Σn²), so the worst group is the cause.
    fn group_findings(
        &self,
        p: usize,
        groups: &[usize],
        counts: &[u32],
        params: &CheckParams,
    ) -> Option<Findings> {
        let (mut sums, unwrapping) = self.disagreements(p, groups, counts)?;
        let medians: Vec<f64> = sums.iter_mut().map(Disagreement::median).collect();
        // The scatter of the direction's quietest other group: a noise model a little off
        // shifts every group's alike.
        let reference = |j: usize| {
            (medians.iter().enumerate())
                .filter(|&(k, _)| k != j)
                .map(|(_, &m)| m)
                .fold(f64::INFINITY, f64::min)
                .max(1.0)
        };
        let worst = (sums.iter().enumerate())
            .filter_map(|(j, d)| {
                let scatter = [medians[j], reference(j)];
                let (score, f) =
                    self.judge_group(p, groups[j], counts.len(), d, scatter, params)?;
                Some((score, groups[j], f))
            })
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, g, f)| (g, f));
        let leaks = (sums.iter().enumerate())
            .filter_map(|(j, d)| {
                let fault = self.light_leak(groups[j], &d.leak, reference(j), params)?;
                Some((groups[j], fault))
            })
            .collect();
        let n = self.model.steps;
        let (first, last) = (groups[0], groups[groups.len() - 1]);
        let kept_share = unwrapping.kept_share();
        let unwrapping = unwrapping
            .excess(params.z)
            .map(|fraction| StackFault::Unwrapping {
                projector: p,
                groups: [first, last],
                frames: [first * n, last * n + n - 1],
                fraction,
            });
        Some(Findings {
            worst,
            leaks,
            unwrapping,
            kept_share,
        })
    }

    /// Per group of `groups` (one direction's, fringe `counts`), projector p's disagreement
    /// over the interior pixels it lights in every one of them.
    fn disagreements(
        &self,
        p: usize,
        groups: &[usize],
        counts: &[u32],
    ) -> Option<(Vec<Disagreement>, Unwrapping)> {
        let cons = Constellation::shared(counts).ok()?;
        let m = groups.len();
        let half_spacing = 0.5 * cons.spacing() as f32;
        let phase_var = 2.0 / self.model.steps as f64;
        let mut sums = vec![Disagreement::default(); m];
        for s in &mut sums {
            s.scaled.reserve(self.fits.len());
        }
        let (mut psi, mut weight, mut b) = (vec![0f32; m], vec![0f32; m], vec![0f64; m]);
        let (mut z, mut hs) = (vec![0f64; m], vec![0f64; m]);
        let mut unwrapping = Unwrapping {
            dims: m - 1,
            ..Unwrapping::default()
        };
        for (blk, block) in self.usable() {
            if !block.interior() {
                continue;
            }
            for f in (4 * blk..4 * blk + 4).map(|i| self.fits.pixel(i)) {
                for (j, &g) in groups.iter().enumerate() {
                    b[j] = block.modulation_sq(f, g, p, self.model.steps).sqrt();
                    weight[j] = (b[j] * b[j]) as f32;
                }
                // Phases of B ≥ 6σ_I are Gaussian to the scatter test's precision (σ_φ ≤
                // 0.09 rad for N = 7; lower, the noise's own B biases the measured spread);
                // the light and unwrapping tests hold from the decoder's validity floor, 5σ_I,
                // on (the coherent test keeps to 6σ_I: its lag model sizes B).
                let sigma = block.var.sqrt();
                if b.iter().any(|&bj| bj < MIN_LINEAR * sigma) {
                    continue;
                }
                let gaussian = b.iter().all(|&bj| bj >= MIN_SNR * sigma);
                for (j, &g) in groups.iter().enumerate() {
                    // C = B·e^{−iφ}: the phase in cycles is arg(C̄)/2π, as the decoder takes
                    // it (≤ 2·10⁻⁶ cycles off atan2).
                    let [re, im] = f.fundamental(g, p);
                    psi[j] = phase_cycles(-im, re);
                }
                let un = cons.unwrap(&psi, &weight);
                let mean_var = b
                    .iter()
                    .map(|bj| phase_var * block.var / (bj * bj))
                    .sum::<f64>();
                unwrapping.add(
                    un.distance >= half_spacing,
                    half_spacing,
                    mean_var / m as f64,
                );
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
                    z[j] = e / (var * (1.0 - h)).sqrt();
                    hs[j] = h;
                    if !gaussian {
                        continue;
                    }
                    let s = &mut sums[j];
                    s.sum_e += e / var;
                    s.sum_w += 1.0 / var;
                    let (sin, cos) = (e as f32).sin_cos();
                    s.sum_ratio[0] += b[j] / mean_b * f64::from(cos);
                    s.sum_ratio[1] -= b[j] / mean_b * f64::from(sin);
                    s.sum_h += h;
                    s.count += 1.0;
                    s.scaled.push(z[j] * z[j]);
                }
                if z.iter().all(|zj| zj.abs() <= OUTLIER) {
                    for j in 0..m {
                        let phi = TAU * f64::from(counts[j]) * t;
                        sums[j].leak.add(block, [b[j], phi, hs[j]], z[j]);
                    }
                }
            }
        }
        Some((sums, unwrapping))
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
        let tested = d.scaled.len() as f64;
        let incoherent =
            tested >= 100.0 && excess > SCATTER && excess > params.z * 1.6 * (2.0 / tested).sqrt();
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
    pub(super) fn lag(&self, p: usize, delta: f64, a: f64) -> Option<(usize, i32)> {
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

/// The first group of an unwrapping fault (its place in the list of group faults).
fn unwrapping_group(f: &StackFault) -> usize {
    match f {
        StackFault::Unwrapping { groups, .. } => groups[0],
        _ => 0,
    }
}

/// The size of a light change (0 for any other fault).
fn percent(f: &StackFault) -> f64 {
    match f {
        StackFault::LightChange { percent, .. } => *percent,
        _ => 0.0,
    }
}

/// x minus its nearest integer, in [−½, ½) (x within ±2⁶² of 0; no libm call).
pub(super) fn centred(x: f64) -> f64 {
    let y = x + 0.5;
    let whole = y as i64 as f64;
    let floor = if whole > y { whole - 1.0 } else { whole };
    y - floor - 0.5
}
