//! Repair of a stack whose only faults are projectors showing another frame's pattern
//! (docs/design.md §6b, eq. 6b.7): takes the check's faults; gives the fringe groups every
//! projector's fusion leaves out (the check confirms them and turns the faults into
//! [`StackNote::Repaired`] notes; the decoder reads them back from the verdict).
//!
//! A projector that showed the wrong pattern in some frames of group g biases what group g
//! measures. Each direction's M fringe counts measure one position: group g still helps
//! find the fringe orders (checked against the other counts alone), but left out of the
//! fused position its bias is gone, and the position rests on the other counts — exact (no
//! model of what was shown), at the cost of that group's share of the information
//! (√(Σn²/Σ_{j≠g}n²) in σ: 1.17–1.32 for counts 20, 21, 25).

use super::verdict::{StackFault, StackNote, StackVerdict};
use crate::phase::unwrap::Constellation;
use hexcal_core::pattern::{Direction, Sequence};

/// The fringe groups (a bit each, frame order) a repair of `faults` on a stack of `seq`
/// would leave out of every projector's fusion: when every fault is a wrong pattern, at most
/// one group of each direction, whose other counts form a constellation of their own (two
/// or more, coprime as a set: for 20, 21, 25 the groups of 20 and 25, not 21), which guards
/// the fringe orders. Each such group is left out of every projector (the wrong frames leak
/// into the other projectors' bins of that group too). `None`: nothing to repair, or not
/// repairable. The check then confirms that the kept groups agree (the lag was placed in
/// the right group) and that the kept positions are not much noisier (eq. 6b.10).
pub(super) fn plan(faults: &[StackFault], seq: &Sequence) -> Option<u32> {
    if faults.is_empty() {
        return None;
    }
    let mut groups = 0u32;
    for fault in faults {
        match fault {
            StackFault::WrongPattern { group, .. } => groups |= 1 << group,
            _ => return None,
        }
    }
    let n_col = seq.counts(Direction::Columns).len();
    for (first, dir) in [(0, Direction::Columns), (n_col, Direction::Rows)] {
        let kept = kept_groups(seq, dir, first, groups);
        let out = seq.counts(dir).len() - kept.len();
        let counts: Vec<u32> = kept.iter().map(|&(_, c)| c).collect();
        if out > 1 || (out == 1 && Constellation::shared(&counts).is_err()) {
            return None;
        }
    }
    Some(groups)
}

/// The groups of direction `dir` (its first group `first`) not in `left_out`, with their
/// counts.
pub(crate) fn kept_groups(
    seq: &Sequence,
    dir: Direction,
    first: usize,
    left_out: u32,
) -> Vec<(usize, u32)> {
    (seq.counts(dir).iter().enumerate())
        .map(|(j, &c)| (first + j, c))
        .filter(|&(g, _)| left_out & (1 << g) == 0)
        .collect()
}

/// The fringe groups (a bit each) a verdict's repairs left out of the fusions.
pub fn left_out(verdict: &StackVerdict) -> u32 {
    (verdict.notes.iter())
        .filter_map(|n| match n {
            StackNote::Repaired {
                fault: StackFault::WrongPattern { group, .. },
            } => Some(1 << group),
            _ => None,
        })
        .fold(0, |a, b| a | b)
}
