//! What the console page shows, as one JSON snapshot: the run's status, each camera's
//! thumbnail and overlay, each device's progress, and the done / not-done verdict.
//!
//! Takes the run's events, the processed poses and the thumbnails; gives [`State`].

use super::stats::{DeviceStats, Overlay};
use crate::app::guide::Guidance;
use serde::Serialize;

/// A device is done with points in at least this fraction of its coverage cells, and its
/// projection uncertainty below the rig's threshold over its whole image.
pub const MIN_COVERAGE: f64 = 0.3;

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
    /// The latest live preview frame, while the board is placed.
    pub live: Option<Live>,
}

/// One camera's latest live preview frame (taken while the board is placed).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Live {
    /// URL of its picture (changes with every round).
    pub thumb: String,
    /// The preview round it comes from (counts up over the run).
    pub round: u64,
    /// Circles detected on it.
    pub circles: usize,
    /// Labelled points and lattice edges (frame px).
    pub overlay: Overlay,
    /// The camera sees the board now.
    pub sees_board: bool,
}

/// The live preview's progress.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Preview {
    /// Rounds (one frame from every camera) so far.
    pub rounds: u64,
    /// Rounds per second over the last few.
    pub rate_hz: f64,
    /// Time to detect and draw the last round (ms).
    pub detect_ms: f64,
    /// What each stage of the last round took, summed over its cameras (ms of CPU).
    pub stages: super::preview::Stages,
    /// Cameras that saw the board in the last round.
    pub seeing: usize,
    /// Why the preview stopped, if it failed.
    pub error: Option<String>,
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
    /// A capture script's prompt waiting for the operator (the button answers it).
    pub prompt: Option<String>,
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
    /// The done threshold on every device's projection uncertainty (px).
    pub threshold: f64,
    /// An interim calibration is under way.
    pub guiding: bool,
    /// What the latest interim calibration says (none before the first).
    pub guidance: Option<Guidance>,
    /// Why the latest interim calibration gave no guidance.
    pub guidance_error: Option<String>,
    /// The live preview, once it has run.
    pub preview: Option<Preview>,
    /// Before the first interim calibration, where to put the next pose
    /// ([`crate::app::guide::first_pose_advice`]).
    pub advice: Option<String>,
}

impl State {
    /// Recompute the verdict: a device is done with [`MIN_COVERAGE`] of its cells covered
    /// and, in the latest interim calibration, its worst projection uncertainty at most the
    /// threshold.
    pub fn judge(&mut self) {
        let guidance = self.guidance.as_ref();
        self.missing = self
            .devices
            .iter()
            .filter_map(|d| {
                let mut need = Vec::new();
                if d.coverage() < MIN_COVERAGE {
                    need.push(format!("coverage {:.0} %", 100.0 * d.coverage()));
                }
                let u = guidance.and_then(|g| g.devices.iter().find(|u| u.name == d.name));
                match (guidance, u.and_then(|u| u.worst)) {
                    (None, _) => need.push("no interim calibration yet".into()),
                    (Some(_), None) => need.push("not calibrated yet".into()),
                    (Some(g), Some(w)) if w > g.threshold => need.push(format!(
                        "projection uncertainty {w:.2} px > {:.2} px",
                        g.threshold
                    )),
                    _ => {}
                }
                (!need.is_empty()).then(|| format!("{}: {}", d.name, need.join(", ")))
            })
            .collect();
        self.done = !self.devices.is_empty() && self.missing.is_empty();
        let seen: Vec<(&str, usize)> = self
            .devices
            .iter()
            .map(|d| (d.name.as_str(), d.poses))
            .collect();
        self.advice = match (guidance, self.pose, self.auto) {
            (None, Some([k, _]), false) => crate::app::guide::first_pose_advice(
                k,
                crate::app::calibrate::MIN_CALIBRATION_POSES,
                &seen,
            ),
            _ => None,
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::app::guide::DeviceUncertainty;
    use crate::observations::DeviceInfo;
    use crate::observations::DeviceKind;

    /// A state of one device, nothing seen yet.
    fn one_device(name: &str, kind: DeviceKind, size: [u32; 2]) -> State {
        let info = DeviceInfo {
            name: name.into(),
            kind,
            width: size[0],
            height: size[1],
        };
        State {
            devices: vec![DeviceStats::new(&info)],
            ..State::default()
        }
    }

    #[test]
    fn first_pose_advice_shows_until_the_first_interim_calibration() {
        let mut s = State {
            pose: Some([1, 6]),
            ..one_device("cam1", DeviceKind::Camera, [960, 600])
        };
        s.judge();
        let advice = s
            .advice
            .clone()
            .expect("advice before the first calibration");
        assert!(
            advice.contains("2 of 3") && advice.contains("cam1 (0 of 1)"),
            "{advice}"
        );
        // Poses placed automatically need no advice; nor does a rig with guidance.
        s.auto = true;
        s.judge();
        assert_eq!(s.advice, None);
        s.auto = false;
        s.guidance = Some(Guidance {
            devices: Vec::new(),
            threshold: 0.25,
            done: false,
            suggestion: None,
        });
        s.judge();
        assert_eq!(s.advice, None);
    }

    #[test]
    fn done_needs_every_device_covered_and_certain() {
        let mut s = one_device("proj0", DeviceKind::Projector, [1280, 800]);
        s.judge();
        assert!(!s.done);
        assert_eq!(
            s.missing,
            ["proj0: coverage 0 %, no interim calibration yet"]
        );
        s.devices[0].cells.iter_mut().take(12).for_each(|c| *c = 5);
        let mut g = Guidance {
            devices: vec![DeviceUncertainty {
                name: "proj0".into(),
                worst: None,
                at: None,
            }],
            threshold: 0.25,
            done: false,
            suggestion: None,
        };
        s.guidance = Some(g.clone());
        s.judge();
        assert_eq!(s.missing, ["proj0: not calibrated yet"]);
        g.devices[0].worst = Some(0.31);
        s.guidance = Some(g.clone());
        s.judge();
        assert_eq!(
            s.missing,
            ["proj0: projection uncertainty 0.31 px > 0.25 px"]
        );
        g.devices[0].worst = Some(0.2);
        s.guidance = Some(g);
        s.judge();
        assert!(s.done && s.missing.is_empty());
        s.devices.clear();
        s.judge();
        assert!(!s.done, "no device is not done");
    }
}
