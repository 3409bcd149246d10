//! YAML loading: every configuration file (controller, simulator, trials, cameras, models,
//! node settings, hand-eye results) is read through [`from_yaml_str`] or [`from_yaml_file`], with
//! one parser (`serde_yaml_ng`) and one error, [`YamlError`], which names the file (or what was
//! parsed) and the parser's line, column and key. Unknown keys are errors where the target type
//! says `deny_unknown_fields`; an empty document gives the type's defaults.

use std::path::Path;

use serde::de::DeserializeOwned;
use serde::Serialize;

pub use serde_yaml_ng::{Mapping, Value};

/// A YAML text could not be read, parsed or mapped onto its type.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{what}: {message}")]
pub struct YamlError {
    /// The file, or what was parsed.
    pub what: String,
    /// The cause (the parser's message with its line and column, or the I/O error).
    pub message: String,
}

impl YamlError {
    fn new(what: &str, e: impl std::fmt::Display) -> Self {
        Self {
            what: what.to_string(),
            message: e.to_string(),
        }
    }
}

/// Parse `text` as `T`; `what` names the file (or what the text is) in the error. A document
/// that is empty (or only comments, or `null`) gives `T` from an empty mapping (its defaults).
pub fn from_yaml_str<T: DeserializeOwned>(what: &str, text: &str) -> Result<T, YamlError> {
    let tree: Value = serde_yaml_ng::from_str(text).map_err(|e| YamlError::new(what, e))?;
    if tree.is_null() {
        return from_yaml_value(what, Value::Mapping(Mapping::new()));
    }
    // Parse the text itself (not the tree) so that errors carry their line and column.
    serde_yaml_ng::from_str(text).map_err(|e| YamlError::new(what, e))
}

/// Read and parse the YAML file at `path` as `T`; the error names the file.
pub fn from_yaml_file<T: DeserializeOwned>(path: &Path) -> Result<T, YamlError> {
    let what = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| YamlError::new(&what, format_args!("cannot read: {e}")))?;
    from_yaml_str(&what, &text)
}

/// Map an already parsed YAML tree onto `T`.
pub fn from_yaml_value<T: DeserializeOwned>(what: &str, value: Value) -> Result<T, YamlError> {
    serde_yaml_ng::from_value(value).map_err(|e| YamlError::new(what, e))
}

/// `value` as a YAML tree.
pub fn to_yaml_value<T: Serialize>(what: &str, value: &T) -> Result<Value, YamlError> {
    serde_yaml_ng::to_value(value).map_err(|e| YamlError::new(what, e))
}

/// `value` as YAML text.
pub fn to_yaml_string<T: Serialize>(what: &str, value: &T) -> Result<String, YamlError> {
    serde_yaml_ng::to_string(value).map_err(|e| YamlError::new(what, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, PartialEq, Deserialize)]
    #[serde(default, deny_unknown_fields)]
    struct S {
        a: f64,
        b: u32,
    }

    impl Default for S {
        fn default() -> Self {
            Self { a: 1.5, b: 7 }
        }
    }

    #[test]
    fn empty_document_gives_defaults() {
        for text in ["", "# only a comment\n", "---\n", "null\n", "~"] {
            assert_eq!(from_yaml_str::<S>("t", text).unwrap(), S::default(), "{text:?}");
        }
        assert_eq!(from_yaml_str::<S>("t", "b: 3\n").unwrap(), S { a: 1.5, b: 3 });
        assert_eq!(from_yaml_str::<S>("t", "a: 2\n").unwrap(), S { a: 2.0, b: 7 });
    }

    #[test]
    fn errors_name_the_file_the_key_and_the_line() {
        let e = from_yaml_str::<S>("cfg.yaml", "a: 1\nc: 2\n").unwrap_err();
        assert_eq!(e.what, "cfg.yaml");
        assert!(e.to_string().starts_with("cfg.yaml: "), "{e}");
        assert!(
            e.message.contains("unknown field `c`") && e.message.contains("line 2"),
            "{e}"
        );
        let e = from_yaml_str::<S>("cfg.yaml", "a: 1\nb: x\n").unwrap_err();
        assert!(
            e.message.contains("b: invalid type") && e.message.contains("line 2"),
            "{e}"
        );
        let e = from_yaml_str::<S>("cfg.yaml", "a: [1\n").unwrap_err();
        assert!(e.message.contains("line"), "{e}");
        let e = from_yaml_file::<S>(Path::new("/nonexistent/cfg.yaml")).unwrap_err();
        assert_eq!(e.what, "/nonexistent/cfg.yaml");
        assert!(e.message.starts_with("cannot read: "), "{e}");
    }
}
