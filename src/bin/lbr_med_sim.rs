//! ROS node `lbr_med_sim`: the LBR Med simulator behind the driver's topics (see trocar_docking::ros::sim_node).
//! Parameters come from its private namespace (config/lbr_med_sim.yaml through the launch files).

fn main() {
    trocar_docking::ros::node::node_main("lbr_med_sim", trocar_docking::ros::sim_node::run)
}
