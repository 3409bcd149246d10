//! The policies the trials run, by arm of the comparison.

use super::baseline::Baseline;
use super::batch::PolicyFactory;
use super::config::{PolicyKind, SimConfig};
use super::controller_policy::ControllerPolicy;
use super::run::Policy;
use crate::control::ControllerParams;
use crate::kinematics::JointLimits;

/// The controller's parameters for one arm in the world `c`: `controller` (normally
/// `config/controller.yaml`) unchanged but for `force_feedback` and the hand-eye
/// calibration's stated error bound (`depth.hand_eye_error_m`, `depth.hand_eye_error_deg`),
/// which is the world's (`measurement.bias_position_m`, `bias_rotation_rad`): what a lab's
/// calibration reports of itself, not a tuning (the realistic world's 2 mm / 1 deg is the
/// shipped value; the paper's world has none).
pub fn controller_params(controller: &ControllerParams, c: &SimConfig, ff: bool) -> ControllerParams {
    let m = &c.sim.measurement;
    let mut p = ControllerParams {
        force_feedback: ff,
        ..controller.clone()
    };
    p.depth.hand_eye_error_m = m.bias_position_m;
    p.depth.hand_eye_error_deg = m.bias_rotation_rad.to_degrees();
    p
}

/// The policy factory of one arm: with (`ff`) or without force feedback, everything else
/// equal. `controller` is the controller's configuration (its `dt_s` the control period of
/// either arm); `limits` are the arm's joint limits (for the controller's guard).
pub fn factory(c: &SimConfig, controller: &ControllerParams, ff: bool, limits: &JointLimits) -> Box<PolicyFactory> {
    let depth = c.trial.goal_depth_m;
    let period = controller.dt_s;
    match c.policy {
        PolicyKind::Baseline => {
            let params = c.baseline.clone();
            Box::new(move |_seed| Ok(Box::new(Baseline::new(&params, depth, period, ff)) as Box<dyn Policy>))
        }
        PolicyKind::Controller => {
            let params = controller_params(controller, c, ff);
            let limits = limits.clone();
            Box::new(move |_seed| ControllerPolicy::new(&params, &limits).map(|p| Box::new(p) as Box<dyn Policy>))
        }
    }
}
