//! Timing harness behind `trocar_docking bench`: one suite per file, each returning
//! [`SuiteReport`]s of latency statistics. Benchmarks, not tests, check the performance
//! targets (criterion benches in `benches/` measure the same code paths).

use std::time::{Duration, Instant};

pub mod controller;
pub mod kinematics;
pub mod sim;
pub mod vision;

/// Latency statistics of repeated runs of one operation, in microseconds.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
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
        let q = |p: f64| v[(((v.len() - 1) as f64) * p).round() as usize];
        Some(Self {
            samples: v.len(),
            median_us: q(0.5),
            p90_us: q(0.9),
            p99_us: q(0.99),
            max_us: v[v.len() - 1],
            mean_us: v.iter().sum::<f64>() / v.len() as f64,
        })
    }
}

/// CPU time consumed so far by the calling thread (`CLOCK_THREAD_CPUTIME_ID`); `None`
/// where the clock is unavailable. Unlike the wall clock it does not advance while the
/// thread is preempted, so it separates the code's own cost from the OS scheduler's.
pub fn thread_cpu_time() -> Option<Duration> {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec; clock_gettime only writes into it.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return None;
    }
    let secs = u64::try_from(ts.tv_sec).ok()?;
    let nanos = u32::try_from(ts.tv_nsec).ok()?;
    Some(Duration::new(secs, nanos))
}

/// Move the calling thread to the real-time `SCHED_FIFO` class at `priority` (1..=99), as
/// a control thread of a 1 kHz loop would run, so that ordinary (`SCHED_OTHER`) work on the
/// machine no longer preempts it. Needs `CAP_SYS_NICE` (or root); the error says why not.
/// It cannot stop preemption by the hypervisor, nor interrupts.
pub fn set_realtime_priority(priority: i32) -> Result<(), String> {
    if !(1..=99).contains(&priority) {
        return Err(format!("real-time priority must be in 1..=99, got {priority}"));
    }
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: pthread_self() is the calling thread; `param` is a valid sched_param.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if rc == 0 {
        Ok(())
    } else {
        Err(format!(
            "SCHED_FIFO priority {priority}: {} (needs CAP_SYS_NICE or root)",
            std::io::Error::from_raw_os_error(rc)
        ))
    }
}

/// The calling thread's scheduling class and priority, e.g. `SCHED_FIFO 80` or
/// `SCHED_OTHER`, for reports.
pub fn scheduler_name() -> String {
    let mut policy = 0;
    let mut param = libc::sched_param { sched_priority: 0 };
    // SAFETY: both out-pointers are valid for writes; pthread_self() is this thread.
    let rc = unsafe { libc::pthread_getschedparam(libc::pthread_self(), &mut policy, &mut param) };
    match (rc, policy) {
        (0, libc::SCHED_FIFO) => format!("SCHED_FIFO {}", param.sched_priority),
        (0, libc::SCHED_RR) => format!("SCHED_RR {}", param.sched_priority),
        (0, libc::SCHED_OTHER) => "SCHED_OTHER".into(),
        (0, p) => format!("policy {p}"),
        _ => "unknown".into(),
    }
}

/// Wall-clock and thread-CPU time of one call of `f`, µs (CPU NaN where unavailable).
pub fn time_wall_and_cpu<R>(f: impl FnOnce() -> R) -> (R, f64, f64) {
    let c0 = thread_cpu_time();
    let t0 = Instant::now();
    let r = f();
    let wall = t0.elapsed();
    let cpu = match (c0, thread_cpu_time()) {
        (Some(a), Some(b)) => b.saturating_sub(a).as_secs_f64() * 1e6,
        _ => f64::NAN,
    };
    (r, wall.as_secs_f64() * 1e6, cpu)
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

    #[test]
    fn percentiles_of_known_samples() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        let s = LatencyStats::from_samples(&v).unwrap();
        assert_eq!(s.samples, 100);
        assert_eq!(s.max_us, 100.0);
        assert!((s.median_us - 50.0).abs() <= 1.0);
        assert!((s.p99_us - 99.0).abs() <= 1.0);
        assert!((s.mean_us - 50.5).abs() < 1e-12);
        assert!(LatencyStats::from_samples(&[f64::NAN]).is_none());
    }

    #[test]
    fn realtime_priority_rejects_out_of_range() {
        assert!(set_realtime_priority(0).is_err());
        assert!(set_realtime_priority(100).is_err());
    }

    #[test]
    fn thread_cpu_time_counts_work_but_not_sleep() {
        // Sleeping costs wall time, not CPU time; spinning costs both.
        let ((), wall, cpu) = time_wall_and_cpu(|| std::thread::sleep(Duration::from_millis(20)));
        assert!(wall >= 20_000.0, "{wall}");
        assert!(cpu < 5_000.0, "slept 20 ms but used {cpu} µs of CPU");
        let ((), wall, cpu) = time_wall_and_cpu(|| {
            let t0 = Instant::now();
            while t0.elapsed() < Duration::from_millis(5) {
                std::hint::black_box(0u64);
            }
        });
        assert!(wall >= 5_000.0, "{wall}");
        assert!(cpu > 0.0 && cpu <= wall + 100.0, "cpu {cpu} wall {wall}");
    }
}
