//! The docking controller and its parts, pure Rust (no ROS, no C++), one folder per job:
//! [`controller`] runs one step per control period ([`io`]: its inputs and outputs) through the phases of the state machine
//! ([`supervisor`]), with the parameters of [`params`];
//! [`docking`] the approach and insertion (the insertion axis, seated completion, the goal
//! window, the metric M); [`scope`] after docking, the port held as a remote centre of motion
//! while the surgeon steers the scope (the law, the fulcrum, the port's breathing, the
//! commands and limits); [`force`] the force sensing (torque tare, payload fit, force
//! estimate and admittance law); [`safety`] the command guard, the typed hold reasons and the
//! tip's motion limits; [`live`] the parameters tuned while it runs; [`sqp`] the optimal control law (costs, Gauss–Newton SQP on
//! Clarabel, active-set warm start).

pub mod controller;
pub mod docking;
pub mod force;
pub mod io;
pub mod live;
pub mod params;
pub mod safety;
pub mod scope;
pub mod sqp;
pub mod supervisor;

pub use controller::{Controller, OptimalController};
pub use io::{ControlInput, ControlOutput, SolveReport, Stamped, TorqueSamples};
pub use params::{ControllerParams, ParamError};
pub use safety::guard::HoldReason;
pub use safety::guarded::{CommandSource, Guarded, StepContext};
pub use scope::command::{PivotReport, ScopeCommand, ScopeLimit, ScopeParams};
pub use supervisor::Phase;
