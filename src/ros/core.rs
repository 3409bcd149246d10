//! The node's view of a docking core: what the `docking_controller` node hands it each
//! control step and what it gets back. The node's topic glue talks to [`DockingCore`] only;
//! the optimal controller (`crate::control`) implements it in `optimal_core`, and a test
//! double or another controller can stand in.

use nalgebra::{Isometry3, Point3, Vector3};

use crate::kinematics::{JointVector, Kinematics};

/// A value with the time it was measured (s, ROS time).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stamped<T> {
    /// Measurement time, s.
    pub stamp: f64,
    /// The value.
    pub value: T,
}

/// The inputs of one control step, already checked by the node (finite, right size, right
/// frame, stamps moving forward); `None` when missing or rejected.
#[derive(Debug, Clone, Default)]
pub struct StepInput {
    /// Now, s (ROS time).
    pub now: f64,
    /// Measured joint positions.
    pub joints: Option<Stamped<JointVector>>,
    /// Measured external joint torques.
    pub tau_ext: Option<Stamped<JointVector>>,
    /// Trocar pose in the base frame (origin at the port, z into the body).
    pub trocar: Option<Stamped<Isometry3<f64>>>,
}

/// The result of one control step.
#[derive(Debug, Clone)]
pub struct StepOutput {
    /// Joint positions to command; `None`: send nothing (hold, idle, done).
    pub command: Option<JointVector>,
    /// Phase name: IDLE, APPROACH, INSERT, DONE, HOLD, ABORTED.
    pub phase: &'static str,
    /// Why the core holds or aborted.
    pub reason: Option<String>,
    /// The five cost terms of the last solve (zeros when the core has none).
    pub costs: [f64; 5],
    /// Solver iterations.
    pub iterations: u32,
    /// Solve time, µs.
    pub solve_time_us: f64,
    /// Solver status text.
    pub solver_status: String,
    /// Estimated external force at the tip, N (base frame).
    pub f_ext: Vector3<f64>,
    /// The admittance reference r, if any.
    pub reference: Option<Point3<f64>>,
    /// Tip pose at the measured joints, if known.
    pub tip: Option<Isometry3<f64>>,
    /// The docking goal, if known.
    pub goal: Option<Point3<f64>>,
    /// M so far, N.
    pub metric_m: f64,
}

impl StepOutput {
    /// An output that commands nothing, in `phase`, with `reason`.
    pub fn idle(phase: &'static str, reason: Option<String>) -> Self {
        Self {
            command: None,
            phase,
            reason,
            costs: [0.0; 5],
            iterations: 0,
            solve_time_us: 0.0,
            solver_status: String::new(),
            f_ext: Vector3::zeros(),
            reference: None,
            tip: None,
            goal: None,
            metric_m: 0.0,
        }
    }
}

/// A docking controller as the node drives it.
pub trait DockingCore: Send {
    /// Begin docking (from IDLE or HOLD); an error says why not.
    fn start(&mut self) -> Result<(), String>;
    /// Stop: command nothing until reset.
    fn abort(&mut self, why: &str);
    /// Back to IDLE, forgetting the trial.
    fn reset(&mut self);
    /// One control step.
    fn step(&mut self, kin: &dyn Kinematics, input: &StepInput) -> StepOutput;
}
