//! The imaging chain from irradiance to a quantised frame: vignetting → Gaussian PSF →
//! colour filter (a Bayer sensor) → shot and read noise → gamma → quantisation
//! (docs/design.md §9).
//!
//! Intensities are in DN of an 8-bit scale (full scale 255) whatever the output depth; a
//! 12- or 16-bit frame stores the same signal times (2^bits − 1)/255, so changing `bits`
//! changes only the quantisation.

use crate::lens::ImageSize;
use crate::target::splitmix64;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use rayon::prelude::*;

/// Full scale of the 8-bit DN scale all levels are given in.
pub const FULL_SCALE: f64 = 255.0;

/// Camera sensor and lens-shading parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sensor {
    /// Standard deviation of the Gaussian PSF (px); 0 for none.
    pub psf_sigma: f64,
    /// Relative light loss in the image corners: gain 1 − v·(ρ/ρ_corner)², ρ the distance
    /// from the image centre.
    pub vignetting: f64,
    /// Shot noise: variance gain·I (DN², I in DN).
    pub shot_gain: f64,
    /// Read noise standard deviation (DN).
    pub read_noise: f64,
    /// Gamma γ applied after the noise: out = 255·(I/255)^(1/γ).
    pub gamma: f64,
    /// Output depth: 8, 12 or 16 bits.
    pub bits: u8,
    /// A colour filter array: the relative response to the (white) light of the four
    /// pixels of each 2×2 cell, row by row (top-left, top-right, bottom-left,
    /// bottom-right), applied to the signal before the noise; `None` for a monochrome
    /// sensor.
    pub cfa: Option<[f32; 4]>,
}

/// A quantised frame, row-major.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Frame {
    /// Image size.
    pub size: ImageSize,
    /// Bits per pixel (8, 12 or 16); values are < 2^bits.
    pub bits: u8,
    /// Pixel values.
    pub data: Vec<u16>,
}

impl Sensor {
    /// The noise-free signal (DN, before gamma): vignetting, then the PSF.
    pub fn optics(&self, size: ImageSize, irradiance: &[f32]) -> Vec<f32> {
        let (w, h) = (size.width as usize, size.height as usize);
        assert_eq!(irradiance.len(), w * h, "irradiance has the image's size");
        let (cx, cy) = (0.5 * (w as f64 - 1.0), 0.5 * (h as f64 - 1.0));
        let corner2 = cx * cx + cy * cy;
        let mut img: Vec<f32> = irradiance.to_vec();
        if self.vignetting != 0.0 {
            img.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                let dy2 = (y as f64 - cy).powi(2);
                for (x, v) in row.iter_mut().enumerate() {
                    let rho2 = (x as f64 - cx).powi(2) + dy2;
                    *v *= (1.0 - self.vignetting * rho2 / corner2.max(1e-12)) as f32;
                }
            });
        }
        if self.psf_sigma > 0.0 {
            img = gaussian_blur(&img, w, h, self.psf_sigma);
        }
        img
    }

    /// Add noise to a noise-free signal, apply gamma and quantise; `seed` picks the noise.
    pub fn expose(&self, size: ImageSize, signal: &[f32], seed: u64) -> Frame {
        let mut data = vec![0u16; signal.len()];
        self.expose_rows(size.width as usize, 0, signal, seed, &mut data);
        Frame {
            size,
            bits: self.bits,
            data,
        }
    }

    /// [`Sensor::expose`] of a band of whole rows of an image `width` wide, from row
    /// `first_row` on, into `out` (as long as `signal`): the same values as those rows of
    /// the whole frame's exposure (each row's noise is seeded by its own index), so a frame
    /// can be exposed band by band without its whole signal.
    pub fn expose_rows(
        &self,
        width: usize,
        first_row: usize,
        signal: &[f32],
        seed: u64,
        out: &mut [u16],
    ) {
        let w = width;
        assert!(matches!(self.bits, 8 | 12 | 16), "8, 12 or 16 bits");
        assert_eq!(signal.len(), out.len(), "a signal value per output sample");
        let max = f64::from((1u32 << self.bits) - 1);
        let scale = max / FULL_SCALE;
        let read2 = (self.read_noise * self.read_noise) as f32;
        let shot = self.shot_gain as f32;
        let (scale, max) = (scale as f32, max as f32);
        let (full, inv_gamma) = (FULL_SCALE as f32, (1.0 / self.gamma) as f32);
        let linear = self.gamma == 1.0;
        // Shot and read noise: variance gain·I + read².
        let noisy = move |s: f32, z: f32| {
            let s = s.max(0.0);
            (s + (shot * s + read2).sqrt() * z).max(0.0)
        };
        // Round to nearest (ties to even) without the libm call or a saturating cast, so it
        // vectorises: adding 2²³ to v ∈ [0, 2¹⁶] leaves round(v) in the mantissa's low bits.
        let quantise =
            move |v: f32| (((v * scale).min(max) + 8_388_608.0).to_bits() & 0x7F_FFFF) as u16;
        out.par_chunks_mut(w)
            .zip(signal.par_chunks(w))
            .enumerate()
            .for_each(|(i, (out, inp))| {
                let y = first_row + i;
                let mut rng = SmallRng::seed_from_u64(splitmix64(seed ^ splitmix64(y as u64)));
                // The filters of this row: even and odd columns (chunks start on even ones).
                let filter = self
                    .cfa
                    .map_or([1.0; 2], |c| [c[2 * (y & 1)], c[2 * (y & 1) + 1]]);
                let mut z = [0f32; 256];
                for (out, inp) in out.chunks_mut(z.len()).zip(inp.chunks(z.len())) {
                    // The deviates first, then arithmetic the compiler vectorises (the
                    // sampler's calls would otherwise serialise the whole loop).
                    for z in &mut z[..out.len()] {
                        *z = rng.sample::<f64, _>(StandardNormal) as f32;
                    }
                    if self.cfa.is_some() {
                        for (x, ((o, &s), &z)) in out.iter_mut().zip(inp).zip(&z).enumerate() {
                            let v = noisy(s * filter[x & 1], z);
                            *o = match linear {
                                true => quantise(v),
                                false => quantise(full * (v / full).powf(inv_gamma)),
                            };
                        }
                    } else if linear {
                        for ((o, &s), &z) in out.iter_mut().zip(inp).zip(&z) {
                            *o = quantise(noisy(s, z));
                        }
                    } else {
                        for ((o, &s), &z) in out.iter_mut().zip(inp).zip(&z) {
                            *o = quantise(full * (noisy(s, z) / full).powf(inv_gamma));
                        }
                    }
                }
            });
    }

    /// The whole chain: [`Sensor::optics`] then [`Sensor::expose`].
    pub fn capture(&self, size: ImageSize, irradiance: &[f32], seed: u64) -> Frame {
        self.expose(size, &self.optics(size, irradiance), seed)
    }
}

/// Separable Gaussian blur, kernel radius ⌈4σ⌉, edges replicated.
pub fn gaussian_blur(img: &[f32], w: usize, h: usize, sigma: f64) -> Vec<f32> {
    let r = (4.0 * sigma).ceil() as usize;
    let mut k: Vec<f32> = (0..=2 * r)
        .map(|i| {
            let d = i as f64 - r as f64;
            (-0.5 * d * d / (sigma * sigma)).exp() as f32
        })
        .collect();
    let s: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    // Horizontal.
    let mut tmp = vec![0.0f32; w * h];
    tmp.par_chunks_mut(w)
        .zip(img.par_chunks(w))
        .for_each(|(out, inp)| {
            let mut padded = Vec::with_capacity(w + 2 * r);
            padded.extend(std::iter::repeat_n(inp[0], r));
            padded.extend_from_slice(inp);
            padded.extend(std::iter::repeat_n(inp[w - 1], r));
            // Tap by tap across the row, so the products vectorise.
            out.fill(0.0);
            for (i, kv) in k.iter().enumerate() {
                for (o, s) in out.iter_mut().zip(&padded[i..i + w]) {
                    *o += kv * s;
                }
            }
        });
    // Vertical.
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (i, kv) in k.iter().enumerate() {
            let yy = (y + i).saturating_sub(r).min(h - 1);
            let src = &tmp[yy * w..(yy + 1) * w];
            for (o, s) in row.iter_mut().zip(src) {
                *o += kv * s;
            }
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(level: f32, size: ImageSize) -> Vec<f32> {
        vec![level; size.pixels()]
    }

    const SIZE: ImageSize = ImageSize {
        width: 400,
        height: 300,
    };

    fn sensor() -> Sensor {
        Sensor {
            psf_sigma: 0.8,
            vignetting: 0.0,
            shot_gain: 0.1,
            read_noise: 2.0,
            gamma: 1.0,
            bits: 8,
            cfa: None,
        }
    }

    #[test]
    fn a_colour_filter_scales_each_cell_position_and_its_noise_follows() {
        // Responses 0.5, 1 / 1, 0.75 on a flat field of 160 DN.
        let s = Sensor {
            cfa: Some([0.5, 1.0, 1.0, 0.75]),
            ..sensor()
        };
        let f = s.capture(SIZE, &flat(160.0, SIZE), 3);
        let w = SIZE.width as usize;
        for (pos, response) in [0.5f64, 1.0, 1.0, 0.75].into_iter().enumerate() {
            let values: Vec<f64> = f
                .data
                .iter()
                .enumerate()
                .filter(|(i, _)| 2 * ((i / w) & 1) + ((i % w) & 1) == pos)
                .map(|(_, &v)| f64::from(v))
                .collect();
            let n = values.len() as f64;
            let mean = values.iter().sum::<f64>() / n;
            let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
            // The filtered signal carries its own shot noise: σ² = gain·r·I + read² + 1/12.
            let level = 160.0 * response;
            let model = 0.1 * level + 4.0 + 1.0 / 12.0;
            assert!(
                (mean - level).abs() < 5.0 * (model / n).sqrt(),
                "{pos}: mean {mean}"
            );
            assert!(
                (var - model).abs() < 5.0 * model * (2.0 / n).sqrt(),
                "{pos}: var {var} vs {model}"
            );
        }
    }

    #[test]
    fn noise_of_a_flat_field_follows_the_model() {
        let level = 100.0;
        let f = sensor().capture(SIZE, &flat(level, SIZE), 7);
        let n = f.data.len() as f64;
        let mean = f.data.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let var = f
            .data
            .iter()
            .map(|&v| (f64::from(v) - mean).powi(2))
            .sum::<f64>()
            / (n - 1.0);
        // Model: σ² = gain·I + read² = 10 + 4, plus 1/12 DN² of rounding. The PSF acts on
        // the noise-free signal only, so pixels are independent: the sample mean has standard
        // error √(14/n) = 0.011 DN and the sample variance var·√(2/n) = 0.057 DN²;
        // allow 5 standard errors.
        let model = 0.1 * f64::from(level) + 4.0 + 1.0 / 12.0;
        assert!(
            (mean - f64::from(level)).abs() < 5.0 * (model / n).sqrt(),
            "mean {mean}"
        );
        assert!(
            (var - model).abs() < 5.0 * model * (2.0 / n).sqrt(),
            "var {var} vs {model}"
        );
    }

    #[test]
    fn a_frame_exposed_band_by_band_is_the_whole_frame() {
        let img: Vec<f32> = (0..SIZE.pixels()).map(|k| (k % 241) as f32).collect();
        let s = Sensor {
            cfa: Some([0.5, 1.0, 1.0, 0.75]),
            gamma: 2.2,
            ..sensor()
        };
        let whole = s.expose(SIZE, &img, 11);
        let w = SIZE.width as usize;
        let mut bands = vec![0u16; img.len()];
        // Bands of 7 rows: odd starts, so the colour filter's row parity is the row's own.
        for (i, out) in bands.chunks_mut(7 * w).enumerate() {
            let signal = &img[i * 7 * w..][..out.len()];
            s.expose_rows(w, i * 7, signal, 11, out);
        }
        assert_eq!(whole.data, bands);
    }

    #[test]
    fn seeds_reproduce_and_differ() {
        let img = flat(50.0, SIZE);
        let a = sensor().capture(SIZE, &img, 3);
        assert_eq!(a, sensor().capture(SIZE, &img, 3));
        let b = sensor().capture(SIZE, &img, 4);
        // Two independent noise fields of σ ≈ 2.6 DN agree in well under half the pixels.
        let same = a.data.iter().zip(&b.data).filter(|(x, y)| x == y).count();
        assert!(same < a.data.len() / 2, "{same} equal pixels");
    }

    #[test]
    fn deeper_frames_quantise_the_same_signal_finer() {
        let img: Vec<f32> = (0..SIZE.pixels()).map(|k| (k % 251) as f32).collect();
        let s8 = sensor();
        let a = s8.capture(SIZE, &img, 9);
        for bits in [12u8, 16] {
            let b = Sensor { bits, ..s8 }.capture(SIZE, &img, 9);
            assert_eq!(b.bits, bits);
            let scale = f64::from((1u32 << bits) - 1) / 255.0;
            let top = b.data.iter().max().copied().unwrap_or(0);
            assert!(f64::from(top) > 200.0 * scale, "{bits}: max {top}");
            // Same noise realisation: the deep code / scale is within half an 8-bit step of
            // the 8-bit code, plus half a deep step of its own rounding.
            for (x, y) in a.data.iter().zip(&b.data) {
                let v = f64::from(*y) / scale;
                assert!((v - f64::from(*x)).abs() <= 0.5 + 0.5 / scale, "{x} vs {y}");
            }
        }
    }

    #[test]
    fn blur_keeps_the_mean_and_spreads_a_point_as_sigma() {
        let (w, h) = (41, 41);
        let mut img = vec![0.0f32; w * h];
        img[20 * w + 20] = 1.0;
        let b = gaussian_blur(&img, w, h, 1.5);
        let sum: f64 = b.iter().map(|&v| f64::from(v)).sum();
        let var_x: f64 = b
            .iter()
            .enumerate()
            .map(|(k, &v)| f64::from(v) * ((k % w) as f64 - 20.0).powi(2))
            .sum();
        assert!((sum - 1.0).abs() < 1e-5);
        // Truncation at 4σ removes 6e-5 of the mass, lowering the variance by < 1e-3 σ².
        assert!((var_x - 2.25).abs() < 3e-3, "{var_x}");
    }

    #[test]
    fn vignetting_darkens_corners_by_the_given_fraction() {
        let s = Sensor {
            psf_sigma: 0.0,
            vignetting: 0.3,
            ..sensor()
        };
        let o = s.optics(SIZE, &flat(100.0, SIZE));
        assert!((o[0] - 70.0).abs() < 1e-3);
        let w = SIZE.width as usize;
        assert!(o[150 * w + 200] > 99.9);
    }
}
