//! trocar_docking: autonomous docking of an endoscope, held by a KUKA LBR Med arm, into a
//! surgical trocar, from vision (a marker on the trocar) and contact (external joint
//! torques), as ROS 1 nodes.
//!
//! One folder per job; imports point down only:
//! `ros`, `cli`, `bench` -> `trials` -> `sim`, `control` -> `vision`, `kinematics` -> `ffi`.
//! - [`kinematics`]: the `Kinematics` trait, the KDL chain, the LBR Med models and URDFs.
//! - [`control`]: the docking controller (pure Rust: no ROS, no C++).
//! - [`vision`]: marker pose (OpenCV/ViSP through the bridge), synthetic camera, hand-eye,
//!   the trocar estimator and the joint history it pairs images with.
//! - [`sim`]: the simulated plant (pure Rust); [`trials`]: the paper's experiment on it.
//! - [`sim_vision`]: the plant seen through the markerless camera pipeline (a pose source for the trials).
//! - [`ros`]: the ROS 1 nodes (rosrust): parameters, message conversions, wiring.
//! - [`cli`], [`bench`](mod@bench): the offline `trocar_docking` command and its benchmark suites.
//! - [`preflight`]: the checks of a set-up before the arm moves (pure), on what the ROS side observed.
//! - [`signal`]: the dead-band shared by the controller and the simulated sensors.
//! - [`realtime`]: the SCHED_FIFO class and the thread CPU clock for the real-time loops.
//! - [`config`]: YAML loading (one parser, one error naming the file, line and key) for every configuration file.
//! - [`validate`]: range checks of configuration values, one style for nodes and CLI.
//! - `ffi` (crate-private): the cxx bridges to KDL, ViSP and OpenCV.
#![warn(missing_docs)]

pub mod bench;
pub mod cli;
pub mod config;
pub mod control;
mod ffi;
pub mod kinematics;
pub mod preflight;
pub mod realtime;
pub mod ros;
pub mod signal;
pub mod sim;
pub mod sim_vision;
pub mod stats;
#[cfg(test)]
mod test_alloc;
pub mod trials;
pub mod validate;
pub mod vision;
