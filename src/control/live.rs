//! Live tuning: the parameters that may change while the controller runs, and when.
//!
//! A change is proposed off the control loop ([`propose`]: the names known, every value in
//! its range, the whole parameter set still valid) and applied by the loop between two steps
//! ([`LiveValues`] is `Copy`: no allocation, no lock). Each parameter has a [`Liveness`]:
//! - [`Liveness::Live`]: applied at the next step in every phase (the docking law's
//!   weights, the pivot's weights): the law re-solves with them; its commands stay within
//!   the motion limits and the guard whatever the weights.
//! - [`Liveness::LowerLive`]: a limit (the force stops, the speeds): lowering it is applied
//!   at once in every phase (a stop may then trigger: that is safe); raising it is refused
//!   while the scope may touch the patient (INSERT, DONE, RETRACT, HOLD, ABORTED), and
//!   applied in IDLE, TARE and APPROACH.
//! - [`Liveness::Idle`]: the admittance's mass, damping and stiffness shape the yield to the
//!   contact; a change mid-contact would change the response the surgeon is watching. They
//!   change only in IDLE (before a start: they apply from the next start).

use crate::config::Renamed;
use crate::control::supervisor::Phase;
use crate::control::ControllerParams;

/// When a parameter may change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Liveness {
    /// In every phase.
    Live,
    /// Lowered in every phase; raised only in IDLE, TARE and APPROACH.
    LowerLive,
    /// Only in IDLE (applies from the next start).
    Idle,
}

/// One tunable parameter: its name (as `dynamic_reconfigure` shows it), its key in
/// `config/controller.yaml`, its range and where it lives.
#[derive(Debug, Clone, Copy)]
pub struct LiveParam {
    /// Name (a valid ROS parameter name).
    pub name: &'static str,
    /// What it is, with its unit.
    pub description: &'static str,
    /// Smallest and largest value accepted.
    pub min: f64,
    /// See `min`.
    pub max: f64,
    /// When it may change.
    pub liveness: Liveness,
    get: fn(&ControllerParams) -> f64,
    set: fn(&mut ControllerParams, f64),
}

macro_rules! live {
    ($name:literal, $desc:literal, $min:expr, $max:expr, $live:ident, $($field:ident).+) => {
        LiveParam {
            name: $name,
            description: $desc,
            min: $min,
            max: $max,
            liveness: Liveness::$live,
            get: |p| p.$($field).+,
            set: |p, v| p.$($field).+ = v,
        }
    };
}

/// How many parameters are tunable.
pub const N_LIVE: usize = 22;

/// The tunable parameters. The ranges are those the controller is built for (the
/// validation of [`ControllerParams`] still runs on every change).
pub const LIVE_PARAMS: [LiveParam; N_LIVE] = [
    live!(
        "approach_w_axis",
        "APPROACH weight of the tip's distance from the axis (c1)",
        0.0,
        1e5,
        Live,
        approach_weights.axis
    ),
    live!(
        "approach_w_goal",
        "APPROACH weight of the tip's distance from the target (c2)",
        0.0,
        1e5,
        Live,
        approach_weights.goal
    ),
    live!(
        "approach_w_align",
        "APPROACH weight of the alignment with the axis (c3)",
        0.0,
        1e4,
        Live,
        approach_weights.align
    ),
    live!(
        "approach_w_step",
        "APPROACH weight of the joint step (c4)",
        1e-4,
        1e3,
        Live,
        approach_weights.step
    ),
    live!(
        "approach_w_reference",
        "APPROACH weight of the admittance reference (c5)",
        0.0,
        1e5,
        Live,
        approach_weights.reference
    ),
    live!(
        "insert_w_axis",
        "INSERT weight of the tip's distance from the axis (c1)",
        0.0,
        1e5,
        Live,
        insert_weights.axis
    ),
    live!(
        "insert_w_goal",
        "INSERT weight of the tip's distance from the target (c2)",
        0.0,
        1e5,
        Live,
        insert_weights.goal
    ),
    live!(
        "insert_w_align",
        "INSERT weight of the alignment with the axis (c3)",
        0.0,
        1e4,
        Live,
        insert_weights.align
    ),
    live!(
        "insert_w_step",
        "INSERT weight of the joint step (c4)",
        1e-4,
        1e3,
        Live,
        insert_weights.step
    ),
    live!(
        "insert_w_reference",
        "INSERT weight of the admittance reference (c5)",
        0.0,
        1e5,
        Live,
        insert_weights.reference
    ),
    live!(
        "approach_speed_m_s",
        "speed of the approach target point, m/s",
        0.005,
        0.1,
        LowerLive,
        approach_speed_m_s
    ),
    live!(
        "insert_speed_m_s",
        "speed of the insertion target point, m/s",
        0.001,
        0.05,
        LowerLive,
        insert_speed_m_s
    ),
    live!(
        "force_stop_n",
        "force stop: hold over this force estimate, N",
        1.0,
        60.0,
        LowerLive,
        guard.force_stop_n
    ),
    live!(
        "retract_force_stop_n",
        "retract's force stop, N (at most force_stop_n)",
        1.0,
        60.0,
        LowerLive,
        scope.retract_force_stop_n
    ),
    live!(
        "max_tip_speed_m_s",
        "the commanded tip's speed limit, m/s",
        0.005,
        0.25,
        LowerLive,
        motion.max_speed_m_s
    ),
    live!(
        "max_tip_angular_speed_rad_s",
        "the commanded tip's angular speed limit, rad/s",
        0.05,
        2.0,
        LowerLive,
        motion.max_angular_speed_rad_s
    ),
    live!(
        "admittance_mass_kg",
        "admittance mass, kg",
        0.01,
        10.0,
        Idle,
        admittance.mass_kg
    ),
    live!(
        "admittance_damping_ns_per_m",
        "admittance damping, N s/m",
        0.0,
        1000.0,
        Idle,
        admittance.damping_ns_per_m
    ),
    live!(
        "admittance_stiffness_n_per_m",
        "admittance stiffness, N/m",
        0.0,
        5000.0,
        Idle,
        admittance.stiffness_n_per_m
    ),
    live!(
        "pivot_rcm_weight",
        "after DONE: weight of the fulcrum's distance from the shaft, 1/m^2",
        1.0,
        1e5,
        Live,
        scope.rcm_weight
    ),
    live!(
        "pivot_max_angular_speed_rad_s",
        "after DONE: pan and tilt speed limit, rad/s",
        0.01,
        1.0,
        LowerLive,
        scope.max_angular_speed_rad_s
    ),
    live!(
        "pivot_max_zoom_speed_m_s",
        "after DONE: in and out speed limit, m/s",
        0.001,
        0.05,
        LowerLive,
        scope.max_zoom_speed_m_s
    ),
];

/// The tunable parameters renamed (each now named with its unit, as its key in
/// `config/controller.yaml`): a request with an old name is refused naming the new one.
pub const RENAMED: &[Renamed] = &[
    Renamed::key("approach_speed", "approach_speed_m_s"),
    Renamed::key("insert_speed", "insert_speed_m_s"),
    Renamed::key("force_stop", "force_stop_n"),
    Renamed::key("retract_force_stop", "retract_force_stop_n"),
    Renamed::key("max_tip_speed", "max_tip_speed_m_s"),
    Renamed::key("max_tip_angular_speed", "max_tip_angular_speed_rad_s"),
    Renamed::key("admittance_mass", "admittance_mass_kg"),
    Renamed::key("admittance_damping", "admittance_damping_ns_per_m"),
    Renamed::key("admittance_stiffness", "admittance_stiffness_n_per_m"),
    Renamed::key("pivot_max_angular_speed", "pivot_max_angular_speed_rad_s"),
    Renamed::key("pivot_max_zoom_speed", "pivot_max_zoom_speed_m_s"),
];

/// A value for every tunable parameter, in [`LIVE_PARAMS`] order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LiveValues(pub [f64; N_LIVE]);

impl LiveValues {
    /// The values of `p`.
    pub fn of(p: &ControllerParams) -> Self {
        Self(LIVE_PARAMS.map(|d| (d.get)(p)))
    }

    /// The value of the parameter `name`.
    pub fn value(&self, name: &str) -> Option<f64> {
        LIVE_PARAMS.iter().position(|d| d.name == name).map(|i| self.0[i])
    }

    /// Write the values into `p`.
    pub fn write_to(&self, p: &mut ControllerParams) {
        for (d, v) in LIVE_PARAMS.iter().zip(self.0) {
            (d.set)(p, v);
        }
    }
}

/// Whether the scope may be in the patient in `phase` (a raised limit is refused there).
fn in_contact(phase: Phase) -> bool {
    !matches!(phase, Phase::Idle | Phase::Tare | Phase::Approach)
}

/// Check the change from `old` to `new` in `phase` against each parameter's liveness;
/// `Err` names the first refused parameter and why. Allocates only to refuse.
pub fn check_phase(phase: Phase, old: &LiveValues, new: &LiveValues) -> Result<(), String> {
    for (d, (o, n)) in LIVE_PARAMS.iter().zip(old.0.iter().zip(new.0.iter())) {
        if o == n {
            continue;
        }
        match d.liveness {
            Liveness::Live => {}
            Liveness::LowerLive if n < o || !in_contact(phase) => {}
            Liveness::LowerLive => {
                return Err(format!(
                    "{} may only be lowered in {phase} ({o} -> {n}): raise a limit in IDLE, TARE or APPROACH",
                    d.name
                ));
            }
            Liveness::Idle if phase == Phase::Idle => {}
            Liveness::Idle => {
                return Err(format!(
                    "{} changes only in IDLE (now {phase}): the admittance shapes the yield to the contact",
                    d.name
                ));
            }
        }
    }
    Ok(())
}

/// The values after `changes` (name, value) to `current`: every name known, every value
/// finite and in its range, and `params` with them still valid.
pub fn propose(params: &ControllerParams, changes: &[(String, f64)]) -> Result<LiveValues, String> {
    let mut v = LiveValues::of(params);
    for (name, value) in changes {
        let i = LIVE_PARAMS.iter().position(|d| d.name == name).ok_or_else(|| {
            match RENAMED.iter().find(|r| r.old == name) {
                Some(r) => format!("{name} is not a tunable parameter: it is now {}", r.new),
                None => format!("{name} is not a tunable parameter"),
            }
        })?;
        let d = &LIVE_PARAMS[i];
        if !(value.is_finite() && (d.min..=d.max).contains(value)) {
            return Err(format!("{name} must be in [{}, {}], got {value}", d.min, d.max));
        }
        v.0[i] = *value;
    }
    let mut p = params.clone();
    v.write_to(&mut p);
    p.validate()?;
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shipped() -> ControllerParams {
        let text = include_str!("../../config/controller.yaml");
        ControllerParams::from_yaml_str(text).unwrap()
    }

    #[test]
    fn the_shipped_values_are_in_range_and_read_back() {
        let p = shipped();
        let v = LiveValues::of(&p);
        for (d, x) in LIVE_PARAMS.iter().zip(v.0) {
            assert!(
                (d.min..=d.max).contains(&x),
                "{} = {x} outside [{}, {}]",
                d.name,
                d.min,
                d.max
            );
        }
        assert_eq!(v.0[12], p.guard.force_stop_n);
        assert_eq!(v.0[17], p.admittance.damping_ns_per_m);
        let mut names: Vec<_> = LIVE_PARAMS.iter().map(|d| d.name).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), N_LIVE, "names are unique");
    }

    #[test]
    fn a_proposal_is_checked_by_name_range_and_validation() {
        let p = shipped();
        let v = propose(&p, &[("insert_speed_m_s".into(), 0.02)]).unwrap();
        let mut q = p.clone();
        v.write_to(&mut q);
        assert_eq!(q.insert_speed_m_s, 0.02);
        assert_eq!(q.guard.force_stop_n, p.guard.force_stop_n, "the others unchanged");
        let e = propose(&p, &[("gain".into(), 1.0)]).unwrap_err();
        assert!(e.contains("gain is not a tunable"), "{e}");
        let e = propose(&p, &[("insert_speed_m_s".into(), 0.5)]).unwrap_err();
        assert!(e.contains("insert_speed_m_s must be in"), "{e}");
        assert!(propose(&p, &[("force_stop_n".into(), f64::NAN)]).is_err());
        // An old name is refused naming the new one.
        let e = propose(&p, &[("force_stop".into(), 15.0)]).unwrap_err();
        assert!(
            e.contains("force_stop is not a tunable parameter: it is now force_stop_n"),
            "{e}"
        );
        // In range, but the whole set is invalid: the retract stop above the force stop.
        let e = propose(&p, &[("force_stop_n".into(), 5.0)]).unwrap_err();
        assert!(e.contains("retract_force_stop"), "{e}");
    }

    #[test]
    fn limits_rise_only_out_of_contact_and_the_admittance_only_in_idle() {
        let old = LiveValues::of(&shipped());
        let with = |i: usize, x: f64| {
            let mut v = old;
            v.0[i] = x;
            v
        };
        let force = LIVE_PARAMS.iter().position(|d| d.name == "force_stop_n").unwrap();
        let k = LIVE_PARAMS
            .iter()
            .position(|d| d.name == "admittance_stiffness_n_per_m")
            .unwrap();
        let w = LIVE_PARAMS.iter().position(|d| d.name == "insert_w_axis").unwrap();
        for phase in [Phase::Insert, Phase::Done, Phase::Retract, Phase::Hold, Phase::Aborted] {
            assert!(
                check_phase(phase, &old, &with(force, 10.0)).is_ok(),
                "lowering in {phase}"
            );
            let e = check_phase(phase, &old, &with(force, 30.0)).unwrap_err();
            assert!(e.contains("force_stop_n may only be lowered"), "{e}");
            assert!(
                check_phase(phase, &old, &with(k, 50.0)).is_err(),
                "admittance in {phase}"
            );
            assert!(check_phase(phase, &old, &with(w, 10.0)).is_ok(), "a weight in {phase}");
        }
        for phase in [Phase::Idle, Phase::Tare, Phase::Approach] {
            assert!(
                check_phase(phase, &old, &with(force, 30.0)).is_ok(),
                "raising in {phase}"
            );
        }
        assert!(check_phase(Phase::Idle, &old, &with(k, 50.0)).is_ok());
        assert!(check_phase(Phase::Approach, &old, &with(k, 50.0)).is_err());
        assert!(check_phase(Phase::Done, &old, &old).is_ok(), "no change");
    }
}
