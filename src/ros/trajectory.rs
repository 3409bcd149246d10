//! How the driver's `joint_trajectory_controller` (ros_controllers, noetic; the LBR's ROS 1
//! driver is a ros_control `RobotHW` that runs it once per FRI cycle) takes our stream of
//! one-point `JointTrajectory` messages, reproduced as its source does, for the simulator:
//!
//! - **The clock.** Each `update(time, period)`
//!   (`joint_trajectory_controller_impl.h`, `JointTrajectoryController::update`) caches
//!   `time_data` and samples the trajectory at that time. A message is judged against the
//!   **next** update, `time_data->time + time_data->period`
//!   (`JointTrajectoryController::updateTrajectoryCommand`), on the driver's clock.
//! - **The start time.** `header.stamp`, or the next update when the stamp is 0
//!   (`joint_trajectory_msg_utils.h`, `internal::startTime`).
//! - **Whole messages dropped.** A message whose last point is due at or before the next
//!   update is dropped whole ("Dropping all N trajectory point(s), as they occur before the
//!   current time", `init_joint_trajectory.h`, `initJointTrajectory` with `findPoint`, whose
//!   `IsBeforePoint` is `time < start + time_from_start`); `initJointTrajectory` returns an empty
//!   trajectory and the controller keeps executing its current one.
//! - **The new segment starts from the current desired state.** The current trajectory is
//!   kept up to `max(start, next update)`, where the trajectory is sampled, and a bridge
//!   segment runs from there to the point at `start + time_from_start` (`initJointTrajectory`,
//!   "Bridge current trajectory to new one").
//! - **Linear interpolation.** Points with positions only are interpolated linearly
//!   (`trajectory_interface/quintic_spline_segment.h`, `QuinticSplineSegment::init`: "If only
//!   positions are specified, linear interpolation will be used"; the lowest common
//!   specification of the two ends), and a segment sampled past its end holds its end.
//!
//! The trajectory is therefore piecewise linear: a list of knots (time, positions). One clock
//! stands for both of the controller's time bases (`time` and `uptime`): the simulator runs
//! the updates at exact periods, where they advance together.
//!
//! [`StreamCounts`] counts what the stream met: messages dropped by the rule (and of them the
//! ones that moved the arm), and **late** ones: a moving message, after a moving one, that
//! finds the trajectory already ended at the last update (the arm was held still there; the stop-and-go of a too
//! short `time_from_start`). Pure and allocation-free; `lbr_med_sim` drives it at the
//! driver's period.

use crate::kinematics::JointVector;

/// Knots kept: a stream whose points are due up to 30 messages ahead of the driver fits;
/// beyond, the oldest knot is let go (only a stream stamped far in the driver's future).
pub const KNOTS: usize = 64;

/// What the stream of commands met at the trajectory controller.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamCounts {
    /// Messages received.
    pub messages: u64,
    /// Messages whose positions differ from the previous message's (the first one: from
    /// the held position).
    pub moving: u64,
    /// Messages dropped whole (due at or before the next update).
    pub dropped: u64,
    /// Moving messages dropped.
    pub dropped_moving: u64,
    /// Moving messages, after a moving one, accepted when the trajectory had ended at the
    /// last update: the arm was held still there while the stream moved.
    pub late: u64,
    /// The smallest lead of a message's point over the next update, s (+inf before any).
    pub min_lead_s: f64,
}

impl Default for StreamCounts {
    fn default() -> Self {
        Self {
            messages: 0,
            moving: 0,
            dropped: 0,
            dropped_moving: 0,
            late: 0,
            min_lead_s: f64::INFINITY,
        }
    }
}

/// What became of one message.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Outcome {
    /// Taken: its point is due `lead_s` after the next update.
    Accepted {
        /// Point time minus the next update's time, s (> 0).
        lead_s: f64,
    },
    /// Dropped whole: its point was due `late_by_s` before (or at) the next update.
    Dropped {
        /// Next update's time minus the point time, s (>= 0; NaN for a non-finite time).
        late_by_s: f64,
    },
}

/// A position `JointTrajectoryController` fed one-point messages (positions only).
#[derive(Debug, Clone)]
pub struct TrajectoryController {
    times: [f64; KNOTS],
    positions: [JointVector; KNOTS],
    len: usize,
    /// `time_data.time` of the last update (driver clock), s.
    time: f64,
    /// `time_data.period`, s.
    period: f64,
    /// The previous message's positions.
    last_command: JointVector,
    /// Whether the previous message moved.
    last_moving: bool,
    counts: StreamCounts,
}

impl TrajectoryController {
    /// Started at driver time `time` holding `q` (the controller's `starting`: its hold
    /// trajectory at the current position), updating every `period` s.
    pub fn new(q: JointVector, time: f64, period: f64) -> Self {
        let mut c = Self {
            times: [f64::NEG_INFINITY; KNOTS],
            positions: [q; KNOTS],
            len: 1,
            time,
            period,
            last_command: q,
            last_moving: false,
            counts: StreamCounts::default(),
        };
        c.times[0] = time;
        c
    }

    /// The update at driver time `time`: the desired positions there (what the hardware
    /// interface is commanded).
    pub fn update(&mut self, time: f64) -> JointVector {
        self.time = time;
        // Segments wholly before this update are never sampled again.
        let mut first = 0;
        while first + 1 < self.len && self.times[first + 1] <= time {
            first += 1;
        }
        self.shift(first);
        self.sample(time)
    }

    /// The trajectory at driver time `t`.
    pub fn sample(&self, t: f64) -> JointVector {
        let n = self.len;
        if t <= self.times[0] {
            return self.positions[0];
        }
        if t >= self.times[n - 1] {
            return self.positions[n - 1];
        }
        let i = (1..n).find(|&i| self.times[i] > t).unwrap_or(n - 1);
        let (t0, t1) = (self.times[i - 1], self.times[i]);
        let s = if t1 > t0 { (t - t0) / (t1 - t0) } else { 1.0 };
        self.positions[i - 1] + (self.positions[i] - self.positions[i - 1]) * s
    }

    /// A one-point message: positions `q` due `time_from_start` s after `stamp` (driver's
    /// clock, s; `None`: a zero stamp, the next update).
    pub fn command(&mut self, stamp: Option<f64>, time_from_start: f64, q: JointVector) -> Outcome {
        let moving = q != self.last_command;
        let stream_moving = moving && self.last_moving;
        self.last_command = q;
        self.last_moving = moving;
        self.counts.messages += 1;
        self.counts.moving += u64::from(moving);
        let next = self.time + self.period;
        let start = stamp.unwrap_or(next);
        let due = start + time_from_start;
        let lead = due - next;
        if lead.is_finite() {
            self.counts.min_lead_s = self.counts.min_lead_s.min(lead);
        }
        // findPoint: kept only when `next < due`; a NaN time is never after `next`.
        if lead.is_nan() || lead <= 0.0 {
            self.counts.dropped += 1;
            self.counts.dropped_moving += u64::from(moving);
            return Outcome::Dropped { late_by_s: -lead };
        }
        if stream_moving && self.times[self.len - 1] <= self.time {
            self.counts.late += 1;
        }
        let bridge_t = start.max(next);
        let bridge_q = self.sample(bridge_t);
        // The current trajectory is kept up to the bridge's start.
        while self.len > 1 && self.times[self.len - 1] >= bridge_t {
            self.len -= 1;
        }
        if self.times[self.len - 1] >= bridge_t {
            self.len = 0;
        }
        let room = KNOTS - 2;
        if self.len > room {
            self.shift(self.len - room);
        }
        self.push(bridge_t, bridge_q);
        self.push(due, q);
        Outcome::Accepted { lead_s: lead }
    }

    /// A position command taken as it is (a `JointGroupPositionController`): held from now.
    pub fn set_position(&mut self, q: JointVector) {
        self.last_command = q;
        self.last_moving = false;
        self.len = 0;
        self.push(self.time, q);
    }

    /// What the stream met so far.
    pub fn counts(&self) -> StreamCounts {
        self.counts
    }

    fn push(&mut self, t: f64, q: JointVector) {
        self.times[self.len] = t;
        self.positions[self.len] = q;
        self.len += 1;
    }

    /// Let the first `k` knots go.
    fn shift(&mut self, k: usize) {
        if k > 0 {
            self.times.copy_within(k..self.len, 0);
            self.positions.copy_within(k..self.len, 0);
            self.len -= k;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn q(x: f64) -> JointVector {
        JointVector::from_element(x)
    }

    const P: f64 = 0.002;

    /// A controller started at 0 and updated once at `t`.
    fn at(t: f64) -> TrajectoryController {
        let mut c = TrajectoryController::new(q(0.0), 0.0, P);
        c.update(t);
        c
    }

    #[test]
    fn a_message_due_at_or_before_the_next_update_is_dropped_whole_and_the_old_trajectory_stands() {
        let mut c = at(1.0);
        assert!(matches!(c.command(Some(0.995), 0.01, q(0.5)), Outcome::Accepted { .. }));
        // Due 1.002 = the next update: dropped ("occur before the current time").
        let o = c.command(Some(0.992), 0.010, q(0.9));
        assert!(
            matches!(o, Outcome::Dropped { late_by_s } if late_by_s.abs() < 1e-12),
            "{o:?}"
        );
        // Due 10 ms before it: dropped, 10 ms late.
        let o = c.command(Some(0.982), 0.010, q(0.9));
        assert!(matches!(o, Outcome::Dropped { late_by_s } if (late_by_s - 0.010).abs() < 1e-12));
        assert!(matches!(
            c.command(Some(f64::NAN), 0.01, q(0.9)),
            Outcome::Dropped { .. }
        ));
        // The accepted trajectory is still executed: 0.5 reached when due (1.005).
        assert_eq!(c.update(1.006), q(0.5));
        let n = c.counts();
        assert_eq!((n.messages, n.moving, n.dropped, n.dropped_moving), (4, 2, 3, 1));
        assert!((n.min_lead_s + 0.010).abs() < 1e-12);
    }

    #[test]
    fn a_zero_stamp_starts_at_the_next_update_whatever_the_clocks() {
        // The driver's clock far from the controller's: a zero stamp is judged on the driver's.
        for t in [5.0, 1e6] {
            let mut c = at(t);
            let o = c.command(None, 0.002, q(1.0));
            assert!(
                matches!(o, Outcome::Accepted { lead_s } if (lead_s - 0.002).abs() < 1e-9),
                "due time_from_start after the next update: {o:?}"
            );
            assert_eq!(c.update(t + P), q(0.0), "the bridge starts at the next update");
            assert!(
                (c.update(t + 2.0 * P)[0] - 1.0).abs() < 1e-9,
                "reached time_from_start later"
            );
        }
        // time_from_start 0 with a zero stamp: due at the next update, dropped.
        assert!(matches!(at(1.0).command(None, 0.0, q(1.0)), Outcome::Dropped { .. }));
    }

    #[test]
    fn the_new_segment_starts_from_the_current_desired_state_and_interpolates_linearly() {
        let mut c = at(1.0);
        c.command(None, 0.010, q(1.0)); // 1.002 -> 1.012: 0 -> 1
        assert!((c.update(1.004)[0] - 0.2).abs() < 1e-9, "linear: a fifth of the way");
        // The next message starts where the trajectory is at the next update (1.006: 0.4).
        c.command(None, 0.010, q(2.0)); // 1.006 -> 1.016: 0.4 -> 2
        assert!((c.update(1.006)[0] - 0.4).abs() < 1e-9, "continuous at the bridge");
        assert!((c.update(1.011)[0] - 1.2).abs() < 1e-9, "half way from 0.4 to 2");
        assert!(
            (c.update(1.020)[0] - 2.0).abs() < 1e-12,
            "held at the point after it is due"
        );
    }

    #[test]
    fn a_stamp_ahead_of_the_next_update_keeps_the_current_trajectory_until_it() {
        let mut c = at(1.0);
        c.command(None, 0.010, q(1.0)); // 1.002 -> 1.012
                                        // Stamped 1.007 (the controller's clock ahead of the driver's): the old segment runs
                                        // until 1.007 (0.5), then the bridge to 3 at 1.017.
        c.command(Some(1.007), 0.010, q(3.0));
        assert!((c.update(1.004)[0] - 0.2).abs() < 1e-9, "the old segment still");
        assert!((c.update(1.007)[0] - 0.5).abs() < 1e-9);
        assert!((c.update(1.012)[0] - 1.75).abs() < 1e-9, "half way from 0.5 to 3");
        assert_eq!(c.counts().dropped, 0);
    }

    #[test]
    fn a_moving_message_after_the_trajectory_ended_at_the_last_update_is_late() {
        let mut c = at(1.0);
        c.command(None, 0.004, q(1.0)); // 1.002 -> 1.006
        c.update(1.002);
        c.update(1.004);
        c.command(None, 0.004, q(2.0)); // the trajectory runs until 1.006: not late
        c.update(1.006);
        c.update(1.008);
        c.update(1.010); // ended at 1.010 (1.006 -> 1.010)
        c.command(None, 0.004, q(3.0)); // late: held at 2 at the last update
        c.command(None, 0.004, q(3.0)); // the same positions: not moving, never late
        let n = c.counts();
        assert_eq!((n.moving, n.late, n.dropped), (3, 1, 0));
    }

    #[test]
    fn the_drivers_controller_file_names_the_joints_and_the_topic_the_stack_uses() {
        // config/lbr_fri_ros_controllers.yaml, what a lab loads on the driver: a position
        // JointTrajectoryController on the driver's joints, whose command topic is the one the
        // docking controller publishes to and the simulator reads.
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        let read = |f: &str| -> serde_yaml_ng::Value {
            serde_yaml_ng::from_str(&std::fs::read_to_string(dir.join(f)).unwrap()).unwrap()
        };
        let drv = read("lbr_fri_ros_controllers.yaml");
        let (name, jtc) = drv
            .as_mapping()
            .unwrap()
            .iter()
            .find(|(_, v)| v["type"] == "position_controllers/JointTrajectoryController")
            .expect("a position JointTrajectoryController");
        let joints: Vec<String> = serde_yaml_ng::from_value(jtc["joints"].clone()).unwrap();
        assert_eq!(joints, crate::kinematics::joint_names());
        let sim = read("lbr_med_sim.yaml");
        let sim_joints: Vec<String> = serde_yaml_ng::from_value(sim["joint_names"].clone()).unwrap();
        assert_eq!(joints, sim_joints);
        let topic = format!("/lbr/{}/command", name.as_str().unwrap());
        assert_eq!(read("docking_controller.yaml")["command_topic"], topic.as_str());
        assert_eq!(sim["command_topic"], topic.as_str());
        assert_eq!(
            drv["joint_state_controller"]["type"],
            "joint_state_controller/JointStateController"
        );
    }

    #[test]
    fn a_long_stream_stamped_ahead_stays_within_its_knots_and_a_position_command_holds() {
        let mut c = at(0.0);
        // Stamped 0.5 s in the driver's future, one a millisecond: the knots stay bounded.
        for k in 0..1000 {
            let t = f64::from(k) * 1e-3;
            if k % 2 == 0 {
                c.update(t);
            }
            c.command(Some(t + 0.5), 0.002, q(t));
        }
        assert!(c.len <= KNOTS);
        assert_eq!(c.counts().dropped, 0);
        c.set_position(q(-1.0));
        assert_eq!(c.update(1.0), q(-1.0));
    }
}
