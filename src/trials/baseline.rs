//! A baseline docking policy for exercising the simulator without the optimal controller:
//! damped-least-squares resolved rates toward a point `standoff_m` before the measured port
//! on its axis, aligning the optical axis with it, then straight along the axis to the
//! goal. Its estimate of f_ext is the damped pseudo-inverse J_lin^-T tau_ext; with force
//! feedback (`admittance_m_per_n` > 0) the target moves by `admittance_m_per_n * f_perp`,
//! the part of f_ext across the measured axis (yield sideways, keep progressing along the
//! axis). Each tick corrects `gain` of the remaining error, up to `speed_m_s`.

use nalgebra::{Matrix6, Point3, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use super::closed_loop::Observation;
use super::run::{Action, Policy};
use crate::kinematics::{JointVector, Kinematics};

/// The baseline reports DONE within this distance of the measured goal, m, ...
const DONE_TOLERANCE_M: f64 = 0.001;
/// ... once it has stayed there this long, s (the arm lags its commands: DONE on the first
/// tick inside left the true tip still sliding in).
const DONE_SETTLE_S: f64 = 0.2;

/// Tunables of the baseline (the `baseline:` section of `config/sim.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct BaselineParams {
    /// Stand-off before the port for alignment, m.
    pub standoff_m: f64,
    /// Cartesian speed limit, m/s.
    pub speed_m_s: f64,
    /// Fraction of the position error corrected per tick.
    pub gain: f64,
    /// Admittance of the force feedback when it is on, m/N.
    pub admittance_m_per_n: f64,
}

crate::shipped_defaults!(BaselineParams, crate::sim::SHIPPED, ["baseline"]);

/// The baseline policy.
#[derive(Debug, Clone)]
pub struct Baseline {
    /// Goal depth along the axis, m.
    pub goal_depth_m: f64,
    /// Stand-off before the port for alignment, m.
    pub standoff_m: f64,
    /// Cartesian speed limit, m/s.
    pub speed_m_s: f64,
    /// Control period, s.
    pub period_s: f64,
    /// Fraction of the position error corrected per tick.
    pub gain: f64,
    /// Admittance of the force feedback, m/N (0: none).
    pub admittance_m_per_n: f64,
    inserting: bool,
    at_goal_s: f64,
}

impl Baseline {
    /// A baseline for goal depth `goal_depth_m` at control period `period_s`, with force
    /// feedback when `ff`.
    pub fn new(p: &BaselineParams, goal_depth_m: f64, period_s: f64, ff: bool) -> Self {
        Self {
            goal_depth_m,
            standoff_m: p.standoff_m,
            speed_m_s: p.speed_m_s,
            period_s,
            gain: p.gain,
            admittance_m_per_n: if ff { p.admittance_m_per_n } else { 0.0 },
            inserting: false,
            at_goal_s: 0.0,
        }
    }
}

impl Policy for Baseline {
    fn period(&self) -> f64 {
        self.period_s
    }

    fn start(&mut self, _kin: &dyn Kinematics) {
        self.inserting = false;
        self.at_goal_s = 0.0;
    }

    fn tick(&mut self, kin: &dyn Kinematics, obs: &Observation) -> Action {
        let hold = |why: &str| Action {
            command: None,
            f_ext: None,
            phase: "HOLD",
            hold_code: None,
            aborted: Some(why.to_string()),
            latched: false,
        };
        let Ok((tip, jac)) = kin.fk_jacobian(&obs.q) else {
            return hold("kinematics failed");
        };
        let f_ext =
            crate::control::force::admittance::tip_force(&jac, &obs.tau_ext, 0.0, 0.05).unwrap_or_else(Vector3::zeros);
        let Some(m) = obs.trocar else {
            return Action {
                command: None,
                f_ext: Some(f_ext),
                phase: "IDLE",
                hold_code: None,
                aborted: None,
                latched: false,
            };
        };
        let axis = m.pose.rotation * Vector3::z();
        let port = Point3::from(m.pose.translation.vector);
        let p = Point3::from(tip.translation.vector);
        let z = tip.rotation * Vector3::z();
        let pre = port - axis * self.standoff_m;
        if !self.inserting && (p - pre).norm() < 0.003 && z.angle(&axis) < 0.03 {
            self.inserting = true;
        }
        let goal = port + axis * self.goal_depth_m;
        if self.inserting && (goal - p).norm() < DONE_TOLERANCE_M && z.angle(&axis) < 0.03 {
            self.at_goal_s += self.period_s;
        } else {
            self.at_goal_s = 0.0;
        }
        if self.at_goal_s >= DONE_SETTLE_S {
            // At the measured goal, aligned: done (nothing more to command).
            return Action {
                command: None,
                f_ext: Some(f_ext),
                phase: "DONE",
                hold_code: None,
                aborted: None,
                latched: false,
            };
        }
        let target = if self.inserting { goal } else { pre };
        let f_perp = f_ext - axis * axis.dot(&f_ext);
        let target = target + f_perp * self.admittance_m_per_n;
        let mut dp = (target - p) * self.gain;
        let step = self.speed_m_s * self.period_s;
        if dp.norm() > step {
            dp *= step / dp.norm();
        }
        let dw = z.cross(&axis) * 0.2;
        let e = Vector6::new(dp.x, dp.y, dp.z, dw.x, dw.y, dw.z);
        let a: Matrix6<f64> = jac * jac.transpose() + Matrix6::identity() * 1e-4;
        let dq = a
            .try_inverse()
            .map_or(JointVector::zeros(), |inv| jac.transpose() * (inv * e));
        Action {
            command: Some(obs.q + dq),
            f_ext: Some(f_ext),
            phase: if self.inserting { "INSERT" } else { "APPROACH" },
            hold_code: None,
            aborted: None,
            latched: false,
        }
    }
}
