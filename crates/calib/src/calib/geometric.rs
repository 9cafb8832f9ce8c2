//! Registration of unanchored views by geometry (docs/design.md §7, "Without projectors").
//!
//! Takes a first calibration from the anchored views and the views still unanchored after
//! the projector registration; gives those views anchored, their labels in the board's own
//! frame, and a second calibration that uses them. The camera's model and pose and the
//! board pose at the view's pose index (known from the other cameras) predict where every
//! circle of the side facing the camera lands in the image. Each circle of the view votes,
//! through the predicted circle nearest it, for the lattice transforms (six rotations, a
//! translation, the side) that take its label there; the winner is accepted on a clear
//! margin over the runner-up. Views that cannot be placed are reported, never guessed.

use super::solve::{calibrate, CalibrateOptions, Calibration};
use super::views::{Evidence, Registered, Unregistered};
use super::CalibError;
use hexcal_core::board::{lattice_votes, Board, Hex, LatticeMap, Side};
use hexcal_core::camera::CameraModel;
use hexcal_core::observations::DeviceInfo;
use hexcal_core::observations::{CameraView, Frame, ViewPoint};
use hexcal_core::Invalid;
use nalgebra::{Isometry3, Point2, Point3, Vector3};
use std::collections::BTreeSet;

/// Settings of geometric registration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GeometricParams {
    /// A circle matches the predicted circle nearest it within this fraction of the
    /// predicted distance to that circle's nearest neighbour (the local pitch in pixels).
    pub max_distance: f64,
    /// Matches needed.
    pub min_matches: usize,
    /// Fraction of the view's circles that must agree on the winning transform.
    pub min_agreement: f64,
    /// The winning transform needs this many times the votes of the runner-up.
    pub margin: f64,
}

impl Default for GeometricParams {
    fn default() -> Self {
        GeometricParams {
            max_distance: 0.3,
            min_matches: 6,
            min_agreement: 0.8,
            margin: 3.0,
        }
    }
}

/// A predicted circle: its label, side and image position, and the predicted distance to
/// its nearest neighbour (px).
#[derive(Clone, Copy, Debug)]
struct Predicted {
    hex: Hex,
    side: Side,
    pixel: Point2<f64>,
    pitch: f64,
}

/// Where the circles of the sides facing the camera land in its image, for the camera
/// `model` at `device_from_board` (T_device_board).
fn predict(
    board: &Board,
    model: &CameraModel,
    device_from_board: &Isometry3<f64>,
) -> Vec<Predicted> {
    let centre = device_from_board.inverse() * Point3::origin();
    let (w, h) = (f64::from(model.width), f64::from(model.height));
    let mut out = Vec::new();
    for &side in board.sides.list() {
        let normal = board.side_transform(side).rotation * Vector3::z();
        let project = |hex: Hex| -> Option<Point2<f64>> {
            let x = board.point(side, hex);
            (normal.dot(&(centre - x)) > 0.0)
                .then(|| model.project(&(device_from_board * x)))
                .flatten()
        };
        for hex in board.lattice() {
            let Some(pixel) = project(hex) else { continue };
            if !(pixel.x > -0.5 && pixel.y > -0.5 && pixel.x < w - 0.5 && pixel.y < h - 0.5) {
                continue;
            }
            let pitch = hex
                .neighbours()
                .into_iter()
                .filter_map(|n| project(n).map(|q| (q - pixel).norm()))
                .fold(f64::INFINITY, f64::min);
            if pitch.is_finite() {
                out.push(Predicted {
                    hex,
                    side,
                    pixel,
                    pitch,
                });
            }
        }
    }
    out
}

/// A view placed on the board: the view with its labels in the side's own frame, the
/// circles matched to predictions and those agreeing with the accepted transform.
#[derive(Clone, Debug, PartialEq)]
pub struct Placed {
    /// The view, anchored.
    pub view: CameraView,
    /// Circles matched to a predicted circle.
    pub matches: usize,
    /// Matches agreeing with the accepted transform.
    pub agreeing: usize,
}

/// Place one unanchored `view` of a camera `model` at `device_from_board` (T_device_board):
/// the lattice transform its circles' nearest predicted circles agree on; refused (with the
/// reason) without enough matches, agreement or margin.
pub fn place_view(
    board: &Board,
    model: &CameraModel,
    device_from_board: &Isometry3<f64>,
    view: &CameraView,
    params: &GeometricParams,
) -> Result<Placed, Invalid> {
    let predicted = predict(board, model, device_from_board);
    let mut pairs = Vec::new();
    for pt in &view.points {
        let nearest = predicted
            .iter()
            .map(|p| ((p.pixel - pt.image).norm(), p))
            .min_by(|a, b| a.0.total_cmp(&b.0));
        let Some((_, p)) = nearest.filter(|(d, p)| *d <= params.max_distance * p.pitch) else {
            continue;
        };
        pairs.push((p.side, pt.hex, p.hex));
    }
    let matches = pairs.len();
    let mut ranked: Vec<((Side, LatticeMap), usize)> = lattice_votes(pairs).into_iter().collect();
    ranked.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    let ((side, best), agree) = match ranked.first() {
        Some(&(m, n)) => (m, n),
        None => return Err("no circle lies near a predicted circle".into()),
    };
    let second = ranked.get(1).map_or(0, |r| r.1);
    let n = view.points.len();
    if matches < params.min_matches || (agree as f64) < params.min_agreement * n as f64 {
        return Err(Invalid(format!(
            "{matches} of {n} circles near a predicted circle, the best lattice transform \
             agrees with {agree}"
        )));
    }
    if (agree as f64) < params.margin * second as f64 {
        return Err(Invalid(format!(
            "ambiguous: the best lattice transform agrees with {agree} circles, the next \
             with {second}"
        )));
    }
    let points = view
        .points
        .iter()
        .map(|p| ViewPoint {
            hex: best.apply(p.hex),
            ..p.clone()
        })
        .collect();
    Ok(Placed {
        view: CameraView {
            frame: Frame::Anchored(side),
            points,
            ..view.clone()
        },
        matches,
        agreeing: agree,
    })
}

/// The views placed by geometry after calibration `cal`, and those refused (with why).
fn place_unanchored(
    board: &Board,
    cal: &Calibration,
    views: &[CameraView],
    params: &GeometricParams,
) -> (Vec<Placed>, Vec<Unregistered>) {
    let mut placed = Vec::new();
    let mut refused = Vec::new();
    for v in views.iter().filter(|v| v.frame == Frame::Unanchored) {
        let d = cal.device_index.iter().position(|&i| i == v.camera);
        let k = cal.pose_index.iter().position(|&i| i == v.pose);
        let result = match (d, k) {
            (None, _) => Err("its camera was not calibrated from anchored views".into()),
            (_, None) => Err("no calibrated camera placed the board at this pose".into()),
            (Some(d), Some(k)) => {
                let device = &cal.devices[d];
                let device_from_board = device.pose * cal.solution.boards[k];
                place_view(board, &device.model, &device_from_board, v, params)
            }
        };
        match result {
            Ok(p) => placed.push(p),
            Err(reason) => refused.push(Unregistered {
                camera: v.camera,
                pose: v.pose,
                reason: format!("by geometry: {reason}"),
            }),
        }
    }
    (placed, refused)
}

/// Calibrate as [`calibrate`] does, then register the views still unanchored by geometry
/// and, when any was placed, calibrate again with them. The registration report covers
/// both ways: views registered by projector coordinates or by geometry, and the leftovers
/// with the reasons of both.
pub fn calibrate_registering(
    board: &Board,
    devices: &[DeviceInfo],
    poses: usize,
    views: &[CameraView],
    options: &CalibrateOptions,
    params: &GeometricParams,
) -> Result<Calibration, CalibError> {
    let first = calibrate(board, devices, poses, views, options)?;
    // The views the projector registration left over, with their original labels.
    let left: BTreeSet<(usize, usize)> = first
        .registration
        .unregistered
        .iter()
        .map(|u| (u.camera, u.pose))
        .collect();
    let leftovers: Vec<CameraView> = views
        .iter()
        .filter(|v| left.contains(&(v.camera, v.pose)))
        .cloned()
        .collect();
    let (placed, refused) = place_unanchored(board, &first, &leftovers, params);
    if placed.is_empty() {
        let mut cal = first;
        cal.registration.unregistered = merge_reasons(&cal.registration.unregistered, &refused);
        return Ok(cal);
    }
    let mut input: Vec<CameraView> = views.to_vec();
    for p in &placed {
        if let Some(v) = input
            .iter_mut()
            .find(|v| (v.camera, v.pose) == (p.view.camera, p.view.pose))
        {
            *v = p.view.clone();
        }
    }
    let mut cal = calibrate(board, devices, poses, &input, options)?;
    let reg = &mut cal.registration;
    reg.unanchored += placed.len();
    reg.registered.extend(placed.iter().map(|p| Registered {
        camera: p.view.camera,
        pose: p.view.pose,
        matches: p.matches,
        agreeing: p.agreeing,
        by: Evidence::Geometry,
    }));
    reg.unregistered = merge_reasons(&reg.unregistered, &refused);
    Ok(cal)
}

/// The projector registration's leftovers with the geometric refusal's reason added.
fn merge_reasons(projector: &[Unregistered], geometric: &[Unregistered]) -> Vec<Unregistered> {
    projector
        .iter()
        .map(|u| {
            let why = geometric
                .iter()
                .find(|g| (g.camera, g.pose) == (u.camera, u.pose));
            Unregistered {
                reason: match why {
                    Some(g) => format!("{}; {}", u.reason, g.reason),
                    None => u.reason.clone(),
                },
                ..u.clone()
            }
        })
        .collect()
}

#[cfg(test)]
mod tests;
