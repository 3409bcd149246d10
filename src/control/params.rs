//! Every parameter of the docking controller (`config/controller.yaml`, the one file that
//! the trials, the demo, the rostests and `robot.launch` all run), with its validation.

use serde::{Deserialize, Serialize};

use super::docking::depth::DepthParams;
use super::docking::seated::SeatedParams;
use super::force::admittance::AdmittanceParams;
use super::force::tare::TareParams;
use super::safety::guard::GuardParams;
use super::safety::motion::MotionLimits;
use super::scope::command::ScopeParams;
use super::sqp::{CostWeights, SqpSettings};
use crate::validate;

pub use crate::config::ParamError;

/// What the controller's parameters are called in errors that have no file.
pub const WHAT: &str = "controller parameter";

/// Every parameter of the controller (`config/controller.yaml`); the defaults are that file
/// as built into the binary ([`crate::config::CONTROLLER`], in `config.rs` with the other
/// shipped files, where each section names it too), and a partial file takes the rest from it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct ControllerParams {
    /// Control period, s.
    pub dt_s: f64,
    /// Force feedback on (c5 active with the weights below) or off (w5 = 0).
    pub force_feedback: bool,
    /// Weights during APPROACH.
    pub approach_weights: CostWeights,
    /// Weights during INSERT.
    pub insert_weights: CostWeights,
    /// Goal depth past the port along the axis, m.
    pub insertion_depth_m: f64,
    /// Stand-off distance of the approach point before the port, m.
    pub standoff_m: f64,
    /// Speed of the approach target point, m/s.
    pub approach_speed_m_s: f64,
    /// Speed of the insertion target point, m/s.
    pub insert_speed_m_s: f64,
    /// APPROACH -> INSERT when the tip is this close to the stand-off point, m.
    pub approach_tolerance_m: f64,
    /// ... and the optical axis within this angle of the insertion axis, deg.
    pub approach_angle_tolerance_deg: f64,
    /// DONE when the tip is this close to the goal, m.
    pub goal_tolerance_m: f64,
    /// ... and the optical axis within this angle, deg.
    pub goal_angle_tolerance_deg: f64,
    /// DONE is judged on the tip-to-goal error and the angle averaged over windows of this
    /// length, s, so that one lucky sample of a noisy trocar estimate does not end the
    /// docking (0 = judged on each sample); see [`super::docking::goal_window`].
    pub goal_window_s: f64,
    /// DONE also for a scope seated in the port beside a biased trocar estimate; see
    /// [`super::docking::seated`].
    pub seated: SeatedParams,
    /// The tip's depth: refined at the seal, and DONE only while known; see
    /// [`super::docking::depth`].
    pub depth: DepthParams,
    /// Time constant of a first-order filter on the trocar pose, s (0 = none).
    pub trocar_filter_time_constant_s: f64,
    /// Time constant of the second-order tracking filter on the trocar position along its
    /// axis, s (0 = the first-order filter there too); see [`crate::signal::TrackingFilter`].
    pub trocar_depth_filter_time_constant_s: f64,
    /// Time constant of the first-order low-pass on the external torques at the rate they
    /// arrive (each FRI cycle), s (0 = the newest sample alone); see
    /// [`crate::signal::StreamLowPass`]. Applied by the controller itself, in each step, to
    /// every raw sample since the last ([`crate::control::ControlInput::torque_samples`]).
    pub torque_filter_time_constant_s: f64,
    /// Hold when external torques are missing or stale (force monitoring blind).
    pub require_torques: bool,
    /// After a force stop, back out along the axis by this distance, m (0 = stay).
    pub retreat_distance_m: f64,
    /// Weight of the joint-limit avoidance cost (0 = off); see [`super::sqp::LimitAvoidance`].
    pub limit_avoidance_weight: f64,
    /// Fraction of each joint's half range (inside the guard's margin) where it starts.
    pub limit_avoidance_zone: f64,
    /// Hold (latched) when the tip has sat at the stand-off point this long without
    /// reaching the alignment tolerance (e.g. a joint limit in the way), s.
    pub approach_stall_timeout_s: f64,
    /// Taring the external torques at start, and tracking their offset out of contact.
    pub tare: TareParams,
    /// Force estimate and admittance law.
    pub admittance: AdmittanceParams,
    /// Safety guard.
    pub guard: GuardParams,
    /// Limits of the commanded tip motion (speed, acceleration, jerk).
    pub motion: MotionLimits,
    /// SQP settings.
    pub sqp: SqpSettings,
    /// Steering the scope through the port after docking.
    pub scope: ScopeParams,
}

crate::shipped_defaults!(ControllerParams, crate::config::CONTROLLER, []);

impl ControllerParams {
    /// Parse YAML (missing fields take their defaults) and validate.
    pub fn from_yaml_str(s: &str) -> Result<Self, ParamError> {
        let p: Self = crate::config::from_yaml_str("controller YAML", s)?;
        p.validate().map_err(|e| ParamError::new(WHAT, e))?;
        Ok(p)
    }

    /// Check every range; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        validate::positive_at_most("dt_s", self.dt_s, 0.1)?;
        self.approach_weights.validate("approach_weights")?;
        self.insert_weights.validate("insert_weights")?;
        validate::positive("insertion_depth_m", self.insertion_depth_m)?;
        validate::non_negative("standoff_m", self.standoff_m)?;
        validate::positive("approach_speed_m_s", self.approach_speed_m_s)?;
        validate::positive("insert_speed_m_s", self.insert_speed_m_s)?;
        validate::positive("approach_tolerance_m", self.approach_tolerance_m)?;
        validate::positive("approach_angle_tolerance_deg", self.approach_angle_tolerance_deg)?;
        validate::positive("goal_tolerance_m", self.goal_tolerance_m)?;
        validate::positive("goal_angle_tolerance_deg", self.goal_angle_tolerance_deg)?;
        validate::non_negative("goal_window_s", self.goal_window_s)?;
        self.seated.validate()?;
        self.depth.validate()?;
        validate::non_negative("trocar_filter_time_constant_s", self.trocar_filter_time_constant_s)?;
        validate::non_negative(
            "trocar_depth_filter_time_constant_s",
            self.trocar_depth_filter_time_constant_s,
        )?;
        validate::non_negative("torque_filter_time_constant_s", self.torque_filter_time_constant_s)?;
        validate::non_negative("retreat_distance_m", self.retreat_distance_m)?;
        validate::non_negative("limit_avoidance_weight", self.limit_avoidance_weight)?;
        validate::positive("approach_stall_timeout_s", self.approach_stall_timeout_s)?;
        if !(0.0..1.0).contains(&self.limit_avoidance_zone) {
            return Err(format!(
                "limit_avoidance_zone must be in [0, 1), got {}",
                self.limit_avoidance_zone
            ));
        }
        self.tare.validate()?;
        self.admittance.validate()?;
        self.guard.validate()?;
        self.motion.validate()?;
        self.scope.validate()?;
        if self.scope.retract_force_stop_n > self.guard.force_stop_n {
            return Err(format!(
                "scope.retract_force_stop_n ({} N) must not be above guard.force_stop_n ({} N)",
                self.scope.retract_force_stop_n, self.guard.force_stop_n
            ));
        }
        if self.motion.max_angular_accel_rad_s2 > self.guard.max_acceleration_rad_s2 {
            return Err(format!(
                "motion.max_angular_accel_rad_s2 ({} rad/s^2) must not be above guard.max_acceleration_rad_s2 \
                 ({} rad/s^2): the arm could not follow the shaped motion",
                self.motion.max_angular_accel_rad_s2, self.guard.max_acceleration_rad_s2
            ));
        }
        self.sqp.validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_file_parses_validates_and_is_every_default() {
        let p = ControllerParams::from_yaml_str(crate::config::CONTROLLER_YAML).unwrap();
        p.validate().unwrap();
        assert_eq!(p, ControllerParams::default());
        assert_eq!(p.seated, SeatedParams::default());
        assert_eq!(p.depth, DepthParams::default());
        assert_eq!(p.tare, TareParams::default());
        assert_eq!(p.admittance, AdmittanceParams::default());
        assert_eq!(p.guard, GuardParams::default());
        assert_eq!(p.motion, MotionLimits::default());
        assert_eq!(p.sqp, SqpSettings::default());
        assert_eq!(p.scope, ScopeParams::default());
        assert_eq!(p.scope.fulcrum, super::super::scope::fulcrum::FulcrumParams::default());
        assert_eq!(
            p.scope.breathing,
            super::super::scope::port_follow::PortFollowParams::default()
        );
        // Figures of the file itself, so that the defaults are read, not made up.
        assert_eq!(
            (p.dt_s, p.guard.force_stop_n, p.scope.fulcrum.prior_depth_m),
            (0.01, 20.0, 0.02)
        );
    }

    #[test]
    fn a_shaped_angular_acceleration_above_the_joints_limit_is_refused() {
        let mut p = ControllerParams::default();
        assert!(p.motion.max_angular_accel_rad_s2 <= p.guard.max_acceleration_rad_s2);
        p.motion.max_angular_accel_rad_s2 = 10.0;
        let e = p.validate().unwrap_err();
        assert!(
            e.contains("motion.max_angular_accel_rad_s2") && e.contains("guard.max_acceleration_rad_s2"),
            "{e}"
        );
        p.guard.max_acceleration_rad_s2 = 10.0;
        p.validate().unwrap();
    }

    #[test]
    fn a_partial_file_takes_the_rest_from_the_shipped_one_and_unknown_keys_are_named() {
        let d = ControllerParams::default();
        for empty in ["", "# nothing\n", "guard: ~\n", "scope: {fulcrum: {}}\n"] {
            assert_eq!(ControllerParams::from_yaml_str(empty).unwrap(), d, "{empty:?}");
        }
        let p =
            ControllerParams::from_yaml_str("guard: {force_stop_n: 15}\nscope: {fulcrum: {stiffness_n_per_m: 7}}\n")
                .unwrap();
        assert_eq!(p.guard.force_stop_n, 15.0);
        assert_eq!(p.scope.fulcrum.stiffness_n_per_m, 7.0);
        let same_rest = ControllerParams {
            guard: GuardParams {
                force_stop_n: d.guard.force_stop_n,
                ..p.guard.clone()
            },
            scope: ScopeParams {
                fulcrum: d.scope.fulcrum.clone(),
                ..p.scope.clone()
            },
            ..p.clone()
        };
        assert_eq!(same_rest, d);
        for (text, key) in [
            ("guard: {force_stp: 15}\n", "guard.force_stp"),
            ("scope: {fulcrum: {stiffnes: 1}}\n", "scope.fulcrum.stiffnes"),
            ("no_such_field: 1\n", "no_such_field"),
        ] {
            let e = ControllerParams::from_yaml_str(text).unwrap_err().to_string();
            assert!(e.contains(&format!("`{key}`: unknown key")), "{e}");
        }
        let e = ControllerParams::from_yaml_str("guard: {force_stop_n: fast}\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("`guard`: invalid type"), "{e}");
        let e = ControllerParams::from_yaml_str("scope: {fulcrum: {stiffness_n_per_m: []}}\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("`scope.fulcrum`: invalid type"), "{e}");
        // A section read on its own names its keys the same way.
        let e = crate::config::from_yaml_str::<GuardParams>("g", "force_stp: 1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("`guard.force_stp`: unknown key"), "{e}");
        // The same from a parameter tree (what the ROS parameter server gives), integers as floats.
        let p: ControllerParams = serde_json::from_value(serde_json::json!({"guard": {"force_stop_n": 15}})).unwrap();
        assert_eq!(p.guard.force_stop_n, 15.0);
        assert_eq!(p.guard.velocity_scale, d.guard.velocity_scale);
    }

    #[test]
    fn an_old_key_is_refused_naming_its_new_name() {
        for (text, message) in [
            ("dt: 0.001\n", "`dt`: the key is now `dt_s`"),
            (
                "guard: {force_stop: 15}\n",
                "`guard.force_stop`: the key is now `guard.force_stop_n`",
            ),
            (
                "scope: {breathing: {max_speed: 0.01}}\n",
                "`scope.breathing.max_speed`: the key is now `scope.breathing.max_speed_m_s`",
            ),
        ] {
            let e = ControllerParams::from_yaml_str(text).unwrap_err().to_string();
            assert!(e.contains(message), "{e}");
        }
        // A section read on its own names the same path.
        let e = crate::config::from_yaml_str::<MotionLimits>("m", "max_accel: 1\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`motion.max_accel`: the key is now `motion.max_accel_m_s2`"),
            "{e}"
        );
        // Every old key is gone from the file, every new one (a removed key has none) is in it.
        let shipped = crate::config::CONTROLLER.section(&[]);
        for r in crate::config::CONTROLLER_RENAMED {
            let at = |path: &str| path.split('.').try_fold(shipped, |node, key| node.get(key)).is_some();
            assert!(!at(r.old) && (r.new.is_empty() || at(r.new)), "{} -> {}", r.old, r.new);
        }
    }
}
