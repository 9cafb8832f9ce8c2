//! The rig (docs/design.md §11, §13): rig files, the device traits every driver implements, and
//! the drivers — the serial trigger controller ([`trigger`]), which pulses the cameras'
//! trigger lines and reports each frame's controller timestamp, the positioners that move
//! the board for capture scripts ([`positioner`], [`script`]), and the simulated rig.

#[cfg(feature = "aravis")]
pub mod aravis;
pub mod device;
pub mod discover;
pub mod file;
#[cfg(any(test, feature = "testkit"))]
pub mod fixture;
pub mod open;
pub mod positioner;
pub mod script;
pub mod sim;
pub mod trigger;
#[cfg(feature = "v4l2")]
pub mod v4l2;
#[cfg(feature = "window")]
pub mod window;

pub use device::{Camera, CameraConfig, DeviceError, Projector, Slide, Trigger, TriggerSource};
pub use open::{open, CaptureTiming, OpenError, OpenedRig, RigDevices, SIMULATED_PORT};
