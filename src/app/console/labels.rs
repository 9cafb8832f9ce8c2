//! What to draw over each camera's picture on the console: its labelled points and lattice
//! edges.
//!
//! Takes a camera's labelled view (or labelled points of a live frame); gives [`Overlay`].

use crate::board::Hex;
use crate::observations::CameraView;
use nalgebra::Point2;
use serde::Serialize;
use std::collections::HashMap;

/// What to draw over a camera's thumbnail: its labelled points and lattice edges.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Overlay {
    /// The pose.
    pub pose: usize,
    /// Circles detected.
    pub circles: usize,
    /// Whether the labels are anchored on the board.
    pub anchored: bool,
    /// Labelled points (image px, rounded to 0.1).
    pub points: Vec<[f32; 2]>,
    /// Lattice neighbours as index pairs into `points`.
    pub edges: Vec<[u32; 2]>,
}

impl Overlay {
    /// The overlay of `view` (none: the board was not found) of pose `pose`.
    pub fn of(pose: usize, circles: usize, view: Option<&CameraView>) -> Overlay {
        let Some(view) = view else {
            return Overlay::labelled(pose, circles, false, &[]);
        };
        let points: Vec<(Hex, Point2<f64>)> =
            view.points.iter().map(|p| (p.hex, p.image)).collect();
        let anchored = matches!(view.frame, crate::observations::Frame::Anchored(_));
        Overlay::labelled(pose, circles, anchored, &points)
    }

    /// The overlay of labelled points (lattice position, image px) of pose `pose`, with the
    /// lattice edges between neighbours.
    pub fn labelled(
        pose: usize,
        circles: usize,
        anchored: bool,
        points: &[(Hex, Point2<f64>)],
    ) -> Overlay {
        let index: HashMap<Hex, u32> = (0..).zip(points).map(|(i, p)| (p.0, i)).collect();
        let mut edges = Vec::new();
        for (i, p) in (0..).zip(points) {
            // Three of the six directions, so each edge is listed once.
            for k in 0..3 {
                if let Some(&j) = index.get(&p.0.neighbour(k)) {
                    edges.push([i, j]);
                }
            }
        }
        let round = |v: f64| ((v * 10.0).round() / 10.0) as f32;
        Overlay {
            pose,
            circles,
            anchored,
            points: points
                .iter()
                .map(|p| [round(p.1.x), round(p.1.y)])
                .collect(),
            edges,
        }
    }
}
