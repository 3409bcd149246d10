//! The paper's optimal control law (eq. 1): cost terms c1..c5 ([`costs`]) and the
//! Gauss–Newton SQP that minimises their weighted sum under joint position and velocity
//! limits, solving each QP with Clarabel ([`solver`]) unless the active set of its last QP,
//! or its unconstrained minimiser, is proven to solve it ([`active_set`]).

pub mod active_set;
pub mod costs;
pub mod solver;

pub use costs::{CostTerms, CostWeights, LimitAvoidance, PivotCost, Targets};
pub use solver::{QpFailure, SqpSettings, SqpSolution, SqpSolver, SqpStatus};
