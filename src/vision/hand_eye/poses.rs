//! Poses for the automatic mode: the camera orbits the marker's centre (tilted about two
//! axes of the image and rolled about the line of sight), so the marker stays where it is in
//! the image while the flange turns about three axes; two of the poses also move closer and
//! farther along the line of sight (orbits alone cannot tell a wrong marker size from a
//! camera shifted along its optical axis). Each camera pose is reached in joint
//! space by damped least squares on the flange, the joints kept a margin inside their limits,
//! and kept only when the marker (through the current hand-eye guess) stays fully in view.

use nalgebra::{Isometry3, Matrix6, Translation3, Unit, UnitQuaternion, Vector3, Vector6};

use super::refine::marker_corners;
use crate::kinematics::{JointVector, Kinematics};
use crate::vision::{CameraModel, VisionError};

/// Parameters of the pose plan. The orbit's tilt and roll and the marker's side are the
/// calibration node's parameters (`config/hand_eye_calibration.yaml`: [`PlanParams::new`]);
/// the margins and the approach are the plan's own.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanParams {
    /// Tilt of the orbit about the image's axes, rad.
    pub tilt_rad: f64,
    /// Roll about the line of sight, rad.
    pub roll_rad: f64,
    /// Joints kept this far inside their limits, rad.
    pub joint_margin_rad: f64,
    /// Every marker corner at least this far inside the image, px.
    pub border_margin_px: f64,
    /// The marker's side, m.
    pub marker_size: f64,
    /// Two poses move along the line of sight by this fraction of the distance, in and out.
    pub approach_fraction: f64,
}

impl PlanParams {
    /// The plan of an orbit tilted by `tilt_rad` and rolled by `roll_rad` about a marker of
    /// side `marker_size` (m), with the plan's own margins: the joints 5 deg inside their
    /// limits, every corner 30 px inside the image, and the approach poses 20 % of the
    /// distance in and out.
    pub fn new(tilt_rad: f64, roll_rad: f64, marker_size: f64) -> Self {
        Self {
            tilt_rad,
            roll_rad,
            joint_margin_rad: 5f64.to_radians(),
            border_margin_px: 30.0,
            marker_size,
            approach_fraction: 0.2,
        }
    }
}

/// The 12 orbits (rotation about the marker's centre in the camera frame, and the move along
/// the line of sight as a fraction of the distance): tilts about x, y and the two diagonals,
/// both ways; rolls both ways; two tilt-and-roll, one closer and one farther.
fn orbit(p: &PlanParams, sight: &Unit<Vector3<f64>>) -> Vec<(UnitQuaternion<f64>, f64)> {
    let t = p.tilt_rad;
    let tilt =
        |x: f64, y: f64, a: f64| UnitQuaternion::from_axis_angle(&Unit::new_normalize(Vector3::new(x, y, 0.0)), a);
    let roll = |a: f64| UnitQuaternion::from_axis_angle(sight, a);
    let a = p.approach_fraction;
    vec![
        (tilt(1.0, 0.0, t), 0.0),
        (tilt(0.0, 1.0, t), 0.0),
        (tilt(1.0, 0.0, -t), 0.0),
        (tilt(0.0, 1.0, -t), 0.0),
        (tilt(1.0, 1.0, t), 0.0),
        (tilt(1.0, -1.0, t), 0.0),
        (tilt(1.0, 1.0, -t), 0.0),
        (tilt(1.0, -1.0, -t), 0.0),
        (roll(p.roll_rad), 0.0),
        (roll(-p.roll_rad), 0.0),
        (tilt(1.0, 0.0, t / 2.0) * roll(p.roll_rad / 2.0), a),
        (tilt(0.0, 1.0, -t / 2.0) * roll(-p.roll_rad / 2.0), -a),
    ]
}

/// Damped least squares from `q0` to the flange pose `goal`, joints clamped inside the limits.
fn solve_ik(kin: &dyn Kinematics, q0: &JointVector, goal: &Isometry3<f64>, margin: f64) -> Option<JointVector> {
    let lim = kin.limits();
    let (lo, hi) = (lim.lower.add_scalar(margin), lim.upper.add_scalar(-margin));
    let mut q = *q0;
    for _ in 0..200 {
        let (p, j) = kin.fk_jacobian(&q).ok()?;
        let dp = goal.translation.vector - p.translation.vector;
        let dr = (goal.rotation * p.rotation.inverse()).scaled_axis();
        if dp.norm() < 1e-5 && dr.norm() < 1e-4 {
            return Some(q);
        }
        let e = Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z);
        let jjt = j * j.transpose() + Matrix6::identity() * 1e-4;
        let dq = j.transpose() * jjt.cholesky()?.solve(&e);
        q = (q + dq).zip_zip_map(&lo, &hi, |v, l, h| v.clamp(l, h));
    }
    None
}

/// The marker's corners ([`marker_corners`]' order) projected into the image from `camera_t_marker`;
/// `None` when one is behind the camera.
pub fn projected_corners(camera: &CameraModel, camera_t_marker: &Isometry3<f64>, size: f64) -> Option<[[f64; 2]; 4]> {
    let c = marker_corners(size);
    let p = |i: usize| camera.project(&(camera_t_marker * c[i]).coords);
    Some([p(0)?, p(1)?, p(2)?, p(3)?])
}

/// The marker's nearest corner distance from the image border, px, seen from `camera_t_marker`
/// (negative when a corner is outside; `None` when one is behind the camera).
pub fn border_distance_px(camera: &CameraModel, camera_t_marker: &Isometry3<f64>, size: f64) -> Option<f64> {
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let corners = projected_corners(camera, camera_t_marker, size)?;
    Some(
        corners
            .iter()
            .map(|[x, y]| x.min(*y).min(w - 1.0 - x).min(h - 1.0 - y))
            .fold(f64::INFINITY, f64::min),
    )
}

/// Joint positions for the automatic mode around `q0` (the marker seen at `camera_t_marker`
/// there), through the hand-eye guess `flange_t_camera`. Orbits that cannot be reached are
/// tried at half their angle, then left out; an error when fewer than 8 remain.
pub fn plan(
    kin: &dyn Kinematics,
    q0: &JointVector,
    flange_t_camera: &Isometry3<f64>,
    camera_t_marker: &Isometry3<f64>,
    camera: &CameraModel,
    p: &PlanParams,
) -> Result<Vec<JointVector>, VisionError> {
    let flange0 = kin.fk(q0).map_err(|e| VisionError::InvalidInput(e.to_string()))?;
    let base_t_camera0 = flange0 * flange_t_camera;
    let base_t_marker = base_t_camera0 * camera_t_marker;
    let centre = camera_t_marker.translation.vector;
    let sight = Unit::new_normalize(centre);
    let mut out = Vec::new();
    for (r, approach) in orbit(p, &sight) {
        for fraction in [1.0, 0.5] {
            let r = UnitQuaternion::identity().slerp(&r, fraction);
            // Rotate the camera about the marker's centre (camera frame at q0), then move it
            // along the line of sight.
            let about = Translation3::from(centre)
                * Isometry3::from_parts(Translation3::identity(), r)
                * Translation3::from(-centre)
                * Translation3::from(centre * approach * fraction);
            let goal = base_t_camera0 * about * flange_t_camera.inverse();
            let Some(q) = solve_ik(kin, q0, &goal, p.joint_margin_rad) else {
                continue;
            };
            let Ok(f) = kin.fk(&q) else { continue };
            let seen = (f * flange_t_camera).inverse() * base_t_marker;
            if border_distance_px(camera, &seen, p.marker_size).is_some_and(|d| d >= p.border_margin_px) {
                out.push(q);
                break;
            }
        }
    }
    if out.len() < super::quality::MIN_SAMPLES {
        return Err(VisionError::InvalidInput(format!(
            "only {} of 12 calibration poses are reachable with the marker in view: move the arm so the marker \
             is near the image centre, 0.2-0.4 m away, and the joints away from their limits",
            out.len()
        )));
    }
    Ok(out)
}
