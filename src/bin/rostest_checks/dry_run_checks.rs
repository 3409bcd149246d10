//! The dry run (`dry_run:=true`): a whole docking steered on the ghost arm, with nothing on
//! the driver's command topic and the real arm never moving.

use ::trocar_docking::kinematics::{joint_names, JointVector};
use ::trocar_docking::ros::convert;
use ::trocar_docking::ros::msgs::{sensor_msgs, trajectory_msgs, trocar_docking};

use crate::common::{subscribe_latest, trigger, wait_for, CheckParams, Latest};
use crate::docking_checks::{check_done_code, wait_for_end};

/// The joints of a JointState in the controller's order, if it has them all.
fn joints(m: &sensor_msgs::JointState) -> Option<JointVector> {
    convert::joint_positions("", m, &joint_names()).ok()
}

/// The largest change of any joint of the real arm since its first state, deg.
fn real_motion_deg(first: &JointVector, now: &Latest<sensor_msgs::JointState>) -> Result<f64, String> {
    let q = now
        .get()
        .as_ref()
        .and_then(joints)
        .ok_or("no joint state of the real arm")?;
    Ok((q - first).amax().to_degrees())
}

/// Start the controller in a dry run and wait for DONE; judge: its code `done_code` (the
/// ghost never meets the seal: DEPTH_UNVERIFIED, the DONE that says the depth was not
/// verified, where a docking would hold DEPTH_UNCERTAIN), no command on the driver's
/// topic, at least `min_commands` on the preview topic, the ghost's joints the last
/// preview command, the real arm still within `max_hold_motion_deg`, the ghost's tip at
/// the goal.
pub fn dry_run(p: &CheckParams) -> Result<String, String> {
    let (status, _s1) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let (driver, _s2) = subscribe_latest::<trajectory_msgs::JointTrajectory>(&p.command_topic)?;
    let (preview, _s3) = subscribe_latest::<trajectory_msgs::JointTrajectory>(&p.preview_topic)?;
    let (ghost, _s4) = subscribe_latest::<sensor_msgs::JointState>(&p.preview_joint_states_topic)?;
    let (real, _s5) = subscribe_latest::<sensor_msgs::JointState>(&p.joint_states_topic)?;
    wait_for(p.startup_timeout, || status.get()).ok_or("no status message")?;
    let first =
        wait_for(p.startup_timeout, || real.get().as_ref().and_then(joints)).ok_or("no joint state of the real arm")?;
    if p.call_start {
        trigger(&format!("{}/start", p.controller), p.startup_timeout)?;
    }
    let done = wait_for_end(p, &status).map_err(|e| format!("the ghost: {e}"))?;
    if done.phase != "DONE" {
        return Err(format!("ABORTED: {}", done.hold_reason));
    }
    check_done_code(p, &done)?;
    // Let the last commands arrive.
    std::thread::sleep(std::time::Duration::from_millis(500));
    if driver.count() > 0 {
        return Err(format!(
            "{} commands reached the driver's topic {} in a dry run",
            driver.count(),
            p.command_topic
        ));
    }
    if preview.count() < p.min_commands {
        return Err(format!(
            "{} commands on {}, expected at least {}",
            preview.count(),
            p.preview_topic,
            p.min_commands
        ));
    }
    let last = preview
        .get()
        .and_then(|c| c.points.first().map(|pt| pt.positions.clone()))
        .ok_or("no preview command")?;
    let g = ghost.get().as_ref().and_then(joints).ok_or("no ghost joint state")?;
    let off = g.iter().zip(&last).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    if off > 1e-9 {
        return Err(format!(
            "the ghost's joints are {off:.2e} rad from the last preview command"
        ));
    }
    let moved = real_motion_deg(&first, &real)?;
    if moved > p.max_hold_motion_deg {
        return Err(format!(
            "the real arm moved {moved:.3} deg in a dry run (bound {:.3} deg)",
            p.max_hold_motion_deg
        ));
    }
    Ok(format!(
        "the ghost DONE ({}: {}) in {:.2} s, tip {:.2} mm from the goal, M = {:.2} N; {} preview commands, none to the driver; \
         the real arm moved {moved:.4} deg",
        done.hold_code,
        done.hold_reason,
        done.elapsed,
        done.tip_to_goal * 1e3,
        done.metric_m,
        preview.count()
    ))
}
