//! The ROS message types the nodes use, generated at compile time by rosrust from the
//! Debian `.msg` files and this package's own (`msg/`, and the vendored driver message
//! `vendor/lbr_msgs/msg/LBRState.msg`). `build.rs` lays out the tree and sets
//! `ROSRUST_MSG_PATH`; see its `ros_message_path`.
#![allow(missing_docs, clippy::all, clippy::pedantic)]

rosrust::rosmsg_include!(
    trocar_docking / DockingStatus,
    diagnostic_msgs / DiagnosticArray,
    lbr_msgs / LBRState,
    std_msgs / Float64MultiArray,
    std_msgs / Header,
    std_msgs / String,
    std_srvs / Trigger,
    sensor_msgs / JointState,
    sensor_msgs / Image,
    sensor_msgs / CameraInfo,
    sensor_msgs / Joy,
    geometry_msgs / PoseStamped,
    geometry_msgs / PoseWithCovarianceStamped,
    geometry_msgs / PointStamped,
    geometry_msgs / WrenchStamped,
    geometry_msgs / TwistStamped,
    geometry_msgs / TransformStamped,
    trajectory_msgs / JointTrajectory,
    visualization_msgs / MarkerArray,
    tf2_msgs / TFMessage,
    rosgraph_msgs / Clock,
    dynamic_reconfigure / Config,
    dynamic_reconfigure / ConfigDescription,
    dynamic_reconfigure / Reconfigure
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
            "geometry_msgs/Point fulcrum",
            "float64 shaft_to_fulcrum",
            "float64 lateral_force",
            "string scope_limit",
        ] {
            assert!(def.contains(field), "{field} missing");
        }
    }

    /// The connections of a ROS bag as (message type, md5 sum), read from the connection
    /// records of its uncompressed index at the end. A record's header fields come in the
    /// order callerid, latching, md5sum, message_definition, topic, type, each behind a
    /// binary length: the type is the last `type=` before the next `md5sum=`, and its
    /// value may run on into the next length byte (compare with `starts_with`).
    fn bag_connections(bytes: &[u8]) -> Vec<(String, String)> {
        let text = String::from_utf8_lossy(bytes);
        let starts: Vec<usize> = text.match_indices("md5sum=").map(|(i, _)| i).collect();
        let mut out = Vec::new();
        for (k, &at) in starts.iter().enumerate() {
            let end = starts.get(k + 1).copied().unwrap_or(text.len());
            let record = &text[at..end];
            let sum: String = record["md5sum=".len()..].chars().take(32).collect();
            let Some(t) = record.rfind("type=") else { continue };
            let kind: String = record[t + "type=".len()..]
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '/' || *c == '_')
                .collect();
            out.push((kind, sum));
        }
        out
    }

    #[test]
    fn no_test_bag_carries_a_docking_status_of_another_definition() {
        // A replayed bag holding /docking/status with an older md5 would not connect to the
        // nodes (the after-docking fields were added later). The bags in tests/bags hold none; should one be
        // recorded with it, its md5 must be the current message's.
        let md5 = super::trocar_docking::DockingStatus::md5sum();
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bags");
        let mut bags = 0;
        for entry in std::fs::read_dir(&dir).expect("tests/bags") {
            let path = entry.expect("entry").path();
            if path.extension().is_none_or(|e| e != "bag") {
                continue;
            }
            bags += 1;
            let bytes = std::fs::read(&path).expect("bag");
            let conns = bag_connections(&bytes);
            assert!(
                conns.iter().any(|(t, _)| t.starts_with("rosgraph_msgs/Clock")),
                "{}: no connection record read ({conns:?})",
                path.display()
            );
            // The parser reads sums right: the driver's LBRState is in every bag.
            let lbr = super::lbr_msgs::LBRState::md5sum();
            assert!(
                conns
                    .iter()
                    .any(|(t, s)| t.starts_with("lbr_msgs/LBRState") && *s == lbr),
                "{}: {conns:?}",
                path.display()
            );
            for (_, sum) in conns
                .iter()
                .filter(|(t, _)| t.starts_with("trocar_docking/DockingStatus"))
            {
                assert_eq!(sum, &md5, "{}: a DockingStatus of another definition", path.display());
            }
        }
        assert!(bags >= 1, "no bag in {}", dir.display());
    }
}
