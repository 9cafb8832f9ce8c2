//! Correspondences in, observations out: one camera's labelled view of one board pose with
//! the projector coordinates decoded at its circles, the registration of views whose grid
//! is not anchored (docs/design.md §7), and the flattening into bundle-adjustment observations.
//!
//! Registration uses projector coordinates as descriptors. An unanchored view's points are
//! matched to anchored points of another camera at the same board pose under the same
//! projector (nearest in projector pixels, within a fraction of the projected lattice
//! pitch); every match votes for a lattice transform (one of six rotations and a
//! translation) and the anchored point's side; a clear majority is accepted. Views that
//! cannot be registered are reported, never guessed.

use super::bundle::{Observation, Via};
use hexcal_core::board::{lattice_votes, Hex, Side};
use hexcal_core::observations::{CameraView, Frame, ViewPoint};
use nalgebra::Point2;
use std::collections::HashMap;

/// What placed an unanchored view on the board.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Evidence {
    /// Projector coordinates shared with anchored views ([`register`]).
    Projectors,
    /// The circles predicted by a first calibration ([`super::geometric`]).
    Geometry,
}

/// An unanchored view that registration placed on the board.
#[derive(Clone, Debug, PartialEq)]
pub struct Registered {
    /// Camera index.
    pub camera: usize,
    /// Board pose index.
    pub pose: usize,
    /// Points matched to anchored points in projector space (or to predicted circles).
    pub matches: usize,
    /// Matches agreeing with the accepted lattice transform.
    pub agreeing: usize,
    /// What placed it.
    pub by: Evidence,
}

/// An unanchored view left out.
#[derive(Clone, Debug, PartialEq)]
pub struct Unregistered {
    /// Camera index.
    pub camera: usize,
    /// Board pose index.
    pub pose: usize,
    /// Why.
    pub reason: String,
}

/// What registration did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Registration {
    /// Unanchored views given.
    pub unanchored: usize,
    /// Of those, the registered ones.
    pub registered: Vec<Registered>,
    /// And those left out.
    pub unregistered: Vec<Unregistered>,
}

/// An anchored circle as a descriptor: its projector pixel under one projector.
#[derive(Clone, Copy, Debug)]
struct AnchoredPoint {
    pixel: Point2<f64>,
    side: Side,
    hex: Hex,
}

/// Settings of [`register`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RegisterParams {
    /// A match must lie within this many projector px.
    pub max_distance: f64,
    /// Matches needed.
    pub min_matches: usize,
    /// Fraction of matches that must agree on the winning transform.
    pub min_agreement: f64,
}

impl Default for RegisterParams {
    fn default() -> Self {
        RegisterParams {
            max_distance: 3.0,
            min_matches: 6,
            min_agreement: 0.8,
        }
    }
}

/// Register the unanchored views against the anchored ones; registered views come back
/// anchored with relabelled points, the others are dropped and reported.
pub fn register(views: &[CameraView], params: &RegisterParams) -> (Vec<CameraView>, Registration) {
    // Anchored points per (pose, projector): (projector pixel, side, hex).
    let mut anchored: HashMap<(usize, usize), Vec<AnchoredPoint>> = HashMap::new();
    for v in views {
        if let Frame::Anchored(side) = v.frame {
            for pt in &v.points {
                for pp in &pt.projectors {
                    anchored
                        .entry((v.pose, pp.projector))
                        .or_default()
                        .push(AnchoredPoint {
                            pixel: pp.pixel,
                            side,
                            hex: pt.hex,
                        });
                }
            }
        }
    }
    let mut out = Vec::with_capacity(views.len());
    let mut report = Registration::default();
    for v in views {
        if v.frame != Frame::Unanchored {
            out.push(v.clone());
            continue;
        }
        report.unanchored += 1;
        // Each (point, anchored neighbour) pair votes for the six rotations' maps.
        let mut pairs = Vec::new();
        for pt in &v.points {
            let mut best: Option<(f64, AnchoredPoint)> = None;
            for pp in &pt.projectors {
                for a in anchored.get(&(v.pose, pp.projector)).into_iter().flatten() {
                    let d = (a.pixel - pp.pixel).norm();
                    if d <= params.max_distance && best.is_none_or(|b| d < b.0) {
                        best = Some((d, *a));
                    }
                }
            }
            if let Some((_, AnchoredPoint { side, hex, .. })) = best {
                pairs.push((side, pt.hex, hex));
            }
        }
        let matches = pairs.len();
        let winner = lattice_votes(pairs)
            .into_iter()
            .max_by_key(|&((_, m), n)| (n, m.rotation));
        match winner {
            Some(((side, map), agree))
                if matches >= params.min_matches
                    && agree as f64 >= params.min_agreement * matches as f64 =>
            {
                report.registered.push(Registered {
                    camera: v.camera,
                    pose: v.pose,
                    matches,
                    agreeing: agree,
                    by: Evidence::Projectors,
                });
                out.push(CameraView {
                    frame: Frame::Anchored(side),
                    points: v
                        .points
                        .iter()
                        .map(|p| ViewPoint {
                            hex: map.apply(p.hex),
                            ..p.clone()
                        })
                        .collect(),
                    ..v.clone()
                });
            }
            Some((_, agree)) => report.unregistered.push(Unregistered {
                camera: v.camera,
                pose: v.pose,
                reason: format!(
                    "{matches} projector matches, the best lattice transform agrees with {agree}"
                ),
            }),
            None => report.unregistered.push(Unregistered {
                camera: v.camera,
                pose: v.pose,
                reason: "no point matched an anchored view under a common projector".into(),
            }),
        }
    }
    (out, report)
}

/// Bundle-adjustment observations of anchored views: one per camera circle and one per
/// (camera, projector, circle).
pub fn observations(views: &[CameraView]) -> Vec<Observation> {
    let mut out = Vec::new();
    for v in views {
        let Frame::Anchored(side) = v.frame else {
            continue;
        };
        for pt in &v.points {
            out.push(Observation {
                device: v.camera,
                pose: v.pose,
                side,
                hex: pt.hex,
                pixel: pt.image,
                via: None,
            });
            out.extend(pt.projectors.iter().map(|pp| Observation {
                device: pp.projector,
                pose: v.pose,
                side,
                hex: pt.hex,
                pixel: pp.pixel,
                via: Some(Via {
                    camera: v.camera,
                    ellipse_center: pt.image,
                }),
            }));
        }
    }
    out
}
