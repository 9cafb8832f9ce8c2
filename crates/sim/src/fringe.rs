//! A synthetic phase-shift scene for the decoder's tests and benchmark: no lens and no board,
//! only what decoding sees. Per camera pixel: each projector's ground-truth (u, v) from a
//! homography, whether it lights the pixel, a vignetted gain, an albedo with dark disks and
//! an ambient level. Frames follow the imaging chain of docs/design.md §9: irradiance with the
//! projector response applied to each pattern inside the sum → Gaussian PSF → read + shot
//! noise → quantisation, all seeded.

mod disturb;

pub use disturb::Disturbance;

use hexcal_core::pattern::{pattern_harmonic, Direction, ProjectorSetup, Sequence};
use nalgebra::{Matrix3, SMatrix, SVector, Vector3};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;
use std::f64::consts::TAU;

/// Camera-side imaging conditions (defaults: docs/design.md §9 "default imaging conditions").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Imaging {
    /// Read noise σ (DN).
    pub read_noise: f64,
    /// Shot-noise variance per DN of signal (DN).
    pub shot_gain: f64,
    /// Gaussian PSF σ (camera px).
    pub psf_sigma: f64,
    /// Ambient light on white (DN).
    pub ambient: f64,
    /// Level that all projectors at full white plus ambient reach on white (DN).
    pub white: f64,
    /// Albedo of the dark parts.
    pub dark_albedo: f64,
}

impl Default for Imaging {
    fn default() -> Self {
        Imaging {
            read_noise: 2.0,
            shot_gain: 0.1,
            psf_sigma: 0.8,
            ambient: 40.0,
            white: 235.0,
            dark_albedo: 0.1,
        }
    }
}

/// One projector of the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneProjector {
    /// Camera pixel → projector pixel.
    pub homography: Matrix3<f64>,
    /// Full-white irradiance on white at the image centre (DN).
    pub gain: f64,
}

/// A synthetic scene seen by one 8-bit camera.
#[derive(Clone, Debug, PartialEq)]
pub struct FringeScene {
    /// Camera width (px).
    pub width: u32,
    /// Camera height (px).
    pub height: u32,
    /// The projectors, in sequence order.
    pub projectors: Vec<SceneProjector>,
    /// Imaging conditions.
    pub imaging: Imaging,
    /// Noise seed.
    pub seed: u64,
}

/// Homography mapping the unit square's corners (0,0), (1,0), (1,1), (0,1) to `quad`.
fn square_to_quad(quad: [[f64; 2]; 4]) -> Matrix3<f64> {
    let src = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    let mut a = SMatrix::<f64, 8, 8>::zeros();
    let mut b = SVector::<f64, 8>::zeros();
    for i in 0..4 {
        let ([x, y], [u, v]) = (src[i], quad[i]);
        a.set_row(2 * i, &[x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y].into());
        a.set_row(
            2 * i + 1,
            &[0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y].into(),
        );
        b[2 * i] = u;
        b[2 * i + 1] = v;
    }
    let h = a.lu().solve(&b).expect("four corners in general position");
    Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0)
}

impl FringeScene {
    /// The standard test scene: P projectors share the light above ambient equally. Each
    /// sees the camera's view as a slightly different perspective quadrilateral of about
    /// 0.9 projector px per camera px (at most 90 % of its screen), so fringes of 1080/25
    /// projector px are ≥ 48 camera px wide as in a real rig. Projector 0… P−2 see it centred in their screen; the last
    /// one's screen corner lies inside the view (a quarter of the width and height are
    /// outside its screen), so it lights only part of the scene.
    pub fn standard(width: u32, height: u32, setups: &[ProjectorSetup], seed: u64) -> FringeScene {
        let imaging = Imaging::default();
        let np = setups.len();
        let share = (imaging.white - imaging.ambient) / np as f64;
        let (cw, ch) = (f64::from(width), f64::from(height));
        let projectors = setups
            .iter()
            .enumerate()
            .map(|(p, s)| {
                let (w, h) = (f64::from(s.width), f64::from(s.height));
                let scale = 0.9f64.min(0.9 * w / cw).min(0.9 * h / ch);
                let (sx, sy) = (scale * cw, scale * ch);
                let (ox, oy) = if p + 1 == np {
                    (-0.25 * sx, -0.25 * sy)
                } else {
                    (0.5 * (w - sx), 0.5 * (h - sy))
                };
                let j = 0.01 * p as f64;
                let corners = [
                    [0.02 + j, 0.03],
                    [0.97, 0.02 + j],
                    [0.98 - j, 0.97],
                    [0.03, 0.98 - j],
                ];
                let to_proj = square_to_quad(corners.map(|[a, b]| [ox + a * sx, oy + b * sy]));
                let from_cam = Matrix3::new(
                    1.0 / cw,
                    0.0,
                    0.5 / cw,
                    0.0,
                    1.0 / ch,
                    0.5 / ch,
                    0.0,
                    0.0,
                    1.0,
                );
                SceneProjector {
                    homography: to_proj * from_cam,
                    gain: share,
                }
            })
            .collect();
        FringeScene {
            width,
            height,
            projectors,
            imaging,
            seed,
        }
    }

    fn albedo(&self, x: f64, y: f64) -> f64 {
        // Dark disks of radius 4 % of the short side on a grid of 1/5 of the width.
        let s = f64::from(self.width) / 5.0;
        let r = 0.04 * f64::from(self.width.min(self.height));
        let (dx, dy) = (
            x - (x / s).floor() * s - 0.5 * s,
            y - (y / s).floor() * s - 0.5 * s,
        );
        if dx * dx + dy * dy < r * r {
            self.imaging.dark_albedo
        } else {
            1.0
        }
    }

    fn vignette(&self, x: f64, y: f64) -> f64 {
        let (w, h) = (f64::from(self.width), f64::from(self.height));
        let (nx, ny) = (2.0 * x / w - 1.0, 2.0 * y / h - 1.0);
        1.0 - 0.15 * (nx * nx + ny * ny)
    }
}

/// Ground truth of a scene under a sequence (per camera pixel, row-major).
#[derive(Clone, Debug)]
pub struct Truth {
    /// Per projector: projector column u at each pixel centre.
    pub u: Vec<Vec<f64>>,
    /// Per projector: projector row v.
    pub v: Vec<Vec<f64>>,
    /// Per projector: noise-free modulation B_p after the PSF, which lowers the fringe
    /// contrast (RMS over the groups, as the decoder reports it) (DN).
    pub modulation: Vec<Vec<f64>>,
    /// Per projector: its full-white irradiance alone after the PSF (DN).
    pub full_white: Vec<Vec<f64>>,
    /// Noise-free ambient image after the PSF (DN).
    pub ambient: Vec<f64>,
    /// Noise-free mean level A (DN).
    pub mean: Vec<f64>,
    /// Per-frame noise σ_I at the mean level, quantisation included (DN).
    pub sigma_i: Vec<f64>,
    /// Pixels whose PSF neighbourhood sees no albedo or coverage edge (there the decoded
    /// coordinate is exactly the pixel centre's; at edges it is the lit part's centroid).
    pub interior: Vec<bool>,
}

impl Truth {
    /// The truth-based standard deviations (σ_u, σ_v) of a decoded projector coordinate,
    /// per camera pixel index, for projector `p` (docs/design.md §6): σ_φ = √(2/N)·σ_I/B,
    /// σ_u = W·σ_φ/(2π·√Σn²), σ_v likewise with H and the row counts.
    pub fn sigma_uv(&self, seq: &Sequence, p: usize) -> impl Fn(usize) -> (f64, f64) + '_ {
        let norm = |d| {
            seq.counts(d)
                .iter()
                .map(|&c| f64::from(c * c))
                .sum::<f64>()
                .sqrt()
        };
        let code = seq.projectors()[p];
        let n = f64::from(seq.steps());
        let ku = f64::from(code.width) / (TAU * norm(Direction::Columns));
        let kv = f64::from(code.height) / (TAU * norm(Direction::Rows));
        move |i| {
            let sphi = (2.0 / n).sqrt() * self.sigma_i[i] / self.modulation[p][i];
            (ku * sphi, kv * sphi)
        }
    }
}

/// Renders the frames of one camera's stack.
pub struct Renderer<'a> {
    scene: &'a FringeScene,
    seq: &'a Sequence,
    /// Per projector: albedo·gain·vignette·coverage at each pixel (DN at full white).
    weight: Vec<Vec<f32>>,
    /// Per projector: (u, v).
    coords: Vec<Vec<[f64; 2]>>,
    albedo: Vec<f32>,
    light: Vec<[f32; 256]>,
    /// The group whose (cos φ, sin φ) are cached.
    group: Option<usize>,
    trig: Vec<Vec<[f32; 2]>>,
    kernel: Vec<f32>,
}

fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    let r = (3.0 * sigma).ceil() as i32;
    let k: Vec<f64> = (-r..=r)
        .map(|i| (-0.5 * f64::from(i * i) / (sigma * sigma)).exp())
        .collect();
    let s: f64 = k.iter().sum();
    k.iter().map(|v| (v / s) as f32).collect()
}

/// Separable blur with clamped borders, rows in parallel.
fn blur(img: &mut [f32], w: usize, kernel: &[f32]) {
    let r = kernel.len() / 2;
    let h = img.len() / w;
    let mut tmp = vec![0f32; img.len()];
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
        let row = &img[y * w..(y + 1) * w];
        for (x, o) in out.iter_mut().enumerate() {
            *o = kernel
                .iter()
                .enumerate()
                .map(|(i, k)| k * row[(x + i).saturating_sub(r).min(w - 1)])
                .sum();
        }
    });
    img.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
        for (x, o) in out.iter_mut().enumerate() {
            *o = kernel
                .iter()
                .enumerate()
                .map(|(i, k)| k * tmp[(y + i).saturating_sub(r).min(h - 1) * w + x])
                .sum();
        }
    });
}

impl<'a> Renderer<'a> {
    /// Prepare the per-pixel maps of `scene` under `seq` (projectors in the same order).
    pub fn new(scene: &'a FringeScene, seq: &'a Sequence) -> Renderer<'a> {
        let (w, h) = (scene.width as usize, scene.height as usize);
        let codes = seq.projectors();
        let mut albedo = vec![0f32; w * h];
        let mut weight = vec![vec![0f32; w * h]; codes.len()];
        let mut coords = vec![vec![[0f64; 2]; w * h]; codes.len()];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let (xf, yf) = (x as f64, y as f64);
                let a = scene.albedo(xf, yf);
                albedo[i] = a as f32;
                for (p, sp) in scene.projectors.iter().enumerate() {
                    let q = sp.homography * Vector3::new(xf, yf, 1.0);
                    let (u, v) = (q.x / q.z, q.y / q.z);
                    coords[p][i] = [u, v];
                    let code = &codes[p];
                    let lit = (-0.5..=f64::from(code.width) - 0.5).contains(&u)
                        && (-0.5..=f64::from(code.height) - 0.5).contains(&v);
                    if lit {
                        weight[p][i] = (a * sp.gain * scene.vignette(xf, yf)) as f32;
                    }
                }
            }
        }
        Renderer {
            scene,
            seq,
            weight,
            coords,
            albedo,
            light: (0..codes.len())
                .map(|p| seq.light_table(p).map(|l| l as f32))
                .collect(),
            group: None,
            trig: Vec::new(),
            kernel: gaussian_kernel(scene.imaging.psf_sigma),
        }
    }

    /// Frame k of the stack, 8 bit.
    pub fn frame(&mut self, k: usize) -> image::GrayImage {
        let code = self.seq.frame(k).expect("frame within the sequence");
        let (w, h) = (self.scene.width as usize, self.scene.height as usize);
        if self.group != Some(code.group) {
            // φ_p = 2π·n·(u + ½)/W at every pixel for this group.
            self.trig = self
                .coords
                .iter()
                .zip(self.seq.projectors())
                .map(|(coords, pc)| {
                    let size = f64::from(match code.direction {
                        Direction::Columns => pc.width,
                        Direction::Rows => pc.height,
                    });
                    let axis = usize::from(code.direction == Direction::Rows);
                    coords
                        .par_iter()
                        .map(|c| {
                            let phi = TAU * f64::from(code.count) * (c[axis] + 0.5) / size;
                            [phi.cos() as f32, phi.sin() as f32]
                        })
                        .collect()
                })
                .collect();
            self.group = Some(code.group);
        }
        let n = self.seq.steps();
        let shifts: Vec<[f32; 2]> = self
            .seq
            .projectors()
            .iter()
            .map(|pc| {
                let t = TAU * f64::from(pc.frequency * code.step % n) / f64::from(n);
                [t.cos() as f32, t.sin() as f32]
            })
            .collect();
        let ambient = self.scene.imaging.ambient as f32;
        let mut irr = vec![0f32; w * h];
        irr.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, e) in row.iter_mut().enumerate() {
                let i = y * w + x;
                let mut s = self.albedo[i] * ambient;
                for (p, &[ct, st]) in shifts.iter().enumerate() {
                    let wgt = self.weight[p][i];
                    if wgt > 0.0 {
                        // c = ½(1 + cos(φ − θ)), quantised to the 8-bit level sent.
                        let [cp, sp] = self.trig[p][i];
                        let c = 0.5 * (1.0 + cp * ct + sp * st);
                        let level = (255.0 * c).round().clamp(0.0, 255.0) as usize;
                        s += wgt * self.light[p][level];
                    }
                }
                *e = s;
            }
        });
        self.expose(irr, k)
    }

    /// The sensor's 8-bit frame k of the irradiance `irr` (DN, row-major): PSF, read and
    /// shot noise seeded by the frame, quantisation.
    fn expose(&self, mut irr: Vec<f32>, k: usize) -> image::GrayImage {
        let (w, h) = (self.scene.width as usize, self.scene.height as usize);
        blur(&mut irr, w, &self.kernel);
        let im = &self.scene.imaging;
        let (read2, shot) = ((im.read_noise * im.read_noise) as f32, im.shot_gain as f32);
        let seed = self.scene.seed;
        let mut out = vec![0u8; w * h];
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            let mut rng = rand::rngs::SmallRng::seed_from_u64(
                seed ^ ((k as u64) << 32) ^ (y as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
            );
            for (x, o) in row.iter_mut().enumerate() {
                let e = irr[y * w + x];
                let z: f32 = StandardNormal.sample(&mut rng);
                let v = e + z * (read2 + shot * e.max(0.0)).sqrt();
                *o = v.round().clamp(0.0, 255.0) as u8;
            }
        });
        image::GrayImage::from_raw(w as u32, h as u32, out).expect("w × h pixels")
    }

    /// The scene's ground truth.
    pub fn truth(&self) -> Truth {
        let w = self.scene.width as usize;
        let im = &self.scene.imaging;
        let codes = self.seq.projectors();
        let blurred = |v: &[f32]| {
            let mut b = v.to_vec();
            blur(&mut b, w, &self.kernel);
            b
        };
        let mut mean: Vec<f64> = blurred(&self.albedo)
            .iter()
            .map(|&a| f64::from(a) * im.ambient)
            .collect();
        let ambient = mean.clone();
        let mut interior: Vec<bool> = {
            let b = blurred(&self.albedo);
            b.iter()
                .zip(&self.albedo)
                .map(|(x, y)| (x - y).abs() < 1e-5)
                .collect()
        };
        let mut modulation = Vec::new();
        let mut full_white = Vec::new();
        let groups: Vec<_> = (0..self.seq.groups())
            .map(|g| {
                self.seq
                    .frame(g * self.seq.steps() as usize)
                    .expect("group start")
            })
            .collect();
        for (p, wgt) in self.weight.iter().enumerate() {
            let gamma = codes[p].response.effective_gamma();
            let (a0, a1) = (pattern_harmonic(gamma, 0), pattern_harmonic(gamma, 1));
            let b = blurred(wgt);
            for (m, &v) in mean.iter_mut().zip(&b) {
                *m += a0 * f64::from(v);
            }
            full_white.push(b.iter().map(|&v| f64::from(v)).collect());
            // Per group: a_1·|PSF ∗ (weight·e^{iφ})|, then the RMS over groups.
            let mut sq = vec![0f64; wgt.len()];
            for fc in &groups {
                let size = f64::from(match fc.direction {
                    Direction::Columns => codes[p].width,
                    Direction::Rows => codes[p].height,
                });
                let axis = usize::from(fc.direction == Direction::Rows);
                let phase = |c: &[f64; 2]| TAU * f64::from(fc.count) * (c[axis] + 0.5) / size;
                let re: Vec<f32> = wgt
                    .iter()
                    .zip(&self.coords[p])
                    .map(|(&w, c)| w * phase(c).cos() as f32)
                    .collect();
                let im: Vec<f32> = wgt
                    .iter()
                    .zip(&self.coords[p])
                    .map(|(&w, c)| w * phase(c).sin() as f32)
                    .collect();
                for ((s2, r), i) in sq.iter_mut().zip(blurred(&re)).zip(blurred(&im)) {
                    *s2 += a1 * a1 * f64::from(r * r + i * i);
                }
            }
            let ng = groups.len() as f64;
            modulation.push(sq.iter().map(|s2| (s2 / ng).sqrt()).collect());
            let lit: Vec<f32> = wgt.iter().map(|&v| f32::from(u8::from(v > 0.0))).collect();
            for ((int, x), y) in interior.iter_mut().zip(blurred(&lit)).zip(&lit) {
                *int &= (x - y).abs() < 1e-5;
            }
        }
        // σ_I² = read² + shot·A + 1/12 (8-bit quantisation).
        let sigma_i = mean
            .iter()
            .map(|&a| (im.read_noise * im.read_noise + im.shot_gain * a + 1.0 / 12.0).sqrt())
            .collect();
        Truth {
            u: self
                .coords
                .iter()
                .map(|c| c.iter().map(|q| q[0]).collect())
                .collect(),
            v: self
                .coords
                .iter()
                .map(|c| c.iter().map(|q| q[1]).collect())
                .collect(),
            modulation,
            full_white,
            ambient,
            mean,
            sigma_i,
            interior,
        }
    }
}
