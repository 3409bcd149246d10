//! Vision: marker detection and pose (OpenCV aruco / ViSP AprilTag corners, ViSP VVS pose),
//! the synthetic camera, hand-eye calibration, and the pure-Rust trocar estimator.
//!
//! Frame conventions: the camera frame is the optical frame (x right, y down, z forward);
//! the marker frame has its origin at the marker centre and is the frame of the library
//! that defines the family ([`MarkerFrame`]): ArUco x right, y up on the printed marker, z
//! out of it; AprilTag (the official frame) x right, y down, z into the tag.

pub mod camera;
pub mod estimator;
pub mod hand_eye;
pub mod image;
pub mod joint_history;
pub mod marker;
pub mod markerless;
pub mod overlay;
pub mod render;
pub mod sim_camera;

pub use camera::{CameraInfoFields, CameraModel, DistortionModel, ImageKind, ImageKindSetting, STEREO_MAX_SKEW_S};
pub use estimator::{EstimateStatus, EstimatorParams, TrocarEstimate, TrocarEstimator};
pub use image::{GreyImage, ImageView};
pub use marker::{
    search_window, MarkerDetection, MarkerDetector, MarkerFamily, MarkerFrame, MarkerSpec, TrackingDetector,
    APRILTAG_FAMILIES,
};
pub use overlay::{ChannelOrder, RgbImage};
pub use render::{facing_pose, facing_pose_in, official_tag_image, render_marker_image, OfficialTag, RenderOptions};

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};

/// The OpenCV and ViSP versions the vision bridge was built against, and the threads OpenCV uses.
pub fn backend_versions() -> String {
    crate::ffi::vision::ffi::vision_backend_versions()
}

/// Errors of the vision layer.
#[derive(Debug, thiserror::Error)]
pub enum VisionError {
    /// Invalid input (image, intrinsics, pose, parameters), with the reason.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// The C++ side (OpenCV, ViSP) reported an error.
    #[error("vision backend: {0}")]
    Backend(String),
    /// A file could not be read or parsed.
    #[error("{0}")]
    Io(String),
}

impl From<crate::validate::RangeError> for VisionError {
    fn from(e: crate::validate::RangeError) -> Self {
        VisionError::InvalidInput(e.to_string())
    }
}

impl From<cxx::Exception> for VisionError {
    fn from(e: cxx::Exception) -> Self {
        VisionError::Backend(e.what().to_string())
    }
}

/// An isometry from 12 numbers: rotation row-major (9) then translation (3). `None` when the
/// rotation is not a finite proper rotation.
pub(crate) fn isometry_from_rt(v: &[f64]) -> Option<Isometry3<f64>> {
    if v.len() != 12 || v.iter().any(|x| !x.is_finite()) {
        return None;
    }
    let m = Matrix3::from_row_slice(&v[..9]);
    let det = m.determinant();
    if (det - 1.0).abs() > 1e-3 || (m.transpose() * m - Matrix3::identity()).norm() > 1e-3 {
        return None;
    }
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
    Some(Isometry3::from_parts(Translation3::new(v[9], v[10], v[11]), rot))
}

/// 12 numbers (rotation row-major, translation) of an isometry.
pub(crate) fn rt_from_isometry(p: &Isometry3<f64>) -> [f64; 12] {
    let r = p.rotation.to_rotation_matrix();
    let m = r.matrix();
    let t = p.translation.vector;
    [
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
        t.x,
        t.y,
        t.z,
    ]
}

/// Translation (m) and rotation (rad) distance between two poses.
pub fn pose_distance(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let dt = (a.translation.vector - b.translation.vector).norm();
    let dr = a.rotation.angle_to(&b.rotation);
    (dt, dr)
}
