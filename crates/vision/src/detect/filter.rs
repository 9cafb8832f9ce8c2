//! Separable Gaussian filtering on borrowed f32 planes: one row at a time, loops shaped for
//! auto-vectorisation (axpy over a row, symmetric taps folded), edges replicated.

use rayon::prelude::*;

/// A borrowed row-major single-channel f32 image.
#[derive(Clone, Copy, Debug)]
pub(crate) struct View<'a> {
    pub(crate) data: &'a [f32],
    pub(crate) width: usize,
    pub(crate) height: usize,
}

impl<'a> View<'a> {
    /// Row `y` (must be < height).
    #[inline(always)]
    pub(crate) fn row(&self, y: usize) -> &'a [f32] {
        &self.data[y * self.width..(y + 1) * self.width]
    }

    /// Bilinear interpolation at (x, y) (px, (0, 0) = centre of the top-left pixel); `None`
    /// outside the convex hull of the pixel centres.
    #[inline(always)]
    pub(crate) fn bilinear(&self, x: f64, y: f64) -> Option<f32> {
        // Signed conversions: one instruction each, unlike usize ↔ f64.
        let (w, h) = (self.width as i64, self.height as i64);
        if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64) {
            return None;
        }
        let x0 = (x as i64).min(w - 2).max(0);
        let y0 = (y as i64).min(h - 2).max(0);
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let i = (y0 * w + x0) as usize;
        let w = self.width;
        let d = &self.data[i..i + w + 2];
        let top = d[0] + fx * (d[1] - d[0]);
        let bot = d[w] + fx * (d[w + 1] - d[w]);
        Some(top + fy * (bot - top))
    }
}

/// An owned plane, e.g. one pyramid level.
#[derive(Clone, Debug)]
pub(crate) struct Plane {
    pub(crate) data: Vec<f32>,
    pub(crate) width: usize,
    pub(crate) height: usize,
}

impl Plane {
    /// Borrow as a [`View`].
    pub(crate) fn view(&self) -> View<'_> {
        View {
            data: &self.data,
            width: self.width,
            height: self.height,
        }
    }
}

/// A sampled, normalised Gaussian, stored as its half `k[0..=R]` (weight of offsets ±j).
#[derive(Clone, Debug)]
pub(crate) struct Kernel {
    pub(crate) half: Vec<f32>,
}

impl Kernel {
    /// Gaussian of standard deviation `sigma` (px), truncated at `truncate`·σ; σ ≈ 0 gives
    /// the identity.
    pub(crate) fn gaussian(sigma: f64, truncate: f64) -> Kernel {
        if sigma < 0.05 {
            return Kernel { half: vec![1.0] };
        }
        let r = (truncate * sigma).ceil().max(1.0) as usize;
        let w: Vec<f64> = (0..=r)
            .map(|j| (-((j * j) as f64) / (2.0 * sigma * sigma)).exp())
            .collect();
        let sum = w[0] + 2.0 * w[1..].iter().sum::<f64>();
        Kernel {
            half: w.iter().map(|v| (v / sum) as f32).collect(),
        }
    }

    /// Half-width R (taps −R..=R).
    pub(crate) fn radius(&self) -> usize {
        self.half.len() - 1
    }
}

/// Vertical pass for one output row: `acc[x] = Σ_j k_|j| · src[clamp(y + j)][x]`.
#[inline(always)]
pub(crate) fn vertical_row(src: View<'_>, y: usize, k: &Kernel, acc: &mut [f32]) {
    let last = src.height as isize - 1;
    let row = |dy: isize| src.row((y as isize + dy).clamp(0, last) as usize);
    let acc = &mut acc[..src.width];
    let k0 = k.half[0];
    for (a, &s) in acc.iter_mut().zip(row(0)) {
        *a = k0 * s;
    }
    for (j, &kj) in k.half.iter().enumerate().skip(1) {
        let (up, dn) = (row(-(j as isize)), row(j as isize));
        for ((a, &u), &d) in acc.iter_mut().zip(up).zip(dn) {
            *a += kj * (u + d);
        }
    }
}

/// Replicates the first and last of the `w` samples at `padded[r..r + w]` into the `r`
/// samples either side.
#[inline(always)]
pub(crate) fn pad_edges(padded: &mut [f32], r: usize, w: usize) {
    let (first, last) = (padded[r], padded[r + w - 1]);
    padded[..r].fill(first);
    padded[r + w..r + w + r].fill(last);
}

/// Horizontal pass: `out[x] = Σ_j k_|j| · padded[r + x + j]`, `padded` holding `r` samples
/// of margin either side of the row.
#[inline(always)]
pub(crate) fn horizontal_row(padded: &[f32], k: &Kernel, out: &mut [f32]) {
    let r = k.radius();
    let w = out.len();
    let k0 = k.half[0];
    for (o, &c) in out.iter_mut().zip(&padded[r..r + w]) {
        *o = k0 * c;
    }
    for (j, &kj) in k.half.iter().enumerate().skip(1) {
        let (left, right) = (&padded[r - j..r - j + w], &padded[r + j..r + j + w]);
        for ((o, &a), &b) in out.iter_mut().zip(left).zip(right) {
            *o += kj * (a + b);
        }
    }
}

/// Rows per parallel job.
const BAND: usize = 16;

/// Separable Gaussian blur of a whole plane (edges replicated), parallel over row bands.
#[cfg(any(test, feature = "testkit"))]
pub(crate) fn blur(src: View<'_>, sigma: f64, truncate: f64) -> Plane {
    let k = Kernel::gaussian(sigma, truncate);
    let (w, h, r) = (src.width, src.height, k.radius());
    let mut data = vec![0.0f32; w * h];
    data.par_chunks_mut(w * BAND).enumerate().for_each_init(
        || vec![0.0f32; w + 2 * r],
        |padded, (band, out)| {
            for (i, out_row) in out.chunks_mut(w).enumerate() {
                vertical_row(src, band * BAND + i, &k, &mut padded[r..r + w]);
                pad_edges(padded, r, w);
                horizontal_row(padded, &k, out_row);
            }
        },
    );
    Plane {
        data,
        width: w,
        height: h,
    }
}

/// Gaussian blur by `sigma` followed by taking every other row and column (pixel (i, j) of
/// the result is pixel (2i, 2j) of the blurred source), parallel over row bands.
pub(crate) fn blur_decimate(src: View<'_>, sigma: f64) -> Plane {
    let k = Kernel::gaussian(sigma, 3.0);
    let (w, h, r) = (src.width, src.height, k.radius());
    let (w2, h2) = (w.div_ceil(2), h.div_ceil(2));
    let mut data = vec![0.0f32; w2 * h2];
    data.par_chunks_mut(w2 * BAND).enumerate().for_each_init(
        || vec![0.0f32; w + 2 * r],
        |padded, (band, out)| {
            for (i, out_row) in out.chunks_mut(w2).enumerate() {
                vertical_row(src, 2 * (band * BAND + i), &k, &mut padded[r..r + w]);
                pad_edges(padded, r, w);
                for (x2, o) in out_row.iter_mut().enumerate() {
                    let c = r + 2 * x2;
                    let mut acc = k.half[0] * padded[c];
                    for (j, &kj) in k.half.iter().enumerate().skip(1) {
                        acc += kj * (padded[c - j] + padded[c + j]);
                    }
                    *o = acc;
                }
            }
        },
    );
    Plane {
        data,
        width: w2,
        height: h2,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernel_is_normalised_with_the_right_variance() {
        for sigma in [0.8, 1.7, 2.83, 6.0] {
            let k = Kernel::gaussian(sigma, 4.0);
            let sum: f64 =
                k.half[0] as f64 + 2.0 * k.half[1..].iter().map(|&v| v as f64).sum::<f64>();
            let var: f64 = 2.0
                * k.half
                    .iter()
                    .enumerate()
                    .map(|(j, &v)| (j * j) as f64 * v as f64)
                    .sum::<f64>();
            assert!((sum - 1.0).abs() < 1e-6);
            // A sampled Gaussian of σ ≥ 0.8 has variance σ² to < 1e-4 relative.
            assert!(
                (var - sigma * sigma).abs() < 1e-3 * sigma * sigma,
                "σ {sigma}: var {var}"
            );
        }
    }

    #[test]
    fn blur_matches_direct_convolution_and_keeps_constants() {
        let (w, h) = (37, 23);
        let data: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 101) as f32).collect();
        let src = View {
            data: &data,
            width: w,
            height: h,
        };
        let sigma = 1.6;
        let out = blur(src, sigma, 3.0);
        let k = Kernel::gaussian(sigma, 3.0);
        let r = k.radius() as isize;
        let at = |x: isize, y: isize| {
            data[(y.clamp(0, h as isize - 1) as usize) * w + x.clamp(0, w as isize - 1) as usize]
        };
        for (x, y) in [(0, 0), (5, 7), (36, 22), (18, 0), (20, 11)] {
            let mut direct = 0.0f64;
            for dy in -r..=r {
                for dx in -r..=r {
                    let kk = k.half[dx.unsigned_abs()] as f64 * k.half[dy.unsigned_abs()] as f64;
                    direct += kk * at(x + dx, y + dy) as f64;
                }
            }
            let got = out.data[y as usize * w + x as usize] as f64;
            assert!((got - direct).abs() < 1e-3, "({x},{y}): {got} vs {direct}");
        }
        let flat = vec![3.5f32; w * h];
        let d = blur_decimate(
            View {
                data: &flat,
                width: w,
                height: h,
            },
            2.0,
        );
        assert_eq!((d.width, d.height), (19, 12));
        assert!(d.data.iter().all(|&v| (v - 3.5).abs() < 1e-5));
    }

    #[test]
    fn bilinear_interpolates_a_plane_exactly() {
        let (w, h) = (6, 5);
        let data: Vec<f32> = (0..w * h)
            .map(|i| (i % w) as f32 * 2.0 + (i / w) as f32 * 3.0)
            .collect();
        let v = View {
            data: &data,
            width: w,
            height: h,
        };
        for (x, y) in [(0.0, 0.0), (2.25, 3.5), (5.0, 4.0), (4.9, 0.1)] {
            let got = v.bilinear(x, y).unwrap() as f64;
            assert!((got - (2.0 * x + 3.0 * y)).abs() < 1e-5);
        }
        assert!(v.bilinear(-0.01, 1.0).is_none());
        assert!(v.bilinear(1.0, 4.01).is_none());
    }
}
