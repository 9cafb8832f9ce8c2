//! Subpixel refinement of one circleness peak (docs/design.md §4): edge points on rays from the
//! coarse centre, each the crossing of the local (background + foreground)/2 level on the
//! circle's *outer* boundary, and a robust direct ellipse fit to them.
//!
//! 1. Outward passes: on every third ray the first falling crossing gives a first
//!    ellipse. From its centre, again, but now stepping over a marker's
//!    white annulus when the profile rises again soon after (see [`outward_fit`]). That is
//!    the outer boundary, or for a marker circle whose annulus blur has made faint, the
//!    inner edge of its dark ring (0.45 R), a concentric ellipse of the same shape.
//! 2. Ring test ([`ring_annulus`]): if that ellipse is closed in by a white annulus, it was
//!    the ring's inner disk and the guess is scaled out to the annulus.
//! 3. Levels ([`levels`]): background from the dark gap outside the current ellipse
//!    (1.3–1.6×, inside the gap that reaches ≥ 1.67× at the board's border and 2.33×
//!    between circles), foreground from the first maximum inside each ray's outer edge.
//! 4. Inward passes: rays at evenly spaced parametric angles of the current ellipse,
//!    walking inward from outside its boundary (first stepping out of any white there,
//!    [`outside`]) to the first rising crossing of the mean level; each pass around the
//!    previous pass's ellipse, until the centre settles.
//! 5. Checks: enough inliers, b/a ≥ [`MIN_AXIS_RATIO`], radius in range, the peak near the
//!    fit, the edge RMS, and that the fit closes the circle ([`closed`]: no white just
//!    outside it, not cut by the frame).

use super::filter::View;
use super::fit::{self, fit_ellipse, Conic};
use super::{Circle, Ellipse};
use nalgebra::{Point2, Vector2};

/// Middle of a marker's white outer annulus (0.75–1 R, docs/design.md §3) / circle radius.
const RING_ANNULUS_MID: f64 = 0.875;
/// Largest fraction of the inward rays that may meet the image border inside the circle. A
/// rim δ px past the border cuts arccos(1 − δ/r)/π of the rays: 12 % lets through slivers
/// of ~0.3 px at r = 4 px and ~1.7 px at r = 40 px. Measured (tests/detect_sim.rs): circles
/// labelled past the border then have centre errors ≤ 0.02 px, against up to 2 px without
/// this check.
const MAX_CUT_RAYS: f64 = 0.12;
/// Smallest accepted b/a: a circle tilted by ≤ 75° (docs/design.md's range, cos 75° = 0.26) still
/// reads ≥ 0.23 under strong perspective; thinner fits are slivers of larger outlines.
const MIN_AXIS_RATIO: f64 = 0.2;
/// The detection peak must lie inside the fitted ellipse scaled by this: a thin ellipse's
/// peak found at a coarse pyramid level can sit a little outside its minor axis, while a fit
/// that wandered to a neighbour leaves its peak ≥ 2.33× away (pitch/radius − 1).
const PEAK_REACH: f64 = 1.5;
/// Most inward passes of the edge-point search.
const MAX_PASSES: usize = 4;
/// After two passes, the search stops once a pass moves the centre less than this (px).
const CONVERGED_PX: f64 = 0.05;
/// Largest fraction of rays on which the image just outside a fitted outline is still white
/// (see [`closed`]).
const MAX_SPILL: f64 = 0.05;
/// Farthest the closure test looks past the outline, as a fraction of the ray's radius ρ:
/// halfway across the narrowest dark gap to a neighbour (1–1.67 ρ, docs/design.md §4), where
/// the blurred edges of both are darkest.
const MAX_CLOSE_OUT: f64 = 1.0 / 3.0;
/// Rays of the outward pass that also measure the background along their whole length.
const BACKGROUND_RAYS: usize = 6;

/// Settings of the refinement.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Settings {
    /// Rays per circle.
    pub(crate) rays: usize,
    /// Smallest foreground − background contrast (image units).
    pub(crate) min_contrast: f32,
    /// Accepted radius range √(ab) (px).
    pub(crate) radius_range: (f64, f64),
    /// Maximum RMS edge-point distance from the ellipse: `(max_rms.0 + max_rms.1 · radius)
    /// · √(a/b)`.
    pub(crate) max_rms: (f64, f64),
}

/// Reusable per-worker buffers.
#[derive(Default)]
pub(crate) struct Scratch {
    /// (cos, sin) of the ray angles 2πi/n.
    dirs: Vec<(f64, f64)>,
    values: Vec<f32>,
    ks: Vec<f32>,
    points: Vec<Point2<f64>>,
    dist: Vec<f64>,
    sorted: Vec<f64>,
    keep: Vec<Point2<f64>>,
}

impl Scratch {
    fn directions(&mut self, n: usize) {
        if self.dirs.len() != n {
            self.dirs = (0..n)
                .map(|i| (std::f64::consts::TAU * i as f64 / n as f64).sin_cos())
                .map(|(s, c)| (c, s))
                .collect();
        }
    }
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

/// Offset from the centre of the point at parametric angle φ, given (cos φ, sin φ).
#[inline]
fn ellipse_offset(e: &Ellipse, (cos, sin): (f64, f64)) -> Vector2<f64> {
    let (s, c) = e.angle.sin_cos();
    let (u, v) = (e.a * cos, e.b * sin);
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

/// Direct fit, then up to twice: drop points farther than max(4·1.4826·MAD, 0.1 px) and
/// refit.
fn robust_fit(points: &[Point2<f64>], s: &mut Scratch) -> Option<Fit> {
    let mut conic: Conic = fit_ellipse(points)?;
    for _ in 0..2 {
        s.dist.clear();
        s.dist
            .extend(points.iter().map(|&p| conic.sampson_distance(p)));
        s.sorted.clear();
        s.sorted.extend_from_slice(&s.dist);
        let m = s.sorted.len() / 2;
        let med = *s.sorted.select_nth_unstable_by(m, f64::total_cmp).1;
        let thr = (4.0 * 1.4826 * med).max(0.1);
        s.keep.clear();
        s.keep.extend(
            points
                .iter()
                .zip(s.dist.iter())
                .filter(|(_, &d)| d <= thr)
                .map(|(&p, _)| p),
        );
        if s.keep.len() == points.len() {
            break; // no outliers: the fit stands
        }
        conic = fit_ellipse(&s.keep)?;
    }
    let ellipse = conic.to_ellipse()?;
    let ss: f64 = s
        .keep
        .iter()
        .map(|&p| conic.sampson_distance(p).powi(2))
        .sum();
    Some(Fit {
        ellipse,
        rms: (ss / s.keep.len() as f64).sqrt(),
        inliers: s.keep.len(),
    })
}

/// Refines a peak at `c0` with radius estimate `r_hat` into a circle, or rejects it.
pub(crate) fn refine(
    img: View<'_>,
    c0: Point2<f64>,
    r_hat: f64,
    score: f32,
    set: &Settings,
    s: &mut Scratch,
) -> Option<Circle> {
    let n = set.rays;
    s.directions(n);
    let min_points = (n * 3 / 5).max(6);
    let guess = first_guess(img, c0, r_hat, set.min_contrast, s)?;

    // 3. Levels around the guess.
    let (bg, fg) = levels(img, &guess, set.min_contrast, s)?;
    let mid = 0.5 * (fg + bg);

    let fit = inward_fit(img, guess, mid, min_points, s)?;
    let e = fit.ellipse;
    let ok = accepted(img, &fit, c0, mid, min_points, set, s);
    ok.then_some(Circle {
        ellipse: e,
        score: score as f64,
        background: bg,
        foreground: fg,
        edge_rms: fit.rms as f32,
    })
}

/// Steps 1 and 2 from the peak at `c0` with radius estimate `r_hat`: the outward passes and
/// the ring test give the first guess of the outline; `None` below `min_contrast` or
/// without a first fit.
fn first_guess(
    img: View<'_>,
    c0: Point2<f64>,
    r_hat: f64,
    min_contrast: f32,
    s: &mut Scratch,
) -> Option<Ellipse> {
    // 1. Outward pass to the first falling crossing, within 3 r̂; the background is the
    //    median over a few rays of their lowest value within 2 r̂ (in the gap).
    let f0 = foreground(img, c0, r_hat)?;
    let step = (r_hat / 10.0).clamp(0.25, 1.0);
    let m = (3.0 * r_hat / step).ceil() as usize + 1;
    let b0 = outward_background(img, c0, step, m, s)?;
    if f0 - b0 < min_contrast {
        return None;
    }
    let mid0 = 0.5 * (f0 + b0);
    // From the peak, first falling crossings only; then again from that ellipse's centre
    // (close to the true one even when the ellipse is a marker's inner disk, which is
    // concentric), now stepping over a white annulus.
    let first = outward_fit(img, c0, f0, mid0, step, m, false, s)?;
    let e1 = first.ellipse;
    let f1 = foreground(img, e1.center, e1.b).unwrap_or(f0);
    // A marker's outer edge is concentric with its ring: an annulus fit whose centre moved
    // stepped over something else (e.g. a bright line beyond the board's border).
    let mut guess = outward_fit(img, e1.center, f1, mid0, step, m, true, s)
        .map(|f| f.ellipse)
        .filter(|e| (e.center - e1.center).norm() <= 0.25 * e1.b + 0.25)
        .unwrap_or(e1);

    // 2. Ring test: is the first ellipse closed in by a white annulus?
    if let Some(k) = ring_annulus(img, &guess, f0 - b0, s) {
        // The annulus spans 0.75–1 R: its middle is at 0.875 R.
        let scale = k / RING_ANNULUS_MID;
        guess.a *= scale;
        guess.b *= scale;
    }
    Some(guess)
}

/// The background seen from `c0`: the median over [`BACKGROUND_RAYS`] rays of their lowest
/// value within the first two thirds of `m` steps of `step` px.
fn outward_background(
    img: View<'_>,
    c0: Point2<f64>,
    step: f64,
    m: usize,
    s: &mut Scratch,
) -> Option<f32> {
    let n = s.dirs.len();
    s.values.clear();
    for i in 0..BACKGROUND_RAYS {
        let (dx, dy) = s.dirs[i * n / BACKGROUND_RAYS];
        let lo = (0..(2 * m) / 3)
            .filter_map(|j| img.bilinear(c0.x + j as f64 * step * dx, c0.y + j as f64 * step * dy))
            .fold(f32::INFINITY, f32::min);
        if lo.is_finite() {
            s.values.push(lo);
        }
    }
    median(&mut s.values)
}

/// Step 4 from the first `guess`: inward passes to the crossings of the mean level `mid`
/// until the centre settles; the last pass's fit, or `None` when a pass finds fewer than
/// `min_points` edge points, is cut by the image border or fails to fit.
///
/// The first pass starts from 1.6× the guess, later ones from 2.5 px outside the previous
/// fit, until the centre moves less than [`CONVERGED_PX`] (at most [`MAX_PASSES`]). A
/// guess found from one end of a steeply tilted marker's annulus is short at that end;
/// each pass reaches further out there. A ray leaving the image starts at its last point
/// inside instead; where the circle is still brighter than the mean level there, its
/// outline runs off the frame. A circle cut on more than [`MAX_CUT_RAYS`] of its rays is
/// dropped: the fit to the rest has a biased centre (a sliver past the border, as for
/// circles whose rim just touches it, leaves the fit to the remaining outline accurate).
fn inward_fit(
    img: View<'_>,
    guess: Ellipse,
    mid: f32,
    min_points: usize,
    s: &mut Scratch,
) -> Option<Fit> {
    let mut fit: Option<Fit> = None;
    // How far the last pass moved the centre (px).
    let mut moved = f64::INFINITY;
    for pass in 0..MAX_PASSES {
        if pass >= 2 && moved < CONVERGED_PX {
            break;
        }
        let g = fit.as_ref().map_or(guess, |f| f.ellipse);
        let cut = inward_points(img, &g, pass, mid, s);
        if cut as f64 > MAX_CUT_RAYS * s.dirs.len() as f64 {
            return None;
        }
        if s.points.len() < min_points {
            return None;
        }
        let points = std::mem::take(&mut s.points);
        fit = robust_fit(&points, s);
        s.points = points;
        moved = (fit.as_ref()?.ellipse.center - g.center).norm();
    }
    fit
}

/// One inward pass around the ellipse `g` (pass number `pass`): the edge points, into
/// `s.points`, where each ray first rises through `mid`; gives the number of rays cut by
/// the image border with the circle still bright there.
fn inward_points(img: View<'_>, g: &Ellipse, pass: usize, mid: f32, s: &mut Scratch) -> usize {
    let c = g.center;
    s.points.clear();
    let mut cut = 0;
    for &d in &s.dirs {
        let o = ellipse_offset(g, d);
        let rho = o.norm();
        let u = o / rho;
        let nominal = if pass == 0 { 1.6 * rho } else { rho + 2.5 };
        let exit = exit_distance(img, c, u);
        let start = outside(img, c, u, nominal.min(exit), (2.2 * rho).min(exit), mid);
        match inward_crossing(img, c, u, start, 0.6 * rho, rho / 16.0, mid) {
            Some(t) => s.points.push(c + t * u),
            None if start >= exit
                && img
                    .bilinear(c.x + start * u.x, c.y + start * u.y)
                    .is_some_and(|v| v >= mid) =>
            {
                cut += 1;
            }
            None => {}
        }
    }
    cut
}

/// Step 5, the checks of the final `fit` of the peak at `c0` (mean level `mid`): enough
/// inliers, a closed outline, b/a, the radius range, the peak near the fit, the edge RMS.
fn accepted(
    img: View<'_>,
    fit: &Fit,
    c0: Point2<f64>,
    mid: f32,
    min_points: usize,
    set: &Settings,
    s: &Scratch,
) -> bool {
    let e = fit.ellipse;
    let radius = e.radius();
    fit.inliers >= min_points
        && closed(img, &e, mid, s)
        && e.b >= MIN_AXIS_RATIO * e.a
        && radius >= set.radius_range.0
        && radius <= set.radius_range.1
        && fit::Conic::from_ellipse(&Ellipse {
            a: PEAK_REACH * e.a,
            b: PEAK_REACH * e.b,
            ..e
        })
        .value(c0)
            < 0.0
        && fit.rms <= (set.max_rms.0 + set.max_rms.1 * radius) * (e.a / e.b).sqrt()
}

/// Whether the fitted outline closes the circle: just outside it, max(1.5 px, 0.2 ρ) past
/// the boundary on each ray (≥ 1 σ of any PSF up to 1.5 px), but at most [`MAX_CLOSE_OUT`]·ρ
/// (the middle of the dark gap before the neighbours, whose edges lie ≥ 1.67 ρ out: on the
/// minor axis of a steeply tilted small circle, ρ ≈ 1.5–2 px, 1.5 px reached the neighbour's
/// blurred edge), the image is below the mean level on all but [`MAX_SPILL`] of the rays. A fit
/// to part of a circle — what an occluder leaves of it, or one end of a steeply tilted
/// marker's annulus with its inner disk — leaves white outside it. Also false when the
/// outline itself runs off the image on more than [`MAX_CUT_RAYS`] of the rays.
fn closed(img: View<'_>, e: &Ellipse, mid: f32, s: &Scratch) -> bool {
    let (mut seen, mut spilled, mut cut) = (0usize, 0usize, 0usize);
    for &d in &s.dirs {
        let o = ellipse_offset(e, d);
        let rho = o.norm();
        let k = 1.0 + (1.5 / rho).clamp(0.2, MAX_CLOSE_OUT);
        if let Some(v) = img.bilinear(e.center.x + k * o.x, e.center.y + k * o.y) {
            seen += 1;
            spilled += usize::from(v >= mid);
        }
        cut += usize::from(img.bilinear(e.center.x + o.x, e.center.y + o.y).is_none());
    }
    spilled as f64 <= MAX_SPILL * seen as f64 && cut as f64 <= MAX_CUT_RAYS * s.dirs.len() as f64
}

/// Background and foreground levels around the ellipse `g`: the background is the median
/// over rays of the lowest value at 1.3–1.6× the boundary; the foreground the median over
/// rays of the first maximum inside the outer edge (found at a quarter of the contrast to
/// the centre), i.e. the white outer annulus of a marker circle that blur has dimmed, so
/// that the mean level sits on the steep part of the outer edge. The maximum is sought
/// within 0.4× the ray's length (short of a marker's inner disk at 0.45 R), but at least
/// min(2 px, 0.4 a): along the minor axis of a thin ellipse (b ≈ 2–3 px at 70–75° of
/// tilt) 0.4 b ends on the blurred edge and read the foreground ~15 % low, which moved
/// the mean-level crossings out and made b ~20 % too long. `None` below `min_contrast`.
fn levels(img: View<'_>, g: &Ellipse, min_contrast: f32, s: &mut Scratch) -> Option<(f32, f32)> {
    let c = g.center;
    let centre = foreground(img, c, g.b)?;
    s.values.clear();
    for &d in s.dirs.iter().step_by(3) {
        let o = ellipse_offset(g, d);
        let lo = [1.3, 1.45, 1.6]
            .iter()
            .filter_map(|&k| img.bilinear(c.x + k * o.x, c.y + k * o.y))
            .fold(f32::INFINITY, f32::min);
        if lo.is_finite() {
            s.values.push(lo);
        }
    }
    let bg = median(&mut s.values)?;
    if centre - bg < min_contrast {
        return None;
    }
    let quarter = bg + 0.25 * (centre - bg);
    s.values.clear();
    for &d in s.dirs.iter().step_by(3) {
        let o = ellipse_offset(g, d);
        let rho = o.norm();
        let u = o / rho;
        if let Some(t) = inward_crossing(img, c, u, 1.6 * rho, 0.6 * rho, rho / 16.0, quarter) {
            if let Some(top) = first_maximum(
                img,
                c,
                u,
                t,
                (t - (0.4 * rho).max((0.4 * g.a).min(2.0))).max(0.0),
                (rho / 32.0).max(0.25),
                0.05 * (centre - bg),
            ) {
                s.values.push(top);
            }
        }
    }
    let fg = median(&mut s.values)?;
    (fg - bg >= min_contrast).then_some((bg, fg))
}

/// Outward pass from `c` (value `f0` there): on every third ray the first crossing below
/// `mid0` within `m` steps of `step` px; with `annulus`, a rise above the level before 2.2×
/// that crossing and a fall again within 1× of it is taken as a marker's white annulus
/// (0.75–1 R seen from its ring's inner edge at 0.45 R: 1.67–2.22×), and that fall as the
/// outer edge (a plain circle's neighbours start at 2.33 R and are 2 R wide). The robust
/// ellipse through the crossings.
#[allow(clippy::too_many_arguments)]
fn outward_fit(
    img: View<'_>,
    c: Point2<f64>,
    f0: f32,
    mid0: f32,
    step: f64,
    m: usize,
    annulus: bool,
    s: &mut Scratch,
) -> Option<Fit> {
    s.points.clear();
    let rays = s.dirs.len().div_ceil(3);
    for &(dx, dy) in s.dirs.iter().step_by(3) {
        let (mut p, mut t1, mut rise) = (f0, None::<f64>, None::<f64>);
        // Crossing of mid0 between samples j − 1 (value p) and j (value q).
        let cross =
            |j: usize, p: f32, q: f32| step * ((j - 1) as f64 + ((p - mid0) / (p - q)) as f64);
        for j in 1..m {
            let t = j as f64 * step;
            let Some(q) = img.bilinear(c.x + t * dx, c.y + t * dy) else {
                break;
            };
            match (t1, rise) {
                (None, _) if q < mid0 => {
                    t1 = Some(cross(j, p, q));
                    if !annulus {
                        break;
                    }
                }
                (Some(first), None) if q >= mid0 => {
                    let tc = cross(j, p, q);
                    if tc > 2.2 * first {
                        break;
                    }
                    rise = Some(tc);
                }
                (Some(first), Some(r)) if q < mid0 => {
                    let tc = cross(j, p, q);
                    if tc - r <= first {
                        t1 = Some(tc);
                    }
                    break;
                }
                (Some(first), Some(r)) if t - r > first => break,
                (Some(first), None) if t > 2.2 * first => break,
                _ => {}
            }
            p = q;
        }
        if let Some(t) = t1 {
            s.points.push(Point2::new(c.x + t * dx, c.y + t * dy));
        }
    }
    if s.points.len() * 5 < rays * 3 {
        return None;
    }
    let points = std::mem::take(&mut s.points);
    let fit = robust_fit(&points, s);
    s.points = points;
    fit
}

/// Whether the ellipse `e` is the inner disk of a marker circle, closed in by its dark ring
/// and then the white outer annulus. On each of 24 rays (parametric angles of `e`), the
/// profile from 1× to 3.5× the boundary gives its largest rise above the lowest value
/// before it, the position k where that rise peaks, and how far the profile falls again
/// after it. A marker's annulus (0.75–1 R seen from the ring's inner edge at 0.45 R: k ≈
/// 1.7–2.2) is a closed, narrow bump: every ray shows a similar rise (15th percentile ≥ 5 %
/// of the contrast and ≥ 0.4 × the median, so even a ring that blur has made faint), falling
/// back by at least half of it, at a consistent k (MAD < 10 %) between 1.4 and 2.6. A plain
/// circle's neighbours start at 2.33× and are 2× wide: they rise without falling back
/// within 3.5×, and only in the ~60 % of directions that meet one. Returns the median k.
fn ring_annulus(img: View<'_>, e: &Ellipse, contrast: f32, s: &mut Scratch) -> Option<f64> {
    const RAYS: usize = 24;
    s.values.clear();
    s.ks.clear();
    let mut falls_back = 0;
    for i in 0..RAYS {
        let o = ellipse_offset(e, s.dirs[i * s.dirs.len() / RAYS]);
        let dk = (0.75 / o.norm()).clamp(0.04, 0.1);
        let steps = (2.5 / dk).ceil() as usize;
        // Largest rise above the lowest value before it, where it peaks, and the lowest
        // value after that peak.
        let (mut lo, mut rise, mut rise_k, mut peak, mut after) =
            (f32::INFINITY, 0.0f32, 0.0, 0.0f32, f32::INFINITY);
        let mut ok = true;
        for j in 0..=steps {
            let k = 1.0 + j as f64 * dk;
            let Some(v) = img.bilinear(e.center.x + k * o.x, e.center.y + k * o.y) else {
                ok = false;
                break;
            };
            lo = lo.min(v);
            after = after.min(v);
            if v - lo > rise {
                (rise, rise_k, peak, after) = (v - lo, k, v, v);
            }
        }
        if ok {
            s.values.push(rise);
            s.ks.push(rise_k as f32);
            falls_back += usize::from(peak - after >= 0.5 * rise);
        }
    }
    let n = s.values.len();
    if n < RAYS / 2 || falls_back * 100 < n * 85 {
        return None;
    }
    let p15 = *s
        .values
        .select_nth_unstable_by(n * 15 / 100, f32::total_cmp)
        .1;
    let med = median(&mut s.values)?;
    if p15 < 0.05 * contrast || p15 < 0.4 * med {
        return None;
    }
    let k = median(&mut s.ks)?;
    s.values.clear();
    s.values.extend(s.ks.iter().map(|&x| (x - k).abs()));
    let mad = median(&mut s.values)?;
    (mad < 0.1 * k && (1.4..=2.6).contains(&k)).then_some(k as f64)
}

/// The start of an inward walk: `t`, or when the image is at or above `level` there (a guess
/// short of the outline, e.g. one end of a steeply tilted marker's annulus taken for its
/// edge), the first point below it stepping out by ½ px up to `t_max`.
fn outside(img: View<'_>, c: Point2<f64>, u: Vector2<f64>, t: f64, t_max: f64, level: f32) -> f64 {
    let mut t = t;
    while t < t_max
        && img
            .bilinear(c.x + t * u.x, c.y + t * u.y)
            .is_some_and(|v| v >= level)
    {
        t = (t + 0.5).min(t_max);
    }
    t
}

/// Walking inward from `c + t_start·u` in steps of `step` px down to `t_end`, the highest
/// value before the profile falls more than `tolerance` below it.
fn first_maximum(
    img: View<'_>,
    c: Point2<f64>,
    u: Vector2<f64>,
    t_start: f64,
    t_end: f64,
    step: f64,
    tolerance: f32,
) -> Option<f32> {
    let mut best = img.bilinear(c.x + t_start * u.x, c.y + t_start * u.y)?;
    let mut t = t_start - step;
    while t >= t_end {
        let v = img.bilinear(c.x + t * u.x, c.y + t * u.y)?;
        if v < best - tolerance {
            break;
        }
        best = best.max(v);
        t -= step;
    }
    Some(best)
}

/// Distance from `c` along the unit direction `u` to the border of the sampled image
/// [0, w − 1] × [0, h − 1] (just inside it).
fn exit_distance(img: View<'_>, c: Point2<f64>, u: Vector2<f64>) -> f64 {
    let limit = |p: f64, d: f64, hi: f64| {
        if d > 0.0 {
            (hi - p) / d
        } else if d < 0.0 {
            -p / d
        } else {
            f64::INFINITY
        }
    };
    let t = limit(c.x, u.x, (img.width - 1) as f64).min(limit(c.y, u.y, (img.height - 1) as f64));
    (t - 1e-9).max(0.0)
}

/// Walking from `c + t_start·u` towards `c + t_end·u`, the first crossing from below `level`
/// to at or above it: steps of `step` px (≥ 0.5), bisections of the bracket down to
/// ≤ 0.125 px, and linear interpolation there (where the bilinear profile is linear to
/// ≲ 0.002 px). Returns t.
fn inward_crossing(
    img: View<'_>,
    c: Point2<f64>,
    u: Vector2<f64>,
    t_start: f64,
    t_end: f64,
    step: f64,
    level: f32,
) -> Option<f64> {
    let at = |t: f64| img.bilinear(c.x + t * u.x, c.y + t * u.y);
    let step = step.max(0.5);
    let mut bisections = 0;
    while step / f64::from(1 << bisections) > 0.125 {
        bisections += 1;
    }
    let mut t = t_start;
    let mut prev = at(t)?;
    while t > t_end {
        let tn = t - step;
        let v = at(tn)?;
        if prev < level && v >= level {
            // Bracket [lo (below), hi (at or above)] in t order: hi < lo.
            let (mut t_lo, mut v_lo, mut t_hi, mut v_hi) = (t, prev, tn, v);
            for _ in 0..bisections {
                let tm = 0.5 * (t_lo + t_hi);
                let vm = at(tm)?;
                if vm >= level {
                    (t_hi, v_hi) = (tm, vm);
                } else {
                    (t_lo, v_lo) = (tm, vm);
                }
            }
            return Some(t_lo - (t_lo - t_hi) * ((level - v_lo) / (v_hi - v_lo)) as f64);
        }
        t = tn;
        prev = v;
    }
    None
}
