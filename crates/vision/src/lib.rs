//! hexcal-vision: the image stages in data order (docs/design.md §4–7).
//!
//! Takes camera stacks and frames (`hexcal-core`'s images and pattern sequence); gives each
//! projector's decoded (u, v) per camera pixel ([`phase`]), circles with subpixel ellipse
//! centres ([`detect`]), labelled lattice points ([`grid`]) and, joining them, the
//! [`hexcal_core::observations`] calibration takes ([`correspond`]).
#![warn(missing_docs)]

pub mod correspond;
pub mod detect;
pub mod grid;
pub mod phase;
pub mod stats;

/// Paths of the test data vendored in the repository (`tests/data`).
#[cfg(test)]
pub(crate) mod testdata {
    use std::path::PathBuf;

    /// The independent sample images with ground truth (`tests/data/samples`, README there).
    pub(crate) fn samples_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/samples")
    }
}
