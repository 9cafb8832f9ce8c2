//! hexcal: joint geometric calibration of structured-light rigs with many cameras and many
//! projectors, from a double-sided hexagonal circle board.
//!
//! Layers, bottom first (docs/design.md §1b; `tests/layers.rs` checks that a module uses only
//! lower layers or earlier modules of its own):
//! - foundation: [`atomic`] file writes, `tomlspan`, [`limits`] on what is read;
//! - vocabulary: [`board`], [`camera`], [`pattern`] (the phase-shift sequence), [`images`],
//!   [`dataset`];
//! - [`sim`]: the simulated world with ground truth;
//! - stages in data order: [`rig`] → [`capture`] → [`phase`] → [`detect`] → [`grid`] →
//!   [`correspond`] → [`calib`] → [`report`];
//! - application: [`app`] (run, capture, calibrate, detect), and `bench` (feature `bench`).
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
pub mod limits;
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
