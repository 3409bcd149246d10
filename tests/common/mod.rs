//! Fixtures the controller tests share: the arm, its start pose and a trocar below it.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
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
