//! The safety guard: every command is checked before it leaves, and the inputs are checked
//! before the controller uses them. Each decision carries a reason.
//!
//! A command passes only if it is finite and inside the step box from the previous command
//! ([`CommandGuard::step_box`]): the joint position limits less a margin, each joint's speed
//! limit (`velocity_scale` of the datasheet's), its acceleration limit
//! (`max_acceleration_rad_s2`) from the velocity of the last published command, a speed
//! from which the joint can still brake before its position limit and before the lead
//! bound around the measured joints, and that lead bound. Otherwise the guard answers with a hold that brakes to a stop
//! within the same limits ([`CommandGuard::walk`]: never an instant stop from speed). Stale
//! joint state, a stale or missing trocar pose, and a tip force over the threshold are
//! reasons to hold as well. [`crate::control::safety::guarded::Guarded`] puts the command
//! check around any command source, so that nothing is published unchecked; the hand-eye
//! node's `~auto` motion goes through the same guard.
//!
//! **Acceleration.** KUKA's LBR Med datasheets give joint speeds, not accelerations; the
//! driver stack's MoveIt configuration for the Med 7 gives `max_acceleration: 10.0` rad/s²
//! on every joint (lbr-stack/lbr_fri_ros2_stack,
//! `lbr_moveit_config/med7_moveit_config/config/joint_limits.yaml`; the Med 14's file sets
//! none). The shipped limit is half of it, as `velocity_scale` halves the speeds.
//!
//! **Braking in discrete steps.** A joint at speed `v` that slows by `a dt` each step of
//! `dt` covers `dt (v + (v - a dt) + ...)`; the largest speed that stops within a distance
//! `d` is therefore `a dt (sqrt(1/4 + 2 d / (a dt²)) - 1/2)` ([`braking_speed`]), used for
//! both the position limits and a hold's walk to its target.

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
    /// Largest joint acceleration of any published command, every joint, rad/s².
    pub max_acceleration_rad_s2: f64,
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
        check("max_acceleration_rad_s2", self.max_acceleration_rad_s2, 0.0, 10.0)?;
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
    /// The velocity of the last published command, rad/s: the next one's acceleration is
    /// judged from it.
    velocity: JointVector,
    /// The measured joints of this step, when known: commands stay within
    /// `max_command_lead_rad` of them.
    measured: Option<JointVector>,
}

/// The largest speed from which a joint slowing by `accel dt` each step of `dt` stops
/// within `distance` (see the module doc), rad/s; at most `accel dt` short of the exact
/// discrete figure, so that the last step never overshoots. Infinite for `dt <= 0`.
pub fn braking_speed(distance: f64, accel: f64, dt: f64) -> f64 {
    if dt <= 0.0 {
        return f64::INFINITY;
    }
    let u = accel * dt;
    // The discrete sum overshoots its continuous root by at most u dt / 8.
    let d = (distance - u * dt / 8.0).max(0.0);
    u * ((0.25 + 2.0 * d / (u * dt)).sqrt() - 0.5)
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
            velocity: JointVector::zeros(),
            measured: None,
        }
    }

    /// The velocity of the last published command (rad/s; zero when none moved): the step
    /// box and the check keep the next command within the acceleration limit of it.
    pub fn set_velocity(&mut self, velocity: JointVector) {
        self.velocity = velocity.map(|v| if v.is_finite() { v } else { 0.0 });
    }

    /// The velocity of the last published command, rad/s.
    pub fn velocity(&self) -> &JointVector {
        &self.velocity
    }

    /// Usable acceleration of every joint, rad/s².
    pub fn max_acceleration(&self) -> f64 {
        self.params.max_acceleration_rad_s2
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

    /// The box a command for a step of `dt` from `prev` must lie in: per joint, the speeds
    /// within the speed limit, within the braking speed to the position limits (with
    /// margin) and within the acceleration limit of the last published velocity, and, when
    /// the measured joints are known, within `max_command_lead_rad` around them. Where the
    /// acceleration limit and a bound disagree (a joint already outside a bound, or braking
    /// from speed), the acceleration limit wins: the box is its point nearest the bound, so
    /// every command of the box is within the acceleration limit, never a jump. Moving back
    /// towards a bound the joint is outside of is always allowed. `dt <= 0`: `prev` only.
    pub fn step_box(&self, prev: &JointVector, dt: f64) -> (JointVector, JointVector) {
        let mut lo = *prev;
        let mut hi = *prev;
        if dt <= 0.0 {
            return (lo, hi);
        }
        let a = self.params.max_acceleration_rad_s2;
        for i in 0..prev.len() {
            let (u, v) = (a * dt, self.velocity[i]);
            let (up, down) = self.brakeable_speeds(i, prev[i], dt);
            let (vl, vh) = nearest_interval((-down, up), (v - u, v + u));
            let (l, h) = (prev[i] + vl * dt, prev[i] + vh * dt);
            let (lead_lo, lead_hi) = self.lead_bounds(i);
            (lo[i], hi[i]) = nearest_interval((lead_lo.min(prev[i]), lead_hi.max(prev[i])), (l, h));
        }
        (lo, hi)
    }

    /// One step from `prev` towards `to` within the step box: each joint at the speed that
    /// stops on `to` ([`braking_speed`], the speed limit), as near as the acceleration
    /// limit allows; on `to` once within reach and at rest there. With `to == prev` a
    /// moving joint brakes to a stop (beyond `prev`, by its braking distance).
    pub fn walk(&self, prev: &JointVector, to: &JointVector, dt: f64) -> JointVector {
        if dt <= 0.0 {
            return *prev;
        }
        let a = self.params.max_acceleration_rad_s2;
        let (lo, hi) = self.step_box(prev, dt);
        JointVector::from_fn(|i, _| {
            let d = to[i] - prev[i];
            // Within one step of acceleration of rest, a joint may land on the target.
            let speed = self.vmax[i]
                .min(d.abs() / dt)
                .min(braking_speed(d.abs(), a, dt).max(a * dt));
            (prev[i] + d.signum() * speed * dt).clamp(lo[i], hi[i])
        })
    }

    /// The largest speeds of joint `i` at `prev` up and down: within the speed limit, and
    /// slow enough to brake within the acceleration limit before the position limit (with
    /// margin) and before the lead bound around the measured joints (an arm that stops
    /// dead never finds the command more than `max_command_lead_rad` ahead of it).
    fn brakeable_speeds(&self, i: usize, prev: f64, dt: f64) -> (f64, f64) {
        let a = self.params.max_acceleration_rad_s2;
        let (lead_lo, lead_hi) = self.lead_bounds(i);
        let up = self.vmax[i]
            .min(braking_speed(self.upper[i] - prev, a, dt))
            .min(braking_speed(lead_hi - prev, a, dt));
        let down = self.vmax[i]
            .min(braking_speed(prev - self.lower[i], a, dt))
            .min(braking_speed(prev - lead_lo, a, dt));
        (up.max(0.0), down.max(0.0))
    }

    /// The lead bounds of joint `i` (infinite without measured joints).
    fn lead_bounds(&self, i: usize) -> (f64, f64) {
        let lead = self.params.max_command_lead_rad;
        self.measured
            .as_ref()
            .map_or((f64::NEG_INFINITY, f64::INFINITY), |q| (q[i] - lead, q[i] + lead))
    }

    /// The command a publisher outside the controller (the hand-eye node's `~auto`) sends
    /// after `prev` for the wanted `want`, `dt` later: `want` where it passes the check, the
    /// walk towards it otherwise; the guard's velocity follows the command sent.
    pub fn follow(&mut self, prev: &JointVector, want: &JointVector, dt: f64) -> JointVector {
        let q = if self.check_command(want, prev, dt).is_ok() {
            *want
        } else {
            self.walk(prev, want, dt)
        };
        if dt > 0.0 {
            self.set_velocity((q - prev) / dt);
        }
        q
    }

    /// Check `cmd` as the next command after `prev`, `dt` seconds later: finite and inside
    /// [`Self::step_box`]; the reason names the first bound it breaks.
    pub fn check_command(&self, cmd: &JointVector, prev: &JointVector, dt: f64) -> Result<(), HoldReason> {
        if !cmd.iter().all(|x| x.is_finite()) {
            return Err(HoldReason::NonFiniteCommand);
        }
        let tol = 1e-9;
        let (lo, hi) = self.step_box(prev, dt);
        for i in 0..cmd.len() {
            if cmd[i] >= lo[i] - tol && cmd[i] <= hi[i] + tol {
                continue;
            }
            let step = cmd[i] - prev[i];
            if dt <= 0.0 || step.abs() > self.vmax[i] * dt + tol {
                return Err(HoldReason::VelocityLimit { joint: i });
            }
            // Outside the limits only if it moves further out.
            if (cmd[i] > self.upper[i] + tol && step > 0.0) || (cmd[i] < self.lower[i] - tol && step < 0.0) {
                return Err(HoldReason::PositionLimit { joint: i });
            }
            let (lead_lo, lead_hi) = self.lead_bounds(i);
            if (cmd[i] > lead_hi + tol && step > 0.0) || (cmd[i] < lead_lo - tol && step < 0.0) {
                let lead = self.measured.map_or(0.0, |q| cmd[i] - q[i]);
                return Err(HoldReason::ArmNotFollowing { joint: i, lead });
            }
            if (step / dt - self.velocity[i]).abs() > self.params.max_acceleration_rad_s2 * dt + tol / dt {
                return Err(HoldReason::AccelerationLimit { joint: i });
            }
            // Too fast to brake before the lead bound, or else before the position limit.
            let brake = |d: f64| braking_speed(d, self.params.max_acceleration_rad_s2, dt) * dt + tol;
            if (step > 0.0 && step > brake(lead_hi - prev[i])) || (step < 0.0 && -step > brake(prev[i] - lead_lo)) {
                let lead = self.measured.map_or(0.0, |q| cmd[i] - q[i]);
                return Err(HoldReason::ArmNotFollowing { joint: i, lead });
            }
            return Err(HoldReason::PositionLimit { joint: i });
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

/// `inner` cut to `outer`; where they do not meet, the point of `outer` nearest `inner`.
fn nearest_interval(inner: (f64, f64), outer: (f64, f64)) -> (f64, f64) {
    let (l, h) = (inner.0.max(outer.0), inner.1.min(outer.1));
    if l <= h {
        (l, h)
    } else if outer.1 < inner.0 {
        (outer.1, outer.1)
    } else {
        (outer.0, outer.0)
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

    /// Walk `g` from `from` (at rest) towards `to` for `steps` steps of `dt`, the guard's
    /// velocity kept as a publisher keeps it; every published command.
    fn walk_all(g: &mut CommandGuard, from: JointVector, to: JointVector, dt: f64, steps: usize) -> Vec<JointVector> {
        let mut q = from;
        let mut out = vec![q];
        for _ in 0..steps {
            let next = g.walk(&q, &to, dt);
            g.set_velocity((next - q) / dt);
            q = next;
            out.push(q);
        }
        out
    }

    /// The largest speed and acceleration of a command stream of period `dt`, as shares of
    /// the guard's limits (starting and ending at rest).
    fn worst_shares(g: &CommandGuard, qs: &[JointVector], dt: f64) -> (f64, f64) {
        let v: Vec<JointVector> = qs.windows(2).map(|w| (w[1] - w[0]) / dt).collect();
        let speed = v
            .iter()
            .flat_map(|v| (0..7).map(move |i| v[i].abs() / g.max_velocity()[i]))
            .fold(0.0, f64::max);
        let rest = [JointVector::zeros()];
        let with_rest: Vec<&JointVector> = rest.iter().chain(v.iter()).collect();
        let accel = with_rest
            .windows(2)
            .flat_map(|w| (0..7).map(move |i| (w[1][i] - w[0][i]).abs() / dt))
            .fold(0.0, f64::max)
            / g.max_acceleration();
        (speed, accel)
    }

    /// An arm that stops dead never finds a command walking away from it more than the lead
    /// bound ahead, within the acceleration limit: the walk slows to the braking speed of
    /// what is left of the bound, from rest and from speed alike.
    #[test]
    fn the_command_brakes_before_the_lead_bound_of_a_stopped_arm() {
        let dt = 0.01;
        let bound = GuardParams::default().max_command_lead_rad;
        for v0 in [0.0f64, 0.3, 0.8] {
            let mut g = guard();
            let measured = JointVector::zeros();
            g.set_measured(Some(measured));
            let mut v = JointVector::zeros();
            v[1] = v0.min(braking_speed(bound, g.max_acceleration(), dt));
            g.set_velocity(v);
            let mut to = measured;
            to[1] = 1.0;
            let qs = walk_all(&mut g, measured, to, dt, 300);
            let lead = qs.iter().map(|q| (q - measured).amax()).fold(0.0, f64::max);
            assert!(
                lead <= bound + 1e-9,
                "from {v0} rad/s: led by {lead} rad, bound {bound}"
            );
            assert!(lead > 0.95 * bound, "from {v0} rad/s: stopped short at {lead} rad");
            let step = qs[1] - qs[0];
            assert!(
                g.check_command(&(qs[300] + step), &qs[300], dt).is_err(),
                "beyond the bound is refused"
            );
        }
    }

    proptest! {
        #[test]
        fn step_box_is_safe(
            prev in proptest::collection::vec(-3.5f64..3.5, 7),
            vel in proptest::collection::vec(-1.0f64..1.0, 7),
            dt in 0.0005f64..0.05,
        ) {
            let mut g = guard();
            let prev = JointVector::from_column_slice(&prev);
            let v = JointVector::from_column_slice(&vel).component_mul(g.max_velocity());
            g.set_velocity(v);
            let (lo, hi) = g.step_box(&prev, dt);
            let a = g.max_acceleration();
            for i in 0..7 {
                prop_assert!(lo[i] <= hi[i]);
                // Within the acceleration limit of the last velocity, always.
                for x in [lo[i], hi[i]] {
                    prop_assert!(((x - prev[i]) / dt - v[i]).abs() <= a * dt + 1e-9);
                }
                // Within the speed limit wherever the acceleration limit allows it.
                if v[i].abs() <= g.max_velocity()[i] {
                    prop_assert!(hi[i] - prev[i] <= g.max_velocity()[i] * dt + 1e-12);
                    prop_assert!(prev[i] - lo[i] <= g.max_velocity()[i] * dt + 1e-12);
                }
            }
            // Any point of the box passes the check.
            prop_assert!(g.check_command(&lo, &prev, dt).is_ok());
            prop_assert!(g.check_command(&hi, &prev, dt).is_ok());
        }

        /// From any speed the guard allows, a hold (walking to where it is) brakes to rest
        /// within the speed and acceleration limits, in the fewest steps the acceleration
        /// limit allows (one more for the discrete margin), and stands still after.
        #[test]
        fn a_hold_brakes_to_rest_within_the_limits(
            vel in proptest::collection::vec(-1.0f64..1.0, 7),
            dt in prop_oneof![Just(0.001), Just(0.01)],
        ) {
            let mut g = guard();
            let q0 = JointVector::from_column_slice(&[0.1, 0.5, -0.2, -1.2, 0.3, 1.0, -0.4]);
            let v = JointVector::from_column_slice(&vel).component_mul(g.max_velocity());
            g.set_velocity(v);
            let a = g.max_acceleration();
            let need = (v.amax() / (a * dt)).ceil() as usize + 1;
            let mut q = q0;
            let mut qs = vec![q0 - v * dt, q0];
            for _ in 0..need + 20 {
                // A hold stands where it is: its target is its own last command.
                let next = g.walk(&q, &q, dt);
                g.set_velocity((next - q) / dt);
                q = next;
                qs.push(q);
            }
            let speeds: Vec<JointVector> = qs.windows(2).map(|w| (w[1] - w[0]) / dt).collect();
            for w in speeds.windows(2) {
                for (i, dv) in (w[1] - w[0]).iter().enumerate() {
                    prop_assert!(dv.abs() <= a * dt + 1e-9, "joint {}: {} -> {}", i + 1, w[0][i], w[1][i]);
                }
            }
            prop_assert!(speeds[need..].iter().all(|s| s.amax() < 1e-9), "not at rest after {} steps", need);
            // Beyond where it was by the braking distance, no more: v^2 / (2a) + v dt.
            for i in 0..7 {
                prop_assert!((q[i] - q0[i]).abs() <= v[i] * v[i] / (2.0 * a) + v[i].abs() * dt + 1e-9);
                prop_assert!((q[i] - q0[i]) * v[i] >= -1e-12, "joint {} went back", i + 1);
            }
        }

        /// A walk to a target from rest ramps up and brakes: it reaches the target, at rest,
        /// within the speed and acceleration limits, and never passes it.
        #[test]
        fn a_walk_ramps_up_and_lands_at_rest(
            d in proptest::collection::vec(-0.5f64..0.5, 7),
            dt in prop_oneof![Just(0.001), Just(0.01)],
        ) {
            let mut g = guard();
            let q0 = JointVector::from_column_slice(&[0.1, 0.5, -0.2, -1.2, 0.3, 1.0, -0.4]);
            let to = q0 + JointVector::from_column_slice(&d);
            let steps = (2.0 / dt) as usize;
            let qs = walk_all(&mut g, q0, to, dt, steps);
            prop_assert!((qs[qs.len() - 1] - to).amax() < 1e-12, "not at the target");
            let (speed, accel) = worst_shares(&g, &qs, dt);
            prop_assert!(speed <= 1.0 + 1e-9 && accel <= 1.0 + 1e-6, "speed {} accel {} x the limits", speed, accel);
            for q in &qs {
                for i in 0..7 {
                    prop_assert!((q[i] - q0[i]) * (to[i] - q[i]) >= -1e-12, "joint {} passed its target", i + 1);
                }
            }
        }
    }

    /// A publisher that wants a cosine profile too steep for the acceleration limit, then
    /// a stop at once: what it sends stays within the limits and ends at rest on the target.
    #[test]
    fn following_a_steep_profile_stays_within_the_limits() {
        let mut g = guard();
        let dt = 0.01;
        let q0 = JointVector::from_column_slice(&[0.1, 0.5, -0.2, -1.2, 0.3, 1.0, -0.4]);
        let mut delta = JointVector::zeros();
        delta[0] = 0.05;
        delta[5] = -0.08;
        let mut sent = vec![q0];
        for k in 1..=80 {
            let s = (f64::from(k.min(20)) / 20.0 * std::f64::consts::PI).cos();
            let want = q0 + delta * ((1.0 - s) / 2.0);
            let last = sent[sent.len() - 1];
            sent.push(g.follow(&last, &want, dt));
        }
        let (speed, accel) = worst_shares(&g, &sent, dt);
        assert!(speed <= 1.0 + 1e-9 && accel <= 1.0 + 1e-6, "{speed} {accel}");
        assert!((sent[sent.len() - 1] - (q0 + delta)).amax() < 1e-12);
        // The wanted profile itself would not have been: its peak acceleration is
        // pi^2 / 2 x 0.08 rad / (0.2 s)^2 = 9.9 rad/s^2.
        assert!(std::f64::consts::PI.powi(2) / 2.0 * 0.08 / 0.04 > g.max_acceleration());
    }

    #[test]
    fn braking_speed_stops_within_its_distance() {
        for (d, a, dt) in [
            (0.1, 5.0, 0.01),
            (0.0003, 5.0, 0.01),
            (1.0, 5.0, 0.001),
            (0.0, 5.0, 0.01),
        ] {
            let mut v = braking_speed(d, a, dt);
            let mut gone = 0.0;
            while v > 0.0 {
                gone += v * dt;
                v -= a * dt;
            }
            assert!(gone <= d + 1e-12, "{gone} > {d}");
            // Not needlessly slow: one step of acceleration more would pass it.
            let mut v = braking_speed(d, a, dt) + 2.0 * a * dt;
            let mut more = 0.0;
            while v > 0.0 {
                more += v * dt;
                v -= a * dt;
            }
            assert!(more > d, "{more} <= {d}");
        }
        assert_eq!(braking_speed(0.1, 5.0, 0.0), f64::INFINITY);
    }

    #[test]
    fn a_command_that_stops_at_once_from_speed_is_refused() {
        let mut g = guard();
        let prev = JointVector::from_column_slice(&[0.1, 0.5, -0.2, -1.2, 0.3, 1.0, -0.4]);
        let mut v = JointVector::zeros();
        v[1] = 0.5;
        g.set_velocity(v);
        // Standing still at once: 0.5 rad/s lost in 10 ms, 50 rad/s^2.
        assert_eq!(
            g.check_command(&prev, &prev, 0.01),
            Err(HoldReason::AccelerationLimit { joint: 1 })
        );
        // Slowing by the acceleration limit's step passes.
        let mut next = prev;
        next[1] += (0.5 - g.max_acceleration() * 0.01) * 0.01;
        assert!(g.check_command(&next, &prev, 0.01).is_ok());
        // From rest, a full-speed step at once is refused, one step of acceleration passes.
        g.set_velocity(JointVector::zeros());
        let mut fast = prev;
        fast[3] += g.max_velocity()[3] * 0.01;
        assert_eq!(
            g.check_command(&fast, &prev, 0.01),
            Err(HoldReason::AccelerationLimit { joint: 3 })
        );
        let mut ramp = prev;
        ramp[3] += g.max_acceleration() * 0.01 * 0.01;
        assert!(g.check_command(&ramp, &prev, 0.01).is_ok());
    }

    #[test]
    fn a_joint_brakes_before_its_position_limit() {
        let mut g = guard();
        let mut prev = JointVector::from_column_slice(&[0.1, 0.5, -0.2, -1.2, 0.3, 1.0, -0.4]);
        prev[0] = g.upper()[0] - 0.01;
        let dt = 0.01;
        let mut far = prev;
        far[0] += 1.0;
        let qs = walk_all(&mut g, prev, far, dt, 200);
        // Walking at the far target beyond the limit: it stops at the limit, at rest.
        let last = qs[qs.len() - 1];
        assert!(last[0] <= g.upper()[0] + 1e-12, "{} past {}", last[0], g.upper()[0]);
        assert!(
            g.upper()[0] - last[0] < 1e-3,
            "stopped {} short",
            g.upper()[0] - last[0]
        );
        let (speed, accel) = worst_shares(&g, &qs, dt);
        assert!(speed <= 1.0 + 1e-9 && accel <= 1.0 + 1e-6, "{speed} {accel}");
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
        assert!(GuardParams {
            max_acceleration_rad_s2: 0.0,
            ..Default::default()
        }
        .validate()
        .is_err());
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
