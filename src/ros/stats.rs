//! Loop statistics a node reports in its status: the measured loop rate over a sliding
//! window and latency percentiles over the last samples. Buffers are allocated once.

/// Rate and latency bookkeeping of a control loop.
#[derive(Debug, Clone)]
pub struct LoopStats {
    window: f64,
    window_start: Option<f64>,
    window_steps: u64,
    rate_hz: f64,
    steps: u64,
    ring: Vec<f64>,
    next: usize,
    filled: usize,
    scratch: Vec<f64>,
}

/// Latency percentiles, ms.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Percentiles {
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Maximum.
    pub max: f64,
}

impl LoopStats {
    /// Rate measured over windows of `window` seconds; latency over the last `capacity`
    /// samples.
    pub fn new(window: f64, capacity: usize) -> Self {
        let capacity = capacity.max(1);
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
            ring: vec![0.0; capacity],
            next: 0,
            filled: 0,
            scratch: vec![0.0; capacity],
        }
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

    /// Record a latency sample (ms); non-finite samples are ignored.
    pub fn latency(&mut self, ms: f64) {
        if !ms.is_finite() {
            return;
        }
        self.ring[self.next] = ms;
        self.next = (self.next + 1) % self.ring.len();
        self.filled = (self.filled + 1).min(self.ring.len());
    }

    /// Percentiles of the recorded latencies (zeros when none).
    pub fn percentiles(&mut self) -> Percentiles {
        let n = self.filled;
        if n == 0 {
            return Percentiles::default();
        }
        let s = &mut self.scratch[..n];
        s.copy_from_slice(&self.ring[..n]);
        s.sort_unstable_by(f64::total_cmp);
        let q = |p: f64| s[(((n - 1) as f64) * p).round() as usize];
        Percentiles {
            p50: q(0.5),
            p99: q(0.99),
            max: s[n - 1],
        }
    }

    /// Forget everything (on reset).
    pub fn clear(&mut self) {
        let (w, c) = (self.window, self.ring.len());
        *self = Self::new(w, c);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        assert_eq!((p.p50, p.p99, p.max), (51.0, 99.0, 100.0));
        for _ in 0..100 {
            s.latency(1.0);
        }
        s.latency(f64::NAN);
        assert_eq!(s.percentiles().max, 1.0);
    }
}
