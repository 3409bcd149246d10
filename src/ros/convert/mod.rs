//! Conversions between ROS messages and the core's nalgebra types, with every check a
//! message from the wire needs: joint names and count, finite values, frames, unit
//! quaternions, stamps that move forward. A bad message becomes an [`InputError`] whose text
//! the node logs and hands to the supervisor as the hold reason. [`image`] converts camera
//! images and intrinsics, [`scope`] the surgeon's scope commands.

pub mod as_stamped;
pub mod image;
pub mod scope;

pub use as_stamped::AsStamped;

pub use scope::{scope_command, scope_stamp, scope_twist};

use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::kinematics::{JointVector, N_JOINTS};
use crate::ros::msgs::{geometry_msgs, lbr_msgs, sensor_msgs, std_msgs, trajectory_msgs};

/// Why an incoming message was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InputError {
    /// An array has the wrong length.
    #[error("{topic}: {field} has {got} values, expected {expected}")]
    WrongCount {
        /// Topic (or message) concerned.
        topic: String,
        /// Field concerned.
        field: &'static str,
        /// Expected length.
        expected: usize,
        /// Received length.
        got: usize,
    },
    /// A joint the arm needs is missing from the message.
    #[error("{topic}: joint {name} missing (got {got:?})")]
    MissingJoint {
        /// Topic concerned.
        topic: String,
        /// The missing joint.
        name: String,
        /// The names received.
        got: Vec<String>,
    },
    /// A value is NaN or infinite.
    #[error("{topic}: {field}[{index}] is not finite")]
    NonFinite {
        /// Topic concerned.
        topic: String,
        /// Field concerned.
        field: &'static str,
        /// Index of the value.
        index: usize,
    },
    /// The pose is in another frame than expected.
    #[error("{topic}: frame '{got}', expected '{expected}'")]
    WrongFrame {
        /// Topic concerned.
        topic: String,
        /// Expected frame.
        expected: String,
        /// Received frame.
        got: String,
    },
    /// The orientation is not a unit quaternion.
    #[error("{topic}: quaternion norm {norm:.3} is not 1")]
    BadQuaternion {
        /// Topic concerned.
        topic: String,
        /// Its norm.
        norm: f64,
    },
    /// The stamp is not newer than the previous message's.
    #[error("{topic}: stamp {got:.6} s is not after the previous {previous:.6} s")]
    OutOfOrder {
        /// Topic concerned.
        topic: String,
        /// Previous stamp, s.
        previous: f64,
        /// This stamp, s.
        got: f64,
    },
}

/// A ROS time as seconds.
pub fn seconds(t: rosrust::Time) -> f64 {
    t.seconds()
}

/// Seconds as a ROS time (negative or non-finite -> 0).
pub fn ros_time(s: f64) -> rosrust::Time {
    if s.is_finite() && s > 0.0 {
        rosrust::Time::from_nanos((s * 1e9).round() as i64)
    } else {
        rosrust::Time::new()
    }
}

fn check_finite(topic: &str, field: &'static str, v: &[f64]) -> Result<(), InputError> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(index) => Err(InputError::NonFinite {
            topic: topic.to_string(),
            field,
            index,
        }),
        None => Ok(()),
    }
}

fn joint_vector(topic: &str, field: &'static str, v: &[f64]) -> Result<JointVector, InputError> {
    if v.len() != N_JOINTS {
        return Err(InputError::WrongCount {
            topic: topic.to_string(),
            field,
            expected: N_JOINTS,
            got: v.len(),
        });
    }
    check_finite(topic, field, v)?;
    Ok(JointVector::from_column_slice(v))
}

/// Joint positions in the order of `names`, picked by name from a JointState.
pub fn joint_positions(
    topic: &str,
    msg: &sensor_msgs::JointState,
    names: &[String],
) -> Result<JointVector, InputError> {
    if msg.name.len() != msg.position.len() {
        return Err(InputError::WrongCount {
            topic: topic.to_string(),
            field: "position",
            expected: msg.name.len(),
            got: msg.position.len(),
        });
    }
    if names.len() != N_JOINTS {
        return Err(InputError::WrongCount {
            topic: topic.to_string(),
            field: "joint_names parameter",
            expected: N_JOINTS,
            got: names.len(),
        });
    }
    let mut q = JointVector::zeros();
    for (i, want) in names.iter().enumerate() {
        let k = msg
            .name
            .iter()
            .position(|n| n == want)
            .ok_or_else(|| InputError::MissingJoint {
                topic: topic.to_string(),
                name: want.clone(),
                got: msg.name.clone(),
            })?;
        q[i] = msg.position[k];
    }
    check_finite(topic, "position", q.as_slice())?;
    Ok(q)
}

/// A JointState message of the arm.
pub fn joint_state(
    stamp: rosrust::Time,
    names: &[String],
    q: &JointVector,
    tau: &JointVector,
) -> sensor_msgs::JointState {
    sensor_msgs::JointState {
        header: header(stamp, ""),
        name: names.to_vec(),
        position: q.as_slice().to_vec(),
        velocity: Vec::new(),
        effort: tau.as_slice().to_vec(),
    }
}

/// The external joint torques of an LBRState message.
pub fn external_torques(topic: &str, msg: &lbr_msgs::LBRState) -> Result<JointVector, InputError> {
    joint_vector(topic, "external_torque", &msg.external_torque)
}

/// An LBRState message as the driver publishes it.
pub fn lbr_state(
    stamp: rosrust::Time,
    sample_time: f64,
    q: &JointVector,
    tau: &JointVector,
    tau_ext: &JointVector,
) -> lbr_msgs::LBRState {
    lbr_msgs::LBRState {
        stamp: std_msgs::Time { data: stamp },
        sample_time,
        position: q.as_slice().to_vec(),
        torque: tau.as_slice().to_vec(),
        external_torque: tau_ext.as_slice().to_vec(),
    }
}

/// Joint positions from a command: the first point of a JointTrajectory, its joints picked
/// by name in the order of `names`.
pub fn trajectory_positions(
    topic: &str,
    msg: &trajectory_msgs::JointTrajectory,
    names: &[String],
) -> Result<JointVector, InputError> {
    let point = msg.points.first().ok_or(InputError::WrongCount {
        topic: topic.to_string(),
        field: "points",
        expected: 1,
        got: 0,
    })?;
    let as_state = sensor_msgs::JointState {
        header: msg.header.clone(),
        name: msg.joint_names.clone(),
        position: point.positions.clone(),
        velocity: Vec::new(),
        effort: Vec::new(),
    };
    joint_positions(topic, &as_state, names)
}

/// Joint positions from a Float64MultiArray command (joint order of the arm).
pub fn multiarray_positions(topic: &str, msg: &std_msgs::Float64MultiArray) -> Result<JointVector, InputError> {
    joint_vector(topic, "data", &msg.data)
}

/// A one-point JointTrajectory reaching `q` after `time_from_start` seconds, published with
/// exactly `stamp` (0 included: [`AsStamped`]).
pub fn trajectory_command(stamp: rosrust::Time, names: &[String], q: &JointVector, time_from_start: f64) -> AsStamped {
    AsStamped(trajectory_msgs::JointTrajectory {
        header: header(stamp, ""),
        joint_names: names.to_vec(),
        points: vec![trajectory_msgs::JointTrajectoryPoint {
            positions: q.as_slice().to_vec(),
            velocities: Vec::new(),
            accelerations: Vec::new(),
            effort: Vec::new(),
            time_from_start: rosrust::Duration::from_nanos((time_from_start.max(0.0) * 1e9) as i64),
        }],
    })
}

/// A Float64MultiArray command (JointGroupPositionController).
pub fn multiarray_command(q: &JointVector) -> std_msgs::Float64MultiArray {
    std_msgs::Float64MultiArray {
        layout: std_msgs::MultiArrayLayout::default(),
        data: q.as_slice().to_vec(),
    }
}

/// Frame names equal up to a leading '/'.
pub fn same_frame(a: &str, b: &str) -> bool {
    a.trim_start_matches('/') == b.trim_start_matches('/')
}

/// A pose from a PoseStamped that must be in `frame`, with a unit quaternion (within 1%,
/// then normalised) and finite values.
pub fn pose_in_frame(topic: &str, msg: &geometry_msgs::PoseStamped, frame: &str) -> Result<Isometry3<f64>, InputError> {
    if !same_frame(&msg.header.frame_id, frame) {
        return Err(InputError::WrongFrame {
            topic: topic.to_string(),
            expected: frame.to_string(),
            got: msg.header.frame_id.clone(),
        });
    }
    pose(topic, &msg.pose)
}

/// A pose from a Pose message (finite, unit quaternion within 1%).
pub fn pose(topic: &str, p: &geometry_msgs::Pose) -> Result<Isometry3<f64>, InputError> {
    let (t, o) = (&p.position, &p.orientation);
    check_finite(topic, "pose", &[t.x, t.y, t.z, o.x, o.y, o.z, o.w])?;
    let q = Quaternion::new(o.w, o.x, o.y, o.z);
    let norm = q.norm();
    if (norm - 1.0).abs() > 0.01 {
        return Err(InputError::BadQuaternion {
            topic: topic.to_string(),
            norm,
        });
    }
    Ok(Isometry3::from_parts(
        Translation3::new(t.x, t.y, t.z),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// A std_msgs/Header.
pub fn header(stamp: rosrust::Time, frame: &str) -> std_msgs::Header {
    std_msgs::Header {
        seq: 0,
        stamp,
        frame_id: frame.to_string(),
    }
}

/// A PointStamped of `p` in `frame`.
pub fn point_stamped(stamp: rosrust::Time, frame: &str, p: &Point3<f64>) -> geometry_msgs::PointStamped {
    geometry_msgs::PointStamped {
        header: header(stamp, frame),
        point: point_msg(p),
    }
}

/// A Point message.
pub fn point_msg(p: &Point3<f64>) -> geometry_msgs::Point {
    geometry_msgs::Point { x: p.x, y: p.y, z: p.z }
}

/// A Vector3 message.
pub fn vector_msg(v: &Vector3<f64>) -> geometry_msgs::Vector3 {
    geometry_msgs::Vector3 { x: v.x, y: v.y, z: v.z }
}

/// A Quaternion message.
pub fn quaternion_msg(q: &UnitQuaternion<f64>) -> geometry_msgs::Quaternion {
    geometry_msgs::Quaternion {
        x: q.i,
        y: q.j,
        z: q.k,
        w: q.w,
    }
}

/// A Pose message.
pub fn pose_msg(p: &Isometry3<f64>) -> geometry_msgs::Pose {
    geometry_msgs::Pose {
        position: point_msg(&Point3::from(p.translation.vector)),
        orientation: quaternion_msg(&p.rotation),
    }
}

/// A PoseStamped message.
pub fn pose_stamped(stamp: rosrust::Time, frame: &str, p: &Isometry3<f64>) -> geometry_msgs::PoseStamped {
    geometry_msgs::PoseStamped {
        header: header(stamp, frame),
        pose: pose_msg(p),
    }
}

/// A TransformStamped of `child` in `parent`.
pub fn transform_stamped(
    stamp: rosrust::Time,
    parent: &str,
    child: &str,
    p: &Isometry3<f64>,
) -> geometry_msgs::TransformStamped {
    geometry_msgs::TransformStamped {
        header: header(stamp, parent),
        child_frame_id: child.to_string(),
        transform: geometry_msgs::Transform {
            translation: vector_msg(&p.translation.vector),
            rotation: quaternion_msg(&p.rotation),
        },
    }
}

/// Rejects stamps that do not move forward on one topic.
#[derive(Debug, Clone, Default)]
pub struct StampOrder {
    last: Option<f64>,
}

impl StampOrder {
    /// Accept `stamp` (s) if it is after the last accepted one; a rejected stamp is not
    /// remembered. [`StampOrder::reset`] forgets (e.g. when a bag loops or time jumps back).
    pub fn accept(&mut self, topic: &str, stamp: f64) -> Result<(), InputError> {
        if let Some(previous) = self.last {
            if stamp <= previous {
                return Err(InputError::OutOfOrder {
                    topic: topic.to_string(),
                    previous,
                    got: stamp,
                });
            }
        }
        self.last = Some(stamp);
        Ok(())
    }

    /// Forget the last stamp.
    pub fn reset(&mut self) {
        self.last = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names() -> Vec<String> {
        crate::kinematics::joint_names()
    }

    fn state(names: Vec<String>, pos: Vec<f64>) -> sensor_msgs::JointState {
        sensor_msgs::JointState {
            name: names,
            position: pos,
            ..Default::default()
        }
    }

    #[test]
    fn joints_are_picked_by_name_in_any_order() {
        let mut n = names();
        n.reverse();
        let pos: Vec<f64> = (0..7).map(|i| 6.0 - i as f64).collect();
        let q = joint_positions("t", &state(n, pos), &names()).unwrap();
        assert_eq!(q.as_slice(), &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
    }

    #[test]
    fn bad_joint_states_are_rejected_with_a_reason() {
        let e = joint_positions("t", &state(names()[..6].to_vec(), vec![0.0; 6]), &names()).unwrap_err();
        assert!(
            matches!(e, InputError::MissingJoint { ref name, .. } if *name == crate::kinematics::joint_name(7)),
            "{e}"
        );
        let e = joint_positions("t", &state(names(), vec![0.0; 6]), &names()).unwrap_err();
        assert!(matches!(e, InputError::WrongCount { got: 6, .. }));
        let mut p = vec![0.0; 7];
        p[3] = f64::NAN;
        let e = joint_positions("t", &state(names(), p), &names()).unwrap_err();
        assert!(matches!(e, InputError::NonFinite { index: 3, .. }));
        let mut other = names();
        other[0] = "A1".into();
        assert!(joint_positions("t", &state(other, vec![0.0; 7]), &names()).is_err());
    }

    #[test]
    fn torques_need_seven_finite_values() {
        let q = JointVector::from_element(0.1);
        let msg = lbr_state(ros_time(1.0), 0.005, &q, &q, &q);
        assert_eq!(external_torques("t", &msg).unwrap(), q);
        let mut short = msg.clone();
        short.external_torque.pop();
        assert!(external_torques("t", &short).is_err());
        let mut nan = msg;
        nan.external_torque[0] = f64::INFINITY;
        assert!(external_torques("t", &nan).is_err());
    }

    #[test]
    fn poses_round_trip_and_bad_ones_are_rejected() {
        let p = Isometry3::new(Vector3::new(0.5, -0.1, 0.3), Vector3::new(0.2, -0.4, 1.0));
        let m = pose_stamped(ros_time(2.5), "lbr_link_0", &p);
        let back = pose_in_frame("t", &m, "/lbr_link_0").unwrap();
        assert!((back.translation.vector - p.translation.vector).norm() < 1e-12);
        assert!(back.rotation.angle_to(&p.rotation) < 1e-9);
        assert!(matches!(
            pose_in_frame("t", &m, "world"),
            Err(InputError::WrongFrame { .. })
        ));
        let mut bad = m.clone();
        bad.pose.orientation.w *= 2.0;
        assert!(matches!(
            pose_in_frame("t", &bad, "lbr_link_0"),
            Err(InputError::BadQuaternion { .. })
        ));
        bad = m;
        bad.pose.position.y = f64::NAN;
        assert!(matches!(
            pose_in_frame("t", &bad, "lbr_link_0"),
            Err(InputError::NonFinite { .. })
        ));
    }

    #[test]
    fn commands_round_trip() {
        let q = JointVector::from_fn(|i, _| 0.1 * i as f64);
        let traj = trajectory_command(ros_time(3.0), &names(), &q, 0.01);
        assert_eq!(trajectory_positions("t", &traj.0, &names()).unwrap(), q);
        assert_eq!(traj.0.header.stamp, ros_time(3.0));
        assert_eq!(multiarray_positions("t", &multiarray_command(&q)).unwrap(), q);
        let empty = trajectory_msgs::JointTrajectory::default();
        assert!(trajectory_positions("t", &empty, &names()).is_err());
    }

    #[test]
    fn stamps_must_move_forward() {
        let mut o = StampOrder::default();
        o.accept("t", 1.0).unwrap();
        assert!(matches!(o.accept("t", 1.0), Err(InputError::OutOfOrder { .. })));
        assert!(o.accept("t", 0.5).is_err());
        o.accept("t", 1.1).unwrap();
        o.reset();
        o.accept("t", 0.2).unwrap();
        assert_eq!(seconds(ros_time(12.25)), 12.25);
        assert_eq!(ros_time(f64::NAN), rosrust::Time::new());
    }
}
