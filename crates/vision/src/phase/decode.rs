//! The stack decoder (docs/design.md §6): one camera's frames in sequence order → per projector
//! wrapped phases, modulation, unwrapped and fused (u, v), reliability and validity; the
//! ambient image; the per-pixel noise model measured from the stack itself.
//!
//! Streaming: frames arrive one by one. The frames of the current (direction, count) group —
//! N of the stack's G·N frames — are kept as they came (8 or 16 bit; the last is read where
//! it arrives); when a group is complete its DFT is taken on all cores in strips of 64
//! pixels whose sums stay in L1 (per pixel: the mean and, for each projector frequency f_p,
//! X_f = Σ I_s·e^{i2πf_p s/N}, with steps s and N − s paired so that the P frequencies share
//! one sum and one difference per pair), and only the wrapped phase and modulation per
//! projector are kept (16 bit each), at the pixels that projector lights (its first-group
//! modulation at the candidate floor); where it does not, only a 16-bit root sum of its
//! modulations over the groups (for the ambient and modulation images).
//! Accumulating the DFT over the whole image frame by frame would stream (2P+1) f32
//! accumulators through memory for every frame (≈ 130 MB per 1920×1200 frame at P = 3,
//! ≈ 12 GB per stack), which is bandwidth-bound; the group buffer (N 8-bit frames) is smaller
//! than those accumulators, and the stack is never held twice.
//!
//! Noise: every group measures the same mean level A, so the spread of the G group means at
//! a pixel estimates σ_I²/N with G − 1 degrees of freedom (free of projector harmonics); a
//! fit σ_I² = a + b·A over all unsaturated pixels gives the read + shot noise model.

use super::check::{repair, CheckParams, StackSampler, StackVerdict};
use super::compact::{CompactStack, RowSink, Sink, NO_SLOT};
use super::maps::{DecodedStack, Mask, NoiseModel};
use super::unwrap::Constellation;
use hexcal_core::pattern::MAX_COUNTS;
use hexcal_core::pattern::{pattern_harmonic, Direction, ProjectorCode, Sequence};
use rayon::prelude::*;
use std::f32::consts::{FRAC_PI_2, PI, TAU};
use std::sync::Arc;

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
    /// The stack of a rig without projectors: one plain frame, no phase to decode.
    #[error("camera {camera}: a rig without projectors takes one plain frame per pose: nothing to decode")]
    CameraOnly {
        /// Camera label.
        camera: String,
    },
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
    /// The stack would need more memory than [`hexcal_core::limits::MAX_DECODER_BYTES`].
    #[error(
        "camera {camera}: decoding {width}×{height} frames of {steps} steps for {projectors} \
         projectors needs {bytes} bytes: at most {} (limits::MAX_DECODER_BYTES)",
        hexcal_core::limits::MAX_DECODER_BYTES
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

/// A pixel's level statistics over the groups (12 bytes; saturation is kept apart).
#[derive(Clone, Copy, Default)]
struct Level {
    /// Mean level of the first group.
    first_mean: f32,
    /// Σ of the other groups' mean minus the first group's.
    sum_dev: f32,
    /// Σ of those deviations squared.
    sum_dev2: f32,
}

/// Streaming decoder of one camera's stack.
pub struct Decoder<T: Sample> {
    seq: Sequence,
    camera: String,
    width: u32,
    height: u32,
    full_scale: f32,
    next: usize,
    /// The current group's frames but its last, (N − 1) × pixels (the last is read where it
    /// arrives).
    frames: Vec<T>,
    /// (cos, sin) of 2π·f_p·s/N at [p·N + s].
    twiddles: Vec<[f32; 2]>,
    /// Per completed group and projector: at the pixels it lights (see `lit`), in pixel
    /// order, the (wrapped phase, modulation) pair, 16 bit each.
    groups: Vec<Vec<Vec<u16>>>,
    /// Per projector: the pixels whose own modulation in the first group reached
    /// [`CANDIDATE`] of full scale (a bit each; no other pair can be valid), and per image
    /// row the slot of the row's first one (height + 1 entries). Filled by the first group.
    lit: Vec<LitPixels>,
    /// Per image row: the slot of its first candidate among all candidates in row-major
    /// order (height + 1 entries, the last one the number of candidates).
    row_slots: Vec<u32>,
    /// Per projector, at the pixels it does not light, in pixel order: √(Σ_g B_g²) over the
    /// groups so far in steps of [`UNLIT_STEP`] (rounded after each group; docs/design.md
    /// §6, "Memory"), for the modulation and ambient images (at a lit pixel Σ B² is rebuilt
    /// from the kept modulations). Filled by the first group.
    unlit_b: Vec<Vec<u16>>,
    levels: Vec<Level>,
    /// Pixels with a sample at full scale in some frame.
    saturated: Vec<bool>,
    columns: Arc<Constellation>,
    rows: Arc<Constellation>,
    /// The stack check's samples ([`super::check`]); taken by the final pass.
    sampler: Option<StackSampler>,
}

/// Modulation quantisation: 2^15 steps per full scale (B ≤ 2·full scale).
const B_STEPS: f32 = 32768.0;

/// Step of the unlit pixels' root sums √(Σ_g B_g²): a quarter of B's 16-bit step, so at most
/// 2^14 steps of B (half of full scale) in all, 13 times the candidate floor; a larger sum
/// (the light changed between groups at a pixel unlit in the first) is clamped there.
const UNLIT_STEP: f32 = 0.25;

/// Fraction of full scale a pixel's first-group modulation must reach, for some projector,
/// for its phases to be kept: half the validity floor of 3 %.
const CANDIDATE: f32 = 0.015;

/// Pixels per strip in the DFT kernel.
const CHUNK: usize = 64;

/// Image rows per band when a group is closed: the band's 16-bit (ψ, B) pairs are all that
/// is held besides the decoder's state (not a whole image's).
const BAND_ROWS: usize = 32;

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
        if seq.is_camera_only() {
            return Err(DecodeError::CameraOnly { camera });
        }
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
        // At most: the group's frames, 4 bytes of sums per projector, the statistics, and per
        // group a 16-bit phase and modulation per projector and pixel (as if every projector
        // lit every pixel).
        let per_pixel = n * std::mem::size_of::<T>()
            + 4 * projectors
            + std::mem::size_of::<Level>()
            + 2
            + seq.groups() * 4 * projectors;
        let check = (4 * super::check::MAX_BLOCKS * seq.frame_count() * 4) as u64;
        let bytes = (npx as u64)
            .saturating_mul(per_pixel as u64)
            .saturating_add(check);
        if bytes > hexcal_core::limits::MAX_DECODER_BYTES {
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
        let cons = |d| {
            Constellation::shared(seq.counts(d)).expect("a validated sequence has valid counts")
        };
        Ok(Decoder {
            seq: seq.clone(),
            camera,
            width,
            height,
            full_scale,
            next: 0,
            frames: super::pages::filled(T::default(), (n - 1) * npx),
            twiddles,
            groups: Vec::with_capacity(seq.groups()),
            row_slots: Vec::new(),
            lit: Vec::new(),
            unlit_b: Vec::new(),
            levels: super::pages::filled(Level::default(), npx),
            saturated: vec![false; npx],
            columns: cons(Direction::Columns),
            rows: cons(Direction::Rows),
            sampler: Some(StackSampler::new(seq, width, height, full_scale)),
        })
    }

    /// The decoder without its stack check (its verdict is then [`StackVerdict::unchecked`]):
    /// what `hexcal bench decode` times beside the checked decoder, to measure what the check
    /// costs within a decode.
    pub fn without_check(mut self) -> Self {
        self.sampler = None;
        self
    }

    /// Bytes the decoder holds now: the group's frame buffer, the lit pixels' 16-bit phases
    /// and modulations, the lit bits and row slots, the unlit pixels' root sums of B, level
    /// statistics and saturation flags (once every group is in, its peak before
    /// [`Self::finish`]).
    pub fn buffer_bytes(&self) -> usize {
        self.frames.len() * std::mem::size_of::<T>()
            + self
                .groups
                .iter()
                .flatten()
                .map(|g| g.len() * 2)
                .sum::<usize>()
            + self.lit.iter().map(LitPixels::bytes).sum::<usize>()
            + self.row_slots.len() * 4
            + self.unlit_b.iter().map(|v| v.len() * 2).sum::<usize>()
            + self.levels.len() * std::mem::size_of::<Level>()
            + self.saturated.len()
            + self.sampler.as_ref().map_or(0, StackSampler::bytes)
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
        // The check samples the frame on one core while the decoder takes it in.
        let mut sampler = self.sampler.take();
        let sample = || {
            if let Some(s) = sampler.as_mut() {
                s.push(k, &frame);
            }
        };
        rayon::join(sample, || self.take_in(k, frame.pixels));
        self.sampler = sampler;
        Ok(())
    }

    /// Store frame k's pixels, or close its group with them when it is the group's last.
    fn take_in(&mut self, k: usize, pixels: &[T]) {
        let (count, npx) = (self.seq.frame_count(), pixels.len());
        let n = self.seq.steps() as usize;
        let step = k % n;
        self.next += 1;
        if step < n - 1 {
            self.frames[step * npx..(step + 1) * npx].copy_from_slice(pixels);
        } else {
            self.close_group(k / n, pixels);
            if self.next == count {
                // The last group is in: the frame buffer is not needed any more.
                self.frames = Vec::new();
            }
        }
    }

    /// Take the DFT of the completed group g (its last frame `last`) on all cores: each
    /// projector's (ψ, B) pairs kept where it lights the pixel and B added to its root sums
    /// where it does not (the first group chooses the lit pixels).
    fn close_group(&mut self, g: usize, last: &[T]) {
        if g == 0 {
            self.close_first_group(last);
        } else {
            self.close_later_group(g, last);
        }
    }

    /// The first group, band by band of [`BAND_ROWS`] rows (each band's rows on all cores):
    /// its modulations choose each projector's lit pixels, where its pairs are kept; its B
    /// starts the root sums elsewhere.
    fn close_first_group(&mut self, last: &[T]) {
        let (w, h) = (self.width as usize, self.height as usize);
        let np = self.seq.projectors().len();
        self.lit = (0..np).map(|_| LitPixels::new(w * h)).collect();
        self.unlit_b = vec![Vec::new(); np];
        let mut kept: Vec<Vec<u16>> = vec![Vec::new(); np];
        let mut band = vec![0u16; BAND_ROWS.min(h) * w * np * 2];
        for y0 in (0..h).step_by(BAND_ROWS) {
            let rows = BAND_ROWS.min(h - y0);
            let out = &mut band[..rows * w * np * 2];
            self.band_dft(y0, last, out);
            mark_lit(out, np, y0 * w, &mut self.lit);
            self.keep_first_band(y0 * w, out, &mut kept);
        }
        kept.iter_mut().for_each(Vec::shrink_to_fit);
        self.unlit_b.iter_mut().for_each(Vec::shrink_to_fit);
        self.row_slots = row_slots(&self.lit, w, h);
        self.lit.iter_mut().for_each(|l| l.count_rows(w, h));
        self.groups.push(kept);
    }

    /// The first group's DFT (its `last` frame apart) of the rows from `y0` on (as many as
    /// `out` holds), row by row on all cores: per pixel and projector the 16-bit (ψ, B) pair
    /// into `out`; sets each pixel's level statistics and saturation flag.
    fn band_dft(&mut self, y0: usize, last: &[T], out: &mut [u16]) {
        let w = self.width as usize;
        let np = self.seq.projectors().len();
        // The statistics are taken out while the kernel reads the frames.
        let (mut levels, mut saturated) = self.take_statistics();
        let kernel = GroupKernel::new(self, 0, last);
        let pixels = y0 * w..y0 * w + out.len() / (np * 2);
        out.par_chunks_mut(w * np * 2)
            .zip(levels[pixels.clone()].par_chunks_mut(w))
            .zip(saturated[pixels].par_chunks_mut(w))
            .enumerate()
            .for_each_init(
                || Strip::new(np),
                |strip, (i, ((out_row, levels), saturated))| {
                    let out = RowOut {
                        pairs: out_row,
                        levels,
                        saturated,
                    };
                    kernel.row(y0 + i, strip, out)
                },
            );
        (self.levels, self.saturated) = (levels, saturated);
    }

    /// The level statistics and saturation flags, taken out of the decoder.
    fn take_statistics(&mut self) -> (Vec<Level>, Vec<bool>) {
        (
            std::mem::take(&mut self.levels),
            std::mem::take(&mut self.saturated),
        )
    }

    /// The first group's band of pixels from `first` on (their (ψ, B) pairs `out`),
    /// projector by projector in pixel order: the pair appended to `kept` where it lights
    /// the pixel, else its B as the first term of its unlit root sums.
    fn keep_first_band(&mut self, first: usize, out: &[u16], kept: &mut [Vec<u16>]) {
        let np = kept.len();
        // Each projector's lists are its own: the projectors run on all cores.
        kept.par_iter_mut()
            .zip(self.unlit_b.par_iter_mut())
            .zip(self.lit.par_iter())
            .enumerate()
            .for_each(|(p, ((kept, sums), lit))| {
                for (i, px) in out.chunks_exact(np * 2).enumerate() {
                    let pair = &px[p * 2..p * 2 + 2];
                    if lit.get(first + i) {
                        kept.extend_from_slice(pair);
                    } else {
                        sums.push(add_unlit(0, pair[1]));
                    }
                }
            });
    }

    /// A later group g (the lit pixels known): every row on all cores, its DFT then its
    /// pairs written straight to their slots in each projector's kept list and root sums
    /// (no band is held: a worker holds one row's pairs).
    fn close_later_group(&mut self, g: usize, last: &[T]) {
        let (w, h) = (self.width as usize, self.height as usize);
        let np = self.seq.projectors().len();
        let mut kept: Vec<Vec<u16>> = (self.lit.iter())
            .map(|l| vec![0u16; l.count() * 2])
            .collect();
        let (mut levels, mut saturated) = self.take_statistics();
        let mut unlit_b = std::mem::take(&mut self.unlit_b);
        let mut targets: Vec<RowTargets<'_>> = (0..h)
            .map(|_| RowTargets {
                kept: Vec::with_capacity(np),
                unlit: Vec::with_capacity(np),
            })
            .collect();
        for ((kept, sums), lit) in kept.iter_mut().zip(&mut unlit_b).zip(&self.lit) {
            let slots = &lit.row_slots;
            let lit_lens = slots.windows(2).map(|s| 2 * (s[1] - s[0]) as usize);
            let unlit_lens = slots.windows(2).map(|s| w - (s[1] - s[0]) as usize);
            for ((t, k), u) in targets
                .iter_mut()
                .zip(cut(kept, lit_lens))
                .zip(cut(sums, unlit_lens))
            {
                t.kept.push(k);
                t.unlit.push(u);
            }
        }
        let kernel = GroupKernel::new(self, g, last);
        let lit = &self.lit;
        targets
            .into_par_iter()
            .zip(levels.par_chunks_mut(w))
            .zip(saturated.par_chunks_mut(w))
            .enumerate()
            .for_each_init(
                || (Strip::new(np), vec![0u16; w * np * 2]),
                |(strip, out_row), (y, ((mut t, levels), saturated))| {
                    let out = RowOut {
                        pairs: out_row,
                        levels,
                        saturated,
                    };
                    kernel.row(y, strip, out);
                    keep_row(out_row, y * w, lit, &mut t);
                },
            );
        (self.levels, self.saturated, self.unlit_b) = (levels, saturated, unlit_b);
        self.groups.push(kept);
    }

    /// Unwrap, fuse and judge every pixel; fails when frames are missing.
    pub fn finish(self) -> Result<DecodedStack, DecodeError> {
        Ok(self.judge(true)?.into_decoded())
    }

    /// As [`Self::finish`], but held compactly: the ambient image and saturation flags for
    /// every pixel, the maps only at the candidate pixels (no modulation image).
    pub fn finish_compact(self) -> Result<CompactStack, DecodeError> {
        self.judge(false)
    }

    /// The final pass (noise fit, then every pixel unwrapped, fused and judged), with the
    /// modulation image of every pixel when `dense_modulation`.
    fn judge(mut self, dense_modulation: bool) -> Result<CompactStack, DecodeError> {
        let count = self.seq.frame_count();
        if self.next != count {
            return Err(DecodeError::Incomplete {
                camera: self.camera,
                received: self.next,
                count,
            });
        }
        drop(std::mem::take(&mut self.frames));
        let sampler = self.sampler.take();
        let np = self.seq.projectors().len();
        let (fundamental, mean_ratio) = harmonics(self.seq.projectors());
        let (w, h) = (self.width as usize, self.height as usize);
        let pass = |noise: NoiseModel, left_out: u32| {
            let mut sink = Sink::new(w * h, np, self.candidates(), dense_modulation);
            let judge = Judge::new(&self, noise, mean_ratio.clone(), left_out);
            let stats = judge.rows(sink.rows(w, &self.row_slots));
            (sink, stats)
        };
        // The verdict beside the final pass with every group and the noise from the group
        // means; a stack the verdict repairs, or whose noise it replaces, is passed again.
        let (verdict, (between, first)) = rayon::join(
            || {
                sampler.map_or_else(StackVerdict::unchecked, |s| {
                    s.verdict(&CheckParams::default())
                })
            },
            || {
                let between = self.noise_between();
                (between, pass(between, 0))
            },
        );
        let left_out = repair::left_out(&verdict);
        let noise = choose_noise(&verdict, between);
        let (sink, stats) = match left_out == 0 && noise == between {
            true => first,
            false => {
                drop(first);
                pass(noise, left_out)
            }
        };
        // The groups' phases, the B² sums and the statistics are dropped with the decoder.
        let saturated = Mask {
            width: self.width,
            height: self.height,
            bits: std::mem::take(&mut self.saturated),
        };
        Ok(sink.into_stack(
            std::mem::take(&mut self.camera),
            (noise, verdict),
            saturated,
            (0..w * h)
                .into_par_iter()
                .map(|i| self.is_candidate(i))
                .collect(),
            &stats,
            &fundamental,
        ))
    }

    /// The noise model from the spread of the group means (docs/design.md §6).
    fn noise_between(&self) -> NoiseModel {
        fit_noise(&noise_sums(
            &self.levels,
            &self.saturated,
            f64::from(self.seq.steps()),
            self.seq.groups(),
        ))
    }

    /// Whether pixel i is a candidate: some projector lights it.
    fn is_candidate(&self, i: usize) -> bool {
        self.lit.iter().any(|l| l.get(i))
    }

    /// Candidate pixels (0 before the first group is in).
    fn candidates(&self) -> usize {
        self.row_slots.last().map_or(0, |&n| n as usize)
    }
}

/// The noise model: `between`, from the spread of the group means (docs/design.md §6),
/// unless the check found the light or the board changing between groups, or repaired a
/// group, which that spread would count as noise; then the check's, measured within the
/// groups, or without the repaired ones (§6b).
fn choose_noise(verdict: &StackVerdict, between: NoiseModel) -> NoiseModel {
    use super::check::{StackFault, StackNote};
    let changed = verdict
        .notes
        .iter()
        .any(|n| matches!(n, StackNote::LightStep { .. } | StackNote::Repaired { .. }))
        || (verdict.faults.iter()).any(|f| matches!(f, StackFault::Motion { .. }));
    match changed {
        true => verdict.figures.noise,
        false => between,
    }
}

/// Marks in each projector's `lit` the pixels of `out` (P (ψ, B) pairs per pixel, from pixel
/// `first` of the image on) where its own B reached [`CANDIDATE`] of full scale; a pixel some
/// projector lights is a candidate.
fn mark_lit(out: &[u16], np: usize, first: usize, lit: &mut [LitPixels]) {
    let floor = (CANDIDATE * B_STEPS).round() as u16;
    for (i, px) in out.chunks_exact(np * 2).enumerate() {
        for (lit, pair) in lit.iter_mut().zip(px.chunks_exact(2)) {
            if pair[1] >= floor {
                lit.set(first + i);
            }
        }
    }
}

/// One image row's places in a later group's lists: per projector, the slots of the row's
/// lit pixels in its kept (ψ, B) pairs and of its unlit pixels in its root sums.
struct RowTargets<'a> {
    kept: Vec<&'a mut [u16]>,
    unlit: Vec<&'a mut [u16]>,
}

/// `data` cut into consecutive pieces of the lengths `lens`.
fn cut<X>(mut data: &mut [X], lens: impl Iterator<Item = usize>) -> Vec<&mut [X]> {
    lens.map(|len| {
        let (head, tail) = std::mem::take(&mut data).split_at_mut(len);
        data = tail;
        head
    })
    .collect()
}

/// The (ψ, B) pairs `out` of a row of pixels from pixel `first` of the image on, projector
/// by projector: a pair written to its projector's next kept slot in `t` where it lights
/// the pixel (`lit`), else its B added to the next root sum.
fn keep_row(out: &[u16], first: usize, lit: &[LitPixels], t: &mut RowTargets<'_>) {
    let np = lit.len();
    for (p, ((lit, kept), sums)) in lit.iter().zip(&mut t.kept).zip(&mut t.unlit).enumerate() {
        let mut kept = kept.chunks_exact_mut(2);
        let mut sums = sums.iter_mut();
        for (i, px) in out.chunks_exact(np * 2).enumerate() {
            let pair = &px[p * 2..p * 2 + 2];
            if lit.get(first + i) {
                if let Some(k) = kept.next() {
                    k.copy_from_slice(pair);
                }
            } else if let Some(r) = sums.next() {
                *r = add_unlit(*r, pair[1]);
            }
        }
    }
}

/// A root sum of B (steps of [`UNLIT_STEP`] of B's step) with one more group's B (16-bit
/// step) added in quadrature, rounded to the nearest step (half away from zero) and
/// clamped to 16 bits.
#[inline(always)]
fn add_unlit(sum: u16, b: u16) -> u16 {
    let r = f32::from(sum) * UNLIT_STEP;
    let b = f32::from(b);
    let x = (r * r + b * b).sqrt() / UNLIT_STEP;
    // x < 2^23: its truncation and the remainder are exact (no libm round).
    let whole = x as u32;
    let whole = whole + u32::from(x - whole as f32 >= 0.5);
    whole.min(65535) as u16
}

/// One projector's lit pixels: a bit per pixel, and per image row the slot of its first lit
/// pixel among all of them in row-major order.
struct LitPixels {
    bits: Vec<u64>,
    /// Height + 1 entries (the last the number of lit pixels); filled by `count_rows`.
    row_slots: Vec<u32>,
}

impl LitPixels {
    /// No pixel of `npx` lit.
    fn new(npx: usize) -> Self {
        LitPixels {
            bits: vec![0; npx.div_ceil(64)],
            row_slots: Vec::new(),
        }
    }

    fn set(&mut self, i: usize) {
        self.bits[i / 64] |= 1 << (i % 64);
    }

    fn get(&self, i: usize) -> bool {
        self.bits[i / 64] >> (i % 64) & 1 == 1
    }

    /// Lit pixels (0 before `count_rows`).
    fn count(&self) -> usize {
        self.row_slots.last().map_or(0, |&n| n as usize)
    }

    /// Fill the row slots of an image of `rows` rows of `w` pixels.
    fn count_rows(&mut self, w: usize, rows: usize) {
        let mut next = 0u32;
        self.row_slots = Vec::with_capacity(rows + 1);
        self.row_slots.push(0);
        for y in 0..rows {
            next += (y * w..(y + 1) * w).filter(|&i| self.get(i)).count() as u32;
            self.row_slots.push(next);
        }
    }

    fn bytes(&self) -> usize {
        self.bits.len() * 8 + self.row_slots.len() * 4
    }
}

/// Per image row of `w` pixels (`h` rows), the slot of its first candidate (a pixel some
/// projector in `lit` lights) and the count at the end.
fn row_slots(lit: &[LitPixels], w: usize, h: usize) -> Vec<u32> {
    let mut slots = Vec::with_capacity(h + 1);
    let mut next = 0u32;
    slots.push(next);
    for y in 0..h {
        next += (y * w..(y + 1) * w)
            .filter(|&i| lit.iter().any(|l| l.get(i)))
            .count() as u32;
        slots.push(next);
    }
    slots
}

/// One worker's sums for a strip of [`CHUNK`] pixels over a group's N steps.
struct Strip {
    /// A step's samples (of the paired steps: I_s + I_{N−s}).
    sum: [f32; CHUNK],
    /// Of the paired steps: I_s − I_{N−s}.
    diff: [f32; CHUNK],
    /// Largest sample.
    peak: [f32; CHUNK],
    /// X_0 = Σ_s I_s.
    dc: [f32; CHUNK],
    /// Per projector: Re X_{f_p}, then Im X_{f_p} ([`CHUNK`] values each).
    reim: Vec<f32>,
}

impl Strip {
    /// Zeroed sums for `np` projectors.
    fn new(np: usize) -> Self {
        Strip {
            sum: [0.0; CHUNK],
            diff: [0.0; CHUNK],
            peak: [0.0; CHUNK],
            dc: [0.0; CHUNK],
            reim: vec![0.0; 2 * np * CHUNK],
        }
    }
}

/// Copies a step's samples `src` into `dst` as f32, zeros past their end.
#[inline(always)]
fn load<T: Sample>(dst: &mut [f32; CHUNK], src: &[T]) {
    dst.fill(0.0);
    for (v, &x) in dst.iter_mut().zip(src) {
        *v = x.value();
    }
}

/// A step's samples `src` as a strip, zeros past their end (read as they are: the sums
/// take them straight to f32).
#[inline(always)]
fn padded<T: Sample>(src: &[T]) -> [T; CHUNK] {
    let mut strip = [T::default(); CHUNK];
    strip[..src.len()].copy_from_slice(src);
    strip
}

/// What every row of one group's DFT shares: the frames, the twiddles and the sizes.
struct GroupKernel<'a, T> {
    /// The group's frames but its last, (N − 1) × pixels.
    frames: &'a [T],
    /// The group's last frame.
    last: &'a [T],
    /// (cos, sin) of 2π·f_p·s/N at [p·N + s].
    twiddles: &'a [[f32; 2]],
    /// Image width (px).
    w: usize,
    /// Pixels per frame.
    npx: usize,
    /// Steps N.
    n: usize,
    /// Projectors P.
    np: usize,
    /// The group's index.
    g: usize,
    /// Saturation level (DN).
    fs: f32,
    /// Quantisation steps of B per DN.
    b_scale: f32,
    /// 1/N.
    inv_n: f32,
}

impl<'a, T: Sample> GroupKernel<'a, T> {
    /// The kernel of group g of `dec`'s stack, whose last frame is `last`.
    fn new(dec: &'a Decoder<T>, g: usize, last: &'a [T]) -> Self {
        let w = dec.width as usize;
        let n = dec.seq.steps() as usize;
        GroupKernel {
            frames: &dec.frames,
            last,
            twiddles: &dec.twiddles,
            w,
            npx: w * dec.height as usize,
            n,
            np: dec.seq.projectors().len(),
            g,
            fs: dec.full_scale,
            b_scale: B_STEPS / dec.full_scale,
            inv_n: 1.0 / n as f32,
        }
    }
}

/// What one row of a group's DFT writes: its pixels' 16-bit (ψ, B) pairs, level statistics
/// and saturation flags.
struct RowOut<'a> {
    pairs: &'a mut [u16],
    levels: &'a mut [Level],
    saturated: &'a mut [bool],
}

impl<T: Sample> GroupKernel<'_, T> {
    /// Row y, strip by strip of [`CHUNK`] pixels (the sums stay in L1 over the N frames):
    /// the DFT into `strip`, then the pixels' level statistics (`levels`), saturation flags
    /// (`saturated`) and their 16-bit (ψ, B) pairs (`out_row`).
    fn row(&self, y: usize, strip: &mut Strip, out: RowOut) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU supports AVX2, checked just above.
                return unsafe { self.row_avx2(y, strip, out) };
            }
        }
        self.row_generic(y, strip, out);
    }

    /// [`Self::row_generic`] compiled for AVX2 (8-wide strip loops; no FMA, so the sums are
    /// the same to the bit as the generic code's).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn row_avx2(&self, y: usize, strip: &mut Strip, out: RowOut) {
        self.row_generic(y, strip, out);
    }

    /// [`Self::row`] for any CPU.
    #[inline(always)]
    fn row_generic(&self, y: usize, strip: &mut Strip, out: RowOut) {
        let np = self.np;
        for x0 in (0..self.w).step_by(CHUNK) {
            let len = CHUNK.min(self.w - x0);
            let at = y * self.w + x0;
            self.dft(at, len, strip);
            // Saturation is rare: look per pixel only when the strip reached it.
            if strip.peak.iter().any(|&m| m >= self.fs) {
                self.mark_saturated(at, &mut out.saturated[x0..x0 + len]);
            }
            self.add_level(&strip.dc, &mut out.levels[x0..x0 + len]);
            self.quantise(strip, &mut out.pairs[x0 * np * 2..(x0 + len) * np * 2]);
        }
    }

    /// Step s's samples of the `len` pixels from pixel `at` on.
    #[inline(always)]
    fn samples(&self, s: usize, at: usize, len: usize) -> &[T] {
        if s + 1 == self.n {
            &self.last[at..][..len]
        } else {
            &self.frames[s * self.npx + at..][..len]
        }
    }

    /// The DFT of the `len` pixels from pixel `at` over the N steps: X_0 into `dc`, Re and
    /// Im X_{f_p} into `reim`, the largest sample into `peak`.
    #[inline(always)]
    fn dft(&self, at: usize, len: usize, strip: &mut Strip) {
        self.first_step(at, len, strip);
        for s in 1..self.n.div_ceil(2) {
            self.paired_steps(s, at, len, strip);
        }
        if self.n % 2 == 0 {
            self.middle_step(at, len, strip);
        }
    }

    /// Step 0 starts every sum (its twiddle is 1).
    #[inline(always)]
    fn first_step(&self, at: usize, len: usize, strip: &mut Strip) {
        let Strip {
            sum,
            peak,
            dc,
            reim,
            ..
        } = strip;
        load(sum, self.samples(0, at, len));
        dc.copy_from_slice(sum);
        peak.copy_from_slice(sum);
        for sums in reim.chunks_exact_mut(2 * CHUNK) {
            let (re, im) = sums.split_at_mut(CHUNK);
            re.copy_from_slice(dc);
            im.fill(0.0);
        }
    }

    /// Steps s and N − s share |twiddle|: e^{±i2πfs/N}, so
    /// X_f += (I_s + I_{N−s})·cos + i·(I_s − I_{N−s})·sin.
    #[inline(always)]
    fn paired_steps(&self, s: usize, at: usize, len: usize, strip: &mut Strip) {
        let n = self.n;
        let Strip {
            sum,
            diff,
            peak,
            dc,
            reim,
        } = strip;
        let (upper, lower) = (
            padded(self.samples(s, at, len)),
            padded(self.samples(n - s, at, len)),
        );
        for i in 0..CHUNK {
            let (a, b) = (upper[i].value(), lower[i].value());
            peak[i] = if a > peak[i] { a } else { peak[i] };
            peak[i] = if b > peak[i] { b } else { peak[i] };
            sum[i] = a + b;
            diff[i] = a - b;
            dc[i] += a + b;
        }
        for (p, sums) in reim.chunks_exact_mut(2 * CHUNK).enumerate() {
            let [c, sn] = self.twiddles[p * n + s];
            let (re, im) = sums.split_at_mut(CHUNK);
            let re: &mut [f32; CHUNK] = re.try_into().expect("CHUNK");
            let im: &mut [f32; CHUNK] = im.try_into().expect("CHUNK");
            for i in 0..CHUNK {
                re[i] += sum[i] * c;
                im[i] += diff[i] * sn;
            }
        }
    }

    /// The middle step of an even N: its twiddle is (−1)^f.
    #[inline(always)]
    fn middle_step(&self, at: usize, len: usize, strip: &mut Strip) {
        let s = self.n / 2;
        let Strip {
            sum,
            peak,
            dc,
            reim,
            ..
        } = strip;
        load(sum, self.samples(s, at, len));
        for i in 0..CHUNK {
            peak[i] = if sum[i] > peak[i] { sum[i] } else { peak[i] };
            dc[i] += sum[i];
        }
        for (p, sums) in reim.chunks_exact_mut(2 * CHUNK).enumerate() {
            let c = self.twiddles[p * self.n + s][0];
            for (r, &v) in sums[..CHUNK].iter_mut().zip(sum.iter()) {
                *r += v * c;
            }
        }
    }

    /// Flags the pixels from `at` (one per entry of `saturated`) that reach full scale in
    /// any step.
    fn mark_saturated(&self, at: usize, saturated: &mut [bool]) {
        let len = saturated.len();
        for s in 0..self.n {
            for (st, &v) in saturated.iter_mut().zip(self.samples(s, at, len)) {
                *st |= v.value() >= self.fs;
            }
        }
    }

    /// Adds the group's mean level of each pixel (from its X_0 in `dc`) to its statistics.
    #[inline(always)]
    fn add_level(&self, dc: &[f32; CHUNK], stats: &mut [Level]) {
        for (st, &d) in stats.iter_mut().zip(dc.iter()) {
            // A = X_0/N (docs/design.md §6).
            let a = d * self.inv_n;
            if self.g == 0 {
                st.first_mean = a;
            } else {
                let dev = a - st.first_mean;
                st.sum_dev += dev;
                st.sum_dev2 += dev * dev;
            }
        }
    }

    /// The strip's sums as 16-bit (ψ, B) pairs per pixel and projector, into `out`.
    #[inline(always)]
    fn quantise(&self, strip: &Strip, out: &mut [u16]) {
        let np = self.np;
        for (p, sums) in strip.reim.chunks_exact(2 * CHUNK).enumerate() {
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
                let b = 2.0 * (re[i] * re[i] + im[i] * im[i]).sqrt() * self.inv_n;
                // Rounded to 16 bits by adding 1.5·2^23: the integer lands in
                // the low mantissa bits (a phase of 1 cycle wraps to 0).
                psi[i] = (ph * 65536.0 + ROUNDER).to_bits() as u16;
                bq[i] = ((b * self.b_scale).min(65535.0) + ROUNDER).to_bits() as u16;
            }
            for ((pair, &ph), &b) in out.chunks_exact_mut(np * 2).zip(&psi).zip(&bq) {
                pair[p * 2] = ph;
                pair[p * 2 + 1] = b;
            }
        }
    }
}

impl Level {
    /// The mean level Ā over the `groups` groups and the per-frame variance σ_I² from the
    /// spread of the group means (N `steps`).
    fn mean_and_var(&self, steps: f64, groups: usize) -> (f64, f64) {
        // Ā = A_0 + Σd/G; Σ_g (A_g − Ā)² = Σd² − (Σd)²/G; σ_I² ≈ N·that/(G − 1).
        let g = groups as f64;
        let (sd, sd2) = (f64::from(self.sum_dev), f64::from(self.sum_dev2));
        let mean = f64::from(self.first_mean) + sd / g;
        let var = steps * (sd2 - sd * sd / g).max(0.0) / (g - 1.0);
        (mean, var)
    }
}

/// The sums [count, ΣA, ΣA², Σσ_I², ΣA·σ_I²] over the pixels not `saturated` (N `steps`,
/// G `groups`), on all cores, for the least-squares line σ_I² = a + b·A.
fn noise_sums(levels: &[Level], saturated: &[bool], steps: f64, groups: usize) -> [f64; 5] {
    levels
        .par_chunks(4096)
        .zip(saturated.par_chunks(4096))
        .map(|(chunk, sat)| {
            let mut s = [0f64; 5];
            for (st, _) in chunk.iter().zip(sat).filter(|(_, &sat)| !sat) {
                let (a, v) = st.mean_and_var(steps, groups);
                s[0] += 1.0;
                s[1] += a;
                s[2] += a * a;
                s[3] += v;
                s[4] += a * v;
            }
            s
        })
        .reduce(|| [0f64; 5], |a, b| std::array::from_fn(|i| a[i] + b[i]))
}

/// Per projector, from its effective γ: the fundamental amplitude a_1(γ) of a full-swing
/// pattern, and the mean over the fundamental a_0/a_1 = (γ+1)/(2γ) (docs/design.md §6).
fn harmonics(codes: &[ProjectorCode]) -> (Vec<f32>, Vec<f32>) {
    let gammas: Vec<f64> = codes.iter().map(|c| c.response.effective_gamma()).collect();
    let fundamental = gammas
        .iter()
        .map(|&g| pattern_harmonic(g, 1) as f32)
        .collect();
    let mean_ratio = gammas
        .iter()
        .map(|&g| (pattern_harmonic(g, 0) / pattern_harmonic(g, 1)) as f32)
        .collect();
    (fundamental, mean_ratio)
}

/// One worker's per-row scratch in the final pass: each pixel's per-frame noise σ_I (DN)
/// and its slot among the row's candidates ([`NO_SLOT`] where it is not one).
#[derive(Default)]
struct RowScratch {
    sigma: Vec<f32>,
    slot: Vec<u32>,
}

/// The groups of one direction a repair keeps ([`repair`]), as their own constellation.
struct KeptGroups {
    cons: Arc<Constellation>,
    /// Which of the direction's groups are kept.
    kept: [bool; MAX_COUNTS],
}

impl KeptGroups {
    /// Direction `dir` of `seq` without the groups in `left_out` (a bit per group); `None`
    /// when none of its groups is left out.
    fn new(seq: &Sequence, dir: Direction, left_out: u32) -> Option<KeptGroups> {
        let first = match dir {
            Direction::Columns => 0,
            Direction::Rows => seq.counts(Direction::Columns).len(),
        };
        let groups = repair::kept_groups(seq, dir, first, left_out);
        let mut kept = [false; MAX_COUNTS];
        for &(g, _) in &groups {
            kept[g - first] = true;
        }
        let kept_counts: Vec<u32> = groups.iter().map(|&(_, c)| c).collect();
        (kept_counts.len() < seq.counts(dir).len()).then(|| KeptGroups {
            cons: Constellation::shared(&kept_counts).expect("a repair keeps a constellation"),
            kept,
        })
    }

    /// Whether the kept groups alone find the fringe orders that all of them found
    /// (position `t`, screen `size` px): the left-out group's bias can lead the full
    /// constellation to a wrong point, which the kept counts alone, free of it, rarely
    /// agree with; noise beyond the kept constellation's reach (≈ 2 % of the pixels at
    /// counts 20, 21) loses the pixel, unbiased (it is orthogonal to the position).
    fn agrees(&self, t: f32, psi: &[f32], wt: &[f32], size: f32) -> bool {
        let (mut ps, mut ws, mut m) = ([0f32; MAX_COUNTS], [0f32; MAX_COUNTS], 0);
        for ((&p, &w), _) in (psi.iter().zip(wt).zip(self.kept)).filter(|(_, k)| *k) {
            (ps[m], ws[m], m) = (p, w, m + 1);
        }
        let alone = self.cons.unwrap(&ps[..m], &ws[..m]).position;
        let d = alone - t;
        (d - d.round()).abs() * size < 0.5
    }
}

/// Projector p's position at one pixel, per direction (columns, rows).
struct Position {
    /// Unwrapped and fused u, v (projector px).
    fused: [f32; 2],
    /// Unwrapping distance (rad).
    distance: [f32; 2],
    /// Predicted σ_u, σ_v (projector px).
    sigma: [f32; 2],
    /// Whether both lie farther than 6σ from the wrap point t = 0 ≡ 1 (and, where a group
    /// was left out, the kept groups agree: [`KeptGroups::agrees`]).
    clear_of_wrap: bool,
}

/// The final pass of [`Decoder::finish`]: a complete decoder's measurements, its noise
/// model and the constants of the per-pixel tests.
struct Judge<'a, T: Sample> {
    dec: &'a Decoder<T>,
    noise: NoiseModel,
    /// Fringe counts of the columns and of the rows.
    counts: [&'a [u32]; 2],
    /// Per projector: mean over fundamental a_0/a_1.
    mean_ratio: Vec<f32>,
    /// A bit per group every fusion leaves out ([`repair`]).
    left_out: u32,
    /// Per direction with a group left out: the kept counts' own constellation.
    kept: [Option<KeptGroups>; 2],
    /// Half the constellation spacing of columns and rows.
    half_spacing: [f32; 2],
    /// DN per quantisation step of B.
    inv_b_scale: f32,
    /// The validity floor on B: 3 % of full scale (DN).
    min_b: f32,
    /// Steps N.
    steps: f64,
    /// Groups G.
    groups: usize,
    /// N as f32.
    n32: f32,
    /// √(2/N).
    noise_gain: f32,
}

impl<'a, T: Sample> Judge<'a, T> {
    /// The final pass over the complete decoder `dec` with its fitted `noise`, the
    /// projectors' a_0/a_1 ratios and the groups each projector's fusion leaves out.
    fn new(dec: &'a Decoder<T>, noise: NoiseModel, mean_ratio: Vec<f32>, left_out: u32) -> Self {
        let kept =
            [Direction::Columns, Direction::Rows].map(|d| KeptGroups::new(&dec.seq, d, left_out));
        let n = dec.seq.steps() as f64;
        let n32 = n as f32;
        Judge {
            dec,
            noise,
            counts: [
                dec.seq.counts(Direction::Columns),
                dec.seq.counts(Direction::Rows),
            ],
            mean_ratio,
            left_out,
            kept,
            half_spacing: [
                0.5 * dec.columns.spacing() as f32,
                0.5 * dec.rows.spacing() as f32,
            ],
            inv_b_scale: dec.full_scale / B_STEPS,
            min_b: 0.03 * dec.full_scale,
            steps: n,
            groups: dec.seq.groups(),
            n32,
            // σ_u = W/(2π)·√(2/N)·σ_I/√(Σ n_i² B_i²) for the weighted fusion (docs/design.md §6).
            noise_gain: (2.0 / n32).sqrt(),
        }
    }

    /// Every row into `rows`, on all cores; per projector, over its valid pixels: count,
    /// Σ B, Σ σ_I², Σ σ_φ², Σ σ_u², Σ σ_v².
    fn rows(&self, rows: Vec<RowSink<'_>>) -> Vec<[f64; 6]> {
        let np = self.mean_ratio.len();
        rows.into_par_iter()
            .enumerate()
            .map_init(RowScratch::default, |scratch, (y, mut row)| {
                self.row(y, &mut row, scratch)
            })
            .reduce(
                || vec![[0f64; 6]; np],
                |a, b| {
                    a.iter()
                        .zip(&b)
                        .map(|(x, y)| std::array::from_fn(|i| x[i] + y[i]))
                        .collect()
                },
            )
    }

    /// Row y into `row`: each pixel's ambient and per projector modulation, and at its
    /// candidates u, v, reliability and validity; gives the row's sums as [`Self::rows`].
    /// The pixels' noise first, then projector by projector (each reads only its own
    /// groups' phases: few memory streams at a time).
    fn row(&self, y: usize, row: &mut RowSink<'_>, scratch: &mut RowScratch) -> Vec<[f64; 6]> {
        let dec = self.dec;
        let w = dec.width as usize;
        scratch.sigma.clear();
        scratch.slot.clear();
        // The row's candidates are its slots in the maps at the candidates, in pixel order.
        let mut k = 0u32;
        for (x, amb) in row.ambient.iter_mut().enumerate().take(w) {
            let px = y * w + x;
            let (mean, _) = dec.levels[px].mean_and_var(self.steps, self.groups);
            scratch.sigma.push(self.noise.sigma(mean) as f32);
            *amb = mean as f32;
            let candidate = dec.is_candidate(px);
            scratch.slot.push(if candidate { k } else { NO_SLOT });
            k += u32::from(candidate);
        }
        (0..self.mean_ratio.len())
            .map(|p| self.projector_row(p, y, row, scratch))
            .collect()
    }

    /// Projector p's part of row y (the pixels' noise and candidate slots in `scratch`):
    /// its modulation subtracted from the ambient, its maps at the candidates; gives its
    /// sums as [`Self::rows`].
    fn projector_row(
        &self,
        p: usize,
        y: usize,
        row: &mut RowSink<'_>,
        scratch: &RowScratch,
    ) -> [f64; 6] {
        let dec = self.dec;
        let w = dec.width as usize;
        let lit = &dec.lit[p];
        let groups: Vec<&[u16]> = dec.groups.iter().map(|g| &g[p][..]).collect();
        let unlit = &dec.unlit_b[p];
        let mut acc = [0f64; 6];
        // The pixels p lights are its slots from lit.row_slots[y] on, counted in `next`.
        let mut next = lit.row_slots[y] as usize;
        for x in 0..w {
            let px = y * w + x;
            let sigma = scratch.sigma[x];
            let var4 = 4.0 * sigma * sigma / self.n32;
            let is_lit = lit.get(px);
            // Σ_g B² from the kept modulations where p lights the pixel, else from p's
            // unlit root sum.
            let (psi_g, bsq_g) = if is_lit {
                self.group_phases(&groups, next)
            } else {
                Default::default()
            };
            let bsq = if is_lit {
                bsq_g[..self.groups].iter().fold(0.0, |s, &b2| s + b2)
            } else {
                let r = f32::from(unlit[px - next]) * (UNLIT_STEP * self.inv_b_scale);
                r * r
            };
            next += usize::from(is_lit);
            let bmod = (bsq / self.groups as f32 - var4).max(0.0).sqrt();
            row.ambient[x] -= self.mean_ratio[p] * bmod;
            if let Some(m) = row.modulation.get_mut(p) {
                m[x] = bmod;
            }
            let k = scratch.slot[x];
            if k == NO_SLOT {
                continue;
            }
            let (k, c) = (k as usize, &mut row.candidates[p]);
            c.modulation[k] = bmod;
            if !is_lit || dec.saturated[px] || bmod < self.min_b.max(5.0 * sigma) {
                // Invalid whatever the phases say: not unwrapped.
                c.u[k] = f32::NAN;
                c.v[k] = f32::NAN;
                c.reliability[k] = f32::NAN;
                c.valid[k] = false;
                continue;
            }
            let pos = self.position(&psi_g, &bsq_g, p, sigma);
            let ok = pos.distance[0] < self.half_spacing[0]
                && pos.distance[1] < self.half_spacing[1]
                && pos.clear_of_wrap;
            c.u[k] = pos.fused[0];
            c.v[k] = pos.fused[1];
            c.reliability[k] = pos.distance[0].max(pos.distance[1]);
            c.valid[k] = ok;
            if ok {
                self.add_valid(&mut acc, bmod, sigma, pos.sigma);
            }
        }
        acc
    }

    /// The wrapped phase ψ (cycles) and B² (DN²) in every group (one projector's kept pairs
    /// of each group in `groups`) at lit pixel `slot`.
    #[inline(always)]
    fn group_phases(
        &self,
        groups: &[&[u16]],
        slot: usize,
    ) -> ([f32; 2 * MAX_COUNTS], [f32; 2 * MAX_COUNTS]) {
        let mut psi_g = [0f32; 2 * MAX_COUNTS];
        let mut bsq_g = [0f32; 2 * MAX_COUNTS];
        for (g, data) in groups.iter().enumerate() {
            let o = &data[slot * 2..][..2];
            psi_g[g] = f32::from(o[0]) * (1.0 / 65536.0);
            let b = f32::from(o[1]) * self.inv_b_scale;
            bsq_g[g] = b * b;
        }
        (psi_g, bsq_g)
    }

    /// Projector p's wrapped phases `psi_g` (cycles) and B² `bsq_g` (DN²) per group
    /// unwrapped and fused per direction, with their σ at per-frame noise `sigma` (DN).
    fn position(&self, psi_g: &[f32], bsq_g: &[f32], p: usize, sigma: f32) -> Position {
        let code = &self.dec.seq.projectors()[p];
        let mc = self.counts[0].len();
        let mut pos = Position {
            fused: [0.0; 2],
            distance: [0.0; 2],
            sigma: [0.0; 2],
            clear_of_wrap: true,
        };
        for (d, (cons, counts, offset, size)) in [
            (&*self.dec.columns, self.counts[0], 0, code.width),
            (&*self.dec.rows, self.counts[1], mc, code.height),
        ]
        .into_iter()
        .enumerate()
        {
            let m = counts.len();
            let ps = &psi_g[offset..offset + m];
            // A group left out still helps find the fringe orders; it has no weight in the
            // position.
            let mut wt = [0f32; MAX_COUNTS];
            for (j, w) in wt[..m].iter_mut().enumerate() {
                if self.left_out & (1 << (offset + j)) == 0 {
                    *w = bsq_g[offset + j];
                }
            }
            let wt = &wt[..m];
            let info: f32 = counts
                .iter()
                .zip(wt)
                .map(|(&ni, &w)| (ni * ni) as f32 * w)
                .sum();
            let un = cons.unwrap(ps, wt);
            let size = size as f32;
            if let Some(kept) = &self.kept[d] {
                pos.clear_of_wrap &= kept.agrees(un.position, ps, wt, size);
            }
            pos.fused[d] = un.position * size - 0.5;
            pos.distance[d] = un.distance;
            let s_pos = size / TAU * self.noise_gain * sigma / info.sqrt();
            pos.sigma[d] = s_pos;
            // Distance to the wrap point t = 0 ≡ 1, in projector px.
            let edge = un.position.min(1.0 - un.position) * size;
            pos.clear_of_wrap &= edge >= 6.0 * s_pos;
        }
        pos
    }

    /// Adds a valid pixel of modulation `bmod`, per-frame noise `sigma` and position σ's
    /// `sigma_pos` to its projector's sums `a`.
    fn add_valid(&self, a: &mut [f64; 6], bmod: f32, sigma: f32, sigma_pos: [f32; 2]) {
        let sphi = self.noise_gain * sigma / bmod;
        a[0] += 1.0;
        a[1] += f64::from(bmod);
        a[2] += f64::from(sigma * sigma);
        a[3] += f64::from(sphi * sphi);
        a[4] += f64::from(sigma_pos[0] * sigma_pos[0]);
        a[5] += f64::from(sigma_pos[1] * sigma_pos[1]);
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
pub(crate) fn phase_cycles(im: f32, re: f32) -> f32 {
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
