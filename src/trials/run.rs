//! One closed-loop trial: a [`Policy`] (the docking controller, or a test double) runs at
//! its control rate against a [`SimWorld`] stepped at the physics rate, until the policy
//! reports DONE, holds latched (a hold only the operator resumes: where a lab's run stops
//! too), aborts, the force exceeds `abort_force_n`, or the timeout. A DONE is judged
//! against the truth there: **docked** when the true tip is within `done_depth_tolerance_m`
//! of the goal depth and inside the port, and the shaft within `done_angle_tolerance_deg`
//! of the true axis; otherwise it is a **false DONE**. Beside it, the paper's test (the tip
//! within `tolerance_m` of the point `goal_depth_m` along the true axis, inside the port)
//! is recorded if it holds at any time in the run.
//!
//! The metric follows the paper: M = (1/T) * integral_0^T ||f_ext|| dt over the trial, from
//! the controller's estimate f_ext = J_lin^-T tau_ext (`m_est`) and, beside it, from the
//! simulator's true contact force (`m_true`) and its component across the trocar's true
//! axis (`m_lateral_true`). The paper's public code reports 2.4 x M.

use std::ops::ControlFlow;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::closed_loop::{ClosedLoop, Observation, PlantError};
use crate::kinematics::{JointVector, Kinematics};
use crate::sim::{check_range, SimError, SimWorld};

pub use crate::control::docking::metrics::PAPER_CODE_SCALE;

/// The hold code of a policy at its goal that does not know the tip's depth well enough.
const DEPTH_UNCERTAIN: &str = "DEPTH_UNCERTAIN";

/// What a policy answers at a control tick.
#[derive(Debug, Clone, PartialEq)]
pub struct Action {
    /// Joint positions to command (None: keep the previous command).
    pub command: Option<JointVector>,
    /// The policy's estimate of the force at the tip, N (None when it has none).
    pub f_ext: Option<Vector3<f64>>,
    /// Phase name, e.g. `APPROACH`.
    pub phase: &'static str,
    /// The code of the reason the policy holds, if it does (e.g. `FORCE_LIMIT`).
    pub hold_code: Option<&'static str>,
    /// Set when the policy gave up (its reason).
    pub aborted: Option<String>,
    /// The policy holds latched: only an operator resumes it (none does in a trial).
    pub latched: bool,
}

/// A closed-loop controller as the simulator drives it.
pub trait Policy {
    /// Called once before the first tick.
    fn start(&mut self, kin: &dyn Kinematics);
    /// One control tick.
    fn tick(&mut self, kin: &dyn Kinematics, obs: &Observation) -> Action;
    /// Its control period, s (the controller's `dt_s`, `config/controller.yaml`): the trial
    /// steps it at this period.
    fn period(&self) -> f64;
}

/// Parameters of a trial (the `trial:` section of `config/sim.yaml`; its defaults are that
/// section as shipped, [`crate::sim::SHIPPED`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct TrialParams {
    /// Goal depth along the trocar axis, m.
    pub goal_depth_m: f64,
    /// The paper's success tolerance on the tip-to-goal distance, m.
    pub tolerance_m: f64,
    /// At DONE, the largest distance of the true tip from the goal depth along the true
    /// axis for the docking to count, m.
    pub done_depth_tolerance_m: f64,
    /// At DONE, the largest angle between the shaft and the true axis, deg.
    pub done_angle_tolerance_deg: f64,
    /// Trial timeout, s.
    pub timeout_s: f64,
    /// Abort when the true contact force exceeds this, N.
    pub abort_force_n: f64,
}

crate::shipped_defaults!(TrialParams, crate::sim::SHIPPED, ["trial"]);

impl TrialParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("trial.goal_depth_m", self.goal_depth_m, 0.0, 0.5)?;
        check_range("trial.tolerance_m", self.tolerance_m, 1e-4, 0.1)?;
        check_range("trial.done_depth_tolerance_m", self.done_depth_tolerance_m, 1e-4, 0.1)?;
        check_range(
            "trial.done_angle_tolerance_deg",
            self.done_angle_tolerance_deg,
            0.01,
            45.0,
        )?;
        check_range("trial.timeout_s", self.timeout_s, 0.01, 3600.0)?;
        check_range("trial.abort_force_n", self.abort_force_n, 0.1, 1e4)
    }
}

/// How a trial ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// The policy reported DONE and the truth agrees: the tip at the goal depth inside the
    /// port, the shaft along the axis.
    Docked,
    /// The policy reported DONE but the truth does not agree.
    FalseDone,
    /// The policy held, latched (only an operator resumes it).
    Held,
    /// The policy reached its goal but held there, DEPTH_UNCERTAIN, instead of DONE: it does
    /// not know the tip's depth within the tolerance (not docked, whatever the truth).
    DepthUncertain,
    /// The timeout passed first.
    Timeout,
    /// The contact force exceeded the abort threshold.
    ForceAbort,
    /// The policy aborted.
    PolicyAbort,
    /// The simulation failed (diverged, kinematics error).
    SimError,
}

impl Outcome {
    /// The outcome's name, as in the JSON (e.g. `force_abort`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Docked => "docked",
            Self::FalseDone => "false_done",
            Self::Held => "held",
            Self::DepthUncertain => "depth_uncertain",
            Self::Timeout => "timeout",
            Self::ForceAbort => "force_abort",
            Self::PolicyAbort => "policy_abort",
            Self::SimError => "sim_error",
        }
    }
}

/// One sample of a trial's time series (at the control rate).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Time, s.
    pub t: f64,
    /// ||f_ext|| estimated by the policy, N (NaN when it has none).
    pub f_est: f64,
    /// ||f|| of the true contact force on the arm, N.
    pub f_true: f64,
    /// The true contact force's component across the trocar's true axis, N.
    pub f_lateral_true: f64,
    /// Tip depth along the true trocar axis, m.
    pub depth: f64,
    /// Tip distance from the true trocar axis, m.
    pub radial: f64,
    /// Distance from the tip to the true goal, m.
    pub goal_dist: f64,
    /// Trocar fulcrum displacement from rest, m.
    pub trocar_shift: f64,
    /// Speed of the true tip (base frame) over the last control period, m/s.
    pub tip_speed: f64,
    /// Norm of the true tip's acceleration over the last two control periods, m/s^2.
    pub tip_accel: f64,
    /// Policy phase.
    pub phase: &'static str,
    /// The policy's hold code ('' when it does not hold).
    pub hold: &'static str,
}

/// The result of one trial.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrialResult {
    /// Seed of the trial.
    pub seed: u64,
    /// How it ended.
    pub outcome: Outcome,
    /// Why (abort reason, error text), empty otherwise.
    pub reason: String,
    /// Duration T, s, to the trial's end (DONE when docked).
    pub time_s: f64,
    /// The paper's success test held at some time in the run: the tip within `tolerance_m`
    /// of the goal, inside the port.
    pub paper_success: bool,
    /// When the paper's test first held, s (NaN: never).
    pub paper_time_s: f64,
    /// At DONE (or the hold DEPTH_UNCERTAIN), the true tip's distance from the goal depth
    /// along the true axis, m (NaN: neither).
    pub done_depth_error_m: f64,
    /// At DONE, the true tip's distance from the true axis, m (NaN: no DONE).
    pub done_radial_m: f64,
    /// At DONE, the newest trocar pose delivered to the controller: its port's offset from
    /// the true port along the true axis, m, signed (+: estimated deeper into the body;
    /// NaN: no DONE, or nothing delivered). The estimate's share of the depth error.
    pub done_estimate_depth_m: f64,
    /// At DONE, the angle between the shaft and the true axis, deg (NaN: no DONE).
    pub done_angle_deg: f64,
    /// M from the policy's f_ext estimate, N (true-force M when the policy has none).
    pub m_est: f64,
    /// M from the true contact force, N.
    pub m_true: f64,
    /// M from the true contact force across the trocar axis, N.
    pub m_lateral_true: f64,
    /// Largest estimated force, N.
    pub max_f_est: f64,
    /// Largest true contact force, N.
    pub max_f_true: f64,
    /// The policy's phase when the trial ended.
    pub final_phase: &'static str,
    /// The policy's hold code when the trial ended ('' when it did not hold).
    pub final_hold: &'static str,
    /// How many times the cannula's seal broke away (stick to slip) in the trial.
    pub seal_breakaways: u32,
    /// RMS of the true tip speed during INSERT, m/s (0 when the trial never inserted).
    pub rms_tip_speed_insert: f64,
    /// Largest true tip speed, m/s.
    pub max_tip_speed: f64,
    /// Largest true tip acceleration, m/s^2.
    pub max_tip_accel: f64,
    /// Time series at the control rate.
    #[serde(skip)]
    pub samples: Vec<Sample>,
}

impl TrialResult {
    /// True when the policy reported DONE and the truth agreed (docked at DONE).
    pub fn success(&self) -> bool {
        self.outcome == Outcome::Docked
    }

    /// A result for a trial that could not run (no world, no policy): a failure with its
    /// reason, no time series, and no metric (NaN: it has none, and the summaries count it).
    pub fn not_run(seed: u64, reason: String) -> Self {
        Self {
            seed,
            outcome: Outcome::SimError,
            reason,
            time_s: 0.0,
            paper_success: false,
            paper_time_s: f64::NAN,
            done_depth_error_m: f64::NAN,
            done_radial_m: f64::NAN,
            done_estimate_depth_m: f64::NAN,
            done_angle_deg: f64::NAN,
            m_est: f64::NAN,
            m_true: f64::NAN,
            m_lateral_true: f64::NAN,
            max_f_est: f64::NAN,
            max_f_true: f64::NAN,
            final_phase: "",
            final_hold: "",
            seal_breakaways: 0,
            rms_tip_speed_insert: f64::NAN,
            max_tip_speed: f64::NAN,
            max_tip_accel: f64::NAN,
            samples: vec![],
        }
    }
}

/// The truth at DONE: where the true tip and shaft are against the true trocar.
#[derive(Debug, Clone, Copy, PartialEq)]
struct DoneTruth {
    depth_error_m: f64,
    radial_m: f64,
    angle_deg: f64,
    estimate_depth_m: f64,
}

/// What a run records beside its time series.
#[derive(Debug, Clone, Copy)]
struct RunEnd {
    outcome: Outcome,
    paper_time_s: Option<f64>,
    done: Option<DoneTruth>,
}

/// Run one trial of `policy` in `world` (fresh from [`SimWorld::new`]).
pub fn run_trial(world: &mut SimWorld, policy: &mut dyn Policy, p: &TrialParams, seed: u64) -> TrialResult {
    let mut samples = Vec::with_capacity((p.timeout_s / policy.period()).ceil() as usize + 2);
    let mut end = RunEnd {
        outcome: Outcome::SimError,
        paper_time_s: None,
        done: None,
    };
    let reason = match drive(world, policy, p, &mut samples, &mut end) {
        Ok(why) => why,
        Err(e) => {
            end.outcome = Outcome::SimError;
            e.to_string()
        }
    };
    let m = metrics(&samples);
    let done = end.done;
    TrialResult {
        seed,
        outcome: end.outcome,
        reason,
        time_s: world.time(),
        paper_success: end.paper_time_s.is_some(),
        paper_time_s: end.paper_time_s.unwrap_or(f64::NAN),
        done_depth_error_m: done.map_or(f64::NAN, |d| d.depth_error_m),
        done_radial_m: done.map_or(f64::NAN, |d| d.radial_m),
        done_estimate_depth_m: done.map_or(f64::NAN, |d| d.estimate_depth_m),
        done_angle_deg: done.map_or(f64::NAN, |d| d.angle_deg),
        m_est: m.m_est,
        m_true: m.m_true,
        m_lateral_true: m.m_lateral_true,
        max_f_est: m.max_f_est,
        max_f_true: m.max_f_true,
        final_phase: samples.last().map_or("", |x| x.phase),
        final_hold: samples.last().map_or("", |x| x.hold),
        seal_breakaways: world.seal().breakaways(),
        rms_tip_speed_insert: m.rms_tip_speed_insert,
        max_tip_speed: m.max_tip_speed,
        max_tip_accel: m.max_tip_accel,
        samples,
    }
}

/// The trials' force abort (a soak cycle's too): after any physics tick, the true contact
/// force over `abort_force_n` ends the run with it (`Break`, N).
pub fn over_abort_force(abort_force_n: f64) -> impl FnMut(&SimWorld) -> ControlFlow<f64> {
    move |w: &SimWorld| {
        let f = w.contact().force.norm();
        if f > abort_force_n {
            ControlFlow::Break(f)
        } else {
            ControlFlow::Continue(())
        }
    }
}

/// Whether the truth agrees with a DONE in `world` now, by the trial's rule (see the
/// module doc): the soak judges its cycles by it too.
pub fn docked_at_done(world: &SimWorld, p: &TrialParams) -> bool {
    judge_done(world, p).1
}

/// The truth at DONE, and whether it counts as docked.
fn judge_done(world: &SimWorld, p: &TrialParams) -> (DoneTruth, bool) {
    let port = world.tip_in_port();
    let radial = (port.x * port.x + port.y * port.y).sqrt();
    let trocar = world.trocar_pose_true();
    let axis = trocar.rotation * Vector3::z();
    let shaft = world.tip_pose().rotation * Vector3::z();
    let estimate_depth_m = world.measure_trocar(world.time()).map_or(f64::NAN, |m| {
        (m.pose.translation.vector - trocar.translation.vector).dot(&axis)
    });
    let truth = DoneTruth {
        depth_error_m: (port.z - p.goal_depth_m).abs(),
        radial_m: radial,
        angle_deg: shaft.angle(&axis).to_degrees(),
        estimate_depth_m,
    };
    let docked = truth.depth_error_m <= p.done_depth_tolerance_m
        && radial < world.params().trocar.port_radius()
        && truth.angle_deg <= p.done_angle_tolerance_deg;
    (truth, docked)
}

/// Whether the run ends after this tick's `action` at time `t`: DONE (judged against the
/// truth), an abort, a latched hold, the timeout. Records when the paper's test first holds.
fn end_of_tick(world: &SimWorld, p: &TrialParams, action: &Action, t: f64, end: &mut RunEnd) -> Option<String> {
    if end.paper_time_s.is_none() && world.docked(p.goal_depth_m, p.tolerance_m) {
        end.paper_time_s = Some(t);
    }
    if action.phase == "DONE" {
        let (truth, docked) = judge_done(world, p);
        end.done = Some(truth);
        if docked {
            end.outcome = Outcome::Docked;
            return Some(String::new());
        }
        end.outcome = Outcome::FalseDone;
        return Some(format!(
                "DONE with the true tip {:.1} mm from the goal depth, {:.2} mm off the axis (port radius {:.2} mm), the shaft {:.2} deg off the axis",
                truth.depth_error_m * 1e3,
                truth.radial_m * 1e3,
                world.params().trocar.port_radius() * 1e3,
                truth.angle_deg
            ));
    }
    if let Some(why) = &action.aborted {
        end.outcome = Outcome::PolicyAbort;
        return Some(why.clone());
    }
    if action.latched && action.hold_code == Some(DEPTH_UNCERTAIN) {
        // Not docked, whatever the truth; the truth is recorded to judge the gate.
        let (truth, _) = judge_done(world, p);
        end.done = Some(truth);
        end.outcome = Outcome::DepthUncertain;
        return Some(format!(
            "held at the goal, depth uncertain; the true tip {:.1} mm from the goal depth",
            truth.depth_error_m * 1e3
        ));
    }
    if action.latched {
        end.outcome = Outcome::Held;
        return Some(format!(
            "held, latched ({}): only an operator resumes it",
            action.hold_code.unwrap_or("no code")
        ));
    }
    if t >= p.timeout_s - 1e-9 {
        end.outcome = Outcome::Timeout;
        return Some(format!("no DONE after {:.1} s", p.timeout_s));
    }
    None
}

/// Run the loop to its end; `end` gets the outcome, the reason is returned.
fn drive(
    world: &mut SimWorld,
    policy: &mut dyn Policy,
    p: &TrialParams,
    samples: &mut Vec<Sample>,
    end: &mut RunEnd,
) -> Result<String, SimError> {
    p.validate()?;
    policy.start(world.kinematics());
    let mut plant = ClosedLoop::new(world, policy.period());
    // The true tip's last position and velocity (finite differences at the control rate).
    let mut last_tip: Option<(f64, Vector3<f64>, Option<Vector3<f64>>)> = None;
    loop {
        let obs = plant.observe(world);
        let t = obs.t;
        let action = policy.tick(world.kinematics(), &obs);
        let port = world.tip_in_port();
        let radial = (port.x * port.x + port.y * port.y).sqrt();
        let f = world.contact().force;
        let axis = world.trocar_pose_true().rotation * Vector3::z();
        let tip = world.tip_pose().translation.vector;
        let (tip_speed, tip_accel) = match last_tip {
            Some((t0, p0, v0)) if t > t0 => {
                let v = (tip - p0) / (t - t0);
                last_tip = Some((t, tip, Some(v)));
                (v.norm(), v0.map_or(0.0, |v0| (v - v0).norm() / (t - t0)))
            }
            _ => {
                last_tip = Some((t, tip, None));
                (0.0, 0.0)
            }
        };
        samples.push(Sample {
            t,
            f_est: action.f_ext.map_or(f64::NAN, |f| f.norm()),
            f_true: f.norm(),
            f_lateral_true: (f - axis * f.dot(&axis)).norm(),
            depth: port.z,
            radial,
            goal_dist: (port.coords - Vector3::new(0.0, 0.0, p.goal_depth_m)).norm(),
            trocar_shift: world.trocar().deviation().shift_m,
            tip_speed,
            tip_accel,
            phase: action.phase,
            hold: action.hold_code.unwrap_or(""),
        });
        if let Some(why) = end_of_tick(world, p, &action, t, end) {
            return Ok(why);
        }
        match plant.advance_until(world, action.command.as_ref(), over_abort_force(p.abort_force_n)) {
            Ok(ControlFlow::Continue(())) => {}
            Ok(ControlFlow::Break(f)) => {
                end.outcome = Outcome::ForceAbort;
                return Ok(format!("contact force {f:.1} N > {} N", p.abort_force_n));
            }
            Err(PlantError::Command(e)) => {
                end.outcome = Outcome::PolicyAbort;
                return Ok(format!("bad command: {e}"));
            }
            Err(PlantError::Physics(e)) => return Err(e),
        }
    }
}

/// The force metrics of one trial's time series.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct Metrics {
    m_est: f64,
    m_true: f64,
    m_lateral_true: f64,
    max_f_est: f64,
    max_f_true: f64,
    rms_tip_speed_insert: f64,
    max_tip_speed: f64,
    max_tip_accel: f64,
}

/// The metrics of a time series, M by the trapezoid rule; the estimate falls back to the
/// true force where the policy gave none.
fn metrics(s: &[Sample]) -> Metrics {
    let est = |x: &Sample| if x.f_est.is_finite() { x.f_est } else { x.f_true };
    let t = s.last().map_or(0.0, |x| x.t) - s.first().map_or(0.0, |x| x.t);
    let mean = |f: &dyn Fn(&Sample) -> f64| {
        let area: f64 = s
            .windows(2)
            .map(|w| 0.5 * (f(&w[0]) + f(&w[1])) * (w[1].t - w[0].t))
            .sum();
        if t > 0.0 {
            area / t
        } else {
            0.0
        }
    };
    Metrics {
        m_est: mean(&est),
        m_true: mean(&|x| x.f_true),
        m_lateral_true: mean(&|x| x.f_lateral_true),
        max_f_est: s.iter().map(est).fold(0.0, f64::max),
        max_f_true: s.iter().map(|x| x.f_true).fold(0.0, f64::max),
        rms_tip_speed_insert: rms(s.iter().filter(|x| x.phase == "INSERT").map(|x| x.tip_speed)),
        max_tip_speed: s.iter().map(|x| x.tip_speed).fold(0.0, f64::max),
        max_tip_accel: s.iter().map(|x| x.tip_accel).fold(0.0, f64::max),
    }
}

/// Root mean square (0 for no values).
fn rms(x: impl Iterator<Item = f64>) -> f64 {
    let (n, sum) = x.fold((0usize, 0.0), |(n, s), v| (n + 1, s + v * v));
    if n == 0 {
        0.0
    } else {
        (sum / n as f64).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(t: f64, f: f64) -> Sample {
        Sample {
            t,
            f_est: f,
            f_true: 2.0 * f,
            f_lateral_true: 0.5 * f,
            depth: 0.0,
            radial: 0.0,
            goal_dist: 0.0,
            trocar_shift: 0.0,
            tip_speed: f,
            tip_accel: 0.0,
            phase: "INSERT",
            hold: "",
        }
    }

    #[test]
    fn metric_is_the_time_average() {
        // f = t on [0, 2]: mean 1; true force 2t: mean 2.
        let s: Vec<Sample> = (0..=200).map(|k| sample(k as f64 * 0.01, k as f64 * 0.01)).collect();
        let m = metrics(&s);
        assert!((m.m_est - 1.0).abs() < 1e-9 && (m.m_true - 2.0).abs() < 1e-9);
        assert!((m.m_lateral_true - 0.5).abs() < 1e-9);
        assert!((m.max_f_est - 2.0).abs() < 1e-12 && (m.max_f_true - 4.0).abs() < 1e-12);
        // tip speed = t on [0, 2] at 201 samples: RMS sqrt(mean t^2) = sqrt(1.34), max 2.
        let want = (s.iter().map(|x| x.t * x.t).sum::<f64>() / 201.0).sqrt();
        assert!(
            (m.rms_tip_speed_insert - want).abs() < 1e-12
                && (want - (200.0f64 * 401.0 / 6.0 * 1e-4).sqrt()).abs() < 1e-9
        );
        assert!((m.max_tip_speed - 2.0).abs() < 1e-12);
        assert_eq!(metrics(&[]), Metrics::default());
    }
}
