//! The audit of the controller's command topic against the guard's own limits: every pair
//! of consecutive commands, holds included, within each joint's speed limit
//! (`guard.velocity_scale` of the LBR Med 7 datasheet's) and the acceleration limit
//! (`guard.max_acceleration_rad_s2`), timed by the commands' header stamps as the guard
//! times its steps ([`CommandAudit`], `src/control/safety/audit.rs`). The shipped
//! `config/controller.yaml` is the one the tests' launch files load. A command after
//! messages the subscription missed (its sequence number skips) is taken without judging
//! the pair across the gap.

use ::trocar_docking::control::safety::audit::CommandAudit;
use ::trocar_docking::control::ControllerParams;
use ::trocar_docking::kinematics::lbr::LbrModel;
use ::trocar_docking::kinematics::{JointLimits, JointVector};

/// The audit of one command topic.
#[derive(Debug, Clone, Copy)]
pub(crate) struct TopicAudit {
    audit: CommandAudit,
    seq: Option<u32>,
}

impl Default for TopicAudit {
    /// The shipped guard on the LBR Med 7, at the shipped control period.
    fn default() -> Self {
        let p = ControllerParams::default();
        Self {
            audit: CommandAudit::new(&p.guard, &JointLimits::of_model(LbrModel::Med7), p.dt_s),
            seq: None,
        }
    }
}

impl TopicAudit {
    /// The command `q` of the message numbered `seq`, stamped `stamp` (s).
    pub(crate) fn add(&mut self, seq: u32, stamp: f64, q: &JointVector) {
        match self.seq {
            Some(s) if seq != s.wrapping_add(1) => self.audit.resync(stamp, q),
            _ => self.audit.add(stamp, q),
        }
        self.seq = Some(seq);
    }

    /// Commands seen.
    pub(crate) fn count(&self) -> usize {
        self.audit.count
    }

    /// The verdict for the check of `code`: both shares, an error where one is over its limit.
    pub(crate) fn verdict(&self, code: &str) -> Result<String, String> {
        self.audit.verdict().map_err(|e| format!("{code}: {e}"))
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
        a.add(0, 0.0, &q);
        for k in 1..=100u32 {
            v = (v + p.guard.max_acceleration_rad_s2 * dt).min(vmax);
            q[0] += v * dt;
            a.add(k, f64::from(k) * dt, &q);
        }
        let ok = a.verdict("X").unwrap();
        assert!(ok.contains("100 % of the guard's speed limit"), "{ok}");
        // A message missed: the jump across it is not a step.
        q[0] += 10.0 * vmax * dt;
        a.add(102, 1.02, &q);
        assert!(a.verdict("X").is_ok());
        assert_eq!(a.count(), 102);
        // Standing still at once from speed.
        q[0] += vmax * dt;
        a.add(103, 1.03, &q);
        a.add(104, 1.04, &q);
        assert!(a.verdict("X").unwrap_err().starts_with("X: "));
    }
}
