//! The `scope_joy` node: a joystick's `sensor_msgs/Joy` -> the surgeon's scope commands
//! (`geometry_msgs/TwistStamped` on `/docking/scope_command`), for the lab. Set-up, then at
//! a fixed rate: read the newest Joy, tick the pure mapping ([`crate::ros::joy`]), publish.
//! The commands are stamped with the ROS clock (simulated time under `/use_sim_time`), which
//! the controller's dead-man compares with its own; the Joy's age is measured on the wall
//! clock, so that a stopped joystick stops the scope whatever the simulated clock does.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::ros::convert;
use crate::ros::joy::{JoyParams, ScopeJoy};
use crate::ros::msgs::{geometry_msgs, sensor_msgs};
use crate::ros::node::{lock, ros_err, NodeError, Throttle};
use crate::ros::pacer::Pacer;
use crate::ros::params;

/// Run the node until shutdown. Call after `rosrust::init`.
pub fn run() -> Result<(), NodeError> {
    let p: JoyParams = params::load_private()?;
    p.validate()?;
    let newest: Arc<Mutex<Option<(sensor_msgs::Joy, Instant)>>> = Arc::default();
    let slot = newest.clone();
    let _sub = rosrust::subscribe(&p.joy_topic, 1, move |m: sensor_msgs::Joy| {
        *lock(&slot) = Some((m, Instant::now()));
    })
    .map_err(ros_err)?;
    let publ = rosrust::publish::<geometry_msgs::TwistStamped>(&p.command_topic, 1).map_err(ros_err)?;
    rosrust::ros_info!(
        "scope_joy: {} -> {} at {} Hz while button {} is held",
        p.joy_topic,
        p.command_topic,
        p.rate_hz,
        p.deadman_button
    );
    let log = Throttle::new(Duration::from_secs(2));
    let mut state = ScopeJoy::default();
    let mut pace = Pacer::new(p.rate_hz);
    while rosrust::is_ok() {
        let joy = lock(&newest).clone();
        let (cmd, err) = state.tick(&p, joy.as_ref().map(|(j, at)| (j, at.elapsed().as_secs_f64())));
        if let (Some(e), true) = (err, log.ready()) {
            rosrust::ros_warn!("scope_joy: {e}: the scope stops");
        }
        if let Some(c) = cmd {
            if let Err(e) = publ.send(convert::scope_twist(rosrust::now(), &p.frame_id, &c)) {
                rosrust::ros_err!("scope_joy: cannot publish: {e}");
            }
        }
        pace.sleep();
    }
    Ok(())
}
