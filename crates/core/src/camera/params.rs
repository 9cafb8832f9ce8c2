//! The lens parameter vector a solver estimates, and which of its entries are free.
//!
//! Order (fixed, OpenCV's): [fx, fy, cx, cy, k1, k2, p1, p2, k3] and, for the rational model,
//! [k4, k5, k6] after them. A [`LensVector`] always holds all twelve; the 5-coefficient model
//! is the rational one with k4–k6 fixed at zero, so indices never move between the two.

use super::CameraModel;
use nalgebra::{SMatrix, SVector};
use serde::{Deserialize, Serialize};

/// Number of lens parameters (4 pinhole + 8 distortion).
pub const LENS_PARAM_COUNT: usize = 12;

/// All twelve lens parameters in [`LensParam`] order.
pub type LensVector = SVector<f64, LENS_PARAM_COUNT>;

/// Derivative of a pixel (or of a normalised point) with respect to the twelve lens
/// parameters, columns in [`LensParam`] order.
pub type LensJacobian = SMatrix<f64, 2, LENS_PARAM_COUNT>;

/// One lens parameter; its discriminant is its index in a [`LensVector`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LensParam {
    /// Focal length along x (px).
    Fx,
    /// Focal length along y (px).
    Fy,
    /// Principal point x (px).
    Cx,
    /// Principal point y (px).
    Cy,
    /// Radial r².
    K1,
    /// Radial r⁴.
    K2,
    /// Tangential p1.
    P1,
    /// Tangential p2.
    P2,
    /// Radial r⁶.
    K3,
    /// Rational denominator r².
    K4,
    /// Rational denominator r⁴.
    K5,
    /// Rational denominator r⁶.
    K6,
}

impl LensParam {
    /// Every parameter, in vector order.
    pub const ALL: [LensParam; LENS_PARAM_COUNT] = [
        LensParam::Fx,
        LensParam::Fy,
        LensParam::Cx,
        LensParam::Cy,
        LensParam::K1,
        LensParam::K2,
        LensParam::P1,
        LensParam::P2,
        LensParam::K3,
        LensParam::K4,
        LensParam::K5,
        LensParam::K6,
    ];

    /// Index in a [`LensVector`] and column in a [`LensJacobian`].
    pub fn index(self) -> usize {
        self as usize
    }

    /// Lower-case name, as in files ("fx", "k1", …).
    pub fn name(self) -> &'static str {
        [
            "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
        ][self.index()]
    }
}

impl std::fmt::Display for LensParam {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Which lens parameters a solver estimates (the others stay at their current values).
///
/// [`LensParams::standard`] frees the nine parameters of the 5-coefficient model,
/// [`LensParams::rational`] all twelve; [`LensParams::fix`] then pins any of them, e.g. k3.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct LensParams {
    /// Bit i set: parameter i is free.
    free: u16,
}

impl LensParams {
    /// fx, fy, cx, cy, k1, k2, p1, p2, k3 free; k4–k6 fixed.
    pub fn standard() -> LensParams {
        LensParams { free: 0x1ff }
    }

    /// All twelve parameters free.
    pub fn rational() -> LensParams {
        LensParams { free: 0xfff }
    }

    /// [`LensParams::rational`] when the model uses k4–k6, else [`LensParams::standard`].
    pub fn for_model(m: &CameraModel) -> LensParams {
        if m.distortion.is_rational() {
            LensParams::rational()
        } else {
            LensParams::standard()
        }
    }

    /// The same set with `p` fixed.
    pub fn fix(self, p: LensParam) -> LensParams {
        LensParams {
            free: self.free & !(1 << p.index()),
        }
    }

    /// The same set with `p` free.
    pub fn free(self, p: LensParam) -> LensParams {
        LensParams {
            free: self.free | (1 << p.index()),
        }
    }

    /// Whether `p` is estimated.
    pub fn is_free(self, p: LensParam) -> bool {
        self.free & (1 << p.index()) != 0
    }

    /// Number of free parameters.
    pub fn len(self) -> usize {
        self.free.count_ones() as usize
    }

    /// Whether every parameter is fixed.
    pub fn is_empty(self) -> bool {
        self.free == 0
    }

    /// The free parameters in vector order; the k-th one is entry k of the compact vector
    /// that [`LensParams::gather`] and [`LensParams::scatter`] use.
    pub fn iter(self) -> impl Iterator<Item = LensParam> {
        LensParam::ALL.into_iter().filter(move |&p| self.is_free(p))
    }

    /// Write the free parameters of `m` into `out` (length [`LensParams::len`]).
    ///
    /// # Panics
    /// When `out` has the wrong length.
    pub fn gather(self, m: &CameraModel, out: &mut [f64]) {
        assert_eq!(out.len(), self.len(), "lens parameter slice length");
        let v = m.lens_vector();
        for (o, p) in out.iter_mut().zip(self.iter()) {
            *o = v[p.index()];
        }
    }

    /// Set the free parameters of `m` from `values` (length [`LensParams::len`]); the fixed
    /// ones keep their values.
    ///
    /// # Panics
    /// When `values` has the wrong length.
    pub fn scatter(self, m: &mut CameraModel, values: &[f64]) {
        assert_eq!(values.len(), self.len(), "lens parameter slice length");
        let mut v = m.lens_vector();
        for (&x, p) in values.iter().zip(self.iter()) {
            v[p.index()] = x;
        }
        m.set_lens_vector(&v);
    }
}
