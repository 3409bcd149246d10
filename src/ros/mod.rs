//! ROS 1 glue (rosrust): message types, parameter loading, message conversions, the JUnit
//! writer rostest needs, and the node wiring. No maths here: the nodes convert messages,
//! call the pure core, and publish.

pub mod camera_checks;
pub mod checks;
pub mod controller_node;
pub mod convert;
pub mod core;
pub mod estimator_node;
pub mod fault_injection;
pub mod image_msgs;
pub mod junit;
pub mod markers;
pub mod msgs;
pub mod node;
pub mod optimal_core;
pub mod params;
pub mod sim_node;
pub mod stats;
