//! The camera mount keeps the trocar's marker in full view over the whole docking.
//!
//! The ZED sits 70 mm beside the endoscope's shaft (config/hand_eye.yaml, the URDF's
//! `camera_nominal`). Looking straight along the shaft, the marker on the trocar's face
//! drifts to the image's top edge as the tip goes in, and leaves it at full depth: the
//! estimator then loses the trocar (or, worse, finds a marker cut by the border). The shipped
//! mount is pitched 15 deg towards the shaft. This test walks the tip along the insertion axis
//! from well before the port to past the goal and checks that every marker corner stays inside
//! the image by a margin, with the shipped calibration; and that the unpitched mount fails it,
//! so that the test can tell the difference.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use std::path::Path;
use trocar_docking::vision::CameraModel;

mod common;

/// The tip frame in the flange frame: the endoscope is 0.25 m long along the flange's z
/// (urdf/lbr_med7_r800_endoscope.urdf, `endoscope_tip_joint`).
const TOOL_LENGTH_M: f64 = 0.25;
/// The marker's side (config/trocar_estimator.yaml, `marker.size_m`).
const MARKER_SIZE_M: f64 = 0.04;
/// Corners closer than this to the border count as out of view (the estimator's
/// `border_margin_px` is 4; this keeps room for breathing and a lateral offset).
const MARGIN_PX: f64 = 20.0;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The smallest distance of a marker corner from the image border, px, with the tip `depth`
/// metres past the port on the axis (negative before it), the shaft `lateral` metres off the
/// axis along `side` and rolled by `roll` rad about it. `None`: a corner is behind the camera.
fn border_distance(mount: &Isometry3<f64>, cam: &CameraModel, depth: f64, lateral: f64, roll: f64) -> Option<f64> {
    // Port at the origin, insertion along +z; the tip frame's z is the shaft.
    let side = Vector3::new(roll.cos(), roll.sin(), 0.0);
    let tip = Isometry3::from_parts(
        Translation3::from(Vector3::z() * depth + side * lateral),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll),
    );
    let flange = tip * Translation3::new(0.0, 0.0, -TOOL_LENGTH_M);
    let camera_pose = flange * mount;
    let [fx, fy, cx, cy] = cam.intrinsics();
    let (w, h) = (f64::from(cam.width), f64::from(cam.height));
    let half = MARKER_SIZE_M / 2.0;
    let mut nearest = f64::INFINITY;
    for (x, y) in [(-half, -half), (half, -half), (half, half), (-half, half)] {
        let p = camera_pose.inverse() * Point3::new(x, y, 0.0);
        if p.z <= 0.0 {
            return None;
        }
        let (u, v) = (cx + fx * p.x / p.z, cy + fy * p.y / p.z);
        nearest = nearest.min(u.min(v).min(w - 1.0 - u).min(h - 1.0 - v));
    }
    Some(nearest)
}

/// The worst border distance over the docking path: stand-off at 0.2 m down to 5 mm past
/// the 30 mm goal, the shaft up to 3 mm off the axis, at any roll.
fn worst_over_docking(mount: &Isometry3<f64>) -> f64 {
    let cam = common::zedm_camera();
    let mut worst = f64::INFINITY;
    for i in 0..=47 {
        let depth = -0.2 + 0.005 * f64::from(i);
        for lateral in [0.0, 0.003] {
            for k in 0..12 {
                let roll = f64::from(k) * std::f64::consts::TAU / 12.0;
                let d = border_distance(mount, &cam, depth, lateral, roll).unwrap_or(f64::NEG_INFINITY);
                worst = worst.min(d);
            }
        }
    }
    worst
}

#[test]
fn the_shipped_mount_keeps_the_marker_in_view_to_full_depth() {
    let worst = worst_over_docking(&common::shipped_mount());
    assert!(
        worst > MARGIN_PX,
        "a marker corner comes within {worst:.1} px of the border"
    );
}

#[test]
fn a_mount_looking_along_the_shaft_loses_the_marker_at_full_depth() {
    let straight = Isometry3::from_parts(common::shipped_mount().translation, UnitQuaternion::identity());
    let worst = worst_over_docking(&straight);
    assert!(worst < MARGIN_PX, "the unpitched mount kept {worst:.1} px");
    // ... at the goal itself, not just at the extremes of the path.
    let at_goal = border_distance(&straight, &common::zedm_camera(), 0.03, 0.0, 0.0).unwrap();
    assert!(at_goal < MARGIN_PX, "{at_goal:.1} px at the goal");
}

#[test]
fn the_urdf_camera_frame_is_the_hand_eye_mount() {
    // RViz and the estimator must agree on where the camera is.
    let urdf = std::fs::read_to_string(root().join("urdf/lbr_med7_r800_endoscope.urdf")).unwrap();
    let line = urdf
        .lines()
        .find(|l| l.contains("<child link=\"camera_nominal\"/>"))
        .expect("camera joint");
    // The images' own frame (the simulator's, config/lbr_med_sim.yaml `camera.frame`) is no
    // link of the URDF: its one parent is the flange, through the estimator's static tf.
    let sim = std::fs::read_to_string(root().join("config/lbr_med_sim.yaml")).unwrap();
    let frame = sim
        .lines()
        .find_map(|l| l.trim().strip_prefix("frame:"))
        .map(|f| f.split('#').next().unwrap().trim())
        .expect("camera.frame");
    assert!(!urdf.contains(&format!("\"{frame}\"")), "the URDF has a link `{frame}`");
    let attr = |name: &str| -> Vec<f64> {
        let start = line.find(&format!("{name}=\"")).unwrap() + name.len() + 2;
        let end = start + line[start..].find('"').unwrap();
        line[start..end]
            .split_whitespace()
            .map(|v| v.parse().unwrap())
            .collect()
    };
    let (xyz, rpy) = (attr("xyz"), attr("rpy"));
    let urdf_mount = Isometry3::from_parts(
        Translation3::new(xyz[0], xyz[1], xyz[2]),
        UnitQuaternion::from_euler_angles(rpy[0], rpy[1], rpy[2]),
    );
    let m = common::shipped_mount();
    assert!((urdf_mount.translation.vector - m.translation.vector).norm() < 1e-6);
    assert!(urdf_mount.rotation.angle_to(&m.rotation) < 1e-5);
}
