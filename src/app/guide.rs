//! Guidance for the person placing the board (issue 19, docs/design.md §15 "Guidance"): from
//! an interim calibration, each device's worst projection uncertainty over its image, the
//! done rule, and the next board pose that lowers the worst device's uncertainty most.
//!
//! Takes a [`Calibration`] (its devices and covariance) and the rig's devices; gives
//! [`Guidance`]. Candidate poses are judged without a re-solve: a candidate's synthetic
//! observations add their information to the device block of the normal equations, with
//! the candidate's own board pose eliminated (the Schur complement of docs/design.md (37)),
//! and the device covariance is that matrix's inverse (38).

pub mod interim;
pub mod operator;
pub mod picture;
pub mod stats;
pub mod verdict;

use crate::board::{Board, Hex, Side};
use crate::calib::bundle::Device;
use crate::calib::diagnostics::lens_covariance;
use crate::calib::solve::Calibration;
use crate::camera::{CameraModel, LensParam};
use crate::observations::DeviceInfo;
use crate::observations::DeviceKind;
use nalgebra::{
    DMatrix, Isometry3, Matrix2x6, Matrix3, Matrix6, Point2, Point3, Translation3, UnitQuaternion,
    Vector2, Vector3,
};
use rayon::prelude::*;
use serde::Serialize;

/// Points per image side at which a device's worst projection uncertainty is taken
/// (corners included).
const GRID: (usize, usize) = (9, 6);

/// Steepest view of the board a detector is trusted with: the angle (deg) between a side's
/// normal and the line from its centre to the device.
pub const MAX_VIEW_ANGLE_DEG: f64 = 60.0;

/// Fewest points a device must see of a candidate pose for it to be drawn in its thumbnail.
pub const MIN_SEEN: usize = 12;

/// One device's projection uncertainty over its image.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DeviceUncertainty {
    /// Device name.
    pub name: String,
    /// Worst projection uncertainty over the image (px, 1σ); `None`: not yet calibrated.
    pub worst: Option<f64>,
    /// Where in its image (px) the worst is.
    pub at: Option<[f64; 2]>,
}

/// The next pose to place.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Suggestion {
    /// The device the sentence is told for: the one that limits the rig when it sees the
    /// pose, else the one that sees most of it (the pose is chosen for the whole rig).
    pub target: String,
    /// The worst device's uncertainty predicted after the pose (px).
    pub predicted: f64,
    /// What to do, in one sentence.
    pub sentence: String,
    /// Per rig device (cameras first), the board's outline (px) in its image at the pose,
    /// when it would see at least `MIN_SEEN` points.
    pub outlines: Vec<Option<Vec<[f32; 2]>>>,
    /// The pose drawn big in one camera's view: its tilt, the turn from the last pose and
    /// one short line ([`picture::picture`]); `None` when no camera would see it.
    pub picture: Option<picture::Picture>,
    /// The pose T_ref_board, in the calibration's reference frame.
    #[serde(skip)]
    pub pose: Isometry3<f64>,
}

/// What the console tells the operator after an interim calibration.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Guidance {
    /// Per rig device (cameras first).
    pub devices: Vec<DeviceUncertainty>,
    /// The threshold (px).
    pub threshold: f64,
    /// Every device calibrated and below the threshold.
    pub done: bool,
    /// The next pose, unless done.
    pub suggestion: Option<Suggestion>,
}

/// One point a board pose shows a device.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sighting {
    /// Device index (in the slice given).
    pub device: usize,
    /// The side seen.
    pub side: Side,
    /// The circle.
    pub hex: Hex,
    /// Its pixel.
    pub pixel: Point2<f64>,
    /// For a projector: the camera (index) through which it is observed.
    pub via: Option<usize>,
}

/// Whether `p` lies in `m`'s image, clear of its border.
fn inside(m: &CameraModel, p: Point2<f64>) -> bool {
    p.x > 2.0 && p.y > 2.0 && p.x < f64::from(m.width) - 3.0 && p.y < f64::from(m.height) - 3.0
}

/// The back side's frame for predictions: the calibrated one, or the plain back of a
/// single-sided board (no circle on it: [`sightings`] never sees it).
pub fn back_frame(cal: &Calibration) -> Isometry3<f64> {
    cal.solution
        .front_back
        .unwrap_or_else(|| cal.board.side_transform(Side::Back))
}

/// T_board_side of `side` with the back side at `front_back`.
fn side_frame(side: Side, front_back: &Isometry3<f64>) -> Isometry3<f64> {
    match side {
        Side::Front => Isometry3::identity(),
        Side::Back => *front_back,
    }
}

/// What `devices` (T_device_ref) see of the board at T_ref_board `pose`: each camera every
/// circle of the side facing it (within [`MAX_VIEW_ANGLE_DEG`]) that falls in its image, and
/// each projector the same circle when the side faces it too and it falls in its raster
/// (projectors are observed through the cameras, §7).
pub fn sightings(
    board: &Board,
    devices: &[Device],
    front_back: &Isometry3<f64>,
    pose: &Isometry3<f64>,
) -> Vec<Sighting> {
    let faces = |dev: &Device, side: Side| {
        let t = dev.pose * pose * side_frame(side, front_back);
        let eye = (t.inverse() * Point3::origin()).coords;
        (eye.z > MAX_VIEW_ANGLE_DEG.to_radians().cos() * eye.norm()).then_some(t)
    };
    let mut out = Vec::new();
    for (c, cam) in devices.iter().enumerate() {
        if cam.kind != DeviceKind::Camera {
            continue;
        }
        for side in Side::BOTH {
            let Some(t) = faces(cam, side) else { continue };
            for circle in board.circles(side) {
                let x = Point3::new(circle.center_2d.x, circle.center_2d.y, 0.0);
                let Some(px) = cam
                    .model
                    .project(&(t * x))
                    .filter(|p| inside(&cam.model, *p))
                else {
                    continue;
                };
                let seen = |device, pixel, via| Sighting {
                    device,
                    side,
                    hex: circle.hex,
                    pixel,
                    via,
                };
                out.push(seen(c, px, None));
                for (p, proj) in devices.iter().enumerate() {
                    if proj.kind != DeviceKind::Projector {
                        continue;
                    }
                    let Some(tp) = faces(proj, side) else {
                        continue;
                    };
                    if let Some(u) = proj.model.project(&(tp * x)) {
                        if inside(&proj.model, u) {
                            out.push(seen(p, u, Some(c)));
                        }
                    }
                }
            }
        }
    }
    out
}

/// Uncertainty (px, 1σ along the worst direction) of where device `dev` sees the rig point
/// at depth `distance` (m, along its axis) behind `pixel`: its lens block and, when
/// `has_pose`, its pose block (T_device_ref's increment, the columns of (J4)) of `cov`
/// propagated through the projection's Jacobians, J·Σ·Jᵀ (docs/design.md §15). A device
/// whose lens is sure but whose position is not (a board side seen in few poses) is not
/// done: the point it would triangulate is off.
pub fn rig_uncertainty(
    dev: &Device,
    free: &[LensParam],
    has_pose: bool,
    cov: &DMatrix<f64>,
    distance: f64,
    pixel: Point2<f64>,
) -> Option<f64> {
    let x_device = Point3::from(dev.model.ray(pixel)? * distance);
    let x_ref = dev.pose.inverse() * x_device;
    let j = dev.model.project_with_jacobians(&dev.pose, &x_ref)?;
    let n = free.len() + if has_pose { 6 } else { 0 };
    let js = DMatrix::from_fn(2, n, |r, c| match free.get(c) {
        Some(f) => j.d_lens[(r, f.index())],
        None => j.d_pose[(r, c - free.len())],
    });
    let s = &js * cov * js.transpose();
    Some(s.symmetric_eigenvalues().max().max(0.0).sqrt())
}

/// The worst [`rig_uncertainty`] over a [`GRID`] of `dev`'s image at depth `distance`, and
/// where.
fn worst(
    dev: &Device,
    free: &[LensParam],
    has_pose: bool,
    cov: &DMatrix<f64>,
    distance: f64,
) -> Option<(f64, [f64; 2])> {
    let m = &dev.model;
    let (nx, ny) = GRID;
    let (w, h) = (f64::from(m.width) - 1.0, f64::from(m.height) - 1.0);
    let mut best: Option<(f64, [f64; 2])> = None;
    for j in 0..ny {
        for i in 0..nx {
            let p = Point2::new(
                w * i as f64 / (nx - 1) as f64,
                h * j as f64 / (ny - 1) as f64,
            );
            let u = rig_uncertainty(dev, free, has_pose, cov, distance, p)?;
            if best.is_none_or(|(b, _)| u > b) {
                best = Some((u, [p.x, p.y]));
            }
        }
    }
    best
}

/// Every device's [`working_distance`] over `boards`.
fn working_distances(devices: &[Device], boards: &[Isometry3<f64>]) -> Vec<f64> {
    devices
        .iter()
        .map(|d| working_distance(d, boards))
        .collect()
}

/// Working distance (m) of device `dev` over board poses T_ref_board `boards`: the median
/// depth of the board origins in front of it (1 m when none is).
pub fn working_distance(dev: &Device, boards: &[Isometry3<f64>]) -> f64 {
    let mut z: Vec<f64> = boards
        .iter()
        .map(|b| (dev.pose * b).translation.vector.z)
        .filter(|z| *z > 0.0)
        .collect();
    if z.is_empty() {
        return 1.0;
    }
    z.sort_by(f64::total_cmp);
    z[z.len() / 2]
}

/// The device block of the calibration: per calibrated device its free lens parameters and
/// where its lens and pose columns start in the block; the state indices of the block.
struct Block {
    lens: Vec<(usize, Vec<LensParam>)>,
    pose: Vec<Option<usize>>,
    state: Vec<usize>,
}

impl Block {
    fn of(cal: &Calibration) -> Block {
        let (mut lens, mut pose, mut state) = (Vec::new(), Vec::new(), Vec::new());
        for d in 0..cal.devices.len() {
            let (free, _) = lens_covariance(cal, d);
            let (at, pose_at) = cal.solution.index[d];
            lens.push((state.len(), free.clone()));
            state.extend(at..at + free.len());
            pose.push(pose_at.map(|p| {
                let here = state.len();
                state.extend(p..p + 6);
                here
            }));
        }
        Block { lens, pose, state }
    }

    /// The lens and pose block of device `d` of covariance `cov` (block order: the lens's
    /// free parameters, then the pose's six when it has one).
    fn device_cov(&self, cov: &DMatrix<f64>, d: usize) -> DMatrix<f64> {
        let (at, free) = &self.lens[d];
        let n = free.len() + if self.pose[d].is_some() { 6 } else { 0 };
        cov.view((*at, *at), (n, n)).into_owned()
    }

    /// Device `d`'s worst [`rig_uncertainty`] under covariance `cov` (block order) at depth
    /// `distance`.
    fn worst(
        &self,
        devices: &[Device],
        cov: &DMatrix<f64>,
        d: usize,
        distance: f64,
    ) -> Option<(f64, [f64; 2])> {
        let has_pose = self.pose[d].is_some();
        let c = self.device_cov(cov, d);
        worst(&devices[d], &self.lens[d].1, has_pose, &c, distance)
    }
}

/// The information (JᵀJ/σ², device block, board pose eliminated) of sightings `seen` of a
/// board at T_ref_board `pose`, by the calibration's `devices`.
fn information(
    b: &Block,
    devices: &[Device],
    front_back: &Isometry3<f64>,
    board: &Board,
    pose: &Isometry3<f64>,
    seen: &[Sighting],
    sigma: f64,
) -> DMatrix<f64> {
    let n = b.state.len();
    let mut haa = DMatrix::<f64>::zeros(n, n);
    let mut hab = DMatrix::<f64>::zeros(n, 6);
    let mut hbb = Matrix6::<f64>::zeros();
    let mut cols: Vec<(usize, Vector2<f64>)> = Vec::with_capacity(24);
    for s in seen {
        let dev = &devices[s.device];
        let p = board.position(s.hex);
        let x_ref = pose * side_frame(s.side, front_back) * Point3::new(p.x, p.y, 0.0);
        let Some(j) = dev.model.project_with_jacobians(&dev.pose, &x_ref) else {
            continue;
        };
        cols.clear();
        let (at, free) = &b.lens[s.device];
        for (k, f) in free.iter().enumerate() {
            cols.push((at + k, j.d_lens.column(f.index()).into_owned()));
        }
        if let Some(at) = b.pose[s.device] {
            for k in 0..6 {
                cols.push((at + k, j.d_pose.column(k).into_owned()));
            }
        }
        let jb = match s.via {
            // Left increment of the board pose: dX_ref = −[X_ref]×·ω + τ.
            None => {
                let mut jb = Matrix2x6::<f64>::zeros();
                jb.fixed_columns_mut::<3>(0)
                    .copy_from(&(-j.d_point * skew(&x_ref.coords)));
                jb.fixed_columns_mut::<3>(3).copy_from(&j.d_point);
                jb
            }
            Some(c) => {
                let plane = pose * side_frame(s.side, front_back);
                match through_camera(b, &devices[c], c, &plane, &x_ref, &j.d_point, &mut cols) {
                    Some(jb) => jb,
                    None => continue,
                }
            }
        };
        for (ci, vi) in &cols {
            for (cj, vj) in &cols {
                haa[(*ci, *cj)] += vi.dot(vj);
            }
            let mut row = hab.fixed_view_mut::<1, 6>(*ci, 0);
            row += vi.transpose() * jb;
        }
        hbb += jb.transpose() * jb;
    }
    if let Some(inv) = hbb.try_inverse() {
        let hbb_inv = DMatrix::from_fn(6, 6, |r, c| inv[(r, c)]);
        haa -= &hab * hbb_inv * hab.transpose();
    }
    haa / (sigma * sigma)
}

/// A projector sighting's dependence on the camera `cam` (index `c`) it is found through,
/// as the adjustment models it (docs/design.md §7, `bundle::linearise`): the projector sees
/// the point where the camera's ray through its pixel of the circle meets the side's plane
/// (T_ref_side `plane`), so the camera's lens and pose move that point, and the board pose
/// moves it only through the plane. Pushes the camera's columns onto `cols`, given the
/// projector pixel's derivative `d_ref` with respect to the point (reference frame); gives
/// the board pose's columns.
fn through_camera(
    b: &Block,
    cam: &Device,
    c: usize,
    plane: &Isometry3<f64>,
    x_ref: &Point3<f64>,
    d_ref: &nalgebra::Matrix2x3<f64>,
    cols: &mut Vec<(usize, Vector2<f64>)>,
) -> Option<Matrix2x6<f64>> {
    use crate::calib::bundle::plane_increment;
    let p_c = cam.pose * x_ref;
    let lambda = p_c.z;
    if lambda <= 0.0 {
        return None;
    }
    let r = p_c.coords / lambda;
    let normal = (cam.pose * plane).rotation * Vector3::z();
    // d pixel / d P_c (camera frame).
    let jpc = d_ref * cam.pose.rotation.to_rotation_matrix().matrix().transpose();
    let (at, free) = &b.lens[c];
    if !free.is_empty() {
        let un = cam
            .model
            .undistort_with_jacobians(cam.model.project(&p_c)?)?;
        // The lens moves the ray: dP_c = λ·(I − r·Nᵀ/(N·r))·(dn, 0).
        let slide = (Matrix3::identity() - r * normal.transpose() / normal.dot(&r)) * lambda;
        let d_lens = jpc * slide.fixed_columns::<2>(0) * un.d_lens;
        for (k, f) in free.iter().enumerate() {
            cols.push((at + k, d_lens.column(f.index()).into_owned()));
        }
    }
    if let Some(at) = b.pose[c] {
        // The camera's pose moves the plane in its frame and T_c⁻¹ as well.
        let (aw, at_) = plane_increment(&r, &normal, lambda, &Isometry3::identity());
        let dw = jpc * (aw + skew(&p_c.coords));
        let dt = jpc * (at_ - Matrix3::identity());
        for k in 0..3 {
            cols.push((at + k, dw.column(k).into_owned()));
            cols.push((at + 3 + k, dt.column(k).into_owned()));
        }
    }
    let (aw, at_) = plane_increment(&r, &normal, lambda, &cam.pose);
    let mut jb = Matrix2x6::<f64>::zeros();
    jb.fixed_columns_mut::<3>(0).copy_from(&(jpc * aw));
    jb.fixed_columns_mut::<3>(3).copy_from(&(jpc * at_));
    Some(jb)
}

fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The console's advice for pose `pose` (0-based) while fewer than `need` poses exist, so
/// no interim calibration yet (docs/design.md §15 "First poses"): the board where every
/// device shows it (cameras in their live pictures, projectors by their light on it), each
/// pose turned as far from the ones before as that allows; `seen` is each device's name and poses seen so far,
/// and the devices missing from some pose are named. `None` from pose `need` on.
pub fn first_pose_advice(pose: usize, need: usize, seen: &[(&str, usize)]) -> Option<String> {
    if pose >= need {
        return None;
    }
    let mut s = format!(
        "First poses ({} of {need} before the first calibration): put the board where every \
         camera shows it in its live picture and every projector lights it",
        pose + 1
    );
    if pose > 0 {
        s += ", turned as far from the poses so far as it goes while every device still sees it";
        let behind: Vec<String> = seen
            .iter()
            .filter(|(_, n)| *n < pose)
            .map(|(name, n)| format!("{name} ({n} of {pose})"))
            .collect();
        if !behind.is_empty() {
            s += &format!("; not seen in every pose so far: {}", behind.join(", "));
        }
    }
    Some(s + ".")
}

/// The first-pose advice ([`first_pose_advice`]) in at most [`picture::MAX_WORDS`] words,
/// for the console's big panel; `None` from pose `need` on.
pub fn first_pose_line(pose: usize, need: usize) -> Option<String> {
    (pose < need).then(|| match pose {
        0 => "Board where every camera sees it".to_string(),
        _ => "Turn the board; every camera still sees it".to_string(),
    })
}

/// Candidate board poses T_ref_board around the working volume of the poses so far: the
/// mean board position and the first pose's orientation, turned about the board's y by
/// up to ±50°, tilted about its x by up to ±40°, shifted in its plane by ±250 / ±200 mm.
pub fn candidates(boards: &[Isometry3<f64>]) -> Vec<Isometry3<f64>> {
    let Some(first) = boards.first() else {
        return Vec::new();
    };
    let centre = boards
        .iter()
        .map(|b| b.translation.vector)
        .sum::<Vector3<f64>>()
        / boards.len() as f64;
    let r0 = first.rotation;
    let mut out = Vec::new();
    for yaw in [-50.0f64, -25.0, 0.0, 25.0, 50.0] {
        for tilt in [-40.0f64, -20.0, 0.0, 20.0, 40.0] {
            let r = r0
                * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw.to_radians())
                * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), tilt.to_radians());
            for dx in [-250.0, 0.0, 250.0] {
                for dy in [-200.0, 0.0, 200.0] {
                    let t = centre + r0 * Vector3::new(dx, dy, 0.0);
                    out.push(Isometry3::from_parts(Translation3::from(t), r));
                }
            }
        }
    }
    out
}

/// The guidance of an interim calibration `cal` of the rig's `devices` (cameras first)
/// against the done `threshold` (px).
pub fn guide(cal: &Calibration, devices: &[DeviceInfo], threshold: f64) -> Guidance {
    let block = Block::of(cal);
    let cov = cal.solution.covariance.block(&block.state);
    let distance = working_distances(&cal.devices, &cal.solution.boards);
    let now: Vec<Option<(f64, [f64; 2])>> = (0..cal.devices.len())
        .map(|d| block.worst(&cal.devices, &cov, d, distance[d]))
        .collect();
    let uncertainties: Vec<DeviceUncertainty> = devices
        .iter()
        .enumerate()
        .map(|(i, info)| {
            let w = cal
                .device_index
                .iter()
                .position(|&r| r == i)
                .and_then(|d| now[d]);
            DeviceUncertainty {
                name: info.name.clone(),
                worst: w.map(|w| w.0),
                at: w.map(|w| w.1),
            }
        })
        .collect();
    let done = uncertainties
        .iter()
        .all(|u| u.worst.is_some_and(|w| w <= threshold));
    let suggestion = (!done)
        .then(|| suggest(cal, devices, &block, &cov, &distance, &uncertainties))
        .flatten();
    Guidance {
        devices: uncertainties,
        threshold,
        done,
        suggestion,
    }
}

/// Every device's worst projection uncertainty (px) predicted for the board at `poses`
/// (T_ref_board) seen by `devices` (T_device_ref, in `layout`'s device order: the truth in
/// a benchmark) with observation noise `sigma` (px), laid out as `layout`'s parameters
/// (its free lens parameters and reference): each pose's information with its board pose
/// eliminated (docs/design.md (37)), summed and inverted (38) over the devices seen in at
/// least `min_poses` poses (of at least [`MIN_SEEN`] points), the others held. `ridge` > 0
/// adds that fraction of each diagonal element to it (a weak prior that keeps directions
/// few poses leave free finite, and large). `None` for a device seen in fewer poses (or
/// an information matrix that does not invert).
pub fn predicted_worst(
    layout: &Calibration,
    devices: &[Device],
    poses: &[Isometry3<f64>],
    sigma: f64,
    min_poses: usize,
    ridge: f64,
) -> Vec<Option<f64>> {
    let block = Block::of(layout);
    let fb = &back_frame(layout);
    let n = block.state.len();
    let mut info = DMatrix::<f64>::zeros(n, n);
    let mut seen_in = vec![0usize; devices.len().min(block.lens.len())];
    for pose in poses {
        let seen = sightings(&layout.board, devices, fb, pose);
        for (d, count) in seen_in.iter_mut().enumerate() {
            *count += usize::from(seen.iter().filter(|s| s.device == d).count() >= MIN_SEEN);
        }
        info += information(&block, devices, fb, &layout.board, pose, &seen, sigma);
    }
    let ready: Vec<usize> = (0..seen_in.len())
        .filter(|&d| seen_in[d] >= min_poses)
        .collect();
    let mut idx = Vec::new();
    let mut block_at = Vec::new();
    for &d in &ready {
        let (at, free) = &block.lens[d];
        let start = idx.len();
        idx.extend(*at..at + free.len());
        if let Some(p) = block.pose[d] {
            idx.extend(p..p + 6);
        }
        block_at.push((start, idx.len() - start));
    }
    let sub = DMatrix::from_fn(idx.len(), idx.len(), |r, c| {
        info[(idx[r], idx[c])] * if r == c { 1.0 + ridge } else { 1.0 }
    });
    let Some(cov) = sub.cholesky().map(|c| c.inverse()) else {
        return vec![None; devices.len()];
    };
    let distance = working_distances(devices, poses);
    let mut out = vec![None; devices.len()];
    for (&d, &(at, len)) in ready.iter().zip(&block_at) {
        let c = cov.view((at, at), (len, len)).into_owned();
        let has_pose = block.pose[d].is_some();
        out[d] = worst(&devices[d], &block.lens[d].1, has_pose, &c, distance[d]).map(|w| w.0);
    }
    out
}

/// The candidate pose that lowers the worst device's predicted uncertainty most, with its
/// sentence and outlines.
fn suggest(
    cal: &Calibration,
    devices: &[DeviceInfo],
    block: &Block,
    cov: &DMatrix<f64>,
    distance: &[f64],
    now: &[DeviceUncertainty],
) -> Option<Suggestion> {
    let info0 = cov.clone().cholesky()?.inverse();
    let sol = &cal.solution;
    let fb = back_frame(cal);
    let predict = |pose: &Isometry3<f64>| -> Option<f64> {
        let seen = sightings(&cal.board, &cal.devices, &fb, pose);
        if seen.is_empty() {
            return None;
        }
        let h = information(
            block,
            &cal.devices,
            &fb,
            &cal.board,
            pose,
            &seen,
            sol.sigma.max(1e-6),
        );
        let after = (&info0 + h).cholesky()?.inverse();
        (0..cal.devices.len())
            .map(|d| {
                block
                    .worst(&cal.devices, &after, d, distance[d])
                    .map(|w| w.0)
            })
            .try_fold(0.0f64, |m, w| Some(m.max(w?)))
    };
    let (pose, predicted) = candidates(&sol.boards)
        .into_par_iter()
        .filter_map(|c| predict(&c).map(|p| (c, p)))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    // The device told about: one not yet calibrated, else the worst one when it sees the
    // pose, else the one that sees most of it.
    let seen = sightings(&cal.board, &cal.devices, &fb, &pose);
    let count = |d: usize| seen.iter().filter(|s| s.device == d).count();
    let index = |name: &str| cal.devices.iter().position(|d| d.name == name);
    let uncalibrated = now.iter().find(|u| u.worst.is_none());
    let worst_device = now
        .iter()
        .max_by(|a, b| a.worst.unwrap_or(0.0).total_cmp(&b.worst.unwrap_or(0.0)))
        .and_then(|u| index(&u.name))
        .filter(|&d| count(d) >= MIN_SEEN);
    let told = worst_device.or_else(|| (0..cal.devices.len()).max_by_key(|&d| count(d)))?;
    let outlines = outlines(cal, devices, &pose);
    let picture = picture::picture(
        cal,
        &pose,
        &outlines,
        (told, &count),
        uncalibrated.map(|u| u.name.as_str()),
    );
    let (target, sentence) = match uncalibrated {
        Some(u) => (
            u.name.clone(),
            format!(
                "show the board to {} (not calibrated yet: it needs the board in view in {} \
                 poses); then {}",
                u.name,
                crate::calib::zhang::MIN_VIEWS,
                sentence(cal, told, &pose)
            ),
        ),
        None => (cal.devices[told].name.clone(), sentence(cal, told, &pose)),
    };
    Some(Suggestion {
        target,
        predicted,
        sentence,
        outlines,
        picture,
        pose,
    })
}

/// Per rig device, the board's outline (convex hull of the circles seen) at `pose`.
fn outlines(
    cal: &Calibration,
    devices: &[DeviceInfo],
    pose: &Isometry3<f64>,
) -> Vec<Option<Vec<[f32; 2]>>> {
    let seen = sightings(&cal.board, &cal.devices, &back_frame(cal), pose);
    devices
        .iter()
        .enumerate()
        .map(|(i, _)| {
            let d = cal.device_index.iter().position(|&r| r == i)?;
            let pts: Vec<Point2<f64>> = seen
                .iter()
                .filter(|s| s.device == d)
                .map(|s| s.pixel)
                .collect();
            (pts.len() >= MIN_SEEN).then(|| {
                hull(&pts)
                    .into_iter()
                    .map(|p| [p.x as f32, p.y as f32])
                    .collect()
            })
        })
        .collect()
}

/// Convex hull (Andrew's monotone chain), counter-clockwise in image coordinates.
fn hull(points: &[Point2<f64>]) -> Vec<Point2<f64>> {
    let mut p = points.to_vec();
    p.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    let cross = |o: &Point2<f64>, a: &Point2<f64>, b: &Point2<f64>| {
        (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x)
    };
    let mut h: Vec<Point2<f64>> = Vec::new();
    for pass in 0..2 {
        let start = h.len();
        for q in p.iter() {
            while h.len() >= start + 2 && cross(&h[h.len() - 2], &h[h.len() - 1], q) <= 0.0 {
                h.pop();
            }
            h.push(*q);
        }
        h.pop();
        if pass == 0 {
            p.reverse();
        }
    }
    h
}

/// "for cam3: board in the lower left of its view, turned about 40° from facing cam3, its
/// right edge nearer": where device `d` sees the board centre at `pose`, the angle between
/// the board's normal and the line to the device, and which edge is nearer to it.
fn sentence(cal: &Calibration, d: usize, pose: &Isometry3<f64>) -> String {
    let dev = &cal.devices[d];
    let name = &dev.name;
    let centre = dev.pose * pose * Point3::origin();
    let (normal, angle) = picture::facing(dev, pose);
    let place = match dev.model.project(&centre) {
        Some(p) => {
            let (w, h) = (f64::from(dev.model.width), f64::from(dev.model.height));
            let col = ["left", "centre", "right"][((3.0 * p.x / w).clamp(0.0, 2.0)) as usize];
            let row = ["upper", "middle", "lower"][((3.0 * p.y / h).clamp(0.0, 2.0)) as usize];
            match (row, col) {
                ("middle", "centre") => format!("in the centre of {name}'s view"),
                ("middle", c) => format!("at the {c} of {name}'s view"),
                (r, "centre") => format!("in the {r} middle of {name}'s view"),
                (r, c) => format!("in the {r} {c} of {name}'s view"),
            }
        }
        None => format!("where {name} sees it"),
    };
    let rounded = (angle / 5.0).round() * 5.0;
    if rounded < 10.0 {
        return format!("for {name}: place the board {place}, facing {name}");
    }
    let edge = picture::nearer_edge(&normal);
    format!(
        "for {name}: place the board {place}, tilted about {rounded:.0}° from facing {name}, \
         its {edge} edge nearer to {name}"
    )
}

#[cfg(test)]
mod tests;
