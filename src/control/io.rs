//! The inputs and outputs of one control step, shared by the controller, the command guard
//! and the after-docking law ([`crate::control::scope::pivot`]), so that none of them imports
//! another for its I/O types.

use nalgebra::{Isometry3, Point3, Vector3};

use super::safety::hold::HoldReason;
use super::scope::command::{PivotReport, ScopeCommand};
use super::sqp::{CostTerms, SqpStatus};
use super::supervisor::{DoneNote, Phase};
use crate::kinematics::JointVector;

/// A value with the time it was measured, s (same clock as [`ControlInput::now`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stamped<T> {
    /// Measurement time, s.
    pub stamp: f64,
    /// The value.
    pub value: T,
}

/// How many raw torque samples a [`ControlInput`] carries at most: 64 ms of the LBR's
/// 1 kHz FRI stream, six periods of the 100 Hz controller.
pub const TORQUE_SAMPLES: usize = 64;

/// The raw external joint torques that arrived since the last control step, oldest first,
/// each with its stamp (s). Fixed capacity ([`TORQUE_SAMPLES`]), no allocation: a push into
/// a full buffer drops the oldest sample and counts it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TorqueSamples {
    samples: tinyvec::ArrayVec<[(f64, JointVector); TORQUE_SAMPLES]>,
    dropped: u64,
}

impl TorqueSamples {
    /// Append the sample `value` stamped `stamp`; when full, the oldest goes (counted).
    pub fn push(&mut self, stamp: f64, value: JointVector) {
        if self.samples.len() == TORQUE_SAMPLES {
            self.samples.remove(0);
            self.dropped += 1;
        }
        self.samples.push((stamp, value));
    }

    /// The samples, oldest first.
    pub fn iter(&self) -> impl Iterator<Item = &(f64, JointVector)> {
        self.samples.iter()
    }

    /// The newest sample.
    pub fn last(&self) -> Option<&(f64, JointVector)> {
        self.samples.last()
    }

    /// How many samples it holds.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether it holds none.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Samples dropped because the buffer was full (since it was made).
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// Empty it, for the next step (the count of dropped samples stays).
    pub fn clear(&mut self) {
        self.samples.clear();
    }
}

/// The inputs of one control step; `None` where missing or rejected.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ControlInput {
    /// Now, s.
    pub now: f64,
    /// Measured joint positions.
    pub joints: Option<Stamped<JointVector>>,
    /// The newest raw external joint torques, Nm (`None`: missing, or the newest message
    /// rejected). The controller low-passes the stream itself
    /// (`torque_filter_time_constant_s`, over [`ControlInput::torque_samples`]).
    pub tau_ext: Option<Stamped<JointVector>>,
    /// Every raw torque sample that arrived since the last step, in order, `tau_ext` the
    /// newest of them. A caller that hands only the newest sample may leave it empty: the
    /// controller then takes `tau_ext` as the one new sample.
    pub torque_samples: TorqueSamples,
    /// Trocar pose in the base frame (origin = port, z = insertion direction into the body).
    pub trocar: Option<Stamped<Isometry3<f64>>>,
    /// The surgeon's newest scope command (after DONE), stamped when it was sent.
    pub scope: Option<Stamped<ScopeCommand>>,
}

/// What the SQP reported, in a step that ran it.
#[derive(Debug, Clone, PartialEq)]
pub struct SolveReport {
    /// Unweighted c1..c5 at the solution.
    pub costs: CostTerms,
    /// QPs solved.
    pub iterations: usize,
    /// Interior-point iterations, over all the step's QPs.
    pub qp_iterations: u32,
    /// QPs solved by Clarabel (the others from a proven active set).
    pub clarabel_qps: usize,
    /// SQP wall time, µs.
    pub solve_time_us: f64,
    /// How the SQP ended.
    pub status: SqpStatus,
}

/// The outputs of one control step; `None` where unknown.
#[derive(Debug, Clone, PartialEq)]
pub struct ControlOutput {
    /// `None`: send nothing (idle, or no joint state yet). `Some`: a guarded joint position
    /// command (during a hold, the last safe command).
    pub command: Option<JointVector>,
    /// The phase after this step.
    pub phase: Phase,
    /// Reason of the last hold or abort.
    pub hold: Option<HoldReason>,
    /// How DONE was reached, when not plainly at the goal.
    pub note: Option<DoneNote>,
    /// The SQP's report, when it ran this step.
    pub solve: Option<SolveReport>,
    /// Filtered tip force estimate, base frame, N.
    pub f_ext: Vector3<f64>,
    /// Admittance reference r.
    pub reference: Option<Point3<f64>>,
    /// Tip pose from the measured joints.
    pub tip: Option<Isometry3<f64>>,
    /// Goal point.
    pub goal: Option<Point3<f64>>,
    /// M so far (time average of ||f_ext|| while moving), N.
    pub metric_m: f64,
    /// While the port is held as a remote centre of motion (after DONE): the fulcrum and
    /// the shaft's distance from it.
    pub pivot: Option<PivotReport>,
}

impl ControlOutput {
    /// An output in `phase` that commands nothing and knows nothing else (no force, no
    /// tip, no solve), for sources that fill in only what they have.
    pub fn empty(phase: Phase) -> Self {
        Self {
            command: None,
            phase,
            hold: None,
            note: None,
            solve: None,
            f_ext: Vector3::zeros(),
            reference: None,
            tip: None,
            goal: None,
            metric_m: 0.0,
            pivot: None,
        }
    }

    /// The text for the surgeon: the hold reason, or how DONE was reached.
    pub fn reason_text(&self) -> Option<String> {
        match (&self.hold, &self.note) {
            (Some(h), _) => Some(h.to_string()),
            (None, Some(n)) => Some(n.to_string()),
            (None, None) => None,
        }
    }

    /// The stable code of [`ControlOutput::reason_text`]: the hold's code, the note's at DONE
    /// (`SEATED`, `DEPTH_UNVERIFIED`: [`DoneNote::code`]), `""` for none.
    pub fn reason_code(&self) -> &'static str {
        match (&self.hold, &self.note) {
            (Some(h), _) => h.code(),
            (None, Some(n)) => n.code(),
            (None, None) => "",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn torque_samples_keep_the_newest_in_order_and_count_the_dropped() {
        let mut s = TorqueSamples::default();
        assert!(s.is_empty() && s.last().is_none());
        let n = TORQUE_SAMPLES + 3;
        for k in 0..n {
            s.push(k as f64, JointVector::repeat(k as f64));
        }
        assert_eq!((s.len(), s.dropped()), (TORQUE_SAMPLES, 3));
        let stamps: Vec<f64> = s.iter().map(|(t, _)| *t).collect();
        let expected: Vec<f64> = (3..n).map(|k| k as f64).collect();
        assert_eq!(stamps, expected, "the oldest went, the rest in order");
        assert_eq!(
            s.last().map(|(t, v)| (*t, v[0])),
            Some(((n - 1) as f64, (n - 1) as f64))
        );
        s.clear();
        assert!(s.is_empty());
        assert_eq!(s.dropped(), 3, "the count outlives a step");
    }
}
