//! ROS node `lbr_med_sim`: the LBR Med simulator behind the driver's topics (see trocar_docking::ros::sim_node).
//! Parameters come from its private namespace (config/lbr_med_sim.yaml through the launch files).

fn main() {
    if let Err(e) = rosrust::try_init("lbr_med_sim") {
        eprintln!("lbr_med_sim: cannot reach the ROS master: {e}");
        std::process::exit(2);
    }
    if let Err(e) = trocar_docking::ros::sim_node::run() {
        rosrust::ros_err!("lbr_med_sim: {e}");
        eprintln!("lbr_med_sim: {e}");
        std::process::exit(1);
    }
}
