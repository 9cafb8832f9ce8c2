//! Subpixel refinement of one circleness peak (DESIGN.md §4): edge points on rays from the
//! coarse centre, each the crossing of the local (background + foreground)/2 level on the
//! circle's *outer* boundary, and a robust direct ellipse fit to them.
//!
//! 1. Outward pass: on each ray the first falling crossing gives a first ellipse. That is
//!    the outer boundary, or for a marker circle possibly the inner edge of its dark ring
//!    (0.45 R), a concentric ellipse of the same shape.
//! 2. Ring test: if that ellipse is dark just outside (×1.3) and white further out (×1.95,
//!    the ring's white outer annulus at 0.75–1 R = 1.67–2.22 × 0.45 R), it was the ring's
//!    inner disk and the guess is scaled by 1/0.45.
//! 3. Inward passes (twice): rays at evenly spaced parametric angles of the current ellipse,
//!    walking inward from 1.6× its boundary (inside the dark gap, which reaches ≥ 1.67×
//!    at the board's border and 2.33× between circles) to the first rising crossing.

use super::filter::View;
use super::fit::{self, fit_ellipse, Conic};
use super::{Circle, Ellipse};
use nalgebra::{Point2, Vector2};

/// Middle of a marker's white outer annulus (0.75–1 R, DESIGN.md §3) / circle radius.
const RING_ANNULUS_MID: f64 = 0.875;

/// Settings of the refinement.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Settings {
    /// Rays per circle.
    pub(crate) rays: usize,
    /// Smallest foreground − background contrast (image units).
    pub(crate) min_contrast: f32,
    /// Accepted radius range √(ab) (px).
    pub(crate) radius_range: (f64, f64),
    /// Maximum RMS edge-point distance from the ellipse: `max_rms.0 + max_rms.1 · radius`.
    pub(crate) max_rms: (f64, f64),
}

/// Reusable per-worker buffers.
#[derive(Default)]
pub(crate) struct Scratch {
    profile: Vec<f32>,
    values: Vec<f32>,
    ks: Vec<f32>,
    points: Vec<Point2<f64>>,
    dist: Vec<f64>,
    keep: Vec<Point2<f64>>,
}

/// A robust fit: the ellipse, its inliers' RMS Sampson distance, and their count.
struct Fit {
    ellipse: Ellipse,
    rms: f64,
    inliers: usize,
}

fn median(v: &mut [f32]) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    let m = v.len() / 2;
    Some(*v.select_nth_unstable_by(m, f32::total_cmp).1)
}

/// Point at parametric angle φ of an ellipse, as an offset from its centre.
#[inline]
fn ellipse_offset(e: &Ellipse, phi: f64) -> Vector2<f64> {
    let (s, c) = e.angle.sin_cos();
    let (u, v) = (e.a * phi.cos(), e.b * phi.sin());
    Vector2::new(c * u - s * v, s * u + c * v)
}

/// Foreground: mean of the centre and four points at 0.15 b around it.
fn foreground(img: View<'_>, c: Point2<f64>, b: f64) -> Option<f32> {
    let d = 0.15 * b;
    let pts = [(0.0, 0.0), (d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d)];
    let mut sum = 0.0;
    for (dx, dy) in pts {
        sum += img.bilinear(c.x + dx, c.y + dy)?;
    }
    Some(sum / pts.len() as f32)
}

/// Direct fit, then twice: drop points farther than max(4·1.4826·MAD, 0.1 px) and refit.
fn robust_fit(points: &[Point2<f64>], s_dist: &mut Vec<f64>, keep: &mut Vec<Point2<f64>>) -> Option<Fit> {
    let mut conic: Conic = fit_ellipse(points)?;
    for _ in 0..2 {
        s_dist.clear();
        s_dist.extend(points.iter().map(|&p| conic.sampson_distance(p)));
        let mut sorted = s_dist.clone();
        let m = sorted.len() / 2;
        let med = *sorted.select_nth_unstable_by(m, f64::total_cmp).1;
        let thr = (4.0 * 1.4826 * med).max(0.1);
        keep.clear();
        keep.extend(points.iter().zip(s_dist.iter()).filter(|(_, &d)| d <= thr).map(|(&p, _)| p));
        conic = fit_ellipse(keep)?;
    }
    let ellipse = conic.to_ellipse()?;
    let ss: f64 = keep.iter().map(|&p| conic.sampson_distance(p).powi(2)).sum();
    Some(Fit { ellipse, rms: (ss / keep.len() as f64).sqrt(), inliers: keep.len() })
}

/// Refines a peak at `c0` with radius estimate `r_hat` into a circle, or rejects it.
pub(crate) fn refine(img: View<'_>, c0: Point2<f64>, r_hat: f64, score: f32, set: &Settings, s: &mut Scratch) -> Option<Circle> {
    let n = set.rays;
    let min_points = (n * 3 / 5).max(6);
    // 1. Outward pass to the first falling crossing, within 3 r̂.
    let f0 = foreground(img, c0, r_hat)?;
    let step = (r_hat / 10.0).clamp(0.25, 1.0);
    let m = (3.0 * r_hat / step).ceil() as usize + 1;
    s.profile.clear();
    s.values.clear();
    for i in 0..n {
        let th = std::f64::consts::TAU * i as f64 / n as f64;
        let (dy, dx) = th.sin_cos();
        let mut lo = f32::INFINITY;
        for j in 0..m {
            let t = j as f64 * step;
            let v = img.bilinear(c0.x + t * dx, c0.y + t * dy).unwrap_or(f32::NAN);
            lo = lo.min(v); // NaN-ignoring
            s.profile.push(v);
        }
        s.values.push(lo);
    }
    let b0 = median(&mut s.values)?;
    if f0 - b0 < set.min_contrast {
        return None;
    }
    let mid0 = 0.5 * (f0 + b0);
    s.points.clear();
    for i in 0..n {
        let prof = &s.profile[i * m..(i + 1) * m];
        let th = std::f64::consts::TAU * i as f64 / n as f64;
        let (dy, dx) = th.sin_cos();
        for j in 1..m {
            let (p, q) = (prof[j - 1], prof[j]);
            if !(p >= mid0) {
                break; // outside the image (NaN) or the centre is not white
            }
            if q < mid0 {
                let t = step * ((j - 1) as f64 + ((p - mid0) / (p - q)) as f64);
                s.points.push(Point2::new(c0.x + t * dx, c0.y + t * dy));
                break;
            }
        }
    }
    if s.points.len() < min_points {
        return None;
    }
    let mut guess = robust_fit(&s.points, &mut s.dist, &mut s.keep)?.ellipse;

    // 2. Ring test: is the first ellipse closed in by a white annulus?
    if let Some(k) = ring_annulus(img, &guess, f0 - b0, s) {
        // The annulus spans 0.75–1 R: its middle is at 0.875 R.
        let scale = k / RING_ANNULUS_MID;
        guess.a *= scale;
        guess.b *= scale;
    }

    // 3. Inward passes from 1.6× the current boundary.
    let mut result = None;
    for _ in 0..2 {
        let c = guess.center;
        let centre = foreground(img, c, guess.b)?;
        s.values.clear();
        for i in 0..n {
            let o = ellipse_offset(&guess, std::f64::consts::TAU * i as f64 / n as f64);
            let lo = [1.3, 1.45, 1.6]
                .iter()
                .filter_map(|&k| img.bilinear(c.x + k * o.x, c.y + k * o.y))
                .fold(f32::INFINITY, f32::min);
            if lo.is_finite() {
                s.values.push(lo);
            }
        }
        let bg = median(&mut s.values)?;
        if centre - bg < set.min_contrast {
            return None;
        }
        // Foreground: the median over rays of the first maximum inside the outer edge (found
        // at a quarter of the contrast), i.e. the white outer annulus of a marker circle
        // that blur has dimmed, so that the level sits on the steep part of the outer edge.
        let quarter = bg + 0.25 * (centre - bg);
        s.values.clear();
        for i in 0..n {
            let o = ellipse_offset(&guess, std::f64::consts::TAU * i as f64 / n as f64);
            let rho = o.norm();
            let u = o / rho;
            if let Some(t) = inward_crossing(img, c, u, 1.6 * rho, 0.6 * rho, quarter) {
                if let Some(top) = first_maximum(img, c, u, t, (t - 0.4 * rho).max(0.0), 0.05 * (centre - bg)) {
                    s.values.push(top);
                }
            }
        }
        let fg = median(&mut s.values)?;
        if fg - bg < set.min_contrast {
            return None;
        }
        let mid = 0.5 * (fg + bg);
        s.points.clear();
        for i in 0..n {
            let o = ellipse_offset(&guess, std::f64::consts::TAU * i as f64 / n as f64);
            let rho = o.norm();
            let u = o / rho;
            if let Some(t) = inward_crossing(img, c, u, 1.6 * rho, 0.6 * rho, mid) {
                s.points.push(c + t * u);
            }
        }
        if s.points.len() < min_points {
            return None;
        }
        let fit = robust_fit(&s.points, &mut s.dist, &mut s.keep)?;
        result = Some((fit, fg, bg));
        guess = result.as_ref()?.0.ellipse;
    }
    let (fit, fg, bg) = result?;
    let e = fit.ellipse;
    let radius = e.radius();
    let ok = fit.inliers >= min_points
        && e.b >= 0.12 * e.a
        && radius >= set.radius_range.0
        && radius <= set.radius_range.1
        && fit::Conic::from_ellipse(&e).value(c0) < 0.0
        && fit.rms <= set.max_rms.0 + set.max_rms.1 * radius;
    ok.then_some(Circle { ellipse: e, score: score as f64, background: bg, foreground: fg, edge_rms: fit.rms as f32 })
}

/// Whether the ellipse `e` is the inner disk of a marker circle, closed in by its dark ring
/// and then the white outer annulus. On each of 48 rays (parametric angles of `e`), the
/// profile from 1× to 3.5× the boundary gives its largest rise above the lowest value
/// before it, and the position k where that rise peaks. A ring is a closed curve: every
/// ray shows a similar rise (15th percentile ≥ 5 % of the contrast and ≥ 0.4 × the median,
/// so even a ring that blur has made faint) at a consistent k (MAD < 10 %). Around a plain
/// circle only the ~60 % of the directions that meet a neighbour (at ≥ 2.33×) rise, the
/// others show noise. Returns the median k of the annulus.
fn ring_annulus(img: View<'_>, e: &Ellipse, contrast: f32, s: &mut Scratch) -> Option<f64> {
    const RAYS: usize = 48;
    s.values.clear();
    s.ks.clear();
    for i in 0..RAYS {
        let o = ellipse_offset(e, std::f64::consts::TAU * i as f64 / RAYS as f64);
        let dk = (0.5 / o.norm()).min(0.1);
        let steps = (2.5 / dk).ceil() as usize;
        // Largest rise above the lowest value before it, and where it peaks.
        let (mut lo, mut rise, mut rise_k) = (f32::INFINITY, 0.0f32, 0.0);
        let mut ok = true;
        for j in 0..=steps {
            let k = 1.0 + j as f64 * dk;
            let Some(v) = img.bilinear(e.center.x + k * o.x, e.center.y + k * o.y) else {
                ok = false;
                break;
            };
            lo = lo.min(v);
            if v - lo > rise {
                (rise, rise_k) = (v - lo, k);
            }
        }
        if ok {
            s.values.push(rise);
            s.ks.push(rise_k as f32);
        }
    }
    let n = s.values.len();
    if n < RAYS / 2 {
        return None;
    }
    let p15 = *s.values.select_nth_unstable_by(n * 15 / 100, f32::total_cmp).1;
    let med = median(&mut s.values)?;
    if p15 < 0.05 * contrast || p15 < 0.4 * med {
        return None;
    }
    let k = median(&mut s.ks)?;
    s.values.clear();
    s.values.extend(s.ks.iter().map(|&x| (x - k).abs()));
    let mad = median(&mut s.values)?;
    (mad < 0.1 * k).then_some(k as f64)
}

/// Walking inward from `c + t_start·u` in steps of 0.25 px down to `t_end`, the highest
/// value before the profile falls more than `tolerance` below it.
fn first_maximum(img: View<'_>, c: Point2<f64>, u: Vector2<f64>, t_start: f64, t_end: f64, tolerance: f32) -> Option<f32> {
    let mut best = img.bilinear(c.x + t_start * u.x, c.y + t_start * u.y)?;
    let mut t = t_start - 0.25;
    while t >= t_end {
        let v = img.bilinear(c.x + t * u.x, c.y + t * u.y)?;
        if v < best - tolerance {
            break;
        }
        best = best.max(v);
        t -= 0.25;
    }
    Some(best)
}

/// Walking from `c + t_start·u` towards `c + t_end·u`, the first crossing from below `level`
/// to at or above it: coarse steps of 0.5 px, then 0.1 px inside the bracket, linear
/// interpolation between the last two samples. Returns t.
fn inward_crossing(img: View<'_>, c: Point2<f64>, u: Vector2<f64>, t_start: f64, t_end: f64, level: f32) -> Option<f64> {
    let at = |t: f64| img.bilinear(c.x + t * u.x, c.y + t * u.y);
    const COARSE: f64 = 0.5;
    const FINE: f64 = 0.1;
    let mut t = t_start;
    let mut prev = at(t)?;
    while t > t_end {
        let tn = t - COARSE;
        let v = at(tn)?;
        if prev < level && v >= level {
            // Refine inside (tn, t]; the last fine sample is v itself.
            let (mut tf, mut pf) = (t, prev);
            for k in 1..=(COARSE / FINE).round() as usize {
                let tq = t - k as f64 * FINE;
                let q = if tq <= tn + 1e-9 { v } else { at(tq)? };
                if q >= level {
                    let tq = tq.max(tn);
                    return Some(tf - (tf - tq) * ((level - pf) / (q - pf)) as f64);
                }
                (tf, pf) = (tq, q);
            }
            return None;
        }
        t = tn;
        prev = v;
    }
    None
}
