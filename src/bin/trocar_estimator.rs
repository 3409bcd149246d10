//! ROS node `trocar_estimator`: camera image -> trocar pose in the base frame (see trocar_docking::ros::estimator_node).
//! Parameters come from its private namespace (config/trocar_estimator.yaml through the launch files).

fn main() {
    trocar_docking::ros::node::node_main("trocar_estimator", trocar_docking::ros::estimator_node::run)
}
