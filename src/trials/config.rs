//! The file `config/sim.yaml`: the simulated world (`sim:`) and the trial rules (`trial:`).

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::baseline::BaselineParams;
use super::run::TrialParams;
use crate::control::ControllerParams;
use crate::sim::{SimError, SimParams};

/// Default location of the simulator configuration, relative to the package root.
pub const DEFAULT_PATH: &str = "config/sim.yaml";

/// Everything `config/sim.yaml` holds.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    /// The simulated world.
    pub sim: SimParams,
    /// Trial rules (goal, tolerance, timeout, abort force, control rate).
    pub trial: TrialParams,
    /// Which policy the trials run.
    pub policy: PolicyKind,
    /// The docking controller's parameters (its `dt` is set from `trial.control_rate_hz`,
    /// `force_feedback` by the arm of the comparison).
    pub controller: ControllerParams,
    /// The baseline policy.
    pub baseline: BaselineParams,
}

/// The policy of the trials.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum PolicyKind {
    /// The docking controller (paper eq. 1), `crate::control`.
    #[default]
    Controller,
    /// The resolved-rate baseline, [`super::baseline`].
    Baseline,
}

impl SimConfig {
    /// Parse and validate YAML.
    pub fn from_yaml_str(s: &str) -> Result<Self, SimError> {
        let c: Self = serde_yaml::from_str(s)?;
        c.validate()?;
        Ok(c)
    }

    /// Check every section.
    pub fn validate(&self) -> Result<(), SimError> {
        self.sim.validate()?;
        self.trial.validate()?;
        self.controller.validate().map_err(|why| SimError::Param {
            name: "controller",
            why,
        })
    }

    /// `config/sim.yaml` when it exists (relative to the working directory), else the
    /// built-in defaults.
    pub fn load_default() -> Result<Self, SimError> {
        let p = Path::new(DEFAULT_PATH);
        if p.exists() {
            Self::from_file(p)
        } else {
            Ok(Self::default())
        }
    }

    /// Read a file.
    pub fn from_file(path: &Path) -> Result<Self, SimError> {
        let s = std::fs::read_to_string(path).map_err(|e| SimError::Input(format!("{}: {e}", path.display())))?;
        Self::from_yaml_str(&s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_config_parses() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(DEFAULT_PATH);
        let c = SimConfig::from_file(&path).unwrap();
        assert_eq!(c.trial.goal_depth_m, 0.03);
        assert_eq!(c.sim.trocar.port_diameter_m, 0.007);
        assert!(SimConfig::from_yaml_str("trial: {timeout_s: -1}").is_err());
    }
}
