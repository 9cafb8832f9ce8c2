//! Calibration (docs/design.md §7–8): registration of unanchored views ([`views`] by
//! projector coordinates, [`geometric`] by a first calibration's predictions), Zhang's
//! planar initialisation per device ([`zhang`]), the pose graph ([`posegraph`]) and one
//! bundle adjustment over all devices, board poses and both sides ([`bundle`], with the
//! circle model of [`circle`]), repeated with the distortion terms the data cannot determine
//! fixed ([`lens_model`]); [`solve::calibrate`] runs them in order.
//!
//! Takes labelled camera views with projector coordinates at their circles and gives every
//! device's model and pose in the reference device's frame, with residuals and covariance.

pub mod bundle;
pub mod circle;
pub mod diagnostics;
pub mod geometric;
pub mod lens_model;
pub mod observability;
pub mod posegraph;
pub mod schur;
pub mod solve;
#[cfg(any(test, feature = "testkit"))]
pub mod synthetic;
pub mod verify;
pub mod views;
pub mod zhang;

use nalgebra::Point2;

/// One board-plane point and where a device observed it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlaneCorrespondence {
    /// Point on the board plane of the side seen (mm), z = 0 in that side's frame.
    pub board: Point2<f64>,
    /// Observed pixel.
    pub image: Point2<f64>,
}

/// All correspondences of one device in one board pose, on one side's plane.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlanarView {
    /// The correspondences.
    pub points: Vec<PlaneCorrespondence>,
}

/// Why a calibration step failed.
#[derive(Debug, thiserror::Error)]
pub enum CalibError {
    /// Not enough views for the step.
    #[error("too few views: {got} given, at least {needed} needed")]
    TooFewViews {
        /// Minimum number of views.
        needed: usize,
        /// Views given.
        got: usize,
    },
    /// The data do not determine the quantity (e.g. parallel views, collinear points).
    #[error("degenerate data: {0}")]
    Degenerate(&'static str),
    /// A device's observations lie in too few board-plane views (pose, side) to determine
    /// its lens (docs/design.md §8, "Observability").
    #[error(
        "{name} cannot be calibrated: it is seen in {views} board views (pose and side), at \
         least {needed} needed"
    )]
    DeviceNotObserved {
        /// Its name.
        name: String,
        /// The views it is seen in.
        views: usize,
        /// The views needed.
        needed: usize,
    },
    /// The normal equations are singular in parameters that cannot be held at a prior:
    /// what the data do not determine (devices' lenses or poses, by name; or a board pose).
    #[error("degenerate data: the views do not determine {0}")]
    NotDetermined(String),
    /// The reference device could not be calibrated.
    #[error("the reference device {name} cannot be calibrated: {reason}")]
    Reference {
        /// Its name.
        name: String,
        /// Why (which views it has, what they lack).
        reason: String,
    },
    /// A stop was requested (Ctrl-C) before the calibration finished.
    #[error("stopped (Ctrl-C) before the calibration finished; nothing of it was written")]
    Stopped,
    /// The input refers to what is not there (a device, pose or index out of range, a
    /// duplicate name or view, a value that is not finite): the JSON path of the offending
    /// value (e.g. `views[3].camera`) and what is wrong.
    #[error(transparent)]
    Input(#[from] hexcal_core::ValidationError),
}

#[cfg(test)]
pub(crate) mod single_sided_tests;
#[cfg(test)]
mod tests;
