//! hexcal-core: the vocabulary every hexcal stage shares (docs/design.md §1b).
//!
//! Takes nothing from the other hexcal crates; gives the board ([`board`]), the camera and
//! projector model ([`camera`]), the phase-shift sequence ([`pattern`]), images ([`images`]),
//! the dataset format ([`dataset`]), the observations that are the seam between the image
//! stages and calibration ([`observations`]), the limits on what is read ([`limits`]), the
//! refusals of what is read ([`invalid`]), atomic file writes ([`atomic`]), the stop
//! request long stages poll ([`stop`]) and the checks that keep every path a file names
//! inside its folder ([`paths`]). A user who only needs the camera model and the
//! calibration files depends on this crate (and `hexcal-calib`) alone.
#![warn(missing_docs)]

pub mod atomic;
pub mod board;
pub mod camera;
pub mod dataset;
pub mod images;
pub mod invalid;
pub mod limits;
pub mod lock;
pub mod observations;
pub mod paths;
pub mod pattern;
pub mod stop;
pub mod tomlspan;

pub use invalid::{Invalid, ValidationError};

/// Paths of the test data vendored in the repository (`tests/data`).
#[cfg(test)]
pub(crate) mod testdata {
    use std::path::PathBuf;

    /// The repository's root (this crate lives in `crates/core`).
    pub(crate) fn repo() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
    }

    /// The independent sample images with ground truth (`tests/data/samples`, README there).
    pub(crate) fn samples_dir() -> PathBuf {
        repo().join("tests/data/samples")
    }
}
