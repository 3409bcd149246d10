//! cxx bridge to ViSP's model-based tracker (`vpMbGenericTracker`, moving edges; see
//! `cpp/model_tracker_bridge.h`). Poses cross as 12 numbers: the rotation row by row, then
//! the translation (m), the model's frame in the camera frame.

/// The raw cxx declarations.
#[cxx::bridge(namespace = "trocar_docking")]
pub mod ffi {
    unsafe extern "C++" {
        include!("trocar_docking/cpp/model_tracker_bridge.h");

        /// The tracker, its camera and model.
        type ModelTrackerCpp;

        /// A tracker for a camera (`intrinsics` fx, fy, cx, cy; `dist` OpenCV order, `fisheye`: ROS
        /// `equidistant`, k1 k2 k3 k4) and a
        /// model (ViSP .cao text, m); `moving_edges`: the search range and site spacing
        /// (px), the edge threshold (ViSP's likelihood) and the contrast tolerance (relative).
        fn new_model_tracker(
            intrinsics: &[f64],
            dist: &[f64],
            fisheye: bool,
            width: i32,
            height: i32,
            cao: &str,
            moving_edges: &[f64],
        ) -> Result<UniquePtr<ModelTrackerCpp>>;

        /// Start on an image (the camera's size, 1, 3 or 4 channels) from a pose (12 numbers).
        fn model_tracker_init(
            t: Pin<&mut ModelTrackerCpp>,
            pixels: &[u8],
            width: i32,
            height: i32,
            channels: i32,
            c_t_o: &[f64],
        ) -> Result<()>;

        /// Leave out of the edge search where `hidden` (the camera's size) is non-zero.
        fn model_tracker_set_mask(t: Pin<&mut ModelTrackerCpp>, hidden: &[u8]) -> Result<()>;

        /// Track into an image: the pose (12), kept (1/0), projection error (deg), edge
        /// sites used, fraction the robust estimator kept.
        fn model_tracker_track(
            t: Pin<&mut ModelTrackerCpp>,
            pixels: &[u8],
            width: i32,
            height: i32,
            channels: i32,
        ) -> Result<Vec<f64>>;
    }
}

// SAFETY: a ModelTrackerCpp owns all its state (the ViSP tracker, its model, the image
// buffers; ViSP's tracker keeps no thread-local state) and is mutated only through
// `Pin<&mut>`, so moving it to another thread is sound.
unsafe impl Send for ffi::ModelTrackerCpp {}

/// Numbers `model_tracker_track` returns.
pub const TRACK_RECORD_LEN: usize = 16;
