//! N closed-loop trials per arm of a comparison (e.g. with and without force feedback),
//! on the same seeds, in parallel (rayon), with summary statistics. Each trial is a pure
//! function of its seed, so the results do not depend on the thread count or order.

use std::collections::BTreeMap;
use std::sync::Arc;

use rayon::prelude::*;
use serde::Serialize;

use super::run::{run_trial, Outcome, Policy, TrialParams, TrialResult, PAPER_CODE_SCALE};
use crate::kinematics::Kinematics;
use crate::sim::noise::PoseSource;
use crate::sim::{SimParams, SimWorld};

/// Mean, standard deviation (sample, n - 1), min and max of a set of values. A value that
/// is not finite (a trial that errored before it had one) is never dropped: it is counted
/// in `missing`, and the statistics are then NaN, so no figure silently leaves it out.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stats {
    /// Number of values.
    pub n: usize,
    /// How many of them are not finite (then mean, std, min and max are NaN).
    pub missing: usize,
    /// Mean (NaN when empty).
    pub mean: f64,
    /// Sample standard deviation (0 for one value, NaN when empty).
    pub std: f64,
    /// Minimum.
    pub min: f64,
    /// Maximum.
    pub max: f64,
}

impl Stats {
    /// Statistics of the values in `v` (NaN when any is not finite, or there are none).
    pub fn of(v: impl IntoIterator<Item = f64>) -> Self {
        let v: Vec<f64> = v.into_iter().collect();
        let n = v.len();
        let missing = v.iter().filter(|x| !x.is_finite()).count();
        if n == 0 || missing > 0 {
            return Self {
                n,
                missing,
                mean: f64::NAN,
                std: f64::NAN,
                min: f64::NAN,
                max: f64::NAN,
            };
        }
        let mean = v.iter().sum::<f64>() / n as f64;
        let var = if n > 1 {
            v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64
        } else {
            0.0
        };
        Self {
            n,
            missing,
            mean,
            std: var.sqrt(),
            min: v.iter().copied().fold(f64::INFINITY, f64::min),
            max: v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        }
    }
}

/// Summary of one arm of the comparison. The headline is `m_true_all`: M on the true
/// contact force over every trial, failures included. Like the paper, `m_true`, `m_est`
/// and `time_s` cover the successful trials.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ArmSummary {
    /// Arm label: `ff` or `no_ff`.
    pub label: String,
    /// Trials run.
    pub trials: usize,
    /// Trials docked at DONE: the controller reported DONE and the truth agreed.
    pub successes: usize,
    /// successes / trials: docked at DONE.
    pub success_rate: f64,
    /// Trials that met the paper's success test (the tip within 5 mm of the goal, inside
    /// the port) at any time in the run.
    pub paper_successes: usize,
    /// paper_successes / trials.
    pub paper_success_rate: f64,
    /// Trials whose DONE the truth contradicts (a failure class of its own).
    pub false_done: usize,
    /// Trials that reached the goal and held there, DEPTH_UNCERTAIN, instead of DONE (not
    /// docked).
    pub depth_uncertain: usize,
    /// M from the true contact force over every trial, N (the headline).
    pub m_true_all: Stats,
    /// M from the true contact force, N (successful trials).
    pub m_true: Stats,
    /// M from the controller's force estimate, N (successful trials).
    pub m_est: Stats,
    /// 2.4 x `m_est`: the paper's public-code scale, for comparison with its 21.4 and 3.4.
    pub m_paper_code_scale: Stats,
    /// M from the estimate over every trial, N.
    pub m_est_all: Stats,
    /// M from the true contact force across the trocar axis over every trial, N.
    pub m_lateral_true_all: Stats,
    /// Completion time T to DONE, s (successful trials).
    pub time_s: Stats,
    /// Largest true contact force over every trial, N.
    pub max_force_true_n: f64,
    /// Largest estimated force over every trial, N.
    pub max_force_est_n: f64,
    /// RMS of the true tip speed during INSERT per trial (every trial that inserted), m/s:
    /// how much the arm shakes while the scope slides in (the insertion itself is 0.03 m/s).
    pub rms_tip_speed_insert: Stats,
    /// Largest true tip speed over every trial, m/s.
    pub max_tip_speed: f64,
    /// Largest true tip acceleration over every trial, m/s^2.
    pub max_tip_accel: f64,
    /// Breakaways of the cannula's seal per trial (every trial): how often it stuck and
    /// then slipped.
    pub seal_breakaways: Stats,
    /// Failed trials by reason: the outcome, the policy's phase and hold code at the end,
    /// e.g. `timeout in HOLD (APPROACH_STALL)`.
    pub failures: BTreeMap<String, usize>,
}

impl ArmSummary {
    /// Summarise the results of one arm.
    pub fn of(label: &str, r: &[TrialResult]) -> Self {
        let ok: Vec<&TrialResult> = r.iter().filter(|x| x.success()).collect();
        let rate = |k: usize| if r.is_empty() { 0.0 } else { k as f64 / r.len() as f64 };
        let paper_successes = r.iter().filter(|x| x.paper_success).count();
        let mut failures = BTreeMap::new();
        for x in r.iter().filter(|x| !x.success()) {
            let key = match (x.final_phase, x.final_hold) {
                ("", _) => x.outcome.name().to_string(),
                (phase, "") => format!("{} in {phase}", x.outcome.name()),
                (phase, hold) => format!("{} in {phase} ({hold})", x.outcome.name()),
            };
            *failures.entry(key).or_insert(0) += 1;
        }
        Self {
            label: label.to_string(),
            trials: r.len(),
            successes: ok.len(),
            success_rate: rate(ok.len()),
            paper_successes,
            paper_success_rate: rate(paper_successes),
            false_done: r.iter().filter(|x| x.outcome == Outcome::FalseDone).count(),
            depth_uncertain: r.iter().filter(|x| x.outcome == Outcome::DepthUncertain).count(),
            m_true_all: Stats::of(r.iter().map(|x| x.m_true)),
            m_true: Stats::of(ok.iter().map(|x| x.m_true)),
            m_est: Stats::of(ok.iter().map(|x| x.m_est)),
            m_paper_code_scale: Stats::of(ok.iter().map(|x| PAPER_CODE_SCALE * x.m_est)),
            m_est_all: Stats::of(r.iter().map(|x| x.m_est)),
            m_lateral_true_all: Stats::of(r.iter().map(|x| x.m_lateral_true)),
            time_s: Stats::of(ok.iter().map(|x| x.time_s)),
            max_force_true_n: max_all(r.iter().map(|x| x.max_f_true)),
            max_force_est_n: max_all(r.iter().map(|x| x.max_f_est)),
            rms_tip_speed_insert: Stats::of(
                r.iter()
                    .filter(|x| x.rms_tip_speed_insert > 0.0)
                    .map(|x| x.rms_tip_speed_insert),
            ),
            max_tip_speed: max_all(r.iter().map(|x| x.max_tip_speed)),
            max_tip_accel: max_all(r.iter().map(|x| x.max_tip_accel)),
            seal_breakaways: Stats::of(r.iter().map(|x| f64::from(x.seal_breakaways))),
            failures,
        }
    }
}

/// The largest of `v` (0 for none; NaN when any is not finite: a trial without the value
/// is not left out silently).
fn max_all(v: impl Iterator<Item = f64>) -> f64 {
    v.fold(0.0, |m, x| {
        if x.is_finite() && m.is_finite() {
            m.max(x)
        } else {
            f64::NAN
        }
    })
}

/// One arm's results and summary.
#[derive(Debug, Clone, Serialize)]
pub struct ArmReport {
    /// Summary.
    pub summary: ArmSummary,
    /// Per-trial results (time series not serialised).
    pub trials: Vec<TrialResult>,
}

/// Builds the kinematics of one trial. Each trial gets its own instance (0.3 ms to build),
/// so parallel trials share no state even with a `Kinematics` that is not safe to share
/// (the KDL bridge before commit fdee84c cached joint poses in `KDL::Joint`'s mutable
/// members, which corrupted trials run on two threads).
pub type KinematicsFactory = dyn Fn() -> Result<Arc<dyn Kinematics>, String> + Sync;

/// Builds the policy of the trial with a given seed (or says why it cannot).
pub type PolicyFactory = dyn Fn(u64) -> Result<Box<dyn Policy>, String> + Sync;

/// Builds the trocar pose source of the trial with a given seed in its fresh world (or says
/// why it cannot); without one the world keeps its noise-model sensor.
pub type PoseSourceFactory = dyn Fn(u64, &SimWorld) -> Result<Box<dyn PoseSource>, String> + Sync;

/// What one arm runs: the world's parameters, the trial's, the kinematics and, if given, the
/// pose source that replaces the world's noise-model sensor.
#[derive(Clone, Copy)]
pub struct ArmSetup<'a> {
    /// The world's parameters.
    pub params: &'a SimParams,
    /// The trial's parameters.
    pub trial: &'a TrialParams,
    /// The kinematics of each trial.
    pub kin: &'a KinematicsFactory,
    /// The pose source of each trial (None: the noise model of `params.measurement`).
    pub source: Option<&'a PoseSourceFactory>,
}

/// Run `seeds.len()` trials for one arm in parallel; `make_policy(seed)` builds the policy
/// of a trial, `tick()` is called after each trial (progress).
pub fn run_arm(
    label: &str,
    params: &SimParams,
    trial: &TrialParams,
    kin: &KinematicsFactory,
    seeds: &[u64],
    make_policy: &PolicyFactory,
    tick: &(dyn Fn() + Sync),
) -> ArmReport {
    let setup = ArmSetup {
        params,
        trial,
        kin,
        source: None,
    };
    run_arm_with(label, &setup, seeds, make_policy, tick)
}

/// As [`run_arm`], with the pose source of `setup`.
pub fn run_arm_with(
    label: &str,
    setup: &ArmSetup<'_>,
    seeds: &[u64],
    make_policy: &PolicyFactory,
    tick: &(dyn Fn() + Sync),
) -> ArmReport {
    let trials: Vec<TrialResult> = seeds
        .par_iter()
        .map(|&seed| {
            let r = one(setup, seed, make_policy);
            tick();
            r
        })
        .collect();
    ArmReport {
        summary: ArmSummary::of(label, &trials),
        trials,
    }
}

fn one(setup: &ArmSetup<'_>, seed: u64, make_policy: &PolicyFactory) -> TrialResult {
    let failed = |why: String| TrialResult::not_run(seed, why);
    let kin = match (setup.kin)() {
        Ok(k) => k,
        Err(e) => return failed(e),
    };
    let mut world = match SimWorld::new(setup.params, kin, seed) {
        Ok(w) => w,
        Err(e) => return failed(e.to_string()),
    };
    if let Some(make) = setup.source {
        match make(seed, &world) {
            Ok(s) => world.set_pose_source(s),
            Err(e) => return failed(e),
        }
    }
    match make_policy(seed) {
        Ok(mut p) => run_trial(&mut world, p.as_mut(), setup.trial, seed),
        Err(e) => failed(e),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_of_known_values() {
        let s = Stats::of([1.0, 2.0, 3.0, 4.0]);
        assert_eq!((s.n, s.missing), (4, 0));
        assert!((s.mean - 2.5).abs() < 1e-12);
        assert!((s.std - (5.0f64 / 3.0).sqrt()).abs() < 1e-12);
        assert_eq!((s.min, s.max), (1.0, 4.0));
        assert!(Stats::of([]).mean.is_nan());
        assert_eq!(Stats::of([2.0]).std, 0.0);
        // A trial without a value is not dropped: it is counted and the mean says so.
        let gap = Stats::of([1.0, f64::NAN, 3.0]);
        assert_eq!((gap.n, gap.missing), (3, 1));
        assert!(gap.mean.is_nan() && gap.max.is_nan());
        assert!(max_all([1.0, f64::NAN].into_iter()).is_nan() && max_all([1.0, 2.0].into_iter()) == 2.0);
    }

    fn result(seed: u64, outcome: Outcome, m: f64, phase: &'static str) -> TrialResult {
        TrialResult {
            seed,
            outcome,
            reason: String::new(),
            time_s: 2.0 * m,
            paper_success: outcome != Outcome::ForceAbort,
            paper_time_s: m,
            done_depth_error_m: f64::NAN,
            done_radial_m: f64::NAN,
            done_estimate_depth_m: f64::NAN,
            done_angle_deg: f64::NAN,
            m_est: m,
            m_true: m,
            m_lateral_true: 0.5 * m,
            max_f_est: 3.0 * m,
            max_f_true: 4.0 * m,
            final_phase: phase,
            final_hold: if phase == "HOLD" { "FORCE_LIMIT" } else { "" },
            seal_breakaways: 0,
            rms_tip_speed_insert: 0.01 * m,
            max_tip_speed: 0.1 * m,
            max_tip_accel: m,
            samples: vec![],
        }
    }

    #[test]
    fn summary_counts_failures_by_reason_and_m_true_all_includes_them() {
        let r = [
            result(1, Outcome::Docked, 1.0, "DONE"),
            result(2, Outcome::Timeout, 3.0, "HOLD"),
            result(3, Outcome::Timeout, 5.0, "HOLD"),
            result(4, Outcome::ForceAbort, 7.0, "INSERT"),
            result(5, Outcome::FalseDone, 1.0, "DONE"),
        ];
        let s = ArmSummary::of("ff", &r);
        assert_eq!((s.trials, s.successes, s.false_done, s.paper_successes), (5, 1, 1, 4));
        assert!((s.success_rate - 0.2).abs() < 1e-12 && (s.paper_success_rate - 0.8).abs() < 1e-12);
        assert!((s.m_true_all.mean - 3.4).abs() < 1e-12 && (s.m_true.mean - 1.0).abs() < 1e-12);
        assert!((s.m_lateral_true_all.mean - 1.7).abs() < 1e-12);
        assert!((s.time_s.mean - 2.0).abs() < 1e-12 && s.max_force_true_n == 28.0);
        assert_eq!(s.failures.get("timeout in HOLD (FORCE_LIMIT)"), Some(&2));
        assert_eq!(s.failures.get("force_abort in INSERT"), Some(&1));
        assert_eq!(s.failures.get("false_done in DONE"), Some(&1));
        assert_eq!(s.failures.len(), 3);
        assert!((s.rms_tip_speed_insert.mean - 0.034).abs() < 1e-12 && (s.max_tip_speed - 0.7).abs() < 1e-12);
    }

    #[test]
    fn a_trial_that_could_not_run_is_a_counted_failure() {
        let r = [
            result(1, Outcome::Docked, 1.0, "DONE"),
            TrialResult::not_run(2, "no world".into()),
        ];
        let s = ArmSummary::of("ff", &r);
        assert_eq!((s.trials, s.successes), (2, 1));
        assert_eq!(s.failures.get("sim_error"), Some(&1));
        assert_eq!(s.m_true_all.missing, 1);
        assert!(s.m_true_all.mean.is_nan() && s.max_force_true_n.is_nan());
        assert!(
            (s.m_true.mean - 1.0).abs() < 1e-12,
            "the successes' M has every success"
        );
    }
}
