//! Diagnostics of a calibration: per-device residual statistics (the paper's Table I), the
//! RMS the joint fit expects, and the warnings a user should act on.
//!
//! Takes a [`Calibration`]; gives numbers and sentences. The report only formats them.

use super::bundle::DeviceKind;
use super::solve::Calibration;
use super::verify::PairCheck;
use crate::camera::{LensParam, LensParams};
use nalgebra::{DMatrix, Isometry3, Point2, Point3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;

/// Devices seen in fewer board poses than this are warned about.
pub const MIN_POSES: usize = 3;
/// A device's RMS above this multiple of its kind's median, or of the RMS the joint fit
/// expects, is warned about.
pub const RMS_RATIO: f64 = 1.5;
/// More than this fraction of a device's observations rejected is warned about.
pub const OUTLIER_FRACTION: f64 = 0.05;

/// Image cells (columns, rows) of the coverage check.
pub const COVERAGE_CELLS: (usize, usize) = (8, 5);
/// More than this fraction of a device's image cells without an observed point is warned
/// about.
pub const EMPTY_FRACTION: f64 = 0.5;
/// A device whose outlier rate exceeds this multiple of its kind's median rate (and
/// [`OUTLIER_FRACTION`] / 5) is warned about.
pub const OUTLIER_RATIO: f64 = 5.0;
/// A verification pair whose length RMS exceeds this multiple of the pairs' median is
/// warned about.
pub const PAIR_RATIO: f64 = 2.0;

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
    let mut params = LensParams::for_model(&cal.devices[d].model);
    if sol.intrinsic_std[d].len() < params.len() {
        params = params.fix(LensParam::K3);
    }
    let free: Vec<LensParam> = params.iter().collect();
    let at = sol.index[d].0;
    let n = free.len();
    let idx: Vec<usize> = (at..at + n).collect();
    (free, sol.covariance.block(&idx))
}

/// Projection uncertainty (px, 1σ along the worst direction) of device `d` at `pixel`:
/// the lens covariance propagated to the pixel of the ray through it, J·Σ·Jᵀ with J the
/// lens Jacobian (J5) at that ray; the device's pose is held (docs/design.md §8).
pub fn projection_uncertainty(cal: &Calibration, d: usize, pixel: Point2<f64>) -> Option<f64> {
    let m = &cal.devices[d].model;
    let (free, cov) = lens_covariance(cal, d);
    let ray = m.ray(pixel)?;
    let j = m
        .project_with_jacobians(&Isometry3::identity(), &Point3::from(ray))?
        .d_lens;
    let js = DMatrix::from_fn(2, free.len(), |r, c| j[(r, free[c].index())]);
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

const CORNER_NAMES: [&str; 4] = ["top-left", "top-right", "bottom-left", "bottom-right"];

/// Coverage holes and extrapolated corners of each device: more than [`EMPTY_FRACTION`] of
/// the image cells empty, or a corner whose projection uncertainty exceeds the noise σ̂
/// of one observation (the model there is less sure than a single measurement).
fn coverage_warnings(cal: &Calibration, w: &mut Vec<String>) {
    for (d, (empty, empty_corners)) in coverage(cal).into_iter().enumerate() {
        let dev = &cal.devices[d];
        let names: Vec<&str> = (0..4)
            .filter(|&c| empty_corners[c])
            .map(|c| CORNER_NAMES[c])
            .collect();
        if empty > EMPTY_FRACTION {
            let (nx, ny) = COVERAGE_CELLS;
            w.push(format!(
                "{}: {:.0} % of its {nx} × {ny} image cells hold no observed point (empty \
                 corners: {}): add poses with the board in {}'s empty regions.",
                dev.name,
                100.0 * empty,
                if names.is_empty() {
                    "none".to_string()
                } else {
                    names.join(", ")
                },
                dev.name
            ));
        }
        let sigma = cal.solution.sigma;
        let worst = corners(cal, d)
            .into_iter()
            .zip(CORNER_NAMES)
            .filter_map(|(p, name)| Some((projection_uncertainty(cal, d, p)?, name)))
            .max_by(|a, b| a.0.total_cmp(&b.0));
        if let Some((u, name)) = worst.filter(|(u, _)| *u > sigma) {
            w.push(format!(
                "{}: the lens model extrapolates in the image corners: projection uncertainty \
                 {u:.3} px at the {name} corner, above the {sigma:.3} px noise of one \
                 observation: add poses with the board in {}'s corners, or fix the terms \
                 the data cannot determine (--fix-k3).",
                dev.name, dev.name
            ));
        }
    }
}

/// Poorly determined distortion terms: estimate within 3σ of zero while its 1σ moves the
/// farthest image corner by more than the noise σ̂ (a term that matters and is not known).
fn parameter_warnings(cal: &Calibration, w: &mut Vec<String>) {
    for (d, dev) in cal.devices.iter().enumerate() {
        let (free, cov) = lens_covariance(cal, d);
        let m = &dev.model;
        let values = m.lens_vector();
        let far = corners(cal, d)
            .into_iter()
            .filter_map(|p| m.ray(p))
            .max_by(|a, b| a.xy().norm().total_cmp(&b.xy().norm()));
        let Some(ray) = far else { continue };
        let Some(jac) = m.project_with_jacobians(&Isometry3::identity(), &Point3::from(ray)) else {
            continue;
        };
        for (i, p) in free.iter().enumerate().filter(|(_, p)| p.index() >= 4) {
            let std = cov[(i, i)].max(0.0).sqrt();
            let value = values[p.index()];
            let col = jac.d_lens.column(p.index()).norm();
            if value.abs() < 3.0 * std && col * std > cal.solution.sigma {
                w.push(format!(
                    "{}: {} = {value:.4} ± {std:.4} is within 3σ of zero but its σ moves the \
                     image corner by {:.2} px: the data cannot determine it; add poses \
                     covering {}'s corners{}.",
                    dev.name,
                    p.name(),
                    col * std,
                    dev.name,
                    if *p == LensParam::K3 {
                        " or calibrate with --fix-k3"
                    } else {
                        ""
                    }
                ));
            }
        }
    }
}

/// Devices with many more outliers than their peers (rate above [`OUTLIER_RATIO`] times
/// the kind's median rate).
fn outlier_warnings(cal: &Calibration, rows: &[ResidualRow], w: &mut Vec<String>) {
    let rate = |r: &ResidualRow| r.outliers as f64 / (r.points + r.outliers).max(1) as f64;
    for (dev, row) in cal.devices.iter().zip(rows) {
        let mut peers: Vec<f64> = rows
            .iter()
            .filter(|r| r.kind == row.kind)
            .map(rate)
            .collect();
        if peers.len() < 3 {
            continue;
        }
        peers.sort_by(f64::total_cmp);
        let median = peers[peers.len() / 2];
        let floor = OUTLIER_FRACTION / 5.0;
        if rate(row) > floor && rate(row) > OUTLIER_RATIO * median {
            w.push(format!(
                "{}: {:.2} % of its observations are outliers, {:.0}× the median {:.2} % of \
                 the {}s: check its focus, exposure and mounting, then recalibrate.",
                dev.name,
                100.0 * rate(row),
                rate(row) / median.max(1e-12),
                100.0 * median,
                kind_name(dev.kind)
            ));
        }
    }
}

/// Verification pairs out of family: length RMS above [`PAIR_RATIO`] times the pairs'
/// median (with at least three pairs).
pub fn verification_warnings(checks: &[PairCheck]) -> Vec<String> {
    let mut rms: Vec<f64> = checks.iter().map(|k| k.length_rms).collect();
    if rms.len() < 3 {
        return Vec::new();
    }
    rms.sort_by(f64::total_cmp);
    let median = rms[rms.len() / 2];
    checks
        .iter()
        .filter(|k| k.length_rms > PAIR_RATIO * median)
        .map(|k| {
            format!(
                "Verification pair {}–{} (held-out pose {}): length RMS {:.4} mm (max {:.4} \
                 mm) is {:.1}× the pairs' median {:.4} mm: recheck these two devices (a moved \
                 device, a poorly covered lens) before trusting their measurements.",
                k.first,
                k.second,
                k.pose,
                k.length_rms,
                k.length_max,
                k.length_rms / median,
                median
            )
        })
        .collect()
}

/// The report's own warnings: few poses, high RMS, many outliers (absolute and against
/// peers), coverage holes, extrapolated corners, poorly determined terms, excluded devices,
/// unregistered views.
pub fn warnings(cal: &Calibration, rows: &[ResidualRow]) -> Vec<String> {
    let mut w = Vec::new();
    coverage_warnings(cal, &mut w);
    parameter_warnings(cal, &mut w);
    outlier_warnings(cal, rows, &mut w);
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
        let total = row.points + row.outliers;
        if total > 0 && row.outliers as f64 > OUTLIER_FRACTION * total as f64 {
            w.push(format!(
                "{}: {} of {} observations ({:.1} %) rejected as outliers.",
                dev.name,
                row.outliers,
                total,
                100.0 * row.outliers as f64 / total as f64
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
                .filter_map(|&p| projection_uncertainty(cal, d, p))
                .map(|u| format!("{u:.3}"))
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
    /// cameras' cells, half of the projectors'): its distortion terms extrapolate there
    /// (the cam0 was 1.63 px off in the corners), which every device is warned
    /// about; nothing else is wrong, and nothing else is said.
    #[test]
    fn the_paper_rig_extrapolates_in_its_corners_and_says_only_that() {
        let cal = paper(|_, _| true);
        figures(&cal);
        let w = warnings(&cal, &residual_table(&cal));
        for d in &cal.devices {
            let about = |what: &str| w.iter().any(|s| s.starts_with(&d.name) && s.contains(what));
            assert!(
                about("extrapolates in the image corners"),
                "{}: {w:#?}",
                d.name
            );
        }
        let kinds = ["extrapolates", "image cells hold no", "cannot determine"];
        assert!(
            w.iter().all(|s| kinds.iter().any(|k| s.contains(k))),
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
        let w = warnings(&cal, &residual_table(&cal));
        let about =
            |name: &str, what: &str| w.iter().any(|s| s.starts_with(name) && s.contains(what));
        assert!(about("cam0", "70 % of its 8 × 5 image cells"), "{w:#?}");
        assert!(about(
            "cam0",
            "empty corners: top-left, top-right, bottom-left, bottom-right"
        ));
        assert!(about("cam0", "k3 = "), "{w:#?}");
        assert!(about("cam2", "of the cameras"), "{w:#?}");
        // No other camera is said to have holes or outliers.
        let peers = w
            .iter()
            .filter(|s| s.contains("outliers") || s.contains("image cells"));
        for s in peers {
            assert!(
                s.starts_with("cam0") || s.starts_with("cam2") || s.starts_with("proj"),
                "{s}"
            );
        }
        // cam0's corners are far less certain than those of the cameras that cover theirs.
        let worst = |d: usize| {
            corners(&cal, d)
                .iter()
                .filter_map(|&p| projection_uncertainty(&cal, d, p))
                .fold(0.0, f64::max)
        };
        assert!((1..6).all(|d| worst(0) > 5.0 * worst(d)));
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
        };
        let mut checks = vec![
            pair("cam0", 0.05),
            pair("cam2", 0.048),
            pair("proj0", 0.052),
        ];
        assert!(verification_warnings(&checks).is_empty());
        checks.push(pair("proj1", 0.148));
        let w = verification_warnings(&checks);
        assert_eq!(w.len(), 1, "{w:#?}");
        assert!(
            w[0].contains("cam1–proj1") && w[0].contains("pose 9"),
            "{w:?}"
        );
    }
}
