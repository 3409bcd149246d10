//! The `docking_controller` node: subscribes the joint states, the driver's LBRState
//! (external torques) and the trocar pose; runs the guarded [`Controller`] at a fixed rate;
//! publishes the joint command, `/docking/status`, `/docking/f_ext`,
//! `/docking/markers` and tf frames of the trocar and the goal; serves `~start`, `~abort`
//! and `~reset`. Every topic and frame name is a parameter (see [`ControllerNodeParams`]).
//!
//! Nothing moves before `~start`. A bad message (wrong joints, NaN, wrong frame, a stamp
//! that goes back) is dropped with a logged reason and clears that input, so the controller
//! holds; a driver or camera that stops makes the input stale, and the controller holds.

use std::sync::{Arc, Mutex};

use nalgebra::{Isometry3, Point3};

use super::convert::{self, InputError, StampOrder};
use super::markers::{self, MarkerStyle, Scene};
use super::msgs::{geometry_msgs, lbr_msgs, sensor_msgs, std_srvs, tf2_msgs, trocar_docking};
use super::node::{lock, ros_err, CommandType, NodeError};
use super::params;
use super::stats::LoopStats;
use crate::control::{ControlInput, ControlOutput, Controller, ControllerParams, Stamped};
use crate::kinematics::lbr::LbrModel;
use crate::kinematics::Kinematics;
use crate::kinematics::{JointVector, LbrKinematics, TIP_LINK};

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
    /// Joint command out.
    pub command_topic: String,
    /// Message type of the command.
    pub command_type: CommandType,
    /// `time_from_start` of the trajectory point, in control periods.
    pub command_lookahead_periods: f64,
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
            joint_names: (1..=7).map(|i| format!("lbr_joint_{i}")).collect(),
            base_frame: crate::kinematics::BASE_LINK.into(),
            trocar_frame: "trocar".into(),
            goal_frame: "docking_goal".into(),
            joint_states_topic: "/lbr/joint_states".into(),
            lbr_state_topic: "/lbr/states".into(),
            trocar_pose_topic: "/trocar/pose".into(),
            command_topic: "/lbr/PositionJointInterface_trajectory_controller/command".into(),
            command_type: CommandType::Trajectory,
            command_lookahead_periods: 1.0,
            status_topic: "/docking/status".into(),
            f_ext_topic: "/docking/f_ext".into(),
            markers_topic: "/docking/markers".into(),
            status_rate_hz: 0.0,
            markers_rate_hz: 20.0,
            autostart: false,
            force_feedback: true,
            latency_samples: 5000,
            realtime_priority: 0,
            markers: MarkerStyle::default(),
            controller: ControllerParams::default(),
        }
    }
}

/// The newest valid inputs, written by the subscriber callbacks.
#[derive(Debug, Default)]
struct Inputs {
    joints: Option<Stamped<JointVector>>,
    tau_ext: Option<Stamped<JointVector>>,
    trocar: Option<Stamped<Isometry3<f64>>>,
    joints_order: StampOrder,
    tau_order: StampOrder,
    trocar_order: StampOrder,
    /// The last input fault, reported as the hold reason until the input recovers.
    fault: Option<String>,
}

impl Inputs {
    fn reject(&mut self, e: &InputError) {
        let text = e.to_string();
        rosrust::ros_warn!("input rejected, holding: {text}");
        self.fault = Some(text);
    }
}

type Shared<T> = Arc<Mutex<T>>;

fn stamp_of(h: &super::msgs::std_msgs::Header) -> f64 {
    convert::seconds(h.stamp)
}

fn subscribe_inputs(p: &ControllerNodeParams, inputs: &Shared<Inputs>) -> Result<Vec<rosrust::Subscriber>, NodeError> {
    let mut subs = Vec::new();
    {
        let (inputs, topic, names) = (inputs.clone(), p.joint_states_topic.clone(), p.joint_names.clone());
        subs.push(
            rosrust::subscribe(&p.joint_states_topic, 2, move |m: sensor_msgs::JointState| {
                let mut i = lock(&inputs);
                let stamp = stamp_of(&m.header);
                let r = convert::joint_positions(&topic, &m, &names)
                    .and_then(|q| i.joints_order.accept(&topic, stamp).map(|()| q));
                match r {
                    Ok(value) => i.joints = Some(Stamped { stamp, value }),
                    Err(e) => {
                        i.joints = None;
                        i.reject(&e);
                    }
                }
            })
            .map_err(ros_err)?,
        );
    }
    {
        let (inputs, topic) = (inputs.clone(), p.lbr_state_topic.clone());
        subs.push(
            rosrust::subscribe(&p.lbr_state_topic, 2, move |m: lbr_msgs::LBRState| {
                let mut i = lock(&inputs);
                let stamp = convert::seconds(m.stamp.data);
                let r =
                    convert::external_torques(&topic, &m).and_then(|t| i.tau_order.accept(&topic, stamp).map(|()| t));
                match r {
                    Ok(value) => i.tau_ext = Some(Stamped { stamp, value }),
                    Err(e) => {
                        i.tau_ext = None;
                        i.reject(&e);
                    }
                }
            })
            .map_err(ros_err)?,
        );
    }
    {
        let (inputs, topic, frame) = (inputs.clone(), p.trocar_pose_topic.clone(), p.base_frame.clone());
        subs.push(
            rosrust::subscribe(&p.trocar_pose_topic, 2, move |m: geometry_msgs::PoseStamped| {
                let mut i = lock(&inputs);
                let stamp = stamp_of(&m.header);
                let r = convert::pose_in_frame(&topic, &m, &frame)
                    .and_then(|t| i.trocar_order.accept(&topic, stamp).map(|()| t));
                match r {
                    Ok(value) => i.trocar = Some(Stamped { stamp, value }),
                    Err(e) => {
                        i.trocar = None;
                        i.reject(&e);
                    }
                }
            })
            .map_err(ros_err)?,
        );
    }
    Ok(subs)
}

/// A `std_srvs/Trigger` service that runs `f` on the controller.
fn trigger_service<F>(name: &str, controller: &Shared<Controller>, f: F) -> Result<rosrust::Service, NodeError>
where
    F: Fn(&mut Controller) -> Result<String, String> + Send + Sync + 'static,
{
    let controller = controller.clone();
    let label = name.to_string();
    rosrust::service::<std_srvs::Trigger, _>(name, move |_req| {
        let r = f(&mut lock(&controller));
        match &r {
            Ok(m) => {
                rosrust::ros_info!("{label}: {m}");
            }
            Err(m) => {
                rosrust::ros_warn!("{label} refused: {m}");
            }
        }
        Ok(match r {
            Ok(message) => std_srvs::TriggerRes { success: true, message },
            Err(message) => std_srvs::TriggerRes {
                success: false,
                message,
            },
        })
    })
    .map_err(ros_err)
}

/// Publishers of the node.
struct Outputs {
    trajectory: Option<rosrust::Publisher<super::msgs::trajectory_msgs::JointTrajectory>>,
    multiarray: Option<rosrust::Publisher<super::msgs::std_msgs::Float64MultiArray>>,
    status: rosrust::Publisher<trocar_docking::DockingStatus>,
    f_ext: rosrust::Publisher<geometry_msgs::WrenchStamped>,
    markers: rosrust::Publisher<super::msgs::visualization_msgs::MarkerArray>,
    tf: rosrust::Publisher<tf2_msgs::TFMessage>,
}

impl Outputs {
    fn new(p: &ControllerNodeParams) -> Result<Self, NodeError> {
        let (trajectory, multiarray) = match p.command_type {
            CommandType::Trajectory => (Some(rosrust::publish(&p.command_topic, 1).map_err(ros_err)?), None),
            CommandType::Float64MultiArray => (None, Some(rosrust::publish(&p.command_topic, 1).map_err(ros_err)?)),
        };
        Ok(Self {
            trajectory,
            multiarray,
            status: rosrust::publish(&p.status_topic, 10).map_err(ros_err)?,
            f_ext: rosrust::publish(&p.f_ext_topic, 10).map_err(ros_err)?,
            markers: rosrust::publish(&p.markers_topic, 2).map_err(ros_err)?,
            tf: rosrust::publish("/tf", 10).map_err(ros_err)?,
        })
    }

    fn command(&self, p: &ControllerNodeParams, stamp: rosrust::Time, q: &JointVector) {
        let r = match (&self.trajectory, &self.multiarray) {
            (Some(t), _) => t.send(convert::trajectory_command(
                stamp,
                &p.joint_names,
                q,
                p.command_lookahead_periods / p.rate_hz,
            )),
            (_, Some(m)) => m.send(convert::multiarray_command(q)),
            _ => Ok(()),
        };
        if let Err(e) = r {
            rosrust::ros_err!("cannot publish the command: {e}");
        }
    }
}

/// Tip distance to the insertion axis of `trocar` (m).
fn distance_to_axis(tip: &Isometry3<f64>, trocar: &Isometry3<f64>) -> f64 {
    let local = trocar.inverse_transform_point(&Point3::from(tip.translation.vector));
    local.x.hypot(local.y)
}

/// Fill a DockingStatus from a control step.
#[allow(clippy::too_many_arguments)]
fn status_msg(
    stamp: rosrust::Time,
    frame: &str,
    out: &ControlOutput,
    trocar: Option<&Isometry3<f64>>,
    fault: Option<&String>,
    elapsed: f64,
    stats: &mut LoopStats,
    ages_ms: (f64, f64),
) -> trocar_docking::DockingStatus {
    let lat = stats.percentiles();
    let (hold_reason, hold_code) = match (fault, out.reason_text()) {
        (Some(f), Some(r)) if !r.contains(f.as_str()) => (format!("{r}; input: {f}"), "INPUT_REJECTED"),
        (Some(_), Some(r)) => (r, "INPUT_REJECTED"),
        (None, Some(r)) => (r, out.reason_code()),
        (Some(f), None) => (f.clone(), "INPUT_REJECTED"),
        (None, None) => (String::new(), ""),
    };
    let costs = out.solve.as_ref().map_or([f64::NAN; 5], |s| s.costs);
    let tip_point = out.tip.map(|t| Point3::from(t.translation.vector));
    trocar_docking::DockingStatus {
        header: convert::header(stamp, frame),
        phase: out.phase.to_string(),
        hold_reason,
        hold_code: hold_code.to_string(),
        cost_axis: costs[0],
        cost_goal: costs[1],
        cost_alignment: costs[2],
        cost_joint_step: costs[3],
        cost_admittance: costs[4],
        iterations: out
            .solve
            .as_ref()
            .map_or(0, |s| u32::try_from(s.iterations).unwrap_or(u32::MAX)),
        solve_time_us: out.solve.as_ref().map_or(0.0, |s| s.solve_time_us),
        solver_status: out
            .solve
            .as_ref()
            .map_or_else(|| "not_run".to_string(), |s| s.status.as_text()),
        f_ext: convert::vector_msg(&out.f_ext),
        f_ext_norm: out.f_ext.norm(),
        metric_m: out.metric_m,
        metric_m_paper_scale: 2.4 * out.metric_m,
        elapsed,
        tip_to_goal: match (tip_point, out.goal) {
            (Some(t), Some(g)) => (t - g).norm(),
            _ => f64::NAN,
        },
        tip_to_axis: match (&out.tip, trocar) {
            (Some(tip), Some(t)) => distance_to_axis(tip, t),
            _ => f64::NAN,
        },
        steps: stats.steps(),
        loop_rate_hz: stats.rate_hz(),
        latency_p50_ms: lat.p50,
        latency_p99_ms: lat.p99,
        latency_max_ms: lat.max,
        trocar_age_ms: ages_ms.0,
        joints_age_ms: ages_ms.1,
    }
}

fn publish_scene(
    p: &ControllerNodeParams,
    o: &Outputs,
    stamp: rosrust::Time,
    out: &ControlOutput,
    trocar: Option<&Isometry3<f64>>,
) {
    let scene = Scene {
        trocar: trocar.copied(),
        goal: out.goal,
        tip: out.tip,
        f_ext: out.f_ext,
        reference: out.reference,
    };
    let _ = o
        .markers
        .send(markers::docking_markers(stamp, &p.base_frame, &scene, &p.markers));
    if let (Some(t), Some(g)) = (trocar, out.goal) {
        let goal = Isometry3::from_parts(g.coords.into(), t.rotation);
        let _ = o.tf.send(tf2_msgs::TFMessage {
            transforms: vec![
                convert::transform_stamped(stamp, &p.base_frame, &p.trocar_frame, t),
                convert::transform_stamped(stamp, &p.base_frame, &p.goal_frame, &goal),
            ],
        });
    }
}

/// Run the node until shutdown. Call after `rosrust::init`.
pub fn run() -> Result<(), NodeError> {
    let p: ControllerNodeParams = params::load_private()?;
    if !(p.rate_hz.is_finite() && p.rate_hz > 0.0 && p.rate_hz <= 5000.0) {
        return Err(NodeError::Invalid(format!("rate_hz = {} (0, 5000]", p.rate_hz)));
    }
    if p.joint_names.len() != crate::kinematics::N_JOINTS {
        return Err(NodeError::Invalid(format!(
            "joint_names has {} names, expected 7",
            p.joint_names.len()
        )));
    }
    let kin = LbrKinematics::from_model_or_file(p.model, &p.urdf_file, TIP_LINK)?;
    let mut cp = p.controller.clone();
    cp.dt = 1.0 / p.rate_hz;
    cp.force_feedback = p.force_feedback;
    let controller =
        Controller::new(cp, kin.limits().clone()).map_err(|e| NodeError::Invalid(format!("controller: {e}")))?;
    let controller = Arc::new(Mutex::new(controller));
    let inputs: Shared<Inputs> = Arc::new(Mutex::new(Inputs::default()));
    let stats = Arc::new(Mutex::new(LoopStats::new(1.0, p.latency_samples)));
    let start_time: Shared<Option<f64>> = Arc::new(Mutex::new(None));

    let outputs = Outputs::new(&p)?;
    let _subs = subscribe_inputs(&p, &inputs)?;
    let _srv_start = {
        let (st, stats) = (start_time.clone(), stats.clone());
        trigger_service("~start", &controller, move |c| {
            c.start()?;
            *lock(&st) = Some(convert::seconds(rosrust::now()));
            lock(&stats).clear();
            Ok("docking started".into())
        })?
    };
    let _srv_abort = trigger_service("~abort", &controller, |c| {
        c.abort("operator abort (~abort)");
        Ok("aborted: holding".into())
    })?;
    let _srv_reset = {
        let (st, inputs) = (start_time.clone(), inputs.clone());
        trigger_service("~reset", &controller, move |c| {
            c.reset();
            *lock(&st) = None;
            lock(&inputs).fault = None;
            Ok("reset to IDLE".into())
        })?
    };
    if p.autostart {
        lock(&controller)
            .start()
            .map_err(|e| NodeError::Invalid(format!("autostart: {e}")))?;
        *lock(&start_time) = Some(convert::seconds(rosrust::now()));
    }
    rosrust::ros_info!(
        "docking_controller: {} Hz, command {:?} on {}, waiting for ~start",
        p.rate_hz,
        p.command_type,
        p.command_topic
    );

    if p.realtime_priority != 0 {
        match crate::realtime::set_realtime_priority(p.realtime_priority) {
            Ok(()) => {
                rosrust::ros_info!("control loop runs at SCHED_FIFO {}", p.realtime_priority);
            }
            Err(e) => {
                rosrust::ros_warn!("control loop at normal priority: {e}");
            }
        }
    }
    let rate = rosrust::rate(p.rate_hz);
    let status_period = if p.status_rate_hz > 0.0 {
        1.0 / p.status_rate_hz
    } else {
        0.0
    };
    let markers_period = if p.markers_rate_hz > 0.0 {
        1.0 / p.markers_rate_hz
    } else {
        f64::INFINITY
    };
    let (mut last_status, mut last_markers) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
    let mut last_latency_stamp = f64::NEG_INFINITY;
    let mut last_now = f64::NEG_INFINITY;
    while rosrust::is_ok() {
        let stamp = rosrust::now();
        let now = convert::seconds(stamp);
        let (input, fault) = {
            let mut i = lock(&inputs);
            if now < last_now {
                // Time went back (a bag looped, the simulator restarted): start the orders afresh.
                i.joints_order.reset();
                i.tau_order.reset();
                i.trocar_order.reset();
                last_latency_stamp = f64::NEG_INFINITY;
            }
            let input = ControlInput {
                now,
                joints: i.joints,
                tau_ext: i.tau_ext,
                trocar: i.trocar,
            };
            if i.joints.is_some() && i.tau_ext.is_some() && i.trocar.is_some() {
                i.fault = None;
            }
            (input, i.fault.clone())
        };
        last_now = now;
        let out = lock(&controller).step(&kin, &input);
        let mut st = lock(&stats);
        st.tick(now);
        if let Some(q) = &out.command {
            outputs.command(&p, stamp, q);
            if let Some(t) = &input.trocar {
                if t.stamp > last_latency_stamp {
                    last_latency_stamp = t.stamp;
                    st.latency((convert::seconds(rosrust::now()) - t.stamp) * 1e3);
                }
            }
        }
        if now - last_status >= status_period {
            last_status = now;
            let elapsed = lock(&start_time).map_or(0.0, |t0| now - t0);
            let ages = (
                input.trocar.as_ref().map_or(f64::INFINITY, |t| (now - t.stamp) * 1e3),
                input.joints.as_ref().map_or(f64::INFINITY, |j| (now - j.stamp) * 1e3),
            );
            let trocar = input.trocar.as_ref().map(|t| &t.value);
            let msg = status_msg(
                stamp,
                &p.base_frame,
                &out,
                trocar,
                fault.as_ref(),
                elapsed,
                &mut st,
                ages,
            );
            let _ = outputs.status.send(msg);
            let _ = outputs.f_ext.send(geometry_msgs::WrenchStamped {
                header: convert::header(stamp, &p.base_frame),
                wrench: geometry_msgs::Wrench {
                    force: convert::vector_msg(&out.f_ext),
                    torque: geometry_msgs::Vector3::default(),
                },
            });
        }
        drop(st);
        if now - last_markers >= markers_period {
            last_markers = now;
            publish_scene(&p, &outputs, stamp, &out, input.trocar.as_ref().map(|t| &t.value));
        }
        rate.sleep();
    }
    Ok(())
}
