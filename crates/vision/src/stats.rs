//! Small robust statistics the stages share.

/// The median of `x` (the upper one of an even count; reorders `x`; 0 when empty).
pub fn median(x: &mut [f64]) -> f64 {
    if x.is_empty() {
        return 0.0;
    }
    let mid = x.len() / 2;
    *x.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// P(χ²_k > x), the regularised upper incomplete gamma Q(k/2, x/2), for k ≥ 1: from Q(1/2)
/// = erfc(√h) or Q(1) = e^{−h} (h = x/2) by Q(a + 1) = Q(a) + hᵃ·e^{−h}/Γ(a + 1).
pub fn chi2_tail(k: usize, x: f64) -> f64 {
    let h = 0.5 * x;
    let (mut q, mut term, mut a) = match k % 2 {
        1 => (
            libm::erfc(h.sqrt()),
            2.0 * (h / std::f64::consts::PI).sqrt() * (-h).exp(),
            1.5,
        ),
        _ => ((-h).exp(), h * (-h).exp(), 2.0),
    };
    for _ in 0..(k.max(1) - 1) / 2 {
        q += term;
        term *= h / a;
        a += 1.0;
    }
    q
}

#[cfg(test)]
mod tests {
    use super::chi2_tail;

    /// Against the closed forms of k = 1…4 and the exponential series of k = 12.
    #[test]
    fn chi2_tails_match_their_closed_forms() {
        for x in [0.5, 3.0, 41.0] {
            let h: f64 = 0.5 * x;
            let e = (-h).exp();
            let odd = 2.0 * (h / std::f64::consts::PI).sqrt() * e;
            let closed = [
                libm::erfc(h.sqrt()),
                e,
                libm::erfc(h.sqrt()) + odd,
                e * (1.0 + h),
            ];
            for (k, want) in (1..).zip(closed) {
                assert!((chi2_tail(k, x) / want - 1.0).abs() < 1e-12, "k {k} x {x}");
            }
            let series: f64 = (0..6)
                .map(|i| h.powi(i) / (1..=i).product::<i32>() as f64)
                .sum();
            assert!(
                (chi2_tail(12, x) / (e * series) - 1.0).abs() < 1e-12,
                "x {x}"
            );
        }
    }
}
