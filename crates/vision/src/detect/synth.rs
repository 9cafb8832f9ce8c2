//! Test patterns for the detector's tests and benchmark: white ellipses (optionally with a
//! marker ring) on a dark background, area-integrated per pixel, then a Gaussian PSF,
//! Gaussian noise and quantisation. (The physical renderer of whole rigs is `simulator/`;
//! this is only a quick, exact pattern generator with known ellipse centres.)

use super::filter::{blur, View};
use super::{Ellipse, FloatImage};
use nalgebra::Point2;

/// One white ellipse; a ringed one carries a dark annulus between 0.45 and 0.75 of its size
/// (docs/design.md §3).
#[derive(Clone, Copy, Debug)]
pub struct Blob {
    /// Outline of the blob.
    pub ellipse: Ellipse,
    /// Whether it carries a marker ring.
    pub ringed: bool,
}

/// Blobs on a uniform background.
#[derive(Clone, Debug)]
pub struct BlobScene {
    /// Image width (px).
    pub width: u32,
    /// Image height (px).
    pub height: u32,
    /// Background level.
    pub background: f32,
    /// Blob level.
    pub foreground: f32,
    /// The blobs (must not overlap).
    pub blobs: Vec<Blob>,
}

/// Sub-samples per axis in a pixel that an outline crosses.
const SUPERSAMPLE: usize = 16;

/// Fraction of the pixel square centred at p inside the ellipse scaled by `s` about its
/// centre: exact for squares wholly in or out, else 16×16 point samples.
fn coverage(e: &Ellipse, s: f64, p: Point2<f64>) -> f64 {
    let (sn, cs) = e.angle.sin_cos();
    let (a, b) = (e.a * s, e.b * s);
    let nr = |x: f64, y: f64| {
        let (dx, dy) = (x - e.center.x, y - e.center.y);
        let (u, v) = (cs * dx + sn * dy, -sn * dx + cs * dy);
        ((u / a).powi(2) + (v / b).powi(2)).sqrt()
    };
    // Within the square every point is ≤ √½ px from p, which moves the normalised radius
    // by ≤ √½ / b.
    let r0 = nr(p.x, p.y);
    let margin = std::f64::consts::FRAC_1_SQRT_2 / b + 1e-9;
    if r0 + margin < 1.0 {
        return 1.0;
    }
    if r0 - margin > 1.0 {
        return 0.0;
    }
    let n = SUPERSAMPLE;
    let mut inside = 0;
    for i in 0..n {
        for j in 0..n {
            let x = p.x - 0.5 + (i as f64 + 0.5) / n as f64;
            let y = p.y - 0.5 + (j as f64 + 0.5) / n as f64;
            inside += (nr(x, y) <= 1.0) as usize;
        }
    }
    inside as f64 / (n * n) as f64
}

/// Renders a scene: each pixel the mean of the scene over its square.
pub fn render(scene: &BlobScene) -> FloatImage {
    let (w, h) = (scene.width, scene.height);
    let mut img = FloatImage::from_pixel(w, h, image::Luma([scene.background]));
    let contrast = (scene.foreground - scene.background) as f64;
    for blob in &scene.blobs {
        let e = &blob.ellipse;
        let x0 = (e.center.x - e.a - 1.0).floor().max(0.0) as u32;
        let y0 = (e.center.y - e.a - 1.0).floor().max(0.0) as u32;
        let x1 = ((e.center.x + e.a + 1.0).ceil().max(0.0) as u32).min(w.saturating_sub(1));
        let y1 = ((e.center.y + e.a + 1.0).ceil().max(0.0) as u32).min(h.saturating_sub(1));
        for y in y0..=y1 {
            for x in x0..=x1 {
                let p = Point2::new(x as f64, y as f64);
                let mut cov = coverage(e, 1.0, p);
                if blob.ringed && cov > 0.0 {
                    cov -= coverage(e, 0.75, p) - coverage(e, 0.45, p);
                }
                img.get_pixel_mut(x, y).0[0] += (contrast * cov) as f32;
            }
        }
    }
    img
}

/// Gaussian point-spread function of standard deviation `sigma` (px), edges replicated.
pub fn blur_psf(img: &FloatImage, sigma: f64) -> FloatImage {
    let v = View {
        data: img.as_raw(),
        width: img.width() as usize,
        height: img.height() as usize,
    };
    let out = blur(v, sigma, 4.0);
    FloatImage::from_raw(img.width(), img.height(), out.data).expect("same size")
}

/// Adds white Gaussian noise of standard deviation `sigma`, reproducibly from `seed`
/// (xorshift64* and Box–Muller).
pub fn add_noise(img: &mut FloatImage, sigma: f32, seed: u64) {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut uniform = move || {
        state ^= state >> 12;
        state ^= state << 25;
        state ^= state >> 27;
        ((state.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    for px in img.pixels_mut() {
        let (u1, u2) = (uniform(), uniform());
        let g = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
        px.0[0] += sigma * g as f32;
    }
}

/// Rounds to integers in 0..=255, as an 8-bit camera would.
pub fn quantise8(img: &mut FloatImage) {
    for px in img.pixels_mut() {
        px.0[0] = px.0[0].round().clamp(0.0, 255.0);
    }
}

/// The hex600 board's circles (docs/design.md §3: pitch 20 mm, radius 6 mm, |x| ≤ 290 mm,
/// |y| ≤ 230 mm, 797 circles) at `radius` px, centred in a `width`×`height` image and
/// foreshortened by `tilt_deg` along y; circles not wholly inside the image are left out,
/// and every seventh is ringed. Levels 30 (background) and 200 (circles).
pub fn lattice(width: u32, height: u32, radius: f64, tilt_deg: f64) -> BlobScene {
    let px_per_mm = radius / 6.0;
    let cos_t = tilt_deg.to_radians().cos();
    let (cx, cy) = (width as f64 / 2.0, height as f64 / 2.0);
    let mut blobs = Vec::new();
    for r in -13i64..=13 {
        for q in -30i64..=30 {
            let (x, y) = (
                20.0 * (q as f64 + r as f64 / 2.0),
                20.0 * 3f64.sqrt() / 2.0 * r as f64,
            );
            if x.abs() > 290.0 || y.abs() > 230.0 {
                continue;
            }
            let (u, v) = (cx + px_per_mm * x, cy - px_per_mm * y * cos_t);
            if u < radius + 2.0
                || v < radius + 2.0
                || u > width as f64 - radius - 2.0
                || v > height as f64 - radius - 2.0
            {
                continue;
            }
            blobs.push(Blob {
                ellipse: Ellipse {
                    center: Point2::new(u, v),
                    a: radius,
                    b: radius * cos_t,
                    angle: 0.0,
                },
                ringed: (q * 3 + r * 5).rem_euclid(7) == 0,
            });
        }
    }
    BlobScene {
        width,
        height,
        background: 30.0,
        foreground: 200.0,
        blobs,
    }
}

/// [`lattice`] rendered with a PSF of σ = 0.9 px, 2 DN noise, 8-bit quantisation.
pub fn lattice_image(width: u32, height: u32, radius: f64, tilt_deg: f64, seed: u64) -> FloatImage {
    let mut img = blur_psf(&render(&lattice(width, height, radius, tilt_deg)), 0.9);
    add_noise(&mut img, 2.0, seed);
    quantise8(&mut img);
    img
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Area integration: the image sum over a blob equals its area × contrast.
    #[test]
    fn rendered_area_matches_the_ellipse_area() {
        let e = Ellipse {
            center: Point2::new(20.3, 17.8),
            a: 9.0,
            b: 5.5,
            angle: 0.4,
        };
        for ringed in [false, true] {
            let scene = BlobScene {
                width: 48,
                height: 40,
                background: 0.0,
                foreground: 1.0,
                blobs: vec![Blob { ellipse: e, ringed }],
            };
            let sum: f64 = render(&scene).pixels().map(|p| p.0[0] as f64).sum();
            let ring = if ringed {
                0.75f64.powi(2) - 0.45f64.powi(2)
            } else {
                0.0
            };
            let area = std::f64::consts::PI * e.a * e.b * (1.0 - ring);
            // 16×16 samples on ~2πr edge pixels: error ≲ 2·perimeter/256 px² at most.
            assert!((sum - area).abs() < 0.1, "ringed {ringed}: {sum} vs {area}");
        }
    }
}
