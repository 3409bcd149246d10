//! Pacing of a node's loop that survives clock jumps. `rosrust::rate` waits for the next
//! tick on the ROS clock: when that clock goes back (a looping bag, a simulator reset) it
//! sleeps until the old time comes again, a silent freeze of the loop; when it jumps
//! forward, it runs the missed ticks back to back. [`Pacer`] waits on the monotonic clock
//! (wall time) or, under `/use_sim_time`, on the simulated clock with a bound in wall time,
//! and starts its schedule afresh after a jump or an overrun: one tick per period, never
//! a burst, never a freeze. It allocates nothing and takes no lock of ours.

use std::time::{Duration, Instant};

/// How many periods of wall time a tick waits at most for a simulated clock that does not
/// advance (a paused simulator), so that the loop still reports.
const MAX_WAIT_PERIODS: u32 = 20;

/// How many periods late the schedule may be and still catch up (run the ticks without
/// sleeping); later, it starts afresh.
pub const MAX_CATCH_UP: u32 = 5;

/// On the simulated clock, how far (s) the clock may run ahead of the schedule and still be
/// caught up, as `rosrust::rate` does (a simulator catching up after a stall advances its
/// clock in bursts); beyond, it is a jump and the schedule starts afresh.
pub const SIM_CATCH_UP_S: f64 = 1.0;

/// A loop's pace at a fixed rate.
#[derive(Debug)]
pub struct Pacer {
    period: Duration,
    sim_time: bool,
    next_wall: Instant,
    next_ros: f64,
}

impl Pacer {
    /// A pace of `rate_hz` on the ROS clock (simulated under `/use_sim_time`, else the
    /// monotonic clock). Call after `rosrust::init`; under `/use_sim_time` it waits for the
    /// first `/clock` (as `rosrust::rate` does), so no step runs at time zero.
    pub fn new(rate_hz: f64) -> Self {
        let sim_time = rosrust::param("/use_sim_time")
            .and_then(|p| p.get::<bool>().ok())
            .unwrap_or(false);
        while sim_time && rosrust::is_ok() && rosrust::now().seconds() <= 0.0 {
            std::thread::sleep(Duration::from_millis(1));
        }
        Self {
            period: Duration::from_secs_f64(1.0 / rate_hz),
            sim_time,
            next_wall: Instant::now(),
            next_ros: rosrust::now().seconds(),
        }
    }

    /// Whether the pace follows the simulated clock.
    pub fn sim_time(&self) -> bool {
        self.sim_time
    }

    /// Sleep until the next tick.
    pub fn sleep(&mut self) {
        if self.sim_time {
            self.sleep_sim();
        } else {
            self.next_wall += self.period;
            let now = Instant::now();
            match self.next_wall.checked_duration_since(now) {
                Some(wait) => std::thread::sleep(wait),
                // Far behind (a stall): start afresh rather than run the missed ticks.
                None if now.duration_since(self.next_wall) > self.period * MAX_CATCH_UP => self.next_wall = now,
                None => {}
            }
        }
    }

    fn sleep_sim(&mut self) {
        let period = self.period.as_secs_f64();
        let start = rosrust::now().seconds();
        self.next_ros += period;
        if start < self.next_ros - 2.0 * period || start > self.next_ros + SIM_CATCH_UP_S.max(period) {
            // The clock went back, jumped forward or the loop stalled: start afresh.
            self.next_ros = start + period;
        }
        let deadline = Instant::now() + self.period * MAX_WAIT_PERIODS;
        let poll = (self.period / 20).clamp(Duration::from_micros(50), Duration::from_micros(500));
        loop {
            let now = rosrust::now().seconds();
            if now >= self.next_ros || now < start || Instant::now() >= deadline || !rosrust::is_ok() {
                return;
            }
            std::thread::sleep(poll);
        }
    }
}
