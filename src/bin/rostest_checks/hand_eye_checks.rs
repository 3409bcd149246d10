//! `hand_eye`: the calibration node's `~auto` in the simulator (which drives the arm through
//! its poses, samples and computes), then `~save`; the saved mount must be within the bounds
//! of the simulator's true mount (`/lbr_med_sim/camera/flange_t_camera`), its held-out
//! residuals within the preflight's bounds (`preflight::Limits`, the `HAND_EYE` check's),
//! no pose skipped, `~auto` within `time_limit`, and the file one the preflight's hand-eye
//! check reads (dated today, with its residuals). With `expect_target_moving` the world's
//! breathing must be named in `~auto`'s reply. Then a result without held-out residuals (down
//! to 3 samples) must be refused by `~save`, the saved file unchanged, and the package's
//! shipped hand-eye file (the estimator's `hand_eye_file`) never written; the estimator on the
//! saved file publishing before the check returns.

use std::time::Instant;

use ::trocar_docking::vision::estimator::PoseYaml;
use ::trocar_docking::vision::hand_eye::HeldOut;

use ::trocar_docking::ros::msgs::geometry_msgs;

use crate::common::{subscribe_latest, trigger, wait_for, CheckParams};

#[derive(serde::Deserialize)]
struct Saved {
    flange_t_camera: PoseYaml,
    held_out: HeldOut,
}

fn read(path: &str) -> Result<String, String> {
    std::fs::read_to_string(path).map_err(|e| format!("{path}: {e}"))
}

/// A result that cannot be judged (3 samples: no held-out residuals) is refused by `~save`,
/// the saved file (`text`) stays the good one and the package's shipped file is not written.
/// Returns `~compute`'s and `~save`'s replies.
fn a_bad_result_is_refused(
    p: &CheckParams,
    text: &str,
    shipped: &str,
    shipped_text: &str,
) -> Result<(String, String), String> {
    let node = &p.hand_eye_node;
    while !trigger(&format!("{node}/remove_sample"), p.startup_timeout)?.contains("; 3 samples,") {}
    let three = trigger(&format!("{node}/compute"), p.startup_timeout).unwrap_or_else(|e| e);
    let refused = match trigger(&format!("{node}/save"), p.startup_timeout) {
        Ok(m) => return Err(format!("~save wrote a 3-sample result: {m}")),
        Err(e) if e.contains("no held-out residuals") => e,
        Err(e) => return Err(format!("~save refused for another reason: {e}")),
    };
    if read(&p.hand_eye_output)? != text {
        return Err("the refused ~save changed the saved file".into());
    }
    if read(shipped)? != shipped_text {
        return Err(format!("the package's {shipped} was written"));
    }
    Ok((three, refused))
}

/// See the module doc.
pub fn hand_eye(p: &CheckParams) -> Result<String, String> {
    let truth: PoseYaml = rosrust::param("/lbr_med_sim/camera/flange_t_camera")
        .ok_or("bad parameter name")?
        .get()
        .map_err(|e| format!("the simulator's true mount: {e}"))?;
    let truth = truth.to_isometry().map_err(|e| e.to_string())?;
    let expect_moving = p.expect_target_moving;
    let shipped: String = rosrust::param("/trocar_estimator/hand_eye_file")
        .ok_or("bad parameter name")?
        .get()
        .map_err(|e| format!("the estimator's hand_eye_file: {e}"))?;
    let shipped_text = read(&shipped)?;
    // The graph is up once the estimator sees the marker (the simulator's camera and its
    // camera_info flowing); then a second for the node to have them too.
    let (marker, _sub) = subscribe_latest::<geometry_msgs::PoseStamped>("/trocar_estimator/marker_pose")?;
    wait_for(p.startup_timeout, || marker.get()).ok_or("no marker pose from the estimator")?;
    std::thread::sleep(std::time::Duration::from_secs(1));
    let node = &p.hand_eye_node;
    let t0 = Instant::now();
    let auto = trigger(&format!("{node}/auto"), p.startup_timeout)?;
    let secs = t0.elapsed().as_secs_f64();
    if secs > p.time_limit {
        return Err(format!("~auto took {secs:.0} s, over {} s: {auto}", p.time_limit));
    }
    if auto.contains("skipped") {
        return Err(format!("~auto skipped a pose: {auto}"));
    }
    if expect_moving != auto.contains("target moving") {
        return Err(format!("the breathing target named: expected {expect_moving}: {auto}"));
    }
    let saved = trigger(&format!("{node}/save"), p.startup_timeout)?;
    let text = read(&p.hand_eye_output)?;
    let s: Saved = ::trocar_docking::config::from_yaml_str(&p.hand_eye_output, &text).map_err(|e| e.to_string())?;
    let m = s.flange_t_camera.to_isometry().map_err(|e| e.to_string())?;
    let dt = (m.translation.vector - truth.translation.vector).norm();
    let dr = m.rotation.angle_to(&truth.rotation).to_degrees();
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    let h = ::trocar_docking::preflight::hand_eye_file(&p.hand_eye_output, &text, now, now)?;
    if h.age_source != "calibrated date" || h.age_days > 1.0 || h.residual_max_m.is_none() {
        return Err(format!("the saved file is not dated today with its residuals: {h:?}"));
    }
    let lim = ::trocar_docking::preflight::Limits::default();
    let (b_mm, b_deg) = (
        lim.hand_eye_max_residual_m * 1e3,
        lim.hand_eye_max_residual_rad.to_degrees(),
    );
    let summary = format!(
        "mount {:.3} mm, {:.3} deg from the truth; held-out {:.3} mm rms ({:.3} max), {:.3} deg rms ({:.3} max); \
         ~auto {secs:.0} s; {auto}; {saved}",
        dt * 1e3,
        dr,
        s.held_out.position_rms_mm,
        s.held_out.position_max_mm,
        s.held_out.rotation_rms_deg,
        s.held_out.rotation_max_deg
    );
    if dt > p.max_mount_error_m || dr > p.max_mount_error_deg {
        return Err(format!(
            "over {} mm / {} deg: {summary}",
            p.max_mount_error_m * 1e3,
            p.max_mount_error_deg
        ));
    }
    if !(s.held_out.position_max_mm <= b_mm && s.held_out.rotation_max_deg <= b_deg) {
        return Err(format!(
            "held-out residuals over the preflight's {b_mm} mm / {b_deg} deg: {summary}"
        ));
    }
    let (three, refused) = a_bad_result_is_refused(p, &text, &shipped, &shipped_text)?;
    // The docking's estimator starts once the file exists: its first pose before `~start`
    // (on a busy host it takes seconds to come up).
    let (pose, _pose_sub) = subscribe_latest::<geometry_msgs::PoseStamped>(::trocar_docking::ros::topics::TROCAR_POSE)?;
    wait_for(p.startup_timeout, || pose.get()).ok_or("no trocar pose from the estimator on the saved file")?;
    Ok(format!("{summary}; then 3 samples ({three}): {refused}"))
}
