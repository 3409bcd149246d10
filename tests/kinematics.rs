//! Kinematics bridge: FK against hand-computed values, the Jacobian against finite
//! differences of FK, and every error path.

use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use proptest::prelude::*;
use trocar_docking::kinematics::lbr::{urdf, LbrModel, ToolParams};
use trocar_docking::kinematics::{
    JointVector, KdlChain, Kinematics, KinematicsError, LbrKinematics, BASE_LINK, TIP_LINK,
};

fn med7() -> LbrKinematics {
    LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).expect("Med 7 model")
}

fn med7_file() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("urdf")
        .join(LbrModel::Med7.file_name())
}

#[test]
fn zero_configuration_heights() {
    // Straight up: the tip height is the sum of the joint offsets plus flange and tool.
    for (model, heights) in [
        (
            LbrModel::Med7,
            [0.1475, 0.1925, 0.2075, 0.1925, 0.2075, 0.1925, 0.091, 0.035],
        ),
        (
            LbrModel::Med14,
            [0.147, 0.2125, 0.228, 0.192, 0.2075, 0.1925, 0.091, 0.035],
        ),
    ] {
        for tool in [0.25, 0.4] {
            let kin = LbrKinematics::from_model(
                model,
                &ToolParams {
                    length_m: tool,
                    diameter_m: 0.005,
                },
            )
            .unwrap();
            let pose = kin.fk(&JointVector::zeros()).unwrap();
            let expected: f64 = heights.iter().sum::<f64>() + tool;
            assert!(
                (pose.translation.z - expected).abs() < 1e-12,
                "{model:?}: {} vs {expected}",
                pose.translation.z
            );
            assert!(pose.translation.x.abs() < 1e-12);
            // Lateral offsets cancel pairwise on both arms.
            assert!(pose.translation.y.abs() < 1e-12, "{model:?} y = {}", pose.translation.y);
            assert!(pose.rotation.angle() < 1e-12);
        }
    }
}

#[test]
fn elbow_at_ninety_degrees_by_hand() {
    // A4 at +90 deg about -y: everything above joint 4 swings towards -x.
    let kin = med7();
    let mut q = JointVector::zeros();
    q[3] = std::f64::consts::FRAC_PI_2;
    let p = kin.fk(&q).unwrap().translation.vector;
    let below = 0.1475 + 0.1925 + 0.2075 + 0.1925; // height of joint 4
    let above = 0.2075 + 0.1925 + 0.091 + 0.035 + 0.25; // beyond joint 4
                                                        // Rotation about -y by +90 deg maps +z to -x.
    assert!((p.x + above).abs() < 1e-9, "x = {}", p.x);
    assert!((p.z - below).abs() < 1e-9, "z = {}", p.z);
}

fn numeric_jacobian(kin: &LbrKinematics, q: &JointVector) -> nalgebra::SMatrix<f64, 6, 7> {
    let h = 1e-6;
    let mut j = nalgebra::SMatrix::<f64, 6, 7>::zeros();
    for i in 0..7 {
        let mut qp = *q;
        let mut qm = *q;
        qp[i] += h;
        qm[i] -= h;
        let (tp, tm): (Isometry3<f64>, Isometry3<f64>) = (kin.fk(&qp).unwrap(), kin.fk(&qm).unwrap());
        let v = (tp.translation.vector - tm.translation.vector) / (2.0 * h);
        // Angular velocity from the rotation difference, in the base frame.
        let dr: UnitQuaternion<f64> = tp.rotation * tm.rotation.inverse();
        let w: Vector3<f64> = dr.scaled_axis() / (2.0 * h);
        j.fixed_view_mut::<3, 1>(0, i).copy_from(&v);
        j.fixed_view_mut::<3, 1>(3, i).copy_from(&w);
    }
    j
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]
    #[test]
    fn jacobian_matches_finite_differences(qv in proptest::collection::vec(-2.0f64..2.0, 7)) {
        let kin = med7();
        let q = JointVector::from_column_slice(&qv);
        let (pose, jac) = kin.fk_jacobian(&q).unwrap();
        let fk = kin.fk(&q).unwrap();
        prop_assert!((pose.translation.vector - fk.translation.vector).norm() < 1e-12);
        prop_assert!(pose.rotation.angle_to(&fk.rotation) < 1e-12);
        let num = numeric_jacobian(&kin, &q);
        let lin = (jac.fixed_rows::<3>(0) - num.fixed_rows::<3>(0)).abs().max();
        let ang = (jac.fixed_rows::<3>(3) - num.fixed_rows::<3>(3)).abs().max();
        prop_assert!(lin < 1e-6, "linear part differs by {}", lin);
        prop_assert!(ang < 1e-6, "angular part differs by {}", ang);
    }
}

#[test]
fn file_and_string_chains_agree_and_limits_are_read() {
    let from_file = LbrKinematics::from_urdf_file(&med7_file(), TIP_LINK).unwrap();
    let from_model = med7();
    let q = JointVector::from_column_slice(&[0.3, 0.6, -0.2, -1.2, 0.4, 0.8, 0.1]);
    let (a, b) = (from_file.fk(&q).unwrap(), from_model.fk(&q).unwrap());
    assert!((a.translation.vector - b.translation.vector).norm() < 1e-12);
    let lim = from_file.limits();
    assert!((lim.upper[1] - 120f64.to_radians()).abs() < 1e-5);
    assert!((lim.lower[6] + 175f64.to_radians()).abs() < 1e-5);
    assert!((lim.velocity[3] - 130f64.to_radians()).abs() < 1e-5);
    assert_eq!(lim.effort[0], 176.0);
    let names: Vec<String> = (1..=7).map(|i| format!("lbr_joint_{i}")).collect();
    assert_eq!(from_file.joint_names(), names.as_slice());
}

#[test]
fn short_chain_and_dynamic_interface() {
    let chain = KdlChain::from_urdf_file(&med7_file(), BASE_LINK, "lbr_link_2").unwrap();
    assert_eq!(chain.n_joints(), 2);
    let pose = chain.fk_slice(&[0.0, 0.0]).unwrap();
    assert!((pose.translation.z - (0.1475 + 0.1925)).abs() < 1e-12);
    assert!((pose.translation.y + 0.0105).abs() < 1e-12);
    let mut jac = vec![0.0; 12];
    chain.fk_jacobian_slice(&[0.1, 0.2], &mut jac).unwrap();
    // A 2-joint chain cannot be an arm.
    assert!(matches!(
        LbrKinematics::from_chain(chain),
        Err(KinematicsError::WrongJointCount { expected: 7, got: 2 })
    ));
}

#[test]
fn error_paths_are_typed_errors() {
    let xml = urdf(LbrModel::Med7, &ToolParams::default()).unwrap();
    let kin = med7();
    // Wrong joint count, NaN, infinity.
    assert!(matches!(
        kin.chain().fk_slice(&[0.0; 6]),
        Err(KinematicsError::WrongJointCount { expected: 7, got: 6 })
    ));
    assert!(matches!(
        kin.chain().fk_slice(&[0.0; 8]),
        Err(KinematicsError::WrongJointCount { .. })
    ));
    let mut q = JointVector::zeros();
    q[4] = f64::NAN;
    assert!(matches!(kin.fk(&q), Err(KinematicsError::NonFinite { index: 4, .. })));
    q[4] = f64::INFINITY;
    assert!(matches!(
        kin.fk_jacobian(&q),
        Err(KinematicsError::NonFinite { index: 4, .. })
    ));
    let mut jac = vec![0.0; 5];
    assert!(kin.chain().fk_jacobian_slice(&[0.0; 7], &mut jac).is_err());
    // Malformed URDF, not XML at all, empty, truncated.
    for bad in ["", "not xml", "<robot name=\"x\">", &xml[..xml.len() / 2]] {
        let e = KdlChain::from_urdf_str(bad, BASE_LINK, TIP_LINK).unwrap_err();
        assert!(matches!(e, KinematicsError::Urdf(_)), "{e}");
    }
    // Unknown links, and a chain run backwards.
    let e = KdlChain::from_urdf_str(&xml, BASE_LINK, "no_such_link").unwrap_err();
    assert!(e.to_string().contains("no_such_link"), "{e}");
    let e = KdlChain::from_urdf_str(&xml, "nope", TIP_LINK).unwrap_err();
    assert!(e.to_string().contains("nope"), "{e}");
    assert!(KdlChain::from_urdf_str(&xml, TIP_LINK, BASE_LINK).is_err());
    // Missing file.
    let e = KdlChain::from_urdf_file(std::path::Path::new("/nonexistent.urdf"), BASE_LINK, TIP_LINK).unwrap_err();
    assert!(matches!(e, KinematicsError::Io { .. }), "{e}");
    // A revolute joint without limits cannot be an arm joint.
    let no_limits = xml.replacen("type=\"revolute\"", "type=\"continuous\"", 1);
    assert!(LbrKinematics::from_urdf_str(&no_limits, TIP_LINK).is_err());
}

#[test]
fn one_chain_is_shared_safely_between_threads() {
    // KDL's Joint::pose caches its last result; the bridge must not depend on it, so one
    // chain evaluated from several threads at different q gives the sequential answers.
    let kin = med7();
    let qs: Vec<JointVector> = (0..4)
        .map(|k| JointVector::from_element(0.1 + 0.3 * k as f64))
        .collect();
    let expect: Vec<_> = qs.iter().map(|q| kin.fk_jacobian(q).unwrap()).collect();
    std::thread::scope(|scope| {
        for (q, (pose, jac)) in qs.iter().zip(&expect) {
            let kin = &kin;
            scope.spawn(move || {
                for _ in 0..20_000 {
                    let (p, j) = kin.fk_jacobian(q).unwrap();
                    assert_eq!(p.translation.vector, pose.translation.vector);
                    assert_eq!(&j, jac);
                }
            });
        }
    });
}

#[test]
fn the_endoscope_length_is_read_from_the_flange_to_the_tip() {
    // The built-in model and its URDF file: the default endoscope's 0.25 m.
    let built_in = LbrKinematics::flange_to_tip_m(LbrModel::Med7, "").unwrap();
    assert!((built_in - ToolParams::default().length_m).abs() < 1e-9, "{built_in}");
    let file = LbrKinematics::flange_to_tip_m(LbrModel::Med7, med7_file().to_str().unwrap()).unwrap();
    assert!((file - built_in).abs() < 1e-9, "{file}");
    // A longer scope written into a URDF is read as such.
    let dir = std::env::temp_dir().join(format!("trocar_docking_scope_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("long_scope.urdf");
    let tool = ToolParams {
        length_m: 0.33,
        diameter_m: 0.01,
    };
    std::fs::write(&path, urdf(LbrModel::Med14, &tool).unwrap()).unwrap();
    let long = LbrKinematics::flange_to_tip_m(LbrModel::Med7, path.to_str().unwrap()).unwrap();
    assert!((long - 0.33).abs() < 1e-9, "{long}");
    // A missing URDF is a typed error.
    assert!(LbrKinematics::flange_to_tip_m(LbrModel::Med7, "/nonexistent.urdf").is_err());
    std::fs::remove_dir_all(&dir).ok();
}
