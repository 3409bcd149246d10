//! Bounded tip motion: speed, acceleration and jerk of the commanded tip, linear and
//! angular, in every phase, whatever the trocar pose's noise and rate.
//!
//! The SQP answers each trocar sample at once: a pose that jumps by millimetres from one
//! message to the next (the paper's raw noise redraws ±5 mm per axis at every message)
//! becomes a command that jumps with it, and the arm shakes. The limiter sits after the
//! SQP and shapes the step it proposes, in task space:
//!
//! 1. the step `Δq = q_sqp - q_prev` moves the tip by the twist `δ = J Δq` (linear, angular);
//! 2. the wanted velocity `δ / dt` is capped at the speed limit, and at the braking speed
//!    for the distance still to go (with the jerk limit's build-up time), so that the tip
//!    stops where the SQP wants it without overshoot. The distance still to go is the larger
//!    of the step and what the caller says is left (the controller: the tip's distance to
//!    the phase's target point, and the alignment error): the SQP often asks for a fraction
//!    of the way per step, and braking on that fraction alone would slow every motion, the
//!    more so the higher the control rate;
//! 3. the velocity moves towards it by at most the acceleration limit per step, and the
//!    acceleration changes by at most the jerk limit per step;
//! 4. the joint step is corrected by the damped least-squares solution of
//!    `J (Δq' - Δq) = v' dt - δ` (the smallest joint change that gives the limited twist, so
//!    the SQP's null-space motion, e.g. off the joint limits, is kept), and brought back
//!    into the step box where the correction leaves it (scaled from the previous command,
//!    keeping the twist's direction, where the box holds it; from the SQP's command, solved
//!    in the box, where the acceleration limit keeps a moving joint off it, then within the
//!    tip's speed limits: `into_box`).
//!
//! Its state is the commanded twist of the last step and its rate; it starts at rest, and
//! every run and every resume from a hold starts at rest (the arm is still then). One
//! 6 x 6 Cholesky per step, on the stack: nothing allocates.

use nalgebra::{Matrix6, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use crate::kinematics::{Jacobian, JointVector};

/// Limits of the commanded tip motion (`motion:` in `config/controller.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct MotionLimits {
    /// Largest tip speed, m/s.
    pub max_speed_m_s: f64,
    /// Largest tip acceleration, m/s².
    pub max_accel_m_s2: f64,
    /// Largest tip jerk, m/s³.
    pub max_jerk_m_s3: f64,
    /// Largest angular speed of the scope, rad/s.
    pub max_angular_speed_rad_s: f64,
    /// Largest angular acceleration, rad/s².
    pub max_angular_accel_rad_s2: f64,
    /// Largest angular jerk, rad/s³.
    pub max_angular_jerk_rad_s3: f64,
}

crate::shipped_defaults!(MotionLimits, crate::config::CONTROLLER, ["motion"]);

impl MotionLimits {
    /// Check every range; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        for (n, v) in [
            ("max_speed_m_s", self.max_speed_m_s),
            ("max_accel_m_s2", self.max_accel_m_s2),
            ("max_jerk_m_s3", self.max_jerk_m_s3),
            ("max_angular_speed_rad_s", self.max_angular_speed_rad_s),
            ("max_angular_accel_rad_s2", self.max_angular_accel_rad_s2),
            ("max_angular_jerk_rad_s3", self.max_angular_jerk_rad_s3),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("motion.{n} must be > 0, got {v}"));
            }
        }
        Ok(())
    }
}

impl MotionLimits {
    /// The linear block.
    fn linear(&self) -> Block {
        Block {
            speed: self.max_speed_m_s,
            accel: self.max_accel_m_s2,
            jerk: self.max_jerk_m_s3,
        }
    }

    /// The angular block.
    fn angular(&self) -> Block {
        Block {
            speed: self.max_angular_speed_rad_s,
            accel: self.max_angular_accel_rad_s2,
            jerk: self.max_angular_jerk_rad_s3,
        }
    }
}

/// One block (linear or angular) of the limits.
#[derive(Debug, Clone, Copy)]
struct Block {
    speed: f64,
    accel: f64,
    jerk: f64,
}

/// `v` with its norm cut to `max`.
fn cap(v: Vector3<f64>, max: f64) -> Vector3<f64> {
    let n = v.norm();
    if n > max && n > 0.0 {
        v * (max / n)
    } else {
        v
    }
}

/// The limited velocity of one block: from `v` (accelerating at `a`) towards the velocity
/// that covers `d` this step, within the block's limits, braking ahead for both the
/// acceleration limit (position) and the jerk limit (velocity), so that neither overshoots.
fn shape(d: Vector3<f64>, left: f64, v: Vector3<f64>, a: Vector3<f64>, b: Block, dt: f64) -> Vector3<f64> {
    let dist = d.norm();
    let to_go = dist.max(left);
    // Stopping distance from speed s: s^2 / (2 a) + s t_j / 2, with t_j = a / j the time the
    // acceleration takes to build up; the speed that stops within `dist`:
    let at = b.accel * b.accel / b.jerk;
    let brake = 0.5 * (-at + (at * at + 8.0 * b.accel * to_go).sqrt());
    let want_speed = (dist / dt).min(b.speed).min(brake);
    let want = if dist > 0.0 { d * (want_speed / dist) } else { d };
    let dv = want - v;
    let n = dv.norm();
    let a_mag = b.accel.min((2.0 * b.jerk * n).sqrt()).min(n / dt);
    let a_want = if n > 0.0 { dv * (a_mag / n) } else { dv };
    let a_new = a + cap(a_want - a, b.jerk * dt);
    cap(v + a_new * dt, b.speed)
}

/// `base + s (to - base)` with the largest `s` in [0, 1] that keeps it in `[lo, hi]`, then
/// clamped: the limited step brought into the guard's step box. `base` is `prev` where the
/// box holds it (every joint slow enough for its acceleration limit to allow a stop at
/// once), so that a step cut by the speed limits keeps its direction and only slows; where
/// the acceleration limit keeps a moving joint off `prev`, `base` is the SQP's own command
/// `sqp` (solved inside the box), so that as much of the limiter's correction is kept as
/// the box allows, and the result is then drawn towards the box's point nearest `prev`
/// (every joint braking as hard as its acceleration limit allows) as far as the tip's speed
/// limits need ([`within_speed`]). Scaling from `prev` there gave the braking edge at every step (the
/// arm crawled), and scaling from the box's centre coasted the arm on its old velocity;
/// both left most 1 kHz soak cycles held or timed out (the box at 1 kHz is 1/100 of its
/// width at 100 Hz).
fn into_box(
    (prev, sqp, to): (&JointVector, &JointVector, &JointVector),
    (lo, hi): (&JointVector, &JointVector),
    speed: impl Fn(&JointVector) -> bool,
) -> JointVector {
    let inside = (0..prev.len()).all(|i| prev[i] >= lo[i] && prev[i] <= hi[i]);
    let base = if inside {
        *prev
    } else {
        sqp.zip_zip_map(lo, hi, |q, l, h| q.clamp(l, h))
    };
    let step = to - base;
    let mut s = 1.0f64;
    for i in 0..step.len() {
        let room = if step[i] > 0.0 {
            hi[i] - base[i]
        } else {
            lo[i] - base[i]
        };
        if step[i] != 0.0 {
            s = s.min((room / step[i]).max(0.0));
        }
    }
    let out = (base + step * s).zip_zip_map(lo, hi, |q, l, h| q.clamp(l, h));
    if inside {
        out
    } else {
        within_speed(&prev.zip_zip_map(lo, hi, |q, l, h| q.clamp(l, h)), &out, speed)
    }
}

/// `brake + l (out - brake)` with the largest `l` in [0, 1] (to 1/1024) for which `ok`
/// holds (the tip's speed limits: a convex set), `out` itself where it holds; `brake`, every
/// joint braking as hard as it may, where nothing else does.
fn within_speed(brake: &JointVector, out: &JointVector, ok: impl Fn(&JointVector) -> bool) -> JointVector {
    let centre = brake;
    if ok(out) {
        return *out;
    }
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    for _ in 0..10 {
        let mid = 0.5 * (lo + hi);
        if ok(&(centre + (out - centre) * mid)) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    centre + (out - centre) * lo
}

/// The limiter's state: the last commanded tip twist and its rate.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MotionLimiter {
    /// Commanded twist (linear; angular), m/s and rad/s.
    velocity: Vector6<f64>,
    /// Its rate, m/s² and rad/s².
    accel: Vector6<f64>,
}

/// Damping of the least-squares correction (m or rad per unit of twist).
const DAMPING: f64 = 1e-3;

impl MotionLimiter {
    /// The commanded tip speed of the last step, m/s.
    pub fn speed(&self) -> f64 {
        self.velocity.fixed_rows::<3>(0).norm()
    }

    /// Back to rest (a new run, a resume: the arm is still).
    pub fn rest(&mut self) {
        *self = Self::default();
    }

    /// Shape the SQP's command `cmd` from `prev` for the limits, with `jac` the Jacobian
    /// (base frame, linear part at the tip) near `prev`, inside the step box `[lo, hi]`;
    /// `left` is the distance (m) and angle (rad) the motion has still to go, for braking
    /// (0: the step itself). A `dt` of 0 (a clock that did not advance) commands `prev`.
    pub fn limit(
        &mut self,
        lim: &MotionLimits,
        jac: &Jacobian,
        (prev, cmd): (&JointVector, &JointVector),
        left: (f64, f64),
        dt: f64,
        (lo, hi): (&JointVector, &JointVector),
    ) -> JointVector {
        if dt.is_nan() || dt <= 0.0 {
            self.rest();
            return *prev;
        }
        let dq = cmd - prev;
        let twist = jac * dq;
        let blocks = [(0, left.0, lim.linear()), (3, left.1, lim.angular())];
        let part = |x: &Vector6<f64>, i: usize| Vector3::new(x[i], x[i + 1], x[i + 2]);
        let mut want = Vector6::zeros();
        for (i, to_go, b) in blocks {
            let v = shape(
                part(&twist, i),
                to_go,
                part(&self.velocity, i),
                part(&self.accel, i),
                b,
                dt,
            );
            want.fixed_rows_mut::<3>(i).copy_from(&(v * dt));
        }
        let err = want - twist;
        let out = if err.norm() > 1e-12 {
            let jjt = jac * jac.transpose() + Matrix6::identity() * (DAMPING * DAMPING);
            match jjt.cholesky() {
                Some(c) => prev + dq + jac.transpose() * c.solve(&err),
                None => *prev,
            }
        } else {
            *cmd
        };
        let (linear, angular) = (lim.max_speed_m_s * dt, lim.max_angular_speed_rad_s * dt);
        let speed_ok = |q: &JointVector| {
            let d = jac * (q - prev);
            let part = |i: usize| Vector3::new(d[i], d[i + 1], d[i + 2]).norm();
            part(0) <= linear * (1.0 + 1e-9) && part(3) <= angular * (1.0 + 1e-9)
        };
        let out = into_box((prev, cmd, &out), (lo, hi), speed_ok);
        let out = if out.iter().all(|x| x.is_finite()) { out } else { *prev };
        // The state follows what is commanded (after the box), so the next step's limits
        // are measured from it.
        let v = jac * (out - prev) / dt;
        self.accel = (v - self.velocity) / dt;
        self.velocity = v;
        out
    }
}

/// Which block of the limits a [`RateShaper`] keeps to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rate {
    /// A linear velocity, m/s.
    Linear,
    /// An angular velocity, rad/s.
    Angular,
}

/// A velocity command (e.g. the surgeon's pan, tilt and zoom rates after docking) brought
/// towards its wanted value within the speed, acceleration and jerk limits, so that a
/// command that starts, stops or reverses at once moves the target smoothly. Used where
/// the target itself is the motion (pivoting), rather than a point the SQP is drawn to.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RateShaper {
    velocity: Vector3<f64>,
    accel: Vector3<f64>,
}

impl RateShaper {
    /// The shaped velocity of this step, towards `want`, braking to stop within `left`
    /// (m or rad; `f64::INFINITY` when nothing is ahead). A `dt` of 0 (or NaN) stops.
    pub fn step(&mut self, lim: &MotionLimits, rate: Rate, want: Vector3<f64>, left: f64, dt: f64) -> Vector3<f64> {
        if dt.is_nan() || dt <= 0.0 || !want.iter().all(|x| x.is_finite()) {
            self.stop();
            return self.velocity;
        }
        let b = match rate {
            Rate::Linear => lim.linear(),
            Rate::Angular => lim.angular(),
        };
        let v = shape(want * dt, left.max(0.0), self.velocity, self.accel, b, dt);
        self.accel = (v - self.velocity) / dt;
        self.velocity = v;
        v
    }

    /// The velocity of the last step.
    pub fn velocity(&self) -> Vector3<f64> {
        self.velocity
    }

    /// At rest at once.
    pub fn stop(&mut self) {
        *self = Self::default();
    }

    /// The velocity was cut to `v` by a limit that stopped the target (the cone, a depth
    /// limit): the shaping goes on from `v`, not accelerating.
    pub fn cut_to(&mut self, v: Vector3<f64>) {
        self.velocity = v;
        self.accel = Vector3::zeros();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 6 x 7 Jacobian whose first six joints move the tip one unit per rad, each along
    /// one twist axis; the seventh is redundant (with the first).
    fn jac() -> Jacobian {
        let mut j = Jacobian::zeros();
        for i in 0..6 {
            j[(i, i)] = 1.0;
        }
        j[(0, 6)] = 1.0;
        j
    }

    fn wide() -> (JointVector, JointVector) {
        (JointVector::repeat(-10.0), JointVector::repeat(10.0))
    }

    /// One limited step with the default limits, [`jac`] and a wide box; `left` m to go.
    fn shaped(m: &mut MotionLimiter, q: &JointVector, cmd: &JointVector, left: f64, dt: f64) -> JointVector {
        let (lo, hi) = wide();
        m.limit(&MotionLimits::default(), &jac(), (q, cmd), (left, 0.0), dt, (&lo, &hi))
    }

    #[test]
    fn a_steady_slow_motion_is_followed_exactly_once_up_to_speed() {
        let mut m = MotionLimiter::default();
        let dt = 0.01;
        // The SQP asks for a target that moves at 0.03 m/s in x (the insertion speed).
        let mut q = JointVector::zeros();
        let mut last = (0.0, 0.0);
        for k in 1..=200 {
            let target = 0.03 * dt * f64::from(k);
            let mut cmd = q;
            let gap = target - (q[0] + q[6]);
            cmd[0] += gap;
            let out = shaped(&mut m, &q, &cmd, gap.abs(), dt);
            last = (target, out[0] + out[6]);
            q = out;
        }
        // Steady state: the tip moves at the target's speed, a fixed lag behind it (the
        // distance it needs to brake from 0.03 m/s: under a millimetre).
        assert!((m.speed() - 0.03).abs() < 1e-6, "speed {}", m.speed());
        let lag = last.0 - last.1;
        assert!(lag.abs() < 1e-3, "lag {lag}");
    }

    #[test]
    fn noise_of_5_mm_per_step_is_cut_to_the_limits_in_speed_acceleration_and_jerk() {
        let lim = MotionLimits::default();
        let mut m = MotionLimiter::default();
        let j = jac();
        let dt = 0.01;
        let mut q = JointVector::zeros();
        let (mut v0, mut a0) = (Vector3::zeros(), Vector3::zeros());
        let mut sum_v2 = 0.0;
        for k in 0..500 {
            // The SQP asks for a jump to a fresh noisy sample each step: +-5 mm in x and y.
            let s = if (k * 7919) % 13 < 6 { 1.0 } else { -1.0 };
            let mut cmd = q;
            cmd[0] = 0.005 * s;
            cmd[1] = -0.005 * s;
            let out = shaped(&mut m, &q, &cmd, 0.0, dt);
            let d = j * (out - q);
            let v = Vector3::new(d[0], d[1], d[2]) / dt;
            let a = (v - v0) / dt;
            let jerk = (a - a0) / dt;
            assert!(v.norm() <= lim.max_speed_m_s * 1.001, "speed {}", v.norm());
            assert!(a.norm() <= lim.max_accel_m_s2 * 1.01, "accel {}", a.norm());
            assert!(jerk.norm() <= lim.max_jerk_m_s3 * 1.01, "jerk {}", jerk.norm());
            sum_v2 += v.norm_squared();
            (v0, a0, q) = (v, a, out);
        }
        // Unlimited, the tip would move 7 mm per step: 0.7 m/s.
        let rms = (sum_v2 / 500.0).sqrt();
        assert!(rms < 0.08, "RMS speed {rms}");
    }

    #[test]
    fn a_far_target_is_reached_at_the_speed_limit_and_without_overshoot() {
        let lim = MotionLimits::default();
        let mut m = MotionLimiter::default();
        let j = jac();
        let dt = 0.01;
        let mut q = JointVector::zeros();
        let mut top = 0.0f64;
        let mut max_x = 0.0f64;
        for _ in 0..300 {
            // The SQP wants x = 20 mm, within a step box of 5 mm per step.
            let mut cmd = q;
            let gap = 0.02 - (q[0] + q[6]);
            cmd[0] += gap.clamp(-0.005, 0.005);
            let out = shaped(&mut m, &q, &cmd, gap.abs(), dt);
            top = top.max((j * (out - q))[0] / dt);
            q = out;
            max_x = max_x.max(q[0] + q[6]);
        }
        let x = q[0] + q[6];
        assert!((x - 0.02).abs() < 1e-5, "ends at {x}");
        assert!(max_x < 0.02 + 2e-4, "overshoot to {max_x}");
        assert!(
            top > 0.5 * lim.max_speed_m_s && top <= lim.max_speed_m_s * 1.001,
            "top speed {top}"
        );
    }

    /// Seconds until the tip is within 0.1 mm of a target 20 mm away, when the SQP asks for
    /// the share `dt / 0.2 s` of the remaining gap per step (a time constant of 0.2 s,
    /// whatever the control period `dt`).
    fn time_to_target(dt: f64, tell_the_gap: bool) -> f64 {
        let mut m = MotionLimiter::default();
        let mut q = JointVector::zeros();
        for k in 1..=(20.0 / dt) as usize {
            let gap = 0.02 - (q[0] + q[6]);
            if gap.abs() < 1e-4 {
                return k as f64 * dt;
            }
            let mut cmd = q;
            cmd[0] += dt / 0.2 * gap;
            let left = if tell_the_gap { gap.abs() } else { 0.0 };
            q = shaped(&mut m, &q, &cmd, left, dt);
        }
        f64::INFINITY
    }

    #[test]
    fn braking_on_what_is_left_keeps_a_partial_step_law_independent_of_the_rate() {
        // Unlimited, 0.2 s * ln(200) = 1.06 s: the limiter must not slow it at either rate.
        let (t100, t1k) = (time_to_target(0.01, true), time_to_target(0.001, true));
        assert!(t100 < 1.15 && t1k < 1.15, "{t100} s at 100 Hz, {t1k} s at 1 kHz");
        // Braking on the step alone throttles the 1 kHz law much more.
        let throttled = time_to_target(0.001, false);
        assert!(throttled > 1.2 * t1k, "{throttled} s against {t1k} s");
    }

    #[test]
    fn the_step_box_and_a_zero_dt_are_respected() {
        let lim = MotionLimits::default();
        let mut m = MotionLimiter::default();
        let j = jac();
        let prev = JointVector::zeros();
        let mut cmd = prev;
        cmd[3] = 0.5;
        let (lo, hi) = (JointVector::repeat(-1e-4), JointVector::repeat(1e-4));
        let out = m.limit(&lim, &j, (&prev, &cmd), (0.0, 0.0), 0.01, (&lo, &hi));
        assert!(out.iter().all(|x| x.abs() <= 1e-4 + 1e-15));
        assert_eq!(m.limit(&lim, &j, (&prev, &cmd), (0.0, 0.0), 0.0, (&lo, &hi)), prev);
        assert_eq!(m.speed(), 0.0);
    }

    #[test]
    fn limits_are_validated() {
        let mut l = MotionLimits::default();
        assert!(l.validate().is_ok());
        l.max_jerk_m_s3 = f64::NAN;
        assert!(l.validate().unwrap_err().contains("motion.max_jerk_m_s3"));
        l.max_jerk_m_s3 = 1.0;
        l.max_speed_m_s = 0.0;
        assert!(l.validate().unwrap_err().contains("motion.max_speed_m_s"));
    }
}
