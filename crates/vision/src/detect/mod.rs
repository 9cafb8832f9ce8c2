//! Circle detection (docs/design.md §4): multi-scale Hessian circleness, non-maximum suppression
//! by radius, and a subpixel centre from an ellipse fitted to each circle's outer edge.
//!
//! Takes a grey image and gives every white circle it finds as an [`Ellipse`] with a radius
//! and a quality score. Stages: `circleness` (peaks of the multi-scale circleness on a
//! pyramid), non-maximum suppression by radius, `refine` (outer-edge points and a direct
//! ellipse fit, `fit`), and a final removal of duplicates. Entry point: [`detect`].

mod circleness;
mod filter;
mod fit;
mod refine;
#[cfg(any(test, feature = "testkit"))]
pub mod synth;

use circleness::{Constants, Peak, Scale, FIRST_LEVEL_MIN_SIGMA, LEVEL_SIGMA, MIN_LEVEL_SIGMA};
use filter::{blur_decimate, Kernel, Plane, View};
use hexcal_core::images::{Ellipse, FloatImage};
use nalgebra::Point2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f64::consts::SQRT_2;

/// One detected circle.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Circle {
    /// The fitted outer-boundary ellipse; its centre is the subpixel circle centre.
    pub ellipse: Ellipse,
    /// Circleness at the detection peak (≤ 0.303 for a perfect disk).
    pub score: f64,
    /// Local background (dark) level around the circle.
    pub background: f32,
    /// Local foreground (white) level of the circle.
    pub foreground: f32,
    /// RMS distance of the inlying edge points from the ellipse (px): the fit's quality.
    pub edge_rms: f32,
}

/// Settings of [`detect`]. The defaults suit white circles of radius 4–40 px on a dark
/// background, imaged with a PSF of σ ≲ 1.5 px.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DetectParams {
    /// Smallest radius √(ab) to look for (px). Default 4.
    pub min_radius: f64,
    /// Largest axis ratio a/b of the ellipses to look for: 5 (the default), the thinnest
    /// fit accepted (b/a ≥ 0.2). 1/cos of a 75° tilt is 3.9, but perspective makes the far
    /// side of a board seen at 73° read a/b up to 4.5 (circles of √(ab) = 3 px there have
    /// b = 1.45 px). A disk of radius r responds most at σ = r/√2, a long ellipse (a bar) of
    /// minor semi-axis b = r/√ratio at σ ≈ b: the scales σ = max(r/√2, 1)·2^(k/4) reach down
    /// to the first at or below max(r/√ratio, 1) (1.68 px at r = 4).
    pub max_aspect: f64,
    /// Largest radius to look for (px): the last scale reaches r/√2. Default 40.
    pub max_radius: f64,
    /// Circleness a peak needs. C ≤ 0.303 (an ideal disk), ≈ 0.15 for a disk of the
    /// reference contrast, and less for tilted (elongated) circles: 0.012–0.02 measured on
    /// 4:1 ellipses with b ≈ 2 px (72° of tilt, r ≈ 4 px). Default 0.008; image noise
    /// alone stays below 10⁻⁴, and peaks on clutter are rejected by the edge fit.
    pub min_circleness: f32,
    /// Reference contrast h_ref for β (image units); `None`: 0.3·(P95 − P5) of the image,
    /// at least 10 σ of its noise.
    pub contrast_ref: Option<f32>,
    /// Smallest foreground − background contrast of a circle, as a fraction of h_ref.
    /// Default 0.25.
    pub min_contrast: f32,
    /// Rays (edge points) per circle. Default 90.
    pub rays: usize,
    /// Largest accepted RMS edge-point distance from the fitted ellipse:
    /// `(max_edge_rms + max_edge_rms_per_px · radius) · √(a/b)` (px). Defaults 0.15 and
    /// 0.01: noise scatters the edge points of a real circle by σ_noise / edge slope ≈
    /// 0.02–0.1 px, while stripes, corners and other non-elliptic outlines leave ≳ 0.3 px.
    /// The √(a/b) allows for blur at the sharp ends of a thin ellipse (radius of curvature
    /// b²/a, 0.6 px at 75° of tilt and r = 5 px), which pulls the mean-level contour in
    /// there by up to ~0.6 px: edge RMS 0.2 px on such circles.
    pub max_edge_rms: f64,
    /// See `max_edge_rms`.
    pub max_edge_rms_per_px: f64,
}

impl Default for DetectParams {
    fn default() -> Self {
        DetectParams {
            min_radius: 4.0,
            max_aspect: 5.0,
            max_radius: 40.0,
            min_circleness: 0.008,
            contrast_ref: None,
            min_contrast: 0.25,
            rays: 90,
            max_edge_rms: 0.15,
            max_edge_rms_per_px: 0.01,
        }
    }
}

/// Detects the white circles of a grey image (docs/design.md §4), strongest first.
pub fn detect(image: &FloatImage, params: &DetectParams) -> Vec<Circle> {
    let (w, h) = (image.width() as usize, image.height() as usize);
    if w < 8 || h < 8 {
        return Vec::new();
    }
    let full = View {
        data: image.as_raw(),
        width: w,
        height: h,
    };
    let h_ref = params
        .contrast_ref
        .map_or_else(|| circleness::reference_contrast(full), |c| c as f64);
    if h_ref.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return Vec::new();
    }
    // Peaks at the scales below r_min/√2, there for thin foreshortened circles, are refined
    // after the others: on a rounder circle they mark parts of it (a marker's annulus) and
    // would refine to a worse fit of a circle the others find whole. The thinnest scales,
    // below r_min/2 (axis ratios 4–5), are suppressed among themselves only and refined
    // last: there a marker's inner disk outscores its whole circle's peak (docs/design.md §4).
    let sigma_disk = (params.min_radius / SQRT_2).max(1.0) - 1e-9;
    let sigma_thinnest = 0.5 * params.min_radius - 1e-9;
    let (peaks, thinnest): (Vec<Peak>, Vec<Peak>) =
        circleness_peaks(full, params, Constants::new(h_ref))
            .into_iter()
            .partition(|p| p.sigma >= sigma_thinnest);
    let (mut peaks, thin): (Vec<Peak>, Vec<Peak>) = suppress(peaks)
        .into_iter()
        .partition(|p| p.sigma >= sigma_disk);
    peaks.extend(thin);
    peaks.extend(suppress(thinnest));
    let settings = refine::Settings {
        rays: params.rays.max(12),
        min_contrast: (params.min_contrast as f64 * h_ref) as f32,
        radius_range: (0.5 * params.min_radius, 1.5 * params.max_radius),
        max_rms: (params.max_edge_rms, params.max_edge_rms_per_px),
    };
    let mut circles = remove_duplicates(refine_all(full, &peaks, &settings));
    circles.sort_by(|a, b| b.score.total_cmp(&a.score));
    circles
}

/// Scales σ_k = σ_disk·2^(k/4), σ_disk = max(r_min/√2, 1), from the first at or below
/// max(r_min/√max_aspect, 1) up to the first reaching r_max/√2, grouped into pyramid
/// octaves; the peaks of every octave in full-resolution coordinates. Anchoring the scales
/// on the disk scale keeps them where they are when max_aspect only adds thinner ones.
fn circleness_peaks(full: View<'_>, params: &DetectParams, k: Constants) -> Vec<Peak> {
    let sigma_disk = (params.min_radius / SQRT_2).max(1.0);
    let sigma_thin = (params.min_radius / params.max_aspect.max(1.0).sqrt()).max(1.0);
    let below = (4.0 * (sigma_disk / sigma_thin).log2() - 1e-9)
        .ceil()
        .max(0.0);
    let sigma_min = sigma_disk * 2f64.powf(-below / 4.0);
    let sigma_max = (params.max_radius / SQRT_2).max(sigma_min);
    let n_scales = (4.0 * (sigma_max / sigma_min).log2() - 1e-9)
        .ceil()
        .max(0.0) as usize
        + 1;
    let octave_of = |sigma: f64| {
        let o = ((sigma / MIN_LEVEL_SIGMA).log2() + 1e-9).floor().max(0.0) as usize;
        o.max(usize::from(sigma >= FIRST_LEVEL_MIN_SIGMA - 1e-9))
    };
    let sigmas: Vec<f64> = (0..n_scales)
        .map(|i| sigma_min * 2f64.powf(i as f64 / 4.0))
        .collect();
    let n_octaves = octave_of(sigmas[n_scales - 1]) + 1;
    let mut peaks = Vec::new();
    let mut level: Option<Plane> = None; // None: the input itself
    for o in 0..n_octaves {
        let step = (1usize << o) as f64;
        let src_sigma = if o == 0 { 0.0 } else { LEVEL_SIGMA };
        let scales: Vec<Scale> = sigmas
            .iter()
            .filter(|&&s| octave_of(s) == o)
            .map(|&s| {
                let sigma = s / step;
                Scale {
                    sigma,
                    kernel: Kernel::gaussian((sigma * sigma - src_sigma * src_sigma).sqrt(), 3.0),
                }
            })
            .collect();
        let view = level.as_ref().map_or(full, Plane::view);
        peaks.extend(circleness::octave_peaks(
            view,
            step,
            &scales,
            k,
            params.min_circleness,
        ));
        if o + 1 < n_octaves {
            let blur = (4.0 * LEVEL_SIGMA * LEVEL_SIGMA - src_sigma * src_sigma).sqrt();
            let next = blur_decimate(view, blur);
            level = Some(next);
        }
    }
    peaks
}

/// Spatial hash of points with square cells, for radius queries.
struct Buckets {
    cell: f64,
    cols: usize,
    rows: usize,
    items: Vec<Vec<usize>>,
}

impl Buckets {
    fn new(cell: f64, max_x: f64, max_y: f64) -> Buckets {
        let cols = (max_x / cell).floor() as usize + 2;
        let rows = (max_y / cell).floor() as usize + 2;
        Buckets {
            cell,
            cols,
            rows,
            items: vec![Vec::new(); cols * rows],
        }
    }

    fn index(&self, p: Point2<f64>) -> (usize, usize) {
        let c = ((p.x / self.cell).floor().max(0.0) as usize).min(self.cols - 1);
        let r = ((p.y / self.cell).floor().max(0.0) as usize).min(self.rows - 1);
        (c, r)
    }

    fn insert(&mut self, p: Point2<f64>, item: usize) {
        let (c, r) = self.index(p);
        self.items[r * self.cols + c].push(item);
    }

    /// Items in the cells that overlap the box [x0, x1] × [y0, y1].
    fn in_box(&self, x0: f64, y0: f64, x1: f64, y1: f64) -> impl Iterator<Item = usize> + '_ {
        let (c0, r0) = self.index(Point2::new(x0, y0));
        let (c1, r1) = self.index(Point2::new(x1, y1));
        (r0..=r1).flat_map(move |rr| {
            (c0..=c1).flat_map(move |cc| self.items[rr * self.cols + cc].iter().copied())
        })
    }

    /// Items in the 3×3 cells around p (all within `cell` of p, and more).
    fn near(&self, p: Point2<f64>) -> impl Iterator<Item = usize> + '_ {
        let (c, r) = self.index(p);
        let (c0, r0) = (c.saturating_sub(1), r.saturating_sub(1));
        let (c1, r1) = ((c + 1).min(self.cols - 1), (r + 1).min(self.rows - 1));
        (r0..=r1).flat_map(move |rr| {
            (c0..=c1).flat_map(move |cc| self.items[rr * self.cols + cc].iter().copied())
        })
    }
}

/// Non-maximum suppression by radius (docs/design.md §4): strongest first, a peak within
/// r̂ = √2·σ* of a stronger kept one is dropped.
fn suppress(mut peaks: Vec<Peak>) -> Vec<Peak> {
    peaks.sort_by(|a, b| b.score.total_cmp(&a.score));
    let cell = peaks.iter().map(|p| SQRT_2 * p.sigma).fold(1.0, f64::max);
    let max_x = peaks.iter().map(|p| p.x).fold(0.0, f64::max);
    let max_y = peaks.iter().map(|p| p.y).fold(0.0, f64::max);
    let mut grid = Buckets::new(cell, max_x, max_y);
    let mut kept: Vec<Peak> = Vec::new();
    for p in peaks {
        let at = Point2::new(p.x, p.y);
        if !grid
            .near(at)
            .any(|i| (Point2::new(kept[i].x, kept[i].y) - at).norm() < SQRT_2 * kept[i].sigma)
        {
            grid.insert(at, kept.len());
            kept.push(p);
        }
    }
    kept
}

/// Refines the peaks (in the given order) in parallel waves; after each wave, the peaks that
/// lie inside a circle found so far are skipped: one circle can hold several peaks that
/// NMS keeps (a marker's inner disk and points on its white annulus, the curved inner side
/// of a large disk's edge), and refining them would only find it again.
fn refine_all(full: View<'_>, peaks: &[Peak], settings: &refine::Settings) -> Vec<Circle> {
    const WAVE_PER_THREAD: usize = 16;
    let wave = WAVE_PER_THREAD * rayon::current_num_threads();
    let max_x = peaks.iter().map(|p| p.x).fold(0.0, f64::max);
    let max_y = peaks.iter().map(|p| p.y).fold(0.0, f64::max);
    const CELL: f64 = 32.0;
    let mut grid = Buckets::new(CELL, max_x, max_y);
    for (i, p) in peaks.iter().enumerate() {
        grid.insert(Point2::new(p.x, p.y), i);
    }
    let mut skip = vec![false; peaks.len()];
    let mut circles = Vec::new();
    let mut next = 0;
    while next < peaks.len() {
        let mut batch = Vec::with_capacity(wave);
        while next < peaks.len() && batch.len() < wave {
            if !skip[next] {
                batch.push(next);
            }
            next += 1;
        }
        let found: Vec<Circle> = batch
            .par_iter()
            .map_init(refine::Scratch::default, |s, &i| {
                let p = &peaks[i];
                refine::refine(
                    full,
                    Point2::new(p.x, p.y),
                    SQRT_2 * p.sigma,
                    p.score,
                    settings,
                    s,
                )
            })
            .flatten()
            .collect();
        for c in &found {
            let conic = fit::Conic::from_ellipse(&c.ellipse);
            let e = &c.ellipse;
            for i in grid.in_box(
                e.center.x - e.a,
                e.center.y - e.a,
                e.center.x + e.a,
                e.center.y + e.a,
            ) {
                if i >= next && conic.value(Point2::new(peaks[i].x, peaks[i].y)) < 0.0 {
                    skip[i] = true;
                }
            }
        }
        circles.extend(found);
    }
    circles
}

/// Several peaks can refine to the same circle (e.g. a marker's inner disk and the whole
/// circle): in the order of refinement, a circle whose centre lies inside a kept one's
/// ellipse, or whose ellipse holds a kept centre, is dropped.
fn remove_duplicates(circles: Vec<Circle>) -> Vec<Circle> {
    let cell = circles.iter().map(|c| c.ellipse.a).fold(1.0, f64::max);
    let max_x = circles
        .iter()
        .map(|c| c.ellipse.center.x)
        .fold(0.0, f64::max);
    let max_y = circles
        .iter()
        .map(|c| c.ellipse.center.y)
        .fold(0.0, f64::max);
    let mut grid = Buckets::new(cell, max_x, max_y);
    let inside = |e: &Ellipse, p: Point2<f64>| fit::Conic::from_ellipse(e).value(p) < 0.0;
    let mut kept: Vec<Circle> = Vec::new();
    for c in circles {
        let at = c.ellipse.center;
        let dup = grid
            .near(at)
            .any(|i| inside(&kept[i].ellipse, at) || inside(&c.ellipse, kept[i].ellipse.center));
        if !dup {
            grid.insert(at, kept.len());
            kept.push(c);
        }
    }
    kept
}

#[cfg(test)]
mod tests;
