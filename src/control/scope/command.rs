//! After docking: the surgeon steers the scope through the port, held as a remote centre
//! of motion (RCM). This module holds the types the controller and the nodes share:
//! the surgeon's [`ScopeCommand`] (from `/docking/scope_command`), the limits that stop a
//! command ([`ScopeLimit`]), their parameters ([`ScopeParams`]) and what the controller
//! reports while pivoting ([`PivotReport`]).
//! The law is [`crate::control::scope::pivot`], the fulcrum's adaptation [`crate::control::scope::fulcrum`].

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::control::scope::fulcrum::FulcrumParams;
use crate::control::scope::port_follow::PortFollowParams;
use crate::control::sqp::CostWeights;
use crate::validate::{in_range, non_negative, positive};

/// A surgeon's scope command, in the `endoscope_tip` frame (a `TwistStamped` on
/// `/docking/scope_command`).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ScopeCommand {
    /// Pan about the fulcrum, rad/s (`angular.x`).
    pub pan: f64,
    /// Tilt about the fulcrum, rad/s (`angular.y`).
    pub tilt: f64,
    /// Roll about the shaft, rad/s (`angular.z`).
    pub roll: f64,
    /// In (+) and out (-) along the shaft, m/s (`linear.z`).
    pub zoom: f64,
}

impl ScopeCommand {
    /// Every field finite.
    pub fn is_finite(&self) -> bool {
        [self.pan, self.tilt, self.roll, self.zoom]
            .iter()
            .all(|x| x.is_finite())
    }
}

/// A limit that stopped (part of) a scope command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub enum ScopeLimit {
    /// A commanded speed was above its limit (cut to it).
    Speed,
    /// The insertion depth reached its minimum.
    MinDepth,
    /// The insertion depth reached its maximum.
    MaxDepth,
    /// The shaft reached the edge of the cone about the docking axis.
    Cone,
}

impl ScopeLimit {
    /// A stable code for the status (`scope_limit`).
    pub fn code(&self) -> &'static str {
        match self {
            Self::Speed => "SPEED",
            Self::MinDepth => "MIN_DEPTH",
            Self::MaxDepth => "MAX_DEPTH",
            Self::Cone => "CONE",
        }
    }
}

impl std::fmt::Display for ScopeLimit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Speed => "scope command above the speed limit: cut to it",
            Self::MinDepth => "scope at its minimum insertion depth",
            Self::MaxDepth => "scope at its maximum insertion depth",
            Self::Cone => "scope at the edge of its cone about the docking axis",
        })
    }
}

/// Parameters of steering after docking (`scope:` in `config/controller.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct ScopeParams {
    /// A command older than this counts as none (dead-man), s.
    pub command_timeout_s: f64,
    /// Largest pan and tilt speed about the fulcrum, rad/s.
    pub max_angular_speed_rad_s: f64,
    /// Largest roll speed about the shaft, rad/s.
    pub max_roll_speed_rad_s: f64,
    /// Largest speed along the shaft, m/s.
    pub max_zoom_speed_m_s: f64,
    /// Insertion depth of the tip past the port (the trocar's entry face, where the
    /// docking measured its insertion) along the shaft: minimum, m.
    pub min_depth_m: f64,
    /// ... and maximum, m.
    pub max_depth_m: f64,
    /// Half angle of the cone about the docking axis the shaft stays in, deg.
    pub cone_half_angle_deg: f64,
    /// Weights of c1..c5 while the port is held: c1 tip to the target shaft line, c2 tip
    /// to its target point, c3 optical axis to the target direction, c4 joint step, c5
    /// (the docking's admittance reference) unused: the fulcrum adapts instead.
    pub weights: CostWeights,
    /// Weight of the fulcrum's squared distance from the shaft line (the RCM term), 1/m².
    pub rcm_weight: f64,
    /// Weight of the roll term |x - x_target|² (the tip's x axis).
    pub roll_weight: f64,
    /// Speed of the withdrawal along the shaft (`~retract`), m/s.
    pub retract_speed_m_s: f64,
    /// Force estimate at which a withdrawal brakes to a stop (within the `motion:` limits)
    /// and holds, `FORCE_LIMIT`, N: below the guard's `force_stop_n`, by what the force grows
    /// while the estimate lags and the withdrawal brakes against a stiff obstacle.
    pub retract_force_stop_n: f64,
    /// The arm's tracking lag in position mode, s: after a force stop the arm goes on
    /// towards its last command for about this long, and the force with it. The stop after
    /// docking acts on the force this lag, the estimate's low-passes and one control period
    /// ahead ([`ScopeParams::force_stop_lead`]).
    pub arm_lag_s: f64,
    /// The fulcrum's adaptation from the force across the shaft.
    pub fulcrum: FulcrumParams,
    /// The port's breathing along the docking axis, followed from the trocar estimate.
    pub breathing: PortFollowParams,
}

crate::shipped_defaults!(ScopeParams, crate::config::CONTROLLER, ["scope"]);

impl ScopeParams {
    /// Check every range; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        let pos = |n: &str, v: f64| {
            positive(&format!("scope.{n}"), v)
                .map(|_| ())
                .map_err(|e| e.to_string())
        };
        pos("command_timeout_s", self.command_timeout_s)?;
        pos("max_angular_speed_rad_s", self.max_angular_speed_rad_s)?;
        pos("max_roll_speed_rad_s", self.max_roll_speed_rad_s)?;
        pos("max_zoom_speed_m_s", self.max_zoom_speed_m_s)?;
        pos("retract_speed_m_s", self.retract_speed_m_s)?;
        in_range("scope.retract_force_stop_n", self.retract_force_stop_n, 1.0, 200.0).map_err(|e| e.to_string())?;
        in_range("scope.arm_lag_s", self.arm_lag_s, 0.0, 1.0).map_err(|e| e.to_string())?;
        self.weights.validate("scope.weights")?;
        non_negative("scope.rcm_weight", self.rcm_weight).map_err(|e| e.to_string())?;
        non_negative("scope.roll_weight", self.roll_weight).map_err(|e| e.to_string())?;
        self.fulcrum.validate()?;
        self.breathing.validate()?;
        pos("min_depth_m", self.min_depth_m)?;
        pos("max_depth_m", self.max_depth_m)?;
        if self.max_depth_m <= self.min_depth_m {
            return Err(format!(
                "scope.max_depth_m ({}) must be above scope.min_depth_m ({})",
                self.max_depth_m, self.min_depth_m
            ));
        }
        let c = self.cone_half_angle_deg;
        if !(c.is_finite() && c > 0.0 && c < 90.0) {
            return Err(format!("scope.cone_half_angle_deg must be in (0, 90), got {c}"));
        }
        Ok(())
    }
}

/// What the controller reports while it holds the port as a remote centre of motion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PivotReport {
    /// The fulcrum point (the estimated port, adapted from the contact), base frame, m.
    pub fulcrum: Point3<f64>,
    /// Distance of the shaft's line (the measured tip's optical axis) from the fulcrum, m.
    pub shaft_distance: f64,
    /// Force across the shaft (the controller's estimate), N.
    pub lateral_force: f64,
    /// Tip depth past the port along the shaft (the limits' depth), m.
    pub depth: f64,
    /// Axis of the allowed cone (the docking axis), base frame, unit.
    pub cone_axis: Vector3<f64>,
    /// Half angle of the cone, rad.
    pub cone_half_angle: f64,
    /// A limit that stopped the current command, if any.
    pub limit: Option<ScopeLimit>,
    /// Why the newest scope command was ignored (not finite, stamped in the future), if
    /// it was: the scope then holds still.
    pub ignored: Option<&'static str>,
    /// The fulcrum's adapted depth past the port along the shaft, m.
    pub fulcrum_depth: f64,
    /// The port's breathing followed along the docking axis since DONE, m
    /// ([`crate::control::scope::port_follow`]).
    pub breathing_offset: f64,
}
