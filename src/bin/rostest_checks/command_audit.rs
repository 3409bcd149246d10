//! The audit of the controller's commands against the guard's own limits: every pair of
//! consecutive commands, holds included, within each joint's speed limit
//! (`guard.velocity_scale` of the LBR Med 7 datasheet's) and the acceleration limit
//! (`guard.max_acceleration_rad_s2`), timed as the guard times its steps ([`CommandAudit`],
//! `src/control/safety/audit.rs`). The shipped `config/controller.yaml` is the one the tests'
//! launch files load.
//!
//! The command itself leaves with `header.stamp` 0 (the trajectory controller starts it at
//! its next update), so its step's time comes from the controller's stamped copy of every
//! command (`/docking/command_joints`, a JointState stamped with the step's time, numbered
//! as the command is): the audit judges the copies, and checks each command on the command
//! topic against the copy of the same number, so that what is judged is what the arm got. A
//! copy after messages the subscription missed (its sequence number skips) is taken without
//! judging the pair across the gap.

use std::collections::VecDeque;

use ::trocar_docking::control::safety::audit::CommandAudit;
use ::trocar_docking::control::ControllerParams;
use ::trocar_docking::kinematics::lbr::LbrModel;
use ::trocar_docking::kinematics::{JointLimits, JointVector};

/// Commands and copies kept unmatched while the other arrives (10 s at 100 Hz).
const PENDING: usize = 1000;

/// The audit of one controller's commands.
#[derive(Debug, Clone)]
pub(crate) struct TopicAudit {
    audit: CommandAudit,
    seq: Option<u32>,
    /// Copies not yet met by their command, oldest first.
    copies: VecDeque<(u32, JointVector)>,
    /// Commands not yet met by their copy, oldest first.
    commands: VecDeque<(u32, JointVector)>,
    /// Commands met by a copy equal to them.
    matched: usize,
    /// Commands on the command topic, all of them.
    on_topic: usize,
    /// The first command that differed from its copy.
    differs: Option<String>,
}

impl Default for TopicAudit {
    /// The shipped guard on the LBR Med 7, at the shipped control period.
    fn default() -> Self {
        let p = ControllerParams::default();
        Self {
            audit: CommandAudit::new(&p.guard, &JointLimits::of_model(LbrModel::Med7), p.dt_s),
            seq: None,
            copies: VecDeque::new(),
            commands: VecDeque::new(),
            matched: 0,
            on_topic: 0,
            differs: None,
        }
    }
}

/// Take the entry numbered `seq` out of `queue`, if it is there.
fn take(queue: &mut VecDeque<(u32, JointVector)>, seq: u32) -> Option<JointVector> {
    let i = queue.iter().position(|(s, _)| *s == seq)?;
    queue.remove(i).map(|(_, q)| q)
}

/// Keep `queue` to [`PENDING`] entries, the newest.
fn push_bounded(queue: &mut VecDeque<(u32, JointVector)>, seq: u32, q: &JointVector) {
    if queue.len() == PENDING {
        queue.pop_front();
    }
    queue.push_back((seq, *q));
}

impl TopicAudit {
    /// The stamped copy `q` of command number `seq`, its step at `stamp` (s): judged.
    pub(crate) fn copy(&mut self, seq: u32, stamp: f64, q: &JointVector) {
        match self.seq {
            Some(s) if seq != s.wrapping_add(1) => self.audit.resync(stamp, q),
            _ => self.audit.add(stamp, q),
        }
        self.seq = Some(seq);
        match take(&mut self.commands, seq) {
            Some(c) => self.meet(seq, &c, q),
            None => push_bounded(&mut self.copies, seq, q),
        }
    }

    /// The command `q` numbered `seq` as the command topic carried it: met with its copy.
    pub(crate) fn command(&mut self, seq: u32, q: &JointVector) {
        self.on_topic += 1;
        match take(&mut self.copies, seq) {
            Some(c) => self.meet(seq, q, &c),
            None => push_bounded(&mut self.commands, seq, q),
        }
    }

    fn meet(&mut self, seq: u32, command: &JointVector, copy: &JointVector) {
        if command == copy {
            self.matched += 1;
        } else if self.differs.is_none() {
            self.differs = Some(format!(
                "command {seq} differs from its stamped copy by {:.3e} rad",
                (command - copy).amax()
            ));
        }
    }

    /// Commands judged.
    pub(crate) fn count(&self) -> usize {
        self.audit.count
    }

    /// The verdict for the check of `code`: both shares, an error where one is over its limit,
    /// where a command differed from its copy, or where fewer than nine in ten of the
    /// commands on the topic met their copy.
    pub(crate) fn verdict(&self, code: &str) -> Result<String, String> {
        if let Some(d) = &self.differs {
            return Err(format!("{code}: {d}"));
        }
        if self.matched * 10 < self.on_topic * 9 {
            return Err(format!(
                "{code}: only {} of the {} commands on the topic met their stamped copy",
                self.matched, self.on_topic
            ));
        }
        self.audit
            .verdict()
            .map(|v| format!("{v}; {} of {} commands met their copy", self.matched, self.on_topic))
            .map_err(|e| format!("{code}: {e}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Judged against the guard's limits, pair by pair: a joint at the guard's speed limit
    /// is 100 % (the datasheet's half), a stop from it in one step fails the acceleration
    /// limit, and a skipped sequence number is not judged as a step.
    #[test]
    fn the_topic_audit_judges_the_guard_limits_and_skips_missed_messages() {
        let p = ControllerParams::default();
        let vmax = JointLimits::of_model(LbrModel::Med7).velocity[0] * p.guard.velocity_scale;
        let dt = p.dt_s;
        let mut a = TopicAudit::default();
        let mut q = JointVector::zeros();
        let mut v = 0.0f64;
        a.copy(0, 0.0, &q);
        a.command(0, &q);
        for k in 1..=100u32 {
            v = (v + p.guard.max_acceleration_rad_s2 * dt).min(vmax);
            q[0] += v * dt;
            a.copy(k, f64::from(k) * dt, &q);
            a.command(k, &q);
        }
        let ok = a.verdict("X").unwrap();
        assert!(ok.contains("100 % of the guard's speed limit"), "{ok}");
        assert!(ok.contains("101 of 101 commands met their copy"), "{ok}");
        // A message missed: the jump across it is not a step.
        q[0] += 10.0 * vmax * dt;
        a.copy(102, 1.02, &q);
        assert!(a.verdict("X").is_ok());
        assert_eq!(a.count(), 102);
        // Standing still at once from speed.
        q[0] += vmax * dt;
        a.copy(103, 1.03, &q);
        a.copy(104, 1.04, &q);
        assert!(a.verdict("X").unwrap_err().starts_with("X: "));
    }

    /// The copies are judged only where they are the commands: a command that differs from
    /// the copy of its number fails, whichever arrives first, and so do commands without
    /// copies.
    #[test]
    fn a_command_must_meet_an_equal_copy() {
        let q = JointVector::zeros();
        let mut moved = q;
        moved[3] = 1e-3;
        let mut a = TopicAudit::default();
        a.command(0, &q);
        a.copy(0, 0.0, &q);
        a.copy(1, 0.01, &q);
        a.command(1, &q);
        assert!(a.verdict("X").is_ok());
        a.command(2, &moved);
        a.copy(2, 0.02, &q);
        let e = a.verdict("X").unwrap_err();
        assert!(
            e.contains("command 2 differs from its stamped copy by 1.000e-3 rad"),
            "{e}"
        );
        let mut b = TopicAudit::default();
        for k in 0..10u32 {
            b.command(k, &q);
        }
        b.copy(0, 0.0, &q);
        let e = b.verdict("X").unwrap_err();
        assert!(e.contains("only 1 of the 10 commands"), "{e}");
    }
}
