//! Simulator, part 2 (docs/design.md §9): one camera's whole phase-shift stack of one board pose,
//! with every projector lighting the board at once.
//!
//! The geometry pass runs once: per camera pixel its footprint-integrated albedo and the
//! board point behind its centre; per projector the projector pixel (u, v) of that point
//! where the projector lights it (the side it faces, inside its raster), kept over the lit
//! pixels' rectangle only. Each frame k is
//! then cheap: I = albedo·(ambient + Σ_p gain_p·light_p(pattern_p,k(u_p, v_p))), with each
//! projector's response (gamma) applied to its own pattern inside the sum, then the sensor
//! chain (PSF, shot and read noise, camera gamma, quantisation), seeded per frame.

use super::texture::face_side;
use super::{geometry, sensor, Scene, SimError};
use hexcal_core::camera::CameraModel;
use hexcal_core::pattern::{Direction, Sequence};
use hexcal_simulator::{Frame, Geometry, ImageSize, Sensor};
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;
use std::sync::Mutex;

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

/// Ground truth of one projector in the camera, held over the smallest pixel rectangle that
/// holds every pixel it lights (a board covers part of the image).
#[derive(Clone, Debug, PartialEq)]
pub struct ProjectorTruth {
    /// Image width (px).
    width: usize,
    /// The rectangle (x0, y0, x1, y1), exclusive ends; empty when nothing is lit.
    bounds: [usize; 4],
    /// Projector column per rectangle pixel, row-major (NaN where unlit).
    u: Vec<f32>,
    /// Projector row per rectangle pixel (NaN where unlit).
    v: Vec<f32>,
}

impl ProjectorTruth {
    /// The truth of an image `width` pixels wide from per-pixel (u, v) over the whole image
    /// (NaN where unlit), kept over the lit pixels' rectangle.
    fn cropped(width: usize, u: &[f32], v: &[f32]) -> Self {
        let mut b: Option<[usize; 4]> = None;
        for (i, _) in u.iter().enumerate().filter(|(_, u)| !u.is_nan()) {
            let (x, y) = (i % width, i / width);
            let r = b.get_or_insert([x, y, x + 1, y + 1]);
            *r = [r[0].min(x), r[1].min(y), r[2].max(x + 1), r[3].max(y + 1)];
        }
        let bounds = b.unwrap_or([0; 4]);
        ProjectorTruth {
            width,
            bounds,
            u: crop(u, width, bounds),
            v: crop(v, width, bounds),
        }
    }

    /// The rectangle (x0, y0, x1, y1) of the lit pixels, exclusive ends; `None` when the
    /// projector lights nothing.
    pub fn bounds(&self) -> Option<[usize; 4]> {
        (self.bounds[2] > self.bounds[0]).then_some(self.bounds)
    }

    /// Where pixel i (row-major) is in the rectangle.
    fn index(&self, i: usize) -> Option<usize> {
        let (x, y) = (i % self.width, i / self.width);
        let [x0, y0, x1, y1] = self.bounds;
        (x >= x0 && x < x1 && y >= y0 && y < y1).then(|| (y - y0) * (x1 - x0) + x - x0)
    }

    /// Projector column of the board point behind pixel i's centre (row-major; NaN where
    /// unlit).
    pub fn u(&self, i: usize) -> f32 {
        self.index(i).map_or(f32::NAN, |j| self.u[j])
    }

    /// Projector row at pixel i (NaN where unlit).
    pub fn v(&self, i: usize) -> f32 {
        self.index(i).map_or(f32::NAN, |j| self.v[j])
    }

    /// Whether the projector lights the board point behind pixel i's centre.
    pub fn lit(&self, i: usize) -> bool {
        !self.u(i).is_nan()
    }

    /// Where pixel i is in the rectangle, when the projector lights it.
    fn lit_index(&self, i: usize) -> Option<usize> {
        self.index(i).filter(|&j| !self.u[j].is_nan())
    }

    /// Pixels in the rectangle.
    fn area(&self) -> usize {
        let [x0, y0, x1, y1] = self.bounds;
        (x1 - x0) * (y1 - y0)
    }
}

/// A camera's stack renderer for one board pose.
pub struct StackRenderer {
    size: ImageSize,
    /// Footprint-integrated albedo over the lit box (box-sized, row-major; empty without
    /// one): projector light reaches no pixel outside it.
    albedo: Vec<f32>,
    gains: Vec<f32>,
    truth: Vec<ProjectorTruth>,
    sensor: Sensor,
    sequence: Sequence,
    light: Vec<[f32; 256]>,
    seed: u64,
    /// The signal with every projector dark (ambient light through the optics), once.
    ambient_signal: Vec<f32>,
    /// Pixel rectangle (x0, y0, x1, y1), exclusive ends, holding every lit pixel plus the
    /// PSF's reach twice over: outside it projector light adds nothing.
    lit_box: Option<[usize; 4]>,
    /// The spatial phases of the group being rendered.
    phases: Mutex<GroupPhases>,
    /// The noise-free signal of the flat frames (black, white), once each: a preview
    /// takes one after another of a board that stays put, and only their noise differs.
    flat_signal: [std::sync::OnceLock<Vec<f32>>; 2],
}

/// Image rows per band when a frame is exposed.
const EXPOSE_ROWS: usize = 64;

/// The fixed-point unit of cached cosines and sines.
const PHASE_UNIT: f64 = 32767.0;

/// Per projector and pixel of its truth's rectangle, (cos θ₀, sin θ₀) of one fringe group, where
/// θ₀ = 2π·n·(pos + ½)/size is the phase at step 0: the group's N frames differ only by a
/// shift, so the cosine of each frame is two products away (frames come group by group).
#[derive(Default)]
struct GroupPhases {
    /// The group these phases belong to.
    group: Option<usize>,
    /// Per projector, over its truth's rectangle, row-major, in units of 1/32767: 3·10⁻⁵ rad, or 4·10⁻⁴
    /// projector px at 25 fringes across 1920 px (half the memory of f32).
    phases: Vec<Vec<[i16; 2]>>,
}

impl GroupPhases {
    /// Compute the phases of `group` over each projector's rectangle.
    fn fill(&mut self, r: &StackRenderer, group: usize) {
        let steps = r.sequence.steps() as usize;
        let frame = r
            .sequence
            .frame(group * steps)
            .expect("group within the sequence");
        let w = r.size.width as usize;
        self.phases.resize(r.truth.len(), Vec::new());
        for ((code, t), out) in r
            .sequence
            .projectors()
            .iter()
            .zip(&r.truth)
            .zip(&mut self.phases)
        {
            let (rows, size) = match frame.direction {
                Direction::Columns => (false, code.width),
                Direction::Rows => (true, code.height),
            };
            let a = 2.0 * std::f64::consts::PI * f64::from(frame.count) / f64::from(size);
            let [x0, y0, x1, _] = t.bounds;
            out.clear();
            out.resize(t.area(), [0; 2]);
            if out.is_empty() {
                continue;
            }
            out.par_chunks_mut(x1 - x0)
                .enumerate()
                .for_each(|(by, row)| {
                    let base = (y0 + by) * w + x0;
                    for (bx, o) in row.iter_mut().enumerate() {
                        let i = base + bx;
                        if t.lit(i) {
                            let pos = f64::from(if rows { t.v(i) } else { t.u(i) });
                            let (s, c) = (a * (pos + 0.5)).sin_cos();
                            *o = [
                                (c * PHASE_UNIT).round() as i16,
                                (s * PHASE_UNIT).round() as i16,
                            ];
                        }
                    }
                });
        }
        self.group = Some(group);
    }
}

/// Projector `p`'s truth in `scene`'s camera from its geometry pass `geo`: the projector
/// pixel of each lit pixel's board point (on the side facing the projector, inside its
/// raster), computed row by row on all cores; one whole-image map at a time (the rest of the
/// image is dark), kept over the lit rectangle.
fn projector_truth(scene: &Scene, geo: &Geometry, p: &StackProjector) -> ProjectorTruth {
    let n = geo.point.len();
    let w = geo.size.width as usize;
    let (mut u, mut v) = (vec![f32::NAN; n], vec![f32::NAN; n]);
    let board_from_proj = p.proj_from_board.inverse();
    let centre = board_from_proj * Point3::origin();
    let (pw, ph) = (f64::from(p.model.width), f64::from(p.model.height));
    u.par_chunks_mut(w)
        .zip(v.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (u, v))| {
            for (x, (u, v)) in u.iter_mut().zip(v.iter_mut()).enumerate() {
                let i = y * w + x;
                let Some(side) = face_side(geo.face[i]) else {
                    continue;
                };
                // The projector lights the side whose outward normal points at it.
                let face = scene.board.side_transform(side);
                let normal = face.rotation * nalgebra::Vector3::z();
                let [px, py, pz] = geo.point[i];
                let pt = Point3::new(f64::from(px), f64::from(py), f64::from(pz));
                if normal.dot(&(centre - pt)) <= 0.0 {
                    continue;
                }
                if let Some(q) = p.model.project(&(p.proj_from_board * pt)) {
                    if q.x >= -0.5 && q.y >= -0.5 && q.x < pw - 0.5 && q.y < ph - 0.5 {
                        *u = q.x as f32;
                        *v = q.y as f32;
                    }
                }
            }
        });
    ProjectorTruth::cropped(w, &u, &v)
}

/// The rectangle `[x0, y0, x1, y1]` (exclusive ends) of an image `width` pixels wide, row-major.
fn crop(image: &[f32], width: usize, [x0, y0, x1, y1]: [usize; 4]) -> Vec<f32> {
    (y0..y1)
        .flat_map(|y| image[y * width + x0..y * width + x1].iter().copied())
        .collect()
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
        let truth: Vec<ProjectorTruth> = projectors
            .iter()
            .map(|p| projector_truth(scene, &geo, p))
            .collect();
        let sensor = sensor(&scene.imaging);
        let (w, h) = (geo.size.width as usize, geo.size.height as usize);
        let ambient: Vec<f32> = geo.albedo.iter().map(|a| a * ambient_dn as f32).collect();
        let ambient_signal = sensor.optics(geo.size, &ambient);
        let reach = 2 * (4.0 * sensor.psf_sigma).ceil() as usize;
        // The union of the projectors' lit rectangles.
        let lit_box = truth
            .iter()
            .filter_map(ProjectorTruth::bounds)
            .reduce(|a, b| {
                [
                    a[0].min(b[0]),
                    a[1].min(b[1]),
                    a[2].max(b[2]),
                    a[3].max(b[3]),
                ]
            });
        let lit_box = lit_box.map(|[x0, y0, x1, y1]| {
            [
                x0.saturating_sub(reach),
                y0.saturating_sub(reach),
                (x1 + reach).min(w),
                (y1 + reach).min(h),
            ]
        });
        Ok(StackRenderer {
            phases: Mutex::new(GroupPhases::default()),
            flat_signal: Default::default(),
            ambient_signal,
            lit_box,
            size: geo.size,
            albedo: lit_box.map_or_else(Vec::new, |b| crop(&geo.albedo, w, b)),
            gains: projectors.iter().map(|p| p.gain_dn as f32).collect(),
            truth,
            sensor,
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

    /// Footprint-integrated albedo at pixel i (row-major), known inside the box projector
    /// light can reach (NaN outside it).
    pub fn albedo(&self, i: usize) -> f32 {
        self.box_index(i).map_or(f32::NAN, |j| self.albedo[j])
    }

    /// Where pixel i is in the lit box.
    fn box_index(&self, i: usize) -> Option<usize> {
        let [x0, y0, x1, y1] = self.lit_box?;
        let (x, y) = (i % self.size.width as usize, i / self.size.width as usize);
        (x >= x0 && x < x1 && y >= y0 && y < y1).then(|| (y - y0) * (x1 - x0) + x - x0)
    }

    /// Whether the albedo is uniform (within 10⁻⁴) over the (2r+1)² pixels around pixel `i`,
    /// all inside the image and the lit box: a pixel whose decoded phase is the decoder's alone (nearer an
    /// albedo edge the PSF mixes the phases of differently bright neighbours, which is
    /// optics, not decoding).
    pub fn uniform_albedo(&self, i: usize, r: usize) -> bool {
        let (w, h) = (self.size.width as usize, self.size.height as usize);
        let (x, y) = (i % w, i / w);
        let a = self.albedo(i);
        x >= r
            && y >= r
            && x + r < w
            && y + r < h
            && (y - r..=y + r)
                .all(|yy| (x - r..=x + r).all(|xx| (self.albedo(yy * w + xx) - a).abs() < 1e-4))
    }

    /// Ground truth of projector `p`.
    pub fn truth(&self, p: usize) -> &ProjectorTruth {
        &self.truth[p]
    }

    /// The projectors' noise-free irradiance inside `lit_box` when projector p shows pattern
    /// `shown[p]` (all of one fringe group) (DN, before the sensor; box-sized, row-major).
    fn projector_irradiance(&self, shown: &[usize], [x0, y0, x1, y1]: [usize; 4]) -> Vec<f32> {
        let frames: Vec<_> = shown
            .iter()
            .map(|&k| {
                self.sequence
                    .frame(k)
                    .expect("frame index within the sequence")
            })
            .collect();
        let frame = frames[0];
        let n = self.sequence.steps();
        let mut cache = self.phases.lock().unwrap_or_else(|e| e.into_inner());
        if cache.group != Some(frame.group) {
            cache.fill(self, frame.group);
        }
        // Per projector the phase shift of this step: θ = θ₀ − 2π·f_p·s/N (docs/design.md §6),
        // so cos θ = cos θ₀·cos(shift) + sin θ₀·sin(shift).
        let shifts: Vec<(f32, f32)> = self
            .sequence
            .projectors()
            .iter()
            .zip(&frames)
            .map(|(code, frame)| {
                let shift = 2.0 * std::f64::consts::PI * f64::from(code.frequency * frame.step % n)
                    / f64::from(n);
                (
                    (shift.cos() / PHASE_UNIT) as f32,
                    (shift.sin() / PHASE_UNIT) as f32,
                )
            })
            .collect();
        let w = self.size.width as usize;
        let bw = x1 - x0;
        let mut irr = vec![0.0f32; bw * (y1 - y0)];
        let cache = &*cache;
        irr.par_chunks_mut(bw).enumerate().for_each(|(by, row)| {
            let base = (y0 + by) * w + x0;
            for (bx, out) in row.iter_mut().enumerate() {
                let i = base + bx;
                let mut e = 0.0;
                for (p, t) in self.truth.iter().enumerate() {
                    if let Some(j) = t.lit_index(i) {
                        let [c0, s0] = cache.phases[p][j];
                        let (c0, s0) = (f32::from(c0), f32::from(s0));
                        let (cs, ss) = shifts[p];
                        let level = 127.5 * (1.0 + c0 * cs + s0 * ss);
                        e += self.gains[p] * self.light[p][(level + 0.5) as usize];
                    }
                }
                *out = self.albedo[by * bw + bx] * e;
            }
        });
        irr
    }

    /// Render through a colour filter array from now on: the response of each pixel of a
    /// 2×2 cell, row by row ([`Sensor::cfa`]); `None` for a monochrome sensor.
    pub fn set_cfa(&mut self, cfa: Option<[f32; 4]>) {
        self.sensor.cfa = cfa;
    }

    /// Frame k of the stack.
    pub fn frame(&self, k: usize) -> Frame {
        self.frame_showing(k, &vec![k; self.truth.len()])
    }

    /// Frame k of the stack with projector p showing pattern `shown[p]` instead (a display
    /// lag, a dropped or repeated frame); the patterns must be of frame k's fringe group.
    pub fn frame_showing(&self, k: usize, shown: &[usize]) -> Frame {
        let shown = self.own_group(k, shown);
        self.expose(
            |b| self.projector_irradiance(&shown, b),
            self.seed.wrapping_add(1 + k as u64),
        )
    }

    /// `shown` when it has a pattern per projector, each of frame k's fringe group; else
    /// frame k's own patterns.
    fn own_group(&self, k: usize, shown: &[usize]) -> Vec<usize> {
        let group = |j: usize| self.sequence.frame(j).map(|f| f.group);
        let own = |j: &usize| group(*j) == group(k);
        match shown.len() == self.truth.len() && shown.iter().all(own) {
            true => shown.to_vec(),
            false => vec![k; self.truth.len()],
        }
    }

    /// Frame k as [`Self::frame_showing`] gives it, with the room's light and the view
    /// changed: the ambient light times `change.ambient`, and the whole image displaced by
    /// `change.shift` camera px (the camera or the rig jolted; bilinear, the border repeated).
    pub fn frame_changed(&self, k: usize, shown: &[usize], change: &FrameChange) -> Frame {
        if *change == FrameChange::default() {
            return self.frame_showing(k, shown);
        }
        let (w, h) = (self.size.width as usize, self.size.height as usize);
        let shown = self.own_group(k, shown);
        let mut signal = self.signal(|b| self.projector_irradiance(&shown, b));
        let extra = change.ambient - 1.0;
        for (s, a) in signal.iter_mut().zip(&self.ambient_signal) {
            *s += extra * a;
        }
        let moved = shifted(&signal, w, h, change.shift);
        let mut data = vec![0u16; w * h];
        let seed = self.seed.wrapping_add(1 + k as u64);
        self.sensor.expose_rows(w, 0, &moved, seed, &mut data);
        Frame {
            size: self.size,
            bits: self.sensor.bits,
            data,
        }
    }

    /// A frame outside the sequence with every projector showing one flat level: full white
    /// (`white`, a preview's flat field) or black (ambient light only); `n` numbers it for
    /// its noise (frames of the sequence and flat frames have seeds of their own).
    pub fn flat_frame(&self, white: bool, n: u64) -> Frame {
        let flat = |[x0, y0, x1, y1]: [usize; 4]| {
            let w = self.size.width as usize;
            let mut irr = vec![0.0f32; (x1 - x0) * (y1 - y0)];
            if white {
                for (by, row) in irr.chunks_mut(x1 - x0).enumerate() {
                    let base = (y0 + by) * w + x0;
                    for (bx, out) in row.iter_mut().enumerate() {
                        let i = base + bx;
                        let e: f32 = (self.truth.iter().zip(&self.gains))
                            .zip(&self.light)
                            .filter(|((t, _), _)| t.lit(i))
                            .map(|((_, g), l)| g * l[255])
                            .sum();
                        *out = self.albedo[by * (x1 - x0) + bx] * e;
                    }
                }
            }
            irr
        };
        let seed = self.seed ^ 0x5eed_f1a7 ^ n.wrapping_mul(0x9e37_79b9_7f4a_7c15);
        let signal = self.flat_signal[usize::from(white)].get_or_init(|| self.signal(flat));
        self.sensor.expose(self.size, signal, seed)
    }

    /// A frame outside the sequence with projector p showing the flat intended level
    /// `levels[p]` (its light through the projector's response table); `n` numbers it for
    /// its noise, as in [`Self::flat_frame`].
    pub fn levels_frame(&self, levels: &[u8], n: u64) -> Frame {
        let flat = |[x0, y0, x1, y1]: [usize; 4]| {
            let w = self.size.width as usize;
            let mut irr = vec![0.0f32; (x1 - x0) * (y1 - y0)];
            for (by, row) in irr.chunks_mut(x1 - x0).enumerate() {
                let base = (y0 + by) * w + x0;
                for (bx, out) in row.iter_mut().enumerate() {
                    let i = base + bx;
                    let e: f32 = (self.truth.iter().zip(&self.gains))
                        .zip(self.light.iter().zip(levels))
                        .filter(|((t, _), _)| t.lit(i))
                        .map(|((_, g), (l, &level))| g * l[usize::from(level)])
                        .sum();
                    *out = self.albedo[by * (x1 - x0) + bx] * e;
                }
            }
            irr
        };
        let seed = self.seed ^ 0x1e7e_15ee ^ n.wrapping_mul(0x9e37_79b9_7f4a_7c15);
        self.sensor.expose(self.size, &self.signal(flat), seed)
    }

    /// Projector p's light stops growing above intended level `level` (a projector whose
    /// response clips), in every frame rendered from now on.
    pub fn clip_light(&mut self, p: usize, level: u8) {
        if let Some(table) = self.light.get_mut(p) {
            let top = table[usize::from(level)];
            for l in table.iter_mut() {
                *l = l.min(top);
            }
            self.flat_signal = Default::default();
        }
    }

    /// The whole frame's noise-free signal of the ambient light plus the projectors'
    /// irradiance `lit` gives inside the lit box (what [`Self::expose`] forms band by band).
    fn signal(&self, lit: impl FnOnce([usize; 4]) -> Vec<f32>) -> Vec<f32> {
        let w = self.size.width as usize;
        let mut signal = self.ambient_signal.clone();
        if let Some(b @ [x0, y0, x1, _]) = self.lit_box {
            let irr = self.optics(b, lit(b));
            for (by, row) in irr.chunks(x1 - x0).enumerate() {
                let start = (y0 + by) * w + x0;
                for (s, v) in signal[start..start + (x1 - x0)].iter_mut().zip(row) {
                    *s += v;
                }
            }
        }
        signal
    }

    /// The sensor's frame of the ambient light plus the projectors' irradiance `lit` gives
    /// inside the lit box, with noise seed `seed`; exposed band by band of
    /// [`EXPOSE_ROWS`] rows (the whole frame's signal is never held).
    fn expose(&self, lit: impl FnOnce([usize; 4]) -> Vec<f32>, seed: u64) -> Frame {
        let (w, h) = (self.size.width as usize, self.size.height as usize);
        // The optics are linear: the ambient signal (once) plus the projectors' light through
        // the optics inside the lit box, exact there because the box reaches twice as far as
        // the PSF beyond the last lit pixel.
        let light = self.lit_box.map(|b| (b, self.optics(b, lit(b))));
        let mut data = vec![0u16; w * h];
        let mut band = vec![0f32; EXPOSE_ROWS.min(h) * w];
        for (i, out) in data.chunks_mut(EXPOSE_ROWS * w).enumerate() {
            let y0 = i * EXPOSE_ROWS;
            let signal = &mut band[..out.len()];
            signal.copy_from_slice(&self.ambient_signal[y0 * w..][..out.len()]);
            if let Some(([x0, by0, x1, by1], irr)) = &light {
                let bw = x1 - x0;
                for y in y0.max(*by0)..(y0 + out.len() / w).min(*by1) {
                    let row = &irr[(y - by0) * bw..][..bw];
                    for (s, v) in signal[(y - y0) * w + x0..][..bw].iter_mut().zip(row) {
                        *s += v;
                    }
                }
            }
            self.sensor.expose_rows(w, y0, signal, seed, out);
        }
        Frame {
            size: self.size,
            bits: self.sensor.bits,
            data,
        }
    }

    /// The projectors' irradiance `irr` over the lit box `[x0, y0, x1, y1]` through the
    /// optics: vignetting, then the PSF.
    fn optics(&self, [x0, y0, x1, y1]: [usize; 4], mut irr: Vec<f32>) -> Vec<f32> {
        let (bw, bh) = (x1 - x0, y1 - y0);
        let (w, h) = (self.size.width as usize, self.size.height as usize);
        if self.sensor.vignetting != 0.0 {
            let (cx, cy) = (0.5 * (w as f64 - 1.0), 0.5 * (h as f64 - 1.0));
            let corner2 = (cx * cx + cy * cy).max(1e-12);
            for (by, row) in irr.chunks_mut(bw).enumerate() {
                let dy2 = ((y0 + by) as f64 - cy).powi(2);
                for (bx, v) in row.iter_mut().enumerate() {
                    let rho2 = ((x0 + bx) as f64 - cx).powi(2) + dy2;
                    *v *= (1.0 - self.sensor.vignetting * rho2 / corner2) as f32;
                }
            }
        }
        if self.sensor.psf_sigma > 0.0 {
            irr = hexcal_simulator::sensor::gaussian_blur(&irr, bw, bh, self.sensor.psf_sigma);
        }
        irr
    }
}

/// How one frame's light and view differ from the stack's (a simulated fault).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameChange {
    /// Factor on the ambient light.
    pub ambient: f32,
    /// Displacement of the whole image (camera px).
    pub shift: [f64; 2],
}

impl Default for FrameChange {
    fn default() -> Self {
        FrameChange {
            ambient: 1.0,
            shift: [0.0; 2],
        }
    }
}

/// `image` (w × h) displaced by `shift`: out(x, y) = image(x − dx, y − dy), bilinear, the
/// border repeated.
fn shifted(image: &[f32], w: usize, h: usize, [dx, dy]: [f64; 2]) -> Vec<f32> {
    let at = |x: isize, y: isize| {
        image[y.clamp(0, h as isize - 1) as usize * w + x.clamp(0, w as isize - 1) as usize]
    };
    let (fx, fy) = (dx.floor(), dy.floor());
    let (tx, ty) = ((dx - fx) as f32, (dy - fy) as f32);
    let (ix, iy) = (fx as isize, fy as isize);
    (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as isize - ix, (i / w) as isize - iy);
            let top = (1.0 - tx) * at(x, y) + tx * at(x - 1, y);
            let bottom = (1.0 - tx) * at(x, y - 1) + tx * at(x - 1, y - 1);
            (1.0 - ty) * top + ty * bottom
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_shifted_image_moves_by_whole_and_fractional_pixels() {
        let (w, h) = (7, 5);
        // A plane a + b·x + c·y: bilinear interpolation is exact on it (inside the border).
        let plane = |x: f64, y: f64| 3.0 + 2.0 * x - 0.5 * y;
        let image: Vec<f32> = (0..w * h)
            .map(|i| plane((i % w) as f64, (i / w) as f64) as f32)
            .collect();
        for shift in [[1.0, 0.0], [0.25, -0.5], [-1.75, 1.5]] {
            let out = shifted(&image, w, h, shift);
            for y in 2..h - 2 {
                for x in 2..w - 2 {
                    let want = plane(x as f64 - shift[0], y as f64 - shift[1]);
                    let got = f64::from(out[y * w + x]);
                    assert!(
                        (got - want).abs() < 1e-5,
                        "{shift:?} at ({x}, {y}): {got} vs {want}"
                    );
                }
            }
        }
        assert_eq!(shifted(&image, w, h, [0.0, 0.0]), image);
    }

    #[test]
    fn truth_is_kept_over_the_lit_rectangle() {
        let (w, h) = (8, 6);
        let mut u = vec![f32::NAN; w * h];
        let mut v = u.clone();
        for (x, y) in [(2, 1), (5, 3), (3, 2)] {
            u[y * w + x] = 10.0 * x as f32;
            v[y * w + x] = y as f32;
        }
        let t = ProjectorTruth::cropped(w, &u, &v);
        assert_eq!(t.bounds(), Some([2, 1, 6, 4]));
        for i in 0..w * h {
            assert_eq!(t.u(i).to_bits(), u[i].to_bits(), "pixel {i}");
            assert_eq!(t.v(i).to_bits(), v[i].to_bits(), "pixel {i}");
            assert_eq!(t.lit(i), !u[i].is_nan(), "pixel {i}");
        }
        let dark = vec![f32::NAN; w * h];
        let t = ProjectorTruth::cropped(w, &dark, &dark);
        assert_eq!(t.bounds(), None);
        assert!((0..w * h).all(|i| !t.lit(i)));
    }
}
