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
//! every pair of consecutive commands, holds included, moves each joint within 110 % of its
//! speed limit times their stamps' difference (the audit of the live fault tests,
//! [`crate::failure_modes`]).

use std::sync::{Arc, Mutex};

use ::trocar_docking::kinematics::lbr::LbrModel;
use ::trocar_docking::kinematics::{joint_names, JointLimits, JointVector};
use ::trocar_docking::ros::convert;
use ::trocar_docking::ros::msgs::{trajectory_msgs, trocar_docking};

use crate::bag_sync;
use crate::common::{call_trigger, trigger_client, wait_for, CheckParams};
use crate::failure_modes::{speed_ratio, MAX_SPEED_RATIO};

/// The live commands, audited as they arrive.
#[derive(Default)]
struct Audit {
    count: usize,
    last: Option<(f64, JointVector)>,
    /// The largest joint speed between consecutive commands, as a share of its limit.
    worst: f64,
    /// The stamp of the pair where it happened, s.
    worst_at: f64,
    malformed: Option<String>,
}

impl Audit {
    fn add(&mut self, msg: &trajectory_msgs::JointTrajectory, names: &[String], limit: &JointVector) {
        self.count += 1;
        let q = match convert::trajectory_positions("command", msg, names) {
            Ok(q) => q,
            Err(e) => {
                self.malformed.get_or_insert(e.to_string());
                return;
            }
        };
        let stamp = convert::seconds(msg.header.stamp);
        if let Some((t0, q0)) = self.last {
            if let Some(r) = speed_ratio(&q0, &q, stamp - t0, limit) {
                if r > self.worst {
                    (self.worst, self.worst_at) = (r, stamp);
                }
            }
        }
        self.last = Some((stamp, q));
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
    let limit = JointLimits::of_model(LbrModel::Med7).velocity;
    let audit = Arc::new(Mutex::new(Audit::default()));
    let _commands = {
        let audit = audit.clone();
        rosrust::subscribe(&p.command_topic, 1000, move |m: trajectory_msgs::JointTrajectory| {
            if let Ok(mut a) = audit.lock() {
                a.add(&m, &names, &limit);
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
    if a.worst > MAX_SPEED_RATIO {
        return Err(format!(
            "{code}: consecutive commands moved a joint at {:.0} % of its speed limit (stamp {:.3} s; bound {:.0} %)",
            a.worst * 100.0,
            a.worst_at,
            MAX_SPEED_RATIO * 100.0
        ));
    }
    if a.count < p.min_commands {
        return Err(format!("{} commands, fewer than {} (silence)", a.count, p.min_commands));
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
    Ok(format!(
        "{}; {} commands, every one within {:.0} % of the joints' speed limits (bound {:.0} %); {timeline}",
        phases.join(" -> "),
        a.count,
        a.worst * 100.0,
        MAX_SPEED_RATIO * 100.0
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn holds(seen: &[(&str, &str)], first_hold: Option<f64>) -> Holds {
        Holds {
            changes: seen.iter().map(|(p, c)| ((*p).to_string(), (*c).to_string())).collect(),
            first_hold,
            stamps: Vec::new(),
        }
    }

    /// The verdict fails on each broken condition: a hold before the fault, another code at
    /// the end, a command pair over 110 % of the speed limit, too few commands.
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
        let a = Audit {
            count: 150,
            worst: 0.5,
            ..Audit::default()
        };
        assert!(judge(&p, &good, Some(10.5), &a).is_ok());
        let early = judge(&p, &good, Some(10.8), &a).unwrap_err();
        assert!(early.contains("before the fault"), "{early}");
        let other = holds(&[("APPROACH", ""), ("HOLD", "TRACKING_ERROR")], Some(10.7));
        assert!(judge(&p, &other, Some(10.5), &a).unwrap_err().contains("not HOLD"));
        let fast = Audit {
            worst: 1.2,
            ..Audit::default()
        };
        assert!(judge(&p, &good, Some(10.5), &Audit { count: 150, ..fast })
            .unwrap_err()
            .contains("speed limit"));
        let silent = Audit {
            count: 20,
            ..Audit::default()
        };
        assert!(judge(&p, &good, Some(10.5), &silent).unwrap_err().contains("silence"));
    }

    /// The audit measures each consecutive pair by its stamps: a joint moving its whole
    /// speed limit's worth in one stamp step is 100 %.
    #[test]
    fn the_audit_divides_each_step_by_the_stamps_difference() {
        let names = joint_names();
        let limit = JointLimits::of_model(LbrModel::Med7).velocity;
        let mut a = Audit::default();
        let msg = |t: f64, q: &JointVector| {
            let mut m = trajectory_msgs::JointTrajectory::default();
            m.header.stamp = rosrust::Time::from_nanos((t * 1e9) as i64);
            m.joint_names.clone_from(&names);
            m.points.push(trajectory_msgs::JointTrajectoryPoint {
                positions: q.iter().copied().collect(),
                ..Default::default()
            });
            m
        };
        let q0 = JointVector::zeros();
        let mut q1 = q0;
        q1[1] = limit[1] * 0.01;
        a.add(&msg(1.0, &q0), &names, &limit);
        a.add(&msg(1.01, &q1), &names, &limit);
        assert_eq!(a.count, 2);
        assert!((a.worst - 1.0).abs() < 1e-3, "{}", a.worst);
    }
}
