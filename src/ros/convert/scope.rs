//! The surgeon's scope command on the wire: a `geometry_msgs/TwistStamped` in the
//! `endoscope_tip` frame (`angular.x` pan, `angular.y` tilt, `angular.z` roll, rad/s;
//! `linear.z` in and out along the shaft, m/s) <-> [`ScopeCommand`], with the checks a
//! command from the wire needs: every used value finite, the frame empty or the tip's.

use super::{check_finite, header, same_frame, InputError};
use crate::control::ScopeCommand;
use crate::ros::msgs::geometry_msgs;

/// The scope command of a TwistStamped whose frame is '' or `tip_frame`. The linear x and
/// y components have no meaning for a scope held through a port and are ignored; NaN in
/// any component is still a rejected message (a broken sender).
pub fn scope_command(
    topic: &str,
    msg: &geometry_msgs::TwistStamped,
    tip_frame: &str,
) -> Result<ScopeCommand, InputError> {
    let frame = &msg.header.frame_id;
    if !frame.is_empty() && !same_frame(frame, tip_frame) {
        return Err(InputError::WrongFrame {
            topic: topic.to_string(),
            expected: tip_frame.to_string(),
            got: frame.clone(),
        });
    }
    let (a, l) = (&msg.twist.angular, &msg.twist.linear);
    check_finite(
        topic,
        "twist (angular x y z, linear x y z)",
        &[a.x, a.y, a.z, l.x, l.y, l.z],
    )?;
    Ok(ScopeCommand {
        pan: a.x,
        tilt: a.y,
        roll: a.z,
        zoom: l.z,
    })
}

/// The stamp a scope command counts from, s: its header stamp, or `arrival` (the node's
/// clock when it came) when the sender left the stamp zero.
pub fn scope_stamp(msg: &geometry_msgs::TwistStamped, arrival: f64) -> f64 {
    let s = super::seconds(msg.header.stamp);
    if s > 0.0 {
        s
    } else {
        arrival
    }
}

/// A TwistStamped carrying `cmd` in `frame`.
pub fn scope_twist(stamp: rosrust::Time, frame: &str, cmd: &ScopeCommand) -> geometry_msgs::TwistStamped {
    let mut m = geometry_msgs::TwistStamped {
        header: header(stamp, frame),
        twist: geometry_msgs::Twist::default(),
    };
    m.twist.angular.x = cmd.pan;
    m.twist.angular.y = cmd.tilt;
    m.twist.angular.z = cmd.roll;
    m.twist.linear.z = cmd.zoom;
    m
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::convert::ros_time;

    const TIP: &str = "endoscope_tip";

    fn cmd() -> ScopeCommand {
        ScopeCommand {
            pan: 0.17,
            tilt: -0.05,
            roll: 0.3,
            zoom: -0.01,
        }
    }

    #[test]
    fn a_twist_maps_angular_xyz_and_linear_z_and_round_trips() {
        let m = scope_twist(ros_time(4.0), TIP, &cmd());
        assert_eq!(m.twist.angular.x, 0.17);
        assert_eq!(m.twist.angular.y, -0.05);
        assert_eq!(m.twist.angular.z, 0.3);
        assert_eq!(m.twist.linear.z, -0.01);
        assert_eq!(scope_command("t", &m, TIP).unwrap(), cmd());
        // Linear x and y do not steer a scope through a port.
        let mut side = m.clone();
        side.twist.linear.x = 0.5;
        side.twist.linear.y = -0.5;
        assert_eq!(scope_command("t", &side, TIP).unwrap(), cmd());
    }

    #[test]
    fn the_frame_may_be_empty_or_the_tip_and_nothing_else() {
        let mut m = scope_twist(ros_time(1.0), "", &cmd());
        assert!(scope_command("t", &m, TIP).is_ok(), "empty frame: the tip's");
        m.header.frame_id = "/endoscope_tip".into();
        assert!(scope_command("t", &m, TIP).is_ok());
        m.header.frame_id = "lbr_link_0".into();
        let e = scope_command("/docking/scope_command", &m, TIP).unwrap_err();
        assert!(matches!(e, InputError::WrongFrame { .. }), "{e}");
        let text = e.to_string();
        assert!(
            text.contains("/docking/scope_command") && text.contains("lbr_link_0") && text.contains(TIP),
            "{text}"
        );
    }

    #[test]
    fn a_non_finite_component_is_rejected_with_its_index() {
        let base = scope_twist(ros_time(1.0), TIP, &cmd());
        let set: [fn(&mut geometry_msgs::TwistStamped, f64); 6] = [
            |m, v| m.twist.angular.x = v,
            |m, v| m.twist.angular.y = v,
            |m, v| m.twist.angular.z = v,
            |m, v| m.twist.linear.x = v,
            |m, v| m.twist.linear.y = v,
            |m, v| m.twist.linear.z = v,
        ];
        for (i, f) in set.iter().enumerate() {
            for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                let mut m = base.clone();
                f(&mut m, bad);
                let e = scope_command("t", &m, TIP).unwrap_err();
                assert!(
                    matches!(e, InputError::NonFinite { index, .. } if index == i),
                    "{i}: {e}"
                );
            }
        }
    }

    #[test]
    fn a_zero_stamp_counts_from_the_arrival() {
        let mut m = scope_twist(ros_time(12.5), TIP, &cmd());
        assert_eq!(scope_stamp(&m, 99.0), 12.5);
        m.header.stamp = rosrust::Time::new();
        assert_eq!(scope_stamp(&m, 99.0), 99.0);
    }
}
