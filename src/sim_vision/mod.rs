//! The simulated world seen through the vision pipeline: [`CameraPoseSource`], a trocar pose
//! source ([`crate::sim::noise::PoseSource`]) that replaces the noise-model sensor by the
//! markerless camera pipeline of the ROS loop (`sim.launch marker:=false`).
//!
//! At the protocol's capture rate it renders the image the `lbr_med_sim` node's camera
//! renders ([`TrocarCamera`]: the true port pose seen through the true camera mount
//! `camera.flange_t_camera` of `config/lbr_med_sim.yaml` from the link-side joints, the
//! scene drawn once per trial from the trial's seed, the pixel noise per frame), runs the
//! markerless estimate into the trocar estimator as the estimator node does per frame
//! ([`track`]: the previous estimate as the prior, the confidence gate, the outlier gate and
//! the filter of `config/trocar_estimator.yaml`), through the hand-eye the controller
//! believes (the true mount times the protocol's calibration bias, drawn as the noise-model
//! sensor draws it for the same seed) and the joints the arm reports, and delivers the
//! filtered pose after the protocol's latency. A frame the pipeline rejects delivers nothing.
//!
//! Its own layer: it imports the simulator and the vision (which do not import each other)
//! and is wired by the command line.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use nalgebra::Isometry3;

use crate::kinematics::lbr::LbrModel;
use crate::kinematics::{Kinematics, LbrKinematics, FLANGE_LINK};
use crate::sim::noise::{BiasFrame, CaptureSchedule, PoseSource, SensorInput, TrocarMeasurement};
use crate::sim::world::measurement_stream;
use crate::sim::MeasurementParams;
use crate::vision::estimator::{marker_in_camera, EstimatorParams, PoseYaml, TrocarEstimator};
use crate::vision::markerless::measurement::track;
use crate::vision::markerless::{MarkerlessEstimator, MarkerlessParams, TrocarModel};
use crate::vision::sim_camera::{SimCameraParams, TrocarCamera};
use crate::vision::{CameraModel, ImageView};

/// What the camera pose source is built from (one per run; each trial builds its source).
#[derive(Debug, Clone)]
pub struct CameraSetup {
    /// The simulated camera (`camera:` of `config/lbr_med_sim.yaml`: the true mount, the
    /// pixel noise, the blur, the wall step, the trocar model shown).
    pub camera: SimCameraParams,
    /// The camera's intrinsics and distortion (the calibration file the node renders with).
    pub calibration: CameraModel,
    /// The markerless gate (`markerless:` of `config/trocar_estimator.yaml`).
    pub markerless: MarkerlessParams,
    /// The estimator's filter and gates (`estimator:` of `config/trocar_estimator.yaml`; its
    /// `flange_t_camera` is replaced by the hand-eye the controller believes).
    pub estimator: EstimatorParams,
    /// The trocar model the estimate looks for.
    pub trocar: TrocarModel,
    /// The arm model (the flange chain the camera rides on).
    pub model: LbrModel,
}

impl CameraSetup {
    /// The shipped set-up (`config/lbr_med_sim.yaml`, `config/trocar_estimator.yaml`, the
    /// shipped trocar model, the LBR Med 7) for the camera `calibration`.
    pub fn shipped(calibration: CameraModel) -> Self {
        Self {
            camera: SimCameraParams::default(),
            calibration,
            markerless: MarkerlessParams::default(),
            estimator: EstimatorParams::default(),
            trocar: TrocarModel::shipped(),
            model: LbrModel::Med7,
        }
    }
}

/// Frame counts over every source that shares them (a run's trials).
#[derive(Debug, Default)]
pub struct FrameCounts {
    /// Frames captured (rendered and estimated).
    pub captured: AtomicU64,
    /// Frames whose estimate passed the confidence gate.
    pub gated: AtomicU64,
    /// Frames fused by the estimator (not rejected as outliers): each delivers a pose.
    pub fused: AtomicU64,
}

impl FrameCounts {
    /// (captured, gated, fused).
    pub fn get(&self) -> (u64, u64, u64) {
        (
            self.captured.load(Ordering::Relaxed),
            self.gated.load(Ordering::Relaxed),
            self.fused.load(Ordering::Relaxed),
        )
    }
}

/// The markerless camera pipeline as a trocar pose source (see the module doc).
pub struct CameraPoseSource {
    flange: LbrKinematics,
    /// The true camera mount (renders).
    true_mount: Isometry3<f64>,
    camera: TrocarCamera,
    estimator: MarkerlessEstimator,
    filter: TrocarEstimator,
    markerless: MarkerlessParams,
    schedule: CaptureSchedule,
    noise_sigma: f64,
    seed: u64,
    seq: u64,
    counts: Option<Arc<FrameCounts>>,
}

impl CameraPoseSource {
    /// The source of the trial of `seed` under the protocol's `measurement` (its rate,
    /// latency and calibration bias, which must act in the camera frame).
    pub fn new(setup: &CameraSetup, measurement: &MeasurementParams, seed: u64) -> Result<Self, String> {
        measurement.validate().map_err(|e| e.to_string())?;
        if measurement.bias_frame != BiasFrame::Camera {
            return Err("the camera pose source needs measurement.bias_frame: camera (a hand-eye error)".into());
        }
        // The same first draw as the noise-model sensor of this seed: the same bias.
        let bias = measurement.draw_bias(&mut measurement_stream(seed));
        let true_mount = setup.camera.flange_t_camera.to_isometry().map_err(|e| e.to_string())?;
        let filter = TrocarEstimator::new(EstimatorParams {
            flange_t_camera: PoseYaml::from_isometry(&(true_mount * bias)),
            ..setup.estimator.clone()
        })
        .map_err(|e| format!("estimator: {e}"))?;
        setup.markerless.validate().map_err(|e| e.to_string())?;
        Ok(Self {
            flange: LbrKinematics::from_model_or_file(setup.model, "", FLANGE_LINK).map_err(|e| e.to_string())?,
            true_mount,
            camera: TrocarCamera::new(&setup.camera, seed, &setup.calibration).map_err(|e| e.to_string())?,
            estimator: MarkerlessEstimator::new(&setup.calibration, &setup.trocar).map_err(|e| e.to_string())?,
            filter,
            markerless: setup.markerless.clone(),
            schedule: CaptureSchedule::new(measurement.rate_hz, measurement.latency_s),
            noise_sigma: setup.camera.noise_sigma,
            seed,
            seq: 0,
            counts: None,
        })
    }

    /// Add this source's frames to `counts`.
    pub fn with_counts(mut self, counts: Arc<FrameCounts>) -> Self {
        self.counts = Some(counts);
        self
    }

    /// The hand-eye the estimate uses (the true mount times the calibration bias).
    pub fn believed_mount(&self) -> Isometry3<f64> {
        self.filter.flange_t_camera()
    }

    /// Render, estimate and fuse the frame captured at `t`; the filtered pose, if the frame
    /// gives one.
    fn capture(&mut self, t: f64, at: &SensorInput<'_>) -> Option<Isometry3<f64>> {
        self.seq += 1;
        let count = |c: &Option<Arc<FrameCounts>>, f: fn(&FrameCounts) -> &AtomicU64| {
            if let Some(c) = c {
                f(c).fetch_add(1, Ordering::Relaxed);
            }
        };
        count(&self.counts, |c| &c.captured);
        // The camera rides on the link side: where the (elastic) arm really is.
        let base_t_flange = self.flange.fk(at.q_link).ok()?;
        let camera_t_trocar = marker_in_camera(&base_t_flange, &self.true_mount, at.true_pose, &Isometry3::identity());
        // The pixel noise of frame `seq` of this trial (the node numbers its frames alone).
        let noise_seed = self.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ self.seq;
        let grey = self.camera.frame(&camera_t_trocar, self.noise_sigma, noise_seed);
        let c = self.camera.camera();
        let view = ImageView {
            data: &grey,
            width: c.width,
            height: c.height,
            channels: 1,
        };
        // The estimator pairs the frame with the joints the arm reports at its stamp.
        let base_t_camera = self.flange.fk(at.q).ok()? * self.filter.flange_t_camera();
        let tracked = track(
            &mut self.estimator,
            &mut self.filter,
            &view,
            t,
            &base_t_camera,
            &self.markerless,
        )
        .ok()?;
        count(&self.counts, |c| &c.gated);
        let pose = tracked.pose?;
        count(&self.counts, |c| &c.fused);
        Some(pose)
    }
}

impl PoseSource for CameraPoseSource {
    fn update(&mut self, t: f64, at: &SensorInput<'_>) {
        if self.schedule.capture_due(t) {
            if let Some(pose) = self.capture(t, at) {
                self.schedule.push(TrocarMeasurement { stamp: t, pose });
            }
        }
        self.schedule.deliver(t);
    }

    fn latest(&self, now: f64) -> Option<TrocarMeasurement> {
        self.schedule.latest(now)
    }
}
