//! Simulator, part 2 (DESIGN.md §9): one camera's whole phase-shift stack of one board pose,
//! with every projector lighting the board at once.
//!
//! The geometry pass runs once: per camera pixel its footprint-integrated albedo and the
//! board point behind its centre; per projector the projector pixel (u, v) of that point and
//! whether the projector lights it (the side it faces, inside its raster). Each frame k is
//! then cheap: I = albedo·(ambient + Σ_p gain_p·light_p(pattern_p,k(u_p, v_p))), with each
//! projector's response (gamma) applied to its own pattern inside the sum, then the sensor
//! chain (PSF, shot and read noise, camera gamma, quantisation), seeded per frame.

use super::texture::face_side;
use super::{geometry, sensor, Scene, SimError};
use crate::camera::CameraModel;
use crate::phase::{Direction, Sequence};
use hexcal_simulator::{Frame, ImageSize, Sensor};
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

/// A projector lighting the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StackProjector {
    /// Its lens model and raster size.
    pub model: CameraModel,
    /// T_projector_board.
    pub proj_from_board: Isometry3<f64>,
    /// Full-white irradiance it adds on white (DN).
    pub gain_dn: f64,
}

/// Ground truth of one projector in the camera: per pixel, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct ProjectorTruth {
    /// Projector column of the board point behind each pixel centre (NaN where unlit).
    pub u: Vec<f32>,
    /// Projector row (NaN where unlit).
    pub v: Vec<f32>,
    /// Whether the projector lights the board point behind the pixel centre.
    pub lit: Vec<bool>,
}

/// A camera's stack renderer for one board pose.
pub struct StackRenderer {
    size: ImageSize,
    albedo: Vec<f32>,
    ambient_dn: f32,
    gains: Vec<f32>,
    truth: Vec<ProjectorTruth>,
    sensor: Sensor,
    sequence: Sequence,
    light: Vec<[f32; 256]>,
    seed: u64,
}

impl StackRenderer {
    /// Prepare the stack of `scene`'s camera and pose under `projectors`, which show
    /// `sequence` (its projector order); `ambient_dn` is the ambient light on white.
    pub fn new(
        scene: &Scene,
        projectors: &[StackProjector],
        ambient_dn: f64,
        sequence: &Sequence,
    ) -> Result<StackRenderer, SimError> {
        if projectors.len() != sequence.projectors().len() {
            return Err(SimError::Scene(format!(
                "{} projectors given for a sequence of {}",
                projectors.len(),
                sequence.projectors().len()
            )));
        }
        let geo = geometry(scene)?;
        let truth = projectors
            .iter()
            .map(|p| {
                let n = geo.point.len();
                let (mut u, mut v, mut lit) =
                    (vec![f32::NAN; n], vec![f32::NAN; n], vec![false; n]);
                let board_from_proj = p.proj_from_board.inverse();
                let centre = board_from_proj * Point3::origin();
                for i in 0..n {
                    let Some(side) = face_side(geo.face[i]) else {
                        continue;
                    };
                    // The projector lights the side whose outward normal points at it.
                    let face = scene.board.side_transform(side);
                    let normal = face.rotation * nalgebra::Vector3::z();
                    let [x, y, z] = geo.point[i];
                    let x = Point3::new(f64::from(x), f64::from(y), f64::from(z));
                    if normal.dot(&(centre - x)) <= 0.0 {
                        continue;
                    }
                    if let Some(q) = p.model.project(&(p.proj_from_board * x)) {
                        let (w, h) = (f64::from(p.model.width), f64::from(p.model.height));
                        if q.x >= -0.5 && q.y >= -0.5 && q.x < w - 0.5 && q.y < h - 0.5 {
                            u[i] = q.x as f32;
                            v[i] = q.y as f32;
                            lit[i] = true;
                        }
                    }
                }
                ProjectorTruth { u, v, lit }
            })
            .collect();
        Ok(StackRenderer {
            size: geo.size,
            albedo: geo.albedo,
            ambient_dn: ambient_dn as f32,
            gains: projectors.iter().map(|p| p.gain_dn as f32).collect(),
            truth,
            sensor: sensor(&scene.imaging),
            light: (0..sequence.projectors().len())
                .map(|p| sequence.light_table(p).map(|l| l as f32))
                .collect(),
            sequence: sequence.clone(),
            seed: scene.seed,
        })
    }

    /// Image size.
    pub fn size(&self) -> ImageSize {
        self.size
    }

    /// Footprint-integrated albedo per pixel, row-major.
    pub fn albedo(&self) -> &[f32] {
        &self.albedo
    }

    /// Ground truth of projector `p`.
    pub fn truth(&self, p: usize) -> &ProjectorTruth {
        &self.truth[p]
    }

    /// The noise-free irradiance of frame k (DN, before the sensor).
    fn irradiance(&self, k: usize) -> Vec<f32> {
        let frame = self
            .sequence
            .frame(k)
            .expect("frame index within the sequence");
        let n = self.sequence.steps();
        // Per projector: the position it encodes in this frame, and the phase
        // θ = a·pos + b = 2π·n·(pos + ½)/size − 2π·f_p·s/N (DESIGN.md §6).
        let phases: Vec<(bool, f32, f32)> = self
            .sequence
            .projectors()
            .iter()
            .map(|code| {
                let (rows, size) = match frame.direction {
                    Direction::Columns => (false, code.width),
                    Direction::Rows => (true, code.height),
                };
                let a = 2.0 * std::f64::consts::PI * f64::from(frame.count) / f64::from(size);
                let shift = 2.0 * std::f64::consts::PI * f64::from(code.frequency * frame.step % n)
                    / f64::from(n);
                (rows, a as f32, (0.5 * a - shift) as f32)
            })
            .collect();
        let w = self.size.width as usize;
        let mut irr = vec![0.0f32; self.albedo.len()];
        irr.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            let base = y * w;
            for (x, out) in row.iter_mut().enumerate() {
                let i = base + x;
                let mut e = self.ambient_dn;
                for (p, t) in self.truth.iter().enumerate() {
                    if t.lit[i] {
                        let (rows, a, b) = phases[p];
                        let pos = if rows { t.v[i] } else { t.u[i] };
                        let level = 127.5 * (1.0 + (a * pos + b).cos());
                        e += self.gains[p] * self.light[p][(level + 0.5) as usize];
                    }
                }
                *out = self.albedo[i] * e;
            }
        });
        irr
    }

    /// Frame k of the stack.
    pub fn frame(&self, k: usize) -> Frame {
        let signal = self.sensor.optics(self.size, &self.irradiance(k));
        self.sensor
            .expose(self.size, &signal, self.seed.wrapping_add(1 + k as u64))
    }
}

#[cfg(test)]
mod tests;
