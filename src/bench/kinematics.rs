//! Kinematics suite: FK + Jacobian through the KDL bridge at random configurations.

use rand::{RngExt, SeedableRng};

use super::{time_each, LatencyStats, SuiteReport};
use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::{JointVector, Kinematics, KinematicsError, LbrKinematics};

/// Run the suite with `n` samples.
pub fn run(n: usize) -> Result<Vec<SuiteReport>, KinematicsError> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut out = vec![];
    for model in [LbrModel::Med7, LbrModel::Med14] {
        let kin = LbrKinematics::from_model(model, &ToolParams::default())?;
        let lim = kin.limits().clone();
        let qs: Vec<JointVector> = (0..n.max(1))
            .map(|_| JointVector::from_fn(|i, _| rng.random_range(lim.lower[i]..lim.upper[i])))
            .collect();
        let t = time_each(&qs, 1000, |q| {
            kin.fk_jacobian(q).map(|(p, j)| p.translation.x + j[(0, 0)])
        });
        if let Some(latency) = LatencyStats::from_samples(&t) {
            out.push(SuiteReport {
                name: format!("fk_jacobian_{model:?}").to_lowercase(),
                latency,
                extra: Default::default(),
            });
        }
    }
    Ok(out)
}
