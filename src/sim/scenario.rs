//! Randomised start of a trial: the arm's start configuration and the trocar's rest pose.
//!
//! q0 = q_nominal + U(-q_spread, q_spread) per joint (q_nominal puts the tip 0.57 m in
//! front of the base, 0.31 m high, pointing down, with room on every joint for the docking
//! pose about 0.15 m lower). The port lies `port_distance_m` from
//! the start tip, in a direction within `approach_cone_deg` of straight down; the trocar's
//! axis (z, into the body) is straight down tilted by U(0, max_tilt_deg) about a random
//! horizontal axis, with a random twist about itself.

use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::RngExt;
use serde::{Deserialize, Serialize};

use super::{check_range, SimError};
use crate::kinematics::{JointVector, Kinematics};

/// Parameters of the randomised start.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ScenarioParams {
    /// Nominal start configuration, rad.
    pub q_nominal: [f64; 7],
    /// Half-range of the uniform perturbation of each joint, rad.
    pub q_spread_rad: f64,
    /// Range of the distance from the start tip to the port, m.
    pub port_distance_m: [f64; 2],
    /// Largest angle of the tip-to-port direction from straight down, deg.
    pub approach_cone_deg: f64,
    /// Largest tilt of the trocar axis from straight down, deg.
    pub max_tilt_deg: f64,
}

impl Default for ScenarioParams {
    fn default() -> Self {
        Self {
            q_nominal: [0.0, 0.45, 0.0, -1.15, 0.0, 1.54, 0.0],
            q_spread_rad: 0.08,
            port_distance_m: [0.10, 0.15],
            approach_cone_deg: 20.0,
            max_tilt_deg: 25.0,
        }
    }
}

impl ScenarioParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        for &q in &self.q_nominal {
            check_range("scenario.q_nominal", q, -std::f64::consts::PI, std::f64::consts::PI)?;
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
        check_range("scenario.max_tilt_deg", self.max_tilt_deg, 0.0, 80.0)
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

    /// Draw a scenario.
    pub fn sample(p: &ScenarioParams, kin: &dyn Kinematics, rng: &mut impl rand::Rng) -> Result<Self, SimError> {
        p.validate()?;
        let lim = kin.limits();
        let s = p.q_spread_rad;
        let mut q0 = p.q_nominal;
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
