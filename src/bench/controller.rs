//! Controller suite: the time of one control step (FK + Jacobian of the measured joints,
//! force estimate, SQP to tolerance with FK + Jacobian per iteration, guard), in closed loop
//! with perfect tracking, dt = 0.01 s, default weights (`config/controller.yaml`), on two
//! scenarios: a docking approach to a static trocar, and a trocar whose port oscillates
//! laterally 5 mm at 0.5 Hz, so that every step has work to do.

use std::time::Instant;

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};

use super::{LatencyStats, SuiteReport};
use crate::controller::{ControlInput, Controller, ControllerParams, Stamped};
use crate::kinematics::{JointVector, Kinematics, KinematicsError, LbrKinematics};
use crate::robot_model::{LbrModel, ToolParams};

/// A benchmark scenario.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scenario {
    /// Static trocar 0.15 m from the tip, 20° misaligned.
    Approach,
    /// The same trocar, its port oscillating laterally ±5 mm at 0.5 Hz.
    Oscillating,
}

impl Scenario {
    /// Name used in reports.
    pub fn name(&self) -> &'static str {
        match self {
            Scenario::Approach => "controller_step_static_trocar",
            Scenario::Oscillating => "controller_step_oscillating_trocar",
        }
    }
}

/// The start configuration of the benchmark and the trocar pose at time `t`.
pub fn scenario_trocar(
    kin: &dyn Kinematics,
    scenario: Scenario,
    t: f64,
) -> Result<(JointVector, Isometry3<f64>), KinematicsError> {
    let q0 = JointVector::from_column_slice(&[0.0, 0.6, 0.0, -1.2, 0.0, 0.9, 0.0]);
    let tip = kin.fk(&q0)?;
    let a0 = tip.rotation * Vector3::z();
    let about = Unit::new_normalize(Vector3::new(0.3, 1.0, 0.0));
    let g = UnitQuaternion::from_axis_angle(&about, 20f64.to_radians()) * a0;
    let toward = UnitQuaternion::from_axis_angle(&about, 10f64.to_radians()) * a0;
    let mut port = tip.translation.vector + toward * 0.15;
    if scenario == Scenario::Oscillating {
        let lateral = g.cross(&Vector3::z()).normalize();
        port += lateral * 0.005 * (2.0 * std::f64::consts::PI * 0.5 * t).sin();
    }
    let rot = UnitQuaternion::rotation_between(&Vector3::z(), &g).unwrap_or_else(UnitQuaternion::identity);
    Ok((q0, Isometry3::from_parts(Translation3::from(port), rot)))
}

/// Run `steps` closed-loop control steps of `scenario`; returns per-step times (µs) and
/// iterations. The loop restarts the docking when it completes, so every sample is a
/// moving step.
pub fn run_scenario(
    kin: &LbrKinematics,
    params: &ControllerParams,
    scenario: Scenario,
    steps: usize,
) -> Result<(Vec<f64>, Vec<usize>), String> {
    let mut c = Controller::new(params.clone(), kin.limits().clone()).map_err(|e| e.to_string())?;
    c.start()?;
    let (q0, _) = scenario_trocar(kin, scenario, 0.0).map_err(|e| e.to_string())?;
    let mut q = q0;
    let mut times = Vec::with_capacity(steps);
    let mut iters = Vec::with_capacity(steps);
    let mut now = 0.0;
    while times.len() < steps {
        now += params.dt;
        let (_, trocar) = scenario_trocar(kin, scenario, now).map_err(|e| e.to_string())?;
        let input = ControlInput {
            now,
            joints: Some(Stamped { stamp: now, value: q }),
            tau_ext: Some(Stamped {
                stamp: now,
                value: JointVector::zeros(),
            }),
            trocar: Some(Stamped {
                stamp: now,
                value: trocar,
            }),
        };
        let t0 = Instant::now();
        let out = c.step(kin, &input);
        let us = t0.elapsed().as_secs_f64() * 1e6;
        if !out.phase.is_moving() {
            // Docked (or held): start over from the initial configuration.
            c.reset();
            c.start()?;
            q = q0;
            continue;
        }
        times.push(us);
        iters.push(out.iterations);
        q = out.command.unwrap_or(q);
    }
    Ok((times, iters))
}

/// Run the suite with `n` steps per scenario.
pub fn run(n: usize) -> Result<Vec<SuiteReport>, String> {
    let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).map_err(|e| e.to_string())?;
    let params = ControllerParams::default();
    let mut out = vec![];
    for scenario in [Scenario::Approach, Scenario::Oscillating] {
        let (times, iters) = run_scenario(&kin, &params, scenario, n.max(10))?;
        let Some(latency) = LatencyStats::from_samples(&times) else {
            continue;
        };
        let mut extra = serde_json::Map::new();
        let mean_it = iters.iter().sum::<usize>() as f64 / iters.len().max(1) as f64;
        extra.insert("mean_iterations".into(), serde_json::json!(mean_it));
        extra.insert("max_iterations".into(), serde_json::json!(iters.iter().max()));
        extra.insert("dt_s".into(), serde_json::json!(params.dt));
        extra.insert(
            "deadline_misses_1ms".into(),
            serde_json::json!(times.iter().filter(|t| **t >= 1000.0).count()),
        );
        out.push(SuiteReport {
            name: scenario.name().into(),
            latency,
            extra,
        });
    }
    Ok(out)
}
