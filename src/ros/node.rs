//! What every node shares: the start-up error type, the command message choice, and small
//! helpers around rosrust.

use std::sync::{Mutex, MutexGuard};

use super::msgs::std_srvs;
use super::params;

/// How a joint command travels (the driver's two controller types).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CommandType {
    /// trajectory_msgs/JointTrajectory with one point (a joint trajectory controller).
    Trajectory,
    /// std_msgs/Float64MultiArray (a JointGroupPositionController).
    Float64MultiArray,
}

/// What a trajectory command's `header.stamp` is. The driver's `joint_trajectory_controller`
/// starts a message at its stamp, or at its own next update when the stamp is 0, and drops a
/// message whose point is due at or before that update ([`crate::ros::trajectory`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CommandStamp {
    /// 0: each point is due `time_from_start` after the driver's next update, on the
    /// driver's own clock: never dropped, whatever the two clocks read.
    NextUpdate,
    /// The control step's time: the point is due at a fixed time after the step, on the
    /// controller's clock; dropped once the transport, the driver's period and the driver's
    /// clock lead take up `time_from_start` (the preflight's `DRIVER_CLOCK` check).
    Step,
}

/// Errors that stop a node at start-up (the loops themselves never stop on bad data).
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// Parameters.
    #[error(transparent)]
    Params(#[from] params::ParamError),
    /// The kinematic chain.
    #[error("kinematics: {0}")]
    Kinematics(#[from] crate::kinematics::KinematicsError),
    /// rosrust (master, topics, services).
    #[error("ros: {0}")]
    Ros(String),
    /// A parameter value is out of range, or a module refused its configuration.
    #[error("{0}")]
    Invalid(String),
}

impl From<crate::validate::RangeError> for NodeError {
    fn from(e: crate::validate::RangeError) -> Self {
        Self::Params(e.into())
    }
}

/// A rosrust error as a [`NodeError`].
pub fn ros_err<E: std::fmt::Display>(e: E) -> NodeError {
    NodeError::Ros(e.to_string())
}

/// Lock a mutex shared with a subscriber callback. A poisoned lock (a callback panicked)
/// still holds the last data written, which is what the loop wants.
pub fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Lets a repeated log line through at most once per period; shareable by callbacks.
#[derive(Debug)]
pub struct Throttle {
    period: std::time::Duration,
    last: Mutex<Option<std::time::Instant>>,
}

impl Throttle {
    /// At most once per `period`.
    pub fn new(period: std::time::Duration) -> Self {
        Self {
            period,
            last: Mutex::new(None),
        }
    }

    /// True (and the period restarts) when the last `true` is at least a period ago.
    pub fn ready(&self) -> bool {
        let now = std::time::Instant::now();
        let mut last = lock(&self.last);
        if last.is_some_and(|t| now.duration_since(t) < self.period) {
            return false;
        }
        *last = Some(now);
        true
    }
}

/// The `main` of a node binary: connect to the master as `name`, run `run`, and exit with
/// 2 when there is no master, 1 (with the error logged and printed) when `run` fails.
pub fn node_main(name: &str, run: fn() -> Result<(), NodeError>) -> ! {
    if let Err(e) = rosrust::try_init(name) {
        eprintln!("{name}: cannot reach the ROS master: {e}");
        std::process::exit(2);
    }
    if let Err(e) = run() {
        rosrust::ros_err!("{name}: {e}");
        eprintln!("{name}: {e}");
        std::process::exit(1);
    }
    std::process::exit(0)
}

/// A service reply: `Ok` is a success, `Err` a refusal, each with its message.
pub type Reply = Result<String, String>;

/// A `std_srvs/Trigger` service answering with `handler`'s reply (logged; `Err` is a
/// refusal).
pub fn reply_service<F>(name: &str, handler: F) -> Result<rosrust::Service, NodeError>
where
    F: Fn() -> Reply + Send + Sync + 'static,
{
    let label = name.to_string();
    rosrust::service::<std_srvs::Trigger, _>(name, move |_req| {
        let r = handler();
        match &r {
            Ok(m) => {
                rosrust::ros_info!("{label}: {m}");
            }
            Err(m) => {
                rosrust::ros_warn!("{label} refused: {m}");
            }
        }
        let (success, message) = match r {
            Ok(m) => (true, m),
            Err(m) => (false, m),
        };
        Ok(std_srvs::TriggerRes { success, message })
    })
    .map_err(ros_err)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn throttle_lets_one_through_per_period() {
        let t = Throttle::new(std::time::Duration::from_millis(50));
        assert!(t.ready());
        assert!(!t.ready());
        std::thread::sleep(std::time::Duration::from_millis(60));
        assert!(t.ready());
    }
}
