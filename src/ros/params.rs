//! Node parameters: each node keeps its settings in one serde struct with defaults, filled
//! from its private namespace on the parameter server (which the launch files load from the
//! YAML in `config/`). Unknown keys are an error, so a typo in a YAML file is reported
//! instead of silently ignored. Values are then range-checked with [`crate::validate`]
//! (each node's `validate`), so a bad value stops the node at start-up with the key named.

use serde::de::DeserializeOwned;

/// A parameter could not be read or does not fit the node's settings.
#[derive(Debug, thiserror::Error)]
pub enum ParamError {
    /// The parameter server did not answer.
    #[error("parameter server: {0}")]
    Server(String),
    /// The values do not match the settings struct (wrong type, unknown key).
    #[error("parameters of {namespace}: {message}")]
    Invalid {
        /// The namespace read.
        namespace: String,
        /// What is wrong.
        message: String,
    },
    /// A value is out of its range.
    #[error("parameter {0}")]
    Range(#[from] crate::validate::RangeError),
    /// A YAML file could not be read.
    #[error("cannot read {path}: {message}")]
    File {
        /// The file.
        path: String,
        /// The cause.
        message: String,
    },
}

/// Build the settings `T` from a parameter tree (missing keys take their defaults).
pub fn from_value<T: DeserializeOwned>(namespace: &str, value: serde_json::Value) -> Result<T, ParamError> {
    let value = match value {
        serde_json::Value::Null => serde_json::Value::Object(Default::default()),
        v => v,
    };
    serde_json::from_value(value).map_err(|e| ParamError::Invalid {
        namespace: namespace.to_string(),
        message: e.to_string(),
    })
}

/// Build the settings `T` from YAML text.
pub fn from_yaml_str<T: DeserializeOwned>(name: &str, yaml: &str) -> Result<T, ParamError> {
    crate::config::from_yaml_str(name, yaml).map_err(|e| ParamError::Invalid {
        namespace: e.what,
        message: e.message,
    })
}

/// Build the settings `T` from a YAML file.
pub fn from_yaml_file<T: DeserializeOwned>(path: &std::path::Path) -> Result<T, ParamError> {
    let text = std::fs::read_to_string(path).map_err(|e| ParamError::File {
        path: path.display().to_string(),
        message: e.to_string(),
    })?;
    from_yaml_str(&path.display().to_string(), &text)
}

/// Read this node's private namespace (`~`) from the parameter server into `T`; a node
/// without parameters gets the defaults. Call after `rosrust::init`.
pub fn load_private<T: DeserializeOwned>() -> Result<T, ParamError> {
    let ns = rosrust::name();
    let param = rosrust::param(&ns).ok_or_else(|| ParamError::Server(format!("bad name {ns}")))?;
    let exists = param.exists().map_err(|e| ParamError::Server(e.to_string()))?;
    if !exists {
        return from_value(&ns, serde_json::Value::Null);
    }
    let value: serde_json::Value = param.get().map_err(|e| ParamError::Server(e.to_string()))?;
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
    }

    #[test]
    fn unknown_keys_and_wrong_types_are_errors() {
        assert!(matches!(
            from_yaml_str::<S>("t", "rat: 3\n"),
            Err(ParamError::Invalid { .. })
        ));
        assert!(matches!(
            from_yaml_str::<S>("t", "rate: fast\n"),
            Err(ParamError::Invalid { .. })
        ));
        assert!(matches!(
            from_yaml_file::<S>(std::path::Path::new("/nonexistent.yaml")),
            Err(ParamError::File { .. })
        ));
    }
}
