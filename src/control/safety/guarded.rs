//! The guard around any command source, as a decorator: whatever produces the joint
//! commands (the optimal controller, or another law standing in), its commands leave
//! through [`Guarded::step`], which checks each one with the [`CommandGuard`] (finite,
//! inside the joint limits less the margin, within the per-step velocity limit from the
//! previous command, within `max_command_lead_rad` of the measured joints) before it can be
//! published. A rejected command is never sent: the source is told to hold at its previous
//! command, latched, with the reason.
//!
//! The wrapper also owns the step timing (the `dt` of each step, never above the nominal
//! period), so that the source's step box and the guard's check use the same `dt`, and the
//! failure modes that only the wrapper sees, each a latched hold with its reason (a new
//! start is needed, and it begins from the measured joints):
//! - **the arm does not follow**: the command led the arm by a quarter of its lead bound or
//!   more for `follow_timeout_s` while the arm moved less than [`MIN_PROGRESS`] of the bound
//!   (`ARM_NOT_FOLLOWING`); an arm that lags but moves (a fast joint behind its trajectory
//!   controller) only slows the command down. The hold is at the measured joints, so a
//!   blocked arm that frees itself does not jump to a command ahead of it;
//! - **the clock jumps**: back (`CLOCK_BACK`), or forward by more than `max_clock_jump_s`
//!   (`CLOCK_FORWARD`); never a silent freeze;
//! - **an input restarts** (the node's call to [`Guarded::interrupt`], e.g. a driver restart).
//!
//! **Every published command within the speed and acceleration limits, holds included.**
//! The wrapper keeps the last command it published and its velocity (the guard judges the
//! next command's acceleration from it), and every command it publishes, the source's or a
//! hold's, lies in the guard's step box from it: a rejection or a source's own hold brakes
//! to a stop within the acceleration limit (never an instant stop from speed), and the
//! source is told where it stands ([`CommandSource::settle`]); a hold walks to where it
//! must stand, ramping up and braking ([`CommandGuard::walk`], [`HoldTarget`]); a start
//! resumes from the last published command and its velocity. A step whose clock did not
//! advance (`dt` 0: a clock fault) walks on the nominal period, the loop's own pace.

use crate::control::io::{ControlInput, ControlOutput};
use crate::control::safety::guard::{CommandGuard, HoldReason};
use crate::control::supervisor::Phase;
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
    /// The command published this step was `at`, not the one proposed (a stand-still or a
    /// hold braked within the acceleration limit, a hold's walk): the source's last command
    /// is `at` from now on, in whatever phase it is.
    fn settle(&mut self, at: JointVector);
    /// Whether the source holds, latched: only the operator's `start` resumes it (a hold
    /// for stale data resumes by itself).
    fn hold_latched(&self) -> bool {
        false
    }
}

/// The least an arm must move on a joint whose command sits on the lead bound, over
/// `follow_timeout_s`, as a fraction of `max_command_lead_rad`, to count as following.
pub const MIN_PROGRESS: f64 = 0.1;

/// Where a hold of the wrapper's stands. Either way it gets there from the last published
/// command within the guard's speed and acceleration limits on every joint (never a jump,
/// never an instant stop); only the place differs, by what the fault says about the arm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HoldTarget {
    /// At the last published command, braked to rest within the acceleration limit (beyond
    /// it by the braking distance): the arm was following it, and the fault says nothing
    /// of where the arm is (a clock that jumped back or forward: the newest joint states
    /// may be stamped on the broken clock). The arm settles on the command it already
    /// tracks; walking anywhere else would move it on data the fault put in doubt.
    Still,
    /// Walk to these measured joints, within the speed limits, and stand there. For
    /// `ARM_NOT_FOLLOWING` the arm is blocked behind the command: standing at the last
    /// command would go on pushing it with the lead (up to `max_command_lead_rad`), and jumping
    /// to the measured joints (as a hold once did) stepped the command back by the whole
    /// lead in one period, twice the speed limit; walking there releases the push without
    /// a jump, and an arm that frees itself then has nothing ahead of it to leap to. For
    /// `DRIVER_RESTART` the driver's new session holds the arm where it stands (the newest
    /// joints): the last command, up to the lead away, would move it at the restart.
    Arm(JointVector),
}

/// A hold the wrapper raised itself: its reason and where it holds (`None`: nothing is
/// commanded, the run went back to IDLE from TARE).
#[derive(Debug, Clone)]
struct Latched {
    reason: HoldReason,
    hold_at: Option<HoldTarget>,
}

/// A command source behind the command guard.
#[derive(Debug)]
pub struct Guarded<S> {
    source: S,
    guard: CommandGuard,
    last_now: Option<f64>,
    /// The newest finite measured joints (a new start begins from them).
    last_measured: Option<JointVector>,
    /// How long the command has led the arm, s (measured time: see [`Self::watch_lead`]),
    /// and the measured joints when it began.
    behind_for: f64,
    behind_from: Option<JointVector>,
    /// The stamp of the newest measured joints, s.
    last_joint_stamp: Option<f64>,
    /// The wrapper's own latched hold, until a start, an abort or a reset.
    latched: Option<Latched>,
    /// The reason of the last output, for a start that re-anchors a hold.
    last_reason: Option<HoldReason>,
    /// The last command published (`None` while nothing is): every command after it, a
    /// hold's included, is in the guard's step box from it.
    sent: Option<JointVector>,
    /// The velocity of the last published step, rad/s (zero when nothing is published).
    velocity: JointVector,
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
            last_joint_stamp: None,
            latched: None,
            last_reason: None,
            sent: None,
            velocity: JointVector::zeros(),
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

    /// The wrapped source and the guard, to change their parameters between two steps.
    pub fn parts_mut(&mut self) -> (&mut S, &mut CommandGuard) {
        (&mut self.source, &mut self.guard)
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

    /// Start docking (from IDLE) or resume after a hold. A resume re-anchors the source at
    /// the last published command (the measured joints when none was published), so that
    /// its first command is one step of the speed limits from it: re-anchoring at the
    /// measured joints stepped the command back by the whole lead (up to
    /// `max_command_lead_rad`) in one period. Where the arm was blocked behind the command or
    /// the driver restarted, the hold has already walked the command to the arm
    /// ([`HoldTarget::Arm`]); elsewhere the arm follows the command it tracks, and the
    /// source's lead bound and tracking check keep its commands with the arm.
    pub fn start(&mut self) -> Result<(), String> {
        let phase = self.source.phase();
        if phase == Phase::Idle {
            // A new run times its steps afresh.
            self.last_now = None;
        } else if phase == Phase::Hold {
            if let Some(q) = self.sent.or(self.last_measured) {
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
        self.sent = None;
        self.velocity = JointVector::zeros();
        self.behind_for = 0.0;
        self.behind_from = None;
        self.last_now = None;
        self.source.reset();
    }

    /// An input restarted under the controller (a driver restart, seen by the node): hold,
    /// latched, for `reason`, walking to the newest measured joints within the speed limits
    /// ([`HoldTarget::Arm`]; at the last command when none is known); a new start is
    /// needed. Nothing happens in IDLE; from TARE the run goes back to IDLE.
    pub fn interrupt(&mut self, reason: HoldReason) {
        let hold_at = match self.last_measured {
            Some(q) => Some(HoldTarget::Arm(q)),
            None => self.sent.or(self.source.last_command()).map(|_| HoldTarget::Still),
        };
        self.raise(reason, hold_at);
    }

    /// The wrapper's own hold for `reason` at `hold_at` (see [`Guarded::interrupt`]). A
    /// second one keeps the first reason: it is the cause.
    fn raise(&mut self, reason: HoldReason, hold_at: Option<HoldTarget>) {
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
            (_, Some(target)) => {
                // The source holds at the last published command; [`Guarded::step`] walks it
                // to the target from there.
                if let Some(q) = self.sent.or(self.source.last_command()) {
                    self.source.reject(reason.clone(), q);
                }
                self.latched = Some(Latched {
                    reason,
                    hold_at: Some(target),
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
        } else if now - t > self.guard.params().max_clock_jump_s {
            (0.0, Some(HoldReason::ClockForward { by_s: now - t }))
        } else {
            ((now - t).min(period), None)
        }
    }

    /// How much measured time this step adds (s): the advance of the measured joints'
    /// stamp since the last step, at most `dt`. A driver that stops sending adds none, so
    /// the arm-following watch cannot mistake a silent driver for a still arm before the
    /// stale-data hold names it.
    fn measured_time(&mut self, input: &ControlInput, dt: f64) -> f64 {
        let stamp = input.joints.map(|j| j.stamp).filter(|s| s.is_finite());
        let advance = match (self.last_joint_stamp, stamp) {
            (Some(a), Some(b)) if b > a => (b - a).min(dt),
            _ => 0.0,
        };
        if stamp.is_some() {
            self.last_joint_stamp = stamp;
        }
        advance
    }

    /// The arm does not follow when the command has led it (by [`LEAD_WATCH_FRACTION`](crate::control::safety::guard::LEAD_WATCH_FRACTION) of
    /// the bound or more) for the timeout of measured time (`dt`, from
    /// [`Self::measured_time`]) while the arm has not moved (by [`MIN_PROGRESS`]
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
                if self.behind_for <= p.follow_timeout_s {
                    return None;
                }
                if (q - q0).amax() > MIN_PROGRESS * p.max_command_lead_rad {
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
        // Every command is checked against the last one published (the source's own last
        // command is the same one, but for a hold's walk, which the source is told of).
        let prev = self.sent.or(self.source.last_command()).or(measured);
        if self.sent.is_none() {
            self.velocity = JointVector::zeros();
        }
        self.guard.set_velocity(self.velocity);
        let ctx = StepContext { guard: &self.guard, dt };
        let mut out = self.source.step(kin, input, &ctx);
        // Where a hold stands (braked or walked to), instead of the source's command.
        let mut stand: Option<JointVector> = None;
        match (out.command, prev) {
            (Some(cmd), Some(prev)) if cmd == prev => stand = Some(prev),
            (Some(cmd), Some(prev)) => {
                if let Err(reason) = self.guard.check_command(&cmd, &prev, dt) {
                    self.source.reject(reason.clone(), prev);
                    stand = Some(prev);
                    out.phase = self.source.phase();
                    out.hold = Some(reason);
                }
            }
            (Some(_), None) => out.command = None,
            (None, _) => {}
        }
        if let Some(why) = jump {
            self.raise(why, out.command.or(prev).map(|_| HoldTarget::Still));
        } else if self.latched.is_none() {
            // Judged on fresh joints only: with none (a silent driver) the arm's progress is
            // unknown, and the stale-data hold speaks for it.
            let fresh = input
                .joints
                .is_some_and(|j| CommandGuard::fresh(input.now - j.stamp, self.guard.params().joint_timeout_s));
            let command = out.command.as_ref().filter(|_| fresh && measured.is_some());
            let measured_for = self.measured_time(input, dt);
            if let Some(why) = self.watch_lead(command, measured_for) {
                // Hold where the arm is (walking there): when it frees itself, nothing jumps.
                let at = measured.map(HoldTarget::Arm).or(out.command.map(|_| HoldTarget::Still));
                self.raise(why, at);
            }
        }
        if let Some(l) = &self.latched {
            stand = match (out.command, l.hold_at, prev) {
                (Some(_), Some(HoldTarget::Arm(q)), _) => Some(q),
                (Some(_), Some(HoldTarget::Still), Some(p)) => Some(p),
                _ => None,
            };
            if stand.is_none() {
                out.command = None;
            }
            out.phase = self.source.phase();
            out.hold = Some(l.reason.clone());
            out.solve = None;
        }
        self.publish(&mut out, stand, prev, dt);
        self.last_reason.clone_from(&out.hold);
        self.sent = out.command;
        out
    }

    /// The command that leaves: a hold's (`stand`: braked or walked there from `prev`
    /// within the limits, the source told where it is; on a step whose clock did not
    /// advance, at the loop's own pace) or the checked one; the velocity follows it.
    fn publish(&mut self, out: &mut ControlOutput, stand: Option<JointVector>, prev: Option<JointVector>, dt: f64) {
        if let (Some(to), Some(from)) = (stand, prev) {
            let pace = if dt > 0.0 { dt } else { self.source.period() };
            let q = self.guard.walk(&from, &to, pace);
            self.source.settle(q);
            self.velocity = (q - from) / pace;
            out.command = Some(q);
        } else {
            self.velocity = match (out.command, prev) {
                (Some(c), Some(p)) if dt > 0.0 => (c - p) / dt,
                (Some(_), Some(_)) => self.velocity,
                _ => JointVector::zeros(),
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::safety::guard::GuardParams;
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
        fn settle(&mut self, at: JointVector) {
            self.last = Some(at);
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
            torque_samples: Default::default(),
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
        at_limit[1] = JointLimits::of_model(LbrModel::Med7).upper[1] - GuardParams::default().position_margin_rad;
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
    /// joints arrive fresh until step `dies_at` (then a silent driver: the last ones,
    /// growing old).
    fn lead_for_half_a_second(dies_at: i32) -> Option<HoldReason> {
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
            let stamp = 1.0 + f64::from(k.min(dies_at)) * 0.01;
            let input = ControlInput {
                scope: None,
                now,
                joints: Some(Stamped { stamp, value: q }),
                tau_ext: None,
                torque_samples: Default::default(),
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
        let fresh = lead_for_half_a_second(i32::MAX);
        assert_eq!(
            fresh.as_ref().map(HoldReason::code),
            Some("ARM_NOT_FOLLOWING"),
            "{fresh:?}"
        );
        // Stale joints say nothing of the arm's progress: the stale-data hold (the source's)
        // speaks for them, not ARM_NOT_FOLLOWING. Also when the driver dies while the
        // command leads, its last joints still within the stale timeout (0.1 s): the watch
        // counts measured time only, so it does not fire in the stale hold's stead.
        assert_eq!(lead_for_half_a_second(0), None);
        assert_eq!(lead_for_half_a_second(5), None);
    }
}

#[cfg(test)]
mod walk_tests {
    //! Every published command within the guard's speed and acceleration limits, through
    //! each of the wrapper's latched holds and the start that resumes it.
    use super::*;
    use crate::control::safety::guard::GuardParams;
    use crate::control::Stamped;
    use crate::kinematics::lbr::{LbrModel, ToolParams};
    use crate::kinematics::{JointLimits, LbrKinematics};
    use proptest::prelude::*;

    const PERIOD: f64 = 0.01;

    /// A source that walks its command towards `goal` inside the guard's step box (a law
    /// whose commands lead a blocked arm), and stands while held.
    struct Chaser {
        goal: JointVector,
        last: Option<JointVector>,
        phase: Phase,
    }

    impl CommandSource for Chaser {
        fn period(&self) -> f64 {
            PERIOD
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
            self.last = None;
        }
        fn last_command(&self) -> Option<JointVector> {
            self.last
        }
        fn step(&mut self, _kin: &dyn Kinematics, input: &ControlInput, ctx: &StepContext<'_>) -> ControlOutput {
            let from = self.last.or(input.joints.map(|j| j.value)).unwrap_or(self.goal);
            let cmd = if self.phase == Phase::Approach {
                ctx.guard.walk(&from, &self.goal, ctx.dt)
            } else {
                from
            };
            self.last = Some(cmd);
            ControlOutput {
                command: Some(cmd),
                ..ControlOutput::empty(self.phase)
            }
        }
        fn reject(&mut self, _reason: HoldReason, hold_at: JointVector) {
            self.phase = Phase::Hold;
            self.last = Some(hold_at);
        }
        fn settle(&mut self, at: JointVector) {
            self.last = Some(at);
        }
    }

    #[derive(Debug, Clone, Copy)]
    enum Fault {
        Blocked,
        ClockBack,
        ClockForward,
        DriverRestart,
    }

    /// The arm stands blocked at `q` while the source leads it by `lead` (rad per joint);
    /// `fault` strikes once the command has reached its lead; after 30 steps held, a start
    /// and 40 more steps (the source leading again). Returns the published commands with
    /// the wrapper's `dt` of each step, the hold's code, and the last command before the
    /// hold.
    fn play(fault: Fault, lead: &JointVector) -> (Vec<(JointVector, f64)>, String, JointVector) {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let limits = JointLimits::of_model(LbrModel::Med7);
        let guard = CommandGuard::new(GuardParams::default(), &limits);
        let q = JointVector::from_column_slice(&[0.1, 0.5, -0.2, -1.2, 0.3, 1.0, -0.4]);
        let source = Chaser {
            goal: q + lead,
            last: None,
            phase: Phase::Approach,
        };
        let max_jump = guard.params().max_clock_jump_s;
        let mut g = Guarded::wrap(source, guard);
        let mut now = 10.0;
        let mut last_now: Option<f64> = None;
        // The arm at rest at q begins the stream (the first command is one step from it).
        let mut sent = vec![(q, PERIOD)];
        let (mut code, mut before) = (String::new(), q);
        let mut struck = None;
        for k in 0..200 {
            // Joint states stamped on the clock they came with (the arm's own, for a clock
            // fault), always fresh.
            let input = ControlInput {
                now,
                joints: Some(Stamped { stamp: now, value: q }),
                ..ControlInput::default()
            };
            let out = g.step(&kin, &input);
            // The loop's own pace where the clock jumped (the wrapper walks on it then).
            let dt = last_now.map_or(PERIOD, |t| {
                let d = now - t;
                if (0.0..=max_jump).contains(&d) && d > 0.0 {
                    d.min(PERIOD)
                } else {
                    PERIOD
                }
            });
            last_now = Some(now);
            if out.phase == Phase::Hold && code.is_empty() {
                code = out.reason_code().to_string();
                // The last command before the hold.
                before = sent[sent.len() - 1].0;
            }
            if let Some(c) = out.command {
                sent.push((c, dt));
            }
            let reached = (g.source().goal - out.command.unwrap_or(q)).amax() < 1e-12;
            now += PERIOD;
            // A clock fault or a restart strikes while the command moves (before the
            // not-following watch could judge the lead); the blocked arm once the command
            // has reached its lead.
            let strike = match fault {
                Fault::Blocked => reached || k == 60,
                _ => k == 8,
            };
            if struck.is_none() && strike {
                struck = Some(k);
                match fault {
                    Fault::Blocked => {} // the watch sees the still arm
                    Fault::ClockBack => now -= 5.0,
                    Fault::ClockForward => now += 5.0,
                    Fault::DriverRestart => g.interrupt(HoldReason::DriverRestart {
                        stamp_jump_s: -0.05,
                        names_reordered: false,
                    }),
                }
            }
            if struck.is_some_and(|s| k == s + 40) {
                assert_eq!(g.phase(), Phase::Hold, "{fault:?}: held until the start");
                g.start().unwrap();
            }
        }
        (sent, code, before)
    }

    /// The largest speed and acceleration of `sent` (each with its step's `dt`), as shares
    /// of the guard's limits, over every joint and step; the stream starts at rest.
    fn worst_shares(sent: &[(JointVector, f64)], vmax: &JointVector) -> (f64, f64) {
        let a = GuardParams::default().max_acceleration_rad_s2;
        let v: Vec<(JointVector, f64)> = sent.windows(2).map(|w| ((w[1].0 - w[0].0) / w[1].1, w[1].1)).collect();
        let speed = v
            .iter()
            .flat_map(|(v, _)| (0..7).map(move |i| v[i].abs() / vmax[i]))
            .fold(0.0, f64::max);
        let rest = [(JointVector::zeros(), PERIOD)];
        let all: Vec<&(JointVector, f64)> = rest.iter().chain(v.iter()).collect();
        let accel = all
            .windows(2)
            .flat_map(|w| (0..7).map(move |i| (w[1].0[i] - w[0].0[i]).abs() / (w[1].1 * a)))
            .fold(0.0, f64::max);
        (speed, accel)
    }

    /// Whether `sent` comes to rest within `steps` of index `from` and stays there for
    /// `stay` steps; where it stands.
    fn rests(sent: &[(JointVector, f64)], from: usize, steps: usize, stay: usize) -> Option<JointVector> {
        (from..from + steps).find_map(|k| {
            let at = sent.get(k)?.0;
            sent.get(k..k + stay)?
                .iter()
                .all(|(c, _)| (c - at).amax() < 1e-12)
                .then_some(at)
        })
    }

    fn vmax() -> JointVector {
        let limits = JointLimits::of_model(LbrModel::Med7);
        *CommandGuard::new(GuardParams::default(), &limits).max_velocity()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn no_command_step_exceeds_the_speed_limit_through_any_hold_or_restart(
            lead in proptest::collection::vec(-1.0f64..1.0, 7),
            which in 0usize..4,
        ) {
            let bound = GuardParams::default().max_command_lead_rad;
            let mut lead = JointVector::from_column_slice(&lead) * bound;
            // Leading by a quarter of the bound or more on one joint, so that the arm's
            // not-following watch runs.
            let sign = if lead[1] >= 0.0 { 1.0 } else { -1.0 };
            lead[1] = sign * lead[1].abs().max(0.5 * bound);
            let fault = [Fault::Blocked, Fault::ClockBack, Fault::ClockForward, Fault::DriverRestart][which];
            let (sent, code, before) = play(fault, &lead);
            let want = match fault {
                Fault::Blocked => "ARM_NOT_FOLLOWING",
                Fault::ClockBack => "CLOCK_BACK",
                Fault::ClockForward => "CLOCK_FORWARD",
                Fault::DriverRestart => "DRIVER_RESTART",
            };
            prop_assert_eq!(code.as_str(), want);
            let (speed, accel) = worst_shares(&sent, &vmax());
            prop_assert!(speed <= 1.0 + 1e-9, "{:?}: a speed of {:.3} x the limit", fault, speed);
            prop_assert!(accel <= 1.0 + 1e-6, "{:?}: an acceleration of {:.3} x the limit", fault, accel);
            // Where the hold stands: at the arm (walked there), or braked to rest from the
            // last command (within its braking distance of it).
            let q = JointVector::from_column_slice(&[0.1, 0.5, -0.2, -1.2, 0.3, 1.0, -0.4]);
            match fault {
                Fault::Blocked | Fault::DriverRestart => {
                    prop_assert!(sent.iter().any(|(c, _)| (c - q).amax() < 1e-12), "{:?}: never reached the arm", fault);
                }
                Fault::ClockBack | Fault::ClockForward => {
                    let at = sent.iter().position(|(c, _)| (c - before).amax() < 1e-12).unwrap();
                    let a = GuardParams::default().max_acceleration_rad_s2;
                    let stop = (vmax().amax() / (a * PERIOD)).ceil() as usize + 2;
                    let stood = rests(&sent, at, stop, 20);
                    prop_assert!(stood.is_some(), "{:?}: did not come to rest", fault);
                    let reach = vmax().amax().powi(2) / (2.0 * a) + vmax().amax() * PERIOD;
                    prop_assert!((stood.unwrap() - before).amax() <= reach, "{:?}: stood too far", fault);
                }
            }
        }
    }

    #[test]
    fn a_blocked_arms_hold_walks_to_it_and_a_clock_jumps_hold_stands() {
        let bound = GuardParams::default().max_command_lead_rad;
        let lead = JointVector::from_column_slice(&[0.0, bound, 0.0, -0.6 * bound, 0.0, 0.0, 0.0]);
        let q = JointVector::from_column_slice(&[0.1, 0.5, -0.2, -1.2, 0.3, 1.0, -0.4]);
        let (sent, code, before) = play(Fault::Blocked, &lead);
        assert_eq!(code, "ARM_NOT_FOLLOWING");
        let vmax = vmax();
        // From the command's lead back to the arm within the time of a ramp up and down at
        // the acceleration limit, plus braking from the speed the command had: no jump, no
        // dawdling.
        let at = sent.iter().position(|(c, _)| (c - before).amax() < 1e-12).unwrap();
        let reached = sent[at..].iter().position(|(c, _)| (c - q).amax() < 1e-12).unwrap();
        let a = GuardParams::default().max_acceleration_rad_s2;
        let steps = ((2.0 * (2.0 * bound / a).sqrt() + vmax[1] / a) / PERIOD).ceil() as usize + 2;
        assert!(reached <= steps, "{reached} steps to the arm, at most {steps} expected");
        let (speed, accel) = worst_shares(&sent, &vmax);
        assert!(speed <= 1.0 + 1e-9 && accel <= 1.0 + 1e-6, "{speed} {accel}");
        let (sent, code, before) = play(Fault::ClockForward, &lead);
        assert_eq!(code, "CLOCK_FORWARD");
        let at = sent.iter().position(|(c, _)| (c - before).amax() < 1e-12).unwrap();
        // Braked to rest within the acceleration limit, then held there until the start
        // (40 steps after the fault).
        let stop = (vmax.amax() / (a * PERIOD)).ceil() as usize + 2;
        let stood = rests(&sent, at, stop, 40 - stop);
        assert!(stood.is_some(), "did not come to rest in {stop} steps");
    }
}
