//! Benchmark harnesses behind the `bench` feature (`hexcal bench …`): they render their own
//! inputs, time the stages and print figures; nothing a calibration needs.

pub mod calib;
pub mod capture;
pub mod check;
pub mod decode;
pub mod detect;
pub mod detect_grid;
pub mod faults;
pub mod formats;
pub mod formats_rig;
pub mod guide;
pub mod preview;
pub mod render;
pub mod script;
