//! The controller's trocar filter: along the axis, where breathing moves the port and no
//! contact guides the tip, a port moving at a steady speed is followed without lag (the
//! second-order tracking filter); across it the first-order filter smooths, lagging by about
//! its time constant.

use nalgebra::{Isometry3, Translation3, Vector3};
use trocar_docking::control::{Controller, ControllerParams};
use trocar_docking::kinematics::Kinematics;

mod common;
use common::{contact_free_input, kin, q_start, trocar};

/// Dock towards a port that moves at `velocity` (base frame, m/s) from t = 0, seen by a
/// 15 Hz camera (each pose stamped at capture, held until the next); the arm follows every
/// command. Returns the goal's offset from where it should be (the true port's goal), split
/// into its part along the axis and its norm across it, after 1.5 s of motion.
fn goal_offset_after_motion(p: ControllerParams, velocity: Vector3<f64>) -> (f64, f64) {
    let kin = kin();
    let troc0 = trocar(&kin);
    let axis = troc0.rotation * Vector3::z();
    let depth = p.insertion_depth_m;
    let mut c = Controller::new(p, kin.limits().clone()).unwrap();
    c.start().unwrap();
    let mut q = q_start();
    let dt = 0.01;
    let frame = 1.0 / 15.0;
    let port_at = |t: f64| {
        Isometry3::from_parts(
            Translation3::from(troc0.translation.vector + velocity * t.max(0.0)),
            troc0.rotation,
        )
    };
    let mut last = (0.0, 0.0);
    for k in 0..=150 {
        let now = k as f64 * dt;
        let capture = (now / frame).floor() * frame;
        let input = contact_free_input(now, q, capture, port_at(capture));
        let out = c.step(&kin, &input);
        q = out.command.unwrap_or(q);
        if let Some(goal) = out.goal {
            let truth = port_at(now).translation.vector + axis * depth;
            let e = goal.coords - truth;
            let along = e.dot(&axis);
            last = (along, (e - axis * along).norm());
        }
    }
    last
}

#[test]
fn a_port_moving_along_its_axis_is_followed_without_lag() {
    let p = ControllerParams::default();
    assert!(
        p.trocar_depth_filter_time_constant_s > 0.0,
        "the shipped filter tracks the depth"
    );
    let kin = kin();
    let axis = trocar(&kin).rotation * Vector3::z();
    // 10 mm/s: a 4 mm breath at 0.4 Hz at its fastest.
    let v = 0.01;
    let (along, across) = goal_offset_after_motion(p.clone(), axis * v);
    // The camera's frame period alone holds a pose up to 67 ms: 0.67 mm at 10 mm/s.
    let hold = v / 15.0;
    assert!(along.abs() <= hold + 1e-4, "tracked along the axis: {along} m");
    assert!(
        across < 1e-6,
        "a motion along the axis moves nothing across: {across} m"
    );

    // The first-order filter alone lags by about its time constant more.
    let first_order = ControllerParams {
        trocar_depth_filter_time_constant_s: 0.0,
        ..p.clone()
    };
    let (lagged, _) = goal_offset_after_motion(first_order, axis * v);
    assert!(
        lagged < -(hold * 0.5 + 0.8 * v * p.trocar_filter_time_constant_s),
        "first-order lag {lagged} m"
    );
}

#[test]
fn across_the_axis_the_first_order_filter_smooths() {
    let p = ControllerParams::default();
    let kin = kin();
    let axis = trocar(&kin).rotation * Vector3::z();
    let side = axis.cross(&Vector3::x()).normalize();
    let v = 0.01;
    let (along, across) = goal_offset_after_motion(p.clone(), side * v);
    assert!(along.abs() < 1e-6, "nothing moves along the axis: {along} m");
    // The first-order lag (about v tau) plus the frame hold, not the tracking filter's none.
    assert!(across > 0.8 * v * p.trocar_filter_time_constant_s, "across: {across} m");
    assert!(
        across < v * (p.trocar_filter_time_constant_s + 1.0 / 15.0) + 1e-4,
        "across: {across} m"
    );
}
