//! The audit of a published command stream against the guard's own limits: each joint's
//! speed (`velocity_scale` of the datasheet's) and acceleration
//! (`guard.max_acceleration_rad_s2`), holds included. What the tests run over every command
//! a controller publishes, in simulated time and from ROS topics.
//!
//! Each pair of consecutive commands is timed as the command guard times its steps
//! ([`crate::control::safety::guarded`]): the clock's advance, at most the nominal period;
//! a clock that did not advance or jumped (back, or forward by more than
//! `max_clock_jump_s`) counts the loop's own pace, the period. A stream starts at rest.
//! Where the listener knows it missed commands (a ROS subscription's sequence numbers),
//! [`CommandAudit::resync`] takes the next one without judging the pair it cannot see.

use crate::control::safety::guard::GuardParams;
use crate::kinematics::{JointLimits, JointVector};

/// Shares of the limits within which an audit passes (rounding only).
pub const AUDIT_TOLERANCE: f64 = 1e-6;

/// The running audit of one command stream.
#[derive(Debug, Clone, Copy)]
pub struct CommandAudit {
    vmax: JointVector,
    amax: f64,
    period: f64,
    max_jump: f64,
    last: Option<(f64, JointVector)>,
    /// The velocity of the last pair (`None`: unknown after a resync), rad/s.
    velocity: Option<JointVector>,
    /// Commands seen.
    pub count: usize,
    /// The largest joint speed over the stream, as a share of that joint's limit.
    pub worst_speed: f64,
    /// The largest joint acceleration over the stream, as a share of the limit.
    pub worst_accel: f64,
    /// The time of the command where the larger of the two shares peaked, s.
    pub worst_at: f64,
}

impl CommandAudit {
    /// An audit for the guard `g` on an arm of `limits`, commands every `period` s.
    pub fn new(g: &GuardParams, limits: &JointLimits, period: f64) -> Self {
        Self {
            vmax: limits.velocity * g.velocity_scale,
            amax: g.max_acceleration_rad_s2,
            period,
            max_jump: g.max_clock_jump_s,
            last: None,
            velocity: Some(JointVector::zeros()),
            count: 0,
            worst_speed: 0.0,
            worst_accel: 0.0,
            worst_at: f64::NAN,
        }
    }

    /// The command `q` published at `t` (the loop's clock), s.
    pub fn add(&mut self, t: f64, q: &JointVector) {
        self.count += 1;
        if let Some((t0, q0)) = self.last {
            let d = t - t0;
            let dt = if d > 0.0 && d <= self.max_jump {
                d.min(self.period)
            } else {
                self.period
            };
            let v = (q - q0) / dt;
            let speed = (0..v.len()).map(|i| v[i].abs() / self.vmax[i]).fold(0.0, f64::max);
            let accel = self.velocity.map_or(0.0, |v0| (v - v0).amax() / (self.amax * dt));
            if speed.max(accel) > self.worst_speed.max(self.worst_accel) {
                self.worst_at = t;
            }
            self.worst_speed = self.worst_speed.max(speed);
            self.worst_accel = self.worst_accel.max(accel);
            self.velocity = Some(v);
        }
        self.last = Some((t, *q));
    }

    /// No command this step (nothing published, IDLE): the next one starts from rest.
    pub fn gap(&mut self) {
        self.last = None;
        self.velocity = Some(JointVector::zeros());
    }

    /// The command `q` at `t` after commands the listener missed: counted, the pair before
    /// it not judged (its time and velocity are unknown), the acceleration judged again
    /// from the pair after it.
    pub fn resync(&mut self, t: f64, q: &JointVector) {
        self.count += 1;
        self.last = Some((t, *q));
        self.velocity = None;
    }

    /// The verdict: a line with both shares, an error where one is over its limit.
    pub fn verdict(&self) -> Result<String, String> {
        let line = format!(
            "{} commands, fastest joint at {:.0} % of the guard's speed limit, {:.0} % of its acceleration limit ({} rad/s^2)",
            self.count,
            self.worst_speed * 100.0,
            self.worst_accel * 100.0,
            self.amax
        );
        if self.worst_speed > 1.0 + AUDIT_TOLERANCE || self.worst_accel > 1.0 + AUDIT_TOLERANCE {
            Err(format!("{line}: over the limit at t = {:.3} s", self.worst_at))
        } else {
            Ok(line)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::lbr::LbrModel;

    /// The audit measures what it claims: a joint at its whole speed limit is 100 %, a
    /// stop from it in one step is far over the acceleration limit, a ramp at the limit
    /// is 100 %.
    #[test]
    fn the_audit_measures_speed_and_acceleration_shares() {
        let g = GuardParams::default();
        let limits = JointLimits::of_model(LbrModel::Med7);
        let vmax = limits.velocity[1] * g.velocity_scale;
        let a = g.max_acceleration_rad_s2;
        let mut audit = CommandAudit::new(&g, &limits, 0.01);
        // A ramp at the acceleration limit up to the speed limit, then cruising.
        let mut q = JointVector::zeros();
        let mut v = 0.0f64;
        audit.add(-0.01, &q);
        for k in 0..100 {
            v = (v + a * 0.01).min(vmax);
            q[1] += v * 0.01;
            audit.add(f64::from(k) * 0.01, &q);
        }
        assert!((audit.worst_speed - 1.0).abs() < 1e-9, "{}", audit.worst_speed);
        assert!((audit.worst_accel - 1.0).abs() < 1e-9, "{}", audit.worst_accel);
        assert!(audit.verdict().is_ok());
        // Then standing still at once.
        audit.add(1.0, &q);
        assert!(audit.worst_accel > 10.0, "{}", audit.worst_accel);
        let e = audit.verdict().unwrap_err();
        assert!(e.contains("over the limit at t = 1.000"), "{e}");
        // After missed commands the pair across the gap is not judged, the next one is.
        let mut audit = CommandAudit::new(&g, &limits, 0.01);
        let mut q = JointVector::zeros();
        audit.add(0.0, &q);
        q[1] += 1.0;
        audit.resync(0.05, &q);
        assert_eq!((audit.count, audit.worst_speed, audit.worst_accel), (2, 0.0, 0.0));
        q[1] += vmax * 0.01;
        audit.add(0.06, &q);
        assert!((audit.worst_speed - 1.0).abs() < 1e-9, "{}", audit.worst_speed);
        assert_eq!(audit.worst_accel, 0.0);
        audit.add(0.07, &q);
        assert!(audit.worst_accel > 10.0, "{}", audit.worst_accel);
    }
}
