//! Another frame's pattern in a group's mean image (docs/design.md §6b, eq. 6b.12): takes a
//! refused stack's fits; gives the projectors and groups whose mean image holds the
//! projector's own fringes. Every group shows the same mean image; a projector that shows
//! frame k + o's pattern in frames a…b of a group adds (1/N)·Σ_k (P_{k+o} − P_k), a fringe of
//! that projector at its phase in the group or a neighbouring one (the sum telescopes to the
//! run's ends), which no motion, light change or sensor noise makes. It needs no residual
//! degrees of freedom and no fringe orders, so it names lags in short and dim sequences, where
//! the phase tests (6b.5, 6b.11) cannot tell a lag from light or motion.

use super::{Stack, StackFault, SHAPES};
use crate::phase::check::CheckParams;
use crate::stats::{chi2_tail, median};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

/// Fringe regressors per projector: in the group and its two neighbours (a pattern up to two
/// frames away lies in one of them), the real and imaginary parts of its fundamental C and of
/// C²/|C|, its second harmonic's fringe (an uncorrected gamma's: a lag leaks it into the
/// other projectors' bins, which would otherwise take it).
const FRINGES: usize = 12;

/// Share of the best projector's sum of squares another projector's fringes must explain
/// alone to be named with it: their fringe maps then correlate at ρ ≥ 0.95 over the board
/// (the sum a map explains goes with ρ²), so the mean cannot tell them apart.
const ALIKE: f64 = 0.9;

/// Least share of the sum of squares the shapes explain (a light change between or within
/// groups) that the fringes must explain. The shapes' ambient image is the level less the
/// projectors' mean light, a few percent off the true one; a light change leaves that
/// error in the mean, and leaks the true ambient image into the fringe bins of a group it
/// happened in (6b.8), whose fringes then explain some of it: up to (10 %)² of the light's
/// sum of squares (a 26 % ambient step left 5·10⁻⁴).
const LIGHT_LEAK: f64 = 0.01;

/// Smallest fringe in a group's mean named as a lag, as a share of a one-frame lag's within
/// the group. A lag across a group boundary leaves less (P_{a−1} and P_b are fringes of two
/// counts, which nearly coincide where the counts' phases agree on the board: a quarter to a
/// third of the one-frame size was measured); motion leaves less still: a drift moves the
/// fringes by ∇φ·v per frame, a fringe of (|∇φ·v|·N/2π) of B in the mean, 0.005 for half a
/// pixel over 90 frames at N = 15 (∇φ ≈ 0.4 rad/px) against this bound's 0.007.
const LAG_SIZE: f64 = 0.25;

/// A lag found in one group's mean image.
struct MeanFringe {
    /// The projectors whose fringes explain it, the best first.
    projectors: Vec<usize>,
    group: usize,
    /// The sum of squares the best one's fringes explain beyond the shapes (in units of the
    /// residual variance).
    explained: f64,
}

impl Stack<'_> {
    /// The lags the groups' mean images show ([`Self::mean_fringes`]), each explaining at
    /// least a quarter of the largest: a lag in one group moves the other groups' reference
    /// (their median) by a fraction of itself where it is as small as the noise, which
    /// leaves a trace of its fringe in every group (1 % of its sum of squares measured; with
    /// the mean as reference, 1/(G − 1)² ≤ 1/9).
    pub(super) fn lags_in_means(&self, params: &CheckParams) -> Vec<StackFault> {
        let n = self.model.steps;
        let found: Vec<MeanFringe> = (0..self.model.groups)
            .into_par_iter()
            .filter_map(|g| self.mean_fringes(g, params))
            .collect();
        let largest = found.iter().map(|f| f.explained).fold(0.0, f64::max);
        (found.into_iter())
            .filter(|f| f.explained >= 0.25 * largest)
            .map(|f| StackFault::FringesInMean {
                projectors: f.projectors,
                group: f.group,
                frames: [f.group * n, f.group * n + n - 1],
            })
            .collect()
    }

    /// The projectors whose fringes group g's mean image holds (6b.12): the one whose
    /// fringes alone explain most beyond the shapes, if that is beyond noise at z and as
    /// large as a lag's, with every other one whose fringes alone explain [`ALIKE`] of that.
    /// (A lag's frames leak into every projector's bin of its group, so the others' fringes
    /// there explain some of it too, but only as much as their maps look like its own.) Sums
    /// of squares are in units of the residual's variance where that exceeds the noise's: an
    /// ambient change the shapes fit imperfectly leaves structure that any regressor takes
    /// some of.
    fn mean_fringes(&self, g: usize, params: &CheckParams) -> Option<MeanFringe> {
        let (groups, projectors) = (self.model.groups, self.model.projectors);
        let near: Vec<usize> = (g.saturating_sub(1)..=(g + 1).min(groups - 1)).collect();
        let normal = self.mean_normal(g, &near)?;
        let columns = |ps: &[usize]| -> Vec<usize> {
            let fringes = |p: usize| (0..FRINGES).map(move |i| SHAPES + FRINGES * p + i);
            (0..SHAPES)
                .chain(ps.iter().flat_map(|&p| fringes(p)))
                .collect()
        };
        let all: Vec<usize> = (0..projectors).collect();
        let (_, shapes) = normal.explained(&columns(&[]))?;
        let (_, full) = normal.explained(&columns(&all))?;
        let dof = (normal.pixels - columns(&all).len() as f64).max(1.0);
        let unit = ((normal.dtd - full) / dof).max(1.0);
        let alone: Vec<(usize, f64, DVector<f64>)> = (0..projectors)
            .filter_map(|p| {
                let (coef, e) = normal.explained(&columns(&[p]))?;
                Some((p, (e - shapes) / unit, coef))
            })
            .collect();
        let (best, explained, coef) = alone.iter().max_by(|a, b| a.1.total_cmp(&b.1))?;
        let threshold = chi2_quantile(4 * near.len(), params.z);
        let light = explained * unit < LIGHT_LEAK * shapes;
        if *explained <= threshold || light || !self.lag_sized(*best, &normal, coef) {
            return None;
        }
        let mut named: Vec<(usize, f64)> = (alone.iter())
            .filter(|a| a.1 >= ALIKE * explained)
            .map(|a| (a.0, a.1))
            .collect();
        named.sort_by(|a, b| b.1.total_cmp(&a.1));
        Some(MeanFringe {
            projectors: named.into_iter().map(|(p, _)| p).collect(),
            group: g,
            explained: *explained,
        })
    }

    /// Whether projector p's fitted fundamental fringe (`coef` over all columns) is at
    /// least [`LAG_SIZE`] of a one-frame lag's within a group, |e^{iθ_p} − 1|/N =
    /// 2·sin(θ_p/2)/N of B (B² the median over the groups of Σ|C|², which a lag lowers in
    /// its own; a sinusoid's mean square is half its amplitude's).
    fn lag_sized(&self, p: usize, normal: &MeanNormal, coef: &DVector<f64>) -> bool {
        let own: Vec<usize> = (0..FRINGES).step_by(4).flat_map(|i| [i, i + 1]).collect();
        let at = |i: usize| SHAPES + FRINGES * p + own[i];
        let beta = DVector::from_fn(own.len(), |i, _| coef[at(i)]);
        let gram = DMatrix::from_fn(own.len(), own.len(), |i, j| normal.gram[(at(i), at(j))]);
        let b2 = median(&mut normal.modulation[p].clone()).max(f64::MIN_POSITIVE);
        let size = (2.0 * beta.dot(&(&gram * &beta)) / b2).sqrt();
        let n = self.model.steps as f64;
        size >= LAG_SIZE * 2.0 * (0.5 * self.model.theta(p)).sin() / n
    }

    /// The normal equations of group g's mean difference d_g = m_g − the other groups'
    /// median (a lag in one of them leaves it: a mean would pass 1/(G − 1) of it to every
    /// group) on the shapes and every projector's fringes in the
    /// `near` groups.
    fn mean_normal(&self, g: usize, near: &[usize]) -> Option<MeanNormal> {
        let (groups, n, projectors) = (self.model.groups, self.model.steps, self.model.projectors);
        let k = SHAPES + FRINGES * projectors;
        // The median's variance over G − 1 normal values, at most π/2 over their count (its
        // large-count limit; 0.45 against 0.52 for three).
        let spread = (1.0 + std::f64::consts::FRAC_PI_2 / (groups - 1) as f64) / n as f64;
        let mut others = vec![0.0; groups - 1];
        let mut normal = MeanNormal {
            ata: DMatrix::zeros(k, k),
            atb: DVector::zeros(k),
            gram: DMatrix::zeros(k, k),
            dtd: 0.0,
            pixels: 0.0,
            modulation: vec![vec![0.0; groups]; projectors],
        };
        let mut x = DVector::<f64>::zeros(k);
        for (blk, block) in self.usable() {
            let var = block.var * spread;
            for f in (4 * blk..4 * blk + 4).map(|i| self.fits.pixel(i)) {
                for (o, h) in others.iter_mut().zip((0..groups).filter(|&h| h != g)) {
                    *o = f64::from(f.mean(h));
                }
                let d = f64::from(f.mean(g)) - median(&mut others);
                x.rows_mut(0, SHAPES).copy_from_slice(&block.shapes);
                for p in 0..projectors {
                    for (i, &h) in near.iter().enumerate() {
                        let [re, im] = f.fundamental(h, p).map(f64::from);
                        let c = re.hypot(im).max(f64::MIN_POSITIVE);
                        let at = SHAPES + FRINGES * p + 4 * i;
                        x[at] = re;
                        x[at + 1] = im;
                        x[at + 2] = (re * re - im * im) / c;
                        x[at + 3] = 2.0 * re * im / c;
                    }
                    for (h, m) in normal.modulation[p].iter_mut().enumerate() {
                        let [re, im] = f.fundamental(h, p).map(f64::from);
                        *m += re * re + im * im;
                    }
                }
                normal.dtd += d * d / var;
                normal.pixels += 1.0;
                normal.ata.ger(1.0 / var, &x, &x, 1.0);
                normal.atb.axpy(d / var, &x, 1.0);
                normal.gram.ger(1.0, &x, &x, 1.0);
            }
        }
        (normal.ata.iter().chain(normal.atb.iter()))
            .all(|v| v.is_finite())
            .then_some(normal)
    }
}

/// Normal equations of a group's mean difference on the shapes and fringes.
struct MeanNormal {
    /// Σ x xᵀ/var and Σ x·d/var over the pixels.
    ata: DMatrix<f64>,
    atb: DVector<f64>,
    /// Σ x xᵀ (unweighted: the fitted fringe's mean square).
    gram: DMatrix<f64>,
    /// Σ d²/var, and the pixels summed.
    dtd: f64,
    pixels: f64,
    /// Per projector and group, Σ |C|² (DN²).
    modulation: Vec<Vec<f64>>,
}

impl MeanNormal {
    /// The least-squares coefficients on the regressors `columns` (the others' 0) and the
    /// sum of squares they explain, bᵀA⁺b: A scaled to unit diagonal, then a pseudo-inverse,
    /// so regressors the image cannot tell apart (no unlit region, a missing neighbour) get
    /// no coefficient.
    fn explained(&self, columns: &[usize]) -> Option<(DVector<f64>, f64)> {
        let k = columns.len();
        let d = DVector::from_fn(k, |i, _| {
            let v = self.ata[(columns[i], columns[i])];
            if v > 0.0 {
                1.0 / v.sqrt()
            } else {
                0.0
            }
        });
        let scaled = DMatrix::from_fn(k, k, |i, j| {
            self.ata[(columns[i], columns[j])] * d[i] * d[j]
        });
        let b = DVector::from_fn(k, |i, _| self.atb[columns[i]]);
        let inv = scaled.pseudo_inverse(1e-9).ok()?;
        let c = (inv * b.component_mul(&d)).component_mul(&d);
        let mut coef = DVector::zeros(self.atb.len());
        for (i, &col) in columns.iter().enumerate() {
            coef[col] = c[i];
        }
        Some((coef, c.dot(&b)))
    }
}

/// χ²_k's upper quantile at the normal's one-sided tail at z, by bisection.
fn chi2_quantile(k: usize, z: f64) -> f64 {
    let target = 0.5 * libm::erfc(z / std::f64::consts::SQRT_2);
    let (mut lo, mut hi) = (0.0, 10.0 * (k as f64 + z * z));
    for _ in 0..100 {
        let x = 0.5 * (lo + hi);
        match chi2_tail(k, x) > target {
            true => lo = x,
            false => hi = x,
        }
    }
    0.5 * (lo + hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The quantile against χ²₂'s closed form, −2·ln(tail), and χ²₆'s tail at it.
    #[test]
    fn chi2_quantiles_match_the_closed_forms() {
        let tail = 0.5 * libm::erfc(6.0 / std::f64::consts::SQRT_2);
        let q2 = chi2_quantile(2, 6.0);
        assert!((q2 + 2.0 * tail.ln()).abs() < 1e-9, "{q2}");
        let h = 0.5 * chi2_quantile(6, 6.0);
        let p6 = (-h).exp() * (1.0 + h + h * h / 2.0);
        assert!((p6 / tail - 1.0).abs() < 1e-9, "{h}: {p6:e}");
    }
}
