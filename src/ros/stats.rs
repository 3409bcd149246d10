//! Loop statistics a node reports in its status: the measured loop rate over a sliding
//! window, latency percentiles over the last samples, and the loop's timing (the period
//! between step starts, its jitter, the duration of a step).
//!
//! Real-time safe: every buffer is allocated once in [`LoopStats::new`]. Recording a sample
//! is a few integer operations into a fixed log-linear histogram ([`WindowHistogram`]) and a
//! fixed ring that remembers which bucket each of the last `capacity` samples went to, so the
//! oldest can be taken out again; reading p50/p99/max walks the per-octave counts and the
//! buckets of the octaves that hold them (no copy, no sort, no allocation: about 2 µs
//! against 74 µs for the former copy-and-sort of 5000 samples) and is cached until the next
//! sample. The histogram keeps 3 significant digits (a bucket is at most 0.2 % of its value
//! wide, reported at its middle) from 1 ns to 17 s.
//!
//! Why not the `hdrhistogram` crate: it keeps the same kind of buckets, but it cannot take a
//! single value out again, so it cannot keep the "last `capacity` samples" window the status
//! reports; and its quantile walks every bucket below the quantile. The offline statistics (benchmarks) use
//! [`crate::bench::percentile`] on sorted samples instead.

use std::time::{Duration, Instant};

/// Sub-buckets per power of two: 2^10, so a bucket is at most 1/512 of its value wide.
const SUB_BITS: u32 = 10;
const SUB: u64 = 1 << SUB_BITS;
const HALF: u64 = SUB / 2;
/// Values are nanoseconds below 2^34 ns (17.2 s); larger ones count in the last bucket.
const TOP_BITS: u32 = 34;
/// Number of buckets: the first `SUB` are exact, each further octave adds `HALF`.
const BUCKETS: usize = (SUB + (TOP_BITS - SUB_BITS) as u64 * HALF) as usize;
/// Groups of buckets counted apart, so a percentile skips whole octaves: the exact range
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

fn bucket_of(ns: u64) -> u16 {
    let v = ns.min((1 << TOP_BITS) - 1);
    if v < SUB {
        return v as u16;
    }
    let octave = 63 - v.leading_zeros(); // >= SUB_BITS
    let shift = octave - (SUB_BITS - 1);
    let mantissa = v >> shift; // in [HALF, SUB)
    (SUB + u64::from(octave - SUB_BITS) * HALF + (mantissa - HALF)) as u16
}

/// The middle of bucket `b`, ns.
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

/// A histogram of the last `capacity` values in milliseconds (kept to 1 ns below 1 µs and
/// 3 significant digits above, up to 17 s), with fixed buckets. Recording and reading allocate
/// nothing; the buffers (about 27 KB plus 2 bytes per sample of the window) are allocated
/// once at construction.
#[derive(Debug, Clone)]
pub struct WindowHistogram {
    counts: Vec<u32>,
    groups: [u32; GROUPS],
    ring: Vec<u16>,
    next: usize,
    filled: usize,
    cache: Option<Percentiles>,
}

impl WindowHistogram {
    /// A window of the last `capacity` values (at least 1).
    pub fn new(capacity: usize) -> Self {
        Self {
            counts: vec![0; BUCKETS],
            groups: [0; GROUPS],
            ring: vec![0; capacity.max(1)],
            next: 0,
            filled: 0,
            cache: None,
        }
    }

    /// How many values the window holds at most.
    pub fn capacity(&self) -> usize {
        self.ring.len()
    }

    /// Values in the window.
    pub fn len(&self) -> usize {
        self.filled
    }

    /// Whether the window is empty.
    pub fn is_empty(&self) -> bool {
        self.filled == 0
    }

    /// Record `value`; the oldest value leaves a full window. Non-finite values are
    /// ignored; negative ones count as 0.
    pub fn record(&mut self, value: f64) {
        if !value.is_finite() {
            return;
        }
        let b = bucket_of((value.max(0.0) * 1e6).round() as u64);
        if self.filled == self.ring.len() {
            let old = self.ring[self.next] as usize;
            self.counts[old] -= 1;
            self.groups[group_of(old)] -= 1;
        } else {
            self.filled += 1;
        }
        self.ring[self.next] = b;
        self.counts[b as usize] += 1;
        self.groups[group_of(b as usize)] += 1;
        self.next = (self.next + 1) % self.ring.len();
        self.cache = None;
    }

    /// p50, p99 and max of the window (zeros when empty), each within the histogram's
    /// resolution of the sample of rank `round((n - 1) p)`. One walk over the octaves and,
    /// within the octaves that hold the ranks, their buckets (a few µs at most); cached until
    /// the next [`WindowHistogram::record`].
    pub fn percentiles(&mut self) -> Percentiles {
        if let Some(p) = self.cache {
            return p;
        }
        let p = self.compute();
        self.cache = Some(p);
        p
    }

    fn compute(&self) -> Percentiles {
        let n = self.filled;
        if n == 0 {
            return Percentiles::default();
        }
        let rank = |p: f64| ((n - 1) as f64 * p).round() as usize;
        let ranks = [rank(0.5), rank(0.99), n - 1];
        let mut out = [0.0; 3];
        let mut k = 0;
        let mut seen = 0usize;
        'groups: for (g, &in_group) in self.groups.iter().enumerate() {
            if seen + in_group as usize <= ranks[k] {
                seen += in_group as usize; // the next rank lies beyond this octave
                continue;
            }
            for b in group_range(g) {
                seen += self.counts[b] as usize;
                while k < 3 && seen > ranks[k] {
                    out[k] = value_of(b) * 1e-6;
                    k += 1;
                }
                if k == 3 {
                    break 'groups;
                }
            }
        }
        Percentiles {
            p50: out[0],
            p99: out[1],
            max: out[2],
        }
    }

    /// The smallest value in the window (0 when empty), within the resolution.
    pub fn min(&self) -> f64 {
        if self.filled == 0 {
            return 0.0;
        }
        self.counts
            .iter()
            .position(|&c| c > 0)
            .map_or(0.0, |b| value_of(b) * 1e-6)
    }

    /// Forget every value (the buffers stay).
    pub fn clear(&mut self) {
        self.counts.fill(0);
        self.groups = [0; GROUPS];
        self.next = 0;
        self.filled = 0;
        self.cache = None;
    }
}

/// Percentiles, ms.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Percentiles {
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Maximum.
    pub max: f64,
}

/// The loop's timing over the window, ms: the period between step starts, its jitter
/// against the nominal period, and the time from a step's start to its end.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LoopTiming {
    /// Periods between consecutive step starts, ms.
    pub period: Percentiles,
    /// The largest |period - nominal period| in the window, ms (0 without a nominal period).
    pub jitter_max: f64,
    /// Step durations (start to end of a step), ms; `max` is the worst step.
    pub step: Percentiles,
    /// Periods recorded since the last clear.
    pub periods: u64,
    /// Periods longer than 1.5 nominal periods (a late or missed tick) since the last clear.
    pub overruns: u64,
}

/// Rate, latency and timing bookkeeping of a control loop. All buffers are allocated in
/// [`LoopStats::new`]; every other method allocates nothing and sorts nothing.
#[derive(Debug, Clone)]
pub struct LoopStats {
    window: f64,
    window_start: Option<f64>,
    window_steps: u64,
    rate_hz: f64,
    steps: u64,
    latency: WindowHistogram,
    period: WindowHistogram,
    step: WindowHistogram,
    nominal_period: Option<Duration>,
    last_start: Option<Instant>,
    periods: u64,
    overruns: u64,
}

impl LoopStats {
    /// Rate measured over windows of `window` seconds (1 s when not finite and > 0);
    /// latency, period and step time over the last `capacity` samples each.
    pub fn new(window: f64, capacity: usize) -> Self {
        Self {
            window: if window.is_finite() && window > 0.0 {
                window
            } else {
                1.0
            },
            window_start: None,
            window_steps: 0,
            rate_hz: 0.0,
            steps: 0,
            latency: WindowHistogram::new(capacity),
            period: WindowHistogram::new(capacity),
            step: WindowHistogram::new(capacity),
            nominal_period: None,
            last_start: None,
            periods: 0,
            overruns: 0,
        }
    }

    /// The period the loop means to keep, for the jitter and the overrun count.
    pub fn with_nominal_period(mut self, period: Duration) -> Self {
        self.nominal_period = Some(period);
        self
    }

    /// Count one loop iteration at time `now` (s). A clock that jumps back restarts the
    /// window.
    pub fn tick(&mut self, now: f64) {
        self.steps += 1;
        match self.window_start {
            Some(t0) if now >= t0 => {
                self.window_steps += 1;
                let dt = now - t0;
                if dt >= self.window {
                    self.rate_hz = self.window_steps as f64 / dt;
                    self.window_start = Some(now);
                    self.window_steps = 0;
                }
            }
            _ => {
                self.window_start = Some(now);
                self.window_steps = 0;
            }
        }
    }

    /// Iterations counted.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// Rate over the last complete window, Hz (0 before the first).
    pub fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    /// Record a latency sample (ms); non-finite samples are ignored, negative ones count
    /// as 0.
    pub fn latency(&mut self, ms: f64) {
        self.latency.record(ms);
    }

    /// Percentiles of the last latency samples, ms (zeros when none), within 0.1 %.
    pub fn percentiles(&mut self) -> Percentiles {
        self.latency.percentiles()
    }

    /// A step starts at `t` (the monotonic clock): records the period since the last
    /// start.
    pub fn step_started(&mut self, t: Instant) {
        if let Some(last) = self.last_start.replace(t) {
            let period = t.saturating_duration_since(last);
            self.period.record(period.as_secs_f64() * 1e3);
            self.periods += 1;
            if self
                .nominal_period
                .is_some_and(|n| period.as_secs_f64() > 1.5 * n.as_secs_f64())
            {
                self.overruns += 1;
            }
        }
    }

    /// The step that started last ends at `t`: records its duration.
    pub fn step_finished(&mut self, t: Instant) {
        if let Some(start) = self.last_start {
            self.step.record(t.saturating_duration_since(start).as_secs_f64() * 1e3);
        }
    }

    /// Period, jitter and step-time statistics of the window.
    pub fn timing(&mut self) -> LoopTiming {
        let period = self.period.percentiles();
        let jitter_max = match (self.nominal_period, self.period.is_empty()) {
            (Some(n), false) => {
                let n = n.as_secs_f64() * 1e3;
                (period.max - n).max(n - self.period.min()).max(0.0)
            }
            _ => 0.0,
        };
        LoopTiming {
            period,
            jitter_max,
            step: self.step.percentiles(),
            periods: self.periods,
            overruns: self.overruns,
        }
    }

    /// Forget everything (on reset); the buffers and the nominal period stay.
    pub fn clear(&mut self) {
        self.window_start = None;
        self.window_steps = 0;
        self.rate_hz = 0.0;
        self.steps = 0;
        self.latency.clear();
        self.period.clear();
        self.step.clear();
        self.last_start = None;
        self.periods = 0;
        self.overruns = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Within the histogram's resolution (a bucket is at most 1/512 of its value wide).
    fn close(got: f64, want: f64) -> bool {
        (got - want).abs() <= want.abs() / 512.0 + 1e-6
    }

    #[test]
    fn buckets_cover_the_range_in_order_and_values_fall_in_their_bucket() {
        let mut last = 0;
        for ns in (0..40).map(|k| 1u64 << k).flat_map(|v| [v, v + v / 3, v * 2 - 1]) {
            let b = bucket_of(ns);
            assert!(b >= last && (b as usize) < BUCKETS, "{ns} -> {b}");
            last = b;
            if ns < 1 << TOP_BITS {
                let mid = value_of(b as usize);
                assert!((mid - ns as f64).abs() <= ns as f64 / 1024.0 + 0.5, "{ns} -> {mid}");
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
    fn rate_is_measured_per_window() {
        let mut s = LoopStats::new(1.0, 10);
        for k in 0..=2000 {
            s.tick(k as f64 * 0.001);
        }
        assert!((s.rate_hz() - 1000.0).abs() < 1.0, "{}", s.rate_hz());
        assert_eq!(s.steps(), 2001);
        s.tick(0.0); // clock jumped back (bag loop): a new window starts
        assert!(s.rate_hz() > 0.0);
    }

    #[test]
    fn percentiles_cover_the_last_samples_only() {
        let mut s = LoopStats::new(1.0, 100);
        assert_eq!(s.percentiles(), Percentiles::default());
        for k in 1..=100 {
            s.latency(k as f64);
        }
        let p = s.percentiles();
        assert!(close(p.p50, 51.0) && close(p.p99, 99.0) && close(p.max, 100.0), "{p:?}");
        for _ in 0..100 {
            s.latency(1.0);
        }
        s.latency(f64::NAN);
        let p = s.percentiles();
        assert!(close(p.max, 1.0) && close(p.p50, 1.0), "{p:?}");
    }

    #[test]
    fn percentiles_of_spread_samples_match_the_sorted_ranks() {
        // 5000 latencies from 0.05 ms to 40 ms, in a scrambled order.
        let v: Vec<f64> = (0..5000u64)
            .map(|k| 0.05 + ((k * 7919) % 5000) as f64 * 0.008)
            .collect();
        let mut s = LoopStats::new(1.0, 5000);
        for &x in &v {
            s.latency(x);
        }
        let mut sorted = v.clone();
        sorted.sort_by(f64::total_cmp);
        let p = s.percentiles();
        let want = |q: f64| crate::stats::quantile_sorted(&sorted, q);
        assert!(close(p.p50, want(0.5)), "{} vs {}", p.p50, want(0.5));
        assert!(close(p.p99, want(0.99)), "{} vs {}", p.p99, want(0.99));
        assert!(close(p.max, want(1.0)), "{} vs {}", p.max, want(1.0));
        s.clear();
        assert_eq!(s.percentiles(), Percentiles::default());
        assert_eq!(s.steps(), 0);
    }

    #[test]
    fn timing_reports_period_jitter_and_the_worst_step() {
        let mut s = LoopStats::new(1.0, 1000).with_nominal_period(Duration::from_millis(1));
        let t0 = Instant::now();
        let ms = |x: f64| t0 + Duration::from_secs_f64(x * 1e-3);
        // 1 ms periods, one late tick (3.5 ms), steps of 0.1 ms and one of 0.8 ms.
        let starts = [0.0, 1.0, 2.0, 3.0, 6.5, 7.5];
        for (k, &t) in starts.iter().enumerate() {
            s.step_started(ms(t));
            s.step_finished(ms(t + if k == 2 { 0.8 } else { 0.1 }));
        }
        let t = s.timing();
        assert_eq!((t.periods, t.overruns), (5, 1));
        assert!(close(t.period.max, 3.5) && close(t.period.p50, 1.0), "{t:?}");
        assert!(close(t.jitter_max, 2.5), "{t:?}");
        assert!(close(t.step.max, 0.8) && close(t.step.p50, 0.1), "{t:?}");
        s.clear();
        assert_eq!(s.timing().periods, 0);
        assert_eq!(s.timing().jitter_max, 0.0);
    }

    #[test]
    fn recording_and_reading_do_not_allocate() {
        let mut s = LoopStats::new(1.0, 5000).with_nominal_period(Duration::from_millis(1));
        let t0 = Instant::now();
        let before = crate::test_alloc::allocations_on_this_thread();
        for k in 0..20_000u32 {
            s.tick(f64::from(k) * 1e-3);
            s.latency(f64::from(k % 97) * 0.1);
            let t = t0 + Duration::from_micros(u64::from(k) * 1000);
            s.step_started(t);
            s.step_finished(t + Duration::from_micros(30));
            let _ = s.percentiles();
            let _ = s.timing();
        }
        assert_eq!(crate::test_alloc::allocations_on_this_thread(), before);
    }
}
