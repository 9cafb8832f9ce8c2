//! Grid building on boards rendered here through a pinhole camera: circle radii 4–40 px,
//! tilts up to 75°, every in-plane rotation, both sides. The true ellipse of each circle is
//! the exact image of its outline (a conic through the homography) and stands in for the
//! detector.

#[path = "support/grid_truth.rs"]
mod truth;

use hexcal::board::{Board, Hex, Side};
use hexcal::grid::{build, GridParams};
use hexcal::images::{Ellipse, FloatImage};
use nalgebra::{Matrix3, Point2, Rotation3, SymmetricEigen, Vector2, Vector3};

/// A view of one side: board-plane point (x, y) in that side's frame (mm) ↦ pixel.
struct View {
    h_inv: Matrix3<f64>,
    width: u32,
    height: u32,
}

impl View {
    /// Camera with focal length `f` (px) looking at the side's point `look` (mm) from
    /// `distance` (mm), the board tilted by `tilt` about an in-plane axis at angle `axis` and
    /// turned by `spin` about its normal (radians).
    fn new(
        f: f64,
        size: (u32, u32),
        look: Vector2<f64>,
        distance: f64,
        tilt: f64,
        axis: f64,
        spin: f64,
    ) -> View {
        // Side frame: x right, y up, z out of the face towards the camera. Camera: x right,
        // y down, z forward. Facing the camera flips y and z: diag(1, −1, −1).
        let face = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
        let r = Rotation3::from_axis_angle(&Vector3::z_axis(), spin)
            * Rotation3::from_axis_angle(
                &nalgebra::Unit::new_normalize(Vector3::new(axis.cos(), axis.sin(), 0.0)),
                tilt,
            );
        let r = face * r.matrix();
        let t = Vector3::new(0.0, 0.0, distance) - r * Vector3::new(look.x, look.y, 0.0);
        let k = Matrix3::new(
            f,
            0.0,
            f64::from(size.0 - 1) / 2.0,
            0.0,
            f,
            f64::from(size.1 - 1) / 2.0,
            0.0,
            0.0,
            1.0,
        );
        let h = k * Matrix3::from_columns(&[r.column(0).into(), r.column(1).into(), t]);
        View {
            h_inv: h.try_inverse().unwrap(),
            width: size.0,
            height: size.1,
        }
    }

    fn to_board(&self, x: f64, y: f64) -> Option<Vector2<f64>> {
        let p = self.h_inv * Vector3::new(x, y, 1.0);
        (p.z.abs() > 1e-12).then(|| Vector2::new(p.x / p.z, p.y / p.z))
    }

    /// The exact image ellipse of the circle of radius `r` about `c` (board mm):
    /// C' = H⁻ᵀ·C·H⁻¹, centre −A⁻¹b, axes from the eigenvalues of A over the level.
    fn ellipse(&self, c: Point2<f64>, r: f64) -> Option<Ellipse> {
        let q = Matrix3::new(
            1.0,
            0.0,
            -c.x,
            0.0,
            1.0,
            -c.y,
            -c.x,
            -c.y,
            c.x * c.x + c.y * c.y - r * r,
        );
        let m = self.h_inv.transpose() * q * self.h_inv;
        let a = m.fixed_view::<2, 2>(0, 0).into_owned();
        let b = m.fixed_view::<2, 1>(0, 2).into_owned();
        let centre = -a.try_inverse()? * b;
        let level = -(m[(2, 2)] + (b.transpose() * centre)[0]);
        let eig = SymmetricEigen::new(a / level);
        if eig.eigenvalues.iter().any(|&l| l <= 0.0) {
            return None;
        }
        // The major axis belongs to the smaller eigenvalue.
        let (i, j) = if eig.eigenvalues[0] < eig.eigenvalues[1] {
            (0, 1)
        } else {
            (1, 0)
        };
        let u = eig.eigenvectors.column(i);
        Some(Ellipse {
            center: Point2::from(centre),
            a: 1.0 / eig.eigenvalues[i].sqrt(),
            b: 1.0 / eig.eigenvalues[j].sqrt(),
            angle: u[1].atan2(u[0]),
        })
    }
}

/// The board's texture on one side at a point (mm): 1 white, 0 black board.
fn texture(board: &Board, ringed: &std::collections::HashSet<Hex>, p: Vector2<f64>) -> f32 {
    if p.x.abs() > board.size[0] / 2.0 || p.y.abs() > board.size[1] / 2.0 {
        return 0.5; // grey surroundings
    }
    // Nearest lattice point by cube rounding of the fractional axial coordinates.
    let rf = p.y / (board.pitch * 0.75f64.sqrt());
    let qf = p.x / board.pitch - rf / 2.0;
    let (mut q, mut r, s) = (qf.round(), rf.round(), (-qf - rf).round());
    let (dq, dr, ds) = ((q - qf).abs(), (r - rf).abs(), (s + qf + rf).abs());
    if dq > dr && dq > ds {
        q = -r - s;
    } else if dr > ds {
        r = -q - s;
    }
    let h = Hex::new(q as i32, r as i32);
    if !board.contains(h) {
        return 0.0;
    }
    let rho = (p - board.position(h).coords).norm() / board.radius;
    let in_ring = ringed.contains(&h) && rho > board.ring[0] && rho < board.ring[1];
    if rho <= 1.0 && !in_ring {
        1.0
    } else {
        0.0
    }
}

/// Render a side through a view: 2×2 supersampling, Gaussian blur σ = 0.8 px, black 20,
/// white 200 (docs/design.md §9 single-frame conditions, noise-free).
fn render(board: &Board, side: Side, view: &View) -> FloatImage {
    let ringed = board.ringed(side);
    let sharp = FloatImage::from_fn(view.width, view.height, |x, y| {
        let mut acc = 0.0;
        for i in [-0.25, 0.25] {
            for j in [-0.25, 0.25] {
                let (sx, sy) = (f64::from(x) + i, f64::from(y) + j);
                acc += view
                    .to_board(sx, sy)
                    .map_or(0.5, |p| texture(board, &ringed, p));
            }
        }
        image::Luma([20.0 + 180.0 * acc / 4.0])
    });
    blur(&sharp, 0.8)
}

/// Separable Gaussian blur, edges clamped.
fn blur(img: &FloatImage, sigma: f64) -> FloatImage {
    let n = (3.0 * sigma).ceil() as i64;
    let k: Vec<f32> = (-n..=n)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let sum: f32 = k.iter().sum();
    let (w, h) = (i64::from(img.width()), i64::from(img.height()));
    let pass = |src: &FloatImage, dx: i64, dy: i64| {
        FloatImage::from_fn(img.width(), img.height(), |x, y| {
            let mut acc = 0.0;
            for (t, kv) in k.iter().enumerate() {
                let o = t as i64 - n;
                let xx = (i64::from(x) + o * dx).clamp(0, w - 1);
                let yy = (i64::from(y) + o * dy).clamp(0, h - 1);
                acc += kv * src.get_pixel(xx as u32, yy as u32).0[0];
            }
            image::Luma([acc / sum])
        })
    };
    pass(&pass(img, 1, 0), 0, 1)
}

/// Render, build from the exact ellipses of every whole circle in view, and check: no wrong
/// label, anchored when the centre cell is whole in view, and every circle that a cell can
/// reach labelled. Returns the labelled count.
fn check(what: &str, side: Side, view: &View) -> usize {
    let board = Board::hex600();
    let image = render(&board, side, view);
    let mut circles = Vec::new();
    let mut hexes = Vec::new();
    for h in board.lattice() {
        let Some(e) = view.ellipse(board.position(h), board.radius) else {
            continue;
        };
        let m = e.a + 2.0;
        let inside = |v: f64, n: u32| v > m && v < f64::from(n) - 1.0 - m;
        if inside(e.center.x, view.width) && inside(e.center.y, view.height) {
            circles.push(truth::detection(&image, e));
            hexes.push(h);
        }
    }
    let grid = build(&image, &circles, &board, &GridParams::default());
    let kept: std::collections::HashSet<Hex> = hexes.iter().copied().collect();
    let centre_whole = std::iter::once(Hex::new(0, 0))
        .chain(Hex::new(0, 0).neighbours())
        .all(|h| kept.contains(&h));
    let radii: Vec<f64> = circles.iter().map(|c| c.ellipse.radius()).collect();
    println!(
        "{what}: {} circles (r {:.1}–{:.1} px), labelled {}, anchored {}, side {:?}, markers {}",
        circles.len(),
        radii.iter().copied().fold(f64::MAX, f64::min),
        radii.iter().copied().fold(0.0, f64::max),
        grid.points.len(),
        grid.anchored,
        grid.side,
        grid.stats.markers.len()
    );
    // One lattice transform for all labels; the identity when anchored.
    let mut votes = std::collections::HashMap::new();
    for p in &grid.points {
        for s in 0..6 {
            *votes
                .entry((s, hexes[p.circle] - p.hex.rotate(s)))
                .or_insert(0usize) += 1;
        }
    }
    let best = votes.values().copied().max().unwrap_or(0);
    assert_eq!(
        best,
        grid.points.len(),
        "{what}: labels not one lattice transform"
    );
    for p in &grid.points {
        assert!(p.side.is_none_or(|s| s == side), "{what}: wrong side");
        if p.anchored {
            assert_eq!(p.hex, hexes[p.circle], "{what}: wrong anchored label");
        }
    }
    assert_eq!(grid.anchored, centre_whole, "{what}: anchoring");
    grid.points.len()
}

#[test]
fn radii_from_4_to_40_px() {
    // Frontal, slightly tilted, centred on the centre cell; the focal length sets the radius.
    for (f, r_px, size) in [
        (800.0, 4.0, (1280, 1024)),
        (1500.0, 10.0, (1280, 1024)),
        (4000.0, 40.0, (1600, 1200)),
    ] {
        let distance = f * 6.0 / r_px;
        let view = View::new(f, size, Vector2::new(15.0, -8.0), distance, 0.2, 0.4, 0.3);
        let n = check(&format!("r ≈ {r_px} px"), Side::Front, &view);
        assert!(n >= 60, "r ≈ {r_px} px: only {n} labelled");
    }
}

#[test]
fn tilts_to_75_degrees_every_rotation_both_sides() {
    // Three in-plane turns per tilt, all six 60° sectors over two tilts, sides alternating.
    for (i, tilt) in [0.0f64, 45.0, 60.0, 75.0].into_iter().enumerate() {
        for j in 0..3 {
            let side = if (i + j) % 2 == 0 {
                Side::Front
            } else {
                Side::Back
            };
            let sector = (3 * i + j) % 6;
            let spin_rad = (sector as f64 * 60.0 + 17.0).to_radians();
            // Shrink the distance with the tilt so circles stay ≥ 4 px across the minor axis.
            let f = 1400.0;
            let distance = 1300.0 * (1.0 - 0.5 * tilt.to_radians().sin());
            let view = View::new(
                f,
                (1280, 1024),
                Vector2::new(10.0, 20.0),
                distance,
                tilt.to_radians(),
                1.1,
                spin_rad,
            );
            check(
                &format!("{side} tilt {tilt}° spin {spin_rad:.2}"),
                side,
                &view,
            );
        }
    }
}
