//! A jammed shaft: a stiff obstacle that catches the scope's tip and holds it where it was
//! caught (a bone, a staple line, another instrument closing on it), so that any motion of
//! the tip, across the shaft (a pan) or along it (a retract), meets a stiff spring. A
//! fault the tests inject ([`super::SimWorld::set_jam`]), not part of a world's
//! parameters.
//!
//! With A the point where the tip was caught (base frame), e the tip and v its velocity,
//! the force on the shaft at the tip is
//! ```text
//! f = -k (e - A) - c v
//! ```
//! isotropic: the obstacle grips the tip in every direction. It acts on the arm alone (the
//! obstacle is fixed in the base frame, not part of the trocar), at the tip, so its moment
//! about the tip is zero, and its stiffness against the tip's motion is k on the linear
//! block, integrated implicitly with the joints' deflection like the trocar contact's
//! ([`super::contact`]).

use nalgebra::{Matrix3, Point3, Vector3};

use super::contact::ContactWrench;
use super::{check_range, SimError};

/// A stiff obstacle holding the tip at `anchor`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Jam {
    /// Where the tip was caught, base frame, m.
    pub anchor: Point3<f64>,
    /// Stiffness, N/m.
    pub stiffness_n_per_m: f64,
    /// Damping, N s/m.
    pub damping_ns_per_m: f64,
}

impl Jam {
    /// A jam catching the tip at `anchor`, checked (stiffness in (0, 1e7] N/m, damping in
    /// [0, 1e4] N s/m).
    pub fn new(anchor: Point3<f64>, stiffness_n_per_m: f64, damping_ns_per_m: f64) -> Result<Self, SimError> {
        check_range("jam.stiffness_n_per_m", stiffness_n_per_m, 1e-9, 1e7)?;
        check_range("jam.damping_ns_per_m", damping_ns_per_m, 0.0, 1e4)?;
        if !anchor.coords.iter().all(|x| x.is_finite()) {
            return Err(SimError::Input("jam anchor not finite".into()));
        }
        Ok(Self {
            anchor,
            stiffness_n_per_m,
            damping_ns_per_m,
        })
    }

    /// The force on the shaft at the tip `e` moving at `v` (module doc), N.
    pub fn force(&self, e: &Point3<f64>, v: &Vector3<f64>) -> Vector3<f64> {
        -(e - self.anchor) * self.stiffness_n_per_m - v * self.damping_ns_per_m
    }

    /// Add the jam's force at the tip `e` (moving at `v`) and its stiffness to `w`, the
    /// wrench on the arm.
    pub fn add_to(&self, w: &mut ContactWrench, e: &Point3<f64>, v: &Vector3<f64>) {
        w.force += self.force(e, v);
        let k = Matrix3::identity() * self.stiffness_n_per_m;
        let mut block = w.stiffness.fixed_view_mut::<3, 3>(0, 0);
        block += k;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_jam_pulls_the_tip_back_to_where_it_was_caught() {
        let jam = Jam::new(Point3::new(0.1, 0.0, 0.3), 5000.0, 0.0).unwrap();
        let f = jam.force(&Point3::new(0.1, 0.002, 0.299), &Vector3::zeros());
        assert!((f - Vector3::new(0.0, -10.0, 5.0)).norm() < 1e-9, "{f}");
        let mut w = ContactWrench::default();
        jam.add_to(&mut w, &Point3::new(0.1, 0.002, 0.3), &Vector3::new(0.0, 0.0, 0.0));
        assert!((w.force.y + 10.0).abs() < 1e-9 && w.moment.norm() == 0.0);
        assert_eq!(w.stiffness[(1, 1)], 5000.0);
        assert_eq!(w.stiffness[(4, 4)], 0.0);
        assert!(Jam::new(Point3::origin(), -1.0, 0.0).is_err());
        assert!(Jam::new(Point3::new(f64::NAN, 0.0, 0.0), 1.0, 0.0).is_err());
    }
}
