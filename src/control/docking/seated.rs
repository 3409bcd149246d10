//! Completion for a scope seated in the port beside a biased trocar estimate.
//!
//! DONE normally needs the tip within `goal_tolerance_m` (1 mm) and `goal_angle_tolerance_deg`
//! (0.5°) of the goal on the *estimated* axis. A trocar estimate off by more than the port's
//! clearance (a hand-eye calibration 2 mm or 0.5° out is common) makes that unreachable: the
//! real port holds the shaft on the real axis, the controller yields to it, and the run would
//! stay in INSERT for ever with the scope in place.
//!
//! The seated test accepts that case, and only with evidence that the port is what holds the
//! tip off the estimated axis. For [`SeatedParams::settle_time_s`] without a break:
//! - the tip is at the goal depth, to within [`SeatedParams::depth_tolerance_m`];
//! - it is within [`SeatedParams::lateral_tolerance_m`] of the estimated axis;
//! - the optical axis is within [`SeatedParams::angle_tolerance_deg`] of it;
//! - the tip stays within [`SeatedParams::max_motion_m`] of where it was, relative to the
//!   estimated port, when the window began. A position range over the window, not a speed
//!   per step: the estimate comes at the camera's rate (15 Hz) with its latency while the port
//!   moves with breathing, so the tip seen from the estimated port jumps by a few tenths of a
//!   millimetre at each new pose even when it sits still in the real port;
//! - when [`SeatedParams::min_lateral_force_n`] is above 0, the measured force across the axis
//!   pushes the tip away from the estimated axis by at least that much.
//!
//! The controller pulls towards the estimated axis, and in free space closes a lateral gap of
//! millimetres in a few hundredths of a second; so a tip that stays still off the axis, at the
//! goal depth, for the settle time is held there by the port. With force feedback the scope
//! yields to the wall, so the force that holds it is small (the admittance stiffness times the
//! part of the offset the axis term asks back: about 0.1 N for 3 mm with the shipped gains),
//! below the force estimate's noise, and the shipped `min_lateral_force_n` is 0: stillness off
//! the axis at depth is the evidence.
//!
//! The DONE reason then says how far off the estimated axis the scope sat, so that the
//! surgeon knows the trocar estimate, most likely the hand-eye calibration, is biased.

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::control::docking::geometry::InsertionAxis;

/// Parameters of the seated test (`seated:` in `config/controller.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct SeatedParams {
    /// Largest distance of the tip from the estimated axis, m (0 = the test is off).
    pub lateral_tolerance_m: f64,
    /// Largest distance of the tip from the goal depth along the estimated axis, m.
    pub depth_tolerance_m: f64,
    /// Largest angle between the optical axis and the estimated axis, deg.
    pub angle_tolerance_deg: f64,
    /// Smallest force across the axis pushing the tip away from the estimated axis, N
    /// (0 = none needed; a force pulling towards the axis still vetoes).
    pub min_lateral_force_n: f64,
    /// Largest displacement of the tip relative to the estimated port over the window, m.
    pub max_motion_m: f64,
    /// How long all of it must hold without a break, s.
    pub settle_time_s: f64,
}

crate::shipped_defaults!(SeatedParams, crate::config::CONTROLLER, ["seated"]);

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
            "lateral_tolerance_m",
            self.lateral_tolerance_m,
            self.lateral_tolerance_m >= 0.0,
        )?;
        check(
            "angle_tolerance_deg",
            self.angle_tolerance_deg,
            self.angle_tolerance_deg > 0.0 && self.angle_tolerance_deg < 90.0,
        )?;
        check(
            "min_lateral_force_n",
            self.min_lateral_force_n,
            self.min_lateral_force_n >= 0.0,
        )?;
        check(
            "depth_tolerance_m",
            self.depth_tolerance_m,
            self.depth_tolerance_m > 0.0,
        )?;
        check("max_motion_m", self.max_motion_m, self.max_motion_m > 0.0)?;
        check("settle_time_s", self.settle_time_s, self.settle_time_s > 0.0)
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

impl std::fmt::Display for Seated {
    /// The DONE reason shown to the surgeon (formatted where it is shown, not in the loop).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
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
    /// The tip relative to the estimated port when the current window began.
    anchor: Option<Vector3<f64>>,
}

impl SeatedCheck {
    /// Forget the history (a new docking, or a phase other than INSERT).
    pub fn reset(&mut self) {
        *self = Self::default();
    }

    /// One INSERT step of `dt` s, the goal `goal_depth` past the port along `axis`: `Some`
    /// once every condition of the module doc has held for the settle time. Non-finite
    /// inputs break the run of good steps.
    pub fn update(
        &mut self,
        p: &SeatedParams,
        axis: &InsertionAxis,
        goal_depth: f64,
        s: &TipState,
        dt: f64,
    ) -> Option<Seated> {
        let offset_v = axis.lateral_offset(&s.tip);
        let depth = axis.depth_of(&s.tip);
        let offset = offset_v.norm();
        let angle_deg = axis.alignment_error(&s.optical_axis).to_degrees();
        let lateral_force = if offset > 0.0 {
            axis.across(&s.force).dot(&offset_v) / offset
        } else {
            0.0
        };
        let force_ok = p.min_lateral_force_n <= 0.0 || lateral_force >= p.min_lateral_force_n;
        let placed = p.lateral_tolerance_m > 0.0
            && (depth - goal_depth).abs() <= p.depth_tolerance_m
            && offset <= p.lateral_tolerance_m
            && angle_deg <= p.angle_tolerance_deg
            && force_ok
            && s.force.iter().all(|v| v.is_finite());
        if !placed {
            self.reset();
            return None;
        }
        // Relative to the port (which moves with breathing): seated means still in it.
        let rel = s.tip - axis.port;
        match self.anchor {
            Some(a) if (rel - a).norm() <= p.max_motion_m => self.held_for += dt,
            _ => {
                // A new window starts here.
                self.anchor = Some(rel);
                self.held_for = 0.0;
            }
        }
        (self.held_for >= p.settle_time_s - 1e-9).then_some(Seated {
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
        states.iter().map(|s| c.update(p, &axis(), 0.03, s, 0.01)).collect()
    }

    #[test]
    fn passes_after_the_settle_time_in_contact() {
        let p = SeatedParams::default();
        let out = run(&p, &vec![seated_tip(1.0); 60]);
        // The first step opens the window; then 50 steps of 10 ms.
        let first = out.iter().position(Option::is_some).unwrap();
        assert_eq!(first, 50);
        let s = out[first].unwrap();
        assert!((s.offset - 0.002).abs() < 1e-12);
        assert!(s.angle_deg < 1e-9);
        assert!(
            (s.lateral_force - 1.0).abs() < 1e-12,
            "the axial component does not count"
        );
        assert!(s.to_string().contains("2.0 mm"), "{s}");
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
            // `slide`: the tip also wobbles across the axis at 2 Hz, `slide` m of amplitude.
            let wobble = slide * (4.0 * std::f64::consts::PI * 0.01 * k as f64).sin();
            t.tip += shift + Vector3::x() * wobble;
            (axis, t)
        };
        let seated = (0..60).any(|k| {
            let (a, t) = moving(k, 0.0);
            c.update(&p, &a, 0.03, &t, 0.01).is_some()
        });
        assert!(seated, "still relative to the port");
        // A new pose at 15 Hz jumps the estimated port by 0.3 mm: still seated.
        let mut c = SeatedCheck::default();
        let seated = (0..60).any(|k| {
            let (a, mut t) = moving(k, 0.0);
            if (k / 7) % 2 == 1 {
                t.tip += Vector3::new(0.0002, 0.0, 0.0002);
            }
            c.update(&p, &a, 0.03, &t, 0.01).is_some()
        });
        assert!(seated, "still, seen from a jumpy estimate");
        // The tip wobbling in the port by 2 mm (while it moves): not seated.
        let mut c = SeatedCheck::default();
        let seated = (0..200).any(|k| {
            let (a, t) = moving(k, 0.002);
            c.update(&p, &a, 0.03, &t, 0.01).is_some()
        });
        assert!(!seated, "sliding in the port");
    }

    #[test]
    fn a_force_floor_applies_only_when_set() {
        // Shipped (no floor): still at depth off the axis suffices, whatever the small force.
        let p = SeatedParams::default();
        for fx in [0.0, -0.05, 0.1] {
            assert!(run(&p, &vec![seated_tip(fx); 60]).iter().any(Option::is_some), "{fx}");
        }
        // With a floor of 0.3 N: no force, too little force, or a force towards the axis
        // (the controller's own pull), never.
        let floor = SeatedParams {
            min_lateral_force_n: 0.3,
            ..p
        };
        for fx in [0.0, 0.2, -1.0] {
            assert!(
                run(&floor, &vec![seated_tip(fx); 200]).iter().all(Option::is_none),
                "{fx}"
            );
        }
        assert!(run(&floor, &vec![seated_tip(0.3); 60]).iter().any(Option::is_some));
    }

    #[test]
    fn each_condition_is_needed_and_a_break_restarts_the_clock() {
        let p = SeatedParams::default();
        let bad = [
            TipState {
                tip: Point3::new(0.002, 0.0, 0.0275), // 2.5 mm short of the goal depth
                ..seated_tip(1.0)
            },
            TipState {
                tip: Point3::new(0.0055, 0.0, 0.03), // 5.5 mm off the axis
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
        // Sliding in at 5 mm/s through the depth band: never still for the settle time.
        let moving: Vec<TipState> = (0..200)
            .map(|k| TipState {
                tip: Point3::new(0.002, 0.0, 0.0285 + 5e-5 * k as f64),
                ..seated_tip(1.0)
            })
            .collect();
        assert!(run(&p, &moving).iter().all(Option::is_none));
        // 40 good steps, one 2.5 mm short of the depth, then good again: the clock starts over.
        let mut states = vec![seated_tip(1.0); 40];
        states.push(TipState {
            tip: Point3::new(0.002, 0.0, 0.0275),
            ..seated_tip(1.0)
        });
        states.extend(vec![seated_tip(1.0); 60]);
        let first = run(&p, &states).iter().position(Option::is_some).unwrap();
        assert_eq!(
            first,
            41 + 50,
            "the window restarts at the first good step after the break"
        );
        // Off: never.
        let off = SeatedParams {
            lateral_tolerance_m: 0.0,
            ..p
        };
        assert!(run(&off, &vec![seated_tip(1.0); 200]).iter().all(Option::is_none));
    }

    #[test]
    fn bad_parameters_are_named() {
        let bad = SeatedParams {
            max_motion_m: f64::NAN,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().contains("max_motion_m"));
        assert!(SeatedParams::default().validate().is_ok());
        let neg = SeatedParams {
            lateral_tolerance_m: -1.0,
            ..Default::default()
        };
        assert!(neg.validate().unwrap_err().contains("lateral_tolerance_m"));
    }
}
