//! Completion for a scope seated in the port beside a biased trocar estimate.
//!
//! DONE normally needs the tip within `goal_tolerance` (1 mm) and `goal_angle_tolerance_deg`
//! (0.5°) of the goal on the *estimated* axis. A trocar estimate off by more than the port's
//! clearance (a hand-eye calibration 2 mm or 0.5° out is common) makes that unreachable: the
//! real port holds the shaft on the real axis, the controller yields to it, and the run would
//! stay in INSERT for ever with the scope in place.
//!
//! The seated test accepts that case, and only with evidence that the port is what holds the
//! tip off the estimated axis. For [`SeatedParams::settle_time`] without a break:
//! - the tip is at the goal depth, to within `goal_tolerance`;
//! - it is within [`SeatedParams::lateral_tolerance`] of the estimated axis;
//! - the optical axis is within [`SeatedParams::angle_tolerance_deg`] of it;
//! - the tip moves slower than [`SeatedParams::max_speed`];
//! - the measured force across the axis pushes the tip *away* from the estimated axis by at
//!   least [`SeatedParams::min_lateral_force`]. The controller pulls towards that axis, so
//!   only a wall can push back that way. Without contact a tip off the axis means that the
//!   controller has not converged, and the normal test applies.
//!
//! The DONE reason then says how far off the estimated axis the scope sat, so that the
//! surgeon knows the trocar estimate, most likely the hand-eye calibration, is biased.

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::control::geometry::InsertionAxis;

/// Parameters of the seated test (`seated:` in `config/controller.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SeatedParams {
    /// Largest distance of the tip from the estimated axis, m (0 = the test is off).
    pub lateral_tolerance: f64,
    /// Largest angle between the optical axis and the estimated axis, deg.
    pub angle_tolerance_deg: f64,
    /// Smallest force across the axis pushing the tip away from the estimated axis, N.
    pub min_lateral_force: f64,
    /// Largest tip speed, m/s.
    pub max_speed: f64,
    /// How long all of it must hold without a break, s.
    pub settle_time: f64,
}

impl Default for SeatedParams {
    fn default() -> Self {
        Self {
            lateral_tolerance: 0.003,
            angle_tolerance_deg: 2.0,
            min_lateral_force: 0.3,
            max_speed: 0.002,
            settle_time: 0.5,
        }
    }
}

impl SeatedParams {
    /// Check ranges; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        let check = |name: &str, v: f64, ok: bool| {
            if v.is_finite() && ok {
                Ok(())
            } else {
                Err(format!("seated.{name} out of range: {v}"))
            }
        };
        check(
            "lateral_tolerance",
            self.lateral_tolerance,
            self.lateral_tolerance >= 0.0,
        )?;
        check(
            "angle_tolerance_deg",
            self.angle_tolerance_deg,
            self.angle_tolerance_deg > 0.0 && self.angle_tolerance_deg < 90.0,
        )?;
        check(
            "min_lateral_force",
            self.min_lateral_force,
            self.min_lateral_force > 0.0,
        )?;
        check("max_speed", self.max_speed, self.max_speed > 0.0)?;
        check("settle_time", self.settle_time, self.settle_time > 0.0)
    }
}

/// One step's view of the tip, for [`SeatedCheck::update`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TipState {
    /// Tip position (from the measured joints), base frame.
    pub tip: Point3<f64>,
    /// Optical axis, unit, base frame.
    pub optical_axis: Vector3<f64>,
    /// Force estimate on the tip, base frame, N.
    pub force: Vector3<f64>,
}

/// How the scope sat when the seated test passed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Seated {
    /// Distance of the tip from the estimated axis, m.
    pub offset: f64,
    /// Angle of the optical axis to the estimated axis, deg.
    pub angle_deg: f64,
    /// Force across the axis pushing the tip away from it, N.
    pub lateral_force: f64,
}

impl Seated {
    /// The DONE reason shown to the surgeon.
    pub fn describe(&self) -> String {
        format!(
            "docked {:.1} mm and {:.1} deg off the estimated axis, held there by the port ({:.1} N across the axis): the trocar estimate is biased; check the hand-eye calibration",
            self.offset * 1e3,
            self.angle_deg,
            self.lateral_force
        )
    }
}

/// The seated test's state: how long its conditions have held.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SeatedCheck {
    held_for: f64,
    /// The tip's last position relative to the axis: depth and lateral offset.
    last_tip: Option<(f64, Vector3<f64>)>,
}

impl SeatedCheck {
    /// Forget the history (a new docking, or a phase other than INSERT).
    pub fn reset(&mut self) {
        *self = Self::default();
    }

    /// One INSERT step of `dt` s, the goal `goal_depth` past the port along `axis` with
    /// depth tolerance `depth_tolerance`: `Some` once every condition of the module doc has
    /// held for the settle time. Non-finite inputs break the run of good steps.
    pub fn update(
        &mut self,
        p: &SeatedParams,
        axis: &InsertionAxis,
        goal_depth: f64,
        depth_tolerance: f64,
        s: &TipState,
        dt: f64,
    ) -> Option<Seated> {
        // Speed relative to the port, which moves with breathing: seated means still in it.
        let offset_v = axis.lateral_offset(&s.tip);
        let depth = axis.depth_of(&s.tip);
        let speed = match self.last_tip {
            Some((d, o)) if dt > 0.0 => ((depth - d).powi(2) + (offset_v - o).norm_squared()).sqrt() / dt,
            _ => f64::INFINITY,
        };
        self.last_tip = Some((depth, offset_v));
        let offset = offset_v.norm();
        let angle_deg = axis.alignment_error(&s.optical_axis).to_degrees();
        let lateral_force = if offset > 0.0 {
            axis.across(&s.force).dot(&offset_v) / offset
        } else {
            0.0
        };
        let ok = p.lateral_tolerance > 0.0
            && (depth - goal_depth).abs() < depth_tolerance
            && offset <= p.lateral_tolerance
            && angle_deg <= p.angle_tolerance_deg
            && speed <= p.max_speed
            && lateral_force >= p.min_lateral_force;
        if !ok {
            self.held_for = 0.0;
            return None;
        }
        self.held_for += dt;
        (self.held_for >= p.settle_time - 1e-9).then_some(Seated {
            offset,
            angle_deg,
            lateral_force,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    /// The estimated axis: through the origin along +z.
    fn axis() -> InsertionAxis {
        InsertionAxis::from_pose(&Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::identity(),
        ))
    }

    /// The tip 30 mm deep, 2 mm off the axis along +x, still, with `fx` N along +x.
    fn seated_tip(fx: f64) -> TipState {
        TipState {
            tip: Point3::new(0.002, 0.0, 0.03),
            optical_axis: Vector3::z(),
            force: Vector3::new(fx, 0.0, -1.0),
        }
    }

    fn run(p: &SeatedParams, states: &[TipState]) -> Vec<Option<Seated>> {
        let mut c = SeatedCheck::default();
        states
            .iter()
            .map(|s| c.update(p, &axis(), 0.03, 0.001, s, 0.01))
            .collect()
    }

    #[test]
    fn passes_after_the_settle_time_in_contact() {
        let p = SeatedParams::default();
        let out = run(&p, &vec![seated_tip(1.0); 60]);
        // The first step has no speed yet; then 50 steps of 10 ms.
        let first = out.iter().position(Option::is_some).unwrap();
        assert_eq!(first, 50);
        let s = out[first].unwrap();
        assert!((s.offset - 0.002).abs() < 1e-12);
        assert!(s.angle_deg < 1e-9);
        assert!(
            (s.lateral_force - 1.0).abs() < 1e-12,
            "the axial component does not count"
        );
        assert!(s.describe().contains("2.0 mm"), "{}", s.describe());
    }

    #[test]
    fn a_tip_still_in_a_breathing_port_is_seated_and_one_sliding_in_it_is_not() {
        let p = SeatedParams::default();
        // The port moves 6 mm/s along its axis (breathing), the tip with it: seated.
        let mut c = SeatedCheck::default();
        let moving = |k: usize, slide: f64| {
            let shift = Vector3::z() * (0.006 * 0.01 * k as f64);
            let axis = InsertionAxis::from_pose(&Isometry3::from_parts(
                Translation3::from(shift),
                UnitQuaternion::identity(),
            ));
            let mut t = seated_tip(1.0);
            // `slide`: the tip also wobbles across the axis, 0.5 mm at 2 Hz (6 mm/s).
            let wobble = slide * (4.0 * std::f64::consts::PI * 0.01 * k as f64).sin();
            t.tip += shift + Vector3::x() * wobble;
            (axis, t)
        };
        let seated = (0..60).any(|k| {
            let (a, t) = moving(k, 0.0);
            c.update(&p, &a, 0.03, 0.001, &t, 0.01).is_some()
        });
        assert!(seated, "still relative to the port");
        // The tip wobbling in the port (while it moves): not seated.
        let mut c = SeatedCheck::default();
        let seated = (0..200).any(|k| {
            let (a, t) = moving(k, 0.0005);
            c.update(&p, &a, 0.03, 0.001, &t, 0.01).is_some()
        });
        assert!(!seated, "sliding in the port");
    }

    #[test]
    fn needs_a_wall_pushing_away_from_the_estimated_axis() {
        let p = SeatedParams::default();
        // No force, too little force, or a force towards the axis (the controller's own
        // pull, or a tip not yet converged): never.
        for fx in [0.0, 0.2, -1.0] {
            assert!(run(&p, &vec![seated_tip(fx); 200]).iter().all(Option::is_none), "{fx}");
        }
    }

    #[test]
    fn each_condition_is_needed_and_a_break_restarts_the_clock() {
        let p = SeatedParams::default();
        let bad = [
            TipState {
                tip: Point3::new(0.002, 0.0, 0.025), // 5 mm short of the goal depth
                ..seated_tip(1.0)
            },
            TipState {
                tip: Point3::new(0.004, 0.0, 0.03), // 4 mm off the axis
                ..seated_tip(1.0)
            },
            TipState {
                optical_axis: Vector3::new(0.1, 0.0, 1.0).normalize(), // 5.7 deg
                ..seated_tip(1.0)
            },
            TipState {
                force: Vector3::new(f64::NAN, 0.0, 0.0),
                ..seated_tip(1.0)
            },
        ];
        for b in bad {
            assert!(run(&p, &vec![b; 200]).iter().all(Option::is_none), "{b:?}");
        }
        // Moving at 5 mm/s along the axis: never still.
        let moving: Vec<TipState> = (0..200)
            .map(|k| TipState {
                tip: Point3::new(0.002, 0.0, 0.0295 + 5e-5 * (k % 20) as f64),
                ..seated_tip(1.0)
            })
            .collect();
        assert!(run(&p, &moving).iter().all(Option::is_none));
        // 40 good steps, one without force, then good again: the clock starts over.
        let mut states = vec![seated_tip(1.0); 40];
        states.push(seated_tip(0.0));
        states.extend(vec![seated_tip(1.0); 60]);
        let first = run(&p, &states).iter().position(Option::is_some).unwrap();
        assert_eq!(first, 41 + 49);
        // Off: never.
        let off = SeatedParams {
            lateral_tolerance: 0.0,
            ..p
        };
        assert!(run(&off, &vec![seated_tip(1.0); 200]).iter().all(Option::is_none));
    }

    #[test]
    fn bad_parameters_are_named() {
        let bad = SeatedParams {
            max_speed: f64::NAN,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().contains("max_speed"));
        assert!(SeatedParams::default().validate().is_ok());
        let neg = SeatedParams {
            lateral_tolerance: -1.0,
            ..Default::default()
        };
        assert!(neg.validate().unwrap_err().contains("lateral_tolerance"));
    }
}
