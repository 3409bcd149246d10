//! Live tuning through `dynamic_reconfigure`'s own tool, `dynparam`: a change shows in
//! `dynparam get`, in `~parameter_updates` and in the controller's behaviour; a change the
//! phase forbids is refused and changes nothing.

use std::process::Command;

use ::trocar_docking::ros::msgs::{dynamic_reconfigure as dr, trocar_docking};

use crate::common::{subscribe_latest, trigger, wait_for, CheckParams, Latest};

/// Run `rosrun dynamic_reconfigure dynparam ARGS`: its exit status and its output (stdout
/// then stderr).
fn dynparam(args: &[&str]) -> Result<(bool, String), String> {
    let out = Command::new("rosrun")
        .args(["dynamic_reconfigure", "dynparam"])
        .args(args)
        .output()
        .map_err(|e| format!("cannot run dynparam: {e}"))?;
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    Ok((out.status.success(), text))
}

/// The value of `name` in the newest `~parameter_updates`.
fn updated(updates: &Latest<dr::Config>, name: &str) -> Option<f64> {
    updates.get()?.doubles.iter().find(|d| d.name == name).map(|d| d.value)
}

/// Lower the force stop to `reconfigure_force_stop` with `dynparam set` while IDLE, see it in
/// `dynparam get` and `~parameter_updates`, start, and see the docking hold on it
/// (FORCE_LIMIT at that limit); then a raise while held is refused (the updates unchanged),
/// and a weight changes live.
pub fn reconfigure(p: &CheckParams) -> Result<String, String> {
    let node = p.controller.as_str();
    let (status, _s1) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let (updates, _s2) = subscribe_latest::<dr::Config>(&format!("{node}/parameter_updates"))?;
    wait_for(p.startup_timeout, || status.get()).ok_or("no status message")?;
    let shipped = wait_for(p.startup_timeout, || updated(&updates, "force_stop")).ok_or("no parameter_updates")?;
    let (ok, got) = dynparam(&["get", node])?;
    if !ok || !got.contains(&format!("'force_stop': {shipped:?}")) {
        return Err(format!("dynparam get does not show force_stop {shipped}: {got}"));
    }
    let stop = p.reconfigure_force_stop;
    let (ok, out) = dynparam(&[
        "set",
        node,
        &format!("{{force_stop: {stop}, retract_force_stop: {stop}}}"),
    ])?;
    if !ok {
        return Err(format!("dynparam set refused in IDLE: {out}"));
    }
    wait_for(5.0, || updated(&updates, "force_stop").filter(|v| *v == stop))
        .ok_or_else(|| format!("parameter_updates does not show force_stop {stop}"))?;
    let (_, got) = dynparam(&["get", node])?;
    if !got.contains(&format!("'force_stop': {stop:?}")) {
        return Err(format!("dynparam get does not show the new force_stop {stop}: {got}"));
    }
    trigger(&format!("{node}/start"), p.startup_timeout)?;
    let held = wait_for(p.time_limit, || status.get().filter(|s| s.phase == "HOLD")).ok_or_else(|| {
        format!(
            "never held on the lowered stop; phase {}",
            status.get().unwrap_or_default().phase
        )
    })?;
    let limit = format!("over the {stop:.1} N limit");
    if held.hold_code != "FORCE_LIMIT" || !held.hold_reason.contains(&limit) {
        return Err(format!(
            "held with {} ({}), not FORCE_LIMIT {limit}",
            held.hold_code, held.hold_reason
        ));
    }
    let (ok, out) = dynparam(&["set", node, "force_stop", "30.0"])?;
    if ok || !out.contains("force_stop may only be lowered") {
        return Err(format!("raising the force stop while held was not refused: {out}"));
    }
    if updated(&updates, "force_stop") != Some(stop) {
        return Err("a refused change reached parameter_updates".into());
    }
    let (ok, out) = dynparam(&["set", node, "insert_w_axis", "500.0"])?;
    if !ok {
        return Err(format!("a weight was refused while held: {out}"));
    }
    wait_for(5.0, || updated(&updates, "insert_w_axis").filter(|v| *v == 500.0))
        .ok_or("parameter_updates does not show insert_w_axis 500")?;
    Ok(format!(
        "dynparam set force_stop {shipped} -> {stop} N in IDLE; the docking held: {} ({}); \
         raising it while held refused; insert_w_axis 500 applied live",
        held.hold_code, held.hold_reason
    ))
}
