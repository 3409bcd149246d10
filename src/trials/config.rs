//! The file `config/sim.yaml`: the simulated world (`sim:`), the trial rules (`trial:`),
//! the policy and the baseline's tunables, the pivot benchmark's durations (`pivot:`), and
//! the named protocols (`protocols:`), each a partial `sim:`/`trial:` tree laid over the base
//! sections ([`SimConfig::with_protocol`]). The file is built into the binary
//! ([`crate::sim::SHIPPED`]) and each section's defaults are its values there: a file that
//! leaves a key out takes the shipped value. The controller the trials run is
//! `config/controller.yaml`, unchanged ([`load_controller`]).

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::baseline::BaselineParams;
use super::pivot::PivotTiming;
use super::run::TrialParams;
use crate::config::Value;
use crate::control::ControllerParams;
use crate::sim::{SimError, SimParams, SHIPPED};

/// Default location of the simulator configuration, relative to the package root.
pub const DEFAULT_PATH: &str = "config/sim.yaml";

/// Default location of the controller configuration (what `robot.launch` runs).
pub const DEFAULT_CONTROLLER_PATH: &str = "config/controller.yaml";

/// `config/controller.yaml` as built into the binary, for runs outside the package root.
pub const EMBEDDED_CONTROLLER_YAML: &str = crate::config::CONTROLLER_YAML;

/// Everything `config/sim.yaml` holds. A section the file leaves out is the shipped one
/// ([`crate::sim::SHIPPED`]); a section it gives is laid over the shipped one key by key,
/// but for `protocols:`, which, given, is the file's own table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    /// The simulated world.
    pub sim: SimParams,
    /// Trial rules (goal, tolerances, timeout, abort force).
    pub trial: TrialParams,
    /// Which policy the trials run.
    pub policy: PolicyKind,
    /// The baseline policy.
    pub baseline: BaselineParams,
    /// Durations of the pivot benchmark's runs around their script.
    pub pivot: PivotTiming,
    /// Named protocols: each a partial tree of `sim:` and `trial:` values that replace the
    /// base ones (maps merge key by key, anything else is replaced).
    pub protocols: BTreeMap<String, Value>,
}

impl Default for SimConfig {
    /// The shipped file, section by section.
    fn default() -> Self {
        static PROTOCOLS: std::sync::OnceLock<BTreeMap<String, Value>> = std::sync::OnceLock::new();
        let protocols = PROTOCOLS.get_or_init(|| {
            crate::config::from_yaml_value(SHIPPED.name(), SHIPPED.section(&["protocols"]).clone())
                .unwrap_or_else(|e| panic!("the built-in {} has a bad `protocols:` table: {e}", SHIPPED.name()))
        });
        Self {
            sim: SimParams::default(),
            trial: TrialParams::default(),
            policy: PolicyKind::default(),
            baseline: BaselineParams::default(),
            pivot: PivotTiming::default(),
            protocols: protocols.clone(),
        }
    }
}

/// The policy of the trials.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(remote = "Self", rename_all = "snake_case")]
pub enum PolicyKind {
    /// The docking controller (paper eq. 1), `crate::control`.
    Controller,
    /// The resolved-rate baseline, [`super::baseline`].
    Baseline,
}

crate::shipped_defaults!(PolicyKind, SHIPPED, ["policy"]);

/// The protocols `config/sim.yaml` ships (the CLI's `--protocol`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Protocol {
    /// The paper's public code: uniform pose noise redrawn every step, no bias, 7 mm port.
    Paper,
    /// A lab bench: sealed 5.5 mm cannula, breathing, camera-rate pose with hand-eye bias,
    /// LBR torque errors, finite joint stiffness.
    #[default]
    Realistic,
    /// The realistic bench without a marker: the pose sensor with the markerless estimate's
    /// measured error (docs/markerless.md).
    RealisticMarkerless,
}

impl Protocol {
    /// The protocol's key in `protocols:`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Paper => "paper",
            Self::Realistic => "realistic",
            Self::RealisticMarkerless => "realistic_markerless",
        }
    }
}

impl std::fmt::Display for Protocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl SimConfig {
    /// Parse and validate YAML.
    pub fn from_yaml_str(s: &str) -> Result<Self, SimError> {
        Self::parse("sim YAML", s)
    }

    /// Parse YAML (`what` names it in errors) and validate.
    fn parse(what: &str, s: &str) -> Result<Self, SimError> {
        let c: Self = crate::config::from_yaml_str(what, s)?;
        c.validate()?;
        Ok(c)
    }

    /// Check every section, and that every protocol applies cleanly.
    pub fn validate(&self) -> Result<(), SimError> {
        self.sim.validate()?;
        self.trial.validate()?;
        self.pivot.validate()?;
        for name in self.protocols.keys() {
            self.with_protocol(name)?;
        }
        Ok(())
    }

    /// This configuration with the protocol `name` applied (its overrides laid over `sim:`
    /// and `trial:`), validated. The result keeps the protocol table.
    pub fn with_protocol(&self, name: &str) -> Result<Self, SimError> {
        let over = self.protocols.get(name).ok_or_else(|| SimError::Param {
            name: "protocols",
            why: format!(
                "no protocol '{name}' (have: {})",
                self.protocols.keys().cloned().collect::<Vec<_>>().join(", ")
            ),
        })?;
        if let Some(bad) = over
            .as_mapping()
            .and_then(|m| m.keys().find(|k| !matches!(k.as_str(), Some("sim" | "trial"))))
        {
            return Err(SimError::Param {
                name: "protocols",
                why: format!("protocol '{name}' may override only sim: and trial:, not {bad:?}"),
            });
        }
        let base = Self {
            protocols: BTreeMap::new(),
            ..self.clone()
        };
        let mut tree = crate::config::to_yaml_value("sim YAML", &base)?;
        crate::config::merge(&mut tree, over);
        let mut out: Self = crate::config::from_yaml_value(name, tree).map_err(|e| SimError::Param {
            name: "protocols",
            why: format!("protocol '{name}': {}", e.message),
        })?;
        out.sim.validate()?;
        out.trial.validate()?;
        out.protocols = self.protocols.clone();
        Ok(out)
    }

    /// `config/sim.yaml` when it exists (relative to the working directory), else the copy
    /// built into the binary.
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
        Self::parse(&path.display().to_string(), &s)
    }
}

/// The controller's parameters: `path` when given; else `config/controller.yaml` when it
/// exists (relative to the working directory); else the copy built into the binary.
pub fn load_controller(path: Option<&Path>) -> Result<ControllerParams, SimError> {
    let default = Path::new(DEFAULT_CONTROLLER_PATH);
    let (text, from) = match path {
        Some(p) => (
            std::fs::read_to_string(p).map_err(|e| SimError::Input(format!("{}: {e}", p.display())))?,
            p.display().to_string(),
        ),
        None if default.exists() => (
            std::fs::read_to_string(default).map_err(|e| SimError::Input(format!("{DEFAULT_CONTROLLER_PATH}: {e}")))?,
            DEFAULT_CONTROLLER_PATH.to_string(),
        ),
        None => (EMBEDDED_CONTROLLER_YAML.to_string(), "built-in controller.yaml".into()),
    };
    ControllerParams::from_yaml_str(&text).map_err(|e| SimError::Input(format!("{from}: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shipped() -> SimConfig {
        SimConfig::from_file(&Path::new(env!("CARGO_MANIFEST_DIR")).join(DEFAULT_PATH)).unwrap()
    }

    /// The shipped file parses and validates (every protocol applied), and it is every
    /// default: of the whole file and of each section.
    #[test]
    fn the_shipped_file_parses_validates_and_is_every_default() {
        let c = shipped();
        c.validate().unwrap();
        assert_eq!(c, SimConfig::default());
        assert_eq!(SimConfig::from_yaml_str("").unwrap(), c);
        let d = &c.sim;
        assert_eq!(
            (
                &d.arm,
                &d.trocar,
                &d.seal,
                &d.breathing,
                &d.contact,
                &d.torque_sensor,
                &d.measurement,
                &d.scenario
            ),
            (
                &crate::sim::ArmParams::default(),
                &crate::sim::TrocarParams::default(),
                &crate::sim::SealParams::default(),
                &crate::sim::BreathingParams::default(),
                &crate::sim::ContactParams::default(),
                &crate::sim::TorqueSensorParams::default(),
                &crate::sim::MeasurementParams::default(),
                &crate::sim::ScenarioParams::default()
            )
        );
        assert_eq!(
            (&c.trial, &c.baseline, &c.pivot, c.policy),
            (
                &TrialParams::default(),
                &BaselineParams::default(),
                &PivotTiming::default(),
                PolicyKind::default()
            )
        );
        // Figures of the file itself, so that the defaults are read, not made up.
        assert_eq!(
            (
                d.substeps,
                d.contact.stiffness_n_per_m,
                c.trial.abort_force_n,
                c.pivot.dock_timeout_s
            ),
            (10, 1e6, 60.0, 20.0)
        );
        assert_eq!(c.policy, PolicyKind::Controller);
        assert_eq!(
            c.protocols.keys().map(String::as_str).collect::<Vec<_>>(),
            ["paper", "realistic", "realistic_markerless"]
        );
    }

    #[test]
    fn shipped_config_parses_with_both_protocols() {
        let c = shipped();
        assert_eq!(c.trial.goal_depth_m, 0.03);
        let paper = c.with_protocol("paper").unwrap();
        assert_eq!(paper.sim.trocar.port_diameter_m, 0.007);
        assert_eq!(paper.sim.measurement.bias_position_m, 0.0);
        assert_eq!(paper.sim.measurement.bias_rotation_rad, 0.0);
        assert_eq!(paper.trial.timeout_s, 30.0);
        let real = c.with_protocol("realistic").unwrap();
        assert_eq!(real.sim.trocar.port_diameter_m, 0.0055);
        assert!(real.sim.seal.static_friction_n > real.sim.seal.kinetic_friction_n);
        assert!(real.sim.breathing.amplitude_axial_m > 0.0);
        assert_eq!(real.sim.measurement.bias_frame, crate::sim::noise::BiasFrame::Camera);
        assert!(SimConfig::from_yaml_str("trial: {timeout_s: -1}").is_err());
    }

    /// A user's file that leaves keys out takes the shipped values for them, section by
    /// section and key by key.
    #[test]
    fn a_key_missing_from_a_users_file_takes_the_shipped_value() {
        let d = SimConfig::default();
        let c = SimConfig::from_yaml_str(
            "sim: {trocar: {mass_kg: 0.5}}\ntrial: {timeout_s: 10}\npivot: {still_s: 1}\npolicy: baseline\n",
        )
        .unwrap();
        assert_eq!(
            (c.sim.trocar.mass_kg, c.trial.timeout_s, c.pivot.still_s, c.policy),
            (0.5, 10.0, 1.0, PolicyKind::Baseline)
        );
        let mut same = c.clone();
        same.sim.trocar.mass_kg = d.sim.trocar.mass_kg;
        same.trial.timeout_s = d.trial.timeout_s;
        same.pivot.still_s = d.pivot.still_s;
        same.policy = d.policy;
        assert_eq!(same, d);
        // A protocol's overrides are laid over the same base: what it leaves out is the base's.
        let p = SimConfig::from_yaml_str("protocols: {p: {sim: {seal: {static_friction_n: 3}}}}")
            .unwrap()
            .with_protocol("p")
            .unwrap();
        assert_eq!(p.sim.seal.static_friction_n, 3.0);
        assert_eq!(p.sim.seal.kinetic_friction_n, d.sim.seal.kinetic_friction_n);
        assert_eq!(p.sim.trocar, d.sim.trocar);
        // The file's own protocol table replaces the shipped one.
        assert_eq!(p.protocols.keys().collect::<Vec<_>>(), ["p"]);
        assert!(SimConfig::from_yaml_str("pivot: {still_s: -1}").is_err());
        assert!(SimConfig::from_yaml_str("policy: nope").is_err());
    }

    /// The error of `text` as a file, or else of its protocol `p` applied.
    fn refusal(text: &str) -> String {
        let e = SimConfig::from_yaml_str(text).and_then(|c| c.with_protocol("p"));
        e.unwrap_err().to_string()
    }

    /// The trials run at the controller's `dt_s`: the old `trial.control_rate_hz` is an error
    /// that names its replacement, at the top level and in a protocol.
    #[test]
    fn the_old_trial_control_rate_names_the_controllers_dt() {
        let gone = "`trial.control_rate_hz`: the key is gone";
        let top = refusal("trial: {control_rate_hz: 100.0}");
        assert!(
            top.contains(gone) && top.contains("`dt_s` in config/controller.yaml"),
            "{top}"
        );
        let e = refusal("protocols: {p: {trial: {control_rate_hz: 1000}}}");
        assert!(e.contains("protocol 'p'") && e.contains(gone), "{e}");
    }

    /// A renamed key is refused naming the new one, and an unknown key naming its path, at
    /// the top level, in a protocol's overrides and through a ROS-style parameter tree.
    #[test]
    fn renamed_and_unknown_keys_are_refused_with_their_path_everywhere() {
        let renamed = "`sim.scenario.q_nominal`: the key is now `sim.scenario.q_nominal_rad`";
        let q = "[0, 0.45, 0, -1.15, 0, 1.54, 0]";
        let e = refusal(&format!("sim: {{scenario: {{q_nominal: {q}}}}}"));
        assert!(e.contains(renamed), "{e}");
        let e = refusal(&format!("protocols: {{p: {{sim: {{scenario: {{q_nominal: {q}}}}}}}}}"));
        assert!(e.contains("protocol 'p'") && e.contains(renamed), "{e}");
        let zeros = [0.0; 7];
        let tree = serde_json::json!({"sim": {"scenario": {"q_nominal": zeros}}});
        let e = crate::config::from_tree::<SimConfig, _>("~world", &tree).unwrap_err();
        assert!(e.to_string().contains(renamed), "{e}");
        let ok = SimConfig::from_yaml_str(&format!("sim: {{scenario: {{q_nominal_rad: {q}}}}}")).unwrap();
        assert_eq!(ok.sim.scenario.q_nominal_rad[1], 0.45);
        let e = refusal("protocols: {p: {sim: {trocar: {typo: 1}}}}");
        assert!(
            e.contains("protocol 'p'") && e.contains("`sim.trocar.typo`: unknown key"),
            "{e}"
        );
    }

    #[test]
    fn the_markerless_protocol_is_the_realistic_plant_with_the_markerless_pose_error() {
        let c = shipped();
        let (real, ml) = (
            c.with_protocol(Protocol::Realistic.name()).unwrap(),
            c.with_protocol(Protocol::RealisticMarkerless.name()).unwrap(),
        );
        let same_plant = SimConfig {
            sim: crate::sim::SimParams {
                measurement: real.sim.measurement.clone(),
                ..ml.sim.clone()
            },
            ..ml.clone()
        };
        assert_eq!(same_plant, real);
        let (m, r) = (&ml.sim.measurement, &real.sim.measurement);
        assert!(m.gaussian_position_m > r.gaussian_position_m && m.gaussian_rotation_rad > r.gaussian_rotation_rad);
        assert!(m.latency_s > r.latency_s && m.rate_hz == r.rate_hz && m.bias_frame == r.bias_frame);
    }

    #[test]
    fn protocol_overrides_merge_and_bad_ones_are_errors() {
        let c = SimConfig::from_yaml_str(
            "sim: {trocar: {port_diameter_m: 0.007, length_m: 0.1}}\nprotocols: {p: {sim: {trocar: {port_diameter_m: 0.006}}}}",
        )
        .unwrap();
        let p = c.with_protocol("p").unwrap();
        assert_eq!(p.sim.trocar.port_diameter_m, 0.006);
        assert_eq!(p.sim.trocar.length_m, 0.1);
        assert!(c.with_protocol("nope").is_err());
        assert!(SimConfig::from_yaml_str("protocols: {p: {sim: {trocar: {typo: 1}}}}").is_err());
        assert!(SimConfig::from_yaml_str("protocols: {p: {controller: {dt: 0.1}}}").is_err());
        assert!(SimConfig::from_yaml_str("protocols: {p: {sim: {trocar: {mass_kg: -1}}}}").is_err());
    }

    #[test]
    fn controller_config_is_the_shipped_file() {
        let from_file = load_controller(Some(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join(DEFAULT_CONTROLLER_PATH),
        ));
        let embedded = ControllerParams::from_yaml_str(EMBEDDED_CONTROLLER_YAML).unwrap();
        assert_eq!(from_file.unwrap(), embedded);
        assert!(load_controller(Some(Path::new("/no/such/controller.yaml"))).is_err());
    }
}
