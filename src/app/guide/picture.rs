//! The next pose as a picture, for the console's big panel (issue 34: readable at 3 m): the
//! camera in whose view the suggested board is drawn, the board's tilt from facing it, the
//! turn from the last pose as an arrow, and one short line of text.
//!
//! Takes an interim calibration, the suggested pose and its outlines; gives [`Picture`].

use crate::calib::bundle::Device;
use crate::calib::solve::Calibration;
use crate::observations::DeviceKind;
use nalgebra::{Isometry3, Point3, Vector3};
use serde::Serialize;

/// Turns and tilts are told to this many degrees; a turn below it is none.
pub const STEP_DEG: f64 = 5.0;

/// The most words of [`Picture::line`].
pub const MAX_WORDS: usize = 8;

/// The turn from the last pose to the suggested one, as seen in the picture's camera.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Turn {
    /// Unit direction in the image (x right, y down) of the board edge to bring nearer to
    /// the camera.
    pub toward: [f64; 2],
    /// The angle between the two poses' board normals (deg, to [`STEP_DEG`]).
    pub deg: f64,
}

/// The next pose drawn big in one camera's view.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Picture {
    /// The camera (rig index, cameras first, as the suggestion's outlines): the device the
    /// sentence is told for when it is a camera that sees the pose, else the camera that
    /// sees most of it.
    pub camera: usize,
    /// The board's tilt from facing that camera (deg, to [`STEP_DEG`]): the angle between
    /// the normal of the side it sees and the line from the board's centre to it.
    pub tilt_deg: f64,
    /// From the last pose to this one; `None` for a turn under [`STEP_DEG`].
    pub turn: Option<Turn>,
    /// What to do, in at most [`MAX_WORDS`] words.
    pub line: String,
}

/// How `dev` sees the board at T_ref_board `pose`: the normal of the side facing it (device
/// frame) and the angle (deg) between that normal and the line from the board's centre to
/// the device.
pub fn facing(dev: &Device, pose: &Isometry3<f64>) -> (Vector3<f64>, f64) {
    let t = dev.pose * pose;
    let centre = t * Point3::origin();
    let mut normal = t.rotation * Vector3::z();
    if normal.dot(&centre.coords) > 0.0 {
        normal = -normal;
    }
    (normal, normal.angle(&(-centre.coords)).to_degrees())
}

/// The edge of a board with facing `normal` (device frame) nearest to the device: "right",
/// "top-left", …
pub fn nearer_edge(normal: &Vector3<f64>) -> String {
    // The edge nearer to the device lies against the normal's sideways component.
    let (sx, sy) = (-normal.x, -normal.y);
    let vertical = if sy > 0.0 { "bottom" } else { "top" };
    let horizontal = if sx > 0.0 { "right" } else { "left" };
    if sx.abs() > 2.0 * sy.abs() {
        horizontal.to_string()
    } else if sy.abs() > 2.0 * sx.abs() {
        vertical.to_string()
    } else {
        format!("{vertical}-{horizontal}")
    }
}

/// `deg` to the nearest [`STEP_DEG`].
fn rounded(deg: f64) -> f64 {
    (deg / STEP_DEG).round() * STEP_DEG
}

/// The picture of the suggested `pose` (T_ref_board) of `cal`: in the view of calibration
/// device `told` when it is a camera with an outline, else of the camera with an outline
/// that sees most of `count` (points per calibration device); `uncalibrated` names a device
/// the pose is first for. `None` when no camera has an outline.
pub fn picture(
    cal: &Calibration,
    pose: &Isometry3<f64>,
    outlines: &[Option<Vec<[f32; 2]>>],
    (told, count): (usize, &dyn Fn(usize) -> usize),
    uncalibrated: Option<&str>,
) -> Option<Picture> {
    let drawn = |d: usize| {
        cal.devices[d].kind == DeviceKind::Camera
            && cal
                .device_index
                .get(d)
                .and_then(|&i| outlines.get(i))
                .is_some_and(Option::is_some)
    };
    let d = Some(told).filter(|&d| drawn(d)).or_else(|| {
        (0..cal.devices.len())
            .filter(|&d| drawn(d))
            .max_by_key(|&d| count(d))
    })?;
    let dev = &cal.devices[d];
    let (normal, tilt) = facing(dev, pose);
    let turn = last_pose(cal).and_then(|last| {
        let (before, _) = facing(dev, &last);
        let deg = rounded(before.angle(&normal).to_degrees());
        let toward = -(normal - before).xy();
        (deg >= STEP_DEG && toward.norm() > 0.0).then(|| Turn {
            toward: (toward / toward.norm()).into(),
            deg,
        })
    });
    let tilt_deg = rounded(tilt);
    let cam = &dev.name;
    let line = match (uncalibrated, tilt_deg < 2.0 * STEP_DEG) {
        (Some(u), _) if u == cam => format!("{cam} needs the board: fill its outline"),
        (Some(u), _) => format!("{u} needs the board: fill {cam}'s outline"),
        (None, true) => format!("{cam}: fill the outline, board facing it"),
        (None, false) => format!(
            "{cam}: fill the outline, {} edge nearer",
            nearer_edge(&normal)
        ),
    };
    Some(Picture {
        camera: cal.device_index[d],
        tilt_deg,
        turn,
        line,
    })
}

/// The board pose T_ref_board of the latest pose `cal` adjusted.
fn last_pose(cal: &Calibration) -> Option<Isometry3<f64>> {
    let latest = (0..cal.pose_index.len()).max_by_key(|&i| cal.pose_index[i])?;
    cal.solution.boards.get(latest).copied()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn the_nearer_edge_lies_against_the_normal() {
        let n = |x: f64, y: f64| Vector3::new(x, y, -1.0).normalize();
        assert_eq!(nearer_edge(&n(-0.5, 0.0)), "right");
        assert_eq!(nearer_edge(&n(0.0, 0.5)), "top");
        assert_eq!(nearer_edge(&n(0.4, -0.3)), "bottom-left");
    }

    #[test]
    fn facing_gives_the_tilt_from_the_line_to_the_device() {
        let dev = Device {
            name: "cam0".into(),
            kind: DeviceKind::Camera,
            model: crate::camera::CameraModel {
                width: 1280,
                height: 800,
                intrinsics: crate::camera::Intrinsics {
                    fx: 1000.0,
                    fy: 1000.0,
                    cx: 640.0,
                    cy: 400.0,
                },
                distortion: crate::camera::Distortion::default(),
            },
            pose: Isometry3::identity(),
        };
        // The board 1 m ahead, turned 40° about its y axis: its front faces away, its back
        // (the side the camera sees) is tilted 40° from facing the camera.
        let pose = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 1000.0),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 40f64.to_radians()),
        );
        let (normal, tilt) = facing(&dev, &pose);
        assert!((tilt - 40.0).abs() < 1e-9, "{tilt}");
        assert!(normal.z < 0.0, "{normal}");
        assert_eq!(nearer_edge(&normal), "right");
    }
}
