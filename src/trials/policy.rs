//! The policies the trials run, by arm of the comparison.

use super::baseline::Baseline;
use super::batch::PolicyFactory;
use super::config::{PolicyKind, SimConfig};
use super::controller_policy::ControllerPolicy;
use super::run::Policy;
use crate::kinematics::JointLimits;

/// The policy factory of one arm: with (`ff`) or without force feedback, everything else
/// equal. `limits` are the arm's joint limits (for the controller's guard).
pub fn factory(c: &SimConfig, ff: bool, limits: &JointLimits) -> Box<PolicyFactory> {
    let depth = c.trial.goal_depth_m;
    let period = 1.0 / c.trial.control_rate_hz;
    match c.policy {
        PolicyKind::Baseline => {
            let params = c.baseline.clone();
            Box::new(move |_seed| Ok(Box::new(Baseline::new(&params, depth, period, ff)) as Box<dyn Policy>))
        }
        PolicyKind::Controller => {
            let mut params = c.controller.clone();
            params.dt = period;
            params.force_feedback = ff;
            let limits = limits.clone();
            Box::new(move |_seed| ControllerPolicy::new(&params, &limits).map(|p| Box::new(p) as Box<dyn Policy>))
        }
    }
}
