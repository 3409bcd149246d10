//! Gauss–Newton SQP on Clarabel: linearise the costs with the Jacobian, solve the box QP
//! for the joint step, repeat to a tolerance or a cap. In real-time-iteration mode (RTI)
//! one QP is solved per control step, as acados does.
//!
//! The QP is min ½ dq^T H dq + g^T dq subject to lo - q_k <= dq <= hi - q_k, where [lo, hi]
//! is the step box of the safety guard (position limits with margin ∩ velocity limit from
//! the previous command). The Clarabel solver is built once with the problem's fixed
//! sparsity (dense upper-triangular H, A = [I; -I]) and only its data is updated per solve,
//! so a solve allocates nothing of its own; Clarabel itself allocates once per solve (its
//! timers; `a_solve_allocates_nothing_of_its_own`).
//!
//! **Active-set warm start** ([`SqpSettings::active_set_warm_start`], on by default). An
//! interior-point solver cannot start from a known solution, but consecutive QPs of a
//! control loop nearly always share their active set: no bound, or the same joints at
//! their velocity limit. So each QP first tries the last QP's active set, then the bounds
//! its unconstrained minimiser crosses ([`super::active_set`]); a guess is taken only when
//! the QP's KKT conditions prove it the exact solution, and Clarabel solves every QP no
//! guess settles. In the benchmark and the simulated trials Clarabel then solves about 1 %
//! of the QPs, and a step costs a few microseconds instead of about 70.
//!
//! **Bounded work per step.** Besides the cap on QPs and on interior-point iterations per
//! QP, a solve has two budgets:
//! - [`SqpSettings::max_total_qp_iterations`], interior-point iterations over all its QPs:
//!   a deterministic bound on the work of one step (the same inputs give the same output);
//! - [`SqpSettings::time_budget_us`], wall time, off by default: for a hard real-time loop.
//!   It bounds the step's latency even after a preemption, at the price of determinism (a
//!   loaded machine cuts more solves short), so simulations and tests leave it off.
//!
//! No QP starts once a budget is spent, and a QP still running when one runs out is stopped
//! (Clarabel's termination callback, checked once per interior-point iteration) and its
//! unfinished result dropped: the solve returns the last completed iterate with
//! [`SqpStatus::TimeBudget`] or [`SqpStatus::QpIterationBudget`]. Every completed iterate
//! lies in the box (each QP step is clamped into it), so it is a safe command; with no QP
//! completed it is the start point itself, i.e. the arm holds for one step.
//! [`SqpSolver::new`] runs one dummy solve, so Clarabel's lazy first-solve work happens at
//! construction and not in the first control step.

use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use clarabel::algebra::CscMatrix;
use clarabel::solver::{
    DefaultSettings, DefaultSettingsBuilder, DefaultSolver, IPSolver, SolverStatus, SupportedConeT,
};
use serde::{Deserialize, Serialize};

use super::active_set::{active_set_of, solve_from_guesses, ActiveSet, NONE_ACTIVE};
use super::costs::{evaluate, quadratic_model, CostTerms, CostWeights, Matrix7, Targets};
use crate::kinematics::{JointVector, Kinematics, N_JOINTS};

/// Settings of the SQP.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct SqpSettings {
    /// Largest number of QPs per control step (1 = real-time iteration).
    pub max_iterations: usize,
    /// Converged when the largest joint step of an iteration is below this, rad.
    pub tolerance_rad: f64,
    /// Levenberg regularisation added to the Hessian's diagonal.
    pub regularization: f64,
    /// Interior-point iterations allowed per QP (a QP that hits the cap has failed).
    pub qp_max_iterations: u32,
    /// Interior-point iterations allowed per solve, over all its QPs (a hard bound: a QP
    /// still unsolved when it has taken the iterations left is stopped, before that last
    /// iteration's convergence check); then the last completed iterate is returned
    /// ([`SqpStatus::QpIterationBudget`]).
    pub max_total_qp_iterations: u32,
    /// Wall-time budget of one solve, µs (0 = none): no QP starts after it, a running QP is
    /// stopped at it and the last completed iterate is returned ([`SqpStatus::TimeBudget`]).
    /// Makes the result depend on the machine's load; see the module doc.
    pub time_budget_us: f64,
    /// Try the last QP's active set (then the bounds the unconstrained minimiser crosses)
    /// before calling Clarabel, and take the result when the KKT conditions prove it the
    /// QP's solution ([`super::active_set`]). Off: Clarabel solves every QP.
    pub active_set_warm_start: bool,
}

crate::shipped_defaults!(SqpSettings, crate::config::CONTROLLER, ["sqp"]);

impl SqpSettings {
    /// Real-time-iteration settings: one QP per step.
    pub fn rti() -> Self {
        Self {
            max_iterations: 1,
            ..Self::default()
        }
    }

    /// Check ranges.
    pub fn validate(&self) -> Result<(), String> {
        if self.max_iterations == 0 || self.max_iterations > 100 {
            return Err(format!(
                "sqp.max_iterations must be in 1..=100, got {}",
                self.max_iterations
            ));
        }
        if !(self.tolerance_rad.is_finite() && self.tolerance_rad > 0.0) {
            return Err(format!("sqp.tolerance_rad must be > 0, got {}", self.tolerance_rad));
        }
        if !(self.regularization.is_finite() && self.regularization >= 0.0) {
            return Err(format!("sqp.regularization must be >= 0, got {}", self.regularization));
        }
        if self.qp_max_iterations == 0 {
            return Err("sqp.qp_max_iterations must be > 0".into());
        }
        if self.max_total_qp_iterations == 0 {
            return Err("sqp.max_total_qp_iterations must be > 0".into());
        }
        // The upper bound keeps the nanosecond deadline far from u64 overflow.
        if !(self.time_budget_us.is_finite() && (0.0..=1e9).contains(&self.time_budget_us)) {
            return Err(format!(
                "sqp.time_budget_us must be in [0, 1e9] µs (0 = none), got {}",
                self.time_budget_us
            ));
        }
        Ok(())
    }
}

/// How a solve ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SqpStatus {
    /// The step fell below the tolerance.
    Converged,
    /// The iteration cap was reached (normal in RTI mode); the solution is usable.
    IterationLimit,
    /// The time budget ran out; the solution is the last completed iterate (the start
    /// point when no QP completed), inside the box and usable.
    TimeBudget,
    /// The interior-point iteration budget ran out; as [`SqpStatus::TimeBudget`].
    QpIterationBudget,
    /// A QP failed; the solution must not be commanded.
    QpFailed(QpFailure),
    /// The kinematics failed; the solution must not be commanded.
    Kinematics,
}

impl SqpStatus {
    /// Whether the solution may be commanded.
    pub fn is_usable(&self) -> bool {
        matches!(
            self,
            SqpStatus::Converged | SqpStatus::IterationLimit | SqpStatus::TimeBudget | SqpStatus::QpIterationBudget
        )
    }

    /// Short text for status messages (static: a failure in the control loop allocates
    /// nothing).
    pub fn as_text(&self) -> &'static str {
        match self {
            SqpStatus::Converged => "converged",
            SqpStatus::IterationLimit => "iteration_limit",
            SqpStatus::TimeBudget => "time_budget",
            SqpStatus::QpIterationBudget => "qp_iteration_budget",
            SqpStatus::QpFailed(f) => f.as_text(),
            SqpStatus::Kinematics => "kinematics failed",
        }
    }
}

/// Why a QP gave no step: a closed set, each with a static text, so that the failure path
/// of the control loop allocates nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum QpFailure {
    /// The Hessian, gradient or box had a NaN or infinite value.
    NonFiniteData,
    /// Clarabel refused the new data.
    DataUpdate,
    /// Clarabel ended with this status, which is not a solution.
    Solver(SolverStatus),
    /// The solution had a NaN or infinite value.
    NonFiniteSolution,
}

impl QpFailure {
    /// Short text for status messages.
    pub fn as_text(&self) -> &'static str {
        match self {
            QpFailure::NonFiniteData => "qp_failed: non-finite QP data",
            QpFailure::DataUpdate => "qp_failed: QP data update refused",
            QpFailure::NonFiniteSolution => "qp_failed: non-finite QP solution",
            QpFailure::Solver(s) => match s {
                SolverStatus::Unsolved => "qp_failed: unsolved",
                SolverStatus::Solved => "qp_failed: solved",
                SolverStatus::AlmostSolved => "qp_failed: almost solved",
                SolverStatus::PrimalInfeasible => "qp_failed: primal infeasible",
                SolverStatus::DualInfeasible => "qp_failed: dual infeasible",
                SolverStatus::AlmostPrimalInfeasible => "qp_failed: almost primal infeasible",
                SolverStatus::AlmostDualInfeasible => "qp_failed: almost dual infeasible",
                SolverStatus::MaxIterations => "qp_failed: interior-point iteration cap",
                SolverStatus::MaxTime => "qp_failed: time limit",
                SolverStatus::NumericalError => "qp_failed: numerical error",
                SolverStatus::InsufficientProgress => "qp_failed: insufficient progress",
                SolverStatus::CallbackTerminated => "qp_failed: stopped by its budget",
            },
        }
    }
}

/// The result of one SQP solve.
#[derive(Debug, Clone, PartialEq)]
pub struct SqpSolution {
    /// The joint positions found (equal to the start when not usable).
    pub q: JointVector,
    /// How it ended.
    pub status: SqpStatus,
    /// QPs solved.
    pub iterations: usize,
    /// Interior-point iterations over all QPs (those of a QP cut off by a budget included).
    pub qp_iterations: u32,
    /// QPs solved by Clarabel; the others were solved from a proven active set.
    pub clarabel_qps: usize,
    /// Wall time of the whole solve, µs.
    pub solve_time_us: f64,
    /// Unweighted c1..c5 at `q` (at the start when not usable).
    pub costs: CostTerms,
}

const NC: usize = 2 * N_JOINTS;

/// One QP's step.
struct QpStep {
    /// The joint step, inside the box.
    dq: JointVector,
    /// Clarabel's interior-point iterations (0 when it was not called).
    qp_iterations: u32,
    /// Whether Clarabel solved it.
    clarabel: bool,
}

/// Why one QP gave no step.
enum QpError {
    /// Stopped by a budget after this many interior-point iterations.
    OutOfBudget(u32),
    /// Anything else (bad data, solver status, non-finite result).
    Failed(QpFailure),
}

/// The budgets of the running solve, shared with Clarabel's termination callback (which
/// must be `Send + Sync`) through atomics, so that setting them per QP allocates nothing.
#[derive(Debug, Clone)]
struct Budget {
    base: Instant,
    /// Wall-clock deadline, ns after `base` (`u64::MAX`: none).
    deadline_ns: Arc<AtomicU64>,
    /// Interior-point iterations the running QP may take.
    qp_iterations: Arc<AtomicU32>,
}

impl Budget {
    fn new() -> Self {
        Self {
            base: Instant::now(),
            deadline_ns: Arc::new(AtomicU64::new(u64::MAX)),
            qp_iterations: Arc::new(AtomicU32::new(u32::MAX)),
        }
    }

    fn nanos_since_base(&self, t: Instant) -> u64 {
        u64::try_from(t.saturating_duration_since(self.base).as_nanos()).unwrap_or(u64::MAX)
    }

    fn set_deadline(&self, at: Option<Instant>) {
        let ns = at.map_or(u64::MAX, |t| self.nanos_since_base(t));
        self.deadline_ns.store(ns, Ordering::Relaxed);
    }

    fn set_qp_iterations(&self, n: u32) {
        self.qp_iterations.store(n, Ordering::Relaxed);
    }

    /// Whether a QP that has taken `iterations` interior-point iterations must stop.
    fn spent(&self, iterations: u32) -> bool {
        iterations >= self.qp_iterations.load(Ordering::Relaxed)
            || self.nanos_since_base(Instant::now()) >= self.deadline_ns.load(Ordering::Relaxed)
    }
}

/// The SQP solver; owns its Clarabel workspace, reused between steps.
pub struct SqpSolver {
    settings: SqpSettings,
    qp: DefaultSolver<f64>,
    budget: Budget,
    p_values: Vec<f64>,
    q_values: Vec<f64>,
    b_values: Vec<f64>,
    /// The active set of the last QP solved, the first guess for the next one.
    active: ActiveSet,
}

impl std::fmt::Debug for SqpSolver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SqpSolver").field("settings", &self.settings).finish()
    }
}

fn upper_triangle_pattern(values: &[f64]) -> CscMatrix<f64> {
    let n = N_JOINTS;
    let mut colptr = vec![0];
    let mut rowval = vec![];
    for j in 0..n {
        rowval.extend(0..=j);
        colptr.push(rowval.len());
    }
    CscMatrix::new(n, n, colptr, rowval, values.to_vec())
}

fn clarabel_settings(s: &SqpSettings) -> Result<DefaultSettings<f64>, String> {
    DefaultSettingsBuilder::default()
        .verbose(false)
        .presolve_enable(false)
        .max_iter(s.qp_max_iterations)
        .build()
        .map_err(|e| format!("clarabel settings: {e}"))
}

impl SqpSolver {
    /// Build the solver and its QP workspace.
    pub fn new(settings: SqpSettings) -> Result<Self, String> {
        settings.validate()?;
        let n = N_JOINTS;
        // Identity Hessian to start; only the values change later.
        let mut p_values = Vec::with_capacity(n * (n + 1) / 2);
        for j in 0..n {
            for i in 0..=j {
                p_values.push(if i == j { 1.0 } else { 0.0 });
            }
        }
        let p = upper_triangle_pattern(&p_values);
        // A = [I; -I]: column j has +1 in row j and -1 in row n + j.
        let colptr: Vec<usize> = (0..=n).map(|j| 2 * j).collect();
        let rowval: Vec<usize> = (0..n).flat_map(|j| [j, n + j]).collect();
        let nzval: Vec<f64> = (0..n).flat_map(|_| [1.0, -1.0]).collect();
        let a = CscMatrix::new(NC, n, colptr, rowval, nzval);
        let q_values = vec![0.0; n];
        let b_values = vec![1.0; NC];
        let cones = [SupportedConeT::NonnegativeConeT(NC)];
        let mut qp = DefaultSolver::new(&p, &q_values, &a, &b_values, &cones, clarabel_settings(&settings)?)
            .map_err(|e| format!("clarabel setup: {e}"))?;
        let budget = Budget::new();
        let watch = budget.clone();
        qp.set_termination_callback(move |info: &clarabel::solver::DefaultInfo<f64>| watch.spent(info.iterations));
        // Warm-up: one solve of the setup data (min ½|x|² in the unit box, x = 0), so the
        // solver's lazy first-solve work (timer maps, page faults of its workspace) happens
        // here rather than in the first control step.
        qp.solve();
        if !matches!(qp.solution.status, SolverStatus::Solved) {
            return Err(format!("clarabel warm-up solve: {:?}", qp.solution.status));
        }
        Ok(Self {
            settings,
            qp,
            budget,
            p_values,
            q_values,
            b_values,
            active: NONE_ACTIVE,
        })
    }

    /// Forget the warm start (the last QP's active set), so that the next solve starts as a
    /// new solver's would: a reset controller then steps exactly as a new one.
    pub fn forget(&mut self) {
        self.active = NONE_ACTIVE;
    }

    /// The settings.
    pub fn settings(&self) -> &SqpSettings {
        &self.settings
    }

    fn solve_qp(
        &mut self,
        h: &Matrix7,
        g: &JointVector,
        lo: &JointVector,
        hi: &JointVector,
    ) -> Result<QpStep, QpError> {
        let n = N_JOINTS;
        let h = (h + h.transpose()) * 0.5;
        if !(h
            .iter()
            .chain(g.iter())
            .chain(lo.iter())
            .chain(hi.iter())
            .all(|x| x.is_finite()))
        {
            return Err(QpError::Failed(QpFailure::NonFiniteData));
        }
        let clamp = |x: &JointVector| x.zip_zip_map(lo, hi, |v, l, u| v.clamp(l, u));
        if self.settings.active_set_warm_start {
            if let Some((x, set)) = solve_from_guesses(&h, g, lo, hi, &self.active) {
                self.active = set;
                return Ok(QpStep {
                    dq: clamp(&x),
                    qp_iterations: 0,
                    clarabel: false,
                });
            }
        }
        let mut k = 0;
        for j in 0..n {
            for i in 0..=j {
                self.p_values[k] = h[(i, j)];
                k += 1;
            }
        }
        for i in 0..n {
            self.q_values[i] = g[i];
            self.b_values[i] = hi[i];
            self.b_values[n + i] = -lo[i];
        }
        let failed = |_: clarabel::solver::DataUpdateError| QpError::Failed(QpFailure::DataUpdate);
        self.qp.update_P(&self.p_values).map_err(failed)?;
        self.qp.update_q(&self.q_values).map_err(failed)?;
        self.qp.update_b(&self.b_values).map_err(failed)?;
        self.qp.solve();
        let sol = &self.qp.solution;
        match sol.status {
            SolverStatus::Solved | SolverStatus::AlmostSolved => {}
            SolverStatus::CallbackTerminated => return Err(QpError::OutOfBudget(sol.iterations)),
            s => return Err(QpError::Failed(QpFailure::Solver(s))),
        }
        let dq = clamp(&JointVector::from_fn(|i, _| sol.x[i]));
        if dq.iter().all(|x| x.is_finite()) {
            self.active = active_set_of(&dq, lo, hi);
            Ok(QpStep {
                dq,
                qp_iterations: sol.iterations,
                clarabel: true,
            })
        } else {
            Err(QpError::Failed(QpFailure::NonFiniteSolution))
        }
    }

    /// Minimise the weighted costs from `q_start` with q in the box [lo, hi].
    /// `q_start` should lie in the box (the previous command does). Never panics; a
    /// failure is reported in the status with `q = q_start`. Stops at a budget (see the
    /// module doc) with the last completed iterate.
    pub fn solve(
        &mut self,
        kin: &dyn Kinematics,
        q_start: &JointVector,
        lo: &JointVector,
        hi: &JointVector,
        targets: &Targets,
        weights: &CostWeights,
    ) -> SqpSolution {
        let t0 = Instant::now();
        let time_budget =
            (self.settings.time_budget_us > 0.0).then(|| Duration::from_secs_f64(self.settings.time_budget_us * 1e-6));
        self.budget.set_deadline(time_budget.map(|b| t0 + b));
        let mut q = *q_start;
        let mut iterations = 0;
        let mut qp_iterations: u32 = 0;
        let mut clarabel_qps = 0;
        let mut status = SqpStatus::IterationLimit;
        while iterations < self.settings.max_iterations {
            let qp_iterations_left = self.settings.max_total_qp_iterations.saturating_sub(qp_iterations);
            if qp_iterations_left == 0 {
                status = SqpStatus::QpIterationBudget;
                break;
            }
            if time_budget.is_some_and(|b| t0.elapsed() >= b) {
                status = SqpStatus::TimeBudget;
                break;
            }
            self.budget.set_qp_iterations(qp_iterations_left);
            let (pose, jac) = match kin.fk_jacobian(&q) {
                Ok(x) => x,
                Err(_) => {
                    status = SqpStatus::Kinematics;
                    break;
                }
            };
            let (h, g) = quadratic_model(&pose, &jac, &q, targets, weights, self.settings.regularization);
            match self.solve_qp(&h, &g, &(lo - q), &(hi - q)) {
                Ok(QpStep {
                    dq,
                    qp_iterations: it,
                    clarabel,
                }) => {
                    q += dq;
                    iterations += 1;
                    qp_iterations = qp_iterations.saturating_add(it);
                    clarabel_qps += usize::from(clarabel);
                    if dq.amax() < self.settings.tolerance_rad {
                        status = SqpStatus::Converged;
                        break;
                    }
                }
                Err(QpError::OutOfBudget(it)) => {
                    qp_iterations = qp_iterations.saturating_add(it);
                    status = if it >= qp_iterations_left {
                        SqpStatus::QpIterationBudget
                    } else {
                        SqpStatus::TimeBudget
                    };
                    break;
                }
                Err(QpError::Failed(e)) => {
                    status = SqpStatus::QpFailed(e);
                    break;
                }
            }
        }
        if !status.is_usable() {
            q = *q_start;
        }
        let costs = kin.fk(&q).map(|p| evaluate(&p, &q, targets)).unwrap_or([f64::NAN; 5]);
        SqpSolution {
            q,
            status,
            iterations,
            qp_iterations,
            clarabel_qps,
            solve_time_us: t0.elapsed().as_secs_f64() * 1e6,
            costs,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::docking::geometry::InsertionAxis;
    use crate::kinematics::lbr::{LbrModel, ToolParams};
    use crate::kinematics::LbrKinematics;
    use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

    fn setup() -> (LbrKinematics, JointVector, Targets) {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let q = JointVector::from_column_slice(&[0.0, 0.6, 0.0, -1.2, 0.0, 0.9, 0.0]);
        let tip = kin.fk(&q).unwrap();
        let trocar = Isometry3::from_parts(
            Translation3::from(tip.translation.vector + Vector3::new(0.02, 0.01, -0.05)),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI - 0.1),
        );
        let axis = InsertionAxis::from_pose(&trocar);
        let t = Targets {
            axis,
            point: axis.point_at(-0.02),
            reference: Point3::origin(),
            q_prev: q,
            limits: None,
            pivot: None,
        };
        (kin, q, t)
    }

    #[test]
    fn converges_inside_a_wide_box_and_lowers_the_cost() {
        let (kin, q, t) = setup();
        let w = CostWeights {
            axis: 10.0,
            goal: 100.0,
            align: 1.0,
            step: 1e-3,
            reference: 0.0,
        };
        let mut s = SqpSolver::new(SqpSettings {
            max_iterations: 30,
            ..Default::default()
        })
        .unwrap();
        let lo = q.add_scalar(-0.5);
        let hi = q.add_scalar(0.5);
        let sol = s.solve(&kin, &q, &lo, &hi, &t, &w);
        assert!(sol.status.is_usable(), "{:?}", sol.status);
        assert_eq!(sol.status, SqpStatus::Converged);
        let weighted = |qq: &JointVector| {
            let c = evaluate(&kin.fk(qq).unwrap(), qq, &t);
            c.iter().zip(w.as_array()).map(|(c, w)| c * w).sum::<f64>()
        };
        let (before, after) = (weighted(&q), weighted(&sol.q));
        assert!(after < 0.5 * before, "{after} vs {before}");
        // A local minimum: no small feasible move of any joint lowers the cost.
        for i in 0..7 {
            for d in [-1e-4, 1e-4] {
                let mut qq = sol.q;
                qq[i] += d;
                if qq[i] >= lo[i] && qq[i] <= hi[i] {
                    assert!(weighted(&qq) >= after - 1e-9, "joint {i} {d}");
                }
            }
        }
        assert!((0..7).all(|i| sol.q[i] >= lo[i] - 1e-12 && sol.q[i] <= hi[i] + 1e-12));
    }

    #[test]
    fn tight_box_is_respected_and_rti_takes_one_qp() {
        let (kin, q, t) = setup();
        let w = CostWeights {
            axis: 10.0,
            goal: 100.0,
            align: 1.0,
            step: 1e-3,
            reference: 0.0,
        };
        let mut s = SqpSolver::new(SqpSettings::rti()).unwrap();
        let lo = q.add_scalar(-0.001);
        let hi = q.add_scalar(0.001);
        let sol = s.solve(&kin, &q, &lo, &hi, &t, &w);
        assert_eq!(sol.iterations, 1);
        assert!((sol.q - q).amax() <= 0.001 + 1e-12);
    }

    fn weights() -> CostWeights {
        CostWeights {
            axis: 10.0,
            goal: 100.0,
            align: 1.0,
            step: 1e-3,
            reference: 0.0,
        }
    }

    /// Kinematics that stall (sleep) from the `slow_from`-th call of `fk_jacobian` on, as a
    /// preempted or overloaded step would.
    struct Stalling {
        inner: LbrKinematics,
        calls: std::sync::atomic::AtomicUsize,
        slow_from: usize,
        stall: Duration,
    }

    impl Kinematics for Stalling {
        fn joint_names(&self) -> &[String] {
            self.inner.joint_names()
        }
        fn limits(&self) -> &crate::kinematics::JointLimits {
            self.inner.limits()
        }
        fn fk(&self, q: &JointVector) -> Result<nalgebra::Isometry3<f64>, crate::kinematics::KinematicsError> {
            self.inner.fk(q)
        }
        fn fk_jacobian(
            &self,
            q: &JointVector,
        ) -> Result<(nalgebra::Isometry3<f64>, crate::kinematics::Jacobian), crate::kinematics::KinematicsError>
        {
            if self.calls.fetch_add(1, Ordering::Relaxed) + 1 >= self.slow_from {
                std::thread::sleep(self.stall);
            }
            self.inner.fk_jacobian(q)
        }
    }

    #[test]
    fn a_spent_budget_returns_the_start_point_as_a_usable_hold() {
        let (kin, q, t) = setup();
        let mut s = SqpSolver::new(SqpSettings {
            time_budget_us: 1e-3,
            ..Default::default()
        })
        .unwrap();
        let (lo, hi) = (q.add_scalar(-0.01), q.add_scalar(0.01));
        let start = q.add_scalar(0.004);
        let sol = s.solve(&kin, &start, &lo, &hi, &t, &weights());
        assert_eq!(sol.status, SqpStatus::TimeBudget);
        assert!(sol.status.is_usable());
        assert_eq!(sol.status.as_text(), "time_budget");
        assert_eq!((sol.iterations, sol.qp_iterations), (0, 0));
        assert_eq!(sol.q, start, "no QP completed: the start point, unchanged");
        assert!(sol.costs.iter().all(|c| c.is_finite()));
    }

    #[test]
    fn a_qp_cut_off_by_the_budget_is_dropped_and_the_last_completed_iterate_kept() {
        let (kin, q, t) = setup();
        let (lo, hi) = (q.add_scalar(-0.05), q.add_scalar(0.05));
        // One QP, to compare with. Clarabel solves every QP here (no active-set warm
        // start), so that the deadline meets a QP in progress.
        let mut rti = SqpSolver::new(SqpSettings {
            active_set_warm_start: false,
            ..SqpSettings::rti()
        })
        .unwrap();
        let one = rti.solve(&kin, &q, &lo, &hi, &t, &weights());
        assert_eq!(one.status, SqpStatus::IterationLimit);
        assert!((one.q - q).amax() > 1e-4, "the first QP moves");
        // The second linearisation stalls past the budget, so the second QP is stopped
        // by the deadline: the result is the first QP's iterate, not garbage, not the start.
        let stalling = Stalling {
            inner: kin,
            calls: Default::default(),
            slow_from: 2,
            stall: Duration::from_millis(60),
        };
        let mut s = SqpSolver::new(SqpSettings {
            max_iterations: 10,
            time_budget_us: 40_000.0,
            active_set_warm_start: false,
            ..Default::default()
        })
        .unwrap();
        let sol = s.solve(&stalling, &q, &lo, &hi, &t, &weights());
        assert_eq!(sol.status, SqpStatus::TimeBudget);
        assert_eq!(sol.iterations, 1);
        assert!((sol.q - one.q).amax() < 1e-12, "{} vs {}", sol.q, one.q);
        assert!((0..7).all(|i| sol.q[i] >= lo[i] && sol.q[i] <= hi[i]));
        assert!(sol.solve_time_us >= 60_000.0);
        // The deadline is per solve: the same solver converges on the next, unhurried one.
        let kin = stalling.inner;
        let sol = s.solve(&kin, &q, &q.add_scalar(-0.5), &q.add_scalar(0.5), &t, &weights());
        assert_eq!(sol.status, SqpStatus::Converged);
    }

    /// The real-time loop's budget of allocations: a QP the active set settles allocates
    /// nothing; a QP Clarabel solves allocates once, inside Clarabel (its solve timers
    /// drop and re-create a sub-timer table on every solve, clarabel 0.11). Any more is
    /// ours and fails here.
    #[test]
    fn a_solve_allocates_nothing_of_its_own() {
        let (kin, q, t) = setup();
        let (lo, hi) = (q.add_scalar(-0.05), q.add_scalar(0.05));
        let count = |s: &mut SqpSolver, start: &JointVector| {
            let before = crate::test_alloc::allocations_on_this_thread();
            let sol = s.solve(&kin, start, &lo, &hi, &t, &weights());
            (crate::test_alloc::allocations_on_this_thread() - before, sol)
        };
        let mut clarabel = SqpSolver::new(SqpSettings {
            active_set_warm_start: false,
            ..SqpSettings::rti()
        })
        .unwrap();
        let mut warm = SqpSolver::new(SqpSettings::rti()).unwrap();
        let mut settled = 0;
        for k in 0..5 {
            let start = q.add_scalar(0.001 * f64::from(k));
            let (n, sol) = count(&mut clarabel, &start);
            assert!(sol.status.is_usable(), "{:?}", sol.status);
            assert!(sol.clarabel_qps > 0, "Clarabel did not solve");
            assert!(n <= 1, "solve {k} with Clarabel: {n} allocations");
            let (n, sol) = count(&mut warm, &start);
            if sol.clarabel_qps == 0 {
                assert_eq!(n, 0, "solve {k} settled by the active set: {n} allocations");
                settled += 1;
            }
        }
        assert!(settled >= 3, "the active set settled only {settled} of 5");
    }

    #[test]
    fn settings_reject_bad_budgets() {
        for b in [-1.0, f64::NAN, f64::INFINITY, 2e9] {
            let s = SqpSettings {
                time_budget_us: b,
                ..Default::default()
            };
            assert!(s.validate().is_err(), "{b}");
            assert!(SqpSolver::new(s).is_err(), "{b}");
        }
        let none = SqpSettings {
            time_budget_us: 0.0,
            ..Default::default()
        };
        assert!(none.validate().is_ok(), "0 = no time budget");
        let zero_work = SqpSettings {
            max_total_qp_iterations: 0,
            ..Default::default()
        };
        assert!(zero_work.validate().is_err());
    }

    #[test]
    fn the_iteration_budget_cuts_deterministically_and_keeps_the_last_completed_iterate() {
        let (kin, q, t) = setup();
        let (lo, hi) = (q.add_scalar(-0.05), q.add_scalar(0.05));
        // The budget counts Clarabel's iterations: Clarabel solves every QP here.
        let one = SqpSolver::new(SqpSettings {
            active_set_warm_start: false,
            ..SqpSettings::rti()
        })
        .unwrap()
        .solve(&kin, &q, &lo, &hi, &t, &weights());
        assert!(one.qp_iterations > 3);
        let budgeted = |total: u32| {
            SqpSolver::new(SqpSettings {
                max_iterations: 10,
                max_total_qp_iterations: total,
                active_set_warm_start: false,
                ..Default::default()
            })
            .unwrap()
            .solve(&kin, &q, &lo, &hi, &t, &weights())
        };
        // Room for the first QP and two iterations of the second: the second is cut off
        // and dropped; the result is exactly the first QP's.
        let sol = budgeted(one.qp_iterations + 2);
        assert_eq!(sol.status, SqpStatus::QpIterationBudget);
        assert!(sol.status.is_usable());
        assert_eq!(sol.status.as_text(), "qp_iteration_budget");
        assert_eq!((sol.iterations, sol.qp_iterations), (1, one.qp_iterations + 2));
        assert_eq!(sol.q, one.q);
        // Exactly the first QP's iterations: it is stopped on its last one, before the
        // convergence check (the budget is a hard bound), so nothing completed.
        let sol = budgeted(one.qp_iterations);
        assert_eq!(sol.status, SqpStatus::QpIterationBudget);
        assert_eq!((sol.iterations, sol.qp_iterations), (0, one.qp_iterations));
        assert_eq!(sol.q, q);
        // Too little for the first QP: the start point, unchanged, and still usable.
        let sol = budgeted(1);
        assert_eq!(sol.status, SqpStatus::QpIterationBudget);
        assert_eq!((sol.iterations, sol.qp_iterations), (0, 1));
        assert_eq!(sol.q, q);
        // Deterministic: the same budget, the same answer.
        assert_eq!(budgeted(one.qp_iterations + 2).q, budgeted(one.qp_iterations + 2).q);
    }

    /// A closed loop with perfect tracking in a tight step box (0.004 rad a step), so that
    /// joints sit on their bounds in many steps. Every QP of the warm-started solver is
    /// also given to Clarabel alone: the warm start's solution never costs more, and
    /// Clarabel's only by its tolerance. The SQP results cost the same to 1e-6, and
    /// Clarabel is called for a minority of the QPs only.
    #[test]
    fn the_active_set_warm_start_finds_clarabels_solutions() {
        let (kin, mut q, t) = setup();
        let solver = |warm: bool| {
            SqpSolver::new(SqpSettings {
                active_set_warm_start: warm,
                ..Default::default()
            })
            .unwrap()
        };
        let (mut warm, mut cold, mut cold_sqp) = (solver(true), solver(false), solver(false));
        let w = weights();
        let total = |q: &JointVector, t: &Targets| {
            let c = evaluate(&kin.fk(q).unwrap(), q, t);
            c.iter().zip(w.as_array()).map(|(c, w)| c * w).sum::<f64>()
        };
        let (mut qps, mut clarabel, mut bound_steps) = (0, 0, 0);
        let mut worst_gap = f64::NEG_INFINITY;
        for k in 0..150 {
            let (lo, hi) = (q.add_scalar(-0.004), q.add_scalar(0.004));
            let t = Targets { q_prev: q, ..t };
            // QP by QP, along the warm-started solver's own iterates.
            let mut qk = q;
            for _ in 0..3 {
                let (pose, jac) = kin.fk_jacobian(&qk).unwrap();
                let (h, g) = quadratic_model(&pose, &jac, &qk, &t, &w, 1e-6);
                let (l, u) = (lo - qk, hi - qk);
                let a = warm.solve_qp(&h, &g, &l, &u).ok().unwrap();
                let b = cold.solve_qp(&h, &g, &l, &u).ok().unwrap();
                assert!(b.clarabel);
                let f = |x: &JointVector| 0.5 * x.dot(&(h * x)) + g.dot(x);
                let (fa, fb) = (f(&a.dq), f(&b.dq));
                // The certified step is the minimiser: it costs no more than Clarabel's,
                // and Clarabel's, off by its tolerance, costs at most about 1e-8 more. For a
                // strictly convex QP, f(b) - f(a) >= ½ (b - a)^T H (b - a) when a is the
                // minimiser, a check of optimality in every direction. (The steps may still
                // differ by 1e-3 rad along the Hessian's weakest direction, the arm's
                // redundancy held only by w4, where the cost hardly changes.)
                assert!(fa <= fb + 1e-15, "step {k}: QP cost {fa} vs Clarabel's {fb}");
                assert!(fb - fa <= 1e-8, "step {k}: QP cost {fa} vs Clarabel's {fb}");
                let d = b.dq - a.dq;
                assert!(0.5 * d.dot(&(h * d)) <= (fb - fa) * (1.0 + 1e-6) + 1e-15, "step {k}");
                worst_gap = worst_gap.max(fa - fb);
                assert!(fa <= fb + 1e-12 * (1.0 + fb.abs()), "step {k}: QP cost {fa} vs {fb}");
                qps += 1;
                clarabel += usize::from(a.clarabel);
                qk += a.dq;
            }
            // The whole solve.
            let a = warm.solve(&kin, &q, &lo, &hi, &t, &w);
            let b = cold_sqp.solve(&kin, &q, &lo, &hi, &t, &w);
            assert!(
                a.status.is_usable() && b.status.is_usable(),
                "{:?} {:?}",
                a.status,
                b.status
            );
            assert_eq!(
                b.clarabel_qps, b.iterations,
                "without the warm start Clarabel solves every QP"
            );
            let (fa, fb) = (total(&a.q, &t), total(&b.q, &t));
            assert!((fa - fb).abs() <= 1e-6 * fb, "step {k}: cost {fa} vs Clarabel's {fb}");
            assert!((0..7).all(|i| a.q[i] >= lo[i] && a.q[i] <= hi[i]));
            bound_steps += usize::from((0..7).any(|i| (a.q[i] - q[i]).abs() > 0.004 - 1e-9));
            q = a.q;
        }
        assert!(bound_steps >= 10, "the box must be active in some steps: {bound_steps}");
        assert!(clarabel * 2 < qps, "Clarabel solved {clarabel} of {qps} QPs");
        eprintln!(
            "Clarabel solved {clarabel} of {qps} QPs; a bound active in {bound_steps} of 150 steps; \
             QP cost, warm start minus Clarabel, at most {worst_gap:.2e}"
        );
    }

    #[test]
    fn bad_data_fails_safely() {
        let (kin, q, mut t) = setup();
        t.point = Point3::new(f64::NAN, 0.0, 0.0);
        let w = CostWeights {
            axis: 1.0,
            goal: 1.0,
            align: 1.0,
            step: 1e-3,
            reference: 0.0,
        };
        let mut s = SqpSolver::new(SqpSettings::default()).unwrap();
        let sol = s.solve(&kin, &q, &q.add_scalar(-0.1), &q.add_scalar(0.1), &t, &w);
        assert!(!sol.status.is_usable());
        assert_eq!(sol.q, q);
        let mut bad_q = q;
        bad_q[0] = f64::INFINITY;
        let sol = s.solve(&kin, &bad_q, &q, &q, &t, &w);
        assert!(matches!(sol.status, SqpStatus::Kinematics));
        assert!(SqpSolver::new(SqpSettings {
            max_iterations: 0,
            ..Default::default()
        })
        .is_err());
    }
}
