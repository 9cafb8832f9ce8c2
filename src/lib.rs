//! hexcal: joint geometric calibration of structured-light rigs with many cameras and many
//! projectors, from a double-sided hexagonal circle board.
//!
//! The layers are crates (docs/design.md §1b; `tests/layers.rs` checks the graph), bottom
//! first:
//! - `hexcal-core`: the vocabulary — [`board`], [`camera`], [`pattern`] (the phase-shift
//!   sequence), [`images`], [`dataset`], [`observations`] (the seam to calibration),
//!   [`limits`], [`atomic`] file writes;
//! - `hexcal-sim`: the simulated world with ground truth ([`sim`]);
//! - stages: `hexcal-rig` ([`rig`] → [`capture`]), `hexcal-vision` ([`phase`] → [`detect`] →
//!   [`grid`] → [`correspond`]), `hexcal-calib` ([`calib`] → [`report`]);
//! - this crate, the application: [`app`] (run, capture, calibrate, detect, the console), and
//!   `bench` (feature `bench`); the `hexcal` binary parses arguments and prints.
//!
//! The lower crates are re-exported under their module names, so `hexcal::calib::…` names
//! the same item as `hexcal_calib::calib::…`.
#![warn(missing_docs)]

pub use hexcal_calib::{calib, report};
pub use hexcal_core::{
    atomic, board, camera, dataset, images, invalid, limits, lock, observations, pattern, stop,
};
pub use hexcal_rig::{capture, check, rig};
pub use hexcal_sim as sim;
pub use hexcal_vision::{correspond, detect, grid, phase};

pub mod app;
#[cfg(feature = "bench")]
pub mod bench;
