//! What the lit board shows (docs/design.md §6b): the fraction that clips, and projectors
//! whose modulation is low.

use super::{Stack, StackNote};
use crate::phase::check::CheckParams;

/// A block is lit when its projectors' modulation reaches this fraction of full scale (the
/// decoder's validity floor).
const LIT: f64 = 0.03;

/// A projector lights a block when its own modulation reaches this fraction of full scale
/// (the decoder's candidate floor).
const CANDIDATE: f64 = 0.015;

impl Stack<'_> {
    /// Block b's modulation of projector p (DN).
    fn modulation(&self, b: usize, p: usize) -> f64 {
        (0..4)
            .map(|j| self.fits.pixel(4 * b + j).modulation(p))
            .sum::<f64>()
            / 4.0
    }

    /// Fraction of the lit blocks that clip.
    pub(super) fn clipped_fraction(&self, full_scale: f32) -> f64 {
        let floor = LIT * f64::from(full_scale);
        let (mut lit, mut clipped) = (0usize, 0usize);
        for (b, &c) in self.clipped.iter().enumerate() {
            let total: f64 = (0..self.model.projectors)
                .map(|p| self.modulation(b, p))
                .sum();
            if total >= floor {
                lit += 1;
                clipped += usize::from(c);
            }
        }
        match lit {
            0 => 0.0,
            _ => clipped as f64 / lit as f64,
        }
    }

    /// A note for every projector whose median modulation over the blocks it lights is below
    /// `params.low_modulation` σ_I.
    pub(super) fn modulation_notes(
        &self,
        full_scale: f32,
        params: &CheckParams,
        notes: &mut Vec<StackNote>,
    ) {
        let floor = CANDIDATE * f64::from(full_scale);
        for p in 0..self.model.projectors {
            let mut snr: Vec<f64> = self
                .usable()
                .map(|(b, blk)| (self.modulation(b, p), blk.var.sqrt()))
                .filter(|&(m, _)| m >= floor)
                .map(|(m, s)| m / s)
                .collect();
            // A projector that lights under 1 % of the sampled board is not this camera's.
            if snr.len() * 100 < self.clipped.len() {
                continue;
            }
            let mid = snr.len() / 2;
            let (_, median, _) = snr.select_nth_unstable_by(mid, f64::total_cmp);
            if *median < params.low_modulation {
                notes.push(StackNote::LowModulation {
                    projector: p,
                    sigma: *median,
                });
            }
        }
    }
}
