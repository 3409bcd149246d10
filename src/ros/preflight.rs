//! The preflight on the ROS graph: subscribes the driver's, the camera's and the estimator's
//! topics for a short window, asks the master who subscribes the command topic and which
//! nodes run, reads the hand-eye file, and hands what it saw to the pure checks
//! ([`crate::preflight`]). `rosrust::run` of the `preflight` binary ([`run_node`]) and the
//! controller's `~preflight` and `~start` services ([`run`]) share it; neither runs on the
//! control loop's thread.
//!
//! **The simulator is a valid set-up.** It is recognised by its node (`simulator_node`)
//! publishing the joint states; then a simulated clock is right, and in its direct mode
//! (`camera_enabled` false) there is no camera, estimator or hand-eye file to check.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::kinematics::Kinematics;
use crate::preflight::{self, Camera, CameraInfo, JointStates, LbrState, Observations, Report, RightCamera, Stream};
use crate::ros::controller_node::node_params::{ControllerNodeParams, PreflightParams};
use crate::ros::estimator_node::EstimatorNodeParams;
use crate::ros::msgs::{geometry_msgs, lbr_msgs, sensor_msgs};
use crate::ros::node::{lock, ros_err, NodeError};
use crate::ros::{convert, params, topics};
use crate::vision::ImageKind;

/// The span of the stamps seen.
#[derive(Debug, Clone, Copy, Default)]
struct Stamps {
    count: usize,
    first: f64,
    last: f64,
}

impl Stamps {
    fn add(&mut self, t: f64) {
        if self.count == 0 {
            (self.first, self.last) = (t, t);
        }
        self.first = self.first.min(t);
        self.last = self.last.max(t);
        self.count += 1;
    }

    fn stream(&self) -> Stream {
        Stream {
            count: self.count,
            span_s: self.last - self.first,
        }
    }
}

/// What the subscribers collected.
#[derive(Debug, Default)]
struct Seen {
    joints: Stamps,
    names: Vec<String>,
    positions: Vec<f64>,
    low: Vec<f64>,
    high: Vec<f64>,
    lbr: Stamps,
    lbr_stamps: Vec<f64>,
    /// Arrival (this node's clock) minus stamp of each joint state (the driver PC's clock) and
    /// LBRState (the robot controller's clock), s.
    joint_delays: Vec<f64>,
    lbr_delays: Vec<f64>,
    sample_time: f64,
    tau_ext: Vec<Vec<f64>>,
    images: Stamps,
    image_stamps: Vec<f64>,
    /// Each image's age on arrival: this node's clock minus its stamp, s.
    image_ages: Vec<f64>,
    image_size: Option<(u32, u32)>,
    right_stamps: Vec<f64>,
    right_baseline: Option<Result<f64, String>>,
    info: Option<CameraInfo>,
    poses: Stamps,
    pose: Option<nalgebra::Isometry3<f64>>,
    pose_error: Option<String>,
}

impl Seen {
    /// A joint state that arrived at `arrival` (this node's clock, s).
    fn joint_states(&mut self, m: &sensor_msgs::JointState, arrival: f64) {
        self.joints.add(convert::seconds(m.header.stamp));
        self.joint_delays.push(arrival - convert::seconds(m.header.stamp));
        if m.name != self.names || m.position.len() != self.low.len() {
            self.names.clone_from(&m.name);
            self.low.clone_from(&m.position);
            self.high.clone_from(&m.position);
        }
        for ((l, h), q) in self.low.iter_mut().zip(self.high.iter_mut()).zip(&m.position) {
            *l = l.min(*q);
            *h = h.max(*q);
        }
        self.positions.clone_from(&m.position);
    }

    /// What was seen; `right`: the estimator's right image topic, where it reads one.
    fn observations(&self, camera: bool, right: Option<&str>) -> Streams {
        let joints = (self.joints.count > 0).then(|| JointStates {
            stream: self.joints.stream(),
            names: self.names.clone(),
            positions: self.positions.clone(),
            motion_rad: self.low.iter().zip(&self.high).map(|(l, h)| h - l).fold(0.0, f64::max),
        });
        let lbr = (self.lbr.count > 0).then(|| LbrState {
            stream: self.lbr.stream(),
            sample_time: self.sample_time,
            cadence_s: preflight::cadence_s(&self.lbr_stamps),
            tau_ext: self.tau_ext.clone(),
        });
        let cam = camera.then(|| Camera {
            info: self.info,
            images: self.images.stream(),
            image_size: self.image_size,
            image_stamps: self.image_stamps.clone(),
            right: right.map(|topic| RightCamera {
                topic: topic.to_string(),
                stamps: self.right_stamps.clone(),
                baseline_m: self.right_baseline.clone(),
            }),
        });
        Streams {
            joint_states: joints,
            lbr_state: lbr,
            camera: cam,
        }
    }
}

/// What the watched streams showed (None: nothing arrived, or no camera in the set-up).
struct Streams {
    joint_states: Option<JointStates>,
    lbr_state: Option<LbrState>,
    camera: Option<Camera>,
}

/// The topics watched.
struct Topics {
    joint_states: String,
    lbr_state: String,
    trocar_pose: String,
    base_frame: String,
    image: String,
    camera_info: String,
    /// The stereo pair's right image and CameraInfo, where the estimator reads them, and how
    /// it reads the CameraInfo.
    right: Option<(String, String, ImageKind)>,
}

/// The image subscribers' queue: a second of images at 15 Hz. The checks count every image
/// (its rate, and STEREO pairs each left image with a right one of its stamp); a two-deep
/// queue lost images whenever a busy host delayed the callbacks (STEREO read 8 of 15 paired
/// on a 2-core host with one busy process beside the rostests), which the checks then read as
/// the camera's fault.
const IMAGE_QUEUE: usize = 15;

/// Subscribe `topic`, handing each message to `f` with the collection.
fn watch<T: rosrust::Message>(
    topic: &str,
    queue: usize,
    seen: &Arc<Mutex<Seen>>,
    f: impl Fn(&mut Seen, T) + Send + Sync + 'static,
) -> Result<rosrust::Subscriber, NodeError> {
    let s = seen.clone();
    rosrust::subscribe(topic, queue, move |m: T| f(&mut lock(&s), m)).map_err(ros_err)
}

/// The subscribers, the stereo pair's right ones apart (they outlive the window: see
/// [`RIGHT_LATE_S`]); each lives as long as its handle.
struct Subscribers {
    right: Vec<rosrust::Subscriber>,
    rest: Vec<rosrust::Subscriber>,
}

/// How long (wall time) the right image's subscriber listens on after the window, for the
/// right images of the window's left images still on the wire: on a busy 2-core host they
/// arrived up to 0.7 s after their left images (the simulated stereo pair, whose two
/// publishers each write to every subscriber in turn, one image of ~1 MB at a time), and
/// STEREO read them as missing. The left images stop at the window's end.
const RIGHT_LATE_S: f64 = 1.0;

/// Wait (the left images' subscriber gone) until a right image as new as the newest left
/// image has arrived, or [`RIGHT_LATE_S`].
fn wait_for_late_right_images(seen: &Arc<Mutex<Seen>>) {
    let newest = |v: &[f64]| v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let t0 = Instant::now();
    while t0.elapsed().as_secs_f64() < RIGHT_LATE_S && rosrust::is_ok() {
        {
            let s = lock(seen);
            if newest(&s.right_stamps) >= newest(&s.image_stamps) - crate::vision::STEREO_MAX_SKEW_S {
                return;
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Subscribe the topics.
fn subscribe(t: &Topics, seen: &Arc<Mutex<Seen>>) -> Result<Subscribers, NodeError> {
    let (topic, frame) = (t.trocar_pose.clone(), t.base_frame.clone());
    let right = match &t.right {
        Some((image, info, kind)) => {
            let kind = *kind;
            vec![
                watch(image, IMAGE_QUEUE, seen, |s, m: sensor_msgs::Image| {
                    s.right_stamps.push(convert::seconds(m.header.stamp));
                })?,
                watch(info, 2, seen, move |s, m: sensor_msgs::CameraInfo| {
                    s.right_baseline = Some(right_baseline(&m, kind));
                })?,
            ]
        }
        None => vec![],
    };
    let rest = vec![
        watch(
            &t.joint_states,
            topics::DRIVER_QUEUE,
            seen,
            |s, m: sensor_msgs::JointState| s.joint_states(&m, convert::seconds(rosrust::now())),
        )?,
        watch(&t.lbr_state, topics::DRIVER_QUEUE, seen, |s, m: lbr_msgs::LBRState| {
            let t = convert::seconds(m.stamp.data);
            s.lbr.add(t);
            s.lbr_stamps.push(t);
            s.lbr_delays.push(convert::seconds(rosrust::now()) - t);
            s.sample_time = m.sample_time;
            s.tau_ext.push(m.external_torque);
        })?,
        watch(
            &t.trocar_pose,
            10,
            seen,
            move |s, m: geometry_msgs::PoseStamped| match convert::pose_in_frame(&topic, &m, &frame) {
                Ok(p) => {
                    s.poses.add(convert::seconds(m.header.stamp));
                    s.pose = Some(p);
                }
                Err(e) => s.pose_error = Some(e.to_string()),
            },
        )?,
        watch(&t.image, IMAGE_QUEUE, seen, |s, m: sensor_msgs::Image| {
            let t = convert::seconds(m.header.stamp);
            s.image_ages.push(convert::seconds(rosrust::now()) - t);
            s.images.add(t);
            s.image_stamps.push(t);
            s.image_size = Some((m.width, m.height));
        })?,
        watch(&t.camera_info, 2, seen, |s, m: sensor_msgs::CameraInfo| {
            s.info = Some(CameraInfo {
                fx: m.K[0],
                fy: m.K[4],
                width: m.width,
                height: m.height,
            });
        })?,
    ];
    Ok(Subscribers { right, rest })
}

/// The stereo baseline a right camera's CameraInfo gives (its projection's `Tx`), m, checked
/// as the estimator checks it; or why it gives none.
fn right_baseline(m: &sensor_msgs::CameraInfo, kind: ImageKind) -> Result<f64, String> {
    let c = convert::image::camera_model(m, kind).map_err(|e| e.to_string())?;
    c.check_stereo_right().map_err(|e| e.to_string())?;
    Ok(c.baseline_m)
}

/// The estimator's parameters on the server, if it has any there.
fn estimator_params(estimator_node: &str) -> Option<EstimatorNodeParams> {
    let tree = rosrust::param(estimator_node)?.get::<serde_json::Value>().ok()?;
    params::from_value(estimator_node, tree).ok()
}

/// The estimator's right image and CameraInfo topics, where it reads a stereo pair's right
/// image (method markerless or fused, both topics set), and how it reads the CameraInfo.
fn stereo_topics(p: Option<&EstimatorNodeParams>) -> Option<(String, String, ImageKind)> {
    p.filter(|p| p.stereo()).map(|p| {
        (
            p.right_image_topic.clone(),
            p.right_camera_info_topic.clone(),
            p.image_kind.resolve(&p.right_image_topic),
        )
    })
}

/// A parameter's value, if it is set.
fn param<T: serde::de::DeserializeOwned>(name: &str) -> Option<T> {
    rosrust::param(name)?.get().ok()
}

/// The nodes publishing and subscribing `topic`.
fn nodes_on(state: &rosrust::api::SystemState, topic: &str, publishers: bool) -> Vec<String> {
    let list = if publishers {
        &state.publishers
    } else {
        &state.subscribers
    };
    list.iter()
        .find(|t| t.name == topic)
        .map(|t| t.connections.clone())
        .unwrap_or_default()
}

/// The hand-eye file the estimator uses, read (None: no estimator and none needed).
fn hand_eye(p: &PreflightParams, estimator: bool, camera: bool) -> Option<Result<preflight::HandEye, String>> {
    if !estimator {
        return camera.then(|| {
            Err(format!(
                "no {} running: the hand-eye file is its parameter hand_eye_file",
                p.estimator_node
            ))
        });
    }
    let path: String = param(&format!("{}/hand_eye_file", p.estimator_node)).unwrap_or_default();
    if path.is_empty() {
        return Some(Err(format!(
            "{} runs with no hand_eye_file: the mount's nominal value, uncalibrated",
            p.estimator_node
        )));
    }
    let read = || -> Result<preflight::HandEye, String> {
        // The mount as the estimator reads it (either format, an easy_handeye frame through
        // the URDF): an unknown frame or an eye-on-base file fails here.
        let est = estimator_params(&p.estimator_node).unwrap_or_default();
        params::hand_eye_mount(&path, est.model, &est.urdf_file)?;
        let text = std::fs::read_to_string(&path).map_err(|e| format!("{path}: {e}"))?;
        let since = |t: std::time::SystemTime| {
            t.duration_since(std::time::UNIX_EPOCH)
                .map_or(f64::NAN, |d| d.as_secs_f64())
        };
        let modified = std::fs::metadata(&path)
            .and_then(|m| m.modified())
            .map_or(f64::NAN, since);
        preflight::hand_eye_file(&path, &text, modified, since(std::time::SystemTime::now()))
    };
    Some(read())
}

/// The host of a node's URI (`http://HOST:PORT/`), asked of the master.
fn node_host(node: &str) -> Option<String> {
    let master = rosrust::api::Master::new(&rosrust::api::resolve::master(), &rosrust::name(), &rosrust::uri()).ok()?;
    let uri = master.lookup_node(node).ok()?;
    let host = uri.split("://").nth(1)?.split(['/', ':']).next()?;
    Some(host.to_string())
}

/// The images against this node's clock, with the nodes publishing them and their machines,
/// and the tolerances of the estimator's pairing and the staleness checks (None: no camera).
fn camera_clock(
    camera: bool,
    ages: &[f64],
    image_topic: &str,
    est: Option<&EstimatorNodeParams>,
    node: &ControllerNodeParams,
) -> Result<Option<preflight::CameraClock>, NodeError> {
    if !camera {
        return Ok(None);
    }
    let state = rosrust::state().map_err(ros_err)?;
    let publishers: Vec<String> = nodes_on(&state, image_topic, true)
        .into_iter()
        .map(|n| {
            let host = node_host(&n).unwrap_or_else(|| "an unknown machine".into());
            format!("{n} on {host}")
        })
        .collect();
    let camera = if publishers.is_empty() {
        format!("nothing publishing {image_topic}:")
    } else {
        format!("{} ({image_topic}):", publishers.join(", "))
    };
    let default = EstimatorNodeParams::default();
    let est = est.unwrap_or(&default);
    Ok(Some(preflight::CameraClock {
        ages_s: ages.to_vec(),
        camera,
        controller_host: rosrust::hostname(),
        tolerance: preflight::CameraClockTolerance {
            pairing_s: est.max_joint_extrapolation_s,
            pose_timeout_s: node.controller.guard.trocar_timeout_s.min(est.estimator.stale_after_s),
        },
    }))
}

/// Who runs: the simulator (with its camera or not) and the estimator.
fn who_runs(
    p: &PreflightParams,
    node: &ControllerNodeParams,
) -> Result<(Option<preflight::Simulator>, bool), NodeError> {
    let state = rosrust::state().map_err(ros_err)?;
    let simulator = nodes_on(&state, &node.joint_states_topic, true)
        .contains(&p.simulator_node)
        .then(|| preflight::Simulator {
            camera: param(&format!("{}/camera_enabled", p.simulator_node)).unwrap_or(true),
        });
    let estimator = nodes_on(&state, &node.trocar_pose_topic, true).contains(&p.estimator_node);
    Ok((simulator, estimator))
}

/// Watch the graph and run the checks, for the controller whose parameters are `node` and
/// whose chain is `kin`. Blocks for up to `wait_s + window_s` (wall time).
pub fn run(p: &PreflightParams, node: &ControllerNodeParams, kin: &dyn Kinematics) -> Result<Report, NodeError> {
    let est = |k: &str| format!("{}/{k}", p.estimator_node);
    let est_params = estimator_params(&p.estimator_node);
    let markerless = est_params.as_ref().is_some_and(|e| !e.method.uses_marker());
    let topics = Topics {
        joint_states: node.joint_states_topic.clone(),
        lbr_state: node.lbr_state_topic.clone(),
        trocar_pose: node.trocar_pose_topic.clone(),
        base_frame: node.base_frame.clone(),
        image: param(&est("image_topic")).unwrap_or_else(|| topics::CAMERA_IMAGE.into()),
        camera_info: param(&est("camera_info_topic")).unwrap_or_else(|| topics::CAMERA_INFO.into()),
        right: stereo_topics(est_params.as_ref()),
    };
    let seen = Arc::new(Mutex::new(Seen::default()));
    let subs = subscribe(&topics, &seen)?;
    let t0 = Instant::now();
    // Until every stream has spoken (the camera's only where there is one), or `wait_s`.
    loop {
        let (simulator, _) = who_runs(p, node)?;
        let camera = simulator.is_none_or(|s| s.camera);
        let all_there = {
            let s = lock(&seen);
            s.joints.count > 0
                && s.lbr.count > 0
                && s.poses.count > 0
                && (!camera || (s.images.count > 0 && s.info.is_some()))
                && (!camera || topics.right.is_none() || (!s.right_stamps.is_empty() && s.right_baseline.is_some()))
        };
        if all_there || t0.elapsed().as_secs_f64() >= p.wait_s || !rosrust::is_ok() {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_secs_f64(p.window_s));
    drop(subs.rest);
    if !subs.right.is_empty() {
        wait_for_late_right_images(&seen);
    }
    drop(subs.right);
    let (simulator, estimator) = who_runs(p, node)?;
    let camera = simulator.is_none_or(|s| s.camera);
    let s = lock(&seen);
    if let Some(e) = &s.pose_error {
        rosrust::ros_warn!("preflight: a trocar pose was rejected: {e}");
    }
    let Streams {
        joint_states,
        lbr_state,
        camera: camera_obs,
    } = s.observations(camera, topics.right.as_ref().map(|r| r.0.as_str()));
    let state = rosrust::state().map_err(ros_err)?;
    let command_subscribers = nodes_on(&state, &node.command_topic, false)
        .into_iter()
        .filter(|n| *n != rosrust::name())
        .collect();
    let obs = Observations {
        simulator,
        use_sim_time: param("/use_sim_time").unwrap_or(false),
        joint_states,
        lbr_state,
        camera: camera_obs,
        marker: preflight::Marker {
            stream: s.poses.stream(),
            last: s.pose,
            configured_size_m: if estimator && !markerless {
                param(&est("marker/size_m"))
            } else {
                None
            },
            simulated_size_m: simulator
                .filter(|s| s.camera)
                .and_then(|_| param(&format!("{}/camera/marker/size_m", p.simulator_node))),
            markerless: estimator && markerless,
        },
        hand_eye: hand_eye(p, estimator, camera),
        driver_clock: driver_clock(&s, node),
        command_subscribers,
        command_topic: node.command_topic.clone(),
        camera_clock: camera_clock(camera, &s.image_ages, &topics.image, est_params.as_ref(), node)?,
    };
    Ok(preflight::evaluate(&obs, &p.limits, &node.controller.tare, kin))
}

/// The driver's stamps against their arrival, and the command stream the controller sends.
fn driver_clock(s: &Seen, node: &ControllerNodeParams) -> Option<preflight::driver_clock::DriverClock> {
    (!s.joint_delays.is_empty()).then(|| preflight::driver_clock::DriverClock {
        joint_state_delays_s: s.joint_delays.clone(),
        lbr_state_delays_s: s.lbr_delays.clone(),
        stamped_commands: node.command_stamp == crate::ros::node::CommandStamp::Step,
        time_from_start_s: node.command_lookahead_periods * node.controller.dt_s,
        // Without an LBRState (LBR_STATE fails), the longest FRI period a position controller runs at.
        driver_period_s: if s.sample_time > 0.0 { s.sample_time } else { 0.005 },
        control_period_s: node.controller.dt_s,
        input_timeout_s: node.controller.guard.joint_timeout_s,
    })
}

/// The `preflight` node: read the controller's parameters from the server (the defaults,
/// said so, when it does not run), run the checks with its own private parameters or, when
/// it has none, the controller's `preflight` section; print the report; exit 1 when a check
/// failed.
pub fn run_node() -> Result<(), NodeError> {
    let own: PreflightParams = params::load_private()?;
    let has_own = rosrust::param(&rosrust::name()).is_some_and(|r| r.exists().unwrap_or(false));
    let node: ControllerNodeParams = match rosrust::param(&own.controller_node).map(|r| r.get::<serde_json::Value>()) {
        Some(Ok(v)) => params::from_value(&own.controller_node, v)?,
        _ => {
            println!(
                "note: no parameters of {}: its defaults (config/docking_controller.yaml's topics, the built-in Med 7)",
                own.controller_node
            );
            ControllerNodeParams::default()
        }
    };
    let p = if has_own { own } else { node.preflight.clone() };
    p.validate()?;
    let kin =
        crate::kinematics::LbrKinematics::from_model_or_file(node.model, &node.urdf_file, crate::kinematics::TIP_LINK)?;
    let report = run(&p, &node, &kin)?;
    println!("{report}");
    if report.passed() {
        Ok(())
    } else {
        Err(NodeError::Invalid(format!(
            "preflight failed: {}",
            report.failed_codes().join(", ")
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_settings_are_the_defaults_and_valid() {
        let text = include_str!("../../config/docking_controller.yaml");
        let node: ControllerNodeParams = params::from_yaml_str("docking_controller.yaml", text).unwrap();
        node.validate().unwrap();
        assert!(node.preflight_on_start);
        let (shipped, default) = (&node.preflight, PreflightParams::default());
        assert_eq!(shipped.limits, default.limits);
        assert_eq!(
            (shipped.window_s, shipped.wait_s, &shipped.simulator_node),
            (default.window_s, default.wait_s, &default.simulator_node)
        );
        let bad = PreflightParams {
            window_s: 0.0,
            ..PreflightParams::default()
        };
        assert!(bad.validate().unwrap_err().to_string().contains("window_s"));
        // The rate floor's old key is refused, naming the new one.
        let old = "preflight:\n  limits:\n    min_joint_states_hz: 100.0\n";
        let e = params::from_yaml_str::<ControllerNodeParams>("old.yaml", old)
            .unwrap_err()
            .to_string();
        assert!(e.contains("preflight.limits.min_driver_hz"), "{e}");
    }

    #[test]
    fn the_right_camera_is_seen_where_the_estimator_reads_one() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        let right = crate::vision::CameraModel::from_yaml_file(&dir.join("camera_zedm_right.yaml")).unwrap();
        let info = convert::image::camera_info(convert::ros_time(5.0), "zedm_right", &right);
        assert!((right_baseline(&info, ImageKind::Rectified).unwrap() - 0.063).abs() < 1e-9);
        assert!((right_baseline(&info, ImageKind::Raw).unwrap() - 0.063).abs() < 1e-9);
        // The left camera's CameraInfo has no baseline: refused as the estimator refuses it.
        let left = crate::vision::CameraModel::from_yaml_file(&dir.join("camera_zedm.yaml")).unwrap();
        let e = right_baseline(
            &convert::image::camera_info(convert::ros_time(5.0), "zedm", &left),
            ImageKind::Rectified,
        )
        .unwrap_err();
        assert!(e.contains("baseline 0.0 mm"), "{e}");
        let mut s = Seen::default();
        for t in [5.0, 5.0667] {
            s.images.add(t);
            s.image_stamps.push(t);
        }
        s.right_stamps.push(5.0);
        s.right_baseline = Some(Ok(0.063));
        // Mono (no right topic): no right camera; stereo: its stamps and baseline.
        assert!(s.observations(true, None).camera.unwrap().right.is_none());
        let c = s.observations(true, Some("/r")).camera.unwrap();
        assert_eq!(c.image_stamps, vec![5.0, 5.0667]);
        assert_eq!(
            c.right,
            Some(RightCamera {
                topic: "/r".into(),
                stamps: vec![5.0],
                baseline_m: Some(Ok(0.063))
            })
        );
    }

    #[test]
    fn joint_states_give_the_rate_of_their_stamps_and_the_motion() {
        let mut s = Seen::default();
        let msg = |t: f64, q: f64| sensor_msgs::JointState {
            header: convert::header(convert::ros_time(t), ""),
            name: vec!["a".into(), "b".into()],
            position: vec![q, 1.0],
            ..Default::default()
        };
        // Out of order, as a queue may deliver them: the span is first to last stamp.
        for (t, q) in [(10.0, 0.0), (10.02, 0.003), (10.01, -0.001)] {
            s.joint_states(&msg(t, q), t + 0.001);
        }
        let seen = s.observations(false, None);
        let j = seen.joint_states.unwrap();
        assert!((j.stream.rate_hz() - 100.0).abs() < 1e-6, "{}", j.stream.rate_hz());
        assert!((j.motion_rad - 0.004).abs() < 1e-12);
        assert_eq!(j.positions, vec![-0.001, 1.0]);
        assert!(seen.lbr_state.is_none() && seen.camera.is_none());
        // Renamed joints restart the motion's range.
        let mut m = msg(10.03, 5.0);
        m.name = vec!["x".into(), "y".into()];
        s.joint_states(&m, 10.031);
        assert_eq!(s.observations(true, None).joint_states.unwrap().motion_rad, 0.0);
        // Each arrival minus its stamp: the driver clock's evidence.
        assert_eq!(s.joint_delays.len(), 4);
        assert!(
            s.joint_delays.iter().all(|d| (d - 0.001).abs() < 1e-9),
            "{:?}",
            s.joint_delays
        );
        assert!(s.observations(true, None).camera.is_some());
    }
}
