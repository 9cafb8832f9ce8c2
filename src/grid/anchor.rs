//! Anchoring a component (DESIGN.md §5): the decoded marker cells of a component propose maps
//! from its frame into a side's board frame; the board's ring pattern confirms or refutes
//! them.

use super::assemble::Component;
use super::ring::Ring;
use crate::board::{Board, Hex, MarkerKind, Side};
use std::collections::{HashMap, HashSet};

/// A map from a component's lattice frame into a side's: h ↦ rotate(h, rotation) + offset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(crate) struct LatticeMap {
    /// 60° counter-clockwise steps.
    pub rotation: u8,
    /// Translation applied after the rotation.
    pub offset: Hex,
}

impl LatticeMap {
    /// Apply the map.
    pub(crate) fn apply(&self, h: Hex) -> Hex {
        h.rotate(self.rotation as usize) + self.offset
    }
}

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
}

impl BoardRings {
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
