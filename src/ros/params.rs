//! Node parameters: each node keeps its settings in one serde struct with defaults, filled
//! from its private namespace on the parameter server (which the launch files load from the
//! YAML in `config/`). Unknown keys are an error, so a typo in a YAML file is reported
//! instead of silently ignored. Values are then range-checked with [`crate::validate`]
//! (each node's `validate`), so a bad value stops the node at start-up with the key named.

use serde::de::DeserializeOwned;

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
