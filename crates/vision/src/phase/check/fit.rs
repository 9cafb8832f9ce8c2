//! Per sampled pixel and fringe group, the phase-shift model fitted by the DFT (docs/design.md
//! §6b, eq. 6b.1): the group mean, each projector's fundamental, the residual per frame; and the
//! noise model measured from the residuals.

use super::super::maps::NoiseModel;
use hexcal_core::pattern::{pattern_harmonic, Sequence, CHECKED_HARMONICS};
use std::f64::consts::TAU;

/// The model of every group: which DFT bins it holds and their twiddles.
pub(super) struct GroupFits {
    /// Phase steps N.
    pub(super) steps: usize,
    /// Fringe groups G.
    pub(super) groups: usize,
    /// Projectors P.
    pub(super) projectors: usize,
    /// Bins 1…⌊N/2⌋ of the model: each projector's fundamental first (index p), then the
    /// harmonics of uncorrected gammas.
    bins: Vec<usize>,
    /// Real parameters q of one group's model (the mean, two per bin, one at N/2).
    pub(super) params: usize,
    /// (cos, sin) of 2π·b·s/N at [bin index · N + s].
    twiddles: Vec<[f32; 2]>,
    /// Per projector a_0/a_1 of its effective gamma: its mean light over its modulation.
    pub(super) mean_ratio: Vec<f64>,
}

/// What the fit keeps of one pixel, in one allocation: per group the mean level (DN), per
/// group Σ of the squared residuals over its frames, and per group and projector the
/// fundamental's complex amplitude C = (2/N)·Σ_s I_s·e^{−i2πf_p s/N} (the contribution at
/// step s is Re(C·e^{i2πf_p s/N})).
#[derive(Clone, Debug, Default)]
pub(super) struct PixelFit {
    /// Groups G.
    groups: usize,
    /// [means (G) | rss (G) | fundamentals (2·G·P, re and im at [g·P + p])].
    data: Vec<f32>,
}

impl PixelFit {
    /// Per group, the mean level (DN).
    pub(super) fn means(&self) -> &[f32] {
        &self.data[..self.groups]
    }

    /// Per group, Σ of the squared residuals over its frames.
    fn rss(&self) -> &[f32] {
        &self.data[self.groups..2 * self.groups]
    }

    /// Group g's fundamental of projector p of `projectors` (re, im).
    pub(super) fn fundamental(&self, g: usize, p: usize, projectors: usize) -> [f32; 2] {
        let at = 2 * self.groups + 2 * (g * projectors + p);
        [self.data[at], self.data[at + 1]]
    }

    /// The per-frame noise variance statistic: one value per group from its residuals when
    /// the model leaves `dof` ≥ 2 (σ_I²·χ²_dof/dof), else one from the group means (N
    /// `steps`): N·median_g (m_g − median m)², robust to a group that differs from the others
    /// (a lag, a light step), whose median over pixels is [`means_median_ratio`]·σ_I².
    pub(super) fn variances(&self, dof: usize, steps: usize) -> Vec<f64> {
        if dof >= 2 {
            return self
                .rss()
                .iter()
                .map(|&r| f64::from(r) / dof as f64)
                .collect();
        }
        let mut m: Vec<f64> = self.means().iter().map(|&m| f64::from(m)).collect();
        vec![steps as f64 * median_square_deviation(&mut m)]
    }

    /// The mean level over the groups (DN).
    pub(super) fn level(&self) -> f64 {
        self.means().iter().map(|&m| f64::from(m)).sum::<f64>() / self.groups as f64
    }

    /// Projector p's modulation: the RMS over groups of |C| (DN).
    pub(super) fn modulation(&self, p: usize, projectors: usize) -> f64 {
        let s: f64 = (0..self.groups)
            .map(|g| {
                let [re, im] = self.fundamental(g, p, projectors);
                f64::from(re * re + im * im)
            })
            .sum();
        (s / self.groups as f64).sqrt()
    }
}

impl GroupFits {
    /// The model of `seq`'s groups; `None` for a single group (nothing to test against).
    pub(super) fn new(seq: &Sequence) -> Option<GroupFits> {
        let n = seq.steps() as usize;
        let fold = |b: usize| (b % n).min(n - b % n);
        let mut bins: Vec<usize> = seq
            .projectors()
            .iter()
            .map(|c| fold(c.frequency as usize))
            .collect();
        for code in seq
            .projectors()
            .iter()
            .filter(|c| c.response.has_harmonics())
        {
            for h in 2..=CHECKED_HARMONICS as usize {
                let b = fold(h * code.frequency as usize);
                if b != 0 && !bins.contains(&b) {
                    bins.push(b);
                }
            }
        }
        let params = 1 + bins
            .iter()
            .map(|&b| if 2 * b == n { 1 } else { 2 })
            .sum::<usize>();
        if n < params || seq.groups() < 2 {
            return None;
        }
        let twiddles = bins
            .iter()
            .flat_map(|&b| {
                (0..n).map(move |s| {
                    let a = TAU * ((b * s) % n) as f64 / n as f64;
                    [a.cos() as f32, a.sin() as f32]
                })
            })
            .collect();
        let mean_ratio = seq
            .projectors()
            .iter()
            .map(|c| {
                let g = c.response.effective_gamma();
                pattern_harmonic(g, 0) / pattern_harmonic(g, 1)
            })
            .collect();
        Some(GroupFits {
            steps: n,
            groups: seq.groups(),
            projectors: seq.projectors().len(),
            bins,
            params,
            twiddles,
            mean_ratio,
        })
    }

    /// Residual degrees of freedom per group, N − q (0 for the shortest sequences, whose
    /// every step the model uses: then no frame can be tested on its own).
    pub(super) fn dof(&self) -> usize {
        self.steps - self.params
    }

    /// A buffer of the bins' coefficients for [`Self::fit`].
    pub(super) fn coefficients(&self) -> Vec<[f32; 2]> {
        vec![[0f32; 2]; self.bins.len()]
    }

    /// Fit one pixel's series (every frame, in order), replacing it by its residuals;
    /// `coef` is a buffer of [`Self::coefficients`].
    pub(super) fn fit(&self, series: &mut [f32], coef: &mut [[f32; 2]]) -> PixelFit {
        let (n, g) = (self.steps, self.groups);
        let mut data = vec![0f32; 2 * g + 2 * g * self.projectors];
        let (sums, fundamentals) = data.split_at_mut(2 * g);
        let (means, rss) = sums.split_at_mut(g);
        for (((seg, mean), rss), fund) in series
            .chunks_exact_mut(n)
            .zip(means)
            .zip(rss)
            .zip(fundamentals.chunks_exact_mut(2 * self.projectors))
        {
            *mean = seg.iter().sum::<f32>() / n as f32;
            for (j, (&b, c)) in self.bins.iter().zip(coef.iter_mut()).enumerate() {
                let tw = &self.twiddles[j * n..(j + 1) * n];
                let (re, im) = seg
                    .iter()
                    .zip(tw)
                    .fold((0f32, 0f32), |(re, im), (&v, &[c, s])| {
                        (re + v * c, im - v * s)
                    });
                let scale = if 2 * b == n { 1.0 } else { 2.0 } / n as f32;
                *c = [re * scale, im * scale];
            }
            for (s, v) in seg.iter_mut().enumerate() {
                let model: f32 = coef
                    .iter()
                    .enumerate()
                    .map(|(j, &[re, im])| {
                        let [c, sn] = self.twiddles[j * n + s];
                        re * c - im * sn
                    })
                    .sum();
                *v -= *mean + model;
                *rss += *v * *v;
            }
            for (f, c) in fund.chunks_exact_mut(2).zip(coef.iter()) {
                f.copy_from_slice(c);
            }
        }
        PixelFit { groups: g, data }
    }

    /// Projector p's temporal frequency θ_p = 2π·f_p/N (rad per step).
    pub(super) fn theta(&self, p: usize) -> f64 {
        TAU * self.bins[p] as f64 / self.steps as f64
    }
}

/// median_g (x_g − median x)² of `x` (reordered).
fn median_square_deviation(x: &mut [f64]) -> f64 {
    let centre = median(x);
    for v in x.iter_mut() {
        *v = (*v - centre).powi(2);
    }
    median(x)
}

/// The median of χ²_ν/ν (Wilson–Hilferty): a residual variance statistic's median over σ_I².
pub(super) fn chi2_median_ratio(dof: f64) -> f64 {
    (1.0 - 2.0 / (9.0 * dof)).powi(3)
}

/// The median over pixels of N·median_g (m_g − median m)² over σ_I² for G groups
/// (the group means' own variance is σ_I²/N): measured once on 20 000 seeded draws of G
/// standard normal values (its standard error ≈ 1 %).
pub(super) fn means_median_ratio(groups: usize) -> f64 {
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    let mut rng = rand::rngs::StdRng::seed_from_u64(0x5eed);
    let mut stats: Vec<f64> = (0..20_000)
        .map(|_| {
            let mut z: Vec<f64> = (0..groups)
                .map(|_| StandardNormal.sample(&mut rng))
                .collect();
            median_square_deviation(&mut z)
        })
        .collect();
    median(&mut stats)
}

/// The median of `x` (reordered; 0 when empty).
pub(super) fn median(x: &mut [f64]) -> f64 {
    if x.is_empty() {
        return 0.0;
    }
    let mid = x.len() / 2;
    *x.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// The noise model σ_I² = a + b·A from per-pixel (level, variance statistic) pairs whose
/// median is `median_ratio`·σ_I²: pixels sorted by level into 16 bins of equal count, the
/// median statistic of each bin ÷ that ratio, a least-squares line through the bins (eq.
/// 6b.2). A few disturbed pixels or frames do not move a median.
pub(super) fn robust_noise(mut pairs: Vec<(f64, f64)>, median_ratio: f64) -> NoiseModel {
    const BINS: usize = 16;
    pairs.retain(|(a, v)| a.is_finite() && v.is_finite());
    if pairs.len() < BINS {
        let v = pairs.iter().map(|p| p.1).sum::<f64>() / pairs.len().max(1) as f64;
        return NoiseModel {
            offset: v,
            slope: 0.0,
            floor: 0.01 * v,
        };
    }
    pairs.sort_by(|x, y| x.0.total_cmp(&y.0));
    let per = pairs.len() / BINS;
    let points: Vec<(f64, f64)> = pairs
        .chunks(per)
        .filter(|c| c.len() == per)
        .map(|c| {
            let level = c.iter().map(|p| p.0).sum::<f64>() / per as f64;
            let mut v: Vec<f64> = c.iter().map(|p| p.1).collect();
            let mid = v.len() / 2;
            let (_, m, _) = v.select_nth_unstable_by(mid, f64::total_cmp);
            (level, *m / median_ratio)
        })
        .collect();
    let n = points.len() as f64;
    let (sa, sv) = points
        .iter()
        .fold((0.0, 0.0), |s, p| (s.0 + p.0, s.1 + p.1));
    let (ma, mv) = (sa / n, sv / n);
    let (sxx, sxy) = points.iter().fold((0.0, 0.0), |s, p| {
        (s.0 + (p.0 - ma) * (p.0 - ma), s.1 + (p.0 - ma) * (p.1 - mv))
    });
    let slope = if sxx > 1e-12 { sxy / sxx } else { 0.0 };
    NoiseModel {
        offset: mv - slope * ma,
        slope,
        floor: 0.01 * mv,
    }
}
