//! cxx bridge to ViSP and OpenCV aruco (see `cpp/vision_bridge.h`).

/// The raw cxx declarations.
#[cxx::bridge(namespace = "trocar_docking")]
pub mod ffi {
    unsafe extern "C++" {
        include!("trocar_docking/cpp/vision_bridge.h");

        /// The versions of the vision libraries this build links.
        fn vision_backend_versions() -> String;

        /// A configured detector (family + camera model).
        type MarkerDetectorCpp;

        /// Build a detector; `intrinsics` = fx, fy, cx, cy; `dist` in OpenCV order.
        fn new_marker_detector(
            family: &str,
            intrinsics: &[f64],
            dist: &[f64],
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
            width: i32,
            height: i32,
            blur_sigma: f64,
            texture_seed: u32,
        ) -> Result<Vec<u8>>;

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
