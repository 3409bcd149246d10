//! The shaft's whole wrench at the tip from the external joint torques, and its low-pass:
//! the force the fulcrum's adaptation reads ([`crate::control::scope::fulcrum`]). Using all
//! six rows of the Jacobian, a moment on the shaft (the trocar's tilt spring, transmitted as
//! a couple across its bore) is not read as a force, as it is by the docking's estimate from
//! the linear rows alone ([`crate::control::force::admittance::tip_force`]).
//!
//! Nothing here allocates.

use nalgebra::{Matrix6, Vector3, Vector6};

use crate::kinematics::{Jacobian, JointVector};
use crate::signal::rc_smoothing;

/// The wrench on the shaft at the tip (force, moment about the tip; base frame) from the
/// external joint torques `tau`: (J J^T + λ² I)^{-1} J tau with all six rows of `jac`.
/// `None` when the inputs are not finite or the system is singular.
pub fn shaft_wrench(jac: &Jacobian, tau: &JointVector, damping: f64) -> Option<(Vector3<f64>, Vector3<f64>)> {
    if !(tau.iter().chain(jac.iter()).all(|x| x.is_finite()) && damping.is_finite()) {
        return None;
    }
    let a: Matrix6<f64> = jac * jac.transpose() + Matrix6::identity() * (damping * damping);
    let w: Vector6<f64> = a.cholesky()?.solve(&(jac * tau));
    w.iter()
        .all(|x| x.is_finite())
        .then(|| (w.fixed_rows::<3>(0).into_owned(), w.fixed_rows::<3>(3).into_owned()))
}

/// A first-order low-pass of the shaft's force at `cutoff_hz` ([`rc_smoothing`]; 0: none).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ForceFilter {
    force: Option<Vector3<f64>>,
}

impl ForceFilter {
    /// Feed the force of one step of `dt`; returns the filtered force.
    pub fn update(&mut self, f: &Vector3<f64>, cutoff_hz: f64, dt: f64) -> Vector3<f64> {
        let out = self.force.map_or(*f, |x| x + (f - x) * rc_smoothing(cutoff_hz, dt));
        self.force = Some(out);
        out
    }

    /// The filtered force (zero before the first).
    pub fn force(&self) -> Vector3<f64> {
        self.force.unwrap_or_else(Vector3::zeros)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_moment_is_not_read_as_a_force() {
        use crate::kinematics::lbr::{LbrModel, ToolParams};
        use crate::kinematics::{Kinematics, LbrKinematics};
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let q = JointVector::from_column_slice(&[0.1, 0.6, -0.1, -1.2, 0.2, 0.9, 0.3]);
        let (_, jac) = kin.fk_jacobian(&q).unwrap();
        let (f, m) = (Vector3::new(0.5, -0.3, 0.2), Vector3::new(0.0, 0.6, -0.1));
        let w = Vector6::new(f.x, f.y, f.z, m.x, m.y, m.z);
        let tau = jac.transpose() * w;
        let (fe, me) = shaft_wrench(&jac, &tau, 1e-4).unwrap();
        assert!((fe - f).norm() < 1e-6 && (me - m).norm() < 1e-6, "{fe} {me}");
        // The linear rows alone read the moment as a force of the same order.
        let lin = crate::control::force::admittance::tip_force(&jac, &tau, 0.0, 1e-4).unwrap();
        assert!((lin - f).norm() > 0.1, "{lin}");
        assert!(shaft_wrench(&jac, &tau.map(|_| f64::NAN), 0.02).is_none());
        let mut filt = ForceFilter::default();
        assert_eq!(filt.update(&f, 20.0, 0.01), f, "the first sample passes");
        let g = filt.update(&Vector3::zeros(), 20.0, 0.01);
        assert!((g - f * (1.0 - rc_smoothing(20.0, 0.01))).norm() < 1e-15, "the RC rule");
        assert!(g.norm() < f.norm() && g.norm() > 0.0);
        assert_eq!(filt.force(), g);
        assert_eq!(ForceFilter::default().force(), Vector3::zeros());
    }
}
