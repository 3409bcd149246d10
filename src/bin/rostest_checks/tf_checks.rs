//! `camera_tf`: the camera tied into the arm's tf tree. The estimator publishes its hand-eye
//! on `/tf_static` from the flange `lbr_link_ee` to the images' own frame (the camera_info's
//! `frame_id`): that transform must be the shipped mount (the estimator's
//! `estimator.flange_t_camera`, which the test's easy_handeye file describes in
//! `lbr_link_7`, carried to the flange through robot_description), and the images' frame must
//! have that one parent on `/tf_static` and `/tf` (the URDF's camera link is another frame).

use std::collections::BTreeSet;

use ::trocar_docking::kinematics::FLANGE_LINK;
use ::trocar_docking::ros::msgs::{sensor_msgs, tf2_msgs};
use ::trocar_docking::ros::topics;
use ::trocar_docking::vision::EstimatorParams;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::common::{wait_for, CheckParams};

/// Every transform seen on `topic`: (parent, child, pose).
type Seen = std::sync::Arc<std::sync::Mutex<Vec<(String, String, Isometry3<f64>)>>>;

fn collect(topic: &str, seen: &Seen) -> Result<rosrust::Subscriber, String> {
    let seen = seen.clone();
    rosrust::subscribe(topic, 100, move |m: tf2_msgs::TFMessage| {
        let Ok(mut s) = seen.lock() else { return };
        for t in m.transforms {
            let (p, r) = (&t.transform.translation, &t.transform.rotation);
            let pose = Isometry3::from_parts(
                Translation3::new(p.x, p.y, p.z),
                UnitQuaternion::from_quaternion(Quaternion::new(r.w, r.x, r.y, r.z)),
            );
            s.push((t.header.frame_id, t.child_frame_id, pose));
        }
    })
    .map_err(|e| format!("subscribe {topic}: {e}"))
}

/// See the module doc.
pub fn camera_tf(p: &CheckParams) -> Result<String, String> {
    let (info, _info_sub) = crate::common::subscribe_latest::<sensor_msgs::CameraInfo>(topics::SIM_CAMERA_INFO)?;
    let frame = wait_for(p.startup_timeout, || info.get())
        .ok_or("no camera_info")?
        .header
        .frame_id;
    let seen: Seen = Seen::default();
    let _subs = [collect("/tf_static", &seen)?, collect(topics::TF, &seen)?];
    let parent_of_frame = || {
        seen.lock()
            .ok()?
            .iter()
            .find(|(_, c, _)| *c == frame)
            .map(|(parent, _, pose)| (parent.clone(), *pose))
    };
    let (parent, pose) =
        wait_for(p.startup_timeout, parent_of_frame).ok_or_else(|| format!("no tf to the images' frame `{frame}`"))?;
    // Two more seconds of /tf (robot_state_publisher) to see any other parent.
    std::thread::sleep(std::time::Duration::from_secs(2));
    let parents: BTreeSet<String> = seen
        .lock()
        .map_err(|_| "poisoned")?
        .iter()
        .filter(|(_, c, _)| *c == frame)
        .map(|(p, _, _)| p.clone())
        .collect();
    if parent != FLANGE_LINK || parents.len() != 1 {
        return Err(format!(
            "`{frame}` has the parents {parents:?}, expected {FLANGE_LINK} alone"
        ));
    }
    let nominal = EstimatorParams::default()
        .flange_t_camera
        .to_isometry()
        .map_err(|e| e.to_string())?;
    let dt = (pose.translation.vector - nominal.translation.vector).norm();
    let dr = pose.rotation.angle_to(&nominal.rotation);
    let summary = format!(
        "{FLANGE_LINK} -> {frame}: {:.4} mm, {:.5} deg from the mount",
        dt * 1e3,
        dr.to_degrees()
    );
    if dt > 1e-6 || dr > 1e-5 {
        return Err(summary);
    }
    Ok(summary)
}
