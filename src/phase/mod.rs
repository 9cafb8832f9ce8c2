//! Multi-projector phase shifting (docs/design.md §6): the decoder that turns one camera's stack into each projector's
//! (u, v) map, modulation, validity, ambient and lit images.
//!
//! Takes the [`Sequence`] and the camera frames in order; gives a [`DecodedStack`] per camera.

mod decode;
pub mod files;
pub mod synthetic;
mod unwrap;

pub use decode::*;
pub use unwrap::*;

#[cfg(test)]
mod tests;
