//! After docking, closed loop on the realistic simulated plant (`config/sim.yaml`'s
//! `realistic` protocol, the shipped `config/controller.yaml`): issue 16's "Done when"
//! sequence, the fulcrum's adaptation, retract.

use std::sync::Arc;

use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::{Kinematics, LbrKinematics};
use trocar_docking::trials::config::{load_controller, SimConfig};
use trocar_docking::trials::pivot::{done_when_script, run_pivot, PivotResult, PivotTiming};

fn kin() -> Arc<dyn Kinematics> {
    Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap())
}

fn realistic() -> SimConfig {
    SimConfig::load_default().unwrap().with_protocol("realistic").unwrap()
}

fn run(seed: u64) -> PivotResult {
    let cfg = realistic();
    let path = std::env::var("PIVOT_CONTROLLER").ok().map(std::path::PathBuf::from);
    let controller = load_controller(path.as_deref()).unwrap();
    run_pivot(
        &cfg.sim,
        &cfg.trial,
        &controller,
        kin(),
        seed,
        &done_when_script(),
        &PivotTiming::default(),
    )
    .unwrap()
}

#[test]
fn explore() {
    for seed in [3] {
        let r = run(seed);
        eprintln!("{}", serde_json::to_string(&r).unwrap());
    }
}
