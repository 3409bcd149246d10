//! `hand_eye`: the calibration node's `~auto` in the simulator (which drives the arm through
//! its poses, samples and computes), then `~save`; the saved mount must be within the bounds
//! of the simulator's true mount (`/lbr_med_sim/camera/flange_t_camera`), `~auto` within
//! `time_limit`, and the file one the preflight's hand-eye check reads (dated today, with
//! its residuals).

use std::time::Instant;

use ::trocar_docking::vision::estimator::PoseYaml;

use ::trocar_docking::ros::msgs::geometry_msgs;

use crate::common::{subscribe_latest, trigger, wait_for, CheckParams};

#[derive(serde::Deserialize)]
struct Mount {
    flange_t_camera: PoseYaml,
}

/// See the module doc.
pub fn hand_eye(p: &CheckParams) -> Result<String, String> {
    let truth: PoseYaml = rosrust::param("/lbr_med_sim/camera/flange_t_camera")
        .ok_or("bad parameter name")?
        .get()
        .map_err(|e| format!("the simulator's true mount: {e}"))?;
    let truth = truth.to_isometry().map_err(|e| e.to_string())?;
    // The graph is up once the estimator sees the marker (the simulator's camera and its
    // camera_info flowing); then a second for the node to have them too.
    let (marker, _sub) = subscribe_latest::<geometry_msgs::PoseStamped>("/trocar_estimator/marker_pose")?;
    wait_for(p.startup_timeout, || marker.get()).ok_or("no marker pose from the estimator")?;
    std::thread::sleep(std::time::Duration::from_secs(1));
    let t0 = Instant::now();
    let auto = trigger(&format!("{}/auto", p.hand_eye_node), p.startup_timeout)?;
    let secs = t0.elapsed().as_secs_f64();
    if secs > p.time_limit {
        return Err(format!("~auto took {secs:.0} s, over {} s: {auto}", p.time_limit));
    }
    let saved = trigger(&format!("{}/save", p.hand_eye_node), p.startup_timeout)?;
    let text = std::fs::read_to_string(&p.hand_eye_output).map_err(|e| format!("{}: {e}", p.hand_eye_output))?;
    let mount: Mount = ::trocar_docking::config::from_yaml_str(&p.hand_eye_output, &text).map_err(|e| e.to_string())?;
    let m = mount.flange_t_camera.to_isometry().map_err(|e| e.to_string())?;
    let dt = (m.translation.vector - truth.translation.vector).norm();
    let dr = m.rotation.angle_to(&truth.rotation).to_degrees();
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    let h = ::trocar_docking::preflight::hand_eye_file(&p.hand_eye_output, &text, now, now)?;
    if h.age_source != "calibrated date" || h.age_days > 1.0 || h.residual_max_m.is_none() {
        return Err(format!("the saved file is not dated today with its residuals: {h:?}"));
    }
    let summary = format!(
        "mount {:.3} mm, {:.3} deg from the truth; ~auto {secs:.0} s; {auto}; {saved}",
        dt * 1e3,
        dr
    );
    if dt > p.max_mount_error_m || dr > p.max_mount_error_deg {
        return Err(format!(
            "over {} mm / {} deg: {summary}",
            p.max_mount_error_m * 1e3,
            p.max_mount_error_deg
        ));
    }
    Ok(summary)
}
