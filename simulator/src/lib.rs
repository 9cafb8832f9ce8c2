//! The physics behind hexcal's simulated rig (DESIGN.md §9).
//!
//! This crate knows nothing of hex boards or of hexcal's lens model: it renders any planar
//! textured target through any lens that implements [`RayModel`], adds the imaging chain
//! (PSF, vignetting, noise, gamma, quantisation), and hosts the trigger-firmware model.

pub mod firmware;
