//! The simulator with the LBR Med 7 model: randomised starts, a closed loop with the
//! baseline policy, determinism.

use std::sync::Arc;

use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::{Kinematics, LbrKinematics};
use trocar_docking::sim::noise::{NoiseModel, PoseSource, SensorInput, TrocarMeasurement};
use trocar_docking::sim::{SimParams, SimWorld};
use trocar_docking::trials::baseline::Baseline;
use trocar_docking::trials::closed_loop::Observation;
use trocar_docking::trials::config::load_controller;
use trocar_docking::trials::run::{run_trial, Action, Outcome, Policy, TrialParams};

fn kin() -> Arc<dyn Kinematics> {
    Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).expect("model"))
}

/// The control period the trials run: the shipped controller's `dt_s`.
fn shipped_period() -> f64 {
    load_controller(None).unwrap().dt_s
}

#[test]
fn starts_are_where_the_experiment_wants_them() {
    let kin = kin();
    let p = SimParams::default();
    for seed in 0..50 {
        let w = SimWorld::new(&p, kin.clone(), seed).unwrap();
        let port = w.trocar_pose_true();
        let tip = w.tip_pose();
        let d = (port.translation.vector - tip.translation.vector).norm();
        assert!((0.1 - 1e-9..=0.15 + 1e-9).contains(&d), "seed {seed}: tip-port {d}");
        let x = port.translation.vector;
        assert!(
            x.x > 0.4 && x.x < 0.75 && x.z > 0.1 && x.z < 0.32,
            "seed {seed}: port at {x}"
        );
        // The axis points into the body: downward, within the tilt range.
        let axis = port.rotation * nalgebra::Vector3::z();
        assert!(axis.z < -(25f64.to_radians().cos()) + 1e-9, "seed {seed}: axis {axis}");
        // The tool starts pointing roughly down.
        assert!((tip.rotation * nalgebra::Vector3::z()).z < -0.9);
    }
}

/// The base world without pose noise, and a trial of 15 s.
fn noiseless() -> (SimParams, TrialParams) {
    let mut p = SimParams::default();
    p.measurement.model = NoiseModel::None;
    let tp = TrialParams {
        timeout_s: 15.0,
        ..Default::default()
    };
    (p, tp)
}

#[test]
fn baseline_docks_without_noise_and_runs_are_reproducible() {
    let kin = kin();
    let (p, tp) = noiseless();
    let run = |seed| {
        let mut w = SimWorld::new(&p, kin.clone(), seed).unwrap();
        let mut b = Baseline::new(&Default::default(), tp.goal_depth_m, shipped_period(), false);
        run_trial(&mut w, &mut b, &tp, seed)
    };
    let a = run(3);
    eprintln!("{:?} {} {} {} {}", a.outcome, a.time_s, a.m_est, a.m_true, a.max_f_true);
    assert_eq!(a.outcome, Outcome::Docked, "{}", a.reason);
    // The trial runs to the policy's DONE, past the paper's 5 mm ball, and judges it there.
    assert_eq!(a.final_phase, "DONE");
    assert!(
        a.paper_success && a.paper_time_s < a.time_s - 0.1,
        "{} vs {}",
        a.paper_time_s,
        a.time_s
    );
    assert!(a.done_depth_error_m <= tp.done_depth_tolerance_m && a.done_angle_deg <= tp.done_angle_tolerance_deg);
    let b = run(3);
    assert_eq!(a, b);
}

/// A policy that reports DONE 3 mm short of the trial's goal: inside the paper's 5 mm ball,
/// outside the 2 mm the truth at DONE allows.
#[test]
fn a_done_short_of_the_goal_is_a_false_done() {
    let kin = kin();
    let (p, tp) = noiseless();
    let mut w = SimWorld::new(&p, kin, 3).unwrap();
    let mut short = Baseline::new(&Default::default(), tp.goal_depth_m - 0.003, shipped_period(), false);
    let r = run_trial(&mut w, &mut short, &tp, 3);
    assert_eq!(r.outcome, Outcome::FalseDone, "{}", r.reason);
    assert!(
        !r.success() && r.paper_success,
        "the paper's test alone would call it docked: {}",
        r.reason
    );
    assert!(
        (r.done_depth_error_m - 0.003).abs() < 0.0015,
        "{}",
        r.done_depth_error_m
    );
    assert!(r.reason.contains("from the goal depth"), "{}", r.reason);
}

/// A pose source that sees the port `shift` m deeper along its axis than it is, at once.
struct Deeper {
    shift: f64,
    latest: Option<TrocarMeasurement>,
}

impl PoseSource for Deeper {
    fn update(&mut self, t: f64, at: &SensorInput<'_>) {
        let mut pose = *at.true_pose;
        pose.translation.vector += at.true_pose.rotation * nalgebra::Vector3::z() * self.shift;
        self.latest = Some(TrocarMeasurement { stamp: t, pose });
    }

    fn latest(&self, _now: f64) -> Option<TrocarMeasurement> {
        self.latest
    }
}

/// At DONE the trial reports the delivered estimate's offset from the true port along the
/// axis, signed: the share of the depth error that came from the estimate.
#[test]
fn done_reports_the_estimates_depth_error() {
    let kin = kin();
    let (p, tp) = noiseless();
    let run = |shift: f64| {
        let mut w = SimWorld::new(&p, kin.clone(), 3).unwrap();
        w.set_pose_source(Box::new(Deeper { shift, latest: None }));
        let mut b = Baseline::new(&Default::default(), tp.goal_depth_m, shipped_period(), false);
        run_trial(&mut w, &mut b, &tp, 3)
    };
    for shift in [0.0015, -0.0015, 0.0] {
        let r = run(shift);
        assert_eq!(r.final_phase, "DONE", "{}", r.reason);
        assert!(
            (r.done_estimate_depth_m - shift).abs() < 1e-4,
            "shift {shift}: {}",
            r.done_estimate_depth_m
        );
        // The baseline docks to the estimated goal: the tip ends the shift off the truth's.
        assert!(
            (r.done_depth_error_m - shift.abs()).abs() < 0.5e-3,
            "shift {shift}: depth error {}",
            r.done_depth_error_m
        );
    }
}

/// A policy that holds latched (only an operator resumes it) ends the trial there, as a
/// failure with the hold's code: no trial waits out its timeout for an operator.
#[test]
fn a_latched_hold_ends_the_trial() {
    struct Jammed(Baseline);
    impl Policy for Jammed {
        fn period(&self) -> f64 {
            self.0.period()
        }
        fn start(&mut self, kin: &dyn Kinematics) {
            self.0.start(kin);
        }
        fn tick(&mut self, kin: &dyn Kinematics, obs: &Observation) -> Action {
            let a = self.0.tick(kin, obs);
            if obs.t < 0.5 {
                return a;
            }
            Action {
                command: None,
                phase: "HOLD",
                hold_code: Some("FORCE_LIMIT"),
                latched: true,
                ..a
            }
        }
    }
    let kin = kin();
    let mut p = SimParams::default();
    p.measurement.model = NoiseModel::None;
    let tp = TrialParams::default();
    let mut w = SimWorld::new(&p, kin, 3).unwrap();
    let mut jammed = Jammed(Baseline::new(&Default::default(), tp.goal_depth_m, 0.01, false));
    let r = run_trial(&mut w, &mut jammed, &tp, 3);
    assert_eq!(r.outcome, Outcome::Held, "{}", r.reason);
    assert!((r.time_s - 0.5).abs() < 0.011, "ended at {} s", r.time_s);
    assert_eq!(r.final_hold, "FORCE_LIMIT");
    assert!(r.done_depth_error_m.is_nan() && r.done_estimate_depth_m.is_nan() && !r.paper_success);
}

#[test]
fn only_reachable_set_ups_are_drawn() {
    use rand::SeedableRng;
    use trocar_docking::sim::scenario::{Scenario, ScenarioParams};
    let kin = kin();
    let margin = 5f64.to_radians();
    let checked = ScenarioParams::default();
    let unchecked = ScenarioParams {
        reach_margin_deg: 0.0,
        ..checked.clone()
    };
    let mut rejected = 0;
    for seed in 0..300u64 {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let s = Scenario::sample(&checked, kin.as_ref(), &mut rng).unwrap();
        assert!(s.reachable(kin.as_ref(), margin).unwrap(), "seed {seed}");
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let raw = Scenario::sample(&unchecked, kin.as_ref(), &mut rng).unwrap();
        if !raw.reachable(kin.as_ref(), margin).unwrap() {
            rejected += 1;
        }
    }
    // Without the check some draws put the docking pose inside the wrist's last 5 deg;
    // not so many that the experiment's distribution is a different one.
    assert!((1..=30).contains(&rejected), "{rejected} of 300 unreachable");
}

#[test]
fn a_trocar_out_of_reach_is_refused_by_the_check() {
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};
    use trocar_docking::sim::scenario::Scenario;
    let kin = kin();
    let p = trocar_docking::sim::scenario::ScenarioParams::default();
    let q0 = p.q_nominal_rad;
    // 2 m away: no joint configuration gets there.
    let far = Scenario {
        q0,
        trocar_rest: Isometry3::from_parts(
            Translation3::new(2.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
        ),
    };
    assert!(!far.reachable(kin.as_ref(), 5f64.to_radians()).unwrap());
    // 12 cm straight below the start tip, pointing down: reachable.
    let tip = kin.fk(&nalgebra::SVector::<f64, 7>::from_column_slice(&q0)).unwrap();
    let near = Scenario {
        q0,
        trocar_rest: Isometry3::from_parts(
            Translation3::from(tip.translation.vector - nalgebra::Vector3::z() * 0.12),
            UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
        ),
    };
    assert!(near.reachable(kin.as_ref(), 5f64.to_radians()).unwrap());
}
