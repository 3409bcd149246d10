//! ROS 1 glue (rosrust): message types, parameter loading, message conversions and the
//! node wiring. The nodes hold no control or estimation maths: each reads its parameters,
//! converts messages, calls the pure core (`crate::control`, `crate::vision`, `crate::sim`),
//! and publishes. The rostest programs are a binary of their own (`src/bin/rostest_checks`).

pub mod controller_node;
pub mod convert;
pub mod estimator_node;
pub mod markers;
pub mod msgs;
pub mod node;
pub mod params;
pub mod sim_node;
pub mod stats;
