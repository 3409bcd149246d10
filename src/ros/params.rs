//! Node parameters: each node keeps its settings in one serde struct with defaults, filled
//! from its private namespace on the parameter server (which the launch files load from the
//! YAML in `config/`). Unknown keys are an error, so a typo in a YAML file is reported
//! instead of silently ignored. Values are then range-checked with [`crate::validate`]
//! (each node's `validate`), so a bad value stops the node at start-up with the key named.

use serde::de::DeserializeOwned;

use crate::kinematics::lbr::{self, LbrModel, ToolParams};
use crate::kinematics::{fixed_transform, FLANGE_LINK};
use crate::vision::hand_eye::{load_mount, Mount};

pub use crate::config::{from_yaml_file, from_yaml_str, ParamError};

/// Build the settings `T` from a parameter tree as the parameter server hands it over
/// (missing keys take their defaults; null gives the defaults), through the same typed
/// deserialization as a YAML file ([`crate::config::from_tree`]); errors name `namespace`.
pub fn from_value<T: DeserializeOwned>(namespace: &str, value: serde_json::Value) -> Result<T, ParamError> {
    crate::config::from_tree(namespace, &value)
}

/// Read this node's private namespace (`~`) from the parameter server into `T`; a node
/// without parameters gets the defaults. Call after `rosrust::init`.
pub fn load_private<T: DeserializeOwned>() -> Result<T, ParamError> {
    let ns = rosrust::name();
    let server = |e: &dyn std::fmt::Display| ParamError::new(&ns, format_args!("parameter server: {e}"));
    let param = rosrust::param(&ns).ok_or_else(|| server(&"bad name"))?;
    let exists = param.exists().map_err(|e| server(&e))?;
    if !exists {
        return from_value(&ns, serde_json::Value::Null);
    }
    let value: serde_json::Value = param.get().map_err(|e| server(&e))?;
    from_value(&ns, value)
}

/// The robot's URDF text: `urdf_file`, else the parameter `/robot_description` (what
/// robot_state_publisher draws), else the built-in `model` with its endoscope.
fn robot_urdf(model: LbrModel, urdf_file: &str) -> Result<String, String> {
    if !urdf_file.is_empty() {
        return std::fs::read_to_string(urdf_file).map_err(|e| format!("{urdf_file}: cannot read: {e}"));
    }
    if let Some(xml) = rosrust::param("/robot_description").and_then(|p| p.get::<String>().ok()) {
        return Ok(xml);
    }
    lbr::urdf(model, &ToolParams::default()).map_err(|e| e.to_string())
}

/// The hand-eye file at `path` in either format (the project's `flange_t_camera`, or an
/// easy_handeye calibration: [`crate::vision::hand_eye::easy_handeye`]), as every node reads
/// it: an easy_handeye effector frame is carried to the flange through the fixed joints of
/// the robot's URDF (`urdf_file`, else `/robot_description`, else the built-in `model`).
/// The error names the parameter `hand_eye_file`.
pub fn hand_eye_mount(path: &str, model: LbrModel, urdf_file: &str) -> Result<Mount, String> {
    let resolve = |frame: &str| {
        let xml = robot_urdf(model, urdf_file)?;
        fixed_transform(&xml, FLANGE_LINK, frame).map_err(|e| e.to_string())
    };
    load_mount(std::path::Path::new(path), &resolve).map_err(|e| format!("`hand_eye_file`: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize, PartialEq)]
    #[serde(default, deny_unknown_fields)]
    struct S {
        rate: f64,
        topic: String,
    }
    impl Default for S {
        fn default() -> Self {
            Self {
                rate: 100.0,
                topic: "/a".into(),
            }
        }
    }

    #[test]
    fn defaults_fill_missing_keys_and_integers_become_floats() {
        let s: S = from_yaml_str("t", "rate: 1000\n").unwrap();
        assert_eq!(
            s,
            S {
                rate: 1000.0,
                topic: "/a".into()
            }
        );
        let d: S = from_value("t", serde_json::Value::Null).unwrap();
        assert_eq!(d, S::default());
        // A tree from the parameter server takes the same path: integers become floats.
        let s: S = from_value("/ns", serde_json::json!({"rate": 1000})).unwrap();
        assert_eq!((s.rate, s.topic.as_str()), (1000.0, "/a"));
    }

    #[test]
    fn unknown_keys_and_wrong_types_are_errors() {
        let e = from_yaml_str::<S>("t", "rat: 3\n").unwrap_err();
        assert!(e.what == "t" && e.message.contains("unknown field `rat`"), "{e}");
        let e = from_yaml_str::<S>("t", "rate: fast\n").unwrap_err();
        assert!(e.message.contains("rate: invalid type"), "{e}");
        let e = from_value::<S>("/ns", serde_json::json!({"rate": "fast"})).unwrap_err();
        assert!(e.what == "/ns" && e.message.contains("invalid type"), "{e}");
        let e = from_value::<S>("/ns", serde_json::json!({"rat": 3})).unwrap_err();
        assert!(e.message.contains("unknown field `rat`"), "{e}");
        let e = from_yaml_file::<S>(std::path::Path::new("/nonexistent.yaml")).unwrap_err();
        assert!(
            e.what == "/nonexistent.yaml" && e.message.starts_with("cannot read"),
            "{e}"
        );
    }
}
