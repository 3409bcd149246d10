//! What every check shares: the test node's parameters, a latest-message subscriber,
//! bounded waits and service calls.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use ::trocar_docking::ros::msgs::std_srvs;
use ::trocar_docking::ros::topics;
use ::trocar_docking::validate::{self, RangeError};

/// Settings of the test node (private parameters), every bound a parameter.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CheckParams {
    /// The controller node's name (its services are `<name>/start` etc.).
    pub controller: String,
    /// Status topic.
    pub status_topic: String,
    /// Command topic (JointTrajectory).
    pub command_topic: String,
    /// The controller's stamped copy of each command (sensor_msgs/JointState).
    pub command_joints_topic: String,
    /// Wall-clock limit for the whole docking, s.
    pub time_limit: f64,
    /// Upper bound on M (N) for a successful docking.
    pub max_metric_m: f64,
    /// Upper bound on the peak force estimate over the docking (N).
    pub max_force: f64,
    /// Wall time to wait for the graph (services, first messages), s.
    pub startup_timeout: f64,
    /// `docking`: the largest accepted RMS speed of the tip (from the measured joints)
    /// during INSERT, m/s (0 = not checked).
    pub max_tip_rms_speed: f64,
    /// `docking`: the simulator's command stream (its counts on `/diagnostics`, as the
    /// driver's trajectory controller met it) must hold at least this many moving commands
    /// and no dropped one (0 = not checked).
    pub min_moving_commands: u64,
    /// Whether the check calls `~start` itself.
    pub call_start: bool,
    /// For `stale_hold`: the hold's code (`hold_code` of the status) must be this.
    pub hold_code: String,
    /// For `docking`, `dry_run`: the status `hold_code` at DONE must be this ('' = anything,
    /// e.g. `SEATED`, `DEPTH_UNVERIFIED`).
    pub done_code: String,
    /// `docking`: a hold DEPTH_UNCERTAIN at the goal is accepted once by `~start`, as the
    /// surgeon does after checking the depth in the endoscope's view, and DONE expected
    /// after it (false: that hold fails the docking).
    pub accept_depth_uncertain: bool,
    /// `docking`: as `accept_depth_uncertain`, but only a hold whose depth rests on a seal
    /// met and refused (`depth_basis` REFUSED: farther off the estimate than the calibration
    /// explains); a seal never felt still fails the docking.
    pub accept_refused_seal: bool,
    /// `docking`: as `accept_depth_uncertain`, but only a hold whose depth was refined at the
    /// seal (`depth_basis` SEAL) with a figure within [`SEAL_EDGE_FACTOR`] times the
    /// controller's tolerance: the gate's caution at its edge (the seal's spread and the tip's
    /// distance from a breathing port's goal); a seal never felt, or refused, still fails.
    pub accept_seal_edge: bool,
    /// `stale_hold`, `bad_input`: how long the command must stay still once held, s.
    pub hold_observe: f64,
    /// `bad_input`: the largest accepted motion of a joint (the arm's, the command's) once
    /// held, deg.
    pub max_hold_motion_deg: f64,
    /// For `replay`: the minimum number of status messages expected.
    pub min_status: usize,
    /// For `replay`: the phases the controller may report.
    pub allowed_phases: Vec<String>,
    /// `replay_controller`: the recorded controller's status (the bag's, remapped).
    pub recorded_status_topic: String,
    /// `replay_controller`: the recorded controller's commands (the bag's, remapped).
    pub recorded_command_topic: String,
    /// `replay_controller`: the fewest commands the live controller must publish.
    pub min_commands: usize,
    /// For `replay`: the estimated trocar pose topic.
    pub pose_topic: String,
    /// For `replay`: the recorded true trocar pose topic.
    pub true_pose_topic: String,
    /// `scope_pivot`: the simulator's true fulcrum (where the wall holds the trocar).
    pub true_fulcrum_topic: String,
    /// For `replay`: the largest accepted distance between estimate and truth, m.
    pub max_position_error: f64,
    /// `replay`: trocar poses the check must see before it judges.
    pub min_poses: usize,
    /// `replay`: a HOLD with this code is accepted too ('' = none is), e.g. the tracking
    /// hold (`TRACKING_ERROR`) when a bag's arm does not follow the live commands.
    pub allowed_hold_code: String,
    /// `latency`: the camera calibration YAML of the played camera.
    pub camera_calibration: String,
    /// `latency`: the played camera's rate, Hz.
    pub camera_rate_hz: f64,
    /// `latency`: the largest accepted 99th percentile of image -> command, ms.
    pub max_latency_ms: f64,
    /// `latency`: the largest accepted median of image -> command, ms.
    pub max_latency_p50_ms: f64,
    /// `docking`: the largest accepted 99th percentile of the controller's own latency, a
    /// trocar pose's capture to the command that used it, over the docking, ms (0 = not
    /// checked).
    pub max_pose_latency_p99_ms: f64,
    /// `docking`: a node beside the test node (`__name:=` this) stopped `starve_stop_s` of
    /// every `starve_period_s` of wall time while the docking runs, as a host too busy to
    /// run it does ('' = none; [`crate::starve`]).
    pub starve_node: String,
    /// How long each stop of `starve_node` lasts, s.
    pub starve_stop_s: f64,
    /// How often `starve_node` is stopped, s.
    pub starve_period_s: f64,
    /// `latency`: where to write the run's figures as one JSON object ('' = nowhere), for
    /// `scripts/measure-latency`.
    pub json_out: String,
    /// Failure modes: the largest accepted lead of the command over the measured joints, deg.
    pub max_lead_deg: f64,
    /// `blocked_arm`: the largest accepted delay of the hold after the lead bound, s.
    pub max_hold_delay_s: f64,
    /// Failure modes: the largest accepted step between commands after a new start, deg.
    pub max_step_deg: f64,
    /// The controller's rate, Hz.
    pub control_rate_hz: f64,
    /// `flood`: how many times the nominal rate every input gets.
    pub flood_factor: f64,
    /// `flood`: the accepted relative deviation of the control loop's rate.
    pub rate_tolerance: f64,
    /// `flood`: the largest accepted RSS growth of a node, MB.
    pub max_rss_growth_mb: f64,
    /// `scope_pivot`: the scope command topic (TwistStamped).
    pub scope_command_topic: String,
    /// `scope_pivot`: the frame of the scope commands.
    pub tip_frame: String,
    /// `scope_pivot`: the measured joint states.
    pub joint_states_topic: String,
    /// `scope_pivot`: the URDF whose KDL chain gives the shaft ('' = the built-in Med 7).
    pub urdf_file: String,
    /// `scope_pivot`: ROS time between DONE and the first command, s.
    pub settle_s: f64,
    /// `scope_pivot`: the rate of the scope commands, Hz.
    pub scope_rate_hz: f64,
    /// `scope_pivot`: pan and tilt speed (rad/s) and how long each lasts (s).
    pub pan_speed: f64,
    /// See `pan_speed`.
    pub pan_time: f64,
    /// `scope_pivot`: in and out speed (m/s) and how long each lasts (s).
    pub zoom_speed: f64,
    /// See `zoom_speed`.
    pub zoom_time: f64,
    /// `scope_pivot`: the largest accepted p95 distance of the shaft from the true port
    /// (the true fulcrum, where the wall holds the trocar), m.
    pub max_shaft_distance: f64,
    /// `scope_pivot`: the smallest accepted sweep of the shaft, deg.
    pub min_sweep_deg: f64,
    /// `scope_pivot`: the largest accepted mean of the status `lateral_force` (the force
    /// estimate across the shaft) while commanded, N.
    pub max_mean_force: f64,
    /// `scope_pivot`: the controller's dead-man timeout (`scope.command_timeout_s`), s.
    pub command_timeout: f64,
    /// `scope_pivot`: time past the dead-man timeout for the scope to stop, s.
    pub dead_man_margin_s: f64,
    /// `scope_pivot`: the largest accepted tip motion once stopped, m.
    pub max_still_motion: f64,
    /// `scope_pivot`: the largest accepted turn of the shaft under bad commands, deg.
    pub max_bad_turn_deg: f64,
    /// `scope_pivot`: how long the tip must stay still, s.
    pub still_window_s: f64,
    /// `scope_pivot`: wall time for `~retract` to reach IDLE, s.
    pub retract_timeout: f64,
    /// `scope_joy`: the joystick node's YAML (its mapping, rate, topics).
    pub joy_config: String,
    /// `preflight`: the check that must fail ('' = every check must pass).
    pub preflight_failure: String,
    /// `preflight`: a check that must pass, not be skipped ('' = none named).
    pub preflight_pass: String,
    /// `reconfigure`: the force stop set through dynparam, N.
    pub reconfigure_force_stop: f64,
    /// `dry_run`: the controller's commands in a dry run (JointTrajectory).
    pub preview_topic: String,
    /// `dry_run`: the ghost arm's joints.
    pub preview_joint_states_topic: String,
    /// `docking`: the largest accepted distance at DONE of the true port from the estimated
    /// insertion axis (`pose_topic` against `true_pose_topic`), m (0 = not checked).
    pub max_axis_error_m: f64,
    /// `docking`: the largest accepted angle at DONE between the estimated insertion axis and
    /// the true port's, deg (0 = not checked).
    pub max_axis_error_deg: f64,
    /// `docking`: the sources (`marker`, `markerless`, comma-separated) that must each have
    /// had a pose published during the run, by the estimator's status lines ('' = not checked).
    pub estimator_published: String,
    /// `docking`: the estimator's status topic (std_msgs/String, one line per frame).
    pub estimator_status_topic: String,
    /// `hand_eye`: the calibration node's name (its services are `<name>/auto` etc.).
    pub hand_eye_node: String,
    /// `hand_eye`: the file the node's `~save` writes.
    pub hand_eye_output: String,
    /// `hand_eye`: the largest accepted distance of the computed mount from the true one, m.
    pub max_mount_error_m: f64,
    /// `hand_eye`: the largest accepted rotation of the computed mount from the true one, deg.
    pub max_mount_error_deg: f64,
    /// `hand_eye`: the world's target moves (breathing): `~auto` must name it.
    pub expect_target_moving: bool,
    /// `replay_fault`: where the bag's fault begins, s after the recorded APPROACH.
    pub fault_after_s: f64,
    /// `replay_controller`, `replay_fault`: the recorded docking the check plays itself
    /// ([`crate::bag_sync`]).
    pub bag: String,
    /// The remapping arguments of its player (`from:=to`).
    pub bag_remaps: Vec<String>,
    /// How long before the recorded APPROACH the live one begins, s ([`crate::bag_sync`]).
    pub start_lead_s: f64,
}

/// A parameter of the controller node's `controller` tree, as the node loaded it: `name`
/// is its path there (`depth/tolerance_m`).
pub fn controller_param(p: &CheckParams, name: &str) -> Result<f64, String> {
    let key = format!("{}/controller/{name}", p.controller);
    rosrust::param(&key)
        .ok_or_else(|| format!("bad name {key}"))?
        .get()
        .map_err(|e| format!("{key}: {e}"))
}

impl Default for CheckParams {
    // A table of every check's defaults, one line each: data, not logic.
    #[allow(clippy::too_many_lines)]
    fn default() -> Self {
        Self {
            controller: "/docking_controller".into(),
            status_topic: topics::DOCKING_STATUS.into(),
            command_topic: topics::COMMAND.into(),
            command_joints_topic: topics::DOCKING_COMMAND_JOINTS.into(),
            time_limit: 60.0,
            max_metric_m: 10.0,
            max_force: 60.0,
            startup_timeout: 30.0,
            max_tip_rms_speed: 0.0,
            min_moving_commands: 0,
            call_start: true,
            hold_code: "STALE_TROCAR_POSE".into(),
            done_code: String::new(),
            accept_depth_uncertain: false,
            accept_refused_seal: false,
            accept_seal_edge: false,
            hold_observe: 1.0,
            max_hold_motion_deg: 0.01,
            min_status: 10,
            allowed_phases: vec!["HOLD".into(), "APPROACH".into(), "INSERT".into(), "DONE".into()],
            recorded_status_topic: "/recorded/docking/status".into(),
            recorded_command_topic: "/recorded/command".into(),
            min_commands: 1,
            pose_topic: topics::TROCAR_POSE.into(),
            true_pose_topic: topics::TROCAR_POSE_TRUE.into(),
            true_fulcrum_topic: topics::TROCAR_FULCRUM_TRUE.into(),
            max_position_error: 0.01,
            min_poses: 1,
            allowed_hold_code: String::new(),
            camera_calibration: String::new(),
            camera_rate_hz: 30.0,
            max_latency_ms: 10.0,
            max_latency_p50_ms: 10.0,
            max_pose_latency_p99_ms: 0.0,
            starve_node: String::new(),
            starve_stop_s: 0.2,
            starve_period_s: 0.6,
            json_out: String::new(),
            max_lead_deg: 2.0,
            max_hold_delay_s: 0.2,
            max_step_deg: 1.0,
            control_rate_hz: 100.0,
            flood_factor: 10.0,
            rate_tolerance: 0.01,
            max_rss_growth_mb: 2.0,
            scope_command_topic: topics::SCOPE_COMMAND.into(),
            tip_frame: ::trocar_docking::kinematics::TIP_LINK.into(),
            joint_states_topic: topics::JOINT_STATES.into(),
            urdf_file: String::new(),
            settle_s: 1.0,
            scope_rate_hz: 50.0,
            pan_speed: 0.17,
            pan_time: 2.0,
            zoom_speed: 0.01,
            zoom_time: 1.0,
            max_shaft_distance: 0.001,
            min_sweep_deg: 15.0,
            max_mean_force: 1.0,
            command_timeout: 0.2,
            dead_man_margin_s: 0.1,
            max_still_motion: 0.0005,
            max_bad_turn_deg: 1.0,
            still_window_s: 2.0,
            retract_timeout: 30.0,
            joy_config: String::new(),
            preflight_failure: String::new(),
            preflight_pass: String::new(),
            reconfigure_force_stop: 1.0,
            preview_topic: "/docking_controller/preview".into(),
            preview_joint_states_topic: "/docking_controller/preview_joint_states".into(),
            max_axis_error_m: 0.0,
            max_axis_error_deg: 0.0,
            estimator_published: String::new(),
            estimator_status_topic: "/trocar_estimator/status".into(),
            hand_eye_node: "/hand_eye_calibration".into(),
            hand_eye_output: String::new(),
            max_mount_error_m: 0.0005,
            max_mount_error_deg: 0.2,
            expect_target_moving: false,
            fault_after_s: 0.5,
            bag: String::new(),
            bag_remaps: Vec::new(),
            start_lead_s: 0.05,
        }
    }
}

impl CheckParams {
    /// Check every bound and duration once, before a check runs: a bad one fails the check
    /// with its key named, instead of a panic in `Duration::from_secs_f64` mid-test.
    pub fn validate(&self) -> Result<(), RangeError> {
        validate::duration("time_limit", self.time_limit)?;
        validate::duration("startup_timeout", self.startup_timeout)?;
        validate::non_negative("hold_observe", self.hold_observe)?;
        validate::non_negative("start_lead_s", self.start_lead_s)?;
        validate::positive("max_metric_m", self.max_metric_m)?;
        validate::positive("max_hold_motion_deg", self.max_hold_motion_deg)?;
        validate::non_negative("max_tip_rms_speed", self.max_tip_rms_speed)?;
        validate::positive("max_force", self.max_force)?;
        validate::positive("max_position_error", self.max_position_error)?;
        validate::period_of_rate("camera_rate_hz", self.camera_rate_hz)?;
        validate::positive("max_latency_ms", self.max_latency_ms)?;
        validate::positive("max_latency_p50_ms", self.max_latency_p50_ms)?;
        validate::non_negative("max_pose_latency_p99_ms", self.max_pose_latency_p99_ms)?;
        validate::positive("max_lead_deg", self.max_lead_deg)?;
        validate::positive("max_hold_delay_s", self.max_hold_delay_s)?;
        validate::positive("max_step_deg", self.max_step_deg)?;
        validate::period_of_rate("control_rate_hz", self.control_rate_hz)?;
        validate::positive_at_most("flood_factor", self.flood_factor, 100.0)?;
        validate::positive("rate_tolerance", self.rate_tolerance)?;
        validate::positive("max_rss_growth_mb", self.max_rss_growth_mb)?;
        validate::non_negative("settle_s", self.settle_s)?;
        validate::period_of_rate("scope_rate_hz", self.scope_rate_hz)?;
        validate::positive("pan_speed", self.pan_speed)?;
        validate::positive("pan_time", self.pan_time)?;
        validate::positive("zoom_speed", self.zoom_speed)?;
        validate::positive("zoom_time", self.zoom_time)?;
        validate::positive("max_shaft_distance", self.max_shaft_distance)?;
        validate::positive("min_sweep_deg", self.min_sweep_deg)?;
        validate::positive("max_mean_force", self.max_mean_force)?;
        validate::positive("command_timeout", self.command_timeout)?;
        validate::non_negative("dead_man_margin_s", self.dead_man_margin_s)?;
        validate::positive("max_still_motion", self.max_still_motion)?;
        validate::positive("max_bad_turn_deg", self.max_bad_turn_deg)?;
        validate::duration("still_window_s", self.still_window_s)?;
        validate::duration("retract_timeout", self.retract_timeout)?;
        validate::positive("reconfigure_force_stop", self.reconfigure_force_stop)?;
        validate::non_negative("max_axis_error_m", self.max_axis_error_m)?;
        validate::non_negative("max_axis_error_deg", self.max_axis_error_deg)?;
        validate::positive("max_mount_error_m", self.max_mount_error_m)?;
        validate::positive("max_mount_error_deg", self.max_mount_error_deg)?;
        Ok(())
    }
}

/// CPU time the hypervisor gave to others (`steal` in `/proc/stat`, all CPUs summed), s;
/// `None` where the kernel does not report it.
pub fn stolen_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let line = stat.lines().find(|l| l.starts_with("cpu "))?;
    let ticks: f64 = line.split_whitespace().nth(8)?.parse().ok()?;
    // SAFETY: sysconf only reads a configuration value.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    (hz > 0).then(|| ticks / hz as f64)
}

/// The newest message of a topic, shared between the subscriber thread and a reader.
#[derive(Debug)]
pub struct Latest<T> {
    slot: Arc<Mutex<(Option<T>, usize)>>,
}

impl<T> Clone for Latest<T> {
    fn clone(&self) -> Self {
        Self {
            slot: self.slot.clone(),
        }
    }
}

impl<T> Default for Latest<T> {
    fn default() -> Self {
        Self {
            slot: Arc::new(Mutex::new((None, 0))),
        }
    }
}

impl<T: Clone> Latest<T> {
    /// Store a message.
    pub fn put(&self, msg: T) {
        if let Ok(mut s) = self.slot.lock() {
            s.0 = Some(msg);
            s.1 += 1;
        }
    }
    /// The newest message, if any.
    pub fn get(&self) -> Option<T> {
        self.slot.lock().ok().and_then(|s| s.0.clone())
    }
    /// How many messages arrived.
    pub fn count(&self) -> usize {
        self.slot.lock().map(|s| s.1).unwrap_or(0)
    }
}

/// Subscribe `topic` into a [`Latest`].
pub fn subscribe_latest<T: rosrust::Message>(topic: &str) -> Result<(Latest<T>, rosrust::Subscriber), String> {
    let latest = Latest::default();
    let l = latest.clone();
    let sub = rosrust::subscribe(topic, 10, move |m: T| l.put(m)).map_err(|e| format!("subscribe {topic}: {e}"))?;
    Ok((latest, sub))
}

/// Wait until `current` has not changed for 50 ms, at most `most` s: a hold brakes to rest
/// within the guard's acceleration limit (never an instant stop from speed), and stillness
/// is judged from rest on.
pub fn wait_until_still<T: PartialEq>(most: f64, current: impl Fn() -> T) {
    let until = Instant::now() + Duration::from_secs_f64(most);
    let mut last = current();
    loop {
        std::thread::sleep(Duration::from_millis(50));
        let now = current();
        if now == last || Instant::now() > until {
            break;
        }
        last = now;
    }
}

/// Poll `f` every 10 ms until it gives `Some` or `timeout` passes (wall clock).
pub fn wait_for<T, F: FnMut() -> Option<T>>(timeout: f64, mut f: F) -> Option<T> {
    let t0 = Instant::now();
    while t0.elapsed().as_secs_f64() < timeout && rosrust::is_ok() {
        if let Some(v) = f() {
            return Some(v);
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    None
}

/// Call a std_srvs/Trigger service, waiting for it to appear.
pub fn trigger(service: &str, timeout: f64) -> Result<String, String> {
    call_trigger(service, &trigger_client(service, timeout)?)
}

/// A client of the std_srvs/Trigger service `service`, once it has appeared (so that a
/// later call is one round trip).
pub fn trigger_client(service: &str, timeout: f64) -> Result<rosrust::Client<std_srvs::Trigger>, String> {
    rosrust::wait_for_service(service, Some(Duration::from_secs_f64(timeout)))
        .map_err(|e| format!("service {service} did not appear: {e}"))?;
    rosrust::client::<std_srvs::Trigger>(service).map_err(|e| format!("client {service}: {e}"))
}

/// Call `client` (of `service`); its message, or why it failed or refused.
pub fn call_trigger(service: &str, client: &rosrust::Client<std_srvs::Trigger>) -> Result<String, String> {
    let res = client
        .req(&std_srvs::TriggerReq {})
        .map_err(|e| format!("{service}: {e}"))?
        .map_err(|e| format!("{service}: {e}"))?;
    if res.success {
        Ok(res.message)
    } else {
        Err(format!("{service} refused: {}", res.message))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_durations_are_named() {
        CheckParams::default().validate().unwrap();
        let bad = [
            CheckParams {
                hold_observe: -1.0,
                ..Default::default()
            },
            CheckParams {
                startup_timeout: f64::NAN,
                ..Default::default()
            },
            CheckParams {
                camera_rate_hz: 0.0,
                ..Default::default()
            },
        ];
        for (p, key) in bad.iter().zip(["hold_observe", "startup_timeout", "camera_rate_hz"]) {
            assert_eq!(p.validate().unwrap_err().key, key);
        }
    }
}
