//! The search window and the tracking detector: a window around the marker finds the same
//! pose as the whole frame; a marker that jumps out of the window, or is lost and comes back,
//! is found again by the whole-frame fallback.

use trocar_docking::vision::{
    facing_pose, pose_distance, render_marker_image, search_window, CameraModel, MarkerDetector, MarkerSpec,
    RenderOptions, TrackingDetector,
};

fn cam() -> CameraModel {
    let mut c = CameraModel::pinhole(1280, 720, 700.0, 700.0, 642.0, 357.0).unwrap();
    c.distortion = vec![-0.17, 0.025, 0.0003, -0.0002, 0.0];
    c
}

fn frame(x: f64, y: f64) -> (Vec<u8>, nalgebra::Isometry3<f64>) {
    let pose = facing_pose(0.3, x, y, 0.3, -0.2, 0.4);
    let opts = RenderOptions {
        plane_scale: 1.6,
        noise_sigma: 2.0,
        ..RenderOptions::default()
    };
    let img = render_marker_image(&MarkerSpec::default(), &cam(), &pose, &opts).unwrap();
    (img.data, pose)
}

fn view(data: &[u8]) -> trocar_docking::vision::ImageView<'_> {
    trocar_docking::vision::ImageView::new(data, 1280, 720, 1).unwrap()
}

#[test]
fn a_window_around_the_marker_gives_the_whole_frame_pose() {
    let mut det = MarkerDetector::new(MarkerSpec::default(), &cam()).unwrap();
    let (img, truth) = frame(0.05, -0.03);
    let full = det.detect(&view(&img)).unwrap();
    assert_eq!(full.len(), 1);
    let win = search_window(&full[0].corners, 1.0, 1280, 720).unwrap();
    assert!(
        win[2] * win[3] < 1280 * 720 / 4,
        "window {win:?} is not a small part of the frame"
    );
    let inside = det.detect_in(&view(&img), Some(win)).unwrap();
    assert_eq!(inside.len(), 1);
    let (dt, dr) = pose_distance(&inside[0].pose_camera_marker, &full[0].pose_camera_marker);
    assert!(dt < 1e-4 && dr < 1e-3, "window pose differs by {dt} m, {dr} rad");
    let (et, _) = pose_distance(&inside[0].pose_camera_marker, &truth);
    assert!(et < 1e-3, "{et} m from the truth");
    // A window elsewhere sees nothing; a window too small to hold a marker searches it all.
    assert!(det.detect_in(&view(&img), Some([0, 0, 200, 200])).unwrap().is_empty());
    assert_eq!(det.detect_in(&view(&img), Some([0, 0, 10, 10])).unwrap().len(), 1);
}

#[test]
fn the_tracker_falls_back_to_the_whole_frame() {
    let det = MarkerDetector::new(MarkerSpec::default(), &cam()).unwrap();
    let mut t = TrackingDetector::new(det, 1.5);
    let (a, pa) = frame(0.05, -0.03);
    let (b, pb) = frame(-0.09, 0.05);
    let blank = vec![128u8; 1280 * 720];
    for (img, truth) in [
        (&a, Some(pa)),
        (&a, Some(pa)),
        (&b, Some(pb)),
        (&blank, None),
        (&a, Some(pa)),
    ] {
        let found = t.detect(&view(img)).unwrap();
        match (found, truth) {
            (Some(d), Some(p)) => {
                let (et, _) = pose_distance(&d.pose_camera_marker, &p);
                assert!(et < 1e-3, "{et} m from the truth");
            }
            (None, None) => {}
            (f, p) => panic!("found {:?}, expected {:?}", f.map(|d| d.id), p.map(|_| 7)),
        }
    }
}
