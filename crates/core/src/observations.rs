//! The observations: the seam between the image stages and calibration (docs/design.md §7).
//!
//! What the image stages give and calibration takes, as one vocabulary: every camera's
//! labelled [`CameraView`] of a board pose (ellipse centres, and at each the pixel every
//! lighting projector shows there), the devices ([`DeviceInfo`], [`DeviceKind`]) and the
//! whole set as the correspondences file ([`Correspondences`]), with the checks a file read
//! from disk must pass.

use crate::board::{Board, Hex, Side};
use crate::invalid::{Invalid, ValidationError};
use crate::limits;
use nalgebra::Point2;
use std::collections::BTreeMap;

/// How a view's lattice labels relate to the board.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Frame {
    /// Labels are in this side's own board frame.
    Anchored(Side),
    /// Labels are in an arbitrary lattice frame, the side unknown.
    Unanchored,
}

/// A projector's decoded pixel at a camera's ellipse centre.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ProjectorPixel {
    /// Device index of the projector.
    pub projector: usize,
    /// Decoded (u, v) (projector px).
    pub pixel: Point2<f64>,
}

/// One labelled circle of a view.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ViewPoint {
    /// Lattice position in the view's frame.
    pub hex: Hex,
    /// Observed ellipse centre (px).
    pub image: Point2<f64>,
    /// Projector coordinates decoded at the ellipse centre, one per lighting projector.
    pub projectors: Vec<ProjectorPixel>,
}

/// One camera's labelled view of one board pose.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraView {
    /// Device index of the camera.
    pub camera: usize,
    /// Board pose index.
    pub pose: usize,
    /// Frame of the labels.
    pub frame: Frame,
    /// The labelled circles.
    pub points: Vec<ViewPoint>,
}

/// Says whether a device index is one a view may use (`Err` says why not).
pub type IndexCheck<'a> = &'a dyn Fn(usize) -> Result<(), Invalid>;

impl CameraView {
    /// The first problem of a view read from a file: (JSON path within the view, what is
    /// wrong). `camera` and `projector` check device indices, `poses` bounds the pose;
    /// lattice positions lie within ±[`crate::limits::MAX_LATTICE_COORD`], pixels are finite.
    pub fn check(
        &self,
        camera: IndexCheck,
        projector: IndexCheck,
        poses: usize,
    ) -> Result<(), ValidationError> {
        camera(self.camera).map_err(|m| m.at("camera"))?;
        if self.pose >= poses {
            return Err(ValidationError::new(
                "pose",
                format!("pose {} is out of range ({poses} poses)", self.pose),
            ));
        }
        let max = crate::limits::MAX_LATTICE_COORD;
        for (i, p) in self.points.iter().enumerate() {
            if p.hex.q.abs() > max || p.hex.r.abs() > max {
                return Err(ValidationError::new(
                    format!("points[{i}].hex"),
                    format!("({}, {}) is beyond ±{max}", p.hex.q, p.hex.r),
                ));
            }
            crate::limits::finite(&[p.image.x, p.image.y])
                .map_err(|m| m.at(format!("points[{i}].image")))?;
            for (j, q) in p.projectors.iter().enumerate() {
                let at = |k: &str| format!("points[{i}].projectors[{j}].{k}");
                projector(q.projector).map_err(|m| m.at(at("projector")))?;
                crate::limits::finite(&[q.pixel.x, q.pixel.y]).map_err(|m| m.at(at("pixel")))?;
            }
        }
        Ok(())
    }
}

/// Whether a device records images or casts them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DeviceKind {
    /// A camera: observes ellipse centres of circles.
    Camera,
    /// A projector: observed through cameras as decoded projector pixels.
    Projector,
}

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

impl Correspondences {
    /// The first problem of a correspondences file: the JSON path and what is wrong, as
    /// [`check_input`] finds it.
    pub fn check(&self) -> Result<(), ValidationError> {
        check_input(&self.devices, self.poses, &self.views)
    }
}

/// The first problem of calibration input: the JSON path and what is wrong. At least one and
/// at most [`limits::MAX_DEVICES`] devices with unique names usable as file names and sizes
/// within [`limits::image_size`]; 1 to [`limits::MAX_POSES`] poses; every view of a camera
/// and a pose in range, at most one per (camera, pose), its projector pixels of projectors
/// ([`CameraView::check`]).
pub fn check_input(
    devices: &[DeviceInfo],
    poses: usize,
    views: &[CameraView],
) -> Result<(), ValidationError> {
    if devices.is_empty() {
        return Err(ValidationError::new("devices", "no device"));
    }
    limits::count(devices.len(), limits::MAX_DEVICES, "devices").map_err(|m| m.at("devices"))?;
    let mut names = BTreeMap::new();
    for (i, d) in devices.iter().enumerate() {
        let at = |k: &str| format!("devices[{i}].{k}");
        limits::device_name(&d.name).map_err(|m| m.at(at("name")))?;
        if let Some(first) = names.insert(d.name.as_str(), i) {
            return Err(ValidationError::new(
                at("name"),
                format!("{:?} is already the name of devices[{first}]", d.name),
            ));
        }
        limits::image_size(d.width, d.height).map_err(|m| m.at(at("width")))?;
    }
    if poses == 0 {
        return Err(ValidationError::new("poses", "no board pose"));
    }
    limits::count(poses, limits::MAX_POSES, "poses").map_err(|m| m.at("poses"))?;
    let kind = |want: DeviceKind, i: usize| match devices.get(i) {
        Some(d) if d.kind == want => Ok(()),
        Some(d) => Err(Invalid(
            format!("device {i} ({}) is a {:?}", d.name, d.kind).to_lowercase(),
        )),
        None => Err(Invalid(format!(
            "device {i} is out of range ({} devices)",
            devices.len()
        ))),
    };
    let camera = |i| kind(DeviceKind::Camera, i);
    let projector = |i| kind(DeviceKind::Projector, i);
    let mut seen = BTreeMap::new();
    for (i, v) in views.iter().enumerate() {
        v.check(&camera, &projector, poses)
            .map_err(|e| e.map_at(|k| format!("views[{i}].{k}")))?;
        if let Some(first) = seen.insert((v.camera, v.pose), i) {
            return Err(ValidationError::new(
                format!("views[{i}]"),
                format!(
                    "camera {} at pose {} already has a view (views[{first}])",
                    v.camera, v.pose
                ),
            ));
        }
    }
    Ok(())
}

/// The first view labelled on a side `board` does not have (the back of a single-sided
/// board): its JSON path (`views[i].frame`) and what is wrong.
pub fn check_sides(board: &Board, views: &[CameraView]) -> Result<(), ValidationError> {
    match views
        .iter()
        .position(|v| matches!(v.frame, Frame::Anchored(side) if !board.has(side)))
    {
        Some(i) => Err(ValidationError::new(
            format!("views[{i}].frame"),
            format!(
                "labelled on the back, but board {} is single-sided (sides = 1): it has no back",
                board.name
            ),
        )),
        None => Ok(()),
    }
}
