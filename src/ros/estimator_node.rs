//! The `trocar_estimator` node: camera image + camera_info in, the trocar pose in the robot
//! base frame out (`/trocar/pose`), with the marker pose in the camera (`~marker_pose`), a
//! debug image with the detected marker drawn (`~debug_image`, only built while someone
//! subscribes), and one line per frame on `~status` (what it published, or why nothing).
//! The maths is the vision module's: `method` (`marker | markerless | fused`) picks the
//! measurement: [`MarkerDetector`] finds the marker, [`MarkerlessEstimator`] the trocar's
//! axis from its shape (the previous estimate, carried into the camera through the arm's
//! motion, resolves the ellipse's two-fold ambiguity; `fused`: the marker when seen, else
//! markerless); [`TrocarEstimator`] carries it into the base frame through the flange pose
//! and the hand-eye transform, gates outliers and filters. A markerless pose also goes out
//! with its covariance (`~pose_with_covariance`; the roll fixed by the convention of
//! [`crate::vision::markerless::measurement`]).
//!
//! The flange pose is the arm's at the image's stamp: joint states are kept in a short
//! [`JointHistory`] and interpolated there, so a moving arm does not smear the estimate.
//! The pose is stamped with the image's stamp, so the controller's latency figure counts
//! from the camera frame. A frame that cannot be used (no camera_info yet, a wrong size or
//! encoding, no joint state at its stamp, no marker, a markerless estimate of low
//! confidence, an outlier) publishes nothing and says why on `~status` and in the log
//! (throttled); the controller then sees its trocar pose age and holds. Each `~status` line
//! ends with the clocks the image shows (`ClockSeen`): its stamp against the newest joint
//! state's (the camera's clock against the robot's, latency included) and that joint state's
//! age on arrival (this machine's clock against the robot's): on two machines, an offset
//! there is the cause of dropped or misplaced frames (docs/two-machines.md).
//!
//! The hand-eye file (`hand_eye_file`: the project's or easy_handeye's) is also published as
//! a static tf from the flange `lbr_link_ee` to the images' own frame ([`CameraTf`]), so the
//! camera hangs in the arm's tf tree.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use nalgebra::Isometry3;

use super::convert;
use super::convert::image as image_msgs;
use super::msgs::{geometry_msgs, sensor_msgs, std_msgs, tf2_msgs};
use super::node::{lock, ros_err, NodeError, Throttle};
use super::params;
use super::stats::LoopStats;
use crate::kinematics::lbr::LbrModel;
use crate::kinematics::{JointVector, Kinematics, LbrKinematics, FLANGE_LINK};
use crate::validate;
use crate::vision::estimator::PoseYaml;
use crate::vision::hand_eye::Mount;
use crate::vision::joint_history::JointHistory;
use crate::vision::markerless::measurement::{self, EstimatorMethod, MarkerlessParams};
use crate::vision::markerless::{MarkerlessEstimator, TrocarModel};
use crate::vision::{
    CameraModel, EstimateStatus, EstimatorParams, ImageKind, ImageKindSetting, ImageView, MarkerDetection,
    MarkerDetector, MarkerSpec, RgbImage, TrackingDetector, TrocarEstimator, STEREO_MAX_SKEW_S,
};

/// Parameters of the node (its private namespace; `config/trocar_estimator.yaml`, whose
/// values, built in, are the defaults: [`crate::config::TROCAR_ESTIMATOR`]).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
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
    /// The stereo pair's right image in ('' = a mono camera): with the markerless method,
    /// a right image of the left image's stamp decides between the two poses the opening's
    /// ellipse admits.
    pub right_image_topic: String,
    /// The right camera's CameraInfo in (its projection's Tx gives the baseline).
    pub right_camera_info_topic: String,
    /// How the CameraInfo of each image is read: `by_topic_name` (an image topic whose last
    /// name starts with `image_rect` is rectified: projected with P, no distortion; any other
    /// is raw: K and D in its distortion model), `raw` or `rectified`.
    pub image_kind: ImageKindSetting,
    /// Joint states in (the flange pose at each image's stamp).
    pub joint_states_topic: String,
    /// Trocar pose out.
    pub trocar_pose_topic: String,
    /// Marker pose in the camera frame out.
    pub marker_pose_topic: String,
    /// Debug image out (RGB8, the detection drawn).
    pub debug_image_topic: String,
    /// One line per frame (std_msgs/String): what was published, or why nothing.
    pub status_topic: String,
    /// A markerless pose with its covariance out (geometry_msgs/PoseWithCovarianceStamped).
    pub pose_covariance_topic: String,
    /// How the trocar is measured: `marker` (the marker on the trocar), `markerless` (its
    /// shape alone) or `fused` (the marker when seen, else markerless).
    pub method: EstimatorMethod,
    /// The trocar model YAML the markerless estimate looks for ('' = the shipped
    /// `config/trocar_model.yaml`, built in).
    pub trocar_model_file: String,
    /// The markerless measurement: the confidence gate and the covariance's scale.
    pub markerless: MarkerlessParams,
    /// Hand-eye file: the project's (`trocar_docking hand-eye --out`) or easy_handeye's (its
    /// effector frame carried to the flange through the URDF); its mount replaces
    /// `estimator.flange_t_camera` and goes out as a static tf from the flange to the
    /// images' frame. '' = use the value in `estimator`.
    pub hand_eye_file: String,
    /// The marker on the trocar.
    pub marker: MarkerSpec,
    /// The estimator (hand-eye, marker-to-port offset, gates, filter, staleness).
    pub estimator: EstimatorParams,
    /// After a detection, search the next frame only this many marker extents around it
    /// (0 = always the whole frame); the whole frame is searched when it is not found there.
    pub search_margin: f64,
    /// Detections with a corner closer than this to the image border are rejected, px: a
    /// marker cut by the border is found as a smaller quad whose pose is centimetres off.
    pub border_margin_px: f64,
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

crate::shipped_defaults!(
    EstimatorNodeParams,
    crate::config::TROCAR_ESTIMATOR,
    [],
    deserialize_only
);

impl EstimatorNodeParams {
    /// The hand-eye file's mount (`None` without one), in either format
    /// ([`params::hand_eye_mount`]).
    pub fn hand_eye(&self) -> Result<Option<Mount>, NodeError> {
        if self.hand_eye_file.is_empty() {
            return Ok(None);
        }
        params::hand_eye_mount(&self.hand_eye_file, self.model, &self.urdf_file)
            .map(Some)
            .map_err(NodeError::Invalid)
    }

    /// The estimator parameters with the hand-eye `mount` applied, validated.
    pub fn estimator_params(&self, mount: Option<&Mount>) -> Result<EstimatorParams, NodeError> {
        let mut e = self.estimator.clone();
        if let Some(m) = mount {
            e.flange_t_camera = PoseYaml::from_isometry(&m.flange_t_camera);
        }
        e.validate()
            .map_err(|err| NodeError::Invalid(format!("estimator: {err}")))?;
        Ok(e)
    }

    /// The trocar model of the markerless estimate, validated.
    pub fn trocar_model(&self) -> Result<TrocarModel, NodeError> {
        if self.trocar_model_file.is_empty() {
            return Ok(TrocarModel::shipped());
        }
        TrocarModel::from_yaml_file(std::path::Path::new(&self.trocar_model_file))
            .map_err(|e| NodeError::Invalid(format!("trocar_model_file: {e}")))
    }

    /// Check every value once at start-up: a bad one stops the node with its key named.
    pub fn validate(&self) -> Result<(), NodeError> {
        if self.joint_names.len() != crate::kinematics::N_JOINTS {
            return Err(NodeError::Invalid(format!(
                "joint_names has {} names, expected 7",
                self.joint_names.len()
            )));
        }
        self.marker
            .validate()
            .map_err(|e| NodeError::Invalid(format!("marker: {e}")))?;
        validate::positive_at_most("joint_history_s", self.joint_history_s, 60.0)?;
        validate::positive_at_most("max_joint_gap_s", self.max_joint_gap_s, 60.0)?;
        validate::non_negative("max_joint_extrapolation_s", self.max_joint_extrapolation_s)?;
        validate::non_negative("search_margin", self.search_margin)?;
        validate::non_negative("border_margin_px", self.border_margin_px)?;
        self.markerless
            .validate()
            .map_err(|e| NodeError::Invalid(e.to_string()))?;
        if self.method.uses_markerless() {
            self.trocar_model()?;
        }
        self.report_period()?;
        validate::integer_in_range("realtime_priority", i64::from(self.realtime_priority), 0, 99)?;
        Ok(())
    }

    /// Whether the node takes the stereo pair's right image: a markerless method and both
    /// right topics set.
    pub fn stereo(&self) -> bool {
        self.method.uses_markerless() && !self.right_image_topic.is_empty() && !self.right_camera_info_topic.is_empty()
    }

    /// How often to log the frame statistics; `None` = never (`report_period_s: 0`).
    pub fn report_period(&self) -> Result<Option<Duration>, NodeError> {
        Ok(validate::period_or_never("report_period_s", self.report_period_s)?)
    }
}

/// Counts of what happened to the frames since the last report.
#[derive(Debug, Default, Clone, Copy)]
struct FrameCounts {
    frames: u64,
    detected: u64,
    markerless: u64,
    published: u64,
}

/// The node's state, shared by the image callback (which does the work) and the reports.
struct Pipeline {
    p: EstimatorNodeParams,
    /// Frames that came with a right image of their stamp (since the last report).
    stereo_frames: u64,
    flange: LbrKinematics,
    /// The flange-to-tip distance of the URDF chain: the endoscope's length, m.
    endoscope_length_m: f64,
    detector: Option<TrackingDetector>,
    markerless: Option<MarkerlessEstimator>,
    model: TrocarModel,
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
    measured: Measured,
    marker: Option<Isometry3<f64>>,
    debug: Option<RgbImage>,
}

impl Pipeline {
    /// Process one frame: measure (marker, markerless or both), pair with the joint state at
    /// its stamp, fuse.
    fn frame(
        &mut self,
        img: &sensor_msgs::Image,
        camera: Option<&CameraModel>,
        right: Option<&StereoRight>,
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
        let image_msgs::Pixels {
            data: pixels,
            channels,
            order,
        } = image_msgs::image_pixels(img)?;
        let view = image_msgs::view(img, &pixels, channels).map_err(|e| e.to_string())?;
        let detection = if self.p.method.uses_marker() {
            self.detect_marker(camera, &view)?
        } else {
            None
        };
        let debug = if want_debug {
            let mut rgb = RgbImage::from_view(&view, order).map_err(|e| e.to_string())?;
            if let Some(d) = &detection {
                rgb.draw_detection(d);
            }
            Some(rgb)
        } else {
            None
        };
        let marker = detection.as_ref().map(|d| d.pose_camera_marker);
        let out = |measured| FrameOutput {
            measured,
            marker,
            debug,
        };
        let measured = match (self.p.method, detection) {
            (EstimatorMethod::Marker, None) => return Ok(out(Measured::nothing("no marker in the image"))),
            (EstimatorMethod::Marker, Some(det)) => self.marker_pose(&det, stamp, &view, history, false)?,
            (EstimatorMethod::Fused, Some(det)) => match self.marker_pose(&det, stamp, &view, history, true) {
                Ok(m) => m,
                // A marker cut by the border: the trocar's shape may still be whole.
                Err(e) if e.contains("border") => self.markerless_pose(camera, &view, right, stamp, history)?,
                Err(e) => return Err(e),
            },
            (EstimatorMethod::Markerless, _) | (EstimatorMethod::Fused, None) => {
                self.markerless_pose(camera, &view, right, stamp, history)?
            }
        };
        self.counts.published += u64::from(measured.trocar.is_some());
        Ok(out(measured))
    }

    /// The marker in `view`, through a detector for `camera` (built when the camera changes).
    fn detect_marker(&mut self, camera: &CameraModel, view: &ImageView) -> Result<Option<MarkerDetection>, String> {
        if self.detector.as_ref().is_none_or(|d| d.detector().camera() != camera) {
            let d = MarkerDetector::new(self.p.marker.clone(), camera).map_err(|e| e.to_string())?;
            self.detector = Some(TrackingDetector::new(d, self.p.search_margin));
        }
        let detector = self.detector.as_mut().ok_or("no detector")?;
        detector.detect(view).map_err(|e| e.to_string())
    }

    /// The hand-eye's error as the endoscope in view tells it
    /// ([`MarkerlessEstimator::camera_t_believed`]; the identity without a markerless
    /// estimator or with `markerless.endoscope_corrects_hand_eye` off).
    fn camera_correction(&self) -> Isometry3<f64> {
        self.markerless
            .as_ref()
            .filter(|_| self.p.markerless.endoscope_corrects_hand_eye)
            .map_or(Isometry3::identity(), MarkerlessEstimator::camera_t_believed)
    }

    /// The base-to-camera pose at `stamp` (the joint history, FK, the hand-eye).
    fn camera_at(&self, stamp: f64, history: &Mutex<JointHistory>) -> Result<Isometry3<f64>, String> {
        let q: JointVector = lock(history).at(stamp).map_err(|e| e.to_string())?;
        let base_t_flange = self.flange.fk(&q).map_err(|e| e.to_string())?;
        Ok(base_t_flange * self.estimator.flange_t_camera())
    }

    /// Fuse the marker's pose (`roll_convention`: with the markerless roll, as `fused` does).
    fn marker_pose(
        &mut self,
        det: &MarkerDetection,
        stamp: f64,
        view: &ImageView,
        history: &Mutex<JointHistory>,
        roll_convention: bool,
    ) -> Result<Measured, String> {
        self.counts.detected += 1;
        let border = det.border_distance_px(view.width, view.height);
        if border < self.p.border_margin_px {
            return Err(format!(
                "marker {border:.1} px from the image border (partly out of view): rejected"
            ));
        }
        let q: JointVector = lock(history).at(stamp).map_err(|e| e.to_string())?;
        let base_t_flange = self.flange.fk(&q).map_err(|e| e.to_string())?;
        // Through the hand-eye the endoscope in view corrected, as the markerless estimate
        // is (none unless a markerless estimator has seen it: `fused`).
        let det = &MarkerDetection {
            pose_camera_marker: self.camera_correction().inverse() * det.pose_camera_marker,
            ..det.clone()
        };
        let status = if roll_convention {
            if !det.reprojection_error_px.is_finite()
                || det.reprojection_error_px > self.estimator.params().max_reprojection_error_px
            {
                EstimateStatus::PoorQuality
            } else {
                let z = self
                    .estimator
                    .measurement_in_base(&base_t_flange, &det.pose_camera_marker);
                self.estimator.fuse(stamp, measurement::with_roll_convention(&z))
            }
        } else {
            self.estimator.update(stamp, &base_t_flange, Some(det))
        };
        match status {
            EstimateStatus::Initialized | EstimateStatus::Updated | EstimateStatus::Reinitialized => {
                let pose = self.estimator.estimate(stamp).map(|e| e.pose_base_trocar);
                Ok(Measured {
                    trocar: pose,
                    covariance: None,
                    status: format!("marker: published ({status:?})"),
                })
            }
            EstimateStatus::Outlier => Err("marker pose rejected as an outlier".into()),
            EstimateStatus::PoorQuality => Err(format!(
                "marker reprojection error {:.2} px above the limit",
                det.reprojection_error_px
            )),
            EstimateStatus::InvalidInput => Err("invalid marker pose or stamp".into()),
            EstimateStatus::NoMeasurement => Ok(Measured::nothing("no marker in the image")),
        }
    }

    /// The markerless estimate of `view` (with the right image of its stamp, if any), the
    /// previous estimate as its prior, fused when its confidence passes the gate.
    fn markerless_pose(
        &mut self,
        camera: &CameraModel,
        view: &ImageView,
        right: Option<&StereoRight>,
        stamp: f64,
        history: &Mutex<JointHistory>,
    ) -> Result<Measured, String> {
        let base_t_camera = self.camera_at(stamp, history)?;
        let right_camera = right.map(|r| &r.camera);
        if self
            .markerless
            .as_ref()
            .is_none_or(|m| m.camera() != camera || m.right_camera() != right_camera)
        {
            // The endoscope in view, masked where the hand-eye puts it.
            let occluder = self
                .p
                .markerless
                .endoscope(&self.estimator.flange_t_camera(), self.endoscope_length_m);
            let e = MarkerlessEstimator::for_cameras(camera, right_camera, &self.model)
                .and_then(|e| e.with_occluder(occluder));
            self.markerless = Some(e.map_err(|e| e.to_string())?);
        }
        let right_pixels = match right.and_then(|r| r.image.as_ref()) {
            Some(img) => Some((
                img,
                image_msgs::image_pixels(img).map_err(|e| format!("right image: {e}"))?,
            )),
            None => None,
        };
        let right_view = match &right_pixels {
            Some((img, px)) => {
                Some(image_msgs::view(img, &px.data, px.channels).map_err(|e| format!("right image: {e}"))?)
            }
            None => None,
        };
        self.stereo_frames += u64::from(right_view.is_some());
        let est = self.markerless.as_mut().ok_or("no markerless estimator")?;
        let tracked = measurement::track(
            est,
            &mut self.estimator,
            view,
            right_view.as_ref(),
            stamp,
            &base_t_camera,
            &self.p.markerless,
        )?;
        let m = tracked.measurement;
        self.counts.markerless += 1;
        match tracked.status {
            s @ (EstimateStatus::Initialized | EstimateStatus::Updated | EstimateStatus::Reinitialized) => {
                let status = format!("markerless: published ({s:?}), confidence {:.2}", m.confidence);
                Ok(Measured {
                    trocar: tracked.pose,
                    covariance: Some(m.covariance),
                    status,
                })
            }
            EstimateStatus::Outlier => Err(format!(
                "markerless pose (confidence {:.2}) rejected as an outlier",
                m.confidence
            )),
            _ => Err("invalid markerless pose or stamp".into()),
        }
    }
}

/// What one frame measured.
struct Measured {
    /// The trocar pose to publish, if any.
    trocar: Option<Isometry3<f64>>,
    /// The covariance of a markerless pose.
    covariance: Option<[f64; 36]>,
    /// What was published, or why nothing (`~status`).
    status: String,
}

impl Measured {
    /// Nothing to publish, and why.
    fn nothing(status: &str) -> Self {
        Self {
            trocar: None,
            covariance: None,
            status: status.into(),
        }
    }
}

/// The stereo pair's right camera and, when one came with the left image's stamp, its image.
struct StereoRight {
    camera: CameraModel,
    image: Option<sensor_msgs::Image>,
}

/// How long a left image waits for its right image before it is estimated mono.
const STEREO_WAIT: Duration = Duration::from_millis(5);

/// What the callbacks share: the joint history, the last camera model (and the right
/// camera's), the latest right image, the pipeline.
#[derive(Clone)]
struct Shared {
    history: Arc<Mutex<JointHistory>>,
    camera: Arc<Mutex<Option<CameraModel>>>,
    right_camera: Arc<Mutex<Option<CameraModel>>>,
    right_image: Arc<Mutex<Option<sensor_msgs::Image>>>,
    pipeline: Arc<Mutex<Pipeline>>,
    /// The newest joint state's stamp and its arrival on this node's clock.
    joint_clock: Arc<Mutex<Option<JointArrival>>>,
}

impl Shared {
    fn new(p: &EstimatorNodeParams, mount: Option<&Mount>) -> Result<Self, NodeError> {
        let estimator = TrocarEstimator::new(p.estimator_params(mount)?)
            .map_err(|e| NodeError::Invalid(format!("estimator: {e}")))?;
        let flange = LbrKinematics::from_model_or_file(p.model, &p.urdf_file, FLANGE_LINK)?;
        let endoscope_length_m = LbrKinematics::flange_to_tip_m(p.model, &p.urdf_file)?;
        let capacity = (p.joint_history_s * 1000.0).ceil() as usize;
        let history = JointHistory::new(capacity, p.max_joint_gap_s, p.max_joint_extrapolation_s);
        let pipeline = Pipeline {
            p: p.clone(),
            stereo_frames: 0,
            flange,
            endoscope_length_m,
            detector: None,
            markerless: None,
            model: p.trocar_model()?,
            estimator,
            last_stamp: None,
            counts: FrameCounts::default(),
            processing: LoopStats::new(1.0, 1000),
            arrival_age: LoopStats::new(1.0, 1000),
            warn: Throttle::new(Duration::from_secs(2)),
        };
        Ok(Self {
            history: Arc::new(Mutex::new(history)),
            camera: Arc::new(Mutex::new(None)),
            right_camera: Arc::new(Mutex::new(None)),
            right_image: Arc::new(Mutex::new(None)),
            pipeline: Arc::new(Mutex::new(pipeline)),
            joint_clock: Arc::new(Mutex::new(None)),
        })
    }
}

/// The camera tied into the arm's tf tree: the hand-eye transform from the flange to the
/// images' own frame (their header's `frame_id`, e.g. the ZED's
/// `zedm_left_camera_optical_frame`), latched on `/tf_static` once the first image names its
/// frame, again should the frame change. So RViz shows the images, the marker pose and the
/// trocar estimate on the arm.
struct CameraTf {
    publisher: rosrust::Publisher<tf2_msgs::TFMessage>,
    flange_t_camera: Isometry3<f64>,
    /// The frame the hand-eye file was calibrated in, if it says (easy_handeye's
    /// `tracking_base_frame`).
    calibrated_frame: Option<String>,
    /// The frame last published for.
    sent: Mutex<Option<String>>,
}

impl CameraTf {
    fn new(flange_t_camera: Isometry3<f64>, mount: Option<&Mount>) -> Result<Self, NodeError> {
        let mut publisher = rosrust::publish("/tf_static", 1).map_err(ros_err)?;
        publisher.set_latching(true);
        Ok(Self {
            publisher,
            flange_t_camera,
            calibrated_frame: mount.and_then(|m| m.camera_frame.clone()),
            sent: Mutex::new(None),
        })
    }

    /// Publish the transform for an image in `frame`, unless done for that frame already.
    fn ensure(&self, frame: &str) {
        let mut sent = lock(&self.sent);
        if frame.is_empty() || sent.as_deref() == Some(frame) {
            return;
        }
        if let Some(c) = self.calibrated_frame.as_deref().filter(|c| *c != frame) {
            rosrust::ros_warn!(
                "the hand-eye file was calibrated in the camera frame `{c}`, the images are in `{frame}`:                  the mount is applied to `{frame}`"
            );
        }
        let t = convert::transform_stamped(rosrust::now(), FLANGE_LINK, frame, &self.flange_t_camera);
        let _ = self.publisher.send(tf2_msgs::TFMessage { transforms: vec![t] });
        rosrust::ros_info!("static tf {FLANGE_LINK} -> {frame} (the hand-eye) on /tf_static");
        *sent = Some(frame.to_string());
    }
}

/// The node's publishers.
struct Publishers {
    camera_tf: CameraTf,
    pose: rosrust::Publisher<geometry_msgs::PoseStamped>,
    marker: rosrust::Publisher<geometry_msgs::PoseStamped>,
    debug: rosrust::Publisher<sensor_msgs::Image>,
    status: rosrust::Publisher<std_msgs::String>,
    covariance: rosrust::Publisher<geometry_msgs::PoseWithCovarianceStamped>,
}

impl Publishers {
    fn new(p: &EstimatorNodeParams, camera_tf: CameraTf) -> Result<Self, NodeError> {
        Ok(Self {
            camera_tf,
            pose: rosrust::publish(&p.trocar_pose_topic, 10).map_err(ros_err)?,
            marker: rosrust::publish(&p.marker_pose_topic, 10).map_err(ros_err)?,
            debug: rosrust::publish(&p.debug_image_topic, 1).map_err(ros_err)?,
            status: rosrust::publish(&p.status_topic, 10).map_err(ros_err)?,
            covariance: rosrust::publish(&p.pose_covariance_topic, 10).map_err(ros_err)?,
        })
    }

    /// Publish what one frame produced, stamped with the image's stamp.
    fn frame(&self, img: &sensor_msgs::Image, base_frame: &str, out: FrameOutput) {
        if let Some(t) = &out.measured.trocar {
            let stamped = convert::pose_stamped(img.header.stamp, base_frame, t);
            if let Some(c) = out.measured.covariance {
                let _ = self.covariance.send(geometry_msgs::PoseWithCovarianceStamped {
                    header: stamped.header.clone(),
                    pose: geometry_msgs::PoseWithCovariance {
                        pose: stamped.pose.clone(),
                        covariance: c,
                    },
                });
            }
            let _ = self.pose.send(stamped);
        }
        self.status(out.measured.status);
        if let Some(m) = &out.marker {
            let _ = self
                .marker
                .send(convert::pose_stamped(img.header.stamp, &img.header.frame_id, m));
        }
        if let Some(d) = out.debug {
            let _ = self.debug.send(image_msgs::image(
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
}

impl Publishers {
    /// One line on `~status`.
    fn status(&self, line: String) {
        let _ = self.status.send(std_msgs::String { data: line });
    }
}

/// The newest joint state: its stamp (the robot's clock) and its arrival (this node's).
#[derive(Debug, Clone, Copy)]
struct JointArrival {
    stamp: f64,
    arrival: f64,
}

/// The clocks as one image shows them to the estimator, s: how much older its stamp is than
/// the newest joint state's (the camera's latency minus the camera clock's offset from the
/// robot's: what the joint-history pairing meets), and how old that joint state was on its
/// arrival by this node's clock (the network's delay plus this machine's clock's offset from
/// the robot's, where the estimator runs on the camera's machine).
#[derive(Debug, Clone, Copy, PartialEq)]
struct ClockSeen {
    image_behind_joints_s: f64,
    joint_age_s: f64,
}

impl ClockSeen {
    /// An image stamped `stamp` against the newest joint state, if any.
    fn of(stamp: f64, joints: Option<JointArrival>) -> Option<Self> {
        joints.map(|j| Self {
            image_behind_joints_s: j.stamp - stamp,
            joint_age_s: j.arrival - j.stamp,
        })
    }
}

impl std::fmt::Display for ClockSeen {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "clock: image stamped {:.0} ms before the newest joint state (the camera's latency minus its clock's \
             offset from the robot's), joint state {:.0} ms old on arrival (the network plus this machine's clock's \
             offset)",
            self.image_behind_joints_s * 1e3,
            self.joint_age_s * 1e3
        )
    }
}

/// Joint states into the history (each image is paired with the arm's pose at its stamp).
fn subscribe_joint_states(p: &EstimatorNodeParams, shared: &Shared) -> Result<rosrust::Subscriber, NodeError> {
    let (history, topic, names) = (
        shared.history.clone(),
        p.joint_states_topic.clone(),
        p.joint_names.clone(),
    );
    let joint_clock = shared.joint_clock.clone();
    let warn = Throttle::new(Duration::from_secs(2));
    rosrust::subscribe(
        &p.joint_states_topic,
        50,
        move |m: sensor_msgs::JointState| match convert::joint_positions(&topic, &m, &names) {
            Ok(q) => {
                let stamp = convert::seconds(m.header.stamp);
                *lock(&joint_clock) = Some(JointArrival {
                    stamp,
                    arrival: convert::seconds(rosrust::now()),
                });
                lock(&history).push(stamp, q);
            }
            Err(e) => {
                if warn.ready() {
                    rosrust::ros_warn!("joint state rejected: {e}");
                }
            }
        },
    )
    .map_err(ros_err)
}

/// The camera model from the CameraInfo of `topic`, read for an image of `kind`, into
/// `camera`; a bad one clears it (the left camera's: frames are dropped; the right camera's:
/// frames go mono).
fn subscribe_camera_info(
    topic: &str,
    kind: ImageKind,
    camera: &Arc<Mutex<Option<CameraModel>>>,
) -> Result<rosrust::Subscriber, NodeError> {
    let (camera, name) = (camera.clone(), topic.to_string());
    let warn = Throttle::new(Duration::from_secs(2));
    rosrust::subscribe(
        topic,
        2,
        move |m: sensor_msgs::CameraInfo| match image_msgs::camera_model(&m, kind) {
            Ok(c) => *lock(&camera) = Some(c),
            Err(e) => {
                *lock(&camera) = None;
                if warn.ready() {
                    rosrust::ros_warn!("{name} rejected until a valid one: {e}");
                }
            }
        },
    )
    .map_err(ros_err)
}

/// The stereo pair's right images: the latest is kept for the left image of its stamp.
fn subscribe_right_images(p: &EstimatorNodeParams, shared: &Shared) -> Result<rosrust::Subscriber, NodeError> {
    let slot = shared.right_image.clone();
    rosrust::subscribe(&p.right_image_topic, 1, move |img: sensor_msgs::Image| {
        *lock(&slot) = Some(img);
    })
    .map_err(ros_err)
}

/// The right camera and the right image captured with the left image stamped `stamp` (taken
/// from the slot, waiting up to [`STEREO_WAIT`] for it: the two images travel on their own
/// connections, and the left one may come first); `None` without a right camera.
fn stereo_right(shared: &Shared, stamp: rosrust::Time) -> Option<StereoRight> {
    // A right CameraInfo without a baseline (P's Tx) is no stereo pair: mono.
    let camera = lock(&shared.right_camera)
        .clone()
        .filter(|c| c.check_stereo_right().is_ok())?;
    let t = convert::seconds(stamp);
    let deadline = Instant::now() + STEREO_WAIT;
    let image = loop {
        let image =
            lock(&shared.right_image).take_if(|r| (convert::seconds(r.header.stamp) - t).abs() <= STEREO_MAX_SKEW_S);
        if image.is_some() || Instant::now() >= deadline {
            break image;
        }
        std::thread::sleep(Duration::from_micros(500));
    };
    Some(StereoRight { camera, image })
}

/// Move the calling thread (rosrust's image callback thread) to SCHED_FIFO `priority`.
fn raise_priority(priority: i32) {
    match crate::realtime::set_realtime_priority(priority) {
        Ok(()) => {
            rosrust::ros_info!("image processing runs at SCHED_FIFO {priority}");
        }
        Err(e) => {
            rosrust::ros_warn!("image processing at normal priority: {e}");
        }
    }
}

/// One image: process it, publish what it gave, count its processing time and age.
fn on_image(img: &sensor_msgs::Image, shared: &Shared, publishers: &Publishers, base_frame: &str) {
    let t0 = Instant::now();
    publishers.camera_tf.ensure(&img.header.frame_id);
    let age_ms = (convert::seconds(rosrust::now()) - convert::seconds(img.header.stamp)) * 1e3;
    let clock = ClockSeen::of(convert::seconds(img.header.stamp), *lock(&shared.joint_clock))
        .map_or_else(|| "clock: no joint state yet".to_string(), |c| c.to_string());
    let cam = lock(&shared.camera).clone();
    let right = stereo_right(shared, img.header.stamp);
    let mut pl = lock(&shared.pipeline);
    let want_debug = publishers.debug.subscriber_count() > 0;
    match pl.frame(img, cam.as_ref(), right.as_ref(), &shared.history, want_debug) {
        Ok(mut out) => {
            if out.measured.trocar.is_none() && pl.warn.ready() {
                rosrust::ros_warn!("frame dropped: {}; {clock}", out.measured.status);
            }
            out.measured.status = format!("{}; {clock}", out.measured.status);
            publishers.frame(img, base_frame, out);
        }
        Err(e) => {
            if pl.warn.ready() {
                rosrust::ros_warn!("frame dropped: {e}; {clock}");
            }
            publishers.status(format!("{}: dropped: {e}; {clock}", pl.p.method));
        }
    }
    pl.processing.latency(t0.elapsed().as_secs_f64() * 1e3);
    pl.arrival_age.latency(age_ms);
}

/// Images: the work happens in this callback, on rosrust's thread for the topic.
fn subscribe_images(
    p: &EstimatorNodeParams,
    shared: &Shared,
    publishers: Publishers,
) -> Result<rosrust::Subscriber, NodeError> {
    let shared = shared.clone();
    let base_frame = p.base_frame.clone();
    let priority = p.realtime_priority;
    let realtime_set = std::sync::Once::new();
    // Queue of one: a slow frame never makes the next one stale.
    rosrust::subscribe(&p.image_topic, 1, move |img: sensor_msgs::Image| {
        if priority != 0 {
            realtime_set.call_once(|| raise_priority(priority));
        }
        on_image(&img, &shared, &publishers, &base_frame);
    })
    .map_err(ros_err)
}

/// Log the frame statistics since the last report, and start counting afresh.
fn report(pipeline: &Mutex<Pipeline>) {
    let mut pl = lock(pipeline);
    let (c, lat, age) = (pl.counts, pl.processing.percentiles(), pl.arrival_age.percentiles());
    if c.frames > 0 {
        rosrust::ros_info!(
            "trocar_estimator: {} frames ({} with a right image), marker in {}, markerless accepted in {}, pose published for {}; processing p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms; image age at arrival p50 {:.1} ms, p99 {:.1} ms",
            c.frames,
            pl.stereo_frames,
            c.detected,
            c.markerless,
            c.published,
            lat.p50,
            lat.p99,
            lat.max,
            age.p50,
            age.p99
        );
    }
    if let Some(m) = pl.markerless.as_ref().filter(|m| m.scope_frames() > 0) {
        let c = m.camera_t_believed();
        rosrust::ros_info!(
            "trocar_estimator: the endoscope in view puts the hand-eye {:.2} mm and {:.2} deg off (camera frame; the median of the last {} frames whose images both showed its axis; applied: {})",
            c.translation.vector.norm() * 1e3,
            c.rotation.angle().to_degrees(),
            m.scope_frames(),
            pl.p.markerless.endoscope_corrects_hand_eye
        );
    }
    pl.counts = FrameCounts::default();
    pl.stereo_frames = 0;
}

/// Run the node until shutdown. Call after `rosrust::init`.
pub fn run() -> Result<(), NodeError> {
    let p: EstimatorNodeParams = params::load_private()?;
    p.validate()?;
    let report_period = p.report_period()?;
    let mount = p.hand_eye()?;
    let shared = Shared::new(&p, mount.as_ref())?;
    let flange_t_camera = lock(&shared.pipeline).estimator.flange_t_camera();
    let publishers = Publishers::new(&p, CameraTf::new(flange_t_camera, mount.as_ref())?)?;
    let mut _subs = vec![
        subscribe_joint_states(&p, &shared)?,
        subscribe_camera_info(
            &p.camera_info_topic,
            p.image_kind.resolve(&p.image_topic),
            &shared.camera,
        )?,
    ];
    if p.stereo() {
        _subs.push(subscribe_camera_info(
            &p.right_camera_info_topic,
            p.image_kind.resolve(&p.right_image_topic),
            &shared.right_camera,
        )?);
        _subs.push(subscribe_right_images(&p, &shared)?);
    }
    _subs.push(subscribe_images(&p, &shared, publishers)?);
    rosrust::ros_info!(
        "trocar_estimator: method {}, {} ({:?}) on {}, marker {} id {:?} {} m, pose on {}",
        p.method,
        p.image_topic,
        p.image_kind.resolve(&p.image_topic),
        p.camera_info_topic,
        p.marker.family,
        p.marker.id,
        p.marker.size_m,
        p.trocar_pose_topic
    );
    // The images are processed in their callback; this thread only reports.
    let mut last_report = Instant::now();
    while rosrust::is_ok() {
        std::thread::sleep(Duration::from_millis(200));
        if report_period.is_some_and(|period| last_report.elapsed() >= period) {
            last_report = Instant::now();
            report(&shared.pipeline);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::topics;

    fn with(yaml: &str) -> Result<(), NodeError> {
        params::from_yaml_str::<EstimatorNodeParams>("t", yaml)?.validate()
    }

    #[test]
    fn the_built_in_file_is_the_defaults_and_a_partial_tree_takes_the_rest_from_it() {
        let text = include_str!("../../config/trocar_estimator.yaml");
        with(text).unwrap();
        let p: EstimatorNodeParams = params::from_yaml_str("trocar_estimator.yaml", text).unwrap();
        let d = EstimatorNodeParams::default();
        d.validate().unwrap();
        assert_eq!(format!("{p:?}"), format!("{d:?}"));
        // Its sections are the defaults of the estimator, the marker and the markerless gate.
        assert_eq!(d.estimator, EstimatorParams::default());
        assert_eq!(d.marker, MarkerSpec::default());
        assert_eq!(d.markerless, MarkerlessParams::default());
        assert_eq!(
            (d.marker.size_m, d.marker.id, d.estimator.reinit_after),
            (0.04, Some(7), 5)
        );
        // The topics the rest of the stack assumes.
        assert_eq!(d.joint_names, crate::kinematics::joint_names());
        for (a, b) in [
            (&d.image_topic, topics::CAMERA_IMAGE),
            (&d.camera_info_topic, topics::CAMERA_INFO),
            (&d.right_image_topic, topics::CAMERA_RIGHT_IMAGE),
            (&d.right_camera_info_topic, topics::CAMERA_RIGHT_INFO),
            (&d.joint_states_topic, topics::JOINT_STATES),
            (&d.trocar_pose_topic, topics::TROCAR_POSE),
        ] {
            assert_eq!(a, b);
        }
        // The ZED's rectified images, read with P and no distortion (by their names).
        assert_eq!(d.image_kind, ImageKindSetting::ByTopicName);
        assert_eq!(d.image_kind.resolve(&d.image_topic), ImageKind::Rectified);
        assert_eq!(d.image_kind.resolve(&d.right_image_topic), ImageKind::Rectified);
        // As the parameter server hands it over: partial; the rest is the file's.
        let p: EstimatorNodeParams = params::from_value(
            "/trocar_estimator",
            serde_json::json!({"marker": {"id": 3}, "estimator": {"gate_translation_m": 0.05}}),
        )
        .unwrap();
        assert_eq!((p.marker.id, p.marker.size_m), (Some(3), 0.04));
        assert_eq!(p.estimator.gate_translation_m, 0.05);
        assert_eq!(p.estimator.stale_after_s, d.estimator.stale_after_s);
        assert_eq!(p.estimator.flange_t_camera, d.estimator.flange_t_camera);
        assert_eq!((p.search_margin, p.border_margin_px), (1.5, 4.0));
        // The old key is refused, naming the new one.
        let e = params::from_value::<EstimatorNodeParams>(
            "/trocar_estimator",
            serde_json::json!({"marker": {"size": 0.05}}),
        )
        .unwrap_err();
        assert!(
            e.message.contains("`marker.size`: the key is now `marker.size_m`"),
            "{e}"
        );
    }

    #[test]
    fn the_right_image_is_taken_with_a_markerless_method_and_both_right_topics() {
        let d = EstimatorNodeParams::default();
        // The shipped method is the marker: no right image, whatever the topics.
        assert!(!d.stereo() && !d.right_image_topic.is_empty());
        for (method, right, info, stereo) in [
            (
                EstimatorMethod::Markerless,
                topics::CAMERA_RIGHT_IMAGE,
                topics::CAMERA_RIGHT_INFO,
                true,
            ),
            (
                EstimatorMethod::Fused,
                topics::CAMERA_RIGHT_IMAGE,
                topics::CAMERA_RIGHT_INFO,
                true,
            ),
            (EstimatorMethod::Markerless, "", topics::CAMERA_RIGHT_INFO, false),
            (EstimatorMethod::Markerless, topics::CAMERA_RIGHT_IMAGE, "", false),
        ] {
            let p = EstimatorNodeParams {
                method,
                right_image_topic: right.into(),
                right_camera_info_topic: info.into(),
                ..d.clone()
            };
            assert_eq!(p.stereo(), stereo, "{method} {right:?} {info:?}");
        }
    }

    #[test]
    fn a_left_image_takes_the_right_image_of_its_stamp_or_goes_mono() {
        let shared = Shared::new(&EstimatorNodeParams::default(), None).unwrap();
        let stamp = rosrust::Time { sec: 100, nsec: 0 };
        // No right camera known yet, or one without a baseline: mono.
        assert!(stereo_right(&shared, stamp).is_none());
        let config = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        *lock(&shared.right_camera) = Some(CameraModel::from_yaml_file(&config.join("camera_zedm.yaml")).unwrap());
        assert!(stereo_right(&shared, stamp).is_none());
        let dir = config.join("camera_zedm_right.yaml");
        *lock(&shared.right_camera) = Some(CameraModel::from_yaml_file(&dir).unwrap());
        let right_at = |sec: u32, nsec: u32| {
            let mut img = sensor_msgs::Image::default();
            img.header.stamp = rosrust::Time { sec, nsec };
            img
        };
        // The right image of the same capture (stamps within 1 ms): taken, the slot emptied.
        *lock(&shared.right_image) = Some(right_at(100, 500_000));
        let r = stereo_right(&shared, stamp).unwrap();
        assert!((r.camera.baseline_m - 0.063).abs() < 1e-9);
        assert_eq!(r.image.unwrap().header.stamp.nsec, 500_000);
        assert!(lock(&shared.right_image).is_none());
        // One of another capture (a frame period away): left in the slot, the left image goes
        // mono after waiting at most a few milliseconds for its own.
        *lock(&shared.right_image) = Some(right_at(100, 66_000_000));
        let t0 = Instant::now();
        let r = stereo_right(&shared, stamp).unwrap();
        let waited = t0.elapsed();
        assert!(r.image.is_none() && lock(&shared.right_image).is_some());
        assert!(waited >= STEREO_WAIT && waited < STEREO_WAIT * 10, "{waited:?}");
    }

    #[test]
    fn the_method_and_the_markerless_section_are_read_and_checked() {
        assert_eq!(EstimatorNodeParams::default().method, EstimatorMethod::Marker);
        let p: EstimatorNodeParams = params::from_yaml_str(
            "t",
            "method: markerless\nmarkerless: {min_confidence: 0.7, sigma_position_m: 0.002}\n",
        )
        .unwrap();
        assert_eq!(p.method, EstimatorMethod::Markerless);
        assert_eq!(p.markerless.min_confidence, 0.7);
        assert_eq!(
            p.markerless.sigma_direction_rad,
            MarkerlessParams::default().sigma_direction_rad
        );
        p.validate().unwrap();
        assert_eq!(p.trocar_model().unwrap(), TrocarModel::shipped());
        assert!(params::from_yaml_str::<EstimatorNodeParams>("t", "method: aruco\n").is_err());
        assert!(params::from_yaml_str::<EstimatorNodeParams>("t", "markerless: {min_conf: 0.5}\n").is_err());
        let e = with("markerless: {min_confidence: 0}").unwrap_err().to_string();
        assert!(e.contains("min_confidence"), "{e}");
        // A missing model file stops a markerless estimator at start-up, not a marker one.
        let e = with("method: fused\ntrocar_model_file: /nonexistent/trocar.yaml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("trocar_model_file"), "{e}");
        with("method: marker\ntrocar_model_file: /nonexistent/trocar.yaml").unwrap();
    }

    #[test]
    fn the_status_says_how_the_images_stamps_stand_to_the_joint_states() {
        // A camera 40 ms slow and 200 ms behind the robot's clock; joint states 1 ms on the wire.
        let joints = JointArrival {
            stamp: 1000.0,
            arrival: 1000.001,
        };
        let c = ClockSeen::of(1000.0 - 0.24, Some(joints)).unwrap();
        assert!((c.image_behind_joints_s - 0.24).abs() < 1e-9 && (c.joint_age_s - 0.001).abs() < 1e-9);
        let line = c.to_string();
        assert!(
            line.contains("image stamped 240 ms before the newest joint state") && line.contains("1 ms old"),
            "{line}"
        );
        assert_eq!(ClockSeen::of(1000.0, None), None);
    }

    #[test]
    fn report_period_zero_is_never_and_negative_or_nan_is_an_error() {
        let p: EstimatorNodeParams = params::from_yaml_str("t", "report_period_s: 0\n").unwrap();
        assert_eq!(p.report_period().unwrap(), None);
        let p: EstimatorNodeParams = params::from_yaml_str("t", "report_period_s: 2.5\n").unwrap();
        assert_eq!(p.report_period().unwrap(), Some(Duration::from_millis(2500)));
        // NaN and infinity cannot come through YAML (JSON has neither): set them directly.
        for bad in [-1.0, f64::NAN, f64::INFINITY, 1e300] {
            let p = EstimatorNodeParams {
                report_period_s: bad,
                ..Default::default()
            };
            let e = p.validate().unwrap_err().to_string();
            assert!(e.contains("`report_period_s`"), "{bad}: {e}");
        }
    }

    #[test]
    fn bad_durations_name_their_key() {
        for (yaml, key) in [
            ("joint_history_s: 0", "joint_history_s"),
            ("joint_history_s: 61", "joint_history_s"),
            ("max_joint_gap_s: -0.1", "max_joint_gap_s"),
            ("max_joint_extrapolation_s: -1", "max_joint_extrapolation_s"),
            ("search_margin: -1", "search_margin"),
            ("realtime_priority: 100", "realtime_priority"),
        ] {
            let e = with(yaml).unwrap_err().to_string();
            assert!(e.contains(&format!("`{key}`")), "{yaml}: {e}");
        }
        let p = EstimatorNodeParams {
            max_joint_gap_s: f64::NAN,
            ..Default::default()
        };
        assert!(p.validate().unwrap_err().to_string().contains("`max_joint_gap_s`"));
    }
}
