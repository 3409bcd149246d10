//! The docking controller: one `step` per control period turns the measured joints, the
//! external torques and the trocar pose into a guarded joint command.
//!
//! Per step: check the inputs (fresh, finite) -> tip force from torques -> admittance
//! reference r -> phase target on the insertion axis -> SQP (costs c1..c5, joint limits with
//! margin, per-step velocity box) -> guard the command -> supervisor transitions. Anything
//! wrong gives a hold at the last safe command with the reason in the output; nothing moves
//! before [`Controller::start`].
//!
//! **Phases.** APPROACH moves the tip to a stand-off point on the axis outside the port,
//! aligning the scope on the way, with a target point that advances at a bounded speed (the
//! tip never slides across the trocar face, and never leaps). INSERT advances the target
//! along the axis to the goal depth with c1 keeping the tip on the axis; the axial force
//! slows the advance but never stops it, and the lateral force moves r so the tip yields
//! sideways (see [`crate::control::admittance`]). DONE when the tip is within the position and angle
//! tolerance of the goal, or when it has settled at the goal depth held off the estimated
//! axis by the port itself (a biased trocar estimate; see [`crate::control::seated`]).
//!
//! **Linearisation point.** The SQP starts from the previous command, not the measured
//! position: the command is what the position-controlled arm tracks, the velocity box is
//! relative to it, and a lagging measurement then never causes a jump. Because commands
//! advance from the last command, the guard also holds while a measured joint is more than
//! `guard.max_tracking_error` from it (the arm stopped following); the hold clears once the
//! arm has caught up.

use nalgebra::{Isometry3, Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::control::admittance::{Admittance, AdmittanceParams};
use crate::control::geometry::{pose_is_finite, InsertionAxis};
use crate::control::guard::{CommandGuard, GuardParams, HoldReason};
use crate::control::metrics::ForceMetric;
use crate::control::seated::{SeatedCheck, SeatedParams, TipState};
use crate::control::sqp::{CostWeights, LimitAvoidance, SqpSettings, SqpSolver, Targets};
pub use crate::control::supervisor::Phase;
use crate::control::supervisor::Supervisor;
use crate::kinematics::{JointLimits, JointVector, Kinematics};

/// Errors in the controller's parameters.
#[derive(Debug, thiserror::Error)]
pub enum ParamError {
    /// The YAML did not parse or had unknown fields.
    #[error("controller YAML: {0}")]
    Yaml(#[from] serde_yaml::Error),
    /// A value is out of range.
    #[error("controller parameter: {0}")]
    Invalid(String),
}

/// Every parameter of the controller (`config/controller.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControllerParams {
    /// Control period, s.
    pub dt: f64,
    /// Force feedback on (c5 active with the weights below) or off (w5 = 0).
    pub force_feedback: bool,
    /// Weights during APPROACH.
    pub approach_weights: CostWeights,
    /// Weights during INSERT.
    pub insert_weights: CostWeights,
    /// Goal depth past the port along the axis, m.
    pub insertion_depth: f64,
    /// Stand-off distance of the approach point before the port, m.
    pub standoff: f64,
    /// Speed of the approach target point, m/s.
    pub approach_speed: f64,
    /// Speed of the insertion target point, m/s.
    pub insert_speed: f64,
    /// APPROACH -> INSERT when the tip is this close to the stand-off point, m.
    pub approach_tolerance: f64,
    /// ... and the optical axis within this angle of the insertion axis, deg.
    pub approach_angle_tolerance_deg: f64,
    /// DONE when the tip is this close to the goal, m.
    pub goal_tolerance: f64,
    /// ... and the optical axis within this angle, deg.
    pub goal_angle_tolerance_deg: f64,
    /// DONE also for a scope seated in the port beside a biased trocar estimate; see
    /// [`crate::control::seated`].
    pub seated: SeatedParams,
    /// Time constant of a first-order filter on the trocar pose, s (0 = none).
    pub trocar_filter_time_constant: f64,
    /// Hold when external torques are missing or stale (force monitoring blind).
    pub require_torques: bool,
    /// After a force stop, back out along the axis by this distance, m (0 = stay).
    pub retreat_distance: f64,
    /// Weight of the joint-limit avoidance cost (0 = off); see [`LimitAvoidance`].
    pub limit_avoidance_weight: f64,
    /// Fraction of each joint's half range (inside the guard's margin) where it starts.
    pub limit_avoidance_zone: f64,
    /// Hold (latched) when the tip has sat at the stand-off point this long without
    /// reaching the alignment tolerance (e.g. a joint limit in the way), s.
    pub approach_stall_timeout: f64,
    /// Force estimate and admittance law.
    pub admittance: AdmittanceParams,
    /// Safety guard.
    pub guard: GuardParams,
    /// SQP settings.
    pub sqp: SqpSettings,
}

impl Default for ControllerParams {
    fn default() -> Self {
        Self {
            dt: 0.01,
            force_feedback: true,
            approach_weights: CostWeights {
                axis: 0.0,
                goal: 1000.0,
                align: 5.0,
                step: 0.05,
                reference: 300.0,
            },
            insert_weights: CostWeights {
                axis: 1000.0,
                goal: 300.0,
                align: 20.0,
                step: 0.05,
                reference: 300.0,
            },
            insertion_depth: 0.03,
            standoff: 0.02,
            approach_speed: 0.08,
            insert_speed: 0.03,
            approach_tolerance: 0.002,
            approach_angle_tolerance_deg: 1.0,
            goal_tolerance: 0.001,
            goal_angle_tolerance_deg: 0.5,
            seated: SeatedParams::default(),
            trocar_filter_time_constant: 0.0,
            require_torques: true,
            retreat_distance: 0.0,
            limit_avoidance_weight: 1.0,
            limit_avoidance_zone: 0.9,
            approach_stall_timeout: 3.0,
            admittance: AdmittanceParams::default(),
            guard: GuardParams::default(),
            sqp: SqpSettings::default(),
        }
    }
}

impl ControllerParams {
    /// Parse YAML (missing fields take their defaults) and validate.
    pub fn from_yaml_str(s: &str) -> Result<Self, ParamError> {
        let p: Self = serde_yaml::from_str(s)?;
        p.validate().map_err(ParamError::Invalid)?;
        Ok(p)
    }

    /// Check every range; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        let pos = |n: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(format!("{n} must be > 0, got {v}"))
            }
        };
        let nonneg = |n: &str, v: f64| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(format!("{n} must be >= 0, got {v}"))
            }
        };
        pos("dt", self.dt)?;
        if self.dt > 0.1 {
            return Err(format!("dt must be <= 0.1 s, got {}", self.dt));
        }
        self.approach_weights.validate("approach_weights")?;
        self.insert_weights.validate("insert_weights")?;
        pos("insertion_depth", self.insertion_depth)?;
        nonneg("standoff", self.standoff)?;
        pos("approach_speed", self.approach_speed)?;
        pos("insert_speed", self.insert_speed)?;
        pos("approach_tolerance", self.approach_tolerance)?;
        pos("approach_angle_tolerance_deg", self.approach_angle_tolerance_deg)?;
        pos("goal_tolerance", self.goal_tolerance)?;
        pos("goal_angle_tolerance_deg", self.goal_angle_tolerance_deg)?;
        self.seated.validate()?;
        nonneg("trocar_filter_time_constant", self.trocar_filter_time_constant)?;
        nonneg("retreat_distance", self.retreat_distance)?;
        nonneg("limit_avoidance_weight", self.limit_avoidance_weight)?;
        pos("approach_stall_timeout", self.approach_stall_timeout)?;
        if !(0.0..1.0).contains(&self.limit_avoidance_zone) {
            return Err(format!(
                "limit_avoidance_zone must be in [0, 1), got {}",
                self.limit_avoidance_zone
            ));
        }
        self.admittance.validate()?;
        self.guard.validate()?;
        self.sqp.validate()
    }
}

/// A value with the time it was measured, s (same clock as [`ControlInput::now`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stamped<T> {
    /// Measurement time, s.
    pub stamp: f64,
    /// The value.
    pub value: T,
}

/// The inputs of one control step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControlInput {
    /// Now, s.
    pub now: f64,
    /// Measured joint positions.
    pub joints: Option<Stamped<JointVector>>,
    /// External joint torques, Nm.
    pub tau_ext: Option<Stamped<JointVector>>,
    /// Trocar pose in the base frame (origin = port, z = insertion direction into the body).
    pub trocar: Option<Stamped<Isometry3<f64>>>,
}

/// The outputs of one control step.
#[derive(Debug, Clone, PartialEq)]
pub struct ControlOutput {
    /// `None`: send nothing (idle, or no joint state yet). `Some`: a guarded joint position
    /// command (during a hold, the last safe command).
    pub command: Option<JointVector>,
    /// The phase after this step.
    pub phase: Phase,
    /// Reason of the last hold or abort.
    pub reason: Option<String>,
    /// Unweighted c1..c5 at the solution.
    pub costs: [f64; 5],
    /// QPs solved this step.
    pub iterations: usize,
    /// Interior-point iterations this step, over all its QPs.
    pub qp_iterations: u32,
    /// QPs of this step solved by Clarabel (the others from a proven active set).
    pub clarabel_qps: usize,
    /// SQP wall time, µs.
    pub solve_time_us: f64,
    /// SQP status text ("converged", "iteration_limit", "time_budget",
    /// "qp_iteration_budget", "qp_failed: …", "not_run"); see [`crate::control::sqp::SqpStatus`].
    pub solver_status: String,
    /// Filtered tip force estimate, base frame, N.
    pub f_ext: Vector3<f64>,
    /// Admittance reference r.
    pub reference: Point3<f64>,
    /// Tip pose from the measured joints.
    pub tip: Isometry3<f64>,
    /// Goal point (NaN before a trocar pose).
    pub goal: Point3<f64>,
    /// M so far (time average of ||f_ext|| while moving), N.
    pub metric_m: f64,
}

/// The docking controller.
#[derive(Debug)]
pub struct Controller {
    params: ControllerParams,
    guard: CommandGuard,
    sqp: SqpSolver,
    admittance: Admittance,
    supervisor: Supervisor,
    metric: ForceMetric,
    last_command: Option<JointVector>,
    last_now: Option<f64>,
    trocar_filtered: Option<(Isometry3<f64>, f64)>,
    target: Option<Point3<f64>>,
    insert_s: f64,
    /// Time spent at the stand-off point without the alignment, s.
    stalled_for: f64,
    seated: SeatedCheck,
    /// Retreat after a force stop: (current target depth, final depth); NaN = not begun.
    retreat_s: Option<(f64, f64)>,
}

fn nan_point() -> Point3<f64> {
    Point3::new(f64::NAN, f64::NAN, f64::NAN)
}

impl Controller {
    /// A controller for an arm with `limits`.
    pub fn new(params: ControllerParams, limits: JointLimits) -> Result<Self, ParamError> {
        params.validate().map_err(ParamError::Invalid)?;
        let guard = CommandGuard::new(params.guard.clone(), &limits);
        let sqp = SqpSolver::new(params.sqp.clone()).map_err(ParamError::Invalid)?;
        Ok(Self {
            admittance: Admittance::new(params.admittance.clone()),
            params,
            guard,
            sqp,
            supervisor: Supervisor::new(),
            metric: ForceMetric::default(),
            last_command: None,
            last_now: None,
            trocar_filtered: None,
            target: None,
            insert_s: 0.0,
            stalled_for: 0.0,
            seated: SeatedCheck::default(),
            retreat_s: None,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &ControllerParams {
        &self.params
    }

    /// The current phase.
    pub fn phase(&self) -> Phase {
        self.supervisor.phase()
    }

    /// Start docking (from IDLE) or resume after a hold.
    pub fn start(&mut self) -> Result<(), String> {
        let was = self.supervisor.phase();
        self.supervisor.start()?;
        if was == Phase::Idle {
            self.metric = ForceMetric::default();
            self.target = None;
            self.admittance.reset();
            // A new run starts from where the arm is (it may have been moved by hand while
            // idle), not from the last command of the previous run.
            self.last_command = None;
        }
        self.retreat_s = None;
        Ok(())
    }

    /// Abort: hold for good until reset.
    pub fn abort(&mut self, why: &str) {
        self.supervisor.abort(why);
        self.retreat_s = None;
    }

    /// Back to IDLE; forgets the run (the last command is kept, so nothing jumps).
    pub fn reset(&mut self) {
        self.supervisor.reset();
        self.metric = ForceMetric::default();
        self.admittance.reset();
        self.target = None;
        self.retreat_s = None;
        self.trocar_filtered = None;
        self.seated.reset();
    }

    /// The force metric so far.
    pub fn metric(&self) -> &ForceMetric {
        &self.metric
    }

    fn output(&self, command: Option<JointVector>, tip: Isometry3<f64>, goal: Point3<f64>) -> ControlOutput {
        ControlOutput {
            command,
            phase: self.supervisor.phase(),
            reason: self.supervisor.reason().map(str::to_string),
            costs: [f64::NAN; 5],
            iterations: 0,
            qp_iterations: 0,
            clarabel_qps: 0,
            solve_time_us: 0.0,
            solver_status: "not_run".into(),
            f_ext: self.admittance.force(),
            reference: self.admittance.reference(&Point3::from(tip.translation.vector)),
            tip,
            goal,
            metric_m: self.metric.mean(),
        }
    }

    fn filtered_trocar(&mut self, pose: Isometry3<f64>, stamp: f64) -> Isometry3<f64> {
        let tc = self.params.trocar_filter_time_constant;
        let out = match self.trocar_filtered {
            Some((prev, t_prev)) if tc > 0.0 && stamp > t_prev => {
                let a = ((stamp - t_prev) / (tc + stamp - t_prev)).clamp(0.0, 1.0);
                let p = prev.translation.vector.lerp(&pose.translation.vector, a);
                let r = prev
                    .rotation
                    .try_slerp(&pose.rotation, a, 1e-9)
                    .unwrap_or(pose.rotation);
                Isometry3::from_parts(p.into(), r)
            }
            Some((prev, t_prev)) if tc > 0.0 && stamp <= t_prev => return prev,
            _ => pose,
        };
        self.trocar_filtered = Some((out, stamp));
        out
    }

    /// One control step. Never panics; see [`ControlOutput`].
    pub fn step(&mut self, kin: &dyn Kinematics, input: &ControlInput) -> ControlOutput {
        let now = input.now;
        let dt = match self.last_now {
            Some(t) if now.is_finite() && now > t => (now - t).min(self.params.dt),
            Some(_) => 0.0,
            None => self.params.dt,
        };
        if now.is_finite() {
            self.last_now = Some(self.last_now.map_or(now, |t| t.max(now)));
        }
        let no_tip = Isometry3::identity();
        let timeouts = self.params.guard.clone();

        // Joint state: without it there is nothing to command.
        let q_meas = match input.joints {
            None => return self.hold_or_idle(HoldReason::NoJointState, None, no_tip, nan_point()),
            Some(j) if !j.value.iter().all(|x| x.is_finite()) => {
                return self.hold_or_idle(HoldReason::NonFiniteJointState, None, no_tip, nan_point())
            }
            Some(j) if !CommandGuard::fresh(now - j.stamp, timeouts.joint_timeout) => {
                return self.hold_or_idle(
                    HoldReason::StaleJointState { age: now - j.stamp },
                    None,
                    no_tip,
                    nan_point(),
                )
            }
            Some(j) => j.value,
        };
        let (tip, jac) = match kin.fk_jacobian(&q_meas) {
            Ok(x) => x,
            Err(e) => {
                return self.hold_or_idle(HoldReason::Kinematics(e.to_string()), Some(q_meas), no_tip, nan_point())
            }
        };
        let prev = self.last_command.unwrap_or(q_meas);
        // The arm must follow the commands while they move (also during a retreat); an
        // unlatched hold keeps checking, so it resumes only once the arm has caught up.
        let ph = self.supervisor.phase();
        let commanding =
            ph.is_moving() || (ph == Phase::Hold && (!self.supervisor.is_latched() || self.retreat_s.is_some()));
        if commanding {
            if let Err(r) = self.guard.check_tracking(&q_meas, &prev) {
                return self.hold_or_idle(r, Some(prev), tip, nan_point());
            }
        }

        // Force: estimate, monitor, and the metric while moving.
        match input.tau_ext {
            Some(t)
                if t.value.iter().all(|x| x.is_finite())
                    && CommandGuard::fresh(now - t.stamp, timeouts.torque_timeout) =>
            {
                self.admittance.update_force(&jac, &t.value, dt);
            }
            Some(t) if self.params.require_torques => {
                let r = HoldReason::StaleTorques { age: now - t.stamp };
                return self.hold_or_idle(r, Some(prev), tip, nan_point());
            }
            None if self.params.require_torques => {
                let r = HoldReason::StaleTorques { age: f64::INFINITY };
                return self.hold_or_idle(r, Some(prev), tip, nan_point());
            }
            _ => {}
        }
        let f = self.admittance.force();
        if self.supervisor.phase().is_moving() {
            self.metric.add(f.norm(), dt);
        }
        if let Err(r) = self.guard.check_force(f.norm()) {
            if self.supervisor.phase().is_moving() {
                self.supervisor.hold(r.to_string(), true);
                if self.params.retreat_distance > 0.0 {
                    self.retreat_s = Some((f64::NAN, f64::NAN)); // begins from the tip depth below
                }
            }
        }

        // Trocar pose.
        let trocar = match input.trocar {
            None => return self.hold_or_idle(HoldReason::NoTrocarPose, Some(prev), tip, nan_point()),
            Some(p) if !pose_is_finite(&p.value) => {
                return self.hold_or_idle(HoldReason::BadTrocarPose, Some(prev), tip, nan_point())
            }
            Some(p) if !CommandGuard::fresh(now - p.stamp, timeouts.trocar_timeout) => {
                return self.hold_or_idle(
                    HoldReason::StaleTrocarPose { age: now - p.stamp },
                    Some(prev),
                    tip,
                    nan_point(),
                )
            }
            Some(p) => self.filtered_trocar(p.value, p.stamp),
        };
        let axis = InsertionAxis::from_pose(&trocar);
        let goal = axis.point_at(self.params.insertion_depth);
        let tip_p = Point3::from(tip.translation.vector);

        // Every input is good: an unlatched hold (stale data) resumes.
        self.supervisor.clear_hold();
        let phase = self.supervisor.phase();
        let retreating = phase == Phase::Hold && self.retreat_s.is_some();
        if !phase.is_moving() && !retreating {
            // Idle sends nothing; DONE, HOLD and ABORTED keep commanding the last command.
            self.last_command = if phase == Phase::Idle { None } else { Some(prev) };
            return self.output(self.last_command, tip, goal);
        }

        // Admittance reference from the force across the axis.
        let f_lat = axis.across(&f);
        let x = self.admittance.step(f_lat, dt);
        let reference = tip_p + x;

        // The target point of c2 for this phase.
        let p = &self.params;
        let standoff = axis.point_at(-p.standoff);
        let (weights, point) = if retreating {
            // Back out along the axis from where the stop happened, at the insertion speed.
            let (s_target, s_end) = match self.retreat_s {
                Some(s) if s.0.is_finite() => s,
                _ => {
                    let s_now = axis.depth_of(&tip_p);
                    (s_now, s_now - p.retreat_distance)
                }
            };
            let s_target = (s_target - p.insert_speed * dt).max(s_end);
            self.retreat_s = Some((s_target, s_end));
            let mut w = p.insert_weights;
            w.reference = 0.0;
            (w, axis.point_at(s_target))
        } else if phase == Phase::Approach {
            let from = self.target.unwrap_or(tip_p);
            let d = standoff - from;
            let step = p.approach_speed * dt;
            let t = if d.norm() > step {
                from + d * (step / d.norm())
            } else {
                standoff
            };
            self.target = Some(t);
            self.insert_s = -p.standoff;
            (p.approach_weights, t)
        } else {
            let f_axial_resisting = -f.dot(&axis.direction);
            let speed = p.insert_speed * self.admittance.insert_speed_ratio(f_axial_resisting);
            // Never run ahead of the tip by more than a few millimetres.
            let s_tip = axis.depth_of(&tip_p);
            self.insert_s = (self.insert_s + speed * dt)
                .min(p.insertion_depth)
                .min(s_tip.max(self.insert_s) + 0.005);
            let t = axis.point_at(self.insert_s);
            self.target = Some(t);
            (p.insert_weights, t)
        };
        let mut weights = weights;
        if !p.force_feedback {
            weights.reference = 0.0;
        }

        // Solve within the step box around the previous command.
        let step_dt = if dt > 0.0 { dt } else { 0.0 };
        let (lo, hi) = self.guard.step_box(&prev, step_dt);
        let start = prev.zip_zip_map(&lo, &hi, |q, l, h| q.clamp(l, h));
        let limits = LimitAvoidance {
            center: (self.guard.upper() + self.guard.lower()) * 0.5,
            half_range: ((self.guard.upper() - self.guard.lower()) * 0.5).map(|h| h.max(1e-3)),
            zone: p.limit_avoidance_zone,
            weight: p.limit_avoidance_weight,
        };
        let targets = Targets {
            axis,
            point,
            reference,
            q_prev: prev,
            limits: Some(limits),
        };
        let sol = self.sqp.solve(kin, &start, &lo, &hi, &targets, &weights);
        let mut out_cmd = prev;
        if !sol.status.is_usable() {
            self.supervisor
                .hold(HoldReason::SolverFailed(sol.status.as_text()).to_string(), false);
        } else if let Err(r) = self.guard.check_command(&sol.q, &prev, step_dt) {
            self.supervisor.hold(r.to_string(), true);
        } else {
            out_cmd = sol.q;
        }
        self.last_command = Some(out_cmd);

        // Transitions, judged on the measured tip.
        let angle = axis.alignment_error(&(tip.rotation * Vector3::z()));
        match self.supervisor.phase() {
            Phase::Approach if (tip_p - standoff).norm() < p.approach_tolerance => {
                if angle < p.approach_angle_tolerance_deg.to_radians() {
                    self.stalled_for = 0.0;
                    self.supervisor.approach_reached();
                } else {
                    self.stalled_for += dt;
                    if self.stalled_for > p.approach_stall_timeout {
                        self.stalled_for = 0.0;
                        let why = format!(
                            "cannot align at the stand-off point: {:.1} deg off after {:.1} s (a joint limit in the way? reposition the arm or the trocar)",
                            angle.to_degrees(),
                            p.approach_stall_timeout
                        );
                        self.supervisor.hold(why, true);
                    }
                }
            }
            Phase::Insert => {
                if (tip_p - goal).norm() < p.goal_tolerance && angle < p.goal_angle_tolerance_deg.to_radians() {
                    self.supervisor.goal_reached(None);
                } else {
                    let state = TipState {
                        tip: tip_p,
                        optical_axis: tip.rotation * Vector3::z(),
                        force: f,
                    };
                    let seated = self
                        .seated
                        .update(&p.seated, &axis, p.insertion_depth, p.goal_tolerance, &state, dt);
                    if let Some(s) = seated {
                        self.supervisor.goal_reached(Some(s.describe()));
                    }
                }
            }
            _ => {}
        }
        if self.supervisor.phase() != Phase::Insert {
            self.seated.reset();
        }

        let mut out = self.output(Some(out_cmd), tip, goal);
        out.costs = sol.costs;
        out.iterations = sol.iterations;
        out.qp_iterations = sol.qp_iterations;
        out.clarabel_qps = sol.clarabel_qps;
        out.solve_time_us = sol.solve_time_us;
        out.solver_status = sol.status.as_text();
        out.reference = reference;
        out
    }

    /// Hold (when moving) or stay idle, for `reason`; command `hold_at` when not idle.
    fn hold_or_idle(
        &mut self,
        reason: HoldReason,
        hold_at: Option<JointVector>,
        tip: Isometry3<f64>,
        goal: Point3<f64>,
    ) -> ControlOutput {
        self.supervisor.hold(reason.to_string(), false);
        let cmd = match self.supervisor.phase() {
            Phase::Idle => None,
            _ => self.last_command.or(hold_at),
        };
        if cmd.is_some() {
            self.last_command = cmd;
        }
        self.output(cmd, tip, goal)
    }
}
