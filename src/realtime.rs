//! Real-time helpers for control threads: the real-time scheduling class (`SCHED_FIFO`) a
//! 1 kHz loop runs in on a lab PC, and the thread's own CPU clock that tells the code's cost
//! apart from preemption. Thin, checked wrappers over libc; used by the benchmarks and by the
//! docking controller node.

use std::time::Duration;

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn realtime_priority_rejects_out_of_range() {
        assert!(set_realtime_priority(0).is_err());
        assert!(set_realtime_priority(100).is_err());
    }
}
