//! hexcal: joint geometric calibration of structured-light rigs with many cameras and many
//! projectors, from a double-sided hexagonal circle board.
//!
//! The stages, in the order data flows through them: [`board`] and [`camera`] (the models
//! every stage shares) → [`rig`] (rig files, device traits, drivers, the simulated rig) →
//! [`capture`] (lockstep capture, datasets) → [`phase`] (decoding) → [`detect`] (circles) →
//! [`grid`] (labelled lattice points), both run on image files by [`detection`] →
//! [`correspond`] (camera and projector observations) → [`calib`] → [`report`];
//! [`pipeline`] streams them all in one process (`hexcal run`). [`sim`] renders board views
//! and capture stacks with ground truth.
#![warn(missing_docs)]

pub mod app;
pub mod atomic;
#[cfg(feature = "bench")]
pub mod bench;
pub mod board;
pub mod calib;
pub mod camera;
pub mod capture;
pub mod correspond;
pub mod dataset;
pub mod detect;
pub mod grid;
pub mod images;
pub mod pattern;
pub mod phase;
pub mod report;
pub mod rig;
pub mod sim;
pub(crate) mod tomlspan;

/// Paths of the test data vendored in the repository (`tests/data`).
#[cfg(test)]
pub(crate) mod testdata {
    use std::path::PathBuf;

    /// The independent sample images with ground truth (`tests/data/samples`, README there).
    pub(crate) fn samples_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/samples")
    }
}
