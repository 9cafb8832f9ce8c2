//! The decoder's results held compactly (docs/design.md §6, "Memory").
//!
//! Takes what the decoder's final pass writes; gives a [`CompactStack`]: the ambient image
//! and saturation flags of every pixel, and each projector's u, v, reliability, modulation
//! and validity only at the candidate pixels (those whose first-group modulation reached the
//! candidate floor, half the validity floor: no other pixel can be valid). `hexcal run`
//! hands a pose's stacks over in this form while the next pose is captured, and reads the
//! maps in place through each pixel's slot ([`CompactStack::candidate_slots`]) while that
//! camera is processed; [`super::Decoder::finish`] spreads them at once into a
//! [`DecodedStack`].

use super::check::StackVerdict;
use super::maps::{DecodedStack, Mask, NoiseModel, PhaseNoise, ProjectorMaps};
use hexcal_core::images::FloatImage;
use rayon::prelude::*;

/// One projector's maps at the candidate pixels, in row-major pixel order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CandidateMaps {
    /// Projector column u (projector px); NaN where the modulation or saturation test fails.
    pub u: Vec<f32>,
    /// Projector row v (NaN as for u).
    pub v: Vec<f32>,
    /// Unwrapping distance, the larger of the two directions' (rad; NaN as for u).
    pub reliability: Vec<f32>,
    /// Modulation B_p (DN), bias-corrected as in [`ProjectorMaps::modulation`].
    pub modulation: Vec<f32>,
    /// Validity as in [`ProjectorMaps::valid`].
    pub valid: Vec<bool>,
}

impl CandidateMaps {
    /// Maps of `n` candidates, to be filled.
    fn zeroed(n: usize) -> Self {
        CandidateMaps {
            u: vec![0.0; n],
            v: vec![0.0; n],
            reliability: vec![0.0; n],
            modulation: vec![0.0; n],
            valid: vec![false; n],
        }
    }

    /// The maps cut into image rows: row y holds the candidates `bounds[y]..bounds[y + 1]`.
    fn rows(&mut self, bounds: &[u32]) -> Vec<CandidateRow<'_>> {
        let CandidateMaps {
            u,
            v,
            reliability,
            modulation,
            valid,
        } = self;
        split(u, bounds)
            .into_iter()
            .zip(split(v, bounds))
            .zip(split(reliability, bounds))
            .zip(split(modulation, bounds))
            .zip(split(valid, bounds))
            .map(
                |((((u, v), reliability), modulation), valid)| CandidateRow {
                    u,
                    v,
                    reliability,
                    modulation,
                    valid,
                },
            )
            .collect()
    }
}

/// `data` cut at the offsets `bounds` (one slice per consecutive pair).
fn split<'a, X>(mut data: &'a mut [X], bounds: &[u32]) -> Vec<&'a mut [X]> {
    bounds
        .windows(2)
        .map(|b| {
            let (head, tail) = std::mem::take(&mut data).split_at_mut((b[1] - b[0]) as usize);
            data = tail;
            head
        })
        .collect()
}

/// One projector's results in a [`CompactStack`].
#[derive(Clone, Debug)]
pub struct CompactProjector {
    /// The maps at the candidate pixels.
    pub at_candidates: CandidateMaps,
    /// Modulation of every pixel, row-major (only from [`super::Decoder::finish`]).
    modulation: Option<Vec<f32>>,
    /// Run-level noise predictions.
    pub noise: PhaseNoise,
    /// Fundamental amplitude a_1(γ) of a full-swing pattern.
    fundamental: f32,
}

/// Everything decoded from one camera's stack, with the maps at the candidate pixels only.
#[derive(Clone, Debug)]
pub struct CompactStack {
    /// Camera label.
    pub camera: String,
    /// Ambient image, as [`DecodedStack::ambient`].
    pub ambient: FloatImage,
    /// Pixels with a saturated sample in any frame.
    pub saturated: Mask,
    /// The measured noise model.
    pub noise: NoiseModel,
    /// Per pixel, row-major: whether it is a candidate.
    candidate: Vec<bool>,
    /// Per projector, in sequence order.
    pub projectors: Vec<CompactProjector>,
    /// The stack check's verdict ([`super::check`]).
    pub verdict: StackVerdict,
}

/// The slot of a pixel that is not a candidate in [`CompactStack::candidate_slots`].
pub const NO_SLOT: u32 = u32::MAX;

impl CompactStack {
    /// Number of candidate pixels.
    pub fn candidates(&self) -> usize {
        self.candidate.iter().filter(|&&c| c).count()
    }

    /// Bytes held by the images and maps.
    pub fn bytes(&self) -> usize {
        let npx = self.candidate.len();
        let per_projector = |p: &CompactProjector| {
            p.at_candidates.u.len() * (4 * 4 + 1) + p.modulation.as_ref().map_or(0, |m| 4 * m.len())
        };
        npx * (4 + 1 + 1) + self.projectors.iter().map(per_projector).sum::<usize>()
    }

    /// Per pixel, row-major, its index in the maps at the candidates ([`NO_SLOT`] where it is
    /// not a candidate): 4 bytes per pixel for every projector's maps, where spreading them
    /// over the image takes 13 per projector.
    pub fn candidate_slots(&self) -> Vec<u32> {
        let mut next = 0u32;
        self.candidate
            .iter()
            .map(|&c| match c {
                true => {
                    next += 1;
                    next - 1
                }
                false => NO_SLOT,
            })
            .collect()
    }

    /// The maps spread over the image as a [`DecodedStack`]; its modulation images are those
    /// of every pixel when the stack has them (from [`super::Decoder::finish`]), else 0 away
    /// from the candidates.
    pub(super) fn into_decoded(self) -> DecodedStack {
        let (w, h) = (self.ambient.width(), self.ambient.height());
        let to_image = |data: Vec<f32>| {
            FloatImage::from_raw(w, h, data).expect("map has width × height values")
        };
        let candidate = &self.candidate;
        // One projector's maps per task, on all cores.
        let projectors = self
            .projectors
            .into_par_iter()
            .map(|p| {
                let c = &p.at_candidates;
                // Each map its own task too: three projectors share two cores evenly.
                let ((u, v), ((reliability, valid), modulation)) = rayon::join(
                    || {
                        rayon::join(
                            || spread(candidate, &c.u, f32::NAN),
                            || spread(candidate, &c.v, f32::NAN),
                        )
                    },
                    || {
                        rayon::join(
                            || {
                                rayon::join(
                                    || spread(candidate, &c.reliability, f32::NAN),
                                    || spread(candidate, &c.valid, false),
                                )
                            },
                            || {
                                p.modulation
                                    .unwrap_or_else(|| spread(candidate, &c.modulation, 0.0))
                            },
                        )
                    },
                );
                ProjectorMaps {
                    u: to_image(u),
                    v: to_image(v),
                    modulation: to_image(modulation),
                    reliability: to_image(reliability),
                    valid: Mask {
                        width: w,
                        height: h,
                        bits: valid,
                    },
                    noise: p.noise,
                    fundamental: p.fundamental,
                }
            })
            .collect();
        DecodedStack {
            camera: self.camera,
            ambient: self.ambient,
            saturated: self.saturated,
            noise: self.noise,
            projectors,
            verdict: self.verdict,
        }
    }
}

/// One value per pixel: the candidates' `values` in order, `fill` at the other pixels.
fn spread<X: Copy>(candidate: &[bool], values: &[X], fill: X) -> Vec<X> {
    let mut next = values.iter();
    let values = candidate.iter().map(|&c| match c {
        true => next.next().copied().unwrap_or(fill),
        false => fill,
    });
    super::pages::collected(candidate.len(), values)
}

/// What the decoder's final pass writes: the ambient of every pixel, the modulation of every
/// pixel (when asked for) and each projector's maps at the candidates.
pub(super) struct Sink {
    ambient: Vec<f32>,
    modulation: Vec<Vec<f32>>,
    candidates: Vec<CandidateMaps>,
}

/// One image row of a [`Sink`].
pub(super) struct RowSink<'a> {
    /// The row's ambient values.
    pub(super) ambient: &'a mut [f32],
    /// Per projector, the row's modulation (empty when the sink keeps none).
    pub(super) modulation: Vec<&'a mut [f32]>,
    /// Per projector, the maps of the row's candidates.
    pub(super) candidates: Vec<CandidateRow<'a>>,
}

/// The maps of one row's candidates.
pub(super) struct CandidateRow<'a> {
    pub(super) u: &'a mut [f32],
    pub(super) v: &'a mut [f32],
    pub(super) reliability: &'a mut [f32],
    pub(super) modulation: &'a mut [f32],
    pub(super) valid: &'a mut [bool],
}

impl Sink {
    /// A sink for `npx` pixels, `np` projectors and `candidates` candidate pixels, with the
    /// modulation of every pixel when `dense_modulation`.
    pub(super) fn new(npx: usize, np: usize, candidates: usize, dense_modulation: bool) -> Self {
        Sink {
            ambient: vec![0.0; npx],
            modulation: match dense_modulation {
                true => (0..np).map(|_| vec![0.0; npx]).collect(),
                false => Vec::new(),
            },
            candidates: (0..np).map(|_| CandidateMaps::zeroed(candidates)).collect(),
        }
    }

    /// The sink cut into rows of `w` pixels, row y's candidates being the slots
    /// `row_slots[y]..row_slots[y + 1]`.
    pub(super) fn rows(&mut self, w: usize, row_slots: &[u32]) -> Vec<RowSink<'_>> {
        let mut ambient = self.ambient.chunks_mut(w);
        let mut modulation: Vec<_> = self
            .modulation
            .iter_mut()
            .map(|m| m.chunks_mut(w))
            .collect();
        let mut candidates: Vec<_> = self
            .candidates
            .iter_mut()
            .map(|c| c.rows(row_slots).into_iter())
            .collect();
        (0..row_slots.len().saturating_sub(1))
            .map_while(|_| {
                Some(RowSink {
                    ambient: ambient.next()?,
                    modulation: modulation
                        .iter_mut()
                        .map(|m| m.next())
                        .collect::<Option<_>>()?,
                    candidates: candidates
                        .iter_mut()
                        .map(|c| c.next())
                        .collect::<Option<_>>()?,
                })
            })
            .collect()
    }

    /// The stack of `camera`: the sink's images and maps with the noise model, the
    /// saturation flags (of the image's size), candidate flags, each projector's noise from
    /// its sums `stats` and its pattern fundamental.
    pub(super) fn into_stack(
        self,
        camera: String,
        (noise, verdict): (NoiseModel, StackVerdict),
        saturated: Mask,
        candidate: Vec<bool>,
        stats: &[[f64; 6]],
        fundamental: &[f32],
    ) -> CompactStack {
        let mut modulation = self.modulation.into_iter();
        let projectors = self
            .candidates
            .into_iter()
            .enumerate()
            .map(|(p, at_candidates)| CompactProjector {
                at_candidates,
                modulation: modulation.next(),
                noise: PhaseNoise::from_sums(&stats[p]),
                fundamental: fundamental[p],
            })
            .collect();
        CompactStack {
            camera,
            ambient: FloatImage::from_raw(saturated.width, saturated.height, self.ambient)
                .expect("ambient has width × height values"),
            saturated,
            noise,
            candidate,
            projectors,
            verdict,
        }
    }
}
