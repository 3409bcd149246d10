//! The policies the trials run, by arm of the comparison.

use super::baseline::Baseline;
use super::config::SimConfig;
use super::trial::Policy;
use super::trials::PolicyFactory;

/// The policy factory of one arm: with (`ff`) or without force feedback.
pub fn factory(c: &SimConfig, ff: bool) -> Box<PolicyFactory> {
    let depth = c.trial.goal_depth_m;
    let period = 1.0 / c.trial.control_rate_hz;
    Box::new(move |_seed| {
        if ff {
            Err("the baseline policy has no force feedback".to_string())
        } else {
            Ok(Box::new(Baseline::new(depth, period)) as Box<dyn Policy>)
        }
    })
}
