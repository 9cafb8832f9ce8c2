//! The multiplexed phase-shift sequence (docs/design.md §6): which frame shows what on which
//! projector, the choice of temporal frequencies and step count, pattern images, and the
//! gamma arithmetic the decoder needs.
//!
//! Frame order: for each direction (columns, then rows), for each fringe count of that
//! direction (in the order given), N phase steps. During frame k every projector p shows its
//! own pattern of the same (direction, count, step) with its own temporal frequency f_p:
//! c_p,k = ½(1 + cos(φ(u, v) − 2π·f_p·s/N)), s the step within the group, φ = 2π·n·(u + ½)/W
//! for columns (n fringes across the projector's width W) and 2π·n·(v + ½)/H for rows.
//! With 2 directions × 3 counts × N = 15 this is 90 frames for P = 3.

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Most fringe counts per direction (the lookup grid lives in M − 1 ≤ 3 dimensions).
pub const MAX_COUNTS: usize = 4;

/// Default fringe counts per screen width (columns) and per screen height (rows).
pub const DEFAULT_COUNTS: [u32; 3] = [20, 21, 25];

/// Highest harmonic of an uncorrected projector gamma that the frequency rule keeps apart
/// from every fundamental (docs/design.md §6: 2nd at 0.286, 3rd at 0.011 of the fundamental for
/// γ = 2.2; the 4th, at 0.0014, is tolerated).
pub const CHECKED_HARMONICS: u32 = 3;

/// How a projector turns an 8-bit drive level into light.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ProjectorResponse {
    /// Linear projector (or one linearised outside hexcal): light ∝ drive.
    Linear,
    /// Uncorrected gamma: light = (drive/255)^γ; patterns are sent linear, so the light has
    /// harmonics that the frequency choice must keep apart.
    Gamma {
        /// Exponent γ (2.2 for a typical projector).
        gamma: f64,
    },
    /// A projector with gamma γ that hexcal linearises: pattern images go through the
    /// inverse-gamma lookup table ([`inverse_gamma_lut`]), so light ∝ intended intensity.
    Linearised {
        /// The projector's exponent γ that the lookup table undoes.
        gamma: f64,
    },
}

impl ProjectorResponse {
    /// Relative light output in [0, 1] for an 8-bit drive level.
    pub fn light(&self, drive: u8) -> f64 {
        let d = f64::from(drive) / 255.0;
        match *self {
            ProjectorResponse::Linear => d,
            ProjectorResponse::Gamma { gamma } | ProjectorResponse::Linearised { gamma } => {
                d.powf(gamma)
            }
        }
    }

    /// The exponent relating intended intensity to light: γ when uncorrected, else 1.
    pub fn effective_gamma(&self) -> f64 {
        match *self {
            ProjectorResponse::Gamma { gamma } => gamma,
            ProjectorResponse::Linear | ProjectorResponse::Linearised { .. } => 1.0,
        }
    }

    /// Whether the light carries the harmonics of an uncorrected gamma.
    pub fn has_harmonics(&self) -> bool {
        matches!(self, ProjectorResponse::Gamma { gamma } if *gamma != 1.0)
    }
}

/// Amplitude of harmonic h of the light c^γ, c = ½(1 + cos θ), relative to full white:
/// c^γ = a_0 + Σ_h a_h·cos(hθ). a_0 is the mean (½ for γ = 1), a_1 the fundamental (½ for γ = 1).
pub fn pattern_harmonic(gamma: f64, h: u32) -> f64 {
    // Periodic trapezoid rule: the integrand is C^⌊2γ⌋ at θ = π, so K = 4096 samples leave
    // an error far below 1e-12 for γ ≥ 1.
    const K: usize = 4096;
    let sum: f64 = (0..K)
        .map(|j| {
            let th = 2.0 * PI * j as f64 / K as f64;
            (0.5 * (1.0 + th.cos())).powf(gamma) * (f64::from(h) * th).cos()
        })
        .sum();
    if h == 0 {
        sum / K as f64
    } else {
        2.0 * sum / K as f64
    }
}

/// The 8-bit inverse-gamma lookup table: entry L is the drive level whose light
/// (drive/255)^γ is closest to L/255.
pub fn inverse_gamma_lut(gamma: f64) -> [u8; 256] {
    std::array::from_fn(|l| inverse_gamma_level(gamma, l as u8))
}

/// One entry of [`inverse_gamma_lut`]: the drive level whose light (drive/255)^γ is closest
/// to level/255.
fn inverse_gamma_level(gamma: f64, level: u8) -> u8 {
    let target = f64::from(level) / 255.0;
    // The best of the two drive levels around the exact inverse.
    let exact = 255.0 * target.powf(1.0 / gamma);
    let lo = exact.floor().clamp(0.0, 255.0) as u8;
    let hi = exact.ceil().clamp(0.0, 255.0) as u8;
    let err = |d: u8| ((f64::from(d) / 255.0).powf(gamma) - target).abs();
    if err(lo) <= err(hi) {
        lo
    } else {
        hi
    }
}

/// The two fringe directions.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    /// Vertical stripes: the phase varies along the projector's x, encoding the column u.
    Columns,
    /// Horizontal stripes: the phase varies along the projector's y, encoding the row v.
    Rows,
}

/// One projector's part of the sequence.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProjectorCode {
    /// Projector image width W (px).
    pub width: u32,
    /// Projector image height H (px).
    pub height: u32,
    /// Temporal frequency f_p (cycles per N steps), 0 < f_p < N/2.
    pub frequency: u32,
    /// How the projector turns drive levels into light.
    pub response: ProjectorResponse,
}

/// What one projector is and how it responds, before frequencies are chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectorSetup {
    /// Projector image width (px).
    pub width: u32,
    /// Projector image height (px).
    pub height: u32,
    /// How the projector turns drive levels into light.
    pub response: ProjectorResponse,
}

/// What frame k of a sequence shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameCode {
    /// Fringe direction.
    pub direction: Direction,
    /// Index of the fringe count within its direction's list.
    pub count_index: usize,
    /// Fringe count n (fringes per screen width or height).
    pub count: u32,
    /// Index of the group (direction, count) among all groups, in frame order.
    pub group: usize,
    /// Phase step s within the group, 0…N−1.
    pub step: u32,
}

/// Where an aliased harmonic lands. (The mean bin needs no case: 2f ≡ 0 is excluded by
/// f < N/2, and 3f ≡ 0 implies 2f ≡ −f, refused first.)
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AliasTarget {
    /// On +f or −f of a projector's frequency.
    Frequency {
        /// The projector whose phase it corrupts.
        projector: usize,
        /// That projector's frequency f_q.
        frequency: u32,
        /// Lands on −f_q rather than +f_q.
        negative: bool,
    },
}

impl std::fmt::Display for AliasTarget {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            AliasTarget::Frequency {
                projector,
                frequency,
                negative,
            } => write!(
                f,
                "projector {projector}'s frequency {}f={}{frequency}",
                if negative { "−" } else { "" },
                if negative { "−" } else { "" }
            ),
        }
    }
}

fn ordinal(h: u32) -> String {
    match h {
        1 => "fundamental".into(),
        2 => "2nd harmonic".into(),
        3 => "3rd harmonic".into(),
        h => format!("{h}th harmonic"),
    }
}

/// Why a sequence is refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SequenceError {
    /// No projectors, but phase steps or fringe counts: a camera-only pose is one frame.
    #[error("sequence: without projectors a pose is one plain frame (steps 1, no fringe counts)")]
    NoProjectors,
    /// Too few phase steps.
    #[error("sequence: steps N = {0} is below 3")]
    TooFewSteps(u32),
    /// A count or size beyond [`crate::limits`].
    #[error("sequence: {0}")]
    Limit(crate::invalid::Invalid),
    /// A frequency outside 0 < f < N/2.
    #[error("sequence: projector {projector}'s frequency f={frequency} is outside 0 < f < N/2 = {half} (N = {steps})", half = *steps as f64 / 2.0)]
    FrequencyRange {
        /// The projector.
        projector: usize,
        /// Its frequency.
        frequency: u32,
        /// N.
        steps: u32,
    },
    /// A harmonic (or a fundamental) lands on another projector's (or its own) frequency.
    #[error("sequence: {} of projector {projector} (f={frequency}) lands on {target} ({harmonic}·{frequency} = {} ≡ {} mod {steps})", ordinal(*harmonic), harmonic * frequency, signed_residue(harmonic * frequency, *steps))]
    Alias {
        /// Harmonic number h (1 for a fundamental colliding with another projector's).
        harmonic: u32,
        /// The projector whose light produces it.
        projector: usize,
        /// That projector's frequency.
        frequency: u32,
        /// Where it lands.
        target: AliasTarget,
        /// N.
        steps: u32,
    },
    /// A projector image of zero size or a bad gamma.
    #[error("sequence: projector {projector}: {what}")]
    Projector {
        /// The projector.
        projector: usize,
        /// What is wrong.
        what: String,
    },
    /// A bad fringe-count set.
    #[error("sequence: {direction:?} fringe counts {counts:?}: {what}")]
    Counts {
        /// Which direction's set.
        direction: Direction,
        /// The set.
        counts: Vec<u32>,
        /// What is wrong.
        what: String,
    },
}

impl SequenceError {
    /// What is wrong, without the leading "sequence: " (for a refusal that names the
    /// sequence's place in a file itself).
    pub fn what(&self) -> String {
        let text = self.to_string();
        match text.strip_prefix("sequence: ") {
            Some(rest) => rest.to_owned(),
            None => text,
        }
    }
}

/// x mod n as the nearest residue to 0, written with a true minus sign.
fn signed_residue(x: u32, n: u32) -> String {
    let r = x % n;
    if 2 * r > n {
        format!("−{}", n - r)
    } else {
        r.to_string()
    }
}

/// A complete multiplexed phase-shift sequence for P projectors at once.
///
/// Construction validates everything (frequencies, aliasing under each projector's gamma,
/// fringe counts); a deserialised sequence is validated the same way.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "SequenceFile", into = "SequenceFile")]
pub struct Sequence {
    steps: u32,
    projectors: Vec<ProjectorCode>,
    column_counts: Vec<u32>,
    row_counts: Vec<u32>,
}

/// The stored form of a [`Sequence`] (validated on load).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SequenceFile {
    steps: u32,
    projectors: Vec<ProjectorCode>,
    column_counts: Vec<u32>,
    row_counts: Vec<u32>,
}

impl TryFrom<SequenceFile> for Sequence {
    type Error = SequenceError;
    fn try_from(f: SequenceFile) -> Result<Self, SequenceError> {
        Sequence::new(f.steps, f.projectors, f.column_counts, f.row_counts)
    }
}

impl From<Sequence> for SequenceFile {
    fn from(s: Sequence) -> Self {
        SequenceFile {
            steps: s.steps,
            projectors: s.projectors,
            column_counts: s.column_counts,
            row_counts: s.row_counts,
        }
    }
}

fn gcd(a: u32, b: u32) -> u32 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

impl Sequence {
    /// The "sequence" of a rig without projectors: one plain frame per camera per pose
    /// (a burst of them when the rig file asks for repeats, averaged by the capture), on
    /// which circles are detected directly.
    pub fn camera_only() -> Sequence {
        Sequence {
            steps: 1,
            projectors: Vec::new(),
            column_counts: Vec::new(),
            row_counts: Vec::new(),
        }
    }

    /// Whether this is [`Sequence::camera_only`]: no projectors, one plain frame.
    pub fn is_camera_only(&self) -> bool {
        self.projectors.is_empty()
            && self.steps == 1
            && self.column_counts.is_empty()
            && self.row_counts.is_empty()
    }

    /// A sequence with explicit N, frequencies and counts; refused when anything aliases.
    pub fn new(
        steps: u32,
        projectors: Vec<ProjectorCode>,
        column_counts: Vec<u32>,
        row_counts: Vec<u32>,
    ) -> Result<Sequence, SequenceError> {
        let seq = Sequence {
            steps,
            projectors,
            column_counts,
            row_counts,
        };
        seq.validate()?;
        Ok(seq)
    }

    /// The default sequence for these projectors (docs/design.md §6): when any projector has an
    /// uncorrected gamma, N = 5P with f_p ≡ ±1 (mod 5) = 1, 4, 6, 9, …; otherwise N = 2P+1 with
    /// f_p = 1…P. Fringe counts {20, 21, 25} for columns and rows.
    pub fn default_for(projectors: &[ProjectorSetup]) -> Result<Sequence, SequenceError> {
        let p = projectors.len() as u32;
        let uncorrected = projectors.iter().any(|s| s.response.has_harmonics());
        let (steps, freqs): (u32, Vec<u32>) = if uncorrected {
            // ±1 mod 5: 1, 4, 6, 9, 11, …
            let f = (0..p).map(|i| {
                if i % 2 == 0 {
                    5 * (i / 2) + 1
                } else {
                    5 * (i / 2) + 4
                }
            });
            (5 * p, f.collect())
        } else {
            (2 * p + 1, (1..=p).collect())
        };
        let codes = projectors
            .iter()
            .zip(freqs)
            .map(|(s, frequency)| ProjectorCode {
                width: s.width,
                height: s.height,
                frequency,
                response: s.response,
            })
            .collect();
        Sequence::new(
            steps,
            codes,
            DEFAULT_COUNTS.to_vec(),
            DEFAULT_COUNTS.to_vec(),
        )
    }

    fn validate(&self) -> Result<(), SequenceError> {
        let n = self.steps;
        if self.projectors.is_empty() {
            return match self.is_camera_only() {
                true => Ok(()),
                false => Err(SequenceError::NoProjectors),
            };
        }
        if n < 3 {
            return Err(SequenceError::TooFewSteps(n));
        }
        if n > crate::limits::MAX_PHASE_STEPS {
            return Err(SequenceError::Limit(
                format!("steps N = {n}: at most {}", crate::limits::MAX_PHASE_STEPS).into(),
            ));
        }
        crate::limits::count(
            self.projectors.len(),
            crate::limits::MAX_DEVICES,
            "projectors",
        )
        .map_err(SequenceError::Limit)?;
        for (p, code) in self.projectors.iter().enumerate() {
            crate::limits::image_size(code.width, code.height).map_err(|m| {
                SequenceError::Projector {
                    projector: p,
                    what: format!("image size {m}"),
                }
            })?;
            if let ProjectorResponse::Gamma { gamma } | ProjectorResponse::Linearised { gamma } =
                code.response
            {
                if !(gamma.is_finite() && gamma > 0.0) {
                    return Err(SequenceError::Projector {
                        projector: p,
                        what: format!("gamma {gamma} is not a positive number"),
                    });
                }
            }
            if code.frequency == 0 || 2 * u64::from(code.frequency) >= u64::from(n) {
                return Err(SequenceError::FrequencyRange {
                    projector: p,
                    frequency: code.frequency,
                    steps: n,
                });
            }
        }
        self.validate_aliases()?;
        self.validate_counts()
    }

    /// No fundamental on another projector's frequency; for uncorrected gamma, no harmonic
    /// 2…3 of any projector on ±f of any projector.
    fn validate_aliases(&self) -> Result<(), SequenceError> {
        let n = self.steps;
        // Fundamentals (h = 1, other projectors only) and, for uncorrected gamma, harmonics
        // 2…3 of every projector against ±f of every projector and the mean.
        for (p, code) in self.projectors.iter().enumerate() {
            let top = if code.response.has_harmonics() {
                CHECKED_HARMONICS
            } else {
                1
            };
            for h in 1..=top {
                let r = (h * code.frequency) % n;
                let alias = |target| SequenceError::Alias {
                    harmonic: h,
                    projector: p,
                    frequency: code.frequency,
                    target,
                    steps: n,
                };
                for (q, other) in self.projectors.iter().enumerate() {
                    if h == 1 && q == p {
                        continue;
                    }
                    for negative in [false, true] {
                        let bin = if negative {
                            n - other.frequency
                        } else {
                            other.frequency
                        };
                        if r == bin {
                            return Err(alias(AliasTarget::Frequency {
                                projector: q,
                                frequency: other.frequency,
                                negative,
                            }));
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// Each direction's fringe counts: 2 to [`MAX_COUNTS`], non-zero, distinct, coprime, and
    /// fringes at least 2 px wide on every projector.
    fn validate_counts(&self) -> Result<(), SequenceError> {
        for (direction, counts) in [
            (Direction::Columns, &self.column_counts),
            (Direction::Rows, &self.row_counts),
        ] {
            let bad = |what: String| SequenceError::Counts {
                direction,
                counts: counts.clone(),
                what,
            };
            if !(2..=MAX_COUNTS).contains(&counts.len()) {
                return Err(bad(format!(
                    "need 2 to {} counts for temporal unwrapping",
                    MAX_COUNTS
                )));
            }
            if counts.contains(&0) {
                return Err(bad("a count is zero".into()));
            }
            let mut sorted = counts.clone();
            sorted.sort_unstable();
            sorted.dedup();
            if sorted.len() != counts.len() {
                return Err(bad("counts repeat".into()));
            }
            if counts.iter().fold(0, |g, &c| gcd(g, c)) != 1 {
                return Err(bad(
                    "counts share a common factor, so the code repeats within the screen".into(),
                ));
            }
            let max = *sorted.last().unwrap_or(&0);
            for (p, code) in self.projectors.iter().enumerate() {
                let size = match direction {
                    Direction::Columns => code.width,
                    Direction::Rows => code.height,
                };
                if 2 * u64::from(max) > u64::from(size) {
                    return Err(bad(format!(
                        "count {max} exceeds half of projector {p}'s {size} px (fringes under 2 px)"
                    )));
                }
            }
        }
        Ok(())
    }

    /// Number of phase steps N per (direction, count) group.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// The projectors, in index order p = 0…P−1.
    pub fn projectors(&self) -> &[ProjectorCode] {
        &self.projectors
    }

    /// Fringe counts of a direction.
    pub fn counts(&self, direction: Direction) -> &[u32] {
        match direction {
            Direction::Columns => &self.column_counts,
            Direction::Rows => &self.row_counts,
        }
    }

    /// Number of (direction, count) groups.
    pub fn groups(&self) -> usize {
        self.column_counts.len() + self.row_counts.len()
    }

    /// Total number of frames (groups × N; 1 for [`Sequence::camera_only`]).
    pub fn frame_count(&self) -> usize {
        match self.is_camera_only() {
            true => 1,
            false => self.groups() * self.steps as usize,
        }
    }

    /// What frame k shows, or `None` past the end (and for the plain frame of
    /// [`Sequence::camera_only`], which shows no pattern).
    pub fn frame(&self, k: usize) -> Option<FrameCode> {
        if self.is_camera_only() || k >= self.frame_count() {
            return None;
        }
        let n = self.steps as usize;
        let group = k / n;
        let step = (k % n) as u32;
        let (direction, count_index) = if group < self.column_counts.len() {
            (Direction::Columns, group)
        } else {
            (Direction::Rows, group - self.column_counts.len())
        };
        Some(FrameCode {
            direction,
            count_index,
            count: self.counts(direction)[count_index],
            group,
            step,
        })
    }

    /// Intended linear intensity c ∈ [0, 1] of projector p in frame k at projector pixel
    /// (u, v) (any real position; (0, 0) is the centre of the top-left pixel).
    ///
    /// Panics when p or k is out of range.
    pub fn intensity(&self, p: usize, k: usize, u: f64, v: f64) -> f64 {
        let code = &self.projectors[p];
        let frame = self.frame(k).expect("frame index within the sequence");
        let (pos, size) = match frame.direction {
            Direction::Columns => (u, code.width),
            Direction::Rows => (v, code.height),
        };
        // Spatial phase φ = 2π·n·(u + ½)/W; temporal shift 2π·f_p·s/N (docs/design.md §6).
        let phi = 2.0 * PI * f64::from(frame.count) * (pos + 0.5) / f64::from(size);
        let shift =
            2.0 * PI * f64::from(code.frequency * frame.step % self.steps) / f64::from(self.steps);
        0.5 * (1.0 + (phi - shift).cos())
    }

    /// The 8-bit drive level projector p is sent in frame k at (u, v): the intensity
    /// quantised, through the inverse-gamma table when the projector is linearised.
    pub fn drive(&self, p: usize, k: usize, u: f64, v: f64) -> u8 {
        let level = (255.0 * self.intensity(p, k, u, v)).round() as u8;
        match self.projectors[p].response {
            ProjectorResponse::Linearised { gamma } => inverse_gamma_level(gamma, level),
            _ => level,
        }
    }

    /// Relative light of projector p for each intended 8-bit level round(255·c): through the
    /// inverse-gamma table when linearised, then the projector's response.
    pub fn light_table(&self, p: usize) -> [f64; 256] {
        let response = self.projectors[p].response;
        std::array::from_fn(|level| {
            let level = level as u8;
            response.light(match response {
                ProjectorResponse::Linearised { gamma } => inverse_gamma_level(gamma, level),
                _ => level,
            })
        })
    }

    /// The image projector p is sent in frame k, at its own resolution.
    pub fn pattern_image(&self, p: usize, k: usize) -> image::GrayImage {
        let code = &self.projectors[p];
        let lut = match code.response {
            ProjectorResponse::Linearised { gamma } => inverse_gamma_lut(gamma),
            _ => std::array::from_fn(|i| i as u8),
        };
        image::GrayImage::from_fn(code.width, code.height, |x, y| {
            let level = (255.0 * self.intensity(p, k, f64::from(x), f64::from(y))).round();
            image::Luma([lut[level as usize]])
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn setups(p: usize, response: ProjectorResponse) -> Vec<ProjectorSetup> {
        vec![
            ProjectorSetup {
                width: 1920,
                height: 1080,
                response,
            };
            p
        ]
    }

    const GAMMA: ProjectorResponse = ProjectorResponse::Gamma { gamma: 2.2 };

    #[test]
    fn default_sequences_follow_the_design_rule() {
        // docs/design.md §6: N = 5P, f = {1}, {1,4}, {1,4,6}, {1,4,6,9} for uncorrected gamma.
        let want = [vec![1], vec![1, 4], vec![1, 4, 6], vec![1, 4, 6, 9]];
        for (i, f) in want.iter().enumerate() {
            let p = i + 1;
            let s = Sequence::default_for(&setups(p, GAMMA)).unwrap();
            assert_eq!(s.steps(), 5 * p as u32);
            let got: Vec<u32> = s.projectors().iter().map(|c| c.frequency).collect();
            assert_eq!(&got, f);
            assert_eq!(s.frame_count(), 2 * 3 * 5 * p);
            let lin = ProjectorResponse::Linearised { gamma: 2.2 };
            let s = Sequence::default_for(&setups(p, lin)).unwrap();
            assert_eq!(s.steps(), 2 * p as u32 + 1);
            let got: Vec<u32> = s.projectors().iter().map(|c| c.frequency).collect();
            assert_eq!(got, (1..=p as u32).collect::<Vec<_>>());
        }
        // P = 3 default: 90 frames, columns first, N steps per count.
        let s = Sequence::default_for(&setups(3, GAMMA)).unwrap();
        assert_eq!(s.frame_count(), 90);
        let f = s.frame(16).unwrap();
        assert_eq!(
            (f.direction, f.count, f.group, f.step),
            (Direction::Columns, 21, 1, 1)
        );
        let f = s.frame(89).unwrap();
        assert_eq!(
            (f.direction, f.count, f.group, f.step),
            (Direction::Rows, 25, 5, 14)
        );
        assert!(s.frame(90).is_none());
    }

    #[test]
    fn camera_only_is_one_plain_frame_and_nothing_else_without_projectors() {
        let s = Sequence::camera_only();
        assert_eq!((s.frame_count(), s.projectors().len()), (1, 0));
        assert!(s.frame(0).is_none());
        let back: Sequence = serde_json::from_str(&serde_json::to_string(&s).unwrap()).unwrap();
        assert_eq!(back, s);
        // Steps or counts without projectors are refused.
        for (steps, counts) in [(5, vec![]), (1, counts())] {
            let e = Sequence::new(steps, vec![], counts.clone(), counts).unwrap_err();
            assert_eq!(e, SequenceError::NoProjectors);
        }
    }

    fn code(frequency: u32, response: ProjectorResponse) -> ProjectorCode {
        ProjectorCode {
            width: 1920,
            height: 1080,
            frequency,
            response,
        }
    }

    fn counts() -> Vec<u32> {
        DEFAULT_COUNTS.to_vec()
    }

    #[test]
    fn aliasing_sequences_are_refused_with_the_landing_bin() {
        // The linear choice N = 2P+1, f = 1, 2 under gamma 2.2: 2·1 lands on f = 2.
        let e =
            Sequence::new(5, vec![code(1, GAMMA), code(2, GAMMA)], counts(), counts()).unwrap_err();
        assert_eq!(
            e.to_string(),
            "sequence: 2nd harmonic of projector 0 (f=1) lands on projector 1's frequency f=2 (2·1 = 2 ≡ 2 mod 5)"
        );
        // 3·2 = 6 ≡ −5 (mod 11) hits −f of the second projector.
        let e = Sequence::new(11, vec![code(2, GAMMA), code(5, GAMMA)], counts(), counts())
            .unwrap_err();
        assert!(matches!(
            e,
            SequenceError::Alias {
                harmonic: 3,
                projector: 0,
                target: AliasTarget::Frequency {
                    projector: 1,
                    negative: true,
                    ..
                },
                ..
            }
        ));
        assert!(
            e.to_string().contains("projector 1's frequency −f=−5"),
            "{e}"
        );
        // Its own conjugate: N = 3, f = 1, 2·1 ≡ −1.
        let e = Sequence::new(3, vec![code(1, GAMMA)], counts(), counts()).unwrap_err();
        assert!(
            e.to_string().contains(
                "2nd harmonic of projector 0 (f=1) lands on projector 0's frequency −f=−1"
            ),
            "{e}"
        );
        let e = Sequence::new(6, vec![code(2, GAMMA)], counts(), counts()).unwrap_err();
        assert!(e.to_string().ends_with("(2·2 = 4 ≡ −2 mod 6)"), "{e}");
        // The same sequences are fine for linear light; equal fundamentals never are.
        let lin = ProjectorResponse::Linear;
        assert!(Sequence::new(5, vec![code(1, lin), code(2, lin)], counts(), counts()).is_ok());
        let e = Sequence::new(5, vec![code(1, lin), code(1, lin)], counts(), counts()).unwrap_err();
        assert!(
            e.to_string()
                .contains("fundamental of projector 0 (f=1) lands on projector 1's frequency f=1"),
            "{e}"
        );
        let e = Sequence::new(10, vec![code(5, lin)], counts(), counts()).unwrap_err();
        assert!(matches!(
            e,
            SequenceError::FrequencyRange {
                projector: 0,
                frequency: 5,
                ..
            }
        ));
    }

    #[test]
    fn bad_counts_are_refused() {
        let one = || vec![code(1, ProjectorResponse::Linear)];
        for bad in [
            vec![20],
            vec![20, 25],
            vec![0, 21],
            vec![21, 21, 20],
            vec![20, 21, 600],
        ] {
            let e = Sequence::new(3, one(), counts(), bad.clone()).unwrap_err();
            assert!(
                matches!(&e, SequenceError::Counts { direction: Direction::Rows, counts, .. } if *counts == bad),
                "{e}"
            );
        }
    }

    #[test]
    fn sequence_round_trips_through_json_and_validates_on_load() {
        let s = Sequence::default_for(&setups(3, GAMMA)).unwrap();
        let json = serde_json::to_string(&s).unwrap();
        assert_eq!(serde_json::from_str::<Sequence>(&json).unwrap(), s);
        let aliasing = json.replacen("\"frequency\":6", "\"frequency\":2", 1);
        let e = serde_json::from_str::<Sequence>(&aliasing).unwrap_err();
        assert!(e.to_string().contains("harmonic"), "{e}");
    }

    #[test]
    fn gamma_harmonics_match_the_design_figures() {
        // docs/design.md §6, γ = 2.2: 2nd 0.286, 3rd 0.011, 4th 0.0014 of the fundamental; mean
        // over fundamental (γ+1)/(2γ) = 0.727; 2·a_1 = 0.989 of full white.
        let a1 = pattern_harmonic(2.2, 1);
        assert!((pattern_harmonic(2.2, 2) / a1 - 0.286).abs() < 0.0005);
        assert!((pattern_harmonic(2.2, 3) / a1 - 0.011).abs() < 0.0005);
        assert!((pattern_harmonic(2.2, 4).abs() / a1 - 0.0014).abs() < 0.00005);
        assert!((pattern_harmonic(2.2, 0) / a1 - 3.2 / 4.4).abs() < 1e-9);
        assert!((2.0 * a1 - 0.989).abs() < 0.0005);
        assert!((pattern_harmonic(1.0, 0) - 0.5).abs() < 1e-12);
        assert!((pattern_harmonic(1.0, 1) - 0.5).abs() < 1e-12);
        assert!(pattern_harmonic(1.0, 2).abs() < 1e-12);
    }

    #[test]
    fn inverse_gamma_lut_linearises_light() {
        let lut = inverse_gamma_lut(2.2);
        let r = ProjectorResponse::Linearised { gamma: 2.2 };
        for (level, &drive) in lut.iter().enumerate() {
            let target = level as f64 / 255.0;
            // Within half a drive step of the light curve (slope ≤ γ/255 per step).
            assert!(
                (r.light(drive) - target).abs() <= 0.5 * 2.2 / 255.0,
                "level {level}"
            );
        }
        assert_eq!((lut[0], lut[255]), (0, 255));
    }

    #[test]
    fn pattern_images_carry_the_documented_phase() {
        // DFT over the N steps of a group at pixel x: arg X_f = 2π·n·(x + ½)/W (mod 2π),
        // within the 8-bit quantisation (≈ 1/255 of the swing: < 0.01 rad).
        let s = Sequence::new(
            7,
            vec![code(2, ProjectorResponse::Linear)],
            counts(),
            counts(),
        )
        .unwrap();
        let group = 1; // columns, n = 21
        let imgs: Vec<image::GrayImage> = (0..7)
            .map(|st| s.pattern_image(0, group * 7 + st))
            .collect();
        assert_eq!(imgs[0].dimensions(), (1920, 1080));
        for x in [0u32, 17, 500, 1919] {
            let (mut re, mut im) = (0.0, 0.0);
            for (st, img) in imgs.iter().enumerate() {
                let v = f64::from(img.get_pixel(x, 300).0[0]);
                let a = TAU_F * 2.0 * st as f64 / 7.0;
                re += v * a.cos();
                im += v * a.sin();
            }
            let want = TAU_F * 21.0 * (f64::from(x) + 0.5) / 1920.0;
            let mut e = im.atan2(re) - want;
            e -= TAU_F * (e / TAU_F).round();
            assert!(e.abs() < 0.01, "x {x}: phase error {e}");
        }
        // Rows vary along y only; a linearised projector's image goes through the table.
        let lin = Sequence::new(
            5,
            vec![code(1, ProjectorResponse::Linearised { gamma: 2.2 })],
            counts(),
            counts(),
        )
        .unwrap();
        let k = 3 * 5 + 2;
        let img = lin.pattern_image(0, k);
        let lut = inverse_gamma_lut(2.2);
        let level = (255.0 * lin.intensity(0, k, 0.0, 40.0)).round() as usize;
        assert_eq!(img.get_pixel(700, 40).0[0], lut[level]);
        assert_eq!(lin.drive(0, k, 12.3, 40.0), lut[level]);
    }

    const TAU_F: f64 = std::f64::consts::TAU;
}
