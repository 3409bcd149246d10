//! Force feedback: the tip force estimate from external joint torques, and the admittance
//! law that turns it into the reference r the controller's c5 term pulls the tip towards.
//!
//! **Force estimate** (the paper's f_ext = J_lin(q)^{-T} tau_ext): each joint torque first
//! passes a dead-band (the LBR's torque estimate is not zero at rest), then
//! f = (J J^T + λ² I)^{-1} J tau, the damped least-squares solution of J^T f = tau, which
//! stays bounded near singular configurations; then a first-order low-pass filter.
//!
//! **Admittance** (a virtual mass-spring-damper driven by the force *across* the insertion
//! axis): M ẍ + D ẋ + K x = f_⊥, integrated semi-implicitly; r = e(q) + x, the current tip
//! displaced by the compliance. Only the lateral force drives it, so the tip yields sideways
//! to contact while the insertion keeps progressing along the axis; the axial force instead
//! slows the insertion (see [`AdmittanceParams::axial_force_full_stop_n`]) and the safety guard
//! stops on a force above its threshold.

use nalgebra::{Matrix3, Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::kinematics::{Jacobian, JointVector};
use crate::validate;

/// Parameters of the force estimate and the admittance law.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct AdmittanceParams {
    /// Per-joint torque dead-band, Nm.
    pub torque_deadband_nm: f64,
    /// Damping λ of the pseudo-inverse, m (units of the Jacobian's linear rows).
    pub pinv_damping: f64,
    /// Cut-off of the force low-pass filter, Hz (0 = no filter).
    pub filter_cutoff_hz: f64,
    /// Forces below this norm are ignored by the admittance, N.
    pub force_deadband_n: f64,
    /// Virtual mass, kg.
    pub mass_kg: f64,
    /// Virtual damping, N s/m.
    pub damping_ns_per_m: f64,
    /// Virtual stiffness, N/m.
    pub stiffness_n_per_m: f64,
    /// Largest displacement of r from the tip, m.
    pub max_displacement_m: f64,
    /// Axial force (resisting insertion) at which insertion stops advancing, N; the advance
    /// speed falls linearly from full at 0 N to [`Self::min_insert_speed_ratio`] here.
    pub axial_force_full_stop_n: f64,
    /// Fraction of the insertion speed kept at the largest axial force, so insertion never
    /// stalls while yielding (0..1).
    pub min_insert_speed_ratio: f64,
}

crate::shipped_defaults!(AdmittanceParams, crate::config::CONTROLLER, ["admittance"]);

impl AdmittanceParams {
    /// Check ranges; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        validate::non_negative("admittance.torque_deadband_nm", self.torque_deadband_nm)?;
        validate::positive("admittance.pinv_damping", self.pinv_damping)?;
        validate::non_negative("admittance.filter_cutoff_hz", self.filter_cutoff_hz)?;
        validate::non_negative("admittance.force_deadband_n", self.force_deadband_n)?;
        validate::positive("admittance.mass_kg", self.mass_kg)?;
        validate::non_negative("admittance.damping_ns_per_m", self.damping_ns_per_m)?;
        validate::non_negative("admittance.stiffness_n_per_m", self.stiffness_n_per_m)?;
        validate::positive("admittance.max_displacement_m", self.max_displacement_m)?;
        validate::positive("admittance.axial_force_full_stop_n", self.axial_force_full_stop_n)?;
        validate::in_range(
            "admittance.min_insert_speed_ratio",
            self.min_insert_speed_ratio,
            0.0,
            1.0,
        )?;
        Ok(())
    }
}

pub use crate::signal::deadband;
use crate::signal::rc_smoothing;

/// f = (J J^T + λ² I)^{-1} J tau for the linear rows of `jac`; `None` when the inputs are
/// not finite.
pub fn tip_force(jac: &Jacobian, tau: &JointVector, deadband_nm: f64, damping: f64) -> Option<Vector3<f64>> {
    if !tau.iter().all(|t| t.is_finite()) || !jac.iter().all(|j| j.is_finite()) {
        return None;
    }
    let tau_db = tau.map(|t| deadband(t, deadband_nm));
    let jl = jac.fixed_rows::<3>(0);
    let a: Matrix3<f64> = jl * jl.transpose() + Matrix3::identity() * damping * damping;
    let f = a.cholesky()?.solve(&(jl * tau_db));
    f.iter().all(|x| x.is_finite()).then_some(f)
}

/// The force estimate and admittance state of one run (the law's parameters are passed
/// in, so that a new run is `Admittance::default()`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Admittance {
    force: Vector3<f64>,
    x: Vector3<f64>,
    v: Vector3<f64>,
}

impl Admittance {
    /// Feed a torque measurement (already known finite) and update the filtered force.
    /// Returns the filtered force; a non-finite estimate leaves the filter unchanged.
    pub fn update_force(&mut self, p: &AdmittanceParams, jac: &Jacobian, tau: &JointVector, dt: f64) -> Vector3<f64> {
        if let Some(f) = tip_force(jac, tau, p.torque_deadband_nm, p.pinv_damping) {
            self.force += (f - self.force) * rc_smoothing(p.filter_cutoff_hz, dt);
        }
        self.force
    }

    /// The filtered force estimate, N.
    pub fn force(&self) -> Vector3<f64> {
        self.force
    }

    /// Advance the admittance by `dt` driven by the filtered force across the axis and
    /// return the displacement x of the reference from the tip.
    pub fn step(&mut self, p: &AdmittanceParams, lateral_force: Vector3<f64>, dt: f64) -> Vector3<f64> {
        let n = lateral_force.norm();
        let f = if n > p.force_deadband_n && n.is_finite() {
            lateral_force * ((n - p.force_deadband_n) / n)
        } else {
            Vector3::zeros()
        };
        if dt > 0.0 && dt.is_finite() {
            // Semi-implicit Euler; stable for dt * (D / M) well beyond our rates.
            let a = (f - self.v * p.damping_ns_per_m - self.x * p.stiffness_n_per_m) / p.mass_kg;
            self.v += a * dt;
            self.x += self.v * dt;
            let xn = self.x.norm();
            if xn > p.max_displacement_m {
                self.x *= p.max_displacement_m / xn;
                self.v = Vector3::zeros();
            }
        }
        self.x
    }

    /// The reference r = tip + x.
    pub fn reference(&self, tip: &Point3<f64>) -> Point3<f64> {
        tip + self.x
    }
}

impl AdmittanceParams {
    /// Insertion speed ratio for an axial force `f_axial_resisting` (N, positive when the
    /// force pushes the tip back out of the trocar).
    pub fn insert_speed_ratio(&self, f_axial_resisting: f64) -> f64 {
        if !f_axial_resisting.is_finite() {
            return self.min_insert_speed_ratio;
        }
        let f = f_axial_resisting.max(0.0);
        (1.0 - f / self.axial_force_full_stop_n).clamp(self.min_insert_speed_ratio, 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::lbr::{LbrModel, ToolParams};
    use crate::kinematics::{Kinematics, LbrKinematics};

    #[test]
    fn force_recovered_from_torques() {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let q = JointVector::from_column_slice(&[0.1, 0.6, -0.1, -1.2, 0.2, 0.9, 0.0]);
        let (_, j) = kin.fk_jacobian(&q).unwrap();
        let f = Vector3::new(3.0, -2.0, 5.0);
        let tau = j.fixed_rows::<3>(0).transpose() * f;
        let est = tip_force(&j, &tau, 0.0, 1e-4).unwrap();
        assert!((est - f).norm() < 1e-3, "{est:?}");
        // A damped inverse shrinks, never amplifies.
        let damped = tip_force(&j, &tau, 0.0, 0.2).unwrap();
        assert!(damped.norm() < f.norm());
        // Dead-band removes small torques entirely.
        assert_eq!(tip_force(&j, &(tau * 1e-3), 1.0, 0.02).unwrap(), Vector3::zeros());
        let mut bad = tau;
        bad[2] = f64::NAN;
        assert!(tip_force(&j, &bad, 0.0, 0.02).is_none());
    }

    #[test]
    fn deadband_shape() {
        assert_eq!(deadband(0.5, 1.0), 0.0);
        assert_eq!(deadband(3.0, 1.0), 2.0);
        assert_eq!(deadband(-3.0, 1.0), -2.0);
    }

    #[test]
    fn admittance_settles_at_force_over_stiffness() {
        let p = AdmittanceParams {
            force_deadband_n: 0.0,
            ..Default::default()
        };
        let k = p.stiffness_n_per_m;
        let mut a = Admittance::default();
        let f = Vector3::new(1.0, 0.0, -0.5);
        // The slow pole is about k / D: settle over many of its time constants.
        for _ in 0..20000 {
            a.step(&p, f, 0.001);
        }
        assert!((a.step(&p, f, 0.001) - f / k).norm() < 1e-6);
        // Saturates at the largest displacement.
        let big = Vector3::new(1e4, 0.0, 0.0);
        for _ in 0..100 {
            a.step(&p, big, 0.01);
        }
        assert!(a.step(&p, big, 0.01).norm() <= p.max_displacement_m + 1e-12);
        a = Admittance::default();
        assert_eq!(a.step(&p, Vector3::zeros(), 0.01), Vector3::zeros());
    }

    #[test]
    fn insertion_slows_but_never_stops() {
        let a = AdmittanceParams::default();
        assert_eq!(a.insert_speed_ratio(-3.0), 1.0);
        assert!(a.insert_speed_ratio(2.5) < 1.0);
        assert_eq!(a.insert_speed_ratio(100.0), a.min_insert_speed_ratio);
        assert_eq!(a.insert_speed_ratio(f64::NAN), a.min_insert_speed_ratio);
        assert!(AdmittanceParams {
            mass_kg: 0.0,
            ..Default::default()
        }
        .validate()
        .is_err());
    }
}
