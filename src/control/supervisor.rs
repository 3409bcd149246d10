//! The supervisor state machine: IDLE -> APPROACH -> INSERT -> DONE, with HOLD and ABORTED.
//!
//! The surgeon stays in the loop: nothing moves before `start`. `abort` stops from any
//! phase and needs `reset` (back to IDLE) before a new start. A hold keeps the arm still
//! and remembers the phase it interrupted. Holds for missing or stale data clear by
//! themselves when the data is fresh again; a latched hold (force limit, solver failure,
//! operator) needs an explicit `start` to resume.

use std::fmt;

use super::docking::depth::DepthBasis;
use super::docking::seated::Seated;
use super::safety::hold::HoldReason;

/// How DONE was reached, when not plainly at the goal with the depth known: what the status
/// shows the surgeon beside DONE.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DoneNote {
    /// Seated in the port beside a biased trocar estimate ([`crate::control::docking::seated`]).
    Seated(Seated),
    /// A dry run (the ghost arm: nothing was inserted) at the goal, with the tip's depth not
    /// known within the tolerance: where a docking would hold DEPTH_UNCERTAIN
    /// ([`crate::control::docking::depth`]), the rehearsal ends DONE and says so.
    DepthUnverified {
        /// The depth's uncertainty, m (about 2 sigma).
        uncertainty_m: f64,
        /// The tolerance it passed, m.
        tolerance_m: f64,
        /// What the depth rests on.
        basis: DepthBasis,
    },
}

impl DoneNote {
    /// The stable code of the status at DONE (`hold_code`).
    pub fn code(&self) -> &'static str {
        match self {
            Self::Seated(_) => "SEATED",
            Self::DepthUnverified { .. } => "DEPTH_UNVERIFIED",
        }
    }
}

impl fmt::Display for DoneNote {
    /// The DONE reason shown to the surgeon (formatted where it is shown, not in the loop).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Seated(s) => s.fmt(f),
            Self::DepthUnverified {
                uncertainty_m,
                tolerance_m,
                basis,
            } => write!(
                f,
                "dry run: nothing was inserted and the tip's depth was not verified (known only to +-{:.1} mm, over the {:.1} mm tolerance: {basis}); a docking would hold here, DEPTH_UNCERTAIN, for the surgeon to check it",
                uncertainty_m * 1e3,
                tolerance_m * 1e3
            ),
        }
    }
}

/// The phase of a docking run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
pub enum Phase {
    /// Waiting for start; nothing moves.
    Idle,
    /// Started: the arm is held still while the external torques are tared
    /// ([`crate::control::force::tare`]); then APPROACH, or back to IDLE with the reason.
    Tare,
    /// Moving the tip to the stand-off point on the insertion axis, aligning the scope.
    Approach,
    /// Sliding along the axis through the port to the goal depth.
    Insert,
    /// The tip is at the goal within tolerance; holding there.
    Done,
    /// Withdrawing along the shaft to the stand-off point (the surgeon's `~retract`), then
    /// IDLE.
    Retract,
    /// Holding still, for the reason given.
    Hold,
    /// Stopped for good; reset to start again.
    Aborted,
}

impl Phase {
    /// The phase's name as DockingStatus carries it.
    pub fn as_str(&self) -> &'static str {
        match self {
            Phase::Idle => "IDLE",
            Phase::Tare => "TARE",
            Phase::Approach => "APPROACH",
            Phase::Insert => "INSERT",
            Phase::Done => "DONE",
            Phase::Retract => "RETRACT",
            Phase::Hold => "HOLD",
            Phase::Aborted => "ABORTED",
        }
    }

    /// Whether the arm is commanded to move in this phase.
    pub fn is_moving(&self) -> bool {
        matches!(self, Phase::Approach | Phase::Insert)
    }
}

impl fmt::Display for Phase {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The state machine.
#[derive(Debug, Clone)]
pub struct Supervisor {
    phase: Phase,
    resume: Phase,
    latched: bool,
    reason: Option<HoldReason>,
    note: Option<DoneNote>,
}

impl Default for Supervisor {
    fn default() -> Self {
        Self::new()
    }
}

impl Supervisor {
    /// IDLE.
    pub fn new() -> Self {
        Self {
            phase: Phase::Idle,
            resume: Phase::Approach,
            latched: false,
            reason: None,
            note: None,
        }
    }

    /// The current phase.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// The reason of the last hold or abort (cleared by a new start from IDLE and when the
    /// goal is reached).
    pub fn reason(&self) -> Option<&HoldReason> {
        self.reason.as_ref()
    }

    /// How DONE was reached, when not plainly at the goal (see [`Supervisor::goal_reached`]).
    pub fn note(&self) -> Option<DoneNote> {
        self.note
    }

    /// Start (from IDLE) or resume (from HOLD). Refused after DONE or ABORTED.
    pub fn start(&mut self) -> Result<(), String> {
        match self.phase {
            Phase::Idle => {
                self.phase = Phase::Tare;
                self.reason = None;
                self.note = None;
                Ok(())
            }
            Phase::Hold => {
                self.phase = self.resume;
                self.latched = false;
                Ok(())
            }
            Phase::Tare | Phase::Approach | Phase::Insert | Phase::Retract => Ok(()),
            Phase::Done => Err("docking is done; reset before starting again".into()),
            Phase::Aborted => Err(format!(
                "aborted ({}); reset before starting again",
                self.reason
                    .as_ref()
                    .map_or_else(|| "no reason".to_string(), ToString::to_string)
            )),
        }
    }

    /// Abort from any phase.
    pub fn abort(&mut self, why: &str) {
        self.phase = Phase::Aborted;
        self.reason = Some(HoldReason::Operator(why.into()));
    }

    /// Back to IDLE, forgetting any hold.
    pub fn reset(&mut self) {
        *self = Self::new();
    }

    /// Hold for `reason`. A latched hold needs `start` to resume. In DONE and RETRACT (the
    /// surgeon steering, the withdrawal) a latched hold (the force stop, a rejected command)
    /// holds too, and `start` resumes DONE or RETRACT; an unlatched one (stale data) keeps
    /// the phase, which holds still without its inputs anyway, with the reason. Elsewhere
    /// the phase does not change (nothing moves there) but the reason is kept.
    pub fn hold(&mut self, reason: HoldReason, latched: bool) {
        match self.phase {
            Phase::Done | Phase::Retract if latched => {
                self.resume = self.phase;
                self.phase = Phase::Hold;
                self.latched = true;
            }
            Phase::Approach | Phase::Insert => {
                self.resume = self.phase;
                self.phase = Phase::Hold;
                self.latched = latched;
            }
            // A latched hold keeps its reason: a passing one (a stale input) must not hide
            // what only a start ends (the status would name the stale input, latched).
            Phase::Hold if self.latched && !latched => return,
            Phase::Hold => self.latched |= latched,
            _ => {}
        }
        self.reason = Some(reason);
    }

    /// Every input is good: an unlatched hold resumes the interrupted phase, and a moving
    /// phase no longer reports the reason of a hold that has passed (the status would
    /// otherwise say "no trocar pose received" while the arm moves; DONE and RETRACT, where
    /// the surgeon steers, count as moving here). A latched hold, and the reason of a
    /// refused start in IDLE, stay.
    pub fn clear_hold(&mut self) {
        match self.phase {
            Phase::Hold if !self.latched => {
                self.phase = self.resume;
                self.reason = None;
            }
            // DONE and RETRACT move the scope too (steered through the port).
            Phase::Tare | Phase::Approach | Phase::Insert | Phase::Done | Phase::Retract => self.reason = None,
            _ => {}
        }
    }

    /// The phase a hold resumes (meaningful in HOLD).
    pub fn resumes(&self) -> Phase {
        self.resume
    }

    /// Whether the current hold is latched.
    pub fn is_latched(&self) -> bool {
        self.phase == Phase::Hold && self.latched
    }

    /// The torques are tared: TARE -> APPROACH.
    pub fn tare_done(&mut self) {
        if self.phase == Phase::Tare {
            self.phase = Phase::Approach;
        }
    }

    /// The tare refused the start: TARE -> IDLE, with the reason.
    pub fn tare_refused(&mut self, reason: HoldReason) {
        if self.phase == Phase::Tare {
            self.phase = Phase::Idle;
            self.reason = Some(reason);
        }
    }

    /// The stand-off point is reached: APPROACH -> INSERT.
    pub fn approach_reached(&mut self) {
        if self.phase == Phase::Approach {
            self.phase = Phase::Insert;
        }
    }

    /// The surgeon's retract: DONE -> RETRACT; refused in any other phase.
    pub fn retract(&mut self) -> Result<(), String> {
        match self.phase {
            Phase::Done => {
                self.phase = Phase::Retract;
                Ok(())
            }
            Phase::Retract => Ok(()),
            p => Err(format!("cannot retract in {p}: only after docking (DONE)")),
        }
    }

    /// The scope is back at the stand-off point: RETRACT -> IDLE (the run has ended).
    pub fn retract_done(&mut self) {
        if self.phase == Phase::Retract {
            *self = Self::new();
        }
    }

    /// The goal is reached but the depth is not known well enough: INSERT -> HOLD for
    /// `reason` (DEPTH_UNCERTAIN), latched; `start` resumes as DONE (the surgeon accepts the
    /// depth).
    pub fn depth_uncertain(&mut self, reason: HoldReason) {
        if self.phase == Phase::Insert {
            self.phase = Phase::Hold;
            self.resume = Phase::Done;
            self.latched = true;
            self.reason = Some(reason);
            self.note = None;
        }
    }

    /// The goal is reached: INSERT -> DONE. `note` says how, when not plainly at the goal;
    /// the reason of any earlier hold is cleared.
    pub fn goal_reached(&mut self, note: Option<DoneNote>) {
        if self.phase == Phase::Insert {
            self.phase = Phase::Done;
            self.reason = None;
            self.note = note;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nominal_run() {
        let mut s = Supervisor::new();
        assert_eq!(s.phase(), Phase::Idle);
        s.approach_reached();
        s.goal_reached(None);
        assert_eq!(s.phase(), Phase::Idle, "nothing happens before start");
        s.start().unwrap();
        assert_eq!(s.phase(), Phase::Tare, "a start tares first");
        s.approach_reached();
        assert_eq!(s.phase(), Phase::Tare);
        s.tare_done();
        assert_eq!(s.phase(), Phase::Approach);
        s.goal_reached(None);
        assert_eq!(s.phase(), Phase::Approach, "no skipping the insertion");
        s.approach_reached();
        assert_eq!(s.phase(), Phase::Insert);
        s.hold(HoldReason::StaleTrocarPose { age: 1.0 }, false);
        s.clear_hold();
        let seated = Seated {
            offset: 0.002,
            angle_deg: 0.1,
            lateral_force: 0.2,
        };
        s.goal_reached(Some(DoneNote::Seated(seated)));
        assert_eq!(s.phase(), Phase::Done);
        assert_eq!(s.note(), Some(DoneNote::Seated(seated)));
        assert_eq!(s.note().map(|n| n.code()), Some("SEATED"));
        assert_eq!(s.reason(), None, "DONE clears the old hold's reason");
        assert!(s.start().is_err());
        s.retract().unwrap();
        assert_eq!(s.phase(), Phase::Retract);
        let stop = HoldReason::ForceLimit {
            force: 16.0,
            limit: 15.0,
        };
        s.hold(stop, true);
        assert_eq!(s.phase(), Phase::Hold, "the force stop holds the withdrawal");
        assert_eq!(s.resumes(), Phase::Retract);
        s.clear_hold();
        assert_eq!(s.phase(), Phase::Hold, "latched: only a start resumes");
        s.start().unwrap();
        assert_eq!(s.phase(), Phase::Retract, "the start continues the withdrawal");
        s.hold(HoldReason::NoJointState, false);
        assert_eq!(s.phase(), Phase::Retract, "a hold keeps the phase, as in DONE");
        assert_eq!(s.reason().map(HoldReason::code), Some("NO_JOINT_STATE"));
        s.clear_hold();
        assert!(s.reason().is_none(), "the data back: the passed hold's reason goes");
        s.retract_done();
        assert_eq!(s.phase(), Phase::Idle);
        assert!(s.retract().unwrap_err().contains("IDLE"));
        s.reset();
        assert_eq!(s.phase(), Phase::Idle);
    }

    #[test]
    fn holds_resume_or_latch() {
        let mut s = Supervisor::new();
        s.start().unwrap();
        s.tare_refused(HoldReason::TareMotion { moved_rad: 0.01 });
        assert_eq!(s.phase(), Phase::Idle, "a refused tare is a refused start");
        assert_eq!(s.reason().map(HoldReason::code), Some("TARE_MOTION"));
        s.start().unwrap();
        s.tare_done();
        s.approach_reached();
        s.hold(HoldReason::StaleTrocarPose { age: 1.0 }, false);
        assert_eq!(s.phase(), Phase::Hold);
        assert_eq!(s.reason().map(HoldReason::code), Some("STALE_TROCAR_POSE"));
        s.clear_hold();
        assert_eq!(s.phase(), Phase::Insert, "resumes the interrupted phase");
        assert!(s.reason().is_none(), "and no longer reports the passed hold");
        s.hold(
            HoldReason::ForceLimit {
                force: 30.0,
                limit: 20.0,
            },
            true,
        );
        s.clear_hold();
        assert_eq!(s.phase(), Phase::Hold, "a latched hold needs start");
        assert!(s.is_latched());
        assert_eq!(
            s.reason().map(HoldReason::code),
            Some("FORCE_LIMIT"),
            "and keeps its reason"
        );
        s.hold(HoldReason::StaleTorques { age: 0.2 }, false);
        assert_eq!(
            s.reason().map(HoldReason::code),
            Some("FORCE_LIMIT"),
            "a passing hold (a stale input) does not hide the latched one"
        );
        assert!(s.is_latched());
        s.start().unwrap();
        assert_eq!(s.phase(), Phase::Insert);
        s.abort("surgeon");
        assert_eq!(s.phase(), Phase::Aborted);
        s.clear_hold();
        assert!(s.start().unwrap_err().contains("surgeon"));
        assert_eq!(Phase::Aborted.as_str(), "ABORTED");
        // At the goal with the depth uncertain: a latched hold that start resumes as DONE.
        let mut s = Supervisor::new();
        s.start().unwrap();
        s.tare_done();
        s.approach_reached();
        s.depth_uncertain(HoldReason::DepthUncertain {
            uncertainty_m: 0.005,
            tolerance_m: 0.002,
            basis: crate::control::docking::depth::DepthBasis::Estimate,
        });
        assert_eq!((s.phase(), s.is_latched()), (Phase::Hold, true));
        assert_eq!(s.reason().map(HoldReason::code), Some("DEPTH_UNCERTAIN"));
        s.clear_hold();
        assert_eq!(s.phase(), Phase::Hold, "only the surgeon accepts the depth");
        s.start().unwrap();
        assert_eq!(s.phase(), Phase::Done, "start accepts it: DONE");
        // Holding in IDLE keeps IDLE.
        let mut s = Supervisor::new();
        s.hold(HoldReason::NoJointState, false);
        assert_eq!(s.phase(), Phase::Idle);
    }
}
