//! Exact solutions of the SQP's box QP from a guessed active set, each one proven optimal
//! by the QP's KKT conditions before it is used; anything unproven goes to Clarabel.
//!
//! The QP is min ½ x^T H x + g^T x subject to lo <= x <= hi, with H symmetric positive
//! definite (the Gauss–Newton Hessian plus the joint-step and Levenberg terms), so it has
//! exactly one minimiser, and x is it if and only if, with r = H x + g:
//! - lo <= x <= hi;
//! - r_i = 0 where lo_i < x_i < hi_i;
//! - r_i <= 0 where x_i = hi_i, and r_i >= 0 where x_i = lo_i (the multipliers' signs).
//!
//! Given which bounds are active, x follows from one 7 x 7 Cholesky solve: the active
//! joints sit on their bounds and the free ones solve H_FF x_F = -(g_F + H_FA x_A). If the
//! result meets the conditions above it is the QP's solution — the same point Clarabel's
//! interior-point method converges to, to within Clarabel's own tolerance. An interior
//! point method cannot be warm-started; this is the warm start: a control step usually
//! has the active set of its last QP (no bound, or the same joints at their velocity
//! limit), so most QPs are settled in about a microsecond and Clarabel solves the rest.
//!
//! Tolerances: a free joint may lie outside its box by [`FEASIBILITY_TOL`] (the caller
//! clamps it in); a multiplier may have the wrong sign by [`MULTIPLIER_TOL`] times the
//! gradient's scale. A bound with lo_i = hi_i fixes its joint and needs no sign check.

use nalgebra::SVector;

use super::costs::Matrix7;
use crate::kinematics::{JointVector, N_JOINTS};

/// How far outside its box a free joint of a certified solution may lie, rad.
pub const FEASIBILITY_TOL: f64 = 1e-12;

/// How far a multiplier may have the wrong sign, relative to max(1, |g|∞).
pub const MULTIPLIER_TOL: f64 = 1e-10;

/// Switches of the primal-dual active-set iteration after the two guesses, at most: each
/// is one 7 x 7 Cholesky solve (about 0.3 µs); a QP not settled by then goes to Clarabel.
pub const SWITCHES: usize = 8;

/// Where one joint sits in a solution.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Bound {
    /// Strictly inside its box.
    #[default]
    Free,
    /// On its lower bound.
    Lower,
    /// On its upper bound.
    Upper,
}

/// Which bound, if any, each joint sits on.
pub type ActiveSet = [Bound; N_JOINTS];

/// No bound active: the unconstrained minimiser.
pub const NONE_ACTIVE: ActiveSet = [Bound::Free; N_JOINTS];

/// The minimiser of the QP with the joints of `set` fixed on their bounds, if it meets
/// the KKT conditions of the box QP (see the module doc); `None` otherwise, or when the
/// reduced Hessian is not numerically positive definite.
pub fn certify(
    h: &Matrix7,
    g: &JointVector,
    lo: &JointVector,
    hi: &JointVector,
    set: &ActiveSet,
) -> Option<JointVector> {
    reduced_minimiser(h, g, lo, hi, set).filter(|x| is_optimal(h, g, lo, hi, set, x))
}

/// The minimiser with the joints of `set` fixed on their bounds and the others free (not
/// checked against the box); `None` for an empty box, a reduced Hessian that is not
/// numerically positive definite, or a non-finite result.
fn reduced_minimiser(
    h: &Matrix7,
    g: &JointVector,
    lo: &JointVector,
    hi: &JointVector,
    set: &ActiveSet,
) -> Option<JointVector> {
    let n = N_JOINTS;
    // An empty box has no solution to certify (Clarabel reports it infeasible).
    if !(0..n).all(|i| lo[i] <= hi[i]) {
        return None;
    }
    let fixed = |i: usize| match set[i] {
        Bound::Free => None,
        Bound::Lower => Some(lo[i]),
        Bound::Upper => Some(hi[i]),
    };
    // The reduced system, kept 7 x 7: a fixed joint's row and column become the identity
    // and its right-hand side its bound.
    let mut m = *h;
    let mut rhs: SVector<f64, N_JOINTS> = -g;
    for j in 0..n {
        if let Some(v) = fixed(j) {
            for i in 0..n {
                if fixed(i).is_none() {
                    rhs[i] -= h[(i, j)] * v;
                }
                m[(i, j)] = 0.0;
                m[(j, i)] = 0.0;
            }
            m[(j, j)] = 1.0;
            rhs[j] = v;
        }
    }
    let x = m.cholesky()?.solve(&rhs);
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Whether `x`, the reduced minimiser for `set`, meets the box QP's KKT conditions.
fn is_optimal(
    h: &Matrix7,
    g: &JointVector,
    lo: &JointVector,
    hi: &JointVector,
    set: &ActiveSet,
    x: &JointVector,
) -> bool {
    let r = h * x + g;
    let r_tol = MULTIPLIER_TOL * g.amax().max(1.0);
    (0..N_JOINTS).all(|i| match set[i] {
        Bound::Free => x[i] >= lo[i] - FEASIBILITY_TOL && x[i] <= hi[i] + FEASIBILITY_TOL,
        _ if lo[i] == hi[i] => true,
        Bound::Lower => r[i] >= -r_tol,
        Bound::Upper => r[i] <= r_tol,
    })
}

/// The active set of a solution `x` of the box QP (as Clarabel returns it: an active
/// bound is met to within a small fraction of the box), for use as the next guess.
pub fn active_set_of(x: &JointVector, lo: &JointVector, hi: &JointVector) -> ActiveSet {
    let mut set = NONE_ACTIVE;
    for i in 0..N_JOINTS {
        let near = 1e-6 * (hi[i] - lo[i]).max(1e-9);
        if x[i] >= hi[i] - near {
            set[i] = Bound::Upper;
        } else if x[i] <= lo[i] + near {
            set[i] = Bound::Lower;
        }
    }
    set
}

/// The QP's solution from the first guess that [`certify`] proves optimal: `hint` (the
/// last QP's active set), then the bounds the unconstrained minimiser crosses (no bound
/// at all when it crosses none), then up to [`SWITCHES`] steps of a primal-dual
/// active-set iteration from there (a free joint that crosses a bound is put on it, a
/// joint whose multiplier has the wrong sign is freed: the switch that settles a QP whose
/// active set changed on several joints at once, as when the arm starts to move).
/// Returns it with its active set, or `None` when nothing is proven.
pub fn solve_from_guesses(
    h: &Matrix7,
    g: &JointVector,
    lo: &JointVector,
    hi: &JointVector,
    hint: &ActiveSet,
) -> Option<(JointVector, ActiveSet)> {
    let at_hint = reduced_minimiser(h, g, lo, hi, hint);
    if let Some(x) = at_hint.filter(|x| is_optimal(h, g, lo, hi, hint, x)) {
        return Some((x, *hint));
    }
    // With no bound in the hint, its reduced minimiser is the unconstrained one: no need
    // to factorise H again.
    let unconstrained = match at_hint {
        Some(x) if *hint == NONE_ACTIVE => x,
        _ => reduced_minimiser(h, g, lo, hi, &NONE_ACTIVE)?,
    };
    let mut set = NONE_ACTIVE;
    for i in 0..N_JOINTS {
        if unconstrained[i] > hi[i] {
            set[i] = Bound::Upper;
        } else if unconstrained[i] < lo[i] {
            set[i] = Bound::Lower;
        }
    }
    let r_tol = MULTIPLIER_TOL * g.amax().max(1.0);
    for _ in 0..=SWITCHES {
        let x = reduced_minimiser(h, g, lo, hi, &set)?;
        if set != *hint && is_optimal(h, g, lo, hi, &set, &x) {
            return Some((x, set));
        }
        let r = h * x + g;
        let mut next = set;
        for i in 0..N_JOINTS {
            next[i] = match set[i] {
                Bound::Free if x[i] > hi[i] + FEASIBILITY_TOL => Bound::Upper,
                Bound::Free if x[i] < lo[i] - FEASIBILITY_TOL => Bound::Lower,
                Bound::Upper if lo[i] < hi[i] && r[i] > r_tol => Bound::Free,
                Bound::Lower if lo[i] < hi[i] && r[i] < -r_tol => Bound::Free,
                b => b,
            };
        }
        if next == set {
            return None;
        }
        set = next;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn spd(a: &[f64], diag: f64) -> Matrix7 {
        let b = Matrix7::from_fn(|i, j| a[(i * 7 + j) % a.len()]);
        b * b.transpose() + Matrix7::identity() * diag
    }

    #[test]
    fn an_interior_minimiser_is_certified_with_no_bound_active() {
        let h = spd(&[0.3, -0.1, 0.7, 0.2, 0.5], 0.1);
        let x_true = JointVector::from_column_slice(&[0.01, -0.02, 0.0, 0.03, -0.01, 0.02, 0.0]);
        let g = -(h * x_true);
        let (lo, hi) = (JointVector::from_element(-0.1), JointVector::from_element(0.1));
        let (x, set) = solve_from_guesses(&h, &g, &lo, &hi, &NONE_ACTIVE).unwrap();
        assert!((x - x_true).amax() < 1e-12);
        assert_eq!(set, NONE_ACTIVE);
    }

    #[test]
    fn a_wrong_guess_is_refused() {
        // Diagonal H: the solution is the clamped unconstrained minimiser.
        let h = Matrix7::identity();
        let g = JointVector::from_column_slice(&[-1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        let (lo, hi) = (JointVector::from_element(-0.5), JointVector::from_element(0.5));
        // Unconstrained: x0 = 1 > 0.5 is infeasible.
        assert!(certify(&h, &g, &lo, &hi, &NONE_ACTIVE).is_none());
        // Joint 0 on its lower bound: its multiplier has the wrong sign.
        let mut wrong = NONE_ACTIVE;
        wrong[0] = Bound::Lower;
        assert!(certify(&h, &g, &lo, &hi, &wrong).is_none());
        // The true active set.
        let mut right = NONE_ACTIVE;
        right[0] = Bound::Upper;
        right[1] = Bound::Lower;
        let x = certify(&h, &g, &lo, &hi, &right).unwrap();
        assert_eq!(x[0], 0.5);
        assert_eq!(x[1], -0.5);
        assert!(x.rows(2, 5).amax() < 1e-15);
        // Fixing a joint that is free at the optimum is refused too: on its upper bound
        // the cost pulls it back inside (r > 0, the wrong sign).
        let mut extra = right;
        extra[2] = Bound::Upper;
        assert!(certify(&h, &g, &lo, &hi, &extra).is_none());
        assert_eq!(
            solve_from_guesses(&h, &g, &lo, &hi, &NONE_ACTIVE).map(|s| s.1),
            Some(right)
        );
    }

    #[test]
    fn bad_data_is_never_certified() {
        let h = Matrix7::identity();
        let mut g = JointVector::zeros();
        g[3] = f64::NAN;
        let (lo, hi) = (JointVector::from_element(-1.0), JointVector::from_element(1.0));
        assert!(solve_from_guesses(&h, &g, &lo, &hi, &NONE_ACTIVE).is_none());
        // An empty box: no guess is proven, whatever it fixes.
        let (mut lo2, mut hi2) = (lo, hi);
        lo2[2] = 0.2;
        hi2[2] = 0.1;
        for b in [Bound::Free, Bound::Lower, Bound::Upper] {
            let mut set = NONE_ACTIVE;
            set[2] = b;
            assert!(certify(&Matrix7::identity(), &JointVector::zeros(), &lo2, &hi2, &set).is_none());
        }
        assert!(solve_from_guesses(&Matrix7::identity(), &JointVector::zeros(), &lo2, &hi2, &NONE_ACTIVE).is_none());
        // Not positive definite.
        let h = -Matrix7::identity();
        assert!(solve_from_guesses(&h, &JointVector::zeros(), &lo, &hi, &NONE_ACTIVE).is_none());
    }

    #[test]
    fn the_active_set_of_a_clamped_point() {
        let (lo, hi) = (JointVector::from_element(-0.01), JointVector::from_element(0.01));
        let mut x = JointVector::zeros();
        x[0] = 0.01 - 1e-12;
        x[1] = -0.01;
        x[2] = 0.0099;
        let s = active_set_of(&x, &lo, &hi);
        assert_eq!(&s[..3], &[Bound::Upper, Bound::Lower, Bound::Free]);
    }

    #[test]
    fn the_switches_settle_a_qp_whose_active_set_changed_on_several_joints() {
        // Two coupled joints. The unconstrained minimiser (5.8, -4.2) crosses joint 0's
        // upper bound and joint 1's lower one, but with both there joint 1's multiplier has
        // the wrong sign: neither guess holds. Freed, joint 1 goes to 0.55, past its upper
        // bound; with both on their upper bounds the conditions hold.
        let mut h = Matrix7::identity();
        h[(0, 1)] = 0.9;
        h[(1, 0)] = 0.9;
        let g = JointVector::from_column_slice(&[-2.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        let (lo, hi) = (JointVector::from_element(-1.0), JointVector::from_element(0.5));
        let mut crossing = NONE_ACTIVE;
        crossing[0] = Bound::Upper;
        crossing[1] = Bound::Lower;
        assert!(certify(&h, &g, &lo, &hi, &crossing).is_none());
        assert!(certify(&h, &g, &lo, &hi, &NONE_ACTIVE).is_none());
        let (x, set) = solve_from_guesses(&h, &g, &lo, &hi, &NONE_ACTIVE).unwrap();
        let mut both = NONE_ACTIVE;
        both[0] = Bound::Upper;
        both[1] = Bound::Upper;
        assert_eq!(set, both);
        assert!((x - JointVector::from_column_slice(&[0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0])).amax() < 1e-15);
    }

    proptest! {
        /// The switches settle (almost) every QP: with random boxes and gradients, the
        /// guesses and switches together certify the solution in at least 95 % of cases
        /// (a QP left to Clarabel is still solved; this bounds how often).
        #[test]
        fn the_switches_settle_nearly_every_qp(
            cases in prop::collection::vec((prop::collection::vec(-1.0f64..1.0, 49), prop::collection::vec(-2.0f64..2.0, 7), prop::collection::vec(0.01f64..0.3, 7)), 40),
        ) {
            let mut settled = 0;
            for (a, g, w) in &cases {
                let h = spd(a, 0.05);
                let g = JointVector::from_column_slice(g);
                let lo = JointVector::from_fn(|i, _| -w[i]);
                let hi = JointVector::from_fn(|i, _| w[i]);
                settled += usize::from(solve_from_guesses(&h, &g, &lo, &hi, &NONE_ACTIVE).is_some());
            }
            prop_assert!(settled * 100 >= 95 * cases.len(), "{settled} of {}", cases.len());
        }
    }

    proptest! {
        /// Whatever a certified solution is, it is the QP's minimiser: feasible, and no
        /// feasible point nearby (a step along each joint, or toward a random feasible
        /// point) has a lower cost.
        #[test]
        fn a_certified_solution_is_the_minimiser(
            a in prop::collection::vec(-1.0f64..1.0, 49),
            diag in 1e-4f64..1.0,
            g in prop::collection::vec(-2.0f64..2.0, 7),
            c in prop::collection::vec(-0.5f64..0.5, 7),
            w in prop::collection::vec(0.0f64..0.3, 7),
            y in prop::collection::vec(0.0f64..1.0, 7),
            guess in prop::collection::vec(0u8..3, 7),
        ) {
            let h = spd(&a, diag);
            let g = JointVector::from_column_slice(&g);
            let lo = JointVector::from_fn(|i, _| c[i] - w[i]);
            let hi = JointVector::from_fn(|i, _| c[i] + w[i]);
            let mut hint = NONE_ACTIVE;
            for i in 0..7 {
                hint[i] = [Bound::Free, Bound::Lower, Bound::Upper][guess[i] as usize];
            }
            let cost = |x: &JointVector| 0.5 * x.dot(&(h * x)) + g.dot(x);
            if let Some((x, _)) = solve_from_guesses(&h, &g, &lo, &hi, &hint) {
                let x = x.zip_zip_map(&lo, &hi, |v, l, u| v.clamp(l, u));
                let f = cost(&x);
                let tol = 1e-9 * (1.0 + f.abs());
                let other = JointVector::from_fn(|i, _| lo[i] + y[i] * (hi[i] - lo[i]));
                for t in [1e-3, 1e-1, 1.0] {
                    let z = x + (other - x) * t;
                    prop_assert!(cost(&z) >= f - tol, "toward a feasible point {t}: {} < {f}", cost(&z));
                }
                for i in 0..7 {
                    for d in [-1e-4, 1e-4] {
                        let mut z = x;
                        z[i] = (z[i] + d).clamp(lo[i], hi[i]);
                        prop_assert!(cost(&z) >= f - tol, "joint {i} {d}");
                    }
                }
            }
        }
    }
}
