//! The policies the trials run, by arm of the comparison.

use super::baseline::Baseline;
use super::config::SimConfig;
use super::trial::Policy;
use super::trials::PolicyFactory;

/// The policy factory of one arm: with (`ff`) or without force feedback.
pub fn factory(c: &SimConfig, ff: bool) -> Box<PolicyFactory> {
    let depth = c.trial.goal_depth_m;
    let period = 1.0 / c.trial.control_rate_hz;
    let params = c.baseline.clone();
    Box::new(move |_seed| Ok(Box::new(Baseline::new(&params, depth, period, ff)) as Box<dyn Policy>))
}
