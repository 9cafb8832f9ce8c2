//! The geometry pass: once per camera and target pose, trace every pixel to the target and
//! integrate the texture over the pixel's footprint. Frames are then shaded from this buffer
//! without tracing again (docs/design.md §9).
//!
//! Pixels are integrated in three ways:
//! - **uniform**: no texture edge or outline within the footprint — the texel at the centre;
//! - **edge**: a texture edge within reach — `edge_samples²` sub-pixels, each integrated
//!   exactly over its square for the nearest edge taken as a straight line (the edge's
//!   curvature across a sub-pixel of ¼ px leaves the line by ≤ (¼)²/(8r) px: 8·10⁻⁴ px at a
//!   radius of curvature r = 10 px, 0.004 px at r = 2 px);
//! - **outline**: a face outline within reach, or a neighbour seeing another face or the
//!   background — `outline_samples²` point samples of the nearest face or the background.

use crate::lens::{ImageSize, RayGrid};
use crate::target::{Background, BackgroundTable, Target, Texel, Texture};
use nalgebra::{Isometry3, Matrix3, Point2, Point3, Vector2, Vector3};
use rayon::prelude::*;

/// Face index of pixels that see the background.
pub const NO_FACE: u8 = u8::MAX;

/// Supersampling settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RenderOptions {
    /// Sub-pixels per axis in pixels crossed by a texture edge (each integrated analytically).
    pub edge_samples: u32,
    /// Point samples per axis in pixels crossed by a face outline.
    pub outline_samples: u32,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            edge_samples: 4,
            outline_samples: 8,
        }
    }
}

/// Per-pixel result of the geometry pass, row-major.
pub struct Geometry {
    /// Image size.
    pub size: ImageSize,
    /// Mean albedo over each pixel's square (texture and background alike).
    pub albedo: Vec<f32>,
    /// Face seen through each pixel centre, or [`NO_FACE`].
    pub face: Vec<u8>,
    /// Target-frame point seen through each pixel centre (NaN where no face is seen).
    pub point: Vec<[f32; 3]>,
    /// Number of pixels integrated as edge pixels.
    pub edge_pixels: usize,
    /// Number of pixels integrated as outline pixels.
    pub outline_pixels: usize,
}

impl Geometry {
    /// Irradiance image (DN) under a uniform illumination that makes albedo 1 read `white`.
    pub fn irradiance(&self, white: f32) -> Vec<f32> {
        self.albedo.par_iter().map(|&a| a * white).collect()
    }
}

/// A face expressed in the camera frame.
struct CamFace<'a> {
    /// `R_face_cam` (transposed face rotation).
    rot_t: Matrix3<f64>,
    origin: Vector3<f64>,
    normal: Vector3<f64>,
    n_dot_o: f64,
    texture: &'a dyn Texture,
}

/// A ray's hit on a face.
struct Hit {
    face: u8,
    /// Ray parameter: the camera-frame point is λ·dir.
    lambda: f64,
    texel: Texel,
}

/// Pixel classes of the first pass.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Class {
    Uniform,
    Edge,
    Outline,
}

/// Traces rays of one camera against one posed target.
struct Tracer<'a> {
    rays: &'a RayGrid<'a>,
    faces: Vec<CamFace<'a>>,
    background: BackgroundTable,
    opts: RenderOptions,
}

impl<'a> Tracer<'a> {
    /// Nearest front-facing face hit within its outline.
    fn hit(&self, dir: &Vector3<f64>) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        for (k, f) in self.faces.iter().enumerate() {
            let denom = f.normal.dot(dir);
            if denom >= 0.0 {
                continue;
            }
            let lambda = f.n_dot_o / denom;
            if lambda <= 0.0 || best.as_ref().is_some_and(|b| b.lambda <= lambda) {
                continue;
            }
            let u = f.rot_t * (dir * lambda - f.origin);
            if let Some(texel) = f.texture.sample(Point2::new(u.x, u.y)) {
                best = Some(Hit {
                    face: k as u8,
                    lambda,
                    texel,
                });
            }
        }
        best
    }

    /// Point on face `k` along `dir` (no outline check).
    fn face_point(&self, k: u8, dir: &Vector3<f64>) -> Option<Point2<f64>> {
        let f = &self.faces[k as usize];
        let denom = f.normal.dot(dir);
        (denom < 0.0).then(|| {
            let u = f.rot_t * (dir * (f.n_dot_o / denom) - f.origin);
            Point2::new(u.x, u.y)
        })
    }

    /// Outline integration of pixel (x, y): n×n point samples of the nearest face or the
    /// background.
    fn outline_albedo(&self, x: usize, y: usize, rays: &mut Vec<Option<Vector3<f64>>>) -> f32 {
        let n = self.opts.outline_samples;
        let h = 1.0 / f64::from(n);
        self.rays.pixel_rays(x, y, n, rays);
        let mut sum = 0.0f64;
        for (k, r) in rays.iter().enumerate() {
            let a = match r.and_then(|d| self.hit(&d)) {
                Some(hit) => hit.texel.albedo,
                None => {
                    let (i, j) = ((k as u32 % n) as f64, (k as u32 / n) as f64);
                    self.background.albedo_at(Point2::new(
                        x as f64 + (i + 0.5) * h - 0.5,
                        y as f64 + (j + 0.5) * h - 0.5,
                    ))
                }
            };
            sum += f64::from(a);
        }
        (sum * h * h) as f32
    }

    /// Edge integration over face `k`: n×n sub-pixels, each integrated exactly for its
    /// nearest edge taken as straight. `jac` = [∂u/∂x, ∂u/∂y] of the face point per pixel.
    /// `None` if a sub-pixel leaves the face (the caller then uses outline integration).
    fn edge_albedo(
        &self,
        (x, y): (usize, usize),
        k: u8,
        jac: [Vector2<f64>; 2],
        rays: &mut Vec<Option<Vector3<f64>>>,
    ) -> Option<f32> {
        let n = self.opts.edge_samples;
        let h = 1.0 / f64::from(n);
        let texture = self.faces[k as usize].texture;
        self.rays.pixel_rays(x, y, n, rays);
        let mut sum = 0.0f64;
        for r in rays.iter() {
            {
                let u = self.face_point(k, &(*r)?)?;
                let t = texture.sample(u)?;
                let mut a = f64::from(t.albedo);
                if let Some(e) = t.edge {
                    // Distance to the edge falls by g·δ for an image step δ: g = Jᵀ·toward.
                    let g = Vector2::new(jac[0].dot(&e.toward), jac[1].dot(&e.toward));
                    let gn = g.norm();
                    if gn > 0.0 {
                        let frac = beyond_fraction(
                            e.distance / gn,
                            g.x.abs() / gn * h,
                            g.y.abs() / gn * h,
                        );
                        a += frac * (f64::from(e.beyond) - a);
                    }
                }
                sum += a;
            }
        }
        Some((sum * h * h) as f32)
    }
}

/// Fraction of a square beyond a straight edge: the square's centre lies at distance `s ≥ 0`
/// from the edge, and `wa`, `wb` are the square's extents along the edge normal contributed
/// by its two sides (side·|cos|, side·|sin|). The normal coordinate of a uniform point of the
/// square is the sum of two uniforms of widths wa and wb, whose CDF is piecewise quadratic.
fn beyond_fraction(s: f64, wa: f64, wb: f64) -> f64 {
    let (a, b) = if wa >= wb { (wa, wb) } else { (wb, wa) };
    if s >= 0.5 * (a + b) {
        0.0
    } else if s > 0.5 * (a - b) {
        let d = 0.5 * (a + b) - s;
        d * d / (2.0 * a * b)
    } else {
        (0.5 * a - s) / a
    }
}

/// Render the geometry of one view: `pose` is `T_cam_target`.
pub fn render_geometry(
    rays: &RayGrid,
    target: &Target,
    pose: &Isometry3<f64>,
    background: &Background,
    opts: RenderOptions,
) -> Geometry {
    assert!(
        target.faces.len() < usize::from(NO_FACE),
        "at most 254 faces"
    );
    let faces = target
        .faces
        .iter()
        .map(|f| {
            let cam_face = pose * f.pose;
            let rot = cam_face.rotation.to_rotation_matrix().into_inner();
            let origin = cam_face.translation.vector;
            let normal = rot.column(2).into_owned();
            let n_dot_o = normal.dot(&origin);
            CamFace {
                rot_t: rot.transpose(),
                origin,
                // A face is seen only from its front (the camera centre on its +z side,
                // n·o < 0); a zero normal makes every ray miss one turned away, keeping the
                // face indices stable.
                normal: if n_dot_o < 0.0 {
                    normal
                } else {
                    Vector3::zeros()
                },
                n_dot_o,
                texture: f.texture.as_ref(),
            }
        })
        .collect();
    let tracer = Tracer {
        rays,
        faces,
        background: background.table(rays.size().width, rays.size().height),
        opts,
    };
    let size = rays.size();
    let (w, h) = (size.width as usize, size.height as usize);
    let target_from_cam = pose.inverse();
    let mut albedo = vec![0.0f32; w * h];
    let mut face = vec![NO_FACE; w * h];
    let mut point = vec![[f32::NAN; 3]; w * h];
    let mut class = vec![Class::Uniform; w * h];

    // Pass 1: pixel centres.
    albedo
        .par_chunks_mut(w)
        .zip(face.par_chunks_mut(w))
        .zip(point.par_chunks_mut(w))
        .zip(class.par_chunks_mut(w))
        .enumerate()
        .for_each_init(Vec::new, |jets, (y, (((alb, fc), pt), cl))| {
            rays.row_jets(y, jets);
            for x in 0..w {
                let p = Point2::new(x as f64, y as f64);
                let Some(jet) = jets[x] else {
                    alb[x] = tracer.background.albedo_at(p);
                    continue;
                };
                let Some(hit) = tracer.hit(&jet.dir) else {
                    alb[x] = tracer.background.albedo_at(p);
                    continue;
                };
                let f = &tracer.faces[hit.face as usize];
                let jac = face_jacobian(f, &jet.dir, hit.lambda, &jet.dx, &jet.dy);
                // Farthest face distance of the pixel square's corners (|J·(±½, ±½)| ≤
                // ‖J‖_F/√2), with 6 % to spare for the map's curvature.
                let reach = 0.75 * (jac[0].norm_squared() + jac[1].norm_squared()).sqrt();
                alb[x] = hit.texel.albedo;
                fc[x] = hit.face;
                let xt = target_from_cam * Point3::from(jet.dir * hit.lambda);
                pt[x] = [xt.x as f32, xt.y as f32, xt.z as f32];
                cl[x] = if hit.texel.outline < reach {
                    Class::Outline
                } else if hit.texel.edge.is_some_and(|e| e.distance < reach) {
                    Class::Edge
                } else {
                    Class::Uniform
                };
            }
        });

    // Pass 2: supersample edge and outline pixels.
    let counts: Vec<(usize, usize)> = albedo
        .par_chunks_mut(w)
        .enumerate()
        .map_init(Vec::new, |sub, (y, alb)| {
            let (mut edges, mut outlines) = (0, 0);
            for (x, out) in alb.iter_mut().enumerate() {
                let k = y * w + x;
                let own = face[k];
                let (x0, x1) = (x.saturating_sub(1), (x + 1).min(w - 1));
                let mut differs = false;
                for yy in y.saturating_sub(1)..(y + 2).min(h) {
                    for &f in &face[yy * w + x0..=yy * w + x1] {
                        differs |= f != own;
                    }
                }
                let p = Point2::new(x as f64, y as f64);
                let edge = if class[k] == Class::Edge && !differs {
                    rays.jet(p).and_then(|jet| {
                        let f = &tracer.faces[own as usize];
                        let denom = f.normal.dot(&jet.dir);
                        let jac = face_jacobian(f, &jet.dir, f.n_dot_o / denom, &jet.dx, &jet.dy);
                        tracer.edge_albedo((x, y), own, jac, sub)
                    })
                } else {
                    None
                };
                if let Some(a) = edge {
                    *out = a;
                    edges += 1;
                } else if differs || class[k] != Class::Uniform {
                    *out = tracer.outline_albedo(x, y, sub);
                    outlines += 1;
                }
            }
            (edges, outlines)
        })
        .collect();
    let (edge_pixels, outline_pixels) =
        counts.iter().fold((0, 0), |(a, b), &(e, o)| (a + e, b + o));
    Geometry {
        size,
        albedo,
        face,
        point,
        edge_pixels,
        outline_pixels,
    }
}

/// ∂u/∂x and ∂u/∂y of the face point u hit by the ray `dir` (parameter λ): with the plane
/// n·X = n·o, X = λ·dir, dX = λ·(I − dir·nᵀ/(n·dir))·d(dir), u = R_faceᵀ·(X − o).
fn face_jacobian(
    f: &CamFace,
    dir: &Vector3<f64>,
    lambda: f64,
    ddx: &Vector3<f64>,
    ddy: &Vector3<f64>,
) -> [Vector2<f64>; 2] {
    let nd = f.normal.dot(dir);
    let col = |dd: &Vector3<f64>| {
        let dx = (dd - dir * (f.normal.dot(dd) / nd)) * lambda;
        let du = f.rot_t * dx;
        Vector2::new(du.x, du.y)
    };
    [col(ddx), col(ddy)]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lens::tests::test_lens;
    use crate::target::{Edge, Face, UniformRect};
    use nalgebra::{Translation3, UnitQuaternion};

    /// A white disk of radius `r` on black, inside a square outline.
    struct Disk {
        r: f64,
        half: f64,
    }

    impl Texture for Disk {
        fn sample(&self, p: Point2<f64>) -> Option<Texel> {
            let outline = self.half - p.x.abs().max(p.y.abs());
            let rho = p.coords.norm();
            let inside = rho <= self.r;
            let out = if rho > 0.0 {
                p.coords / rho
            } else {
                Vector2::x()
            };
            (outline >= 0.0).then_some(Texel {
                albedo: if inside { 1.0 } else { 0.1 },
                edge: Some(Edge {
                    distance: (rho - self.r).abs(),
                    toward: if inside { out } else { -out },
                    beyond: if inside { 0.1 } else { 1.0 },
                }),
                outline,
            })
        }
    }

    #[test]
    fn beyond_fraction_matches_brute_force() {
        for &(s, ang) in &[
            (0.0, 0.3),
            (0.1, 0.0),
            (0.2, 0.7),
            (0.05, 1.2),
            (0.4, 0.785),
        ] {
            let (sn, cs) = f64::sin_cos(ang);
            let n = 400;
            let mut count = 0;
            for j in 0..n {
                for i in 0..n {
                    let (x, y) = (
                        (i as f64 + 0.5) / n as f64 - 0.5,
                        (j as f64 + 0.5) / n as f64 - 0.5,
                    );
                    count += usize::from(x * cs + y * sn > s);
                }
            }
            let brute = count as f64 / (n * n) as f64;
            let exact = beyond_fraction(s, cs.abs(), sn.abs());
            assert!(
                (brute - exact).abs() < 4.0 / n as f64,
                "s {s} ang {ang}: {brute} vs {exact}"
            );
        }
    }

    /// A frontal disk through a pinhole: the integrated albedo has the image disk's area and
    /// centroid.
    #[test]
    fn disk_coverage_has_the_right_area_and_centre() {
        let mut lens = test_lens();
        lens.k1 = 0.0;
        lens.k2 = 0.0;
        let rays = RayGrid::new(&lens);
        let (r, z) = (12.0, 300.0); // 12 mm at 300 mm with f = 300 px: 12 px radius
        let target = Target {
            faces: vec![
                Face {
                    pose: Isometry3::identity(),
                    texture: Box::new(Disk { r, half: 60.0 }),
                },
                Face {
                    // A wall behind the disk, turned away from the camera: never seen.
                    pose: Isometry3::from_parts(
                        Translation3::new(0.0, 0.0, -50.0),
                        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI),
                    ),
                    texture: Box::new(UniformRect {
                        half: Vector2::new(1e3, 1e3),
                        albedo: 0.5,
                    }),
                },
            ],
        };
        // Camera looking at the face's front: the face's +z points at the camera.
        let pose = Isometry3::from_parts(
            Translation3::new(2.37, -1.61, z),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        );
        let c = lens.project((pose * Point3::origin()).coords);
        let rpx = r * lens.f / z;
        let g = render_geometry(
            &rays,
            &target,
            &pose,
            &Background::uniform(0.0),
            RenderOptions::default(),
        );
        assert!(g.edge_pixels > 0);
        assert!(g.face.iter().all(|&f| f == 0 || f == NO_FACE));
        let w = g.size.width as usize;
        let mut worst: f64 = 0.0;
        for y in (c.y - 16.0) as usize..(c.y + 17.0) as usize {
            for x in (c.x - 16.0) as usize..(c.x + 17.0) as usize {
                let (dx, dy) = (x as f64 - c.x, y as f64 - c.y);
                let exact = disk_square_area(rpx, dx - 0.5, dx + 0.5, dy - 0.5, dy + 0.5);
                let got = (f64::from(g.albedo[y * w + x]) - 0.1) / 0.9;
                worst = worst.max((got - exact).abs());
            }
        }
        // Each 1/4-px sub-pixel takes the edge as its tangent line; the arc departs from it by
        // the sagitta, enclosing ≤ h³/(8r) per sub-pixel and n of them along the edge per
        // pixel: ≤ h²/(8r) = 6.5e-4 of a pixel at r = 12 px (plus 1e-7 of f32 rounding).
        let h = 0.25;
        assert!(
            worst < h * h / (8.0 * rpx) + 1e-6,
            "worst coverage error {worst}"
        );
    }

    /// Area of the disk x² + y² ≤ r² inside [x0, x1] × [y0, y1], by the midpoint rule over x
    /// on 20 000 strips (error ~1e-9 for unit squares).
    fn disk_square_area(r: f64, x0: f64, x1: f64, y0: f64, y1: f64) -> f64 {
        let n = 20_000;
        let dx = (x1 - x0) / n as f64;
        (0..n)
            .map(|i| {
                let x = x0 + (i as f64 + 0.5) * dx;
                let s = (r * r - x * x).max(0.0).sqrt();
                (s.min(y1) - (-s).max(y0)).max(0.0) * dx
            })
            .sum()
    }
}
