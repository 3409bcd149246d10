//! cxx bridge to ViSP and OpenCV aruco (see `cpp/vision_bridge.h`).

/// The raw cxx declarations.
#[cxx::bridge(namespace = "trocar_docking")]
pub mod ffi {
    unsafe extern "C++" {
        include!("trocar_docking/cpp/vision_bridge.h");

        /// The versions of the vision libraries this build links, and OpenCV's thread count.
        fn vision_backend_versions() -> String;

        /// A configured detector (family + camera model).
        type MarkerDetectorCpp;

        /// Build a detector; `intrinsics` = fx, fy, cx, cy; `dist` in OpenCV order, or with
        /// `fisheye` (ROS `equidistant`) k1 k2 k3 k4.
        fn new_marker_detector(
            family: &str,
            intrinsics: &[f64],
            dist: &[f64],
            fisheye: bool,
            width: i32,
            height: i32,
        ) -> Result<UniquePtr<MarkerDetectorCpp>>;

        /// Detect markers; 22 numbers per marker (id, R 9, t 3, corners 8, rms px).
        /// `roi` = x, y, w, h (full-image px) limits the ArUco search; empty = whole frame.
        #[allow(clippy::too_many_arguments)]
        fn detect_markers(
            det: Pin<&mut MarkerDetectorCpp>,
            pixels: &[u8],
            width: i32,
            height: i32,
            channels: i32,
            id: i32,
            size: f64,
            roi: &[i32],
        ) -> Result<Vec<f64>>;

        /// Render a marker on a textured plane at camera pose cMo (R row-major + t).
        #[allow(clippy::too_many_arguments)]
        fn render_marker(
            family: &str,
            id: i32,
            size: f64,
            plane_size: f64,
            cmo: &[f64],
            intrinsics: &[f64],
            dist: &[f64],
            fisheye: bool,
            width: i32,
            height: i32,
            blur_sigma: f64,
            texture_seed: u32,
        ) -> Result<Vec<u8>>;

        /// The official tag `id` of an AprilTag family (libapriltag's `apriltag_to_image`),
        /// one byte a cell; `dims` gets total_width, width_at_border, the id count.
        fn official_apriltag(family: &str, id: i32, dims: &mut [i32]) -> Result<Vec<u8>>;

        /// Read an image file (1 = grey, 3 = RGB); writes width, height to `dims`.
        fn read_image(path: &str, channels: i32, dims: &mut [i32]) -> Result<Vec<u8>>;

        /// Write an image file (format from the extension).
        fn write_image(path: &str, pixels: &[u8], width: i32, height: i32, channels: i32) -> Result<()>;

        /// ViSP hand-eye calibration; cMo and rMe n x 12; returns eMc (12).
        fn hand_eye_calibrate(cmo: &[f64], rme: &[f64]) -> Result<Vec<f64>>;
    }
}

// SAFETY: a MarkerDetectorCpp owns all its state (OpenCV dictionary, ViSP detector, scratch
// buffers) and is only used through `Pin<&mut>`, so moving it to another thread is sound.
unsafe impl Send for ffi::MarkerDetectorCpp {}

/// Number of f64 per detection record returned by `detect_markers`.
pub const DETECTION_RECORD_LEN: usize = 22;

#[cfg(test)]
mod tests {
    use super::ffi;

    const K: [f64; 4] = [500.0, 500.0, 32.0, 24.0];

    fn detector() -> cxx::UniquePtr<ffi::MarkerDetectorCpp> {
        ffi::new_marker_detector("DICT_4X4_50", &K, &[], false, 64, 48).unwrap()
    }

    fn refused<T>(r: Result<T, cxx::Exception>, what: &str) {
        match r {
            Ok(_) => panic!("accepted: {what}"),
            Err(e) => assert!(e.what().contains(what), "{what}: {}", e.what()),
        }
    }

    // Called past the safe wrappers' own checks: the C++ side must refuse on its own.
    #[test]
    fn detector_construction_checks_every_length_and_dimension() {
        refused(
            ffi::new_marker_detector("DICT_4X4_50", &K[..3], &[], false, 64, 48),
            "fx, fy, cx, cy",
        );
        refused(
            ffi::new_marker_detector("DICT_4X4_50", &K, &[0.0; 3], false, 64, 48),
            "distortion",
        );
        // The equidistant (fisheye) model has exactly k1 k2 k3 k4.
        refused(
            ffi::new_marker_detector("DICT_4X4_50", &K, &[0.0; 5], true, 64, 48),
            "equidistant (fisheye) model has 4 coefficients",
        );
        assert!(ffi::new_marker_detector("DICT_4X4_50", &K, &[0.0; 4], true, 64, 48).is_ok());
        refused(
            ffi::new_marker_detector("DICT_4X4_50", &K, &[], false, 0, 48),
            "image size",
        );
        refused(
            ffi::new_marker_detector("DICT_4X4_50", &K, &[], false, 64, 20001),
            "image size",
        );
        refused(
            ffi::new_marker_detector("DICT_9X9", &K, &[], false, 64, 48),
            "unknown marker family",
        );
    }

    #[test]
    fn detection_checks_the_buffer_the_size_and_the_window() {
        let mut d = detector();
        let grey = vec![128u8; 64 * 48];
        let out = ffi::detect_markers(d.pin_mut(), &grey, 64, 48, 1, -1, 0.05, &[]).unwrap();
        assert!(out.is_empty());
        refused(
            ffi::detect_markers(d.pin_mut(), &grey[1..], 64, 48, 1, -1, 0.05, &[]),
            "pixel buffer",
        );
        refused(
            ffi::detect_markers(d.pin_mut(), &grey, 64, 48, 3, -1, 0.05, &[]),
            "pixel buffer",
        );
        refused(
            ffi::detect_markers(d.pin_mut(), &grey, 48, 64, 1, -1, 0.05, &[]),
            "camera model",
        );
        refused(
            ffi::detect_markers(d.pin_mut(), &grey, 64, 48, 2, -1, 0.05, &[]),
            "channels",
        );
        refused(
            ffi::detect_markers(d.pin_mut(), &grey, 64, 48, 1, -1, 0.05, &[0, 0, 8]),
            "search window",
        );
        refused(
            ffi::detect_markers(d.pin_mut(), &grey, 64, 48, 1, -1, 0.05, &[0, 0, -8, 8]),
            "search window",
        );
        refused(
            ffi::detect_markers(d.pin_mut(), &grey, 64, 48, 1, -1, f64::NAN, &[]),
            "marker size",
        );
    }

    #[test]
    fn opencv_runs_on_the_calling_thread_from_the_start() {
        // Set once at load time, before any detector exists (none is built here).
        let v = ffi::vision_backend_versions();
        assert!(v.starts_with("ViSP 3.") && v.ends_with("(threads: 1)"), "{v}");
    }

    #[test]
    fn rendering_images_and_hand_eye_check_their_inputs() {
        let mut cmo = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.5].to_vec();
        let render = |cmo: &[f64], plane: f64| {
            ffi::render_marker("DICT_4X4_50", 7, 0.05, plane, cmo, &K, &[], false, 64, 48, 0.0, 1)
        };
        assert_eq!(render(&cmo, 0.15).unwrap().len(), 64 * 48);
        refused(render(&cmo[..11], 0.15), "12 numbers");
        refused(render(&cmo, 0.065), "quiet zone");
        cmo[11] = f64::NAN;
        refused(render(&cmo, 0.15), "finite");
        refused(ffi::read_image("/nonexistent.png", 1, &mut [0; 1]), "dims");
        refused(ffi::write_image("/tmp/x.png", &[0; 10], 4, 4, 1), "pixel buffer");
        refused(ffi::write_image("/tmp/x.png", &[0; 1], 1, 1, 1), "image size");
        refused(ffi::hand_eye_calibrate(&[0.0; 36], &[0.0; 35]), "n x 12");
        refused(ffi::hand_eye_calibrate(&[f64::NAN; 36], &[0.0; 36]), "finite");
    }
}
