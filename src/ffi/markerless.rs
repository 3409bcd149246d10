//! cxx bridge to the image-level steps of the markerless trocar estimator (OpenCV; see
//! `cpp/markerless_bridge.h`). Points cross in undistorted normalised camera coordinates.

/// The raw cxx declarations.
#[cxx::bridge(namespace = "trocar_docking")]
pub mod ffi {
    unsafe extern "C++" {
        include!("trocar_docking/cpp/markerless_bridge.h");

        /// The camera model and the last loaded image.
        type MarkerlessDetectorCpp;

        /// A detector for a camera: `intrinsics` = fx, fy, cx, cy; `dist` in OpenCV order, or
        /// with `fisheye` (ROS `equidistant`) k1 k2 k3 k4.
        fn new_markerless_detector(
            intrinsics: &[f64],
            dist: &[f64],
            fisheye: bool,
            width: i32,
            height: i32,
        ) -> Result<UniquePtr<MarkerlessDetectorCpp>>;

        /// Load an image of the camera's size (1, 3 or 4 channels), smoothed by `smooth_sigma` px.
        fn markerless_load(
            det: Pin<&mut MarkerlessDetectorCpp>,
            pixels: &[u8],
            width: i32,
            height: i32,
            channels: i32,
            smooth_sigma: f64,
        ) -> Result<()>;

        /// Dark elliptical blobs with a lighter surround: 7 numbers each (undistorted px:
        /// centre x, y, semi-axes a >= b, angle of a (rad), contrast, rms contour distance).
        fn markerless_ellipses(
            det: Pin<&mut MarkerlessDetectorCpp>,
            min_axis_px: f64,
            max_axis_px: f64,
            max_count: i32,
        ) -> Result<Vec<f64>>;

        /// A known occluder in view (the endoscope's shaft): 3-D points (camera frame) in
        /// sections of `section_len`; the region consecutive sections cover, grown by
        /// `margin_px`, is masked in every later image. Empty `points` clears it.
        fn markerless_set_occluder(
            det: Pin<&mut MarkerlessDetectorCpp>,
            points: &[f64],
            section_len: i32,
            margin_px: f64,
        ) -> Result<()>;

        /// Moving edges along normals: in 4 per point (x, y, nx, ny), out 4 per point
        /// (found: 0, 1, or 2 where the occluder's mask hides the search; x, y, signed
        /// strength).
        fn markerless_search_edges(
            det: &MarkerlessDetectorCpp,
            points: &[f64],
            range_px: f64,
            polarity: i32,
            min_strength: f64,
            through_occluder: bool,
        ) -> Result<Vec<f64>>;
    }
}

// SAFETY: a MarkerlessDetectorCpp owns all its state (camera model, image buffers) and is
// mutated only through `Pin<&mut>`, so moving it to another thread is sound.
unsafe impl Send for ffi::MarkerlessDetectorCpp {}

/// Numbers per record of `markerless_ellipses`.
pub const ELLIPSE_RECORD_LEN: usize = 7;
/// Numbers per point of `markerless_search_edges` (in and out).
pub const EDGE_RECORD_LEN: usize = 4;

#[cfg(test)]
mod tests {
    use super::ffi;

    const K: [f64; 4] = [500.0, 500.0, 32.0, 24.0];

    fn refused<T>(r: Result<T, cxx::Exception>, what: &str) {
        match r {
            Ok(_) => panic!("accepted: {what}"),
            Err(e) => assert!(e.what().contains(what), "{what}: {}", e.what()),
        }
    }

    // Called past the safe wrappers' own checks: the C++ side must refuse on its own.
    #[test]
    fn the_cpp_side_checks_every_length_and_value() {
        refused(
            ffi::new_markerless_detector(&K[..3], &[], false, 64, 48),
            "fx, fy, cx, cy",
        );
        refused(ffi::new_markerless_detector(&K, &[0.0; 3], false, 64, 48), "distortion");
        refused(ffi::new_markerless_detector(&K, &[], false, 4, 48), "image size");
        refused(
            ffi::new_markerless_detector(&K, &[], true, 64, 48),
            "4 coefficients (k1 k2 k3 k4), got 0",
        );
        let mut d = ffi::new_markerless_detector(&K, &[], false, 64, 48).unwrap();
        refused(ffi::markerless_ellipses(d.pin_mut(), 3.0, 10.0, 4), "no image loaded");
        refused(
            ffi::markerless_search_edges(&d, &[0.0; 4], 2.0, 0, 1.0, false),
            "no image loaded",
        );
        let grey = vec![100u8; 64 * 48];
        refused(
            ffi::markerless_load(d.pin_mut(), &grey[1..], 64, 48, 1, 1.0),
            "pixel buffer",
        );
        refused(ffi::markerless_load(d.pin_mut(), &grey, 48, 64, 1, 1.0), "camera model");
        refused(ffi::markerless_load(d.pin_mut(), &grey, 64, 48, 2, 1.0), "channels");
        refused(ffi::markerless_load(d.pin_mut(), &grey, 64, 48, 1, f64::NAN), "sigma");
        ffi::markerless_load(d.pin_mut(), &grey, 64, 48, 1, 1.0).unwrap();
        assert!(ffi::markerless_ellipses(d.pin_mut(), 3.0, 10.0, 4).unwrap().is_empty());
        // The occluder: whole points, whole sections, in front of the camera, a sane margin.
        let sec = |z: f64| [0.0, 0.0, z, 0.01, 0.0, z, 0.0, 0.01, z];
        let two: Vec<f64> = sec(0.2).into_iter().chain(sec(0.3)).collect();
        refused(
            ffi::markerless_set_occluder(d.pin_mut(), &two[1..], 3, 1.0),
            "3 numbers each",
        );
        refused(
            ffi::markerless_set_occluder(d.pin_mut(), &two[..9], 3, 1.0),
            "two or more sections",
        );
        refused(ffi::markerless_set_occluder(d.pin_mut(), &two, 3, -1.0), "margin");
        let behind: Vec<f64> = sec(-0.2).into_iter().chain(sec(0.3)).collect();
        refused(
            ffi::markerless_set_occluder(d.pin_mut(), &behind, 3, 1.0),
            "in front of the camera",
        );
        let nan: Vec<f64> = two.iter().map(|v| if *v == 0.01 { f64::NAN } else { *v }).collect();
        refused(ffi::markerless_set_occluder(d.pin_mut(), &nan, 3, 1.0), "finite");
        // Set, the image centre's search reports it hidden (2); cleared, searched again (0/1).
        ffi::markerless_set_occluder(d.pin_mut(), &two, 3, 1.0).unwrap();
        let centre = [0.0, 0.0, 1.0, 0.0];
        assert_eq!(
            ffi::markerless_search_edges(&d, &centre, 2.0, 0, 1.0, false).unwrap()[0],
            2.0
        );
        // Searched through the mask (the occluder's own outline): not hidden.
        assert!(ffi::markerless_search_edges(&d, &centre, 2.0, 0, 1.0, true).unwrap()[0] < 1.5);
        ffi::markerless_set_occluder(d.pin_mut(), &[], 3, 0.0).unwrap();
        assert!(ffi::markerless_search_edges(&d, &centre, 2.0, 0, 1.0, false).unwrap()[0] < 1.5);
        refused(ffi::markerless_ellipses(d.pin_mut(), 10.0, 3.0, 4), "semi-axis");
        refused(ffi::markerless_ellipses(d.pin_mut(), 3.0, 10.0, 0), "max_count");
        refused(
            ffi::markerless_search_edges(&d, &[0.0; 5], 2.0, 0, 1.0, false),
            "4 numbers",
        );
        refused(
            ffi::markerless_search_edges(&d, &[f64::NAN; 4], 2.0, 0, 1.0, false),
            "finite",
        );
        refused(
            ffi::markerless_search_edges(&d, &[0.0; 4], 0.0, 0, 1.0, false),
            "search range",
        );
        refused(
            ffi::markerless_search_edges(&d, &[0.0; 4], 2.0, 2, 1.0, false),
            "polarity",
        );
        // A flat image has no edge anywhere.
        let out = ffi::markerless_search_edges(&d, &[0.0, 0.0, 1.0, 0.0], 3.0, 0, 1.0, false).unwrap();
        assert_eq!(out, vec![0.0; 4]);
    }
}
