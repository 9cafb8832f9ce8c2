//! Grid building (DESIGN.md §5): local hexagonal cells with chord-normalised distances,
//! marker-ring decoding, and breadth-first assembly into one labelled lattice.
//!
//! Takes the detected circles of one image (and the image, to read marker rings) and gives
//! labelled points: lattice position, side when known, and whether the labels are anchored
//! in the side's board frame.

use crate::board::{Hex, Side};
use nalgebra::Point2;
use serde::{Deserialize, Serialize};

/// A detected circle with its lattice label.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LabelledPoint {
    /// Index into the detections this grid was built from.
    pub circle: usize,
    /// Ellipse centre in the image (px).
    pub image: Point2<f64>,
    /// Lattice position: in the side's board frame when `anchored`, else in an arbitrary but
    /// self-consistent lattice frame shared by all points of the grid.
    pub hex: Hex,
    /// Side seen, when side markers fixed it.
    pub side: Option<Side>,
    /// Whether `hex` and `side` are in that side's own board frame.
    pub anchored: bool,
}
