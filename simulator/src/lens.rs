//! Lenses as seen by the renderer: a pixel → ray map, and a cached grid of exact rays that
//! gives the ray (and its derivatives) at any sub-pixel position by cubic interpolation.

use nalgebra::{Point2, Vector3};
use rayon::prelude::*;

/// Image size in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageSize {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
}

impl ImageSize {
    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// Any lens the renderer can look through: the ray through a pixel, in the device frame
/// (x right, y down, z forward), pixel (0, 0) at the centre of the top-left pixel.
pub trait Lens: Sync {
    /// Image size.
    fn size(&self) -> ImageSize;
    /// Direction (any length) of the ray through a sub-pixel position; `None` where the lens
    /// model is not valid.
    fn ray(&self, pixel: Point2<f64>) -> Option<Vector3<f64>>;
}

/// A ray and its derivatives with respect to the pixel position.
#[derive(Clone, Copy, Debug)]
pub struct RayJet {
    /// Direction (near unit length).
    pub dir: Vector3<f64>,
    /// ∂dir/∂x.
    pub dx: Vector3<f64>,
    /// ∂dir/∂y.
    pub dy: Vector3<f64>,
}

/// Node spacing of [`RayGrid`] (px).
const STEP: f64 = 4.0;

/// Exact rays of a lens on a grid every `STEP` pixels, interpolated by tensor cubic Lagrange
/// polynomials (exact for cubics; error O(STEP⁴·∂⁴ray): ~1e-6 px for k1 = −0.3 at f = 300 px,
/// falling as 1/f³). Each grid cell is checked at its centre against the exact ray; cells where
/// the interpolation is off by more than [`RayGrid::TOLERANCE_PX`], or a node is invalid, fall
/// back to the lens itself. Build it once per camera; it serves every board pose.
pub struct RayGrid<'a> {
    lens: &'a dyn Lens,
    size: ImageSize,
    /// Node (i, j) sits at pixel (X0 + i·STEP, X0 + j·STEP).
    nx: usize,
    ny: usize,
    /// Unit rays at the nodes (NaN where the lens has none; such cells are never trusted).
    nodes: Vec<Vector3<f64>>,
    /// Per cell (between nodes i..i+1, j..j+1): whether interpolation is trusted.
    cell_ok: Vec<bool>,
    fallback_cells: usize,
}

/// Pixel position of node 0 (one node outside the image so every pixel has a 4×4 stencil).
const X0: f64 = -0.5 - STEP;

impl<'a> RayGrid<'a> {
    /// Largest accepted interpolation error at a cell centre (px).
    pub const TOLERANCE_PX: f64 = 1e-5;

    /// Trace the grid's nodes and check every cell.
    pub fn new(lens: &'a dyn Lens) -> RayGrid<'a> {
        let size = lens.size();
        let count = |n: u32| ((f64::from(n) - 0.5 + 2.0 * STEP - X0) / STEP).ceil() as usize + 1;
        let (nx, ny) = (count(size.width), count(size.height));
        let nodes: Vec<Vector3<f64>> = (0..nx * ny)
            .into_par_iter()
            .map(|k| {
                let p = Point2::new(X0 + (k % nx) as f64 * STEP, X0 + (k / nx) as f64 * STEP);
                lens.ray(p)
                    .map_or(Vector3::repeat(f64::NAN), |v| v.normalize())
            })
            .collect();
        let mut grid = RayGrid {
            lens,
            size,
            nx,
            ny,
            nodes,
            cell_ok: vec![true; nx * ny],
            fallback_cells: 0,
        };
        let margin = |k: usize| {
            let (i, j) = (k % nx, k / nx);
            i == 0 || j == 0 || i + 3 > nx || j + 3 > ny
        };
        let ok: Vec<bool> = (0..nx * ny)
            .into_par_iter()
            .map(|k| {
                let (i, j) = (k % nx, k / nx);
                if margin(k) {
                    return false;
                }
                let p = Point2::new(X0 + (i as f64 + 0.5) * STEP, X0 + (j as f64 + 0.5) * STEP);
                let (Some(exact), Some(jet)) = (lens.ray(p), grid.interpolate(p)) else {
                    return false;
                };
                let exact = exact.normalize();
                // Pixel error ≈ angular error / angle per pixel.
                let per_px = jet.dx.norm().max(jet.dy.norm());
                let err = (exact - jet.dir / jet.dir.norm()).norm() / per_px;
                err <= Self::TOLERANCE_PX
            })
            .collect();
        grid.fallback_cells = (0..nx * ny).filter(|&k| !margin(k) && !ok[k]).count();
        grid.cell_ok = ok;
        grid
    }

    /// Image size of the lens.
    pub fn size(&self) -> ImageSize {
        self.size
    }

    /// Number of grid cells answered by the lens itself (interpolation not trusted).
    pub fn fallback_cells(&self) -> usize {
        self.fallback_cells
    }

    /// Cubic interpolation from the 4×4 nodes around `p`, without the cell check.
    fn interpolate(&self, p: Point2<f64>) -> Option<RayJet> {
        let (u, v) = ((p.x - X0) / STEP, (p.y - X0) / STEP);
        let (i, j) = (u.floor() as isize, v.floor() as isize);
        if i < 1 || j < 1 || i as usize + 3 > self.nx || j as usize + 3 > self.ny {
            return None;
        }
        let (wx, dwx) = lagrange4(u - i as f64);
        let (wy, dwy) = lagrange4(v - j as f64);
        let mut jet = RayJet {
            dir: Vector3::zeros(),
            dx: Vector3::zeros(),
            dy: Vector3::zeros(),
        };
        for b in 0..4 {
            let row = (j as usize + b - 1) * self.nx + i as usize - 1;
            for a in 0..4 {
                let n = self.nodes[row + a];
                jet.dir += n * (wx[a] * wy[b]);
                jet.dx += n * (dwx[a] * wy[b] / STEP);
                jet.dy += n * (wx[a] * dwy[b] / STEP);
            }
        }
        jet.dir.x.is_finite().then_some(jet)
    }

    /// The rays (with derivatives) through the pixel centres of row `y`, written to `out`
    /// (one per column): the same interpolant as [`RayGrid::jet`], evaluated separably.
    pub fn row_jets(&self, y: usize, out: &mut Vec<Option<RayJet>>) {
        out.clear();
        let v = (y as f64 - X0) / STEP;
        // v ≥ 1 for every row: truncation is the floor (f64::floor is a libm call).
        let j = v as usize;
        let (wy, dwy) = lagrange4(v - j as f64);
        // Interpolate every node column along y first (value and ∂/∂y).
        let (col, dcol): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = (0..self.nx)
            .map(|i| {
                let (mut c, mut d) = (Vector3::zeros(), Vector3::zeros());
                for b in 0..4 {
                    let n = self.nodes[(j + b - 1) * self.nx + i];
                    c += n * wy[b];
                    d += n * (dwy[b] / STEP);
                }
                (c, d)
            })
            .unzip();
        for x in 0..self.size.width as usize {
            let u = (x as f64 - X0) / STEP;
            let i = u as usize;
            if !self.cell_ok[j * self.nx + i] {
                out.push(self.jet(Point2::new(x as f64, y as f64)));
                continue;
            }
            let (wx, dwx) = lagrange4(u - i as f64);
            let mut jet = RayJet {
                dir: Vector3::zeros(),
                dx: Vector3::zeros(),
                dy: Vector3::zeros(),
            };
            for a in 0..4 {
                jet.dir += col[i + a - 1] * wx[a];
                jet.dx += col[i + a - 1] * (dwx[a] / STEP);
                jet.dy += dcol[i + a - 1] * wx[a];
            }
            out.push(Some(jet));
        }
    }

    /// The ray through a sub-pixel position with its derivatives; `None` where the lens is
    /// not valid.
    pub fn jet(&self, p: Point2<f64>) -> Option<RayJet> {
        if self.trusted(p) {
            return self.interpolate(p);
        }
        // Fallback: the lens itself, derivatives by central differences.
        const H: f64 = 1e-3;
        let r = |dx: f64, dy: f64| {
            self.lens
                .ray(Point2::new(p.x + dx, p.y + dy))
                .map(|v| v / v.norm())
        };
        let dir = r(0.0, 0.0)?;
        let (xp, xm, yp, ym) = (r(H, 0.0)?, r(-H, 0.0)?, r(0.0, H)?, r(0.0, -H)?);
        Some(RayJet {
            dir,
            dx: (xp - xm) / (2.0 * H),
            dy: (yp - ym) / (2.0 * H),
        })
    }

    /// The ray through a sub-pixel position (no derivatives).
    pub fn ray(&self, p: Point2<f64>) -> Option<Vector3<f64>> {
        if self.trusted(p) {
            let (u, v) = ((p.x - X0) / STEP, (p.y - X0) / STEP);
            // Trusted positions have u, v ≥ 1: truncation is the floor.
            let (i, j) = (u as usize, v as usize);
            let (wx, _) = lagrange4(u - i as f64);
            let (wy, _) = lagrange4(v - j as f64);
            let mut dir = Vector3::zeros();
            for (b, wyb) in wy.iter().enumerate() {
                let row = (j + b - 1) * self.nx + i - 1;
                let mut r = Vector3::zeros();
                for (a, wxa) in wx.iter().enumerate() {
                    r += self.nodes[row + a] * *wxa;
                }
                dir += r * *wyb;
            }
            Some(dir)
        } else {
            self.lens.ray(p).map(|v| v / v.norm())
        }
    }

    /// The rays through the n×n sub-pixel sample points of pixel (x, y) (at offsets
    /// (k + ½)/n − ½), row by row, written to `out`. A pixel never straddles two grid cells
    /// (cell edges fall on pixel edges), so one 4×4 stencil serves all of them.
    pub fn pixel_rays(&self, x: usize, y: usize, n: u32, out: &mut Vec<Option<Vector3<f64>>>) {
        out.clear();
        let h = 1.0 / f64::from(n);
        let offset = |k: u32| (f64::from(k) + 0.5) * h - 0.5;
        let (u0, v0) = ((x as f64 - X0) / STEP, (y as f64 - X0) / STEP);
        let (i, j) = (u0 as usize, v0 as usize);
        if !self.cell_ok[j * self.nx + i] {
            for b in 0..n {
                for a in 0..n {
                    let p = Point2::new(x as f64 + offset(a), y as f64 + offset(b));
                    out.push(self.lens.ray(p).map(|v| v / v.norm()));
                }
            }
            return;
        }
        let wx: Vec<[f64; 4]> = (0..n)
            .map(|a| lagrange4((x as f64 + offset(a) - X0) / STEP - i as f64).0)
            .collect();
        for b in 0..n {
            let (wy, _) = lagrange4((y as f64 + offset(b) - X0) / STEP - j as f64);
            let cols: [Vector3<f64>; 4] = std::array::from_fn(|a| {
                (0..4).fold(Vector3::zeros(), |acc, bb| {
                    acc + self.nodes[(j + bb - 1) * self.nx + i + a - 1] * wy[bb]
                })
            });
            for w in &wx {
                out.push(Some(
                    cols[0] * w[0] + cols[1] * w[1] + cols[2] * w[2] + cols[3] * w[3],
                ));
            }
        }
    }

    fn trusted(&self, p: Point2<f64>) -> bool {
        let (u, v) = ((p.x - X0) / STEP, (p.y - X0) / STEP);
        if !(u >= 1.0 && v >= 1.0) {
            return false;
        }
        let (i, j) = (u as usize, v as usize);
        i < self.nx && j < self.ny && self.cell_ok[j * self.nx + i]
    }
}

/// Cubic Lagrange weights on nodes −1, 0, 1, 2 at t ∈ [0, 1), and their derivatives.
fn lagrange4(t: f64) -> ([f64; 4], [f64; 4]) {
    let (a, b, c, d) = (t + 1.0, t, t - 1.0, t - 2.0);
    let w = [
        -b * c * d / 6.0,
        a * c * d / 2.0,
        -a * b * d / 2.0,
        a * b * c / 6.0,
    ];
    let dw = [
        -(c * d + b * d + b * c) / 6.0,
        (c * d + a * d + a * c) / 2.0,
        -(b * d + a * d + a * b) / 2.0,
        (b * c + a * c + a * b) / 6.0,
    ];
    (w, dw)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A pinhole with strong radial distortion, inverted by Newton's method: the test lens.
    pub(crate) struct RadialLens {
        pub size: ImageSize,
        pub f: f64,
        pub c: Point2<f64>,
        pub k1: f64,
        pub k2: f64,
    }

    impl RadialLens {
        pub fn project(&self, x: Vector3<f64>) -> Point2<f64> {
            let (u, v) = (x.x / x.z, x.y / x.z);
            let r2 = u * u + v * v;
            let s = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
            Point2::new(self.c.x + self.f * u * s, self.c.y + self.f * v * s)
        }
    }

    impl Lens for RadialLens {
        fn size(&self) -> ImageSize {
            self.size
        }
        fn ray(&self, p: Point2<f64>) -> Option<Vector3<f64>> {
            let (dx, dy) = ((p.x - self.c.x) / self.f, (p.y - self.c.y) / self.f);
            let rd = (dx * dx + dy * dy).sqrt();
            // Solve r·(1 + k1 r² + k2 r⁴) = rd.
            let mut r = rd;
            for _ in 0..30 {
                let g = r * (1.0 + self.k1 * r * r + self.k2 * r.powi(4)) - rd;
                let dg = 1.0 + 3.0 * self.k1 * r * r + 5.0 * self.k2 * r.powi(4);
                if dg <= 0.0 {
                    return None;
                }
                r -= g / dg;
            }
            let s = if rd > 0.0 { r / rd } else { 1.0 };
            Some(Vector3::new(dx * s, dy * s, 1.0))
        }
    }

    pub(crate) fn test_lens() -> RadialLens {
        RadialLens {
            size: ImageSize {
                width: 320,
                height: 240,
            },
            f: 300.0,
            c: Point2::new(161.3, 118.9),
            k1: -0.3,
            k2: 0.08,
        }
    }

    #[test]
    fn interpolated_rays_reproject_to_their_pixels() {
        let lens = test_lens();
        let grid = RayGrid::new(&lens);
        // This lens bends strongly in its corners (the ray's 4th derivative grows there):
        // a few corner cells fall back to the lens.
        assert!(
            grid.fallback_cells() * 50 < grid.nodes.len(),
            "{}",
            grid.fallback_cells()
        );
        let mut worst: f64 = 0.0;
        for k in 0..2000 {
            // A quasi-random sub-pixel position anywhere in the image.
            let p = Point2::new(
                (k as f64 * 0.618_034).fract() * 320.0 - 0.5,
                (k as f64 * 0.414_214).fract() * 240.0 - 0.5,
            );
            let back = lens.project(grid.ray(p).unwrap());
            worst = worst.max((back - p).norm());
            // The derivative matches a central difference of the interpolant.
            let jet = grid.jet(p).unwrap();
            let h = 1e-4;
            let fd = (grid.ray(p + nalgebra::Vector2::new(h, 0.0)).unwrap()
                - grid.ray(p - nalgebra::Vector2::new(h, 0.0)).unwrap())
                / (2.0 * h);
            assert!((fd - jet.dx).norm() < 1e-8 * jet.dx.norm().max(1e-3) + 1e-9);
        }
        // The cell check guarantees TOLERANCE_PX at cell centres; anywhere else the cubic
        // error has the same order.
        assert!(worst < 2.0 * RayGrid::TOLERANCE_PX, "worst {worst} px");
        // Per-pixel sub-sample evaluation is the same interpolant.
        let mut sub = Vec::new();
        for (x, y) in [(0, 0), (13, 77), (319, 239)] {
            grid.pixel_rays(x, y, 4, &mut sub);
            for (k, r) in sub.iter().enumerate() {
                let p = Point2::new(
                    x as f64 + ((k % 4) as f64 + 0.5) / 4.0 - 0.5,
                    y as f64 + ((k / 4) as f64 + 0.5) / 4.0 - 0.5,
                );
                assert!((r.unwrap() - grid.ray(p).unwrap()).norm() < 1e-14);
            }
        }
        // Row-wise evaluation is the same interpolant.
        let mut row = Vec::new();
        for y in [0, 7, 100, 239] {
            grid.row_jets(y, &mut row);
            assert_eq!(row.len(), 320);
            for (x, r) in row.iter().enumerate() {
                let (a, b) = (
                    r.unwrap(),
                    grid.jet(Point2::new(x as f64, y as f64)).unwrap(),
                );
                assert!(
                    (a.dir - b.dir).norm() + (a.dx - b.dx).norm() + (a.dy - b.dy).norm() < 1e-14
                );
            }
        }
    }

    #[test]
    fn cells_beyond_the_lens_model_fall_back_to_the_lens() {
        // k1 = −0.3 alone folds at undistorted radius 1.054, i.e. 141 px from the centre at
        // f = 200: the image corners have no ray.
        let lens = RadialLens {
            f: 200.0,
            k2: 0.0,
            ..test_lens()
        };
        let grid = RayGrid::new(&lens);
        assert!(grid.fallback_cells() > 0);
        let mut invalid = 0;
        for k in 0..4000 {
            let p = Point2::new(
                (k as f64 * 0.618_034).fract() * 320.0 - 0.5,
                (k as f64 * 0.414_214).fract() * 240.0 - 0.5,
            );
            match (grid.ray(p), lens.ray(p)) {
                (Some(a), Some(b)) => {
                    let back = lens.project(a);
                    assert!((back - p).norm() < 2.0 * RayGrid::TOLERANCE_PX, "{p} {b}");
                }
                (None, None) => invalid += 1,
                (a, b) => panic!("{p}: grid {a:?} lens {b:?}"),
            }
        }
        assert!(invalid > 0);
    }
}
