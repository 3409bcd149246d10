//! Hand-eye calibration (eye-in-hand) with ViSP's vpHandEyeCalibration: from pairs of
//! flange poses in the base (FK) and marker poses in the camera, the camera pose in the
//! flange (eMc), with residuals: the marker is fixed in the base, so each pair's
//! base_T_marker = base_T_flange * eMc * camera_T_marker should be the same pose.
//!
//! For a live calibration: `samples` (the acceptance rules), `refine` (a non-linear
//! refinement over all samples), `quality` (held-out residuals, conditioning, set-up faults),
//! `poses` (the automatic mode's poses), `target` (a sample's marker from a window of
//! detections: a still target's mean, a moving one's same phase). `easy_handeye`: a
//! calibration saved by easy_handeye, carried to the flange, and the one reader of a hand-eye
//! file in either format.

pub mod easy_handeye;
pub mod poses;
pub mod quality;
pub mod refine;
pub mod samples;
pub mod target;

pub use easy_handeye::{load_mount, mount_of_text, EasyHandeye, Mount};
pub use quality::{calibrate_samples, Calibration, HeldOut};
pub use refine::{ObservationModel, Sample};
pub use samples::{AcceptanceRules, Refusal, SampleSet, Stillness};

use std::path::Path;

use nalgebra::{Isometry3, Vector3};
use serde::{Deserialize, Serialize};

use super::estimator::PoseYaml;
use super::{isometry_from_rt, rt_from_isometry, VisionError};
use crate::ffi::vision::ffi;

/// One calibration sample.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HandEyeSample {
    /// Flange pose in the base frame (FK).
    pub base_t_flange: PoseYaml,
    /// Marker pose in the camera frame (detection).
    pub camera_t_marker: PoseYaml,
}

/// The input file: a list of samples.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HandEyeInput {
    /// Samples (at least 3, rotating about at least 2 axes).
    pub samples: Vec<HandEyeSample>,
}

/// The result, as written to YAML (the estimator reads `flange_t_camera`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HandEyeResult {
    /// Camera pose in the flange frame (eMc).
    pub flange_t_camera: PoseYaml,
    /// Marker pose in the base implied by the calibration (mean).
    pub base_t_marker: PoseYaml,
    /// RMS of the per-sample marker position deviation from the mean, m.
    pub residual_translation_rms_m: f64,
    /// Largest per-sample marker position deviation, m.
    pub residual_translation_max_m: f64,
    /// RMS of the per-sample marker rotation deviation, rad.
    pub residual_rotation_rms_rad: f64,
    /// Largest per-sample marker rotation deviation, rad.
    pub residual_rotation_max_rad: f64,
    /// Number of samples used.
    pub samples: usize,
}

impl HandEyeInput {
    /// Read a YAML (or JSON) file.
    pub fn from_file(path: &Path) -> Result<Self, VisionError> {
        crate::config::from_yaml_file(path).map_err(|e| VisionError::Io(e.to_string()))
    }
}

/// The text of a hand-eye file (what the estimator's `hand_eye_file` and the preflight
/// read): a comment naming `source`, the `calibrated` date (YYYY-MM-DD, UTC), the result and,
/// from a live calibration, the held-out residuals and the warnings.
pub fn file_text(
    source: &str,
    date: &str,
    result: &HandEyeResult,
    held_out: Option<&HeldOut>,
    warnings: &[String],
) -> Result<String, VisionError> {
    let mut text = format!(
        "# Camera pose in the flange frame (eMc) from {source}, with residuals;\n\
         # `calibrated` (UTC) dates it for the preflight's age check.\ncalibrated: {date}\n{}",
        yaml(result)?
    );
    if let Some(h) = held_out {
        text.push_str(&format!("held_out:\n{}", indent(&yaml(h)?)));
    }
    if !warnings.is_empty() {
        text.push_str(&format!("warnings:\n{}", indent(&yaml(&warnings)?)));
    }
    Ok(text)
}

fn yaml<T: Serialize>(v: &T) -> Result<String, VisionError> {
    crate::config::to_yaml_string("hand-eye file", v).map_err(|e| VisionError::Io(e.to_string()))
}

fn indent(s: &str) -> String {
    s.lines().map(|l| format!("  {l}\n")).collect()
}

/// Calibrate from pose pairs.
pub fn calibrate(
    base_t_flange: &[Isometry3<f64>],
    camera_t_marker: &[Isometry3<f64>],
) -> Result<HandEyeResult, VisionError> {
    if base_t_flange.len() != camera_t_marker.len() {
        return Err(VisionError::InvalidInput(
            "as many flange poses as marker poses are needed".into(),
        ));
    }
    if base_t_flange.len() < 3 {
        return Err(VisionError::InvalidInput("at least 3 pose pairs are needed".into()));
    }
    let flat = |v: &[Isometry3<f64>]| -> Vec<f64> { v.iter().flat_map(rt_from_isometry).collect() };
    let (cmo, rme) = (flat(camera_t_marker), flat(base_t_flange));
    if cmo.iter().chain(rme.iter()).any(|v| !v.is_finite()) {
        return Err(VisionError::InvalidInput("poses must be finite".into()));
    }
    let emc = ffi::hand_eye_calibrate(&cmo, &rme)?;
    let emc = isometry_from_rt(&emc).ok_or_else(|| VisionError::Backend("hand-eye returned a non-rotation".into()))?;
    Ok(residuals(&emc, base_t_flange, camera_t_marker))
}

/// Calibrate from an input file's samples.
pub fn calibrate_input(input: &HandEyeInput) -> Result<HandEyeResult, VisionError> {
    let mut f = Vec::with_capacity(input.samples.len());
    let mut m = Vec::with_capacity(input.samples.len());
    for s in &input.samples {
        f.push(s.base_t_flange.to_isometry()?);
        m.push(s.camera_t_marker.to_isometry()?);
    }
    calibrate(&f, &m)
}

/// The marker pose in the base implied by each sample, and their spread about the mean.
pub fn residuals(
    flange_t_camera: &Isometry3<f64>,
    base_t_flange: &[Isometry3<f64>],
    camera_t_marker: &[Isometry3<f64>],
) -> HandEyeResult {
    let rmo: Vec<Isometry3<f64>> = base_t_flange
        .iter()
        .zip(camera_t_marker)
        .map(|(f, m)| f * flange_t_camera * m)
        .collect();
    let n = rmo.len().max(1) as f64;
    let mean_t: Vector3<f64> = rmo.iter().map(|p| p.translation.vector).sum::<Vector3<f64>>() / n;
    // Rotation mean: the first sample's rotation moved by the mean rotation vector of the others.
    let r0 = rmo.first().map(|p| p.rotation).unwrap_or_default();
    let mean_w: Vector3<f64> = rmo
        .iter()
        .map(|p| (r0.inverse() * p.rotation).scaled_axis())
        .sum::<Vector3<f64>>()
        / n;
    let mean_r = r0 * nalgebra::UnitQuaternion::from_scaled_axis(mean_w);
    let dt: Vec<f64> = rmo.iter().map(|p| (p.translation.vector - mean_t).norm()).collect();
    let dr: Vec<f64> = rmo.iter().map(|p| p.rotation.angle_to(&mean_r)).collect();
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / n).sqrt();
    let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    HandEyeResult {
        flange_t_camera: PoseYaml::from_isometry(flange_t_camera),
        base_t_marker: PoseYaml::from_isometry(&Isometry3::from_parts(mean_t.into(), mean_r)),
        residual_translation_rms_m: rms(&dt),
        residual_translation_max_m: max(&dt),
        residual_rotation_rms_rad: rms(&dr),
        residual_rotation_max_rad: max(&dr),
        samples: rmo.len(),
    }
}
