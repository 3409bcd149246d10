//! The guard around any command source, as a decorator: whatever produces the joint
//! commands (the optimal controller, or another law standing in), its commands leave
//! through [`Guarded::step`], which checks each one with the [`CommandGuard`] (finite,
//! inside the joint limits less the margin, within the per-step velocity limit from the
//! previous command) before it can be published. A rejected command is never sent: the
//! source is told to hold at its previous command, latched, with the reason.
//!
//! The wrapper also owns the step timing (the `dt` of each step, never above the nominal
//! period and 0 when the clock does not advance), so that the source's step box and the
//! guard's check use the same `dt`.

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
    /// advance).
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
    /// Back to IDLE, forgetting the run.
    fn reset(&mut self);
    /// The last command this source sent, if any (the guard checks the next one against it).
    fn last_command(&self) -> Option<JointVector>;
    /// One step: the proposed output. Its command is checked before it leaves.
    fn step(&mut self, kin: &dyn Kinematics, input: &ControlInput, ctx: &StepContext<'_>) -> ControlOutput;
    /// The guard rejected the command just proposed: hold at `hold_at` (latched) for `reason`.
    fn reject(&mut self, reason: HoldReason, hold_at: JointVector);
}

/// A command source behind the command guard.
#[derive(Debug)]
pub struct Guarded<S> {
    source: S,
    guard: CommandGuard,
    last_now: Option<f64>,
}

impl<S: CommandSource> Guarded<S> {
    /// Put `source` behind `guard`.
    pub fn wrap(source: S, guard: CommandGuard) -> Self {
        Self {
            source,
            guard,
            last_now: None,
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

    /// Start docking (from IDLE) or resume after a hold.
    pub fn start(&mut self) -> Result<(), String> {
        self.source.start()
    }

    /// Abort: hold for good until reset.
    pub fn abort(&mut self, why: &str) {
        self.source.abort(why);
    }

    /// Back to IDLE; forgets the run.
    pub fn reset(&mut self) {
        self.source.reset();
    }

    fn step_dt(&mut self, now: f64) -> f64 {
        let period = self.source.period();
        let dt = match self.last_now {
            Some(t) if now.is_finite() && now > t => (now - t).min(period),
            Some(_) => 0.0,
            None => period,
        };
        if now.is_finite() {
            self.last_now = Some(self.last_now.map_or(now, |t| t.max(now)));
        }
        dt
    }

    /// One control step: the source proposes, the guard checks. Never panics. A command
    /// that cannot be checked (no previous command and no measured joints) is not sent.
    pub fn step(&mut self, kin: &dyn Kinematics, input: &ControlInput) -> ControlOutput {
        let dt = self.step_dt(input.now);
        let prev = self.source.last_command().or(input.joints.map(|j| j.value));
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
}
