//! Randomised start of a trial: the arm's start configuration and the trocar's rest pose.
//!
//! q0 = q_nominal_rad + U(-q_spread_rad, q_spread_rad) per joint (q_nominal_rad puts the tip
//! 0.57 m in front of the base, 0.31 m high, pointing down, with room on every joint for the
//! docking pose about 0.15 m lower). The port lies `port_distance_m` from
//! the start tip, in a direction within `approach_cone_deg` of straight down; the trocar's
//! axis (z, into the body) is straight down tilted by U(0, max_tilt_deg) about a random
//! horizontal axis, with a random twist about itself.
//!
//! **Reachable set-ups only.** A lab positions the arm so that the trocar lies within the
//! wrist's range; a draw whose docking pose (stand-off point and goal, shaft on the axis) no
//! converged inverse kinematics from q0 reaches with every joint `reach_margin_deg` inside
//! its limits is drawn again (up to `max_draws` times). Without it about 1 draw in 40 puts
//! the docking pose inside the last 5 deg of the wrist's bend (A6), where the controller's
//! guard rightly stops the approach (ALIGNMENT_STALL): a set-up fault, the same in both arms.

use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::RngExt;
use serde::{Deserialize, Serialize};

use super::{check_range, SimError};
use crate::kinematics::{JointVector, Kinematics};

/// Parameters of the randomised start.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct ScenarioParams {
    /// Nominal start configuration, rad.
    pub q_nominal_rad: [f64; 7],
    /// Half-range of the uniform perturbation of each joint, rad.
    pub q_spread_rad: f64,
    /// Range of the distance from the start tip to the port, m.
    pub port_distance_m: [f64; 2],
    /// Largest angle of the tip-to-port direction from straight down, deg.
    pub approach_cone_deg: f64,
    /// Largest tilt of the trocar axis from straight down, deg.
    pub max_tilt_deg: f64,
    /// A draw is kept only if its docking pose is reachable with every joint this far inside
    /// its limits, deg (the controller's guard margin, `guard.position_margin_rad`); 0 = no check.
    pub reach_margin_deg: f64,
    /// Draws tried before giving up with an error.
    pub max_draws: u32,
}

crate::shipped_defaults!(ScenarioParams, crate::sim::SHIPPED, ["sim", "scenario"]);

impl ScenarioParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        for &q in &self.q_nominal_rad {
            check_range("scenario.q_nominal_rad", q, -std::f64::consts::PI, std::f64::consts::PI)?;
        }
        check_range("scenario.q_spread_rad", self.q_spread_rad, 0.0, 1.0)?;
        check_range("scenario.port_distance_m[0]", self.port_distance_m[0], 0.0, 1.0)?;
        check_range(
            "scenario.port_distance_m[1]",
            self.port_distance_m[1],
            self.port_distance_m[0],
            1.0,
        )?;
        check_range("scenario.approach_cone_deg", self.approach_cone_deg, 0.0, 80.0)?;
        check_range("scenario.max_tilt_deg", self.max_tilt_deg, 0.0, 80.0)?;
        check_range("scenario.reach_margin_deg", self.reach_margin_deg, 0.0, 30.0)?;
        check_range("scenario.max_draws", f64::from(self.max_draws), 1.0, 1e6)
    }
}

/// The start of one trial.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scenario {
    /// Start configuration, rad.
    pub q0: [f64; 7],
    /// Rest pose of the port (base frame, z into the body).
    pub trocar_rest: Isometry3<f64>,
}

impl Scenario {
    /// Start configuration as a joint vector.
    pub fn q0(&self) -> JointVector {
        JointVector::from_column_slice(&self.q0)
    }

    /// Draw a scenario whose docking pose is reachable (see the module doc).
    pub fn sample(p: &ScenarioParams, kin: &dyn Kinematics, rng: &mut impl rand::Rng) -> Result<Self, SimError> {
        p.validate()?;
        for _ in 0..p.max_draws {
            let s = Self::draw(p, kin, rng)?;
            if p.reach_margin_deg <= 0.0 || s.reachable(kin, p.reach_margin_deg.to_radians())? {
                return Ok(s);
            }
        }
        Err(SimError::Param {
            name: "scenario",
            why: format!("no reachable docking pose in {} draws", p.max_draws),
        })
    }

    /// Whether the stand-off point (20 mm before the port) and the goal (30 mm past it), with
    /// the shaft on the axis, are reachable from q0 with every joint `margin` rad inside its
    /// limits.
    pub fn reachable(&self, kin: &dyn Kinematics, margin: f64) -> Result<bool, SimError> {
        let axis = self.trocar_rest.rotation * Vector3::z();
        let port = Point3::from(self.trocar_rest.translation.vector);
        let mut q = self.q0();
        for depth in [-0.02, 0.03] {
            match reach(kin, &q, &(port + axis * depth), &axis, margin)? {
                Some(qd) => q = qd,
                None => return Ok(false),
            }
        }
        Ok(true)
    }

    /// One draw, reachable or not.
    fn draw(p: &ScenarioParams, kin: &dyn Kinematics, rng: &mut impl rand::Rng) -> Result<Self, SimError> {
        let lim = kin.limits();
        let s = p.q_spread_rad;
        let mut q0 = p.q_nominal_rad;
        for (i, q) in q0.iter_mut().enumerate() {
            let d = if s > 0.0 { rng.random_range(-s..=s) } else { 0.0 };
            *q = (*q + d).clamp(lim.lower[i], lim.upper[i]);
        }
        let tip = kin.fk(&JointVector::from_column_slice(&q0))?;
        let mut tilt_down = |max_deg: f64| {
            let az = rng.random_range(0.0..std::f64::consts::TAU);
            let ang = if max_deg > 0.0 {
                rng.random_range(0.0..=max_deg.to_radians())
            } else {
                0.0
            };
            let axis = Unit::new_normalize(Vector3::new(az.cos(), az.sin(), 0.0));
            UnitQuaternion::from_axis_angle(&axis, ang)
        };
        let dir = tilt_down(p.approach_cone_deg) * Vector3::new(0.0, 0.0, -1.0);
        let tilt = tilt_down(p.max_tilt_deg);
        let [d0, d1] = p.port_distance_m;
        let dist = if d1 > d0 { rng.random_range(d0..=d1) } else { d0 };
        let twist = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let port: Point3<f64> = Point3::from(tip.translation.vector) + dir * dist;
        // Straight down: rotate pi about x, so z -> -z; then twist about the axis and tilt.
        let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        let rot = tilt * down * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), twist);
        Ok(Self {
            q0,
            trocar_rest: Isometry3::from_parts(Translation3::from(port.coords), rot),
        })
    }
}

/// Damped least-squares inverse kinematics of the tip onto `point` with its optical axis
/// along `dir` (the roll about the shaft left free), joints kept `margin` inside their
/// limits, the redundancy pulling the joints towards the middle of their ranges. `Some(q)`
/// when it converges to 0.3 mm and 0.3 deg.
fn reach(
    kin: &dyn Kinematics,
    q_start: &JointVector,
    point: &Point3<f64>,
    dir: &Vector3<f64>,
    margin: f64,
) -> Result<Option<JointVector>, SimError> {
    let lim = kin.limits();
    let lo = lim.lower.map(|v| v + margin);
    let hi = lim.upper.map(|v| v - margin);
    let mid = (lim.lower + lim.upper) * 0.5;
    let half = (lim.upper - lim.lower) * 0.5;
    let mut q = q_start.zip_zip_map(&lo, &hi, |v, l, h| v.clamp(l, h));
    for _ in 0..400 {
        let (pose, jac) = kin.fk_jacobian(&q)?;
        let a = pose.rotation * Vector3::z();
        let e_p = point - Point3::from(pose.translation.vector);
        let e_r = a.cross(dir);
        if e_p.norm() < 3e-4 && a.angle(dir) < 0.3f64.to_radians() {
            return Ok(Some(q));
        }
        // Task: position, and the rotation across the optical axis (roll is free).
        let p_a = nalgebra::Matrix3::identity() - a * a.transpose();
        let mut jt = jac;
        let jw = p_a * jac.fixed_rows::<3>(3);
        jt.fixed_rows_mut::<3>(3).copy_from(&jw);
        let mut err = nalgebra::Vector6::zeros();
        err.fixed_rows_mut::<3>(0).copy_from(&(e_p * 0.5));
        err.fixed_rows_mut::<3>(3).copy_from(&(p_a * e_r * 0.5));
        let jjt = jt * jt.transpose() + nalgebra::Matrix6::identity() * 1e-4;
        let Some(chol) = jjt.cholesky() else {
            return Ok(None);
        };
        let dq_task = jt.transpose() * chol.solve(&err);
        let null = nalgebra::SMatrix::<f64, 7, 7>::identity() - jt.transpose() * chol.solve(&jt);
        let centre = (mid - q).component_div(&half) * 0.05;
        let dq = dq_task + null * centre;
        q = (q + dq).zip_zip_map(&lo, &hi, |v, l, h| v.clamp(l, h));
    }
    Ok(None)
}
