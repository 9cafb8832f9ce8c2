//! What the console page shows, as one JSON snapshot: the run's status, each camera's
//! thumbnail and overlay, each device's progress, and the done / not-done verdict.
//!
//! Takes the run's events, the processed poses and the thumbnails; gives [`State`].

use super::stats::{DeviceStats, Overlay};
use serde::Serialize;

/// A device needs at least this many calibration poses to be done.
pub const MIN_POSES: usize = 3;
/// ... and points in at least this fraction of its coverage cells.
pub const MIN_COVERAGE: f64 = 0.3;
/// ... and board tilts spanning at least this many degrees (views that differ in tilt
/// separate the focal length from the distance).
pub const MIN_TILT_SPAN: f64 = 10.0;

/// One camera's picture on the page.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CameraPanel {
    /// Name.
    pub name: String,
    /// Image size (px).
    pub size: [u32; 2],
    /// URL of its latest thumbnail (changes with every new one).
    pub thumb: Option<String>,
    /// The pose the thumbnail shows.
    pub thumb_pose: Option<usize>,
    /// Source pixels per thumbnail pixel.
    pub thumb_step: u32,
    /// Labelled points of the latest processed pose.
    pub overlay: Option<Overlay>,
}

/// The page's whole state.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct State {
    /// Increases with every change.
    pub version: u64,
    /// "starting", "waiting" (for the board), "capturing", "calibrating", "finished" or
    /// "stopped".
    pub status: String,
    /// One sentence for the operator.
    pub message: String,
    /// Poses are placed without waiting (`--auto`): no capture button.
    pub auto: bool,
    /// The pose being placed or captured, and the poses in all.
    pub pose: Option<[usize; 2]>,
    /// Frames captured of the current pose, and the frames of a pose.
    pub frames: Option<[usize; 2]>,
    /// Every device reached the done rule.
    pub done: bool,
    /// What keeps each device that is not done from being done.
    pub missing: Vec<String>,
    /// Cameras, in rig order.
    pub cameras: Vec<CameraPanel>,
    /// Devices: cameras, then projectors.
    pub devices: Vec<DeviceStats>,
    /// Problems reading what the run wrote (shown, never fatal).
    pub warnings: Vec<String>,
}

impl State {
    /// Recompute the verdict: a device is done with [`MIN_POSES`] poses, [`MIN_COVERAGE`]
    /// of its cells covered and a tilt span of [`MIN_TILT_SPAN`].
    pub fn judge(&mut self) {
        self.missing = self
            .devices
            .iter()
            .filter_map(|d| {
                let mut need = Vec::new();
                if d.poses < MIN_POSES {
                    need.push(format!("{} more poses", MIN_POSES - d.poses));
                }
                if d.coverage() < MIN_COVERAGE {
                    need.push(format!("coverage {:.0} %", 100.0 * d.coverage()));
                }
                let span = d.tilt.map_or(0.0, |[lo, hi]| hi - lo);
                if span < MIN_TILT_SPAN {
                    need.push(format!("tilt range {span:.0}°"));
                }
                (!need.is_empty()).then(|| format!("{}: {}", d.name, need.join(", ")))
            })
            .collect();
        self.done = !self.devices.is_empty() && self.missing.is_empty();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::bundle::DeviceKind;
    use crate::calib::solve::DeviceInfo;

    #[test]
    fn done_needs_every_device_posed_covered_and_tilted() {
        let info = DeviceInfo {
            name: "proj0".into(),
            kind: DeviceKind::Projector,
            width: 1280,
            height: 800,
        };
        let mut s = State {
            devices: vec![DeviceStats::new(&info)],
            ..State::default()
        };
        s.judge();
        assert!(!s.done);
        assert_eq!(
            s.missing,
            ["proj0: 3 more poses, coverage 0 %, tilt range 0°"]
        );
        let d = &mut s.devices[0];
        d.poses = 3;
        d.cells.iter_mut().take(12).for_each(|c| *c = 5);
        d.tilt = Some([12.0, 21.0]);
        s.judge();
        assert_eq!(s.missing, ["proj0: tilt range 9°"]);
        s.devices[0].tilt = Some([12.0, 22.5]);
        s.judge();
        assert!(s.done && s.missing.is_empty());
        s.devices.clear();
        s.judge();
        assert!(!s.done, "no device is not done");
    }
}
