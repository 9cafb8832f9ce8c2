//! hexcal-rig: the rig and its capture (docs/design.md §10–12).
//!
//! Takes a rig file; gives its devices behind traits — simulated, Aravis, V4L2, window
//! projectors, the serial trigger controller, positioners ([`rig`]) — and the lockstep engine
//! that shows pattern k, triggers and collects frame k from every camera, pose after pose,
//! into stacks and dataset folders ([`capture`]).
#![warn(missing_docs)]

pub mod capture;
pub mod check;
pub mod rig;
