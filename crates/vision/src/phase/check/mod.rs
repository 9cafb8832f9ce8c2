//! The stack check (docs/design.md §6b): every camera stack tested against its own
//! phase-shift model and noise, on the decoder's pass over the frames.
//!
//! Takes the frames as the decoder receives them; keeps every sample of a sparse set of
//! 2 × 2 pixel blocks on a grid (at most [`MAX_BLOCKS`]: ≈ 12 MB for 90 frames); gives a
//! [`StackVerdict`]: the faults that make the stack unusable (motion, a projector showing
//! another frame's pattern, light changing within a group, unexplained disturbance,
//! clipping), each named with its size, and harmless notes (a light step between groups,
//! low modulation).
//!
//! Per sampled pixel and fringe group the model I_s = A + Σ_b Re(C_b·e^{i2πbs/N}) over the
//! bins b the projectors use (fundamentals, and the harmonics of uncorrected gammas) is
//! fitted by the DFT; what is left has N − q degrees of freedom of pure noise in a clean
//! stack. The noise σ_I² = a + b·A is measured from those residuals (robustly: medians in
//! level bins), so it is free of anything that changes between groups. Then:
//! - per group, the group mean minus the overall mean is regressed on an offset, the ambient
//!   and mean images and their gradients: light steps and motion between groups;
//! - per frame, the residual is regressed on the same shapes (light changing and the board
//!   jolting within a group), and what stays unexplained is tested against hypotheses "frame
//!   k of projector p shows the pattern of frame j";
//! - the fraction of the lit board that reaches full scale.

mod fit;
mod frames;
pub mod repair;
mod verdict;

pub use verdict::*;

#[cfg(test)]
mod tests;

use super::decode::{FrameRef, Sample};
use fit::GroupFits;
use hexcal_core::pattern::Sequence;

/// Most 2 × 2 blocks sampled.
pub const MAX_BLOCKS: usize = 8_192;

/// The check's thresholds (docs/design.md §6b derives them).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CheckParams {
    /// Significance of a finding, in standard deviations of its statistic under a clean
    /// stack (6: about 10⁻⁹ per test, so a thousand stacks of hundreds of tests each never
    /// see one).
    pub z: f64,
    /// Largest motion between groups that passes (camera px).
    pub motion_px: f64,
    /// Largest per-frame disturbance that passes, summed over a group's frames (σ_I units):
    /// it biases a circle of `n` pixels by at most √(2n/N)·that times its own noise.
    pub disturbance_sigma: f64,
    /// Largest coherent phase bias of one group that passes, in units of the per-pixel
    /// phase noise: a circle of n = 300 pixels averages the noise down by √n, not the bias,
    /// and the fusion of M = 3 counts passes about 1/√3 of one group's bias, so 0.025 keeps
    /// the bias under ¼ of the circle's own noise.
    pub phase_bias: f64,
    /// Largest fraction of the lit board that may clip.
    pub clipped: f64,
    /// Median modulation below which a projector gets a note (σ_I units; the decoder's
    /// validity floor: most of its pixels fail there).
    pub low_modulation: f64,
    /// Largest predicted growth of a projector's position noise (σ ratio) a repair may
    /// cost (eq. 6b.10): a used stack counts as accurate within 1.5× the clean stack's
    /// error, and the prediction fell short of the measured growth by up to 1.1× on the
    /// drawn faults (docs/design.md §6b), so 1.5/1.1.
    pub repair_cost: f64,
}

impl Default for CheckParams {
    fn default() -> Self {
        CheckParams {
            z: 6.0,
            motion_px: 0.03,
            disturbance_sigma: 0.04,
            phase_bias: 0.025,
            clipped: 0.02,
            low_modulation: 5.0,
            repair_cost: 1.35,
        }
    }
}

/// Samples of a stack's 2 × 2 blocks, gathered frame by frame.
pub struct StackSampler {
    seq: Sequence,
    width: usize,
    full_scale: f32,
    /// Top-left pixel of each block.
    blocks: Vec<[u32; 2]>,
    /// Frame-major samples as they arrive: pixel i (block i / 4, corner i % 4) of frame k at
    /// [k·4B + i] (contiguous writes, and each group fitted across pixels).
    samples: Vec<f32>,
    /// Blocks with a sample at full scale.
    clipped: Vec<bool>,
}

impl StackSampler {
    /// A sampler of `width` × `height` frames of `seq` (saturation at `full_scale`): blocks
    /// on a square grid whose step keeps their number at most [`MAX_BLOCKS`], away from the
    /// image border.
    pub fn new(seq: &Sequence, width: u32, height: u32, full_scale: f32) -> StackSampler {
        let (w, h) = (width as usize, height as usize);
        let area = (w * h) as f64;
        let mut step = (area / MAX_BLOCKS as f64).sqrt().ceil().max(4.0) as usize;
        let blocks_of = |step: usize| {
            let (x0, y0) = (step / 2, step / 2);
            (y0..h.saturating_sub(1))
                .step_by(step)
                .flat_map(move |y| {
                    (x0..w.saturating_sub(1))
                        .step_by(step)
                        .map(move |x| [x as u32, y as u32])
                })
                .collect::<Vec<_>>()
        };
        let mut blocks = blocks_of(step);
        while blocks.len() > MAX_BLOCKS {
            step += 1;
            blocks = blocks_of(step);
        }
        let k = seq.frame_count();
        StackSampler {
            seq: seq.clone(),
            width: w,
            full_scale,
            samples: vec![0.0; blocks.len() * 4 * k],
            clipped: vec![false; blocks.len()],
            blocks,
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.samples.len() * 4 + self.blocks.len() * 9
    }

    /// Take frame k's samples (the decoder has checked its size and order).
    pub fn push<T: Sample>(&mut self, k: usize, frame: &FrameRef<'_, T>) {
        let w = self.width;
        let m = 4 * self.blocks.len();
        let out = &mut self.samples[k * m..(k + 1) * m];
        for ((&[x, y], o), clipped) in self
            .blocks
            .iter()
            .zip(out.chunks_exact_mut(4))
            .zip(&mut self.clipped)
        {
            let at = y as usize * w + x as usize;
            for (o, i) in o.iter_mut().zip([at, at + 1, at + w, at + w + 1]) {
                *o = frame.pixels[i].value();
                *clipped |= *o >= self.full_scale;
            }
        }
    }

    /// The verdict on the stack (every frame pushed).
    pub fn verdict(self, params: &CheckParams) -> StackVerdict {
        let fits = match GroupFits::new(&self.seq) {
            Some(f) => f,
            None => return frames::unchecked(self.blocks.len()),
        };
        frames::judge(self, &fits, params)
    }
}
