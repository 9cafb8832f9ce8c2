//! Joining components across gaps (docs/design.md §5): an occluder that splits the board leaves
//! several components, each labelled in a lattice frame of its own. Lattice positions beyond
//! the gap are predicted from a reference component by local homographies (image → lattice
//! plane, fitted to the reference circles nearest each candidate circle). A component joins
//! when its circles nearest the reference fall on predicted lattice positions under one
//! lattice transform (a clear majority of them, no position already held), and one homography
//! fits the circles on both sides of the gap with the joined labels: a transform off by a
//! lattice step still lands on lattice positions, but it stretches or squeezes the gap.

use super::assemble::{Component, PlacedCell};
use super::GridParams;
use hexcal_core::board::Hex;
use hexcal_core::board::{lattice_votes, LatticeMap};
use nalgebra::{Matrix3, Point2, SMatrix, SymmetricEigen, Vector2, Vector3};
use std::collections::HashMap;

/// √3/2: the lattice's row height in pitch units.
const ROW: f64 = 0.866_025_403_784_438_6;

/// A lattice position in the lattice plane, in pitch units (docs/design.md (5) over d).
pub(super) fn plane(h: Hex) -> Vector2<f64> {
    Vector2::new(f64::from(h.q) + 0.5 * f64::from(h.r), ROW * f64::from(h.r))
}

/// The lattice position nearest a plane point (cube rounding), and its distance (pitch).
fn nearest_hex(p: Vector2<f64>) -> (Hex, f64) {
    let rf = p.y / ROW;
    let qf = p.x - 0.5 * rf;
    let sf = -qf - rf;
    let (mut q, mut r, s) = (qf.round(), rf.round(), sf.round());
    let (dq, dr, ds) = ((q - qf).abs(), (r - rf).abs(), (s - sf).abs());
    if dq > dr && dq > ds {
        q = -r - s;
    } else if dr > ds {
        r = -q - s;
    }
    let h = Hex::new(q as i32, r as i32);
    (h, (plane(h) - p).norm())
}

/// The similarity taking points to zero mean and mean distance √2 (Hartley's normalisation).
fn normaliser(points: impl Iterator<Item = Vector2<f64>> + Clone) -> Matrix3<f64> {
    let n = points.clone().count().max(1) as f64;
    let c = points.clone().sum::<Vector2<f64>>() / n;
    let spread = points.map(|p| (p - c).norm()).sum::<f64>() / n;
    let s = std::f64::consts::SQRT_2 / spread.max(1e-12);
    Matrix3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0)
}

/// The homography H with `to ~ H·from`, by the normalised direct linear transform.
fn fit_homography(pairs: &[(Vector2<f64>, Vector2<f64>)]) -> Option<Matrix3<f64>> {
    if pairs.len() < 4 {
        return None;
    }
    let ta = normaliser(pairs.iter().map(|p| p.0));
    let tb = normaliser(pairs.iter().map(|p| p.1));
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for (a, b) in pairs {
        let a = ta * Vector3::new(a.x, a.y, 1.0);
        let b = tb * Vector3::new(b.x, b.y, 1.0);
        let rows = [
            [a.x, a.y, 1.0, 0.0, 0.0, 0.0, -b.x * a.x, -b.x * a.y, -b.x],
            [0.0, 0.0, 0.0, a.x, a.y, 1.0, -b.y * a.x, -b.y * a.y, -b.y],
        ];
        for row in rows {
            let v = SMatrix::<f64, 9, 1>::from(row);
            ata += v * v.transpose();
        }
    }
    let eig = SymmetricEigen::new(ata);
    let k = eig.eigenvalues.imin();
    let h = eig.eigenvectors.column(k);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    Some(tb.try_inverse()? * hn * ta)
}

/// H applied to a point; `None` at the line sent to infinity.
pub(super) fn apply(h: &Matrix3<f64>, p: Vector2<f64>) -> Option<Vector2<f64>> {
    let v = h * Vector3::new(p.x, p.y, 1.0);
    (v.z.abs() > 1e-12).then(|| Vector2::new(v.x / v.z, v.y / v.z))
}

/// The plane distances (pitch units) between H(image) and the lattice positions.
pub(super) fn residuals(h: &Matrix3<f64>, pairs: &[(Vector2<f64>, Vector2<f64>)]) -> Vec<f64> {
    pairs
        .iter()
        .map(|(a, b)| apply(h, *a).map_or(f64::INFINITY, |p| (p - b).norm()))
        .collect()
}

/// How far above the median residual of its support a circle's residual may lie before the
/// local fit leaves it out. For n = 16 residual norms of Gaussian centre noise σ (Rayleigh,
/// median 1.18σ) the largest exceeds 4.7σ = 4 medians with probability 16·e^(−11) ≈ 3·10⁻⁴;
/// leaving out a sound circle then costs only a little support.
pub(super) const OUTLIER_MEDIANS: f64 = 4.0;

/// A homography that fits `pairs` within `tolerance` (pitch units) (docs/design.md §5,
/// "Joining across gaps"). Up to `outliers` circles are left out, worst first, each when its
/// residual exceeds [`OUTLIER_MEDIANS`] times the median: a circle cut by the occluder can
/// keep a centre off by a pixel under blur, and as the support's circle nearest the gap it
/// would bend every prediction across it.
pub(super) fn sound_fit(
    mut pairs: Vec<(Vector2<f64>, Vector2<f64>)>,
    tolerance: f64,
    outliers: usize,
) -> Option<Matrix3<f64>> {
    let mut left_out = 0;
    loop {
        let h = fit_homography(&pairs)?;
        let res = residuals(&h, &pairs);
        let (worst, &w) = res.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1))?;
        let mut sorted = res.clone();
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2];
        if left_out == outliers || w <= OUTLIER_MEDIANS * median {
            return (w <= tolerance).then_some(h);
        }
        pairs.swap_remove(worst);
        left_out += 1;
    }
}

/// The component that others join: its circles' image centres and lattice positions.
pub(super) struct Reference {
    /// Image centre and lattice position of every circle.
    pub(super) points: Vec<(Vector2<f64>, Hex)>,
    taken: HashMap<Hex, u32>,
}

impl Reference {
    pub(super) fn new(comp: &Component, centres: &[Point2<f64>]) -> Reference {
        Reference {
            points: comp
                .points
                .iter()
                .map(|&(c, h)| (centres[c as usize].coords, h))
                .collect(),
            taken: comp.points.iter().map(|&(c, h)| (h, c)).collect(),
        }
    }

    /// Indices of the `k` reference circles nearest `p` in the image.
    pub(super) fn nearest(&self, p: Vector2<f64>, k: usize) -> Vec<usize> {
        let mut order: Vec<(f64, usize)> = self
            .points
            .iter()
            .enumerate()
            .map(|(i, (q, _))| ((q - p).norm_squared(), i))
            .collect();
        let k = k.min(order.len());
        if k < order.len() {
            order.select_nth_unstable_by(k, |a, b| a.0.total_cmp(&b.0));
        }
        order.truncate(k);
        order.into_iter().map(|(_, i)| i).collect()
    }

    /// (image, lattice plane) pairs of the reference circles `idx`.
    pub(super) fn pairs(&self, idx: &[usize]) -> Vec<(Vector2<f64>, Vector2<f64>)> {
        idx.iter()
            .map(|&i| (self.points[i].0, plane(self.points[i].1)))
            .collect()
    }
}

/// Predict, from the reference, the lattice position of the circle at `image`; `None` unless
/// the local fit (the reference circles nearest it) is sound and the circle falls within the
/// tolerance of a lattice position.
fn predict(r: &Reference, image: Vector2<f64>, p: &GridParams) -> Option<Hex> {
    let support = r.nearest(image, p.join_support);
    let h = sound_fit(r.pairs(&support), p.join_fit_tolerance, p.join_fit_outliers)?;
    let (hex, off) = nearest_hex(apply(&h, image)?);
    (off <= p.join_tolerance).then_some(hex)
}

/// The circles of `points` nearest the reference (at most `n`): image centre and label.
fn nearest_to(r: &Reference, points: &[(Vector2<f64>, Hex)], n: usize) -> Vec<(Vector2<f64>, Hex)> {
    let mut by_gap: Vec<(f64, Vector2<f64>, Hex)> = points
        .iter()
        .map(|&(x, h)| {
            let gap = r
                .points
                .iter()
                .map(|(q, _)| (q - x).norm_squared())
                .fold(f64::INFINITY, f64::min);
            (gap, x, h)
        })
        .collect();
    by_gap.sort_by(|a, b| a.0.total_cmp(&b.0));
    by_gap.truncate(n);
    by_gap.into_iter().map(|(_, x, h)| (x, h)).collect()
}

/// The lattice transform from the frame of `points` into the reference's on which the
/// predictions of the candidates (the points nearest the reference) agree: a clear majority
/// of them.
fn vote(r: &Reference, points: &[(Vector2<f64>, Hex)], p: &GridParams) -> Option<LatticeMap> {
    let candidates = nearest_to(r, points, p.join_candidates);
    let pairs = candidates
        .iter()
        .filter_map(|&(x, label)| Some(((), label, predict(r, x, p)?)));
    let ((_, map), agree) = lattice_votes(pairs)
        .into_iter()
        .max_by_key(|&((_, m), n)| (n, std::cmp::Reverse((m.rotation, m.offset))))?;
    (agree >= p.min_join_points && agree as f64 >= p.join_agreement * candidates.len() as f64)
        .then_some(map)
}

/// The lattice transform taking `comp` into the reference's frame, if it joins: the
/// reference's predictions of the component's circles and the component's predictions of
/// the reference's circles agree on it (two independent sets of local fits, one on each side
/// of the gap), and it puts no circle on a position the reference holds.
fn transform(
    r: &Reference,
    comp: &Component,
    centres: &[Point2<f64>],
    p: &GridParams,
) -> Option<LatticeMap> {
    let other = Reference::new(comp, centres);
    let map = vote(r, &other.points, p)?;
    if vote(&other, &r.points, p)? != map.inverse() {
        return None;
    }
    (!other
        .points
        .iter()
        .any(|&(_, h)| r.taken.contains_key(&map.apply(h))))
    .then_some(map)
}

/// Move `comp` into the reference component's frame by `map` and add it there.
fn merge(into: &mut Component, comp: Component, map: LatticeMap) {
    into.points
        .extend(comp.points.into_iter().map(|(c, h)| (c, map.apply(h))));
    into.cells
        .extend(comp.cells.into_iter().map(|c| PlacedCell {
            centre: map.apply(c.centre),
            rotation: (c.rotation + map.rotation) % 6,
            ..c
        }));
    into.rejected += comp.rejected;
}

/// Join into `reference` every component of `others` that fits it across a gap (largest
/// first, again until none joins), each one only when `admit` accepts its transform too.
/// Gives the number joined; `others` keeps those that did not join.
pub(crate) fn join_into(
    reference: &mut Component,
    others: &mut Vec<Component>,
    centres: &[Point2<f64>],
    params: &GridParams,
    admit: &dyn Fn(&Component, LatticeMap) -> bool,
) -> usize {
    let mut joined = 0;
    others.sort_by_key(|c| std::cmp::Reverse(c.points.len()));
    loop {
        let r = Reference::new(reference, centres);
        let found = others.iter().enumerate().find_map(|(i, c)| {
            transform(&r, c, centres, params)
                .filter(|&m| admit(c, m))
                .map(|m| (i, m))
        });
        let Some((i, map)) = found else {
            return joined;
        };
        merge(reference, others.remove(i), map);
        joined += 1;
    }
}

#[cfg(test)]
mod tests;
