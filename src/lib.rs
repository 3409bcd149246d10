//! trocar_docking: autonomous docking of an endoscope, held by a KUKA LBR Med arm, into a
//! surgical trocar, from vision (a marker on the trocar) and contact (external joint
//! torques), as ROS 1 nodes.
//!
//! The pure core (no ROS, no C++) is testable without roscore; the bridges wrap C++
//! (KDL, ViSP, OpenCV) behind safe Rust; `ros` holds only topic and parameter glue.
#![warn(missing_docs)]

pub mod admittance;
pub mod bench;
pub mod cli;
pub mod controller;
pub mod docking;
pub mod ffi;
pub mod geometry;
pub mod kinematics;
pub mod metrics;
pub mod plot;
pub mod realtime;
pub mod robot_model;
pub mod ros;
pub mod safety;
pub mod seated;
pub mod sim;
pub mod supervisor;
pub mod timeline;
pub mod vision;
