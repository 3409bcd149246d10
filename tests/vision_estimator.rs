//! The trocar estimator: frame chain, smoothing, following, outliers, ageing.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use trocar_docking::vision::{facing_pose, EstimateStatus, EstimatorParams, MarkerDetection, TrocarEstimator};

fn detection(pose_camera_marker: Isometry3<f64>) -> MarkerDetection {
    MarkerDetection {
        id: 0,
        pose_camera_marker,
        corners: [[0.0; 2]; 4],
        reprojection_error_px: 0.1,
    }
}

fn flange() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.4, 0.1, 0.5),
        UnitQuaternion::from_euler_angles(3.0, 0.2, -0.4),
    )
}

#[test]
fn chain_base_flange_camera_marker_trocar() {
    let p = EstimatorParams::default();
    let mut est = TrocarEstimator::new(p.clone()).unwrap();
    let cm = facing_pose(0.3, 0.01, 0.02, 0.1, 0.0, 0.2);
    assert_eq!(
        est.update(0.0, &flange(), Some(&detection(cm))),
        EstimateStatus::Initialized
    );
    let e = est.estimate(0.0).unwrap();
    let expected = flange() * p.flange_t_camera.to_isometry().unwrap() * cm * p.marker_t_trocar.to_isometry().unwrap();
    assert!((e.pose_base_trocar.to_homogeneous() - expected.to_homogeneous()).norm() < 1e-12);
    // The default offset turns z into the trocar (opposite the marker normal).
    let zm = (flange() * p.flange_t_camera.to_isometry().unwrap() * cm).rotation * Vector3::z();
    let zt = e.pose_base_trocar.rotation * Vector3::z();
    assert!((zm + zt).norm() < 1e-12);
    assert!(!e.stale);
}

/// Feed noisy measurements of `truth(t)` at 30 Hz; returns the errors of the estimate and
/// of the raw measurements (m) after a settling second.
fn run(truth: impl Fn(f64) -> Vector3<f64>, sigma: f64) -> (f64, f64) {
    run_with(smoothing(0.15), truth, sigma)
}

/// The shipped parameters with the filter's time constant `tau`, s.
fn smoothing(tau: f64) -> EstimatorParams {
    EstimatorParams {
        time_constant_s: tau,
        ..EstimatorParams::default()
    }
}

fn run_with(p: EstimatorParams, truth: impl Fn(f64) -> Vector3<f64>, sigma: f64) -> (f64, f64) {
    let mut est = TrocarEstimator::new(p).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
    let n = Normal::new(0.0, sigma).unwrap();
    let (mut e_est, mut e_raw, mut k) = (0.0, 0.0, 0.0);
    for i in 0..300 {
        let t = i as f64 / 30.0;
        let z = truth(t) + Vector3::new(n.sample(&mut rng), n.sample(&mut rng), n.sample(&mut rng));
        let pose = Isometry3::from_parts(Translation3::from(z), UnitQuaternion::identity());
        let s = est.fuse(t, pose);
        assert!(
            matches!(s, EstimateStatus::Initialized | EstimateStatus::Updated),
            "{s:?} at {t}"
        );
        if t > 1.0 {
            let e = est.estimate(t).unwrap().pose_base_trocar.translation.vector;
            e_est += (e - truth(t)).norm_squared();
            e_raw += (z - truth(t)).norm_squared();
            k += 1.0;
        }
    }
    ((e_est / k).sqrt(), (e_raw / k).sqrt())
}

#[test]
fn steady_under_noise() {
    let (est, raw) = run(|_| Vector3::new(0.5, 0.0, 0.3), 0.002);
    assert!(est < 0.5 * raw, "filtered rms {est} vs raw {raw}");
}

/// Shipped, the estimator does not smooth (the controller's trocar filter is the one
/// low-pass): a moving trocar is followed without lag, a noisy one passed through as measured.
#[test]
fn the_shipped_estimator_passes_the_measurement_through() {
    assert_eq!(EstimatorParams::default().time_constant_s, 0.0);
    let (est, _) = run_with(
        EstimatorParams::default(),
        |t| Vector3::new(0.5 + 0.01 * t, 0.0, 0.3),
        0.0,
    );
    assert!(est < 1e-9, "tracking error {est} m");
    let (est, raw) = run_with(EstimatorParams::default(), |_| Vector3::new(0.5, 0.0, 0.3), 0.002);
    assert!((est - raw).abs() < 1e-12, "{est} vs {raw}");
}

#[test]
fn follows_a_moving_trocar() {
    // 1 cm/s drift (breathing-scale motion): the estimate lags by about v * tau.
    let (est, _) = run(|t| Vector3::new(0.5 + 0.01 * t, 0.0, 0.3), 0.0);
    assert!(est < 0.004, "tracking error {est} m");
}

#[test]
fn outliers_rejected_then_a_real_jump_is_accepted() {
    let p = EstimatorParams::default();
    let mut est = TrocarEstimator::new(p.clone()).unwrap();
    let at = |x: f64| Isometry3::translation(x, 0.0, 0.3);
    assert_eq!(est.fuse(0.0, at(0.5)), EstimateStatus::Initialized);
    assert_eq!(est.fuse(0.03, at(0.6)), EstimateStatus::Outlier);
    assert_eq!(est.fuse(0.06, at(0.5)), EstimateStatus::Updated);
    let x = est.estimate(0.06).unwrap().pose_base_trocar.translation.x;
    assert!((x - 0.5).abs() < 1e-9);
    // The trocar really moved: consistent far measurements restart the filter.
    let mut last = EstimateStatus::Outlier;
    for k in 0..p.reinit_after {
        last = est.fuse(0.1 + 0.03 * f64::from(k), at(0.56));
    }
    assert_eq!(last, EstimateStatus::Reinitialized);
    assert!((est.estimate(1.0).unwrap().pose_base_trocar.translation.x - 0.56).abs() < 1e-9);
}

#[test]
fn ages_and_goes_stale_without_measurements() {
    let p = EstimatorParams::default();
    let mut est = TrocarEstimator::new(p.clone()).unwrap();
    assert!(est.estimate(0.0).is_none());
    assert_eq!(est.update(0.0, &flange(), None), EstimateStatus::NoMeasurement);
    est.update(
        1.0,
        &flange(),
        Some(&detection(facing_pose(0.3, 0.0, 0.0, 0.0, 0.0, 0.0))),
    );
    assert_eq!(est.update(1.2, &flange(), None), EstimateStatus::NoMeasurement);
    let e = est.estimate(1.2).unwrap();
    assert!(!e.stale && (e.age_s - 0.2).abs() < 1e-12);
    let e = est.estimate(1.0 + p.stale_after_s + 0.01).unwrap();
    assert!(e.stale);
    assert!(est.estimate(f64::NAN).unwrap().stale);
}

#[test]
fn bad_measurements_are_refused() {
    let mut est = TrocarEstimator::new(EstimatorParams::default()).unwrap();
    let good = detection(facing_pose(0.3, 0.0, 0.0, 0.0, 0.0, 0.0));
    let mut poor = good.clone();
    poor.reprojection_error_px = 10.0;
    assert_eq!(est.update(0.0, &flange(), Some(&poor)), EstimateStatus::PoorQuality);
    let mut nan = good.clone();
    nan.pose_camera_marker.translation.x = f64::NAN;
    assert_eq!(est.update(0.0, &flange(), Some(&nan)), EstimateStatus::InvalidInput);
    assert_eq!(
        est.update(f64::NAN, &flange(), Some(&good)),
        EstimateStatus::InvalidInput
    );
    assert_eq!(est.update(1.0, &flange(), Some(&good)), EstimateStatus::Initialized);
    assert_eq!(est.update(0.5, &flange(), Some(&good)), EstimateStatus::InvalidInput);
    let bad = EstimatorParams {
        stale_after_s: -1.0,
        ..Default::default()
    };
    assert!(TrocarEstimator::new(bad).is_err());
}

#[test]
fn a_file_of_the_estimator_section_takes_the_shipped_values_for_what_it_leaves_out() {
    let dir = std::env::temp_dir().join(format!("trocar_docking_estimator_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("estimator.yaml");
    std::fs::write(&path, "gate_translation_m: 0.05\n").unwrap();
    let p = EstimatorParams::from_yaml_file(&path).unwrap();
    // The shipped section: `estimator:` in config/trocar_estimator.yaml.
    let d = EstimatorParams::default();
    assert_eq!(
        (d.time_constant_s, d.gate_translation_m, d.reinit_after),
        (0.0, 0.02, 5)
    );
    assert_eq!(
        p,
        EstimatorParams {
            gate_translation_m: 0.05,
            ..d
        }
    );
    std::fs::write(&path, "gate_translation: 0.05\n").unwrap();
    let e = EstimatorParams::from_yaml_file(&path).unwrap_err().to_string();
    assert!(e.contains("`estimator.gate_translation`: unknown key"), "{e}");
    std::fs::write(&path, "stale_after_s: -1\n").unwrap();
    assert!(EstimatorParams::from_yaml_file(&path).is_err());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn marker_in_camera_inverts_the_estimator_chain() {
    let est = TrocarEstimator::new(EstimatorParams::default()).unwrap();
    let p = EstimatorParams::default();
    let (fc, mt) = (
        p.flange_t_camera.to_isometry().unwrap(),
        p.marker_t_trocar.to_isometry().unwrap(),
    );
    let trocar = Isometry3::from_parts(
        Translation3::new(0.6, -0.05, 0.2),
        UnitQuaternion::from_euler_angles(2.9, 0.1, 0.3),
    );
    let seen = trocar_docking::vision::estimator::marker_in_camera(&flange(), &fc, &trocar, &mt);
    let back = est.measurement_in_base(&flange(), &seen);
    let (dt, dr) = trocar_docking::vision::pose_distance(&back, &trocar);
    assert!(dt < 1e-12 && dr < 1e-9, "{dt} m, {dr} rad");
}
