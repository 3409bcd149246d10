//! Docking: the approach to the port and the insertion along its axis ([`geometry`]: the
//! insertion axis), DONE judged over windows ([`goal_window`]) or when the port itself holds
//! the tip ([`seated`]), and only while the tip's depth is known ([`depth`]: refined at the
//! cannula's seal), and the paper's force metric M ([`metrics`]).

pub mod depth;
pub mod geometry;
pub mod goal_window;
pub mod metrics;
pub mod seated;
