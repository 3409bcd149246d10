//! ROS node `hand_eye_calibration`: eye-in-hand calibration from live topics (see
//! trocar_docking::ros::hand_eye_node). Parameters come from its private namespace
//! (config/hand_eye_calibration.yaml through launch/calibrate.launch).

fn main() {
    trocar_docking::ros::node::node_main("hand_eye_calibration", trocar_docking::ros::hand_eye_node::run)
}
