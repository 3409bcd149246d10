//! The safety guard: every command is checked before it leaves, and the inputs are checked
//! before the controller uses them. Each decision carries a reason.
//!
//! A command passes only if it is finite, inside the joint position limits less a margin,
//! and within the per-step velocity limit from the previous command. Otherwise the guard
//! answers with a hold at the previous command (a hold never moves the arm). Stale joint
//! state, a stale or missing trocar pose, and a tip force over the threshold are reasons to
//! hold as well. [`crate::control::safety::guarded::Guarded`] puts the command check around any command
//! source, so that nothing is published unchecked.

use serde::{Deserialize, Serialize};

pub use crate::control::safety::hold::HoldReason;
use crate::kinematics::{JointLimits, JointVector};

/// The share of `max_command_lead_rad` from which the command counts as waiting for the arm
/// (the not-following watch of [`crate::control::safety::guarded`] runs from there).
pub const LEAD_WATCH_FRACTION: f64 = 0.25;

/// Parameters of the guard.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct GuardParams {
    /// Margin inside each position limit, rad.
    pub position_margin_rad: f64,
    /// Fraction of each joint's velocity limit the controller may use (0..1].
    pub velocity_scale: f64,
    /// Tip force that stops the docking, N.
    pub force_stop_n: f64,
    /// Joint state older than this holds, s.
    pub joint_timeout_s: f64,
    /// Trocar pose older than this holds, s.
    pub trocar_timeout_s: f64,
    /// External torques older than this hold (only with force feedback on), s.
    pub torque_timeout_s: f64,
    /// Hold while a measured joint is further than this from the last command, rad. The
    /// commands advance from the last command (not the measurement), so without this check
    /// an arm that stopped following would, on resuming, chase a command far ahead of it.
    pub max_tracking_error_rad: f64,
    /// The command never leads the measured joints by more than this on any joint, rad (the
    /// step box is cut to it, in every phase): on a blocked arm the command waits instead of
    /// winding up.
    pub max_command_lead_rad: f64,
    /// Hold (latched, `ARM_NOT_FOLLOWING`, where the arm is) once the command has sat on its
    /// lead bound this long with the arm not moving on that joint, s.
    pub follow_timeout_s: f64,
    /// A step whose clock advanced by more than this is a clock jump (or a stalled loop):
    /// hold, latched (`CLOCK_FORWARD`), s. Any step back in time holds too (`CLOCK_BACK`).
    pub max_clock_jump_s: f64,
}

crate::shipped_defaults!(GuardParams, crate::config::CONTROLLER, ["guard"]);

impl GuardParams {
    /// Check ranges; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        let check = |n: &str, v: f64, lo: f64, hi: f64| {
            if v.is_finite() && v > lo && v <= hi {
                Ok(())
            } else {
                Err(format!("guard.{n} must be in ({lo}, {hi}], got {v}"))
            }
        };
        check("position_margin_rad", self.position_margin_rad + 1e-12, 0.0, 0.5)?;
        check("velocity_scale", self.velocity_scale, 0.0, 1.0)?;
        check("force_stop_n", self.force_stop_n, 0.0, 200.0)?;
        check("joint_timeout_s", self.joint_timeout_s, 0.0, 10.0)?;
        check("trocar_timeout_s", self.trocar_timeout_s, 0.0, 60.0)?;
        check("torque_timeout_s", self.torque_timeout_s, 0.0, 10.0)?;
        check("max_tracking_error_rad", self.max_tracking_error_rad, 0.0, 1.0)?;
        check("max_command_lead_rad", self.max_command_lead_rad, 0.0, 0.5)?;
        check("follow_timeout_s", self.follow_timeout_s, 0.0, 10.0)?;
        check("max_clock_jump_s", self.max_clock_jump_s, 0.0, 60.0)
    }
}

/// The command guard for one arm.
#[derive(Debug, Clone)]
pub struct CommandGuard {
    params: GuardParams,
    lower: JointVector,
    upper: JointVector,
    vmax: JointVector,
    /// The measured joints of this step, when known: commands stay within
    /// `max_command_lead_rad` of them.
    measured: Option<JointVector>,
}

impl CommandGuard {
    /// A guard for `limits`.
    pub fn new(params: GuardParams, limits: &JointLimits) -> Self {
        let m = params.position_margin_rad;
        let lower = limits.lower.map(|l| l + m);
        let upper = limits.upper.map(|u| u - m);
        let vmax = limits.velocity * params.velocity_scale;
        Self {
            params,
            lower,
            upper,
            vmax,
            measured: None,
        }
    }

    /// The measured joints of the coming step (`None`: unknown or not finite); the step box
    /// and the command check then keep the command within `max_command_lead_rad` of them.
    pub fn set_measured(&mut self, measured: Option<JointVector>) {
        self.measured = measured.filter(|q| q.iter().all(|x| x.is_finite()));
    }

    /// The measured joints the lead bound applies to, if any.
    pub fn measured(&self) -> Option<&JointVector> {
        self.measured.as_ref()
    }

    /// The joint whose command `cmd` leads the measured joints by [`LEAD_WATCH_FRACTION`] of
    /// the lead bound or more, with its lead (`cmd - measured`), if any. Not the bound itself:
    /// the motion limits ([`crate::control::safety::motion`]) brake the command as it nears the bound, so a
    /// blocked arm's command creeps towards it without ever sitting on it.
    pub fn lead_saturated(&self, cmd: &JointVector) -> Option<(usize, f64)> {
        let q = self.measured.as_ref()?;
        let bound = self.params.max_command_lead_rad * LEAD_WATCH_FRACTION;
        (0..cmd.len())
            .map(|i| (i, cmd[i] - q[i]))
            .find(|(_, lead)| lead.abs() >= bound)
    }

    /// The parameters.
    pub fn params(&self) -> &GuardParams {
        &self.params
    }
    /// Lower position bounds with the margin, rad.
    pub fn lower(&self) -> &JointVector {
        &self.lower
    }
    /// Upper position bounds with the margin, rad.
    pub fn upper(&self) -> &JointVector {
        &self.upper
    }
    /// Usable velocity per joint, rad/s.
    pub fn max_velocity(&self) -> &JointVector {
        &self.vmax
    }

    /// The box a command for a step of `dt` from `prev` must lie in: the position limits
    /// (with margin) intersected with the velocity limit and, when the measured joints are
    /// known, with `max_command_lead_rad` around them. When `prev` is itself outside these
    /// bounds, the box still contains `prev`'s nearest feasible motion, never a jump.
    pub fn step_box(&self, prev: &JointVector, dt: f64) -> (JointVector, JointVector) {
        let mut lo = JointVector::zeros();
        let mut hi = JointVector::zeros();
        for i in 0..prev.len() {
            let dq = self.vmax[i] * dt;
            let (lead_lo, lead_hi) = self.lead_bounds(i);
            // Moving back towards the feasible range is always allowed; never a jump.
            let l = self.lower[i].max(prev[i] - dq).max(lead_lo).min(prev[i]);
            let h = self.upper[i].min(prev[i] + dq).min(lead_hi).max(prev[i]);
            lo[i] = l;
            hi[i] = h;
        }
        (lo, hi)
    }

    /// The lead bounds of joint `i` (infinite without measured joints).
    fn lead_bounds(&self, i: usize) -> (f64, f64) {
        let lead = self.params.max_command_lead_rad;
        self.measured
            .as_ref()
            .map_or((f64::NEG_INFINITY, f64::INFINITY), |q| (q[i] - lead, q[i] + lead))
    }

    /// Check `cmd` as the next command after `prev`, `dt` seconds later.
    pub fn check_command(&self, cmd: &JointVector, prev: &JointVector, dt: f64) -> Result<(), HoldReason> {
        if !cmd.iter().all(|x| x.is_finite()) {
            return Err(HoldReason::NonFiniteCommand);
        }
        let tol = 1e-9;
        for i in 0..cmd.len() {
            let step = cmd[i] - prev[i];
            if step.abs() > self.vmax[i] * dt + tol {
                return Err(HoldReason::VelocityLimit { joint: i });
            }
            // Outside the limits only if it moves further out.
            if (cmd[i] > self.upper[i] + tol && step > 0.0) || (cmd[i] < self.lower[i] - tol && step < 0.0) {
                return Err(HoldReason::PositionLimit { joint: i });
            }
            // Further ahead of the measured joints than the lead bound, moving further out.
            let (lead_lo, lead_hi) = self.lead_bounds(i);
            if (cmd[i] > lead_hi + tol && step > 0.0) || (cmd[i] < lead_lo - tol && step < 0.0) {
                let lead = self.measured.map_or(0.0, |q| cmd[i] - q[i]);
                return Err(HoldReason::ArmNotFollowing { joint: i, lead });
            }
        }
        Ok(())
    }

    /// Hold if the measured joints are further than `max_tracking_error_rad` from the last
    /// command (NaN counts as too far).
    pub fn check_tracking(&self, measured: &JointVector, commanded: &JointVector) -> Result<(), HoldReason> {
        for i in 0..measured.len() {
            let error = (measured[i] - commanded[i]).abs();
            if error.is_nan() || error > self.params.max_tracking_error_rad {
                return Err(HoldReason::TrackingError { joint: i, error });
            }
        }
        Ok(())
    }

    /// A new force stop (live tuning, [`crate::control::live`]; checked there), N.
    pub fn set_force_stop(&mut self, force_stop: f64) {
        self.params.force_stop_n = force_stop;
    }

    /// Hold if the force norm is over the stop threshold.
    pub fn check_force(&self, force: f64) -> Result<(), HoldReason> {
        if force.is_finite() && force <= self.params.force_stop_n {
            Ok(())
        } else {
            Err(HoldReason::ForceLimit {
                force,
                limit: self.params.force_stop_n,
            })
        }
    }

    /// Whether data of `age` seconds is fresh for `timeout` (data from the future by more
    /// than the timeout is a clock fault, not fresh).
    pub fn fresh(age: f64, timeout: f64) -> bool {
        age.is_finite() && age <= timeout && age >= -timeout
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::lbr::LbrModel;
    use proptest::prelude::*;

    fn guard() -> CommandGuard {
        CommandGuard::new(GuardParams::default(), &JointLimits::of_model(LbrModel::Med7))
    }

    proptest! {
        #[test]
        fn step_box_is_safe(prev in proptest::collection::vec(-3.5f64..3.5, 7), dt in 0.0005f64..0.05) {
            let g = guard();
            let prev = JointVector::from_column_slice(&prev);
            let (lo, hi) = g.step_box(&prev, dt);
            for i in 0..7 {
                prop_assert!(lo[i] <= hi[i]);
                prop_assert!(lo[i] <= prev[i] && prev[i] <= hi[i]);
                prop_assert!(hi[i] - prev[i] <= g.max_velocity()[i] * dt + 1e-12);
                prop_assert!(prev[i] - lo[i] <= g.max_velocity()[i] * dt + 1e-12);
            }
            // Any point of the box passes the check.
            prop_assert!(g.check_command(&lo, &prev, dt).is_ok());
            prop_assert!(g.check_command(&hi, &prev, dt).is_ok());
        }
    }

    #[test]
    fn tracking_error_over_the_tolerance_holds() {
        let g = guard();
        let cmd = JointVector::zeros();
        let mut q = cmd;
        q[3] = g.params().max_tracking_error_rad * 0.9;
        assert!(g.check_tracking(&q, &cmd).is_ok());
        q[3] = -g.params().max_tracking_error_rad * 1.1;
        assert!(matches!(
            g.check_tracking(&q, &cmd),
            Err(HoldReason::TrackingError { joint: 3, .. })
        ));
        q[3] = f64::NAN;
        assert!(g.check_tracking(&q, &cmd).is_err());
    }

    #[test]
    fn rejects_bad_commands() {
        let g = guard();
        let prev = JointVector::zeros();
        let mut c = prev;
        c[2] = f64::NAN;
        assert_eq!(g.check_command(&c, &prev, 0.01), Err(HoldReason::NonFiniteCommand));
        let mut c = prev;
        c[1] = 0.5;
        assert_eq!(
            g.check_command(&c, &prev, 0.01),
            Err(HoldReason::VelocityLimit { joint: 1 })
        );
        let mut p = prev;
        p[0] = g.upper()[0];
        let mut c = p;
        c[0] += 0.001;
        assert_eq!(
            g.check_command(&c, &p, 0.01),
            Err(HoldReason::PositionLimit { joint: 0 })
        );
        assert!(g.check_force(19.0).is_ok());
        assert!(matches!(g.check_force(21.0), Err(HoldReason::ForceLimit { .. })));
        assert!(g.check_force(f64::NAN).is_err());
        assert!(
            CommandGuard::fresh(0.05, 0.1) && !CommandGuard::fresh(0.2, 0.1) && !CommandGuard::fresh(f64::NAN, 0.1)
        );
        assert!(GuardParams {
            velocity_scale: 1.5,
            ..Default::default()
        }
        .validate()
        .is_err());
        assert!(HoldReason::StaleTrocarPose { age: 0.7 }.to_string().contains("marker"));
    }
}
