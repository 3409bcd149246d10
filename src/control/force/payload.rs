//! The pose-dependent part of the torques' offset: a payload the load data gets wrong.
//!
//! The LBR subtracts the gravity of the tool it was told about; a camera mount weighed by
//! hand or a cable left out leaves a mass error dm at some point r of the tool (tip frame),
//! whose gravity reads as external torque: g(q) = J_v^T (dm g0) + J_w^T ((R r) x dm g0). The
//! tare ([`crate::control::force::tare`]) removes the offset at the poses it sees out of contact, but the
//! offset changes as the scope then pivots about the port (tens of degrees after docking),
//! and that change reads as a force across the shaft (0.5 N and more for 0.15 kg at 0.2 m).
//!
//! g(q) is linear in θ = [dm; s], s = dm r: g(q) = G(q) θ with
//! G = [J_v^T g0, -J_w^T [g0]x R] (7 x 4). While the tare tracks the offset out of contact,
//! every sample also feeds a least-squares fit of τ = b + G(q) θ (b the constant offsets),
//! with a zero-mean prior on θ (`payload_prior_kg`, and the same times 0.3 m for s): where
//! the poses seen do not excite θ, the prior keeps it near zero and nothing changes. After
//! the last tracked sample the correction is G(q) θ - G(q_last) θ: zero where the tare last
//! saw the torques, the payload's change of gravity elsewhere.
//!
//! Fixed-size matrices throughout: nothing here allocates.

use nalgebra::{SMatrix, SVector, UnitQuaternion, Vector3, Vector4};

use crate::kinematics::{Jacobian, JointVector};

/// Gravity, base frame (z up), m/s^2.
const GRAVITY: Vector3<f64> = Vector3::new(0.0, 0.0, -9.81);

/// The lever of the prior on s = dm r: the payload sits within this of the tip's frame
/// origin per axis (the tool is 0.25 m long), m.
const PRIOR_LEVER_M: f64 = 0.3;

/// The torques' error per sample that the fit expects (the low-passed noise and what the
/// model leaves out), Nm, and the time over which it stays correlated, s: each sample of
/// `dt` weighs dt / (σ² T).
const SAMPLE_SIGMA_NM: f64 = 0.2;
const SAMPLE_CORRELATION_S: f64 = 0.1;

/// The regressor G(q) of θ = [dm; s] at the tip's Jacobian `jac` (base frame, linear rows
/// at the tip) and orientation `rot`.
pub fn regressor(jac: &Jacobian, rot: &UnitQuaternion<f64>) -> SMatrix<f64, 7, 4> {
    let jv = jac.fixed_rows::<3>(0);
    let jw = jac.fixed_rows::<3>(3);
    let mut g = SMatrix::<f64, 7, 4>::zeros();
    g.set_column(0, &(jv.transpose() * GRAVITY));
    let m = -(jw.transpose() * GRAVITY.cross_matrix() * rot.to_rotation_matrix().matrix());
    g.fixed_columns_mut::<3>(1).copy_from(&m);
    g
}

/// The fit of one run (reset with the tare at every start).
#[derive(Debug, Clone, PartialEq)]
pub struct PayloadFit {
    info: SMatrix<f64, 11, 11>,
    rhs: SVector<f64, 11>,
    /// The regressor of the last fitted sample.
    last: Option<SMatrix<f64, 7, 4>>,
    /// The last solution and the prior it was solved under.
    theta: Option<Vector4<f64>>,
    solved_prior: f64,
    dirty: bool,
}

impl Default for PayloadFit {
    fn default() -> Self {
        Self {
            info: SMatrix::zeros(),
            rhs: SVector::zeros(),
            last: None,
            theta: None,
            solved_prior: f64::NAN,
            dirty: false,
        }
    }
}

impl PayloadFit {
    /// Feed a sample of the offset `tau` (out of contact) at `jac`, `rot`, lasting `dt`.
    /// Non-finite inputs are skipped.
    pub fn add(&mut self, jac: &Jacobian, rot: &UnitQuaternion<f64>, tau: &JointVector, dt: f64) {
        let g = regressor(jac, rot);
        if !(dt > 0.0 && dt.is_finite() && g.iter().chain(tau.iter()).all(|x| x.is_finite())) {
            return;
        }
        let w = dt / (SAMPLE_SIGMA_NM * SAMPLE_SIGMA_NM * SAMPLE_CORRELATION_S);
        let mut a = SMatrix::<f64, 7, 11>::zeros();
        a.fixed_columns_mut::<7>(0).fill_with_identity();
        a.fixed_columns_mut::<4>(7).copy_from(&g);
        self.info += a.transpose() * a * w;
        self.rhs += a.transpose() * tau * w;
        self.last = Some(g);
        self.dirty = true;
    }

    /// The fitted θ = [dm (kg); dm r (kg m, tip frame)] under a prior of `prior_kg` (0: off,
    /// none), re-solved when samples came, or the prior changed, since the last call.
    pub fn theta(&mut self, prior_kg: f64) -> Option<Vector4<f64>> {
        if !(prior_kg > 0.0 && prior_kg.is_finite()) || self.last.is_none() {
            return None;
        }
        if self.dirty || prior_kg != self.solved_prior {
            self.dirty = false;
            self.solved_prior = prior_kg;
            let mut n = self.info;
            let s = prior_kg * PRIOR_LEVER_M;
            n[(7, 7)] += 1.0 / (prior_kg * prior_kg);
            for i in 8..11 {
                n[(i, i)] += 1.0 / (s * s);
            }
            self.theta = n
                .cholesky()
                .map(|c| c.solve(&self.rhs).fixed_rows::<4>(7).into_owned())
                .filter(|t| t.iter().all(|x| x.is_finite()));
        }
        self.theta
    }

    /// The payload's change of gravity torque from the last fitted sample's pose to `jac`,
    /// `rot`: zero when there is no fit.
    pub fn change(&mut self, prior_kg: f64, jac: &Jacobian, rot: &UnitQuaternion<f64>) -> JointVector {
        match (self.theta(prior_kg), self.last) {
            (Some(t), Some(g0)) => {
                let d = (regressor(jac, rot) - g0) * t;
                if d.iter().all(|x| x.is_finite()) {
                    d
                } else {
                    JointVector::zeros()
                }
            }
            _ => JointVector::zeros(),
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::kinematics::lbr::{LbrModel, ToolParams};
    use crate::kinematics::{Kinematics, LbrKinematics};

    /// The sim's model of a load-data error (`src/sim/torque.rs`): J_c^T (dm g0) at the
    /// point `r` of the tip frame, J_c = J_v - [c - tip]x J_w. (Also the tare's tests.)
    pub(crate) fn payload_torque(jac: &Jacobian, rot: &UnitQuaternion<f64>, dm: f64, r: &Vector3<f64>) -> JointVector {
        let f = GRAVITY * dm;
        let lever = rot * r;
        jac.fixed_rows::<3>(0).transpose() * f + jac.fixed_rows::<3>(3).transpose() * lever.cross(&f)
    }

    #[test]
    fn a_payload_seen_over_varied_poses_predicts_its_torque_at_new_ones() {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let (dm, r) = (0.15, Vector3::new(0.01, -0.02, -0.2));
        let bias = JointVector::from_column_slice(&[0.8, -0.6, 0.2, 1.0, -0.3, 0.1, 0.05]);
        let q0 = JointVector::from_column_slice(&[0.3, 0.6, -0.2, -1.2, 0.4, 0.8, 0.1]);
        let mut fit = PayloadFit::default();
        // An approach: the shoulder, elbow and wrist turn by 0.2-0.6 rad, not in step.
        for k in 0..=300 {
            let s = k as f64 / 300.0;
            let (a, b) = (0.6 * s, 0.5 * (3.0 * s).sin());
            let q = q0 + JointVector::from_column_slice(&[0.2 * s, 0.2 * b, 0.0, 0.3 * s, a, -b, 0.2 * s]);
            let (tip, jac) = kin.fk_jacobian(&q).unwrap();
            let tau = bias + payload_torque(&jac, &tip.rotation, dm, &r);
            fit.add(&jac, &tip.rotation, &tau, 0.01);
        }
        // The mass itself is not what the fit is for (a lighter mass further along the tool
        // does much the same over these poses, and the prior shrinks the part the poses do
        // not tell apart): with a prior of 100 kg it comes out at the true 0.15 kg, with
        // the shipped 0.5 kg about half of it.
        assert!((fit.theta(100.0).unwrap()[0] - dm).abs() < 0.01);
        assert!(fit.theta(0.5).unwrap()[0] > 0.0);
        // Pivoted on from the last pose by 0.4 rad at the wrist: the change predicted within
        // a seventh of what it is.
        let b = 0.5 * 3.0f64.sin();
        let q1 = q0 + JointVector::from_column_slice(&[0.2, 0.2 * b, 0.0, 0.3, 0.6, -b, 0.2]);
        let q2 = q1 + JointVector::from_column_slice(&[0.0, 0.0, 0.0, 0.0, 0.4, 0.3, 0.0]);
        let (t1, j1) = kin.fk_jacobian(&q1).unwrap();
        let (t2, j2) = kin.fk_jacobian(&q2).unwrap();
        let truth = payload_torque(&j2, &t2.rotation, dm, &r) - payload_torque(&j1, &t1.rotation, dm, &r);
        let predicted = fit.change(0.5, &j2, &t2.rotation);
        assert!(truth.amax() > 0.05, "the pose change matters: {truth}");
        // Measured 0.08.
        assert!(
            (predicted - truth).amax() < 0.15 * truth.amax(),
            "{predicted} vs {truth}"
        );
        // At the last fitted pose: no change.
        assert!(fit.change(0.5, &j1, &t1.rotation).amax() < 1e-9);
        // Off: nothing.
        assert_eq!(fit.change(0.0, &j2, &t2.rotation), JointVector::zeros());
    }

    #[test]
    fn one_pose_says_nothing_and_the_prior_keeps_it_at_zero() {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let q = JointVector::from_column_slice(&[0.3, 0.6, -0.2, -1.2, 0.4, 0.8, 0.1]);
        let (tip, jac) = kin.fk_jacobian(&q).unwrap();
        let mut fit = PayloadFit::default();
        for _ in 0..300 {
            fit.add(&jac, &tip.rotation, &JointVector::repeat(0.7), 0.01);
        }
        // The constant offsets explain it all: θ stays at zero.
        assert!(fit.theta(0.5).unwrap().amax() < 1e-6);
        // Bad samples are skipped; no sample, no fit.
        let mut empty = PayloadFit::default();
        empty.add(&jac, &tip.rotation, &JointVector::repeat(f64::NAN), 0.01);
        assert_eq!(empty.theta(0.5), None);
    }
}
