//! The preflight: the checks of a set-up before the arm moves, on what was observed of it
//! (pure: the ROS side, [`crate::ros::preflight`], gathers the [`Observations`] and prints the
//! [`Report`]). Each check gives one line: its code, pass, fail or not checked, what was seen
//! and, on a failure, what to do.
//!
//! The checks: the driver's streams and their rates (joint states at 100 Hz or more, the
//! LBRState once per FRI cycle, its `sample_time`), the joint names against the controller's
//! URDF, the external torques at rest (the tare's limits, [`crate::control::TareParams`]), the
//! camera's calibration and image rate, the trocar pose (the marker seen) and the marker's
//! size, the hand-eye file (age, residuals), the trocar within reach (the scenario's
//! inverse kinematics, [`Scenario::reachable`], from the current joints), the clock, the
//! camera's clock against the controller's ([`camera_clock`]: two machines), the driver's
//! clock against the controller's and the command's lead ([`driver_clock`]), and a
//! subscriber on the command topic. The FRI session state and control mode are reported as
//! not checked: the driver's LBRState carries neither.

use nalgebra::Isometry3;

pub mod driver_clock;

use crate::control::force::tare::TareParams;
use crate::kinematics::{Kinematics, N_JOINTS};
use crate::sim::scenario::Scenario;

/// How long a right image may trail its left one on the wire before the left image counts
/// as unpaired in `STEREO`, s: the two images travel on two topics, and the newest left
/// images of a window may still wait for theirs (the rostests' image latency reached p99
/// 150 ms at 15 Hz on a busy 2-core host, 2026-12-07).
pub const STEREO_IN_FLIGHT_S: f64 = 0.25;

pub mod camera_clock;
pub use camera_clock::{CameraClock, CameraClockTolerance};

/// The outcome of one check.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Passed.
    Pass,
    /// Failed: nothing may move.
    Fail,
    /// Not applicable to this set-up, or not observable (the detail says why).
    NotChecked,
}

/// One check's line.
#[derive(Debug, Clone, PartialEq)]
pub struct Check {
    /// Stable code (`JOINT_NAMES`, `MARKER`, ...).
    pub code: &'static str,
    /// Outcome.
    pub verdict: Verdict,
    /// What was seen.
    pub detail: String,
    /// What to do when it fails.
    pub fix: &'static str,
}

impl std::fmt::Display for Check {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let tag = match self.verdict {
            Verdict::Pass => "PASS",
            Verdict::Fail => "FAIL",
            Verdict::NotChecked => "SKIP",
        };
        write!(f, "{tag} {:<18} {}", self.code, self.detail)?;
        if self.verdict == Verdict::Fail {
            write!(f, "\n     fix: {}", self.fix)?;
        }
        Ok(())
    }
}

/// Every check's line, in order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Report {
    /// The checks.
    pub checks: Vec<Check>,
}

impl Report {
    /// True when no check failed.
    pub fn passed(&self) -> bool {
        self.first_failure().is_none()
    }

    /// The first failed check.
    pub fn first_failure(&self) -> Option<&Check> {
        self.checks.iter().find(|c| c.verdict == Verdict::Fail)
    }

    /// The codes of the failed checks.
    pub fn failed_codes(&self) -> Vec<&'static str> {
        self.checks
            .iter()
            .filter(|c| c.verdict == Verdict::Fail)
            .map(|c| c.code)
            .collect()
    }
}

impl std::fmt::Display for Report {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for c in &self.checks {
            writeln!(f, "{c}")?;
        }
        match self.failed_codes().as_slice() {
            [] => write!(f, "preflight passed"),
            codes => write!(f, "preflight FAILED: {}", codes.join(", ")),
        }
    }
}

/// The bounds of the checks.
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct Limits {
    /// Lowest rate at which the driver's joint states and LBRState reach the controller, Hz:
    /// its loop reads them at 100 Hz (the driver publishes both once per FRI cycle).
    pub min_driver_hz: f64,
    /// Accepted shortfall of a rate below its nominal value (measurement over a short window).
    pub rate_tolerance: f64,
    /// Lowest camera image rate, Hz: at 5 Hz a frame comes every 0.2 s, so with the
    /// pipeline's ~40 ms and one frame lost the pose is still younger than the controller's
    /// 0.5 s `guard.trocar_timeout_s`; below it the docking would hold on stale poses.
    pub min_image_hz: f64,
    /// Lowest trocar pose rate, Hz (the same reasoning).
    pub min_marker_hz: f64,
    /// Oldest accepted hand-eye calibration, days: the camera mount drifts and is knocked
    /// (a ZED mini on a 3D-printed bracket), and a lab recalibrates at least monthly.
    pub hand_eye_max_age_days: f64,
    /// Largest accepted hand-eye translation residual (the file's max), m.
    pub hand_eye_max_residual_m: f64,
    /// Largest accepted hand-eye rotation residual (the file's max), rad.
    pub hand_eye_max_residual_rad: f64,
    /// The trocar must be reachable with every joint this far inside its limits, deg (the
    /// guard's margin, `guard.position_margin_rad` of config/controller.yaml).
    pub reach_margin_deg: f64,
    /// The longest a camera takes from capture to the controller's machine, s: a frame's
    /// exposure (up to a frame period, 67 ms at 15 Hz) and readout, the driver's
    /// rectification, the network (the simulated camera renders 35-55 ms a frame, more on a
    /// loaded host). Images older than this on arrival put the camera's clock behind
    /// ([`camera_clock`]).
    pub camera_latency_max_s: f64,
}

crate::shipped_defaults!(
    Limits,
    crate::config::DOCKING_CONTROLLER_NODE,
    ["preflight", "limits"],
    deserialize_only
);

impl Limits {
    /// Check every value; the error names the key.
    pub fn validate(&self) -> Result<(), crate::validate::RangeError> {
        use crate::validate::{positive, positive_at_most};
        positive("limits.min_driver_hz", self.min_driver_hz)?;
        positive_at_most("limits.rate_tolerance", self.rate_tolerance, 0.9)?;
        positive("limits.min_image_hz", self.min_image_hz)?;
        positive("limits.min_marker_hz", self.min_marker_hz)?;
        positive("limits.hand_eye_max_age_days", self.hand_eye_max_age_days)?;
        positive("limits.hand_eye_max_residual_m", self.hand_eye_max_residual_m)?;
        positive("limits.hand_eye_max_residual_rad", self.hand_eye_max_residual_rad)?;
        positive_at_most("limits.reach_margin_deg", self.reach_margin_deg, 30.0)?;
        positive_at_most("limits.camera_latency_max_s", self.camera_latency_max_s, 1.0)?;
        Ok(())
    }
}

/// The median interval between consecutive `stamps` (in any order; sorted here), s: a
/// stream's period even when some messages were lost on the way (each loss makes one long
/// interval, which the median passes over while fewer than half are lost). NaN with fewer
/// than two stamps.
pub fn cadence_s(stamps: &[f64]) -> f64 {
    let mut t: Vec<f64> = stamps.iter().copied().filter(|x| x.is_finite()).collect();
    t.sort_by(f64::total_cmp);
    let mut d: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    d.sort_by(f64::total_cmp);
    crate::stats::quantile_sorted(&d, 0.5)
}

/// Stamps of a stream over the window.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Stream {
    /// Messages received.
    pub count: usize,
    /// First to last stamp, s.
    pub span_s: f64,
}

impl Stream {
    /// Messages per second of their stamps (NaN with fewer than two, or no span).
    pub fn rate_hz(&self) -> f64 {
        if self.count < 2 || self.span_s <= 0.0 || !self.span_s.is_finite() {
            return f64::NAN;
        }
        (self.count - 1) as f64 / self.span_s
    }
}

/// The joint states seen.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct JointStates {
    /// Their stamps.
    pub stream: Stream,
    /// Names of the last message.
    pub names: Vec<String>,
    /// Positions of the last message, in its name order.
    pub positions: Vec<f64>,
    /// Largest range of a joint's position over the window, rad.
    pub motion_rad: f64,
}

/// The LBRState seen.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct LbrState {
    /// Their stamps.
    pub stream: Stream,
    /// The FRI cycle of the last message (`sample_time`), s.
    pub sample_time: f64,
    /// The median interval between consecutive stamps, s ([`cadence_s`]): the driver's
    /// period, whatever was lost on the way.
    pub cadence_s: f64,
    /// The external torques of every message, Nm.
    pub tau_ext: Vec<Vec<f64>>,
}

/// The camera's calibration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraInfo {
    /// Focal lengths, px.
    pub fx: f64,
    /// See `fx`.
    pub fy: f64,
    /// Image size, px.
    pub width: u32,
    /// See `width`.
    pub height: u32,
}

/// The camera seen.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Camera {
    /// The last camera_info, if any.
    pub info: Option<CameraInfo>,
    /// The images' stamps.
    pub images: Stream,
    /// Size of the last image, px.
    pub image_size: Option<(u32, u32)>,
    /// The images' stamps, s (the stereo pairs are counted by them).
    pub image_stamps: Vec<f64>,
    /// The stereo pair's right camera, where the estimator reads one (None: it reads no right
    /// image: method marker, or its right topics '').
    pub right: Option<RightCamera>,
}

/// The stereo pair's right camera, as the estimator is set to read it.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RightCamera {
    /// The estimator's right image topic.
    pub topic: String,
    /// The right images' stamps, s.
    pub stamps: Vec<f64>,
    /// The baseline its last CameraInfo gives, m, or why it gives none (None: no CameraInfo).
    pub baseline_m: Option<Result<f64, String>>,
}

/// The trocar pose (the marker) seen.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Marker {
    /// Stamps of the trocar poses.
    pub stream: Stream,
    /// The last pose (base frame).
    pub last: Option<Isometry3<f64>>,
    /// The estimator's marker size, m (None: no estimator, the pose comes directly).
    pub configured_size_m: Option<f64>,
    /// The simulated marker's size, m (the simulator's camera), to compare with.
    pub simulated_size_m: Option<f64>,
    /// The estimator finds the trocar by its shape alone (method `markerless`): no marker,
    /// so no size to check.
    pub markerless: bool,
}

/// What the hand-eye file says.
#[derive(Debug, Clone, PartialEq)]
pub struct HandEye {
    /// The file.
    pub path: String,
    /// Its age, days.
    pub age_days: f64,
    /// Where the age comes from (its `calibrated` date, or the file's modification time).
    pub age_source: &'static str,
    /// The largest translation residual it carries, m.
    pub residual_max_m: Option<f64>,
    /// The largest rotation residual it carries, rad.
    pub residual_max_rad: Option<f64>,
}

/// The simulator, when it is the set-up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Simulator {
    /// Whether it renders the camera (else it publishes the trocar pose directly).
    pub camera: bool,
}

/// Everything the checks look at.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Observations {
    /// The simulator, if it is running (recognised by its node's parameters and `/clock`).
    pub simulator: Option<Simulator>,
    /// `/use_sim_time`.
    pub use_sim_time: bool,
    /// Joint states (None: none arrived).
    pub joint_states: Option<JointStates>,
    /// LBRState (None: none arrived).
    pub lbr_state: Option<LbrState>,
    /// The camera (None: the set-up has none, the simulator's direct pose).
    pub camera: Option<Camera>,
    /// The trocar pose.
    pub marker: Marker,
    /// The hand-eye file (None: no estimator in the set-up; Err: why it cannot be used).
    pub hand_eye: Option<Result<HandEye, String>>,
    /// The driver's clock and the command stream (None: no driver stamps seen).
    pub driver_clock: Option<driver_clock::DriverClock>,
    /// Nodes subscribed to the command topic.
    pub command_subscribers: Vec<String>,
    /// The command topic.
    pub command_topic: String,
    /// The images' stamps against the controller's clock (None: no camera).
    pub camera_clock: Option<CameraClock>,
}

fn check(code: &'static str, ok: bool, detail: String, fix: &'static str) -> Check {
    let verdict = if ok { Verdict::Pass } else { Verdict::Fail };
    Check {
        code,
        verdict,
        detail,
        fix,
    }
}

fn not_checked(code: &'static str, detail: String) -> Check {
    Check {
        code,
        verdict: Verdict::NotChecked,
        detail,
        fix: "",
    }
}

/// Run every check. `kin` is the controller's chain (its URDF's joint names and limits).
pub fn evaluate(obs: &Observations, lim: &Limits, tare: &TareParams, kin: &dyn Kinematics) -> Report {
    let mut checks = vec![clock(obs)];
    checks.extend(driver(obs, lim));
    checks.push(driver_clock::driver_clock_check(
        obs.driver_clock.as_ref(),
        obs.use_sim_time,
    ));
    checks.push(joint_names(obs, kin));
    checks.push(torques_at_rest(obs, tare));
    checks.extend(camera(obs, lim));
    let frame_period = obs.camera.as_ref().map_or(f64::NAN, |c| cadence_s(&c.image_stamps));
    checks.push(camera_clock::camera_clock(obs.camera_clock.as_ref(), lim, frame_period));
    checks.push(stereo(obs, lim));
    checks.push(marker(obs, lim));
    checks.push(hand_eye(obs, lim));
    checks.push(reach(obs, lim, kin));
    checks.push(check(
        "COMMAND_SUBSCRIBER",
        !obs.command_subscribers.is_empty(),
        if obs.command_subscribers.is_empty() {
            format!("nothing subscribes to {}", obs.command_topic)
        } else {
            format!("{} <- {}", obs.command_topic, obs.command_subscribers.join(", "))
        },
        "start the driver's position controller, or set command_topic to the topic it takes",
    ));
    Report { checks }
}

fn clock(obs: &Observations) -> Check {
    let detail = match (obs.use_sim_time, obs.simulator) {
        (true, Some(_)) => "simulated clock (/use_sim_time) from lbr_med_sim: the simulator is the set-up".into(),
        (true, None) => "/use_sim_time is true but no simulator runs: a real robot on a simulated clock".into(),
        (false, Some(_)) => "wall clock; the simulator is the set-up".into(),
        (false, None) => "wall clock (a real robot)".into(),
    };
    check(
        "CLOCK",
        !(obs.use_sim_time && obs.simulator.is_none()),
        detail,
        "rosparam set /use_sim_time false (robot.launch sets it) and restart the nodes",
    )
}

fn driver(obs: &Observations, lim: &Limits) -> Vec<Check> {
    let js = match &obs.joint_states {
        None => check(
            "JOINT_STATES",
            false,
            "no joint states".into(),
            "start the driver (lbr_fri_ros) and the FRI application on the robot; check the topic name",
        ),
        Some(j) => {
            let r = j.stream.rate_hz();
            check(
                "JOINT_STATES",
                r >= lim.min_driver_hz * (1.0 - lim.rate_tolerance),
                format!("{r:.0} Hz (>= {:.0})", lim.min_driver_hz),
                "the driver publishes the joint states at the FRI rate: check the FRI send period and the network",
            )
        }
    };
    let lbr = match &obs.lbr_state {
        None => check(
            "LBR_STATE",
            false,
            "no LBRState".into(),
            "start the driver (lbr_fri_ros) with its state publisher; check the topic name",
        ),
        Some(s) => {
            // The driver's period is the typical interval between stamps; what arrives may be
            // fewer (a subscriber held back by the scheduler drops, rosrust's reader thread
            // keeps eight messages), which counts only against the controller's need.
            let (fri, cadence, r) = (1.0 / s.sample_time, 1.0 / s.cadence_s, s.stream.rate_hz());
            check(
                "LBR_STATE",
                s.sample_time > 0.0
                    && (cadence - fri).abs() <= fri * lim.rate_tolerance
                    && r >= lim.min_driver_hz * (1.0 - lim.rate_tolerance),
                format!(
                    "one every {:.2} ms ({cadence:.0} Hz), FRI cycle {:.1} ms ({fri:.0} Hz); {r:.0} Hz received \
                     ({:.0} % of the cycles, >= {:.0} Hz)",
                    s.cadence_s * 1e3,
                    s.sample_time * 1e3,
                    100.0 * r * s.sample_time,
                    lim.min_driver_hz
                ),
                "the LBRState must come once per FRI cycle: check the FRI send period and the network",
            )
        }
    };
    let fri = not_checked(
        "FRI_STATE",
        "session state (COMMANDING) and control mode (position) not checked: the driver's LBRState \
         carries neither; see them on the smartPAD"
            .into(),
    );
    vec![js, lbr, fri]
}

fn joint_names(obs: &Observations, kin: &dyn Kinematics) -> Check {
    let fix = "make the driver's joint names those of the controller's URDF (urdf_file, model)";
    let Some(j) = &obs.joint_states else {
        return check("JOINT_NAMES", false, "no joint states to compare".into(), fix);
    };
    let want = kin.joint_names();
    let missing: Vec<&str> = want
        .iter()
        .filter(|n| !j.names.contains(n))
        .map(String::as_str)
        .collect();
    let ok = missing.is_empty() && j.names.len() == want.len() && j.positions.len() == j.names.len();
    let detail = if ok {
        format!("{} joints, as the URDF", want.len())
    } else {
        format!(
            "{} names ({}), the URDF has {}; missing: {}",
            j.names.len(),
            j.names.join(" "),
            want.len(),
            if missing.is_empty() {
                "none".into()
            } else {
                missing.join(" ")
            }
        )
    };
    check("JOINT_NAMES", ok, detail, fix)
}

/// The joints of the last joint state in the chain's order, if every name is there.
fn joints_in_chain_order(j: &JointStates, kin: &dyn Kinematics) -> Option<[f64; N_JOINTS]> {
    let mut q = [0.0; N_JOINTS];
    if kin.joint_names().len() != N_JOINTS {
        return None;
    }
    for (qi, name) in q.iter_mut().zip(kin.joint_names()) {
        let k = j.names.iter().position(|n| n == name)?;
        *qi = *j.positions.get(k)?;
    }
    q.iter().all(|v| v.is_finite()).then_some(q)
}

fn torques_at_rest(obs: &Observations, tare: &TareParams) -> Check {
    let fix = "nothing may touch the arm or the scope; check the tool's load data (mass, centre of \
               mass) on the robot and redo the driver's torque calibration";
    let Some(s) = obs.lbr_state.as_ref().filter(|s| !s.tau_ext.is_empty()) else {
        return check("TORQUES_AT_REST", false, "no external torques".into(), fix);
    };
    let n = s.tau_ext[0].len();
    if n == 0
        || s.tau_ext
            .iter()
            .any(|t| t.len() != n || t.iter().any(|v| !v.is_finite()))
    {
        return check(
            "TORQUES_AT_REST",
            false,
            "external torques malformed (count or NaN)".into(),
            fix,
        );
    }
    let m = s.tau_ext.len() as f64;
    let (mut worst_mean, mut worst_sd) = (0.0f64, 0.0f64);
    for k in 0..n {
        let mean = s.tau_ext.iter().map(|t| t[k]).sum::<f64>() / m;
        let var = s.tau_ext.iter().map(|t| (t[k] - mean).powi(2)).sum::<f64>() / m;
        worst_mean = worst_mean.max(mean.abs());
        worst_sd = worst_sd.max(var.sqrt());
    }
    let motion = obs.joint_states.as_ref().map_or(0.0, |j| j.motion_rad);
    check(
        "TORQUES_AT_REST",
        worst_mean <= tare.max_offset_nm && worst_sd <= tare.max_noise_nm && motion <= tare.max_motion_rad,
        format!(
            "largest mean {worst_mean:.2} Nm (<= {:.1}), sd {worst_sd:.2} Nm (<= {:.1}), joint motion {:.4} rad \
             (<= {:.3})",
            tare.max_offset_nm, tare.max_noise_nm, motion, tare.max_motion_rad
        ),
        fix,
    )
}

/// Why the camera's checks are skipped in the simulator's direct mode.
const NO_CAMERA: &str = "no camera: the simulator publishes the trocar pose directly (trocar_source direct)";

fn camera(obs: &Observations, lim: &Limits) -> Vec<Check> {
    let Some(c) = &obs.camera else {
        let why = NO_CAMERA;
        return vec![
            not_checked("CAMERA_INFO", why.into()),
            not_checked("IMAGE_RATE", why.into()),
        ];
    };
    let info = match c.info {
        None => check(
            "CAMERA_INFO",
            false,
            "no camera_info".into(),
            "start the camera driver; check camera_info_topic",
        ),
        Some(i) => {
            let focal = i.fx.is_finite() && i.fy.is_finite() && i.fx > 0.0 && i.fy > 0.0;
            let size = c.image_size.is_some_and(|s| s == (i.width, i.height)) && i.width > 0 && i.height > 0;
            let img = c
                .image_size
                .map_or("no image".to_string(), |(w, h)| format!("images {w}x{h}"));
            check(
                "CAMERA_INFO",
                focal && size,
                format!("fx {:.1} fy {:.1} px, {}x{}; {img}", i.fx, i.fy, i.width, i.height),
                "calibrate the camera (camera_info with finite, positive focal lengths) at the resolution it streams",
            )
        }
    };
    let r = c.images.rate_hz();
    let rate = check(
        "IMAGE_RATE",
        r >= lim.min_image_hz,
        format!("{r:.1} Hz (>= {:.0})", lim.min_image_hz),
        "check the camera's frame rate, its USB link and the image topic",
    );
    vec![info, rate]
}

/// The stereo pair's right image, where the estimator reads one: it must come with the left
/// images (a right image of the same stamp, [`crate::vision::STEREO_MAX_SKEW_S`], with
/// nearly every left image since the first right one: the rate tolerance's share may be
/// missing) and its CameraInfo must give a baseline of 1 mm to 1 m. Without them the
/// estimator runs mono, waiting a few ms per image for the right one, and the markerless
/// docking succeeds less often.
fn stereo(obs: &Observations, lim: &Limits) -> Check {
    let fix = "start the camera's right image and its camera_info (the ZED wrapper: right/image_rect_color, \
               right/camera_info) or set the estimator's right_image_topic and right_camera_info_topic to them; \
               '' for both runs mono on purpose (it docks less often: docs/markerless.md)";
    let Some(c) = &obs.camera else {
        return not_checked("STEREO", NO_CAMERA.into());
    };
    let Some(r) = &c.right else {
        return not_checked(
            "STEREO",
            "the estimator reads no right image (method marker, or its right topics '')".into(),
        );
    };
    let baseline = match &r.baseline_m {
        None => Err("no right camera_info".to_string()),
        Some(Err(e)) => Err(format!("right camera_info: {e}")),
        Some(Ok(b)) => Ok(*b),
    };
    let skew = crate::vision::STEREO_MAX_SKEW_S;
    // From the first right image on (its subscriber may connect after the left one's), to
    // the last: left images newer than the newest right one are still in flight on the
    // other topic while that is within STEREO_IN_FLIGHT_S of the newest left image (a right
    // stream that stopped earlier counts against it).
    let first = r.stamps.iter().copied().fold(f64::INFINITY, f64::min);
    let last = r.stamps.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let newest = c.image_stamps.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let in_flight = |t: f64| newest - last <= STEREO_IN_FLIGHT_S && t > last + skew;
    let left: Vec<f64> = c
        .image_stamps
        .iter()
        .copied()
        .filter(|t| r.stamps.is_empty() || (*t >= first - skew && !in_flight(*t)))
        .collect();
    let paired = left
        .iter()
        .filter(|t| r.stamps.iter().any(|s| (s - *t).abs() <= skew))
        .count();
    let need = 1.0 - lim.rate_tolerance;
    let share = if left.is_empty() {
        0.0
    } else {
        paired as f64 / left.len() as f64
    };
    let base = baseline
        .as_ref()
        .map_or_else(Clone::clone, |b| format!("baseline {:.1} mm", b * 1e3));
    check(
        "STEREO",
        !left.is_empty() && share >= need && baseline.is_ok(),
        format!(
            "{paired} of {} images with a right image of their stamp on {} (>= {:.0} %); {base}",
            left.len(),
            r.topic,
            need * 100.0
        ),
        fix,
    )
}

fn marker(obs: &Observations, lim: &Limits) -> Check {
    let m = &obs.marker;
    let fix = if m.markerless {
        "put the trocar in the camera's view, lit, uncovered, its opening facing the camera; the trocar model \
         (trocar_model_file) must be the trocar's measured sizes (docs/markerless.md)"
    } else {
        "put the marker in the camera's view, lit, uncovered; its size (marker.size_m) must be the printed one"
    };
    let r = m.stream.rate_hz();
    if m.last.is_none() {
        let what = if m.markerless {
            "trocar not found"
        } else {
            "marker not seen"
        };
        return check("MARKER", false, format!("no trocar pose ({what})"), fix);
    }
    let size = match (m.configured_size_m, m.simulated_size_m) {
        _ if m.markerless => (
            true,
            "markerless: the trocar's shape, no marker size to check".to_string(),
        ),
        (None, _) => (true, "size not checked (the pose comes directly)".to_string()),
        (Some(s), None) => (
            s.is_finite() && s > 0.0,
            format!("estimator's marker {:.1} mm", s * 1e3),
        ),
        (Some(s), Some(t)) => (
            (s - t).abs() <= 1e-6,
            format!("estimator's marker {:.1} mm, simulated {:.1} mm", s * 1e3, t * 1e3),
        ),
    };
    check(
        "MARKER",
        r >= lim.min_marker_hz && size.0,
        format!("trocar pose at {r:.1} Hz (>= {:.0}); {}", lim.min_marker_hz, size.1),
        fix,
    )
}

fn hand_eye(obs: &Observations, lim: &Limits) -> Check {
    let fix = "recalibrate: trocar_docking hand-eye --input SAMPLES --out FILE, and set the launch's hand_eye:=FILE";
    match &obs.hand_eye {
        None => not_checked(
            "HAND_EYE",
            "no estimator: the simulator publishes the trocar pose directly".into(),
        ),
        Some(Err(e)) => check("HAND_EYE", false, e.clone(), fix),
        Some(Ok(h)) => {
            let res_ok = h.residual_max_m.is_none_or(|r| r <= lim.hand_eye_max_residual_m)
                && h.residual_max_rad.is_none_or(|r| r <= lim.hand_eye_max_residual_rad);
            let res = match (h.residual_max_m, h.residual_max_rad) {
                (Some(t), Some(r)) => format!(
                    "residuals {:.2} mm (<= {:.1}), {:.2} deg (<= {:.1})",
                    t * 1e3,
                    lim.hand_eye_max_residual_m * 1e3,
                    r.to_degrees(),
                    lim.hand_eye_max_residual_rad.to_degrees()
                ),
                _ => "no residuals in the file".into(),
            };
            check(
                "HAND_EYE",
                h.age_days.is_finite() && h.age_days <= lim.hand_eye_max_age_days && res_ok,
                format!(
                    "{}: {:.0} days old by its {} (<= {:.0}); {res}",
                    h.path, h.age_days, h.age_source, lim.hand_eye_max_age_days
                ),
                fix,
            )
        }
    }
}

fn reach(obs: &Observations, lim: &Limits, kin: &dyn Kinematics) -> Check {
    let fix = "move the arm (hand guiding) or the patient so that the trocar lies in the wrist's range, then rerun";
    let (Some(j), Some(trocar)) = (&obs.joint_states, obs.marker.last) else {
        return check("REACH", false, "no joints or no trocar estimate to test".into(), fix);
    };
    let Some(q0) = joints_in_chain_order(j, kin) else {
        return check("REACH", false, "the joint states lack the URDF's joints".into(), fix);
    };
    let s = Scenario {
        q0,
        trocar_rest: trocar,
    };
    let p = trocar.translation.vector;
    let at = format!("trocar at ({:.3}, {:.3}, {:.3}) m", p.x, p.y, p.z);
    match s.reachable(kin, lim.reach_margin_deg.to_radians()) {
        Ok(ok) => check(
            "REACH",
            ok,
            format!(
                "{at}: stand-off and goal {} with every joint {:.0} deg inside its limits",
                if ok { "reached" } else { "NOT reached" },
                lim.reach_margin_deg
            ),
            fix,
        ),
        Err(e) => check("REACH", false, format!("{at}: {e}"), fix),
    }
}

/// Days since 1970-01-01 of a proleptic Gregorian date (H. Hinnant's `days_from_civil`).
fn days_from_civil(y: i64, m: u32, d: u32) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = i64::from((m + 9) % 12);
    let doy = (153 * mp + 2) / 5 + i64::from(d) - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// The `YYYY-MM-DD` date (UTC) of `unix_s` seconds since the epoch (H. Hinnant's
/// `civil_from_days`): what `trocar_docking hand-eye --out` writes as `calibrated`.
pub fn date_of(unix_s: f64) -> String {
    let z = (unix_s / 86_400.0).floor() as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!("{y:04}-{m:02}-{d:02}")
}

/// A `YYYY-MM-DD` date as seconds since the Unix epoch (midnight UTC).
fn parse_date(s: &str) -> Option<f64> {
    let mut it = s.trim().splitn(3, '-');
    let y: i64 = it.next()?.parse().ok()?;
    let m: u32 = it.next()?.parse().ok()?;
    let d: u32 = it.next()?.parse().ok()?;
    ((1..=12).contains(&m) && (1..=31).contains(&d)).then(|| days_from_civil(y, m, d) as f64 * 86_400.0)
}

/// Read a hand-eye file's text (`trocar_docking hand-eye --out`: `flange_t_camera`, and the
/// residuals `residual_translation_max_m`, `residual_rotation_max_rad` when it carries them;
/// an optional `calibrated: YYYY-MM-DD`; or easy_handeye's, with `transformation` and no
/// date). Its age is from `calibrated` if present (a copied file's modification time says
/// nothing), else from `modified_unix_s`.
pub fn hand_eye_file(path: &str, text: &str, modified_unix_s: f64, now_unix_s: f64) -> Result<HandEye, String> {
    let v: serde_json::Value =
        crate::config::from_yaml_str(path, text).map_err(|e| format!("{path}: not YAML: {}", e.message))?;
    if v.get("flange_t_camera").is_none() && v.get("transformation").is_none() {
        return Err(format!(
            "{path}: no flange_t_camera (trocar_docking hand-eye) or transformation (easy_handeye)"
        ));
    }
    let num = |k: &str| v.get(k).and_then(serde_json::Value::as_f64);
    let (t, source) = match v.get("calibrated") {
        Some(c) => {
            let s = c.as_str().map(str::to_string).unwrap_or_else(|| c.to_string());
            let t = parse_date(&s).ok_or_else(|| format!("{path}: calibrated '{s}' is not a YYYY-MM-DD date"))?;
            (t, "calibrated date")
        }
        None => (modified_unix_s, "modification time"),
    };
    let res = |k: &str| match v.get(k) {
        None => Ok(None),
        Some(_) => num(k)
            .filter(|x| x.is_finite() && *x >= 0.0)
            .map(Some)
            .ok_or_else(|| format!("{path}: {k} is not a non-negative number")),
    };
    Ok(HandEye {
        path: path.into(),
        age_days: (now_unix_s - t) / 86_400.0,
        age_source: source,
        residual_max_m: res("residual_translation_max_m")?,
        residual_max_rad: res("residual_rotation_max_rad")?,
    })
}

#[cfg(test)]
mod tests;
