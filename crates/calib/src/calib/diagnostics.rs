//! Diagnostics of a calibration: per-device residual statistics (the paper's Table I), the
//! RMS the joint fit expects, and the warnings a user should act on.
//!
//! Takes a [`Calibration`]; gives numbers and sentences. The report only formats them.

use super::solve::Calibration;
use super::verify::PairCheck;
use hexcal_core::camera::{CameraModel, LensParam};
use hexcal_core::observations::DeviceKind;
use nalgebra::{DMatrix, Isometry3, Point2, Point3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;

/// Devices seen in fewer board poses than this are warned about.
pub const MIN_POSES: usize = 3;
/// A device's RMS above this multiple of its kind's median, or of the RMS the joint fit
/// expects, is warned about.
pub const RMS_RATIO: f64 = 1.5;
/// Image cells (columns, rows) of the coverage check.
pub const COVERAGE_CELLS: (usize, usize) = (8, 5);

/// What the user needs of the calibration (the rig file's `[guidance]`, `hexcal calibrate
/// --target-px/--target-mm`): a warning fires only where the calibration misses it, or where
/// a check is out of family by more than it (docs/design.md §8, "Warnings").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Target {
    /// Projection uncertainty (px, 1σ) every device should stay below over its image: the
    /// operator console's done rule uses the same number.
    pub uncertainty_px: f64,
    /// Held-out length error (mm RMS over the verification pairs) the rig should meet.
    pub length_mm: f64,
}

/// Default [`Target::uncertainty_px`]: mrcal's default for its valid-intrinsics region.
pub const DEFAULT_TARGET_PX: f64 = VALID_UNCERTAINTY;
/// Default [`Target::length_mm`]: the acceptance bound of the simulated paper rig.
pub const DEFAULT_TARGET_MM: f64 = 0.1;

impl Default for Target {
    fn default() -> Self {
        Target {
            uncertainty_px: DEFAULT_TARGET_PX,
            length_mm: DEFAULT_TARGET_MM,
        }
    }
}

/// What is said about a calibration, computed once and shown alike by the HTML page, the
/// residual files and the printed summary: the residual table, every warning and the notes.
#[derive(Clone, Debug, PartialEq)]
pub struct Diagnosis {
    /// Per device (as in the calibration), the paper's Table I row.
    pub rows: Vec<ResidualRow>,
    /// The report's own warnings ([`warnings`]), then the verification's
    /// ([`verification_warnings`]), then the caller's (skipped poses, refused stacks).
    pub warnings: Vec<String>,
    /// What is worth knowing but needs no action (outliers of one steep view).
    pub notes: Vec<String>,
    /// The target the warnings were judged against.
    pub target: Target,
}

impl Diagnosis {
    /// The diagnosis of `cal` against the user's `target`, verified by `verification` (may
    /// be empty), with the caller's own warnings `extra` last.
    pub fn of(
        cal: &Calibration,
        verification: &[PairCheck],
        extra: &[String],
        target: &Target,
    ) -> Diagnosis {
        let rows = residual_table(cal);
        let is_projector = |name: &str| {
            cal.devices
                .iter()
                .any(|d| d.name == name && d.kind == DeviceKind::Projector)
        };
        let mut notes = Vec::new();
        let warnings = warnings(cal, &rows, target, &mut notes)
            .into_iter()
            .chain(verification_warnings(verification, is_projector, target))
            .chain(extra.iter().cloned())
            .collect();
        notes.extend(noise_limited_pairs(verification, target));
        Diagnosis {
            rows,
            warnings,
            notes,
            target: *target,
        }
    }
}

/// One row of the paper's Table I: a device's residual statistics.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualRow {
    /// Device name.
    pub name: String,
    /// Camera or projector.
    pub kind: DeviceKind,
    /// Observations used (inliers).
    pub points: usize,
    /// Observations rejected as outliers.
    pub outliers: usize,
    /// Mean of the inliers' residual norms (px).
    pub mean: f64,
    /// Standard deviation of the inliers' residual norms (px).
    pub std: f64,
    /// RMS of the inliers' residual norms (px).
    pub rms: f64,
    /// Board poses in which the device has observations.
    pub poses: usize,
}

/// The per-device residual table of a calibration.
pub fn residual_table(cal: &Calibration) -> Vec<ResidualRow> {
    cal.devices
        .iter()
        .enumerate()
        .map(|(d, dev)| {
            let (mut norms, mut outliers, mut poses) = (Vec::new(), 0, BTreeSet::new());
            for (o, r) in cal.observations.iter().zip(&cal.solution.residuals) {
                if o.device == d {
                    poses.insert(o.pose);
                    if r.outlier {
                        outliers += 1;
                    } else {
                        norms.push(r.error.norm());
                    }
                }
            }
            let n = norms.len().max(1) as f64;
            let mean = norms.iter().sum::<f64>() / n;
            let var = norms.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
            let rms = (norms.iter().map(|x| x * x).sum::<f64>() / n).sqrt();
            ResidualRow {
                name: dev.name.clone(),
                kind: dev.kind,
                points: norms.len(),
                outliers,
                mean,
                std: var.sqrt(),
                rms,
                poses: poses.len(),
            }
        })
        .collect()
}

/// RMS of 2D residual norms the joint fit expects: √2·σ̂·√(1 − p/n) (docs/design.md §8).
pub fn expected_rms(cal: &Calibration) -> f64 {
    let (n, p) = cal.solution.dof;
    let keep = if n > 0 {
        (1.0 - p as f64 / n as f64).max(0.0)
    } else {
        1.0
    };
    std::f64::consts::SQRT_2 * cal.solution.sigma * keep.sqrt()
}

/// Per device, the fraction of its image cells ([`COVERAGE_CELLS`]) holding no inlier
/// observation, and which of the four corner cells (top-left, top-right, bottom-left,
/// bottom-right) are empty.
pub fn coverage(cal: &Calibration) -> Vec<(f64, [bool; 4])> {
    let (nx, ny) = COVERAGE_CELLS;
    cal.devices
        .iter()
        .enumerate()
        .map(|(d, dev)| {
            let mut hit = vec![false; nx * ny];
            let (w, h) = (dev.model.width as f64, dev.model.height as f64);
            for (o, r) in cal.observations.iter().zip(&cal.solution.residuals) {
                let (x, y) = (o.pixel.x + 0.5, o.pixel.y + 0.5);
                if o.device == d && !r.outlier && x >= 0.0 && y >= 0.0 && x < w && y < h {
                    let (i, j) = ((x / w * nx as f64) as usize, (y / h * ny as f64) as usize);
                    hit[j.min(ny - 1) * nx + i.min(nx - 1)] = true;
                }
            }
            let empty = hit.iter().filter(|&&h| !h).count() as f64 / hit.len() as f64;
            let corners = [0, nx - 1, (ny - 1) * nx, ny * nx - 1].map(|c| !hit[c]);
            (empty, corners)
        })
        .collect()
}

/// The covariance of device `d`'s free lens parameters (a block of (33)) and which they
/// are, in [`LensParam`] order.
pub fn lens_covariance(cal: &Calibration, d: usize) -> (Vec<LensParam>, DMatrix<f64>) {
    let sol = &cal.solution;
    let free: Vec<LensParam> = sol.free[d].iter().collect();
    let at = sol.index[d].0;
    let n = free.len();
    let idx: Vec<usize> = (at..at + n).collect();
    (free, sol.covariance.block(&idx))
}

/// Projection uncertainty (px, 1σ along the worst direction) of device `d` at `pixel`:
/// the lens covariance propagated to the pixel of the ray through it, J·Σ·Jᵀ with J the
/// lens Jacobian (J5) at that ray; the device's pose is held (docs/design.md §8).
pub fn projection_uncertainty(cal: &Calibration, d: usize, pixel: Point2<f64>) -> Option<f64> {
    let (free, cov) = lens_covariance(cal, d);
    lens_uncertainty(&cal.devices[d].model, &free, &cov, pixel)
}

/// Projection uncertainty (px, 1σ along the worst direction) at `pixel` of lens `m` whose
/// parameters `free` have covariance `cov`: J·Σ·Jᵀ with J the lens Jacobian (J5) at the
/// ray through the pixel.
pub fn lens_uncertainty(
    m: &CameraModel,
    free: &[LensParam],
    cov: &DMatrix<f64>,
    pixel: Point2<f64>,
) -> Option<f64> {
    let ray = m.ray(pixel)?;
    let j = m
        .project_with_jacobians(&Isometry3::identity(), &Point3::from(ray))?
        .d_lens;
    let js = DMatrix::from_fn(2, free.len(), |r, c| j[(r, free[c].index())]);
    let s = &js * cov * js.transpose();
    Some(s.symmetric_eigenvalues().max().max(0.0).sqrt())
}

/// Uncertainty (px, 1σ along the worst direction) of device `d`'s lens at `pixel` relative
/// to its image centre: the lens covariance propagated to the difference of the two
/// projections, (J_p − J_c)·Σ·(J_p − J_c)ᵀ with J the lens Jacobian (J5) at each pixel's
/// ray. A shift common to the whole image (principal point against the device's rotation)
/// cancels, so what remains is how uncertain the lens's shape is there: where the model
/// extrapolates (docs/design.md §8, "Warnings").
pub fn shape_uncertainty(cal: &Calibration, d: usize, pixel: Point2<f64>) -> Option<f64> {
    let m = &cal.devices[d].model;
    let (free, cov) = lens_covariance(cal, d);
    let centre = Point2::new(m.width as f64 / 2.0 - 0.5, m.height as f64 / 2.0 - 0.5);
    let jac = |p: Point2<f64>| {
        let ray = m.ray(p)?;
        let j = m
            .project_with_jacobians(&Isometry3::identity(), &Point3::from(ray))?
            .d_lens;
        Some(DMatrix::from_fn(2, free.len(), |r, c| {
            j[(r, free[c].index())]
        }))
    };
    let js = jac(pixel)? - jac(centre)?;
    let s = &js * cov * js.transpose();
    Some(s.symmetric_eigenvalues().max().max(0.0).sqrt())
}

/// Projection uncertainty (px) below which a pixel counts as well determined: mrcal's
/// default for its valid-intrinsics region.
pub const VALID_UNCERTAINTY: f64 = 1.0;
/// Directions of the valid-intrinsics polygon.
const REGION_DIRECTIONS: usize = 36;

/// Device `d`'s valid-intrinsics region: a polygon (px) around the principal point whose
/// vertex in each of 36 directions is the farthest point, walking out in
/// 1 % steps of the image diagonal and within the image, up to which the
/// [`projection_uncertainty`] stays below `threshold` (px). `None` when the principal
/// point itself is not below it. A star-shaped approximation of the region.
pub fn valid_region(cal: &Calibration, d: usize, threshold: f64) -> Option<Vec<[f64; 2]>> {
    let m = &cal.devices[d].model;
    let (w, h) = (m.width as f64 - 1.0, m.height as f64 - 1.0);
    let c = Point2::new(m.intrinsics.cx.clamp(0.0, w), m.intrinsics.cy.clamp(0.0, h));
    let ok = |p: Point2<f64>| projection_uncertainty(cal, d, p).is_some_and(|u| u < threshold);
    if !ok(c) {
        return None;
    }
    let step = 0.01 * (w * w + h * h).sqrt();
    let inside = |p: &Point2<f64>| p.x >= 0.0 && p.y >= 0.0 && p.x <= w && p.y <= h;
    let polygon = (0..REGION_DIRECTIONS)
        .map(|k| {
            let a = std::f64::consts::TAU * k as f64 / REGION_DIRECTIONS as f64;
            let dir = nalgebra::Vector2::new(a.cos(), a.sin()) * step;
            let mut p = c;
            while inside(&(p + dir)) && ok(p + dir) {
                p += dir;
            }
            [p.x, p.y]
        })
        .collect();
    Some(polygon)
}

/// The four image corners of device `d` (pixel centres), top-left first.
fn corners(cal: &Calibration, d: usize) -> [Point2<f64>; 4] {
    let m = &cal.devices[d].model;
    let (w, h) = (m.width as f64 - 1.0, m.height as f64 - 1.0);
    [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)].map(|(x, y)| Point2::new(x, y))
}

/// The nine parts of an image (thirds across and down, row by row) that warnings name.
const REGION_NAMES: [&str; 9] = [
    "top-left corner",
    "top edge",
    "top-right corner",
    "left edge",
    "centre",
    "right edge",
    "bottom-left corner",
    "bottom edge",
    "bottom-right corner",
];

/// Where device `d`'s lens model extrapolates beyond the user's target: over the corners
/// and centres of its [`COVERAGE_CELLS`] (image corners included), the points whose
/// [`shape_uncertainty`] exceeds `limit` (px), as (uncertainty, pixel, region index), worst
/// first.
fn uncertain_points(cal: &Calibration, d: usize, limit: f64) -> Vec<(f64, Point2<f64>, usize)> {
    let m = &cal.devices[d].model;
    let (w, h) = (m.width as f64 - 1.0, m.height as f64 - 1.0);
    let (nx, ny) = COVERAGE_CELLS;
    let mut at = Vec::new();
    for j in 0..=2 * ny {
        for i in 0..=2 * nx {
            at.push(Point2::new(
                w * i as f64 / (2 * nx) as f64,
                h * j as f64 / (2 * ny) as f64,
            ));
        }
    }
    let region = |p: &Point2<f64>| {
        let third = |x: f64, size: f64| ((3.0 * x / size) as usize).min(2);
        3 * third(p.y, h + 1.0) + third(p.x, w + 1.0)
    };
    let mut out: Vec<(f64, Point2<f64>, usize)> = at
        .into_iter()
        .filter_map(|p| Some((shape_uncertainty(cal, d, p)?, p, region(&p))))
        .filter(|u| u.0 > limit)
        .collect();
    out.sort_by(|a, b| b.0.total_cmp(&a.0));
    out
}

/// Distortion terms of device `d` still estimated whose estimate lies within 3σ of zero
/// while their 1σ moves the farthest image corner by more than `limit` px (a term that
/// matters against the user's target and is not known), as "k1 = v ± s (…)". The radial
/// terms the data cannot determine are fixed before ([`super::lens_model`]); this names
/// the others.
fn undetermined_terms(cal: &Calibration, d: usize, limit: f64) -> Vec<String> {
    let (free, cov) = lens_covariance(cal, d);
    let m = &cal.devices[d].model;
    let values = m.lens_vector();
    let far = corners(cal, d)
        .into_iter()
        .filter_map(|p| m.ray(p))
        .max_by(|a, b| a.xy().norm().total_cmp(&b.xy().norm()));
    let Some(jac) =
        far.and_then(|ray| m.project_with_jacobians(&Isometry3::identity(), &Point3::from(ray)))
    else {
        return Vec::new();
    };
    let mut terms = Vec::new();
    for (i, p) in free.iter().enumerate().filter(|(_, p)| p.index() >= 4) {
        let std = cov[(i, i)].max(0.0).sqrt();
        let value = values[p.index()];
        let col = jac.d_lens.column(p.index()).norm();
        if value.abs() < 3.0 * std && col * std > limit {
            terms.push(format!(
                "{} = {value:.4} ± {std:.4} (its σ moves the corner by {:.3} px)",
                p.name(),
                col * std
            ));
        }
    }
    terms
}

/// One warning per device about its lens: the regions where its model extrapolates
/// ([`uncertain_points`]) with the worst uncertainty and how many image cells hold no
/// observed point, and the terms the data cannot determine ([`undetermined_terms`]);
/// with where to put the board. A coverage hole the rest of the image determines is not
/// worth a pose and is not mentioned.
fn lens_warnings(cal: &Calibration, target: &Target, w: &mut Vec<String>) {
    let (nx, ny) = COVERAGE_CELLS;
    let limit = target.uncertainty_px;
    for (d, (empty, _)) in coverage(cal).into_iter().enumerate() {
        let points = uncertain_points(cal, d, limit);
        let terms = undetermined_terms(cal, d, limit);
        if points.is_empty() && terms.is_empty() {
            continue;
        }
        let mut regions: Vec<usize> = points.iter().map(|p| p.2).collect();
        regions.sort_unstable();
        regions.dedup();
        let names: Vec<&str> = regions.iter().map(|&r| REGION_NAMES[r]).collect();
        let name = &cal.devices[d].name;
        let mut text = format!("{name}:");
        if let Some(&(worst, at, _)) = points.first() {
            text += &format!(
                " the lens model extrapolates in its {}: projection uncertainty up to \
                 {worst:.3} px relative to its centre (at pixel {:.0}, {:.0}), above your \
                 {limit} px target; {:.0} % of its {nx} × {ny} image cells hold no \
                 observed point.",
                names.join(", "),
                at.x,
                at.y,
                100.0 * empty,
            );
        }
        if !terms.is_empty() {
            text += &format!(
                " The data cannot determine {}: each is within 3σ of zero.",
                terms.join(", ")
            );
        }
        text += &format!(
            " Add poses with the board in {name}'s {}.",
            if names.is_empty() {
                "corners and edges".to_string()
            } else {
                names.join(", ")
            }
        );
        w.push(text);
    }
}

/// ln(k!) (exact sum up to 30, Stirling's series beyond).
fn ln_factorial(k: u64) -> f64 {
    if k <= 30 {
        return (2..=k).map(|i| (i as f64).ln()).sum();
    }
    let x = k as f64;
    x * x.ln() - x + 0.5 * (std::f64::consts::TAU * x).ln() + 1.0 / (12.0 * x)
        - 1.0 / (360.0 * x.powi(3))
}

/// P(X ≥ k) for X Poisson with mean `lambda` > 0 (the upper tail summed until its terms
/// vanish; 1 for k ≤ λ, where it is not needed).
fn poisson_tail(k: u64, lambda: f64) -> f64 {
    if k as f64 <= lambda {
        return 1.0;
    }
    let mut sum = 0.0;
    for i in k.. {
        let term = (-lambda + i as f64 * lambda.ln() - ln_factorial(i)).exp();
        sum += term;
        if term < 1e-17 * sum || i > k + 100_000 {
            break;
        }
    }
    sum.min(1.0)
}

/// Outlier rate that rejection at [`super::bundle::Options::outlier_sigmas`] = 4 robust σ
/// gives on Gaussian noise alone: P(|r| > 4σ) = e⁻⁸ for 2D residual norms (Rayleigh).
pub const GAUSSIAN_OUTLIER_RATE: f64 = 3.354_626_279_025_119e-4;

/// A device's outlier count is out of family when, against the rate of its peers (the
/// other devices of its kind, or all others when it has fewer than two; at least
/// [`GAUSSIAN_OUTLIER_RATE`]), it is at least twice the expected count and a Poisson
/// count that high has a probability below 10⁻³ divided by the number of devices.
pub const OUTLIER_SIGNIFICANCE: f64 = 1e-3;

/// Outliers this concentrated in a few of a device's poses (at most a quarter of them,
/// at least one) are those views', not the device's.
pub const FEW_VIEWS_SHARE: f64 = 0.8;

/// Device `d`'s outliers by board pose, when [`FEW_VIEWS_SHARE`] of them lie in at most a
/// quarter of the poses it sees: those poses (input index, with the angle in degrees
/// between the board's normal and the line from the device to the board's centre there),
/// most outliers first, and the share they hold.
fn outliers_in_few_views(cal: &Calibration, d: usize) -> Option<(Vec<(usize, f64)>, f64)> {
    let mut count = std::collections::BTreeMap::<usize, usize>::new();
    let mut seen = BTreeSet::new();
    for (o, r) in cal.observations.iter().zip(&cal.solution.residuals) {
        if o.device == d {
            seen.insert(o.pose);
            if r.outlier {
                *count.entry(o.pose).or_default() += 1;
            }
        }
    }
    let total: usize = count.values().sum();
    let mut by: Vec<(usize, usize)> = count.into_iter().collect();
    by.sort_by_key(|p| std::cmp::Reverse(p.1));
    let few = (seen.len() / 4).max(1);
    let held: usize = by.iter().take(few).map(|p| p.1).sum();
    let share = held as f64 / total.max(1) as f64;
    if total == 0 || share < FEW_VIEWS_SHARE {
        return None;
    }
    let mut poses = Vec::new();
    let mut acc = 0;
    for &(pose, n) in &by {
        let t = cal.devices[d].pose * cal.solution.boards[pose];
        let normal = t.rotation * nalgebra::Vector3::z();
        let towards = t.translation.vector.normalize();
        let tilt = normal
            .dot(&towards)
            .abs()
            .clamp(0.0, 1.0)
            .acos()
            .to_degrees();
        poses.push((cal.pose_index.get(pose).copied().unwrap_or(pose), tilt));
        acc += n;
        if acc as f64 >= FEW_VIEWS_SHARE * total as f64 {
            break;
        }
    }
    Some((poses, acc as f64 / total as f64))
}

/// Devices with many more outliers than their peers ([`OUTLIER_SIGNIFICANCE`]): a warning
/// when they are spread over its views (a device fault: focus, exposure, a move), a note
/// naming the poses when a few views hold [`FEW_VIEWS_SHARE`] of them (steep or spoiled
/// views, left out; nothing to do).
fn outlier_warnings(
    cal: &Calibration,
    rows: &[ResidualRow],
    w: &mut Vec<String>,
    notes: &mut Vec<String>,
) {
    let total = |r: &ResidualRow| (r.points + r.outliers) as f64;
    for (d, (dev, row)) in cal.devices.iter().zip(rows).enumerate() {
        let same = |e: usize, r: &ResidualRow| e != d && r.kind == row.kind;
        let kind_peers = rows.iter().enumerate().filter(|(e, r)| same(*e, r)).count();
        let peers: Vec<&ResidualRow> = rows
            .iter()
            .enumerate()
            .filter(|(e, r)| *e != d && (kind_peers < 2 || same(*e, r)))
            .map(|(_, r)| r)
            .collect();
        let seen: f64 = peers.iter().map(|r| total(r)).sum();
        if peers.is_empty() || seen == 0.0 || total(row) == 0.0 {
            continue;
        }
        let peer_rate = peers.iter().map(|r| r.outliers as f64).sum::<f64>() / seen;
        let expected = total(row) * peer_rate.max(GAUSSIAN_OUTLIER_RATE);
        let k = row.outliers as u64;
        let p = poisson_tail(k, expected);
        if k as f64 >= 2.0 * expected && p < OUTLIER_SIGNIFICANCE / rows.len() as f64 {
            if let Some((poses, share)) = outliers_in_few_views(cal, d) {
                let named: Vec<String> = (poses.iter())
                    .map(|(p, tilt)| format!("pose {p} (the board at {tilt:.0}° to its view)"))
                    .collect();
                notes.push(format!(
                    "{}: {:.1} % of its observations are outliers, {:.0} % of them in {}: \
                     those views' points there were left out; the device itself fits as its \
                     peers do.",
                    dev.name,
                    100.0 * row.outliers as f64 / total(row),
                    100.0 * share,
                    named.join(", ")
                ));
                continue;
            }
            w.push(format!(
                "{}: {} of its {} observations ({:.2} %) are outliers, where its peers' \
                 rate ({:.3} %) predicts {expected:.1} (chance {p:.1e}): check its focus, \
                 exposure and mounting (a moved {} gives outliers in every pose after the \
                 move), then recalibrate.",
                dev.name,
                row.outliers,
                total(row),
                100.0 * row.outliers as f64 / total(row),
                100.0 * peer_rate,
                kind_name(dev.kind)
            ));
        }
    }
}

/// Each device's observation noise (px per axis, in `cal.devices` order): its inliers'
/// residual RMS over √2 (the table's RMS is of residual vectors); NaN for a device without
/// a row. What [`crate::calib::verify::verify_with_noise`] predicts pairs' errors from.
pub fn observation_noise(cal: &Calibration) -> Vec<f64> {
    let rows = residual_table(cal);
    (cal.devices.iter())
        .map(|d| match rows.iter().find(|r| r.name == d.name) {
            Some(r) => r.rms / std::f64::consts::SQRT_2,
            None => f64::NAN,
        })
        .collect()
}

/// A verification pair is out of family when its modified z-score among the pairs of its
/// type, 0.6745·(x − median)/MAD of the length RMS x, exceeds this (Iglewicz and
/// Hoaglin's cut-off for outliers; robust to the outliers themselves).
pub const PAIR_Z: f64 = 3.5;

/// Verification pairs whose error the calibration, not the measurement, makes and that
/// miss the user's target, with at least three pairs of the type for the family test;
/// `is_projector` tells a device's kind by name. A pair whose predicted noise is known
/// ([`PairCheck::predicted_rms`], (39)) is warned about when what its noise does not
/// explain, √(rms² − predicted²), exceeds the target; one without, when it is out of
/// family ([`PAIR_Z`]) among the pairs of its type (two cameras, or a camera and a
/// projector, which triangulate with different precision) and above the target.
pub fn verification_warnings(
    checks: &[PairCheck],
    is_projector: impl Fn(&str) -> bool,
    target: &Target,
) -> Vec<String> {
    let kind = |k: &PairCheck| is_projector(&k.first) || is_projector(&k.second);
    let mut out = Vec::new();
    for k in checks {
        let what = match k.predicted_rms {
            Some(p) => calibration_part(k, p, target),
            None => out_of_family(k, checks, &kind, target),
        };
        out.extend(what.map(|why| {
            format!(
                "Verification pair {}–{} (held-out pose {}): length RMS {:.4} mm (max {:.4} \
                 mm) {why}: recheck these two devices (a moved device, a lens poorly covered \
                 where this pose lies) before trusting their measurements.",
                k.first, k.second, k.pose, k.length_rms, k.length_max,
            )
        }));
    }
    if let Some(rms) = super::verify::verification_rms(checks).filter(|r| *r > target.length_mm) {
        out.push(format!(
            "The held-out length error is {rms:.4} mm RMS over {} pairs, above your {} mm \
             target: add poses where the lenses are least certain (the report's uncertainty \
             maps), or check the board's scale and flatness.",
            checks.len(),
            target.length_mm
        ));
    }
    out
}

/// Why pair `k` of predicted noise `predicted` is the calibration's fault: the part of its
/// length RMS the noise does not explain exceeds the target.
fn calibration_part(k: &PairCheck, predicted: f64, target: &Target) -> Option<String> {
    let excess = (k.length_rms.powi(2) - predicted.powi(2)).max(0.0).sqrt();
    (excess > target.length_mm).then(|| {
        format!(
            "is {excess:.4} mm more than its observations' noise explains ({predicted:.4} mm \
             through this pair's geometry), above your {} mm target",
            target.length_mm
        )
    })
}

/// Why pair `k` is out of family among the `checks` of its `kind` and above the target.
fn out_of_family(
    k: &PairCheck,
    checks: &[PairCheck],
    kind: &dyn Fn(&PairCheck) -> bool,
    target: &Target,
) -> Option<String> {
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        let n = v.len();
        (v[(n - 1) / 2] + v[n / 2]) / 2.0
    };
    let family: Vec<f64> = (checks.iter())
        .filter(|o| kind(o) == kind(k))
        .map(|o| o.length_rms)
        .collect();
    if family.len() < 3 {
        return None;
    }
    let m = median(family.clone());
    let mad = median(family.iter().map(|x| (x - m).abs()).collect());
    let z = 0.6745 * (k.length_rms - m) / mad.max(1e-12 * m.max(1e-300));
    // Out of family and above the target: a pair within the target is good enough.
    (z > PAIR_Z && k.length_rms > target.length_mm).then(|| {
        format!(
            "is out of family: the {} {} pairs' median is {m:.4} mm (robust z {z:.1})",
            family.len(),
            if kind(k) {
                "camera–projector"
            } else {
                "camera–camera"
            },
        )
    })
}

/// Notes on held-out pairs whose observations' noise alone, through their triangulation
/// geometry (39), gives a length error above the target: the pair's geometry, not the
/// calibration, limits what it can measure.
pub fn noise_limited_pairs(checks: &[PairCheck], target: &Target) -> Vec<String> {
    (checks.iter())
        .filter_map(|k| Some((k, k.predicted_rms?)))
        .filter(|(_, p)| *p > target.length_mm)
        .map(|(k, p)| {
            format!(
                "{}–{} (held-out pose {}): its observations' noise alone gives {p:.4} mm \
                 (measured {:.4} mm) through this pair's triangulation geometry and this \
                 pose's view, above your {} mm target: the measurement, not the calibration, \
                 limits it; measure with a pair that sees the board across a wider angle and \
                 less steeply.",
                k.first, k.second, k.pose, k.length_rms, target.length_mm
            )
        })
        .collect()
}

/// The report's own warnings: what the data could not determine (one line each,
/// [`crate::calib::observability`]), few poses, high RMS, many outliers (absolute and
/// against peers), coverage holes, extrapolated corners, poorly determined terms, excluded
/// devices, unregistered views.
pub fn warnings(
    cal: &Calibration,
    rows: &[ResidualRow],
    target: &Target,
    notes: &mut Vec<String>,
) -> Vec<String> {
    // A transform no observation depends on (one side seen) changes nothing computed: a
    // note; the others are held where the data would have said otherwise: warnings.
    use super::observability::Unobserved;
    let (quiet, held): (Vec<&Unobserved>, Vec<&Unobserved>) =
        (cal.solution.held.iter()).partition(|u| matches!(u, Unobserved::SideTransformOneSideSeen));
    notes.extend(quiet.iter().map(ToString::to_string));
    let mut w: Vec<String> = held.iter().map(ToString::to_string).collect();
    lens_warnings(cal, target, &mut w);
    outlier_warnings(cal, rows, &mut w, notes);
    let expected = expected_rms(cal);
    for (dev, row) in cal.devices.iter().zip(rows) {
        if row.poses < MIN_POSES {
            w.push(format!(
                "{} ({}) is seen in only {} board pose{} (at least {MIN_POSES} wanted): its \
                 model rests on few views; capture more poses that it sees.",
                dev.name,
                kind_name(dev.kind),
                row.poses,
                if row.poses == 1 { "" } else { "s" }
            ));
        }
        let mut same: Vec<f64> = rows
            .iter()
            .filter(|r| r.kind == dev.kind && r.points > 0)
            .map(|r| r.rms)
            .collect();
        if same.len() >= 3 && row.points > 0 {
            same.sort_by(f64::total_cmp);
            let median = same[same.len() / 2];
            if row.rms > RMS_RATIO * median {
                w.push(format!(
                    "{}: RMS {:.4} px is {:.1}× the median {:.4} px of the {}s.",
                    dev.name,
                    row.rms,
                    row.rms / median,
                    median,
                    kind_name(dev.kind)
                ));
            }
        }
        if row.points > 0 && expected > 0.0 && row.rms > RMS_RATIO * expected {
            w.push(format!(
                "{}: RMS {:.4} px is {:.1}× the {:.4} px the joint fit expects \
                 (√2·σ̂·√(1 − p/n)): its noise is above the rig's, or its model does not fit.",
                dev.name,
                row.rms,
                row.rms / expected,
                expected
            ));
        }
    }
    for e in &cal.excluded {
        w.push(format!(
            "{} was not calibrated: {}. Capture poses in which it sees (or lights) the board \
             in at least {MIN_POSES} orientations, then recalibrate.",
            e.name, e.reason
        ));
    }
    for u in &cal.registration.unregistered {
        let camera = cal
            .device_index
            .iter()
            .position(|&i| i == u.camera)
            .map_or_else(
                || format!("camera #{}", u.camera),
                |d| cal.devices[d].name.clone(),
            );
        w.push(format!(
            "The unanchored view of {camera} in board pose {} was not registered and is not \
             used: {}.",
            u.pose, u.reason
        ));
    }
    w
}

/// "camera" or "projector".
pub fn kind_name(k: DeviceKind) -> &'static str {
    match k {
        DeviceKind::Camera => "camera",
        DeviceKind::Projector => "projector",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::solve::calibrate;
    use crate::calib::synthetic::SyntheticRig;

    /// The target of the tests on σ = 0.1 px synthetic data: the noise of one observation.
    const NOISE_TARGET: Target = Target {
        uncertainty_px: 0.1,
        length_mm: DEFAULT_TARGET_MM,
    };

    /// A length target the verification tests' pairs (about 0.05 mm) meet.
    const PAIR_TARGET: Target = Target {
        uncertainty_px: DEFAULT_TARGET_PX,
        length_mm: 0.1,
    };

    fn paper(keep: impl Fn(usize, Point2<f64>) -> bool) -> Calibration {
        let rig = SyntheticRig::paper(10, 0.1, 3);
        let mut views = rig.views();
        for v in &mut views {
            let camera = v.camera;
            v.points.retain(|p| keep(camera, p.image));
        }
        calibrate(
            &rig.board,
            &rig.device_infos(),
            rig.boards.len(),
            &views,
            &Default::default(),
        )
        .expect("paper rig calibrates")
    }

    fn figures(cal: &Calibration) {
        for (d, (empty, _)) in coverage(cal).into_iter().enumerate() {
            let u: Vec<String> = corners(cal, d)
                .iter()
                .filter_map(|&p| {
                    Some((
                        projection_uncertainty(cal, d, p)?,
                        shape_uncertainty(cal, d, p)?,
                    ))
                })
                .map(|(u, s)| format!("{u:.3} (shape {s:.3})"))
                .collect();
            eprintln!(
                "{}: {:.0} % cells empty, corner uncertainty {} px (σ̂ {:.3})",
                cal.devices[d].name,
                100.0 * empty,
                u.join(" "),
                cal.solution.sigma
            );
        }
    }

    /// The paper rig's poses leave the image corners without points (a third of the
    /// cameras' cells, half of the projectors'); its lens models are chosen as
    /// `lens_model::tests` requires. Whatever is said is one warning per
    /// device at most of each kind, and only of the kinds that are true of it: extrapolated
    /// regions and poorly determined terms (no outliers, RMS or pose counts: none apply).
    #[test]
    fn the_paper_rig_says_only_what_is_true_of_it() {
        let cal = paper(|_, _| true);
        figures(&cal);
        crate::calib::lens_model::tests::the_paper_rig_fixes_what_its_data_cannot_determine(
            &SyntheticRig::paper(10, 0.1, 3),
            &cal,
        );
        let w = warnings(&cal, &residual_table(&cal), &NOISE_TARGET, &mut Vec::new());
        eprintln!("{} warnings: {w:#?}", w.len());
        let kinds = ["extrapolates", "cannot determine"];
        assert!(
            w.iter().all(|s| kinds.iter().any(|k| s.contains(k))),
            "{w:#?}"
        );
        for d in &cal.devices {
            for k in kinds {
                let n = w
                    .iter()
                    .filter(|s| s.starts_with(&format!("{}:", d.name)) && s.contains(k));
                assert!(n.count() <= 1, "{}: {w:#?}", d.name);
            }
        }
    }

    /// The paper rig (its image corners without points) at ten times the real noise, judged
    /// against the default target (1 px, 0.1 mm): no warning, as a healthy rig must get;
    /// against the noise of one observation it is told where its lenses extrapolate.
    #[test]
    fn a_healthy_rig_gets_no_warning_at_the_users_target() {
        let cal = paper(|_, _| true);
        let mut notes = Vec::new();
        let w = warnings(&cal, &residual_table(&cal), &Target::default(), &mut notes);
        assert!(w.is_empty() && notes.is_empty(), "{w:#?} {notes:#?}");
        let strict = warnings(&cal, &residual_table(&cal), &NOISE_TARGET, &mut notes);
        assert!(
            strict.iter().any(|s| s.contains("extrapolates")),
            "{strict:#?}"
        );
    }

    /// Outliers that all lie in one pose are that view's: a note naming the pose and its
    /// tilt, no warning.
    #[test]
    fn outliers_of_one_view_are_a_note_naming_the_pose() {
        let mut cal = paper(|_, _| true);
        let pose = cal
            .observations
            .iter()
            .find(|o| cal.devices[o.device].name == "cam2")
            .unwrap()
            .pose;
        let mut k = 0;
        for (o, r) in cal.observations.iter().zip(&mut cal.solution.residuals) {
            if cal.devices[o.device].name == "cam2" && o.pose == pose {
                k += 1;
                r.outlier |= k % 3 == 0;
            }
        }
        let mut notes = Vec::new();
        let w = warnings(&cal, &residual_table(&cal), &Target::default(), &mut notes);
        assert!(!w.iter().any(|s| s.contains("outliers")), "{w:#?}");
        let input = cal.pose_index[pose];
        assert!(
            notes.len() == 1
                && notes[0].starts_with("cam2:")
                && notes[0].contains(&format!("% of them in pose {input} (the board at ")),
            "{notes:#?}"
        );
    }

    /// A well-covered rig (every device's whole image seen, corners included), calibrated
    /// from its views: no warning at all.
    #[test]
    fn a_well_covered_rig_is_not_warned_about() {
        let rig = SyntheticRig::covered(0.1, 11, 0.0);
        let cal = calibrate(
            &rig.board,
            &rig.device_infos(),
            rig.boards.len(),
            &rig.views(),
            &Default::default(),
        )
        .expect("the covered rig calibrates");
        figures(&cal);
        let w = warnings(&cal, &residual_table(&cal), &NOISE_TARGET, &mut Vec::new());
        assert!(w.is_empty(), "{w:#?}");
    }

    /// Each warning kind fires on a rig built to show it, about the device concerned only:
    /// on the well-covered rig, cam1 defocused (its centres 4× noisier) is named by its
    /// RMS, and cam2 seen in two poses only is named as not calibrated.
    #[test]
    fn a_defocused_camera_and_one_seen_in_two_poses_are_named() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let rig = SyntheticRig::covered(0.1, 11, 0.0);
        let mut views = rig.views();
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        // 0.1 px at first: √(0.4² − 0.1²) more makes 0.4 px.
        let blur = Normal::new(0.0, (0.4f64.powi(2) - 0.01).sqrt()).unwrap();
        for v in views.iter_mut().filter(|v| v.camera == 1) {
            for p in &mut v.points {
                p.image.x += blur.sample(&mut rng);
                p.image.y += blur.sample(&mut rng);
                // A projector pixel is read at the observed centre, so it would move with
                // it; the synthetic one is at the true centre: left out here.
                p.projectors.clear();
            }
        }
        let mut seen: Vec<usize> = (views.iter().filter(|v| v.camera == 2))
            .map(|v| v.pose)
            .collect();
        seen.sort_unstable();
        seen.dedup();
        views.retain(|v| v.camera != 2 || seen[..2].contains(&v.pose));
        let cal = calibrate(
            &rig.board,
            &rig.device_infos(),
            rig.boards.len(),
            &views,
            &Default::default(),
        )
        .expect("the rig calibrates without cam2");
        let w = warnings(
            &cal,
            &residual_table(&cal),
            &Target::default(),
            &mut Vec::new(),
        );
        let about = |name: &str| w.iter().filter(|s| s.contains(name)).count();
        assert!(
            w.iter()
                .any(|s| s.starts_with("cam1: RMS") || s.starts_with("cam1 ")),
            "{w:#?}"
        );
        assert!(about("cam2") >= 1, "{w:#?}");
        assert_eq!(about("cam0") + about("proj0"), 0, "{w:#?}");
    }

    /// Two cameras on one side, the board turned over between poses: the front→back
    /// transform is held, and said so in one line.
    #[test]
    fn a_side_transform_held_is_said_once() {
        let rig = SyntheticRig::one_sided(2, 0, 8, 0.1, 12);
        let cal = calibrate(
            &rig.board,
            &rig.device_infos(),
            rig.boards.len(),
            &rig.views(),
            &Default::default(),
        )
        .expect("a one-sided rig calibrates");
        let w = warnings(&cal, &residual_table(&cal), &NOISE_TARGET, &mut Vec::new());
        let held: Vec<_> = w.iter().filter(|w| w.contains("front→back")).collect();
        assert_eq!(held.len(), 1, "{w:#?}");
        assert!(
            held[0].contains("no pose is seen from both sides"),
            "{w:#?}"
        );
    }

    #[test]
    fn coverage_holes_and_outliers_are_warned() {
        // cam0 keeps only the points in the middle third of its image.
        let centre = |c: usize, p: Point2<f64>| {
            c != 0 || ((640.0..1280.0).contains(&p.x) && (400.0..800.0).contains(&p.y))
        };
        let mut cal = paper(centre);
        figures(&cal);
        // cam2: one observation in ten marked an outlier (the others have almost none).
        let mut k = 0;
        for (o, r) in cal.observations.iter().zip(&mut cal.solution.residuals) {
            if cal.devices[o.device].name == "cam2" {
                k += 1;
                r.outlier |= k % 10 == 0;
            }
        }
        let w = warnings(&cal, &residual_table(&cal), &NOISE_TARGET, &mut Vec::new());
        let about =
            |name: &str, what: &str| w.iter().any(|s| s.starts_with(name) && s.contains(what));
        assert!(about("cam0", "70 % of its 8 × 5 image cells"), "{w:#?}");
        assert!(
            about(
                "cam0",
                "extrapolates in its top-left corner, top-right corner, left edge, right edge, \
                 bottom-left corner, bottom-right corner"
            ),
            "{w:#?}"
        );
        assert!(about("cam2", "are outliers, where its peers"), "{w:#?}");
        // No other device is said to have outliers.
        for s in w.iter().filter(|s| s.contains("outliers")) {
            assert!(s.starts_with("cam2"), "{s}");
        }
        // Its corners are less certain than where it has points (a centre-only camera's
        // k1, k2 still extrapolate).
        let far = shape_uncertainty(&cal, 0, Point2::new(0.0, 0.0)).unwrap();
        assert!(far > cal.solution.sigma, "{far}");
        // Its valid-intrinsics region is smaller than any other camera's, and each
        // vertex is where the uncertainty is still below the threshold.
        let area = |d: usize| {
            let r = valid_region(&cal, d, VALID_UNCERTAINTY).unwrap_or_default();
            for v in &r {
                let u = projection_uncertainty(&cal, d, Point2::new(v[0], v[1])).unwrap();
                assert!(u < VALID_UNCERTAINTY, "{d}: {u}");
            }
            let n = r.len();
            (0..n)
                .map(|i| r[i][0] * r[(i + 1) % n][1] - r[(i + 1) % n][0] * r[i][1])
                .sum::<f64>()
                .abs()
                / 2.0
        };
        let areas: Vec<f64> = (0..6).map(area).collect();
        eprintln!("valid-intrinsics areas (px²): {areas:?}");
        assert!((1..6).all(|d| areas[0] < areas[d]), "{areas:?}");
    }

    /// Poisson tails against sums of the density, and the Gaussian outlier rate e⁻⁸.
    #[test]
    fn poisson_tail_and_gaussian_rate() {
        let density = |i: u64, l: f64| (-l + i as f64 * l.ln() - ln_factorial(i)).exp();
        for (k, l) in [(3u64, 1.0f64), (12, 4.0), (60, 30.0), (200, 150.0)] {
            let below: f64 = (0..k).map(|i| density(i, l)).sum();
            assert!((poisson_tail(k, l) - (1.0 - below)).abs() < 1e-9, "{k} {l}");
        }
        let exact: f64 = (1..=40).map(|i| (i as f64).ln()).sum();
        assert!((ln_factorial(40) - exact).abs() < 1e-9);
        assert!((GAUSSIAN_OUTLIER_RATE - (-8f64).exp()).abs() < 1e-18);
    }

    #[test]
    fn a_verification_pair_out_of_family_is_warned() {
        let pair = |second: &str, rms: f64| PairCheck {
            first: "cam1".into(),
            second: second.into(),
            pose: 9,
            points: 200,
            length_rms: rms,
            length_max: 3.0 * rms,
            flatness_rms: 0.01,
            predicted_rms: None,
        };
        let proj = |n: &str| n.starts_with("proj");
        let mut checks = vec![
            pair("cam0", 0.05),
            pair("cam2", 0.048),
            pair("cam3", 0.046),
            pair("proj0", 0.052),
            pair("proj2", 0.061),
            pair("proj3", 0.055),
        ];
        assert!(verification_warnings(&checks, proj, &Target::default()).is_empty());
        // 0.148 mm is out of family among the camera–projector pairs; cam4's 0.052 mm is
        // in family among the camera–camera pairs.
        checks.push(pair("proj1", 0.148));
        checks.push(pair("cam4", 0.052));
        let w = verification_warnings(&checks, proj, &PAIR_TARGET);
        assert_eq!(w.len(), 1, "{w:#?}");
        assert!(
            w[0].contains("cam1–proj1") && w[0].contains("pose 9"),
            "{w:?}"
        );
        // With each pair's predicted noise known, its own prediction is the yardstick:
        // 0.148 mm of which noise explains 0.14 mm is the pair's geometry (a note, no
        // warning); 0.2 mm where noise explains 0.05 mm is the calibration's.
        let with = |mut k: PairCheck, p: f64| {
            k.predicted_rms = Some(p);
            k
        };
        let mut known: Vec<PairCheck> = checks.iter().map(|k| with(k.clone(), 0.04)).collect();
        known[6] = with(pair("proj1", 0.148), 0.14);
        assert!(verification_warnings(&known, proj, &PAIR_TARGET).is_empty());
        let notes = noise_limited_pairs(&known, &PAIR_TARGET);
        assert_eq!(notes.len(), 1, "{notes:?}");
        assert!(notes[0].starts_with(
            "cam1–proj1 (held-out pose 9): its observations' noise alone gives 0.1400 mm"
        ));
        known[6] = with(pair("proj1", 0.2), 0.05);
        let w = verification_warnings(&known, proj, &PAIR_TARGET);
        assert_eq!(w.len(), 1, "{w:#?}");
        assert!(
            w[0].contains("is 0.1936 mm more than its observations' noise explains"),
            "{w:?}"
        );
        assert!(noise_limited_pairs(&known, &PAIR_TARGET).is_empty());
    }
}
