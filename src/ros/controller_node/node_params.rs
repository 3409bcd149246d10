//! The parameters of the `docking_controller` node ([`ControllerNodeParams`]) with the
//! preflight's ([`PreflightParams`], the node's `~preflight` and the `preflight` node's
//! own): one module that both the node ([`crate::ros::controller_node`]) and the preflight
//! ([`crate::ros::preflight`]) read, so that neither imports the other's parameters.

use crate::control::ControllerParams;
use crate::kinematics::lbr::LbrModel;
use crate::preflight::Limits;
use crate::ros::markers::MarkerStyle;
use crate::ros::node::{CommandType, NodeError};
use crate::validate;

/// Parameters of the node (its private namespace; `config/docking_controller.yaml`, whose
/// values, built in, are the defaults: [`crate::config::DOCKING_CONTROLLER_NODE`]).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct ControllerNodeParams {
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
    /// Every command also goes out here as a `sensor_msgs/JointState` stamped with its
    /// control step's time and numbered as the command is (the command's own stamp is 0):
    /// the guard's clock, for audits, bags and plots. Not in a dry run.
    pub command_joints_topic: String,
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
    /// The trajectory command's `header.stamp`: 0 (`next_update`) or the step's time.
    pub command_stamp: crate::ros::node::CommandStamp,
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
    /// Run the preflight on a `~start` that begins a docking (the controller IDLE; not one
    /// that resumes a hold) and refuse the start when a check fails (`autostart` does not
    /// run it).
    pub preflight_on_start: bool,
    /// The preflight's settings (`~preflight`).
    pub preflight: PreflightParams,
    /// Parameters of the optimal controller (`config/controller.yaml`, loaded under
    /// `~controller`; its defaults when absent); its `dt_s` is the control period, its
    /// `force_feedback` set from the node's.
    #[serde(default)]
    pub controller: ControllerParams,
}

crate::shipped_defaults!(
    ControllerNodeParams,
    crate::config::DOCKING_CONTROLLER_NODE,
    [],
    deserialize_only
);

impl ControllerNodeParams {
    /// Check every rate, count and name; the error names the key.
    pub fn validate(&self) -> Result<(), NodeError> {
        // 5000 Hz down to 10 Hz
        validate::in_range("controller.dt_s", self.controller.dt_s, 2e-4, 0.1)?;
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
#[serde(remote = "Self", deny_unknown_fields)]
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

crate::shipped_defaults!(
    PreflightParams,
    crate::config::DOCKING_CONTROLLER_NODE,
    ["preflight"],
    deserialize_only
);

impl PreflightParams {
    /// Check every value; the error names the key.
    pub fn validate(&self) -> Result<(), NodeError> {
        crate::validate::positive_at_most("window_s", self.window_s, 60.0)?;
        crate::validate::positive_at_most("wait_s", self.wait_s, 600.0)?;
        self.limits.validate()?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_file_is_the_defaults_and_a_partial_tree_takes_the_rest_from_it() {
        let text = include_str!("../../../config/docking_controller.yaml");
        let p: ControllerNodeParams = crate::config::from_yaml_str("docking_controller.yaml", text).unwrap();
        p.validate().unwrap();
        let d = ControllerNodeParams::default();
        assert_eq!(format!("{p:?}"), format!("{d:?}"));
        // Figures of the file itself.
        assert_eq!(
            (d.controller.dt_s, d.latency_samples, d.preflight.window_s),
            (0.01, 5000, 1.0)
        );
        assert_eq!(
            (d.preflight.limits.min_image_hz, d.markers.force_scale_m_per_n),
            (5.0, 0.2)
        );
        assert_eq!(d.preflight.limits, Limits::default());
        // As the parameter server hands it over: partial, with the controller under `controller`.
        let tree = serde_json::json!({
            "preflight": {"limits": {"min_image_hz": 10}},
            "controller": {"dt_s": 0.001, "guard": {"force_stop_n": 15}},
        });
        let p: ControllerNodeParams = crate::ros::params::from_value("/docking_controller", tree).unwrap();
        assert_eq!((p.controller.dt_s, p.preflight.limits.min_image_hz), (0.001, 10.0));
        assert_eq!(p.preflight.limits.min_marker_hz, d.preflight.limits.min_marker_hz);
        assert_eq!(p.controller.guard.force_stop_n, 15.0);
        assert_eq!(p.controller.guard.velocity_scale, d.controller.guard.velocity_scale);
        assert_eq!(p.command_topic, d.command_topic);
        let e = crate::ros::params::from_value::<ControllerNodeParams>(
            "/docking_controller",
            serde_json::json!({"preflight": {"limits": {"min_image_fps": 10}}}),
        )
        .unwrap_err();
        assert_eq!(e.what, "/docking_controller");
        // The old rate key is refused naming the controller's period; an old key of the file
        // (or of the controller's, under `controller`) names its new one; a period out of range
        // is refused.
        let why = crate::ros::params::from_value::<ControllerNodeParams>(
            "/docking_controller",
            serde_json::json!({"rate_hz": 1000}),
        )
        .unwrap_err()
        .to_string();
        assert!(
            why.contains("`rate_hz`: the key is gone") && why.contains("`dt_s`"),
            "{why}"
        );
        for (tree, message) in [
            (
                serde_json::json!({"markers": {"force_scale": 0.1}}),
                "`markers.force_scale`: the key is now `markers.force_scale_m_per_n`",
            ),
            (
                serde_json::json!({"controller": {"guard": {"force_stop": 15}}}),
                "`controller.guard.force_stop`: the key is now `guard.force_stop_n`",
            ),
            // Left over under the controller's own parameters (~controller/rate_hz): named as
            // itself with its replacement, not as an unknown `controller`.
            (
                serde_json::json!({"controller": {"rate_hz": 1000}}),
                "`controller.rate_hz`: the key is gone (the control rate is the controller's period, `dt_s` = 1 / rate \
                 in config/controller.yaml (~controller/dt_s; the launch files' rate:=HZ sets it))",
            ),
        ] {
            let e = crate::ros::params::from_value::<ControllerNodeParams>("/docking_controller", tree)
                .unwrap_err()
                .to_string();
            assert!(e.contains(message), "{e}");
        }
        let fast: ControllerNodeParams =
            crate::ros::params::from_value("/docking_controller", serde_json::json!({"controller": {"dt_s": 1e-5}}))
                .unwrap();
        assert!(fast.validate().unwrap_err().to_string().contains("controller.dt_s"));
        assert!(
            e.message.contains("`preflight.limits.min_image_fps`: unknown key"),
            "{e}"
        );
    }
}
