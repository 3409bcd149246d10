//! A markerless estimate as a trocar measurement for the estimator (pure Rust): the axis
//! (camera frame) carried into the base frame as a port pose with the roll fixed by
//! [`with_roll_convention`], the previous estimate carried into the camera as the prior that
//! resolves the two-fold ambiguity, the gate on the confidence (with the reason a frame is
//! dropped), the covariance of the 5 DOF from the confidence, and one frame through all of
//! it into the trocar estimator's filter ([`track`]: the estimator node's and the trials'
//! camera source's one path).
//!
//! **Roll convention.** The axis fixes the port's z axis (into the body); its roll about that
//! axis is not observable without a marker and does not matter for docking. The port frame's
//! x axis is the base frame's x axis projected onto the plane normal to the trocar's axis (the
//! base y axis when the trocar's axis lies within 25 deg of base x), y = z x x. The same
//! convention is applied to marker measurements in the `fused` method, so switching between
//! the two sources does not rotate the estimate.

use nalgebra::{Isometry3, Matrix3, Translation3, Unit, Vector3};
use serde::{Deserialize, Serialize};

use super::estimator::{MarkerlessEstimate, MarkerlessEstimator, Occluder};
use super::geometry::rotation_of_axis;
pub use super::geometry::with_roll_convention;
use super::Axis;
use crate::validate;
use crate::vision::estimator::{EstimateStatus, TrocarEstimator};
use crate::vision::{ImageView, VisionError};

/// How the trocar estimator measures the trocar.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EstimatorMethod {
    /// The marker on the trocar (the paper's set-up).
    #[default]
    Marker,
    /// The trocar's shape alone (the opening's ellipse, refined on the image's edges).
    Markerless,
    /// The marker when it is seen, else the markerless estimate.
    Fused,
}

impl EstimatorMethod {
    /// Whether this method looks for the marker.
    pub fn uses_marker(self) -> bool {
        matches!(self, Self::Marker | Self::Fused)
    }

    /// Whether this method runs the markerless estimate.
    pub fn uses_markerless(self) -> bool {
        matches!(self, Self::Markerless | Self::Fused)
    }
}

impl std::fmt::Display for EstimatorMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Marker => "marker",
            Self::Markerless => "markerless",
            Self::Fused => "fused",
        })
    }
}

/// Parameters of the markerless measurement (`markerless:` in `config/trocar_estimator.yaml`,
/// whose values, built in, are the defaults: [`crate::config::TROCAR_ESTIMATOR`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct MarkerlessParams {
    /// Estimates below this confidence publish nothing (the frame's reason says why).
    pub min_confidence: f64,
    /// Standard deviation of the port centre at confidence 1, m (scaled by 1 / confidence).
    pub sigma_position_m: f64,
    /// Standard deviation of the axis direction at confidence 1, rad (scaled by 1 / confidence).
    pub sigma_direction_rad: f64,
    /// The radius of the endoscope's shaft, m, whose outline in view is masked out of the
    /// images ([`MarkerlessParams::endoscope`]; 0 = not in view).
    pub endoscope_radius_m: f64,
    /// Correct the hand-eye by the endoscope's axis as both eyes of a stereo pair see it
    /// ([`MarkerlessEstimator::camera_t_believed`]): off, the hand-eye is used as it is.
    pub endoscope_corrects_hand_eye: bool,
}

crate::shipped_defaults!(MarkerlessParams, crate::config::TROCAR_ESTIMATOR, ["markerless"]);

impl MarkerlessParams {
    /// Check the values (the confidence gate in (0, 1], the sigmas positive).
    pub fn validate(&self) -> Result<(), VisionError> {
        validate::positive_at_most("markerless.min_confidence", self.min_confidence, 1.0)?;
        validate::positive_at_most("markerless.sigma_position_m", self.sigma_position_m, 0.1)?;
        validate::positive_at_most("markerless.sigma_direction_rad", self.sigma_direction_rad, 0.5)?;
        let r = self.endoscope_radius_m;
        if !(r.is_finite() && (0.0..=0.05).contains(&r)) {
            return Err(VisionError::InvalidInput(format!(
                "markerless.endoscope_radius_m must be in [0, 0.05] m (0 = not in view), got {r}"
            )));
        }
        Ok(())
    }

    /// The endoscope in view as the estimator masks it: a straight shaft of
    /// `endoscope_radius_m` along the flange's z axis, `length_m` from the flange to its tip,
    /// seen from the camera at `flange_t_camera` (the hand-eye); `None` with a radius of 0.
    pub fn endoscope(&self, flange_t_camera: &Isometry3<f64>, length_m: f64) -> Option<Occluder> {
        (self.endoscope_radius_m > 0.0).then(|| Occluder::endoscope(flange_t_camera, length_m, self.endoscope_radius_m))
    }
}

/// The variance given to the roll (rad^2): unobserved, as ROS marks an unknown DOF.
pub const ROLL_VARIANCE: f64 = 1e6;

/// The port pose in the base frame of an axis seen from a camera at `base_t_camera`.
pub fn port_pose(base_t_camera: &Isometry3<f64>, axis: &Axis) -> Isometry3<f64> {
    let p = base_t_camera * nalgebra::Point3::from(axis.point);
    let z = Unit::new_normalize(base_t_camera.rotation * axis.direction.into_inner());
    Isometry3::from_parts(Translation3::from(p.coords), rotation_of_axis(&z))
}

/// The axis direction (camera frame) of the trocar at `base_t_trocar` seen from a camera at
/// `base_t_camera`: the prior that picks between the two poses an ellipse admits.
pub fn prior_direction(base_t_camera: &Isometry3<f64>, base_t_trocar: &Isometry3<f64>) -> Unit<Vector3<f64>> {
    Unit::new_normalize(base_t_camera.rotation.inverse() * (base_t_trocar.rotation * Vector3::z()))
}

/// The covariance (6 x 6 row-major, ROS order x y z, rotation about x y z, base frame) of a
/// port pose with `confidence`: isotropic position sigma / confidence, the axis direction's
/// two tilts sigma / confidence, the roll [`ROLL_VARIANCE`].
pub fn covariance(pose: &Isometry3<f64>, confidence: f64, p: &MarkerlessParams) -> [f64; 36] {
    let c = confidence.clamp(1e-3, 1.0);
    let (sp, sr) = (p.sigma_position_m / c, p.sigma_direction_rad / c);
    let r = pose.rotation.to_rotation_matrix().into_inner();
    // In the port frame: tilts about x and y, roll about z; rotated into the base frame.
    let local = Matrix3::from_diagonal(&Vector3::new(sr * sr, sr * sr, ROLL_VARIANCE));
    let rot = r * local * r.transpose();
    let mut out = [0.0; 36];
    for i in 0..3 {
        out[i * 6 + i] = sp * sp;
        for j in 0..3 {
            out[(i + 3) * 6 + j + 3] = rot[(i, j)];
        }
    }
    out
}

/// A markerless estimate accepted as a measurement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerlessMeasurement {
    /// The port pose in the base frame (roll by the convention).
    pub pose: Isometry3<f64>,
    /// The estimate's confidence.
    pub confidence: f64,
    /// Its covariance ([`covariance`]).
    pub covariance: [f64; 36],
}

/// The estimate of one frame as a measurement, or why it publishes nothing.
pub fn accept(
    estimate: Option<&MarkerlessEstimate>,
    base_t_camera: &Isometry3<f64>,
    p: &MarkerlessParams,
) -> Result<MarkerlessMeasurement, String> {
    let e = estimate.ok_or("no trocar opening found in the image")?;
    let finite = e.confidence.is_finite()
        && e.axis
            .point
            .iter()
            .chain(e.axis.direction.iter())
            .all(|v| v.is_finite());
    if !finite {
        return Err("markerless estimate not finite".into());
    }
    if e.confidence < p.min_confidence {
        return Err(format!(
            "markerless confidence {:.2} below {:.2} (edge support {:.2}, fit {:.2} px, ambiguity margin {:.2})",
            e.confidence, p.min_confidence, e.edge_support, e.fit_rms_px, e.ambiguity_margin
        ));
    }
    let pose = port_pose(base_t_camera, &e.axis);
    Ok(MarkerlessMeasurement {
        pose,
        confidence: e.confidence,
        covariance: covariance(&pose, e.confidence, p),
    })
}

/// One frame of the markerless estimate as the trocar estimator takes it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tracked {
    /// The frame's measurement (it passed the confidence gate).
    pub measurement: MarkerlessMeasurement,
    /// What the estimator's filter did with it (`Outlier`: rejected by its gate).
    pub status: EstimateStatus,
    /// The filtered port pose at the frame's stamp (roll by the convention) when the
    /// measurement was fused; `None` when it was rejected.
    pub pose: Option<Isometry3<f64>>,
}

/// One frame `view`, captured at `stamp` from a camera at `base_t_camera` (the hand-eye as
/// believed, corrected by the endoscope in view when `p.endoscope_corrects_hand_eye`:
/// [`MarkerlessEstimator::camera_t_believed`];
/// with `right`, the stereo pair's right image captured with it, if any), through the
/// markerless estimate into the trocar estimator `filter`: the filter's estimate carried into the camera as the prior
/// ([`prior_direction`]) and as the port the endoscope goes into
/// ([`MarkerlessEstimator::set_port_hint`]), the estimate ([`MarkerlessEstimator::estimate_stereo`]), the confidence gate
/// ([`accept`]), then the filter's outlier gate and update ([`TrocarEstimator::fuse`]).
/// `Err`: why the frame gives no measurement (the filter unchanged).
pub fn track(
    estimator: &mut MarkerlessEstimator,
    filter: &mut TrocarEstimator,
    view: &ImageView,
    right: Option<&ImageView>,
    stamp: f64,
    base_t_camera: &Isometry3<f64>,
    p: &MarkerlessParams,
) -> Result<Tracked, String> {
    // The camera where the endoscope in view puts it (the hand-eye as believed until then,
    // or when the correction is off).
    let believed = *base_t_camera;
    let correction = |e: &MarkerlessEstimator| {
        if p.endoscope_corrects_hand_eye {
            e.camera_t_believed().inverse()
        } else {
            Isometry3::identity()
        }
    };
    let base_t_camera = &(believed * correction(estimator));
    let tracked = filter.estimate(stamp);
    let prior = tracked
        .as_ref()
        .map(|e| prior_direction(base_t_camera, &e.pose_base_trocar));
    // Where the track puts the port: the endoscope's shaft inside it is hidden by it.
    let port = tracked.map(|e| Axis::of_pose(&(base_t_camera.inverse() * e.pose_base_trocar)));
    estimator.set_port_hint(port.as_ref()).map_err(|e| e.to_string())?;
    let e = estimator
        .estimate_stereo(view, right, prior.as_ref())
        .map_err(|e| e.to_string())?;
    // This frame's view of the endoscope may have moved the correction.
    let base_t_camera = &(believed * correction(estimator));
    let m = accept(e.as_ref(), base_t_camera, p)?;
    let status = filter.fuse(stamp, m.pose);
    let pose = match status {
        EstimateStatus::Initialized | EstimateStatus::Updated | EstimateStatus::Reinitialized => filter
            .estimate(stamp)
            .map(|e| with_roll_convention(&e.pose_base_trocar)),
        _ => None,
    };
    Ok(Tracked {
        measurement: m,
        status,
        pose,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    fn estimate(axis: Axis, confidence: f64) -> MarkerlessEstimate {
        MarkerlessEstimate {
            axis,
            confidence,
            fit_rms_px: 0.3,
            edge_support: 0.9,
            opening_support: 0.95,
            ambiguity_margin: 1.0,
        }
    }

    fn camera() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(0.5, -0.1, 0.6),
            UnitQuaternion::from_euler_angles(3.0, 0.2, -0.4),
        )
    }

    #[test]
    fn the_method_parses_from_yaml_and_defaults_to_the_marker() {
        assert_eq!(EstimatorMethod::default(), EstimatorMethod::Marker);
        for (s, m) in [
            ("marker", EstimatorMethod::Marker),
            ("markerless", EstimatorMethod::Markerless),
            ("fused", EstimatorMethod::Fused),
        ] {
            assert_eq!(crate::config::from_yaml_str::<EstimatorMethod>("t", s).unwrap(), m);
            assert_eq!(m.to_string(), s);
        }
        assert!(crate::config::from_yaml_str::<EstimatorMethod>("t", "aruco").is_err());
        assert!(EstimatorMethod::Fused.uses_marker() && EstimatorMethod::Fused.uses_markerless());
        assert!(!EstimatorMethod::Marker.uses_markerless() && !EstimatorMethod::Markerless.uses_marker());
    }

    #[test]
    fn the_roll_convention_keeps_origin_and_axis_and_ignores_the_input_roll() {
        let base = Isometry3::from_parts(
            Translation3::new(0.6, 0.05, 0.2),
            UnitQuaternion::from_euler_angles(2.9, 0.3, 0.0),
        );
        let z = base.rotation * Vector3::z();
        let out: Vec<Isometry3<f64>> = [0.0, 1.0, -2.5]
            .iter()
            .map(|roll| with_roll_convention(&(base * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), *roll))))
            .collect();
        for o in &out {
            assert!((o.translation.vector - base.translation.vector).norm() < 1e-12);
            assert!((o.rotation * Vector3::z() - z).norm() < 1e-12);
            // x lies in the plane of base x and the axis, on base x's side.
            let x = o.rotation * Vector3::x();
            assert!(x.dot(&Vector3::x()) > 0.0 && x.dot(&Vector3::x().cross(&z)).abs() < 1e-12);
            assert!(o.rotation.angle_to(&out[0].rotation) < 1e-9);
        }
        // An axis along base x takes base y as the reference.
        let along_x = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2),
        );
        let o = with_roll_convention(&along_x);
        assert!((o.rotation * Vector3::z() - Vector3::x()).norm() < 1e-12);
        assert!((o.rotation * Vector3::x() - Vector3::y()).norm() < 1e-12);
    }

    #[test]
    fn an_axis_seen_from_the_camera_lands_on_the_true_port_and_its_prior_is_the_true_axis() {
        let base_t_camera = camera();
        let truth = with_roll_convention(&Isometry3::from_parts(
            Translation3::new(0.62, -0.05, 0.25),
            UnitQuaternion::from_euler_angles(3.0, 0.15, 0.0),
        ));
        let axis = Axis::of_pose(&(base_t_camera.inverse() * truth));
        let pose = port_pose(&base_t_camera, &axis);
        let (dt, dr) = crate::vision::pose_distance(&pose, &truth);
        assert!(dt < 1e-12 && dr < 1e-9, "{dt} {dr}");
        let prior = prior_direction(&base_t_camera, &truth);
        assert!(prior.angle(&axis.direction) < 1e-9);
        // The arm moved: the prior follows the camera.
        let moved = base_t_camera * UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3);
        let seen = (moved.inverse() * truth).rotation * Vector3::z();
        assert!(prior_direction(&moved, &truth).angle(&seen) < 1e-9);
    }

    #[test]
    fn the_covariance_grows_as_the_confidence_falls_and_leaves_the_roll_unknown() {
        let p = MarkerlessParams::default();
        let pose = with_roll_convention(&Isometry3::from_parts(
            Translation3::new(0.6, 0.0, 0.2),
            UnitQuaternion::from_euler_angles(2.8, 0.3, 0.1),
        ));
        let hi = covariance(&pose, 1.0, &p);
        let lo = covariance(&pose, 0.5, &p);
        assert!((hi[0] - 1e-6).abs() < 1e-15 && (lo[0] - 4e-6).abs() < 1e-15);
        let block = |c: &[f64; 36]| Matrix3::from_fn(|i, j| c[(i + 3) * 6 + j + 3]);
        let axis = pose.rotation * Vector3::z();
        let tilt = pose.rotation * Vector3::x();
        // Along the axis: the roll's variance; across it: the tilt's, 4 x at half the confidence.
        assert!((axis.dot(&(block(&hi) * axis)) - ROLL_VARIANCE).abs() < 1e-6);
        let (th, tl) = (tilt.dot(&(block(&hi) * tilt)), tilt.dot(&(block(&lo) * tilt)));
        assert!((th - p.sigma_direction_rad.powi(2)).abs() < 1e-9 && (tl / th - 4.0).abs() < 1e-6);
        // Symmetric, no position-rotation coupling.
        for i in 0..6 {
            for j in 0..6 {
                assert!((hi[i * 6 + j] - hi[j * 6 + i]).abs() < 1e-9);
                if (i < 3) != (j < 3) {
                    assert_eq!(hi[i * 6 + j], 0.0);
                }
            }
        }
    }

    #[test]
    fn low_confidence_no_opening_and_nan_publish_nothing_and_say_why() {
        let p = MarkerlessParams::default();
        let axis = Axis {
            point: Vector3::new(0.01, 0.02, 0.25),
            direction: Unit::new_normalize(Vector3::new(0.1, -0.2, 1.0)),
        };
        let e = accept(None, &camera(), &p).unwrap_err();
        assert!(e.contains("no trocar opening"), "{e}");
        let e = accept(Some(&estimate(axis, 0.3)), &camera(), &p).unwrap_err();
        assert!(e.contains("confidence 0.30 below 0.50"), "{e}");
        let mut bad = estimate(axis, 0.9);
        bad.axis.point.x = f64::NAN;
        assert!(accept(Some(&bad), &camera(), &p).unwrap_err().contains("not finite"));
        let m = accept(Some(&estimate(axis, 0.8)), &camera(), &p).unwrap();
        assert_eq!(m.confidence, 0.8);
        assert!((m.covariance[0] - (0.001f64 / 0.8).powi(2)).abs() < 1e-15);
        assert!((m.pose.translation.vector - (camera() * nalgebra::Point3::from(axis.point)).coords).norm() < 1e-12);
    }

    #[test]
    fn bad_parameters_are_refused_with_their_key() {
        for (p, key) in [
            (
                MarkerlessParams {
                    min_confidence: 0.0,
                    ..Default::default()
                },
                "min_confidence",
            ),
            (
                MarkerlessParams {
                    min_confidence: 1.5,
                    ..Default::default()
                },
                "min_confidence",
            ),
            (
                MarkerlessParams {
                    sigma_position_m: f64::NAN,
                    ..Default::default()
                },
                "sigma_position_m",
            ),
            (
                MarkerlessParams {
                    sigma_direction_rad: -1.0,
                    ..Default::default()
                },
                "sigma_direction_rad",
            ),
            (
                MarkerlessParams {
                    endoscope_radius_m: f64::NAN,
                    ..Default::default()
                },
                "endoscope_radius_m",
            ),
            (
                MarkerlessParams {
                    endoscope_radius_m: -0.001,
                    ..Default::default()
                },
                "endoscope_radius_m",
            ),
        ] {
            let e = p.validate().unwrap_err().to_string();
            assert!(e.contains(key), "{e}");
        }
        assert!(MarkerlessParams::default().validate().is_ok());
    }

    #[test]
    fn the_removed_tracker_key_is_refused_with_the_reason() {
        let e = crate::config::from_yaml_str::<MarkerlessParams>("trocar_estimator.yaml", "tracker_frames: 15\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`markerless.tracker_frames`: the key is gone (ViSP's model-based tracker is removed"),
            "{e}"
        );
    }

    #[test]
    fn the_shipped_estimator_masks_a_5_mm_endoscope_and_a_radius_of_0_masks_nothing() {
        let mount = Isometry3::translation(0.0, 0.07, 0.04);
        let p = MarkerlessParams::default();
        let o = p
            .endoscope(&mount, 0.25)
            .expect("the shipped estimator masks the endoscope");
        assert_eq!(o.shaft.radius, 0.0025);
        // Its tip end lies past the tip on the flange's z axis, seen from the camera.
        assert!((o.shaft.start[2] - (0.25 - 0.04)).abs() <= 0.01, "{:?}", o.shaft.start);
        let none = MarkerlessParams {
            endoscope_radius_m: 0.0,
            ..p
        };
        assert!(none.endoscope(&mount, 0.25).is_none());
    }
}
