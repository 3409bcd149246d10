//! The arm in FRI position mode: each joint tracks its commanded position through a rate
//! limiter and a short second-order lag, as the LBR's joint position controller does.
//!
//! Per joint i, at the physics period dt:
//! ```text
//! r  <- r + clamp(q_cmd - r, -s v_max dt, +s v_max dt)           (rate-limited reference)
//! a   = w^2 (r - q) - 2 z w qd                                   (critically damped lag)
//! qd <- clamp(qd + a dt, -v_max, v_max);  q <- clamp(q + qd dt, q_min, q_max)
//! ```
//! with w = 1 / lag_time_constant_s, z = damping_ratio, s = velocity_scale.
//!
//! **Joint elasticity.** The LBR's joints are elastic (harmonic drive, torque sensor): the
//! position controller holds the motor side at q, and an external torque tau_ext twists
//! the link side by K^-1 tau_ext (K = diag of `joint_stiffness_nm_per_rad`, 0 = rigid). The
//! link-side deflection d relaxes to it with the time constant T of the joints' link-side
//! mode (first order):
//! ```text
//! T dd/dt = K^-1 tau_ext(d) - d;   q_link = q + d
//! ```
//! integrated by backward Euler over a sub-step h, in the deflection and in the contact it
//! presses against: with a = h / (T + h) and K_q = -d tau_ext / d d = J^T K_c J (K_c the
//! contact's stiffness against the tip's motion, [`super::contact::ContactWrench`]),
//! ```text
//! (I + a K^-1 K_q) (d' - d) = a (K^-1 tau_ext - d)
//! ```
//! The explicit form (K_q left out) is stable only while a (1 + |K^-1 K_q|) < 2: a cannula
//! as stiff as a real one (1e6 N/m per contact, config/sim.yaml) against joints of 1e4 Nm/rad
//! breaks that at sub-steps of 0.1 ms; the implicit one holds at any sub-step.
//! At rest under a tip force f, the tip moves by J K^-1 J^T f. The joint positions the
//! arm reports are the motor side q (as the LBR's position sensors sit before the elastic
//! element), so the controller does not see d.

use serde::{Deserialize, Serialize};

use super::{check_range, SimError};
use crate::kinematics::{JointLimits, JointVector};

/// A joint-space matrix (the contact's stiffness seen by the joints).
pub type JointMatrix = nalgebra::SMatrix<f64, 7, 7>;

/// Parameters of the joint tracking model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct ArmParams {
    /// Time constant of the tracking lag, s (1 / natural frequency).
    pub lag_time_constant_s: f64,
    /// Damping ratio of the lag (1 = critically damped).
    pub damping_ratio: f64,
    /// Fraction of the joint velocity limits the reference may move at.
    pub velocity_scale: f64,
    /// Joint stiffness per joint, Nm/rad (0 = rigid).
    pub joint_stiffness_nm_per_rad: [f64; 7],
    /// Time constant of the link-side deflection, s.
    pub deflection_time_constant_s: f64,
}

crate::shipped_defaults!(ArmParams, crate::sim::SHIPPED, ["sim", "arm"]);

impl ArmParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("arm.lag_time_constant_s", self.lag_time_constant_s, 1e-4, 1.0)?;
        check_range("arm.damping_ratio", self.damping_ratio, 0.1, 10.0)?;
        check_range("arm.velocity_scale", self.velocity_scale, 0.01, 1.0)?;
        for k in self.joint_stiffness_nm_per_rad {
            if k != 0.0 {
                check_range("arm.joint_stiffness_nm_per_rad", k, 100.0, 1e8)?;
            }
        }
        check_range(
            "arm.deflection_time_constant_s",
            self.deflection_time_constant_s,
            1e-4,
            1.0,
        )
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
    /// 1 / stiffness per joint (0 = rigid), rad/Nm.
    compliance: JointVector,
    deflection: JointVector,
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
            compliance: JointVector::from_fn(|i, _| {
                let k = params.joint_stiffness_nm_per_rad[i];
                if k > 0.0 {
                    1.0 / k
                } else {
                    0.0
                }
            }),
            deflection: JointVector::zeros(),
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

    /// Relax the link-side deflection for `h` seconds under the external torque `tau`, which
    /// falls by `stiffness` (K_q = -d tau / d d, joint space) as the joints deflect: the
    /// implicit step of the module doc. A singular system (not for a positive semi-definite
    /// K_q) falls back to the explicit step.
    pub fn relax(&mut self, tau: &JointVector, stiffness: &JointMatrix, h: f64) {
        let a = h / (self.params.deflection_time_constant_s + h);
        let rhs = (self.compliance.component_mul(tau) - self.deflection) * a;
        if stiffness.iter().all(|k| *k == 0.0) {
            self.deflection += rhs;
            return;
        }
        let mut m = *stiffness * a;
        for i in 0..self.q.len() {
            for j in 0..self.q.len() {
                m[(i, j)] *= self.compliance[i];
            }
            m[(i, i)] += 1.0;
        }
        let step = m.lu().solve(&rhs).filter(|x| x.iter().all(|v| v.is_finite()));
        self.deflection += step.unwrap_or(rhs);
    }

    /// Link-side deflection from the motor side, rad.
    pub fn deflection(&self) -> &JointVector {
        &self.deflection
    }

    /// Link-side joint positions (motor side plus deflection), rad: where the arm is.
    pub fn q_link(&self) -> JointVector {
        self.q + self.deflection
    }

    /// Measured (motor-side) joint positions, rad.
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
    fn an_elastic_joint_deflects_by_torque_over_stiffness() {
        let p = ArmParams {
            joint_stiffness_nm_per_rad: [2e4, 2e4, 2e4, 2e4, 1e4, 1e4, 0.0],
            ..Default::default()
        };
        let mut a = Arm::new(&p, &JointLimits::of_model(LbrModel::Med7), &JointVector::zeros()).unwrap();
        let tau = JointVector::from_column_slice(&[4.0, -2.0, 1.0, 0.0, 3.0, -1.0, 5.0]);
        for _ in 0..500 {
            a.relax(&tau, &JointMatrix::zeros(), 2e-4);
        }
        for i in 0..7 {
            let k = p.joint_stiffness_nm_per_rad[i];
            let want = if k > 0.0 { tau[i] / k } else { 0.0 };
            assert!(
                (a.deflection()[i] - want).abs() < 1e-3 * want.abs() + 1e-12,
                "joint {i}"
            );
        }
        assert_eq!(a.q(), &JointVector::zeros());
        assert_eq!(a.q_link(), *a.deflection());
        assert!(Arm::new(
            &ArmParams {
                joint_stiffness_nm_per_rad: [-1.0; 7],
                ..Default::default()
            },
            &JointLimits::of_model(LbrModel::Med7),
            &JointVector::zeros()
        )
        .is_err());
    }

    /// Joints of 1e4 Nm/rad pressed by a contact that takes 100 times that back as they
    /// deflect (tau = tau0 - K_q d): the implicit step settles on the static balance
    /// (I + K^-1 K_q) d = K^-1 tau0 at a sub-step where the explicit one diverges.
    #[test]
    fn a_stiff_contact_on_elastic_joints_settles_at_any_sub_step() {
        let k = 1e4;
        let p = ArmParams {
            joint_stiffness_nm_per_rad: [k; 7],
            ..Default::default()
        };
        let limits = JointLimits::of_model(LbrModel::Med7);
        let tau0 = JointVector::from_column_slice(&[4.0, -2.0, 1.0, 0.0, 3.0, -1.0, 5.0]);
        let mut kq = JointMatrix::identity() * (100.0 * k);
        kq[(0, 1)] = 20.0 * k;
        kq[(1, 0)] = 20.0 * k;
        let want = (JointMatrix::identity() + kq / k).lu().solve(&(tau0 / k)).unwrap();
        let run = |passed: &JointMatrix| {
            let mut a = Arm::new(&p, &limits, &JointVector::zeros()).unwrap();
            for _ in 0..2000 {
                let tau = tau0 - kq * a.deflection();
                a.relax(&tau, passed, 1e-4);
            }
            *a.deflection()
        };
        let implicit = run(&kq);
        assert!((implicit - want).amax() < 1e-6 * want.amax(), "{implicit} vs {want}");
        let explicit = run(&JointMatrix::zeros());
        let off = (explicit - want).amax();
        assert!(off.is_nan() || off > 1e-3, "the explicit step settled: {explicit}");
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
