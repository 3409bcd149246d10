//! How the simulated arm takes a streamed trajectory, as a `joint_trajectory_controller`
//! does: each new point replaces the rest of the trajectory; the setpoint moves from where
//! it is when the point arrives to the point's positions, reaching them when the point is
//! due (`header.stamp + time_from_start`), and stays there if no newer point comes. A point
//! that moves the arm and arrives after the previous one was due finds the arm stopped: it
//! is **late**, and [`TrajectoryFollower`] counts it (the stop-and-go a too short
//! `time_from_start` gives).
//! Pure and allocation-free; `lbr_med_sim` drives it every physics step.

use crate::kinematics::JointVector;

/// The setpoint of a streamed one-point trajectory, and how many points came late.
#[derive(Debug, Clone)]
pub struct TrajectoryFollower {
    from: JointVector,
    to: JointVector,
    t_from: f64,
    t_to: f64,
    points: u64,
    moving: u64,
    late: u64,
}

impl TrajectoryFollower {
    /// Holding `q` until the first point.
    pub fn new(q: JointVector) -> Self {
        Self {
            from: q,
            to: q,
            t_from: f64::NEG_INFINITY,
            t_to: f64::NEG_INFINITY,
            points: 0,
            moving: 0,
            late: 0,
        }
    }

    /// The setpoint at time `t`, s.
    pub fn setpoint(&self, t: f64) -> JointVector {
        let span = self.t_to - self.t_from;
        if span.is_nan() || span <= 0.0 || t >= self.t_to {
            return self.to;
        }
        let s = ((t - self.t_from) / span).clamp(0.0, 1.0);
        self.from + (self.to - self.from) * s
    }

    /// A point with positions `q` due at `due` arrived at `now` (both s, one clock). A
    /// point due in the past is reached at once.
    pub fn push(&mut self, now: f64, q: JointVector, due: f64) {
        if self.points > 0 && q != self.to {
            self.moving += 1;
            if now > self.t_to {
                self.late += 1;
            }
        }
        self.from = self.setpoint(now);
        self.t_from = now;
        self.to = q;
        self.t_to = if due.is_finite() { due.max(now) } else { now };
        self.points += 1;
    }

    /// Points received.
    pub fn points(&self) -> u64 {
        self.points
    }

    /// Points (after the first) that moved the setpoint.
    pub fn moving(&self) -> u64 {
        self.moving
    }

    /// Moving points that arrived after the previous one was due (the arm had stopped).
    pub fn late(&self) -> u64 {
        self.late
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_are_reached_when_due_and_a_late_one_is_counted() {
        let q = |x: f64| JointVector::from_element(x);
        let mut f = TrajectoryFollower::new(q(0.0));
        assert_eq!(f.setpoint(5.0), q(0.0));
        // Due 30 ms ahead, streamed every 10 ms: always moving, never late.
        f.push(1.000, q(0.3), 1.030);
        assert!((f.setpoint(1.015)[0] - 0.15).abs() < 1e-12, "half way");
        f.push(1.010, q(0.4), 1.040);
        assert!(
            (f.setpoint(1.010)[0] - 0.1).abs() < 1e-12,
            "starts where the setpoint was"
        );
        assert_eq!(f.late(), 0);
        // Due 10 ms ahead and 2 ms late: the arm had stopped at the point.
        f.push(1.020, q(0.5), 1.030);
        f.push(1.032, q(0.6), 1.042);
        assert_eq!(f.setpoint(1.032), q(0.5), "stopped at the last point");
        assert_eq!((f.points(), f.moving(), f.late()), (4, 3, 1));
        // The same point again (holding still) is never late.
        f.push(1.1, q(0.6), 1.11);
        assert_eq!((f.moving(), f.late()), (3, 1));
        assert_eq!(f.setpoint(1.5), q(0.6), "stays at the last point");
        // A point due in the past (or with no due time) is reached at once.
        f.push(2.0, q(0.7), 1.0);
        assert_eq!(f.setpoint(2.0), q(0.7));
        f.push(2.1, q(0.8), f64::NAN);
        assert_eq!(f.setpoint(2.1), q(0.8));
    }
}
