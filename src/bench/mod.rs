//! Timing harness behind `trocar_docking bench`: one suite per file, each returning
//! [`SuiteReport`]s of latency statistics. Benchmarks, not tests, check the performance
//! targets (`make bench` runs every suite).

pub use crate::realtime::{scheduler_name, set_realtime_priority, thread_cpu_time};
use std::time::Instant;

use crate::stats::quantile_sorted;

pub mod controller;
pub mod kinematics;
pub mod markerless;
pub mod sim;
pub mod vision;

/// Latency statistics of repeated runs of one operation, in microseconds.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LatencyStats {
    /// Number of samples.
    pub samples: usize,
    /// Median, µs.
    pub median_us: f64,
    /// 90th percentile, µs.
    pub p90_us: f64,
    /// 99th percentile, µs.
    pub p99_us: f64,
    /// Maximum, µs.
    pub max_us: f64,
    /// Mean, µs.
    pub mean_us: f64,
}

impl LatencyStats {
    /// Statistics of `samples_us` (µs); `None` when there are no finite samples.
    pub fn from_samples(samples_us: &[f64]) -> Option<Self> {
        let mut v: Vec<f64> = samples_us.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        let q = |p: f64| quantile_sorted(&v, p);
        Some(Self {
            samples: v.len(),
            median_us: q(0.5),
            p90_us: q(0.9),
            p99_us: q(0.99),
            max_us: q(1.0),
            mean_us: v.iter().sum::<f64>() / v.len() as f64,
        })
    }
}

/// What one timed call returned, and how long it took.
#[derive(Debug, Clone, Copy)]
pub struct Timed<R> {
    /// The call's result.
    pub value: R,
    /// Wall-clock time, µs.
    pub wall_us: f64,
    /// The thread's CPU time, µs (NaN where the thread CPU clock is unavailable).
    pub cpu_us: f64,
}

/// Wall-clock and thread-CPU time of one call of `f`, µs (CPU NaN where unavailable).
pub fn time_wall_and_cpu<R>(f: impl FnOnce() -> R) -> Timed<R> {
    let c0 = thread_cpu_time();
    let t0 = Instant::now();
    let r = f();
    let wall = t0.elapsed();
    let cpu = match (c0, thread_cpu_time()) {
        (Some(a), Some(b)) => b.saturating_sub(a).as_secs_f64() * 1e6,
        _ => f64::NAN,
    };
    Timed {
        value: r,
        wall_us: wall.as_secs_f64() * 1e6,
        cpu_us: cpu,
    }
}

/// One benchmarked operation: its name, latency, and extra figures (iterations, errors…).
#[derive(Debug, Clone, serde::Serialize)]
pub struct SuiteReport {
    /// Operation name, e.g. `fk_jacobian_med7`.
    pub name: String,
    /// Latency statistics.
    pub latency: LatencyStats,
    /// Extra named figures.
    pub extra: serde_json::Map<String, serde_json::Value>,
}

/// Time `f` once per element of `inputs` (after `warmup` untimed calls), in µs per call.
pub fn time_each<T, R>(inputs: &[T], warmup: usize, mut f: impl FnMut(&T) -> R) -> Vec<f64> {
    for x in inputs.iter().cycle().take(warmup.min(inputs.len() * 10)) {
        std::hint::black_box(f(x));
    }
    inputs
        .iter()
        .map(|x| {
            let t0 = Instant::now();
            std::hint::black_box(f(x));
            t0.elapsed().as_secs_f64() * 1e6
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn percentiles_of_known_samples() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        let s = LatencyStats::from_samples(&v).unwrap();
        assert_eq!(s.samples, 100);
        assert_eq!(s.max_us, 100.0);
        // The rule of crate::stats: interpolated between the closest ranks.
        assert!((s.median_us - 50.5).abs() < 1e-12);
        assert!((s.p90_us - 90.1).abs() < 1e-9);
        assert!((s.p99_us - 99.01).abs() < 1e-9);
        assert!((s.mean_us - 50.5).abs() < 1e-12);
        assert!(LatencyStats::from_samples(&[f64::NAN]).is_none());
    }

    #[test]
    fn thread_cpu_time_counts_work_but_not_sleep() {
        // Sleeping costs wall time, not CPU time; spinning costs both.
        // The least of three tries: on a virtual machine the hypervisor's stolen time is
        // charged to the running thread (docs/simulation.md, Soak), now and then milliseconds.
        let mut cpu = f64::INFINITY;
        for _ in 0..3 {
            let Timed {
                wall_us: wall,
                cpu_us: c,
                ..
            } = time_wall_and_cpu(|| std::thread::sleep(Duration::from_millis(20)));
            assert!(wall >= 20_000.0, "{wall}");
            cpu = cpu.min(c);
        }
        assert!(cpu < 5_000.0, "slept 20 ms but used {cpu} µs of CPU");
        let Timed {
            wall_us: wall,
            cpu_us: cpu,
            ..
        } = time_wall_and_cpu(|| {
            let t0 = Instant::now();
            while t0.elapsed() < Duration::from_millis(5) {
                std::hint::black_box(0u64);
            }
        });
        assert!(wall >= 5_000.0, "{wall}");
        // The same unit as the wall time (a ns/µs mix-up is 1000x off). Not `<= wall`: on a
        // virtual machine the thread CPU clock counts time the vCPU did not run
        // (docs/simulation.md, Soak) and has read more than the wall time under a parallel
        // `cargo test`.
        assert!(cpu > 0.0 && cpu <= 2.0 * wall, "cpu {cpu} wall {wall}");
    }
}
