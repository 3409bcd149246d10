//! `rosrun trocar_docking preflight`: check the set-up before the arm moves (the driver's
//! streams, joint names, torques at rest, camera, marker, hand-eye file, reach, clock, the
//! command's subscriber); one line per check, exit code 1 when one fails, 2 without a master.

fn main() {
    trocar_docking::ros::node::node_main("preflight", trocar_docking::ros::preflight::run_node);
}
