//! The cxx bridges to C++ (KDL, ViSP, OpenCV). Only this module sees cxx types; the
//! modules above it wrap them in safe Rust with nalgebra types and typed errors.

pub mod kdl;
pub mod markerless;
pub mod vision;
