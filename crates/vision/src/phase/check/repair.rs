//! Repair of a stack whose only faults are projectors showing another frame's pattern
//! (docs/design.md §6b, "Repair"): takes the verdict; gives, per projector, the fringe groups
//! its fusion leaves out, and the verdict with those faults turned into notes.
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

/// The repair of `verdict` on a stack of `seq`: a bit per fringe group (frame order) that
/// every projector's fusion leaves out. Repairable when every fault is a wrong pattern, at
/// most one group of each direction, whose other counts form a constellation of their own
/// (two or more, coprime as a set: for 20, 21, 25 the groups of 20 and 25, not 21), which
/// guards the fringe orders. Each such group is left out of every projector (the wrong
/// frames leak into the other projectors' bins of that group too). `None`: nothing to
/// repair, or not repairable.
pub fn plan(verdict: &StackVerdict, seq: &Sequence) -> Option<u32> {
    if verdict.faults.is_empty() {
        return None;
    }
    let mut groups = 0u32;
    for fault in &verdict.faults {
        match fault {
            StackFault::WrongPattern { group, .. } => groups |= 1 << group,
            _ => return None,
        }
    }
    let n_col = seq.counts(Direction::Columns).len();
    for (first, dir) in [(0, Direction::Columns), (n_col, Direction::Rows)] {
        let counts = seq.counts(dir);
        let out = (groups >> first) & ((1 << counts.len()) - 1);
        let kept: Vec<u32> = (counts.iter().enumerate())
            .filter(|(j, _)| out & (1 << j) == 0)
            .map(|(_, &c)| c)
            .collect();
        if out.count_ones() > 1 || (out != 0 && Constellation::shared(&kept).is_err()) {
            return None;
        }
    }
    Some(groups)
}

/// `verdict` with its faults turned into [`StackNote::Repaired`] notes (the stack is
/// used).
pub fn repaired(mut verdict: StackVerdict) -> StackVerdict {
    let faults = std::mem::take(&mut verdict.faults);
    verdict.notes.extend(
        faults
            .into_iter()
            .map(|fault| StackNote::Repaired { fault }),
    );
    verdict
}
