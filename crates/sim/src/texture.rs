//! The board as the simulator sees it: one textured face per side (white circles with dark
//! marker rings on a black rectangle) and four uniform faces for the board's edges.

use hexcal_core::board::{Board, Side};
use hexcal_simulator::{Edge, Face, Target, Texel, Texture, UniformRect};
use nalgebra::{Isometry3, Point2, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};

/// Albedos of the printed board (1 = the white of the circles).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoardAlbedo {
    /// Circles.
    pub white: f32,
    /// Board and marker rings.
    pub black: f32,
    /// The board's edge faces.
    pub edge: f32,
}

/// What a lattice point carries on one side.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Cell {
    Empty,
    Circle,
    Ringed,
}

/// One side of a board as a [`Texture`] in that side's own frame (mm).
pub struct BoardTexture {
    pitch: f64,
    inv_pitch: f64,
    /// 1 / row spacing (1 / (pitch·√3/2)).
    inv_row: f64,
    radius: f64,
    ring: [f64; 2],
    half: Vector2<f64>,
    white: f32,
    black: f32,
    q0: i32,
    r0: i32,
    nq: i32,
    nr: i32,
    cells: Vec<Cell>,
}

impl BoardTexture {
    /// The texture of `side` of `board`.
    pub fn new(board: &Board, side: Side, albedo: BoardAlbedo) -> BoardTexture {
        let circles = board.circles(side);
        let (q0, q1) = circles.iter().fold((i32::MAX, i32::MIN), |(a, b), c| {
            (a.min(c.hex.q), b.max(c.hex.q))
        });
        let (r0, r1) = circles.iter().fold((i32::MAX, i32::MIN), |(a, b), c| {
            (a.min(c.hex.r), b.max(c.hex.r))
        });
        let (nq, nr) = (q1 - q0 + 1, r1 - r0 + 1);
        let mut cells = vec![Cell::Empty; (nq * nr) as usize];
        for c in &circles {
            cells[((c.hex.r - r0) * nq + c.hex.q - q0) as usize] =
                if c.ringed { Cell::Ringed } else { Cell::Circle };
        }
        BoardTexture {
            pitch: board.pitch,
            inv_pitch: 1.0 / board.pitch,
            inv_row: 1.0 / (board.pitch * 0.75f64.sqrt()),
            radius: board.radius,
            ring: [board.ring[0] * board.radius, board.ring[1] * board.radius],
            half: Vector2::new(board.size[0] / 2.0, board.size[1] / 2.0),
            white: albedo.white,
            black: albedo.black,
            q0,
            r0,
            nq,
            nr,
            cells,
        }
    }

    fn cell(&self, q: i32, r: i32) -> Cell {
        let (i, j) = (q - self.q0, r - self.r0);
        if i < 0 || j < 0 || i >= self.nq || j >= self.nr {
            Cell::Empty
        } else {
            self.cells[(j * self.nq + i) as usize]
        }
    }

    fn centre(&self, q: i32, r: i32) -> Vector2<f64> {
        let (q, r) = (f64::from(q), f64::from(r));
        Vector2::new(self.pitch * (q + 0.5 * r), self.pitch * 0.75f64.sqrt() * r)
    }

    /// Albedo at distance `rho` from the centre of a circle of kind `cell`.
    fn level(&self, cell: Cell, rho: f64) -> f32 {
        let ringed = cell == Cell::Ringed && rho > self.ring[0] && rho <= self.ring[1];
        if rho <= self.radius && !ringed {
            self.white
        } else {
            self.black
        }
    }
}

impl Texture for BoardTexture {
    fn sample(&self, p: Point2<f64>) -> Option<Texel> {
        let outline = (self.half.x - p.x.abs()).min(self.half.y - p.y.abs());
        if outline < 0.0 {
            return None;
        }
        // Nearest lattice point by cube rounding of the axial coordinates (§3).
        let rf = p.y * self.inv_row;
        let qf = p.x * self.inv_pitch - 0.5 * rf;
        let sf = -qf - rf;
        // Round half away from zero with an inline truncation (f64::round is a libm call).
        let round = |v: f64| (v + 0.5f64.copysign(v)) as i64 as f64;
        let (mut q, mut r, s) = (round(qf), round(rf), round(sf));
        let (dq, dr, ds) = ((q - qf).abs(), (r - rf).abs(), (s - sf).abs());
        if dq > dr && dq > ds {
            q = -r - s;
        } else if dr > ds {
            r = -q - s;
        }
        let (q, r) = (q as i32, r as i32);
        // The nearest circle is the nearest lattice point's, else a neighbour's (at the rim
        // of the circle area); farther circles are ≥ 1.5 pitches away: no edge near.
        let nearest = match self.cell(q, r) {
            Cell::Empty => hexcal_core::board::Hex::DIRECTIONS
                .iter()
                .map(|d| (q + d.q, r + d.r))
                .filter(|&(a, b)| self.cell(a, b) != Cell::Empty)
                .map(|(a, b)| (self.cell(a, b), p.coords - self.centre(a, b)))
                .min_by(|a, b| a.1.norm_squared().total_cmp(&b.1.norm_squared())),
            cell => Some((cell, p.coords - self.centre(q, r))),
        };
        let Some((cell, d)) = nearest else {
            return Some(Texel {
                albedo: self.black,
                edge: None,
                outline,
            });
        };
        let rho = d.norm();
        let out = if rho > 0.0 { d / rho } else { Vector2::x() };
        // The nearest edge radius: R, or for a ringed circle the nearest of 0.45R, 0.75R, R
        // (midpoints between them split the choice).
        let re = if cell != Cell::Ringed || rho >= 0.5 * (self.ring[1] + self.radius) {
            self.radius
        } else if rho >= 0.5 * (self.ring[0] + self.ring[1]) {
            self.ring[1]
        } else {
            self.ring[0]
        };
        let inside = rho <= re;
        // The level just across the edge at radius re.
        let beyond = self.level(cell, if inside { re * (1.0 + 1e-9) } else { re });
        Some(Texel {
            albedo: self.level(cell, rho),
            edge: Some(Edge {
                distance: (rho - re).abs(),
                toward: if inside { out } else { -out },
                beyond,
            }),
            outline,
        })
    }
}

/// Index of the board's faces in the [`Target`] built by [`board_target`].
pub fn face_side(face: u8) -> Option<Side> {
    match face {
        0 => Some(Side::Front),
        1 => Some(Side::Back),
        _ => None,
    }
}

/// The board as a simulator target in the board frame: face 0 the front, face 1 the back
/// (through the board's side transform; plain black on a single-sided board), faces 2–5 the
/// edges of a slab of the board's size and thickness between z = 0 and z = −t (exact for the
/// nominal side transform; none on a single-sided board, a plate of no thickness).
pub fn board_target(board: &Board, albedo: BoardAlbedo) -> Target {
    let (hw, hh) = (board.size[0] / 2.0, board.size[1] / 2.0);
    let mut faces: Vec<Face> = Side::BOTH
        .iter()
        .map(|&side| Face {
            pose: board.side_transform(side),
            texture: if board.has(side) {
                Box::new(BoardTexture::new(board, side, albedo))
            } else {
                Box::new(UniformRect {
                    half: Vector2::new(hw, hh),
                    albedo: albedo.black,
                })
            },
        })
        .collect();
    let Some(t) = board.thickness else {
        return Target { faces };
    };
    // (outward normal, face x axis, centre, half extents along face x and y).
    let edges = [
        (
            Vector3::x(),
            -Vector3::z(),
            Vector3::new(hw, 0.0, -t / 2.0),
            [t / 2.0, hh],
        ),
        (
            -Vector3::x(),
            Vector3::z(),
            Vector3::new(-hw, 0.0, -t / 2.0),
            [t / 2.0, hh],
        ),
        (
            Vector3::y(),
            Vector3::x(),
            Vector3::new(0.0, hh, -t / 2.0),
            [hw, t / 2.0],
        ),
        (
            -Vector3::y(),
            Vector3::x(),
            Vector3::new(0.0, -hh, -t / 2.0),
            [hw, t / 2.0],
        ),
    ];
    for (ez, ex, centre, half) in edges {
        let ey = ez.cross(&ex);
        let rot = Rotation3::from_basis_unchecked(&[ex, ey, ez]);
        faces.push(Face {
            pose: Isometry3::from_parts(
                Translation3::from(centre),
                UnitQuaternion::from_rotation_matrix(&rot),
            ),
            texture: Box::new(UniformRect {
                half: Vector2::new(half[0], half[1]),
                albedo: albedo.edge,
            }),
        });
    }
    Target { faces }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hexcal_core::board::Hex;

    const ALBEDO: BoardAlbedo = BoardAlbedo {
        white: 1.0,
        black: 0.1,
        edge: 0.2,
    };

    #[test]
    fn texture_follows_the_board_layout() {
        let board = Board::hex600();
        for side in Side::BOTH {
            let tex = BoardTexture::new(&board, side, ALBEDO);
            let ringed = board.ringed(side);
            for c in board.circles(side) {
                let p = board.position(c.hex);
                let at = |rho: f64| tex.sample(p + Vector2::new(rho, 0.0)).unwrap();
                assert_eq!(at(0.0).albedo, 1.0);
                assert_eq!(
                    at(0.6 * 6.0).albedo,
                    if ringed.contains(&c.hex) { 0.1 } else { 1.0 }
                );
                assert_eq!(at(5.9).albedo, 1.0);
                assert_eq!(at(6.1).albedo, 0.1);
                let e = at(5.5).edge.unwrap();
                assert!((e.distance - 0.5).abs() < 1e-9 && e.beyond == 0.1 && e.toward.x > 0.99);
            }
            // Outside the board, and the black margin beyond the last circle.
            assert!(tex.sample(Point2::new(300.5, 0.0)).is_none());
            let t = tex.sample(Point2::new(299.0, 0.0)).unwrap();
            assert_eq!(t.albedo, 0.1);
            assert!((t.outline - 1.0).abs() < 1e-9);
        }
        // The centre cell's ring code on the front: neighbour k ringed iff bit k is set.
        let tex = BoardTexture::new(&board, Side::Front, ALBEDO);
        for k in 0..6 {
            let p = board.position(Hex::new(0, 0).neighbour(k));
            let ringed = tex.sample(p + Vector2::new(0.0, 3.6)).unwrap().albedo == 0.1;
            assert_eq!(ringed, board.codes.front_center.bit(k));
        }
    }

    #[test]
    fn edge_faces_close_the_slab() {
        let board = Board::hex600();
        let target = board_target(&board, ALBEDO);
        assert_eq!(target.faces.len(), 6);
        for f in &target.faces[2..] {
            let n = f.pose.rotation * Vector3::z();
            let c = f.pose.translation.vector;
            // The face centre is the slab's box face centre and its normal points outward
            // along that axis (a proper rotation: a left-handed basis would flip it).
            let axis = (c - Vector3::new(0.0, 0.0, -5.0)).normalize();
            assert!((n - axis).norm() < 1e-12, "{n} vs {axis}");
            assert!((c.x.abs() - 300.0).abs() < 1e-12 || (c.y.abs() - 250.0).abs() < 1e-12);
            // Its texture spans the thickness: points 4.9 mm either side of the mid-plane
            // are on it, 5.1 mm are not.
            let along_z = f.pose.rotation.inverse() * Vector3::z();
            let inside = |d: f64| {
                f.texture
                    .sample(Point2::new(along_z.x * d, along_z.y * d))
                    .is_some()
            };
            assert!(inside(4.9) && inside(-4.9) && !inside(5.1) && !inside(-5.1));
        }
        // Front face normal +z, back face normal −z.
        assert!((target.faces[0].pose.rotation * Vector3::z()).z > 0.99);
        assert!((target.faces[1].pose.rotation * Vector3::z()).z < -0.99);
    }
}
