//! The stack decoder (docs/design.md §6): one camera's frames in sequence order → per projector
//! wrapped phases, modulation, unwrapped and fused (u, v), reliability and validity; the
//! ambient image; the per-pixel noise model measured from the stack itself.
//!
//! Streaming: frames arrive one by one. The frames of the current (direction, count) group —
//! N of the stack's G·N frames — are kept as they came (8 or 16 bit); when a group is
//! complete its DFT is taken on all cores in strips of 64 pixels whose sums stay in L1 (per
//! pixel: the mean and, for each projector frequency f_p, X_f = Σ I_s·e^{i2πf_p s/N}, with
//! steps s and N − s paired so that the P frequencies share one sum and one difference per
//! pair), and only the wrapped phase and modulation per projector are kept (16 bit each).
//! Accumulating the DFT over the whole image frame by frame would stream (2P+1) f32
//! accumulators through memory for every frame (≈ 130 MB per 1920×1200 frame at P = 3,
//! ≈ 12 GB per stack), which is bandwidth-bound; the group buffer (N 8-bit frames) is smaller
//! than those accumulators, and the stack is never held twice.
//!
//! Noise: every group measures the same mean level A, so the spread of the G group means at
//! a pixel estimates σ_I²/N with G − 1 degrees of freedom (free of projector harmonics); a
//! fit σ_I² = a + b·A over all unsaturated pixels gives the read + shot noise model.

use super::unwrap::Constellation;
use crate::pattern::MAX_COUNTS;
use crate::pattern::{pattern_harmonic, Direction, Sequence};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f32::consts::{FRAC_PI_2, PI, TAU};

/// A single-channel image of linear floating-point values (the same type as
/// `detect::GrayImage`).
pub type FloatImage = image::ImageBuffer<image::Luma<f32>, Vec<f32>>;

/// A camera sample type the decoder accepts.
pub trait Sample: Copy + Default + Send + Sync + 'static {
    /// The value as f32 (DN).
    fn value(self) -> f32;
}

impl Sample for u8 {
    fn value(self) -> f32 {
        f32::from(self)
    }
}

impl Sample for u16 {
    fn value(self) -> f32 {
        f32::from(self)
    }
}

impl Sample for f32 {
    fn value(self) -> f32 {
        self
    }
}

/// A borrowed camera frame: row-major pixels, `width` per row.
#[derive(Clone, Copy, Debug)]
pub struct FrameRef<'a, T> {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Pixel values, row-major (exactly width × height of them in a whole frame).
    pub pixels: &'a [T],
}

impl<'a, T: image::Primitive> From<&'a image::ImageBuffer<image::Luma<T>, Vec<T>>>
    for FrameRef<'a, T>
{
    fn from(img: &'a image::ImageBuffer<image::Luma<T>, Vec<T>>) -> Self {
        FrameRef {
            width: img.width(),
            height: img.height(),
            pixels: img.as_raw(),
        }
    }
}

/// A stack that does not match its sequence.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DecodeError {
    /// An empty frame size or a full scale that is not a positive number.
    #[error("camera {camera}: frames of {width}×{height} with full scale {full_scale} cannot be decoded")]
    Format {
        /// Camera label.
        camera: String,
        /// Frame width.
        width: u32,
        /// Frame height.
        height: u32,
        /// Saturation level.
        full_scale: f32,
    },
    /// The stack would need more memory than [`crate::limits::MAX_DECODER_BYTES`].
    #[error(
        "camera {camera}: decoding {width}×{height} frames of {steps} steps for {projectors} \
         projectors needs {bytes} bytes: at most {} (limits::MAX_DECODER_BYTES)",
        crate::limits::MAX_DECODER_BYTES
    )]
    TooLarge {
        /// Camera label.
        camera: String,
        /// Frame width.
        width: u32,
        /// Frame height.
        height: u32,
        /// Phase steps.
        steps: u32,
        /// Projectors.
        projectors: usize,
        /// Bytes it would hold.
        bytes: u64,
    },
    /// A frame arrived out of order: frame `expected` is missing.
    #[error("camera {camera}: frame {got} arrived while frame {expected} was due (frame {expected} is missing or out of order)")]
    OutOfOrder {
        /// Camera label.
        camera: String,
        /// The frame that was due.
        expected: usize,
        /// The frame that arrived.
        got: usize,
    },
    /// A frame past the end of the sequence.
    #[error("camera {camera}: frame {frame} is beyond the sequence's {count} frames")]
    TooMany {
        /// Camera label.
        camera: String,
        /// The frame index.
        frame: usize,
        /// Frames in the sequence.
        count: usize,
    },
    /// A frame of another size than the stack.
    #[error(
        "camera {camera}: frame {frame} is {got_width}×{got_height}, the stack is {width}×{height}"
    )]
    Size {
        /// Camera label.
        camera: String,
        /// The frame index.
        frame: usize,
        /// The frame's width.
        got_width: u32,
        /// The frame's height.
        got_height: u32,
        /// The stack's width.
        width: u32,
        /// The stack's height.
        height: u32,
    },
    /// A frame with fewer (or more) pixel values than its size says.
    #[error(
        "camera {camera}: frame {frame} is truncated: {got} pixel values for {expected} pixels"
    )]
    Truncated {
        /// Camera label.
        camera: String,
        /// The frame index.
        frame: usize,
        /// Values received.
        got: usize,
        /// Values expected.
        expected: usize,
    },
    /// The stack ended early.
    #[error("camera {camera}: stack ends after {received} frames, the sequence has {count} (frame {received} is missing)")]
    Incomplete {
        /// Camera label.
        camera: String,
        /// Frames received.
        received: usize,
        /// Frames in the sequence.
        count: usize,
    },
}

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
    width: u32,
    height: u32,
    bits: Vec<bool>,
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
    fundamental: f32,
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
}

#[derive(Clone, Copy, Default)]
struct PixelStats {
    /// Mean level of the first group.
    first_mean: f32,
    /// Σ of the other groups' mean minus the first group's.
    sum_dev: f32,
    /// Σ of those deviations squared.
    sum_dev2: f32,
    saturated: bool,
}

/// Streaming decoder of one camera's stack.
pub struct Decoder<T: Sample> {
    seq: Sequence,
    camera: String,
    width: u32,
    height: u32,
    full_scale: f32,
    next: usize,
    /// The current group's frames, N × pixels.
    frames: Vec<T>,
    /// (cos, sin) of 2π·f_p·s/N at [p·N + s].
    twiddles: Vec<[f32; 2]>,
    /// Per completed group: per candidate pixel and projector (wrapped phase, modulation),
    /// 16 bit.
    groups: Vec<Vec<u16>>,
    /// Per pixel: its slot among the candidates (pixels where some projector's modulation
    /// in the first group reached [`CANDIDATE`] of full scale), or `u32::MAX`.
    slots: Vec<u32>,
    /// Per pixel and projector: Σ over groups of the quantised B² (every pixel, for the
    /// modulation and ambient images).
    bsq: Vec<f32>,
    pixels: Vec<PixelStats>,
    columns: Constellation,
    rows: Constellation,
}

/// Modulation quantisation: 2^15 steps per full scale (B ≤ 2·full scale).
const B_STEPS: f32 = 32768.0;

/// Fraction of full scale a pixel's first-group modulation must reach, for some projector,
/// for its phases to be kept: half the validity floor of 3 %.
const CANDIDATE: f32 = 0.015;

/// Pixels per strip in the DFT kernel.
const CHUNK: usize = 64;

/// 1.5·2^23: x + ROUNDER, for 0 ≤ x < 2^22, holds round(x) in its low mantissa bits.
const ROUNDER: f32 = 12_582_912.0;

impl<T: Sample> Decoder<T> {
    /// A decoder for `camera` (a label used in errors) with frames of `width` × `height`
    /// whose saturation level is `full_scale` (255 for 8 bit, 4095 for 12 bit, …); fails on
    /// an empty size or a full scale that is not positive.
    pub fn new(
        seq: &Sequence,
        camera: impl Into<String>,
        width: u32,
        height: u32,
        full_scale: f32,
    ) -> Result<Self, DecodeError> {
        let camera = camera.into();
        if width == 0 || height == 0 || !(full_scale.is_finite() && full_scale > 0.0) {
            return Err(DecodeError::Format {
                camera,
                width,
                height,
                full_scale,
            });
        }
        let npx = width as usize * height as usize;
        let n = seq.steps() as usize;
        let projectors = seq.projectors().len();
        // The group's frames, B² sums and statistics, and per group a 16-bit phase and
        // modulation per projector and pixel.
        let per_pixel = n * std::mem::size_of::<T>()
            + 4 * projectors
            + std::mem::size_of::<PixelStats>()
            + seq.groups() * 4 * projectors;
        let bytes = (npx as u64).saturating_mul(per_pixel as u64);
        if bytes > crate::limits::MAX_DECODER_BYTES {
            return Err(DecodeError::TooLarge {
                camera,
                width,
                height,
                steps: seq.steps(),
                projectors,
                bytes,
            });
        }
        let twiddles = seq
            .projectors()
            .iter()
            .flat_map(|code| {
                (0..n).map(move |s| {
                    let a = std::f64::consts::TAU * ((code.frequency as usize * s) % n) as f64
                        / n as f64;
                    [a.cos() as f32, a.sin() as f32]
                })
            })
            .collect();
        let cons =
            |d| Constellation::new(seq.counts(d)).expect("a validated sequence has valid counts");
        Ok(Decoder {
            seq: seq.clone(),
            camera,
            width,
            height,
            full_scale,
            next: 0,
            frames: vec![T::default(); n * npx],
            twiddles,
            groups: Vec::with_capacity(seq.groups()),
            slots: Vec::new(),
            bsq: vec![0.0; npx * seq.projectors().len()],
            pixels: vec![PixelStats::default(); npx],
            columns: cons(Direction::Columns),
            rows: cons(Direction::Rows),
        })
    }

    /// Bytes the decoder holds now: the group's frame buffer, the candidates' 16-bit phases
    /// and modulations, the per-pixel slots, B² sums and statistics (once every group is in,
    /// its peak before [`Self::finish`]).
    pub fn buffer_bytes(&self) -> usize {
        self.frames.len() * std::mem::size_of::<T>()
            + self.groups.iter().map(|g| g.len() * 2).sum::<usize>()
            + self.slots.len() * 4
            + self.bsq.len() * 4
            + self.pixels.len() * std::mem::size_of::<PixelStats>()
    }

    /// Feed frame k (frames must come in sequence order, each exactly once).
    pub fn push_frame(&mut self, k: usize, frame: FrameRef<'_, T>) -> Result<(), DecodeError> {
        let count = self.seq.frame_count();
        if k >= count {
            return Err(DecodeError::TooMany {
                camera: self.camera.clone(),
                frame: k,
                count,
            });
        }
        if k != self.next {
            return Err(DecodeError::OutOfOrder {
                camera: self.camera.clone(),
                expected: self.next,
                got: k,
            });
        }
        if (frame.width, frame.height) != (self.width, self.height) {
            return Err(DecodeError::Size {
                camera: self.camera.clone(),
                frame: k,
                got_width: frame.width,
                got_height: frame.height,
                width: self.width,
                height: self.height,
            });
        }
        let npx = self.width as usize * self.height as usize;
        if frame.pixels.len() != npx {
            return Err(DecodeError::Truncated {
                camera: self.camera.clone(),
                frame: k,
                got: frame.pixels.len(),
                expected: npx,
            });
        }
        let n = self.seq.steps() as usize;
        let step = k % n;
        self.frames[step * npx..(step + 1) * npx].copy_from_slice(frame.pixels);
        self.next += 1;
        if step == n - 1 {
            self.close_group(k / n);
            if self.next == count {
                // The last group is in: the frame buffer is not needed any more.
                self.frames = Vec::new();
            }
        }
        Ok(())
    }

    /// Take the DFT of the completed group g, row by row on all cores.
    fn close_group(&mut self, g: usize) {
        let w = self.width as usize;
        let npx = w * self.height as usize;
        let n = self.seq.steps() as usize;
        let np = self.seq.projectors().len();
        let fs = self.full_scale;
        let b_scale = B_STEPS / fs;
        let frames = &self.frames;
        let twiddles = &self.twiddles;
        let mut out = vec![0u16; npx * np * 2];
        let inv_n = 1.0 / n as f32;
        out.par_chunks_mut(w * np * 2)
            .zip(self.pixels.par_chunks_mut(w))
            .enumerate()
            .for_each_init(
                || vec![0f32; (4 + 2 * np) * CHUNK],
                |scratch, (y, (out_row, stats_row))| {
                    // Strips of CHUNK pixels: the sums stay in L1 over the N frames.
                    for x0 in (0..w).step_by(CHUNK) {
                        let len = CHUNK.min(w - x0);
                        let (sum, rest) = scratch.split_at_mut(CHUNK);
                        let (diff, rest) = rest.split_at_mut(CHUNK);
                        let (peak, rest) = rest.split_at_mut(CHUNK);
                        let (dc, reim) = rest.split_at_mut(CHUNK);
                        let sum: &mut [f32; CHUNK] = sum.try_into().expect("CHUNK");
                        let diff: &mut [f32; CHUNK] = diff.try_into().expect("CHUNK");
                        let peak: &mut [f32; CHUNK] = peak.try_into().expect("CHUNK");
                        let dc: &mut [f32; CHUNK] = dc.try_into().expect("CHUNK");
                        let row = |s: usize| &frames[s * npx + y * w + x0..][..len];
                        // Step 0 starts every sum (its twiddle is 1).
                        sum.fill(0.0);
                        for (v, &x) in sum.iter_mut().zip(row(0)) {
                            *v = x.value();
                        }
                        dc.copy_from_slice(sum);
                        peak.copy_from_slice(sum);
                        for sums in reim.chunks_exact_mut(2 * CHUNK) {
                            let (re, im) = sums.split_at_mut(CHUNK);
                            re.copy_from_slice(dc);
                            im.fill(0.0);
                        }
                        // Steps s and N − s share |twiddle|: e^{±i2πfs/N}, so
                        // X_f += (I_s + I_{N−s})·cos + i·(I_s − I_{N−s})·sin.
                        for s in 1..n.div_ceil(2) {
                            diff.fill(0.0);
                            for (v, &x) in diff.iter_mut().zip(row(n - s)) {
                                *v = x.value();
                            }
                            sum.fill(0.0);
                            for (v, &x) in sum.iter_mut().zip(row(s)) {
                                *v = x.value();
                            }
                            for i in 0..CHUNK {
                                let (a, b) = (sum[i], diff[i]);
                                peak[i] = if a > peak[i] { a } else { peak[i] };
                                peak[i] = if b > peak[i] { b } else { peak[i] };
                                sum[i] = a + b;
                                diff[i] = a - b;
                                dc[i] += a + b;
                            }
                            for (p, sums) in reim.chunks_exact_mut(2 * CHUNK).enumerate() {
                                let [c, sn] = twiddles[p * n + s];
                                let (re, im) = sums.split_at_mut(CHUNK);
                                let re: &mut [f32; CHUNK] = re.try_into().expect("CHUNK");
                                let im: &mut [f32; CHUNK] = im.try_into().expect("CHUNK");
                                for i in 0..CHUNK {
                                    re[i] += sum[i] * c;
                                    im[i] += diff[i] * sn;
                                }
                            }
                        }
                        if n % 2 == 0 {
                            // The middle step's twiddle is (−1)^f.
                            let s = n / 2;
                            sum.fill(0.0);
                            for (v, &x) in sum.iter_mut().zip(row(s)) {
                                *v = x.value();
                            }
                            for i in 0..CHUNK {
                                peak[i] = if sum[i] > peak[i] { sum[i] } else { peak[i] };
                                dc[i] += sum[i];
                            }
                            for (p, sums) in reim.chunks_exact_mut(2 * CHUNK).enumerate() {
                                let c = twiddles[p * n + s][0];
                                for (r, &v) in sums[..CHUNK].iter_mut().zip(sum.iter()) {
                                    *r += v * c;
                                }
                            }
                        }
                        // Saturation is rare: look per pixel only when the strip reached it.
                        if peak.iter().any(|&m| m >= fs) {
                            for s in 0..n {
                                for (st, &v) in stats_row[x0..x0 + len].iter_mut().zip(row(s)) {
                                    st.saturated |= v.value() >= fs;
                                }
                            }
                        }
                        for (st, &d) in stats_row[x0..x0 + len].iter_mut().zip(dc.iter()) {
                            // A = X_0/N (docs/design.md §6).
                            let a = d * inv_n;
                            if g == 0 {
                                st.first_mean = a;
                            } else {
                                let dev = a - st.first_mean;
                                st.sum_dev += dev;
                                st.sum_dev2 += dev * dev;
                            }
                        }
                        for (p, sums) in reim.chunks_exact(2 * CHUNK).enumerate() {
                            let (re, im) = sums.split_at(CHUNK);
                            let re: &[f32; CHUNK] = re.try_into().expect("CHUNK");
                            let im: &[f32; CHUNK] = im.try_into().expect("CHUNK");
                            // φ_p = arg X_{f_p}, B_p = 2|X_{f_p}|/N (docs/design.md §6), as 16-bit
                            // fractions of a cycle and of full scale (rounded: both ≥ 0; a
                            // phase of 1 cycle wraps to 0).
                            let mut psi = [0u16; CHUNK];
                            let mut bq = [0u16; CHUNK];
                            for i in 0..CHUNK {
                                let ph = phase_cycles(im[i], re[i]);
                                let b = 2.0 * (re[i] * re[i] + im[i] * im[i]).sqrt() * inv_n;
                                // Rounded to 16 bits by adding 1.5·2^23: the integer lands in
                                // the low mantissa bits (a phase of 1 cycle wraps to 0).
                                psi[i] = (ph * 65536.0 + ROUNDER).to_bits() as u16;
                                bq[i] = ((b * b_scale).min(65535.0) + ROUNDER).to_bits() as u16;
                            }
                            let o = &mut out_row[x0 * np * 2..(x0 + len) * np * 2];
                            for ((pair, &ph), &b) in o.chunks_exact_mut(np * 2).zip(&psi).zip(&bq) {
                                pair[p * 2] = ph;
                                pair[p * 2 + 1] = b;
                            }
                        }
                    }
                },
            );
        // Σ B² of every pixel; then keep (ψ, B) of the candidates only (docs/design.md §6: a pixel
        // needs B ≥ 3 % of full scale to be valid, so one below half that in the first group
        // cannot be).
        let inv_b_scale = fs / B_STEPS;
        self.bsq
            .par_chunks_mut(w * np)
            .zip(out.par_chunks(w * np * 2))
            .for_each(|(acc, o)| {
                for (a, pair) in acc.iter_mut().zip(o.chunks_exact(2)) {
                    let b = f32::from(pair[1]) * inv_b_scale;
                    *a += b * b;
                }
            });
        if g == 0 {
            let floor = (CANDIDATE * B_STEPS).round() as u16;
            let mut next = 0u32;
            self.slots = out
                .chunks_exact(np * 2)
                .map(|px| {
                    if px.chunks_exact(2).any(|pair| pair[1] >= floor) {
                        next += 1;
                        next - 1
                    } else {
                        u32::MAX
                    }
                })
                .collect();
        }
        let kept: Vec<u16> = out
            .chunks_exact(np * 2)
            .zip(&self.slots)
            .filter(|(_, &slot)| slot != u32::MAX)
            .flat_map(|(px, _)| px.iter().copied())
            .collect();
        self.groups.push(kept);
    }

    /// Unwrap, fuse and judge every pixel; fails when frames are missing.
    pub fn finish(self) -> Result<DecodedStack, DecodeError> {
        let count = self.seq.frame_count();
        if self.next != count {
            return Err(DecodeError::Incomplete {
                camera: self.camera,
                received: self.next,
                count,
            });
        }
        let Decoder {
            seq,
            camera,
            width,
            height,
            full_scale,
            frames,
            groups,
            slots,
            bsq: bsq_all,
            pixels,
            columns,
            rows,
            ..
        } = self;
        drop(frames);
        let w = width as usize;
        let n = seq.steps() as f64;
        let ng = seq.groups();
        let np = seq.projectors().len();

        let mean_and_var = |st: &PixelStats| {
            // Ā = A_0 + Σd/G; Σ_g (A_g − Ā)² = Σd² − (Σd)²/G; σ_I² ≈ N·that/(G − 1).
            let g = ng as f64;
            let (sd, sd2) = (f64::from(st.sum_dev), f64::from(st.sum_dev2));
            let mean = f64::from(st.first_mean) + sd / g;
            let var = n * (sd2 - sd * sd / g).max(0.0) / (g - 1.0);
            (mean, var)
        };
        // Least-squares line σ_I² = a + b·A over unsaturated pixels.
        let sums = pixels
            .par_chunks(4096)
            .map(|chunk| {
                let mut s = [0f64; 5];
                for st in chunk.iter().filter(|st| !st.saturated) {
                    let (a, v) = mean_and_var(st);
                    s[0] += 1.0;
                    s[1] += a;
                    s[2] += a * a;
                    s[3] += v;
                    s[4] += a * v;
                }
                s
            })
            .reduce(|| [0f64; 5], |a, b| std::array::from_fn(|i| a[i] + b[i]));
        let noise = fit_noise(&sums);

        let codes = seq.projectors();
        let gammas: Vec<f64> = codes.iter().map(|c| c.response.effective_gamma()).collect();
        let fundamental: Vec<f32> = gammas
            .iter()
            .map(|&g| pattern_harmonic(g, 1) as f32)
            .collect();
        // Mean over fundamental: (γ+1)/(2γ) (docs/design.md §6).
        let mean_ratio: Vec<f32> = gammas
            .iter()
            .map(|&g| (pattern_harmonic(g, 0) / pattern_harmonic(g, 1)) as f32)
            .collect();
        let col_counts = seq.counts(Direction::Columns);
        let row_counts = seq.counts(Direction::Rows);
        let mc = col_counts.len();
        let half_spacing = [0.5 * columns.spacing() as f32, 0.5 * rows.spacing() as f32];
        let inv_b_scale = full_scale / B_STEPS;
        let min_b = 0.03 * full_scale;
        let n32 = n as f32;
        // σ_u = W/(2π)·√(2/N)·σ_I/√(Σ n_i² B_i²) for the weighted fusion (docs/design.md §6).
        let noise_gain = (2.0 / n32).sqrt();

        let npx = w * height as usize;
        let image = || vec![0f32; npx];
        let mut ambient = image();
        let mut saturated = vec![false; npx];
        let mut u_maps: Vec<Vec<f32>> = (0..np).map(|_| image()).collect();
        let mut v_maps: Vec<Vec<f32>> = (0..np).map(|_| image()).collect();
        let mut b_maps: Vec<Vec<f32>> = (0..np).map(|_| image()).collect();
        let mut r_maps: Vec<Vec<f32>> = (0..np).map(|_| image()).collect();
        let mut valid: Vec<Vec<bool>> = (0..np).map(|_| vec![false; npx]).collect();

        struct Row<'a> {
            ambient: &'a mut [f32],
            saturated: &'a mut [bool],
            u: Vec<&'a mut [f32]>,
            v: Vec<&'a mut [f32]>,
            b: Vec<&'a mut [f32]>,
            r: Vec<&'a mut [f32]>,
            valid: Vec<&'a mut [bool]>,
        }
        let mut out_rows: Vec<Row> = ambient
            .chunks_mut(w)
            .zip(saturated.chunks_mut(w))
            .map(|(a, s)| Row {
                ambient: a,
                saturated: s,
                u: Vec::with_capacity(np),
                v: Vec::with_capacity(np),
                b: Vec::with_capacity(np),
                r: Vec::with_capacity(np),
                valid: Vec::with_capacity(np),
            })
            .collect();
        for ((((um, vm), bm), rm), okm) in u_maps
            .iter_mut()
            .zip(v_maps.iter_mut())
            .zip(b_maps.iter_mut())
            .zip(r_maps.iter_mut())
            .zip(valid.iter_mut())
        {
            for (row, ((((u, v), b), r), ok)) in out_rows.iter_mut().zip(
                um.chunks_mut(w)
                    .zip(vm.chunks_mut(w))
                    .zip(bm.chunks_mut(w))
                    .zip(rm.chunks_mut(w))
                    .zip(okm.chunks_mut(w)),
            ) {
                row.u.push(u);
                row.v.push(v);
                row.b.push(b);
                row.r.push(r);
                row.valid.push(ok);
            }
        }

        // Per projector: valid count, Σ B, Σ σ_I², Σ σ_φ², Σ σ_u², Σ σ_v².
        let stats = out_rows
            .into_par_iter()
            .enumerate()
            .map(|(y, mut row)| {
                let mut acc = vec![[0f64; 6]; np];
                for x in 0..w {
                    let px = y * w + x;
                    let st = &pixels[px];
                    let (mean, _) = mean_and_var(st);
                    let sigma = noise.sigma(mean) as f32;
                    let var4 = 4.0 * sigma * sigma / n32;
                    row.saturated[x] = st.saturated;
                    let mut amb = mean as f32;
                    for p in 0..np {
                        let code = &codes[p];
                        // This pixel's (ψ, B) of projector p in every group.
                        let mut psi_g = [0f32; 2 * MAX_COUNTS];
                        let mut bsq_g = [0f32; 2 * MAX_COUNTS];
                        let bsq = bsq_all[px * np + p];
                        let slot = slots[px];
                        if slot != u32::MAX {
                            for (g, data) in groups.iter().enumerate() {
                                let o = &data[(slot as usize * np + p) * 2..][..2];
                                psi_g[g] = f32::from(o[0]) * (1.0 / 65536.0);
                                let b = f32::from(o[1]) * inv_b_scale;
                                bsq_g[g] = b * b;
                            }
                        }
                        let bmod = (bsq / ng as f32 - var4).max(0.0).sqrt();
                        amb -= mean_ratio[p] * bmod;
                        row.b[p][x] = bmod;
                        if st.saturated || slot == u32::MAX || bmod < min_b.max(5.0 * sigma) {
                            // Invalid whatever the phases say: not unwrapped.
                            row.u[p][x] = f32::NAN;
                            row.v[p][x] = f32::NAN;
                            row.r[p][x] = f32::NAN;
                            row.valid[p][x] = false;
                            continue;
                        }
                        let mut fused = [0f32; 2];
                        let mut dist = [0f32; 2];
                        let mut sigma_pos = [0f32; 2];
                        let mut clear_of_wrap = true;
                        for (d, (cons, counts, offset, size)) in [
                            (&columns, col_counts, 0, code.width),
                            (&rows, row_counts, mc, code.height),
                        ]
                        .into_iter()
                        .enumerate()
                        {
                            let m = counts.len();
                            let (ps, wt) = (&psi_g[offset..offset + m], &bsq_g[offset..offset + m]);
                            let info: f32 = counts
                                .iter()
                                .zip(wt)
                                .map(|(&ni, &w)| (ni * ni) as f32 * w)
                                .sum();
                            let un = cons.unwrap(ps, wt);
                            let size = size as f32;
                            fused[d] = un.position * size - 0.5;
                            dist[d] = un.distance;
                            let s_pos = size / TAU * noise_gain * sigma / info.sqrt();
                            sigma_pos[d] = s_pos;
                            // Distance to the wrap point t = 0 ≡ 1, in projector px.
                            let edge = un.position.min(1.0 - un.position) * size;
                            clear_of_wrap &= edge >= 6.0 * s_pos;
                        }
                        let ok =
                            dist[0] < half_spacing[0] && dist[1] < half_spacing[1] && clear_of_wrap;
                        row.u[p][x] = fused[0];
                        row.v[p][x] = fused[1];
                        row.r[p][x] = dist[0].max(dist[1]);
                        row.valid[p][x] = ok;
                        if ok {
                            let sphi = noise_gain * sigma / bmod;
                            let a = &mut acc[p];
                            a[0] += 1.0;
                            a[1] += f64::from(bmod);
                            a[2] += f64::from(sigma * sigma);
                            a[3] += f64::from(sphi * sphi);
                            a[4] += f64::from(sigma_pos[0] * sigma_pos[0]);
                            a[5] += f64::from(sigma_pos[1] * sigma_pos[1]);
                        }
                    }
                    row.ambient[x] = amb;
                }
                acc
            })
            .reduce(
                || vec![[0f64; 6]; np],
                |a, b| {
                    a.iter()
                        .zip(&b)
                        .map(|(x, y)| std::array::from_fn(|i| x[i] + y[i]))
                        .collect()
                },
            );
        drop(groups);
        drop(slots);
        drop(bsq_all);
        let to_image = |data: Vec<f32>| {
            FloatImage::from_raw(width, height, data).expect("map has width × height values")
        };
        let mask = |bits: Vec<bool>| Mask {
            width,
            height,
            bits,
        };
        let projectors = u_maps
            .into_iter()
            .zip(v_maps)
            .zip(b_maps)
            .zip(r_maps)
            .zip(valid)
            .enumerate()
            .map(|(p, ((((u, v), b), r), ok))| {
                let a = stats[p];
                let c = a[0].max(1.0);
                ProjectorMaps {
                    u: to_image(u),
                    v: to_image(v),
                    modulation: to_image(b),
                    reliability: to_image(r),
                    valid: mask(ok),
                    noise: PhaseNoise {
                        valid_pixels: a[0] as usize,
                        modulation: a[1] / c,
                        sigma_i: (a[2] / c).sqrt(),
                        sigma_phi: (a[3] / c).sqrt(),
                        sigma_u: (a[4] / c).sqrt(),
                        sigma_v: (a[5] / c).sqrt(),
                    },
                    fundamental: fundamental[p],
                }
            })
            .collect();
        Ok(DecodedStack {
            camera,
            ambient: to_image(ambient),
            saturated: mask(saturated),
            noise,
            projectors,
        })
    }
}

/// Fit σ_I² = a + b·A from the sums [count, ΣA, ΣA², Σs², ΣA·s²]; a flat line when the
/// levels do not spread.
fn fit_noise(s: &[f64; 5]) -> NoiseModel {
    let [cnt, sa, saa, sv, sav] = *s;
    if cnt < 2.0 {
        return NoiseModel {
            offset: 0.0,
            slope: 0.0,
            floor: 0.0,
        };
    }
    let mean_v = sv / cnt;
    let det = cnt * saa - sa * sa;
    let (offset, slope) = if det > 1e-9 * cnt * saa {
        let b = (cnt * sav - sa * sv) / det;
        ((sv - b * sa) / cnt, b)
    } else {
        (mean_v, 0.0)
    };
    NoiseModel {
        offset,
        slope,
        floor: 0.01 * mean_v,
    }
}

/// arg(re + i·im) in cycles, in [0, 1] (1 ≡ 0, for a zero angle approached from below);
/// |error| < 2·10⁻⁶ cycles (Abramowitz & Stegun 4.4.49 on the reduced octant, ≤ 10⁻⁵ rad).
#[inline(always)]
fn phase_cycles(im: f32, re: f32) -> f32 {
    // Selects, not branches (phases are random): the loop over a strip vectorises.
    let (ax, ay) = (re.abs(), im.abs());
    let (lo, hi) = (ax.min(ay), ax.max(ay));
    let a = lo / hi.max(f32::MIN_POSITIVE);
    let a2 = a * a;
    let r = a
        * (0.999_866
            + a2 * (-0.330_299_5 + a2 * (0.180_141 + a2 * (-0.085_133 + a2 * 0.020_835_1))));
    let r = if ay > ax { FRAC_PI_2 - r } else { r };
    let r = if re < 0.0 { PI - r } else { r };
    let c = r * (1.0 / TAU);
    if im < 0.0 {
        1.0 - c
    } else {
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_phase_matches_atan2() {
        let mut worst = 0f64;
        for i in 0..100_000 {
            let a = i as f64 * 0.000_062_831_853;
            for r in [1e-3, 1.0, 1e4] {
                let (s, c) = a.sin_cos();
                let got = f64::from(phase_cycles((r * s) as f32, (r * c) as f32));
                let mut e = got - a / std::f64::consts::TAU;
                e -= e.round();
                worst = worst.max(e.abs());
                assert!((0.0..=1.0).contains(&got));
            }
        }
        assert!(worst < 2e-6, "worst error {worst} cycles");
    }

    #[test]
    fn noise_fit_recovers_a_line() {
        let mut s = [0f64; 5];
        for i in 0..100 {
            let a = f64::from(i) * 2.0;
            let v = 4.0 + 0.1 * a;
            s = [s[0] + 1.0, s[1] + a, s[2] + a * a, s[3] + v, s[4] + a * v];
        }
        let m = fit_noise(&s);
        assert!((m.offset - 4.0).abs() < 1e-9 && (m.slope - 0.1).abs() < 1e-12);
        assert!((m.sigma(100.0) - 14f64.sqrt()).abs() < 1e-9);
    }
}
