//! The rig: drivers for the hardware a capture drives (DESIGN.md §11). So far the serial
//! trigger controller ([`trigger`]), which pulses the cameras' trigger lines and reports
//! each frame's controller timestamp.

pub mod file;
pub mod trigger;
