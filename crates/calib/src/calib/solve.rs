//! The whole calibration from labelled views (docs/design.md §7–8): registration of unanchored
//! views, Zhang's initialisation per device, the pose graph, one bundle adjustment.
//!
//! Takes the rig's devices (names, kinds, image sizes), the board and every camera's
//! [`CameraView`]s; gives a [`Calibration`]: every device's model and pose in the reference
//! device's frame, the board poses, the adjustment's residuals and covariance, and what
//! could not be used (devices with too few views, views not connected to the reference,
//! views not registered), each reported by name.

use super::bundle::{self, Device, Observation, Options, Problem, Solution};
use super::lens_model::{adjust_selecting, LensChoice};
use super::posegraph::{chain, PairEstimate};
use super::views::{observations, register, RegisterParams, Registration};
use super::zhang;
use super::{CalibError, PlanarView, PlaneCorrespondence};
use hexcal_core::board::{Board, Side};
use hexcal_core::camera::CameraModel;
use hexcal_core::observations::{check_input, check_sides, CameraView, DeviceInfo};
use hexcal_core::{Invalid, ValidationError};
use std::collections::BTreeMap;

impl From<&Device> for DeviceInfo {
    /// The name, kind and image size of an adjusted device.
    fn from(d: &Device) -> Self {
        DeviceInfo {
            name: d.name.clone(),
            kind: d.kind,
            width: d.model.width,
            height: d.model.height,
        }
    }
}

/// Settings of [`calibrate`].
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrateOptions {
    /// Registration of unanchored views.
    pub register: RegisterParams,
    /// The bundle adjustment (its `reference` is the gauge device).
    pub bundle: Options,
    /// Points a (device, pose, side) view needs to count for initialisation.
    pub min_view_points: usize,
    /// Fix the distortion terms the data cannot determine ([`super::lens_model`]); off,
    /// every term of the model is estimated (the solver's own tests against the truth).
    pub select_lens: bool,
}

impl Default for CalibrateOptions {
    fn default() -> Self {
        CalibrateOptions {
            register: RegisterParams::default(),
            bundle: Options::default(),
            min_view_points: 12,
            select_lens: true,
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
    /// Per device, the distortion terms the data determine and those fixed
    /// ([`super::lens_model`]).
    pub lens: Vec<LensChoice>,
}

/// Zhang's start of one device: views grouped by (pose, side), each view's pose.
struct Start {
    model: CameraModel,
    pairs: Vec<PairEstimate>,
}

/// Views of one device grouped by (pose, side): one correspondence per circle.
type Groups = BTreeMap<(usize, Side), BTreeMap<hexcal_core::board::Hex, PlaneCorrespondence>>;

/// Zhang's start of device `device` from its views of at least `min_points` circles; the
/// error names the views it has and what they lack.
fn initialise(
    board: &Board,
    info: &DeviceInfo,
    device: usize,
    obs: &[Observation],
    min_points: usize,
) -> Result<Start, Invalid> {
    // Group by (pose, side); a projector sees each circle through several cameras: keep one
    // correspondence per circle (the first) for the start.
    let mut groups = Groups::new();
    for o in obs.iter().filter(|o| o.device == device) {
        groups
            .entry((o.pose, o.side))
            .or_default()
            .entry(o.hex)
            .or_insert(PlaneCorrespondence {
                board: board.position(o.hex),
                image: o.pixel,
            });
    }
    let keys: Vec<(usize, Side)> = groups
        .iter()
        .filter(|(_, g)| g.len() >= min_points)
        .map(|(k, _)| *k)
        .collect();
    if keys.len() < zhang::MIN_VIEWS {
        return Err(Invalid(too_few_views(&groups, keys.len(), min_points)));
    }
    let views: Vec<PlanarView> = keys
        .iter()
        .map(|k| PlanarView {
            points: groups[k].values().copied().collect(),
        })
        .collect();
    let (model, poses) = zhang::initialise(&views, info.width, info.height).map_err(|e| {
        Invalid(format!(
            "Zhang initialisation from {} views ({}): {e}",
            views.len(),
            keys.iter()
                .map(|&(k, s)| format!("pose {k} {s}"))
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })?;
    let pairs = keys
        .iter()
        .zip(&poses)
        .zip(&views)
        .map(|((&(pose, side), device_from_side), view)| PairEstimate {
            device,
            pose,
            device_from_board: device_from_side * board.side_transform(side).inverse(),
            points: view.points.len(),
        })
        .collect();
    Ok(Start { model, pairs })
}

/// "2 usable views, at least 3 needed (pose 4 front has 7 circles, a view needs 12)".
fn too_few_views(groups: &Groups, usable: usize, min_points: usize) -> String {
    let mut text = format!(
        "{usable} usable views, at least {} needed",
        zhang::MIN_VIEWS
    );
    let sparse: Vec<String> = groups
        .iter()
        .filter(|(_, g)| g.len() < min_points)
        .map(|((k, s), g)| format!("pose {k} {s} has {} circles", g.len()))
        .collect();
    if groups.is_empty() {
        text += " (no labelled circle of it in any view)";
    } else if !sparse.is_empty() {
        text += &format!(" ({}; a view needs {min_points})", sparse.join(", "));
    }
    text
}

/// Refuses a reference device index out of range.
fn check_reference(devices: &[DeviceInfo], reference: usize) -> Result<(), CalibError> {
    if reference >= devices.len() {
        return Err(CalibError::Input(ValidationError::new(
            "reference",
            format!(
                "device {reference} is out of range ({} devices)",
                devices.len()
            ),
        )));
    }
    Ok(())
}

/// The devices with a start that the graph reached: their input indices, the devices, and
/// each input device's new index; those it did not reach join `excluded`.
fn kept_devices(
    devices: &[DeviceInfo],
    models: &[Option<CameraModel>],
    chained: &[Option<nalgebra::Isometry3<f64>>],
    excluded: &mut Vec<Excluded>,
) -> (Vec<usize>, Vec<Device>, Vec<Option<usize>>) {
    let mut device_index = Vec::new();
    let mut kept = Vec::new();
    let mut new_device = vec![None; devices.len()];
    for (d, info) in devices.iter().enumerate() {
        match (models[d], chained[d]) {
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
    (device_index, kept, new_device)
}

/// The board poses the graph reached, renumbered: their input indices, their poses, and
/// the observations of kept devices at kept poses (renumbered by `new_device`); a
/// projector observation also needs its camera kept.
fn kept_poses(
    chained: &[Option<nalgebra::Isometry3<f64>>],
    obs: &[Observation],
    new_device: &[Option<usize>],
) -> (Vec<usize>, Vec<nalgebra::Isometry3<f64>>, Vec<Observation>) {
    let mut pose_index = Vec::new();
    let mut new_pose = vec![None; chained.len()];
    let mut boards = Vec::new();
    for (k, b) in chained.iter().enumerate() {
        if let Some(b) = b {
            new_pose[k] = Some(boards.len());
            pose_index.push(k);
            boards.push(*b);
        }
    }
    let observations = obs
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
    (pose_index, boards, observations)
}

/// Calibrate every device from the cameras' labelled views of `poses` board poses.
pub fn calibrate(
    board: &Board,
    devices: &[DeviceInfo],
    poses: usize,
    views: &[CameraView],
    options: &CalibrateOptions,
) -> Result<Calibration, CalibError> {
    check_input(devices, poses, views)?;
    check_sides(board, views)?;
    check_reference(devices, options.bundle.reference)?;
    let (views, registration) = register(views, &options.register);
    let obs = observations(&views);
    // Millions of circles on a dome: no copy is held longer than it is needed.
    drop(views);
    let mut excluded = Vec::new();
    let mut models = vec![None; devices.len()];
    let mut pairs = Vec::new();
    for (d, info) in devices.iter().enumerate() {
        match initialise(board, info, d, &obs, options.min_view_points) {
            Ok(start) => {
                models[d] = Some(start.model);
                pairs.extend(start.pairs);
            }
            Err(reason) => excluded.push(Excluded {
                name: info.name.clone(),
                reason: reason.into(),
            }),
        }
    }
    let reference = options.bundle.reference;
    if models[reference].is_none() {
        let name = devices[reference].name.clone();
        let reason = excluded
            .iter()
            .find(|e| e.name == name)
            .map_or(String::new(), |e| e.reason.clone());
        return Err(CalibError::Reference { name, reason });
    }
    let graph = chain(&pairs, devices.len(), poses, reference);
    // Keep the devices and poses the graph reached; renumber them.
    let (device_index, kept, new_device) =
        kept_devices(devices, &models, &graph.devices, &mut excluded);
    let (pose_index, boards, observations) = kept_poses(&graph.boards, &obs, &new_device);
    drop(obs);
    let bundle_options = Options {
        reference: new_device[reference].expect("the reference is kept"),
        ..options.bundle.clone()
    };
    let problem = Problem {
        board: board.clone(),
        devices: kept,
        boards,
        observations,
    };
    let (solution, lens) = adjust_selecting(&problem, &bundle_options, options.select_lens)?;
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
        lens,
    })
}
