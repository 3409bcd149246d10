//! Sample statistics of the offline figures: one quantile rule.
//!
//! The rule is linear interpolation between the closest ranks (Hyndman and Fan's
//! definition 7, the default of R and NumPy): the `p`-quantile of `n` ascending samples
//! `v` is `v[i] + f (v[i + 1] - v[i])` with `i + f = p (n - 1)`; the median of an even count
//! is the mean of the middle two, p = 1 the largest sample. Every offline figure uses it: the
//! pivot benchmark's p95 figures, the trials' box plots, the benchmarks' latency and
//! accuracy percentiles, the rostest pivot check. The nodes' real-time loop statistics
//! ([`crate::ros::stats`]) and the soak's step times keep fixed histograms instead (no
//! sample kept, nothing sorted), read by the nearest rank of their bins.

/// The `p`-quantile (0..=1, clamped) of `sorted` (ascending) by the rule of this module; NaN
/// when empty.
pub fn quantile_sorted(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let pos = p.clamp(0.0, 1.0) * (sorted.len() - 1) as f64;
    let (i, f) = (pos.floor() as usize, pos.fract());
    let j = (i + 1).min(sorted.len() - 1);
    sorted[i] * (1.0 - f) + sorted[j] * f
}

/// The `p`-quantile of the finite values of `v`, in any order (NaN if there are none).
pub fn finite_quantile(v: &[f64], p: f64) -> f64 {
    let mut v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else {
        quantile_sorted(&v, p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_interpolate_between_the_closest_ranks() {
        let v = [1.0, 2.0, 3.0, 4.0, 5.0];
        assert_eq!(quantile_sorted(&v, 0.5), 3.0);
        assert_eq!(quantile_sorted(&v, 0.25), 2.0);
        assert!((quantile_sorted(&v, 0.95) - 4.8).abs() < 1e-12);
        assert!((quantile_sorted(&[1.0, 2.0], 0.5) - 1.5).abs() < 1e-12);
        assert_eq!(quantile_sorted(&[7.0], 0.99), 7.0);
        assert!(quantile_sorted(&[], 0.5).is_nan());
    }

    #[test]
    fn finite_quantile_skips_non_finite_values_and_sorts() {
        assert_eq!(finite_quantile(&[3.0, f64::NAN, 1.0, f64::INFINITY, 2.0], 0.5), 2.0);
        assert!(finite_quantile(&[f64::NAN], 0.5).is_nan());
        assert!(finite_quantile(&[], 0.5).is_nan());
    }
}
