//! Per frame (docs/design.md §6b, eq. 6b.4): the residual of the group's phase-shift
//! model, regressed on the shapes (light changing or the board jolting within a group), and
//! what stays unexplained measured against the median frame's; a group whose frames are
//! disturbed by more than the budget fails.

use super::{runs, Stack, StackFault};
use crate::phase::check::CheckParams;
use crate::stats::median;
use nalgebra::SVector;
use rayon::prelude::*;

/// The cause of a frame's disturbance.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Cause {
    /// The light changed (percent of the mean level, signed).
    Light(f64),
    /// The board jolted (px within the group).
    Jolt(f64),
    /// None of the above.
    Other,
}

/// One frame's finding: its cause and the RMS disturbance (σ_I units).
#[derive(Clone, Copy, Debug)]
struct Finding {
    cause: Cause,
    sigma: f64,
}

impl Stack<'_> {
    /// The faults of groups whose frames are disturbed beyond the budget; gives each frame's
    /// disturbance (σ_I units, 0 where nothing significant).
    pub(super) fn within_groups(&self, params: &CheckParams) -> (Vec<StackFault>, Vec<f64>) {
        let used = 4 * self.usable().count();
        if used == 0 || self.model.dof() < 2 {
            return (Vec::new(), vec![0.0; self.frames]);
        }
        let m = self.model;
        let shrink = m.dof() as f64 / m.steps as f64;
        let (rhs, energy) = self.frame_sums(shrink);
        let energy: Vec<f64> = energy.iter().map(|e| e / used as f64).collect();
        let cov = self.covariance(|blk| blk.var / 4.0 * shrink);
        let fits: Vec<_> = rhs
            .into_iter()
            .map(|atb| super::Fit::new(cov, atb))
            .collect();
        let mut rest: Vec<f64> = (0..self.frames)
            .map(|k| energy[k] - fits[k].explained / used as f64)
            .collect();
        let baseline = median(&mut rest.clone());
        let noise_sd = baseline * (2.0 / used as f64).sqrt();
        let findings: Vec<Option<Finding>> = (0..self.frames)
            .map(|k| {
                let fit = &fits[k];
                let explained = fit.explained > 2.0 * params.z * params.z;
                rest[k] -= baseline;
                let unexplained = rest[k] > params.z * noise_sd;
                let e = (explained as u8 as f64) * fit.explained / used as f64
                    + (unexplained as u8 as f64) * rest[k];
                if e <= 0.0 {
                    return None;
                }
                let sigma = (e / shrink).sqrt();
                let cause = match unexplained && rest[k] > fit.explained / used as f64 {
                    true => Cause::Other,
                    false => self.light_or_jolt(fit, shrink),
                };
                Some(Finding { cause, sigma })
            })
            .collect();
        let faults = self.group_faults(&findings, params);
        let sigma = findings
            .iter()
            .map(|f| f.map_or(0.0, |f| f.sigma))
            .collect();
        (faults, sigma)
    }

    /// Per frame, on all cores: the right-hand side Σ_b x_b·R_b/var_b of its block
    /// residuals R_b regressed on the shapes (var_b = σ_I²/4·(N − q)/N), and Σ over the
    /// usable pixels of residual² / (σ_I²·(N − q)/N), whose expected value per pixel is 1 in
    /// a clean stack.
    fn frame_sums(&self, shrink: f64) -> (Vec<SVector<f64, 5>>, Vec<f64>) {
        let m = self.fits.len();
        let blocks: Vec<(usize, &super::Block)> = self.usable().collect();
        self.residuals
            .par_chunks(m.max(1))
            .map(|frame| {
                let (mut rhs, mut energy) = (SVector::<f64, 5>::zeros(), 0.0);
                for &(b, blk) in &blocks {
                    let r = [0, 1, 2, 3].map(|j| f64::from(frame[4 * b + j]));
                    let mean = r.iter().sum::<f64>() / 4.0;
                    rhs += mean / (blk.var / 4.0 * shrink) * SVector::<f64, 5>::from(blk.shapes);
                    energy += r.iter().map(|v| v * v).sum::<f64>() / (blk.var * shrink);
                }
                (rhs, energy)
            })
            .unzip()
    }

    /// Light change or jolt, whichever explains more of a frame's residual.
    fn light_or_jolt(&self, fit: &super::Fit, shrink: f64) -> Cause {
        let (mut light, mut motion, mut level) = (0.0, 0.0, 0.0);
        let mut signed = 0.0;
        for (_, blk) in self.usable() {
            let (l, mo) = (fit.light(blk), fit.motion(blk));
            light += l * l / blk.var;
            motion += mo * mo / blk.var;
            signed += l;
            level += blk.shapes[2];
        }
        match light >= motion {
            true => Cause::Light(100.0 * signed / level / shrink),
            false => {
                let (d, _) = fit.displacement();
                Cause::Jolt(d[0].hypot(d[1]) / shrink)
            }
        }
    }

    /// The faults of every group whose findings sum to more than the budget: one per run of
    /// consecutive frames with the same cause.
    fn group_faults(&self, findings: &[Option<Finding>], params: &CheckParams) -> Vec<StackFault> {
        let mut faults = Vec::new();
        let n = self.model.steps;
        let mut failed = vec![None; findings.len()];
        for (g, chunk) in findings.chunks(n).enumerate() {
            let total: f64 = chunk.iter().flatten().map(|f| f.sigma).sum();
            if total > params.disturbance_sigma {
                for (s, f) in chunk.iter().enumerate() {
                    failed[g * n + s] = f.map(|f| CauseKey::of(f.cause));
                }
            }
        }
        for (first, last, key) in runs(&failed) {
            let worst = findings[first..=last]
                .iter()
                .flatten()
                .max_by(|a, b| a.sigma.total_cmp(&b.sigma))
                .expect("a run has findings");
            faults.push(key.fault(first, last, worst));
        }
        faults
    }
}

/// A cause without its size, for grouping consecutive frames.
#[derive(Clone, Copy, Debug, PartialEq)]
enum CauseKey {
    Light,
    Jolt,
    Other,
}

impl CauseKey {
    fn of(cause: Cause) -> CauseKey {
        match cause {
            Cause::Light(_) => CauseKey::Light,
            Cause::Jolt(_) => CauseKey::Jolt,
            Cause::Other => CauseKey::Other,
        }
    }

    /// The fault of frames `first`–`last`, sized by its worst finding.
    fn fault(self, first: usize, last: usize, worst: &Finding) -> StackFault {
        match (self, worst.cause) {
            (CauseKey::Light, Cause::Light(percent)) => StackFault::LightChange {
                first_frame: first,
                last_frame: last,
                percent: percent.abs(),
            },
            (CauseKey::Jolt, Cause::Jolt(px)) => StackFault::Jolt {
                first_frame: first,
                last_frame: last,
                px,
            },
            _ => StackFault::Disturbed {
                first_frame: first,
                last_frame: last,
                sigma: worst.sigma,
            },
        }
    }
}
