//! Recorded driver faults played into `robot.launch` on the bag's own clock
//! (`tests/bags/fault_*.bag`, `scripts/fault-bags`): the controller runs as a lab runs it, the
//! bag plays the driver and the trocar pose. The bag plays open loop: its arm follows the
//! recorded controller's commands, not the live ones, so the check plays the bag itself and
//! starts the live controller in step with the recorded one ([`crate::bag_sync`]: it then
//! sees what the recorded one saw, and its commands stay close to the recorded arm until
//! the fault). Checked over the whole run:
//! the controller publishes commands (at least `min_commands`); it does not hold before the
//! fault (`fault_after_s` after the recorded APPROACH), holds with the fault's code
//! (`hold_code`) after it, and still holds with it at the end;
//! every pair of consecutive commands, holds included, within the guard's own speed and
//! acceleration limits (the audit of the live fault tests, [`crate::command_audit`]).

use std::sync::{Arc, Mutex};

use ::trocar_docking::kinematics::joint_names;
use ::trocar_docking::ros::convert;
use ::trocar_docking::ros::msgs::{sensor_msgs, trajectory_msgs, trocar_docking};

use crate::bag_sync;
use crate::command_audit::TopicAudit;
use crate::common::{call_trigger, trigger_client, wait_for, CheckParams};

/// The live commands, audited as they arrive.
#[derive(Default)]
struct Audit {
    guard: TopicAudit,
    malformed: Option<String>,
}

impl Audit {
    fn add(&mut self, msg: &trajectory_msgs::JointTrajectory, names: &[String]) {
        match convert::trajectory_positions("command", msg, names) {
            Ok(q) => self.guard.command(msg.header.seq, &q),
            Err(e) => {
                self.malformed.get_or_insert(e.to_string());
            }
        }
    }

    fn copy(&mut self, msg: &sensor_msgs::JointState, names: &[String]) {
        match convert::joint_positions("command copy", msg, names) {
            Ok(q) => self.guard.copy(msg.header.seq, convert::seconds(msg.header.stamp), &q),
            Err(e) => {
                self.malformed.get_or_insert(e.to_string());
            }
        }
    }
}

/// What the live status showed.
#[derive(Default, Clone)]
struct Holds {
    /// The phases and hold codes, in order, each change once.
    changes: Vec<(String, String)>,
    /// The stamp of the first HOLD, s.
    first_hold: Option<f64>,
    /// The stamp of each change, s.
    stamps: Vec<f64>,
}

impl Holds {
    /// The changes with their stamps relative to `origin` (the recorded APPROACH), for a
    /// failure's message.
    fn timeline(&self, origin: Option<f64>) -> String {
        let o = origin.unwrap_or(f64::NAN);
        let parts: Vec<String> = self
            .changes
            .iter()
            .zip(&self.stamps)
            .map(|((ph, c), t)| format!("{} at {:+.3} s", format!("{ph} {c}").trim_end(), t - o))
            .collect();
        format!("{} (times from the recorded APPROACH)", parts.join(", "))
    }
}

/// Play a fault bag into the controller (module doc).
pub fn replay_fault(p: &CheckParams) -> Result<String, String> {
    let names = joint_names();
    let audit = Arc::new(Mutex::new(Audit::default()));
    let _commands = {
        let audit = audit.clone();
        rosrust::subscribe(&p.command_topic, 1000, move |m: trajectory_msgs::JointTrajectory| {
            if let Ok(mut a) = audit.lock() {
                a.add(&m, &names);
            }
        })
        .map_err(|e| e.to_string())?
    };
    let _copies = {
        let audit = audit.clone();
        let names = joint_names();
        rosrust::subscribe(&p.command_joints_topic, 1000, move |m: sensor_msgs::JointState| {
            if let Ok(mut a) = audit.lock() {
                a.copy(&m, &names);
            }
        })
        .map_err(|e| e.to_string())?
    };
    let holds = Arc::new(Mutex::new(Holds::default()));
    let _status = {
        let holds = holds.clone();
        rosrust::subscribe(&p.status_topic, 100, move |s: trocar_docking::DockingStatus| {
            if let Ok(mut h) = holds.lock() {
                if s.phase == "HOLD" && h.first_hold.is_none() {
                    h.first_hold = Some(convert::seconds(s.header.stamp));
                }
                let now = (s.phase, s.hold_code);
                if h.changes.last() != Some(&now) {
                    h.changes.push(now);
                    h.stamps.push(convert::seconds(s.header.stamp));
                }
            }
        })
        .map_err(|e| e.to_string())?
    };
    // When the recorded controller entered APPROACH, s (the fault is `fault_after_s` later).
    let approach = Arc::new(Mutex::new(None));
    let _a = {
        let approach = approach.clone();
        rosrust::subscribe(
            &p.recorded_status_topic,
            100,
            move |s: trocar_docking::DockingStatus| {
                if let Ok(mut a) = approach.lock() {
                    if s.phase == "APPROACH" && a.is_none() {
                        *a = Some(convert::seconds(s.header.stamp));
                    }
                }
            },
        )
        .map_err(|e| e.to_string())?
    };
    let service = format!("{}/start", p.controller);
    let start = trigger_client(&service, p.startup_timeout)?;
    let _player = bag_sync::play_and_start(p, || call_trigger(&service, &start))?;
    let code = p.hold_code.as_str();
    let held = |h: &Holds| h.changes.iter().any(|(ph, c)| ph == "HOLD" && c == code);
    wait_for(p.time_limit, || holds.lock().ok().filter(|h| held(h)).map(|_| ())).ok_or_else(|| {
        let origin = approach.lock().ok().and_then(|a| *a);
        format!(
            "no HOLD {code}: statuses {:?}",
            holds.lock().map(|h| h.timeline(origin))
        )
    })?;
    // Held: watched on while the bag plays on (the recorded arm moving away), then judged.
    std::thread::sleep(std::time::Duration::from_secs_f64(p.hold_observe));
    let seen = holds.lock().map_err(|e| e.to_string())?.clone();
    let fault_at = approach.lock().map_err(|e| e.to_string())?.map(|t| t + p.fault_after_s);
    let a = audit.lock().map_err(|e| e.to_string())?;
    judge(p, &seen, fault_at, &a)
}

/// The run's verdict (module doc): `seen` the live statuses, `fault_at` when the bag's fault
/// began (s), `a` the audited commands.
fn judge(p: &CheckParams, seen: &Holds, fault_at: Option<f64>, a: &Audit) -> Result<String, String> {
    let code = p.hold_code.as_str();
    let timeline = seen.timeline(fault_at.map(|f| f - p.fault_after_s));
    let (first_hold, seen) = (seen.first_hold, &seen.changes);
    if let Some(e) = &a.malformed {
        return Err(format!("a malformed command: {e}"));
    }
    let audit = a.guard.verdict(code)?;
    if a.guard.count() < p.min_commands {
        return Err(format!(
            "{} commands, fewer than {} (silence)",
            a.guard.count(),
            p.min_commands
        ));
    }
    // Nothing held before the fault: the live controller followed the recording until then.
    match (fault_at, first_hold) {
        (Some(f), Some(h)) if h < f => {
            return Err(format!("held {:.2} s before the fault: {timeline}", f - h));
        }
        (None, _) => return Err("the recording never entered APPROACH".into()),
        _ => {}
    }
    let last = seen.last().cloned().unwrap_or_default();
    if last != ("HOLD".to_string(), code.to_string()) {
        return Err(format!("ended in {last:?}, not HOLD {code}: statuses {seen:?}"));
    }
    let phases: Vec<String> = seen
        .iter()
        .map(|(ph, c)| if c.is_empty() { ph.clone() } else { format!("{ph} {c}") })
        .collect();
    Ok(format!("{}; {audit}; {timeline}", phases.join(" -> ")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ::trocar_docking::kinematics::JointVector;

    fn holds(seen: &[(&str, &str)], first_hold: Option<f64>) -> Holds {
        Holds {
            changes: seen.iter().map(|(p, c)| ((*p).to_string(), (*c).to_string())).collect(),
            first_hold,
            stamps: Vec::new(),
        }
    }

    /// A command message numbered `seq` (its stamp 0, as the controller sends it).
    fn msg(seq: u32, q: &JointVector) -> trajectory_msgs::JointTrajectory {
        let mut m = trajectory_msgs::JointTrajectory::default();
        m.header.seq = seq;
        m.joint_names = joint_names();
        m.points.push(trajectory_msgs::JointTrajectoryPoint {
            positions: q.iter().copied().collect(),
            ..Default::default()
        });
        m
    }

    /// The command numbered `seq`, `q` at its step `t`: the command and its stamped copy.
    fn sent(a: &mut Audit, seq: u32, t: f64, q: &JointVector) {
        a.add(&msg(seq, q), &joint_names());
        let mut c = convert::joint_state(
            rosrust::Time::from_nanos((t * 1e9) as i64),
            &joint_names(),
            q,
            &JointVector::zeros(),
        );
        c.header.seq = seq;
        a.copy(&c, &joint_names());
    }

    /// `n` commands at 100 Hz standing still, then (`jump`) one 0.1 rad step of joint 2.
    fn audited(n: u32, jump: bool) -> Audit {
        let mut a = Audit::default();
        let mut q = JointVector::zeros();
        for k in 0..n {
            sent(&mut a, k, f64::from(k) * 0.01, &q);
        }
        if jump {
            q[1] = 0.1;
            sent(&mut a, n, f64::from(n) * 0.01, &q);
        }
        a
    }

    /// The verdict fails on each broken condition: a hold before the fault, another code at
    /// the end, a command pair over the guard's speed or acceleration limit, too few
    /// commands, a malformed command.
    #[test]
    fn the_verdict_fails_on_each_broken_condition() {
        let p = CheckParams {
            hold_code: "ARM_NOT_FOLLOWING".into(),
            min_commands: 100,
            ..CheckParams::default()
        };
        let good = holds(
            &[("TARE", ""), ("APPROACH", ""), ("HOLD", "ARM_NOT_FOLLOWING")],
            Some(10.7),
        );
        let a = audited(150, false);
        let ok = judge(&p, &good, Some(10.5), &a).unwrap();
        assert!(ok.contains("150 commands, fastest joint at 0 %"), "{ok}");
        let early = judge(&p, &good, Some(10.8), &a).unwrap_err();
        assert!(early.contains("before the fault"), "{early}");
        let other = holds(&[("APPROACH", ""), ("HOLD", "TRACKING_ERROR")], Some(10.7));
        assert!(judge(&p, &other, Some(10.5), &a).unwrap_err().contains("not HOLD"));
        let fast = judge(&p, &good, Some(10.5), &audited(150, true)).unwrap_err();
        assert!(fast.contains("over the limit at t = 1.500"), "{fast}");
        assert!(judge(&p, &good, Some(10.5), &audited(20, false))
            .unwrap_err()
            .contains("silence"));
        let mut bad = audited(150, false);
        let mut m = msg(150, &JointVector::zeros());
        m.joint_names.pop();
        bad.add(&m, &joint_names());
        assert!(judge(&p, &good, Some(10.5), &bad).unwrap_err().contains("malformed"));
    }

    /// The audit reads each copy's sequence number and stamp: the same jump across a
    /// missed message is not judged as one step.
    #[test]
    fn the_audit_reads_each_message_sequence_number_and_stamp() {
        let mut a = audited(10, false);
        let mut q = JointVector::zeros();
        q[1] = 0.1;
        sent(&mut a, 12, 0.12, &q);
        assert!(a.guard.verdict("X").is_ok());
        sent(&mut a, 13, 0.13, &q);
        assert!(a.guard.verdict("X").is_ok());
        assert_eq!(a.guard.count(), 12);
        assert!(audited(10, true).guard.verdict("X").is_err());
    }
}
