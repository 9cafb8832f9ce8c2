//! Image vocabulary shared by every stage (docs/design.md §2): camera frames as delivered
//! ([`CameraFrame`]), linear grey images ([`FloatImage`]), image ellipses ([`Ellipse`]) and
//! image files ([`load_gray`]). Pixel (0, 0) is the centre of the top-left pixel.

mod frame;
mod io;
pub mod to_grey;

pub use frame::{CameraFrame, Pixels};
pub use io::*;

use nalgebra::{Matrix2, Point2};
use serde::{Deserialize, Serialize};

/// A single-channel image of linear `f32` intensities (any scale); `image::GrayImage` is
/// the 8-bit one.
pub type FloatImage = image::ImageBuffer<image::Luma<f32>, Vec<f32>>;

/// An image ellipse: centre, semi-axes and orientation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ellipse {
    /// Centre (px), (0, 0) at the centre of the top-left pixel.
    pub center: Point2<f64>,
    /// Semi-major axis (px).
    pub a: f64,
    /// Semi-minor axis (px).
    pub b: f64,
    /// Angle of the major axis from +x towards +y (rad).
    pub angle: f64,
}

impl Ellipse {
    /// Second-moment matrix M of the uniform ellipse: (a²/4)·u·uᵀ + (b²/4)·v·vᵀ, so that its
    /// diameter along a unit direction w is 4/√(wᵀM⁻¹w).
    pub fn moment_matrix(&self) -> Matrix2<f64> {
        let (s, c) = self.angle.sin_cos();
        let (a2, b2) = (self.a * self.a / 4.0, self.b * self.b / 4.0);
        Matrix2::new(
            a2 * c * c + b2 * s * s,
            (a2 - b2) * c * s,
            (a2 - b2) * c * s,
            a2 * s * s + b2 * c * c,
        )
    }

    /// Geometric-mean radius √(a·b) (px).
    pub fn radius(&self) -> f64 {
        (self.a * self.b).sqrt()
    }
}
