use nalgebra::{Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;

use super::*;
use crate::kinematics::lbr::LbrModel;
use crate::kinematics::{LbrKinematics, TIP_LINK};
use crate::sim::ScenarioParams;

fn kin() -> LbrKinematics {
    LbrKinematics::from_model_or_file(LbrModel::Med7, "", TIP_LINK).unwrap()
}

/// The 16 images of `good`'s camera: 15 Hz over 1 s.
fn left_stamps() -> Vec<f64> {
    (0..16).map(|i| 100.0 + f64::from(i) / 15.0).collect()
}

/// A set-up as the simulator in the camera mode presents it: every check passes.
fn good(kin: &dyn Kinematics) -> Observations {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let s = Scenario::sample(&ScenarioParams::default(), kin, &mut rng).unwrap();
    let names = crate::kinematics::joint_names();
    Observations {
        simulator: Some(Simulator { camera: true }),
        use_sim_time: true,
        joint_states: Some(JointStates {
            stream: Stream {
                count: 501,
                span_s: 1.0,
            },
            names,
            positions: s.q0.to_vec(),
            motion_rad: 1e-5,
        }),
        lbr_state: Some(LbrState {
            stream: Stream {
                count: 501,
                span_s: 1.0,
            },
            sample_time: 0.002,
            cadence_s: 0.002,
            tau_ext: (0..100)
                .map(|i| (0..7).map(|k| 0.3 + 0.1 * f64::from((i + k) % 3)).collect())
                .collect(),
        }),
        camera: Some(Camera {
            info: Some(CameraInfo {
                fx: 700.0,
                fy: 700.0,
                width: 1280,
                height: 720,
            }),
            images: Stream { count: 16, span_s: 1.0 },
            image_size: Some((1280, 720)),
            image_stamps: left_stamps(),
            right: None,
        }),
        marker: Marker {
            stream: Stream { count: 15, span_s: 1.0 },
            last: Some(s.trocar_rest),
            configured_size_m: Some(0.04),
            simulated_size_m: Some(0.04),
            markerless: false,
        },
        hand_eye: Some(Ok(HandEye {
            path: "hand_eye.yaml".into(),
            age_days: 3.0,
            age_source: "modification time",
            residual_max_m: Some(0.0008),
            residual_max_rad: Some(0.003),
        })),
        driver_clock: Some(driver_clock::DriverClock {
            joint_state_delays_s: vec![3e-4; 500],
            lbr_state_delays_s: vec![3e-4; 500],
            stamped_commands: false,
            time_from_start_s: 0.02,
            driver_period_s: 0.002,
            control_period_s: 0.01,
            input_timeout_s: 0.1,
        }),
        command_subscribers: vec!["/lbr_med_sim".into()],
        command_topic: "/cmd".into(),
        camera_clock: Some(CameraClock {
            ages_s: vec![0.041, 0.038, 0.052],
            camera: "/lbr_med_sim on 127.0.0.1".into(),
            controller_host: "127.0.0.1".into(),
            tolerance: CameraClockTolerance {
                pairing_s: 0.02,
                pose_timeout_s: 0.5,
            },
        }),
    }
}

#[test]
fn a_camera_clock_off_fails_its_own_check_only() {
    let k = kin();
    let mut o = good(&k);
    for a in &mut o.camera_clock.as_mut().unwrap().ages_s {
        *a += 0.2;
    }
    assert_eq!(failed(&o), vec!["CAMERA_CLOCK"]);
    o.camera_clock = None;
    o.camera = None;
    let r = evaluate(&o, &Limits::default(), &TareParams::default(), &k);
    let c = r.checks.iter().find(|c| c.code == "CAMERA_CLOCK").unwrap();
    assert_eq!(c.verdict, Verdict::NotChecked);
}

fn failed(obs: &Observations) -> Vec<&'static str> {
    evaluate(obs, &Limits::default(), &TareParams::default(), &kin()).failed_codes()
}

#[test]
fn a_good_set_up_passes_and_says_what_it_does_not_check() {
    let k = kin();
    let r = evaluate(&good(&k), &Limits::default(), &TareParams::default(), &k);
    assert!(r.passed(), "{r}");
    let fri = r.checks.iter().find(|c| c.code == "FRI_STATE").unwrap();
    assert_eq!(fri.verdict, Verdict::NotChecked);
    assert!(r.to_string().ends_with("preflight passed"));
    assert!(r.to_string().contains("lbr_med_sim"));
}

#[test]
fn each_fault_fails_its_own_check_only() {
    let k = kin();
    type Fault = fn(&mut Observations);
    let faults: [(&str, Fault); 15] = [
        ("JOINT_STATES", |o| {
            o.joint_states.as_mut().unwrap().stream.span_s = 10.0
        }),
        ("LBR_STATE", |o| o.lbr_state.as_mut().unwrap().sample_time = 0.001),
        ("JOINT_NAMES", |o| {
            o.joint_states.as_mut().unwrap().names[6] = "a7".into()
        }),
        ("TORQUES_AT_REST", |o| {
            o.lbr_state.as_mut().unwrap().tau_ext[5][2] = 400.0
        }),
        ("TORQUES_AT_REST", |o| {
            o.joint_states.as_mut().unwrap().motion_rad = 0.01
        }),
        ("CAMERA_INFO", |o| {
            o.camera.as_mut().unwrap().info.as_mut().unwrap().fx = f64::NAN
        }),
        ("CAMERA_INFO", |o| {
            o.camera.as_mut().unwrap().image_size = Some((640, 360))
        }),
        ("IMAGE_RATE", |o| o.camera.as_mut().unwrap().images.count = 5),
        ("MARKER", |o| o.marker.simulated_size_m = Some(0.05)),
        ("MARKER", |o| o.marker.stream.count = 2),
        ("HAND_EYE", |o| {
            if let Some(Ok(h)) = &mut o.hand_eye {
                h.age_days = 31.0;
            }
        }),
        ("HAND_EYE", |o| {
            if let Some(Ok(h)) = &mut o.hand_eye {
                h.residual_max_m = Some(0.003);
            }
        }),
        ("CLOCK", |o| o.simulator = None),
        ("COMMAND_SUBSCRIBER", |o| o.command_subscribers.clear()),
        ("DRIVER_CLOCK", |o| {
            if let Some(c) = &mut o.driver_clock {
                c.joint_state_delays_s = vec![-0.15; 500];
            }
        }),
    ];
    for (code, fault) in faults {
        let mut o = good(&k);
        fault(&mut o);
        // Without the URDF's joints the reach cannot be tested: it fails too.
        let want = if code == "JOINT_NAMES" {
            vec![code, "REACH"]
        } else {
            vec![code]
        };
        assert_eq!(failed(&o), want, "fault for {code}");
    }
}

#[test]
fn no_driver_fails_the_driver_checks_and_what_needs_the_joints() {
    let k = kin();
    let mut o = good(&k);
    o.joint_states = None;
    o.lbr_state = None;
    assert_eq!(
        failed(&o),
        vec!["JOINT_STATES", "LBR_STATE", "JOINT_NAMES", "TORQUES_AT_REST", "REACH"]
    );
}

#[test]
fn no_marker_fails_the_marker_and_the_reach() {
    let k = kin();
    let mut o = good(&k);
    o.marker.last = None;
    o.marker.stream = Stream::default();
    assert_eq!(failed(&o), vec!["MARKER", "REACH"]);
}

#[test]
fn a_trocar_out_of_reach_or_at_the_wrist_limit_fails() {
    let k = kin();
    let mut o = good(&k);
    let t = o.marker.last.unwrap();
    // 1.2 m further down: farther from the shoulder than the arm and the scope reach.
    o.marker.last = Some(Translation3::from(Vector3::new(0.0, 0.0, -1.2)) * t);
    assert_eq!(failed(&o), vec!["REACH"]);
    // 0.8 m further out in front: the same.
    let mut o = good(&k);
    o.marker.last = Some(Translation3::from(Vector3::new(0.8, 0.0, 0.0)) * t);
    assert_eq!(failed(&o), vec!["REACH"]);
    // Pointing up into the trocar from below, at the same place.
    let mut o = good(&k);
    let flip = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    o.marker.last = Some(Isometry3::from_parts(t.translation, flip * t.rotation));
    assert_eq!(failed(&o), vec!["REACH"]);
}

#[test]
fn a_simulated_clock_without_the_simulator_fails_and_the_direct_mode_skips_the_camera() {
    let k = kin();
    let mut o = good(&k);
    o.simulator = Some(Simulator { camera: false });
    o.camera = None;
    o.hand_eye = None;
    o.marker.configured_size_m = None;
    let r = evaluate(&o, &Limits::default(), &TareParams::default(), &k);
    assert!(r.passed(), "{r}");
    let skipped: Vec<_> = r
        .checks
        .iter()
        .filter(|c| c.verdict == Verdict::NotChecked)
        .map(|c| c.code)
        .collect();
    assert_eq!(
        skipped,
        vec!["FRI_STATE", "CAMERA_INFO", "IMAGE_RATE", "STEREO", "HAND_EYE"]
    );
}

#[test]
fn hand_eye_files_age_by_their_date_else_their_modification_time() {
    let pose = "flange_t_camera: {translation: [0, 0.07, 0.04], quaternion_xyzw: [0, 0, 0, 1]}\n";
    let now = days_from_civil(2026, 3, 1) as f64 * 86_400.0;
    let h = hand_eye_file("f", pose, now - 2.0 * 86_400.0, now).unwrap();
    assert!((h.age_days - 2.0).abs() < 1e-9);
    assert_eq!(h.residual_max_m, None);
    let dated =
        format!("{pose}calibrated: 2026-01-30\nresidual_translation_max_m: 0.0011\nresidual_rotation_max_rad: 0.002\n");
    let h = hand_eye_file("f", &dated, now, now).unwrap();
    assert!((h.age_days - 30.0).abs() < 1e-9, "{}", h.age_days);
    assert_eq!(h.age_source, "calibrated date");
    assert_eq!(h.residual_max_m, Some(0.0011));
    assert!(hand_eye_file("f", "a: 1\n", now, now)
        .unwrap_err()
        .contains("flange_t_camera"));
    // easy_handeye's file carries no date: its age is its modification time's.
    let easy = "parameters: {eye_on_hand: true, robot_effector_frame: lbr_link_7}\n\
                transformation: {x: 0, y: 0.07, z: 0.075, qx: 0, qy: 0, qz: 0, qw: 1}\n";
    let h = hand_eye_file("f", easy, now - 3.0 * 86_400.0, now).unwrap();
    assert!((h.age_days - 3.0).abs() < 1e-9 && h.age_source == "modification time");
    assert!(hand_eye_file("f", &format!("{pose}calibrated: March\n"), now, now).is_err());
    assert!(hand_eye_file("f", &format!("{pose}residual_rotation_max_rad: .nan\n"), now, now).is_err());
    for day in [0, 59, 11_016, 19_782, 20_513] {
        let t = f64::from(day) * 86_400.0 + 3600.0;
        assert_eq!(parse_date(&date_of(t)), Some(f64::from(day) * 86_400.0), "day {day}");
    }
    assert_eq!(date_of(0.0), "1970-01-01");
    assert_eq!(date_of(951_782_400.0), "2000-02-29");
    // Leap years and the epoch.
    assert_eq!(days_from_civil(1970, 1, 1), 0);
    assert_eq!(days_from_civil(2000, 3, 1) - days_from_civil(2000, 2, 28), 2);
}

#[test]
fn default_limits_are_valid_and_a_bad_one_is_named() {
    Limits::default().validate().unwrap();
    let bad = Limits {
        rate_tolerance: 1.5,
        ..Limits::default()
    };
    assert_eq!(bad.validate().unwrap_err().key, "limits.rate_tolerance");
}

#[test]
fn the_cadence_is_the_median_interval_whatever_was_lost() {
    // 500 Hz for 1 s, in any order, with bursts of ten messages lost (20 % in all): the
    // period stays 2 ms.
    let mut t: Vec<f64> = (0..500)
        .filter(|i| i % 50 >= 10)
        .map(|i| 0.002 * f64::from(i))
        .collect();
    t.reverse();
    assert!((cadence_s(&t) - 0.002).abs() < 1e-12, "{}", cadence_s(&t));
    // A driver at 400 Hz.
    let slow: Vec<f64> = (0..400).map(|i| 0.0025 * f64::from(i)).collect();
    assert!((cadence_s(&slow) - 0.0025).abs() < 1e-12);
    assert!(cadence_s(&[1.0]).is_nan());
    assert!(cadence_s(&[f64::NAN, 1.0]).is_nan());
}

fn lbr_check(o: &Observations) -> (bool, String) {
    let k = kin();
    let r = evaluate(o, &Limits::default(), &TareParams::default(), &k);
    let c = r.checks.iter().find(|c| c.code == "LBR_STATE").unwrap();
    (c.verdict == Verdict::Pass, c.detail.clone())
}

#[test]
fn lbr_state_lost_on_the_way_passes_but_a_slow_driver_or_a_starved_controller_fails() {
    let k = kin();
    // The driver at its FRI cycle, 16 % of it lost in this node's subscriber (a loaded host).
    let mut o = good(&k);
    o.lbr_state.as_mut().unwrap().stream.count = 421;
    let (ok, detail) = lbr_check(&o);
    assert!(ok, "{detail}");
    assert!(detail.contains("420 Hz received (84 % of the cycles"), "{detail}");
    // The driver sending every 2.5 ms while the FRI cycle is 2 ms: fails.
    let mut o = good(&k);
    o.lbr_state.as_mut().unwrap().cadence_s = 0.0025;
    let (ok, detail) = lbr_check(&o);
    assert!(!ok && detail.contains("(400 Hz)"), "{detail}");
    // Just inside the tolerance (10 %): 2.2 ms passes.
    o.lbr_state.as_mut().unwrap().cadence_s = 0.00221;
    assert!(lbr_check(&o).0);
    // The right cadence but under 90 Hz reaching the controller: fails.
    let mut o = good(&k);
    o.lbr_state.as_mut().unwrap().stream.count = 81;
    let (ok, detail) = lbr_check(&o);
    assert!(!ok && detail.contains("80 Hz received"), "{detail}");
    assert_eq!(failed(&o), vec!["LBR_STATE"]);
}

#[test]
fn the_stereo_check_wants_a_right_image_with_nearly_every_left_one_and_a_baseline() {
    let k = kin();
    let with_right = |stamps: Vec<f64>, baseline: Option<Result<f64, String>>| {
        let mut o = good(&k);
        o.camera.as_mut().unwrap().right = Some(RightCamera {
            topic: "/zedm/zed_node/right/image_rect_color".into(),
            stamps,
            baseline_m: baseline,
        });
        o
    };
    let stereo = |o: &Observations| {
        let r = evaluate(o, &Limits::default(), &TareParams::default(), &k);
        let c = r.checks.iter().find(|c| c.code == "STEREO").unwrap().clone();
        (c, failed(o))
    };
    // A marker set-up (no right image read): not checked, and the set-up passes.
    let (c, f) = stereo(&good(&k));
    assert_eq!(c.verdict, Verdict::NotChecked);
    assert!(f.is_empty(), "{f:?}");
    // Every left image with its right image, stamped alike to within 0.5 ms: passes.
    let b = Some(Ok(0.063));
    let paired: Vec<f64> = left_stamps().iter().map(|t| t + 5e-4).collect();
    let (c, f) = stereo(&with_right(paired.clone(), b.clone()));
    assert_eq!(c.verdict, Verdict::Pass, "{c}");
    assert!(f.is_empty(), "{f:?}");
    assert!(c.detail.contains("16 of 16") && c.detail.contains("63.0 mm"), "{c}");
    // The right subscriber connected after the fourth left image: counted from the first
    // right image on, still every pair.
    let (c, _) = stereo(&with_right(paired[4..].to_vec(), b.clone()));
    assert_eq!(c.verdict, Verdict::Pass, "{c}");
    assert!(c.detail.contains("12 of 12"), "{c}");
    // The last two right images still on the wire (the newest right 0.13 s before the newest
    // left): those two left images are not judged yet. A right stream that stopped half-way
    // (0.53 s before the newest left image) fails.
    let (c, _) = stereo(&with_right(paired[..14].to_vec(), b.clone()));
    assert_eq!(c.verdict, Verdict::Pass, "{c}");
    assert!(c.detail.contains("14 of 14"), "{c}");
    let (c, f) = stereo(&with_right(paired[..8].to_vec(), b.clone()));
    assert_eq!(f, vec!["STEREO"]);
    assert!(c.detail.contains("8 of 16"), "{c}");
    // One of 16 missing passes (the rate tolerance, 10 %); one in three missing fails, and
    // it fails STEREO alone.
    let mut one_lost = paired.clone();
    one_lost.remove(9);
    assert_eq!(stereo(&with_right(one_lost, b.clone())).0.verdict, Verdict::Pass);
    let third_lost: Vec<f64> = paired
        .iter()
        .copied()
        .enumerate()
        .filter(|(i, _)| i % 3 != 1)
        .map(|(_, t)| t)
        .collect();
    assert_eq!(stereo(&with_right(third_lost, b.clone())).1, vec!["STEREO"]);
    // Right images of other stamps (2 ms off: another capture), none at all, a CameraInfo
    // without a baseline or none: each fails STEREO alone, saying why.
    let skewed: Vec<f64> = left_stamps().iter().map(|t| t + 2e-3).collect();
    let (c, f) = stereo(&with_right(skewed, b.clone()));
    assert_eq!(f, vec!["STEREO"]);
    // (the first left image precedes the first right one by more than the skew: left out)
    assert!(c.detail.contains("0 of 15"), "{c}");
    let (c, f) = stereo(&with_right(vec![], b));
    assert_eq!(f, vec!["STEREO"]);
    assert!(
        c.detail.contains("0 of 16") && c.fix.contains("right_image_topic"),
        "{c}"
    );
    let (c, f) = stereo(&with_right(paired.clone(), Some(Err("baseline 0.0 mm".into()))));
    assert_eq!(f, vec!["STEREO"]);
    assert!(c.detail.contains("right camera_info: baseline 0.0 mm"), "{c}");
    let (c, f) = stereo(&with_right(paired, None));
    assert_eq!(f, vec!["STEREO"]);
    assert!(c.detail.contains("no right camera_info"), "{c}");
}

#[test]
fn a_markerless_estimator_has_no_marker_size_to_check_and_says_what_to_look_at() {
    let k = kin();
    let mut o = good(&k);
    o.marker.markerless = true;
    o.marker.configured_size_m = None;
    let r = evaluate(&o, &Limits::default(), &TareParams::default(), &k);
    let c = r.checks.iter().find(|c| c.code == "MARKER").unwrap();
    assert_eq!(c.verdict, Verdict::Pass, "{c}");
    assert!(c.detail.contains("markerless"), "{c}");
    // A simulated marker of another size does not matter without a marker.
    o.marker.simulated_size_m = Some(0.05);
    assert!(failed(&o).is_empty());
    // No pose: the trocar was not found, and the fix names the trocar model.
    o.marker.last = None;
    let r = evaluate(&o, &Limits::default(), &TareParams::default(), &k);
    let c = r.checks.iter().find(|c| c.code == "MARKER").unwrap();
    assert_eq!(c.verdict, Verdict::Fail);
    assert!(
        c.detail.contains("trocar not found") && c.fix.contains("trocar_model_file"),
        "{c}"
    );
}
