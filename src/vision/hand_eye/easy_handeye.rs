//! A hand-eye calibration saved by easy_handeye (IFL-CAMP/easy_handeye), read as the
//! project's mount (the camera in the flange `lbr_link_ee`), and the one reader of a hand-eye
//! file in either format ([`load_mount`]).
//!
//! easy_handeye's file, as its own code writes it
//! (`easy_handeye/src/easy_handeye/handeye_calibration.py`, `HandeyeCalibration.to_dict` and
//! `to_yaml`, saved by `to_file` to `~/.ros/easy_handeye/<namespace>.yaml`):
//!
//! ```yaml
//! parameters: {eye_on_hand: true, robot_base_frame: ..., robot_effector_frame: ...,
//!              tracking_base_frame: ..., tracking_marker_frame: ..., namespace: ..., ...}
//! transformation: {x: ..., y: ..., z: ..., qx: ..., qy: ..., qz: ..., qw: ...}
//! ```
//!
//! Its releases before `HandeyeCalibrationParameters` wrote `eye_on_hand`,
//! `tracking_base_frame` and `robot_effector_frame` (or `robot_base_frame`) at the top level,
//! and the first ones `tool_frame` and `optical_origin_frame` (the same file's older
//! `to_dict`, and `easy_handeye/src/handeyecalibration/handeye_calibration.py`): each key is
//! looked for under `parameters`, then at the top level, then under its old name.
//!
//! The transformation is a `TransformStamped` whose `header.frame_id` is
//! `robot_effector_frame` when `eye_on_hand` (else `robot_base_frame`) and whose
//! `child_frame_id` is `tracking_base_frame` (`HandeyeCalibration.__init__`): the pose of the
//! camera in the effector frame, `effector_T_camera`, with the quaternion in the order
//! `qx qy qz qw`. The effector frame is a lab's choice (`lbr_link_7`, a tool frame): it is
//! carried to the flange through the URDF's fixed joints (`flange_T_effector`, the caller's
//! resolver, KDL in practice), so `flange_T_camera = flange_T_effector * effector_T_camera`.
//! An eye-on-base calibration (the camera fixed in the world) is no mount and is refused.

use std::path::Path;

use nalgebra::Isometry3;

use super::super::estimator::PoseYaml;
use super::super::VisionError;
use crate::config::Value;

/// An eye-on-hand calibration of easy_handeye.
#[derive(Debug, Clone, PartialEq)]
pub struct EasyHandeye {
    /// The robot frame the camera was calibrated in (`robot_effector_frame`).
    pub effector_frame: String,
    /// The camera's frame (`tracking_base_frame`): its optical frame, where the tracker's
    /// poses were.
    pub camera_frame: String,
    /// The camera's pose in `effector_frame` (`transformation`).
    pub effector_t_camera: Isometry3<f64>,
}

/// A hand-eye mount as the nodes use it: the camera in the flange, and the camera's frame
/// when the file names it.
#[derive(Debug, Clone, PartialEq)]
pub struct Mount {
    /// The camera's pose in the flange `lbr_link_ee` (eMc).
    pub flange_t_camera: Isometry3<f64>,
    /// The camera frame the calibration was made in (easy_handeye's `tracking_base_frame`,
    /// the project's `camera_frame`), if the file says.
    pub camera_frame: Option<String>,
}

/// Whether the YAML tree `v` is an easy_handeye file (it has `transformation`) rather than
/// the project's (`flange_t_camera`).
pub fn is_easy_handeye(v: &Value) -> bool {
    v.get("transformation").is_some() && v.get("flange_t_camera").is_none()
}

/// The value of the first of `keys` found under `parameters`, else at the top level, with
/// where it was (`parameters.` or ``).
fn field<'a>(v: &'a Value, keys: &[&str]) -> Option<(&'static str, &'a Value)> {
    let params = v.get("parameters");
    keys.iter()
        .find_map(|k| params.and_then(|p| p.get(*k)))
        .map(|x| ("parameters.", x))
        .or_else(|| keys.iter().find_map(|k| v.get(*k)).map(|x| ("", x)))
}

fn string_field(what: &str, v: &Value, keys: &[&str]) -> Result<String, VisionError> {
    match field(v, keys) {
        Some((_, Value::String(s))) if !s.trim().is_empty() => Ok(s.trim().to_string()),
        Some((at, x)) => Err(VisionError::Io(format!(
            "{what}: {at}{} is {x:?}, not a frame name",
            keys[0]
        ))),
        None => Err(VisionError::Io(format!("{what}: no {} (easy_handeye file)", keys[0]))),
    }
}

impl EasyHandeye {
    /// Read easy_handeye's YAML tree `v` (`what` names the file in errors). Refused: an
    /// eye-on-base calibration, a missing frame or number, a non-finite or zero quaternion.
    pub fn from_value(what: &str, v: &Value) -> Result<Self, VisionError> {
        match field(v, &["eye_on_hand"]) {
            Some((_, Value::Bool(true))) => {}
            Some((at, Value::Bool(false))) => {
                let base = string_field(what, v, &["robot_base_frame", "base_link_frame"])
                    .unwrap_or_else(|_| "its robot base".into());
                return Err(VisionError::Io(format!(
                    "{what}: {at}eye_on_hand is false: an eye-on-base calibration (the camera fixed in \
                     `{base}`), not a camera on the flange; calibrate with eye_on_hand: true"
                )));
            }
            Some((at, x)) => {
                return Err(VisionError::Io(format!(
                    "{what}: {at}eye_on_hand is {x:?}, not true or false"
                )))
            }
            None => return Err(VisionError::Io(format!("{what}: no eye_on_hand (easy_handeye file)"))),
        }
        let effector_frame = string_field(what, v, &["robot_effector_frame", "tool_frame"])?;
        let camera_frame = string_field(what, v, &["tracking_base_frame", "optical_origin_frame"])?;
        let t = v
            .get("transformation")
            .ok_or_else(|| VisionError::Io(format!("{what}: no transformation")))?;
        let num = |k: &str| {
            t.get(k)
                .and_then(Value::as_f64)
                .ok_or_else(|| VisionError::Io(format!("{what}: transformation.{k} is missing or not a number")))
        };
        let pose = PoseYaml {
            translation: [num("x")?, num("y")?, num("z")?],
            quaternion_xyzw: [num("qx")?, num("qy")?, num("qz")?, num("qw")?],
        };
        let effector_t_camera = pose
            .to_isometry()
            .map_err(|e| VisionError::Io(format!("{what}: transformation: {e}")))?;
        Ok(Self {
            effector_frame,
            camera_frame,
            effector_t_camera,
        })
    }

    /// The camera in the flange: `flange_t_effector` is the effector frame in the flange
    /// (`resolve(effector_frame)`, e.g. through the URDF's fixed joints); its error (an
    /// unknown frame, one joined to the flange by a moving joint) is passed on naming the
    /// frame.
    pub fn mount(&self, resolve: &dyn Fn(&str) -> Result<Isometry3<f64>, String>) -> Result<Mount, VisionError> {
        let flange_t_effector = resolve(&self.effector_frame)
            .map_err(|e| VisionError::InvalidInput(format!("robot_effector_frame `{}`: {e}", self.effector_frame)))?;
        Ok(Mount {
            flange_t_camera: flange_t_effector * self.effector_t_camera,
            camera_frame: Some(self.camera_frame.clone()),
        })
    }
}

/// The mount of a hand-eye file's text in either format: the project's (`flange_t_camera`,
/// `trocar_docking hand-eye --out`; an optional `camera_frame`) or easy_handeye's (carried to
/// the flange through `resolve`, which is only called for easy_handeye's). `what` names the
/// file in errors.
pub fn mount_of_text(
    what: &str,
    text: &str,
    resolve: &dyn Fn(&str) -> Result<Isometry3<f64>, String>,
) -> Result<Mount, VisionError> {
    let v: Value = crate::config::from_yaml_str(what, text).map_err(|e| VisionError::Io(e.to_string()))?;
    if is_easy_handeye(&v) {
        return EasyHandeye::from_value(what, &v)?.mount(resolve);
    }
    let pose = v.get("flange_t_camera").ok_or_else(|| {
        VisionError::Io(format!(
            "{what}: neither flange_t_camera (trocar_docking hand-eye) nor transformation (easy_handeye)"
        ))
    })?;
    let pose: PoseYaml = crate::config::from_yaml_value(&format!("{what}: flange_t_camera"), pose.clone())
        .map_err(|e| VisionError::Io(e.to_string()))?;
    let flange_t_camera = pose
        .to_isometry()
        .map_err(|e| VisionError::Io(format!("{what}: flange_t_camera: {e}")))?;
    let camera_frame = v.get("camera_frame").and_then(Value::as_str).map(str::to_string);
    Ok(Mount {
        flange_t_camera,
        camera_frame,
    })
}

impl Mount {
    /// The text of the project's hand-eye file of this mount: a comment naming `source`, the
    /// `calibrated` date (YYYY-MM-DD, UTC; the preflight's age check), `flange_t_camera` and,
    /// when known, `camera_frame`.
    pub fn file_text(&self, source: &str, date: &str) -> Result<String, VisionError> {
        #[derive(serde::Serialize)]
        struct File<'a> {
            flange_t_camera: PoseYaml,
            #[serde(skip_serializing_if = "Option::is_none")]
            camera_frame: Option<&'a str>,
        }
        let body = crate::config::to_yaml_string(
            "hand-eye file",
            &File {
                flange_t_camera: PoseYaml::from_isometry(&self.flange_t_camera),
                camera_frame: self.camera_frame.as_deref(),
            },
        )
        .map_err(|e| VisionError::Io(e.to_string()))?;
        Ok(format!(
            "# Camera pose in the flange frame lbr_link_ee (eMc) from {source};\n\
             # `calibrated` (UTC) dates it for the preflight's age check.\ncalibrated: {date}\n{body}"
        ))
    }
}

/// [`mount_of_text`] of the file at `path`.
pub fn load_mount(path: &Path, resolve: &dyn Fn(&str) -> Result<Isometry3<f64>, String>) -> Result<Mount, VisionError> {
    let what = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| VisionError::Io(format!("{what}: cannot read: {e}")))?;
    mount_of_text(&what, &text, resolve)
}
