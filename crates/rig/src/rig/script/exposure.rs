//! A capture step's own exposure and gain (docs/rig-file.md, "Scripts and positioners"):
//! checked on load against the rig's timing and cameras, and turned into one setting per
//! camera for the capture engine.

use super::{Plan, StepSpec, Unroller};
use crate::rig::file::RigFile;
use hexcal_core::limits;
use hexcal_core::ValidationError;
use serde::Serialize;

/// The exposure and gain a capture step sets for its captures, undone after each.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Exposure {
    /// Exposure (µs); none keeps each camera's own.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exposure_us: Option<f64>,
    /// Gain (dB); none keeps each camera's own.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gain_db: Option<f64>,
    /// The cameras it applies to (rig-file names); empty: every camera.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub cameras: Vec<String>,
}

impl Exposure {
    /// Per camera of `rig` (in file order): its (exposure µs, gain dB) for this capture, or
    /// `None` for a camera it leaves alone.
    pub fn settings(&self, rig: &RigFile) -> Vec<Option<(f64, f64)>> {
        rig.cameras
            .iter()
            .map(|c| {
                let applies = self.cameras.is_empty() || self.cameras.contains(&c.name);
                applies.then(|| {
                    (
                        self.exposure_us.unwrap_or(1e3 * c.exposure_ms),
                        self.gain_db.unwrap_or(c.gain_db),
                    )
                })
            })
            .collect()
    }

    /// How the dry-run timeline shows it, e.g. `exposure 5000 µs, gain 6 dB (left, right)`.
    pub fn describe(&self) -> String {
        let mut parts = Vec::new();
        if let Some(e) = self.exposure_us {
            parts.push(format!("exposure {} µs", super::format_number(e)));
        }
        if let Some(g) = self.gain_db {
            parts.push(format!("gain {} dB", super::format_number(g)));
        }
        let mut text = parts.join(", ");
        if !self.cameras.is_empty() {
            text += &format!(" ({})", self.cameras.join(", "));
        }
        text
    }
}

impl Unroller<'_> {
    /// The exposure and gain of capture step `s` at `at`: an exposure that fits in a
    /// pattern's display time after settling (as the cameras' own `exposure_ms` must), a
    /// finite gain, cameras the rig has, each once, and `cameras` only with one of the two.
    pub(super) fn exposure(
        &self,
        s: &StepSpec,
        at: &str,
    ) -> Result<Option<Exposure>, ValidationError> {
        let key = |k: &str| format!("{at}.{k}");
        if let Some(e) = s.exposure_us {
            let t = &self.rig.timing;
            let window = 1e3 * (t.frame_period_ms - t.settle_ms);
            if !(e > 0.0 && e <= window) {
                return Err(ValidationError::new(
                    key("exposure_us"),
                    format!(
                        "{e} µs does not fit in a pattern's display time after settling \
                         ({} − {} ms = {window} µs)",
                        t.frame_period_ms, t.settle_ms
                    ),
                ));
            }
        }
        if let Some(g) = s.gain_db {
            limits::within(g, -limits::MAX_GAIN_DB, limits::MAX_GAIN_DB)
                .map_err(|m| m.at(key("gain_db")))?;
        }
        let cameras = s.cameras.clone().unwrap_or_default();
        if s.cameras.is_some() && cameras.is_empty() {
            return Err(ValidationError::new(
                key("cameras"),
                "name at least one camera",
            ));
        }
        for (i, name) in cameras.iter().enumerate() {
            if !self.rig.cameras.iter().any(|c| &c.name == name) {
                return Err(ValidationError::new(
                    key("cameras"),
                    format!("no camera is named {name:?}"),
                ));
            }
            if cameras[..i].contains(name) {
                return Err(ValidationError::new(
                    key("cameras"),
                    format!("{name:?} is named twice"),
                ));
            }
        }
        match (s.exposure_us, s.gain_db) {
            (None, None) if s.cameras.is_some() => Err(ValidationError::new(
                key("cameras"),
                "cameras says whom exposure_us or gain_db apply to: give one of them",
            )),
            (None, None) => Ok(None),
            (exposure_us, gain_db) => Ok(Some(Exposure {
                exposure_us,
                gain_db,
                cameras,
            })),
        }
    }
}

/// Per pose whose capture step sets its own exposure or gain: every camera's setting for
/// it ([`Exposure::settings`]).
pub type PoseExposures = std::collections::BTreeMap<usize, Vec<Option<(f64, f64)>>>;

impl Plan {
    /// The settings of every capture that sets its own exposure or gain, for `rig`'s
    /// cameras.
    pub fn exposures(&self, rig: &RigFile) -> PoseExposures {
        self.steps
            .iter()
            .filter_map(|s| match &s.action {
                super::Action::Capture {
                    pose,
                    exposure: Some(e),
                    ..
                } => Some((*pose, e.settings(rig))),
                _ => None,
            })
            .collect()
    }
}
