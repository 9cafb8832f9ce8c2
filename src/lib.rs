//! hexcal: joint geometric calibration of structured-light rigs with many cameras and many
//! projectors, from a double-sided hexagonal circle board.
//!
//! The stages, in the order data flows through them:
//! [`board`] and [`camera`] (the models every stage shares) → [`detect`] (circles) →
//! [`grid`] (labelled lattice points), both run on image files by [`detection`]; [`sim`]
//! renders board views with ground truth.
#![warn(missing_docs)]

pub mod atomic;
pub mod board;
pub mod calib;
pub mod camera;
pub mod capture;
pub mod correspond;
pub mod detect;
pub mod detection;
pub mod grid;
pub mod imageio;
pub mod phase;
pub mod pipeline;
pub mod report;
pub mod rig;
pub mod sim;
pub(crate) mod tomlspan;
