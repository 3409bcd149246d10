//! The `lbr_med_sim` node: [`crate::sim::SimWorld`] behind the real driver's topics. It
//! publishes `/lbr/joint_states` and `/lbr/states` (the vendored LBRState) at the FRI rate,
//! takes the same command topics as the driver, publishes the simulated camera (image +
//! camera_info of the trocar marker) and, in the paper's mode, a noisy `/trocar/pose`
//! directly. With `publish_clock` it owns `/clock` (for `/use_sim_time`) and can run faster
//! or slower than real time (`real_time_factor`).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::convert;
use super::msgs::{geometry_msgs, lbr_msgs, rosgraph_msgs, sensor_msgs, std_msgs, trajectory_msgs};
use super::params;
use crate::kinematics::{JointVector, Kinematics, LbrKinematics};
use crate::robot_model::{LbrModel, ToolParams};
use crate::sim::config::SimConfig;
use crate::sim::SimWorld;

use super::node::{ros_err, CommandType, NodeError};

/// Parameters of the node (`config/lbr_med_sim.yaml`).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimNodeParams {
    /// Arm model.
    pub model: LbrModel,
    /// Joint names (as the driver publishes them).
    pub joint_names: Vec<String>,
    /// FRI rate: joint states and LBRState, Hz.
    pub fri_rate_hz: f64,
    /// Simulated seconds per wall second.
    pub real_time_factor: f64,
    /// Publish `/clock` (set with `/use_sim_time`).
    pub publish_clock: bool,
    /// Random seed of the simulation (noise, trocar placement).
    pub seed: u64,
    /// Joint states out.
    pub joint_states_topic: String,
    /// LBRState out.
    pub lbr_state_topic: String,
    /// Command in.
    pub command_topic: String,
    /// Command message type.
    pub command_type: CommandType,
    /// Publish the camera image and camera_info.
    pub camera_enabled: bool,
    /// Camera rate, Hz.
    pub camera_rate_hz: f64,
    /// Image out.
    pub image_topic: String,
    /// CameraInfo out.
    pub camera_info_topic: String,
    /// Publish the simulator's noisy trocar pose measurement directly (the paper's mode; its
    /// rate, latency and noise are `world.sim.measurement`).
    pub direct_pose_enabled: bool,
    /// Direct trocar pose out.
    pub trocar_pose_topic: String,
    /// Ground-truth trocar pose out (for tests and RViz), '' = off.
    pub trocar_true_topic: String,
    /// Base frame.
    pub base_frame: String,
    /// Stop camera and direct pose after this many simulated seconds (negative: never).
    pub trocar_dropout_after: f64,
    /// The simulator's own parameters (`config/sim.yaml`, loaded under `~world`; its
    /// `sim:` section is used).
    pub world: SimConfig,
}

impl Default for SimNodeParams {
    fn default() -> Self {
        Self {
            model: LbrModel::Med7,
            joint_names: (1..=7).map(|i| format!("lbr_joint_{i}")).collect(),
            fri_rate_hz: 500.0,
            real_time_factor: 1.0,
            publish_clock: false,
            seed: 1,
            joint_states_topic: "/lbr/joint_states".into(),
            lbr_state_topic: "/lbr/states".into(),
            command_topic: "/lbr/PositionJointInterface_trajectory_controller/command".into(),
            command_type: CommandType::Trajectory,
            camera_enabled: true,
            camera_rate_hz: 30.0,
            image_topic: "/zedm/zed_node/left/image_rect_color".into(),
            camera_info_topic: "/zedm/zed_node/left/camera_info".into(),
            direct_pose_enabled: false,
            trocar_pose_topic: "/trocar/pose".into(),
            trocar_true_topic: "/trocar/pose_true".into(),
            base_frame: crate::kinematics::BASE_LINK.into(),
            trocar_dropout_after: -1.0,
            world: SimConfig::default(),
        }
    }
}

/// The newest valid command, or the reason the last one was rejected.
type CommandSlot = Arc<Mutex<Option<JointVector>>>;

fn subscribe_command(p: &SimNodeParams, slot: &CommandSlot) -> Result<rosrust::Subscriber, NodeError> {
    let (slot, topic, names) = (slot.clone(), p.command_topic.clone(), p.joint_names.clone());
    let accept = move |r: Result<JointVector, convert::InputError>| match r {
        Ok(q) => {
            if let Ok(mut s) = slot.lock() {
                *s = Some(q);
            }
        }
        Err(e) => {
            rosrust::ros_warn!("command rejected, arm keeps its last command: {e}");
        }
    };
    match p.command_type {
        CommandType::Trajectory => {
            rosrust::subscribe(&p.command_topic, 2, move |m: trajectory_msgs::JointTrajectory| {
                accept(convert::trajectory_positions(&topic, &m, &names))
            })
        }
        CommandType::Float64MultiArray => {
            rosrust::subscribe(&p.command_topic, 2, move |m: std_msgs::Float64MultiArray| {
                accept(convert::multiarray_positions(&topic, &m))
            })
        }
    }
    .map_err(ros_err)
}

/// Fires every `period` of simulated time.
#[derive(Debug, Clone, Copy)]
struct Every {
    period: f64,
    next: f64,
}

impl Every {
    fn new(rate_hz: f64, start: f64) -> Self {
        let period = if rate_hz.is_finite() && rate_hz > 0.0 {
            1.0 / rate_hz
        } else {
            f64::INFINITY
        };
        Self { period, next: start }
    }
    fn due(&mut self, t: f64) -> bool {
        if t + 1e-9 >= self.next {
            self.next += self.period;
            if self.next < t {
                self.next = t + self.period;
            }
            true
        } else {
            false
        }
    }
}

/// Run the node until shutdown. Call after `rosrust::init`.
pub fn run() -> Result<(), NodeError> {
    let p: SimNodeParams = params::load_private()?;
    if !(p.real_time_factor > 0.0 && p.real_time_factor.is_finite()) {
        return Err(NodeError::Invalid(format!("real_time_factor = {}", p.real_time_factor)));
    }
    let kin = LbrKinematics::from_model(p.model, &ToolParams::default())?;
    let shared_kin: Arc<dyn Kinematics> = Arc::new(kin.clone());
    let mut world =
        SimWorld::new(&p.world.sim, shared_kin, p.seed).map_err(|e| NodeError::Invalid(format!("sim: {e}")))?;
    let dt = p.world.sim.dt();

    let command: CommandSlot = Arc::new(Mutex::new(None));
    let _sub = subscribe_command(&p, &command)?;
    let pub_js = rosrust::publish::<sensor_msgs::JointState>(&p.joint_states_topic, 10).map_err(ros_err)?;
    let pub_lbr = rosrust::publish::<lbr_msgs::LBRState>(&p.lbr_state_topic, 10).map_err(ros_err)?;
    let pub_clock = if p.publish_clock {
        Some(rosrust::publish::<rosgraph_msgs::Clock>("/clock", 10).map_err(ros_err)?)
    } else {
        None
    };
    let pub_pose = if p.direct_pose_enabled {
        Some(rosrust::publish::<geometry_msgs::PoseStamped>(&p.trocar_pose_topic, 10).map_err(ros_err)?)
    } else {
        None
    };
    let pub_true = if p.trocar_true_topic.is_empty() {
        None
    } else {
        Some(rosrust::publish::<geometry_msgs::PoseStamped>(&p.trocar_true_topic, 2).map_err(ros_err)?)
    };
    if p.camera_enabled {
        return Err(NodeError::Invalid(
            "camera_enabled: the simulated camera needs the vision module, not in this build; use direct_pose_enabled"
                .into(),
        ));
    }

    // Simulated time starts at the wall clock, so stamps look like the real driver's.
    let t0 = convert::seconds(rosrust::Time::from(std::time::SystemTime::now()));
    let wall0 = Instant::now();
    let (mut fri, mut truth) = (Every::new(p.fri_rate_hz, t0), Every::new(10.0, t0));
    let mut last_measurement = f64::NEG_INFINITY;
    let sample_time = 1.0 / p.fri_rate_hz;
    rosrust::ros_info!(
        "lbr_med_sim: {:?}, FRI {} Hz, physics {} s, x{} real time, clock {}",
        p.model,
        p.fri_rate_hz,
        dt,
        p.real_time_factor,
        p.publish_clock
    );
    while rosrust::is_ok() {
        if let Some(q) = command.lock().ok().and_then(|mut s| s.take()) {
            if let Err(e) = world.set_command(&q) {
                rosrust::ros_warn!("command rejected by the arm, keeping the last one: {e}");
            }
        }
        if let Err(e) = world.step(dt) {
            return Err(NodeError::Invalid(format!("simulation stopped: {e}")));
        }
        let t = t0 + world.time();
        let stamp = if p.publish_clock {
            convert::ros_time(t)
        } else {
            rosrust::now()
        };
        if let Some(c) = &pub_clock {
            let _ = c.send(rosgraph_msgs::Clock { clock: stamp });
        }
        if fri.due(t) {
            let q = world.joint_positions();
            let tau_ext = world.external_torques();
            let tau = JointVector::zeros();
            let _ = pub_js.send(convert::joint_state(stamp, &p.joint_names, &q, &tau));
            let _ = pub_lbr.send(convert::lbr_state(stamp, sample_time, &q, &tau, &tau_ext));
        }
        let live = p.trocar_dropout_after < 0.0 || world.time() < p.trocar_dropout_after;
        if let (true, Some(publ), Some(m)) = (live, &pub_pose, world.measure_trocar(world.time())) {
            if m.stamp > last_measurement {
                last_measurement = m.stamp;
                // Stamped at capture: the controller's latency then counts the sensor delay.
                let capture = if p.publish_clock {
                    convert::ros_time(t0 + m.stamp)
                } else {
                    stamp
                };
                let _ = publ.send(convert::pose_stamped(capture, &p.base_frame, &m.pose));
            }
        }
        if truth.due(t) {
            if let Some(publ) = &pub_true {
                let _ = publ.send(convert::pose_stamped(stamp, &p.base_frame, &world.trocar_pose_true()));
            }
        }
        // Pace: simulated time runs real_time_factor times as fast as the wall clock.
        let ahead = world.time() / p.real_time_factor - wall0.elapsed().as_secs_f64();
        if ahead > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(ahead));
        }
    }
    Ok(())
}
