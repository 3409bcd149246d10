//! Trials in parallel: the same seeds give the same numbers whatever the thread count.

use std::sync::Arc;

use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::{JointLimits, Kinematics, LbrKinematics};
use trocar_docking::trials::batch::{run_arm, ArmReport};
use trocar_docking::trials::config::{load_controller, SimConfig};
use trocar_docking::trials::run::Outcome;

fn kin() -> Result<Arc<dyn Kinematics>, String> {
    LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())
        .map(|k| Arc::new(k) as Arc<dyn Kinematics>)
        .map_err(|e| e.to_string())
}

fn run(cfg: &SimConfig, ff: bool, threads: usize) -> ArmReport {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    let seeds: Vec<u64> = (10..16).collect();
    let controller = load_controller(None).unwrap();
    let factory = trocar_docking::trials::policy::factory(cfg, &controller, ff, &JointLimits::of_model(LbrModel::Med7));
    let done = std::sync::atomic::AtomicUsize::new(0);
    let tick = || {
        done.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    };
    let r = pool.install(|| run_arm("x", &cfg.sim, &cfg.trial, &kin, &seeds, factory.as_ref(), &tick));
    assert_eq!(done.into_inner(), seeds.len());
    r
}

fn protocol(name: &str) -> SimConfig {
    SimConfig::load_default().unwrap().with_protocol(name).unwrap()
}

#[test]
fn same_seeds_same_numbers_in_parallel() {
    let mut cfg = protocol("realistic");
    cfg.trial.timeout_s = 4.0;
    for ff in [false, true] {
        let a = run(&cfg, ff, 1);
        let b = run(&cfg, ff, 2);
        // Debug text compares NaN (no successes yet) as equal, and every bit of each float.
        assert_eq!(format!("{:?}", a.summary), format!("{:?}", b.summary));
        assert_eq!(format!("{:?}", a.trials), format!("{:?}", b.trials));
        assert_eq!(a.summary.trials, 6);
        assert!(a.trials.iter().all(|t| t.time_s > 0.0 || !t.reason.is_empty()));
    }
}

#[test]
fn force_feedback_lowers_contact_forces() {
    let mut cfg = protocol("paper");
    cfg.trial.timeout_s = 8.0;
    let no_ff = run(&cfg, false, 2);
    let ff = run(&cfg, true, 2);
    let m = |r: &ArmReport| r.trials.iter().map(|t| t.m_true).sum::<f64>();
    let peak = |r: &ArmReport| r.summary.max_force_true_n;
    // Both arms go the whole way in: DONE, or held at the goal on the depth's uncertainty
    // (the paper world's pose noise; control::docking::depth), so M covers whole insertions.
    let inserted = |r: &ArmReport| {
        r.trials
            .iter()
            .filter(|t| matches!(t.outcome, Outcome::Docked | Outcome::DepthUncertain))
            .count()
    };
    assert!(
        inserted(&no_ff) >= 5 && inserted(&ff) >= 5,
        "inserted without FF {}, with {}",
        inserted(&no_ff),
        inserted(&ff)
    );
    assert!(
        m(&ff) < 0.7 * m(&no_ff),
        "M with FF {} vs without {}",
        m(&ff),
        m(&no_ff)
    );
    assert!(peak(&ff) < peak(&no_ff));
}
