//! ROS 1 glue (rosrust): the three nodes and what they share. The nodes hold no control or
//! estimation maths: each reads and validates its parameters, converts messages, calls the
//! pure core (`crate::control`, `crate::vision`, `crate::sim`), and publishes.
//!
//! - Nodes: [`controller_node`] (`docking_controller`, driving the guarded
//!   [`crate::control::Controller`]), [`estimator_node`] (`trocar_estimator`), [`sim_node`]
//!   (`lbr_med_sim`), [`joy_node`] (`scope_joy`: a joystick -> scope commands, mapped by
//!   [`joy`]).
//! - [`preflight`]: the preflight on the graph (the `preflight` binary, the controller's
//!   `~preflight` and `~start`), over the pure checks of [`crate::preflight`].
//! - Shared: [`node`] (start-up errors, `main`, throttled logs), [`params`] (parameters from
//!   the server, checked with [`crate::validate`]), [`topics`] (default topic names),
//!   [`msgs`] (the generated message types), [`convert`] (messages <-> core types, input
//!   checks), [`markers`] (RViz), [`stats`] (allocation-free loop statistics), [`handover`]
//!   (lock-free hand-over between the real-time loop and the rosrust threads), [`pacer`]
//!   (a loop's pace that survives clock jumps), [`trajectory`] (how the simulated arm
//!   takes a streamed trajectory, as a joint_trajectory_controller).
//!
//! The rostest programs are a binary of their own (`src/bin/rostest_checks`).

pub mod controller_node;
pub mod convert;
pub mod estimator_node;
pub mod hand_eye_node;
pub mod handover;
pub mod joy;
pub mod joy_node;
pub mod markers;
pub mod msgs;
pub mod node;
pub mod pacer;
pub mod params;
pub mod preflight;
pub mod reconfigure;
pub mod sim_lockstep;
pub mod sim_node;
pub mod stats;
pub mod topics;
pub mod trajectory;
