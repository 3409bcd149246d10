//! The cost terms of the controller and their Gauss–Newton quadratic model.
//!
//! With e(q) the tip position, a(q) the optical axis (tip z), p_t the port, g_a the
//! insertion direction and P = I - g_a g_a^T:
//!
//! | term | residual | meaning |
//! |---|---|---|
//! | c1 | P (e - p_t) | tip to the insertion axis (the paper's e - n(g_a)) |
//! | c2 | e - g | tip to the current target point g on the axis |
//! | c3 | a - g_a | optical axis alignment |
//! | c4 | q - q_prev | joint step (velocity) |
//! | c5 | P (e - r) | tip to the admittance reference r, across the axis |
//!
//! c5 acts across the insertion axis only, as the admittance does ([`crate::control::force::admittance`]):
//! the paper's e - r also penalises the tip's motion along the axis, which with an arm that
//! contact deflects (a seal's friction, finite joint stiffness) holds the tip short of the
//! goal by the deflection times w5 / w2.
//!
//! Each c_i is the squared norm of its residual. For c5 the paper writes the unsquared norm
//! ||e - r||; its gradient is undefined at e = r and its Hessian unbounded near it, which
//! breaks a Gauss–Newton model exactly where the tip follows r closely. The squared form is
//! smooth, and the weight w5 sets the same trade-off.
//!
//! After docking ([`crate::control::scope::pivot`]) two more terms hold the port as a remote centre
//! of motion ([`PivotCost`]): the fulcrum f's distance from the shaft line,
//! P_a (f - e) with P_a = I - a a^T (the RCM residual), and the roll residual x - x_t of the
//! tip's x axis. Linearising e and a about q_lin
//! (`e ≈ e0 + J_v dq`, `a ≈ a0 - [a0]x J_w dq`) turns the weighted sum into
//! ½ dq^T H dq + g^T dq + const.

use nalgebra::{Isometry3, Matrix3, Point3, SMatrix, SVector, Vector3};
use serde::{Deserialize, Serialize};

use crate::control::docking::geometry::{across, InsertionAxis};
use crate::kinematics::{Jacobian, JointVector};

/// 7 x 7 matrix of the QP.
pub type Matrix7 = SMatrix<f64, 7, 7>;

/// Weights w1..w5 of the cost terms.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CostWeights {
    /// w1: tip to axis, 1/m².
    pub axis: f64,
    /// w2: tip to target point, 1/m².
    pub goal: f64,
    /// w3: alignment.
    pub align: f64,
    /// w4: joint step, 1/rad².
    pub step: f64,
    /// w5: tip to admittance reference, 1/m² (0 = force feedback off).
    pub reference: f64,
}

impl CostWeights {
    /// As an array, c1..c5 order.
    pub fn as_array(&self) -> [f64; 5] {
        [self.axis, self.goal, self.align, self.step, self.reference]
    }

    /// Check that every weight is finite and >= 0.
    pub fn validate(&self, name: &str) -> Result<(), String> {
        for (i, w) in self.as_array().iter().enumerate() {
            if !(w.is_finite() && *w >= 0.0) {
                return Err(format!("{name}: weight w{} must be finite and >= 0, got {w}", i + 1));
            }
        }
        Ok(())
    }
}

/// A cost that keeps joints away from their limits, zero in the middle of the range: for
/// u_i = (q_i - center_i) / half_range_i, residual max(0, |u_i| - zone) sign(u_i). It does
/// not bias the task where the joints are comfortable, and steers the arm's redundancy off
/// a limit before the box constraint stalls the Gauss–Newton step against it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LimitAvoidance {
    /// Middle of each joint's range, rad.
    pub center: JointVector,
    /// Half of each joint's range, rad (> 0).
    pub half_range: JointVector,
    /// Fraction of the half range where the cost starts (0..1).
    pub zone: f64,
    /// Weight.
    pub weight: f64,
}

impl LimitAvoidance {
    /// Residual and its (diagonal) derivative per joint.
    fn residual(&self, q: &JointVector) -> (JointVector, JointVector) {
        let mut r = JointVector::zeros();
        let mut d = JointVector::zeros();
        for i in 0..q.len() {
            let u = (q[i] - self.center[i]) / self.half_range[i];
            if u.abs() > self.zone {
                r[i] = (u.abs() - self.zone) * u.signum();
                d[i] = 1.0 / self.half_range[i];
            }
        }
        (r, d)
    }

    /// The cost's value at `q` (unweighted).
    pub fn value(&self, q: &JointVector) -> f64 {
        self.residual(q).0.norm_squared()
    }
}

/// What the cost terms pull towards at one control step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Targets {
    /// The insertion axis.
    pub axis: InsertionAxis,
    /// Target point of c2.
    pub point: Point3<f64>,
    /// Admittance reference r of c5 (ignored when w5 = 0).
    pub reference: Point3<f64>,
    /// The previous command, for c4.
    pub q_prev: JointVector,
    /// Joint-limit avoidance, if any.
    pub limits: Option<LimitAvoidance>,
    /// The remote centre of motion after docking, if held.
    pub pivot: Option<PivotCost>,
}

/// The terms that hold a fulcrum on the shaft line and the roll about the shaft (after
/// docking; see [`crate::control::scope::pivot`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PivotCost {
    /// The fulcrum point the shaft line must pass through, base frame, m.
    pub fulcrum: Point3<f64>,
    /// Target direction of the tip's x axis (roll about the shaft), unit.
    pub x_axis: Vector3<f64>,
    /// Weight of the fulcrum's squared distance from the shaft line, 1/m².
    pub rcm_weight: f64,
    /// Weight of the squared roll residual |x - x_t|².
    pub roll_weight: f64,
}

impl PivotCost {
    /// The fulcrum's offset from the shaft line of `pose` (its z axis through its origin),
    /// P_a (f - e): zero when the shaft passes through the fulcrum.
    pub fn rcm_residual(&self, pose: &Isometry3<f64>) -> Vector3<f64> {
        let a = pose.rotation * Vector3::z();
        across(&a, &(self.fulcrum - Point3::from(pose.translation.vector)))
    }

    /// The weighted value of both terms at `pose`.
    pub fn value(&self, pose: &Isometry3<f64>) -> f64 {
        let x = pose.rotation * Vector3::x();
        self.rcm_weight * self.rcm_residual(pose).norm_squared() + self.roll_weight * (x - self.x_axis).norm_squared()
    }

    /// Residuals and their Jacobians (3 x 7 each) at `pose` with the geometric Jacobian's
    /// linear rows `jv` and angular rows `jw`: d r_rcm = (-P_a J_v + (a^T u) [a]x J_w +
    /// a (u^T [a]x) J_w) dq with u = f - e (from da = w x a), and d x = -[x]x J_w dq.
    fn linearised(
        &self,
        pose: &Isometry3<f64>,
        jv: &SMatrix<f64, 3, 7>,
        jw: &SMatrix<f64, 3, 7>,
    ) -> [(Vector3<f64>, SMatrix<f64, 3, 7>); 2] {
        let a = pose.rotation * Vector3::z();
        let x = pose.rotation * Vector3::x();
        let u = self.fulcrum - Point3::from(pose.translation.vector);
        let ax = a.cross_matrix();
        let proj = Matrix3::identity() - a * a.transpose();
        let j_rcm = -proj * jv + ax * jw * a.dot(&u) + a * (u.transpose() * ax * jw);
        [
            (self.rcm_residual(pose), j_rcm),
            (x - self.x_axis, -x.cross_matrix() * jw),
        ]
    }
}

/// Unweighted values of c1..c5.
pub type CostTerms = [f64; 5];

/// Evaluate c1..c5 at a tip pose and joint vector.
pub fn evaluate(pose: &Isometry3<f64>, q: &JointVector, t: &Targets) -> CostTerms {
    let e = Point3::from(pose.translation.vector);
    let a = pose.rotation * Vector3::z();
    [
        t.axis.lateral_offset(&e).norm_squared(),
        (e - t.point).norm_squared(),
        (a - t.axis.direction.into_inner()).norm_squared(),
        (q - t.q_prev).norm_squared(),
        t.axis.across(&(e - t.reference)).norm_squared(),
    ]
}

/// The Gauss–Newton model ½ dq^T H dq + g^T dq of the weighted cost about `q_lin`, plus a
/// Levenberg term `regularization` |dq|².
pub fn quadratic_model(
    pose: &Isometry3<f64>,
    jac: &Jacobian,
    q_lin: &JointVector,
    t: &Targets,
    w: &CostWeights,
    regularization: f64,
) -> (Matrix7, SVector<f64, 7>) {
    let e = Point3::from(pose.translation.vector);
    let a = pose.rotation * Vector3::z();
    let jv = jac.fixed_rows::<3>(0).into_owned();
    let jw = jac.fixed_rows::<3>(3).into_owned();
    let g_a = t.axis.direction.into_inner();
    let proj = Matrix3::identity() - g_a * g_a.transpose();

    let mut h = Matrix7::identity() * (2.0 * (regularization + w.step));
    let mut g = (q_lin - t.q_prev) * (2.0 * w.step);
    let mut add = |weight: f64, r: Vector3<f64>, jr: SMatrix<f64, 3, 7>| {
        if weight > 0.0 {
            h += jr.transpose() * jr * (2.0 * weight);
            g += jr.transpose() * r * (2.0 * weight);
        }
    };
    add(w.axis, proj * (e - t.axis.port), proj * jv);
    add(w.goal, e - t.point, jv);
    add(w.align, a - g_a, -a.cross_matrix() * jw);
    add(w.reference, proj * (e - t.reference), proj * jv);
    if let Some(pc) = &t.pivot {
        let [(r_rcm, j_rcm), (r_roll, j_roll)] = pc.linearised(pose, &jv, &jw);
        add(pc.rcm_weight, r_rcm, j_rcm);
        add(pc.roll_weight, r_roll, j_roll);
    }
    if let Some(l) = &t.limits {
        if l.weight > 0.0 {
            let (r, d) = l.residual(q_lin);
            for i in 0..r.len() {
                h[(i, i)] += 2.0 * l.weight * d[i] * d[i];
                g[i] += 2.0 * l.weight * d[i] * r[i];
            }
        }
    }
    (h, g)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::lbr::{LbrModel, ToolParams};
    use crate::kinematics::{Kinematics, LbrKinematics};
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn model_matches_cost_to_first_order() {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let q = JointVector::from_column_slice(&[0.1, 0.6, -0.1, -1.2, 0.2, 0.9, 0.3]);
        let (pose, jac) = kin.fk_jacobian(&q).unwrap();
        let trocar = Isometry3::from_parts(
            Translation3::new(0.62, 0.05, 0.25),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI - 0.2),
        );
        let t = Targets {
            axis: InsertionAxis::from_pose(&trocar),
            point: Point3::new(0.6, 0.0, 0.3),
            reference: Point3::new(0.58, 0.02, 0.35),
            q_prev: q.add_scalar(0.01),
            limits: Some(LimitAvoidance {
                center: JointVector::zeros(),
                half_range: JointVector::from_element(1.0),
                zone: 0.5,
                weight: 2.0,
            }),
            pivot: Some(PivotCost {
                fulcrum: Point3::new(0.61, 0.04, 0.3),
                x_axis: Vector3::new(0.0, 0.6, 0.8),
                rcm_weight: 4.0,
                roll_weight: 0.9,
            }),
        };
        let w = CostWeights {
            axis: 3.0,
            goal: 2.0,
            align: 0.7,
            step: 0.1,
            reference: 1.5,
        };
        let total = |q: &JointVector| {
            let p = kin.fk(q).unwrap();
            evaluate(&p, q, &t)
                .iter()
                .zip(w.as_array())
                .map(|(c, w)| c * w)
                .sum::<f64>()
                + t.limits.map_or(0.0, |l| l.weight * l.value(q))
                + t.pivot.map_or(0.0, |pc| pc.value(&p))
        };
        let (_, g) = quadratic_model(&pose, &jac, &q, &t, &w, 0.0);
        // The model's gradient is the true gradient of the weighted cost.
        for i in 0..7 {
            let h = 1e-6;
            let (mut qp, mut qm) = (q, q);
            qp[i] += h;
            qm[i] -= h;
            let fd = (total(&qp) - total(&qm)) / (2.0 * h);
            assert!(
                (fd - g[i]).abs() < 1e-5 * (1.0 + fd.abs()),
                "joint {i}: {fd} vs {}",
                g[i]
            );
        }
        let c = evaluate(&pose, &q, &t);
        assert!(c.iter().all(|x| x.is_finite() && *x >= 0.0));
        assert!((c[3] - 7.0 * 1e-4).abs() < 1e-12);
        assert!(CostWeights { align: -1.0, ..w }.validate("x").is_err());
    }
}
