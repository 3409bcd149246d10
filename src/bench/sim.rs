//! Simulator suite: one physics step (free and in contact) and the closed loop (physics at
//! 1 kHz + the trial policy at its control rate), with its real-time factor on one core.

use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Isometry3, Translation3};

use super::{time_each, LatencyStats, SuiteReport};
use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::{Kinematics, LbrKinematics};
use crate::sim::scenario::Scenario;
use crate::sim::{SimError, SimWorld};
use crate::trials::config::SimConfig;
use crate::trials::run::run_trial;

/// A world whose tip sits 20 mm deep in the port, 3 mm off its axis: the shaft presses
/// the bore wall (1 mm clearance) along its length.
pub fn world_in_contact(cfg: &SimConfig, kin: Arc<dyn Kinematics>, seed: u64) -> Result<SimWorld, SimError> {
    let free = SimWorld::new(&cfg.sim, kin.clone(), seed)?;
    let tip = free.tip_pose();
    let port = tip
        * Isometry3::from_parts(
            Translation3::new(0.003, 0.0, -0.02),
            nalgebra::UnitQuaternion::identity(),
        );
    let scenario = Scenario {
        q0: free.scenario().q0,
        trocar_rest: port,
    };
    SimWorld::with_scenario(&cfg.sim, kin, &scenario, seed)
}

fn step_latency(world: &mut SimWorld, n: usize) -> Option<LatencyStats> {
    let idx: Vec<usize> = (0..n.max(1)).collect();
    let t = time_each(&idx, 100, |_| world.step_physics().is_ok());
    LatencyStats::from_samples(&t)
}

/// Run the suite: `n` physics steps per step benchmark, `trials` closed-loop trials per arm.
pub fn run(
    cfg: &SimConfig,
    n: usize,
    trials: usize,
) -> Result<Vec<SuiteReport>, Box<dyn std::error::Error + Send + Sync>> {
    let kin: Arc<dyn Kinematics> = Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())?);
    let mut out = vec![];
    let mut free = SimWorld::new(&cfg.sim, kin.clone(), 1)?;
    if let Some(latency) = step_latency(&mut free, n) {
        out.push(SuiteReport {
            name: "sim_physics_step_free".into(),
            latency,
            extra: Default::default(),
        });
    }
    let mut contact = world_in_contact(cfg, kin.clone(), 1)?;
    contact.step(0.05)?;
    let touching = contact.contact().contacts;
    if let Some(latency) = step_latency(&mut contact, n) {
        let mut extra = serde_json::Map::new();
        extra.insert("spheres_in_contact".into(), touching.into());
        extra.insert("force_n".into(), contact.contact().force.norm().into());
        out.push(SuiteReport {
            name: "sim_physics_step_contact".into(),
            latency,
            extra,
        });
    }
    let controller = crate::trials::config::load_controller(None)?;
    for ff in [false, true] {
        let factory = crate::trials::policy::factory(cfg, &controller, ff, kin.limits());
        let mut per_sim_second = vec![];
        let (mut wall, mut simulated) = (0.0, 0.0);
        for seed in 1..=trials.max(1) as u64 {
            let mut world = SimWorld::new(&cfg.sim, kin.clone(), seed)?;
            let Ok(mut policy) = factory(seed) else {
                continue;
            };
            let t0 = Instant::now();
            let r = run_trial(&mut world, policy.as_mut(), &cfg.trial, seed);
            let dt = t0.elapsed().as_secs_f64();
            if r.time_s > 0.0 {
                per_sim_second.push(dt / r.time_s * 1e6);
                wall += dt;
                simulated += r.time_s;
            }
        }
        let Some(latency) = LatencyStats::from_samples(&per_sim_second) else {
            continue;
        };
        let mut extra = serde_json::Map::new();
        extra.insert("trials".into(), per_sim_second.len().into());
        extra.insert("simulated_s".into(), simulated.into());
        extra.insert("wall_s".into(), wall.into());
        extra.insert("real_time_factor".into(), (simulated / wall.max(1e-12)).into());
        extra.insert("unit".into(), "µs of wall time per simulated second, per trial".into());
        out.push(SuiteReport {
            name: format!("closed_loop_{}", if ff { "ff" } else { "no_ff" }),
            latency,
            extra,
        });
    }
    Ok(out)
}
