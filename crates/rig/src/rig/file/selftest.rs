//! Rig-file keys of the self-tests (docs/rig-file.md, "Self-tests"): the `[checks]` table that
//! says when `run` checks projector–camera sync and sets the exposure, and a simulated
//! projector's display faults (`[projector.sim_display]`: lag, dropped and repeated frames,
//! a response that clips) that the self-tests are tested against.

use hexcal_core::ValidationError;
use serde::{Deserialize, Serialize};

/// When a run-start self-test runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CheckWhen {
    /// On a rig with a real camera or projector; not on a fully simulated one.
    #[default]
    Auto,
    /// Always.
    On,
    /// Never (for the exposure: the rig file's `exposure_ms` and `gain_db` are fixed).
    Off,
}

impl CheckWhen {
    /// Whether the test runs on a rig that is (`simulated`) or is not fully simulated.
    pub fn runs(self, simulated: bool) -> bool {
        match self {
            CheckWhen::Auto => !simulated,
            CheckWhen::On => true,
            CheckWhen::Off => false,
        }
    }
}

/// The `[checks]` table.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChecksSpec {
    /// The short sync check at the start of `run`.
    #[serde(default)]
    pub sync: CheckWhen,
    /// Setting every camera's exposure at the start of `run`.
    #[serde(default)]
    pub exposure: CheckWhen,
    /// Where the brightest board white should sit, as a fraction of full scale.
    #[serde(default = "default_white")]
    pub white_level: f64,
    /// The most gain the exposure test may set (dB), once the exposure is at its longest.
    #[serde(default = "default_max_gain")]
    pub max_gain_db: f64,
}

/// Default of [`ChecksSpec::max_gain_db`]: more gain adds more noise than light.
pub const DEFAULT_MAX_GAIN_DB: f64 = 12.0;

fn default_max_gain() -> f64 {
    DEFAULT_MAX_GAIN_DB
}

/// Default of [`ChecksSpec::white_level`].
pub const DEFAULT_WHITE_LEVEL: f64 = 0.8;

fn default_white() -> f64 {
    DEFAULT_WHITE_LEVEL
}

impl Default for ChecksSpec {
    fn default() -> Self {
        ChecksSpec {
            sync: CheckWhen::Auto,
            exposure: CheckWhen::Auto,
            white_level: DEFAULT_WHITE_LEVEL,
            max_gain_db: DEFAULT_MAX_GAIN_DB,
        }
    }
}

impl ChecksSpec {
    /// `white_level` within (0.1, 0.98], `max_gain_db` within [0, 48].
    pub fn check(&self) -> Result<(), ValidationError> {
        let g = self.max_gain_db;
        if !(g.is_finite() && (0.0..=48.0).contains(&g)) {
            return Err(ValidationError::new(
                "checks.max_gain_db",
                format!("{g} dB: a gain in [0, 48] dB"),
            ));
        }
        let w = self.white_level;
        if !(w.is_finite() && w > 0.1 && w <= 0.98) {
            return Err(ValidationError::new(
                "checks.white_level",
                format!("{w}: a fraction of full scale in (0.1, 0.98]"),
            ));
        }
        Ok(())
    }
}

/// How a simulated projector's display misbehaves.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimDisplay {
    /// Time from `show` to light on the board (ms).
    #[serde(default)]
    pub lag_ms: f64,
    /// The display's refresh rate (Hz): a repeated frame comes one refresh late.
    #[serde(default = "default_refresh")]
    pub refresh_hz: f64,
    /// Every n-th slide shown is never displayed (the previous one stays).
    #[serde(default)]
    pub drop_every: Option<u32>,
    /// Every n-th slide shown comes one refresh late (the previous one shows twice).
    #[serde(default)]
    pub repeat_every: Option<u32>,
    /// Drive levels above this give no more light (the response clips).
    #[serde(default)]
    pub clip_level: Option<u8>,
}

fn default_refresh() -> f64 {
    60.0
}

impl SimDisplay {
    /// A finite lag up to 10 s, a refresh rate in [1, 1000] Hz, counts from 2, a clip level
    /// above 0; `at` names a key.
    pub fn check(&self, at: &dyn Fn(&str) -> String) -> Result<(), ValidationError> {
        if !(self.lag_ms.is_finite() && (0.0..=10_000.0).contains(&self.lag_ms)) {
            return Err(ValidationError::new(
                at("sim_display.lag_ms"),
                format!("{} ms: a lag in [0, 10000] ms", self.lag_ms),
            ));
        }
        if !(self.refresh_hz.is_finite() && (1.0..=1000.0).contains(&self.refresh_hz)) {
            return Err(ValidationError::new(
                at("sim_display.refresh_hz"),
                format!("{} Hz: a refresh rate in [1, 1000] Hz", self.refresh_hz),
            ));
        }
        for (key, n) in [
            ("drop_every", self.drop_every),
            ("repeat_every", self.repeat_every),
        ] {
            if n.is_some_and(|n| n < 2) {
                return Err(ValidationError::new(
                    at(&format!("sim_display.{key}")),
                    "at least 2 (every slide cannot be lost)",
                ));
            }
        }
        if self.clip_level == Some(0) {
            return Err(ValidationError::new(
                at("sim_display.clip_level"),
                "0: a projector that clips at black shows nothing",
            ));
        }
        Ok(())
    }

    /// The extra delay of a repeated frame: one refresh period.
    pub fn refresh(&self) -> std::time::Duration {
        std::time::Duration::from_secs_f64(1.0 / self.refresh_hz)
    }
}

impl super::RigFile {
    /// Whether every camera and projector is simulated (and the trigger controller, if any,
    /// is the simulated one): where the run-start self-tests run only when asked.
    pub fn fully_simulated(&self) -> bool {
        use super::{CameraDriver, ProjectorDriver};
        self.cameras.iter().all(|c| c.driver == CameraDriver::Sim)
            && self
                .projectors
                .iter()
                .all(|p| p.driver == ProjectorDriver::Sim)
            && (self.trigger.as_ref()).is_none_or(|t| t.port == crate::rig::SIMULATED_PORT)
    }
}
