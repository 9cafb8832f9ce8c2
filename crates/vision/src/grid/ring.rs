//! Marker-ring reading (docs/design.md §3, §5): is a dark annulus 0.45R–0.75R printed inside a
//! detected white circle?

use std::sync::OnceLock;
use {crate::detect::Circle, hexcal_core::images::FloatImage};

/// What the annulus of one circle shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Ring {
    /// Clearly white across the annulus.
    Plain,
    /// Clearly darkened: a marker ring.
    Ringed,
    /// Too close to the threshold, or not measurable (off the image, no contrast).
    Unsure,
}

/// Angular samples around the annulus.
const ANGLES: usize = 32;
/// Radial samples across the annulus, as fractions of its width (centres of equal parts).
const RADIAL: [f64; 3] = [1.0 / 6.0, 0.5, 5.0 / 6.0];

/// Darkening of the annulus of `circle`: (white − annulus mean) / (white − background), 0
/// for a plain white circle, up to 1 for a sharp, fully dark ring. `white` is the level of
/// the board's white near the circle (its own foreground, or a brighter plain neighbour's:
/// blur dims the white left around a small ring). `band` is
/// the annulus as fractions (inner, outer) of the circle's radius, applied to the fitted
/// outer-boundary ellipse scaled about its centre.
///
/// Each sample is weighted by the ellipse's radius along its ray: where the ellipse is
/// foreshortened the ring is thin, blurred away, and would only dilute the reading.
pub(crate) fn ring_contrast(
    image: &FloatImage,
    circle: &Circle,
    white: f32,
    band: [f64; 2],
) -> Option<f64> {
    let contrast = f64::from(white) - f64::from(circle.background);
    if contrast <= 0.0 {
        return None;
    }
    static UNIT: OnceLock<[(f64, f64); ANGLES]> = OnceLock::new();
    let unit = UNIT.get_or_init(|| {
        std::array::from_fn(|m| {
            (std::f64::consts::TAU * (m as f64 + 0.5) / ANGLES as f64).sin_cos()
        })
    });
    let e = &circle.ellipse;
    let (sa, ca) = e.angle.sin_cos();
    let (mut sum, mut weight) = (0.0, 0.0);
    for &(st, ct) in unit {
        // Point of the unit ellipse along parameter t: a·cos t·u + b·sin t·v.
        let (px, py) = (e.a * ct, e.b * st);
        let dx = px * ca - py * sa;
        let dy = px * sa + py * ca;
        let w = (px * px + py * py).sqrt();
        for f in RADIAL {
            let s = band[0] + f * (band[1] - band[0]);
            let v = bilinear(image, e.center.x + s * dx, e.center.y + s * dy)?;
            sum += w * f64::from(v);
            weight += w;
        }
    }
    let mean = sum / weight;
    Some((f64::from(white) - mean) / contrast)
}

/// Classify a ring contrast against the two thresholds of [`super::GridParams`].
pub(crate) fn classify(contrast: Option<f64>, plain_below: f64, ringed_above: f64) -> Ring {
    match contrast {
        Some(c) if c < plain_below => Ring::Plain,
        Some(c) if c > ringed_above => Ring::Ringed,
        _ => Ring::Unsure,
    }
}

/// Bilinear interpolation with pixel centres at integer coordinates; `None` outside the
/// image.
fn bilinear(image: &FloatImage, x: f64, y: f64) -> Option<f32> {
    let (w, h) = (image.width() as usize, image.height() as usize);
    if w < 2 || h < 2 || !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64) {
        return None;
    }
    // x, y ≥ 0 here, so truncation is the floor.
    let (x0, y0) = ((x as usize).min(w - 2), (y as usize).min(h - 2));
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let raw = image.as_raw();
    let p = |xx: usize, yy: usize| raw[yy * w + xx];
    let top = p(x0, y0) * (1.0 - fx) + p(x0 + 1, y0) * fx;
    let bottom = p(x0, y0 + 1) * (1.0 - fx) + p(x0 + 1, y0 + 1) * fx;
    Some(top * (1.0 - fy) + bottom * fy)
}

#[cfg(test)]
mod tests {
    use super::*;
    use hexcal_core::images::Ellipse;
    use nalgebra::Point2;

    /// A sharp synthetic circle of radius `r` at (x, y), optionally with a ring, sampled at 4×4
    /// points per pixel; white 200, black 20.
    fn disk(r: f64, ringed: bool, band: [f64; 2]) -> (FloatImage, Circle) {
        blurred_disk(r, ringed, band, 0.0)
    }

    /// [`disk`] seen through a Gaussian PSF of `sigma` px (none at 0).
    fn blurred_disk(r: f64, ringed: bool, band: [f64; 2], sigma: f64) -> (FloatImage, Circle) {
        let (cx, cy) = (20.3, 19.6);
        let img = FloatImage::from_fn(41, 41, |x, y| {
            let mut acc = 0.0;
            for i in 0..4 {
                for j in 0..4 {
                    let dx = f64::from(x) + (f64::from(i) + 0.5) / 4.0 - 0.5 - cx;
                    let dy = f64::from(y) + (f64::from(j) + 0.5) / 4.0 - 0.5 - cy;
                    let rho = dx.hypot(dy) / r;
                    let white = rho <= 1.0 && !(ringed && rho > band[0] && rho < band[1]);
                    acc += if white { 200.0 } else { 20.0 };
                }
            }
            image::Luma([acc / 16.0])
        });
        let img = if sigma > 0.0 {
            let n = (4.0 * sigma).ceil() as i32;
            let k: Vec<f32> = (-n..=n)
                .map(|i| (-f64::from(i * i) / (2.0 * sigma * sigma)).exp() as f32)
                .collect();
            let total: f32 = k.iter().sum();
            let pass = |src: &FloatImage, dx: i32, dy: i32| {
                FloatImage::from_fn(41, 41, |x, y| {
                    let v: f32 = (-n..=n)
                        .map(|o| {
                            let xx = (x as i32 + o * dx).clamp(0, 40) as u32;
                            let yy = (y as i32 + o * dy).clamp(0, 40) as u32;
                            k[(o + n) as usize] * src.get_pixel(xx, yy).0[0]
                        })
                        .sum();
                    image::Luma([v / total])
                })
            };
            pass(&pass(&img, 1, 0), 0, 1)
        } else {
            img
        };
        let circle = Circle {
            ellipse: Ellipse {
                center: Point2::new(cx, cy),
                a: r,
                b: r,
                angle: 0.3,
            },
            score: 0.3,
            background: 20.0,
            foreground: 200.0,
            edge_rms: 0.0,
        };
        (img, circle)
    }

    #[test]
    fn sharp_ring_reads_dark_and_plain_reads_white() {
        let band = [0.45, 0.75];
        for r in [5.0, 12.0] {
            let (img, c) = disk(r, true, band);
            let ringed = ring_contrast(&img, &c, c.foreground, band).unwrap();
            // Samples sit in the middle 2/3 of the annulus: fully dark up to the partial
            // coverage of pixels straddling the ring edges (≤ 1 px of a ≥ 1.5 px wide ring).
            assert!(ringed > 0.6, "r = {r}: ringed contrast {ringed}");
            let (img, c) = disk(r, false, band);
            let plain = ring_contrast(&img, &c, c.foreground, band).unwrap();
            assert!(plain.abs() < 1e-3, "r = {r}: plain contrast {plain}");
        }
    }

    /// The default thresholds against a model of blur: a plain circle's annulus darkens only
    /// through the PSF (0.16 at r = 3.5 px, σ = 1 px; 0.24 at σ = 1.3 px), a ring keeps
    /// ≥ 0.52 of the contrast against the true levels (a foreground measured inside a
    /// blurred small ringed circle reads lower and brings it down to ≈ 0.35).
    #[test]
    fn blurred_circles_classify_down_to_3_5_px() {
        let band = [0.45, 0.75];
        let p = crate::grid::GridParams::default();
        let read = |r, ringed, sigma| {
            let (img, c) = blurred_disk(r, ringed, band, sigma);
            classify(
                ring_contrast(&img, &c, c.foreground, band),
                p.ring_plain_below,
                p.ring_ringed_above,
            )
        };
        for sigma in [0.8, 1.0] {
            for r in [3.5, 4.0, 5.0, 7.0] {
                assert_eq!(read(r, false, sigma), Ring::Plain, "σ {sigma}, r {r}");
                assert_eq!(read(r, true, sigma), Ring::Ringed, "σ {sigma}, r {r}");
            }
        }
        // Beyond: r/σ = 2.7 must not read as a ring.
        assert_ne!(read(3.5, false, 1.3), Ring::Ringed);
        assert_eq!(read(3.5, true, 1.3), Ring::Ringed);
    }

    #[test]
    fn off_image_is_unsure() {
        let band = [0.45, 0.75];
        let (img, mut c) = disk(8.0, false, band);
        c.ellipse.center.x = 1.0;
        assert_eq!(
            classify(ring_contrast(&img, &c, c.foreground, band), 0.2, 0.3),
            Ring::Unsure
        );
    }
}
