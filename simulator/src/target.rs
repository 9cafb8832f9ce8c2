//! What the camera looks at: a rigid target made of one-sided planar faces, each with its own
//! texture, in front of a smooth background.

use nalgebra::{Isometry3, Point2, Vector2};

/// The nearest texture edge seen from a point of a face.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Edge {
    /// Distance from the point to the edge (face units, ≥ 0).
    pub distance: f64,
    /// Unit direction (face frame) from the point towards the edge, normal to it.
    pub toward: Vector2<f64>,
    /// Albedo just beyond the edge.
    pub beyond: f32,
}

/// The texture at one point of a face.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Texel {
    /// Albedo at the point (1 = the reference white).
    pub albedo: f32,
    /// The nearest edge between two albedos inside the face, if any is near (a texture may
    /// leave out edges farther than its own feature size).
    pub edge: Option<Edge>,
    /// Distance to the face's outline (face units), beyond which something else is seen.
    pub outline: f64,
}

/// A piecewise-constant texture on a face, in the face's own 2D frame (x right, y up as seen
/// looking at the face).
pub trait Texture: Send + Sync {
    /// The texel at a face point; `None` outside the face.
    fn sample(&self, p: Point2<f64>) -> Option<Texel>;
}

/// A uniform rectangle centred on the face origin.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UniformRect {
    /// Half extents along x and y (face units).
    pub half: Vector2<f64>,
    /// Albedo.
    pub albedo: f32,
}

impl Texture for UniformRect {
    fn sample(&self, p: Point2<f64>) -> Option<Texel> {
        let outline = (self.half.x - p.x.abs()).min(self.half.y - p.y.abs());
        (outline >= 0.0).then_some(Texel {
            albedo: self.albedo,
            edge: None,
            outline,
        })
    }
}

/// One planar face: visible only from its +z side.
pub struct Face {
    /// `T_target_face`: maps face points (x, y, 0) into the target frame.
    pub pose: Isometry3<f64>,
    /// What is printed on it.
    pub texture: Box<dyn Texture>,
}

/// A rigid target: faces in the target frame. The renderer sees, per ray, the nearest face
/// that is hit from its front within its outline; faces are numbered in this order.
#[derive(Default)]
pub struct Target {
    /// The faces (at most 255).
    pub faces: Vec<Face>,
}

/// What is seen where no face is hit: a smooth (edge-free) albedo over the image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Background {
    /// Mean albedo.
    pub albedo: f32,
    /// Relative amplitude of the variation (0 = uniform; the albedo stays within
    /// albedo·(1 ± variation)).
    pub variation: f32,
    /// Feature size of the variation (px).
    pub scale_px: f64,
    /// Seed of the variation.
    pub seed: u64,
}

impl Background {
    /// A uniform background.
    pub fn uniform(albedo: f32) -> Background {
        Background {
            albedo,
            variation: 0.0,
            scale_px: 1.0,
            seed: 0,
        }
    }

    /// Albedo at a sub-pixel position: smooth value noise (C¹ cubic blend of seeded lattice
    /// values), so no pixel of the background needs supersampling.
    pub fn albedo_at(&self, p: Point2<f64>) -> f32 {
        self.blend(p, |i, j| lattice_value(self.seed, i, j))
    }

    /// [`Background::albedo_at`] with the lattice values taken from `val`.
    fn blend(&self, p: Point2<f64>, val: impl Fn(i64, i64) -> f64) -> f32 {
        if self.variation == 0.0 {
            return self.albedo;
        }
        let (u, v) = (p.x / self.scale_px, p.y / self.scale_px);
        // Inline floor (f64::floor is a libm call on baseline x86-64).
        let floor = |t: f64| {
            let k = t as i64 as f64;
            if k > t {
                k - 1.0
            } else {
                k
            }
        };
        let (i, j) = (floor(u), floor(v));
        let (fu, fv) = (u - i, v - j);
        let s = |t: f64| t * t * (3.0 - 2.0 * t);
        let (su, sv) = (s(fu), s(fv));
        let (i, j) = (i as i64, j as i64);
        let top = val(i, j) * (1.0 - su) + val(i + 1, j) * su;
        let bottom = val(i, j + 1) * (1.0 - su) + val(i + 1, j + 1) * su;
        let n = top * (1.0 - sv) + bottom * sv; // in [−1, 1]
        self.albedo * (1.0 + self.variation * n as f32)
    }

    /// The lattice values covering an image, for fast lookups.
    pub(crate) fn table(&self, width: u32, height: u32) -> BackgroundTable {
        let nx = (f64::from(width) / self.scale_px).ceil() as usize + 3;
        let ny = (f64::from(height) / self.scale_px).ceil() as usize + 3;
        let values = (0..nx * ny)
            .map(|k| lattice_value(self.seed, (k % nx) as i64 - 1, (k / nx) as i64 - 1))
            .collect();
        BackgroundTable {
            background: *self,
            nx,
            ny,
            values,
        }
    }
}

/// A [`Background`] with its lattice values over an image precomputed (same values).
pub(crate) struct BackgroundTable {
    background: Background,
    nx: usize,
    ny: usize,
    /// Value of lattice node (i, j) at ((j + 1)·nx + i + 1).
    values: Vec<f64>,
}

impl BackgroundTable {
    /// As [`Background::albedo_at`].
    pub(crate) fn albedo_at(&self, p: Point2<f64>) -> f32 {
        let b = &self.background;
        b.blend(p, |i, j| {
            let (a, c) = (i + 1, j + 1);
            if a >= 0 && c >= 0 && (a as usize) < self.nx && (c as usize) < self.ny {
                self.values[c as usize * self.nx + a as usize]
            } else {
                lattice_value(b.seed, i, j)
            }
        })
    }
}

/// A seeded pseudo-random value in [−1, 1] per lattice node (SplitMix64 of the coordinates).
fn lattice_value(seed: u64, i: i64, j: i64) -> f64 {
    let h = splitmix64(seed ^ splitmix64(i as u64 ^ splitmix64(j as u64)));
    (h >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
}

/// SplitMix64 finaliser: a well-mixed 64-bit hash.
pub(crate) fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}
