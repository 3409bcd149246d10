//! The ROS message types the nodes use, generated at compile time by rosrust from the
//! Debian `.msg` files and this package's own (`msg/`, and the vendored driver message
//! `vendor/lbr_msgs/msg/LBRState.msg`). `build.rs` lays out the tree and sets
//! `ROSRUST_MSG_PATH`; see its `ros_message_path`.
#![allow(missing_docs, clippy::all, clippy::pedantic)]

rosrust::rosmsg_include!(
    trocar_docking / DockingStatus,
    lbr_msgs / LBRState,
    std_msgs / Float64MultiArray,
    std_msgs / Header,
    std_srvs / Trigger,
    sensor_msgs / JointState,
    sensor_msgs / Image,
    sensor_msgs / CameraInfo,
    geometry_msgs / PoseStamped,
    geometry_msgs / WrenchStamped,
    geometry_msgs / TransformStamped,
    trajectory_msgs / JointTrajectory,
    visualization_msgs / MarkerArray,
    tf2_msgs / TFMessage,
    rosgraph_msgs / Clock
);

#[cfg(test)]
mod tests {
    use rosrust::Message;

    #[test]
    fn vendored_lbr_state_matches_the_real_driver_md5() {
        // md5 of lbr_fri_ros's lbr_msgs/LBRState: publishers and subscribers only connect
        // when the sums agree.
        assert_eq!(super::lbr_msgs::LBRState::md5sum(), "71e053993298b574a690156a73db8a42");
    }

    #[test]
    fn docking_status_has_the_documented_fields() {
        let def = super::trocar_docking::DockingStatus::msg_definition();
        for field in [
            "string phase",
            "string hold_reason",
            "string hold_code",
            "float64 cost_axis",
            "float64 metric_m",
            "float64 latency_p99_ms",
        ] {
            assert!(def.contains(field), "{field} missing");
        }
    }
}
