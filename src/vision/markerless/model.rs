//! The trocar's shape as the markerless estimator sees it (`config/trocar_model.yaml`):
//! a head (cylinder) whose top face holds a circular opening, and a cannula below it on
//! the same axis. Port frame: origin at the opening's centre on the top face, z along the
//! axis into the body.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::validate;
use crate::vision::VisionError;

/// The head: a cylinder from the top face (z = 0) down to z = `height`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Head {
    /// Radius, m.
    pub radius: f64,
    /// Height along the axis, m.
    pub height: f64,
}

/// The circular opening in the head's top face (the port).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Opening {
    /// Radius, m.
    pub radius: f64,
}

/// The cannula: a cylinder from the head's bottom (z = head height) into the body.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Cannula {
    /// Outer radius, m.
    pub radius: f64,
    /// Length below the head, m.
    pub length: f64,
}

/// The trocar model, in metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrocarModel {
    /// The head.
    pub head: Head,
    /// The opening in its top face.
    pub opening: Opening,
    /// The cannula below it.
    pub cannula: Cannula,
}

impl TrocarModel {
    /// Read and validate a model YAML file.
    pub fn from_yaml_file(path: &Path) -> Result<Self, VisionError> {
        let s = std::fs::read_to_string(path).map_err(|e| VisionError::Io(format!("{}: {e}", path.display())))?;
        Self::from_yaml_str(&s).map_err(|e| match e {
            VisionError::Io(m) => VisionError::Io(format!("{}: {m}", path.display())),
            other => other,
        })
    }

    /// Parse and validate a model YAML string.
    pub fn from_yaml_str(s: &str) -> Result<Self, VisionError> {
        let m: Self =
            crate::config::from_yaml_str("trocar model YAML", s).map_err(|e| VisionError::Io(e.to_string()))?;
        m.validate()?;
        Ok(m)
    }

    /// Every size positive and of a trocar's order (at most 0.1 m across, 0.5 m long); the
    /// opening inside the head, the cannula no wider than the head.
    pub fn validate(&self) -> Result<(), VisionError> {
        validate::positive_at_most("head.radius", self.head.radius, 0.1)?;
        validate::positive_at_most("head.height", self.head.height, 0.2)?;
        validate::positive_at_most("opening.radius", self.opening.radius, 0.1)?;
        validate::positive_at_most("cannula.radius", self.cannula.radius, 0.1)?;
        validate::positive_at_most("cannula.length", self.cannula.length, 0.5)?;
        if self.opening.radius >= 0.95 * self.head.radius {
            return Err(VisionError::InvalidInput(format!(
                "opening.radius {} m must be below 0.95 x head.radius {} m (the face around it is what the estimator sees)",
                self.opening.radius, self.head.radius
            )));
        }
        if self.cannula.radius > self.head.radius {
            return Err(VisionError::InvalidInput(format!(
                "cannula.radius {} m is wider than head.radius {} m",
                self.cannula.radius, self.head.radius
            )));
        }
        Ok(())
    }

    /// The shipped model (`config/trocar_model.yaml`).
    pub fn shipped() -> Self {
        Self::from_yaml_str(SHIPPED)
            .unwrap_or_else(|e| unreachable!("config/trocar_model.yaml is checked by a test: {e}"))
    }
}

const SHIPPED: &str = include_str!("../../../config/trocar_model.yaml");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_model_parses_and_matches_the_simulated_trocar() {
        let m = TrocarModel::from_yaml_str(SHIPPED).unwrap();
        // The opening is the simulator's entry funnel; the cannula holds its 5.5 mm bore.
        assert!((m.opening.radius - 0.008).abs() < 1e-12);
        assert!(m.cannula.radius > 0.0055 / 2.0);
        assert_eq!(TrocarModel::shipped(), m);
    }

    #[test]
    fn missing_negative_and_inconsistent_values_are_clear_errors() {
        let ok =
            "head: {radius: 0.0125, height: 0.025}\nopening: {radius: 0.008}\ncannula: {radius: 0.0035, length: 0.1}\n";
        assert!(TrocarModel::from_yaml_str(ok).is_ok());
        let e = TrocarModel::from_yaml_str(&ok.replace("height: 0.025", "height: -0.025"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("head.height") && e.contains("-0.025"), "{e}");
        let e = TrocarModel::from_yaml_str(&ok.replace("opening: {radius: 0.008}\n", ""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("opening"), "{e}");
        let e = TrocarModel::from_yaml_str(&ok.replace("length: 0.1", "length: .nan"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannula.length"), "{e}");
        let e = TrocarModel::from_yaml_str(&ok.replace("radius: 0.008", "radius: 0.02"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("opening.radius"), "{e}");
        let e = TrocarModel::from_yaml_str(&ok.replace("radius: 0.0035", "radius: 0.02"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannula.radius"), "{e}");
        assert!(TrocarModel::from_yaml_str(&ok.replace("cannula:", "canula:")).is_err());
        assert!(TrocarModel::from_yaml_file(Path::new("/nonexistent/trocar.yaml")).is_err());
    }
}
