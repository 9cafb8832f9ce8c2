//! Each group against the position its direction's other counts give alone (docs/design.md
//! §6b, 6b.11): takes a refused stack's fits; gives the lags a whole direction's fusion
//! hid. A lag whose bias takes every group of its direction to wrong fringe orders stands
//! out in no group against the fused position (6b.5), and is read as light changing in its
//! group or as motion; judged against the other counts alone, which it does not touch, its
//! group's phases are off by the lag's δ and its modulation by a (6b.7).

use super::phases::{centred, MIN_SNR};
use super::{Stack, StackFault};
use crate::phase::check::CheckParams;
use crate::phase::decode::phase_cycles;
use crate::phase::Constellation;
use crate::stats::chi2_tail;
use hexcal_core::pattern::{Direction, Sequence, MAX_COUNTS};
use rayon::prelude::*;
use std::f64::consts::TAU;

/// Largest probability that noise takes a pixel's other counts to wrong orders: pixels
/// above it are left out. Below, a pixel at wrong orders has a disagreement spread over the
/// circle, which adds nothing to the mean of e^{−ie} but its spread: the mean is scaled back
/// by the expected share at the right orders.
const WRONG_ORDERS: f64 = 0.5;

/// One group's disagreement with the other counts' position, summed over the pixels.
#[derive(Default)]
struct Alone {
    /// Σ of (B_j/B̄_others)·e^{−ie} (re, im), e in rad: its mean over the pixels at the
    /// right orders is 1 + w; and Σ of the imaginary part squared.
    sum_ratio: [f64; 2],
    sum_im2: f64,
    /// Σ σ_φ² of the group (rad²).
    sum_var: f64,
    /// Pixels, and Σ of their probability of the right orders.
    count: f64,
    right: f64,
}

impl Stack<'_> {
    /// The lags the groups show against their direction's other counts alone: per
    /// direction, the projector of the largest bias among those where some group's phase and
    /// modulation change fit a lag (a lag leaks into the other projectors' bins of its
    /// group).
    pub(super) fn lags_alone(&self, seq: &Sequence, params: &CheckParams) -> Vec<StackFault> {
        let n = self.model.steps;
        let n_col = seq.counts(Direction::Columns).len();
        let tasks: Vec<(usize, usize, Direction)> = (0..self.model.projectors)
            .flat_map(|p| [(p, 0, Direction::Columns), (p, n_col, Direction::Rows)])
            .collect();
        let found: Vec<(f64, usize, StackFault)> = tasks
            .into_par_iter()
            .filter_map(|(p, first, dir)| {
                let counts = seq.counts(dir);
                let score = (0..counts.len())
                    .filter_map(|j| {
                        let sums = self.alone(p, first, counts, j)?;
                        self.judge_alone(p, &sums, params)
                    })
                    .max_by(f64::total_cmp)?;
                let last = first + counts.len() - 1;
                let fault = StackFault::LagInGroups {
                    projector: p,
                    groups: [first, last],
                    frames: [first * n, last * n + n - 1],
                };
                Some((score, first, fault))
            })
            .collect();
        let mut lags: Vec<(f64, usize, StackFault)> = Vec::new();
        for (score, first, fault) in found {
            match lags.iter_mut().find(|l| l.1 == first) {
                Some(l) if l.0 >= score => {}
                Some(l) => *l = (score, first, fault),
                None => lags.push((score, first, fault)),
            }
        }
        lags.into_iter().map(|(_, _, f)| f).collect()
    }

    /// Group j of a direction (its first group `first`, fringe `counts`) against the
    /// position the other counts give alone, over the interior pixels where every group
    /// reaches [`MIN_SNR`] and the others' own constellation finds the orders; `None` when
    /// the other counts form no constellation.
    fn alone(&self, p: usize, first: usize, counts: &[u32], j: usize) -> Option<Alone> {
        let others: Vec<u32> = (counts.iter().enumerate())
            .filter(|&(k, _)| k != j)
            .map(|(_, &c)| c)
            .collect();
        let cons = Constellation::shared(&others).ok()?;
        let (m, r) = (counts.len(), 0.5 * cons.spacing());
        let phase_var = 2.0 / self.model.steps as f64;
        let (mut psi, mut b) = ([0f32; MAX_COUNTS], [0f64; MAX_COUNTS]);
        // The other counts' phases and weights, in their order.
        let (mut ps, mut ws) = ([0f32; MAX_COUNTS - 1], [0f32; MAX_COUNTS - 1]);
        let mut sums = Alone::default();
        for (blk, block) in self.usable().filter(|(_, b)| b.interior()) {
            let sigma = block.var.sqrt();
            for f in (4 * blk..4 * blk + 4).map(|i| self.fits.pixel(i)) {
                for k in 0..m {
                    b[k] = block
                        .modulation_sq(f, first + k, p, self.model.steps)
                        .sqrt();
                    let [re, im] = f.fundamental(first + k, p);
                    psi[k] = phase_cycles(-im, re);
                }
                if b[..m].iter().any(|&bk| bk < MIN_SNR * sigma) {
                    continue;
                }
                let var = |k: usize| phase_var * block.var / (b[k] * b[k]);
                for (i, k) in (0..m).filter(|&k| k != j).enumerate() {
                    (ps[i], ws[i]) = (psi[k], (b[k] * b[k]) as f32);
                }
                let mean_var = (0..m).filter(|&k| k != j).map(var).sum::<f64>() / (m - 1) as f64;
                let wrong = chi2_tail(m - 2, r * r / mean_var);
                if wrong > WRONG_ORDERS {
                    continue;
                }
                let t = f64::from(cons.unwrap(&ps[..m - 1], &ws[..m - 1]).position);
                let e = TAU * centred(f64::from(psi[j]) - f64::from(counts[j]) * t);
                let mean_b = (0..m).filter(|&k| k != j).map(|k| b[k]).sum::<f64>() / (m - 1) as f64;
                let im = -b[j] / mean_b * e.sin();
                sums.sum_ratio[0] += b[j] / mean_b * e.cos();
                sums.sum_ratio[1] += im;
                sums.sum_im2 += im * im;
                sums.sum_var += var(j);
                sums.count += 1.0;
                sums.right += 1.0 - wrong;
            }
        }
        Some(sums)
    }

    /// The score (the bias in noise units) of a group whose disagreement with the other
    /// counts is coherent (the mean of Im e^{−ie} beyond z standard errors, measured from
    /// its spread), beyond the budget of 6b.5 (with no leverage: the group has no part in the
    /// reference), and fits a lag of projector p.
    fn judge_alone(&self, p: usize, d: &Alone, params: &CheckParams) -> Option<f64> {
        if d.right < 100.0 {
            return None;
        }
        let [re, im] = d.sum_ratio.map(|v| v / d.right);
        let se = d.sum_im2.sqrt() / d.right;
        let (delta, a) = (-im.atan2(re), re.hypot(im) - 1.0);
        let sigma_phi = (d.sum_var / d.count).sqrt();
        if im.abs() <= params.z * se || delta.abs() <= params.phase_bias * sigma_phi {
            return None;
        }
        self.lag(p, delta, a)?;
        Some(delta.abs() / sigma_phi)
    }
}
