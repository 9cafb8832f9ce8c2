//! Gauge-free verification of a calibration (docs/design.md §10): triangulate a board pose the
//! calibration did not use from device pairs and compare with the board's geometry.
//!
//! Takes calibrated devices and labelled views of held-out poses; gives per device pair
//! (camera–camera and camera–projector) the triangulated circles' length errors (distances
//! between board points against the nominal ones, VDI/VDE 2634 style) and their flatness.
//! Camera observations are ellipse centres: each pair first triangulates them, fits the
//! board pose to the points, predicts every observation's perspective bias (§8) from it,
//! and triangulates again with the bias removed. A pair whose figures cannot be trusted (no
//! baseline, points behind a device, non-finite figures) is skipped with the reason.

use super::bundle::Device;
use super::circle::ellipse_center;
use hexcal_core::board::{Board, Hex, Side};
use hexcal_core::observations::{CameraView, Frame};
use nalgebra::{
    Isometry3, Matrix3, Point2, Point3, Rotation3, SymmetricEigen, Translation3, UnitQuaternion,
    Vector2, Vector3, U3,
};
use std::collections::BTreeMap;

/// Verification figures of one device pair on one held-out pose.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PairCheck {
    /// First device (a camera).
    pub first: String,
    /// Second device (a camera or a projector).
    pub second: String,
    /// Board pose index.
    pub pose: usize,
    /// Circles triangulated.
    pub points: usize,
    /// RMS of (measured − nominal) over all point-pair distances (mm).
    pub length_rms: f64,
    /// Largest |measured − nominal| (mm).
    pub length_max: f64,
    /// RMS distance of the points from their best-fit plane (mm).
    pub flatness_rms: f64,
    /// The length RMS the devices' observation noise alone gives through this pair's
    /// triangulation geometry (mm; docs/design.md (39)), when their noise is known.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub predicted_rms: Option<f64>,
}

/// A device pair of a held-out pose that shares ten circles but gives no figures to trust,
/// and why (no baseline, points behind a device, parallel rays, figures not finite).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SkippedPair {
    /// First device (a camera).
    pub first: String,
    /// Second device (a camera or a projector).
    pub second: String,
    /// Board pose index.
    pub pose: usize,
    /// Why the pair gives no figures.
    pub reason: String,
}

impl std::fmt::Display for SkippedPair {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}–{} at pose {} not checked: {}",
            self.first, self.second, self.pose, self.reason
        )
    }
}

/// What [`verify`] gives: the pairs checked, and the pairs that could not be.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Verification {
    /// Figures of every pair checked.
    pub checks: Vec<PairCheck>,
    /// Pairs with ten shared circles that gave no figures, with the reason.
    pub skipped: Vec<SkippedPair>,
}

/// The smallest angle (degrees) the baseline of a pair may subtend at the triangulated
/// board: below it the pair's depth is a guess (1° gives ~57× the pixel error in depth).
pub const MIN_TRIANGULATION_DEG: f64 = 1.0;

/// One device's ray through a pixel, in the reference frame: origin and unit direction;
/// `None` where the lens model cannot be inverted.
pub fn ray(device: &Device, pixel: Point2<f64>) -> Option<(Point3<f64>, Vector3<f64>)> {
    let d = device.model.ray(pixel)?;
    let inv = device.pose.inverse();
    Some((inv * Point3::origin(), (inv.rotation * d).normalize()))
}

/// Midpoint of the shortest segment between two rays (origin, unit direction); `None` when
/// they are parallel.
pub fn midpoint(
    a: (Point3<f64>, Vector3<f64>),
    b: (Point3<f64>, Vector3<f64>),
) -> Option<Point3<f64>> {
    let w = a.0 - b.0;
    let (p, q, r) = (a.1.dot(&b.1), a.1.dot(&w), b.1.dot(&w));
    let den = 1.0 - p * p;
    if den < 1e-12 {
        return None;
    }
    let s = (p * r - q) / den;
    let t = (r - p * q) / den;
    Some(Point3::from(
        ((a.0 + a.1 * s).coords + (b.0 + b.1 * t).coords) / 2.0,
    ))
}

/// Iterations an SVD or eigen-decomposition may take (they converge in tens; points gone
/// non-finite never converge, and the pair is left out instead).
const MAX_ITERATIONS: usize = 10_000;

/// Rigid transform taking `from` onto `to` in the least-squares sense (Kabsch); `None`
/// when the decomposition does not converge.
fn fit_rigid(from: &[Point3<f64>], to: &[Point3<f64>]) -> Option<Isometry3<f64>> {
    let n = from.len() as f64;
    let cf = from.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n;
    let ct = to.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n;
    let h = from.iter().zip(to).fold(Matrix3::zeros(), |h, (f, t)| {
        h + (f.coords - cf) * (t.coords - ct).transpose()
    });
    let svd = h.try_svd(true, true, f64::EPSILON, MAX_ITERATIONS)?;
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut d = Matrix3::identity();
    d[(2, 2)] = (vt.transpose() * u.transpose()).determinant().signum();
    let r = vt.transpose() * d * u.transpose();
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Some(Isometry3::from_parts(
        Translation3::from(ct - rot * cf),
        rot,
    ))
}

/// The least-squares plane of `points`: their centroid and the eigen-decomposition of their
/// scatter matrix (the normal is the eigenvector of the smallest eigenvalue); `None` when
/// the decomposition does not converge.
fn plane_fit(points: &[Point3<f64>]) -> Option<(Vector3<f64>, SymmetricEigen<f64, U3>)> {
    let n = points.len() as f64;
    let c = points.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n;
    let cov = points.iter().fold(Matrix3::zeros(), |m, p| {
        m + (p.coords - c) * (p.coords - c).transpose()
    });
    Some((c, cov.try_symmetric_eigen(f64::EPSILON, MAX_ITERATIONS)?))
}

/// RMS distance from the least-squares plane (NaN when the decomposition does not converge).
fn flatness(points: &[Point3<f64>]) -> f64 {
    match plane_fit(points) {
        Some((_, eig)) => (eig.eigenvalues.min() / points.len() as f64)
            .max(0.0)
            .sqrt(),
        None => f64::NAN,
    }
}

/// Observations of one circle by the two devices of a pair.
struct Pairing {
    hex: Hex,
    first: Point2<f64>,
    /// The second device's pixel and, for a camera, its ellipse centre to de-bias.
    second: Point2<f64>,
}

/// What every pair of a verification shares: the board, the devices and their noise (px
/// per axis; may be short or empty: unknown).
struct Context<'a> {
    board: &'a Board,
    devices: &'a [Device],
    noise: &'a [f64],
}

impl Context<'_> {
    /// The noise of devices i and j, when both are known.
    fn noise_of(&self, i: usize, j: usize) -> Option<(f64, f64)> {
        let known = |d: usize| (self.noise.get(d).copied()).filter(|s| s.is_finite() && *s > 0.0);
        Some((known(i)?, known(j)?))
    }
}

/// Step of the numerical Jacobian of a triangulated point (px).
const JACOBIAN_STEP_PX: f64 = 0.05;

/// Per shared circle, the covariance of its length-error point (mm²; docs/design.md
/// (39)): the triangulated point less, for a camera–projector pair, its nominal point
/// (where the camera's ray meets the board `plane`, point and normal), under noise σ_i,
/// σ_j (px per axis) in the two devices' pixels; from a central-difference Jacobian.
fn error_covariances(
    devices: &[Device],
    (i, j): (usize, usize),
    (si, sj): (f64, f64),
    plane: Option<(Vector3<f64>, Vector3<f64>)>,
    pairs: &[Pairing],
) -> Option<Vec<Matrix3<f64>>> {
    let error = |a: Point2<f64>, b: Point2<f64>| -> Option<Vector3<f64>> {
        let (ra, rb) = (ray(&devices[i], a)?, ray(&devices[j], b)?);
        let x = midpoint(ra, rb)?.coords;
        Some(match plane {
            None => x,
            Some((q, n)) => x - (ra.0.coords + ra.1 * (n.dot(&(q - ra.0.coords)) / n.dot(&ra.1))),
        })
    };
    let h = JACOBIAN_STEP_PX;
    let steps = [Vector2::new(h, 0.0), Vector2::new(0.0, h)];
    pairs
        .iter()
        .map(|p| {
            let mut cov = Matrix3::zeros();
            for d in steps {
                let di =
                    (error(p.first + d, p.second)? - error(p.first - d, p.second)?) / (2.0 * h);
                let dj =
                    (error(p.first, p.second + d)? - error(p.first, p.second - d)?) / (2.0 * h);
                cov += si * si * di * di.transpose() + sj * sj * dj * dj.transpose();
            }
            Some(cov)
        })
        .collect()
}

/// The length RMS the point covariances predict over all point pairs (mm; (39)): per pair
/// a, b the variance gᵀ(Σ_a + Σ_b)g along their direction g.
fn predicted_rms(points: &[Point3<f64>], covariances: &[Matrix3<f64>]) -> f64 {
    let (mut var, mut n) = (0.0, 0usize);
    for a in 0..points.len() {
        for b in a + 1..points.len() {
            let g = (points[a] - points[b]).normalize();
            var += (g.transpose() * (covariances[a] + covariances[b]) * g)[(0, 0)];
            n += 1;
        }
    }
    (var / n.max(1) as f64).sqrt()
}

/// How much noisier this pose's observations are than the devices' noise says (at least 1;
/// (39)): the points' scatter off a smooth surface (a quadric fitted in the plane's frame,
/// which takes up a bend a calibration error would make) against the scatter the
/// covariances predict along the plane's normal. A steep view's observations are noisier
/// than a device's average; noise scatters point by point, a calibration error deforms
/// smoothly. `None` when no plane or quadric can be fitted.
fn noise_scale(points: &[Point3<f64>], covariances: &[Matrix3<f64>]) -> Option<f64> {
    let n = points.len();
    if n <= 12 {
        return None;
    }
    let (c, eig) = plane_fit(points)?;
    let k = eig.eigenvalues.imin();
    let normal = eig.eigenvectors.column(k).into_owned();
    let (e1, e2) = (
        eig.eigenvectors.column((k + 1) % 3),
        eig.eigenvectors.column((k + 2) % 3),
    );
    // Least squares z = a + b·x + c·y + d·x² + e·xy + f·y² in the plane's frame.
    let mut a = nalgebra::DMatrix::zeros(n, 6);
    let mut z = nalgebra::DVector::zeros(n);
    for (r, p) in points.iter().enumerate() {
        let d = p.coords - c;
        let (x, y) = (d.dot(&e1), d.dot(&e2));
        for (col, v) in [1.0, x, y, x * x, x * y, y * y].into_iter().enumerate() {
            a[(r, col)] = v;
        }
        z[r] = d.dot(&normal);
    }
    let fit = a.clone().svd(true, true).solve(&z, 1e-12).ok()?;
    let scatter = ((&a * fit - &z).norm_squared() / (n - 6) as f64).sqrt();
    let predicted = (covariances.iter())
        .map(|s| (normal.transpose() * s * normal)[(0, 0)])
        .sum::<f64>()
        / n as f64;
    Some((scatter / predicted.sqrt()).max(1.0)).filter(|k| k.is_finite())
}

/// The pair `(i, j)` of one side of one pose: `None` with fewer than ten shared circles,
/// else its figures or why it gives none ([`SkippedPair`]).
fn check_pair(
    ctx: &Context,
    (i, j): (usize, usize),
    second_is_camera: bool,
    side: Side,
    pose: usize,
    pairs: &[Pairing],
) -> Option<Result<PairCheck, SkippedPair>> {
    if pairs.len() < 10 {
        return None;
    }
    let devices = ctx.devices;
    let skipped = |reason: String| SkippedPair {
        first: devices[i].name.clone(),
        second: devices[j].name.clone(),
        pose,
        reason,
    };
    Some(pair_figures(ctx, (i, j), second_is_camera, side, pose, pairs).map_err(skipped))
}

/// `Err` unless the triangulated `points` lie in front of devices `i` and `j` and their
/// baseline subtends at least [`MIN_TRIANGULATION_DEG`] there.
fn triangulable(
    devices: &[Device],
    (i, j): (usize, usize),
    points: &[Point3<f64>],
) -> Result<(), String> {
    let centre = |d: &Device| d.pose.inverse() * Point3::origin();
    let (a, b) = (centre(&devices[i]), centre(&devices[j]));
    let baseline = (a - b).norm();
    if !baseline.is_finite() || baseline < 1e-6 {
        return Err(format!(
            "no baseline to triangulate over (the devices are {baseline:.4} mm apart)"
        ));
    }
    for d in [i, j] {
        let behind = |p: &Point3<f64>| {
            let z = (devices[d].pose * p).z;
            z.is_nan() || z <= 0.0
        };
        if points.iter().any(behind) {
            return Err(format!(
                "the triangulated circles are not in front of {}",
                devices[d].name
            ));
        }
    }
    let n = points.len() as f64;
    let centroid = points.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n;
    let (ca, cb) = (centroid - a.coords, centroid - b.coords);
    let angle = ca.angle(&cb).to_degrees();
    if angle.is_nan() || angle < MIN_TRIANGULATION_DEG {
        return Err(format!(
            "a baseline of {baseline:.1} mm subtends {angle:.2}° at the board (at least \
             {MIN_TRIANGULATION_DEG}°)"
        ));
    }
    Ok(())
}

/// The figures of a pair with ten or more shared circles, or why it gives none.
fn pair_figures(
    ctx: &Context,
    (i, j): (usize, usize),
    second_is_camera: bool,
    side: Side,
    pose: usize,
    pairs: &[Pairing],
) -> Result<PairCheck, String> {
    let (board, devices) = (ctx.board, ctx.devices);
    let nominal: Vec<Point3<f64>> = pairs.iter().map(|p| board.point(side, p.hex)).collect();
    let triangulate = |bias_i: &dyn Fn(&Pairing) -> Point2<f64>,
                       bias_j: &dyn Fn(&Pairing) -> Point2<f64>| {
        pairs
            .iter()
            .map(|p| midpoint(ray(&devices[i], bias_i(p))?, ray(&devices[j], bias_j(p))?))
            .collect::<Option<Vec<_>>>()
    };
    let parallel = || "rays through shared circles are parallel or not defined".to_string();
    let no_fit = || "the board pose fit to the points does not converge".to_string();
    let first = triangulate(&|p| p.first, &|p| p.second).ok_or_else(parallel)?;
    triangulable(devices, (i, j), &first)?;
    let mut plane = None;
    let (points, nominal) = if second_is_camera {
        // Fit the pose to the points, remove each camera's ellipse-centre bias predicted
        // from it (§8), triangulate again.
        let ref_from_board = fit_rigid(&nominal, &first).ok_or_else(no_fit)?;
        let debias = |d: usize, p: &Pairing, pixel: Point2<f64>| {
            let dev = &devices[d];
            let face = dev.pose * ref_from_board * board.side_transform(side);
            let c = board.position(p.hex);
            let centre = dev.model.project(&(face * Point3::new(c.x, c.y, 0.0)));
            match (centre, ellipse_center(&dev.model, &face, c, board.radius)) {
                (Some(centre), Some(e)) => pixel - (e - centre),
                _ => pixel,
            }
        };
        let points = triangulate(&|p| debias(i, p, p.first), &|p| debias(j, p, p.second))
            .ok_or_else(parallel)?;
        (points, nominal)
    } else {
        // A projector pixel belongs to the board point behind the camera's observed ellipse
        // centre (§7), so the raw rays meet there: compare with that point's nominal
        // position, the circle centre moved by its offset on the board (found with the
        // fitted pose; the ~0.1 mm offset barely depends on the pose's small error).
        let ref_from_side =
            fit_rigid(&nominal, &first).ok_or_else(no_fit)? * board.side_transform(side);
        let normal = ref_from_side.rotation * Vector3::z();
        let q = ref_from_side.translation.vector;
        plane = Some((q, normal));
        let moved = pairs
            .iter()
            .map(|p| {
                let (o, d) = ray(&devices[i], p.first)?;
                let x = o + d * (normal.dot(&(q - o.coords)) / normal.dot(&d));
                let on_side = ref_from_side.inverse() * x;
                Some(board.side_transform(side) * Point3::new(on_side.x, on_side.y, 0.0))
            })
            .collect::<Option<Vec<_>>>()
            .ok_or_else(parallel)?;
        (first, moved)
    };
    let (mut sq, mut max, mut n) = (0.0, 0.0f64, 0usize);
    for a in 0..points.len() {
        for b in a + 1..points.len() {
            let e = (points[a] - points[b]).norm() - (nominal[a] - nominal[b]).norm();
            sq += e * e;
            max = max.max(e.abs());
            n += 1;
        }
    }
    let check = PairCheck {
        first: devices[i].name.clone(),
        second: devices[j].name.clone(),
        pose,
        points: points.len(),
        length_rms: (sq / n as f64).sqrt(),
        length_max: max,
        flatness_rms: flatness(&points),
        // No prediction rather than a non-finite one (it would silence the pair's warning).
        predicted_rms: ctx.noise_of(i, j).and_then(|noise| {
            let covariances = error_covariances(devices, (i, j), noise, plane, pairs)?;
            let p = predicted_rms(&points, &covariances) * noise_scale(&points, &covariances)?;
            p.is_finite().then_some(p)
        }),
    };
    let figures = [check.length_rms, check.length_max, check.flatness_rms];
    if figures.iter().any(|v| !v.is_finite()) {
        return Err("its figures are not finite numbers".into());
    }
    Ok(check)
}

/// Check every camera–camera pair that sees a common side of a held-out pose, and every
/// camera–projector pair; `views` index `devices` (anchored views only are used). A pair
/// without figures to trust is skipped, with the reason, never reported as a result.
pub fn verify(board: &Board, devices: &[Device], views: &[CameraView]) -> Verification {
    verify_with_noise(board, devices, views, &[])
}

/// [`verify`], with each device's observation noise `noise[d]` (px per axis; the
/// calibration's residual RMS): every pair of two devices of known noise also gets the
/// length RMS that noise alone predicts ([`PairCheck::predicted_rms`]).
pub fn verify_with_noise(
    board: &Board,
    devices: &[Device],
    views: &[CameraView],
    noise: &[f64],
) -> Verification {
    let ctx = Context {
        board,
        devices,
        noise,
    };
    // Per (pose, side): camera d → hex → ellipse centre; projector p → (camera, hex) → pixel.
    type PerSide = BTreeMap<usize, BTreeMap<Hex, Point2<f64>>>;
    let mut cams: BTreeMap<(usize, Side), PerSide> = BTreeMap::new();
    let mut out = Vec::new();
    for v in views {
        let Frame::Anchored(side) = v.frame else {
            continue;
        };
        let per = cams.entry((v.pose, side)).or_default();
        for pt in &v.points {
            per.entry(v.camera).or_default().insert(pt.hex, pt.image);
        }
        // Camera–projector pairs of this view.
        let mut by_proj: BTreeMap<usize, Vec<Pairing>> = BTreeMap::new();
        for pt in &v.points {
            for pp in &pt.projectors {
                by_proj.entry(pp.projector).or_default().push(Pairing {
                    hex: pt.hex,
                    first: pt.image,
                    second: pp.pixel,
                });
            }
        }
        for (p, pairs) in by_proj {
            out.extend(check_pair(&ctx, (v.camera, p), false, side, v.pose, &pairs));
        }
    }
    for (&(pose, side), per) in &cams {
        let ids: Vec<usize> = per.keys().copied().collect();
        for (a, &i) in ids.iter().enumerate() {
            for &j in &ids[a + 1..] {
                let pairs: Vec<Pairing> = per[&i]
                    .iter()
                    .filter_map(|(h, e)| {
                        per[&j].get(h).map(|f| Pairing {
                            hex: *h,
                            first: *e,
                            second: *f,
                        })
                    })
                    .collect();
                out.extend(check_pair(&ctx, (i, j), true, side, pose, &pairs));
            }
        }
    }
    let mut verification = Verification::default();
    for result in out {
        match result {
            Ok(check) => verification.checks.push(check),
            Err(skipped) => verification.skipped.push(skipped),
        }
    }
    verification
}

/// RMS of the pairs' length errors (mm), if any pair was checked.
pub fn verification_rms(checks: &[PairCheck]) -> Option<f64> {
    (!checks.is_empty()).then(|| {
        (checks.iter().map(|k| k.length_rms.powi(2)).sum::<f64>() / checks.len() as f64).sqrt()
    })
}
