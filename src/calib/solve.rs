//! The whole calibration from labelled views (docs/design.md §7–8): registration of unanchored
//! views, Zhang's initialisation per device, the pose graph, one bundle adjustment.
//!
//! Takes the rig's devices (names, kinds, image sizes), the board and every camera's
//! [`CameraView`]s; gives a [`Calibration`]: every device's model and pose in the reference
//! device's frame, the board poses, the adjustment's residuals and covariance, and what
//! could not be used (devices with too few views, views not connected to the reference,
//! views not registered), each reported by name.

use super::bundle::{self, Device, DeviceKind, Observation, Options, Problem, Solution};
use super::posegraph::{chain, PairEstimate};
use super::views::{observations, register, CameraView, RegisterParams, Registration};
use super::zhang;
use super::{CalibError, PlanarView, PlaneCorrespondence};
use crate::board::{Board, Side};
use crate::camera::CameraModel;
use std::collections::BTreeMap;

/// A device to calibrate.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DeviceInfo {
    /// Name used in reports and outputs.
    pub name: String,
    /// Camera or projector.
    pub kind: DeviceKind,
    /// Image (or projector raster) width (px).
    pub width: u32,
    /// Image (or projector raster) height (px).
    pub height: u32,
}

/// Everything calibration needs from the stages before it, as a file (JSON): the board,
/// the devices, the number of board poses, and every camera's labelled views with projector
/// pixels at their circles.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Correspondences {
    /// A built-in board name or a board file path.
    pub board: String,
    /// The devices, indexed by the views.
    pub devices: Vec<DeviceInfo>,
    /// Number of board poses.
    pub poses: usize,
    /// The labelled views.
    pub views: Vec<CameraView>,
}

/// Settings of [`calibrate`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CalibrateOptions {
    /// Registration of unanchored views.
    pub register: RegisterParams,
    /// The bundle adjustment (its `reference` is the gauge device).
    pub bundle: Options,
    /// Points a (device, pose, side) view needs to count for initialisation.
    pub min_view_points: usize,
}

impl Default for CalibrateOptions {
    fn default() -> Self {
        CalibrateOptions {
            register: RegisterParams::default(),
            bundle: Options::default(),
            min_view_points: 12,
        }
    }
}

/// A device left out, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Excluded {
    /// Device name.
    pub name: String,
    /// Why it was left out.
    pub reason: String,
}

/// The result of [`calibrate`].
#[derive(Clone, Debug)]
pub struct Calibration {
    /// The board used (side transform as given; the refined one is in the solution).
    pub board: Board,
    /// Calibrated devices, in input order among those kept.
    pub devices: Vec<Device>,
    /// The reference device (index into `devices`): its frame is the rig's, its pose the
    /// identity.
    pub reference: usize,
    /// Input index of each calibrated device.
    pub device_index: Vec<usize>,
    /// Input index of each adjusted board pose.
    pub pose_index: Vec<usize>,
    /// Devices left out.
    pub excluded: Vec<Excluded>,
    /// What registration did.
    pub registration: Registration,
    /// The observations adjusted (device and pose indices into `devices`/`pose_index`).
    pub observations: Vec<Observation>,
    /// The adjustment.
    pub solution: Solution,
}

/// Zhang's start of one device: views grouped by (pose, side), each view's pose.
struct Start {
    model: CameraModel,
    pairs: Vec<PairEstimate>,
}

fn initialise(
    board: &Board,
    info: &DeviceInfo,
    device: usize,
    obs: &[Observation],
    min_points: usize,
) -> Result<Start, CalibError> {
    // Group by (pose, side); a projector sees each circle through several cameras: keep one
    // correspondence per circle (the first) for the start.
    let mut groups: BTreeMap<(usize, u8), BTreeMap<crate::board::Hex, PlaneCorrespondence>> =
        BTreeMap::new();
    for o in obs.iter().filter(|o| o.device == device) {
        let side = match o.side {
            Side::Front => 0,
            Side::Back => 1,
        };
        groups
            .entry((o.pose, side))
            .or_default()
            .entry(o.hex)
            .or_insert(PlaneCorrespondence {
                board: board.position(o.hex),
                image: o.pixel,
            });
    }
    let keys: Vec<(usize, u8)> = groups
        .iter()
        .filter(|(_, g)| g.len() >= min_points)
        .map(|(k, _)| *k)
        .collect();
    let views: Vec<PlanarView> = keys
        .iter()
        .map(|k| PlanarView {
            points: groups[k].values().copied().collect(),
        })
        .collect();
    let (model, poses) =
        zhang::initialise(&views, info.width, info.height).map_err(|e| CalibError::Start {
            views: views.len(),
            reason: Box::new(e),
        })?;
    let pairs = keys
        .iter()
        .zip(&poses)
        .zip(&views)
        .map(|((&(pose, side), device_from_side), view)| {
            let side = if side == 0 { Side::Front } else { Side::Back };
            PairEstimate {
                device,
                pose,
                device_from_board: device_from_side * board.side_transform(side).inverse(),
                points: view.points.len(),
            }
        })
        .collect();
    Ok(Start { model, pairs })
}

/// Calibrate every device from the cameras' labelled views of `poses` board poses.
pub fn calibrate(
    board: &Board,
    devices: &[DeviceInfo],
    poses: usize,
    views: &[CameraView],
    options: &CalibrateOptions,
) -> Result<Calibration, CalibError> {
    let (views, registration) = register(views, &options.register);
    let obs = observations(&views);
    let mut excluded = Vec::new();
    let mut models = vec![None; devices.len()];
    let mut pairs = Vec::new();
    for (d, info) in devices.iter().enumerate() {
        match initialise(board, info, d, &obs, options.min_view_points) {
            Ok(start) => {
                models[d] = Some(start.model);
                pairs.extend(start.pairs);
            }
            Err(e) => excluded.push(Excluded {
                name: info.name.clone(),
                reason: e.to_string(),
            }),
        }
    }
    let reference = options.bundle.reference;
    if models.get(reference).is_none_or(Option::is_none) {
        return Err(CalibError::Degenerate(
            "the reference device could not be initialised",
        ));
    }
    let graph = chain(&pairs, devices.len(), poses, reference);
    // Keep the devices and poses the graph reached; renumber them.
    let mut device_index = Vec::new();
    let mut kept = Vec::new();
    let mut new_device = vec![None; devices.len()];
    for (d, info) in devices.iter().enumerate() {
        match (models[d], graph.devices[d]) {
            (Some(model), Some(pose)) => {
                new_device[d] = Some(kept.len());
                device_index.push(d);
                kept.push(Device {
                    name: info.name.clone(),
                    kind: info.kind,
                    model,
                    pose,
                });
            }
            (Some(_), None) => excluded.push(Excluded {
                name: info.name.clone(),
                reason: "shares no board pose with the devices linked to the reference".into(),
            }),
            (None, _) => {}
        }
    }
    let mut pose_index = Vec::new();
    let mut new_pose = vec![None; poses];
    let mut boards = Vec::new();
    for (k, b) in graph.boards.iter().enumerate() {
        if let Some(b) = b {
            new_pose[k] = Some(boards.len());
            pose_index.push(k);
            boards.push(*b);
        }
    }
    // A projector observation also needs its camera kept.
    let observations: Vec<Observation> = obs
        .iter()
        .filter_map(|o| {
            let via = match o.via {
                Some(v) => Some(bundle::Via {
                    camera: new_device[v.camera]?,
                    ..v
                }),
                None => None,
            };
            Some(Observation {
                device: new_device[o.device]?,
                pose: new_pose[o.pose]?,
                via,
                ..*o
            })
        })
        .collect();
    let bundle_options = Options {
        reference: new_device[reference].expect("the reference is kept"),
        ..options.bundle
    };
    let problem = Problem {
        board: board.clone(),
        devices: kept,
        boards,
        observations,
    };
    let solution = bundle::adjust(&problem, &bundle_options)?;
    Ok(Calibration {
        board: board.clone(),
        devices: solution.devices.clone(),
        reference: bundle_options.reference,
        device_index,
        pose_index,
        excluded,
        registration,
        observations: problem.observations,
        solution,
    })
}
