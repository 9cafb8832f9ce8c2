//! The done rule, decided by the run and shown by the console: a device is done with
//! [`MIN_COVERAGE`] of its image's cells covered and, in the latest interim calibration, its
//! worst projection uncertainty at most the rig file's threshold; until the first interim
//! calibration, advice on where the first poses go.
//!
//! Takes each device's [`DeviceStats`] and the latest [`Guidance`]; gives [`Verdict`].

use super::stats::DeviceStats;
use super::Guidance;
use serde::Serialize;

/// A device is done with points in at least this fraction of its coverage cells, and its
/// projection uncertainty below the rig's threshold over its whole image.
pub const MIN_COVERAGE: f64 = 0.3;

/// What the guidance loop has decided so far.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Verdict {
    /// Every device reached the done rule.
    pub done: bool,
    /// What keeps each device that is not done from being done.
    pub missing: Vec<String>,
    /// Devices: cameras, then projectors.
    pub devices: Vec<DeviceStats>,
    /// The done threshold on every device's projection uncertainty (px).
    pub threshold: f64,
    /// An interim calibration is under way.
    pub guiding: bool,
    /// What the latest interim calibration says (none before the first).
    pub guidance: Option<Guidance>,
    /// Why the latest interim calibration gave no guidance.
    pub guidance_error: Option<String>,
    /// Before the first interim calibration, where to put the next pose
    /// ([`super::first_pose_advice`]).
    pub advice: Option<String>,
    /// The advice in one short line ([`super::first_pose_line`]).
    pub advice_line: Option<String>,
}

impl Verdict {
    /// Recompute the verdict: a device is done with [`MIN_COVERAGE`] of its cells covered
    /// and, in the latest interim calibration, its worst projection uncertainty at most the
    /// threshold; `pose` is the pose being placed, `auto` says the run places poses itself
    /// (no advice then).
    pub fn judge(&mut self, pose: Option<usize>, auto: bool) {
        let guidance = self.guidance.as_ref();
        self.missing = self
            .devices
            .iter()
            .filter_map(|d| {
                let mut need = Vec::new();
                if d.coverage < MIN_COVERAGE {
                    need.push(format!("coverage {:.0} %", 100.0 * d.coverage));
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
        let need = crate::app::calibrate::MIN_CALIBRATION_POSES;
        (self.advice, self.advice_line) = match (guidance, pose, auto) {
            (None, Some(k), false) => (
                super::first_pose_advice(k, need, &seen),
                super::first_pose_line(k, need),
            ),
            _ => (None, None),
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
    fn one_device(name: &str, kind: DeviceKind, size: [u32; 2]) -> Verdict {
        let info = DeviceInfo {
            name: name.into(),
            kind,
            width: size[0],
            height: size[1],
        };
        Verdict {
            devices: vec![DeviceStats::new(&info)],
            ..Verdict::default()
        }
    }

    #[test]
    fn first_pose_advice_shows_until_the_first_interim_calibration() {
        let mut s = one_device("cam1", DeviceKind::Camera, [960, 600]);
        s.judge(Some(1), false);
        let advice = s
            .advice
            .clone()
            .expect("advice before the first calibration");
        assert!(
            advice.contains("2 of 3") && advice.contains("cam1 (0 of 1)"),
            "{advice}"
        );
        let line = s.advice_line.clone().expect("its short line");
        assert!(line.split_whitespace().count() <= crate::app::guide::picture::MAX_WORDS);
        // Poses placed automatically need no advice; nor does a rig with guidance.
        s.judge(Some(1), true);
        assert_eq!((&s.advice, &s.advice_line), (&None, &None));
        s.guidance = Some(Guidance {
            devices: Vec::new(),
            threshold: 0.25,
            done: false,
            suggestion: None,
        });
        s.judge(Some(1), false);
        assert_eq!(s.advice, None);
    }

    #[test]
    fn done_needs_every_device_covered_and_certain() {
        let mut s = one_device("proj0", DeviceKind::Projector, [1280, 800]);
        s.judge(None, false);
        assert!(!s.done);
        assert_eq!(
            s.missing,
            ["proj0: coverage 0 %, no interim calibration yet"]
        );
        s.devices[0].coverage = MIN_COVERAGE;
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
        s.judge(None, false);
        assert_eq!(s.missing, ["proj0: not calibrated yet"]);
        g.devices[0].worst = Some(0.31);
        s.guidance = Some(g.clone());
        s.judge(None, false);
        assert_eq!(
            s.missing,
            ["proj0: projection uncertainty 0.31 px > 0.25 px"]
        );
        g.devices[0].worst = Some(0.2);
        s.guidance = Some(g);
        s.judge(None, false);
        assert!(s.done && s.missing.is_empty());
        s.devices.clear();
        s.judge(None, false);
        assert!(!s.done, "no device is not done");
    }
}
