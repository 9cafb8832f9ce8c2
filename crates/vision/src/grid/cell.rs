//! Pass 1 of grid building (docs/design.md §5): one local hexagonal cell per detection, found
//! with chord-normalised distances in the centre circle's own ellipse metric.

use super::GridParams;
use crate::detect::Circle;
use nalgebra::{Matrix2, Vector2};

/// A uniform bucket grid over circle centres for radius queries.
pub(crate) struct Buckets {
    size: f64,
    origin: Vector2<f64>,
    cols: usize,
    rows: usize,
    /// Circle indices sorted by bucket; bucket b holds `items[start[b]..start[b + 1]]`.
    items: Vec<u32>,
    start: Vec<u32>,
}

impl Buckets {
    /// Index `circles` in square buckets of side `size` (px).
    pub(crate) fn new(circles: &[Circle], size: f64) -> Buckets {
        let (mut lo, mut hi) = (Vector2::repeat(f64::MAX), Vector2::repeat(f64::MIN));
        for c in circles.iter().filter(|c| usable(c)) {
            lo = lo.inf(&c.ellipse.center.coords);
            hi = hi.sup(&c.ellipse.center.coords);
        }
        if lo.x > hi.x {
            (lo, hi) = (Vector2::zeros(), Vector2::zeros());
        }
        // At most ~4 buckets per circle on average: keeps memory bounded for stray outliers.
        let span = hi - lo;
        let size = size.max((span.x * span.y / (4.0 * circles.len().max(1) as f64)).sqrt());
        let cols = (span.x / size) as usize + 1;
        let rows = (span.y / size) as usize + 1;
        let bucket = |c: &Circle| {
            let p = (c.ellipse.center.coords - lo) / size;
            (p.y as usize).min(rows - 1) * cols + (p.x as usize).min(cols - 1)
        };
        let mut start = vec![0u32; cols * rows + 1];
        for c in circles.iter().filter(|c| usable(c)) {
            start[bucket(c) + 1] += 1;
        }
        for b in 0..cols * rows {
            start[b + 1] += start[b];
        }
        let mut fill = start.clone();
        let mut items = vec![0u32; start[cols * rows] as usize];
        for (i, c) in circles.iter().enumerate().filter(|(_, c)| usable(c)) {
            let b = bucket(c);
            items[fill[b] as usize] = i as u32;
            fill[b] += 1;
        }
        Buckets {
            size,
            origin: lo,
            cols,
            rows,
            items,
            start,
        }
    }

    /// Call `f` for every indexed circle whose bucket meets the square of half-side `radius`
    /// about `p` (a superset of the disk of that radius).
    pub(crate) fn around(&self, p: Vector2<f64>, radius: f64, mut f: impl FnMut(u32)) {
        let lo = (p - self.origin).add_scalar(-radius) / self.size;
        let hi = (p - self.origin).add_scalar(radius) / self.size;
        if hi.x < 0.0 || hi.y < 0.0 || lo.x >= self.cols as f64 || lo.y >= self.rows as f64 {
            return;
        }
        let clamp = |v: f64, n: usize| (v.max(0.0) as usize).min(n - 1);
        let (x0, x1) = (clamp(lo.x, self.cols), clamp(hi.x, self.cols));
        let (y0, y1) = (clamp(lo.y, self.rows), clamp(hi.y, self.rows));
        for y in y0..=y1 {
            let row = y * self.cols;
            for b in row + x0..=row + x1 {
                for &i in &self.items[self.start[b] as usize..self.start[b + 1] as usize] {
                    f(i);
                }
            }
        }
    }
}

/// Whether a detection's ellipse is finite with positive semi-axes; others are ignored.
fn usable(c: &Circle) -> bool {
    let e = &c.ellipse;
    e.center.coords.iter().all(|v| v.is_finite())
        && e.a.is_finite()
        && e.b.is_finite()
        && e.angle.is_finite()
        && e.a > 0.0
        && e.b > 0.0
}

/// One local cell: a centre circle and its neighbours in six counter-clockwise slots as seen
/// on screen (slot s and s + 3 opposite).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Cell {
    /// The centre circle.
    pub center: u32,
    /// Neighbour circle per slot; `None` where the lattice neighbour was not found.
    pub slots: [Option<u32>; 6],
    /// Number of complete opposing pairs that were accepted (2 or 3).
    pub pairs: u8,
    /// Worst normalised residual of the cell's checks (each check passes at ≤ 1).
    pub error: f64,
}

impl Cell {
    /// Whether all six neighbours were found.
    pub(crate) fn is_full(&self) -> bool {
        self.slots.iter().all(Option::is_some)
    }

    /// Its circles: the centre (slot `None`), then each found neighbour with its slot.
    pub(crate) fn members(&self) -> impl Iterator<Item = (Option<usize>, u32)> + '_ {
        std::iter::once((None, self.center)).chain(
            self.slots
                .iter()
                .enumerate()
                .filter_map(|(j, m)| m.map(|m| (Some(j), m))),
        )
    }
}

/// The whitening map W = M^(−1/2)/4 of a circle's outer-boundary ellipse, so that |W·Δ| is
/// the chord-normalised distance ν = √(ΔᵀM⁻¹Δ)/4 (docs/design.md §5). W is symmetric positive
/// definite: it keeps the screen's handedness.
fn whitening(c: &Circle) -> Matrix2<f64> {
    let e = &c.ellipse;
    let (s, co) = e.angle.sin_cos();
    let u = Vector2::new(co, s);
    let v = Vector2::new(-s, co);
    // M = (a²/4)uuᵀ + (b²/4)vvᵀ ⇒ M^(−1/2) = (2/a)uuᵀ + (2/b)vvᵀ.
    (u * u.transpose()) * (0.5 / e.a) + (v * v.transpose()) * (0.5 / e.b)
}

/// Whether `other`'s ellipse has the shape of the centre's (whitening `w`) within `ratio`
/// along every direction: the semi-axes of `other` in the centre's whitened frame, √ of the
/// eigenvalues of 16·W·M·W, lie in [1/ratio, ratio]. Neighbours under the local affine map
/// are alike; a circle cut by an occluder and fitted to what is left of it is short along
/// the cut even when its √(ab) is not.
fn alike(w: &Matrix2<f64>, other: &Circle, ratio: f64) -> bool {
    let e = &other.ellipse;
    let (s, co) = e.angle.sin_cos();
    let (u, v) = (Vector2::new(co, s), Vector2::new(-s, co));
    let m = (u * u.transpose()) * (e.a * e.a / 4.0) + (v * v.transpose()) * (e.b * e.b / 4.0);
    let shape = (w * m * w) * 16.0;
    let (lo, hi) = (1.0 / (ratio * ratio), ratio * ratio);
    shape
        .symmetric_eigenvalues()
        .iter()
        .all(|&l| l >= lo && l <= hi)
}

/// Counter-clockwise screen angle of a y-down vector: atan2(−y, x).
fn screen_angle(z: Vector2<f64>) -> f64 {
    (-z.y).atan2(z.x)
}

/// A candidate neighbour in the centre's whitened frame.
#[derive(Clone, Copy)]
struct Candidate {
    index: u32,
    z: Vector2<f64>,
}

/// An accepted opposing pair (indices into the candidate list).
#[derive(Clone, Copy)]
struct Pair {
    a: usize,
    b: usize,
    cost: f64,
}

/// Why a detection has no cell (pass-1 diagnostics).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Rejection {
    /// The ellipse is not finite or has a non-positive axis.
    Degenerate,
    /// Fewer than two opposing pairs were found (board edge, missing neighbours, stray blob).
    TooFewPairs,
    /// Pairs were found but their slots or the affine consistency failed.
    Inconsistent,
}

/// Pass 1 for every circle: `Ok(cell)` or why there is none.
/// `nu` is the board's d/R, the chord-normalised length of an opposing pair.
pub(crate) fn find_cells(
    circles: &[Circle],
    nu: f64,
    params: &GridParams,
) -> Vec<Result<Cell, Rejection>> {
    let half = 0.5 * nu;
    let max_near = half * params.max_neighbour_ratio;
    let major = |c: &Circle| c.ellipse.a.max(c.ellipse.b);
    let mut sizes: Vec<f64> = circles.iter().filter(|c| usable(c)).map(major).collect();
    let bucket = if sizes.is_empty() {
        1.0
    } else {
        let mid = sizes.len() / 2;
        *sizes.select_nth_unstable_by(mid, f64::total_cmp).1 * 2.0 * max_near
    };
    let buckets = Buckets::new(circles, bucket.max(1.0));
    let mut candidates = Vec::with_capacity(64);
    circles
        .iter()
        .enumerate()
        .map(|(i, c)| {
            if !usable(c) {
                return Err(Rejection::Degenerate);
            }
            candidates.clear();
            let w = whitening(c);
            let centre = c.ellipse.center.coords;
            // |WΔ| ≥ |Δ|/(2a): a neighbour within ν ≤ max_near lies within 2a·max_near px.
            buckets.around(centre, 2.0 * major(c) * max_near, |j| {
                if j as usize == i {
                    return;
                }
                let other = &circles[j as usize];
                if !alike(&w, other, params.radius_ratio) {
                    return;
                }
                let z = w * (other.ellipse.center.coords - centre);
                let n = z.norm();
                if n <= max_near && n * params.max_neighbour_ratio >= half {
                    candidates.push(Candidate { index: j, z });
                }
            });
            candidates.sort_by(|a, b| a.z.norm_squared().total_cmp(&b.z.norm_squared()));
            candidates.truncate(params.candidates);
            local_cell(i as u32, &candidates, nu, params)
        })
        .collect()
}

/// Build one cell from its candidates (whitened, nearest first).
fn local_cell(
    center: u32,
    cands: &[Candidate],
    nu: f64,
    params: &GridParams,
) -> Result<Cell, Rejection> {
    let half = 0.5 * nu;
    // Opposing pairs: ν = |z_b − z_a| within ±tol of d/R, centre near their midpoint.
    let mut pairs = Vec::new();
    for a in 0..cands.len() {
        for b in a + 1..cands.len() {
            let (za, zb) = (cands[a].z, cands[b].z);
            let length = (zb - za).norm();
            let rel = (length / nu - 1.0).abs() / params.pair_tolerance;
            let mid = (za + zb).norm() / length / params.midpoint_tolerance;
            if rel <= 1.0 && mid <= 1.0 {
                pairs.push(Pair {
                    a,
                    b,
                    cost: rel.max(mid),
                });
            }
        }
    }
    pairs.sort_by(|p, q| p.cost.total_cmp(&q.cost));
    // Greedy choice of up to three disjoint pairs on axes 60° apart (mod 180°).
    let axis = |p: &Pair| screen_angle(cands[p.b].z - cands[p.a].z);
    let mut chosen: Vec<Pair> = Vec::with_capacity(3);
    for p in &pairs {
        if chosen.len() == 3 {
            break;
        }
        let disjoint = chosen
            .iter()
            .all(|q| p.a != q.a && p.a != q.b && p.b != q.a && p.b != q.b);
        let spaced = chosen.iter().all(|q| {
            let d = (axis(p) - axis(q)).rem_euclid(std::f64::consts::PI);
            let off = (d - std::f64::consts::FRAC_PI_3)
                .abs()
                .min((d - 2.0 * std::f64::consts::FRAC_PI_3).abs());
            off <= params.slot_tolerance
        });
        if disjoint && spaced {
            chosen.push(*p);
        }
    }
    if chosen.len() < 2 {
        return Err(Rejection::TooFewPairs);
    }
    // Slots: counter-clockwise on screen from the best pair's first member.
    let reference = screen_angle(cands[chosen[0].a].z);
    let slot_of = |z: Vector2<f64>| -> Option<usize> {
        let steps = (screen_angle(z) - reference) / std::f64::consts::FRAC_PI_3;
        let s = steps.round();
        ((steps - s).abs() * std::f64::consts::FRAC_PI_3 <= params.slot_tolerance)
            .then_some(s.rem_euclid(6.0) as usize)
    };
    let mut slots: [Option<usize>; 6] = [None; 6];
    for p in &chosen {
        let (Some(sa), Some(sb)) = (slot_of(cands[p.a].z), slot_of(cands[p.b].z)) else {
            return Err(Rejection::Inconsistent);
        };
        if (sa + 3) % 6 != sb || slots[sa].is_some() || slots[sb].is_some() {
            return Err(Rejection::Inconsistent);
        }
        slots[sa] = Some(p.a);
        slots[sb] = Some(p.b);
    }
    let mut error = chosen.iter().map(|p| p.cost).fold(0.0, f64::max);
    let z = |slots: &[Option<usize>; 6], s: usize| slots[s % 6].map(|c| cands[c].z);
    if chosen.len() == 2 {
        // The missing axis follows from the other two, D(k+1) = D(k) + D(k+2): take the
        // single candidates that sit there (the board's edge leaves one of them out).
        let m = (0..3)
            .find(|&s| slots[s].is_none())
            .expect("one axis is missing");
        for s in [m, m + 3] {
            let predicted = z(&slots, s + 5).unwrap() + z(&slots, s + 1).unwrap();
            let best = (0..cands.len())
                .filter(|c| !slots.contains(&Some(*c)))
                .map(|c| (c, (cands[c].z - predicted).norm() / half))
                .min_by(|a, b| a.1.total_cmp(&b.1));
            if let Some((c, dev)) = best.filter(|b| b.1 <= params.affine_tolerance) {
                slots[s] = Some(c);
                error = error.max(dev / params.affine_tolerance);
            }
        }
    } else {
        // Central differences cancel the perspective's second-order terms: the pair
        // half-differences P(k) = (z(k) − z(k+3))/2 obey P(1) = P(0) + P(2) closely.
        let p = |k| (z(&slots, k).unwrap() - z(&slots, k + 3).unwrap()) * 0.5;
        let dev = (p(1) - p(0) - p(2)).norm() / half / params.pair_affine_tolerance;
        if dev > 1.0 {
            return Err(Rejection::Inconsistent);
        }
        error = error.max(dev);
    }
    // Affine consistency of the single neighbour vectors, D(k+1) = D(k) + D(k+2).
    for k in 0..6 {
        if let (Some(a), Some(b), Some(c)) = (z(&slots, k), z(&slots, k + 1), z(&slots, k + 2)) {
            let dev = (b - a - c).norm() / half / params.affine_tolerance;
            if dev > 1.0 {
                return Err(Rejection::Inconsistent);
            }
            error = error.max(dev);
        }
    }
    Ok(Cell {
        center,
        slots: slots.map(|s| s.map(|c| cands[c].index)),
        pairs: chosen.len() as u8,
        error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use hexcal_core::board::{Board, Hex};
    use hexcal_core::images::Ellipse;
    use nalgebra::{Matrix2, Point2};

    /// Circles of the lattice within `reach` of the origin seen through the affine map
    /// `a` (board mm, y up → pixels, y down): each circle's ellipse is the image of the
    /// board circle, from the singular value decomposition of `a`.
    fn affine_lattice(a: Matrix2<f64>, reach: i32) -> (Vec<Circle>, Vec<Hex>) {
        let board = Board::hex600();
        let svd = a.svd(true, false);
        let u = svd.u.unwrap();
        let (i, j) = if svd.singular_values[0] >= svd.singular_values[1] {
            (0, 1)
        } else {
            (1, 0)
        };
        let ellipse = |c: Point2<f64>| Ellipse {
            center: c,
            a: board.radius * svd.singular_values[i],
            b: board.radius * svd.singular_values[j],
            angle: u[(1, i)].atan2(u[(0, i)]),
        };
        let hexes: Vec<Hex> = board
            .lattice()
            .into_iter()
            .filter(|h| h.distance(Hex::new(0, 0)) <= reach)
            .collect();
        let circles = hexes
            .iter()
            .map(|&h| Circle {
                ellipse: ellipse(
                    Point2::from(a * board.position(h).coords)
                        + nalgebra::Vector2::new(500.0, 400.0),
                ),
                score: 0.3,
                background: 20.0,
                foreground: 200.0,
                edge_rms: 0.0,
            })
            .collect();
        (circles, hexes)
    }

    /// Slots run counter-clockwise on screen, which is counter-clockwise on the board seen
    /// from the front (y up flipped to y down): slot j + 1 is the board offset of slot j turned
    /// by +60°. Checked frontal and at 70° tilt with an in-plane turn, where the plain
    /// Euclidean nearest neighbours are not the lattice neighbours.
    #[test]
    fn slots_are_counter_clockwise_on_the_board() {
        let flip = Matrix2::new(1.0, 0.0, 0.0, -1.0);
        let turn = |t: f64| Matrix2::new(t.cos(), -t.sin(), t.sin(), t.cos());
        let tilt = Matrix2::new(1.0, 0.0, 0.0, 70f64.to_radians().cos());
        for a in [flip * 0.5, turn(0.4) * tilt * turn(1.0) * flip * 0.5] {
            let (circles, hexes) = affine_lattice(a, 3);
            let cells = find_cells(&circles, 20.0 / 6.0, &GridParams::default());
            let centre = hexes.iter().position(|&h| h == Hex::new(0, 0)).unwrap();
            let cell = cells[centre].as_ref().expect("the centre has a cell");
            assert!(cell.is_full() && cell.pairs == 3);
            let offset = |j: usize| hexes[cell.slots[j % 6].unwrap() as usize];
            // The six Euclidean nearest (excluding the centre itself).
            let c0 = circles[centre].ellipse.center;
            let mut near: Vec<usize> = (0..circles.len()).filter(|&k| k != centre).collect();
            near.sort_by(|&p, &q| {
                (circles[p].ellipse.center - c0)
                    .norm()
                    .total_cmp(&(circles[q].ellipse.center - c0).norm())
            });
            let plain_knn_ok = near[..6]
                .iter()
                .all(|&k| hexes[k].distance(Hex::new(0, 0)) == 1);
            assert_eq!(
                plain_knn_ok,
                a == flip * 0.5,
                "the tilted case must defeat plain k-NN"
            );
            for j in 0..6 {
                assert_eq!(offset(j + 1), offset(j).rotate(1), "slot {j}");
            }
            // Every interior circle has a full cell; the rim has none or a partial one.
            for (k, h) in hexes.iter().enumerate() {
                if h.distance(Hex::new(0, 0)) < 3 {
                    assert!(cells[k].as_ref().is_ok_and(Cell::is_full), "{h:?}");
                }
            }
        }
    }
}
