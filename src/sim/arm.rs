//! The arm in FRI position mode: each joint tracks its commanded position through a rate
//! limiter and a short second-order lag, as the LBR's joint position controller does.
//!
//! Per joint i, at the physics period dt:
//! ```text
//! r  <- r + clamp(q_cmd - r, -s v_max dt, +s v_max dt)           (rate-limited reference)
//! a   = w^2 (r - q) - 2 z w qd                                   (critically damped lag)
//! qd <- clamp(qd + a dt, -v_max, v_max);  q <- clamp(q + qd dt, q_min, q_max)
//! ```
//! with w = 1 / lag_time_constant_s, z = damping_ratio, s = velocity_scale. The arm is
//! position-controlled and far stiffer than the trocar mount, so contact does not deflect it.

use serde::{Deserialize, Serialize};

use super::{check_range, SimError};
use crate::kinematics::{JointLimits, JointVector};

/// Parameters of the joint tracking model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ArmParams {
    /// Time constant of the tracking lag, s (1 / natural frequency).
    pub lag_time_constant_s: f64,
    /// Damping ratio of the lag (1 = critically damped).
    pub damping_ratio: f64,
    /// Fraction of the joint velocity limits the reference may move at.
    pub velocity_scale: f64,
}

impl Default for ArmParams {
    fn default() -> Self {
        Self {
            lag_time_constant_s: 0.01,
            damping_ratio: 1.0,
            velocity_scale: 1.0,
        }
    }
}

impl ArmParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("arm.lag_time_constant_s", self.lag_time_constant_s, 1e-4, 1.0)?;
        check_range("arm.damping_ratio", self.damping_ratio, 0.1, 10.0)?;
        check_range("arm.velocity_scale", self.velocity_scale, 0.01, 1.0)
    }
}

/// Joint state of the simulated arm.
#[derive(Debug, Clone, PartialEq)]
pub struct Arm {
    params: ArmParams,
    limits: JointLimits,
    q: JointVector,
    qd: JointVector,
    reference: JointVector,
    command: JointVector,
}

impl Arm {
    /// An arm at rest at `q0` (clamped into the limits), commanded to stay there.
    pub fn new(params: &ArmParams, limits: &JointLimits, q0: &JointVector) -> Result<Self, SimError> {
        params.validate()?;
        if q0.iter().any(|x| !x.is_finite()) {
            return Err(SimError::Input("start joint positions are not finite".into()));
        }
        let q = q0.zip_zip_map(&limits.lower, &limits.upper, |x, lo, hi| x.clamp(lo, hi));
        Ok(Self {
            params: params.clone(),
            limits: limits.clone(),
            q,
            qd: JointVector::zeros(),
            reference: q,
            command: q,
        })
    }

    /// Command new joint positions (clamped into the limits). A non-finite command is
    /// rejected and the previous command kept.
    pub fn set_command(&mut self, q_cmd: &JointVector) -> Result<(), SimError> {
        if let Some(i) = q_cmd.iter().position(|x| !x.is_finite()) {
            return Err(SimError::Input(format!("commanded joint {i} is not finite")));
        }
        self.command = q_cmd.zip_zip_map(&self.limits.lower, &self.limits.upper, |x, lo, hi| x.clamp(lo, hi));
        Ok(())
    }

    /// Advance by `dt` seconds.
    pub fn step(&mut self, dt: f64) {
        let w = 1.0 / self.params.lag_time_constant_s;
        let z = self.params.damping_ratio;
        for i in 0..self.q.len() {
            let vmax = self.limits.velocity[i];
            let dr = self.params.velocity_scale * vmax * dt;
            self.reference[i] += (self.command[i] - self.reference[i]).clamp(-dr, dr);
            let a = w * w * (self.reference[i] - self.q[i]) - 2.0 * z * w * self.qd[i];
            self.qd[i] = (self.qd[i] + a * dt).clamp(-vmax, vmax);
            let q = self.q[i] + self.qd[i] * dt;
            self.q[i] = q.clamp(self.limits.lower[i], self.limits.upper[i]);
            if self.q[i] != q {
                self.qd[i] = 0.0;
            }
        }
    }

    /// Measured joint positions, rad.
    pub fn q(&self) -> &JointVector {
        &self.q
    }
    /// Joint velocities, rad/s.
    pub fn qd(&self) -> &JointVector {
        &self.qd
    }
    /// The last accepted command.
    pub fn command(&self) -> &JointVector {
        &self.command
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::lbr::LbrModel;

    fn arm() -> Arm {
        Arm::new(
            &ArmParams::default(),
            &JointLimits::of_model(LbrModel::Med7),
            &JointVector::zeros(),
        )
        .unwrap()
    }

    #[test]
    fn tracks_a_step_command_within_the_velocity_limit() {
        let mut a = arm();
        let target = JointVector::repeat(0.2);
        a.set_command(&target).unwrap();
        let vmax = JointLimits::of_model(LbrModel::Med7).velocity;
        for _ in 0..1000 {
            a.step(1e-3);
            for i in 0..7 {
                assert!(a.qd()[i].abs() <= vmax[i] + 1e-12);
            }
        }
        assert!((a.q() - target).amax() < 1e-4, "{}", a.q());
        // The first joint moves at 98 deg/s at most: 0.2 rad takes >= 0.117 s.
        let mut b = arm();
        b.set_command(&target).unwrap();
        for _ in 0..100 {
            b.step(1e-3);
        }
        assert!(b.q()[0] < 0.2 * 0.99);
    }

    #[test]
    fn rejects_nan_and_clamps_to_limits() {
        let mut a = arm();
        let mut bad = JointVector::zeros();
        bad[3] = f64::NAN;
        assert!(a.set_command(&bad).is_err());
        assert_eq!(a.command(), &JointVector::zeros());
        a.set_command(&JointVector::repeat(10.0)).unwrap();
        let up = JointLimits::of_model(LbrModel::Med7).upper;
        assert_eq!(a.command(), &up);
    }
}
