//! `preflight`: run the `preflight` binary (the one `rosrun trocar_docking preflight` runs)
//! against the graph and judge its exit code and lines; then (with `call_start`) call the
//! controller's `~preflight`, which must agree, and its `~start`: it must start when every
//! check passes, and otherwise refuse, naming the failed check, and the controller stay IDLE
//! with nothing on the command topic.

use std::process::Command;
use std::time::Duration;

use ::trocar_docking::ros::msgs::{trajectory_msgs, trocar_docking};

use crate::common::{subscribe_latest, trigger, wait_for, CheckParams};

/// The `preflight` binary beside this one (both are cargo's, linked into the devel space).
fn preflight_binary() -> Result<std::path::PathBuf, String> {
    let me = std::env::current_exe().map_err(|e| format!("own path: {e}"))?;
    let me = std::fs::canonicalize(&me).unwrap_or(me);
    Ok(me.with_file_name("preflight"))
}

/// Run the binary; its exit code and its output.
fn run_binary() -> Result<(Option<i32>, String), String> {
    let bin = preflight_binary()?;
    let out = Command::new(&bin)
        .args(["__name:=preflight_under_test"])
        .output()
        .map_err(|e| format!("{}: {e}", bin.display()))?;
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    Ok((out.status.code(), text))
}

/// See the module doc.
pub fn preflight(p: &CheckParams) -> Result<String, String> {
    let start_service = format!("{}/start", p.controller);
    if p.call_start {
        rosrust::wait_for_service(&start_service, Some(Duration::from_secs_f64(p.startup_timeout)))
            .map_err(|e| format!("{start_service} did not appear: {e}"))?;
    }
    let (code, text) = run_binary()?;
    let expect = p.preflight_failure.as_str();
    if expect.is_empty() {
        if code != Some(0) || !text.contains("preflight passed") {
            return Err(format!("preflight did not pass (exit {code:?}):\n{text}"));
        }
    } else {
        let line = format!("FAIL {expect} ");
        if code != Some(1) || !text.lines().any(|l| l.starts_with(&line)) {
            return Err(format!(
                "preflight did not fail {expect} with exit code 1 (exit {code:?}):\n{text}"
            ));
        }
    }
    let must_pass = format!("PASS {} ", p.preflight_pass);
    if !p.preflight_pass.is_empty() && !text.lines().any(|l| l.starts_with(&must_pass)) {
        return Err(format!("preflight did not pass {}:\n{text}", p.preflight_pass));
    }
    let summary = text
        .lines()
        .filter(|l| {
            l.starts_with("FAIL")
                || l.starts_with("preflight")
                || (!p.preflight_pass.is_empty() && l.starts_with(&must_pass))
        })
        .collect::<Vec<_>>()
        .join(" | ");
    if !p.call_start {
        return Ok(format!("binary exit {code:?}: {summary}"));
    }
    let service = format!("{}/preflight", p.controller);
    match (expect.is_empty(), trigger(&service, p.startup_timeout)) {
        (true, Ok(m)) if m.ends_with("preflight passed") => {}
        (false, Err(e)) if e.contains(&format!("preflight failed: {expect}")) || e.contains(&format!(", {expect}")) => {
        }
        (_, r) => return Err(format!("{service} disagrees with the binary: {r:?}")),
    }
    let (status, _s) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let (command, _c) = subscribe_latest::<trajectory_msgs::JointTrajectory>(&p.command_topic)?;
    match (expect.is_empty(), trigger(&start_service, p.startup_timeout)) {
        (true, Ok(m)) => Ok(format!("{summary}; ~start: {}", m.lines().last().unwrap_or_default())),
        (true, Err(e)) => Err(format!("{summary}; but ~start refused: {e}")),
        (false, Ok(m)) => Err(format!("~start started although {expect} fails: {m}")),
        (false, Err(e)) => {
            if !e.contains("preflight failed") || !e.contains(expect) {
                return Err(format!("~start refused without naming {expect}: {e}"));
            }
            // The loop never heard of the start: IDLE, and no command.
            std::thread::sleep(Duration::from_secs_f64(p.hold_observe));
            let phase = wait_for(p.startup_timeout, || status.get()).map(|s| s.phase);
            if phase.as_deref().is_some_and(|ph| ph != "IDLE") {
                return Err(format!("after the refusal the phase is {phase:?}, not IDLE"));
            }
            if command.count() > 0 {
                return Err(format!("{} commands published after the refusal", command.count()));
            }
            Ok(format!("{summary}; ~start refused: {e}; phase {phase:?}, no command"))
        }
    }
}
