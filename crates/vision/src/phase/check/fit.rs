//! Per sampled pixel and fringe group, the phase-shift model fitted by the DFT (docs/design.md
//! §6b, eq. 6b.1): the group mean, each projector's fundamental, the residual per frame; and the
//! noise model measured from the residuals.

use super::super::maps::NoiseModel;
use crate::stats::median;
use hexcal_core::pattern::{pattern_harmonic, Sequence, CHECKED_HARMONICS};
use rayon::prelude::*;
use std::f64::consts::TAU;
use std::ops::Range;

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

/// What the fit keeps of every sampled pixel, as rows of one value per pixel (so each
/// group is fitted across pixels at once): per group the mean level (DN), Σ of the squared
/// residuals over its frames, and per projector the fundamental's complex amplitude
/// C = (2/N)·Σ_s I_s·e^{−i2πf_p s/N} (the contribution at step s is Re(C·e^{i2πf_p s/N})).
pub(super) struct Fits {
    /// Pixels sampled.
    pixels: usize,
    /// Groups G.
    groups: usize,
    /// Projectors P.
    projectors: usize,
    /// Row g·(2 + 2P) + r of `pixels` values: r = 0 the means, 1 the rss, 2 + 2p and 3 + 2p
    /// projector p's fundamental (re, im).
    data: Vec<f32>,
}

impl Fits {
    /// Pixels sampled.
    pub(super) fn len(&self) -> usize {
        self.pixels
    }

    /// Pixel i's fit.
    pub(super) fn pixel(&self, i: usize) -> PixelFit<'_> {
        PixelFit { fits: self, i }
    }

    /// Row r of group g, pixel i.
    fn at(&self, g: usize, r: usize, i: usize) -> f32 {
        self.data[(g * (2 + 2 * self.projectors) + r) * self.pixels + i]
    }
}

/// One pixel's fit.
#[derive(Clone, Copy)]
pub(super) struct PixelFit<'a> {
    fits: &'a Fits,
    i: usize,
}

impl<'a> PixelFit<'a> {
    /// Group g's mean level (DN).
    pub(super) fn mean(&self, g: usize) -> f32 {
        self.fits.at(g, 0, self.i)
    }

    /// Group g's fundamental of projector p (re, im).
    pub(super) fn fundamental(&self, g: usize, p: usize) -> [f32; 2] {
        [
            self.fits.at(g, 2 + 2 * p, self.i),
            self.fits.at(g, 3 + 2 * p, self.i),
        ]
    }

    /// The per-frame noise variance statistic of the groups not in `left_out` (a bit each):
    /// one value per group from its residuals when the model leaves `dof` ≥ 2
    /// (σ_I²·χ²_dof/dof), else one from the group means (N `steps`): N·median_g (m_g −
    /// median m)², robust to a group that differs from the others (a lag, a light step),
    /// whose median over pixels is [`means_median_ratio`]·σ_I² (G the groups kept).
    pub(super) fn variances(
        self,
        dof: usize,
        steps: usize,
        left_out: u32,
    ) -> impl Iterator<Item = f64> + 'a {
        let groups = (0..self.fits.groups).filter(move |g| left_out & (1 << g) == 0);
        let from_means = (dof < 2).then(|| {
            let mut m: Vec<f64> = groups.clone().map(|g| f64::from(self.mean(g))).collect();
            steps as f64 * median_square_deviation(&mut m)
        });
        let from_rss = (dof >= 2)
            .then(|| groups.map(move |g| f64::from(self.fits.at(g, 1, self.i)) / dof as f64));
        from_rss.into_iter().flatten().chain(from_means)
    }

    /// The mean level over the groups (DN).
    pub(super) fn level(&self) -> f64 {
        let g = self.fits.groups;
        (0..g).map(|g| f64::from(self.mean(g))).sum::<f64>() / g as f64
    }

    /// Projector p's modulation: the RMS over groups of |C| (DN).
    pub(super) fn modulation(&self, p: usize) -> f64 {
        let g = self.fits.groups;
        let s: f64 = (0..g)
            .map(|g| {
                let [re, im] = self.fundamental(g, p);
                f64::from(re * re + im * im)
            })
            .sum();
        (s / g as f64).sqrt()
    }
}

/// Pixels fitted at once: their sums stay in the first-level cache.
const TILE: usize = 256;

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

    /// Fit every pixel of frame-major `samples` (pixel i of frame k at [k·m + i], m pixels),
    /// replacing them by their residuals; each group on its own core, its pixels a tile at
    /// a time.
    pub(super) fn fit(&self, samples: &mut [f32], m: usize) -> Fits {
        let rows = 2 + 2 * self.projectors;
        let mut data = vec![0f32; self.groups * rows * m];
        if m > 0 {
            samples
                .par_chunks_mut(self.steps * m)
                .zip(data.par_chunks_mut(rows * m))
                .for_each(|(frames, out)| {
                    for first in (0..m).step_by(TILE) {
                        self.fit_tile(frames, out, m, first..m.min(first + TILE));
                    }
                });
        }
        Fits {
            pixels: m,
            groups: self.groups,
            projectors: self.projectors,
            data,
        }
    }

    /// One group's fit (eq. 6b.1) of the pixels in `tile`: its `frames` (N rows of m) become
    /// residuals, its rows of `out` get the means, rss and fundamentals.
    fn fit_tile(&self, frames: &mut [f32], out: &mut [f32], m: usize, tile: Range<usize>) {
        let (n, t) = (self.steps, tile.len());
        let row = |s: usize| s * m + tile.start..s * m + tile.end;
        // The mean, then (re, im) of each bin, over the tile's pixels.
        let mut sums = vec![0f32; (1 + 2 * self.bins.len()) * t];
        let (mean, coef) = sums.split_at_mut(t);
        for s in 0..n {
            let values = &frames[row(s)];
            add(mean, values, 1.0);
            for (j, c) in coef.chunks_exact_mut(2 * t).enumerate() {
                let [cos, sin] = self.twiddles[j * n + s];
                let (re, im) = c.split_at_mut(t);
                add(re, values, cos);
                add(im, values, -sin);
            }
        }
        mean.iter_mut().for_each(|v| *v /= n as f32);
        for (&b, c) in self.bins.iter().zip(coef.chunks_exact_mut(2 * t)) {
            let scale = if 2 * b == n { 1.0 } else { 2.0 } / n as f32;
            c.iter_mut().for_each(|v| *v *= scale);
        }
        let mut rss = vec![0f32; t];
        let mut model = vec![0f32; t];
        for s in 0..n {
            model.fill(0.0);
            for (j, c) in coef.chunks_exact(2 * t).enumerate() {
                let [cos, sin] = self.twiddles[j * n + s];
                let (re, im) = c.split_at(t);
                for ((v, &re), &im) in model.iter_mut().zip(re).zip(im) {
                    *v += re * cos - im * sin;
                }
            }
            let values = &mut frames[row(s)];
            for (((v, &mu), &md), r) in values.iter_mut().zip(&*mean).zip(&model).zip(&mut rss) {
                *v -= mu + md;
                *r += *v * *v;
            }
        }
        let mut put = |r: usize, from: &[f32]| {
            out[r * m + tile.start..r * m + tile.end].copy_from_slice(from)
        };
        put(0, mean);
        put(1, &rss);
        for (p, c) in coef.chunks_exact(2 * t).take(self.projectors).enumerate() {
            put(2 + 2 * p, &c[..t]);
            put(3 + 2 * p, &c[t..]);
        }
    }

    /// Projector p's temporal frequency θ_p = 2π·f_p/N (rad per step).
    pub(super) fn theta(&self, p: usize) -> f64 {
        TAU * self.bins[p] as f64 / self.steps as f64
    }
}

/// acc += w·values, element by element.
fn add(acc: &mut [f32], values: &[f32], w: f32) {
    for (a, &v) in acc.iter_mut().zip(values) {
        *a += v * w;
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
