//! Detection edge cases: bad inputs give errors or empty results, never panics; distortion,
//! RGB input and the id filter behave.

use std::path::Path;

use trocar_docking::vision::{
    facing_pose, pose_distance, render_marker_image, CameraModel, ImageView, MarkerDetector, MarkerSpec, RenderOptions,
};

fn cam() -> CameraModel {
    CameraModel::pinhole(1280, 720, 800.0, 800.0, 640.0, 360.0).unwrap()
}

fn spec(id: Option<u32>) -> MarkerSpec {
    MarkerSpec {
        family: "DICT_4X4_50".parse().unwrap(),
        id,
        size_m: 0.05,
    }
}

#[test]
fn bad_images_are_errors_and_blank_images_are_empty() {
    let mut det = MarkerDetector::new(spec(None), &cam()).unwrap();
    let empty: [u8; 0] = [];
    assert!(det
        .detect(&ImageView {
            data: &empty,
            width: 0,
            height: 0,
            channels: 1
        })
        .is_err());
    let small = vec![128u8; 640 * 480];
    assert!(det
        .detect(&ImageView {
            data: &small,
            width: 640,
            height: 480,
            channels: 1
        })
        .is_err());
    let short = vec![128u8; 100];
    assert!(det
        .detect(&ImageView {
            data: &short,
            width: 1280,
            height: 720,
            channels: 1
        })
        .is_err());
    let blank = vec![200u8; 1280 * 720];
    let v = ImageView::new(&blank, 1280, 720, 1).unwrap();
    assert!(det.detect(&v).unwrap().is_empty());
    let noise: Vec<u8> = (0..1280 * 720u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 24) as u8)
        .collect();
    assert!(det
        .detect(&ImageView::new(&noise, 1280, 720, 1).unwrap())
        .unwrap()
        .is_empty());
}

#[test]
fn absurd_intrinsics_and_specs_are_rejected_before_cpp() {
    let mut c = cam();
    c.fx = -5.0;
    assert!(MarkerDetector::new(spec(None), &c).is_err());
    let mut c = cam();
    c.distortion = vec![0.1, 0.2, 0.3];
    assert!(MarkerDetector::new(spec(None), &c).is_err());
    let bad = MarkerSpec {
        size_m: 0.0,
        ..spec(None)
    };
    assert!(MarkerDetector::new(bad.clone(), &cam()).is_err());
    let p = facing_pose(0.4, 0.0, 0.0, 0.0, 0.0, 0.0);
    assert!(render_marker_image(&bad, &cam(), &p, &RenderOptions::default()).is_err());
    let behind = facing_pose(-0.4, 0.0, 0.0, 0.0, 0.0, 0.0);
    assert!(render_marker_image(&spec(Some(1)), &cam(), &behind, &RenderOptions::default()).is_err());
    let nan = facing_pose(f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0);
    assert!(render_marker_image(&spec(Some(1)), &cam(), &nan, &RenderOptions::default()).is_err());
}

#[test]
fn id_filter_rgb_input_and_convention() {
    let truth = facing_pose(0.5, 0.03, -0.02, 0.3, -0.2, 0.4);
    let img = render_marker_image(&spec(Some(3)), &cam(), &truth, &RenderOptions::default()).unwrap();
    let mut other = MarkerDetector::new(spec(Some(4)), &cam()).unwrap();
    assert!(other.detect(&img.view()).unwrap().is_empty());
    let rgb: Vec<u8> = img.data.iter().flat_map(|&g| [g, g, g]).collect();
    let mut det = MarkerDetector::new(spec(Some(3)), &cam()).unwrap();
    let found = det.detect(&ImageView::new(&rgb, 1280, 720, 3).unwrap()).unwrap();
    assert_eq!(found.len(), 1);
    let m = &found[0];
    assert_eq!(m.id, 3);
    let (dt, dr) = pose_distance(&m.pose_camera_marker, &truth);
    assert!(dt < 1e-3 && dr.to_degrees() < 0.2, "{dt} m {} deg", dr.to_degrees());
    // z out of the marker: the marker normal points back at the camera.
    let z = m.pose_camera_marker.rotation * nalgebra::Vector3::z();
    assert!(z.z < -0.5);
    // ArUco corners TL, TR, BR, BL: TL is left of TR in a marker that is barely turned.
    assert!(m.corners[0][0] < m.corners[1][0] && m.corners[1][1] < m.corners[2][1]);
    assert!(m.reprojection_error_px < 0.5);
    let bgra: Vec<u8> = img.data.iter().flat_map(|&g| [g, g, g, 255]).collect();
    let found4 = det.detect(&ImageView::new(&bgra, 1280, 720, 4).unwrap()).unwrap();
    assert_eq!(found4.len(), 1);
    assert!(pose_distance(&found4[0].pose_camera_marker, &m.pose_camera_marker).0 < 1e-9);
}

#[test]
fn distorted_camera_round_trip() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/camera_zedm.yaml");
    let zed = CameraModel::from_yaml_file(&path).unwrap();
    assert!(zed.distortion.iter().any(|&d| d != 0.0));
    // Off-centre, where distortion bends the edges most.
    let truth = facing_pose(0.45, 0.17, 0.09, 0.2, 0.3, -0.5);
    let s = spec(Some(7));
    let img = render_marker_image(&s, &zed, &truth, &RenderOptions::default()).unwrap();
    let mut det = MarkerDetector::new(s, &zed).unwrap();
    let found = det.detect(&img.view()).unwrap();
    assert_eq!(found.len(), 1);
    let (dt, dr) = pose_distance(&found[0].pose_camera_marker, &truth);
    assert!(dt < 1e-3 && dr.to_degrees() < 0.3, "{dt} m {} deg", dr.to_degrees());
}
