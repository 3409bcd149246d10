//! ROS node `docking_controller`: the docking controller (see trocar_docking::ros::controller_node).
//! Parameters come from its private namespace (config/docking_controller.yaml through the launch files).

fn main() {
    if let Err(e) = rosrust::try_init("docking_controller") {
        eprintln!("docking_controller: cannot reach the ROS master: {e}");
        std::process::exit(2);
    }
    if let Err(e) = trocar_docking::ros::controller_node::run() {
        rosrust::ros_err!("docking_controller: {e}");
        eprintln!("docking_controller: {e}");
        std::process::exit(1);
    }
}
