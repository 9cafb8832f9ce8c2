//! The physics behind hexcal's simulated rig (docs/design.md §9).
//!
//! This crate knows nothing of hex boards or of hexcal's lens model: it renders any planar
//! textured target through any lens that implements [`Lens`], adds the imaging chain
//! (PSF, vignetting, noise, gamma, quantisation), and hosts the trigger-firmware model and
//! the model of a motorised board stage ([`stage`]).
//!
//! Rendering is split so that frames are cheap: per camera a [`RayGrid`] (exact rays,
//! interpolated); per camera and target pose a [`Geometry`] (what each pixel sees and its
//! footprint-integrated albedo); per frame only shading and the [`Sensor`] chain.
#![warn(missing_docs)]

pub mod firmware;
pub mod geometry;
pub mod lens;
pub mod sensor;
pub mod stage;
pub mod target;

pub use geometry::{render_geometry, Geometry, RenderOptions, NO_FACE};
pub use lens::{ImageSize, Lens, RayGrid, RayJet};
pub use sensor::{Frame, Sensor};
pub use target::{Background, Edge, Face, Target, Texel, Texture, UniformRect};
