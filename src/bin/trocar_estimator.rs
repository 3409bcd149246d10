//! ROS node `trocar_estimator`: camera image -> trocar pose in the base frame (see trocar_docking::ros::estimator_node).
//! Parameters come from its private namespace (config/trocar_estimator.yaml through the launch files).

fn main() {
    if let Err(e) = rosrust::try_init("trocar_estimator") {
        eprintln!("trocar_estimator: cannot reach the ROS master: {e}");
        std::process::exit(2);
    }
    if let Err(e) = trocar_docking::ros::estimator_node::run() {
        rosrust::ros_err!("trocar_estimator: {e}");
        eprintln!("trocar_estimator: {e}");
        std::process::exit(1);
    }
}
