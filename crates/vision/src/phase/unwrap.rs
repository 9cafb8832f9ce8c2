//! Temporal phase unwrapping by orthographic projection (docs/design.md §6).
//!
//! With M fringe counts n_i across the screen and t ∈ [0, 1) the position on it, the wrapped
//! phases (in cycles) are ψ_i = n_i·t − k_i with integer fringe orders k_i. Projecting ψ onto
//! the hyperplane orthogonal to n removes t: Q^T ψ = −Q^T k. The nearest point of the finite
//! constellation {−Q^T k} gives the orders; its distance is the reliability. The positions
//! (ψ_i + k_i)/n_i are then fused with weights n_i²/σ_φ,i².
//!
//! The constellation is complete: besides the tuples k_i = ⌊n_i·t⌋ it holds every tuple that
//! noise can produce where fringe edges of different counts lie within ¼ of the longest
//! period of each other, which includes the wrapped-around boundary tuples at t = 0 ≡ 1.

use hexcal_core::pattern::MAX_COUNTS;
use std::collections::BTreeSet;
use std::sync::{Arc, Mutex, PoisonError};

/// How many count sets [`Constellation::shared`] keeps built.
pub const SHARED_CONSTELLATIONS: usize = 8;

/// Why a constellation cannot be built.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ConstellationError {
    /// Wrong number of counts.
    #[error("fringe counts {0:?}: need 2 to {MAX_COUNTS} counts")]
    Arity(Vec<u32>),
    /// Zero or repeated counts, or counts with a common factor.
    #[error("fringe counts {0:?}: counts must be distinct, non-zero and coprime as a set")]
    Counts(Vec<u32>),
}

/// One unwrapped position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Unwrapped {
    /// Fused position t ∈ [0, 1) across the screen (u = t·W − ½).
    pub position: f32,
    /// Distance of the projected phase vector from the chosen constellation point (rad).
    pub distance: f32,
}

/// The constellation of fringe-order tuples of a count set, with a lookup grid for the
/// nearest-point search.
#[derive(Clone, Debug)]
pub struct Constellation {
    counts: Vec<u32>,
    counts_f32: [f32; MAX_COUNTS],
    /// Orthonormal basis of the hyperplane orthogonal to n: `dims` rows of M entries.
    basis: Vec<[f32; MAX_COUNTS]>,
    /// Fringe orders k of each point (the points −Q^T k live in the grid).
    orders: Vec<[i32; MAX_COUNTS]>,
    /// Smallest distance between two points (cycles).
    spacing: f64,
    grid: Grid,
}

/// Uniform grid over the projected unit cube; each cell lists the points that can be the
/// nearest to some position inside it.
#[derive(Clone, Debug)]
struct Grid {
    origin: [f32; MAX_COUNTS - 1],
    dims: [usize; MAX_COUNTS - 1],
    /// CSR: candidates of cell c are `candidates[start[c]..start[c + 1]]`.
    start: Vec<u32>,
    candidates: Vec<u32>,
    /// The candidates' coordinates, inline for the search.
    candidate_points: Vec<[f32; MAX_COUNTS - 1]>,
    /// Per cell: its only candidate, or `u16::MAX` when several remain.
    single: Vec<u16>,
    /// The projected constellation points −Q^T k, `dims` coordinates each (padded).
    points: Vec<[f32; MAX_COUNTS - 1]>,
    /// 1 / cell.
    inv_cell: f32,
}

fn gcd(a: u32, b: u32) -> u32 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

impl Constellation {
    /// The complete constellation of a fringe-count set (2…4 distinct, coprime counts).
    pub fn new(counts: &[u32]) -> Result<Constellation, ConstellationError> {
        let m = counts.len();
        if !(2..=MAX_COUNTS).contains(&m) {
            return Err(ConstellationError::Arity(counts.to_vec()));
        }
        let distinct: BTreeSet<u32> = counts.iter().copied().collect();
        if distinct.len() != m
            || counts.contains(&0)
            || counts.iter().fold(0, |g, &c| gcd(g, c)) != 1
        {
            return Err(ConstellationError::Counts(counts.to_vec()));
        }
        let dims = m - 1;
        let n: Vec<f64> = counts.iter().map(|&c| f64::from(c)).collect();
        let basis = orthonormal_complement(&n);

        // Fringe-order tuples: slide a window of width δ = ¼ of the longest period over
        // t ∈ [0, 1); inside each window every count may take either order on each side of
        // its edges, so each window contributes the product of the per-count ranges.
        let n_min = f64::from(*counts.iter().min().unwrap_or(&1));
        let delta = 0.25 / n_min;
        let mut events: Vec<f64> = Vec::new();
        for &c in counts {
            for j in 0..c {
                let e = f64::from(j) / f64::from(c);
                for s in [-0.5, 0.5] {
                    events.push((e + s * delta).rem_euclid(1.0));
                }
            }
        }
        events.sort_by(f64::total_cmp);
        events.dedup_by(|a, b| (*a - *b).abs() < 1e-12);
        let mut tuples: BTreeSet<Vec<i32>> = BTreeSet::new();
        for (i, &e) in events.iter().enumerate() {
            let next = events.get(i + 1).copied().unwrap_or(events[0] + 1.0);
            let t = 0.5 * (e + next);
            let ranges: Vec<(i32, i32)> = n
                .iter()
                .map(|&ni| {
                    let lo = (ni * (t - 0.5 * delta)).floor() as i32;
                    let hi = (ni * (t + 0.5 * delta)).floor() as i32;
                    (lo, hi)
                })
                .collect();
            let mut k: Vec<i32> = ranges.iter().map(|r| r.0).collect();
            // Odometer over the product of the ranges.
            loop {
                tuples.insert(canonical(&k, counts));
                let mut i = 0;
                loop {
                    if i == m {
                        break;
                    }
                    if k[i] < ranges[i].1 {
                        k[i] += 1;
                        break;
                    }
                    k[i] = ranges[i].0;
                    i += 1;
                }
                if i == m {
                    break;
                }
            }
        }

        let mut points = Vec::with_capacity(tuples.len());
        let mut orders = Vec::with_capacity(tuples.len());
        for k in &tuples {
            let mut z = [0f32; MAX_COUNTS - 1];
            for (d, q) in basis.iter().enumerate() {
                z[d] = -(0..m).map(|i| q[i] * f64::from(k[i])).sum::<f64>() as f32;
            }
            let mut kk = [0i32; MAX_COUNTS];
            kk[..m].copy_from_slice(k);
            points.push(z);
            orders.push(kk);
        }
        let dist = |a: &[f32; MAX_COUNTS - 1], b: &[f32; MAX_COUNTS - 1]| {
            (0..dims)
                .map(|d| (f64::from(a[d]) - f64::from(b[d])).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        let mut spacing = f64::INFINITY;
        for a in 0..points.len() {
            for b in a + 1..points.len() {
                spacing = spacing.min(dist(&points[a], &points[b]));
            }
        }
        let basis32: Vec<[f32; MAX_COUNTS]> = basis
            .iter()
            .map(|q| {
                let mut r = [0f32; MAX_COUNTS];
                for i in 0..m {
                    r[i] = q[i] as f32;
                }
                r
            })
            .collect();
        let grid = Grid::build(&basis, points, dims, spacing);
        let mut counts_f32 = [0f32; MAX_COUNTS];
        for (c, &n) in counts_f32.iter_mut().zip(counts) {
            *c = n as f32;
        }
        Ok(Constellation {
            counts: counts.to_vec(),
            counts_f32,
            basis: basis32,
            orders,
            spacing,
            grid,
        })
    }

    /// The constellation of `counts`, built once per process and then shared: building one
    /// takes tens of milliseconds of CPU, and every decoder of a run uses the same few
    /// (the last [`SHARED_CONSTELLATIONS`] count sets are kept).
    pub fn shared(counts: &[u32]) -> Result<Arc<Constellation>, ConstellationError> {
        static BUILT: Mutex<Vec<Arc<Constellation>>> = Mutex::new(Vec::new());
        // A panic elsewhere while the list was held leaves it whole: its entries are
        // immutable once pushed.
        let mut built = BUILT.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(c) = built.iter().find(|c| c.counts == counts) {
            return Ok(Arc::clone(c));
        }
        let c = Arc::new(Constellation::new(counts)?);
        if built.len() == SHARED_CONSTELLATIONS {
            built.remove(0);
        }
        built.push(Arc::clone(&c));
        Ok(c)
    }

    /// The fringe counts.
    pub fn counts(&self) -> &[u32] {
        &self.counts
    }

    /// Number of distinct constellation points.
    pub fn len(&self) -> usize {
        self.grid.points.len()
    }

    /// Whether the constellation is empty (never, for a valid count set).
    pub fn is_empty(&self) -> bool {
        self.grid.points.is_empty()
    }

    /// Smallest distance between two constellation points (rad).
    pub fn spacing(&self) -> f64 {
        self.spacing * std::f64::consts::TAU
    }

    /// Unwrap wrapped phases `psi[i]` ∈ [0, 1) (cycles) of the counts, fusing the positions
    /// with weights `weight[i]`·n_i² (pass weight ∝ 1/σ_φ,i², e.g. B_i²).
    pub fn unwrap(&self, psi: &[f32], weight: &[f32]) -> Unwrapped {
        match self.counts.len() {
            2 => self.unwrap_m::<2, 1>(psi, weight),
            3 => self.unwrap_m::<3, 2>(psi, weight),
            _ => self.unwrap_m::<4, 3>(psi, weight),
        }
    }

    /// [`Self::unwrap`] for M counts (D = M − 1 projected dimensions), unrolled.
    #[inline(always)]
    fn unwrap_m<const M: usize, const D: usize>(&self, psi: &[f32], weight: &[f32]) -> Unwrapped {
        let psi: &[f32; M] = psi.try_into().expect("one phase per count");
        let weight: &[f32; M] = weight.try_into().expect("one weight per count");
        let mut z = [0f32; MAX_COUNTS - 1];
        for (zd, q) in z.iter_mut().zip(&self.basis).take(D) {
            *zd = (0..M).map(|i| q[i] * psi[i]).sum();
        }
        let (best, d2) = self.grid.nearest::<D>(&z);
        let k = &self.orders[best];
        // Fused position: t = Σ w_i n_i (ψ_i + k_i) / Σ w_i n_i² (least squares along n).
        let (mut num, mut den) = (0f32, 0f32);
        for i in 0..M {
            let ni = self.counts_f32[i];
            let w = weight[i].max(f32::MIN_POSITIVE) * ni;
            num += w * (psi[i] + k[i] as f32);
            den += w * ni;
        }
        let t = num / den;
        // t ∈ (−1, 2): wrap into [0, 1) without a libm floor.
        let whole = t as i32 as f32;
        let whole = if whole > t { whole - 1.0 } else { whole };
        Unwrapped {
            position: t - whole,
            distance: d2.sqrt() * std::f32::consts::TAU,
        }
    }
}

/// Representative of k modulo n (k and k + n give the same projected point): k_0 in [0, n_0).
fn canonical(k: &[i32], counts: &[u32]) -> Vec<i32> {
    let n0 = counts[0] as i32;
    let shift = k[0].div_euclid(n0);
    k.iter()
        .zip(counts)
        .map(|(&ki, &ni)| ki - shift * ni as i32)
        .collect()
}

/// Orthonormal basis (M − 1 vectors) of the hyperplane orthogonal to n, by Gram–Schmidt on
/// the unit vectors.
fn orthonormal_complement(n: &[f64]) -> Vec<Vec<f64>> {
    let m = n.len();
    let norm = n.iter().map(|x| x * x).sum::<f64>().sqrt();
    let mut vecs: Vec<Vec<f64>> = vec![n.iter().map(|x| x / norm).collect()];
    for e in 0..m {
        let mut v: Vec<f64> = (0..m).map(|i| if i == e { 1.0 } else { 0.0 }).collect();
        for q in &vecs {
            let dot: f64 = v.iter().zip(q).map(|(a, b)| a * b).sum();
            for (vi, qi) in v.iter_mut().zip(q) {
                *vi -= dot * qi;
            }
        }
        let len = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if len > 1e-6 && vecs.len() < m {
            vecs.push(v.iter().map(|x| x / len).collect());
        }
    }
    vecs.remove(0);
    vecs
}

impl Grid {
    fn build(
        basis: &[Vec<f64>],
        points: Vec<[f32; MAX_COUNTS - 1]>,
        dims: usize,
        spacing: f64,
    ) -> Grid {
        // The projected unit cube: per axis, the sums of the negative and positive entries.
        let mut origin = [0f32; MAX_COUNTS - 1];
        let mut extent = [0f64; MAX_COUNTS - 1];
        for (d, q) in basis.iter().enumerate() {
            let lo: f64 = q.iter().map(|x| x.min(0.0)).sum();
            let hi: f64 = q.iter().map(|x| x.max(0.0)).sum();
            origin[d] = lo as f32;
            extent[d] = hi - lo;
        }
        // Cells of 1/16 spacing (mostly a single candidate), capped at 2^16 cells in all.
        let max_cells_per_axis = (2f64.powi(16)).powf(1.0 / dims as f64).floor();
        let widest = extent[..dims].iter().cloned().fold(0.0, f64::max);
        let cell = (spacing / 16.0).max(widest / max_cells_per_axis);
        let mut gdims = [1usize; MAX_COUNTS - 1];
        for d in 0..dims {
            gdims[d] = ((extent[d] / cell).ceil() as usize).max(1);
        }
        let total: usize = gdims[..dims].iter().product();
        let mut start = Vec::with_capacity(total + 1);
        let mut candidates = Vec::new();
        start.push(0u32);
        let mut lo = [0f64; MAX_COUNTS - 1];
        let mut hi = [0f64; MAX_COUNTS - 1];
        for c in 0..total {
            let mut rest = c;
            for d in 0..dims {
                let i = rest % gdims[d];
                rest /= gdims[d];
                lo[d] = f64::from(origin[d]) + i as f64 * cell;
                hi[d] = lo[d] + cell;
            }
            // Squared min / max distance from each point to the cell box.
            let mut best_max = f64::INFINITY;
            let mut mins = Vec::with_capacity(points.len());
            for p in &points {
                let (mut dmin, mut dmax) = (0.0, 0.0);
                for d in 0..dims {
                    let x = f64::from(p[d]);
                    let below = (lo[d] - x).max(0.0) + (x - hi[d]).max(0.0);
                    dmin += below * below;
                    let far = (x - lo[d]).abs().max((x - hi[d]).abs());
                    dmax += far * far;
                }
                best_max = f64::min(best_max, dmax);
                mins.push(dmin);
            }
            for (i, &dmin) in mins.iter().enumerate() {
                if dmin <= best_max {
                    candidates.push(i as u32);
                }
            }
            start.push(candidates.len() as u32);
        }
        let candidate_points = candidates.iter().map(|&c| points[c as usize]).collect();
        let single = start
            .windows(2)
            .map(|r| {
                if r[1] - r[0] == 1 && points.len() < usize::from(u16::MAX) {
                    candidates[r[0] as usize] as u16
                } else {
                    u16::MAX
                }
            })
            .collect();
        Grid {
            origin,
            single,
            points,
            inv_cell: (1.0 / cell) as f32,
            dims: gdims,
            start,
            candidates,
            candidate_points,
        }
    }

    #[inline(always)]
    fn nearest<const D: usize>(&self, z: &[f32; MAX_COUNTS - 1]) -> (usize, f32) {
        let dist2 = |p: &[f32; MAX_COUNTS - 1]| -> f32 {
            (0..D).map(|d| (p[d] - z[d]) * (p[d] - z[d])).sum()
        };
        let mut idx = 0usize;
        let mut stride = 1usize;
        for ((&zd, &o), &n) in z.iter().zip(&self.origin).zip(&self.dims).take(D) {
            // Truncation of a non-negative value is its floor.
            let i = ((zd - o) * self.inv_cell).max(0.0) as usize;
            idx += i.min(n - 1) * stride;
            stride *= n;
        }
        let only = self.single[idx];
        if only != u16::MAX {
            let c = usize::from(only);
            return (c, dist2(&self.points[c]));
        }
        let (lo, hi) = (self.start[idx] as usize, self.start[idx + 1] as usize);
        let mut best = (lo, f32::INFINITY);
        for (j, p) in self.candidate_points[lo..hi].iter().enumerate() {
            let d2 = dist2(p);
            if d2 < best.1 {
                best = (lo + j, d2);
            }
        }
        (self.candidates[best.0] as usize, best.1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};
    use rayon::prelude::*;

    fn sq_dist(a: &[f32; MAX_COUNTS - 1], b: &[f32; MAX_COUNTS - 1], dims: usize) -> f32 {
        (0..dims).map(|d| (a[d] - b[d]) * (a[d] - b[d])).sum()
    }

    /// Brute-force nearest point (for checking the grid).
    fn nearest_brute(c: &Constellation, z: &[f32; MAX_COUNTS - 1]) -> usize {
        let dims = c.counts.len() - 1;
        let pts = &c.grid.points;
        (0..pts.len())
            .min_by(|&a, &b| sq_dist(&pts[a], z, dims).total_cmp(&sq_dist(&pts[b], z, dims)))
            .unwrap_or(0)
    }

    #[test]
    fn spacing_of_default_counts_matches_design() {
        // docs/design.md §6: {20, 21, 25} has constellation spacing 1.05 rad; {15, 19} 0.26 rad.
        let c = Constellation::new(&[20, 21, 25]).unwrap();
        assert!((c.spacing() - 1.05).abs() < 0.01, "spacing {}", c.spacing());
        let c = Constellation::new(&[15, 19]).unwrap();
        assert!((c.spacing() - 0.26).abs() < 0.01, "spacing {}", c.spacing());
    }

    #[test]
    fn shared_constellations_are_built_once_per_count_set() {
        let a = Constellation::shared(&[20, 21, 25]).unwrap();
        let b = Constellation::shared(&[15, 19]).unwrap();
        assert!(Arc::ptr_eq(
            &a,
            &Constellation::shared(&[20, 21, 25]).unwrap()
        ));
        assert_eq!(a.counts(), &[20, 21, 25]);
        assert_eq!(b.counts(), &[15, 19]);
        assert_eq!(a.len(), Constellation::new(&[20, 21, 25]).unwrap().len());
        assert!(matches!(
            Constellation::shared(&[20, 25]),
            Err(ConstellationError::Counts(_))
        ));
    }

    #[test]
    fn refuses_bad_count_sets() {
        assert!(matches!(
            Constellation::new(&[20]),
            Err(ConstellationError::Arity(_))
        ));
        assert!(matches!(
            Constellation::new(&[20, 25]),
            Err(ConstellationError::Counts(_))
        ));
        assert!(matches!(
            Constellation::new(&[20, 20, 21]),
            Err(ConstellationError::Counts(_))
        ));
    }

    #[test]
    fn grid_lookup_equals_brute_force() {
        let mut rng = rand::rngs::SmallRng::seed_from_u64(7);
        for counts in [&[20u32, 21, 25][..], &[15, 19], &[16, 19, 21, 23]] {
            let c = Constellation::new(counts).unwrap();
            let m = counts.len();
            for _ in 0..20_000 {
                let psi: Vec<f32> = (0..m).map(|_| rng.random::<f32>()).collect();
                let mut z = [0f32; MAX_COUNTS - 1];
                for (d, q) in c.basis.iter().enumerate() {
                    z[d] = (0..m).map(|i| q[i] * psi[i]).sum();
                }
                let (g, gd) = match m {
                    2 => c.grid.nearest::<1>(&z),
                    3 => c.grid.nearest::<2>(&z),
                    _ => c.grid.nearest::<3>(&z),
                };
                let b = nearest_brute(&c, &z);
                let bd = sq_dist(&c.grid.points[b], &z, m - 1);
                assert!(
                    g == b || (gd - bd).abs() < 1e-7,
                    "{counts:?}: grid {g} brute {b}"
                );
            }
        }
    }

    #[test]
    fn boundary_and_near_edge_tuples_are_present() {
        let c = Constellation::new(&[20, 21, 25]).unwrap();
        let has = |k: [i32; 3]| {
            let ck = canonical(&k, &[20, 21, 25]);
            c.orders.iter().any(|o| o[..3] == ck[..])
        };
        // Wrapped-around boundary at t = 0: any subset of the phases read just below 1.
        for k in [[-1, 0, 0], [0, -1, 0], [0, 0, -1], [-1, -1, 0], [0, -1, -1]] {
            assert!(has(k), "boundary tuple {k:?} missing");
        }
        // Edges 1/20 = 0.05 and 1/21 = 0.0476 are 0.0024 apart (< ¼·1/20): the crossed tuple
        // (k_20 = 1, k_21 = 0) is reached for t just below 1/21 when ψ_20 wraps early.
        assert!(has([1, 0, 1]));
        // A far-apart crossing is absent: k_20 = 10 (t ≥ 0.5) with k_21 = 0 (t < 1/21).
        assert!(!has([10, 0, 12]));
    }

    /// Gross unwrapping errors over 10⁷ phase vectors at σ_φ = 0.073 rad, the largest phase
    /// noise a valid pixel can have at the default N = 15 (B ≥ 5σ_I: σ_φ = √(2/15)/5). The
    /// design measures < 10⁻⁸ per pixel at 0.09 rad, so the expected count is < 0.1; any
    /// error here is a constellation or lookup defect. Positions are drawn uniformly, so the
    /// edge regions and the t = 0 ≡ 1 boundary get their share.
    #[test]
    fn no_gross_errors_at_validity_threshold_noise() {
        let counts = [20u32, 21, 25];
        let c = Constellation::new(&counts).unwrap();
        let sigma_phi = (2.0f64 / 15.0).sqrt() / 5.0;
        let sigma_t = sigma_phi / (std::f64::consts::TAU * 1466f64.sqrt());
        let noise = Normal::new(0.0, sigma_phi / std::f64::consts::TAU).unwrap();
        let errors: usize = (0..100u64)
            .into_par_iter()
            .map(|chunk| {
                let mut rng = rand::rngs::SmallRng::seed_from_u64(1000 + chunk);
                let mut bad = 0;
                for _ in 0..100_000 {
                    let t: f64 = rng.random();
                    let psi: [f32; 3] = std::array::from_fn(|i| {
                        (f64::from(counts[i]) * t + noise.sample(&mut rng)).rem_euclid(1.0) as f32
                    });
                    let r = c.unwrap(&psi, &[1.0; 3]);
                    let mut e = f64::from(r.position) - t;
                    e -= e.round();
                    if e.abs() > 6.0 * sigma_t {
                        bad += 1;
                    }
                }
                bad
            })
            .sum();
        assert_eq!(errors, 0);
    }

    /// At σ_φ = 0.15 rad the design measures ≈ 10⁻³ gross errors per pixel; the complete
    /// constellation must reproduce that order (well under 10⁻²) and the distance must catch
    /// part of them.
    #[test]
    fn gross_error_rate_at_high_noise_matches_design() {
        let counts = [20u32, 21, 25];
        let c = Constellation::new(&counts).unwrap();
        let noise = Normal::new(0.0, 0.15 / std::f64::consts::TAU).unwrap();
        // A wrong order moves t by ≥ min n_i/Σn² ≈ 0.014, far beyond 6σ_t = 0.0037.
        let sigma_t = 0.15 / (std::f64::consts::TAU * 1466f64.sqrt());
        let mut rng = rand::rngs::SmallRng::seed_from_u64(3);
        let trials = 200_000;
        let mut bad = 0;
        for _ in 0..trials {
            let t: f64 = rng.random();
            let psi: [f32; 3] = std::array::from_fn(|i| {
                (f64::from(counts[i]) * t + noise.sample(&mut rng)).rem_euclid(1.0) as f32
            });
            let r = c.unwrap(&psi, &[1.0; 3]);
            let mut e = f64::from(r.position) - t;
            e -= e.round();
            if e.abs() > 6.0 * sigma_t {
                bad += 1;
            }
        }
        let rate = bad as f64 / trials as f64;
        eprintln!("gross error rate at σ_φ = 0.15 rad: {rate}");
        // 10⁻³ ± Poisson: 200 expected; accept 3·10⁻⁴…3·10⁻³.
        assert!((3e-4..3e-3).contains(&rate), "gross error rate {rate}");
    }
}
