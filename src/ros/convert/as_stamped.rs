//! A `trajectory_msgs/JointTrajectory` that goes out with its `header.stamp` as set, a zero
//! stamp included.
//!
//! rosrust's `Publisher::send` calls the message's `set_header`, and the generated one
//! (rosrust_codegen `msg.rs`, for every message with a `header`) replaces a zero stamp with
//! the publisher's clock ("if self.header.stamp.nanos() == 0 { self.header.stamp =
//! clock.now(); }"). For a trajectory command that turns the driver's "start at the next
//! update" (`header.stamp` 0, ros_controllers' `joint_trajectory_msg_utils.h`, `startTime`)
//! into the controller's step time, which a driver clock ahead of the controller's makes due
//! before the driver's next update: the trajectory controller drops it
//! ([`crate::ros::trajectory`]). [`AsStamped`] has the same type, definition, md5 sum and wire
//! bytes, and a `set_header` that numbers the message (`seq`, as rosrust's does) and leaves
//! the stamp alone.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use crate::ros::msgs::trajectory_msgs::JointTrajectory;

/// A joint trajectory published with exactly its stamp (see the module doc).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct AsStamped(pub JointTrajectory);

impl rosrust::RosMsg for AsStamped {
    fn encode<W: std::io::Write>(&self, w: W) -> std::io::Result<()> {
        self.0.encode(w)
    }

    fn decode<R: std::io::Read>(r: R) -> std::io::Result<Self> {
        JointTrajectory::decode(r).map(Self)
    }
}

impl rosrust::Message for AsStamped {
    fn msg_definition() -> String {
        JointTrajectory::msg_definition()
    }

    fn md5sum() -> String {
        JointTrajectory::md5sum()
    }

    fn msg_type() -> String {
        JointTrajectory::msg_type()
    }

    fn set_header(&mut self, _clock: &Arc<dyn rosrust::Clock>, seq: &Arc<AtomicUsize>) {
        if self.0.header.seq == 0 {
            self.0.header.seq = seq.fetch_add(1, Ordering::SeqCst) as u32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rosrust::{Message, RosMsg};

    /// A clock that reads 5 s.
    struct FiveSeconds;

    impl rosrust::Clock for FiveSeconds {
        fn now(&self) -> rosrust::Time {
            rosrust::Time::from_nanos(5_000_000_000)
        }
        fn sleep(&self, _d: rosrust::Duration) {}
        fn wait_until(&self, _t: rosrust::Time) {}
    }

    #[test]
    fn a_zero_stamp_goes_out_zero_where_rosrust_fills_in_its_clock() {
        let clock: Arc<dyn rosrust::Clock> = Arc::new(FiveSeconds);
        let seq = Arc::new(AtomicUsize::new(7));
        // rosrust's own: the zero stamp becomes the clock's time.
        let mut plain = JointTrajectory::default();
        plain.set_header(&clock, &seq);
        assert_eq!(plain.header.stamp.sec, 5, "rosrust fills a zero stamp");
        let mut ours = AsStamped::default();
        ours.set_header(&clock, &seq);
        assert_eq!((ours.0.header.stamp.sec, ours.0.header.stamp.nsec), (0, 0));
        assert_eq!(ours.0.header.seq, 8, "numbered as rosrust numbers");
        // The same type and bytes on the wire.
        assert_eq!(AsStamped::md5sum(), JointTrajectory::md5sum());
        assert_eq!(AsStamped::msg_type(), "trajectory_msgs/JointTrajectory");
        plain.header = ours.0.header.clone();
        assert_eq!(ours.encode_vec().unwrap(), plain.encode_vec().unwrap());
        assert_eq!(AsStamped::decode_slice(&plain.encode_vec().unwrap()).unwrap(), ours);
    }
}
