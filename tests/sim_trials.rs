//! Trials in parallel: the same seeds give the same numbers whatever the thread count.

use std::sync::Arc;

use trocar_docking::kinematics::{Kinematics, LbrKinematics};
use trocar_docking::robot_model::{LbrModel, ToolParams};
use trocar_docking::sim::config::SimConfig;
use trocar_docking::sim::trials::{run_arm, ArmReport};

fn kin() -> Result<Arc<dyn Kinematics>, String> {
    LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())
        .map(|k| Arc::new(k) as Arc<dyn Kinematics>)
        .map_err(|e| e.to_string())
}

fn run(cfg: &SimConfig, ff: bool, threads: usize) -> ArmReport {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    let seeds: Vec<u64> = (10..14).collect();
    let factory = trocar_docking::sim::policy::factory(cfg, ff);
    let done = std::sync::atomic::AtomicUsize::new(0);
    let tick = || {
        done.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    };
    let r = pool.install(|| run_arm("x", &cfg.sim, &cfg.trial, &kin, &seeds, factory.as_ref(), &tick));
    assert_eq!(done.into_inner(), seeds.len());
    r
}

#[test]
fn same_seeds_same_numbers_in_parallel() {
    let mut cfg = SimConfig::load_default().unwrap();
    cfg.trial.timeout_s = 4.0;
    for ff in [false, true] {
        let a = run(&cfg, ff, 1);
        let b = run(&cfg, ff, 2);
        // Debug text compares NaN (no successes yet) as equal, and every bit of each float.
        assert_eq!(format!("{:?}", a.summary), format!("{:?}", b.summary));
        assert_eq!(format!("{:?}", a.trials), format!("{:?}", b.trials));
        assert_eq!(a.summary.trials, 4);
        assert!(a.trials.iter().all(|t| t.time_s > 0.0 || !t.reason.is_empty()));
    }
}
