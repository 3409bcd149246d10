//! The parameters of the `docking_controller` node ([`ControllerNodeParams`]) with the
//! preflight's ([`PreflightParams`], the node's `~preflight` and the `preflight` node's
//! own): one module that both the node ([`crate::ros::controller_node`]) and the preflight
//! ([`crate::ros::preflight`]) read, so that neither imports the other's parameters.

use crate::control::ControllerParams;
use crate::kinematics::lbr::LbrModel;
use crate::kinematics::TIP_LINK;
use crate::preflight::Limits;
use crate::ros::markers::MarkerStyle;
use crate::ros::node::{CommandType, NodeError};
use crate::ros::topics;
use crate::validate;

/// Parameters of the node (its private namespace; `config/docking_controller.yaml`).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControllerNodeParams {
    /// Control rate, Hz.
    pub rate_hz: f64,
    /// Arm model when `urdf_file` is empty.
    pub model: LbrModel,
    /// URDF to build the chain `lbr_link_0` -> `endoscope_tip` from ('' = built-in model).
    pub urdf_file: String,
    /// Joint names in chain order (as in the joint states and the command).
    pub joint_names: Vec<String>,
    /// Robot base frame (the trocar pose must be in it).
    pub base_frame: String,
    /// tf frame published for the trocar.
    pub trocar_frame: String,
    /// tf frame published for the goal.
    pub goal_frame: String,
    /// Joint states in.
    pub joint_states_topic: String,
    /// LBRState (external torques) in.
    pub lbr_state_topic: String,
    /// Trocar pose in.
    pub trocar_pose_topic: String,
    /// The surgeon's scope commands in (TwistStamped), after DONE.
    pub scope_command_topic: String,
    /// The frame scope commands are in (a command in another, non-empty frame is rejected).
    pub tip_frame: String,
    /// Joint command out (to the driver; never published in a dry run).
    pub command_topic: String,
    /// Dry run: the commands go to `preview_topic` (same type) instead of `command_topic`,
    /// the controller steers a ghost arm at its own commands ([`ghost`]), and the ghost's
    /// joints go out on `preview_joint_states_topic` (for a second robot_state_publisher).
    pub dry_run: bool,
    /// The dry run's commands out.
    pub preview_topic: String,
    /// The dry run's ghost joints out (`sensor_msgs/JointState`).
    pub preview_joint_states_topic: String,
    /// Message type of the command.
    pub command_type: CommandType,
    /// `time_from_start` of the trajectory point, in control periods.
    pub command_lookahead_periods: f64,
    /// Joint states that resume after a gap longer than this (s) are a driver restart: the
    /// controller holds (`DRIVER_RESTART`) until a new start. Shorter gaps hold as stale
    /// data and resume by themselves. Stamps that go back or names in another order are a
    /// restart whatever the gap.
    pub driver_restart_gap_s: f64,
    /// Status out.
    pub status_topic: String,
    /// Force out.
    pub f_ext_topic: String,
    /// Markers out.
    pub markers_topic: String,
    /// Status rate, Hz (0 = every control step).
    pub status_rate_hz: f64,
    /// Markers and tf rate, Hz.
    pub markers_rate_hz: f64,
    /// Start docking without a `~start` call (tests, demos).
    pub autostart: bool,
    /// Use the external force (admittance); false runs the controller without it.
    pub force_feedback: bool,
    /// Latency samples kept for the percentiles.
    pub latency_samples: usize,
    /// Run the control loop in the real-time class `SCHED_FIFO` at this priority (1..=99;
    /// needs CAP_SYS_NICE or an rtprio limit); 0 = normal scheduling. If it cannot be had
    /// the node warns and runs at normal priority.
    pub realtime_priority: i32,
    /// Marker sizes.
    pub markers: MarkerStyle,
    /// Run the preflight on `~start` and refuse the start when a check fails (`autostart`
    /// does not run it).
    pub preflight_on_start: bool,
    /// The preflight's settings (`~preflight`).
    pub preflight: PreflightParams,
    /// Parameters of the optimal controller (`config/controller.yaml`, loaded under
    /// `~controller`); its `dt` is set from `rate_hz` and `force_feedback` from the node's.
    pub controller: ControllerParams,
}

impl Default for ControllerNodeParams {
    fn default() -> Self {
        Self {
            rate_hz: 100.0,
            model: LbrModel::Med7,
            urdf_file: String::new(),
            joint_names: crate::kinematics::joint_names(),
            base_frame: crate::kinematics::BASE_LINK.into(),
            trocar_frame: "trocar".into(),
            goal_frame: "docking_goal".into(),
            joint_states_topic: topics::JOINT_STATES.into(),
            lbr_state_topic: topics::LBR_STATE.into(),
            trocar_pose_topic: topics::TROCAR_POSE.into(),
            scope_command_topic: topics::SCOPE_COMMAND.into(),
            tip_frame: TIP_LINK.into(),
            command_topic: topics::COMMAND.into(),
            command_type: CommandType::Trajectory,
            dry_run: false,
            preview_topic: "~preview".into(),
            preview_joint_states_topic: "~preview_joint_states".into(),
            command_lookahead_periods: 2.0,
            driver_restart_gap_s: 0.5,
            status_topic: topics::DOCKING_STATUS.into(),
            f_ext_topic: topics::DOCKING_F_EXT.into(),
            markers_topic: topics::DOCKING_MARKERS.into(),
            status_rate_hz: 0.0,
            markers_rate_hz: 20.0,
            autostart: false,
            force_feedback: true,
            latency_samples: 5000,
            realtime_priority: 0,
            markers: MarkerStyle::default(),
            preflight_on_start: true,
            preflight: PreflightParams::default(),
            controller: ControllerParams::default(),
        }
    }
}

impl ControllerNodeParams {
    /// Check every rate, count and name; the error names the key.
    pub fn validate(&self) -> Result<(), NodeError> {
        validate::positive_at_most("rate_hz", self.rate_hz, 5000.0)?;
        validate::non_negative("status_rate_hz", self.status_rate_hz)?;
        validate::non_negative("markers_rate_hz", self.markers_rate_hz)?;
        validate::positive_at_most("command_lookahead_periods", self.command_lookahead_periods, 100.0)?;
        validate::positive_at_most("driver_restart_gap_s", self.driver_restart_gap_s, 60.0)?;
        validate::integer_in_range("realtime_priority", i64::from(self.realtime_priority), 0, 99)?;
        self.preflight.validate()?;
        if self.latency_samples == 0 {
            return Err(NodeError::Invalid("latency_samples must be >= 1".into()));
        }
        if self.dry_run && (self.preview_topic.is_empty() || self.preview_topic == self.command_topic) {
            return Err(NodeError::Invalid(format!(
                "preview_topic '{}' must be set and differ from command_topic '{}': a dry run never commands the driver",
                self.preview_topic, self.command_topic
            )));
        }
        if self.joint_names.len() != crate::kinematics::N_JOINTS {
            return Err(NodeError::Invalid(format!(
                "joint_names has {} names, expected {}",
                self.joint_names.len(),
                crate::kinematics::N_JOINTS
            )));
        }
        Ok(())
    }
}

/// Settings of the preflight (the `preflight` node's private parameters; the controller's
/// `~preflight`).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PreflightParams {
    /// How long the streams are watched, s (wall time).
    pub window_s: f64,
    /// How long to wait for the first message of every stream before the window, s.
    pub wait_s: f64,
    /// The docking controller (its parameters: topics, URDF, tare limits).
    pub controller_node: String,
    /// The trocar estimator (its image topics, marker size, hand-eye file).
    pub estimator_node: String,
    /// The simulator's node.
    pub simulator_node: String,
    /// The bounds of the checks.
    pub limits: Limits,
}

impl Default for PreflightParams {
    fn default() -> Self {
        Self {
            window_s: 1.0,
            wait_s: 5.0,
            controller_node: "/docking_controller".into(),
            estimator_node: "/trocar_estimator".into(),
            simulator_node: "/lbr_med_sim".into(),
            limits: Limits::default(),
        }
    }
}

impl PreflightParams {
    /// Check every value; the error names the key.
    pub fn validate(&self) -> Result<(), NodeError> {
        crate::validate::positive_at_most("window_s", self.window_s, 60.0)?;
        crate::validate::positive_at_most("wait_s", self.wait_s, 600.0)?;
        self.limits.validate()?;
        Ok(())
    }
}
