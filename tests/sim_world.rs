//! The simulator with the LBR Med 7 model: randomised starts, a closed loop with the
//! baseline policy, determinism.

use std::sync::Arc;

use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::{Kinematics, LbrKinematics};
use trocar_docking::sim::noise::NoiseModel;
use trocar_docking::sim::{SimParams, SimWorld};
use trocar_docking::trials::baseline::Baseline;
use trocar_docking::trials::run::{run_trial, Outcome, TrialParams};

fn kin() -> Arc<dyn Kinematics> {
    Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).expect("model"))
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

#[test]
fn baseline_docks_without_noise_and_runs_are_reproducible() {
    let kin = kin();
    let mut p = SimParams::default();
    p.measurement.model = NoiseModel::None;
    let tp = TrialParams {
        timeout_s: 15.0,
        ..Default::default()
    };
    let run = |seed| {
        let mut w = SimWorld::new(&p, kin.clone(), seed).unwrap();
        let mut b = Baseline::new(&Default::default(), tp.goal_depth_m, 1.0 / tp.control_rate_hz, false);
        run_trial(&mut w, &mut b, &tp, seed)
    };
    let a = run(3);
    eprintln!("{:?} {} {} {} {}", a.outcome, a.time_s, a.m_est, a.m_true, a.max_f_true);
    assert_eq!(a.outcome, Outcome::Docked, "{}", a.reason);
    let b = run(3);
    assert_eq!(a, b);
}
