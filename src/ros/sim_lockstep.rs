//! The simulator's clock in lockstep with the controller's commands.
//!
//! Under `/use_sim_time` the simulator owns the clock and paces it on the wall clock. On a
//! busy host the controller's process may get no processor for tens of milliseconds while
//! the simulator's clock runs on: the arm then reaches its last command and stands, the
//! controller wakes to an arm that did not follow and holds (`ARM_NOT_FOLLOWING`), and a
//! test fails for the host's load rather than for the stack. A simulator whose controller
//! runs in its own update (gazebo_ros_control's `RobotHWSim`, called from the physics step)
//! cannot drift from it so; this stack's controller is a separate node, so the simulator
//! instead never lets its clock run more than `command_lockstep_s` of simulated time past
//! the last command it received: it waits (in wall time) for the next one. A slow host then
//! slows the simulation, as the camera's lockstep does for rendering
//! ([`super::sim_node::SimNodeParams::camera_lockstep`]), and never changes what the
//! controller meets in simulated time.
//!
//! The controller publishes a command every control period, moving or holding (the
//! trajectory controller keeps the last one), so on an idle host commands come every 1 to
//! 10 ms and the lockstep never waits. Before the first command, and once the controller
//! has been silent for [`GIVE_UP`] of wall time (stopped, killed, restarting), the clock
//! runs free, as it would without a controller; the next command engages the lockstep again.
//!
//! **The estimator's poses** meet the same starvation: the camera's lockstep holds the clock
//! while a frame renders, but the estimator's work on it runs on the wall clock, so on a
//! busy host the controller got poses up to 180 ms old (capture to command, p99, beside one
//! busy process) against about 90 ms idle. With the camera as the trocar's source the
//! simulator also keeps its clock within `pose_lockstep_s` of the capture stamp of the
//! newest pose on the trocar pose topic (a frame period plus the render and the estimate:
//! 150 ms as shipped, so an idle host never waits), by the same rule: a stream's last event
//! and a bound, free before the first pose and after [`GIVE_UP`] without one (the marker
//! lost, hidden, or the estimator stopped), engaged again by the next pose.

use std::time::{Duration, Instant};

/// How long (wall time) the clock waits for a silent controller before it runs free: longer
/// than a busy host starves a process (tens of milliseconds), short enough that a node that
/// commands only while it moves (the hand-eye calibration's) costs little at each stop.
pub const GIVE_UP: Duration = Duration::from_millis(250);

/// Whether the clock may advance, and the waits' counts.
#[derive(Debug, Clone, Default)]
pub struct CommandLockstep {
    /// Simulated time the clock may run past the last command, s (0: off).
    bound_s: f64,
    /// When the last command arrived (simulated time, s).
    last_arrival: Option<f64>,
    /// The controller went silent: the clock runs free until the next command.
    free: bool,
    /// Waits so far, and their total wall time.
    waits: u64,
    waited: Duration,
}

impl CommandLockstep {
    /// A lockstep that lets the clock run at most `bound_s` of simulated time past the last
    /// command (`0`, or a non-finite value: off).
    pub fn new(bound_s: f64) -> Self {
        Self {
            bound_s: if bound_s.is_finite() && bound_s > 0.0 {
                bound_s
            } else {
                0.0
            },
            ..Self::default()
        }
    }

    /// A command arrived at simulated time `t`.
    pub fn arrived(&mut self, t: f64) {
        self.last_arrival = Some(t);
        self.free = false;
    }

    /// Whether the clock, at simulated time `t`, must wait for a command before it advances.
    pub fn must_wait(&self, t: f64) -> bool {
        match self.last_arrival {
            Some(a) if self.bound_s > 0.0 && !self.free => t - a > self.bound_s,
            _ => false,
        }
    }

    /// A wait ended after `waited` of wall time, with a command (`got`) or without one (the
    /// controller is taken as silent, and the clock runs free until its next command).
    pub fn waited(&mut self, waited: Duration, got: bool) {
        self.waits += 1;
        self.waited += waited;
        if !got {
            self.free = true;
        }
    }

    /// Wait (wall time) until `ready()`, polling every 200 us, or for [`GIVE_UP`] at most (or
    /// until `running()` turns false: the node shutting down); the wait is counted, and one
    /// that ends without `ready()` lets the clock run free. Returns the wall time waited and
    /// whether `ready()` ended it.
    pub fn wait_until(&mut self, mut ready: impl FnMut() -> bool, running: impl Fn() -> bool) -> (Duration, bool) {
        let start = Instant::now();
        let got = loop {
            if ready() {
                break true;
            }
            if start.elapsed() >= GIVE_UP || !running() {
                break false;
            }
            std::thread::sleep(Duration::from_micros(200));
        };
        let waited = start.elapsed();
        self.waited(waited, got);
        (waited, got)
    }

    /// Whether the clock runs free of a silent controller.
    pub fn free(&self) -> bool {
        self.free
    }

    /// The waits so far and their total wall time.
    pub fn waits(&self) -> (u64, Duration) {
        (self.waits, self.waited)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clock_waits_only_once_a_command_stream_is_overdue() {
        let mut l = CommandLockstep::new(0.03);
        assert!(!l.must_wait(100.0), "no command yet: the clock runs free");
        l.arrived(1.0);
        assert!(!l.must_wait(1.029), "within the bound");
        assert!(l.must_wait(1.0301), "past the bound");
        l.arrived(1.031);
        assert!(!l.must_wait(1.05));
        assert_eq!(l.waits(), (0, Duration::ZERO));
    }

    #[test]
    fn a_silent_controller_lets_the_clock_run_free_until_its_next_command() {
        let mut l = CommandLockstep::new(0.03);
        l.arrived(1.0);
        assert!(l.must_wait(1.1));
        l.waited(Duration::from_millis(4), true);
        assert!(
            l.must_wait(1.1) && !l.free(),
            "a wait that got a command changes nothing by itself"
        );
        l.waited(GIVE_UP, false);
        assert!(l.free() && !l.must_wait(5.0), "silent: free");
        l.arrived(5.0);
        assert!(!l.free() && l.must_wait(5.1), "the next command engages it again");
        assert_eq!(l.waits(), (2, Duration::from_millis(4) + GIVE_UP));
    }

    #[test]
    fn a_wait_ends_when_the_stream_is_ready_or_gives_up_and_runs_free() {
        let mut l = CommandLockstep::new(0.03);
        l.arrived(1.0);
        let mut polls = 0;
        let (_, got) = l.wait_until(
            || {
                polls += 1;
                polls == 3
            },
            || true,
        );
        assert!(got && polls == 3 && !l.free(), "ready on the third poll");
        let (waited, got) = l.wait_until(|| false, || false);
        assert!(
            !got && waited < GIVE_UP && l.free(),
            "shutting down: no wait for GIVE_UP, and free"
        );
        assert_eq!(l.waits().0, 2);
    }

    #[test]
    fn zero_negative_or_nan_turns_it_off() {
        for b in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let mut l = CommandLockstep::new(b);
            l.arrived(0.0);
            assert!(!l.must_wait(1e6), "{b}");
        }
    }
}
