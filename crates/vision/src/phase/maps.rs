//! What the phase decoder gives (docs/design.md §6): per camera stack, the ambient image,
//! the saturated pixels, the measured noise model, and per projector its (u, v) maps with
//! validity, modulation and predicted noise.
//!
//! Takes nothing from the decoder itself: the decoder ([`super::Decoder`]) and the compact
//! candidate store ([`super::CompactStack`]) both fill these types.

use hexcal_core::images::FloatImage;
use serde::{Deserialize, Serialize};

/// Per-frame noise model measured from a stack: σ_I² = offset + slope·A at mean level A.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct NoiseModel {
    /// Variance at zero signal (read noise² + quantisation) (DN²).
    pub offset: f64,
    /// Variance per DN of signal (shot noise gain) (DN).
    pub slope: f64,
    /// Lower bound on the variance (1 % of the mean measured variance), guarding a fit whose
    /// line dips below zero outside the measured range (DN²).
    pub floor: f64,
}

impl NoiseModel {
    /// Per-frame noise σ_I at mean level A (DN).
    pub fn sigma(&self, mean: f64) -> f64 {
        (self.offset + self.slope * mean).max(self.floor).sqrt()
    }
}

/// Run-level phase noise of one projector: the predictions of docs/design.md §6 from the
/// measured modulation and noise, over the projector's valid pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhaseNoise {
    /// Valid pixels.
    pub valid_pixels: usize,
    /// Mean modulation B_p (DN).
    pub modulation: f64,
    /// RMS per-frame noise σ_I (DN).
    pub sigma_i: f64,
    /// RMS predicted phase noise σ_φ = √(2/N)·σ_I/B_p (rad).
    pub sigma_phi: f64,
    /// RMS predicted σ_u = W·σ_φ/(2π·√Σn_i²) (projector px).
    pub sigma_u: f64,
    /// RMS predicted σ_v (projector px).
    pub sigma_v: f64,
}

/// A per-pixel yes/no image.
#[derive(Clone, Debug, PartialEq)]
pub struct Mask {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) bits: Vec<bool>,
}

impl Mask {
    /// Width (px).
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height (px).
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The value at (x, y).
    pub fn get(&self, x: u32, y: u32) -> bool {
        self.bits[(y * self.width + x) as usize]
    }

    /// All values, row-major.
    pub fn as_slice(&self) -> &[bool] {
        &self.bits
    }

    /// Number of set pixels.
    pub fn count(&self) -> usize {
        self.bits.iter().filter(|&&b| b).count()
    }

    /// As an 8-bit image (255 where set).
    pub fn to_image(&self) -> image::GrayImage {
        image::GrayImage::from_fn(self.width, self.height, |x, y| {
            image::Luma([if self.get(x, y) { 255 } else { 0 }])
        })
    }
}

/// One projector's decoded maps in one camera.
#[derive(Clone, Debug)]
pub struct ProjectorMaps {
    /// Projector column u per camera pixel (projector px, (0, 0) at a pixel centre); NaN
    /// where the modulation or saturation test already fails (those are not unwrapped).
    pub u: FloatImage,
    /// Projector row v per camera pixel (NaN as for u).
    pub v: FloatImage,
    /// Modulation B_p (DN), bias-corrected for noise: √(mean_g B_g² − 4σ_I²/N).
    pub modulation: FloatImage,
    /// Unwrapping distance, the larger of the two directions' (rad); small is reliable
    /// (NaN as for u).
    pub reliability: FloatImage,
    /// Where (u, v) is trustworthy: B_p ≥ max(5σ_I, 3 % full scale), no saturated frame,
    /// unwrapping distance < ½ constellation spacing, and farther than 6σ_u from the
    /// screen's wrap point t = 0 ≡ 1 (where the left and right edges share a code).
    pub valid: Mask,
    /// Run-level noise predictions.
    pub noise: PhaseNoise,
    /// Fundamental amplitude a_1(γ) of a full-swing pattern (½ when linear).
    pub(super) fundamental: f32,
}

impl ProjectorMaps {
    /// The projector's full-white contribution alone (no ambient, no other projector):
    /// B_p / a_1(γ), i.e. 2·B_p when linear and 2·B_p/0.989 for γ = 2.2 (docs/design.md §6).
    pub fn lit_image(&self) -> FloatImage {
        let mut img = self.modulation.clone();
        for p in img.pixels_mut() {
            p.0[0] /= self.fundamental;
        }
        img
    }
}

/// Everything decoded from one camera's stack.
#[derive(Clone, Debug)]
pub struct DecodedStack {
    /// Camera label.
    pub camera: String,
    /// Ambient ("all projectors off") image A − Σ_p (a_0/a_1)(γ_p)·B_p (DN).
    pub ambient: FloatImage,
    /// Pixels with a saturated sample in any frame.
    pub saturated: Mask,
    /// The measured noise model.
    pub noise: NoiseModel,
    /// Per projector, in sequence order.
    pub projectors: Vec<ProjectorMaps>,
    /// The stack check's verdict ([`super::check`]).
    pub verdict: super::check::StackVerdict,
}

impl PhaseNoise {
    /// From a projector's sums over its valid pixels: [count, Σ B, Σ σ_I², Σ σ_φ², Σ σ_u²,
    /// Σ σ_v²].
    pub(super) fn from_sums(a: &[f64; 6]) -> Self {
        let c = a[0].max(1.0);
        PhaseNoise {
            valid_pixels: a[0] as usize,
            modulation: a[1] / c,
            sigma_i: (a[2] / c).sqrt(),
            sigma_phi: (a[3] / c).sqrt(),
            sigma_u: (a[4] / c).sqrt(),
            sigma_v: (a[5] / c).sqrt(),
        }
    }
}
