//! A calibration with its quality: ViSP's solution refined over all samples, residuals on
//! held-out samples (leave-one-out), warnings on a poorly conditioned set, and the usual
//! set-up faults (marker size wrong, robot poses in the wrong frame).

use nalgebra::{Isometry3, Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use super::refine::{refine, ObservationModel, RefineOptions, Sample};
use super::{calibrate, residuals};
use crate::vision::VisionError;

/// Below this many samples the set is poorly conditioned.
pub const MIN_SAMPLES: usize = 8;
/// Below this largest rotation between two samples the set is poorly conditioned, rad.
pub const MIN_SPREAD_RAD: f64 = 30.0 * std::f64::consts::PI / 180.0;
/// A rotation axis counts when the samples turn about it by this much (RMS), rad.
pub const AXIS_RMS_RAD: f64 = 3.0 * std::f64::consts::PI / 180.0;
/// A fitted marker scale this far from 1 is reported as a wrong marker size.
pub const SCALE_FAULT: f64 = 0.03;
/// ... and the fit with the scale free must be this many times better than with it fixed.
pub const SCALE_FIT_GAIN: f64 = 1.5;
/// A median difference between the flange's and the camera's rotation angles above this
/// (rad) is reported as a robot-pose frame mismatch.
pub const ANGLE_MISMATCH_RAD: f64 = 1.0 * std::f64::consts::PI / 180.0;

/// Residuals on held-out samples: each sample against the calibration of all the others.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct HeldOut {
    /// RMS of the held-out marker position in the base against the others' fit, mm.
    pub position_rms_mm: f64,
    /// Largest of them, mm.
    pub position_max_mm: f64,
    /// RMS of the held-out marker rotation against the others' fit, deg.
    pub rotation_rms_deg: f64,
    /// Largest of them, deg.
    pub rotation_max_deg: f64,
    /// RMS of the held-out corners reprojected through the others' fit, px (corners known).
    pub reprojection_rms_px: Option<f64>,
}

/// The conditioning of a sample set.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Conditioning {
    /// Number of samples.
    pub samples: usize,
    /// Largest rotation between two samples' flanges, deg.
    pub spread_deg: f64,
    /// Number of axes the flange turns about by more than `AXIS_RMS_RAD` (0..=3).
    pub rotation_axes: usize,
}

/// A calibration and its quality.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// Camera pose in the flange (eMc), refined.
    pub flange_t_camera: Isometry3<f64>,
    /// Marker pose in the base, refined.
    pub base_t_marker: Isometry3<f64>,
    /// ViSP's closed-form eMc before the refinement.
    pub visp_flange_t_camera: Isometry3<f64>,
    /// Residuals of the fit (the marker in the base per sample about the mean), as the CLI
    /// writes them.
    pub fit: super::HandEyeResult,
    /// Residuals on held-out samples.
    pub held_out: HeldOut,
    /// The set's conditioning.
    pub conditioning: Conditioning,
    /// Poor conditioning, in words (empty: none).
    pub warnings: Vec<String>,
    /// Set-up faults detected, in words (empty: none).
    pub faults: Vec<String>,
}

fn split(samples: &[Sample]) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>) {
    samples.iter().map(|s| (s.base_t_flange, s.camera_t_marker)).unzip()
}

fn mean_base_t_marker(emc: &Isometry3<f64>, samples: &[Sample]) -> Result<Isometry3<f64>, VisionError> {
    let (f, m) = split(samples);
    residuals(emc, &f, &m).base_t_marker.to_isometry()
}

/// A solution: ViSP's closed form and its refinement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Solution {
    /// Camera pose in the flange (eMc), refined.
    pub flange_t_camera: Isometry3<f64>,
    /// Marker pose in the base, refined.
    pub base_t_marker: Isometry3<f64>,
    /// ViSP's closed-form eMc.
    pub visp_flange_t_camera: Isometry3<f64>,
}

/// ViSP's closed-form solution refined over all samples.
pub fn solve(samples: &[Sample], model: &ObservationModel, o: &RefineOptions) -> Result<Solution, VisionError> {
    let (f, m) = split(samples);
    let visp = calibrate(&f, &m)?.flange_t_camera.to_isometry()?;
    let bm = mean_base_t_marker(&visp, samples)?;
    let r = refine(samples, model, &visp, &bm, o)?;
    Ok(Solution {
        flange_t_camera: r.flange_t_camera,
        base_t_marker: r.base_t_marker,
        visp_flange_t_camera: visp,
    })
}

/// The conditioning of a set of flange poses.
pub fn conditioning(base_t_flange: &[Isometry3<f64>]) -> Conditioning {
    let mut spread: f64 = 0.0;
    for (i, a) in base_t_flange.iter().enumerate() {
        for b in &base_t_flange[i + 1..] {
            spread = spread.max(a.rotation.angle_to(&b.rotation));
        }
    }
    // Rotation vectors of each flange about the mean orientation, in the flange frame.
    let axes = match base_t_flange.first() {
        None => 0,
        Some(first) => {
            let r0 = first.rotation;
            let w: Vec<Vector3<f64>> = base_t_flange
                .iter()
                .map(|p| (r0.inverse() * p.rotation).scaled_axis())
                .collect();
            let n = w.len() as f64;
            let mean = w.iter().sum::<Vector3<f64>>() / n;
            let cov: Matrix3<f64> = w
                .iter()
                .map(|v| (v - mean) * (v - mean).transpose())
                .sum::<Matrix3<f64>>()
                / n;
            cov.symmetric_eigenvalues()
                .iter()
                .filter(|e| e.max(0.0).sqrt() > AXIS_RMS_RAD)
                .count()
        }
    };
    Conditioning {
        samples: base_t_flange.len(),
        spread_deg: spread.to_degrees(),
        rotation_axes: axes,
    }
}

/// Warnings for a poorly conditioned set.
pub fn conditioning_warnings(c: &Conditioning) -> Vec<String> {
    let mut w = Vec::new();
    if c.rotation_axes < 2 {
        w.push(format!(
            "the flange turns about {} axis(es): rotate about at least two (eMc is not observable otherwise)",
            c.rotation_axes
        ));
    }
    if c.samples < MIN_SAMPLES {
        w.push(format!("{} samples: take at least {MIN_SAMPLES}", c.samples));
    }
    if c.spread_deg < MIN_SPREAD_RAD.to_degrees() {
        w.push(format!(
            "rotation spread {:.1} deg: spread the flange's orientations over at least {:.0} deg",
            c.spread_deg,
            MIN_SPREAD_RAD.to_degrees()
        ));
    }
    w
}

/// The median difference between the rotation angle of the flange's motion and of the
/// camera's motion over all pairs of samples, rad. The two are equal whatever the mount
/// (AX = XB conjugates the rotations): a difference means the robot poses are not the
/// flange's in the base (another link or frame, a joint order or unit error).
pub fn rotation_angle_mismatch(samples: &[Sample]) -> f64 {
    let mut d = Vec::new();
    for (i, a) in samples.iter().enumerate() {
        for b in &samples[i + 1..] {
            let flange = a.base_t_flange.rotation.angle_to(&b.base_t_flange.rotation);
            let camera = a.camera_t_marker.rotation.angle_to(&b.camera_t_marker.rotation);
            d.push((flange - camera).abs());
        }
    }
    if d.is_empty() {
        return 0.0;
    }
    d.sort_by(f64::total_cmp);
    crate::stats::quantile_sorted(&d, 0.5)
}

/// The frame-mismatch fault in words, when the rotation angles disagree.
pub fn frame_mismatch(samples: &[Sample]) -> Option<String> {
    let mismatch = rotation_angle_mismatch(samples);
    (mismatch > ANGLE_MISMATCH_RAD).then(|| {
        format!(
            "robot-pose frame mismatch: the flange's and the camera's rotations differ by {:.2} deg (median over \
             pairs); the joint states or the FK are not the flange's pose in the base (another link, joint \
             order, units)",
            mismatch.to_degrees()
        )
    })
}

/// What is wrong with the camera_info of the detections, if anything: missing (no camera
/// model: the corners cannot be modelled). Its distortion is no concern: the camera_info is
/// read for the estimator's image as the estimator reads it (a rectified image with P and no
/// distortion, a raw one with K and D: [`crate::vision::camera`]).
pub fn camera_info_warning(camera: Option<&crate::vision::CameraModel>) -> Option<String> {
    camera.is_none().then(|| {
        "camera_info missing: no camera model for the detections (check the camera_info topic and the camera \
         driver)"
            .into()
    })
}

/// Leave-one-out residuals: each sample against the calibration of the others (started from
/// the full set's solution).
pub fn held_out(
    samples: &[Sample],
    model: &ObservationModel,
    o: &RefineOptions,
    full: (&Isometry3<f64>, &Isometry3<f64>),
) -> Result<HeldOut, VisionError> {
    let (mut dt, mut dr, mut px) = (Vec::new(), Vec::new(), Vec::new());
    let mut rest = Vec::with_capacity(samples.len());
    for (i, s) in samples.iter().enumerate() {
        rest.clear();
        rest.extend(samples.iter().enumerate().filter(|(j, _)| *j != i).map(|(_, s)| *s));
        let r = refine(&rest, model, full.0, full.1, o)?;
        let seen = s.base_t_flange * r.flange_t_camera * s.camera_t_marker;
        dt.push((seen.translation.vector - r.base_t_marker.translation.vector).norm() * 1e3);
        dr.push(seen.rotation.angle_to(&r.base_t_marker.rotation).to_degrees());
        if let (Some(cam), Some(corners)) = (&model.camera, &s.corners) {
            let ctm = super::refine::predicted_camera_t_marker(&s.base_t_flange, &r.flange_t_camera, &r.base_t_marker);
            for (c, m) in super::refine::marker_corners(model.marker_size).iter().zip(corners) {
                if let Some(p) = cam.project(&(ctm * c).coords) {
                    px.push((p[0] - m[0]).powi(2) + (p[1] - m[1]).powi(2));
                }
            }
        }
    }
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt();
    let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    Ok(HeldOut {
        position_rms_mm: rms(&dt),
        position_max_mm: max(&dt),
        rotation_rms_deg: rms(&dr),
        rotation_max_deg: max(&dr),
        reprojection_rms_px: (!px.is_empty()).then(|| (px.iter().sum::<f64>() / px.len() as f64).sqrt()),
    })
}

/// Set-up faults: the marker size (a free scale fits far from 1) and the robot-pose frame
/// (the flange's and the camera's rotation angles disagree).
pub fn faults(
    samples: &[Sample],
    model: &ObservationModel,
    o: &RefineOptions,
    full: (&Isometry3<f64>, &Isometry3<f64>),
) -> Result<Vec<String>, VisionError> {
    let mut f = Vec::new();
    if let Some(m) = frame_mismatch(samples) {
        // A scale fitted on inconsistent rotations means nothing.
        f.push(m);
        return Ok(f);
    }
    let fixed = refine(samples, model, full.0, full.1, o)?;
    let free = RefineOptions { free_scale: true, ..*o };
    let r = refine(samples, model, full.0, full.1, &free)?;
    // A scale away from 1 that the residuals want: fixing it at 1 must cost clearly more than
    // the noise (a weakly observed scale wanders without changing the fit).
    if (r.scale - 1.0).abs() > SCALE_FAULT && fixed.rms > SCALE_FIT_GAIN * r.rms {
        f.push(format!(
            "marker size wrong: the residuals fit a marker {:.1} % {} ({:.4} m instead of {:.4} m); check the \
             printed marker's side",
            (r.scale - 1.0).abs() * 100.0,
            if r.scale > 1.0 { "larger" } else { "smaller" },
            model.marker_size * r.scale,
            model.marker_size
        ));
    }
    Ok(f)
}

/// Calibrate a sample set: ViSP + refinement, fit and held-out residuals, warnings, faults.
pub fn calibrate_samples(samples: &[Sample], model: &ObservationModel) -> Result<Calibration, VisionError> {
    let o = RefineOptions::default();
    let Solution {
        flange_t_camera: emc,
        base_t_marker: bm,
        visp_flange_t_camera: visp,
    } = solve(samples, model, &o).map_err(|e| match frame_mismatch(samples) {
        Some(m) => VisionError::InvalidInput(format!("{e}; {m}")),
        None => e,
    })?;
    let (f, m) = split(samples);
    let mut fit = residuals(&emc, &f, &m);
    fit.base_t_marker = super::super::estimator::PoseYaml::from_isometry(&bm);
    let conditioning = conditioning(&f);
    let held_out = if samples.len() > 3 {
        held_out(samples, model, &o, (&emc, &bm))?
    } else {
        HeldOut::default()
    };
    Ok(Calibration {
        flange_t_camera: emc,
        base_t_marker: bm,
        visp_flange_t_camera: visp,
        fit,
        held_out,
        conditioning,
        warnings: conditioning_warnings(&conditioning),
        faults: faults(samples, model, &o, (&emc, &bm))?,
    })
}

/// Whether a calibration meets the residual bounds `max_m` (m) and `max_rad` (rad) of the
/// preflight's `HAND_EYE` check (`limits.hand_eye_max_residual_m`, `_rad`): its held-out
/// residuals (each sample against the others' fit, the largest) and the fit's largest (what
/// the preflight reads from the file) within them; held-out residuals need at least 4
/// samples. The error names the figures and the bounds.
pub fn within_bounds(c: &Calibration, max_m: f64, max_rad: f64) -> Result<(), String> {
    let (b_mm, b_deg) = (max_m * 1e3, max_rad.to_degrees());
    if c.fit.samples <= 3 {
        return Err(format!(
            "{} samples: no held-out residuals to judge (at least 4 samples, 8 advised)",
            c.fit.samples
        ));
    }
    let h = &c.held_out;
    let (fit_mm, fit_deg) = (
        c.fit.residual_translation_max_m * 1e3,
        c.fit.residual_rotation_max_rad.to_degrees(),
    );
    // NaN fails every comparison: not within.
    let within = |v: f64, b: f64| v <= b;
    if within(h.position_max_mm, b_mm)
        && within(fit_mm, b_mm)
        && within(h.rotation_max_deg, b_deg)
        && within(fit_deg, b_deg)
    {
        return Ok(());
    }
    Err(format!(
        "held-out residuals {:.2} mm rms ({:.2} max), {:.3} deg rms ({:.3} max), fit {fit_mm:.2} mm / {fit_deg:.3} deg \
         max, over the preflight's bounds {b_mm:.1} mm / {b_deg:.2} deg (limits.hand_eye_max_residual_m, \
         limits.hand_eye_max_residual_rad): the preflight would refuse ~start on this file",
        h.position_rms_mm, h.position_max_mm, h.rotation_rms_deg, h.rotation_max_deg
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Samples whose flanges turn by `angles` (rad) about z while the camera sees the marker
    /// still: each pair's mismatch is the difference of its two angles.
    fn turning_flange(angles: &[f64]) -> Vec<Sample> {
        angles
            .iter()
            .map(|a| Sample {
                base_t_flange: Isometry3::new(Vector3::zeros(), Vector3::z() * *a),
                camera_t_marker: Isometry3::translation(0.0, 0.0, 0.3),
                corners: None,
            })
            .collect()
    }

    #[test]
    fn the_rotation_angle_mismatch_is_the_median_over_pairs_by_the_one_quantile_rule() {
        // Pairs 0.1, 0.3, 0.2: the middle one.
        let odd = rotation_angle_mismatch(&turning_flange(&[0.0, 0.1, 0.3]));
        assert!((odd - 0.2).abs() < 1e-12, "{odd}");
        // Pairs 0.1, 0.2, 0.3, 0.4, 0.6, 0.7: the mean of the two middle ones.
        let even = rotation_angle_mismatch(&turning_flange(&[0.0, 0.1, 0.3, 0.7]));
        assert!((even - 0.35).abs() < 1e-12, "{even}");
        assert_eq!(rotation_angle_mismatch(&turning_flange(&[0.2])), 0.0, "no pair");
    }

    fn calibration(samples: usize, held_out_mm: f64, held_out_deg: f64) -> Calibration {
        let fit = residuals(
            &Isometry3::identity(),
            &[Isometry3::identity(); 4],
            &[Isometry3::identity(); 4],
        );
        Calibration {
            flange_t_camera: Isometry3::identity(),
            base_t_marker: Isometry3::identity(),
            visp_flange_t_camera: Isometry3::identity(),
            fit: crate::vision::hand_eye::HandEyeResult { samples, ..fit },
            held_out: HeldOut {
                position_rms_mm: held_out_mm / 2.0,
                position_max_mm: held_out_mm,
                rotation_rms_deg: held_out_deg / 2.0,
                rotation_max_deg: held_out_deg,
                reprojection_rms_px: None,
            },
            conditioning: conditioning(&[]),
            warnings: Vec::new(),
            faults: Vec::new(),
        }
    }

    #[test]
    fn a_calibration_is_within_the_preflights_bounds_only_by_its_held_out_and_fit_residuals() {
        let (m, rad) = (0.002, 0.5_f64.to_radians());
        assert_eq!(within_bounds(&calibration(8, 1.9, 0.45), m, rad), Ok(()));
        // The figures of a calibration on a breathing marker sampled at random phases.
        let e = within_bounds(&calibration(7, 9.1, 0.3), m, rad).unwrap_err();
        assert!(
            e.contains("4.55 mm rms (9.10 max)") && e.contains("bounds 2.0 mm / 0.50 deg"),
            "{e}"
        );
        assert!(within_bounds(&calibration(8, 1.0, 0.6), m, rad).is_err());
        assert!(within_bounds(&calibration(8, f64::NAN, 0.1), m, rad).is_err());
        // The fit's largest residual is what the preflight reads from the file.
        let mut c = calibration(8, 1.0, 0.1);
        c.fit.residual_translation_max_m = 0.0021;
        assert!(within_bounds(&c, m, rad).unwrap_err().contains("fit 2.10 mm"));
        // Three samples have no held-out residuals: nothing to judge.
        let e = within_bounds(&calibration(3, 0.0, 0.0), m, rad).unwrap_err();
        assert!(e.contains("no held-out residuals"), "{e}");
    }
}
