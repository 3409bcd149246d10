//! Camera model: pinhole intrinsics and distortion, from the ROS camera calibration YAML
//! (what `camera_calibration` writes and `camera_info_manager` reads) or CameraInfo fields.

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
    /// `plumb_bob`, `rational_polynomial` or `equidistant` (the last is not supported).
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

/// Pinhole intrinsics with OpenCV-ordered distortion (k1 k2 p1 p2 [k3 [k4 k5 k6]]).
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
    /// Distortion coefficients, OpenCV order; empty or all zero = none.
    pub distortion: Vec<f64>,
    /// Camera name.
    pub name: String,
    /// The stereo baseline, m: for the right camera of a rectified stereo pair, how far to the
    /// right (+x) of the left camera it sits (ROS: the projection matrix's `Tx = -fx * baseline`);
    /// 0 for a single camera or the left one of a pair.
    pub baseline_m: f64,
}

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
            name: String::new(),
            baseline_m: 0.0,
        };
        c.validate()?;
        Ok(c)
    }

    /// From sensor_msgs/CameraInfo fields (`K` row-major 9, `D`, model name).
    pub fn from_camera_info(
        width: u32,
        height: u32,
        k: &[f64],
        d: &[f64],
        distortion_model: &str,
    ) -> Result<Self, VisionError> {
        if k.len() != 9 {
            return Err(VisionError::InvalidInput(format!(
                "K has {} values, expected 9",
                k.len()
            )));
        }
        match distortion_model {
            "plumb_bob" | "rational_polynomial" | "" => {}
            m => {
                return Err(VisionError::InvalidInput(format!(
                    "distortion model `{m}` not supported (plumb_bob, rational_polynomial)"
                )))
            }
        }
        let c = Self {
            width,
            height,
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
            distortion: d.to_vec(),
            name: String::new(),
            baseline_m: 0.0,
        };
        c.validate()?;
        Ok(c)
    }

    /// From the parsed calibration YAML.
    pub fn from_calibration(c: &CalibrationYaml) -> Result<Self, VisionError> {
        let k = &c.camera_matrix;
        if k.rows != 3 || k.cols != 3 {
            return Err(VisionError::InvalidInput("camera_matrix must be 3x3".into()));
        }
        let mut m = Self::from_camera_info(
            c.image_width,
            c.image_height,
            &k.data,
            &c.distortion_coefficients.data,
            &c.distortion_model,
        )?;
        m.name = c.camera_name.clone();
        if let Some(p) = &c.projection_matrix {
            if p.rows != 3 || p.cols != 4 || p.data.len() != 12 {
                return Err(VisionError::InvalidInput("projection_matrix must be 3x4".into()));
            }
            m.set_baseline_from_projection(&p.data)?;
        }
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
            distortion_model: if self.distortion.len() > 5 {
                "rational_polynomial"
            } else {
                "plumb_bob"
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
        if !matches!(self.distortion.len(), 0 | 4 | 5 | 8 | 12 | 14) {
            return bad(format!(
                "{} distortion coefficients (0, 4, 5, 8, 12 or 14)",
                self.distortion.len()
            ));
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
    /// rational model, k1 k2 p1 p2 [k3 [k4 k5 k6]]; thin-prism and tilt terms ignored).
    /// `None` for a point less than 1 mm in front of the camera.
    pub fn project(&self, p: &nalgebra::Vector3<f64>) -> Option<[f64; 2]> {
        if p.z.is_nan() || p.z <= 1e-3 {
            return None;
        }
        let (x, y) = (p.x / p.z, p.y / p.z);
        let d = |i: usize| self.distortion.get(i).copied().unwrap_or(0.0);
        let r2 = x * x + y * y;
        let (r4, r6) = (r2 * r2, r2 * r2 * r2);
        let num = 1.0 + d(0) * r2 + d(1) * r4 + d(4) * r6;
        let den = 1.0 + d(5) * r2 + d(6) * r4 + d(7) * r6;
        let g = num / den;
        let (p1, p2) = (d(2), d(3));
        let xd = g * x + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = g * y + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        Some([self.fx * xd + self.cx, self.fy * yd + self.cy])
    }

    /// Whether the model has any non-zero distortion coefficient.
    pub fn is_distorted(&self) -> bool {
        self.distortion.iter().any(|d| *d != 0.0)
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

    #[test]
    fn absurd_models_are_rejected() {
        assert!(CameraModel::pinhole(1280, 720, 0.0, 700.0, 640.0, 360.0).is_err());
        assert!(CameraModel::pinhole(1280, 720, f64::NAN, 700.0, 640.0, 360.0).is_err());
        assert!(CameraModel::pinhole(0, 720, 700.0, 700.0, 640.0, 360.0).is_err());
        assert!(CameraModel::pinhole(1280, 720, 700.0, 700.0, 1e6, 360.0).is_err());
        assert!(CameraModel::from_camera_info(1280, 720, &[1.0; 4], &[], "plumb_bob").is_err());
        assert!(CameraModel::from_camera_info(
            1280,
            720,
            &[700.0, 0.0, 640.0, 0.0, 700.0, 360.0, 0.0, 0.0, 1.0],
            &[0.0; 3],
            "plumb_bob"
        )
        .is_err());
        assert!(CameraModel::from_yaml_str("image_width: 3").is_err());
    }
}
