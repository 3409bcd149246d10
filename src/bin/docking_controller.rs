//! ROS node `docking_controller`: the docking controller (see trocar_docking::ros::controller_node).
//! Parameters come from its private namespace (config/docking_controller.yaml through the launch files).

fn main() {
    trocar_docking::ros::node::node_main("docking_controller", trocar_docking::ros::controller_node::run)
}
