//! hexcal-calib: calibration from observations (docs/design.md §7–8, §13).
//!
//! Takes the devices and every camera's labelled views ([`hexcal_core::observations`]); gives
//! the calibration — Zhang's initialisation, the pose graph, one bundle adjustment over all
//! devices and board poses, verification on held-out poses ([`calib`]) — and what is written
//! from it: the residual table, the HTML report and the exports for neighbouring tools
//! ([`report`]). Depends on `hexcal-core` only.
#![warn(missing_docs)]

pub mod calib;
pub mod report;
