//! Small robust statistics the stages share.

/// The median of `x` (the upper one of an even count; reorders `x`; 0 when empty).
pub fn median(x: &mut [f64]) -> f64 {
    if x.is_empty() {
        return 0.0;
    }
    let mid = x.len() / 2;
    *x.select_nth_unstable_by(mid, f64::total_cmp).1
}
