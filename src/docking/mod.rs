//! The paper's optimal control law (eq. 1): cost terms c1..c5 ([`costs`]) and the
//! Gauss–Newton SQP that minimises their weighted sum under joint position and velocity
//! limits, solving each QP with Clarabel ([`sqp`]).

pub mod costs;
pub mod sqp;

pub use costs::{CostTerms, CostWeights, Targets};
pub use sqp::{SqpSettings, SqpSolution, SqpSolver, SqpStatus};
