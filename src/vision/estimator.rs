//! The trocar estimator (pure Rust, no C++): marker pose in the camera -> trocar pose in the
//! robot base frame, through the flange pose (FK) and the hand-eye transform; a fixed
//! marker-to-trocar offset; gating of outliers; a first-order filter on SE(3) (translation
//! low-pass, rotation slerp) that smooths noise but follows a moving trocar; and ageing:
//! without an accepted measurement for `stale_after_s` the estimate is flagged stale.
//!
//! base_T_trocar = base_T_flange * flange_T_camera * camera_T_marker * marker_T_trocar.

use std::path::Path;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::VisionError;
use crate::signal::exp_smoothing;
use crate::validate;

/// A pose as YAML: translation (m) and quaternion x, y, z, w.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseYaml {
    /// Translation, m.
    pub translation: [f64; 3],
    /// Quaternion x, y, z, w.
    pub quaternion_xyzw: [f64; 4],
}

impl PoseYaml {
    /// Convert to an isometry (the quaternion is normalised; zero or non-finite -> error).
    pub fn to_isometry(&self) -> Result<Isometry3<f64>, VisionError> {
        let [x, y, z, w] = self.quaternion_xyzw;
        let q = nalgebra::Quaternion::new(w, x, y, z);
        let n = q.norm();
        if !(n.is_finite() && n > 1e-6) || self.translation.iter().any(|v| !v.is_finite()) {
            return Err(VisionError::InvalidInput(
                "pose must be finite with a non-zero quaternion".into(),
            ));
        }
        let t = self.translation;
        Ok(Isometry3::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_quaternion(q),
        ))
    }

    /// From an isometry.
    pub fn from_isometry(p: &Isometry3<f64>) -> Self {
        let t = p.translation.vector;
        let q = p.rotation;
        Self {
            translation: [t.x, t.y, t.z],
            quaternion_xyzw: [q.i, q.j, q.k, q.w],
        }
    }
}

/// Estimator parameters (`estimator:` in `config/trocar_estimator.yaml`, whose values, built
/// in, are the defaults: [`crate::config::TROCAR_ESTIMATOR`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct EstimatorParams {
    /// Camera pose in the flange frame (hand-eye, eMc).
    pub flange_t_camera: PoseYaml,
    /// Trocar port pose in the marker frame (z = insertion direction).
    pub marker_t_trocar: PoseYaml,
    /// Filter time constant, s (0 = no smoothing).
    pub time_constant_s: f64,
    /// Measurements farther than this from the estimate are outliers, m.
    pub gate_translation_m: f64,
    /// Measurements rotated more than this from the estimate are outliers, rad.
    pub gate_rotation_rad: f64,
    /// After this many consecutive outliers that agree with each other the filter restarts
    /// on them (the trocar really moved).
    pub reinit_after: u32,
    /// Detections with a larger RMS reprojection error are rejected, px.
    pub max_reprojection_error_px: f64,
    /// Without an accepted measurement for this long the estimate is stale, s.
    pub stale_after_s: f64,
}

crate::shipped_defaults!(EstimatorParams, crate::config::TROCAR_ESTIMATOR, ["estimator"]);

impl EstimatorParams {
    /// Read from a YAML file of the `estimator:` section's keys (missing keys take the shipped
    /// values), validated.
    pub fn from_yaml_file(path: &Path) -> Result<Self, VisionError> {
        let p: Self = crate::config::from_yaml_file(path).map_err(|e| VisionError::Io(e.to_string()))?;
        p.validate()?;
        Ok(p)
    }

    /// Check every number is finite and positive where it must be.
    pub fn validate(&self) -> Result<(), VisionError> {
        self.flange_t_camera.to_isometry()?;
        self.marker_t_trocar.to_isometry()?;
        validate::positive("gate_translation_m", self.gate_translation_m)?;
        validate::positive("gate_rotation_rad", self.gate_rotation_rad)?;
        validate::positive("max_reprojection_error_px", self.max_reprojection_error_px)?;
        validate::positive("stale_after_s", self.stale_after_s)?;
        validate::non_negative("time_constant_s", self.time_constant_s)?;
        Ok(())
    }
}

/// What `update` did with a measurement.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum EstimateStatus {
    /// First accepted measurement: the filter started.
    Initialized,
    /// Accepted and fused.
    Updated,
    /// Rejected as an outlier (too far from the estimate).
    Outlier,
    /// Consecutive consistent outliers: the filter restarted on the new pose.
    Reinitialized,
    /// Rejected: reprojection error too large.
    PoorQuality,
    /// Rejected: non-finite input or time going backwards.
    InvalidInput,
    /// No detection this frame: the estimate ages.
    NoMeasurement,
}

/// The current trocar estimate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TrocarEstimate {
    /// Trocar port pose in the base frame (z = insertion direction).
    pub pose_base_trocar: Isometry3<f64>,
    /// Time of the last accepted measurement, s.
    pub stamp: f64,
    /// Age at the query time, s.
    pub age_s: f64,
    /// True when older than `stale_after_s`: the controller must hold.
    pub stale: bool,
}

/// The estimator state.
#[derive(Debug, Clone)]
pub struct TrocarEstimator {
    params: EstimatorParams,
    flange_t_camera: Isometry3<f64>,
    marker_t_trocar: Isometry3<f64>,
    state: Option<(Isometry3<f64>, f64)>,
    outliers: Vec<Isometry3<f64>>,
    last_time: Option<f64>,
}

impl TrocarEstimator {
    /// A new estimator (validates the parameters).
    pub fn new(params: EstimatorParams) -> Result<Self, VisionError> {
        params.validate()?;
        Ok(Self {
            flange_t_camera: params.flange_t_camera.to_isometry()?,
            marker_t_trocar: params.marker_t_trocar.to_isometry()?,
            outliers: Vec::with_capacity(params.reinit_after as usize + 1),
            params,
            state: None,
            last_time: None,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &EstimatorParams {
        &self.params
    }

    /// The camera pose in the flange frame (the hand-eye transform in use).
    pub fn flange_t_camera(&self) -> Isometry3<f64> {
        self.flange_t_camera
    }

    /// The trocar pose in the base frame that one measurement implies.
    pub fn measurement_in_base(
        &self,
        base_t_flange: &Isometry3<f64>,
        camera_t_marker: &Isometry3<f64>,
    ) -> Isometry3<f64> {
        base_t_flange * self.flange_t_camera * camera_t_marker * self.marker_t_trocar
    }

    /// Feed one frame at time `now` (s): the flange pose from FK and the marker detection,
    /// if any. Returns what was done with it.
    pub fn update(
        &mut self,
        now: f64,
        base_t_flange: &Isometry3<f64>,
        detection: Option<&super::MarkerDetection>,
    ) -> EstimateStatus {
        let Some(det) = detection else {
            return EstimateStatus::NoMeasurement;
        };
        if !now.is_finite() || self.last_time.is_some_and(|t| now < t) || !finite_pose(base_t_flange) {
            return EstimateStatus::InvalidInput;
        }
        if !finite_pose(&det.pose_camera_marker) || !det.reprojection_error_px.is_finite() {
            return EstimateStatus::InvalidInput;
        }
        if det.reprojection_error_px > self.params.max_reprojection_error_px {
            return EstimateStatus::PoorQuality;
        }
        let z = self.measurement_in_base(base_t_flange, &det.pose_camera_marker);
        self.fuse(now, z)
    }

    /// Fuse a trocar pose measured directly in the base frame at time `now`.
    pub fn fuse(&mut self, now: f64, z: Isometry3<f64>) -> EstimateStatus {
        if !now.is_finite() || self.last_time.is_some_and(|t| now < t) || !finite_pose(&z) {
            return EstimateStatus::InvalidInput;
        }
        self.last_time = Some(now);
        let Some((x, t_prev)) = self.state else {
            self.state = Some((z, now));
            self.outliers.clear();
            return EstimateStatus::Initialized;
        };
        let (dt, dr) = super::pose_distance(&x, &z);
        if dt > self.params.gate_translation_m || dr > self.params.gate_rotation_rad {
            // A stale estimate accepts the new pose at once: the old one is worthless.
            if now - t_prev > self.params.stale_after_s {
                self.state = Some((z, now));
                self.outliers.clear();
                return EstimateStatus::Reinitialized;
            }
            let consistent = self.outliers.last().is_none_or(|o| {
                let (a, b) = super::pose_distance(o, &z);
                a <= self.params.gate_translation_m && b <= self.params.gate_rotation_rad
            });
            if !consistent {
                self.outliers.clear();
            }
            self.outliers.push(z);
            if self.outliers.len() as u32 >= self.params.reinit_after.max(1) {
                self.state = Some((z, now));
                self.outliers.clear();
                return EstimateStatus::Reinitialized;
            }
            return EstimateStatus::Outlier;
        }
        self.outliers.clear();
        let a = exp_smoothing(now - t_prev, self.params.time_constant_s);
        let t: Vector3<f64> = x.translation.vector.lerp(&z.translation.vector, a);
        let r = x.rotation.try_slerp(&z.rotation, a, 1e-9).unwrap_or(z.rotation);
        self.state = Some((Isometry3::from_parts(Translation3::from(t), r), now));
        EstimateStatus::Updated
    }

    /// The estimate at time `now`, or `None` before the first accepted measurement.
    pub fn estimate(&self, now: f64) -> Option<TrocarEstimate> {
        let (pose, stamp) = self.state?;
        let age = if now.is_finite() {
            (now - stamp).max(0.0)
        } else {
            f64::INFINITY
        };
        Some(TrocarEstimate {
            pose_base_trocar: pose,
            stamp,
            age_s: age,
            stale: age.is_nan() || age > self.params.stale_after_s,
        })
    }

    /// Forget everything.
    pub fn reset(&mut self) {
        self.state = None;
        self.outliers.clear();
        self.last_time = None;
    }
}

/// The inverse of the estimator's chain: where a camera on the flange sees the marker of a
/// trocar at `base_t_trocar` (what a simulated camera renders).
/// camera_T_marker = (base_T_flange * flange_T_camera)^-1 * base_T_trocar * marker_T_trocar^-1.
pub fn marker_in_camera(
    base_t_flange: &Isometry3<f64>,
    flange_t_camera: &Isometry3<f64>,
    base_t_trocar: &Isometry3<f64>,
    marker_t_trocar: &Isometry3<f64>,
) -> Isometry3<f64> {
    (base_t_flange * flange_t_camera).inverse() * base_t_trocar * marker_t_trocar.inverse()
}

fn finite_pose(p: &Isometry3<f64>) -> bool {
    p.translation.vector.iter().all(|v| v.is_finite()) && p.rotation.coords.iter().all(|v| v.is_finite())
}
