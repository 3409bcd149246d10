//! Camera model: pinhole intrinsics and distortion, from the ROS camera calibration YAML
//! (what `camera_calibration` writes and `camera_info_manager` reads) or CameraInfo fields.
//!
//! Which of a CameraInfo's matrices describe an image is ROS's convention, from
//! `sensor_msgs/CameraInfo.msg`'s own comments and image_geometry's `PinholeCameraModel`
//! (ros-perception/vision_opencv): K and D are "for the raw (distorted) images", P
//! "specifies the intrinsic (camera) matrix of the processed (rectified) image"
//! (`project3dToPixel` projects with P's fx', fy', cx', cy' and no distortion;
//! `rectifyImage`, what image_proc's rectify runs, maps the raw image through K, D, R onto P).
//! So [`CameraModel::from_camera_info`] reads a rectified image ([`ImageKind::Rectified`]:
//! `image_rect`, `image_rect_color`) with P and no distortion, and a raw one
//! ([`ImageKind::Raw`]: `image_raw`, `image`, `image_color`) with K and D in the named
//! distortion model: `plumb_bob` (5 coefficients k1 k2 t1 t2 k3), `rational_polynomial` (8:
//! k1 k2 t1 t2 k3 k4 k5 k6, OpenCV's rational model) or `equidistant` (4: k1 k2 k3 k4 on the
//! ray's angle, OpenCV's fisheye model, `cv::fisheye`); any other model is refused by name.
//! A node knows which image it reads from its image topic's last name (`image_rect*`:
//! rectified, anything else raw) unless its `image_kind` parameter says
//! ([`ImageKindSetting`]).

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::VisionError;

/// A row-major matrix as the ROS calibration YAML stores it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct YamlMatrix {
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Row-major values.
    pub data: Vec<f64>,
}

/// The ROS camera calibration file (camera_info_manager format).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationYaml {
    /// Image width, px.
    pub image_width: u32,
    /// Image height, px.
    pub image_height: u32,
    /// Camera name.
    #[serde(default)]
    pub camera_name: String,
    /// K, 3x3.
    pub camera_matrix: YamlMatrix,
    /// `plumb_bob`, `rational_polynomial` or `equidistant`.
    #[serde(default = "default_model")]
    pub distortion_model: String,
    /// D, 1xN.
    pub distortion_coefficients: YamlMatrix,
    /// R, 3x3.
    #[serde(default)]
    pub rectification_matrix: Option<YamlMatrix>,
    /// P, 3x4.
    #[serde(default)]
    pub projection_matrix: Option<YamlMatrix>,
}

fn default_model() -> String {
    "plumb_bob".into()
}

/// A stereo camera stamps the two images of one capture alike: a right image pairs with the
/// left image whose stamp is within this, s (the estimator node pairs them so, and the
/// preflight counts the pairs so).
pub const STEREO_MAX_SKEW_S: f64 = 1e-3;

/// The lens model of a camera's distortion coefficients.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DistortionModel {
    /// OpenCV's rational model, k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]] (ROS `plumb_bob`,
    /// `rational_polynomial`); no coefficients or all zero: a pinhole.
    #[default]
    Rational,
    /// OpenCV's fisheye model (ROS `equidistant`): exactly k1 k2 k3 k4, the distorted angle
    /// `θd = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)` of a ray at `θ` from the axis.
    Equidistant,
}

/// Which image a CameraInfo describes (ROS's image_pipeline names).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageKind {
    /// A camera driver's image (`image_raw`, `image`, `image_color`): K and D.
    Raw,
    /// A rectified image (`image_rect`, `image_rect_color`): P, no distortion.
    Rectified,
}

impl ImageKind {
    /// By an image topic's last name: `image_rect*` is rectified, anything else raw.
    pub fn of_topic(topic: &str) -> Self {
        let name = topic.rsplit('/').next().unwrap_or_default();
        if name.starts_with("image_rect") {
            Self::Rectified
        } else {
            Self::Raw
        }
    }
}

/// A node's `image_kind` parameter: how it reads its image's CameraInfo.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImageKindSetting {
    /// By the image topic's last name ([`ImageKind::of_topic`]).
    #[default]
    ByTopicName,
    /// Raw whatever the topic's name.
    Raw,
    /// Rectified whatever the topic's name.
    Rectified,
}

impl ImageKindSetting {
    /// The kind of the image on `image_topic`.
    pub fn resolve(self, image_topic: &str) -> ImageKind {
        match self {
            Self::ByTopicName => ImageKind::of_topic(image_topic),
            Self::Raw => ImageKind::Raw,
            Self::Rectified => ImageKind::Rectified,
        }
    }
}

/// The calibration fields of a sensor_msgs/CameraInfo (row-major K 3x3, R 3x3, P 3x4).
#[derive(Debug, Clone, Copy)]
pub struct CameraInfoFields<'a> {
    /// Image width, px.
    pub width: u32,
    /// Image height, px.
    pub height: u32,
    /// The distortion model's name.
    pub distortion_model: &'a str,
    /// D.
    pub d: &'a [f64],
    /// K, 9 values.
    pub k: &'a [f64],
    /// R, 9 values.
    pub r: &'a [f64],
    /// P, 12 values.
    pub p: &'a [f64],
}

const IDENTITY_3: [f64; 9] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];

/// Pinhole intrinsics with OpenCV-ordered distortion (k1 k2 p1 p2 [k3 [k4 k5 k6]], or the
/// fisheye model's k1 k2 k3 k4).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraModel {
    /// Image width, px.
    pub width: u32,
    /// Image height, px.
    pub height: u32,
    /// Focal length x, px.
    pub fx: f64,
    /// Focal length y, px.
    pub fy: f64,
    /// Principal point x, px.
    pub cx: f64,
    /// Principal point y, px.
    pub cy: f64,
    /// Distortion coefficients, OpenCV order; empty or all zero = none (rational model).
    pub distortion: Vec<f64>,
    /// The lens model of `distortion`.
    pub distortion_model: DistortionModel,
    /// Camera name.
    pub name: String,
    /// The stereo baseline, m: for the right camera of a rectified stereo pair, how far to the
    /// right (+x) of the left camera it sits (ROS: the projection matrix's `Tx = -fx * baseline`);
    /// 0 for a single camera or the left one of a pair.
    pub baseline_m: f64,
}

/// fx, fy, cx, cy, the distortion coefficients and their model.
type Intrinsics = (f64, f64, f64, f64, Vec<f64>, DistortionModel);

impl CameraModel {
    /// A distortion-free camera, validated.
    pub fn pinhole(width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64) -> Result<Self, VisionError> {
        let c = Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            distortion: vec![],
            distortion_model: DistortionModel::Rational,
            name: String::new(),
            baseline_m: 0.0,
        };
        c.validate()?;
        Ok(c)
    }

    /// The camera of an image from its CameraInfo, by ROS's convention (module doc): a
    /// rectified image through P (fx = P[0], fy = P[5], cx = P[2], cy = P[6], the baseline
    /// from Tx = P[3]) without distortion; a raw one through K and D in the named model (the
    /// baseline from P's Tx when P is set, which needs R = identity: a raw image is not in the
    /// rectified pair's frame otherwise). Wrong lengths, NaN, zero focal lengths and unknown
    /// models are errors that say which.
    pub fn from_camera_info(info: &CameraInfoFields<'_>, kind: ImageKind) -> Result<Self, VisionError> {
        let bad = |m: String| Err(VisionError::InvalidInput(m));
        if info.k.len() != 9 || info.r.len() != 9 || info.p.len() != 12 {
            return bad(format!(
                "K, R, P have {}, {}, {} values, expected 9, 9, 12",
                info.k.len(),
                info.r.len(),
                info.p.len()
            ));
        }
        if let Some(v) = [info.k, info.r, info.p, info.d]
            .concat()
            .iter()
            .find(|v| !v.is_finite())
        {
            return bad(format!("camera_info has a non-finite value ({v}) in K, R, P or D"));
        }
        let p = info.p;
        let projection_set = p.iter().any(|v| *v != 0.0);
        let (fx, fy, cx, cy, distortion, distortion_model) = match kind {
            ImageKind::Rectified => Self::rectified_projection(p)?,
            ImageKind::Raw => Self::raw_projection(info)?,
        };
        let mut c = Self {
            width: info.width,
            height: info.height,
            fx,
            fy,
            cx,
            cy,
            distortion,
            distortion_model,
            name: String::new(),
            baseline_m: 0.0,
        };
        if projection_set {
            c.set_baseline_from_projection(p)?;
        }
        if kind == ImageKind::Raw
            && c.baseline_m != 0.0
            && info.r.iter().zip(IDENTITY_3).any(|(a, b)| (a - b).abs() > 1e-9)
        {
            return bad(
                "a raw image of a stereo pair's right camera (P's Tx set) with a rectification R other than the \
                 identity: its rays are not in the pair's rectified frame; read its image_rect"
                    .into(),
            );
        }
        c.validate()?;
        Ok(c)
    }

    /// A rectified image's intrinsics: P's, with no distortion.
    fn rectified_projection(p: &[f64]) -> Result<Intrinsics, VisionError> {
        let bad = |m: String| Err(VisionError::InvalidInput(m));
        if p[0] <= 0.0 || p[5] <= 0.0 {
            return bad(format!(
                "a rectified image is projected with P, whose focal lengths P[0] = {}, P[5] = {} are not \
                 positive (an uncalibrated camera, or a raw image: set image_kind: raw)",
                p[0], p[5]
            ));
        }
        if p[7] != 0.0 {
            return bad(format!("P's Ty = {} (a vertical stereo pair) is not supported", p[7]));
        }
        Ok((p[0], p[5], p[2], p[6], vec![], DistortionModel::Rational))
    }

    /// A raw image's intrinsics: K and D in the named distortion model.
    fn raw_projection(info: &CameraInfoFields<'_>) -> Result<Intrinsics, VisionError> {
        let bad = |m: String| Err(VisionError::InvalidInput(m));
        let k = info.k;
        if k[0] <= 0.0 || k[4] <= 0.0 {
            return bad(format!(
                "a raw image is projected with K, whose focal lengths K[0] = {}, K[4] = {} are not positive \
                 (an uncalibrated camera)",
                k[0], k[4]
            ));
        }
        let (model, n) = match info.distortion_model {
            "plumb_bob" => (DistortionModel::Rational, 5),
            "rational_polynomial" => (DistortionModel::Rational, 8),
            "equidistant" => (DistortionModel::Equidistant, 4),
            m => {
                return bad(format!(
                    "distortion model '{m}' not supported for a raw image (plumb_bob, rational_polynomial, \
                     equidistant)"
                ))
            }
        };
        // image_geometry takes an empty D as no distortion; an equidistant lens always bends.
        let empty_ok = model == DistortionModel::Rational && info.d.is_empty();
        if info.d.len() != n && !empty_ok {
            return bad(format!(
                "distortion model '{}' has {n} coefficients, D has {}",
                info.distortion_model,
                info.d.len()
            ));
        }
        Ok((k[0], k[4], k[2], k[5], info.d.to_vec(), model))
    }

    /// From the parsed calibration YAML: the raw camera (K and D; the baseline from P's Tx).
    pub fn from_calibration(c: &CalibrationYaml) -> Result<Self, VisionError> {
        let k = &c.camera_matrix;
        if k.rows != 3 || k.cols != 3 {
            return Err(VisionError::InvalidInput("camera_matrix must be 3x3".into()));
        }
        let r = match &c.rectification_matrix {
            Some(r) if r.rows != 3 || r.cols != 3 => {
                return Err(VisionError::InvalidInput("rectification_matrix must be 3x3".into()))
            }
            Some(r) => r.data.clone(),
            None => IDENTITY_3.to_vec(),
        };
        let p = match &c.projection_matrix {
            Some(p) if p.rows != 3 || p.cols != 4 || p.data.len() != 12 => {
                return Err(VisionError::InvalidInput("projection_matrix must be 3x4".into()))
            }
            Some(p) => p.data.clone(),
            None => vec![0.0; 12],
        };
        let mut m = Self::from_camera_info(
            &CameraInfoFields {
                width: c.image_width,
                height: c.image_height,
                distortion_model: &c.distortion_model,
                d: &c.distortion_coefficients.data,
                k: &k.data,
                r: &r,
                p: &p,
            },
            ImageKind::Raw,
        )?;
        m.name = c.camera_name.clone();
        Ok(m)
    }

    /// Set [`CameraModel::baseline_m`] from a ROS projection matrix `P` (row-major 3 x 4):
    /// `-P[0][3] / P[0][0]`.
    pub fn set_baseline_from_projection(&mut self, p: &[f64]) -> Result<(), VisionError> {
        if p.len() != 12 || !(p[0].is_finite() && p[0] > 0.0 && p[3].is_finite()) {
            return Err(VisionError::InvalidInput(
                "projection matrix: 12 finite values with P[0][0] > 0 expected".into(),
            ));
        }
        self.baseline_m = -p[3] / p[0];
        self.validate()
    }

    /// Check that this model can be the right camera of a rectified stereo pair: a
    /// baseline of 1 mm to 1 m (from its projection's `Tx = -fx * baseline`).
    pub fn check_stereo_right(&self) -> Result<(), VisionError> {
        if (1e-3..=1.0).contains(&self.baseline_m) {
            return Ok(());
        }
        Err(VisionError::InvalidInput(format!(
            "baseline {:.1} mm (projection Tx = -fx * baseline): a right camera needs 1 mm to 1 m",
            self.baseline_m * 1e3 + 0.0
        )))
    }

    /// Where the right camera of a rectified stereo pair (this model, with its
    /// [`CameraModel::baseline_m`]) sees the left camera's points: a translation by minus the
    /// baseline along x.
    pub fn stereo_right_t_left(&self) -> nalgebra::Isometry3<f64> {
        nalgebra::Isometry3::translation(-self.baseline_m, 0.0, 0.0)
    }

    /// Read a ROS camera calibration YAML file.
    pub fn from_yaml_file(path: &Path) -> Result<Self, VisionError> {
        let s = std::fs::read_to_string(path).map_err(|e| VisionError::Io(format!("{}: {e}", path.display())))?;
        Self::from_yaml_str(&s)
    }

    /// Parse a ROS camera calibration YAML string.
    pub fn from_yaml_str(s: &str) -> Result<Self, VisionError> {
        let c: CalibrationYaml =
            crate::config::from_yaml_str("camera YAML", s).map_err(|e| VisionError::Io(e.to_string()))?;
        Self::from_calibration(&c)
    }

    /// The calibration YAML of this model (P = K | 0, R = identity).
    pub fn to_calibration(&self) -> CalibrationYaml {
        let k = vec![self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0];
        CalibrationYaml {
            image_width: self.width,
            image_height: self.height,
            camera_name: self.name.clone(),
            camera_matrix: YamlMatrix {
                rows: 3,
                cols: 3,
                data: k,
            },
            distortion_model: match self.distortion_model {
                DistortionModel::Equidistant => "equidistant",
                DistortionModel::Rational if self.distortion.len() > 5 => "rational_polynomial",
                DistortionModel::Rational => "plumb_bob",
            }
            .into(),
            distortion_coefficients: YamlMatrix {
                rows: 1,
                cols: self.distortion.len(),
                data: self.distortion.clone(),
            },
            rectification_matrix: Some(YamlMatrix {
                rows: 3,
                cols: 3,
                data: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            }),
            projection_matrix: Some(YamlMatrix {
                rows: 3,
                cols: 4,
                data: vec![
                    self.fx,
                    0.0,
                    self.cx,
                    -self.fx * self.baseline_m,
                    0.0,
                    self.fy,
                    self.cy,
                    0.0,
                    0.0,
                    0.0,
                    1.0,
                    0.0,
                ],
            }),
        }
    }

    /// Check the model is physically plausible (rejects values that would trip C++ asserts).
    pub fn validate(&self) -> Result<(), VisionError> {
        let bad = |m: String| Err(VisionError::InvalidInput(m));
        if self.width == 0 || self.height == 0 || self.width > 20_000 || self.height > 20_000 {
            return bad(format!("image size {}x{} out of range", self.width, self.height));
        }
        let (w, h) = (f64::from(self.width), f64::from(self.height));
        if ![self.fx, self.fy, self.cx, self.cy].iter().all(|v| v.is_finite()) {
            return bad("intrinsics must be finite".into());
        }
        if self.fx < 1.0 || self.fy < 1.0 || self.fx > 100.0 * w || self.fy > 100.0 * h {
            return bad(format!("focal lengths {} {} px are absurd", self.fx, self.fy));
        }
        if !(-w..=2.0 * w).contains(&self.cx) || !(-h..=2.0 * h).contains(&self.cy) {
            return bad(format!(
                "principal point ({}, {}) far outside the image",
                self.cx, self.cy
            ));
        }
        match self.distortion_model {
            DistortionModel::Rational if !matches!(self.distortion.len(), 0 | 4 | 5 | 8 | 12 | 14) => {
                return bad(format!(
                    "{} distortion coefficients (0, 4, 5, 8, 12 or 14)",
                    self.distortion.len()
                ));
            }
            DistortionModel::Equidistant if self.distortion.len() != 4 => {
                return bad(format!(
                    "{} distortion coefficients (the equidistant model has 4: k1 k2 k3 k4)",
                    self.distortion.len()
                ));
            }
            _ => {}
        }
        if self.distortion.iter().any(|d| !d.is_finite() || d.abs() > 1e3) {
            return bad("distortion coefficients must be finite and moderate".into());
        }
        if !(self.baseline_m.is_finite() && self.baseline_m.abs() <= 1.0) {
            return bad(format!(
                "stereo baseline {} m (from the projection matrix's Tx) not within 1 m",
                self.baseline_m
            ));
        }
        Ok(())
    }

    /// fx, fy, cx, cy.
    pub fn intrinsics(&self) -> [f64; 4] {
        [self.fx, self.fy, self.cx, self.cy]
    }

    /// The pixel of a point in the camera optical frame, through the distortion (OpenCV's
    /// rational model, k1 k2 p1 p2 [k3 [k4 k5 k6]], thin-prism and tilt terms ignored; or its
    /// fisheye model, `cv::fisheye::projectPoints`). `None` for a point less than 1 mm in
    /// front of the camera.
    pub fn project(&self, p: &nalgebra::Vector3<f64>) -> Option<[f64; 2]> {
        if p.z.is_nan() || p.z <= 1e-3 {
            return None;
        }
        let (x, y) = (p.x / p.z, p.y / p.z);
        let d = |i: usize| self.distortion.get(i).copied().unwrap_or(0.0);
        let r2 = x * x + y * y;
        if self.distortion_model == DistortionModel::Equidistant {
            let r = r2.sqrt();
            let theta = r.atan();
            let t2 = theta * theta;
            let theta_d = theta * (1.0 + t2 * (d(0) + t2 * (d(1) + t2 * (d(2) + t2 * d(3)))));
            let s = if r > 1e-12 { theta_d / r } else { 1.0 };
            return Some([self.fx * s * x + self.cx, self.fy * s * y + self.cy]);
        }
        let (r4, r6) = (r2 * r2, r2 * r2 * r2);
        let num = 1.0 + d(0) * r2 + d(1) * r4 + d(4) * r6;
        let den = 1.0 + d(5) * r2 + d(6) * r4 + d(7) * r6;
        let g = num / den;
        let (p1, p2) = (d(2), d(3));
        let xd = g * x + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = g * y + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        Some([self.fx * xd + self.cx, self.fy * yd + self.cy])
    }

    /// Whether a pixel is not where the pinhole puts it: a non-zero coefficient, or the
    /// equidistant model (which bends rays even with zero coefficients).
    pub fn is_distorted(&self) -> bool {
        self.is_equidistant() || self.distortion.iter().any(|d| *d != 0.0)
    }

    /// The camera of this camera's rectified image, as a calibration with R = identity and
    /// P = [K | Tx] describes it (what image_proc's rectify makes of the raw image): the same
    /// intrinsics and baseline, no distortion.
    pub fn rectified(&self) -> Self {
        Self {
            distortion: vec![],
            distortion_model: DistortionModel::Rational,
            ..self.clone()
        }
    }

    /// Whether the distortion is the equidistant (fisheye) model.
    pub fn is_equidistant(&self) -> bool {
        self.distortion_model == DistortionModel::Equidistant
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yaml_round_trip_and_shipped_file() {
        let mut c = CameraModel::pinhole(1280, 720, 700.0, 701.0, 640.5, 360.2).unwrap();
        c.distortion = vec![-0.17, 0.02, 0.0005, -0.0003, 0.0];
        let s = crate::config::to_yaml_string("camera", &c.to_calibration()).unwrap();
        assert_eq!(CameraModel::from_yaml_str(&s).unwrap(), c);
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/camera_zedm.yaml");
        let z = CameraModel::from_yaml_file(&path).unwrap();
        assert_eq!((z.width, z.height), (1280, 720));
        assert!((600.0..800.0).contains(&z.fx));
        assert_eq!(z.baseline_m, 0.0);
        // The right camera of the stereo pair: its baseline from P's Tx, kept on a round trip.
        let r = CameraModel::from_yaml_file(&path.with_file_name("camera_zedm_right.yaml")).unwrap();
        assert!((r.baseline_m - 0.063).abs() < 1e-6, "{}", r.baseline_m);
        let p = r.stereo_right_t_left() * nalgebra::Point3::new(0.1, 0.0, 0.3);
        assert!((p.x - 0.037).abs() < 1e-6);
        let s = crate::config::to_yaml_string("camera", &r.to_calibration()).unwrap();
        assert_eq!(CameraModel::from_yaml_str(&s).unwrap(), r);
        let bad = s.replace("-44.1504", "NaN");
        assert!(CameraModel::from_yaml_str(&bad).is_err());
    }

    /// A wide lens in the equidistant model (a ray 40° off the axis lands 2 % short of θ).
    fn fisheye() -> CameraModel {
        let mut c = CameraModel::pinhole(1280, 720, 520.0, 520.0, 641.0, 359.0).unwrap();
        c.distortion = vec![-0.04, 0.01, -0.003, 0.0005];
        c.distortion_model = DistortionModel::Equidistant;
        c.validate().unwrap();
        c
    }

    /// The marker's corners (TL TR BR BL, `cpp/vision_bridge.cpp` object_corners) at `pose`.
    fn corners(pose: &nalgebra::Isometry3<f64>, size: f64) -> Vec<nalgebra::Vector3<f64>> {
        let h = 0.5 * size;
        [(-h, h), (h, h), (h, -h), (-h, -h)]
            .iter()
            .map(|&(x, y)| (pose * nalgebra::Point3::new(x, y, 0.0)).coords)
            .collect()
    }

    #[test]
    fn an_equidistant_camera_is_honoured_through_opencv_s_fisheye_model() {
        use crate::vision::{facing_pose, render_marker_image, MarkerDetector, MarkerSpec, RenderOptions};
        let cam = fisheye();
        let spec = MarkerSpec::default();
        let pinhole = CameraModel::pinhole(1280, 720, cam.fx, cam.fy, cam.cx, cam.cy).unwrap();
        let (mut worst_fish, mut worst_pinhole, mut worst_px) = (0.0f64, 0.0f64, 0.0f64);
        // Near the centre and towards the corners, where the lens bends most.
        for (x, y) in [(0.0, 0.0), (0.16, 0.09), (-0.2, -0.1), (0.22, -0.12)] {
            let pose = facing_pose(0.3, x, y, 0.15, -0.1, 0.4);
            // Rendered through cv::fisheye (the C++ renderer), detected through it.
            let img = render_marker_image(&spec, &cam, &pose, &RenderOptions::default()).unwrap();
            let found = MarkerDetector::new(spec.clone(), &cam)
                .unwrap()
                .detect(&img.view())
                .unwrap();
            let d = found
                .first()
                .expect("the marker is found through the equidistant model");
            let err = (d.pose_camera_marker.translation.vector - pose.translation.vector).norm();
            worst_fish = worst_fish.max(err);
            // The detected corners are where CameraModel::project (Rust) puts the true ones.
            for (c, p) in d.corners.iter().zip(corners(&pose, spec.size_m)) {
                let [u, v] = cam.project(&p).unwrap();
                worst_px = worst_px.max((u - c[0]).hypot(v - c[1]));
            }
            // The same image read as a pinhole (the lens ignored) is off, or not found.
            let as_pinhole = MarkerDetector::new(spec.clone(), &pinhole)
                .unwrap()
                .detect(&img.view())
                .unwrap();
            let off = as_pinhole.first().map_or(f64::INFINITY, |d| {
                (d.pose_camera_marker.translation.vector - pose.translation.vector).norm()
            });
            worst_pinhole = worst_pinhole.max(off);
        }
        eprintln!(
            "equidistant: worst {:.3} mm, corners {worst_px:.3} px from Rust's projection; as a pinhole: worst {:.1} mm",
            worst_fish * 1e3,
            worst_pinhole * 1e3
        );
        assert!(worst_fish < 0.2e-3, "{worst_fish}");
        assert!(worst_px < 0.1, "{worst_px}");
        assert!(worst_pinhole > 20e-3, "{worst_pinhole}");
        // The equidistant model needs its 4 coefficients, in the bridges too.
        let mut bad = cam.clone();
        bad.distortion.push(0.0);
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("equidistant model has 4"));
    }

    #[test]
    fn absurd_models_are_rejected() {
        assert!(CameraModel::pinhole(1280, 720, 0.0, 700.0, 640.0, 360.0).is_err());
        assert!(CameraModel::pinhole(1280, 720, f64::NAN, 700.0, 640.0, 360.0).is_err());
        assert!(CameraModel::pinhole(0, 720, 700.0, 700.0, 640.0, 360.0).is_err());
        assert!(CameraModel::pinhole(1280, 720, 700.0, 700.0, 1e6, 360.0).is_err());
        fn raw(k: &[f64], d: &[f64]) -> Result<CameraModel, VisionError> {
            let info = CameraInfoFields {
                width: 1280,
                height: 720,
                distortion_model: "plumb_bob",
                d,
                k,
                r: &IDENTITY_3,
                p: &[0.0; 12],
            };
            CameraModel::from_camera_info(&info, ImageKind::Raw)
        }
        let e = raw(&[1.0; 4], &[]).unwrap_err().to_string();
        assert!(e.contains("K, R, P have 4, 9, 12 values"), "{e}");
        let k = [700.0, 0.0, 640.0, 0.0, 700.0, 360.0, 0.0, 0.0, 1.0];
        assert!(raw(&k, &[0.0; 3]).is_err());
        assert!(raw(&k, &[0.0; 5]).is_ok());
        assert!(CameraModel::from_yaml_str("image_width: 3").is_err());
    }
}
