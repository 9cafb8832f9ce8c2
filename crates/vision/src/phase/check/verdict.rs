//! What the stack check concludes (docs/design.md §6b): the faults that make a stack unusable,
//! each with its cause and size, the notes that do not, and the figures behind them.

use super::super::maps::NoiseModel;
use serde::{Deserialize, Serialize};

/// A fault that makes a stack unusable: its projector observations would be biased, or most
/// of them lost, without a word.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum StackFault {
    /// The board moved between fringe groups (the largest step between two groups, or the
    /// drift over the sequence when no one step dominates).
    Motion {
        /// The group before the move (0-based, frame order).
        from_group: usize,
        /// The group after it.
        to_group: usize,
        /// How far it moved (camera px).
        px: f64,
    },
    /// One projector's phases in one fringe group disagree with its other groups, as when it
    /// showed another frame's pattern in some of the group's frames (display lag, a dropped
    /// or repeated frame).
    WrongPattern {
        /// The projector (sequence order).
        projector: usize,
        /// The group (0-based, frame order).
        group: usize,
        /// Its first and last frame.
        frames: [usize; 2],
        /// How many of its frames showed another pattern (estimated).
        count: usize,
        /// The pattern shown instead, as an offset in frames (−1: the previous frame's).
        offset: i32,
    },
    /// One projector showed another frame's pattern somewhere in one direction's groups,
    /// with a bias that took the direction's fused position to wrong fringe orders, so
    /// that no one group stands out: a group, judged against the position the other counts
    /// give alone, is off by what a lag gives (which group is not certain: each reference
    /// but one holds the lagged group).
    LagInGroups {
        /// The projector (sequence order).
        projector: usize,
        /// The direction's first and last group.
        groups: [usize; 2],
        /// Their first and last frame.
        frames: [usize; 2],
    },
    /// A fringe group's mean image holds a projector's fringes (every group shows the same
    /// mean image): the projector showed another frame's pattern in some of its frames.
    /// More than one projector is named when their fringes look alike on the board, so that
    /// the mean cannot tell which.
    FringesInMean {
        /// The projectors it may be (sequence order), the likeliest first.
        projectors: Vec<usize>,
        /// The group.
        group: usize,
        /// Its first and last frame.
        frames: [usize; 2],
    },
    /// One projector's phases in one fringe group disagree with its other groups by more
    /// than noise, with no one cause that fits.
    PhaseDisagreement {
        /// The projector (sequence order).
        projector: usize,
        /// The group.
        group: usize,
        /// Its first and last frame.
        frames: [usize; 2],
        /// RMS disagreement in units of the phase noise.
        sigma: f64,
    },
    /// One projector's phases of one direction match no fringe-order tuple at more of its
    /// pixels than the noise explains: its groups disagree by a large fraction of a fringe (a
    /// whole group shown late, a large light change), and pixels near them take wrong orders.
    Unwrapping {
        /// The projector (sequence order).
        projector: usize,
        /// The direction's first and last group.
        groups: [usize; 2],
        /// Their first and last frame.
        frames: [usize; 2],
        /// Fraction of the tested pixels that failed beyond the expected.
        fraction: f64,
    },
    /// The light changed within a fringe group (room light flicker or a step, a camera whose
    /// exposure wandered): frames differ from the phase-shift model by a common level.
    LightChange {
        /// The first frame affected.
        first_frame: usize,
        /// The last frame affected.
        last_frame: usize,
        /// The largest change, in percent of the mean level.
        percent: f64,
    },
    /// The board jolted within a fringe group.
    Jolt {
        /// The first frame affected.
        first_frame: usize,
        /// The last frame affected.
        last_frame: usize,
        /// How far it moved (camera px).
        px: f64,
    },
    /// Frames that fit neither the phase-shift model nor any named cause.
    Disturbed {
        /// The first frame affected.
        first_frame: usize,
        /// The last frame affected.
        last_frame: usize,
        /// RMS size of the disturbance in units of the per-frame noise σ_I.
        sigma: f64,
    },
    /// White parts of the board clip: their projector pixels are lost.
    Clipped {
        /// Fraction of the lit board whose samples reach full scale in some frame.
        fraction: f64,
    },
}

impl StackFault {
    /// One line: what happened, its size, and what to do.
    pub fn describe(&self) -> String {
        match *self {
            StackFault::Motion {
                from_group,
                to_group,
                px,
            } if to_group == from_group + 1 => format!(
                "the board moved {px:.2} px between fringe groups {} and {} — hold it still",
                from_group + 1,
                to_group + 1
            ),
            StackFault::Motion {
                from_group,
                to_group,
                px,
            } => format!(
                "the board drifted {px:.2} px between fringe groups {} and {} — hold it still",
                from_group + 1,
                to_group + 1
            ),
            StackFault::WrongPattern {
                projector,
                group,
                frames: [a, b],
                count,
                offset,
            } => format!(
                "projector {projector} showed {} in about {count} of the frames of fringe group {} ({}) — check the projector's sync and raise settle_ms",
                pattern_offset(offset),
                group + 1,
                frames(a, b)
            ),
            StackFault::LagInGroups {
                projector,
                groups: [g, h],
                frames: [a, b],
            } => format!(
                "projector {projector} showed another frame's pattern in some frames of fringe groups {}–{} ({}) — check the projector's sync and raise settle_ms",
                g + 1,
                h + 1,
                frames(a, b)
            ),
            StackFault::FringesInMean {
                ref projectors,
                group,
                frames: [a, b],
            } => {
                let who = (projectors.iter().map(|p| p.to_string()))
                    .collect::<Vec<_>>()
                    .join(" or ");
                format!(
                    "projector {who} showed another frame's pattern in fringe group {} ({}): the group's mean image holds its fringes — check the projector's sync and raise settle_ms",
                    group + 1,
                    frames(a, b)
                )
            }
            StackFault::PhaseDisagreement {
                projector,
                group,
                frames: [a, b],
                sigma,
            } => format!(
                "projector {projector}'s phases in fringe group {} ({}) disagree with its other groups ({sigma:.1} × noise) — check the board, the projector's sync and the light",
                group + 1,
                frames(a, b)
            ),
            StackFault::Unwrapping {
                projector,
                groups: [g, h],
                frames: [a, b],
                fraction,
            } => format!(
                "projector {projector}'s fringe groups {}–{} ({}) do not agree on a position at {:.0} % of its pixels — check the projector's sync and raise settle_ms, hold the board still and keep the light steady",
                g + 1,
                h + 1,
                frames(a, b),
                100.0 * fraction
            ),
            StackFault::LightChange {
                first_frame,
                last_frame,
                percent,
            } => format!(
                "the light changed by {percent:.1} % in {} — keep room light steady and the exposure fixed",
                frames(first_frame, last_frame)
            ),
            StackFault::Jolt {
                first_frame,
                last_frame,
                px,
            } => format!(
                "the board moved {px:.2} px in {} — hold it still",
                frames(first_frame, last_frame)
            ),
            StackFault::Disturbed {
                first_frame,
                last_frame,
                sigma,
            } => format!(
                "{} do not fit the fringe model ({sigma:.2} σ) — check the board, the projectors and the light",
                frames(first_frame, last_frame)
            ),
            StackFault::Clipped { fraction } => format!(
                "{:.1} % of the lit board clips — lower the exposure or gain",
                100.0 * fraction
            ),
        }
    }
}

/// "frame 31" or "frames 31–33" (as the stack's files `frame-031.png` are numbered).
fn frames(first: usize, last: usize) -> String {
    match first == last {
        true => format!("frame {first}"),
        false => format!("frames {first}–{last}"),
    }
}

/// "the previous frame's pattern", "the pattern of 2 frames later", …
fn pattern_offset(offset: i32) -> String {
    match offset {
        -1 => "the previous frame's pattern (one frame late)".into(),
        1 => "the next frame's pattern (one frame early)".into(),
        o if o < 0 => format!("the pattern of {} frames earlier", -o),
        o => format!("the pattern of {o} frames later"),
    }
}

/// Something worth knowing about a stack that does not make it unusable.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum StackNote {
    /// The light level changed between fringe groups (harmless to the phases, which each
    /// group measures against its own mean; the noise was measured within the groups).
    LightStep {
        /// The group before the change.
        from_group: usize,
        /// The group after it.
        to_group: usize,
        /// The change, in percent of the mean level.
        percent: f64,
    },
    /// A projector lights the board with little modulation (too dark, too far, defocused).
    LowModulation {
        /// The projector (sequence order).
        projector: usize,
        /// Its median modulation over the pixels it lights, in units of σ_I.
        sigma: f64,
    },
    /// The sequence has a single fringe group: nothing to test a group against, so the
    /// stack was not checked.
    Unchecked,
    /// A fault the decoder repaired exactly (a wrong pattern: its fringe group left out of
    /// the fusion, §6b "Repair"); the stack is used.
    Repaired {
        /// The fault.
        fault: StackFault,
    },
}

impl StackNote {
    /// One line.
    pub fn describe(&self) -> String {
        match *self {
            StackNote::LightStep {
                from_group,
                to_group,
                percent,
            } => format!(
                "the light changed by {percent:+.1} % between fringe groups {} and {} (harmless: each group has its own level; noise measured within groups)",
                from_group + 1,
                to_group + 1
            ),
            StackNote::LowModulation { projector, sigma } => format!(
                "projector {projector} lights the board with a modulation of only {sigma:.1} σ — brighter, nearer or better focused gives more accurate pixels"
            ),
            StackNote::Unchecked => {
                "the sequence has one fringe group: nothing to check the stack against".into()
            }
            StackNote::Repaired { ref fault } => match *fault {
                StackFault::WrongPattern { group, .. } => format!(
                    "repaired: {}; fringe group {} was left out of every projector's positions",
                    fault.describe(),
                    group + 1
                ),
                _ => format!("repaired: {}", fault.describe()),
            },
        }
    }
}

/// The check's measurements, for the dataset and the report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CheckFigures {
    /// Pixels sampled (2 × 2 blocks on a grid).
    pub samples: usize,
    /// The noise model measured within the fringe groups.
    pub noise: NoiseModel,
    /// Per group, the board's displacement from its mean position (camera px).
    pub displacement: Vec<[f64; 2]>,
    /// Per frame, the RMS disturbance the phase-shift model does not explain (σ_I units).
    pub disturbance: Vec<f64>,
    /// Fraction of the lit board that clips.
    pub clipped: f64,
}

/// The check's conclusion on one camera's stack.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StackVerdict {
    /// What makes the stack unusable (empty: it can be used).
    pub faults: Vec<StackFault>,
    /// What is worth knowing but harmless.
    pub notes: Vec<StackNote>,
    /// The measurements.
    pub figures: CheckFigures,
}

impl StackVerdict {
    /// Whether the stack can be used.
    pub fn passed(&self) -> bool {
        self.faults.is_empty()
    }

    /// Every figure finite (a verdict read back from a file).
    pub fn check(&self) -> Result<(), hexcal_core::ValidationError> {
        let f = &self.figures;
        let n = [f.noise.offset, f.noise.slope, f.noise.floor, f.clipped];
        let all = n
            .iter()
            .chain(f.displacement.iter().flatten())
            .chain(&f.disturbance);
        match all.clone().all(|v| v.is_finite()) {
            true => Ok(()),
            false => Err(hexcal_core::ValidationError::new(
                "verdict.figures",
                "a figure is not a finite number",
            )),
        }
    }

    /// The faults, one line each joined by "; " (empty when it passed).
    pub fn summary(&self) -> String {
        self.faults
            .iter()
            .map(StackFault::describe)
            .collect::<Vec<_>>()
            .join("; ")
    }
}
