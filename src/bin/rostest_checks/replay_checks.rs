//! Checks on recorded bags replayed into the nodes: the estimator against the recorded
//! truth (`replay`), and the controller's own output from a recorded docking's inputs
//! (`replay_controller`).

use std::sync::{Arc, Mutex};

use ::trocar_docking::control::ControllerParams;
use ::trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use ::trocar_docking::kinematics::{joint_names, JointLimits, JointVector, Kinematics, LbrKinematics};
use ::trocar_docking::ros::convert;
use ::trocar_docking::ros::msgs::{trajectory_msgs, trocar_docking};
use ::trocar_docking::ros::params;

use crate::bag_sync;
use crate::common::{call_trigger, subscribe_latest, trigger_client, wait_for, CheckParams};

/// Recorded topics are replayed into the nodes: the controller must publish status in the
/// allowed phases, and the estimator a trocar pose within `max_position_error` of the
/// recorded truth.
pub fn replay(p: &CheckParams) -> Result<String, String> {
    use ::trocar_docking::ros::msgs::geometry_msgs::PoseStamped;
    let (status, _s1) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let (truth, _s3) = subscribe_latest::<PoseStamped>(&p.true_pose_topic)?;
    // Every estimate is compared with the newest true pose when it arrives; the worst counts.
    let (pose, _s2) = subscribe_latest::<PoseStamped>(&p.pose_topic)?;
    let worst = Arc::new(Mutex::new((0.0_f64, 0_usize)));
    let _s4 = {
        let (truth, worst) = (truth.clone(), worst.clone());
        rosrust::subscribe(&p.pose_topic, 100, move |m: PoseStamped| {
            let Some(t) = truth.get() else { return };
            let err = match (convert::pose("estimate", &m.pose), convert::pose("truth", &t.pose)) {
                (Ok(e), Ok(t)) => (e.translation.vector - t.translation.vector).norm(),
                _ => f64::INFINITY,
            };
            if let Ok(mut w) = worst.lock() {
                w.0 = if err.is_nan() { f64::INFINITY } else { w.0.max(err) };
                w.1 += 1;
            }
        })
        .map_err(|e| e.to_string())?
    };
    wait_for(p.time_limit, || {
        (status.count() >= p.min_status && pose.count() >= p.min_poses.max(1) && truth.count() > 0).then_some(())
    })
    .ok_or_else(|| {
        format!(
            "got {} status, {} estimated and {} true poses",
            status.count(),
            pose.count(),
            truth.count()
        )
    })?;
    let s = status.get().unwrap_or_default();
    let allowed_hold = !p.allowed_hold_code.is_empty() && s.phase == "HOLD" && s.hold_code == p.allowed_hold_code;
    if !(p.allowed_phases.contains(&s.phase) || allowed_hold) {
        return Err(format!(
            "phase {} ({}) not among {:?}",
            s.phase, s.hold_reason, p.allowed_phases
        ));
    }
    let (err, compared) = worst.lock().map(|w| *w).map_err(|e| e.to_string())?;
    if compared == 0 {
        return Err("no estimate arrived after a true pose: nothing compared".into());
    }
    if err.is_nan() || err > p.max_position_error {
        return Err(format!(
            "a trocar estimate {:.1} mm from the truth (worst of {compared})",
            err * 1e3
        ));
    }
    Ok(format!(
        "{} status (phase {}), {} trocar estimates, every one of {compared} compared within {:.2} mm of the truth",
        status.count(),
        s.phase,
        pose.count(),
        err * 1e3
    ))
}

/// The phases a status topic went through, each with its hold code, in order (a repeat
/// of the same phase and code is one entry).
#[derive(Debug, Default)]
struct PhaseLog {
    entries: Vec<(String, String)>,
}

impl PhaseLog {
    fn subscribe(topic: &str) -> Result<(Arc<Mutex<Self>>, rosrust::Subscriber), String> {
        let log = Arc::new(Mutex::new(Self::default()));
        let l = log.clone();
        let sub = rosrust::subscribe(topic, 1000, move |s: trocar_docking::DockingStatus| {
            if let Ok(mut l) = l.lock() {
                let code = if s.phase == "HOLD" { s.hold_code } else { String::new() };
                if l.entries.last() != Some(&(s.phase.clone(), code.clone())) {
                    l.entries.push((s.phase, code));
                }
            }
        })
        .map_err(|e| format!("subscribe {topic}: {e}"))?;
        Ok((log, sub))
    }

    /// From the first TARE on, the phases; a HOLD for stale data that the run left again
    /// for the phase it held in (a late message under load) is dropped, and counted.
    fn docking_phases(&self) -> (Vec<String>, usize) {
        let from = self
            .entries
            .iter()
            .position(|(p, _)| p == "TARE")
            .unwrap_or(self.entries.len());
        let e = &self.entries[from..];
        let mut out: Vec<String> = Vec::new();
        let mut transient = 0;
        for (i, (phase, code)) in e.iter().enumerate() {
            let before = out.last();
            let after = e.get(i + 1).map(|(p, _)| p);
            if phase == "HOLD" && code.starts_with("STALE_") && before.is_some() && after == before {
                transient += 1;
                continue;
            }
            if before != Some(phase) {
                out.push(phase.clone());
            }
        }
        (out, transient)
    }

    fn last_phase(&self) -> Option<String> {
        self.entries.last().map(|(p, _)| p.clone())
    }
}

/// The live controller's commands, each checked as it arrives: finite, inside the joint
/// limits, and within the guard's step (the joint velocity limit times `velocity_scale`
/// times the control period) of the previous command, per published message.
struct CommandAudit {
    limits: JointLimits,
    /// The largest joint step per message, rad.
    max_step: JointVector,
    count: usize,
    last: Option<(u32, JointVector)>,
    /// The largest step as a share of its bound.
    worst_step_ratio: f64,
    /// The commands with their stamps, s.
    commands: Vec<(f64, JointVector)>,
    violation: Option<String>,
}

impl CommandAudit {
    fn new(limits: JointLimits, params: &ControllerParams, rate_hz: f64) -> Self {
        let max_step = limits.velocity * params.guard.velocity_scale / rate_hz;
        Self {
            limits,
            max_step,
            count: 0,
            last: None,
            worst_step_ratio: 0.0,
            commands: Vec::new(),
            violation: None,
        }
    }

    fn add(&mut self, msg: &trajectory_msgs::JointTrajectory, names: &[String]) {
        self.count += 1;
        let q = match convert::trajectory_positions("command", msg, names) {
            Ok(q) => q,
            Err(e) => {
                self.violation
                    .get_or_insert(format!("a malformed or non-finite command: {e}"));
                return;
            }
        };
        for i in 0..7 {
            if q[i] < self.limits.lower[i] || q[i] > self.limits.upper[i] {
                self.violation.get_or_insert(format!(
                    "joint {} commanded to {:.4} rad, outside its limits",
                    i + 1,
                    q[i]
                ));
            }
        }
        let seq = msg.header.seq;
        if let Some((seq0, q0)) = self.last {
            // Messages the subscription missed are steps too (one command per step).
            let steps = f64::from(seq.wrapping_sub(seq0).max(1));
            for i in 0..7 {
                let ratio = (q[i] - q0[i]).abs() / (steps * self.max_step[i]);
                self.worst_step_ratio = self.worst_step_ratio.max(ratio);
                if ratio > 1.0 + 1e-6 {
                    self.violation.get_or_insert(format!(
                        "command {} (stamp {:.3} s): joint {} stepped {:.3} deg in {steps} step(s), bound {:.3} deg per step",
                        self.count,
                        convert::seconds(msg.header.stamp),
                        i + 1,
                        (q[i] - q0[i]).abs().to_degrees(),
                        self.max_step[i].to_degrees()
                    ));
                }
            }
        }
        self.last = Some((seq, q));
        self.commands.push((convert::seconds(msg.header.stamp), q));
    }
}

/// The largest joint difference, rad, between each live command and the recorded command
/// nearest in time.
fn largest_gap(live: &[(f64, JointVector)], recorded: &[(f64, JointVector)]) -> f64 {
    live.iter()
        .filter_map(|(t, q)| {
            let k = recorded.partition_point(|(tr, _)| tr < t);
            let near = [k.checked_sub(1), Some(k)]
                .into_iter()
                .flatten()
                .filter_map(|j| recorded.get(j))
                .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))?;
            Some((q - near.1).amax())
        })
        .fold(0.0, f64::max)
}

/// The one way an open-loop replay may end otherwise than the recording: the recorded arm
/// stops at the recording's DONE while the live controller, a few steps behind, still
/// inserts; its command then leads an arm that no longer moves, and the guard rightly holds
/// (`ARM_NOT_FOLLOWING`). Every phase before the last must be the recording's.
fn stopped_by_the_recording(got: &[String], want: &[String], live_hold: &str) -> bool {
    got.len() == want.len()
        && got.len() >= 2
        && got[..got.len() - 1] == want[..want.len() - 1]
        && want.last().is_some_and(|p| p == "DONE")
        && got.last().is_some_and(|p| p == "HOLD")
        && got[got.len() - 2] == "INSERT"
        && live_hold == "ARM_NOT_FOLLOWING"
}

/// How the live phases `got` end against the recorded `want`: as recorded (""), or stopped
/// by the recording (a note), or an error.
fn phase_end(got: &[String], want: &[String], live_hold: &str, commands: usize) -> Result<String, String> {
    if got == want {
        Ok(String::new())
    } else if stopped_by_the_recording(got, want, live_hold) {
        Ok("; ended holding ARM_NOT_FOLLOWING: the recorded arm stopped at its DONE while the live controller still inserted (an open-loop replay)".to_string())
    } else {
        Err(format!(
            "phases {got:?}, recorded {want:?} ({commands} commands; live hold '{live_hold}')"
        ))
    }
}

/// A recorded docking (its joints, torques and noisy trocar pose, with its clock) replayed
/// into a fresh controller, played by the check and started in step with the recorded
/// controller ([`crate::bag_sync`]): the live controller's own commands must be finite, inside the joint limits and within the
/// guard's per-step speed, at least `min_commands` of them, and it must go through the
/// recorded phases (the recorded status, remapped to `recorded_status_topic`) to the same
/// end (DONE). A stale-data hold that resumes (a late message under load) is left out of
/// both sequences and reported.
pub fn replay_controller(p: &CheckParams) -> Result<String, String> {
    let names = joint_names();
    let prefix = format!("{}/controller", p.controller);
    let cp: ControllerParams = rosrust::param(&prefix)
        .ok_or_else(|| format!("bad name {prefix}"))?
        .get::<serde_json::Value>()
        .map_err(|e| format!("{prefix}: {e}"))
        .and_then(|v| params::from_value(&prefix, v).map_err(|e| e.to_string()))?;
    let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).map_err(|e| e.to_string())?;
    let audit = Arc::new(Mutex::new(CommandAudit::new(kin.limits().clone(), &cp, 1.0 / cp.dt_s)));
    let _commands = {
        let (audit, names) = (audit.clone(), names.clone());
        rosrust::subscribe(&p.command_topic, 1000, move |m: trajectory_msgs::JointTrajectory| {
            if let Ok(mut a) = audit.lock() {
                a.add(&m, &names);
            }
        })
        .map_err(|e| e.to_string())?
    };
    let recorded_commands = Arc::new(Mutex::new(Vec::new()));
    let _recorded_commands = {
        let (out, names) = (recorded_commands.clone(), names.clone());
        rosrust::subscribe(
            &p.recorded_command_topic,
            1000,
            move |m: trajectory_msgs::JointTrajectory| {
                if let (Ok(q), Ok(mut v)) = (convert::trajectory_positions("", &m, &names), out.lock()) {
                    v.push((convert::seconds(m.header.stamp), q));
                }
            },
        )
        .map_err(|e| e.to_string())?
    };
    let (live, _s1) = PhaseLog::subscribe(&p.status_topic)?;
    let (recorded, _s2) = PhaseLog::subscribe(&p.recorded_status_topic)?;
    let (live_now, _s4) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let phase_of = |log: &Arc<Mutex<PhaseLog>>| log.lock().ok().and_then(|l| l.last_phase());
    let service = format!("{}/start", p.controller);
    let start = trigger_client(&service, p.startup_timeout)?;
    let _player = bag_sync::play_and_start(p, || call_trigger(&service, &start))?;
    // The live run ends where the recorded one does; past the recorded end, it has a
    // second to catch up.
    let ended = |s: Option<String>| matches!(s.as_deref(), Some("DONE" | "ABORTED" | "IDLE"));
    // The first part of the bag ended in the recorded IDLE: its docking starts in the second.
    wait_for(p.startup_timeout, || {
        phase_of(&recorded).filter(|s| s != "IDLE").map(|_| ())
    })
    .ok_or("the recording's controller never started (is the bag playing?)")?;
    wait_for(p.time_limit, || ended(phase_of(&recorded)).then_some(()))
        .ok_or_else(|| format!("the recording never ended its docking: {:?}", phase_of(&recorded)))?;
    let _ = wait_for(1.0, || ended(phase_of(&live)).then_some(()));
    let (want, skipped_rec) = recorded.lock().map_err(|e| e.to_string())?.docking_phases();
    let (got, skipped_live) = live.lock().map_err(|e| e.to_string())?.docking_phases();
    let a = audit.lock().map_err(|e| e.to_string())?;
    if let Some(v) = &a.violation {
        return Err(format!(
            "unsafe command ({} received): {v}; phases {got:?}, recorded {want:?}",
            a.count
        ));
    }
    let live_hold = live_now.get().map(|s| s.hold_code).unwrap_or_default();
    let end = phase_end(&got, &want, &live_hold, a.count)?;
    if a.count < p.min_commands {
        return Err(format!("{} commands, fewer than {}", a.count, p.min_commands));
    }
    let gap = largest_gap(&a.commands, &recorded_commands.lock().map_err(|e| e.to_string())?);
    Ok(format!(
        "phases {} as recorded{end} ({skipped_live} live and {skipped_rec} recorded stale-data holds resumed); \
         {} commands, every one finite and inside the limits, steps at most {:.0} % of the guard's; \
         largest difference from the recorded command {:.3} deg",
        got.join(" -> "),
        a.count,
        a.worst_step_ratio * 100.0,
        gap.to_degrees()
    ))
}

#[cfg(test)]
mod replay_end_tests {
    use super::stopped_by_the_recording;

    fn v(p: &[&str]) -> Vec<String> {
        p.iter().map(|s| (*s).to_string()).collect()
    }

    #[test]
    fn only_a_final_arm_not_following_after_insert_is_the_recordings_stop() {
        let want = v(&["TARE", "APPROACH", "INSERT", "DONE"]);
        let held = v(&["TARE", "APPROACH", "INSERT", "HOLD"]);
        assert!(stopped_by_the_recording(&held, &want, "ARM_NOT_FOLLOWING"));
        assert!(!stopped_by_the_recording(&held, &want, "FORCE_LIMIT"));
        assert!(!stopped_by_the_recording(
            &v(&["TARE", "APPROACH", "HOLD"]),
            &want,
            "ARM_NOT_FOLLOWING"
        ));
        assert!(!stopped_by_the_recording(
            &v(&["TARE", "HOLD", "INSERT", "HOLD"]),
            &want,
            "ARM_NOT_FOLLOWING"
        ));
    }
}
