//! A lab's easy_handeye calibration read as the project's mount (`trocar_docking hand-eye
//! --from-easy-handeye`, and every reader of a hand-eye file): the effector frame carried to
//! the flange through the URDF's fixed joints. The files below are laid out as easy_handeye's
//! `HandeyeCalibration.to_yaml` writes them (`yaml.dump` of `to_dict`, block style, keys
//! sorted; easy_handeye/src/easy_handeye/handeye_calibration.py), in its current layout
//! (`parameters:`) and its older one (the frames at the top level).

use std::path::{Path, PathBuf};
use std::process::Command;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use trocar_docking::kinematics::{fixed_transform, FLANGE_LINK};
use trocar_docking::vision::hand_eye::{load_mount, mount_of_text, Mount};

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn urdf_path() -> PathBuf {
    root().join("urdf/lbr_med7_r800_endoscope.urdf")
}

fn urdf() -> String {
    std::fs::read_to_string(urdf_path()).unwrap()
}

/// The physical mount: the camera in the flange `lbr_link_ee`, off every axis.
fn true_mount() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.012, 0.071, 0.041),
        UnitQuaternion::from_euler_angles(0.27, -0.05, 0.11),
    )
}

/// The flange `lbr_link_ee` in `lbr_link_7`: 35 mm along z (the URDF's fixed joint
/// `lbr_joint_ee`, `<origin xyz="0 0 0.035"/>`).
fn link7_t_flange() -> Isometry3<f64> {
    Isometry3::translation(0.0, 0.0, 0.035)
}

/// An easy_handeye file (current layout) of `effector_t_camera` in `effector`.
fn easy_handeye(effector: &str, eye_on_hand: bool, effector_t_camera: &Isometry3<f64>) -> String {
    let (t, q) = (effector_t_camera.translation.vector, effector_t_camera.rotation);
    format!(
        "parameters:\n  eye_on_hand: {eye_on_hand}\n  freehand_robot_movement: false\n  move_group: manipulator\n  \
         move_group_namespace: /\n  namespace: /trocar_eye_on_hand/\n  robot_base_frame: lbr_link_0\n  \
         robot_effector_frame: {effector}\n  tracking_base_frame: zedm_left_camera_optical_frame\n  \
         tracking_marker_frame: trocar_marker\ntransformation:\n  qw: {}\n  qx: {}\n  qy: {}\n  qz: {}\n  x: {}\n  y: {}\n  z: {}\n",
        q.w, q.i, q.j, q.k, t.x, t.y, t.z
    )
}

/// The same in easy_handeye's older layout: the frames at the top level.
fn easy_handeye_top_level(effector: &str, effector_t_camera: &Isometry3<f64>) -> String {
    let (t, q) = (effector_t_camera.translation.vector, effector_t_camera.rotation);
    format!(
        "eye_on_hand: true\nrobot_effector_frame: {effector}\ntracking_base_frame: zedm_left_camera_optical_frame\n\
         transformation:\n  qw: {}\n  qx: {}\n  qy: {}\n  qz: {}\n  x: {}\n  y: {}\n  z: {}\n",
        q.w, q.i, q.j, q.k, t.x, t.y, t.z
    )
}

fn mount(text: &str) -> Result<Mount, String> {
    let xml = urdf();
    let resolve = |frame: &str| fixed_transform(&xml, FLANGE_LINK, frame).map_err(|e| e.to_string());
    mount_of_text("calib.yaml", text, &resolve).map_err(|e| e.to_string())
}

fn distance(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    (
        (a.translation.vector - b.translation.vector).norm(),
        a.rotation.angle_to(&b.rotation),
    )
}

#[test]
fn a_calibration_in_lbr_link_7_and_one_in_the_flange_give_the_same_mount() {
    let m = true_mount();
    let at_flange = mount(&easy_handeye("lbr_link_ee", true, &m)).unwrap();
    let at_link7 = mount(&easy_handeye("lbr_link_7", true, &(link7_t_flange() * m))).unwrap();
    let old_layout = mount(&easy_handeye_top_level("lbr_link_7", &(link7_t_flange() * m))).unwrap();
    for got in [&at_flange, &at_link7, &old_layout] {
        let (dt, dr) = distance(&got.flange_t_camera, &m);
        assert!(dt < 1e-6 && dr < 1e-6, "{dt} m, {dr} rad off");
        assert_eq!(got.camera_frame.as_deref(), Some("zedm_left_camera_optical_frame"));
    }
    // Read by hand as if it were in the flange, the lbr_link_7 file puts the camera 35 mm
    // off along the scope: what the resolution through the URDF removes.
    let naive = mount(&easy_handeye("lbr_link_ee", true, &(link7_t_flange() * m))).unwrap();
    let (dt, _) = distance(&naive.flange_t_camera, &m);
    assert!((dt - 0.035).abs() < 1e-9, "{dt}");
    // The URDF's own transform between the two links, through KDL.
    let t = fixed_transform(&urdf(), "lbr_link_7", FLANGE_LINK).unwrap();
    assert!(distance(&t, &link7_t_flange()).0 < 1e-12);
}

#[test]
fn an_unknown_frame_a_moving_joint_and_an_eye_on_base_file_are_refused_by_name() {
    let m = true_mount();
    let e = mount(&easy_handeye("tool0", true, &m)).unwrap_err();
    assert!(
        e.contains("robot_effector_frame `tool0`") && e.contains("no link `tool0`"),
        "{e}"
    );
    let e = mount(&easy_handeye("lbr_link_6", true, &m)).unwrap_err();
    assert!(
        e.contains("`lbr_link_6` is not joined to `lbr_link_ee` by fixed joints") && e.contains("lbr_joint_7"),
        "{e}"
    );
    let e = mount(&easy_handeye("lbr_link_ee", false, &m)).unwrap_err();
    assert!(
        e.contains("parameters.eye_on_hand is false") && e.contains("eye-on-base") && e.contains("lbr_link_0"),
        "{e}"
    );
    let broken = easy_handeye("lbr_link_ee", true, &m).replace("  qw: ", "  qw_: ");
    let e = mount(&broken).unwrap_err();
    assert!(e.contains("transformation.qw is missing"), "{e}");
    let e = mount("a: 1\n").unwrap_err();
    assert!(
        e.contains("neither flange_t_camera") && e.contains("transformation"),
        "{e}"
    );
}

#[test]
fn the_projects_own_file_is_read_as_it_is_without_the_urdf() {
    let text = std::fs::read_to_string(root().join("config/hand_eye.yaml")).unwrap();
    let never = |f: &str| -> Result<Isometry3<f64>, String> { panic!("resolved {f}") };
    let m = mount_of_text("hand_eye.yaml", &text, &never).unwrap();
    assert!((m.flange_t_camera.translation.vector - Vector3::new(0.0, 0.07, 0.04)).norm() < 1e-9);
}

#[test]
fn the_cli_converts_an_easy_handeye_file_into_the_projects() {
    let dir = std::env::temp_dir().join(format!("easy_handeye_cli_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (input, out) = (dir.join("trocar_eye_on_hand.yaml"), dir.join("hand_eye.yaml"));
    std::fs::write(
        &input,
        easy_handeye("lbr_link_7", true, &(link7_t_flange() * true_mount())),
    )
    .unwrap();
    let run = |input: &Path| {
        Command::new(env!("CARGO_BIN_EXE_trocar_docking"))
            .args(["hand-eye", "--from-easy-handeye"])
            .arg(input)
            .arg("--urdf")
            .arg(urdf_path())
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap()
    };
    let r = run(&input);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let never = |f: &str| -> Result<Isometry3<f64>, String> { panic!("resolved {f}") };
    let written = load_mount(&out, &never).unwrap();
    let (dt, dr) = distance(&written.flange_t_camera, &true_mount());
    assert!(dt < 1e-6 && dr < 1e-6, "{dt} m, {dr} rad off");
    assert_eq!(written.camera_frame.as_deref(), Some("zedm_left_camera_optical_frame"));
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(text.contains("calibrated: 20"), "{text}");
    // Eye on base: refused with one line naming it, exit code 1, nothing written.
    std::fs::remove_file(&out).unwrap();
    std::fs::write(&input, easy_handeye("lbr_link_ee", false, &true_mount())).unwrap();
    let r = run(&input);
    let err = String::from_utf8_lossy(&r.stderr);
    assert_eq!(r.status.code(), Some(1), "{err}");
    assert!(err.contains("eye_on_hand is false"), "{err}");
    assert!(!out.exists());
    std::fs::remove_dir_all(&dir).unwrap();
}
