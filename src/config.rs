//! YAML loading: every configuration file (controller, simulator, trials, cameras, models,
//! node settings, hand-eye results) is read through [`from_yaml_str`] or [`from_yaml_file`], with
//! one parser (`serde_yaml_ng`) and one error, [`ParamError`], which names the file (or the
//! parameter namespace, or what was parsed), the key and the reason (with the parser's line
//! and column where it has them). A parameter tree (a protocol's overrides, what the ROS
//! parameter server hands over) takes the same typed path as a file: [`from_yaml_value`]. Unknown keys are errors where the target type
//! says `deny_unknown_fields`; an empty document gives the type's defaults.
//!
//! A type whose defaults are a section of a shipped file ([`Shipped`], declared with
//! [`shipped_defaults!`](crate::shipped_defaults)) has each number written once, in that file
//! with its comment and source: its `Default` is the section as built into the binary, and
//! whatever it is read from (a YAML file, the ROS parameter server) is laid over that section
//! key by key, so that a missing key takes the shipped value.

use std::path::Path;
use std::sync::OnceLock;

use serde::de::{DeserializeOwned, Deserializer, Error as _};
use serde::{Deserialize, Serialize};

pub use serde_yaml_ng::{Mapping, Value};

/// A parameter could not be read, parsed or mapped onto its type, or is out of range: the
/// one error of every configuration file and parameter namespace.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{what}: {message}")]
pub struct ParamError {
    /// The file, the parameter namespace, or what was parsed.
    pub what: String,
    /// The key and the reason (the parser's message with its line and column, the range
    /// rule broken, or the I/O error).
    pub message: String,
}

impl ParamError {
    /// `what` (a file, a namespace) is wrong for `reason`.
    pub fn new(what: &str, reason: impl std::fmt::Display) -> Self {
        Self {
            what: what.to_string(),
            message: reason.to_string(),
        }
    }
}

/// A value out of its range, where the file or namespace is not known (the key is named).
impl From<crate::validate::RangeError> for ParamError {
    fn from(e: crate::validate::RangeError) -> Self {
        Self::new("parameter", e)
    }
}

/// Parse `text` as `T`; `what` names the file (or what the text is) in the error. A document
/// that is empty (or only comments, or `null`) gives `T` from an empty mapping (its defaults).
pub fn from_yaml_str<T: DeserializeOwned>(what: &str, text: &str) -> Result<T, ParamError> {
    let tree: Value = serde_yaml_ng::from_str(text).map_err(|e| ParamError::new(what, e))?;
    if tree.is_null() {
        return from_yaml_value(what, tree);
    }
    // Parse the text itself (not the tree) so that errors carry their line and column.
    serde_yaml_ng::from_str(text).map_err(|e| ParamError::new(what, e))
}

/// Read and parse the YAML file at `path` as `T`; the error names the file.
pub fn from_yaml_file<T: DeserializeOwned>(path: &Path) -> Result<T, ParamError> {
    let what = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| ParamError::new(&what, format_args!("cannot read: {e}")))?;
    from_yaml_str(&what, &text)
}

/// Map a parameter tree onto `T` (missing keys take their defaults; null gives `T` from an
/// empty mapping): a parsed YAML file, a protocol's overrides, or (through
/// [`from_tree`]) what the ROS parameter server hands over.
pub fn from_yaml_value<T: DeserializeOwned>(what: &str, value: Value) -> Result<T, ParamError> {
    let value = if value.is_null() {
        Value::Mapping(Mapping::new())
    } else {
        value
    };
    serde_yaml_ng::from_value(value).map_err(|e| ParamError::new(what, e))
}

/// Map any serde tree (e.g. the JSON value of a ROS parameter namespace) onto `T` through
/// [`from_yaml_value`]: one typed deserialization and one error for files and trees.
pub fn from_tree<T: DeserializeOwned, V: Serialize>(what: &str, tree: &V) -> Result<T, ParamError> {
    from_yaml_value(what, to_yaml_value(what, tree)?)
}

/// `value` as a YAML tree.
pub fn to_yaml_value<T: Serialize>(what: &str, value: &T) -> Result<Value, ParamError> {
    serde_yaml_ng::to_value(value).map_err(|e| ParamError::new(what, e))
}

/// `value` as YAML text.
pub fn to_yaml_string<T: Serialize>(what: &str, value: &T) -> Result<String, ParamError> {
    serde_yaml_ng::to_string(value).map_err(|e| ParamError::new(what, e))
}

/// Lay `over` onto `base`: mappings merge key by key (recursively), other values replace.
pub fn merge(base: &mut Value, over: &Value) {
    match (base, over) {
        (Value::Mapping(b), Value::Mapping(o)) => {
            for (k, v) in o {
                match b.get_mut(k) {
                    Some(slot) => merge(slot, v),
                    None => {
                        b.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        (b, o) => *b = o.clone(),
    }
}

/// The text of `config/controller.yaml` as built into the binary.
pub const CONTROLLER_YAML: &str = include_str!("../config/controller.yaml");

/// `config/controller.yaml` as built into the binary: every default of
/// `control::ControllerParams` and of its sections is its value there (written once, with its
/// comment and source).
pub static CONTROLLER: Shipped = Shipped::with_renamed("config/controller.yaml", CONTROLLER_YAML, CONTROLLER_RENAMED);

/// Why `rate_hz` is gone, on the controller node and in the controller's own file.
const RATE_IS_DT: &str = "the control rate is the controller's period, `dt_s` = 1 / rate in config/controller.yaml \
                          (~controller/dt_s; the launch files' rate:=HZ sets it)";

/// The renamed keys of `config/controller.yaml` (each now named with its unit): an old key is
/// refused naming the new one.
pub(crate) const CONTROLLER_RENAMED: &[Renamed] = &[
    Renamed {
        old: "rate_hz",
        new: "",
        note: RATE_IS_DT,
    },
    Renamed::key("dt", "dt_s"),
    Renamed::key("insertion_depth", "insertion_depth_m"),
    Renamed::key("standoff", "standoff_m"),
    Renamed::key("approach_speed", "approach_speed_m_s"),
    Renamed::key("insert_speed", "insert_speed_m_s"),
    Renamed::key("approach_tolerance", "approach_tolerance_m"),
    Renamed::key("goal_tolerance", "goal_tolerance_m"),
    Renamed::key("goal_window", "goal_window_s"),
    Renamed::key("trocar_filter_time_constant", "trocar_filter_time_constant_s"),
    Renamed::key("torque_filter_time_constant", "torque_filter_time_constant_s"),
    Renamed::key("retreat_distance", "retreat_distance_m"),
    Renamed::key("approach_stall_timeout", "approach_stall_timeout_s"),
    Renamed::key("seated.lateral_tolerance", "seated.lateral_tolerance_m"),
    Renamed::key("seated.depth_tolerance", "seated.depth_tolerance_m"),
    Renamed::key("seated.min_lateral_force", "seated.min_lateral_force_n"),
    Renamed::key("seated.max_motion", "seated.max_motion_m"),
    Renamed::key("seated.settle_time", "seated.settle_time_s"),
    Renamed::key("admittance.torque_deadband", "admittance.torque_deadband_nm"),
    Renamed::key("admittance.force_deadband", "admittance.force_deadband_n"),
    Renamed::key("admittance.mass", "admittance.mass_kg"),
    Renamed::key("admittance.damping", "admittance.damping_ns_per_m"),
    Renamed::key("admittance.stiffness", "admittance.stiffness_n_per_m"),
    Renamed::key("admittance.max_displacement", "admittance.max_displacement_m"),
    Renamed::key("admittance.axial_force_full_stop", "admittance.axial_force_full_stop_n"),
    Renamed::key("guard.position_margin", "guard.position_margin_rad"),
    Renamed::key("guard.force_stop", "guard.force_stop_n"),
    Renamed::key("guard.joint_timeout", "guard.joint_timeout_s"),
    Renamed::key("guard.trocar_timeout", "guard.trocar_timeout_s"),
    Renamed::key("guard.torque_timeout", "guard.torque_timeout_s"),
    Renamed::key("guard.max_tracking_error", "guard.max_tracking_error_rad"),
    Renamed::key("guard.max_command_lead", "guard.max_command_lead_rad"),
    Renamed::key("guard.follow_timeout", "guard.follow_timeout_s"),
    Renamed::key("guard.max_clock_jump", "guard.max_clock_jump_s"),
    Renamed::key("motion.max_speed", "motion.max_speed_m_s"),
    Renamed::key("motion.max_accel", "motion.max_accel_m_s2"),
    Renamed::key("motion.max_jerk", "motion.max_jerk_m_s3"),
    Renamed::key("motion.max_angular_speed", "motion.max_angular_speed_rad_s"),
    Renamed::key("motion.max_angular_accel", "motion.max_angular_accel_rad_s2"),
    Renamed::key("motion.max_angular_jerk", "motion.max_angular_jerk_rad_s3"),
    Renamed::key("sqp.tolerance", "sqp.tolerance_rad"),
    Renamed::key("scope.command_timeout", "scope.command_timeout_s"),
    Renamed::key("scope.max_angular_speed", "scope.max_angular_speed_rad_s"),
    Renamed::key("scope.max_roll_speed", "scope.max_roll_speed_rad_s"),
    Renamed::key("scope.max_zoom_speed", "scope.max_zoom_speed_m_s"),
    Renamed::key("scope.min_depth", "scope.min_depth_m"),
    Renamed::key("scope.max_depth", "scope.max_depth_m"),
    Renamed::key("scope.retract_speed", "scope.retract_speed_m_s"),
    Renamed::key("scope.retract_force_stop", "scope.retract_force_stop_n"),
    Renamed::key("scope.arm_lag", "scope.arm_lag_s"),
    Renamed::key("scope.breathing.max_offset", "scope.breathing.max_offset_m"),
    Renamed::key("scope.breathing.max_speed", "scope.breathing.max_speed_m_s"),
    Renamed::key("scope.breathing.max_age", "scope.breathing.max_age_s"),
    Renamed::key("scope.breathing.max_jump", "scope.breathing.max_jump_m"),
    Renamed::key("scope.fulcrum.prior_depth", "scope.fulcrum.prior_depth_m"),
    Renamed::key("scope.fulcrum.stiffness", "scope.fulcrum.stiffness_n_per_m"),
    Renamed::key("scope.fulcrum.damping", "scope.fulcrum.damping_ns_per_m"),
    Renamed::key("scope.fulcrum.force_deadband", "scope.fulcrum.force_deadband_n"),
    Renamed::key(
        "scope.fulcrum.still_force_deadband",
        "scope.fulcrum.still_force_deadband_n",
    ),
    Renamed::key("scope.fulcrum.max_displacement", "scope.fulcrum.max_displacement_m"),
    Renamed::key("scope.fulcrum.max_lateral_speed", "scope.fulcrum.max_lateral_speed_m_s"),
    Renamed::key("scope.fulcrum.depth_gain", "scope.fulcrum.depth_gain_m_per_ns"),
    Renamed::key("scope.fulcrum.min_pivot_speed", "scope.fulcrum.min_pivot_speed_rad_s"),
    Renamed::key("scope.fulcrum.axial_damping", "scope.fulcrum.axial_damping_ns_per_m"),
    Renamed::key("scope.fulcrum.axial_deadband", "scope.fulcrum.axial_deadband_n"),
    Renamed::key(
        "scope.fulcrum.axial_still_deadband",
        "scope.fulcrum.axial_still_deadband_n",
    ),
    Renamed::key("scope.fulcrum.axial_max_speed", "scope.fulcrum.axial_max_speed_m_s"),
];

/// `config/docking_controller.yaml` (the docking controller node's private parameters, and
/// the preflight's) as built into the binary: the defaults of the node's settings
/// (`ros::controller_node::node_params`) and of the preflight's limits.
pub static DOCKING_CONTROLLER_NODE: Shipped = Shipped::with_renamed(
    "config/docking_controller.yaml",
    include_str!("../config/docking_controller.yaml"),
    DOCKING_CONTROLLER_NODE_RENAMED,
);

/// Why the drawn trocar's sizes are gone from `markers`.
const TROCAR_DRAWN_FROM_MODEL: &str = "the trocar is drawn as its head and cannula from config/trocar_model.yaml";

/// The renamed and removed keys of `config/docking_controller.yaml`.
const DOCKING_CONTROLLER_NODE_RENAMED: &[Renamed] = &[
    Renamed {
        old: "rate_hz",
        new: "",
        note: RATE_IS_DT,
    },
    Renamed::key("preflight.limits.min_joint_states_hz", "preflight.limits.min_driver_hz"),
    Renamed::key("markers.axis_length", "markers.axis_length_m"),
    Renamed::key("markers.optical_axis_length", "markers.optical_axis_length_m"),
    Renamed::key("markers.force_scale", "markers.force_scale_m_per_n"),
    Renamed::key("markers.force_max_length", "markers.force_max_length_m"),
    Renamed::key("markers.sphere", "markers.sphere_diameter_m"),
    Renamed {
        old: "markers.trocar_diameter",
        new: "",
        note: TROCAR_DRAWN_FROM_MODEL,
    },
    Renamed {
        old: "markers.trocar_length",
        new: "",
        note: TROCAR_DRAWN_FROM_MODEL,
    },
    Renamed {
        old: "markers.trocar_diameter_m",
        new: "",
        note: TROCAR_DRAWN_FROM_MODEL,
    },
    Renamed {
        old: "markers.trocar_length_m",
        new: "",
        note: TROCAR_DRAWN_FROM_MODEL,
    },
    Renamed::key("markers.cone_length", "markers.cone_length_m"),
];

/// `config/scope_joy.yaml` (the `scope_joy` node's private parameters: a common gamepad in its
/// Xbox layout) as built into the binary: the defaults of `ros::joy::JoyParams`.
pub static SCOPE_JOY: Shipped = Shipped::with_renamed(
    "config/scope_joy.yaml",
    include_str!("../config/scope_joy.yaml"),
    &[
        Renamed::key("joy_timeout", "joy_timeout_s"),
        Renamed::key("pan.scale", "pan.scale_rad_s"),
        Renamed::key("tilt.scale", "tilt.scale_rad_s"),
        Renamed::key("roll.scale", "roll.scale_rad_s"),
        Renamed::key("zoom.scale", "zoom.scale_m_s"),
    ],
);

/// `config/lbr_med_sim.yaml` (the `lbr_med_sim` node's private parameters) as built into the
/// binary: the defaults of `ros::sim_node::SimNodeParams` and of its simulated camera (whose
/// `marker` is laid over the estimator's, [`TROCAR_ESTIMATOR`], and refused by its table).
pub static LBR_MED_SIM: Shipped = Shipped::with_renamed(
    "config/lbr_med_sim.yaml",
    include_str!("../config/lbr_med_sim.yaml"),
    &[
        Renamed {
            old: "trocar_dropout_after",
            new: "trocar_dropout_after_s",
            note: "",
        },
        Renamed {
            old: "camera.blur_sigma",
            new: "camera.blur_sigma_px",
            note: "",
        },
        Renamed {
            old: "camera.wall_step",
            new: "camera.wall_step_px",
            note: "",
        },
    ],
);

/// `config/trocar_estimator.yaml` (the `trocar_estimator` node's private parameters) as built
/// into the binary: the defaults of `ros::estimator_node::EstimatorNodeParams`, and of its
/// sections: the estimator (`vision::EstimatorParams`), the marker (`vision::MarkerSpec`) and
/// the markerless measurement (`vision::markerless::MarkerlessParams`).
pub static TROCAR_ESTIMATOR: Shipped = Shipped::with_renamed(
    "config/trocar_estimator.yaml",
    include_str!("../config/trocar_estimator.yaml"),
    &[
        Renamed {
            old: "marker.size",
            new: "marker.size_m",
            note: "",
        },
        Renamed {
            old: "markerless.tracker_frames",
            new: "",
            note: "ViSP's model-based tracker is removed: no pose it carried ever passed the confidence gate, \
                   so it changed no trial's outcome; each image's own estimate is the measurement",
        },
    ],
);

/// `config/hand_eye_calibration.yaml` (the `hand_eye_calibration` node's private parameters)
/// as built into the binary: the defaults of `ros::hand_eye_node::HandEyeNodeParams`.
pub static HAND_EYE_CALIBRATION: Shipped = Shipped::with_renamed(
    "config/hand_eye_calibration.yaml",
    include_str!("../config/hand_eye_calibration.yaml"),
    &[
        Renamed {
            old: "marker_size",
            new: "marker_size_m",
            note: "",
        },
        Renamed {
            old: "max_joint_speed",
            new: "max_joint_speed_rad_s",
            note: "",
        },
        Renamed {
            old: "max_tracking_error",
            new: "max_tracking_error_rad",
            note: "",
        },
    ],
);

/// A YAML file shipped in `config/` and built into the binary (`include_str!`), parsed once
/// on first use; its sections are the defaults of the types declared with
/// [`shipped_defaults!`](crate::shipped_defaults). A unit test of each file proves that it
/// parses and validates, so the parse here cannot fail in a build that passed its tests.
pub struct Shipped {
    name: &'static str,
    text: &'static str,
    renamed: &'static [Renamed],
    tree: OnceLock<Value>,
}

/// A key of a shipped file that was renamed or removed: given under its old name, it is
/// refused with an error that names its replacement, rather than as merely unknown (a lab's
/// old launch file or YAML must not be half-read).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Renamed {
    /// The old key's dotted path in the file (e.g. `guard.force_stop`).
    pub old: &'static str,
    /// The dotted path that replaced it (empty: removed).
    pub new: &'static str,
    /// Why, or what to do instead (may be empty).
    pub note: &'static str,
}

impl Renamed {
    /// The key `old` renamed `new`, with no note.
    pub const fn key(old: &'static str, new: &'static str) -> Self {
        Self { old, new, note: "" }
    }

    /// The refusal's text, naming the old path and the replacement.
    fn message(&self) -> String {
        let mut m = if self.new.is_empty() {
            format!("`{}`: the key is gone", self.old)
        } else {
            format!("`{}`: the key is now `{}`", self.old, self.new)
        };
        if !self.note.is_empty() {
            m.push_str(" (");
            m.push_str(self.note);
            m.push(')');
        }
        m
    }
}

impl Shipped {
    /// The file `name` (for messages) with its text.
    pub const fn new(name: &'static str, text: &'static str) -> Self {
        Self {
            name,
            text,
            renamed: &[],
            tree: OnceLock::new(),
        }
    }

    /// The file `name` with its text and the table of its renamed and removed keys (see
    /// [`Renamed`]).
    pub const fn with_renamed(name: &'static str, text: &'static str, renamed: &'static [Renamed]) -> Self {
        Self {
            name,
            text,
            renamed,
            tree: OnceLock::new(),
        }
    }

    /// The renamed or removed key at dotted path `old`, if the file lists it.
    pub fn renamed(&self, old: &str) -> Option<&'static Renamed> {
        self.renamed.iter().find(|r| r.old == old)
    }

    /// The file's name, as in `config/`.
    pub const fn name(&self) -> &'static str {
        self.name
    }

    /// The section at `path` (keys from the top; empty for the whole file).
    ///
    /// # Panics
    /// If the built-in file does not parse or lacks the section: a defect of the build that
    /// the file's unit test reports.
    pub fn section(&self, path: &[&str]) -> &Value {
        let tree = self.tree.get_or_init(|| {
            serde_yaml_ng::from_str(self.text)
                .unwrap_or_else(|e| panic!("the built-in {} does not parse: {e}", self.name))
        });
        path.iter().fold(tree, |node, key| {
            node.get(key)
                .unwrap_or_else(|| panic!("the built-in {} has no section {}", self.name, path.join(".")))
        })
    }
}

/// Deserialize a type declared with [`shipped_defaults!`](crate::shipped_defaults): the value
/// `d` holds (a mapping, possibly partial; null for none) laid over the shipped section at
/// `path`, then read by `derived`, the type's derived (`#[serde(remote = "Self")]`)
/// deserializer, which rejects unknown keys. Its error names the unknown key's dotted path
/// (e.g. `` `guard.force_stp`: unknown key ``), or else the section.
pub fn deserialize_over<'de, D, T>(
    d: D,
    path: &[&str],
    file: &Shipped,
    derived: impl FnOnce(Value) -> Result<T, serde_yaml_ng::Error>,
) -> Result<T, D::Error>
where
    D: Deserializer<'de>,
{
    let given = Value::deserialize(d)?;
    let shipped = file.section(path);
    let mut tree = shipped.clone();
    if !given.is_null() {
        merge(&mut tree, &given);
    }
    derived(tree).map_err(|e| {
        let e = e.to_string();
        let mut at: Vec<String> = path.iter().map(|k| k.to_string()).collect();
        if let Some(unknown) = unknown_key(&given, shipped, file, &mut at, &e) {
            D::Error::custom(unknown)
        } else if let Some(named) = e.strip_prefix('`') {
            // An inner section has named itself already (from the top of its own file, when
            // it is this type's one field that the file does not ship: name that field too).
            match unshipped_fields(&given, shipped).as_slice() {
                [field] if path.is_empty() => D::Error::custom(format_args!("`{field}.{named}")),
                _ => D::Error::custom(e),
            }
        } else if path.is_empty() {
            D::Error::custom(e)
        } else {
            D::Error::custom(format_args!("`{}`: {e}", path.join(".")))
        }
    })
}

/// The keys of `given` that `shipped` lacks (at the top).
fn unshipped_fields<'a>(given: &'a Value, shipped: &Value) -> Vec<&'a str> {
    let (Value::Mapping(g), Value::Mapping(s)) = (given, shipped) else {
        return Vec::new();
    };
    g.keys()
        .filter(|k| s.get(*k).is_none())
        .filter_map(Value::as_str)
        .collect()
}

/// The first key of `given` that `shipped` lacks, as an error naming its dotted path (under
/// `path`) and either its replacement (a key the file lists as renamed or removed) or the
/// keys that exist there. A key the file lacks but the type has (`derived`, the type's own
/// error, does not call it unknown: a section read from its own file, as the controller
/// node's `controller`) is no unknown key.
fn unknown_key(
    given: &Value,
    shipped: &Value,
    file: &Shipped,
    path: &mut Vec<String>,
    derived: &str,
) -> Option<String> {
    let (Value::Mapping(g), Value::Mapping(s)) = (given, shipped) else {
        return None;
    };
    for (k, v) in g {
        let name = k.as_str().map_or_else(|| format!("{k:?}"), str::to_string);
        match s.get(k) {
            None => {
                let known: Vec<_> = s.keys().filter_map(Value::as_str).collect();
                path.push(name);
                if let Some(r) = file.renamed(&path.join(".")) {
                    return Some(r.message());
                }
                if !derived.contains(&format!("unknown field `{}`", path[path.len() - 1])) {
                    path.pop();
                    continue;
                }
                return Some(format!(
                    "`{}`: unknown key (expected one of: {})",
                    path.join("."),
                    known.join(", ")
                ));
            }
            Some(sv) => {
                path.push(name);
                if let Some(e) = unknown_key(v, sv, file, path, derived) {
                    return Some(e);
                }
                path.pop();
            }
        }
    }
    None
}

/// Declare that a configuration type's defaults are a section of a [`Shipped`] file: the
/// type derives `Deserialize` (and `Serialize`) with `#[serde(remote = "Self",
/// deny_unknown_fields)]` (no container `default`; a field the file leaves out has its own
/// `#[serde(default)]`), and this macro writes its `Default` (the section, parsed once and
/// cloned), its `Deserialize` (what is given laid over the section; see
/// [`deserialize_over`]) and, unless `deserialize_only` follows, its `Serialize`.
///
/// `shipped_defaults!(GuardParams, SHIPPED, ["guard"]);`
#[macro_export]
macro_rules! shipped_defaults {
    ($ty:ty, $file:expr, [$($key:literal),*]) => {
        $crate::shipped_defaults!($ty, $file, [$($key),*], deserialize_only);

        impl ::serde::Serialize for $ty {
            fn serialize<S: ::serde::Serializer>(&self, s: S) -> ::std::result::Result<S::Ok, S::Error> {
                <$ty>::serialize(self, s)
            }
        }
    };
    ($ty:ty, $file:expr, [$($key:literal),*], deserialize_only) => {
        impl ::std::default::Default for $ty {
            /// The section of the shipped file (see [`crate::config::Shipped`]).
            fn default() -> Self {
                static DEFAULT: ::std::sync::OnceLock<$ty> = ::std::sync::OnceLock::new();
                DEFAULT
                    .get_or_init(|| {
                        let path: &[&str] = &[$($key),*];
                        <$ty>::deserialize($file.section(path).clone()).unwrap_or_else(|e| {
                            panic!(
                                "the built-in {} section `{}` does not fit {}: {e}",
                                $file.name(),
                                path.join("."),
                                stringify!($ty)
                            )
                        })
                    })
                    .clone()
            }
        }

        impl<'de> ::serde::Deserialize<'de> for $ty {
            fn deserialize<D: ::serde::Deserializer<'de>>(d: D) -> ::std::result::Result<Self, D::Error> {
                let path: &[&str] = &[$($key),*];
                $crate::config::deserialize_over(d, path, &$file, |v| <$ty>::deserialize(v))
            }
        }
    };
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

    static RENAMED_FILE: Shipped = Shipped::with_renamed(
        "t.yaml",
        "speed_m_per_s: 0.5\ninner: {gain: 2.0}\n",
        &[
            Renamed {
                old: "speed",
                new: "speed_m_per_s",
                note: "",
            },
            Renamed {
                old: "inner.rate_hz",
                new: "",
                note: "the rate is the controller's dt",
            },
        ],
    );

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    #[serde(remote = "Self", deny_unknown_fields)]
    struct Inner {
        gain: f64,
    }
    crate::shipped_defaults!(Inner, RENAMED_FILE, ["inner"]);

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    #[serde(remote = "Self", deny_unknown_fields)]
    struct Outer {
        speed_m_per_s: f64,
        inner: Inner,
    }
    crate::shipped_defaults!(Outer, RENAMED_FILE, []);

    #[test]
    fn a_renamed_or_removed_key_is_refused_naming_its_replacement() {
        let d = Outer::default();
        assert_eq!((d.speed_m_per_s, d.inner.gain), (0.5, 2.0));
        let p: Outer = from_yaml_str("cfg.yaml", "inner: {gain: 3}\n").unwrap();
        assert_eq!((p.speed_m_per_s, p.inner.gain), (0.5, 3.0));
        let e = from_yaml_str::<Outer>("cfg.yaml", "speed: 0.2\n").unwrap_err();
        assert!(e.message.contains("`speed`: the key is now `speed_m_per_s`"), "{e}");
        let e = from_yaml_str::<Outer>("cfg.yaml", "inner: {rate_hz: 100}\n").unwrap_err();
        assert!(
            e.message
                .contains("`inner.rate_hz`: the key is gone (the rate is the controller's dt)"),
            "{e}"
        );
        // A key that was never there is still unknown, with the keys that exist.
        let e = from_yaml_str::<Outer>("cfg.yaml", "sped: 0.2\n").unwrap_err();
        assert!(
            e.message
                .contains("`sped`: unknown key (expected one of: speed_m_per_s, inner)"),
            "{e}"
        );
    }

    /// A node's file that does not ship the section `own`, read from its own file (as the
    /// controller node's `controller` is config/controller.yaml).
    static NODE_FILE: Shipped = Shipped::new("node.yaml", "rate_s: 1.0\n");

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    #[serde(remote = "Self", deny_unknown_fields)]
    struct Node {
        rate_s: f64,
        #[serde(default)]
        own: Outer,
    }
    crate::shipped_defaults!(Node, NODE_FILE, []);

    #[test]
    fn a_key_under_a_section_with_its_own_file_is_named_under_that_section() {
        let n: Node = from_yaml_str("node", "own: {inner: {gain: 4}}\n").unwrap();
        assert_eq!((n.rate_s, n.own.inner.gain, n.own.speed_m_per_s), (1.0, 4.0, 0.5));
        let e = from_yaml_str::<Node>("node", "own: {inner: {rate_hz: 100}}\n").unwrap_err();
        assert!(
            e.message
                .contains("`own.inner.rate_hz`: the key is gone (the rate is the controller's dt)"),
            "{e}"
        );
        let e = from_yaml_str::<Node>("node", "own: {speed: 1}\n").unwrap_err();
        assert!(e.message.contains("`own.speed`: the key is now `speed_m_per_s`"), "{e}");
        // A bad value there is no unknown key `own`.
        let e = from_yaml_str::<Node>("node", "own: {speed_m_per_s: fast}\n").unwrap_err();
        assert!(
            !e.message.contains("unknown key") && e.message.contains("invalid type"),
            "{e}"
        );
        let e = from_yaml_str::<Node>("node", "rate: 2\n").unwrap_err();
        assert!(
            e.message.contains("`rate`: unknown key (expected one of: rate_s)"),
            "{e}"
        );
    }
}
