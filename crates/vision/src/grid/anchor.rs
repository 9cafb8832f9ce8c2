//! Anchoring a component (docs/design.md §5): the decoded marker cells of a component propose maps
//! from its frame into a side's board frame; the board's ring pattern confirms or refutes
//! them.

use super::assemble::Component;
use super::ring::Ring;
use super::GridParams;
use hexcal_core::board::{Board, Hex, LatticeMap, MarkerKind, Side};
use std::collections::{HashMap, HashSet};

/// A decoded marker cell placed in a component.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PlacedMarker {
    /// The cell's centre circle.
    pub circle: u32,
    /// What it decoded as.
    pub kind: MarkerKind,
    /// Its centre in the component's frame.
    pub at: Hex,
    /// Rotation σ from the component's frame to the marker's side frame: board direction =
    /// frame direction + σ.
    pub rotation: u8,
}

/// How a board hypothesis fits one component.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Evidence {
    /// Decoded markers at a marker cell of their kind with the hypothesis' rotation.
    pub markers_agree: usize,
    /// Decoded markers anywhere else, or of another kind or rotation.
    pub markers_disagree: usize,
    /// Circles read ringed where the board has a ring.
    pub rings_agree: usize,
    /// Circles whose confident reading contradicts the board.
    pub rings_disagree: usize,
    /// Labelled circles mapped off the board.
    pub off_board: usize,
}

/// Ring sets and marker cells of both sides, computed once.
pub(crate) struct BoardRings {
    ringed: [HashSet<Hex>; 2],
    markers: [HashMap<Hex, MarkerKind>; 2],
}

impl BoardRings {
    /// Tabulate a board.
    pub(crate) fn new(board: &Board) -> BoardRings {
        BoardRings {
            ringed: Side::BOTH.map(|s| board.ringed(s)),
            markers: Side::BOTH.map(|s| {
                board
                    .marker_cells(s)
                    .into_iter()
                    .map(|m| (m.center, m.kind))
                    .collect()
            }),
        }
    }

    /// Whether a placed marker sits, under `map`, on a marker cell of its kind on `side` with
    /// the map's rotation (every marker of a side shares the side's orientation).
    pub(crate) fn agrees(&self, side: Side, map: LatticeMap, m: &PlacedMarker) -> bool {
        self.markers[index(side)].get(&map.apply(m.at)) == Some(&m.kind)
            && m.rotation == map.rotation
    }
}

fn index(side: Side) -> usize {
    match side {
        Side::Front => 0,
        Side::Back => 1,
    }
}

/// Weigh the hypothesis "`map` takes `comp` into `side`'s frame" against the component's
/// markers and ring readings.
pub(crate) fn weigh(
    board: &Board,
    rings: &BoardRings,
    comp: &Component,
    markers: &[PlacedMarker],
    readings: &[Ring],
    side: Side,
    map: LatticeMap,
) -> Evidence {
    let s = index(side);
    let mut ev = Evidence::default();
    for m in markers {
        if rings.agrees(side, map, m) {
            ev.markers_agree += 1;
        } else {
            ev.markers_disagree += 1;
        }
    }
    for &(circle, h) in &comp.points {
        let at = map.apply(h);
        if !board.contains(at) {
            ev.off_board += 1;
            continue;
        }
        let ringed = rings.ringed[s].contains(&at);
        match (readings[circle as usize], ringed) {
            (Ring::Ringed, true) => ev.rings_agree += 1,
            (Ring::Ringed, false) | (Ring::Plain, true) => ev.rings_disagree += 1,
            _ => {}
        }
    }
    ev
}

/// A component's frame after anchoring.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Frame {
    /// The side, when known.
    pub side: Option<Side>,
    /// From the component's frame to the output labels.
    pub map: LatticeMap,
    /// Whether the labels are in the side's board frame.
    pub anchored: bool,
    /// The accepted centre hypothesis' evidence (default when not anchored).
    pub evidence: Evidence,
}

impl Frame {
    /// Whether a placed marker agrees with this frame: at a marker cell of its kind when
    /// anchored; on the side, with the rotation and on the marker lattice when only the side
    /// is fixed.
    pub(crate) fn confirms(&self, m: &PlacedMarker, rings: &BoardRings, spacing: i32) -> bool {
        match self.side {
            Some(side) if self.anchored => rings.agrees(side, self.map, m),
            Some(side) => {
                let at = self.map.apply(m.at);
                m.kind.side() == side
                    && m.rotation == self.map.rotation
                    && !m.kind.is_center()
                    && at.q.rem_euclid(spacing.max(1)) == 0
                    && at.r.rem_euclid(spacing.max(1)) == 0
            }
            None => false,
        }
    }
}

/// Anchor a component: an accepted centre hypothesis, else agreeing side marks, else its own
/// frame.
pub(crate) fn frame(
    board: &Board,
    rings: &BoardRings,
    comp: &Component,
    markers: &[PlacedMarker],
    readings: &[Ring],
    params: &GridParams,
) -> Frame {
    // Centre hypotheses not refuted by the rings or the board's outline, scored by marker
    // agreement; the best is accepted when more markers agree than disagree and no other
    // hypothesis scores as well (one false ring can make two locally symmetric readings).
    let mut centre: Vec<(Side, LatticeMap, Evidence)> = markers
        .iter()
        .filter(|m| m.kind.is_center())
        .map(|m| {
            let map = LatticeMap {
                rotation: m.rotation,
                offset: -m.at.rotate(m.rotation as usize),
            };
            let side = m.kind.side();
            let ev = weigh(board, rings, comp, markers, readings, side, map);
            (side, map, ev)
        })
        .filter(|(_, _, ev)| {
            let bearing = ev.rings_agree + ev.rings_disagree;
            ev.rings_disagree as f64 <= params.max_ring_disagreement * bearing as f64
                && ev.off_board <= params.max_off_board
        })
        .collect();
    let score = |ev: &Evidence| ev.markers_agree as i64 - ev.markers_disagree as i64;
    centre.sort_by_key(|(_, _, ev)| std::cmp::Reverse(score(ev)));
    let centre = match centre.as_slice() {
        [best, rest @ ..]
            if score(&best.2) > 0 && rest.iter().all(|o| score(&o.2) < score(&best.2)) =>
        {
            Some(*best)
        }
        _ => None,
    };
    if let Some((side, map, evidence)) = centre {
        return Frame {
            side: Some(side),
            map,
            anchored: true,
            evidence,
        };
    }
    // Side marks: vote for (side, rotation, offset modulo the marker lattice).
    let s = board.marker_spacing.unwrap_or(1).max(1);
    let mut votes: HashMap<(Side, u8, Hex), (usize, Hex)> = HashMap::new();
    for m in markers.iter().filter(|m| !m.kind.is_center()) {
        let offset = -m.at.rotate(m.rotation as usize);
        let class = Hex::new(offset.q.rem_euclid(s), offset.r.rem_euclid(s));
        votes
            .entry((m.kind.side(), m.rotation, class))
            .or_insert((0, offset))
            .0 += 1;
    }
    let side_fix = votes
        .iter()
        .max_by_key(|(_, (n, _))| *n)
        .map(|(&(side, rotation, _), &(n, offset))| (side, rotation, n, offset))
        .filter(|&(_, _, n, _)| n >= params.min_side_marks && 2 * (markers.len() - n) < n);
    match side_fix {
        Some((side, rotation, _, offset)) => Frame {
            side: Some(side),
            map: LatticeMap { rotation, offset },
            anchored: false,
            evidence: Evidence::default(),
        },
        None => Frame {
            side: None,
            map: LatticeMap::IDENTITY,
            anchored: false,
            evidence: Evidence::default(),
        },
    }
}
