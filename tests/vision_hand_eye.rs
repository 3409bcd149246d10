//! Hand-eye calibration through ViSP on synthetic pose pairs, and the CLI round trip.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use trocar_docking::vision::estimator::PoseYaml;
use trocar_docking::vision::hand_eye::{calibrate, HandEyeInput, HandEyeResult, HandEyeSample};

fn truth() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.01, 0.07, 0.04),
        UnitQuaternion::from_euler_angles(0.02, -0.03, 0.05),
    )
}

/// Flange poses around a fixed marker, and the marker seen from each (with optional noise).
fn pairs(n: usize, noise_m: f64) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
    let base_marker = Isometry3::from_parts(Translation3::new(0.6, 0.0, 0.1), UnitQuaternion::identity());
    let (mut f, mut m) = (vec![], vec![]);
    for _ in 0..n {
        let flange = Isometry3::from_parts(
            Translation3::new(
                rng.random_range(0.4..0.6),
                rng.random_range(-0.1..0.1),
                rng.random_range(0.4..0.5),
            ),
            UnitQuaternion::from_euler_angles(
                std::f64::consts::PI + rng.random_range(-0.4..0.4),
                rng.random_range(-0.4..0.4),
                rng.random_range(-0.8..0.8),
            ),
        );
        let mut cm = (flange * truth()).inverse() * base_marker;
        cm.translation.vector += Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ) * noise_m;
        f.push(flange);
        m.push(cm);
    }
    (f, m)
}

fn error(r: &HandEyeResult) -> (f64, f64) {
    let e = r.flange_t_camera.to_isometry().unwrap();
    (
        (e.translation.vector - truth().translation.vector).norm(),
        e.rotation.angle_to(&truth().rotation),
    )
}

#[test]
fn recovers_the_camera_pose_with_small_residuals() {
    let (f, m) = pairs(12, 0.0);
    let r = calibrate(&f, &m).unwrap();
    let (dt, dr) = error(&r);
    assert!(dt < 1e-4 && dr < 1e-4, "{dt} m {dr} rad");
    assert!(r.residual_translation_max_m < 1e-4);
    let (f, m) = pairs(12, 0.001);
    let r = calibrate(&f, &m).unwrap();
    assert!(r.residual_translation_rms_m > 1e-4, "noise must show in the residuals");
    assert!(error(&r).0 < 0.005);
}

#[test]
fn too_few_or_mismatched_pairs_are_errors() {
    let (f, m) = pairs(2, 0.0);
    assert!(calibrate(&f, &m).is_err());
    let (f, m) = pairs(5, 0.0);
    assert!(calibrate(&f, &m[..4]).is_err());
}

#[test]
fn cli_writes_yaml_the_estimator_reads() {
    let (f, m) = pairs(8, 0.0);
    let input = HandEyeInput {
        samples: f
            .iter()
            .zip(&m)
            .map(|(a, b)| HandEyeSample {
                base_t_flange: PoseYaml::from_isometry(a),
                camera_t_marker: PoseYaml::from_isometry(b),
            })
            .collect(),
    };
    let dir = std::env::temp_dir().join(format!("handeye_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let inp = dir.join("pairs.yaml");
    let out = dir.join("hand_eye.yaml");
    std::fs::write(&inp, trocar_docking::config::to_yaml_string("input", &input).unwrap()).unwrap();
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_trocar_docking"))
        .args(["hand-eye", "--input"])
        .arg(&inp)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let text = std::fs::read_to_string(&out).unwrap();
    let r: HandEyeResult = trocar_docking::config::from_yaml_str("result", &text).unwrap();
    assert!(error(&r).0 < 1e-4);
    // Dated today, with its residuals: the preflight's HAND_EYE check reads both (its age by
    // the date, not by the file's modification time, 10 days later here).
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    let h = trocar_docking::preflight::hand_eye_file("hand_eye.yaml", &text, now + 10.0 * 86_400.0, now).unwrap();
    assert_eq!(h.age_source, "calibrated date");
    assert!((0.0..1.0).contains(&h.age_days), "{}", h.age_days);
    assert_eq!(h.residual_max_m, Some(r.residual_translation_max_m));
    assert_eq!(h.residual_max_rad, Some(r.residual_rotation_max_rad));
    let _ = std::fs::remove_dir_all(&dir);
}
