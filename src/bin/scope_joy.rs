//! ROS node `scope_joy`: a joystick (sensor_msgs/Joy) -> the surgeon's scope commands on
//! `/docking/scope_command` (see trocar_docking::ros::joy_node). Parameters come from its
//! private namespace (config/scope_joy.yaml through the launch files, `joystick:=true`).

fn main() {
    trocar_docking::ros::node::node_main("scope_joy", trocar_docking::ros::joy_node::run)
}
