//! The policies the trials run, by arm of the comparison.

use super::baseline::Baseline;
use super::batch::PolicyFactory;
use super::config::{PolicyKind, SimConfig};
use super::controller_policy::ControllerPolicy;
use super::run::Policy;
use crate::control::ControllerParams;
use crate::kinematics::JointLimits;

/// The controller's parameters for one arm: `controller` (normally `config/controller.yaml`)
/// unchanged but for `force_feedback`.
pub fn controller_params(controller: &ControllerParams, ff: bool) -> ControllerParams {
    ControllerParams {
        force_feedback: ff,
        ..controller.clone()
    }
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
            let params = controller_params(controller, ff);
            let limits = limits.clone();
            Box::new(move |_seed| ControllerPolicy::new(&params, &limits).map(|p| Box::new(p) as Box<dyn Policy>))
        }
    }
}
