//! Sample statistics: one quantile rule for the offline figures, one median for the real-time
//! windows ([`upper_median_in_place`]).
//!
//! The rule is linear interpolation between the closest ranks (Hyndman and Fan's
//! definition 7, the default of R and NumPy): the `p`-quantile of `n` ascending samples
//! `v` is `v[i] + f (v[i + 1] - v[i])` with `i + f = p (n - 1)`; the median of an even count
//! is the mean of the middle two, p = 1 the largest sample. Every offline figure uses it: the
//! pivot benchmark's p95 figures, the trials' box plots, the benchmarks' latency and
//! accuracy percentiles, the rostest pivot check.
//!
//! Where the samples cannot be kept (the nodes' real-time loop statistics,
//! [`crate::ros::stats`], and the soak's step times over millions of steps), a
//! [`LogHistogram`] counts them in fixed buckets and applies the same rule to the values of
//! its buckets: the ranks `i` and `i + 1` are read from the buckets that hold them, so its
//! quantiles equal the sorted samples' within the bucket width (at most 0.2 % of the value).

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

/// The upper median of `v` (the sample of rank `n / 2` in ascending order: for an even count
/// the upper of the middle two, not their mean), found in place by selection, without
/// allocating or sorting; NaN when empty. The one exception to the interpolation rule of this
/// module: it is for the real-time windows (the markerless estimator's shaft correction),
/// where a correction must be one that was seen, and the window is re-ordered in place.
pub fn upper_median_in_place(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// Sub-buckets per power of two: 2^10, so a bucket is at most 1/512 of its value wide.
const SUB_BITS: u32 = 10;
const SUB: u64 = 1 << SUB_BITS;
const HALF: u64 = SUB / 2;
/// Values below 2^34 units (17.2 s in nanoseconds); larger ones count in the last bucket.
const TOP_BITS: u32 = 34;
/// Number of buckets: the first `SUB` are exact, each further octave adds `HALF`.
const BUCKETS: usize = (SUB + (TOP_BITS - SUB_BITS) as u64 * HALF) as usize;
/// Groups of buckets counted apart, so a quantile skips whole octaves: the exact range
/// below `SUB`, then one group per octave.
const GROUPS: usize = 1 + (TOP_BITS - SUB_BITS) as usize;

fn group_of(b: usize) -> usize {
    if b < SUB as usize {
        0
    } else {
        1 + (b - SUB as usize) / HALF as usize
    }
}

/// The buckets of group `g`.
fn group_range(g: usize) -> std::ops::Range<usize> {
    if g == 0 {
        0..SUB as usize
    } else {
        let start = SUB as usize + (g - 1) * HALF as usize;
        start..start + HALF as usize
    }
}

/// The bucket of `v` (integer units, e.g. ns).
fn bucket_of(v: u64) -> u16 {
    let v = v.min((1 << TOP_BITS) - 1);
    if v < SUB {
        return v as u16;
    }
    let octave = 63 - v.leading_zeros(); // >= SUB_BITS
    let shift = octave - (SUB_BITS - 1);
    let mantissa = v >> shift; // in [HALF, SUB)
    (SUB + u64::from(octave - SUB_BITS) * HALF + (mantissa - HALF)) as u16
}

/// The middle of bucket `b`, in the recorded units.
fn value_of(b: usize) -> f64 {
    let b = b as u64;
    if b < SUB {
        return b as f64;
    }
    let octave = (b - SUB) / HALF + u64::from(SUB_BITS);
    let shift = octave - u64::from(SUB_BITS - 1);
    let mantissa = (b - SUB) % HALF + HALF;
    let low = mantissa << shift;
    low as f64 + ((1u64 << shift) as f64 - 1.0) / 2.0
}

/// A histogram of non-negative integer values (e.g. nanoseconds) in fixed log-linear buckets:
/// exact below 1024, 3 significant digits above (a bucket is at most 1/512 of its value wide,
/// read at its middle), up to 2^34 (larger values count in the last bucket). Its buffers
/// (about 27 KB) are allocated once in [`LogHistogram::new`]; recording, removing and reading
/// allocate nothing and sort nothing. A value can be taken out again
/// ([`LogHistogram::remove`]), which is what a sliding window needs; the `hdrhistogram`
/// crate keeps the same kind of buckets but cannot.
#[derive(Debug, Clone)]
pub struct LogHistogram {
    counts: Vec<u32>,
    groups: [u32; GROUPS],
    n: u64,
}

impl Default for LogHistogram {
    fn default() -> Self {
        Self::new()
    }
}

impl LogHistogram {
    /// An empty histogram.
    pub fn new() -> Self {
        Self {
            counts: vec![0; BUCKETS],
            groups: [0; GROUPS],
            n: 0,
        }
    }

    /// Count `value`; returns its bucket, for [`LogHistogram::remove`].
    pub fn record(&mut self, value: u64) -> u16 {
        let b = bucket_of(value);
        self.counts[b as usize] = self.counts[b as usize].saturating_add(1);
        self.groups[group_of(b as usize)] = self.groups[group_of(b as usize)].saturating_add(1);
        self.n += 1;
        b
    }

    /// Take out one value of `bucket` (as [`LogHistogram::record`] returned it); nothing if
    /// that bucket is empty.
    pub fn remove(&mut self, bucket: u16) {
        let b = bucket as usize;
        if b < BUCKETS && self.counts[b] > 0 {
            self.counts[b] -= 1;
            self.groups[group_of(b)] -= 1;
            self.n -= 1;
        }
    }

    /// Values counted.
    pub fn len(&self) -> u64 {
        self.n
    }

    /// Whether nothing is counted.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Forget every value (the buffers stay).
    pub fn clear(&mut self) {
        self.counts.fill(0);
        self.groups = [0; GROUPS];
        self.n = 0;
    }

    /// The values (bucket middles) of the samples of rank `r` and `r + 1` (0-based,
    /// ascending; the second clamped to the largest): one walk over the octaves and the
    /// buckets of the octave that holds them.
    fn values_at(&self, r: u64) -> (f64, f64) {
        let last = self.n - 1;
        let (r, s) = (r.min(last), (r + 1).min(last));
        let mut seen = 0u64;
        let mut first = None;
        for (g, &in_group) in self.groups.iter().enumerate() {
            if seen + u64::from(in_group) <= r && first.is_none() {
                seen += u64::from(in_group);
                continue;
            }
            for b in group_range(g) {
                seen += u64::from(self.counts[b]);
                if first.is_none() && seen > r {
                    first = Some(value_of(b));
                }
                if seen > s {
                    return (first.unwrap_or(value_of(b)), value_of(b));
                }
            }
        }
        let top = value_of(BUCKETS - 1);
        (first.unwrap_or(top), top)
    }

    /// The `p`-quantile (0..=1, clamped) by the module's rule, applied to the buckets holding
    /// the two closest ranks; 0 when empty.
    pub fn quantile(&self, p: f64) -> f64 {
        if self.n == 0 {
            return 0.0;
        }
        let pos = p.clamp(0.0, 1.0) * (self.n - 1) as f64;
        let (lo, hi) = self.values_at(pos.floor() as u64);
        let f = pos.fract();
        lo * (1.0 - f) + hi * f
    }

    /// The smallest value counted (its bucket's middle); 0 when empty.
    pub fn min(&self) -> f64 {
        if self.n == 0 {
            return 0.0;
        }
        self.counts.iter().position(|&c| c > 0).map_or(0.0, value_of)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_upper_median_is_a_sample_the_upper_middle_of_an_even_count() {
        assert_eq!(upper_median_in_place(&mut [3.0, -1.0, 2.0]), 2.0);
        // Even: the upper of the middle two (2 and 5), not their mean.
        assert_eq!(upper_median_in_place(&mut [9.0, 2.0, 5.0, -4.0]), 5.0);
        assert_eq!(upper_median_in_place(&mut [7.0]), 7.0);
        assert!(upper_median_in_place(&mut []).is_nan());
    }

    /// Within the histogram's resolution (a bucket is at most 1/512 of its value wide).
    fn close(got: f64, want: f64) -> bool {
        (got - want).abs() <= want.abs() / 512.0 + 1e-9
    }

    #[test]
    fn buckets_cover_the_range_in_order_and_values_fall_in_their_bucket() {
        let mut last = 0;
        for v in (0..40).map(|k| 1u64 << k).flat_map(|v| [v, v + v / 3, v * 2 - 1]) {
            let b = bucket_of(v);
            assert!(b >= last && (b as usize) < BUCKETS, "{v} -> {b}");
            last = b;
            if v < 1 << TOP_BITS {
                let mid = value_of(b as usize);
                assert!((mid - v as f64).abs() <= v as f64 / 1024.0 + 0.5, "{v} -> {mid}");
            }
        }
        assert_eq!(bucket_of(u64::MAX) as usize, BUCKETS - 1);
        // The groups tile the buckets.
        let mut next = 0;
        for g in 0..GROUPS {
            let r = group_range(g);
            assert_eq!(r.start, next);
            assert!(r.clone().all(|b| group_of(b) == g));
            next = r.end;
        }
        assert_eq!(next, BUCKETS);
    }

    #[test]
    fn histogram_quantiles_follow_the_sorted_rule_within_a_bucket() {
        // Spread values (50 us to 40 ms in ns), scrambled, and a small exact range.
        for v in [
            (0..5000u64)
                .map(|k| 50_000 + ((k * 7919) % 5000) * 8_000)
                .collect::<Vec<_>>(),
            (1..=100u64).collect(),
            vec![7, 7, 900_000],
        ] {
            let mut h = LogHistogram::new();
            for &x in &v {
                h.record(x);
            }
            let mut sorted: Vec<f64> = v.iter().map(|&x| x as f64).collect();
            sorted.sort_by(f64::total_cmp);
            for p in [0.0, 0.25, 0.5, 0.95, 0.99, 0.999, 1.0] {
                let (got, want) = (h.quantile(p), quantile_sorted(&sorted, p));
                assert!(close(got, want), "p {p}: {got} vs {want} of {} values", v.len());
            }
            assert!(close(h.min(), sorted[0]));
        }
        // Exact below 1024: the median of 1..=100 interpolates to 50.5, as the sorted rule.
        let mut h = LogHistogram::new();
        (1..=100u64).for_each(|x| {
            h.record(x);
        });
        assert_eq!(h.quantile(0.5), 50.5);
        assert_eq!(LogHistogram::new().quantile(0.5), 0.0);
    }

    #[test]
    fn histogram_values_can_be_taken_out_again() {
        let mut h = LogHistogram::new();
        let big = h.record(5_000_000);
        for x in 1..=10u64 {
            h.record(x);
        }
        assert!(close(h.quantile(1.0), 5_000_000.0));
        h.remove(big);
        assert_eq!((h.len(), h.quantile(1.0)), (10, 10.0));
        h.remove(big); // an empty bucket: nothing happens
        assert_eq!(h.len(), 10);
        h.clear();
        assert!(h.is_empty());
    }

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
