//! The plant: an LBR Med in FRI position mode with elastic joints ([`arm`]) holding an
//! endoscope whose shaft touches ([`contact`]) a compliantly mounted, breathing trocar
//! ([`trocar`]) and slides through its seal ([`seal`]), measured by a noisy pose sensor
//! ([`noise`]) and the arm's joint torque sensors with the LBR's model error ([`torque`]),
//! and, as an injected fault, a stiff obstacle that catches the tip ([`jam`]),
//! from randomised starts ([`scenario`]). [`world::SimWorld`] steps it all at 1 kHz. The experiment that closes
//! the loop around it (policies, trials, statistics) is [`crate::trials`].
//!
//! Pure Rust, no ROS, no C++: the arm is seen through the [`Kinematics`](crate::kinematics::Kinematics)
//! trait. Every random draw comes from a seeded ChaCha stream, so a seed fixes a run.
//! Parameters are serde structs read from `config/sim.yaml`; their defaults are that file as
//! built into the binary ([`SHIPPED`]), so each value is written once, there, with its source.

pub mod arm;
pub mod contact;
pub mod jam;
pub mod noise;
pub mod scenario;
pub mod seal;
pub mod torque;
pub mod trocar;
pub mod world;

use serde::{Deserialize, Serialize};

use crate::config::{Renamed, Shipped};

pub use arm::ArmParams;
pub use contact::ContactParams;
pub use jam::Jam;
pub use noise::MeasurementParams;
pub use scenario::{Scenario, ScenarioParams};
pub use seal::SealParams;
pub use torque::TorqueSensorParams;
pub use trocar::{BreathingParams, TrocarParams};
pub use world::SimWorld;

/// Errors of the simulator.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A parameter is out of its valid range.
    #[error("invalid simulator parameter {name}: {why}")]
    Param {
        /// Parameter path, e.g. `trocar.mass_kg`.
        name: &'static str,
        /// What is wrong.
        why: String,
    },
    /// An input (command, pose, duration) is NaN, infinite or out of range.
    #[error("invalid input: {0}")]
    Input(String),
    /// The kinematics failed.
    #[error(transparent)]
    Kinematics(#[from] crate::kinematics::KinematicsError),
    /// The state became non-finite (unstable parameters).
    #[error("simulation diverged at t = {t:.4} s: {what}")]
    Diverged {
        /// Simulated time.
        t: f64,
        /// Which state.
        what: &'static str,
    },
    /// The YAML could not be parsed.
    #[error(transparent)]
    Yaml(#[from] crate::config::ParamError),
}

/// `config/sim.yaml` as built into the binary: the defaults of [`SimParams`] and its sections
/// (`sim:`), and of the trials' sections (`trial:`, `policy:`, `baseline:`, `pivot:`,
/// `protocols:`; [`crate::trials::config::SimConfig`]), each value written once, in the file.
pub static SHIPPED: Shipped = Shipped::with_renamed("config/sim.yaml", include_str!("../../config/sim.yaml"), RENAMED);

/// The keys of `config/sim.yaml` that were renamed or removed: given under the old name (in a
/// file, a protocol's overrides or the node's `~world` namespace), they are refused naming the
/// new one.
const RENAMED: &[Renamed] = &[
    Renamed {
        old: "sim.scenario.q_nominal",
        new: "sim.scenario.q_nominal_rad",
        note: "",
    },
    Renamed {
        old: "trial.control_rate_hz",
        new: "",
        note: "the trials run at the controller's period, `dt_s` in config/controller.yaml",
    },
];

/// Check that `v` is finite and within `[lo, hi]`.
pub(crate) fn check_range(name: &'static str, v: f64, lo: f64, hi: f64) -> Result<(), SimError> {
    if v.is_finite() && v >= lo && v <= hi {
        Ok(())
    } else {
        Err(SimError::Param {
            name,
            why: format!("{v} is not in [{lo}, {hi}]"),
        })
    }
}

/// Every parameter of the simulated world (the `sim:` section of `config/sim.yaml`; its
/// defaults are that section as shipped, [`SHIPPED`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct SimParams {
    /// Physics rate, Hz (the FRI rate of the LBR: 1000).
    pub physics_rate_hz: f64,
    /// Sub-steps of the trocar and contact integration per physics step (stiff contact).
    pub substeps: usize,
    /// The arm in FRI position mode.
    pub arm: ArmParams,
    /// The trocar geometry and its compliant mount.
    pub trocar: TrocarParams,
    /// The cannula's seal (axial stick-slip friction).
    pub seal: SealParams,
    /// Breathing motion of the trocar's mount.
    pub breathing: BreathingParams,
    /// Shaft-trocar contact.
    pub contact: ContactParams,
    /// The joint torque sensors (external torque estimate).
    pub torque_sensor: TorqueSensorParams,
    /// The trocar pose measurement.
    pub measurement: MeasurementParams,
    /// Randomised start poses.
    pub scenario: ScenarioParams,
}

crate::shipped_defaults!(SimParams, SHIPPED, ["sim"]);

impl SimParams {
    /// Parse from YAML (missing fields take their defaults) and validate.
    pub fn from_yaml_str(s: &str) -> Result<Self, SimError> {
        let p: Self = crate::config::from_yaml_str("sim YAML", s)?;
        p.validate()?;
        Ok(p)
    }

    /// Check every parameter.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("physics_rate_hz", self.physics_rate_hz, 100.0, 100_000.0)?;
        if !(1..=100).contains(&self.substeps) {
            return Err(SimError::Param {
                name: "substeps",
                why: format!("{} is not in 1..=100", self.substeps),
            });
        }
        self.arm.validate()?;
        self.trocar.validate()?;
        self.seal.validate()?;
        self.breathing.validate()?;
        self.contact.validate()?;
        self.torque_sensor.validate()?;
        self.measurement.validate()?;
        self.scenario.validate()?;
        Ok(())
    }

    /// Physics period, s.
    pub fn dt(&self) -> f64 {
        1.0 / self.physics_rate_hz
    }
}

/// Independent random streams of one seed (scenario, measurement noise, torque noise), so
/// changing one model's draws does not shift the others.
pub(crate) fn stream(seed: u64, purpose: u64) -> rand_chacha::ChaCha8Rng {
    use rand::SeedableRng;
    // splitmix64 of (seed, purpose): well-spread, deterministic sub-seeds.
    let mut z = seed ^ purpose.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    rand_chacha::ChaCha8Rng::seed_from_u64(z)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_yaml_round_trips() {
        let p = SimParams::default();
        p.validate().unwrap();
        let y = crate::config::to_yaml_string("sim", &p).unwrap();
        assert_eq!(SimParams::from_yaml_str(&y).unwrap(), p);
    }

    /// A partial `sim:` section takes the rest from the shipped one, and a renamed key is
    /// refused naming the new one.
    #[test]
    fn a_partial_section_takes_the_shipped_values() {
        let d = SimParams::default();
        assert_eq!((d.physics_rate_hz, d.substeps), (1000.0, 10));
        let p = SimParams::from_yaml_str("substeps: 20\nscenario: {max_draws: 7}\n").unwrap();
        assert_eq!((p.substeps, p.scenario.max_draws), (20, 7));
        let same = SimParams {
            substeps: d.substeps,
            scenario: d.scenario.clone(),
            ..p.clone()
        };
        assert_eq!(same, d);
        assert_eq!(p.scenario.q_nominal_rad, d.scenario.q_nominal_rad);
        let e = SimParams::from_yaml_str("scenario: {q_nominal: [0, 0, 0, 0, 0, 0, 0]}")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`sim.scenario.q_nominal`: the key is now `sim.scenario.q_nominal_rad`"),
            "{e}"
        );
    }

    #[test]
    fn bad_values_are_rejected() {
        assert!(SimParams::from_yaml_str("physics_rate_hz: .nan").is_err());
        assert!(SimParams::from_yaml_str("substeps: 0").is_err());
        assert!(SimParams::from_yaml_str("no_such_field: 1").is_err());
        assert!(SimParams::from_yaml_str("trocar: {mass_kg: -1}").is_err());
    }
}
