//! Controller suite: the time of one control step (FK + Jacobian of the measured joints,
//! force estimate, SQP to tolerance with FK + Jacobian per iteration, guard), in closed loop
//! with perfect tracking, dt = 0.01 s, the default parameters (`config/controller.yaml`)
//! unless others are given, on two scenarios: a docking approach to a static trocar, and a
//! trocar whose port oscillates laterally 5 mm at 0.5 Hz, so that every step has work to do.
//!
//! Each step is timed on the wall clock and on the thread's CPU clock. A step slow on the
//! wall clock only was preempted by the OS. One slow on both either did more work (see its
//! interior-point iterations) or ran on a slowed CPU: in a virtual machine the guest's CPU
//! clock also runs while the hypervisor has the vCPU descheduled, and a busy sibling
//! hardware thread slows it too, so the iteration count is the algorithm's own measure.
//!
//! **What is sampled.** Every APPROACH and INSERT step with a solve. Left out, each counted
//! by class in the report's `excluded_steps` ([`Excluded`]): the TARE steps at each start
//! (0.3 s: 29-30 steps of the arm held still, no solve), the step that ends the tare (it
//! reports APPROACH without a solve), and the step that ends a docking (DONE or a hold), after
//! which the run starts over.

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};

use super::{scheduler_name, time_wall_and_cpu, LatencyStats, SuiteReport, Timed};
use crate::control::sqp::SqpStatus;
use crate::control::Phase;
use crate::control::{Controller, ControllerParams};
use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::{JointVector, Kinematics, KinematicsError, LbrKinematics};
use crate::sim::noise::TrocarMeasurement;
use crate::trials::closed_loop::{control_input, Observation};

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

/// Per-step measurements of one scenario run, in step order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ScenarioSamples {
    /// Wall-clock time of each step, µs.
    pub wall_us: Vec<f64>,
    /// Thread CPU time of each step, µs (NaN where the clock is unavailable).
    pub cpu_us: Vec<f64>,
    /// QPs solved in each step.
    pub iterations: Vec<usize>,
    /// Interior-point iterations in each step, over all its QPs.
    pub qp_iterations: Vec<u32>,
    /// QPs of each step that Clarabel solved (the others from a proven active set).
    pub clarabel_qps: Vec<usize>,
    /// Steps whose SQP stopped at its time budget.
    pub time_budget_steps: usize,
    /// Steps whose SQP stopped at its interior-point iteration budget.
    pub qp_iteration_budget_steps: usize,
    /// Steps run but not sampled, by class (see [`Excluded`]).
    pub excluded: Excluded,
}

/// The steps a scenario run steps the controller through but leaves out of its samples,
/// each class counted: none is the loop under test (the SQP).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Excluded {
    /// TARE steps: the arm held still while the torques are averaged, at every start.
    pub tare: usize,
    /// Moving steps without a solve (the step that ends the tare reports APPROACH).
    pub moving_without_solve: usize,
    /// Steps that ended a docking (DONE, or a hold), after which the run starts over.
    pub ended: usize,
}

impl Excluded {
    /// All excluded steps.
    pub fn total(&self) -> usize {
        self.tare + self.moving_without_solve + self.ended
    }
}

/// Run `steps` closed-loop control steps of `scenario` and time each one (wall clock and
/// thread CPU). The loop restarts the docking when it completes, so every sample is a
/// moving step with a solve, the first one after construction included; the steps left out
/// (each start's tare, the step ending it, the step that ends a docking) are counted by
/// class in [`ScenarioSamples::excluded`].
pub fn run_scenario(
    kin: &LbrKinematics,
    params: &ControllerParams,
    scenario: Scenario,
    steps: usize,
) -> Result<ScenarioSamples, String> {
    let mut c = Controller::new(params.clone(), kin.limits().clone()).map_err(|e| e.to_string())?;
    c.start()?;
    let (q0, _) = scenario_trocar(kin, scenario, 0.0).map_err(|e| e.to_string())?;
    let mut q = q0;
    let mut s = ScenarioSamples {
        wall_us: Vec::with_capacity(steps),
        cpu_us: Vec::with_capacity(steps),
        iterations: Vec::with_capacity(steps),
        qp_iterations: Vec::with_capacity(steps),
        clarabel_qps: Vec::with_capacity(steps),
        ..Default::default()
    };
    let mut now = 0.0;
    let mut restarts = 0usize;
    while s.wall_us.len() < steps {
        now += params.dt_s;
        let (_, trocar) = scenario_trocar(kin, scenario, now).map_err(|e| e.to_string())?;
        // An ideal arm (at its command, no contact): the controller's own time alone.
        let seen = Observation {
            t: now,
            q,
            tau_ext: JointVector::zeros(),
            torque_samples: Default::default(),
            trocar: Some(TrocarMeasurement {
                stamp: now,
                pose: trocar,
            }),
        };
        let input = control_input(&seen, None);
        let Timed {
            value: out,
            wall_us: wall,
            cpu_us: cpu,
        } = time_wall_and_cpu(|| c.step(kin, &input));
        if out.phase == Phase::Tare {
            // The torque tare at each start holds the arm still: not the loop under test.
            s.excluded.tare += 1;
            continue;
        }
        if out.phase.is_moving() && out.solve.is_none() {
            // The tare's last step, which ends in APPROACH.
            s.excluded.moving_without_solve += 1;
            continue;
        }
        if !out.phase.is_moving() {
            s.excluded.ended += 1;
            // Docked (or held): start over from the initial configuration.
            restarts += 1;
            if restarts > steps {
                return Err(format!(
                    "{}: no progress ({:?}: {:?})",
                    scenario.name(),
                    out.phase,
                    out.reason_text()
                ));
            }
            c.reset();
            c.start()?;
            q = q0;
            continue;
        }
        s.wall_us.push(wall);
        s.cpu_us.push(cpu);
        let solve = out.solve.as_ref();
        s.iterations.push(solve.map_or(0, |r| r.iterations));
        s.qp_iterations.push(solve.map_or(0, |r| r.qp_iterations));
        s.clarabel_qps.push(solve.map_or(0, |r| r.clarabel_qps));
        s.time_budget_steps += usize::from(solve.is_some_and(|r| r.status == SqpStatus::TimeBudget));
        s.qp_iteration_budget_steps += usize::from(solve.is_some_and(|r| r.status == SqpStatus::QpIterationBudget));
        q = out.command.unwrap_or(q);
    }
    Ok(s)
}

/// The control deadline the suite counts misses of, µs (a 1 kHz FRI period).
pub const DEADLINE_US: f64 = 1000.0;

fn misses(samples_us: &[f64]) -> usize {
    samples_us.iter().filter(|t| **t >= DEADLINE_US).count()
}

fn mean<T: Copy + Into<f64>>(v: &[T]) -> f64 {
    v.iter().map(|x| (*x).into()).sum::<f64>() / v.len().max(1) as f64
}

/// Per-step counts as `u32`, for [`mean`] (saturating; a step never does 4e9 QPs).
fn counts(v: &[usize]) -> Vec<u32> {
    v.iter().map(|i| u32::try_from(*i).unwrap_or(u32::MAX)).collect()
}

/// The report of one scenario run with `params`: wall-clock statistics as the latency,
/// thread-CPU statistics and the solver's work as extra figures.
pub fn report(name: &str, params: &ControllerParams, s: &ScenarioSamples) -> Option<SuiteReport> {
    let latency = LatencyStats::from_samples(&s.wall_us)?;
    let worst = s
        .wall_us
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map_or(0, |(i, _)| i);
    let iterations = counts(&s.iterations);
    let mut extra = serde_json::Map::new();
    let mut put = |k: &str, v: serde_json::Value| {
        extra.insert(k.into(), v);
    };
    put("cpu_time", serde_json::json!(LatencyStats::from_samples(&s.cpu_us)));
    put("deadline_misses_1ms", serde_json::json!(misses(&s.wall_us)));
    put("deadline_misses_1ms_cpu", serde_json::json!(misses(&s.cpu_us)));
    put("mean_iterations", serde_json::json!(mean(&iterations)));
    put("max_iterations", serde_json::json!(iterations.iter().max()));
    put("mean_qp_iterations", serde_json::json!(mean(&s.qp_iterations)));
    put("max_qp_iterations", serde_json::json!(s.qp_iterations.iter().max()));
    let clarabel_qps = counts(&s.clarabel_qps);
    put("mean_clarabel_qps", serde_json::json!(mean(&clarabel_qps)));
    // The steps where Clarabel solved at least one QP, timed apart: the warm start's
    // misses, the slow tail of the distribution.
    let with_clarabel: Vec<f64> = s
        .wall_us
        .iter()
        .zip(&s.clarabel_qps)
        .filter(|(_, c)| **c > 0)
        .map(|(t, _)| *t)
        .collect();
    put(
        "clarabel_steps",
        serde_json::json!({"count": with_clarabel.len(), "wall": LatencyStats::from_samples(&with_clarabel)}),
    );
    put(
        "sqp_active_set_warm_start",
        serde_json::json!(params.sqp.active_set_warm_start),
    );
    put("time_budget_steps", serde_json::json!(s.time_budget_steps));
    put(
        "qp_iteration_budget_steps",
        serde_json::json!(s.qp_iteration_budget_steps),
    );
    put(
        "first_step_us",
        serde_json::json!({"wall": s.wall_us.first(), "cpu": s.cpu_us.first()}),
    );
    put(
        "worst_step",
        serde_json::json!({
            "index": worst,
            "wall_us": s.wall_us.get(worst),
            "cpu_us": s.cpu_us.get(worst),
            "iterations": s.iterations.get(worst),
            "qp_iterations": s.qp_iterations.get(worst),
            "clarabel_qps": s.clarabel_qps.get(worst),
        }),
    );
    put(
        "excluded_steps",
        serde_json::json!({
            "tare": s.excluded.tare,
            "moving_without_solve": s.excluded.moving_without_solve,
            "ended_docking": s.excluded.ended,
            "total": s.excluded.total(),
        }),
    );
    put("steps_run", serde_json::json!(s.wall_us.len() + s.excluded.total()));
    put("scheduler", serde_json::json!(scheduler_name()));
    put("dt_s", serde_json::json!(params.dt_s));
    put("sqp_time_budget_us", serde_json::json!(params.sqp.time_budget_us));
    put(
        "sqp_max_total_qp_iterations",
        serde_json::json!(params.sqp.max_total_qp_iterations),
    );
    Some(SuiteReport {
        name: name.into(),
        latency,
        extra,
    })
}

/// Run the suite with `n` steps per scenario and the controller's `params`.
pub fn run(n: usize, params: &ControllerParams) -> Result<Vec<SuiteReport>, String> {
    let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).map_err(|e| e.to_string())?;
    let mut out = vec![];
    for scenario in [Scenario::Approach, Scenario::Oscillating] {
        let samples = run_scenario(&kin, params, scenario, n.max(10))?;
        out.extend(report(scenario.name(), params, &samples));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn figure(r: &SuiteReport, key: &str) -> f64 {
        r.extra[key]
            .as_f64()
            .unwrap_or_else(|| panic!("{key} in {:?}", r.extra))
    }

    #[test]
    fn reports_both_scenarios_with_the_solvers_work() {
        let params = ControllerParams::default();
        let reports = run(200, &params).unwrap();
        let names: Vec<&str> = reports.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(names, [Scenario::Approach.name(), Scenario::Oscillating.name()]);
        for r in &reports {
            assert_eq!(r.latency.samples, 200);
            assert!(r.latency.median_us > 0.0 && r.latency.median_us <= r.latency.max_us);
            let qps = figure(r, "mean_iterations");
            assert!((1.0..=3.0).contains(&qps), "{qps}");
            // With the warm start most QPs never reach Clarabel.
            let clarabel = figure(r, "mean_clarabel_qps");
            assert!(clarabel < 0.5 * qps, "{clarabel} of {qps}");
            let n = r.extra["clarabel_steps"]["count"].as_u64().unwrap();
            assert!(n > 0 && n < 200, "{n}");
            // Every step run is sampled or excluded in a counted class: 200 steps of an
            // approach (no docking ends) after one tare of 0.3 s.
            let ex = &r.extra["excluded_steps"];
            let tare_steps = (params.tare.window_s / params.dt_s).round() as u64;
            assert_eq!(ex["ended_docking"].as_u64(), Some(0), "{ex}");
            assert_eq!(ex["moving_without_solve"].as_u64(), Some(1), "{ex}");
            let tare = ex["tare"].as_u64().unwrap();
            assert!((tare_steps - 1..=tare_steps).contains(&tare), "{ex}");
            assert_eq!(r.extra["steps_run"].as_u64(), Some(200 + tare + 1), "{ex}");
        }
        // Without it Clarabel solves every QP, in every step.
        let mut cold = params.clone();
        cold.sqp.active_set_warm_start = false;
        for r in run(50, &cold).unwrap() {
            assert_eq!(figure(&r, "mean_clarabel_qps"), figure(&r, "mean_iterations"));
            assert_eq!(r.extra["clarabel_steps"]["count"].as_u64(), Some(50));
            assert!(figure(&r, "mean_qp_iterations") > 3.0);
        }
    }
}
