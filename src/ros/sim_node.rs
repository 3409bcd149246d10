//! The `lbr_med_sim` node: [`crate::sim::SimWorld`] behind the real driver's topics. It
//! publishes `/lbr/joint_states` and `/lbr/states` (the vendored LBRState) at the FRI rate,
//! takes the same command topics as the driver, publishes the simulated camera (image +
//! camera_info: the trocar's marker, or with `camera.show_marker: false` the trocar itself,
//! its head, opening and cannula before the abdominal wall, no marker) and, in the paper's mode, a noisy `/trocar/pose`
//! directly. With `publish_clock` it owns `/clock` (for `/use_sim_time`) and can run faster
//! or slower than real time (`real_time_factor`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use nalgebra::Isometry3;

use super::convert;
use super::convert::image as image_msgs;
use super::markers;
use super::msgs::{
    diagnostic_msgs, geometry_msgs, lbr_msgs, rosgraph_msgs, sensor_msgs, std_msgs, trajectory_msgs, visualization_msgs,
};
use super::params;
use super::sim_lockstep::CommandLockstep;
use super::topics;
use super::trajectory::{Outcome, StreamCounts, TrajectoryController};
use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::{JointVector, Kinematics, LbrKinematics, FLANGE_LINK};
use crate::sim::SimWorld;
use crate::trials::config::SimConfig;
use crate::vision::estimator::marker_in_camera;
use crate::vision::markerless::TrocarModel;
use crate::vision::render::add_gaussian_noise;
use crate::vision::sim_camera::{blank_frame, right_noise_seed, TrocarCamera};
use crate::vision::{render_marker_image, CameraModel, MarkerSpec, RenderOptions, VisionError};

use super::node::{ros_err, CommandType, NodeError};

/// The simulated camera's publisher queue (rosrust keeps one queue per publisher, whose
/// thread writes each message to every subscriber in turn, and drops the oldest message when
/// the queue is full): 4 frames, 0.27 s at 15 Hz, so that a subscriber whose reading thread is
/// starved for a few frames still gets every left and right image; a subscriber's own queue
/// keeps it fresh.
const CAMERA_QUEUE: usize = 4;

/// Parameters of the node (its private namespace; `config/lbr_med_sim.yaml`, whose values,
/// built in, are the defaults: [`crate::config::LBR_MED_SIM`]).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct SimNodeParams {
    /// Arm model.
    pub model: LbrModel,
    /// Joint names (as the driver publishes them).
    pub joint_names: Vec<String>,
    /// FRI rate: joint states and LBRState, Hz; the driver's trajectory controller updates
    /// once per FRI cycle (its period: 1 to 5 ms, 200 to 1000 Hz).
    pub fri_rate_hz: f64,
    /// Tests only: the driver's clock ahead of the controller's (ROS time), ms (negative:
    /// behind). The trajectory controller's updates and the driver's stamps
    /// (`/lbr/joint_states`, `/lbr/states`) read it; 0 as shipped.
    pub driver_clock_ahead_ms: f64,
    /// The driver clock's leads (ms) at which each command is also judged by the trajectory
    /// controller's rule, beside the one the arm follows (counts only: what the same stream
    /// meets on a driver whose clock reads so far ahead of the controller's).
    pub judge_clock_ahead_ms: Vec<f64>,
    /// The command stream's counts ([`crate::ros::trajectory::StreamCounts`]) out, once a
    /// second, as a `diagnostic_msgs/DiagnosticArray`.
    pub diagnostics_topic: String,
    /// Simulated seconds per wall second.
    pub real_time_factor: f64,
    /// Publish `/clock` (set with `/use_sim_time`).
    pub publish_clock: bool,
    /// With `publish_clock`: the simulated clock runs at most this far (s) past the last
    /// command received, then waits for the next one ([`super::sim_lockstep`]), so that a
    /// controller starved of the processor on a busy host slows the simulation instead of
    /// meeting an arm that stood still; 0 = off (the clock never waits for the controller).
    pub command_lockstep_s: f64,
    /// With `publish_clock`, `camera_lockstep` and the camera as the trocar's source (not
    /// `direct_pose_enabled`): the simulated clock runs at most this far (s) past the capture
    /// of the newest frame the estimator answered on `trocar_pose_topic`, then waits for its
    /// next pose ([`super::sim_lockstep`]), so that an estimator starved of the processor on
    /// a busy host slows the simulation instead of handing the controller older poses; 0 = off.
    pub pose_lockstep_s: f64,
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
    /// With `publish_clock`: the simulated clock waits for the camera, as a simulator's
    /// sensors do in lockstep (Gazebo's): a frame due while the last one is still rendering
    /// is taken once the renderer is free, so every frame comes at `camera_rate_hz` of
    /// simulated time and a slow host slows the simulation instead of dropping frames.
    /// false, or on the wall clock: such a frame is dropped, as a real camera drops frames.
    pub camera_lockstep: bool,
    /// Tests only: wall-clock seconds each rendered frame takes on top of its render, to
    /// stand for a slow or loaded host (0 = none).
    pub camera_render_delay_s: f64,
    /// The simulated camera's clock offset from the simulator's, s (tests only; 0 as shipped):
    /// added to every image's and camera_info's stamp, as a camera driver on a second machine
    /// whose clock is this far ahead (negative: behind) stamps its frames. Under
    /// `/use_sim_time` every node reads the simulator's `/clock`, so a machine's own clock
    /// shows only where a driver stamps with it: here.
    pub camera_stamp_offset_s: f64,
    /// Image out.
    pub image_topic: String,
    /// CameraInfo out.
    pub camera_info_topic: String,
    /// The stereo pair's right image out (with `camera.right_calibration_file`, without the
    /// marker; published just before the left image of the same stamp).
    pub right_image_topic: String,
    /// The right camera's CameraInfo out.
    pub right_camera_info_topic: String,
    /// Publish the simulator's noisy trocar pose measurement directly (its rate, latency,
    /// noise and hand-eye bias are the world protocol's `sim.measurement`).
    pub direct_pose_enabled: bool,
    /// Direct trocar pose out.
    pub trocar_pose_topic: String,
    /// Ground-truth trocar pose out (for tests and RViz), '' = off.
    pub trocar_true_topic: String,
    /// Ground-truth fulcrum out: where the wall holds the trocar at rest, breathing (the
    /// true port the scope should pivot about; for tests and RViz), '' = off.
    pub trocar_fulcrum_true_topic: String,
    /// The truth drawn for RViz out (`visualization_msgs/MarkerArray`: the true trocar and
    /// the abdominal wall at the fulcrum, [`markers::truth_markers`]), '' = off.
    pub trocar_true_markers_topic: String,
    /// Base frame.
    pub base_frame: String,
    /// Stop camera and direct pose after this many simulated seconds (negative: never),
    /// counted from [`Self::trocar_dropout_from`].
    pub trocar_dropout_after_s: f64,
    /// What `trocar_dropout_after_s` counts from.
    pub trocar_dropout_from: DropoutFrom,
    /// The simulated camera: its model, mount and the marker it sees.
    pub camera: SimCameraParams,
    /// The simulator's own parameters (`config/sim.yaml`, loaded under `~world`; its
    /// `sim:` section, with the protocol `world_protocol` applied, is used; its built-in
    /// values when absent). Read apart from the rest by [`Self::from_tree`].
    #[serde(skip)]
    pub world: SimConfig,
    /// The protocol of `world` the plant runs (`realistic`: seal, breathing, torque
    /// errors, elastic joints; `paper`; '' = the base `sim:` section).
    pub world_protocol: String,
}

crate::shipped_defaults!(SimNodeParams, crate::config::LBR_MED_SIM, [], deserialize_only);

impl SimNodeParams {
    /// The parameters from the node's namespace `ns` as the parameter server hands it over:
    /// the simulator's own tree `world` (`config/sim.yaml`) read as a [`SimConfig`] (its
    /// errors named under `ns/world`), the rest laid over the shipped file.
    pub fn from_tree(ns: &str, mut tree: serde_json::Value) -> Result<Self, params::ParamError> {
        let world = tree.as_object_mut().and_then(|m| m.remove("world"));
        let mut p: Self = params::from_value(ns, tree)?;
        if let Some(w) = world {
            p.world = params::from_value(&format!("{ns}/world"), w)?;
        }
        Ok(p)
    }
}

impl SimNodeParams {
    /// The driver's period (1 to 5 ms, the FRI send periods a position controller runs at)
    /// and the test clock offset (at most 1 s either way).
    pub fn validate_driver(&self) -> Result<(), crate::validate::RangeError> {
        crate::validate::in_range("fri_rate_hz", self.fri_rate_hz, 200.0, 1000.0)?;
        crate::validate::in_range("driver_clock_ahead_ms", self.driver_clock_ahead_ms, -1000.0, 1000.0)?;
        crate::validate::integer_in_range(
            "judge_clock_ahead_ms (count)",
            self.judge_clock_ahead_ms.len() as i64,
            0,
            8,
        )?;
        for &a in &self.judge_clock_ahead_ms {
            crate::validate::in_range("judge_clock_ahead_ms", a, -1000.0, 1000.0)?;
        }
        Ok(())
    }
}

pub use crate::vision::sim_camera::SimCameraParams;

/// One frame to render: the trocar's port in the camera at the capture time.
struct CameraJob {
    stamp: rosrust::Time,
    camera_t_trocar: Isometry3<f64>,
    seq: u64,
}

/// What the simulated camera draws.
enum SimScene {
    /// The marker on its plate (`marker_t_trocar`: the port in the marker frame), and the
    /// stereo pair's right camera, which sees it too.
    Marker {
        spec: MarkerSpec,
        opts: RenderOptions,
        marker_t_trocar: Isometry3<f64>,
        right: Option<Box<CameraModel>>,
    },
    /// The trocar without a marker.
    Trocar(Box<TrocarCamera>),
    /// The marker until the camera first comes within `within_m` of the port, then the
    /// trocar without it for good (`camera.marker_hidden_within_m`).
    MarkerUntil {
        marker: Box<SimScene>,
        trocar: Box<TrocarCamera>,
        within_m: f64,
        hidden: std::sync::atomic::AtomicBool,
    },
}

impl SimScene {
    /// The scene of the camera parameters `c` for a camera `model`: the marker, or the
    /// trocar with lighting, materials and the wall drawn once per run from `seed`.
    fn of(
        c: &SimCameraParams,
        seed: u64,
        model: &CameraModel,
        marker_t_trocar: Isometry3<f64>,
    ) -> Result<Self, NodeError> {
        let invalid = |e: crate::vision::sim_camera::CameraSetupError| NodeError::Invalid(e.to_string());
        let hidden_within = c.marker_hidden_within().map_err(invalid)?;
        // Noise is added per frame by the camera thread.
        let trocar = || -> Result<Box<TrocarCamera>, NodeError> {
            let right = c.right_camera().map_err(invalid)?;
            Ok(Box::new(
                TrocarCamera::new(c, seed, model, right.as_ref()).map_err(invalid)?,
            ))
        };
        if !c.show_marker {
            return Ok(Self::Trocar(trocar()?));
        }
        let marker = Self::Marker {
            spec: c.marker.clone(),
            opts: RenderOptions {
                blur_sigma: c.blur_sigma_px,
                plane_scale: c.plane_scale,
                ..RenderOptions::default()
            },
            marker_t_trocar,
            right: c.right_camera().map_err(invalid)?.map(Box::new),
        };
        Ok(match hidden_within {
            None => marker,
            Some(within_m) => Self::MarkerUntil {
                marker: Box::new(marker),
                trocar: trocar()?,
                within_m,
                hidden: std::sync::atomic::AtomicBool::new(false),
            },
        })
    }

    /// The scene a frame with the port at `camera_t_trocar` shows, and whether the marker was
    /// hidden by this frame: the marker's scene hides the marker for good once the camera is
    /// within its distance of the port.
    fn at(&self, camera_t_trocar: &Isometry3<f64>) -> (&Self, bool) {
        use std::sync::atomic::Ordering;
        match self {
            Self::MarkerUntil {
                marker,
                within_m,
                hidden,
                ..
            } => {
                let now =
                    camera_t_trocar.translation.vector.norm() < *within_m && !hidden.swap(true, Ordering::Relaxed);
                if hidden.load(Ordering::Relaxed) {
                    (self, now)
                } else {
                    (marker, false)
                }
            }
            _ => (self, false),
        }
    }

    /// The trocar camera of a scene that renders the trocar, or will once its marker is
    /// hidden ([`SimScene::at`] gives the scene of a frame).
    fn trocar(&self) -> Option<&TrocarCamera> {
        match self {
            Self::Trocar(camera) | Self::MarkerUntil { trocar: camera, .. } => Some(camera),
            Self::Marker { .. } => None,
        }
    }

    /// A port pose in the camera that must render: the marker or the trocar 0.3 m ahead.
    fn check_pose(&self) -> Isometry3<f64> {
        match self {
            Self::Marker {
                marker_t_trocar, spec, ..
            } => crate::vision::facing_pose_in(spec.family.frame(), 0.3, 0.0, 0.0, 0.0, 0.0, 0.0) * marker_t_trocar,
            Self::Trocar(_) => Isometry3::translation(0.0, 0.0, 0.3),
            Self::MarkerUntil { marker, .. } => marker.check_pose(),
        }
    }

    /// Add the camera's pixel noise of `sigma` grey levels to a frame (`seq`: its number):
    /// the marker's as before, the trocar's by the cheaper table (the same distribution).
    fn add_noise(&self, grey: &mut [u8], sigma: f64, seq: u64) {
        match self {
            Self::Marker { .. } => add_gaussian_noise(grey, sigma, seq),
            Self::Trocar(_) | Self::MarkerUntil { .. } => TrocarCamera::add_noise(grey, sigma, seq),
        }
    }

    /// The grey image of the port at `camera_t_trocar` (noise is added by the caller).
    fn render(&self, model: &CameraModel, camera_t_trocar: &Isometry3<f64>) -> Result<Vec<u8>, VisionError> {
        match self {
            Self::Marker {
                spec,
                opts,
                marker_t_trocar,
                ..
            } => render_marker_image(spec, model, &(camera_t_trocar * marker_t_trocar.inverse()), opts).map(|g| g.data),
            Self::Trocar(camera) | Self::MarkerUntil { trocar: camera, .. } => camera.render(camera_t_trocar),
        }
    }

    /// The right camera of the stereo pair, if the scene renders its image.
    fn right_camera(&self) -> Option<&CameraModel> {
        match self {
            Self::Marker { right, .. } => right.as_deref(),
            Self::Trocar(camera) | Self::MarkerUntil { trocar: camera, .. } => camera.right_camera(),
        }
    }

    /// The right camera's image of the port at `camera_t_trocar` (left camera frame), with
    /// its own pixel noise of `sigma` (`noise_seed`: the left frame's); `None` without a right
    /// camera. A frame that cannot render is blank, as the left one.
    fn right_frame(&self, camera_t_trocar: &Isometry3<f64>, sigma: f64, noise_seed: u64) -> Option<Vec<u8>> {
        match self {
            Self::Marker { right, .. } => {
                let r = right.as_deref()?;
                let mut grey = self
                    .render(r, &(r.stereo_right_t_left() * camera_t_trocar))
                    .unwrap_or_else(|_| blank_frame(r));
                if sigma > 0.0 {
                    self.add_noise(&mut grey, sigma, right_noise_seed(noise_seed));
                }
                Some(grey)
            }
            Self::Trocar(camera) | Self::MarkerUntil { trocar: camera, .. } => {
                camera.right_frame(camera_t_trocar, sigma, noise_seed)
            }
        }
    }
}

/// The simulated camera: renders on its own thread (a frame takes tens of ms) so the
/// physics and the FRI topics keep their rate between frames. A frame due while the last one
/// is still rendering waits for the renderer in lockstep ([`SimNodeParams::camera_lockstep`]:
/// the simulated clock stops meanwhile), else it is skipped, as a real camera drops frames.
struct SimCamera {
    jobs: std::sync::mpsc::SyncSender<CameraJob>,
    flange_kin: LbrKinematics,
    flange_t_camera: Isometry3<f64>,
    seq: u64,
    lockstep: bool,
}

/// The camera thread's side: its publishers, parameters and model.
struct CameraOutput {
    image: rosrust::Publisher<sensor_msgs::Image>,
    info: rosrust::Publisher<sensor_msgs::CameraInfo>,
    /// The right camera's image and CameraInfo (a stereo scene).
    right: Option<(
        rosrust::Publisher<sensor_msgs::Image>,
        rosrust::Publisher<sensor_msgs::CameraInfo>,
    )>,
    params: SimCameraParams,
    model: CameraModel,
    /// Tests only: a wall-clock delay added to each frame's render.
    render_delay: Duration,
}

impl CameraOutput {
    /// Render and publish every job until the simulator drops its sender.
    fn run(&self, jobs: &std::sync::mpsc::Receiver<CameraJob>, scene: &SimScene, pool: &rayon::ThreadPool, noise: f64) {
        let (c, model) = (&self.params, &self.model);
        if scene.trocar().is_some() {
            lower_priority();
        }
        let mut render_ms = super::stats::LoopStats::new(1.0, 1000);
        for job in jobs {
            // Out of view or behind the camera: the camera still delivers a (blank) frame.
            let t0 = Instant::now();
            let (scene, hidden_now) = scene.at(&job.camera_t_trocar);
            if hidden_now {
                rosrust::ros_info!(
                    "lbr_med_sim camera: the marker is hidden from now on (camera.marker_hidden_within_m)"
                );
            }
            let left = || {
                scene
                    .render(model, &job.camera_t_trocar)
                    .unwrap_or_else(|_| blank_frame(model))
            };
            // The right image of a stereo scene with every `right_every`-th frame, rendered
            // beside the left one (the pool has a thread per camera).
            // (Only for a subscriber: a marker-only estimator reads no right image.)
            let (mut grey, right) = match &self.right {
                Some((image, _)) if c.right_due(job.seq) && image.subscriber_count() > 0 => {
                    pool.install(|| rayon::join(left, || scene.right_frame(&job.camera_t_trocar, noise, job.seq)))
                }
                _ => (pool.install(left), None),
            };
            if !self.render_delay.is_zero() {
                std::thread::sleep(self.render_delay);
            }
            render_ms.latency(t0.elapsed().as_secs_f64() * 1e3);
            if job.seq % 150 == 0 {
                let l = render_ms.percentiles();
                rosrust::ros_info!(
                    "lbr_med_sim camera: render p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms ({} frames)",
                    l.p50,
                    l.p99,
                    l.max,
                    job.seq
                );
            }
            if noise > 0.0 {
                scene.add_noise(&mut grey, noise, job.seq);
            }
            // The right image first: the estimator pairs each left image with the latest right.
            if let (Some((image, info)), Some(r), Some(rm)) = (&self.right, right, scene.right_camera()) {
                if let Ok((data, channels)) = image_msgs::grey_as(&c.encoding, r) {
                    let _ = info.send(image_msgs::camera_info(job.stamp, &c.frame, rm));
                    let _ = image.send(image_msgs::image(
                        job.stamp,
                        &c.frame,
                        rm.width,
                        rm.height,
                        &c.encoding,
                        channels,
                        data,
                    ));
                }
            }
            let Ok((data, channels)) = image_msgs::grey_as(&c.encoding, grey) else {
                continue;
            };
            let _ = self.info.send(image_msgs::camera_info(job.stamp, &c.frame, model));
            let _ = self.image.send(image_msgs::image(
                job.stamp,
                &c.frame,
                model.width,
                model.height,
                &c.encoding,
                channels,
                data,
            ));
        }
    }
}

impl SimCamera {
    fn start(p: &SimNodeParams) -> Result<Self, NodeError> {
        let c = &p.camera;
        let invalid = |what: &str, e: &dyn std::fmt::Display| NodeError::Invalid(format!("camera.{what}: {e}"));
        if c.calibration_file.is_empty() {
            return Err(NodeError::Invalid(
                "camera.calibration_file must name a camera calibration YAML when camera_enabled".into(),
            ));
        }
        let model = CameraModel::from_yaml_file(std::path::Path::new(&c.calibration_file))
            .map_err(|e| invalid("calibration_file", &e))?;
        c.marker.validate().map_err(|e| invalid("marker", &e))?;
        image_msgs::encoding_layout(&c.encoding).map_err(|e| invalid("encoding", &e))?;
        let flange_t_camera = c
            .flange_t_camera
            .to_isometry()
            .map_err(|e| invalid("flange_t_camera", &e))?;
        let marker_t_trocar = c
            .marker_t_trocar
            .to_isometry()
            .map_err(|e| invalid("marker_t_trocar", &e))?;
        let scene = SimScene::of(c, p.seed, &model, marker_t_trocar)?;
        // Check the options once here, so the thread cannot fail on them later.
        scene
            .render(&model, &scene.check_pose())
            .map_err(|e| invalid("render", &e))?;
        if let SimScene::MarkerUntil { marker, .. } = &scene {
            marker
                .render(&model, &marker.check_pose())
                .map_err(|e| invalid("render", &e))?;
        }
        let pub_img = rosrust::publish::<sensor_msgs::Image>(&p.image_topic, CAMERA_QUEUE).map_err(ros_err)?;
        let pub_info =
            rosrust::publish::<sensor_msgs::CameraInfo>(&p.camera_info_topic, CAMERA_QUEUE).map_err(ros_err)?;
        let right = match scene.right_camera() {
            Some(_) => Some((
                rosrust::publish::<sensor_msgs::Image>(&p.right_image_topic, CAMERA_QUEUE).map_err(ros_err)?,
                rosrust::publish::<sensor_msgs::CameraInfo>(&p.right_camera_info_topic, CAMERA_QUEUE)
                    .map_err(ros_err)?,
            )),
            None => None,
        };
        // A rendezvous channel: a frame is only taken when the renderer is free.
        let (tx, rx) = std::sync::mpsc::sync_channel::<CameraJob>(0);
        let (c, noise) = (c.clone(), c.noise_sigma);
        // The markerless renderer runs on rayon: a thread of its own per camera (the stereo
        // pair's two images render side by side), niced (as is the camera thread then), so
        // the physics and the FRI topics keep their core (a real camera does not slow the
        // arm down). The marker's renderer is one C++ call.
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(if scene.right_camera().is_some() { 2 } else { 1 })
            .start_handler(|_| lower_priority())
            .build()
            .map_err(|e| NodeError::Invalid(format!("camera thread pool: {e}")))?;
        let out = CameraOutput {
            image: pub_img,
            info: pub_info,
            right,
            params: c,
            model,
            render_delay: Duration::from_secs_f64(p.camera_render_delay_s),
        };
        std::thread::spawn(move || out.run(&rx, &scene, &pool, noise));
        Ok(Self {
            jobs: tx,
            flange_kin: LbrKinematics::from_model_or_file(p.model, "", FLANGE_LINK)?,
            flange_t_camera,
            seq: 0,
            lockstep: p.camera_lockstep && p.publish_clock,
        })
    }

    /// Capture a frame of `world` now, stamped `stamp` (the camera's clock): in lockstep it
    /// waits for the renderer to finish the last frame, else the frame is skipped while the
    /// last one renders. Returns the wall time waited.
    fn capture(&mut self, world: &SimWorld, stamp: rosrust::Time) -> Duration {
        // The camera rides on the link side: where the (elastic) arm really is.
        let Ok(base_t_flange) = self.flange_kin.fk(&world.joint_positions_link()) else {
            return Duration::ZERO;
        };
        let camera_t_trocar = marker_in_camera(
            &base_t_flange,
            &self.flange_t_camera,
            &world.trocar_pose_true(),
            &Isometry3::identity(),
        );
        self.seq += 1;
        let job = CameraJob {
            stamp,
            camera_t_trocar,
            seq: self.seq,
        };
        if !self.lockstep {
            let _ = self.jobs.try_send(job);
            return Duration::ZERO;
        }
        // The rendezvous channel takes the job once the renderer is free.
        let t0 = Instant::now();
        let _ = self.jobs.send(job);
        t0.elapsed()
    }
}

/// A frame captured at `stamp` (the simulator's clock) as a camera whose clock is
/// `offset_s` ahead stamps it.
fn camera_stamp(stamp: rosrust::Time, offset_s: f64) -> rosrust::Time {
    if offset_s == 0.0 {
        return stamp;
    }
    convert::ros_time(convert::seconds(stamp) + offset_s)
}

/// Nice the calling thread by 10 (the simulated camera's renderer: below the physics).
fn lower_priority() {
    // SAFETY: setpriority on the calling thread's id (gettid) only changes its nice value.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, 10);
    }
}

/// When a command's point is due.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Timing {
    /// A trajectory point: its `header.stamp` (s; `None`: zero) and `time_from_start` (s).
    Trajectory { stamp: Option<f64>, time_from_start: f64 },
    /// A position command (Float64MultiArray): at once.
    Position,
}

/// A command as it arrived.
#[derive(Debug, Clone, Copy)]
struct CommandPoint {
    q: JointVector,
    timing: Timing,
}

/// Commands arrived since the last physics step, oldest first: each is judged by the
/// trajectory controller's rule, none replaced unseen.
type CommandQueue = Arc<Mutex<std::collections::VecDeque<CommandPoint>>>;

/// Commands kept between two physics steps (1 ms): a flood beyond loses the oldest.
const COMMAND_QUEUE: usize = 32;

/// A trajectory message's timing: its stamp (0: none) and its first point's time_from_start.
fn timing(m: &trajectory_msgs::JointTrajectory) -> Timing {
    let tfs = m.points.first().map_or(0.0, |p| {
        f64::from(p.time_from_start.sec) + f64::from(p.time_from_start.nsec) * 1e-9
    });
    let stamp = convert::seconds(m.header.stamp);
    Timing::Trajectory {
        stamp: (stamp != 0.0).then_some(stamp),
        time_from_start: tfs,
    }
}

fn subscribe_command(p: &SimNodeParams, queue: &CommandQueue) -> Result<rosrust::Subscriber, NodeError> {
    let (queue, topic, names) = (queue.clone(), p.command_topic.clone(), p.joint_names.clone());
    let accept = move |r: Result<JointVector, convert::InputError>, timing: Timing| match r {
        Ok(q) => {
            if let Ok(mut s) = queue.lock() {
                if s.len() == COMMAND_QUEUE {
                    s.pop_front();
                }
                s.push_back(CommandPoint { q, timing });
            }
        }
        Err(e) => {
            rosrust::ros_warn!("command rejected, arm keeps its last command: {e}");
        }
    };
    match p.command_type {
        CommandType::Trajectory => {
            rosrust::subscribe(&p.command_topic, 2, move |m: trajectory_msgs::JointTrajectory| {
                accept(convert::trajectory_positions(&topic, &m, &names), timing(&m))
            })
        }
        CommandType::Float64MultiArray => {
            rosrust::subscribe(&p.command_topic, 2, move |m: std_msgs::Float64MultiArray| {
                accept(convert::multiarray_positions(&topic, &m), Timing::Position)
            })
        }
    }
    .map_err(ros_err)
}

/// The clock in lockstep with the estimator's poses (`pose_lockstep_s`): the newest pose's
/// capture stamp, written by the pose subscriber (f64 bits, lock-free), read by the loop.
struct PoseLockstep {
    newest: Arc<AtomicU64>,
    /// The newest stamp the loop has taken (f64 bits).
    seen: u64,
    /// A capture stamp minus this is its simulated time (the clock's origin and the camera's
    /// offset).
    origin: f64,
    /// `pose_lockstep_s`.
    bound_s: f64,
    lockstep: CommandLockstep,
    /// The waits to the log, every 10 s of simulated time.
    log: Every,
    _sub: rosrust::Subscriber,
}

impl PoseLockstep {
    /// The lockstep where it applies (module doc of [`super::sim_lockstep`]), else `None`.
    fn start(p: &SimNodeParams, t0: f64) -> Result<Option<Self>, NodeError> {
        let applies = p.publish_clock && p.camera_enabled && p.camera_lockstep && !p.direct_pose_enabled;
        if !applies || p.pose_lockstep_s <= 0.0 {
            return Ok(None);
        }
        let newest = Arc::new(AtomicU64::new(f64::NEG_INFINITY.to_bits()));
        let write = newest.clone();
        let sub = rosrust::subscribe(&p.trocar_pose_topic, 10, move |m: geometry_msgs::PoseStamped| {
            let t = convert::seconds(m.header.stamp);
            if t.is_finite() && t > f64::from_bits(write.load(Ordering::Acquire)) {
                write.store(t.to_bits(), Ordering::Release);
            }
        })
        .map_err(ros_err)?;
        Ok(Some(Self {
            newest,
            seen: f64::NEG_INFINITY.to_bits(),
            origin: t0 + p.camera_stamp_offset_s,
            bound_s: p.pose_lockstep_s,
            lockstep: CommandLockstep::new(p.pose_lockstep_s),
            log: Every::new(0.1, 10.0),
            _sub: sub,
        }))
    }

    /// Take a newer pose, if one came: its capture is the lockstep's last arrival.
    fn take(&mut self) {
        let n = self.newest.load(Ordering::Acquire);
        if n != self.seen {
            self.seen = n;
            self.lockstep.arrived(f64::from_bits(n) - self.origin);
        }
    }

    /// Before the clock advances past simulated time `t`: wait (wall time) for a pose
    /// captured within `pose_lockstep_s` of `t`, or until [`GIVE_UP`](super::sim_lockstep::GIVE_UP) (no pose: the marker
    /// lost, the estimator stopped), after which the clock runs free until the next pose.
    /// Returns the wall time waited.
    fn await_pose(&mut self, t: f64) -> Duration {
        self.take();
        if !self.lockstep.must_wait(t) {
            return Duration::ZERO;
        }
        let (newest, origin, bound) = (&self.newest, self.origin, self.bound_s);
        let fresh = || t - (f64::from_bits(newest.load(Ordering::Acquire)) - origin) <= bound;
        let (waited, got) = self.lockstep.wait_until(fresh, rosrust::is_ok);
        if got {
            self.take();
        } else {
            // Free until a pose newer than those seen in the wait.
            self.seen = self.newest.load(Ordering::Acquire);
        }
        if self.log.due(t) {
            let (n, w) = self.lockstep.waits();
            rosrust::ros_info!(
                "lbr_med_sim: the clock waited for the estimator's pose {n} times, {:.2} s in all",
                w.as_secs_f64()
            );
        }
        waited
    }
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

/// The world the node simulates: `~world` with `~world_protocol` applied.
fn world_config(p: &SimNodeParams) -> Result<SimConfig, NodeError> {
    if p.world_protocol.is_empty() {
        return Ok(p.world.clone());
    }
    p.world
        .with_protocol(&p.world_protocol)
        .map_err(|e| NodeError::Invalid(format!("world_protocol '{}': {e}", p.world_protocol)))
}

/// A publisher on `topic` when `on`.
fn optional<T: rosrust::Message>(
    on: bool,
    topic: &str,
    queue: usize,
) -> Result<Option<rosrust::Publisher<T>>, NodeError> {
    if on {
        rosrust::publish::<T>(topic, queue).map(Some).map_err(ros_err)
    } else {
        Ok(None)
    }
}

/// What the trocar sources' dropout time counts from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DropoutFrom {
    /// The start of the simulation.
    Start,
    /// The arm's first moving command: a test that needs the arm moving when the pose
    /// stops does not depend on how long the nodes took to start.
    FirstMotion,
}

/// Whether the trocar sources (camera, direct pose) still deliver at simulated time `t`,
/// with the arm's first moving command at `first_motion` (None: not yet).
fn trocar_live(dropout_after_s: f64, from: DropoutFrom, t: f64, first_motion: Option<f64>) -> bool {
    if dropout_after_s < 0.0 {
        return true;
    }
    match from {
        DropoutFrom::Start => t < dropout_after_s,
        DropoutFrom::FirstMotion => first_motion.is_none_or(|t0| t - t0 < dropout_after_s),
    }
}

/// The node's publishers (the camera's live on its thread).
struct Outputs {
    joint_states: rosrust::Publisher<sensor_msgs::JointState>,
    lbr_state: rosrust::Publisher<lbr_msgs::LBRState>,
    clock: Option<rosrust::Publisher<rosgraph_msgs::Clock>>,
    pose: Option<rosrust::Publisher<geometry_msgs::PoseStamped>>,
    truth: Option<rosrust::Publisher<geometry_msgs::PoseStamped>>,
    fulcrum_truth: Option<rosrust::Publisher<geometry_msgs::PointStamped>>,
    /// The truth drawn, with the trocar it draws.
    truth_markers: Option<(rosrust::Publisher<visualization_msgs::MarkerArray>, TrocarModel)>,
}

impl Outputs {
    fn new(p: &SimNodeParams) -> Result<Self, NodeError> {
        Ok(Self {
            joint_states: rosrust::publish(&p.joint_states_topic, topics::DRIVER_QUEUE).map_err(ros_err)?,
            lbr_state: rosrust::publish(&p.lbr_state_topic, topics::DRIVER_QUEUE).map_err(ros_err)?,
            clock: optional(p.publish_clock, "/clock", 10)?,
            pose: optional(p.direct_pose_enabled, &p.trocar_pose_topic, 10)?,
            truth: optional(!p.trocar_true_topic.is_empty(), &p.trocar_true_topic, 2)?,
            fulcrum_truth: optional(!p.trocar_fulcrum_true_topic.is_empty(), &p.trocar_fulcrum_true_topic, 2)?,
            truth_markers: match optional(!p.trocar_true_markers_topic.is_empty(), &p.trocar_true_markers_topic, 2)? {
                Some(publ) => Some((
                    publ,
                    p.camera.trocar_model().map_err(|e| NodeError::Invalid(e.to_string()))?,
                )),
                None => None,
            },
        })
    }

    /// The driver's topics: joint states and LBRState (motor-side joints, as the LBR).
    fn driver(&self, p: &SimNodeParams, world: &SimWorld, stamp: rosrust::Time, sample_time: f64) {
        let q = world.joint_positions();
        let tau_ext = world.external_torques();
        let tau = JointVector::zeros();
        let _ = self
            .joint_states
            .send(convert::joint_state(stamp, &p.joint_names, &q, &tau));
        let _ = self
            .lbr_state
            .send(convert::lbr_state(stamp, sample_time, &q, &tau, &tau_ext));
    }

    /// The ground truth (trocar pose, fulcrum), where its topics are set.
    fn truth(&self, p: &SimNodeParams, world: &SimWorld, stamp: rosrust::Time) {
        if let Some(publ) = &self.truth {
            let _ = publ.send(convert::pose_stamped(stamp, &p.base_frame, &world.trocar_pose_true()));
        }
        if let Some(publ) = &self.fulcrum_truth {
            let _ = publ.send(convert::point_stamped(stamp, &p.base_frame, &world.trocar().anchor()));
        }
        if let Some((publ, model)) = &self.truth_markers {
            let (trocar, fulcrum) = (world.trocar_pose_true(), world.trocar().anchor());
            let _ = publ.send(markers::truth_markers(stamp, &p.base_frame, &trocar, &fulcrum, model));
        }
    }

    /// In the direct mode, a pose measurement newer than `last` (its stamp, updated),
    /// stamped at capture: the controller's latency then counts the sensor delay.
    fn direct_pose(&self, p: &SimNodeParams, world: &SimWorld, t0: f64, stamp: rosrust::Time, last: &mut f64) {
        let (Some(publ), Some(m)) = (&self.pose, world.measure_trocar(world.time())) else {
            return;
        };
        if m.stamp > *last {
            *last = m.stamp;
            let capture = if p.publish_clock {
                convert::ros_time(t0 + m.stamp)
            } else {
                stamp
            };
            let _ = publ.send(convert::pose_stamped(capture, &p.base_frame, &m.pose));
        }
    }
}

/// The commands as the driver's trajectory controller takes them
/// ([`TrajectoryController`], updated once per FRI cycle on the driver's clock); its
/// counts go out on the diagnostics once a second, and every 10 s to the log.
struct ArmCommand {
    jtc: TrajectoryController,
    /// The driver's clock minus the simulated ROS time, s.
    clock_ahead: f64,
    /// The same stream judged on drivers whose clocks lead by other amounts (s): counts only.
    judges: Vec<(f64, TrajectoryController)>,
    /// The driver's updates (once per FRI cycle).
    driver_update: Every,
    diagnostics_out: rosrust::Publisher<diagnostic_msgs::DiagnosticArray>,
    log: Every,
    diagnostics: Every,
    /// The largest lead of a command over the measured joints, rad.
    max_lead: f64,
    /// When the first moving command came (simulated time, s).
    first_motion: Option<f64>,
    /// Commands taken from the queue this step (its own buffer: no allocation per step).
    taken: std::collections::VecDeque<CommandPoint>,
    /// The clock in lockstep with the commands (`command_lockstep_s`).
    lockstep: CommandLockstep,
}

impl ArmCommand {
    fn new(p: &SimNodeParams, world: &SimWorld, t0: f64) -> Result<Self, NodeError> {
        p.validate_driver()?;
        let clock_ahead = p.driver_clock_ahead_ms * 1e-3;
        Ok(Self {
            jtc: TrajectoryController::new(world.joint_positions(), t0 + clock_ahead, 1.0 / p.fri_rate_hz),
            clock_ahead,
            judges: p
                .judge_clock_ahead_ms
                .iter()
                .map(|&ms| {
                    let a = ms * 1e-3;
                    (
                        a,
                        TrajectoryController::new(world.joint_positions(), t0 + a, 1.0 / p.fri_rate_hz),
                    )
                })
                .collect(),
            driver_update: Every::new(p.fri_rate_hz, t0),
            diagnostics_out: rosrust::publish(&p.diagnostics_topic, 10).map_err(ros_err)?,
            log: Every::new(0.1, t0 + 10.0),
            diagnostics: Every::new(1.0, t0 + 1.0),
            max_lead: 0.0,
            first_motion: None,
            taken: std::collections::VecDeque::with_capacity(COMMAND_QUEUE),
            lockstep: CommandLockstep::new(if p.publish_clock { p.command_lockstep_s } else { 0.0 }),
        })
    }

    /// One physics step at simulated ROS time `now`: the commands arrived since the last
    /// step judged, then the driver's update where one is due.
    fn step(&mut self, queue: &CommandQueue, world: &mut SimWorld, now: f64) {
        self.take(queue, world);
        if self.driver_update.due(now) {
            self.update(world, now);
        }
    }

    /// Before the clock advances past simulated time `t`: in lockstep, wait (wall time) for
    /// the controller's next command when the last one is more than `command_lockstep_s` old;
    /// returns the wall time waited (the pace's origin moves on by it).
    fn await_command(&mut self, queue: &CommandQueue, t: f64) -> Duration {
        if !self.lockstep.must_wait(t) {
            return Duration::ZERO;
        }
        // A poisoned queue (its subscriber panicked) cannot bring a command: run free.
        let arrived = || queue.lock().map(|q| !q.is_empty()).unwrap_or(false);
        let (waited, got) = self.lockstep.wait_until(arrived, rosrust::is_ok);
        if !got {
            rosrust::ros_warn!(
                "lbr_med_sim: no command for {:.1} s of wall time: the clock runs on without the controller until its next command",
                waited.as_secs_f64()
            );
        }
        waited
    }

    /// Judge the commands arrived since the last step (simulated ROS time `now`, s).
    fn take(&mut self, queue: &CommandQueue, world: &SimWorld) {
        if let Ok(mut q) = queue.lock() {
            std::mem::swap(&mut *q, &mut self.taken);
        }
        if !self.taken.is_empty() {
            self.lockstep.arrived(world.time());
        }
        while let Some(c) = self.taken.pop_front() {
            // A point the arm would refuse never reaches the controller.
            if let Some(i) = c.q.iter().position(|x| !x.is_finite()) {
                rosrust::ros_warn!("command rejected: joint {i} is not finite; the arm keeps its trajectory");
                continue;
            }
            self.max_lead = self.max_lead.max((c.q - world.joint_positions()).amax());
            match c.timing {
                Timing::Position => {
                    self.jtc.set_position(c.q);
                    for (_, j) in &mut self.judges {
                        j.set_position(c.q);
                    }
                }
                Timing::Trajectory { stamp, time_from_start } => {
                    for (_, j) in &mut self.judges {
                        j.command(stamp, time_from_start, c.q);
                    }
                    if let Outcome::Dropped { late_by_s } = self.jtc.command(stamp, time_from_start, c.q) {
                        rosrust::ros_warn!(
                            "lbr_med_sim: dropping all 1 trajectory point(s), as they occur before the current \
                             time: last point is {late_by_s:.4} s in the past (joint_trajectory_controller's rule)"
                        );
                    }
                }
            }
            if self.first_motion.is_none() && self.jtc.counts().moving > 0 {
                self.first_motion = Some(world.time());
            }
        }
    }

    /// The driver's update at simulated ROS time `now`: the controller's desired positions
    /// become the arm's setpoint.
    fn update(&mut self, world: &mut SimWorld, now: f64) {
        let _ = world.set_command(&self.jtc.update(now + self.clock_ahead));
        for (a, j) in &mut self.judges {
            j.update(now + *a);
        }
    }

    /// The counts to the log (every 10 s) and the diagnostics (every second).
    fn report(&mut self, now: f64, stamp: rosrust::Time) {
        let n = self.jtc.counts();
        if self.log.due(now) && n.moving > 0 {
            rosrust::ros_info!(
                "lbr_med_sim: {} trajectory messages, {} moving, {} dropped ({} moving), {} late (the arm held at \
                 the previous point); smallest lead over the next update {:.1} ms; largest command lead {:.2} deg; \
                 the clock waited for the controller {} times, {:.2} s in all",
                n.messages,
                n.moving,
                n.dropped,
                n.dropped_moving,
                n.late,
                n.min_lead_s * 1e3,
                self.max_lead.to_degrees(),
                self.lockstep.waits().0,
                self.lockstep.waits().1.as_secs_f64()
            );
        }
        if self.diagnostics.due(now) {
            let _ = self
                .diagnostics_out
                .send(stream_diagnostics(stamp, &n, &self.judges, self.lockstep.waits()));
        }
    }
}

/// Name of the command stream's diagnostic status.
pub const STREAM_DIAGNOSTIC: &str = "lbr_med_sim: trajectory controller";

/// The key of the moving commands dropped on a driver whose clock leads by `ahead_s`.
pub fn judged_dropped_key(ahead_s: f64) -> String {
    format!("dropped_moving_if_driver_ahead_{:.0}ms", ahead_s * 1e3)
}

/// The stream's counts as a diagnostic (with the moving commands each judge dropped): WARN
/// when a moving command was dropped.
fn stream_diagnostics(
    stamp: rosrust::Time,
    n: &StreamCounts,
    judges: &[(f64, TrajectoryController)],
    (waits, waited): (u64, Duration),
) -> diagnostic_msgs::DiagnosticArray {
    let kv = |key: &str, value: String| diagnostic_msgs::KeyValue { key: key.into(), value };
    let level = if n.dropped_moving > 0 {
        diagnostic_msgs::DiagnosticStatus::WARN
    } else {
        diagnostic_msgs::DiagnosticStatus::OK
    };
    diagnostic_msgs::DiagnosticArray {
        header: convert::header(stamp, ""),
        status: vec![diagnostic_msgs::DiagnosticStatus {
            level,
            name: STREAM_DIAGNOSTIC.into(),
            message: format!(
                "{} of {} moving commands dropped, {} late",
                n.dropped_moving, n.moving, n.late
            ),
            hardware_id: "lbr_med_sim".into(),
            values: vec![
                kv("messages", n.messages.to_string()),
                kv("moving", n.moving.to_string()),
                kv("dropped", n.dropped.to_string()),
                kv("dropped_moving", n.dropped_moving.to_string()),
                kv("late", n.late.to_string()),
                kv("min_lead_ms", format!("{:.3}", n.min_lead_s * 1e3)),
                kv("lockstep_waits", waits.to_string()),
                kv("lockstep_waited_s", format!("{:.3}", waited.as_secs_f64())),
            ]
            .into_iter()
            .chain(
                judges
                    .iter()
                    .map(|(a, j)| kv(&judged_dropped_key(*a), j.counts().dropped_moving.to_string())),
            )
            .collect(),
        }],
    }
}

/// `stamp` read on the driver's clock, `ahead` s ahead.
fn driver_clock(stamp: rosrust::Time, ahead: f64) -> rosrust::Time {
    if ahead == 0.0 {
        stamp
    } else {
        convert::ros_time(convert::seconds(stamp) + ahead)
    }
}

/// Check the simulated clock's pace and the camera's clock offset (said in the log when set).
fn check_clocks(p: &SimNodeParams) -> Result<(), NodeError> {
    if !(p.real_time_factor > 0.0 && p.real_time_factor.is_finite()) {
        return Err(NodeError::Invalid(format!("real_time_factor = {}", p.real_time_factor)));
    }
    crate::validate::in_range("camera_stamp_offset_s", p.camera_stamp_offset_s, -60.0, 60.0)?;
    crate::validate::in_range("command_lockstep_s", p.command_lockstep_s, 0.0, 1.0)?;
    crate::validate::in_range("pose_lockstep_s", p.pose_lockstep_s, 0.0, 1.0)?;
    if p.camera_stamp_offset_s != 0.0 {
        rosrust::ros_warn!(
            "lbr_med_sim: the camera's stamps are {:+.0} ms off the simulator's clock (camera_stamp_offset_s, a test's camera clock offset)",
            p.camera_stamp_offset_s * 1e3
        );
    }
    Ok(())
}

/// Run the node until shutdown. Call after `rosrust::init`.
pub fn run() -> Result<(), NodeError> {
    let p = SimNodeParams::from_tree(&rosrust::name(), params::load_private()?)?;
    check_clocks(&p)?;
    let kin = LbrKinematics::from_model(p.model, &ToolParams::default())?;
    let shared_kin: Arc<dyn Kinematics> = Arc::new(kin.clone());
    let world_cfg = world_config(&p)?;
    let mut world =
        SimWorld::new(&world_cfg.sim, shared_kin, p.seed).map_err(|e| NodeError::Invalid(format!("sim: {e}")))?;
    let dt = world_cfg.sim.dt();

    let command: CommandQueue = Arc::new(Mutex::new(std::collections::VecDeque::with_capacity(COMMAND_QUEUE)));
    let _sub = subscribe_command(&p, &command)?;
    let out = Outputs::new(&p)?;
    let mut camera = if p.camera_enabled {
        Some(SimCamera::start(&p)?)
    } else {
        None
    };

    // Simulated time starts at the wall clock, so stamps look like the real driver's.
    let t0 = convert::seconds(rosrust::Time::from(std::time::SystemTime::now()));
    // The wall-clock origin of the pace; moved on by the time the clock waited for the
    // camera in lockstep, so that the simulation runs slower then instead of catching up
    // in a burst.
    let mut wall0 = Instant::now();
    let (mut fri, mut truth) = (Every::new(p.fri_rate_hz, t0), Every::new(10.0, t0));
    let mut frames = Every::new(p.camera_rate_hz, t0);
    let mut last_measurement = f64::NEG_INFINITY;
    rosrust::ros_info!(
        "lbr_med_sim: {:?}, world protocol '{}', FRI {} Hz, physics {} s, x{} real time, clock {}",
        p.model,
        p.world_protocol,
        p.fri_rate_hz,
        dt,
        p.real_time_factor,
        p.publish_clock
    );
    let mut arm = ArmCommand::new(&p, &world, t0)?;
    let mut poses = PoseLockstep::start(&p, t0)?;
    while rosrust::is_ok() {
        let now = if p.publish_clock {
            t0 + world.time()
        } else {
            convert::seconds(rosrust::now())
        };
        let t = world.time();
        wall0 += arm.await_command(&command, t) + poses.as_mut().map_or(Duration::ZERO, |l| l.await_pose(t));
        arm.step(&command, &mut world, now);
        if let Err(e) = world.step(dt) {
            return Err(NodeError::Invalid(format!("simulation stopped: {e}")));
        }
        let t = t0 + world.time();
        let stamp = if p.publish_clock {
            convert::ros_time(t)
        } else {
            rosrust::now()
        };
        if let Some(c) = &out.clock {
            let _ = c.send(rosgraph_msgs::Clock { clock: stamp });
        }
        if fri.due(t) {
            out.driver(&p, &world, driver_clock(stamp, arm.clock_ahead), 1.0 / p.fri_rate_hz);
        }
        arm.report(t, stamp);
        let live = trocar_live(
            p.trocar_dropout_after_s,
            p.trocar_dropout_from,
            world.time(),
            arm.first_motion,
        );
        if let (true, Some(cam)) = (live, camera.as_mut()) {
            if frames.due(t) {
                wall0 += cam.capture(&world, camera_stamp(stamp, p.camera_stamp_offset_s));
            }
        }
        if live {
            out.direct_pose(&p, &world, t0, stamp, &mut last_measurement);
        }
        if truth.due(t) {
            out.truth(&p, &world, stamp);
        }
        // Pace: simulated time runs real_time_factor times as fast as the wall clock.
        let ahead = world.time() / p.real_time_factor - wall0.elapsed().as_secs_f64();
        if ahead > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(ahead));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::markerless::TrocarModel;
    use nalgebra::Vector3;

    #[test]
    fn the_trocar_sources_stop_after_their_time_from_the_start_or_the_first_motion() {
        use DropoutFrom::{FirstMotion, Start};
        assert!(trocar_live(-1.0, Start, 1e6, None));
        assert!(trocar_live(2.0, Start, 1.99, None) && !trocar_live(2.0, Start, 2.0, None));
        assert!(!trocar_live(0.0, Start, 0.0, None), "0: no pose from the start");
        // From the first motion: live however long the start-up takes, then 1 s more.
        assert!(trocar_live(1.0, FirstMotion, 30.0, None));
        assert!(trocar_live(1.0, FirstMotion, 30.9, Some(30.0)));
        assert!(!trocar_live(1.0, FirstMotion, 31.0, Some(30.0)));
    }

    /// The node's parameters as the launch file loads them: `config/lbr_med_sim.yaml` in
    /// the private namespace, `config/sim.yaml` under `~world` (through JSON, as the
    /// parameter server hands them over).
    fn shipped() -> SimNodeParams {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        let read = |f: &str| -> serde_json::Value { crate::config::from_yaml_file(&dir.join(f)).unwrap() };
        let mut tree = read("lbr_med_sim.yaml");
        tree["world"] = read("sim.yaml");
        SimNodeParams::from_tree("lbr_med_sim", tree).unwrap()
    }

    #[test]
    fn the_right_camera_renders_the_marker_and_the_trocar_and_a_bad_one_names_its_key() {
        let p = shipped();
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        let cam = CameraModel::from_yaml_file(&dir.join("camera_zedm.yaml")).unwrap();
        let marker_t_trocar = p.camera.marker_t_trocar.to_isometry().unwrap();
        // As sim.launch sets it.
        let stereo = SimCameraParams {
            right_calibration_file: dir.join("camera_zedm_right.yaml").to_string_lossy().into_owned(),
            ..p.camera.clone()
        };
        // The marker's scene renders the right image too (a stereo camera sends both, and
        // `fused` reads it): the marker where the right camera sees it, 63 mm to the left.
        let marker = SimScene::of(&stereo, 1, &cam, marker_t_trocar).unwrap();
        let right = marker.right_camera().unwrap().clone();
        let port = marker.check_pose();
        let grey = marker.right_frame(&port, 0.0, 1).unwrap();
        let view = crate::vision::ImageView::new(&grey, right.width, right.height, 1).unwrap();
        let mut det = crate::vision::MarkerDetector::new(p.camera.marker.clone(), &right).unwrap();
        let found = det.detect(&view).unwrap();
        let want = right.stereo_right_t_left() * port * marker_t_trocar.inverse();
        assert_eq!(found.len(), 1);
        let d = found[0].pose_camera_marker.translation.vector - want.translation.vector;
        assert!(d.norm() < 2e-3, "{d:?}");
        let trocar = SimScene::of(
            &SimCameraParams {
                show_marker: false,
                ..stereo.clone()
            },
            1,
            &cam,
            marker_t_trocar,
        )
        .unwrap();
        assert!((trocar.right_camera().unwrap().baseline_m - 0.063).abs() < 1e-9);
        // A camera driver's raw topics (image_pipeline's names), not the ZED's rectified ones.
        assert_eq!(
            [
                p.image_topic.as_str(),
                p.camera_info_topic.as_str(),
                p.right_image_topic.as_str(),
                p.right_camera_info_topic.as_str()
            ],
            [
                topics::SIM_CAMERA_IMAGE,
                topics::SIM_CAMERA_INFO,
                topics::SIM_CAMERA_RIGHT_IMAGE,
                topics::SIM_CAMERA_RIGHT_INFO
            ]
        );
        let bad = SimCameraParams {
            show_marker: false,
            right_calibration_file: dir.join("camera_zedm.yaml").to_string_lossy().into_owned(),
            ..stereo
        };
        let e = SimScene::of(&bad, 1, &cam, marker_t_trocar).err().unwrap().to_string();
        assert!(
            e.contains("camera.right_calibration_file") && e.contains("baseline"),
            "{e}"
        );
    }

    #[test]
    fn a_marker_hidden_within_a_distance_stays_hidden_and_the_trocar_shows() {
        let p = shipped();
        assert_eq!(p.camera.marker_hidden_within_m, 0.0, "never, as shipped");
        let cam = CameraModel::from_yaml_file(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/camera_zedm.yaml"),
        )
        .unwrap();
        let marker_t_trocar = p.camera.marker_t_trocar.to_isometry().unwrap();
        let hidden = SimCameraParams {
            marker_hidden_within_m: 0.25,
            ..p.camera.clone()
        };
        let scene = SimScene::of(&hidden, 1, &cam, marker_t_trocar).unwrap();
        let (far, near) = (
            Isometry3::translation(0.0, 0.0, 0.3),
            Isometry3::translation(0.0, 0.0, 0.2),
        );
        // 0.3 m away: the marker; within 0.25 m: the trocar, and from then on whatever the
        // distance (the marker is gone for good).
        assert!(matches!(scene.at(&far), (SimScene::Marker { .. }, false)));
        assert!(scene.at(&far).0.trocar().is_none());
        assert!(matches!(scene.at(&near), (SimScene::MarkerUntil { .. }, true)));
        let (back, again) = scene.at(&far);
        assert!(back.trocar().is_some() && !again);
        let trocar = SimScene::of(
            &SimCameraParams {
                show_marker: false,
                ..p.camera.clone()
            },
            1,
            &cam,
            marker_t_trocar,
        )
        .unwrap();
        assert!(back.render(&cam, &far).unwrap() == trocar.render(&cam, &far).unwrap());
        // Without the marker, or at 0: nothing to hide. Negative or NaN: refused, naming it.
        let none = SimCameraParams {
            show_marker: false,
            ..hidden.clone()
        };
        assert!(matches!(
            SimScene::of(&none, 1, &cam, marker_t_trocar).unwrap(),
            SimScene::Trocar(_)
        ));
        assert!(matches!(
            SimScene::of(&p.camera, 1, &cam, marker_t_trocar).unwrap(),
            SimScene::Marker { .. }
        ));
        for bad in [-0.1, f64::NAN] {
            let c = SimCameraParams {
                marker_hidden_within_m: bad,
                ..p.camera.clone()
            };
            let e = SimScene::of(&c, 1, &cam, marker_t_trocar).err().unwrap().to_string();
            assert!(e.contains("camera.marker_hidden_within_m"), "{e}");
        }
    }

    #[test]
    fn the_camera_shows_the_marker_by_default_and_the_trocar_without_it() {
        let p = shipped();
        assert!(p.camera.show_marker);
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/camera_zedm.yaml");
        let cam = CameraModel::from_yaml_file(&dir).unwrap();
        let marker_t_trocar = p.camera.marker_t_trocar.to_isometry().unwrap();
        let marker = SimScene::of(&p.camera, 1, &cam, marker_t_trocar).unwrap();
        let without = SimCameraParams {
            show_marker: false,
            ..p.camera.clone()
        };
        let trocar = SimScene::of(&without, 1, &cam, marker_t_trocar).unwrap();
        assert!(matches!(marker, SimScene::Marker { .. }) && matches!(trocar, SimScene::Trocar(_)));
        let bad_model = SimCameraParams {
            trocar_model_file: "/nonexistent/trocar.yaml".into(),
            ..without
        };
        let e = SimScene::of(&bad_model, 1, &cam, marker_t_trocar)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("camera.trocar_model_file"), "{e}");
        let (w, cx, cy) = (cam.width as usize, cam.cx.round() as usize, cam.cy.round() as usize);
        let (t, m) = (
            trocar.render(&cam, &trocar.check_pose()).unwrap(),
            marker.render(&cam, &marker.check_pose()).unwrap(),
        );
        // The trocar 0.3 m ahead: the dark opening (8 mm: 19 px) at the centre, the lit face
        // around it (at 23 px); the marker is another picture.
        assert!(
            t[cy * w + cx] + 40 < t[cy * w + cx + 23],
            "{} {}",
            t[cy * w + cx],
            t[cy * w + cx + 23]
        );
        assert!(t != m);
        // The markerless estimate finds it where it is.
        let mut est = crate::vision::markerless::MarkerlessEstimator::new(&cam, &TrocarModel::shipped()).unwrap();
        let view = crate::vision::ImageView {
            data: &t,
            width: cam.width,
            height: cam.height,
            channels: 1,
        };
        let e = est.estimate(&view, None).unwrap().unwrap();
        assert!(
            (e.axis.point - Vector3::new(0.0, 0.0, 0.3)).norm() < 2e-3,
            "{:?}",
            e.axis
        );
    }

    #[test]
    fn the_built_in_file_is_the_defaults_and_a_partial_tree_takes_the_rest_from_it() {
        let text = include_str!("../../config/lbr_med_sim.yaml");
        let p: SimNodeParams = params::from_yaml_str("lbr_med_sim.yaml", text).unwrap();
        let d = SimNodeParams::default();
        assert_eq!(format!("{p:?}"), format!("{d:?}"));
        // Figures of the file itself.
        assert_eq!(
            (d.fri_rate_hz, d.camera_rate_hz, d.trocar_dropout_after_s),
            (500.0, 15.0, -1.0)
        );
        assert_eq!(
            (d.camera.blur_sigma_px, d.camera.wall_step_px, d.camera.marker.size_m),
            (0.6, 4, 0.04)
        );
        // As the parameter server hands it over: partial; the rest is the file's.
        let p: SimNodeParams = params::from_value(
            "/lbr_med_sim",
            serde_json::json!({"seed": 9, "camera": {"noise_sigma": 0, "marker": {"id": 3}}}),
        )
        .unwrap();
        assert_eq!((p.seed, p.camera.noise_sigma, p.camera.marker.id), (9, 0.0, Some(3)));
        assert_eq!((p.camera.blur_sigma_px, p.camera.marker.size_m), (0.6, 0.04));
        assert_eq!(
            (p.camera.frame.as_str(), p.fri_rate_hz),
            ("camera_optical_frame", 500.0)
        );
        // The old keys are refused, naming the new ones.
        for (old, new) in [
            (serde_json::json!({"trocar_dropout_after": 2}), "trocar_dropout_after_s"),
            (serde_json::json!({"camera": {"blur_sigma": 1}}), "camera.blur_sigma_px"),
            (serde_json::json!({"camera": {"wall_step": 2}}), "camera.wall_step_px"),
            (
                serde_json::json!({"camera": {"marker": {"size": 0.05}}}),
                "marker.size_m",
            ),
        ] {
            let e = params::from_value::<SimNodeParams>("/lbr_med_sim", old).unwrap_err();
            assert!(e.message.contains(&format!("is now `{new}`")), "{e}");
        }
        // An error inside the simulator's own tree is named under `world`.
        let e = SimNodeParams::from_tree("/lbr_med_sim", serde_json::json!({"seed": 2, "world": {"simm": {}}}))
            .unwrap_err();
        assert!(e.what == "/lbr_med_sim/world" && e.message.contains("simm"), "{e}");
        let p = SimNodeParams::from_tree("/lbr_med_sim", serde_json::json!({"seed": 2})).unwrap();
        assert_eq!((p.seed, &p.world), (2, &SimConfig::default()));
    }

    #[test]
    fn the_camera_stamps_its_frames_with_its_own_clock_offset() {
        let t = convert::ros_time(1_800_000_000.25);
        assert_eq!(camera_stamp(t, 0.0), t);
        let behind = convert::seconds(camera_stamp(t, -0.2)) - convert::seconds(t);
        let ahead = convert::seconds(camera_stamp(t, 0.02)) - convert::seconds(t);
        assert!(
            (behind + 0.2).abs() < 1e-6 && (ahead - 0.02).abs() < 1e-6,
            "{behind} {ahead}"
        );
        assert_eq!(shipped().camera_stamp_offset_s, 0.0);
    }

    #[test]
    fn the_node_runs_the_realistic_world_by_default() {
        let p = shipped();
        assert_eq!(p.world_protocol, "realistic");
        let w = world_config(&p).unwrap();
        assert_eq!(w.sim.trocar.port_diameter_m, 0.0055);
        assert!(w.sim.seal.static_friction_n > 0.0 && w.sim.breathing.amplitude_axial_m > 0.0);
        assert!(w.sim.torque_sensor.bias_nm > 0.0 && w.sim.arm.joint_stiffness_nm_per_rad[0] > 0.0);
        let paper = world_config(&SimNodeParams {
            world_protocol: "paper".into(),
            ..p.clone()
        })
        .unwrap();
        assert_eq!(paper.sim.trocar.port_diameter_m, 0.007);
        assert!(world_config(&SimNodeParams {
            world_protocol: "nope".into(),
            ..p
        })
        .is_err());
    }
}
