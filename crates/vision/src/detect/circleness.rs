//! Multi-scale circleness (paper Eqs. 1–4, docs/design.md §4) and its 3×3 peaks.
//!
//! Scale-normalised Hessians σ²·H of the Gaussian-smoothed image on a pyramid: each scale
//! is evaluated on the coarsest level where its σ is at least [`MIN_LEVEL_SIGMA`] level
//! px; each level is the previous one blurred to σ = 2 and decimated by 2, so it starts
//! already smoothed by σ = 1 (its px). Central differences at σ ≥ √2 add a variance of
//! 1/6 px² to the second derivatives (≤ 8 % of σ², 17 % at the first level's σ = 1):
//! immaterial for detection. Each row band of a level computes every scale of its
//! octave (vertical then horizontal Gaussian pass, then the Hessian by central differences,
//! i.e. the discrete Gaussian-derivative filters), keeps the maximum circleness and its
//! scale, and reports 3×3 local maxima: no full-size intermediate image is written.

use super::filter::{horizontal_row, pad_edges, vertical_row, Kernel, View};
use rayon::prelude::*;

/// Smallest smoothing σ (in a level's own px) evaluated on that level: √2, so that a level
/// holds the scales σ ∈ [√2, 2√2) of its px and the first octave (r ≥ 4 px, σ ≥ 2.83) is
/// already evaluated at half resolution, where the image smoothed by σ ≥ 2.83 px is
/// band-limited (its spectrum at the half-resolution Nyquist frequency is < 1e-4). Scales
/// of 2–2.83 px (thin foreshortened circles) are evaluated at half resolution too, at
/// 1–1.41 level px ([`FIRST_LEVEL_MIN_SIGMA`]).
pub(crate) const MIN_LEVEL_SIGMA: f64 = std::f64::consts::SQRT_2;
/// Smallest σ (full-resolution px) evaluated at half resolution: 2, i.e. 1 level px. The
/// image smoothed by σ = 2 px keeps e^(−π²σ²/8) < 0.8 % of its spectrum at the
/// half-resolution Nyquist frequency: immaterial for detection (the centre comes from the
/// full-resolution edge fit), and 4× cheaper than full resolution.
pub(crate) const FIRST_LEVEL_MIN_SIGMA: f64 = 2.0;
/// Smoothing (own px) of a decimated level.
pub(crate) const LEVEL_SIGMA: f64 = 1.0;
/// Rows per parallel job.
const BAND: usize = 48;

/// The two constants of the circleness measure.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Constants {
    /// α of the eigenvalue-ratio factor.
    pub(crate) alpha: f32,
    /// β of the magnitude factor.
    pub(crate) beta: f32,
}

impl Constants {
    /// α = 1/(4 ln 2) and β = e²·ln2/(2·h_ref²) (docs/design.md §4).
    pub(crate) fn new(h_ref: f64) -> Constants {
        let ln2 = std::f64::consts::LN_2;
        let e2 = std::f64::consts::E * std::f64::consts::E;
        Constants {
            alpha: (1.0 / (4.0 * ln2)) as f32,
            beta: (e2 * ln2 / (2.0 * h_ref * h_ref)) as f32,
        }
    }

    /// Circleness of a scale-normalised Hessian (Eqs. 3–4), scalar reference form.
    #[cfg(test)]
    pub(crate) fn circleness(&self, lxx: f64, lxy: f64, lyy: f64) -> f64 {
        let tr = lxx + lyy;
        let disc = ((lxx - lyy).powi(2) + 4.0 * lxy * lxy).sqrt();
        let (l1, l2) = (0.5 * (tr - disc), 0.5 * (tr + disc)); // |λ1| ≥ |λ2| when both < 0
        if l2 >= 0.0 {
            return 0.0;
        }
        let (a, b) = (self.alpha as f64, self.beta as f64);
        (1.0 - (-a * l2 * l2 / (l1 * l1)).exp()) * (1.0 - (-b * (l1 * l1 + l2 * l2)).exp())
    }
}

/// One scale evaluated on a level.
#[derive(Clone, Debug)]
pub(crate) struct Scale {
    /// Total smoothing σ in the level's px (the normalisation σ²).
    pub(crate) sigma: f64,
    /// Kernel bringing the level from its own smoothing to `sigma`.
    pub(crate) kernel: Kernel,
}

/// A circleness peak in full-resolution coordinates.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Peak {
    /// Position (px), subpixel by a parabola through the 3×3 neighbourhood.
    pub(crate) x: f64,
    /// Position (px).
    pub(crate) y: f64,
    /// Arg-max scale σ* (full-resolution px).
    pub(crate) sigma: f64,
    /// Circleness at the peak.
    pub(crate) score: f32,
}

/// exp(−x) for x ≥ 0 (relative error < 2e-6, from rounding x·log2(e) to f32), branch-free
/// and without float→int casts so
/// that row loops vectorise: x·log2(e) = n + f with n an integer (rounded by the 1.5·2²³
/// trick) and |f| ≤ ½, e^(−x) = 2^(−n)·e^(−f·ln2).
#[inline(always)]
fn exp_neg(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0; // 1.5·2²³: adding it rounds to an integer
    let t = (x * std::f32::consts::LOG2_E).min(125.0);
    let y = t + MAGIC;
    let n = y - MAGIC;
    let g = (n - t) * std::f32::consts::LN_2; // |g| ≤ ½ ln 2
                                              // e^g by its Taylor series to degree 6 (|g| ≤ 0.35: remainder < 1.2e-7).
    let p = 1.0
        + g * (1.0
            + g * (0.5
                + g * (1.0 / 6.0 + g * (1.0 / 24.0 + g * (1.0 / 120.0 + g * (1.0 / 720.0))))));
    // 2^(−n) from the integer in y's low mantissa bits.
    let n_int = y.to_bits().wrapping_sub(MAGIC.to_bits());
    p * f32::from_bits((127u32.wrapping_sub(n_int)) << 23)
}

/// Circleness along one row from three rows of the smoothed level (Eqs. 1–4): the
/// scale-normalised Hessian by central differences, its eigenvalues and C. `out[i]` belongs
/// to column i + 1.
#[inline(always)]
fn circleness_row(up: &[f32], mid: &[f32], dn: &[f32], s2: f32, k: Constants, out: &mut [f32]) {
    let n = out.len();
    let (ul, uc, ur) = (&up[..n], &up[1..n + 1], &up[2..n + 2]);
    let (ml, mc, mr) = (&mid[..n], &mid[1..n + 1], &mid[2..n + 2]);
    let (dl, dc, dr) = (&dn[..n], &dn[1..n + 1], &dn[2..n + 2]);
    for i in 0..n {
        let c2 = 2.0 * mc[i];
        let lxx = s2 * (ml[i] + mr[i] - c2);
        let lyy = s2 * (uc[i] + dc[i] - c2);
        let lxy = (0.25 * s2) * (dr[i] - dl[i] - ur[i] + ul[i]);
        // Eq. 2: λ = ½(tr ± √((Lxx − Lyy)² + 4Lxy²)); λ1 the more negative.
        let tr = lxx + lyy;
        let d = lxx - lyy;
        let disc = (d * d + 4.0 * lxy * lxy).sqrt();
        let l1 = 0.5 * (tr - disc);
        let l2 = 0.5 * (tr + disc);
        let (s1, s2q) = (l1 * l1, l2 * l2);
        // Eq. 4: C = (1 − e^(−α λ2²/λ1²))·(1 − e^(−β(λ1² + λ2²))) when both are negative.
        let ratio = s2q / (s1 + f32::MIN_POSITIVE);
        let c = (1.0 - exp_neg(k.alpha * ratio)) * (1.0 - exp_neg(k.beta * (s1 + s2q)));
        out[i] = if l2 < 0.0 { c } else { 0.0 };
    }
}

/// Per-job scratch buffers (allocated once per worker, never per pixel).
struct Scratch {
    padded: Vec<f32>,
    smooth: Vec<f32>,
    cmax: Vec<f32>,
    carg: Vec<f32>,
    crow: Vec<f32>,
}

/// Circleness peaks of one octave: `src` is the level (sampled every `step` full-resolution
/// px), `scales` its scales; peaks ≥ `threshold`.
pub(crate) fn octave_peaks(
    src: View<'_>,
    step: f64,
    scales: &[Scale],
    k: Constants,
    threshold: f32,
) -> Vec<Peak> {
    let (w, h) = (src.width, src.height);
    if w < 3 || h < 3 || scales.is_empty() {
        return Vec::new();
    }
    let rmax = scales.iter().map(|s| s.kernel.radius()).max().unwrap_or(0);
    let bands = h.div_ceil(BAND);
    let per_band: Vec<Vec<Peak>> = (0..bands)
        .into_par_iter()
        .map_init(
            || Scratch {
                padded: vec![0.0; w + 2 * rmax],
                smooth: vec![0.0; (BAND + 4) * w],
                cmax: vec![0.0; (BAND + 2) * w],
                carg: vec![0.0; (BAND + 2) * w],
                crow: vec![0.0; w],
            },
            |s, band| band_peaks(src, step, scales, k, threshold, band, s),
        )
        .collect();
    per_band.into_iter().flatten().collect()
}

#[inline(always)]
fn band_peaks(
    src: View<'_>,
    step: f64,
    scales: &[Scale],
    k: Constants,
    threshold: f32,
    band: usize,
    s: &mut Scratch,
) -> Vec<Peak> {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            return unsafe { band_peaks_avx2(src, step, scales, k, threshold, band, s) };
        }
    }
    band_peaks_generic(src, step, scales, k, threshold, band, s)
}

/// [`band_peaks_generic`] compiled for AVX2 (8-wide row loops).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn band_peaks_avx2(
    src: View<'_>,
    step: f64,
    scales: &[Scale],
    k: Constants,
    threshold: f32,
    band: usize,
    s: &mut Scratch,
) -> Vec<Peak> {
    band_peaks_generic(src, step, scales, k, threshold, band, s)
}

#[inline(always)]
fn band_peaks_generic(
    src: View<'_>,
    step: f64,
    scales: &[Scale],
    k: Constants,
    threshold: f32,
    band: usize,
    s: &mut Scratch,
) -> Vec<Peak> {
    let (w, h) = (src.width, src.height);
    let (y0, y1) = (band * BAND, ((band + 1) * BAND).min(h));
    // Circleness is needed one row beyond the band (3×3 maxima), the smoothed level one more.
    let (cy0, cy1) = (y0.saturating_sub(1), (y1 + 1).min(h));
    let (ly0, ly1) = (cy0.saturating_sub(1), (cy1 + 1).min(h));
    let cmax = &mut s.cmax[..(cy1 - cy0) * w];
    let carg = &mut s.carg[..(cy1 - cy0) * w];
    cmax.fill(0.0);
    carg.fill(0.0);
    for (si, sc) in scales.iter().enumerate() {
        let r = sc.kernel.radius();
        for y in ly0..ly1 {
            let padded = &mut s.padded[..w + 2 * r];
            vertical_row(src, y, &sc.kernel, &mut padded[r..r + w]);
            pad_edges(padded, r, w);
            horizontal_row(
                padded,
                &sc.kernel,
                &mut s.smooth[(y - ly0) * w..(y - ly0 + 1) * w],
            );
        }
        let s2 = (sc.sigma * sc.sigma) as f32;
        for y in cy0.max(1)..cy1.min(h - 1) {
            let row = |yy: usize| &s.smooth[(yy - ly0) * w..(yy - ly0 + 1) * w];
            let crow = &mut s.crow[..w - 2];
            circleness_row(row(y - 1), row(y), row(y + 1), s2, k, crow);
            let base = (y - cy0) * w + 1;
            let (cm, ca) = (&mut cmax[base..base + w - 2], &mut carg[base..base + w - 2]);
            let sif = si as f32;
            for ((m, a), &c) in cm.iter_mut().zip(ca.iter_mut()).zip(crow.iter()) {
                let better = c > *m;
                *m = if better { c } else { *m };
                *a = if better { sif } else { *a };
            }
        }
    }
    // 3×3 local maxima (ties go to the first in raster order), parabolic subpixel offsets.
    let mut peaks = Vec::new();
    let at = |x: usize, y: usize| cmax[(y - cy0) * w + x];
    for y in y0.max(1)..y1.min(h - 1) {
        for x in 1..w - 1 {
            let c = at(x, y);
            if c < threshold {
                continue;
            }
            let before = [
                at(x - 1, y - 1),
                at(x, y - 1),
                at(x + 1, y - 1),
                at(x - 1, y),
            ];
            let after = [
                at(x + 1, y),
                at(x - 1, y + 1),
                at(x, y + 1),
                at(x + 1, y + 1),
            ];
            if before.iter().any(|&v| v >= c) || after.iter().any(|&v| v > c) {
                continue;
            }
            let sub = |m: f32, p: f32| {
                let den = m - 2.0 * c + p;
                if den < 0.0 {
                    (0.5 * (m - p) / den).clamp(-0.5, 0.5) as f64
                } else {
                    0.0
                }
            };
            let (dx, dy) = (
                sub(at(x - 1, y), at(x + 1, y)),
                sub(at(x, y - 1), at(x, y + 1)),
            );
            peaks.push(Peak {
                x: (x as f64 + dx) * step,
                y: (y as f64 + dy) * step,
                sigma: scales[carg[(y - cy0) * w + x] as usize].sigma * step,
                score: c,
            });
        }
    }
    peaks
}

/// Reference contrast h_ref (docs/design.md §4): 0.3·(P95 − P5) of the image intensities, but
/// at least 10 σ_noise, so that an image of mostly flat background does not make noise
/// look contrasted (a disk of contrast 3 σ_noise then scores C < 0.02). From a regular
/// subsample of at most ~250 000 pixels.
pub(crate) fn reference_contrast(img: View<'_>) -> f64 {
    let n = img.data.len();
    let stride = (n / 250_000).max(1);
    let mut v: Vec<f32> = img.data.iter().step_by(stride).copied().collect();
    if v.is_empty() {
        return 0.0;
    }
    let m = v.len();
    let i5 = m * 5 / 100;
    let i95 = (m * 95 / 100).min(m - 1);
    let p95 = *v.select_nth_unstable_by(i95, f32::total_cmp).1;
    let p5 = *v[..i95.max(1)]
        .select_nth_unstable_by(i5.min(i95.max(1) - 1), f32::total_cmp)
        .1;
    (0.3 * (p95 - p5) as f64).max(10.0 * noise_sigma(img, stride))
}

/// Noise σ from horizontal neighbour differences: 1.4826·MAD/√2 (edges are outliers).
fn noise_sigma(img: View<'_>, stride: usize) -> f64 {
    let w = img.width;
    if w < 2 {
        return 0.0;
    }
    let mut d: Vec<f32> = (0..img.data.len() / stride)
        .map(|i| i * stride)
        .filter(|&i| i % w + 1 < w)
        .map(|i| (img.data[i + 1] - img.data[i]).abs())
        .collect();
    if d.is_empty() {
        return 0.0;
    }
    let mid = d.len() / 2;
    let mad = *d.select_nth_unstable_by(mid, f32::total_cmp).1;
    1.4826 * mad as f64 / std::f64::consts::SQRT_2
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_exp_is_accurate() {
        for i in 0..2000 {
            let x = i as f32 * 0.01;
            let (got, want) = (exp_neg(x) as f64, (-(x as f64)).exp());
            assert!(
                (got - want).abs() <= 2e-6 * want + 1e-30,
                "x {x}: {got} vs {want}"
            );
        }
        assert!(exp_neg(1e6) < 1e-30);
    }

    /// The vectorised row kernel agrees with the scalar formula of Eqs. 1–4.
    #[test]
    fn row_kernel_matches_scalar_formula() {
        let k = Constants::new(40.0);
        let n = 64;
        let f = |x: f32, y: f32| {
            100.0 * (-(x * x * 0.02 + 0.01 * x * y + y * y * 0.05)).exp() + 3.0 * x
        };
        let rows: Vec<Vec<f32>> = (0..3)
            .map(|y| {
                (0..n + 2)
                    .map(|x| f(x as f32 - 30.0, y as f32 - 1.2))
                    .collect()
            })
            .collect();
        let mut out = vec![0.0; n];
        let s2 = 4.0f32;
        circleness_row(&rows[0], &rows[1], &rows[2], s2, k, &mut out);
        for (i, &got) in out.iter().enumerate() {
            let (x, y) = (i + 1, 1);
            let v = |dx: isize, dy: isize| {
                rows[(y as isize + dy) as usize][(x as isize + dx) as usize] as f64
            };
            let s2 = s2 as f64;
            let lxx = s2 * (v(-1, 0) + v(1, 0) - 2.0 * v(0, 0));
            let lyy = s2 * (v(0, -1) + v(0, 1) - 2.0 * v(0, 0));
            let lxy = 0.25 * s2 * (v(1, 1) - v(-1, 1) - v(1, -1) + v(-1, -1));
            let want = k.circleness(lxx, lxy, lyy);
            assert!(
                (got as f64 - want).abs() < 1e-5,
                "column {x}: {got} vs {want}"
            );
        }
        assert!(out.iter().any(|&c| c > 0.01), "the blob must register");
    }

    /// docs/design.md §4: for a disk of contrast h_ref the normalised eigenvalues peak near −h/e,
    /// so C ≈ 0.303·½; with the Gaussian-smoothed ideal disk the second factor is exactly ½
    /// when both eigenvalues equal −h/e.
    #[test]
    fn circleness_of_an_ideal_disk_at_reference_contrast() {
        let h = 50.0;
        let k = Constants::new(h);
        let l = -h / std::f64::consts::E;
        let c = k.circleness(l, 0.0, l);
        assert!((c - 0.5 * (1.0 - (-(k.alpha as f64)).exp())).abs() < 1e-6);
        assert!((c - 0.1516).abs() < 1e-3);
        assert_eq!(k.circleness(-1.0, 0.0, 0.5), 0.0);
    }

    #[test]
    fn noise_floor_of_the_reference_contrast() {
        // White noise of σ = 2 on a flat image: h_ref = 10 σ within the MAD's sampling error.
        let mut img = hexcal_core::images::FloatImage::new(400, 300);
        crate::detect::synth::add_noise(&mut img, 2.0, 3);
        let v = View {
            data: img.as_raw(),
            width: 400,
            height: 300,
        };
        let h = reference_contrast(v);
        assert!((h - 20.0).abs() < 0.6, "h_ref {h}");
    }

    #[test]
    fn reference_contrast_of_a_two_level_image() {
        let mut d = vec![10.0f32; 10_000];
        d[..3000].fill(110.0);
        let v = View {
            data: &d,
            width: 100,
            height: 100,
        };
        assert!((reference_contrast(v) - 30.0).abs() < 1e-9);
    }
}
