//! Marker detection and pose: ArUco corners from OpenCV aruco (sub-pixel refined), AprilTag
//! corners from ViSP's `vpDetectorAprilTag`; pose from IPPE-square initialisation refined
//! by ViSP's virtual visual servoing (vpPose), distortion included.
//!
//! `pose_camera_marker` maps marker coordinates to camera (optical frame) coordinates. Each
//! family keeps the frame of the library that defines it, [`MarkerFamily::frame`]; corners
//! are in pixels (distorted image, pixel centres at integers), in the frame's order:
//!
//! - ArUco (`DICT_4X4_50`, ...; OpenCV is their authority), [`MarkerFrame::OpenCv`]:
//!   corners top-left, top-right, bottom-right, bottom-left of the upright marker as
//!   `cv::aruco::drawMarker` draws it; x right, y up, z out of the marker.
//! - AprilTag (`tag16h5`, `tag25h9`, `tag36h10`, `tag36h11`; OpenCV's `DICT_APRILTAG_*`
//!   names are read as these), [`MarkerFrame::AprilTag`], the official AprilRobotics
//!   library's frame: corners in the order of `apriltag_detection_t::p` (apriltag.h:
//!   "wrap counter-clock wise around the tag"), left-bottom, right-bottom, right-top,
//!   left-top of the upright tag as `apriltag_to_image()` (apriltag.c) draws it from the
//!   family's codes (tag36h11.c), the order the Python binding documents as `lb-rb-rt-lt`
//!   (python3-apriltag); corner i at (-s, s), (s, s), (s, -s), (-s, -s) for half side s, the
//!   object points of `estimate_tag_pose_orthogonal_iteration` (apriltag_pose.c): x right,
//!   y down, z into the tag (away from a camera that sees it).
//!
//! ViSP 3.5 keeps libapriltag's corners: `vpDetectorAprilTag::getPolygon` is `det->p[0..3]`
//! in order (vpDetectorAprilTag.cpp, `Impl::detect`), and so are ours. Its own pose
//! (`Impl::getPose`) is the official one turned 180° about x (x right, y up, z out of the
//! tag) unless `setZAlignedWithCameraAxis(true)`: the bridge does not use it, it solves the
//! pose from the corners above. OpenCV 4.6 draws its `DICT_APRILTAG_*` dictionaries turned
//! 180° against the official tags, so no AprilTag goes through OpenCV: the renderer draws
//! them from libapriltag's codes, the detector is ViSP's. `tests/apriltag_official.rs` holds
//! both to the official detector (python3-apriltag) on official tag pixels.

use std::fmt;
use std::str::FromStr;

use nalgebra::Isometry3;

use super::{isometry_from_rt, CameraModel, ImageView, VisionError};
use crate::ffi::vision::{ffi, DETECTION_RECORD_LEN};

/// A marker family: an OpenCV aruco dictionary or an official AprilTag family.
#[derive(Debug, Clone, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum MarkerFamily {
    /// An OpenCV predefined dictionary, by its name (e.g. `DICT_4X4_50`, `DICT_ARUCO_ORIGINAL`).
    Aruco(String),
    /// An official AprilTag family, by its official name ([`APRILTAG_FAMILIES`]; ViSP's
    /// detector, libapriltag's codes).
    AprilTag(String),
}

/// A marker frame: corner order and axes (the module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MarkerFrame {
    /// OpenCV's ArUco frame: corners TL, TR, BR, BL; x right, y up, z out of the marker.
    OpenCv,
    /// The official AprilTag frame: corners left-bottom, right-bottom, right-top, left-top;
    /// x right, y down, z into the tag.
    AprilTag,
}

impl MarkerFrame {
    /// The corners' order, short: `TL TR BR BL` or `LB RB RT LT` (left-bottom first).
    pub fn corner_names(self) -> &'static str {
        match self {
            MarkerFrame::OpenCv => "TL TR BR BL",
            MarkerFrame::AprilTag => "LB RB RT LT",
        }
    }

    /// The axes on the upright marker, short.
    pub fn axes(self) -> &'static str {
        match self {
            MarkerFrame::OpenCv => "x right, y up, z out of the marker",
            MarkerFrame::AprilTag => "x right, y down, z into the tag",
        }
    }
}

/// The official AprilTag families accepted, with their number of ids (libapriltag's
/// `ncodes`). OpenCV's `DICT_APRILTAG_16h5`, `_25h9`, `_36h10`, `_36h11` name the same codes.
pub const APRILTAG_FAMILIES: &[(&str, u32)] =
    &[("tag16h5", 30), ("tag25h9", 35), ("tag36h10", 2320), ("tag36h11", 587)];

/// The OpenCV dictionary names accepted, with their number of ids.
pub const ARUCO_DICTIONARIES: &[(&str, u32)] = &[
    ("DICT_4X4_50", 50),
    ("DICT_4X4_100", 100),
    ("DICT_4X4_250", 250),
    ("DICT_4X4_1000", 1000),
    ("DICT_5X5_50", 50),
    ("DICT_5X5_100", 100),
    ("DICT_5X5_250", 250),
    ("DICT_5X5_1000", 1000),
    ("DICT_6X6_50", 50),
    ("DICT_6X6_100", 100),
    ("DICT_6X6_250", 250),
    ("DICT_6X6_1000", 1000),
    ("DICT_7X7_50", 50),
    ("DICT_7X7_100", 100),
    ("DICT_7X7_250", 250),
    ("DICT_7X7_1000", 1000),
    ("DICT_ARUCO_ORIGINAL", 1024),
];

impl MarkerFamily {
    /// The name (OpenCV dictionary name, or the official AprilTag family name).
    pub fn name(&self) -> &str {
        match self {
            MarkerFamily::Aruco(n) | MarkerFamily::AprilTag(n) => n,
        }
    }

    /// Number of distinct ids in the family.
    pub fn id_count(&self) -> u32 {
        let table = match self {
            MarkerFamily::Aruco(_) => ARUCO_DICTIONARIES,
            MarkerFamily::AprilTag(_) => APRILTAG_FAMILIES,
        };
        table.iter().find(|(d, _)| *d == self.name()).map_or(0, |(_, c)| *c)
    }

    /// The family's frame: corner order and axes.
    pub fn frame(&self) -> MarkerFrame {
        match self {
            MarkerFamily::Aruco(_) => MarkerFrame::OpenCv,
            MarkerFamily::AprilTag(_) => MarkerFrame::AprilTag,
        }
    }
}

impl FromStr for MarkerFamily {
    type Err = VisionError;
    fn from_str(s: &str) -> Result<Self, VisionError> {
        let t = s.trim();
        // `tag36h11`, `36h11` and OpenCV's `DICT_APRILTAG_36h11` are one official family.
        let l = t.to_ascii_lowercase();
        let bare = l.strip_prefix("dict_apriltag_").or(l.strip_prefix("tag")).unwrap_or(&l);
        if let Some((name, _)) = APRILTAG_FAMILIES.iter().find(|(n, _)| n[3..] == *bare) {
            return Ok(MarkerFamily::AprilTag((*name).to_string()));
        }
        let u = t.to_ascii_uppercase();
        let u = if u.starts_with("DICT_") { u } else { format!("DICT_{u}") };
        if ARUCO_DICTIONARIES.iter().any(|(d, _)| *d == u) {
            Ok(MarkerFamily::Aruco(u))
        } else {
            Err(VisionError::InvalidInput(format!(
                "unknown marker family `{s}` (OpenCV names such as DICT_4X4_50, DICT_ARUCO_ORIGINAL, or tag16h5, tag25h9, tag36h10, tag36h11)"
            )))
        }
    }
}

impl TryFrom<String> for MarkerFamily {
    type Error = VisionError;
    fn try_from(s: String) -> Result<Self, VisionError> {
        s.parse()
    }
}

impl From<MarkerFamily> for String {
    fn from(f: MarkerFamily) -> String {
        f.name().to_string()
    }
}

impl fmt::Display for MarkerFamily {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Which marker to look for.
///
/// Its defaults are the marker the simulator shows and the launch files expect: `marker:` in
/// `config/trocar_estimator.yaml`, built in ([`crate::config::TROCAR_ESTIMATOR`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct MarkerSpec {
    /// Family.
    pub family: MarkerFamily,
    /// Id to keep; `None` keeps every id of the family.
    pub id: Option<u32>,
    /// Side of the black square, m.
    pub size_m: f64,
}

crate::shipped_defaults!(MarkerSpec, crate::config::TROCAR_ESTIMATOR, ["marker"]);

impl MarkerSpec {
    /// Check size and id.
    pub fn validate(&self) -> Result<(), VisionError> {
        crate::validate::between("size_m", self.size_m, 1e-4, 10.0)?;
        if let Some(id) = self.id {
            if id >= self.family.id_count() {
                return Err(VisionError::InvalidInput(format!(
                    "id {id} not in {} ({} ids)",
                    self.family,
                    self.family.id_count()
                )));
            }
        }
        Ok(())
    }
}

/// One detected marker.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MarkerDetection {
    /// Marker id.
    pub id: u32,
    /// Marker pose in the camera optical frame.
    pub pose_camera_marker: Isometry3<f64>,
    /// Corner pixels, in the order of the family's [`MarkerFrame`] (ArUco TL, TR, BR, BL;
    /// AprilTag left-bottom, right-bottom, right-top, left-top).
    pub corners: [[f64; 2]; 4],
    /// RMS reprojection error of the corners, px.
    pub reprojection_error_px: f64,
}

impl MarkerDetection {
    /// The smallest distance of a corner from the edge of a `width` x `height` image, px
    /// (negative when a corner lies outside it). A marker cut by the image border can still
    /// be detected, as a smaller quad whose pose is centimetres off: callers reject
    /// detections closer to the border than a margin.
    pub fn border_distance_px(&self, width: u32, height: u32) -> f64 {
        let (w, h) = (f64::from(width), f64::from(height));
        self.corners
            .iter()
            .map(|[x, y]| x.min(y.min((w - 1.0 - x).min(h - 1.0 - y))))
            .fold(f64::INFINITY, f64::min)
    }
}

/// A detector for one marker spec and camera. Keeps its C++ state (dictionary, AprilTag
/// detector, buffers) between frames; `Send`, not `Sync`.
pub struct MarkerDetector {
    spec: MarkerSpec,
    camera: CameraModel,
    inner: cxx::UniquePtr<ffi::MarkerDetectorCpp>,
}

impl fmt::Debug for MarkerDetector {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("MarkerDetector")
            .field("spec", &self.spec)
            .field("camera", &self.camera)
            .finish()
    }
}

impl MarkerDetector {
    /// Build a detector (validates the spec and the camera model first).
    pub fn new(spec: MarkerSpec, camera: &CameraModel) -> Result<Self, VisionError> {
        spec.validate()?;
        camera.validate()?;
        let inner = ffi::new_marker_detector(
            spec.family.name(),
            &camera.intrinsics(),
            &camera.distortion,
            camera.is_equidistant(),
            camera.width as i32,
            camera.height as i32,
        )?;
        if inner.is_null() {
            return Err(VisionError::Backend("detector construction returned null".into()));
        }
        Ok(Self {
            spec,
            camera: camera.clone(),
            inner,
        })
    }

    /// The spec.
    pub fn spec(&self) -> &MarkerSpec {
        &self.spec
    }

    /// The camera model.
    pub fn camera(&self) -> &CameraModel {
        &self.camera
    }

    /// Detect markers of the spec in `image` (grey or RGB8, the camera's size). No marker ->
    /// an empty vector; a wrong size or a malformed buffer -> an error.
    pub fn detect(&mut self, image: &ImageView<'_>) -> Result<Vec<MarkerDetection>, VisionError> {
        self.detect_in(image, None)
    }

    /// As [`MarkerDetector::detect`], searching only the window `roi` = x, y, width, height
    /// (px) for ArUco markers (corners are still refined and reported in full-image pixels);
    /// AprilTag, and a window too small to hold a marker, search the whole frame.
    pub fn detect_in(
        &mut self,
        image: &ImageView<'_>,
        roi: Option<[u32; 4]>,
    ) -> Result<Vec<MarkerDetection>, VisionError> {
        image.validate()?;
        if image.width != self.camera.width || image.height != self.camera.height {
            return Err(VisionError::InvalidInput(format!(
                "image is {}x{}, camera model is {}x{}",
                image.width, image.height, self.camera.width, self.camera.height
            )));
        }
        let id = self.spec.id.map_or(-1, |i| i as i32);
        let window: Vec<i32> = roi
            .map(|r| r.iter().map(|&v| v.min(i32::MAX as u32) as i32).collect())
            .unwrap_or_default();
        let pinned = self
            .inner
            .as_mut()
            .ok_or_else(|| VisionError::Backend("detector is null".into()))?;
        let rec = ffi::detect_markers(
            pinned,
            image.data,
            image.width as i32,
            image.height as i32,
            image.channels as i32,
            id,
            self.spec.size_m,
            &window,
        )?;
        Ok(rec
            .chunks_exact(DETECTION_RECORD_LEN)
            .filter_map(parse_record)
            .collect())
    }
}

/// The window around `corners` grown by `margin` times the marker's pixel extent on every
/// side, clipped to a `width` x `height` image: where the marker will be in the next frame.
pub fn search_window(corners: &[[f64; 2]; 4], margin: f64, width: u32, height: u32) -> Option<[u32; 4]> {
    if corners.iter().flatten().any(|v| !v.is_finite()) || !(margin.is_finite() && margin >= 0.0) {
        return None;
    }
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for [x, y] in corners {
        (x0, y0, x1, y1) = (x0.min(*x), y0.min(*y), x1.max(*x), y1.max(*y));
    }
    let grow = margin * (x1 - x0).max(y1 - y0);
    let clip = |v: f64, hi: u32| v.clamp(0.0, f64::from(hi)) as u32;
    let (ax, ay) = (clip(x0 - grow, width), clip(y0 - grow, height));
    let (bx, by) = (clip((x1 + grow).ceil(), width), clip((y1 + grow).ceil(), height));
    (bx > ax && by > ay).then(|| [ax, ay, bx - ax, by - ay])
}

/// A detector that follows the marker: after a detection it searches the next frame near
/// the last one (a fraction of the frame: less work, and a shorter latency tail), and the
/// whole frame when the marker is not found there or was lost.
#[derive(Debug)]
pub struct TrackingDetector {
    detector: MarkerDetector,
    margin: f64,
    last: Option<[[f64; 2]; 4]>,
}

impl TrackingDetector {
    /// Track with a search window `margin` marker extents wide around the last detection
    /// (0 = always search the whole frame).
    pub fn new(detector: MarkerDetector, margin: f64) -> Self {
        Self {
            detector,
            margin: if margin.is_finite() { margin.max(0.0) } else { 0.0 },
            last: None,
        }
    }

    /// The detector.
    pub fn detector(&self) -> &MarkerDetector {
        &self.detector
    }

    /// The best detection in `image` (lowest reprojection error), if any.
    pub fn detect(&mut self, image: &ImageView<'_>) -> Result<Option<MarkerDetection>, VisionError> {
        let window = match (self.last, self.margin > 0.0) {
            (Some(c), true) => search_window(&c, self.margin, image.width, image.height),
            _ => None,
        };
        let best = |v: Vec<MarkerDetection>| {
            v.into_iter()
                .min_by(|a, b| a.reprojection_error_px.total_cmp(&b.reprojection_error_px))
        };
        let mut found = best(self.detector.detect_in(image, window)?);
        if found.is_none() && window.is_some() {
            found = best(self.detector.detect_in(image, None)?);
        }
        self.last = found.as_ref().map(|d| d.corners);
        Ok(found)
    }
}

/// One 22-number record -> a detection; `None` if it is not finite or not a rotation.
fn parse_record(r: &[f64]) -> Option<MarkerDetection> {
    if !(r[0].is_finite() && r[0] >= 0.0) || r[21].is_nan() {
        return None;
    }
    let pose = isometry_from_rt(&r[1..13])?;
    let mut corners = [[0.0; 2]; 4];
    for (k, c) in corners.iter_mut().enumerate() {
        *c = [r[13 + 2 * k], r[14 + 2 * k]];
    }
    if corners.iter().flatten().any(|v| !v.is_finite()) {
        return None;
    }
    Some(MarkerDetection {
        id: r[0] as u32,
        pose_camera_marker: pose,
        corners,
        reprojection_error_px: r[21],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn family_names_parse() {
        assert_eq!(
            "DICT_4X4_50".parse::<MarkerFamily>().unwrap(),
            MarkerFamily::Aruco("DICT_4X4_50".into())
        );
        assert_eq!("4x4_50".parse::<MarkerFamily>().unwrap().name(), "DICT_4X4_50");
        let tag36h11 = MarkerFamily::AprilTag("tag36h11".into());
        for name in [
            "tag36h11",
            "36h11",
            "Tag36H11",
            "DICT_APRILTAG_36h11",
            "dict_apriltag_36H11",
        ] {
            assert_eq!(name.parse::<MarkerFamily>().unwrap(), tag36h11, "{name}");
        }
        assert_eq!("DICT_APRILTAG_16h5".parse::<MarkerFamily>().unwrap().name(), "tag16h5");
        assert_eq!(
            "tag25h9".parse::<MarkerFamily>().unwrap().frame(),
            MarkerFrame::AprilTag
        );
        assert_eq!(tag36h11.id_count(), 587);
        assert_eq!(
            "DICT_4X4_50".parse::<MarkerFamily>().unwrap().frame(),
            MarkerFrame::OpenCv
        );
        assert!("tag36h12".parse::<MarkerFamily>().is_err());
        assert!("DICT_APRILTAG_41h12".parse::<MarkerFamily>().is_err());
        assert!("DICT_9X9_50".parse::<MarkerFamily>().is_err());
        assert_eq!(MarkerFamily::Aruco("DICT_ARUCO_ORIGINAL".into()).id_count(), 1024);
    }

    #[test]
    fn search_windows_grow_and_clip() {
        let c = [[100.0, 100.0], [140.0, 100.0], [140.0, 130.0], [100.0, 130.0]];
        assert_eq!(search_window(&c, 1.0, 640, 360), Some([60, 60, 120, 110]));
        assert_eq!(search_window(&c, 5.0, 640, 360), Some([0, 0, 340, 330]));
        let mut bad = c;
        bad[2][0] = f64::NAN;
        assert_eq!(search_window(&bad, 1.0, 640, 360), None);
        let outside = [[700.0, 400.0], [710.0, 400.0], [710.0, 410.0], [700.0, 410.0]];
        assert_eq!(search_window(&outside, 0.5, 640, 360), None);
    }

    #[test]
    fn border_distance_is_the_nearest_corner_to_an_edge() {
        let det = |c: [[f64; 2]; 4]| MarkerDetection {
            id: 7,
            pose_camera_marker: Isometry3::identity(),
            corners: c,
            reprojection_error_px: 0.1,
        };
        let inside = det([[100.0, 100.0], [140.0, 100.0], [140.0, 130.0], [100.0, 130.0]]);
        assert_eq!(inside.border_distance_px(640, 360), 100.0);
        assert_eq!(inside.border_distance_px(150, 360), 9.0);
        let cut = det([[100.0, 0.5], [140.0, 0.0], [140.0, 30.0], [100.0, 30.0]]);
        assert_eq!(cut.border_distance_px(640, 360), 0.0);
        let right = det([[600.0, 100.0], [642.0, 100.0], [642.0, 130.0], [600.0, 130.0]]);
        assert!(right.border_distance_px(640, 360) < 0.0);
    }

    #[test]
    fn the_default_is_the_shipped_marker_and_a_partial_spec_takes_the_rest_from_it() {
        let d = MarkerSpec::default();
        assert_eq!((d.family.name(), d.id, d.size_m), ("DICT_4X4_50", Some(7), 0.04));
        d.validate().unwrap();
        let p: MarkerSpec = crate::config::from_yaml_str("t", "id: 3\n").unwrap();
        assert_eq!((p.family, p.id, p.size_m), (d.family.clone(), Some(3), 0.04));
        // `id: null` keeps every id of the family.
        let p: MarkerSpec = crate::config::from_yaml_str("t", "id: null\n").unwrap();
        assert_eq!(p.id, None);
        let e = crate::config::from_yaml_str::<MarkerSpec>("t", "size: 0.05\n").unwrap_err();
        assert!(
            e.message.contains("`marker.size`: the key is now `marker.size_m`"),
            "{e}"
        );
    }

    #[test]
    fn specs_are_validated() {
        let fam = MarkerFamily::Aruco("DICT_4X4_50".into());
        assert!(MarkerSpec {
            family: fam.clone(),
            id: Some(49),
            size_m: 0.05
        }
        .validate()
        .is_ok());
        assert!(MarkerSpec {
            family: fam.clone(),
            id: Some(50),
            size_m: 0.05
        }
        .validate()
        .is_err());
        assert!(MarkerSpec {
            family: fam,
            id: None,
            size_m: f64::NAN
        }
        .validate()
        .is_err());
    }
}
