//! Fixtures the tests share: the arm, its start pose, a trocar below it, and an input
//! without contact; the simulated camera, its mount, and the shipped hand-eye.

// Each test file uses some of them.
#![allow(dead_code)]

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use trocar_docking::control::{ControlInput, Stamped};
use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::{JointVector, Kinematics, LbrKinematics};

/// The LBR Med 7 with the default endoscope.
pub fn kin() -> LbrKinematics {
    LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap()
}

/// The start pose of the arm.
pub fn q_start() -> JointVector {
    JointVector::from_column_slice(&[0.0, 0.6, 0.0, -1.2, 0.0, 0.9, 0.0])
}

/// A trocar 0.1 m below the start tip, axis pointing down.
pub fn trocar(kin: &LbrKinematics) -> Isometry3<f64> {
    let tip = kin.fk(&q_start()).unwrap();
    Isometry3::from_parts(
        Translation3::from(tip.translation.vector + Vector3::new(0.01, 0.0, -0.1)),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
    )
}

/// An input measured at `now` with no contact (zero external torques): the joints `q`, and
/// the trocar pose `trocar` captured at `trocar_stamp`.
pub fn contact_free_input(now: f64, q: JointVector, trocar_stamp: f64, trocar: Isometry3<f64>) -> ControlInput {
    ControlInput {
        scope: None,
        now,
        joints: Some(Stamped { stamp: now, value: q }),
        tau_ext: Some(Stamped {
            stamp: now,
            value: JointVector::zeros(),
        }),
        torque_samples: Default::default(),
        trocar: Some(Stamped {
            stamp: trocar_stamp,
            value: trocar,
        }),
    }
}

/// The simulated camera (config/camera_zedm.yaml).
pub fn zedm_camera() -> trocar_docking::vision::CameraModel {
    trocar_docking::vision::CameraModel::from_yaml_file(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/camera_zedm.yaml"),
    )
    .unwrap()
}

/// The simulator's camera mount (config/lbr_med_sim.yaml `camera.flange_t_camera`).
pub fn camera_mount() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.001, 0.0695, 0.0405),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 15.2f64.to_radians()),
    )
}

/// The shipped hand-eye (config/hand_eye.yaml `flange_t_camera`), read as `render-trocar
/// --mount` and `trocar-pose --endoscope-mount` read it.
pub fn shipped_mount() -> Isometry3<f64> {
    trocar_docking::cli::markerless::read_mount(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/hand_eye.yaml"),
    )
    .unwrap()
}
