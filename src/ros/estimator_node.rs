//! The `trocar_estimator` node: camera image + camera_info in, the trocar pose in the robot
//! base frame out (`/trocar/pose`), with the marker pose in the camera (`~marker_pose`) and
//! a debug image with the detected marker drawn (`~debug_image`, only built while someone
//! subscribes). The maths is the vision module's: [`MarkerDetector`] finds the marker,
//! [`TrocarEstimator`] carries it into the base frame through the flange pose and the
//! hand-eye transform, gates outliers and filters.
//!
//! The flange pose is the arm's at the image's stamp: joint states are kept in a short
//! [`JointHistory`] and interpolated there, so a moving arm does not smear the estimate.
//! The pose is stamped with the image's stamp, so the controller's latency figure counts
//! from the camera frame. A frame that cannot be used (no camera_info yet, a wrong size or
//! encoding, no joint state at its stamp, no marker, an outlier) publishes nothing and
//! says why in the log (throttled); the controller then sees its trocar pose age and holds.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use nalgebra::Isometry3;

use super::convert;
use super::convert::image as image_msgs;
use super::msgs::{geometry_msgs, sensor_msgs};
use super::node::{lock, ros_err, NodeError, Throttle};
use super::params;
use super::stats::LoopStats;
use crate::kinematics::lbr::LbrModel;
use crate::kinematics::{JointVector, Kinematics, LbrKinematics, FLANGE_LINK};
use crate::vision::estimator::PoseYaml;
use crate::vision::joint_history::JointHistory;
use crate::vision::{
    CameraModel, EstimateStatus, EstimatorParams, MarkerDetector, MarkerSpec, RgbImage, TrackingDetector,
    TrocarEstimator,
};

/// Parameters of the node (its private namespace; `config/trocar_estimator.yaml`).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EstimatorNodeParams {
    /// Arm model when `urdf_file` is empty.
    pub model: LbrModel,
    /// URDF with the chain `lbr_link_0` -> `lbr_link_ee` ('' = built-in model).
    pub urdf_file: String,
    /// Joint names in chain order, as in the joint states.
    pub joint_names: Vec<String>,
    /// Robot base frame: the trocar pose is published in it.
    pub base_frame: String,
    /// Camera image in.
    pub image_topic: String,
    /// CameraInfo in.
    pub camera_info_topic: String,
    /// Joint states in (the flange pose at each image's stamp).
    pub joint_states_topic: String,
    /// Trocar pose out.
    pub trocar_pose_topic: String,
    /// Marker pose in the camera frame out.
    pub marker_pose_topic: String,
    /// Debug image out (RGB8, the detection drawn).
    pub debug_image_topic: String,
    /// Hand-eye result YAML (`trocar_docking hand-eye --out`); its `flange_t_camera`
    /// replaces `estimator.flange_t_camera`. '' = use the value in `estimator`.
    pub hand_eye_file: String,
    /// The marker on the trocar.
    pub marker: MarkerSpec,
    /// The estimator (hand-eye, marker-to-port offset, gates, filter, staleness).
    pub estimator: EstimatorParams,
    /// After a detection, search the next frame only this many marker extents around it
    /// (0 = always the whole frame); the whole frame is searched when it is not found there.
    pub search_margin: f64,
    /// Joint states kept to pair with image stamps, s.
    pub joint_history_s: f64,
    /// Joint states farther apart than this are not interpolated between, s.
    pub max_joint_gap_s: f64,
    /// An image this much newer than the newest joint state still uses it, s.
    pub max_joint_extrapolation_s: f64,
    /// How often the node logs its frame statistics, s (0 = never).
    pub report_period_s: f64,
    /// Process images in the real-time class `SCHED_FIFO` at this priority (1..=99; needs
    /// CAP_SYS_NICE or an rtprio limit); 0 = normal scheduling. If it cannot be had the node
    /// warns and runs at normal priority.
    pub realtime_priority: i32,
}

impl Default for EstimatorNodeParams {
    fn default() -> Self {
        Self {
            model: LbrModel::Med7,
            urdf_file: String::new(),
            joint_names: (1..=7).map(|i| format!("lbr_joint_{i}")).collect(),
            base_frame: crate::kinematics::BASE_LINK.into(),
            image_topic: "/zedm/zed_node/left/image_rect_color".into(),
            camera_info_topic: "/zedm/zed_node/left/camera_info".into(),
            joint_states_topic: "/lbr/joint_states".into(),
            trocar_pose_topic: "/trocar/pose".into(),
            marker_pose_topic: "~marker_pose".into(),
            debug_image_topic: "~debug_image".into(),
            hand_eye_file: String::new(),
            marker: MarkerSpec::default(),
            estimator: EstimatorParams::default(),
            search_margin: 1.5,
            joint_history_s: 1.0,
            max_joint_gap_s: 0.05,
            max_joint_extrapolation_s: 0.02,
            report_period_s: 10.0,
            realtime_priority: 0,
        }
    }
}

/// The hand-eye result file: only `flange_t_camera` is read.
#[derive(Debug, serde::Deserialize)]
struct HandEyeFile {
    flange_t_camera: PoseYaml,
}

impl EstimatorNodeParams {
    /// The estimator parameters with the hand-eye file applied, validated.
    pub fn estimator_params(&self) -> Result<EstimatorParams, NodeError> {
        let mut e = self.estimator.clone();
        if !self.hand_eye_file.is_empty() {
            let f: HandEyeFile = params::from_yaml_file(std::path::Path::new(&self.hand_eye_file))?;
            e.flange_t_camera = f.flange_t_camera;
        }
        e.validate()
            .map_err(|err| NodeError::Invalid(format!("estimator: {err}")))?;
        Ok(e)
    }

    fn validate(&self) -> Result<(), NodeError> {
        if self.joint_names.len() != crate::kinematics::N_JOINTS {
            return Err(NodeError::Invalid(format!(
                "joint_names has {} names, expected 7",
                self.joint_names.len()
            )));
        }
        self.marker
            .validate()
            .map_err(|e| NodeError::Invalid(format!("marker: {e}")))?;
        for (v, n) in [
            (self.joint_history_s, "joint_history_s"),
            (self.max_joint_gap_s, "max_joint_gap_s"),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 60.0) {
                return Err(NodeError::Invalid(format!("{n} = {v} must be in (0, 60]")));
            }
        }
        if !(self.max_joint_extrapolation_s.is_finite() && self.max_joint_extrapolation_s >= 0.0) {
            return Err(NodeError::Invalid("max_joint_extrapolation_s must be >= 0".into()));
        }
        Ok(())
    }
}

/// Counts of what happened to the frames since the last report.
#[derive(Debug, Default, Clone, Copy)]
struct FrameCounts {
    frames: u64,
    detected: u64,
    published: u64,
}

/// The node's state, shared by the image callback (which does the work) and the reports.
struct Pipeline {
    p: EstimatorNodeParams,
    flange: LbrKinematics,
    detector: Option<TrackingDetector>,
    estimator: TrocarEstimator,
    last_stamp: Option<f64>,
    counts: FrameCounts,
    processing: LoopStats,
    /// Age of each image at its arrival (ROS time - stamp): the camera's own latency.
    arrival_age: LoopStats,
    warn: Throttle,
}

/// What one frame produced.
struct FrameOutput {
    trocar: Option<Isometry3<f64>>,
    marker: Option<Isometry3<f64>>,
    debug: Option<RgbImage>,
}

impl Pipeline {
    /// Process one frame: detect, pair with the joint state at its stamp, fuse.
    fn frame(
        &mut self,
        img: &sensor_msgs::Image,
        camera: Option<&CameraModel>,
        history: &Mutex<JointHistory>,
        want_debug: bool,
    ) -> Result<FrameOutput, String> {
        self.counts.frames += 1;
        let stamp = convert::seconds(img.header.stamp);
        if !(stamp.is_finite() && stamp > 0.0) {
            return Err("image stamp is zero".into());
        }
        if self.last_stamp.is_some_and(|t| stamp + 1.0 < t) {
            // Time went back by more than a second (a bag looped, the simulator restarted).
            self.estimator.reset();
        }
        self.last_stamp = Some(stamp);
        let camera = camera.ok_or("no camera_info received yet")?;
        if self.detector.as_ref().is_none_or(|d| d.detector().camera() != camera) {
            let d = MarkerDetector::new(self.p.marker.clone(), camera).map_err(|e| e.to_string())?;
            self.detector = Some(TrackingDetector::new(d, self.p.search_margin));
        }
        let (pixels, channels, order) = image_msgs::image_pixels(img)?;
        let view = image_msgs::view(img, &pixels, channels).map_err(|e| e.to_string())?;
        let detector = self.detector.as_mut().ok_or("no detector")?;
        let detection = detector.detect(&view).map_err(|e| e.to_string())?;
        let debug = if want_debug {
            let mut rgb = RgbImage::from_view(&view, order).map_err(|e| e.to_string())?;
            if let Some(d) = &detection {
                rgb.draw_detection(d);
            }
            Some(rgb)
        } else {
            None
        };
        let Some(det) = detection else {
            return Ok(FrameOutput {
                trocar: None,
                marker: None,
                debug,
            });
        };
        self.counts.detected += 1;
        let q: JointVector = lock(history).at(stamp).map_err(|e| e.to_string())?;
        let base_t_flange = self.flange.fk(&q).map_err(|e| e.to_string())?;
        let status = self.estimator.update(stamp, &base_t_flange, Some(&det));
        let trocar = match status {
            EstimateStatus::Initialized | EstimateStatus::Updated | EstimateStatus::Reinitialized => {
                self.estimator.estimate(stamp).map(|e| e.pose_base_trocar)
            }
            EstimateStatus::Outlier => return Err("marker pose rejected as an outlier".into()),
            EstimateStatus::PoorQuality => {
                return Err(format!(
                    "marker reprojection error {:.2} px above the limit",
                    det.reprojection_error_px
                ))
            }
            EstimateStatus::InvalidInput => return Err("invalid marker pose or stamp".into()),
            EstimateStatus::NoMeasurement => None,
        };
        if trocar.is_some() {
            self.counts.published += 1;
        }
        Ok(FrameOutput {
            trocar,
            marker: Some(det.pose_camera_marker),
            debug,
        })
    }
}

/// Run the node until shutdown. Call after `rosrust::init`.
pub fn run() -> Result<(), NodeError> {
    let p: EstimatorNodeParams = params::load_private()?;
    p.validate()?;
    let estimator =
        TrocarEstimator::new(p.estimator_params()?).map_err(|e| NodeError::Invalid(format!("estimator: {e}")))?;
    let flange = LbrKinematics::from_model_or_file(p.model, &p.urdf_file, FLANGE_LINK)?;
    let capacity = (p.joint_history_s * 1000.0).ceil() as usize;
    let history = Arc::new(Mutex::new(JointHistory::new(
        capacity,
        p.max_joint_gap_s,
        p.max_joint_extrapolation_s,
    )));
    let camera: Arc<Mutex<Option<CameraModel>>> = Arc::new(Mutex::new(None));

    let pub_pose = rosrust::publish::<geometry_msgs::PoseStamped>(&p.trocar_pose_topic, 10).map_err(ros_err)?;
    let pub_marker = rosrust::publish::<geometry_msgs::PoseStamped>(&p.marker_pose_topic, 10).map_err(ros_err)?;
    let pub_debug = rosrust::publish::<sensor_msgs::Image>(&p.debug_image_topic, 1).map_err(ros_err)?;

    let _sub_js =
        {
            let (history, topic, names) = (history.clone(), p.joint_states_topic.clone(), p.joint_names.clone());
            let warn = Throttle::new(Duration::from_secs(2));
            rosrust::subscribe(&p.joint_states_topic, 50, move |m: sensor_msgs::JointState| {
                match convert::joint_positions(&topic, &m, &names) {
                    Ok(q) => lock(&history).push(convert::seconds(m.header.stamp), q),
                    Err(e) => {
                        if warn.ready() {
                            rosrust::ros_warn!("joint state rejected: {e}");
                        }
                    }
                }
            })
            .map_err(ros_err)?
        };
    let _sub_info = {
        let camera = camera.clone();
        let warn = Throttle::new(Duration::from_secs(2));
        rosrust::subscribe(
            &p.camera_info_topic,
            2,
            move |m: sensor_msgs::CameraInfo| match image_msgs::camera_model(&m) {
                Ok(c) => *lock(&camera) = Some(c),
                Err(e) => {
                    *lock(&camera) = None;
                    if warn.ready() {
                        rosrust::ros_warn!("camera_info rejected, frames are dropped until a valid one: {e}");
                    }
                }
            },
        )
        .map_err(ros_err)?
    };
    let pipeline = Arc::new(Mutex::new(Pipeline {
        p: p.clone(),
        flange,
        detector: None,
        estimator,
        last_stamp: None,
        counts: FrameCounts::default(),
        processing: LoopStats::new(1.0, 1000),
        arrival_age: LoopStats::new(1.0, 1000),
        warn: Throttle::new(Duration::from_secs(2)),
    }));
    let _sub_image = {
        let (pipeline, camera, history) = (pipeline.clone(), camera.clone(), history.clone());
        let base_frame = p.base_frame.clone();
        let priority = p.realtime_priority;
        let realtime_set = std::sync::Once::new();
        // Queue of one: a slow frame never makes the next one stale.
        rosrust::subscribe(&p.image_topic, 1, move |img: sensor_msgs::Image| {
            // rosrust runs this callback on its own thread: raise that thread once.
            if priority != 0 {
                realtime_set.call_once(|| match crate::realtime::set_realtime_priority(priority) {
                    Ok(()) => {
                        rosrust::ros_info!("image processing runs at SCHED_FIFO {priority}");
                    }
                    Err(e) => {
                        rosrust::ros_warn!("image processing at normal priority: {e}");
                    }
                });
            }
            let t0 = Instant::now();
            let age_ms = (convert::seconds(rosrust::now()) - convert::seconds(img.header.stamp)) * 1e3;
            let cam = lock(&camera).clone();
            let mut pl = lock(&pipeline);
            match pl.frame(&img, cam.as_ref(), &history, pub_debug.subscriber_count() > 0) {
                Ok(out) => {
                    if let Some(t) = &out.trocar {
                        let _ = pub_pose.send(convert::pose_stamped(img.header.stamp, &base_frame, t));
                    }
                    if let Some(m) = &out.marker {
                        let _ = pub_marker.send(convert::pose_stamped(img.header.stamp, &img.header.frame_id, m));
                    }
                    if out.marker.is_none() && pl.warn.ready() {
                        rosrust::ros_warn!("no marker {} in the image", pl.p.marker.family);
                    }
                    if let Some(d) = out.debug {
                        let _ = pub_debug.send(image_msgs::image(
                            img.header.stamp,
                            &img.header.frame_id,
                            d.width,
                            d.height,
                            "rgb8",
                            3,
                            d.data,
                        ));
                    }
                }
                Err(e) => {
                    if pl.warn.ready() {
                        rosrust::ros_warn!("frame dropped: {e}");
                    }
                }
            }
            pl.processing.latency(t0.elapsed().as_secs_f64() * 1e3);
            pl.arrival_age.latency(age_ms);
        })
        .map_err(ros_err)?
    };
    rosrust::ros_info!(
        "trocar_estimator: {} on {}, marker {} id {:?} {} m, pose on {}",
        p.image_topic,
        p.camera_info_topic,
        p.marker.family,
        p.marker.id,
        p.marker.size,
        p.trocar_pose_topic
    );
    let report = Throttle::new(Duration::from_secs_f64(if p.report_period_s > 0.0 {
        p.report_period_s
    } else {
        f64::MAX / 4.0
    }));
    while rosrust::is_ok() {
        std::thread::sleep(Duration::from_millis(200));
        if p.report_period_s > 0.0 && report.ready() {
            let mut pl = lock(&pipeline);
            let (c, lat, age) = (pl.counts, pl.processing.percentiles(), pl.arrival_age.percentiles());
            if c.frames > 0 {
                rosrust::ros_info!(
                    "trocar_estimator: {} frames, marker in {}, pose published for {}; processing p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms; image age at arrival p50 {:.1} ms, p99 {:.1} ms",
                    c.frames,
                    c.detected,
                    c.published,
                    lat.p50,
                    lat.p99,
                    lat.max,
                    age.p50,
                    age.p99
                );
            }
            pl.counts = FrameCounts::default();
        }
    }
    Ok(())
}
