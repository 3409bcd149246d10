//! The docking controller and its parts, pure Rust (no ROS, no C++): the optimal control
//! law ([`sqp`]: costs, Gauss–Newton SQP on Clarabel, active-set warm start), the force
//! estimate and admittance law ([`admittance`]), the command guard ([`guard`]), the phase
//! state machine ([`supervisor`]), seated completion ([`seated`]), the metric M
//! ([`metrics`]), live tuning ([`live`]), the insertion-axis geometry ([`geometry`]), and after docking the port
//! held as a remote centre of motion ([`pivot`], [`fulcrum`], [`port_follow`], [`scope`]); [`controller`]
//! runs them in one step per control period.

pub mod admittance;
pub mod controller;
pub mod fulcrum;
pub mod geometry;
pub mod goal_window;
pub mod guard;
pub mod guarded;
pub mod hold;
pub mod live;
pub mod metrics;
pub mod motion;
pub mod params;
pub mod payload;
pub mod pivot;
pub mod port_follow;
pub mod scope;
pub mod seated;
pub mod sqp;
pub mod supervisor;
pub mod tare;

pub use controller::{ControlInput, ControlOutput, Controller, OptimalController, SolveReport, Stamped};
pub use guard::HoldReason;
pub use guarded::{CommandSource, Guarded, StepContext};
pub use params::{ControllerParams, ParamError};
pub use scope::{PivotReport, ScopeCommand, ScopeLimit, ScopeParams};
pub use supervisor::Phase;
