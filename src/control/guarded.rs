//! The guard around any command source, as a decorator: whatever produces the joint
//! commands (the optimal controller, or another law standing in), its commands leave
//! through [`Guarded::step`], which checks each one with the [`CommandGuard`] (finite,
//! inside the joint limits less the margin, within the per-step velocity limit from the
//! previous command, within `max_command_lead` of the measured joints) before it can be
//! published. A rejected command is never sent: the source is told to hold at its previous
//! command, latched, with the reason.
//!
//! The wrapper also owns the step timing (the `dt` of each step, never above the nominal
//! period), so that the source's step box and the guard's check use the same `dt`, and the
//! failure modes that only the wrapper sees, each a latched hold with its reason (a new
//! start is needed, and it begins from the measured joints):
//! - **the arm does not follow**: the command led the arm by a quarter of its lead bound or
//!   more for `follow_timeout` while the arm moved less than [`MIN_PROGRESS`] of the bound
//!   (`ARM_NOT_FOLLOWING`); an arm that lags but moves (a fast joint behind its trajectory
//!   controller) only slows the command down. The hold is at the measured joints, so a
//!   blocked arm that frees itself does not jump to a command ahead of it;
//! - **the clock jumps**: back (`CLOCK_BACK`), or forward by more than `max_clock_jump`
//!   (`CLOCK_FORWARD`); never a silent freeze;
//! - **an input restarts** (the node's call to [`Guarded::interrupt`], e.g. a driver restart).

use super::controller::{ControlInput, ControlOutput};
use super::guard::{CommandGuard, HoldReason};
use super::supervisor::Phase;
use crate::kinematics::{JointVector, Kinematics};

/// What a source gets from its guard for one step.
#[derive(Debug, Clone, Copy)]
pub struct StepContext<'a> {
    /// The guard the command will be checked by (its step box, limits and input checks).
    pub guard: &'a CommandGuard,
    /// Time since the last step, s (at most the nominal period; 0 when the clock did not
    /// advance or jumped).
    pub dt: f64,
}

/// Anything that proposes joint commands, one step at a time.
pub trait CommandSource {
    /// Nominal control period, s.
    fn period(&self) -> f64;
    /// The current phase.
    fn phase(&self) -> Phase;
    /// Begin (from IDLE) or resume (after a hold); an error says why not.
    fn start(&mut self) -> Result<(), String>;
    /// Stop for good (until reset), with the operator's reason.
    fn abort(&mut self, why: &str);
    /// Withdraw along the shaft to the stand-off point, then IDLE (after DONE); an error
    /// says why not.
    fn retract(&mut self) -> Result<(), String> {
        Err(format!("cannot retract in {}", self.phase()))
    }
    /// Back to IDLE, forgetting the run.
    fn reset(&mut self);
    /// The last command this source sent, if any (the guard checks the next one against it).
    fn last_command(&self) -> Option<JointVector>;
    /// One step: the proposed output. Its command is checked before it leaves.
    fn step(&mut self, kin: &dyn Kinematics, input: &ControlInput, ctx: &StepContext<'_>) -> ControlOutput;
    /// The guard rejected the command just proposed: hold at `hold_at` (latched) for `reason`.
    fn reject(&mut self, reason: HoldReason, hold_at: JointVector);
    /// Whether the source holds, latched: only the operator's `start` resumes it (a hold
    /// for stale data resumes by itself).
    fn hold_latched(&self) -> bool {
        false
    }
}

/// The least an arm must move on a joint whose command sits on the lead bound, over
/// `follow_timeout`, as a fraction of `max_command_lead`, to count as following.
pub const MIN_PROGRESS: f64 = 0.1;

/// A hold the wrapper raised itself: its reason and where it holds (`None`: nothing is
/// commanded, the run went back to IDLE from TARE).
#[derive(Debug, Clone)]
struct Latched {
    reason: HoldReason,
    hold_at: Option<JointVector>,
}

/// A command source behind the command guard.
#[derive(Debug)]
pub struct Guarded<S> {
    source: S,
    guard: CommandGuard,
    last_now: Option<f64>,
    /// The newest finite measured joints (a new start begins from them).
    last_measured: Option<JointVector>,
    /// How long the command has led the arm, s, and the measured joints when it began.
    behind_for: f64,
    behind_from: Option<JointVector>,
    /// The wrapper's own latched hold, until a start, an abort or a reset.
    latched: Option<Latched>,
    /// The reason of the last output, for a start that re-anchors a hold.
    last_reason: Option<HoldReason>,
}

impl<S: CommandSource> Guarded<S> {
    /// Put `source` behind `guard`.
    pub fn wrap(source: S, guard: CommandGuard) -> Self {
        Self {
            source,
            guard,
            last_now: None,
            last_measured: None,
            behind_for: 0.0,
            behind_from: None,
            latched: None,
            last_reason: None,
        }
    }

    /// The wrapped source.
    pub fn source(&self) -> &S {
        &self.source
    }

    /// The guard.
    pub fn guard(&self) -> &CommandGuard {
        &self.guard
    }

    /// The current phase.
    pub fn phase(&self) -> Phase {
        self.source.phase()
    }

    /// Whether the run holds, latched (the wrapper's own hold or the source's): it does not
    /// resume by itself; the operator's `start` does.
    pub fn hold_latched(&self) -> bool {
        self.source.phase() == Phase::Hold && (self.latched.is_some() || self.source.hold_latched())
    }

    /// Start docking (from IDLE) or resume after a hold. A resume begins from the measured
    /// joints, not from the command held before (the arm may have been blocked behind it,
    /// or moved while held): nothing jumps.
    pub fn start(&mut self) -> Result<(), String> {
        let phase = self.source.phase();
        if phase == Phase::Idle {
            // A new run times its steps afresh.
            self.last_now = None;
        } else if phase == Phase::Hold {
            if let Some(q) = self.last_measured {
                let why = self
                    .latched
                    .as_ref()
                    .map(|l| l.reason.clone())
                    .or_else(|| self.last_reason.clone())
                    // (a hold always has a reason; this only keeps the re-anchor total)
                    .unwrap_or(HoldReason::NoJointState);
                self.source.reject(why, q);
            }
        }
        self.source.start()?;
        self.latched = None;
        self.behind_for = 0.0;
        self.behind_from = None;
        Ok(())
    }

    /// Withdraw along the shaft to the stand-off point, then IDLE; an error says why not.
    pub fn retract(&mut self) -> Result<(), String> {
        self.source.retract()
    }

    /// Abort: hold for good until reset.
    pub fn abort(&mut self, why: &str) {
        self.latched = None;
        self.source.abort(why);
    }

    /// Back to IDLE; forgets the run.
    pub fn reset(&mut self) {
        self.latched = None;
        self.behind_for = 0.0;
        self.behind_from = None;
        self.last_now = None;
        self.source.reset();
    }

    /// An input restarted under the controller (a driver restart, seen by the node): hold,
    /// latched, for `reason`, at the last command; a new start is needed. Nothing happens
    /// in IDLE; from TARE the run goes back to IDLE.
    pub fn interrupt(&mut self, reason: HoldReason) {
        let hold_at = self.source.last_command().or(self.last_measured);
        self.raise(reason, hold_at);
    }

    /// The wrapper's own hold for `reason` at `hold_at` (see [`Guarded::interrupt`]). A
    /// second one keeps the first reason: it is the cause.
    fn raise(&mut self, reason: HoldReason, hold_at: Option<JointVector>) {
        self.behind_for = 0.0;
        self.behind_from = None;
        if self.latched.is_some() {
            return;
        }
        match (self.source.phase(), hold_at) {
            (Phase::Idle, _) => {}
            (Phase::Tare, _) | (_, None) => {
                // Nothing moved yet (or nothing can be held): back to IDLE.
                self.source.reset();
                self.latched = Some(Latched { reason, hold_at: None });
            }
            (_, Some(q)) => {
                self.source.reject(reason.clone(), q);
                self.latched = Some(Latched {
                    reason,
                    hold_at: Some(q),
                });
            }
        }
    }

    /// This step's `dt`, and the clock jump it is, if any.
    fn step_dt(&mut self, now: f64) -> (f64, Option<HoldReason>) {
        let period = self.source.period();
        let Some(t) = self.last_now else {
            if now.is_finite() {
                self.last_now = Some(now);
            }
            return (period, None);
        };
        if !now.is_finite() {
            return (0.0, None);
        }
        self.last_now = Some(now);
        if now < t {
            (0.0, Some(HoldReason::ClockBack { by_s: t - now }))
        } else if now - t > self.guard.params().max_clock_jump {
            (0.0, Some(HoldReason::ClockForward { by_s: now - t }))
        } else {
            ((now - t).min(period), None)
        }
    }

    /// The arm does not follow when the command has led it (by [`LEAD_WATCH_FRACTION`](super::guard::LEAD_WATCH_FRACTION) of
    /// the bound or more) for the timeout while the arm has not moved (by [`MIN_PROGRESS`]
    /// of the bound on any joint) since the lead began. Not "sat on the bound without a
    /// break": against a blocked arm the limited command wanders inside its lead box, in and
    /// out of the bound.
    fn watch_lead(&mut self, command: Option<&JointVector>, dt: f64) -> Option<HoldReason> {
        let saturated = command.and_then(|c| self.guard.lead_saturated(c));
        let q = self.guard.measured().copied();
        match (saturated, q) {
            (Some((joint, lead)), Some(q)) if self.source.phase() != Phase::Idle => {
                let q0 = *self.behind_from.get_or_insert(q);
                self.behind_for += dt;
                let p = self.guard.params();
                if self.behind_for <= p.follow_timeout {
                    return None;
                }
                if (q - q0).amax() > MIN_PROGRESS * p.max_command_lead {
                    // Lagging, but moving: a new window from here.
                    self.behind_for = 0.0;
                    self.behind_from = Some(q);
                    return None;
                }
                Some(HoldReason::ArmNotFollowing { joint, lead })
            }
            _ => {
                self.behind_for = 0.0;
                self.behind_from = None;
                None
            }
        }
    }

    /// One control step: the source proposes, the guard checks. Never panics. A command
    /// that cannot be checked (no previous command and no measured joints) is not sent.
    pub fn step(&mut self, kin: &dyn Kinematics, input: &ControlInput) -> ControlOutput {
        let (dt, jump) = self.step_dt(input.now);
        let measured = input
            .joints
            .map(|j| j.value)
            .filter(|q| q.iter().all(|x| x.is_finite()));
        if measured.is_some() {
            self.last_measured = measured;
        }
        self.guard.set_measured(measured);
        let prev = self.source.last_command().or(measured);
        let ctx = StepContext { guard: &self.guard, dt };
        let mut out = self.source.step(kin, input, &ctx);
        match (out.command, prev) {
            (Some(cmd), Some(prev)) => {
                if let Err(reason) = self.guard.check_command(&cmd, &prev, dt) {
                    self.source.reject(reason.clone(), prev);
                    out.command = Some(prev);
                    out.phase = self.source.phase();
                    out.hold = Some(reason);
                }
            }
            (Some(_), None) => out.command = None,
            (None, _) => {}
        }
        if let Some(why) = jump {
            self.raise(why, out.command.or(prev));
        } else if self.latched.is_none() {
            // Judged on fresh joints only: with none (a silent driver) the arm's progress is
            // unknown, and the stale-data hold speaks for it.
            let fresh = input
                .joints
                .is_some_and(|j| CommandGuard::fresh(input.now - j.stamp, self.guard.params().joint_timeout));
            let command = out.command.as_ref().filter(|_| fresh && measured.is_some());
            if let Some(why) = self.watch_lead(command, dt) {
                // Hold where the arm is: when it frees itself, nothing jumps.
                self.raise(why, measured.or(out.command));
            }
        }
        if let Some(l) = &self.latched {
            out.command = out.command.and(l.hold_at);
            out.phase = self.source.phase();
            out.hold = Some(l.reason.clone());
            out.solve = None;
        }
        self.last_reason.clone_from(&out.hold);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::guard::GuardParams;
    use crate::control::Stamped;
    use crate::kinematics::lbr::{LbrModel, ToolParams};
    use crate::kinematics::{JointLimits, LbrKinematics};

    /// A stand-in source that proposes whatever it is told to.
    struct Scripted {
        propose: JointVector,
        last: Option<JointVector>,
        phase: Phase,
        rejected: Option<HoldReason>,
    }

    impl CommandSource for Scripted {
        fn period(&self) -> f64 {
            0.01
        }
        fn phase(&self) -> Phase {
            self.phase
        }
        fn start(&mut self) -> Result<(), String> {
            self.phase = Phase::Approach;
            Ok(())
        }
        fn abort(&mut self, _why: &str) {
            self.phase = Phase::Aborted;
        }
        fn reset(&mut self) {
            self.phase = Phase::Idle;
        }
        fn last_command(&self) -> Option<JointVector> {
            self.last
        }
        fn step(&mut self, _kin: &dyn Kinematics, _input: &ControlInput, _ctx: &StepContext<'_>) -> ControlOutput {
            self.last = Some(self.propose);
            ControlOutput {
                command: Some(self.propose),
                ..ControlOutput::empty(self.phase)
            }
        }
        fn reject(&mut self, reason: HoldReason, hold_at: JointVector) {
            self.phase = Phase::Hold;
            self.last = Some(hold_at);
            self.rejected = Some(reason);
        }
    }

    fn run(propose: JointVector, joints: JointVector) -> (ControlOutput, Guarded<Scripted>) {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let limits = JointLimits::of_model(LbrModel::Med7);
        let source = Scripted {
            propose,
            last: None,
            phase: Phase::Approach,
            rejected: None,
        };
        let mut g = Guarded::wrap(source, CommandGuard::new(GuardParams::default(), &limits));
        let input = ControlInput {
            scope: None,
            now: 1.0,
            joints: Some(Stamped {
                stamp: 1.0,
                value: joints,
            }),
            tau_ext: None,
            trocar: None,
        };
        let out = g.step(&kin, &input);
        (out, g)
    }

    #[test]
    fn no_source_gets_a_bad_command_past_the_guard() {
        let q = JointVector::from_column_slice(&[0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 0.0]);
        // A small step passes unchanged.
        let mut ok = q;
        ok[0] += 1e-4;
        let (out, g) = run(ok, q);
        assert_eq!(out.command, Some(ok));
        assert!(g.source().rejected.is_none());
        // A jump, a NaN, a step out of the limits: held at the measured joints, latched,
        // with the guard's reason.
        let mut jump = q;
        jump[2] += 0.3;
        let mut nan = q;
        nan[4] = f64::NAN;
        // At the upper limit less the margin, one small step further out.
        let mut at_limit = q;
        at_limit[1] = JointLimits::of_model(LbrModel::Med7).upper[1] - GuardParams::default().position_margin;
        let mut beyond = at_limit;
        beyond[1] += 1e-4;
        for (bad, measured, code) in [
            (jump, q, "VELOCITY_LIMIT"),
            (nan, q, "NON_FINITE_COMMAND"),
            (beyond, at_limit, "POSITION_LIMIT"),
        ] {
            let (out, g) = run(bad, measured);
            let q = measured;
            assert_eq!(out.command, Some(q), "{code}: held where the arm is");
            assert_eq!(out.phase, Phase::Hold);
            assert_eq!(out.reason_code(), code);
            assert_eq!(g.source().rejected.as_ref().map(HoldReason::code), Some(code));
            assert_eq!(g.source().last_command(), Some(q), "the source holds too");
        }
    }

    /// The Scripted source proposes a command 1 deg ahead of a still arm for 0.5 s; the
    /// joints arrive fresh, or stop (a silent driver: the last ones, growing old).
    fn lead_for_half_a_second(fresh: bool) -> Option<HoldReason> {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let limits = JointLimits::of_model(LbrModel::Med7);
        let q = JointVector::from_column_slice(&[0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 0.0]);
        let mut ahead = q;
        ahead[1] += 1f64.to_radians();
        let source = Scripted {
            propose: ahead,
            last: Some(ahead),
            phase: Phase::Approach,
            rejected: None,
        };
        let mut g = Guarded::wrap(source, CommandGuard::new(GuardParams::default(), &limits));
        for k in 0..50 {
            let now = 1.0 + f64::from(k) * 0.01;
            let stamp = if fresh { now } else { 1.0 };
            let input = ControlInput {
                scope: None,
                now,
                joints: Some(Stamped { stamp, value: q }),
                tau_ext: None,
                trocar: None,
            };
            let out = g.step(&kin, &input);
            if out.phase == Phase::Hold {
                return out.hold;
            }
        }
        None
    }

    #[test]
    fn a_still_arm_behind_its_command_is_not_following_but_a_silent_driver_is_not_judged() {
        let fresh = lead_for_half_a_second(true);
        assert_eq!(
            fresh.as_ref().map(HoldReason::code),
            Some("ARM_NOT_FOLLOWING"),
            "{fresh:?}"
        );
        // Stale joints say nothing of the arm's progress: the stale-data hold (the source's)
        // speaks for them, not ARM_NOT_FOLLOWING.
        assert_eq!(lead_for_half_a_second(false), None);
    }
}
