//! Frames of a stack gone wrong, for the stack check's tests (docs/design.md §6b): a
//! projector showing another frame's pattern, the board moved (its albedo shifts under the
//! projectors' light, which stays), the ambient light or the camera gain changed.

use super::Renderer;
use hexcal_core::pattern::Direction;
use rayon::prelude::*;
use std::f64::consts::TAU;

/// Sub-samples per pixel side of the moved board's albedo (its edges move by fractions of
/// a pixel, so it is area-sampled).
const SUPERSAMPLE: usize = 4;

/// What is wrong with one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Disturbance {
    /// Per projector, the frame whose pattern it shows (`None`: its own).
    pub shown: Vec<Option<usize>>,
    /// Where the board is (camera px): its albedo moves, the projectors' light does not.
    pub shift: [f64; 2],
    /// Factor on the ambient light.
    pub ambient: f64,
    /// Factor on all light reaching the sensor (a camera gain or exposure change).
    pub gain: f64,
}

impl Disturbance {
    /// Nothing wrong, for a rig of `projectors`.
    pub fn none(projectors: usize) -> Disturbance {
        Disturbance {
            shown: vec![None; projectors],
            shift: [0.0; 2],
            ambient: 1.0,
            gain: 1.0,
        }
    }
}

impl Renderer<'_> {
    /// Frame k as `d` makes it. The board is area-sampled here (also when it has not moved),
    /// so compare such frames with frames of this method, not of [`Renderer::frame`].
    pub fn frame_with(&mut self, k: usize, d: &Disturbance) -> image::GrayImage {
        let (w, h) = (self.scene.width as usize, self.scene.height as usize);
        let albedo = self.area_albedo(d.shift);
        let patterns: Vec<Vec<f32>> = (0..self.weight.len())
            .map(|p| self.pattern_light(p, d.shown[p].unwrap_or(k)))
            .collect();
        let ambient = (self.scene.imaging.ambient * d.ambient) as f32;
        let gain = d.gain as f32;
        let mut irr = vec![0f32; w * h];
        irr.par_iter_mut().enumerate().for_each(|(i, e)| {
            let ratio = albedo[i] / self.albedo[i];
            let lit: f32 = (0..patterns.len())
                .map(|p| self.weight[p][i] * ratio * patterns[p][i])
                .sum();
            *e = gain * (albedo[i] * ambient + lit);
        });
        self.expose(irr, k)
    }

    /// The board's albedo moved by `shift`, averaged over each pixel's area.
    fn area_albedo(&self, [dx, dy]: [f64; 2]) -> Vec<f32> {
        let (w, h) = (self.scene.width as usize, self.scene.height as usize);
        let n = SUPERSAMPLE as f64;
        (0..w * h)
            .into_par_iter()
            .map(|i| {
                let (x, y) = ((i % w) as f64 - dx, (i / w) as f64 - dy);
                let sum: f64 = (0..SUPERSAMPLE * SUPERSAMPLE)
                    .map(|s| {
                        let ox = ((s % SUPERSAMPLE) as f64 + 0.5) / n - 0.5;
                        let oy = ((s / SUPERSAMPLE) as f64 + 0.5) / n - 0.5;
                        self.scene.albedo(x + ox, y + oy)
                    })
                    .sum();
                (sum / (n * n)) as f32
            })
            .collect()
    }

    /// Projector p's light (relative, through its response) at every pixel when it shows
    /// frame j's pattern.
    fn pattern_light(&self, p: usize, j: usize) -> Vec<f32> {
        let code = self.seq.frame(j).expect("frame within the sequence");
        let pc = self.seq.projectors()[p];
        let size = f64::from(match code.direction {
            Direction::Columns => pc.width,
            Direction::Rows => pc.height,
        });
        let axis = usize::from(code.direction == Direction::Rows);
        let n = self.seq.steps();
        let shift = TAU * f64::from(pc.frequency * code.step % n) / f64::from(n);
        self.coords[p]
            .par_iter()
            .map(|c| {
                let phi = TAU * f64::from(code.count) * (c[axis] + 0.5) / size;
                let level = (255.0 * 0.5 * (1.0 + (phi - shift).cos())).round();
                self.light[p][level.clamp(0.0, 255.0) as usize]
            })
            .collect()
    }
}
