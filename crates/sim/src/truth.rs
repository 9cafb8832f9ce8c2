//! Ground truth of a simulated view: for every circle of the seen side that is imaged, its
//! projected centre, the centre and shape of its imaged outline, and whether it is whole in
//! the frame (field names as in the shared detection samples).
//!
//! The outline ellipse is the algebraic conic fit of [`RIM_POINTS`] rim points projected
//! exactly through the full lens model. For a pinhole the outline is an exact ellipse and
//! the fit reproduces it (its centre is the pole of the vanishing line, docs/design.md §4/§8);
//! with distortion the outline is not quite an ellipse, and the fit is the ellipse an
//! edge-fitting detector converges to. On the shared samples this agrees with their
//! `ellipse` to their 1e-6 px rounding (so does the rim polygon's area centroid), whereas
//! distorting the pinhole pole instead is off by up to 0.02 px.

use hexcal_core::board::{Board, Side};
use hexcal_core::camera::CameraModel;
use hexcal_core::images::Ellipse;
use nalgebra::{Isometry3, Point2, Point3, SymmetricEigen, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Rim points projected per circle for its outline ellipse.
pub const RIM_POINTS: usize = 256;

/// Ground truth of one circle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CircleTruth {
    /// Lattice q in the side's own frame.
    pub q: i32,
    /// Lattice r in the side's own frame.
    pub r: i32,
    /// Side the circle is printed on.
    pub side: Side,
    /// The circle's centre projected through the full model (px).
    pub proj: [f64; 2],
    /// Centre of the imaged outline (px); `None` if part of the rim is outside the lens
    /// model's valid region.
    pub ellipse: Option<[f64; 2]>,
    /// √(a·b) of the outline ellipse (px).
    pub radius: Option<f64>,
    /// Semi-axes (a ≥ b) of the outline ellipse (px).
    pub axes: Option<[f64; 2]>,
    /// Angle of the major axis from +x towards +y (degrees, (−90, 90]).
    pub angle_deg: Option<f64>,
    /// Whether the circle carries a marker ring.
    pub ringed: bool,
    /// Whether the whole outline lies inside the frame.
    pub whole: bool,
}

/// Which side of the board faces a camera at pose `T_cam_board` (`None` when edge-on).
pub fn side_seen(board: &Board, cam_from_board: &Isometry3<f64>) -> Option<Side> {
    Side::BOTH.into_iter().find(|&side| {
        let face = cam_from_board * board.side_transform(side);
        let normal = face.rotation * Vector3::z();
        // The camera centre (origin) lies on the face's +z side.
        normal.dot(&face.translation.vector) < 0.0
    })
}

/// The image outline of a board circle: rim points projected through the full model.
/// `None` if a rim point is behind the camera or outside the lens model's valid region (the
/// projection does not ray back onto the point).
pub fn outline(
    camera: &CameraModel,
    face: &Isometry3<f64>,
    centre: Point2<f64>,
    radius: f64,
    n: usize,
) -> Option<Vec<Point2<f64>>> {
    (0..n)
        .map(|k| {
            let phi = 2.0 * std::f64::consts::PI * k as f64 / n as f64;
            let x = face
                * Point3::new(
                    centre.x + radius * phi.cos(),
                    centre.y + radius * phi.sin(),
                    0.0,
                );
            let p = camera.project(&x)?;
            let back = camera.ray(p)?;
            ((back.xy() - x.coords.xy() / x.z).norm() < 1e-9).then_some(p)
        })
        .collect()
}

/// Algebraic conic fit to points on an outline (minimum ‖D·a‖ with ‖a‖ = 1 on centred,
/// scaled coordinates): exact for points on an ellipse.
pub fn fit_ellipse(points: &[Point2<f64>]) -> Option<Ellipse> {
    let n = points.len() as f64;
    let mean = points.iter().fold(Vector2::zeros(), |s, p| s + p.coords) / n;
    let scale = (points
        .iter()
        .map(|p| (p.coords - mean).norm_squared())
        .sum::<f64>()
        / n)
        .sqrt();
    if scale.is_nan() || scale <= 0.0 {
        return None;
    }
    let mut s = nalgebra::Matrix6::<f64>::zeros();
    for p in points {
        let (x, y) = ((p.x - mean.x) / scale, (p.y - mean.y) / scale);
        let row = nalgebra::Vector6::new(x * x, x * y, y * y, x, y, 1.0);
        s += row * row.transpose();
    }
    let eig = SymmetricEigen::new(s);
    let (k, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let c = eig.eigenvectors.column(k);
    let e = conic_to_ellipse([c[0], c[1], c[2], c[3], c[4], c[5]])?;
    Some(Ellipse {
        center: Point2::from(e.center.coords * scale + mean),
        a: e.a * scale,
        b: e.b * scale,
        angle: e.angle,
    })
}

/// The ellipse A x² + B xy + C y² + D x + E y + F = 0 (`None` if not a real ellipse).
fn conic_to_ellipse([a, b, c, d, e, f]: [f64; 6]) -> Option<Ellipse> {
    let det = 4.0 * a * c - b * b;
    if det.is_nan() || det <= 0.0 {
        return None;
    }
    // Centre: ∇ = 0 → [2A B; B 2C]·x = −(D, E).
    let x0 = (b * e - 2.0 * c * d) / det;
    let y0 = (b * d - 2.0 * a * e) / det;
    let f0 = f + 0.5 * (d * x0 + e * y0);
    let m = nalgebra::Matrix2::new(a, 0.5 * b, 0.5 * b, c);
    let eig = SymmetricEigen::new(m);
    let (l0, l1) = (eig.eigenvalues[0], eig.eigenvalues[1]);
    let (s0, s1) = (-f0 / l0, -f0 / l1);
    if !(s0 > 0.0 && s1 > 0.0) {
        return None;
    }
    // Major axis along the eigenvector of the smaller eigenvalue.
    let (major, minor, k) = if s0 >= s1 { (s0, s1, 0) } else { (s1, s0, 1) };
    let v = eig.eigenvectors.column(k);
    Some(Ellipse {
        center: Point2::new(x0, y0),
        a: major.sqrt(),
        b: minor.sqrt(),
        angle: v[1].atan2(v[0]),
    })
}

/// Ground truth of every imaged circle of the side that faces the camera (none if the
/// board is seen edge-on).
pub fn circles(
    board: &Board,
    camera: &CameraModel,
    cam_from_board: &Isometry3<f64>,
) -> Vec<CircleTruth> {
    let Some(side) = side_seen(board, cam_from_board) else {
        return Vec::new();
    };
    let face = cam_from_board * board.side_transform(side);
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let in_frame = |p: &Point2<f64>| p.x >= -0.5 && p.y >= -0.5 && p.x < w - 0.5 && p.y < h - 0.5;
    board
        .circles(side)
        .iter()
        .filter_map(|c| {
            let centre = face * Point3::new(c.center_2d.x, c.center_2d.y, 0.0);
            let proj = camera.project(&centre)?;
            let rim = outline(camera, &face, c.center_2d, board.radius, RIM_POINTS);
            let visible = in_frame(&proj) || rim.as_ref().is_some_and(|r| r.iter().any(in_frame));
            if !visible {
                return None;
            }
            let ellipse = rim.as_deref().and_then(fit_ellipse);
            let whole = rim.as_ref().is_some_and(|r| r.iter().all(in_frame));
            Some(CircleTruth {
                q: c.hex.q,
                r: c.hex.r,
                side,
                proj: [proj.x, proj.y],
                ellipse: ellipse.map(|e| [e.center.x, e.center.y]),
                radius: ellipse.map(|e| e.radius()),
                axes: ellipse.map(|e| [e.a, e.b]),
                angle_deg: ellipse.map(|e| {
                    let d = e.angle.to_degrees();
                    // Fold into (−90, 90].
                    d - 180.0 * ((d - 90.0) / 180.0).ceil()
                }),
                ringed: c.ringed,
                whole,
            })
        })
        .collect()
}
