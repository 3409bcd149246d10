//! The `hand_eye_calibration` node: eye-in-hand calibration from live topics. Joint states
//! in (the flange pose through the KDL chain), the estimator's marker pose in the camera
//! (`/trocar_estimator/marker_pose`) and camera_info in; services (std_srvs/Trigger)
//! `~take_sample`, `~remove_sample`, `~compute`, `~auto`, `~save`, `~save_force`; `~samples`
//! (the count and the rotation spread) and `~markers` (the calibrated camera frame, each
//! sample's marker) out. The maths is `vision::hand_eye`'s; `~auto` streams joint commands on
//! the driver's command topic through the controller's command guard (the shipped `guard:` of
//! `config/controller.yaml`: its speed, acceleration and position limits,
//! [`crate::control::safety::guard::CommandGuard::follow`]) and, on stale joint states or an
//! arm not following, brakes to a stop within the same limits and holds there. A sample waits
//! for the arm to be still, then watches the marker for a window (`vision::hand_eye::target`:
//! a still target's mean, a breathing one's same phase). `~save` writes only a calibration
//! within the preflight's residual bounds (`~save_force`: whatever its residuals), by default
//! under `$ROS_HOME` (never into the package).

use std::collections::VecDeque;
use std::f64::consts::PI;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use nalgebra::{Isometry3, Vector3};

use super::convert;
use super::msgs::{geometry_msgs, sensor_msgs, std_msgs, visualization_msgs};
use super::node::{lock, reply_service, ros_err, CommandType, NodeError, Reply};
use super::params;
use crate::control::safety::guard::{CommandGuard, GuardParams};
use crate::kinematics::lbr::LbrModel;
use crate::kinematics::{JointVector, Kinematics, LbrKinematics, FLANGE_LINK};
use crate::validate;
use crate::vision::hand_eye::poses::{border_distance_px, plan, projected_corners, PlanParams};
use crate::vision::hand_eye::quality::{camera_info_warning, within_bounds};
use crate::vision::hand_eye::samples::Refusal;
use crate::vision::hand_eye::target::{assess, Assessment, Detection, TargetRules};
use crate::vision::hand_eye::{
    calibrate_samples, file_text, AcceptanceRules, Calibration, ObservationModel, Sample, SampleSet, Stillness,
};
use crate::vision::{CameraModel, ImageKindSetting};

/// Parameters of the node (its private namespace; `config/hand_eye_calibration.yaml`, whose
/// values, built in, are the defaults: [`crate::config::HAND_EYE_CALIBRATION`]).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct HandEyeNodeParams {
    /// Arm model when `urdf_file` is empty.
    pub model: LbrModel,
    /// URDF with the chain `lbr_link_0` -> `lbr_link_ee` ('' = built-in model).
    pub urdf_file: String,
    /// Joint names in chain order, as in the joint states.
    pub joint_names: Vec<String>,
    /// Robot base frame (the markers are drawn in it).
    pub base_frame: String,
    /// Joint states in.
    pub joint_states_topic: String,
    /// The estimator's marker pose in the camera optical frame.
    pub marker_pose_topic: String,
    /// CameraInfo in (the camera model of the detections).
    pub camera_info_topic: String,
    /// The estimator's image, whose CameraInfo `camera_info_topic` is: it is read as the
    /// estimator reads it (`image_kind`).
    pub image_topic: String,
    /// How the CameraInfo is read: `by_topic_name` (`image_topic`'s last name `image_rect*`:
    /// rectified, P and no distortion; any other: raw, K and D), `raw` or `rectified`.
    pub image_kind: ImageKindSetting,
    /// The driver's joint position command (for `~auto`).
    pub command_topic: String,
    /// `trajectory` (one-point JointTrajectory) or `float64_multi_array`.
    pub command_type: CommandType,
    /// The current hand-eye guess (`~auto` plans through it), a hand-eye file (the
    /// project's or easy_handeye's).
    pub hand_eye_file: String,
    /// Where `~save` writes ('' = `$ROS_HOME/trocar_docking/hand_eye.yaml`, `$ROS_HOME`
    /// by default `~/.ros`: never the package's shipped file).
    pub output_file: String,
    /// The marker's side, m.
    pub marker_size_m: f64,
    /// `~auto`: the fastest joint speed, rad/s.
    pub max_joint_speed_rad_s: f64,
    /// `~auto`: command rate, Hz.
    pub command_rate_hz: f64,
    /// `~auto`: at each pose, wait at most this long for the arm and the detection to be still, s.
    pub settle_timeout_s: f64,
    /// `~auto`: stop when a joint lags its command by more than this, rad.
    pub max_tracking_error_rad: f64,
    /// Joint states or detections older than this are stale, s.
    pub stale_after_s: f64,
    /// The acceptance rules' still period of the arm, s.
    pub still_for_s: f64,
    /// Watch the marker at most this long at a pose (longer than a breath), s.
    pub target_window_s: f64,
    /// The marker within 0.5 mm / 0.3 deg this long is still, s.
    pub target_still_s: f64,
    /// The acceptance rules' border margin, px.
    pub border_margin_px: f64,
    /// The automatic mode's tilt about the image axes, deg.
    pub auto_tilt_deg: f64,
    /// The automatic mode's roll about the line of sight, deg.
    pub auto_roll_deg: f64,
}

crate::shipped_defaults!(
    HandEyeNodeParams,
    crate::config::HAND_EYE_CALIBRATION,
    [],
    deserialize_only
);

impl HandEyeNodeParams {
    /// Range checks, each naming its key.
    pub fn validate(&self) -> Result<(), NodeError> {
        validate::in_range("marker_size_m", self.marker_size_m, 0.005, 1.0)?;
        validate::in_range("max_joint_speed_rad_s", self.max_joint_speed_rad_s, 0.01, 1.0)?;
        validate::in_range("command_rate_hz", self.command_rate_hz, 10.0, 1000.0)?;
        validate::in_range("settle_timeout_s", self.settle_timeout_s, 0.5, 60.0)?;
        validate::in_range("max_tracking_error_rad", self.max_tracking_error_rad, 0.001, 0.5)?;
        validate::in_range("stale_after_s", self.stale_after_s, 0.01, 5.0)?;
        validate::in_range("still_for_s", self.still_for_s, 0.0, 10.0)?;
        validate::in_range("target_window_s", self.target_window_s, 1.0, 30.0)?;
        validate::in_range("target_still_s", self.target_still_s, 0.2, self.target_window_s)?;
        validate::in_range("border_margin_px", self.border_margin_px, 0.0, 200.0)?;
        validate::in_range("auto_tilt_deg", self.auto_tilt_deg, 5.0, 45.0)?;
        validate::in_range("auto_roll_deg", self.auto_roll_deg, 0.0, 90.0)?;
        if self.joint_names.len() != 7 {
            return Err(NodeError::Invalid(format!(
                "`joint_names`: 7 names are needed, got {}",
                self.joint_names.len()
            )));
        }
        Ok(())
    }

    /// The sample rules of these parameters.
    pub fn rules(&self) -> AcceptanceRules {
        AcceptanceRules::new(self.still_for_s, self.border_margin_px)
    }

    /// The automatic mode's pose plan of these parameters.
    pub fn plan_params(&self) -> PlanParams {
        PlanParams::new(
            self.auto_tilt_deg.to_radians(),
            self.auto_roll_deg.to_radians(),
            self.marker_size_m,
        )
    }

    /// How a sample's target is watched.
    pub fn target_rules(&self) -> TargetRules {
        TargetRules::new(self.target_window_s, self.target_still_s)
    }

    /// Where `~save` writes: `output_file`, else [`default_output_path`] of the environment.
    pub fn output_path(&self) -> Result<PathBuf, String> {
        if self.output_file.is_empty() {
            default_output_path(
                std::env::var("ROS_HOME").ok().as_deref(),
                std::env::var("HOME").ok().as_deref(),
            )
        } else {
            Ok(PathBuf::from(&self.output_file))
        }
    }
}

/// The default file of `~save`: `trocar_docking/hand_eye.yaml` under `ros_home`
/// (`$ROS_HOME`), else under `home`/.ros (ROS's own default for `ROS_HOME`, as roslaunch's
/// logs), never the package's shipped `config/hand_eye.yaml`.
pub fn default_output_path(ros_home: Option<&str>, home: Option<&str>) -> Result<PathBuf, String> {
    let base = match (ros_home.filter(|s| !s.is_empty()), home.filter(|s| !s.is_empty())) {
        (Some(r), _) => PathBuf::from(r),
        (None, Some(h)) => PathBuf::from(h).join(".ros"),
        (None, None) => return Err("neither ROS_HOME nor HOME is set: set the parameter `output_file`".into()),
    };
    Ok(base.join("trocar_docking").join("hand_eye.yaml"))
}

/// What the callbacks and services share.
struct State {
    q: Option<(f64, JointVector)>,
    marker: Option<(f64, Isometry3<f64>)>,
    camera: Option<CameraModel>,
    stillness: Stillness,
    /// The recent detections (the last `target_window_s` and more).
    detections: VecDeque<Detection>,
    set: SampleSet,
    calibration: Option<Calibration>,
    auto_running: bool,
}

/// The node: parameters, chain, state, publishers.
struct Node {
    p: HandEyeNodeParams,
    kin: LbrKinematics,
    guess: Isometry3<f64>,
    state: Mutex<State>,
    samples: rosrust::Publisher<std_msgs::String>,
    markers: rosrust::Publisher<visualization_msgs::MarkerArray>,
    trajectory: Option<rosrust::Publisher<convert::AsStamped>>,
    multiarray: Option<rosrust::Publisher<std_msgs::Float64MultiArray>>,
}

fn now() -> f64 {
    convert::seconds(rosrust::now())
}

impl Node {
    fn fresh<T: Copy>(&self, v: Option<(f64, T)>, t: f64) -> Option<T> {
        v.filter(|(at, _)| t - at <= self.p.stale_after_s).map(|(_, x)| x)
    }

    fn model(&self, st: &State) -> ObservationModel {
        ObservationModel {
            camera: st.camera.clone(),
            marker_size: self.p.marker_size_m,
        }
    }

    /// `~take_sample`: wait (at most `settle_timeout_s`) for the arm to be still, then watch
    /// the marker (at most `target_window_s`) and take the sample the window gives.
    fn take_sample(&self) -> Reply {
        let t0 = now();
        loop {
            std::thread::sleep(Duration::from_millis(100));
            if !rosrust::is_ok() {
                return Err("shutting down".into());
            }
            if let Some(msg) = self.watch(t0)? {
                return Ok(msg);
            }
        }
    }

    /// One look at the arm and the window since `t0`: `None` to keep waiting.
    fn watch(&self, t0: f64) -> Result<Option<String>, String> {
        let t = now();
        let mut st = lock(&self.state);
        let q = self.fresh(st.q, t).ok_or("no fresh joint state")?;
        let camera = st
            .camera
            .clone()
            .ok_or_else(|| camera_info_warning(None).unwrap_or_default())?;
        let arm = st.stillness.arm_still_for(t, self.p.stale_after_s);
        let needed = self.p.still_for_s;
        if arm < needed {
            if t - t0 > self.p.settle_timeout_s {
                let waited = t - t0;
                let r = Refusal::NotStill {
                    still_s: arm,
                    needed_s: needed,
                };
                return Err(format!("{r} (waited {waited:.1} s)"));
            }
            return Ok(None);
        }
        let rules = self.p.target_rules();
        if t - t0 > self.p.settle_timeout_s + rules.window_s + 1.0 {
            return Err(format!(
                "the arm did not stay still for a {:.1} s window within {:.1} s",
                rules.window_s,
                t - t0
            ));
        }
        // The window begins once the arm has been still `still_for_s`.
        let start = t - arm + needed;
        let base_t_flange = self.kin.fk(&q).map_err(|e| e.to_string())?;
        let base_r_camera = (base_t_flange * self.guess).rotation;
        let reference = st.set.phase_reference();
        let window = st.detections.make_contiguous();
        let watched = match assess(window, start, t, &rules, &base_r_camera, reference.as_ref()) {
            Assessment::Wait => return Ok(None),
            Assessment::TooFewDetections(n) => {
                return Err(Refusal::FewDetections {
                    detections: n,
                    window_s: t - start,
                }
                .to_string())
            }
            Assessment::Drifting(m) => return Err(Refusal::TargetMoving(m).to_string()),
            Assessment::Sample(w) => w,
        };
        let marker = watched.camera_t_marker;
        let border = border_distance_px(&camera, &marker, self.p.marker_size_m).unwrap_or(-1.0);
        let sample = Sample {
            base_t_flange,
            camera_t_marker: marker,
            corners: projected_corners(&camera, &marker, self.p.marker_size_m),
        };
        let i = st
            .set
            .try_add_moving(sample, arm, border, watched.moving)
            .map_err(|e| e.to_string())?;
        let how = match &watched.moving {
            None => format!("the marker still, {} detections averaged", watched.detections),
            Some(m) => format!(
                "target moving: {m}; sampled at its lowest point ({} detections averaged)",
                watched.detections
            ),
        };
        let msg = format!("sample {} taken ({how}); {}", i + 1, self.summary(&st));
        self.publish_samples(&st);
        Ok(Some(msg))
    }

    fn summary(&self, st: &State) -> String {
        format!(
            "{} samples, rotation spread {:.1} deg",
            st.set.samples().len(),
            st.set.rotation_spread_rad().to_degrees()
        )
    }

    fn publish_samples(&self, st: &State) {
        let _ = self.samples.send(std_msgs::String { data: self.summary(st) });
    }

    /// `~remove_sample`: the last one.
    fn remove_sample(&self) -> Reply {
        let mut st = lock(&self.state);
        st.set.remove_last().ok_or("no sample to remove")?;
        let msg = format!("last sample removed; {}", self.summary(&st));
        self.publish_samples(&st);
        Ok(msg)
    }

    /// `~compute`: ViSP + refinement, held-out residuals, warnings and faults.
    fn compute(&self) -> Reply {
        let mut st = lock(&self.state);
        let mut c = calibrate_samples(st.set.samples(), &self.model(&st)).map_err(|e| e.to_string())?;
        c.warnings.extend(st.set.target_note());
        let msg = describe(&c, &self.guess, st.camera.as_ref());
        let faults = c.faults.clone();
        st.calibration = Some(c);
        if faults.is_empty() {
            Ok(msg)
        } else {
            Err(msg)
        }
    }

    /// `~save`: the computed calibration to `output_file`, if within the preflight's bounds.
    fn save(&self) -> Reply {
        self.write(false)
    }

    /// `~save_force`: the same, whatever its residuals (never with faults).
    fn save_force(&self) -> Reply {
        self.write(true)
    }

    fn write(&self, force: bool) -> Reply {
        let st = lock(&self.state);
        let c = st
            .calibration
            .as_ref()
            .ok_or("nothing computed yet: call ~compute first")?;
        if !c.faults.is_empty() {
            return Err(format!(
                "not saved, the calibration has faults: {}",
                c.faults.join("; ")
            ));
        }
        let lim = crate::preflight::Limits::default();
        let bounds = within_bounds(c, lim.hand_eye_max_residual_m, lim.hand_eye_max_residual_rad);
        if let (Err(e), false) = (&bounds, force) {
            return Err(format!(
                "not saved: {e}; take more samples over a wider spread, with the arm and the target still, or \
                 ~save_force to write it anyway"
            ));
        }
        let date = crate::preflight::date_of(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64()),
        );
        let text = file_text(
            "the `hand_eye_calibration` node",
            &date,
            &c.fit,
            Some(&c.held_out),
            &c.warnings,
        )
        .map_err(|e| e.to_string())?;
        let path = self.p.output_path()?;
        let shown = path.display();
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        }
        std::fs::write(&path, text).map_err(|e| format!("{shown}: {e}"))?;
        let over = bounds
            .err()
            .map_or(String::new(), |e| format!("; FORCED over the bounds: {e}"));
        Ok(format!(
            "saved to {shown} ({} samples, calibrated {date}); dock with robot.launch hand_eye:={shown}{over}",
            c.fit.samples
        ))
    }

    /// Send one joint command.
    fn command(&self, q: &JointVector, time_from_start: f64) {
        if let Some(p) = &self.trajectory {
            let _ = p.send(convert::trajectory_command(
                rosrust::now(),
                &self.p.joint_names,
                q,
                time_from_start,
            ));
        }
        if let Some(p) = &self.multiarray {
            let _ = p.send(convert::multiarray_command(q));
        }
    }

    /// Move to `target` on a cosine profile at most `max_joint_speed_rad_s` fast, streaming
    /// commands through the command guard; on stale joint states or an arm lagging its
    /// command, brake to a stop within the guard's limits, hold there and stop with the
    /// reason.
    fn move_to(&self, target: &JointVector) -> Result<(), String> {
        let start = self.fresh(lock(&self.state).q, now()).ok_or("no fresh joint state")?;
        let delta = target - start;
        let duration = (delta.amax() * PI / (2.0 * self.p.max_joint_speed_rad_s)).max(0.2);
        let dt = 1.0 / self.p.command_rate_hz;
        let steps = (duration / dt).ceil() as usize;
        // The arm is at rest at the start of each move (the last one ended standing).
        let mut guard = CommandGuard::new(GuardParams::default(), self.kin.limits());
        let mut sent = start;
        // The commands of the last `stale_after_s` (a joint state accepted as fresh may be
        // that old: on a loaded host it arrives late), the lag measured from the nearest.
        let mut recent: VecDeque<(f64, JointVector)> = VecDeque::from([(now(), start)]);
        for k in 1..=steps + (0.5 / dt) as usize {
            let s = (k.min(steps) as f64 / steps as f64 * PI).cos();
            let q_cmd = start + delta * ((1.0 - s) / 2.0);
            let t = now();
            while recent.len() > 1 && recent.front().is_some_and(|(at, _)| t - at > self.p.stale_after_s) {
                recent.pop_front();
            }
            let measured = self.fresh(lock(&self.state).q, t);
            let lag = |q: &JointVector| recent.iter().map(|(_, c)| (q - c).amax()).fold(f64::INFINITY, f64::min);
            let fault = match measured {
                None => Some("joint states stale".to_string()),
                Some(q) if lag(&q) > self.p.max_tracking_error_rad + delta.amax() * dt * 2.0 => Some(format!(
                    "the arm lags its commands of the last {:.2} s by {:.3} rad",
                    self.p.stale_after_s,
                    lag(&q)
                )),
                _ => None,
            };
            if let Some(f) = fault {
                self.brake(&mut guard, sent, dt);
                return Err(format!("motion stopped, the arm held: {f}"));
            }
            if !rosrust::is_ok() {
                return Err("shutting down".into());
            }
            sent = guard.follow(&sent, &q_cmd, dt);
            self.command(&sent, 2.0 * dt);
            recent.push_back((t, sent));
            std::thread::sleep(Duration::from_secs_f64(dt));
        }
        Ok(())
    }

    /// Brake from `sent` to a stop within the guard's limits, streaming the commands.
    fn brake(&self, guard: &mut CommandGuard, mut sent: JointVector, dt: f64) {
        let most = (guard.max_velocity().amax() / (guard.max_acceleration() * dt)).ceil() as usize + 2;
        for _ in 0..most {
            if guard.velocity().amax() == 0.0 || !rosrust::is_ok() {
                break;
            }
            sent = guard.follow(&sent, &sent, dt);
            self.command(&sent, 2.0 * dt);
            std::thread::sleep(Duration::from_secs_f64(dt));
        }
        self.command(&sent, 2.0 * dt);
    }

    /// `~auto`: 12 poses around the current one, a sample at each, back, compute.
    fn auto(&self) -> Reply {
        {
            let mut st = lock(&self.state);
            if st.auto_running {
                return Err("~auto is already running".into());
            }
            st.auto_running = true;
        }
        let r = self.auto_run();
        lock(&self.state).auto_running = false;
        r
    }

    fn auto_run(&self) -> Reply {
        let t0 = std::time::Instant::now();
        // The start: a fresh joint state, detection and camera_info, waited for at most
        // `settle_timeout_s` (on a loaded host a detection may come later than `stale_after_s`).
        let start = || -> Result<_, String> {
            let st = lock(&self.state);
            let t = now();
            Ok((
                self.fresh(st.q, t).ok_or("no fresh joint state")?,
                self.fresh(st.marker, t)
                    .ok_or("no marker detection: bring the marker into view")?,
                st.camera
                    .clone()
                    .ok_or_else(|| camera_info_warning(None).unwrap_or_default())?,
            ))
        };
        let mut first = start();
        while first.is_err() && t0.elapsed().as_secs_f64() < self.p.settle_timeout_s && rosrust::is_ok() {
            std::thread::sleep(Duration::from_millis(50));
            first = start();
        }
        let (q0, marker, camera) = first?;
        let plan_params = self.p.plan_params();
        let poses = plan(&self.kin, &q0, &self.guess, &marker, &camera, &plan_params).map_err(|e| e.to_string())?;
        let mut notes = Vec::new();
        for (i, q) in poses.iter().enumerate() {
            self.move_to(q)?;
            if let Err(e) = self.take_sample() {
                notes.push(format!("pose {}: {e}", i + 1));
            }
        }
        self.move_to(&q0)?;
        let computed = self.compute();
        let secs = t0.elapsed().as_secs_f64();
        let head = format!("{} poses in {secs:.0} s", poses.len());
        let skipped = if notes.is_empty() {
            String::new()
        } else {
            format!("; skipped: {}", notes.join("; "))
        };
        match computed {
            Ok(m) => Ok(format!("{head}{skipped}; {m}")),
            Err(m) => Err(format!("{head}{skipped}; {m}")),
        }
    }

    /// The calibrated camera frame at the current pose and each sample's marker.
    fn publish_markers(&self) {
        let st = lock(&self.state);
        let emc = st.calibration.as_ref().map_or(self.guess, |c| c.flange_t_camera);
        let stamp = rosrust::now();
        let mut out = Vec::new();
        if let Some(q) = self.fresh(st.q, now()) {
            if let Ok(f) = self.kin.fk(&q) {
                out.extend(axes_markers(stamp, &self.p.base_frame, &(f * emc), 0));
            }
        }
        for (i, s) in st.set.samples().iter().enumerate() {
            let m = s.base_t_flange * emc * s.camera_t_marker;
            out.push(marker_plate(
                stamp,
                &self.p.base_frame,
                &m,
                self.p.marker_size_m,
                10 + i as i32,
            ));
        }
        drop(st);
        let _ = self.markers.send(visualization_msgs::MarkerArray { markers: out });
    }
}

/// The reply of `~compute`: eMc, its change from the guess, the residuals, warnings, faults.
pub fn describe(c: &Calibration, guess: &Isometry3<f64>, camera: Option<&CameraModel>) -> String {
    let e = c.flange_t_camera;
    let t = e.translation.vector;
    let q = e.rotation;
    let h = &c.held_out;
    let mut s = format!(
        "eMc t [{:+.5} {:+.5} {:+.5}] m q_xyzw [{:+.5} {:+.5} {:+.5} {:+.5}] ({:.2} mm, {:.3} deg from the guess); \
         {} samples, spread {:.1} deg, {} axes; held-out residuals {:.3} mm rms ({:.3} max), {:.3} deg rms ({:.3} max)",
        t.x,
        t.y,
        t.z,
        q.i,
        q.j,
        q.k,
        q.w,
        (t - guess.translation.vector).norm() * 1e3,
        q.angle_to(&guess.rotation).to_degrees(),
        c.conditioning.samples,
        c.conditioning.spread_deg,
        c.conditioning.rotation_axes,
        h.position_rms_mm,
        h.position_max_mm,
        h.rotation_rms_deg,
        h.rotation_max_deg
    );
    if let Some(px) = h.reprojection_rms_px {
        s.push_str(&format!(", {px:.3} px"));
    }
    for w in &c.warnings {
        s.push_str(&format!("; WARNING {w}"));
    }
    if let Some(w) = camera_info_warning(camera) {
        s.push_str(&format!("; NOTE {w}"));
    }
    for f in &c.faults {
        s.push_str(&format!("; FAULT {f}"));
    }
    s
}

fn marker_base(stamp: rosrust::Time, frame: &str, id: i32, kind: i32) -> visualization_msgs::Marker {
    visualization_msgs::Marker {
        header: convert::header(stamp, frame),
        ns: "hand_eye".into(),
        id,
        type_: kind,
        action: visualization_msgs::Marker::ADD as i32,
        ..Default::default()
    }
}

/// Three arrows (x red, y green, z blue), 5 cm, for a frame.
fn axes_markers(stamp: rosrust::Time, frame: &str, pose: &Isometry3<f64>, id: i32) -> Vec<visualization_msgs::Marker> {
    [Vector3::x(), Vector3::y(), Vector3::z()]
        .iter()
        .enumerate()
        .map(|(k, axis)| {
            let mut m = marker_base(stamp, frame, id + k as i32, visualization_msgs::Marker::ARROW as i32);
            let o = pose.translation.vector;
            let tip = o + pose.rotation * axis * 0.05;
            m.points = vec![convert::point_msg(&o.into()), convert::point_msg(&tip.into())];
            m.scale = geometry_msgs::Vector3 {
                x: 0.004,
                y: 0.008,
                z: 0.0,
            };
            m.pose.orientation.w = 1.0;
            m.color = std_msgs::ColorRGBA {
                r: (k == 0) as u8 as f32,
                g: (k == 1) as u8 as f32,
                b: (k == 2) as u8 as f32,
                a: 1.0,
            };
            m
        })
        .collect()
}

/// A thin plate where a sample puts the marker.
fn marker_plate(
    stamp: rosrust::Time,
    frame: &str,
    pose: &Isometry3<f64>,
    size: f64,
    id: i32,
) -> visualization_msgs::Marker {
    let mut m = marker_base(stamp, frame, id, visualization_msgs::Marker::CUBE as i32);
    m.pose = convert::pose_msg(pose);
    m.scale = geometry_msgs::Vector3 {
        x: size,
        y: size,
        z: 0.001,
    };
    m.color = std_msgs::ColorRGBA {
        r: 1.0,
        g: 0.6,
        b: 0.0,
        a: 0.5,
    };
    m
}

fn subscribe(node: &Arc<Node>) -> Result<Vec<rosrust::Subscriber>, NodeError> {
    let p = &node.p;
    let n = node.clone();
    let (topic, names) = (p.joint_states_topic.clone(), p.joint_names.clone());
    let joints = rosrust::subscribe(&p.joint_states_topic, 10, move |m: sensor_msgs::JointState| {
        if let Ok(q) = convert::joint_positions(&topic, &m, &names) {
            let t = now();
            let mut st = lock(&n.state);
            let rules = st.set.rules;
            st.stillness.joints(t, q.as_slice(), &rules);
            st.q = Some((t, q));
        }
    })
    .map_err(ros_err)?;
    let n = node.clone();
    let topic = p.marker_pose_topic.clone();
    let marker = rosrust::subscribe(&p.marker_pose_topic, 10, move |m: geometry_msgs::PoseStamped| {
        if let Ok(pose) = convert::pose(&topic, &m.pose) {
            let t = now();
            let mut st = lock(&n.state);
            let rules = st.set.rules;
            st.stillness.marker(t, Some(&pose), &rules);
            st.marker = Some((t, pose));
            let keep = n.p.target_window_s + n.p.settle_timeout_s + 2.0;
            while st.detections.front().is_some_and(|d| d.t < t - keep) {
                st.detections.pop_front();
            }
            st.detections.push_back(Detection {
                t,
                camera_t_marker: pose,
            });
        }
    })
    .map_err(ros_err)?;
    let n = node.clone();
    let kind = p.image_kind.resolve(&p.image_topic);
    let info = rosrust::subscribe(&p.camera_info_topic, 2, move |m: sensor_msgs::CameraInfo| {
        lock(&n.state).camera = super::convert::image::camera_model(&m, kind).ok();
    })
    .map_err(ros_err)?;
    Ok(vec![joints, marker, info])
}

/// A service's handler on the node.
type Handler = fn(&Node) -> Reply;

fn services(node: &Arc<Node>) -> Result<Vec<rosrust::Service>, NodeError> {
    let handlers: [(&str, Handler); 6] = [
        ("~take_sample", Node::take_sample),
        ("~remove_sample", Node::remove_sample),
        ("~compute", Node::compute),
        ("~save", Node::save),
        ("~save_force", Node::save_force),
        ("~auto", Node::auto),
    ];
    handlers
        .iter()
        .map(|(name, f)| {
            let (n, f) = (node.clone(), *f);
            reply_service(name, move || f(&n))
        })
        .collect()
}

/// Run the node until shutdown. Call after `rosrust::init`.
pub fn run() -> Result<(), NodeError> {
    let p: HandEyeNodeParams = params::load_private()?;
    p.validate()?;
    let kin = LbrKinematics::from_model_or_file(p.model, &p.urdf_file, FLANGE_LINK)?;
    let guess = if p.hand_eye_file.is_empty() {
        crate::vision::EstimatorParams::default()
            .flange_t_camera
            .to_isometry()
            .map_err(|e| NodeError::Invalid(format!("estimator.flange_t_camera: {e}")))?
    } else {
        params::hand_eye_mount(&p.hand_eye_file, p.model, &p.urdf_file)
            .map_err(NodeError::Invalid)?
            .flange_t_camera
    };
    let (trajectory, multiarray) = match p.command_type {
        CommandType::Trajectory => (Some(rosrust::publish(&p.command_topic, 10).map_err(ros_err)?), None),
        CommandType::Float64MultiArray => (None, Some(rosrust::publish(&p.command_topic, 10).map_err(ros_err)?)),
    };
    let node = Arc::new(Node {
        state: Mutex::new(State {
            q: None,
            marker: None,
            camera: None,
            stillness: Stillness::default(),
            detections: VecDeque::new(),
            set: SampleSet::new(p.rules()),
            calibration: None,
            auto_running: false,
        }),
        samples: rosrust::publish("~samples", 2).map_err(ros_err)?,
        markers: rosrust::publish("~markers", 2).map_err(ros_err)?,
        trajectory,
        multiarray,
        kin,
        guess,
        p,
    });
    let _subs = subscribe(&node)?;
    let _services = services(&node)?;
    let out = node.p.output_path().map_err(NodeError::Invalid)?;
    rosrust::ros_info!(
        "hand_eye_calibration: marker pose on {}, joints on {}, commands on {}; saves to {}",
        node.p.marker_pose_topic,
        node.p.joint_states_topic,
        node.p.command_topic,
        out.display()
    );
    while rosrust::is_ok() {
        std::thread::sleep(Duration::from_millis(500));
        node.publish_markers();
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    #[test]
    fn the_built_in_file_is_the_defaults_and_bad_values_name_their_key() {
        let text = include_str!("../../config/hand_eye_calibration.yaml");
        let p: HandEyeNodeParams = params::from_yaml_str("hand_eye_calibration.yaml", text).unwrap();
        p.validate().unwrap();
        let d = HandEyeNodeParams::default();
        assert_eq!(format!("{p:?}"), format!("{d:?}"));
        assert_eq!(
            (d.marker_size_m, d.max_joint_speed_rad_s, d.max_tracking_error_rad),
            (0.04, 0.3, 0.05)
        );
        assert_eq!((d.target_window_s, d.target_still_s), (6.5, 2.0));
        // The marker is the estimator's.
        assert_eq!(d.marker_size_m, crate::vision::MarkerSpec::default().size_m);
        // Partial: the rest is the file's.
        let p: HandEyeNodeParams =
            params::from_value("/hand_eye_calibration", serde_json::json!({"auto_tilt_deg": 10})).unwrap();
        assert_eq!(
            (p.auto_tilt_deg, p.auto_roll_deg, p.command_rate_hz),
            (10.0, 25.0, 50.0)
        );
        for (yaml, key) in [
            ("max_joint_speed_rad_s: 3", "max_joint_speed_rad_s"),
            ("marker_size_m: 0", "marker_size_m"),
            ("auto_tilt_deg: 60", "auto_tilt_deg"),
            ("target_still_s: 7", "target_still_s"),
        ] {
            let e = params::from_yaml_str::<HandEyeNodeParams>("t", yaml)
                .unwrap()
                .validate()
                .unwrap_err()
                .to_string();
            assert!(e.contains(&format!("`{key}`")), "{yaml}: {e}");
        }
        assert!(params::from_yaml_str::<HandEyeNodeParams>("t", "max_speed: 1").is_err());
        // The old keys are refused, naming the new ones.
        for (old, new) in [
            ("marker_size", "marker_size_m"),
            ("max_joint_speed", "max_joint_speed_rad_s"),
            ("max_tracking_error", "max_tracking_error_rad"),
        ] {
            let e = params::from_yaml_str::<HandEyeNodeParams>("t", &format!("{old}: 0.1\n")).unwrap_err();
            assert!(e.message.contains(&format!("`{old}`: the key is now `{new}`")), "{e}");
        }
    }

    #[test]
    fn save_writes_under_ros_home_by_default_never_into_the_package() {
        let shipped = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/config/hand_eye.yaml"));
        let d = default_output_path(Some("/data/ros"), Some("/home/lab")).unwrap();
        assert_eq!(d, std::path::Path::new("/data/ros/trocar_docking/hand_eye.yaml"));
        let d = default_output_path(None, Some("/home/lab")).unwrap();
        assert_eq!(d, std::path::Path::new("/home/lab/.ros/trocar_docking/hand_eye.yaml"));
        assert_eq!(
            default_output_path(Some(""), Some("/h")).unwrap(),
            std::path::Path::new("/h/.ros/trocar_docking/hand_eye.yaml")
        );
        assert!(default_output_path(None, None).unwrap_err().contains("output_file"));
        // The shipped parameters take the default; an explicit file is honoured.
        let p = HandEyeNodeParams::default();
        assert!(p.output_file.is_empty());
        assert_ne!(p.output_path().unwrap(), shipped);
        let p = HandEyeNodeParams {
            output_file: "/tmp/mine.yaml".into(),
            ..p
        };
        assert_eq!(p.output_path().unwrap(), std::path::Path::new("/tmp/mine.yaml"));
    }

    #[test]
    fn the_markers_draw_the_frame_axes_along_the_pose() {
        let pose = Isometry3::from_parts(
            nalgebra::Translation3::new(0.1, 0.2, 0.3),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), PI / 2.0),
        );
        let m = axes_markers(rosrust::Time::default(), "b", &pose, 0);
        // x of the frame points along the base's y.
        let tip = &m[0].points[1];
        assert!((tip.x - 0.1).abs() < 1e-9 && (tip.y - 0.25).abs() < 1e-9, "{tip:?}");
        assert_eq!(m.len(), 3);
    }
}
