//! Multi-projector phase shifting (docs/design.md §6): the decoder that turns one camera's stack into each projector's
//! (u, v) map, modulation, validity, ambient and lit images.
//!
//! Takes the [`hexcal_core::pattern::Sequence`] and the camera frames in order; gives a [`DecodedStack`] per camera.

#[cfg(any(test, feature = "bench"))]
pub mod accuracy;
pub mod check;
mod compact;
mod decode;
pub mod files;
mod maps;
mod pages;
mod unwrap;

pub use compact::*;
pub use decode::*;
pub use maps::*;
pub use unwrap::*;

#[cfg(test)]
mod tests;
