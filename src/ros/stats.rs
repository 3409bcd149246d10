//! Loop statistics a node reports in its status: the measured loop rate over a sliding
//! window, latency percentiles over the last samples, and the loop's timing (the period
//! between step starts, its jitter, the duration of a step).
//!
//! Real-time safe: every buffer is allocated once in [`LoopStats::new`]. Recording a sample
//! is a few integer operations into the project's fixed log-linear histogram
//! ([`crate::stats::LogHistogram`]) and a fixed ring that remembers which bucket each of the
//! last `capacity` samples went to, so the oldest can be taken out again
//! ([`WindowHistogram`]); reading p50/p99/max walks the per-octave counts and the buckets of
//! the octave that holds each rank (no copy, no sort, no allocation) and is cached until the
//! next sample. The percentiles follow the one quantile rule of [`crate::stats`], within the
//! histogram's resolution (3 significant digits, 1 ns to 17 s).

use std::time::{Duration, Instant};

use crate::stats::LogHistogram;

/// A histogram of the last `capacity` values in milliseconds (kept to 1 ns below 1 µs and
/// 3 significant digits above, up to 17 s): a [`LogHistogram`] of nanoseconds and a ring that
/// remembers the bucket of each value in the window, so the oldest can be taken out again.
/// Recording and reading allocate nothing; the buffers (about 27 KB plus 2 bytes per sample
/// of the window) are allocated once at construction.
#[derive(Debug, Clone)]
pub struct WindowHistogram {
    histogram: LogHistogram,
    ring: Vec<u16>,
    next: usize,
    cache: Option<Percentiles>,
}

impl WindowHistogram {
    /// A window of the last `capacity` values (at least 1).
    pub fn new(capacity: usize) -> Self {
        Self {
            histogram: LogHistogram::new(),
            ring: vec![0; capacity.max(1)],
            next: 0,
            cache: None,
        }
    }

    /// How many values the window holds at most.
    pub fn capacity(&self) -> usize {
        self.ring.len()
    }

    /// Values in the window.
    pub fn len(&self) -> usize {
        self.histogram.len() as usize
    }

    /// Whether the window is empty.
    pub fn is_empty(&self) -> bool {
        self.histogram.is_empty()
    }

    /// Record `value`; the oldest value leaves a full window. Non-finite values are
    /// ignored; negative ones count as 0.
    pub fn record(&mut self, value: f64) {
        if !value.is_finite() {
            return;
        }
        if self.len() == self.ring.len() {
            self.histogram.remove(self.ring[self.next]);
        }
        self.ring[self.next] = self.histogram.record((value.max(0.0) * 1e6).round() as u64);
        self.next = (self.next + 1) % self.ring.len();
        self.cache = None;
    }

    /// p50, p99 and max of the window (zeros when empty), by the rule of [`crate::stats`]
    /// within the histogram's resolution; cached until the next [`WindowHistogram::record`].
    pub fn percentiles(&mut self) -> Percentiles {
        if let Some(p) = self.cache {
            return p;
        }
        let q = |p: f64| self.histogram.quantile(p) * 1e-6;
        let p = Percentiles {
            p50: q(0.5),
            p99: q(0.99),
            max: q(1.0),
        };
        self.cache = Some(p);
        p
    }

    /// The smallest value in the window (0 when empty), within the resolution.
    pub fn min(&self) -> f64 {
        self.histogram.min() * 1e-6
    }

    /// Forget every value (the buffers stay).
    pub fn clear(&mut self) {
        self.histogram.clear();
        self.next = 0;
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
        assert!(
            close(p.p50, 50.5) && close(p.p99, 99.01) && close(p.max, 100.0),
            "{p:?}"
        );
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
