//! The docking controller: one `step` per control period turns the measured joints, the
//! external torques and the trocar pose into a joint command, which leaves through the
//! command guard ([`Controller`] = [`Guarded`]`<`[`OptimalController`]`>`).
//!
//! Per step: check the inputs (fresh, finite) -> tip force from torques -> admittance
//! reference r -> phase target on the insertion axis -> SQP (costs c1..c5, joint limits with
//! margin, per-step velocity box) -> supervisor transitions; then the guard checks the
//! command. Anything wrong gives a hold at the last safe command with the reason in the
//! output; nothing moves before [`Controller::start`].
//!
//! **Phases.** APPROACH moves the tip to a stand-off point on the axis outside the port,
//! aligning the scope on the way, with a target point that advances at a bounded speed (the
//! tip never slides across the trocar face, and never leaps). INSERT advances the target
//! along the axis to the goal depth with c1 keeping the tip on the axis; the axial force
//! slows the advance but never stops it, and the lateral force moves r so the tip yields
//! sideways (see [`super::force::admittance`]). DONE when the tip is within the position and angle
//! tolerance of the goal, or when it has settled at the goal depth held off the estimated
//! axis by the port itself (a biased trocar estimate; see [`super::docking::seated`]).
//!
//! **Linearisation point.** The SQP starts from the previous command, not the measured
//! position: the command is what the position-controlled arm tracks, the velocity box is
//! relative to it, and a lagging measurement then never causes a jump. Because commands
//! advance from the last command, the controller also holds while a measured joint is more
//! than `guard.max_tracking_error_rad` from it (the arm stopped following); the hold clears
//! once the arm has caught up.

use nalgebra::{Isometry3, Point3, Vector3};

use super::docking::depth::{AxisFilter, DepthEstimate, DepthReport, Filters};
use super::docking::geometry::{pose_is_finite, InsertionAxis};
use super::docking::goal_window::GoalWindow;
use super::docking::metrics::ForceMetric;
use super::docking::seated::{SeatedCheck, TipState};
use super::force::admittance::Admittance;
use super::force::tare::{Tare, TareStep};
use super::io::{ControlInput, ControlOutput, SolveReport, Stamped};
use super::live::{self, LiveValues};
pub use super::params::{ControllerParams, ParamError};
use super::safety::guard::{CommandGuard, HoldReason};
use super::safety::guarded::{CommandSource, Guarded, StepContext};
use super::safety::motion::MotionLimiter;
use super::scope::pivot::{live_command, Pivot, PivotParams};
use super::sqp::{CostWeights, LimitAvoidance, PivotCost, SqpSolver, Targets};
use super::supervisor::{DoneNote, Phase, Supervisor};
use crate::kinematics::{Jacobian, JointLimits, JointVector, Kinematics};
use crate::signal::{StreamLowPass, TrackingFilter};

/// Retreat after a force stop: the current target depth and the final depth, m.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Retreat {
    depth: f64,
    end: f64,
}

/// Where the retreat after a force stop stands.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
enum RetreatState {
    /// No retreat.
    #[default]
    Off,
    /// A force stop asked for one: it begins from the tip's depth at the next step.
    Due,
    /// Backing out along the axis.
    Backing(Retreat),
}

impl RetreatState {
    /// Whether a retreat is due or under way.
    fn active(self) -> bool {
        self != Self::Off
    }
}

/// Everything one docking run changes; a new run is `RunState::default()`.
#[derive(Debug, Clone, Default)]
struct RunState {
    supervisor: Supervisor,
    admittance: Admittance,
    metric: ForceMetric,
    last_command: Option<JointVector>,
    /// The filtered trocar pose at the stamp of the last measurement.
    trocar_filtered: Option<(Isometry3<f64>, f64)>,
    /// The trocar position's tracking filter (made with the parameters at first use).
    trocar_track: Option<TrackingFilter<3>>,
    target: Option<Point3<f64>>,
    insert_depth: f64,
    /// Time spent at the stand-off point without the alignment, s.
    stalled_for: f64,
    seated: SeatedCheck,
    /// The tip's depth: refined at the seal, and its uncertainty.
    depth: DepthEstimate,
    /// The depth's report of the last INSERT step.
    depth_report: Option<DepthReport>,
    /// The DONE gate's last failing report at the goal, and how long ago the first failed, s:
    /// the gate judges on for `depth.gate_wait_s`, then holds.
    depth_failed: Option<(DepthReport, f64)>,
    /// The tip-to-goal error and the alignment angle, averaged over windows in INSERT.
    goal_window: GoalWindow,
    /// The commanded tip motion, for its limits.
    motion: MotionLimiter,
    tare: Tare,
    /// The retreat after a force stop.
    retreat: RetreatState,
    /// After DONE: the port held as the remote centre of motion.
    pivot: Option<Pivot>,
    /// A start resumed DONE or RETRACT from a hold: the law re-anchors at the measured tip.
    reanchor: bool,
    /// The measured joints when the force stop after docking fired: the held command walks
    /// back to them ([`OptimalController::pivot_force_stop`]).
    force_stop_at: Option<JointVector>,
}

/// An early end of a step: hold (or stay idle) for `reason`, commanding `hold_at`.
struct Early {
    reason: HoldReason,
    hold_at: Option<JointVector>,
    tip: Option<Isometry3<f64>>,
}

/// The measured arm of one step.
struct MeasuredArm {
    q: JointVector,
    tip: Isometry3<f64>,
    jac: Jacobian,
    /// The previous command (the measured joints at the start of a run).
    prev: JointVector,
}

/// The targets of c2 for the step's SQP solve: the axis, the target point and the
/// admittance's reference point.
struct AxisTargets {
    axis: InsertionAxis,
    point: Point3<f64>,
    reference: Point3<f64>,
}

/// How far ahead the force stop after docking looks, s: how long a force that rises at a
/// steady rate goes on rising after the estimate showed it, i.e. the lag of the estimate
/// behind the true force (the torques' low-pass `torque_filter_time_constant_s` plus the
/// estimate's first-order low-pass at `admittance.filter_cutoff_hz`, 1 / (2 pi f_c): each
/// first-order lag delays a ramp by its time constant), plus one control period (the
/// step whose command brakes), plus the arm's tracking lag `scope.arm_lag_s` (a position-mode
/// joint servo reaches a stopped command about that late). With the shipped values
/// 5 + 8 + 10 + 20 = 43 ms.
fn force_stop_lead(p: &ControllerParams) -> f64 {
    force_estimate_lag(p) + p.dt_s + p.scope.arm_lag_s
}

/// The lag of the force estimate behind the tip's force, s: the torques' low-pass and the
/// estimate's first-order low-pass (a first-order chain delays a ramp by the sum of its time
/// constants); the part of [`force_stop_lead`] that is the estimate's.
fn force_estimate_lag(p: &ControllerParams) -> f64 {
    let fc = p.admittance.filter_cutoff_hz;
    let estimate = if fc > 0.0 {
        1.0 / (2.0 * std::f64::consts::PI * fc)
    } else {
        0.0
    };
    p.torque_filter_time_constant_s + estimate
}

/// The trocar filter along the axis ([`OptimalController::filtered_trocar`]).
fn axis_filter(p: &ControllerParams) -> AxisFilter {
    if p.trocar_depth_filter_time_constant_s > 0.0 {
        AxisFilter::Tracking(p.trocar_depth_filter_time_constant_s)
    } else if p.trocar_filter_time_constant_s > 0.0 {
        AxisFilter::FirstOrder(p.trocar_filter_time_constant_s)
    } else {
        AxisFilter::None
    }
}

/// The docking controller, guarded: what the nodes, the trials and the tests run.
pub type Controller = Guarded<OptimalController>;

impl Guarded<OptimalController> {
    /// A guarded controller for an arm with `limits`.
    pub fn new(params: ControllerParams, limits: JointLimits) -> Result<Self, ParamError> {
        let guard = CommandGuard::new(params.guard.clone(), &limits);
        Ok(Self::wrap(OptimalController::new(params)?, guard))
    }

    /// The parameters.
    pub fn params(&self) -> &ControllerParams {
        &self.source().params
    }

    /// The force metric so far.
    pub fn metric(&self) -> &ForceMetric {
        &self.source().run.metric
    }

    /// The tip's depth as the last INSERT step knew it (its correction at the seal and its
    /// uncertainty); None before INSERT.
    pub fn depth(&self) -> Option<DepthReport> {
        self.source().run.depth_report
    }
}

/// The controller's low-pass of the raw external torques (`torque_filter_time_constant_s`,
/// [`StreamLowPass`]): applied to every sample in the order they arrived, at their own rate
/// (every FRI cycle, 1-2 ms), not once per control period, so it keeps the noise of the
/// samples between two steps out of the estimate. It belongs to the torque stream, not to a
/// run: a start or a reset keeps it, and a stamp that goes back (a new world, a driver
/// restart) starts it again at that sample.
#[derive(Debug, Clone)]
struct TorqueFilter {
    low_pass: StreamLowPass<7>,
    /// The newest sample fed: its stamp and the filter's output there.
    last: Option<(f64, JointVector)>,
}

impl TorqueFilter {
    fn new(time_constant: f64) -> Self {
        Self {
            low_pass: StreamLowPass::new(time_constant),
            last: None,
        }
    }

    /// Feed the step's new samples (`tau_ext` too when they did not carry it: a caller
    /// that hands the newest sample alone); the filtered torques at `tau_ext`'s stamp.
    fn feed(&mut self, input: &ControlInput) -> Option<Stamped<JointVector>> {
        for (stamp, x) in input.torque_samples.iter() {
            self.last = Some((*stamp, self.low_pass.update(*stamp, x)));
        }
        let t = input.tau_ext?;
        let value = match self.last {
            Some((stamp, y)) if stamp == t.stamp => y,
            _ => {
                let y = self.low_pass.update(t.stamp, &t.value);
                self.last = Some((t.stamp, y));
                y
            }
        };
        Some(Stamped { stamp: t.stamp, value })
    }
}

/// The paper's optimal control law with its phases (unguarded: run it as [`Controller`]).
#[derive(Debug)]
pub struct OptimalController {
    params: ControllerParams,
    sqp: SqpSolver,
    run: RunState,
    torques: TorqueFilter,
    /// A dry run: the arm is a ghost ([`Controller::set_dry_run`]).
    dry_run: bool,
}

impl Controller {
    /// Apply live-tuned values between two steps ([`crate::control::live`]): refused, with
    /// the reason, where the phase does not allow a change; otherwise the law and the guard
    /// use them from the next step. Allocates only to refuse.
    pub fn set_live(&mut self, values: &LiveValues) -> Result<(), String> {
        let phase = self.phase();
        let (law, guard) = self.parts_mut();
        live::check_phase(phase, &LiveValues::of(&law.params), values)?;
        values.write_to(&mut law.params);
        guard.set_force_stop(law.params.guard.force_stop_n);
        Ok(())
    }

    /// A dry run (`dry_run`): the arm the controller steers is a ghost that follows its
    /// commands and touches nothing, so it never meets the seal and the tip's depth is never
    /// verified. Where a docking would hold at the goal, DEPTH_UNCERTAIN, the dry run ends
    /// DONE with the note DEPTH_UNVERIFIED (the figure and its basis), so the rehearsal
    /// ends and says what the docking would do there.
    pub fn set_dry_run(&mut self, dry_run: bool) {
        self.parts_mut().0.dry_run = dry_run;
    }
}

impl OptimalController {
    /// The law with `params` (validated).
    pub fn new(params: ControllerParams) -> Result<Self, ParamError> {
        params.validate().map_err(|e| ParamError::new(super::params::WHAT, e))?;
        let sqp = SqpSolver::new(params.sqp.clone()).map_err(|e| ParamError::new(super::params::WHAT, e))?;
        Ok(Self {
            torques: TorqueFilter::new(params.torque_filter_time_constant_s),
            params,
            sqp,
            run: RunState::default(),
            dry_run: false,
        })
    }

    fn output(
        &self,
        command: Option<JointVector>,
        tip: Option<Isometry3<f64>>,
        goal: Option<Point3<f64>>,
    ) -> ControlOutput {
        let s = &self.run.supervisor;
        ControlOutput {
            command,
            phase: s.phase(),
            hold: s.reason().cloned(),
            note: s.note(),
            solve: None,
            f_ext: self.run.admittance.force(),
            reference: tip.map(|t| self.run.admittance.reference(&Point3::from(t.translation.vector))),
            tip,
            goal,
            metric_m: self.run.metric.mean(),
            pivot: None,
        }
    }

    /// The trocar pose filtered by its stamps: a first-order filter of time constant
    /// `trocar_filter_time_constant_s` on the pose, and along its axis, where breathing moves
    /// the port and no contact guides the tip, the second-order tracking filter of
    /// `trocar_depth_filter_time_constant_s` ([`TrackingFilter`]), which follows a moving port
    /// without the first-order filter's lag (0: the first-order filter along the axis too).
    /// A pose no newer than the last changes nothing.
    fn filtered_trocar(&mut self, pose: Isometry3<f64>, stamp: f64) -> Isometry3<f64> {
        let tc = self.params.trocar_filter_time_constant_s;
        let out = match self.run.trocar_filtered {
            Some((prev, t_prev)) if tc > 0.0 && stamp > t_prev => {
                let a = ((stamp - t_prev) / (tc + stamp - t_prev)).clamp(0.0, 1.0);
                let p = prev.translation.vector.lerp(&pose.translation.vector, a);
                let r = prev
                    .rotation
                    .try_slerp(&pose.rotation, a, 1e-9)
                    .unwrap_or(pose.rotation);
                Isometry3::from_parts(p.into(), r)
            }
            Some((prev, t_prev)) if stamp <= t_prev => return prev,
            _ => pose,
        };
        let mut out = out;
        let depth_tc = self.params.trocar_depth_filter_time_constant_s;
        if depth_tc > 0.0 {
            let gap = self.params.guard.trocar_timeout_s;
            let track = self
                .run
                .trocar_track
                .get_or_insert_with(|| TrackingFilter::new(depth_tc, gap));
            let tracked = track.update(stamp, &pose.translation.vector);
            let axis = out.rotation * Vector3::z();
            out.translation.vector += axis * axis.dot(&(tracked - out.translation.vector));
        }
        if self.run.trocar_filtered.is_some_and(|(_, t)| stamp > t) {
            self.run.depth.observe_pose(
                &Point3::from(pose.translation.vector),
                &(out.rotation * Vector3::z()),
                stamp,
            );
        }
        self.run.trocar_filtered = Some((out, stamp));
        out
    }

    /// Hold (when moving) or stay idle, for `e.reason`; command `e.hold_at` when not idle.
    fn hold_or_idle(&mut self, e: Early) -> ControlOutput {
        self.run.supervisor.hold(e.reason, false);
        self.run.motion.rest();
        self.run.goal_window.reset();
        let cmd = match self.run.supervisor.phase() {
            Phase::Idle => None,
            _ => self.run.last_command.or(e.hold_at),
        };
        if cmd.is_some() {
            self.run.last_command = cmd;
        }
        self.output(cmd, e.tip, None)
    }

    /// The measured joints, checked, with the tip pose and Jacobian there.
    #[allow(clippy::result_large_err)] // `Early` is a hold on its way out, not a hot path
    fn measured_arm(
        &self,
        kin: &dyn Kinematics,
        input: &ControlInput,
        guard: &CommandGuard,
    ) -> Result<MeasuredArm, Early> {
        let early = |reason, hold_at, tip| Early { reason, hold_at, tip };
        let q = match input.joints {
            None => return Err(early(HoldReason::NoJointState, None, None)),
            Some(j) if !j.value.iter().all(|x| x.is_finite()) => {
                return Err(early(HoldReason::NonFiniteJointState, None, None))
            }
            Some(j) if !CommandGuard::fresh(input.now - j.stamp, guard.params().joint_timeout_s) => {
                return Err(early(
                    HoldReason::StaleJointState {
                        age: input.now - j.stamp,
                    },
                    None,
                    None,
                ))
            }
            Some(j) => j.value,
        };
        let (tip, jac) = kin
            .fk_jacobian(&q)
            .map_err(|e| early(HoldReason::Kinematics(e.to_string().into()), Some(q), None))?;
        let prev = self.run.last_command.unwrap_or(q);
        // The arm must follow the commands while they move (also during a retreat); an
        // unlatched hold keeps checking, so it resumes only once the arm has caught up.
        let s = &self.run.supervisor;
        let ph = s.phase();
        let commanding = ph.is_moving() || (ph == Phase::Hold && (!s.is_latched() || self.run.retreat.active()));
        if commanding {
            guard
                .check_tracking(&q, &prev)
                .map_err(|r| early(r, Some(prev), Some(tip)))?;
        }
        Ok(MeasuredArm { q, tip, jac, prev })
    }

    /// Update the force estimate from the torques; the metric while moving; the force stop.
    #[allow(clippy::result_large_err)] // `Early` is a hold on its way out, not a hot path
    fn update_force(
        &mut self,
        input: &ControlInput,
        arm: &MeasuredArm,
        guard: &CommandGuard,
        dt: f64,
    ) -> Result<(), Early> {
        let early = |reason| Early {
            reason,
            hold_at: Some(arm.prev),
            tip: Some(arm.tip),
        };
        let before = self.run.admittance.force().norm();
        match input.tau_ext {
            Some(t)
                if t.value.iter().all(|x| x.is_finite())
                    && CommandGuard::fresh(input.now - t.stamp, guard.params().torque_timeout_s) =>
            {
                let tau = self.run.tare.correct(&t.value);
                self.run
                    .admittance
                    .update_force(&self.params.admittance, &arm.jac, &tau, dt);
            }
            Some(t) if self.params.require_torques => {
                return Err(early(HoldReason::StaleTorques {
                    age: input.now - t.stamp,
                }))
            }
            None if self.params.require_torques => return Err(early(HoldReason::StaleTorques { age: f64::INFINITY })),
            _ => {}
        }
        let f = self.run.admittance.force();
        let phase = self.run.supervisor.phase();
        let moving = phase.is_moving();
        if moving {
            self.run.metric.add(f.norm(), dt);
        }
        if let Err(r) = guard.check_force(f.norm()) {
            if moving {
                self.run.supervisor.hold(r, true);
                if self.params.retreat_distance_m > 0.0 {
                    self.run.retreat = RetreatState::Due;
                }
                return Ok(());
            }
        }
        self.pivot_force_stop(phase, f.norm(), (f.norm() - before) / dt, &arm.q);
        Ok(())
    }

    /// The force stop after docking: in DONE over the guard's `force_stop_n`, in RETRACT over
    /// `scope.retract_force_stop_n` (lower: the withdrawal must brake before the stop), hold,
    /// latched, `FORCE_LIMIT`; the law stops ([`Pivot::stop`]) and the command walks back to
    /// the joints `measured` now, within the guard's speed and acceleration limits
    /// ([`CommandGuard::walk`]), and stands there: the scope stays where it stopped, neither
    /// pulled out nor pushed in. Not at the last command: a position-mode arm reaches a
    /// command `scope.arm_lag_s` late, so the last command leads the arm by its speed times
    /// that lag (0.4 mm at 20 mm/s, 8 N into a 20 000 N/m obstacle), and standing there
    /// went on pushing into what stopped it. Only the operator's start resumes (DONE
    /// re-anchored at the measured tip, RETRACT going on).
    ///
    /// It acts on the force predicted when the arm will have stopped: `force` (the
    /// estimate's norm) plus its rate `rate` times [`force_stop_lead`]
    /// (a rising force only): against a stiff obstacle the true force rises on while the
    /// estimate lags it and the arm brakes and catches up with its command.
    fn pivot_force_stop(&mut self, phase: Phase, force: f64, rate: f64, measured: &JointVector) {
        let limit = match phase {
            Phase::Done => self.params.guard.force_stop_n,
            Phase::Retract => self.params.scope.retract_force_stop_n,
            _ => return,
        };
        let ahead = if rate.is_finite() {
            rate.max(0.0) * force_stop_lead(&self.params)
        } else {
            0.0
        };
        if force.is_finite() && force + ahead <= limit {
            return;
        }
        // The hold reports the predicted force, which passed the limit.
        let force = force + ahead;
        self.run.supervisor.hold(HoldReason::ForceLimit { force, limit }, true);
        if let Some(p) = self.run.pivot.as_mut() {
            p.stop();
            self.run.force_stop_at = Some(*measured);
        }
    }

    /// The trocar pose, checked and filtered.
    #[allow(clippy::result_large_err)] // `Early` is a hold on its way out, not a hot path
    fn trocar_pose(
        &mut self,
        input: &ControlInput,
        arm: &MeasuredArm,
        guard: &CommandGuard,
    ) -> Result<Isometry3<f64>, Early> {
        let early = |reason| Early {
            reason,
            hold_at: Some(arm.prev),
            tip: Some(arm.tip),
        };
        match input.trocar {
            None => Err(early(HoldReason::NoTrocarPose)),
            Some(p) if !pose_is_finite(&p.value) => Err(early(HoldReason::BadTrocarPose)),
            Some(p) if !CommandGuard::fresh(input.now - p.stamp, guard.params().trocar_timeout_s) => {
                Err(early(HoldReason::StaleTrocarPose {
                    age: input.now - p.stamp,
                }))
            }
            Some(p) => Ok(self.filtered_trocar(p.value, p.stamp)),
        }
    }

    /// The weights and the target point of c2 for this step's phase.
    fn phase_target(
        &mut self,
        axis: &InsertionAxis,
        tip: Point3<f64>,
        f: Vector3<f64>,
        goal_depth: f64,
        dt: f64,
    ) -> (CostWeights, Point3<f64>) {
        let p = &self.params;
        let (mut weights, point) = if self.run.retreat.active() {
            // Back out along the axis from where the stop happened, at the insertion speed.
            let r = match self.run.retreat {
                RetreatState::Backing(r) => r,
                _ => {
                    let s_now = axis.depth_of(&tip);
                    Retreat {
                        depth: s_now,
                        end: s_now - p.retreat_distance_m,
                    }
                }
            };
            let depth = (r.depth - p.insert_speed_m_s * dt).max(r.end);
            self.run.retreat = RetreatState::Backing(Retreat { depth, ..r });
            let mut w = p.insert_weights;
            w.reference = 0.0;
            (w, axis.point_at(depth))
        } else if self.run.supervisor.phase() == Phase::Approach {
            let standoff = axis.point_at(-p.standoff_m);
            let from = self.run.target.unwrap_or(tip);
            let d = standoff - from;
            let step = p.approach_speed_m_s * dt;
            let t = if d.norm() > step {
                from + d * (step / d.norm())
            } else {
                standoff
            };
            self.run.target = Some(t);
            self.run.insert_depth = -p.standoff_m;
            (p.approach_weights, t)
        } else {
            let f_axial_resisting = -f.dot(&axis.direction);
            let speed = p.insert_speed_m_s * p.admittance.insert_speed_ratio(f_axial_resisting);
            // Never run ahead of the tip by more than a few millimetres.
            let s_tip = axis.depth_of(&tip);
            let r = &mut self.run;
            r.insert_depth = (r.insert_depth + speed * dt)
                .min(goal_depth)
                .min(s_tip.max(r.insert_depth) + 0.005);
            let t = axis.point_at(r.insert_depth);
            r.target = Some(t);
            (p.insert_weights, t)
        };
        if !p.force_feedback {
            weights.reference = 0.0;
        }
        (weights, point)
    }

    /// Solve the SQP within the step box around the previous command; hold on a failure.
    fn solve(
        &mut self,
        kin: &dyn Kinematics,
        ctx: &StepContext<'_>,
        arm: &MeasuredArm,
        targets_for: AxisTargets,
        weights: &CostWeights,
        pivot: Option<PivotCost>,
    ) -> (JointVector, SolveReport) {
        let AxisTargets { axis, point, reference } = targets_for;
        let pivot_on = pivot.is_some();
        let prev = arm.prev;
        let g = ctx.guard;
        let (lo, hi) = g.step_box(&prev, ctx.dt);
        let start = prev.zip_zip_map(&lo, &hi, |q, l, h| q.clamp(l, h));
        let limits = LimitAvoidance {
            center: (g.upper() + g.lower()) * 0.5,
            half_range: ((g.upper() - g.lower()) * 0.5).map(|h| h.max(1e-3)),
            zone: self.params.limit_avoidance_zone,
            weight: self.params.limit_avoidance_weight,
        };
        let targets = Targets {
            axis,
            point,
            reference,
            q_prev: prev,
            limits: Some(limits),
            pivot,
        };
        let sol = self.sqp.solve(kin, &start, &lo, &hi, &targets, weights);
        let cmd = if sol.status.is_usable() && pivot_on {
            // Pivoting (DONE, RETRACT) shapes its own rates within the motion limits (see
            // [`super::scope::pivot`]) and uses no trocar pose, whose noise the limiter is for;
            // limiting its linear and angular parts apart would move the shaft off the
            // fulcrum.
            self.run.motion.rest();
            sol.q
        } else if sol.status.is_usable() {
            // The tip's speed, acceleration and jerk bounded (see [`super::safety::motion`]).
            // Braking for what is left: the tip's distance to the phase's target point and
            // the alignment error.
            let tip = Point3::from(arm.tip.translation.vector);
            let left = (
                (point - tip).norm(),
                axis.alignment_error(&(arm.tip.rotation * Vector3::z())),
            );
            self.run
                .motion
                .limit(&self.params.motion, &arm.jac, (&prev, &sol.q), left, ctx.dt, (&lo, &hi))
        } else {
            self.run.motion.rest();
            let why = HoldReason::SolverFailed(sol.status.as_text());
            self.run.supervisor.hold(why, false);
            prev
        };
        let report = SolveReport {
            costs: sol.costs,
            iterations: sol.iterations,
            qp_iterations: sol.qp_iterations,
            clarabel_qps: sol.clarabel_qps,
            solve_time_us: sol.solve_time_us,
            status: sol.status,
        };
        (cmd, report)
    }

    /// Phase transitions, judged on the measured tip.
    fn transitions(&mut self, axis: &InsertionAxis, goal_depth: f64, tip: &Isometry3<f64>, f: Vector3<f64>, dt: f64) {
        let goal = axis.point_at(goal_depth);
        let p = &self.params;
        let tip_p = Point3::from(tip.translation.vector);
        let optical_axis = tip.rotation * Vector3::z();
        let angle = axis.alignment_error(&optical_axis);
        let r = &mut self.run;
        let phase = r.supervisor.phase();
        match phase {
            Phase::Approach if (tip_p - axis.point_at(-p.standoff_m)).norm() < p.approach_tolerance_m => {
                if angle < p.approach_angle_tolerance_deg.to_radians() {
                    r.stalled_for = 0.0;
                    r.supervisor.approach_reached();
                } else {
                    r.stalled_for += dt;
                    if r.stalled_for > p.approach_stall_timeout_s {
                        r.stalled_for = 0.0;
                        let why = HoldReason::AlignmentStall {
                            angle_deg: angle.to_degrees(),
                            after_s: p.approach_stall_timeout_s,
                        };
                        r.supervisor.hold(why, true);
                    }
                }
            }
            Phase::Insert => {
                // DONE is judged on the error and angle averaged over a window, so that one
                // lucky sample of a noisy trocar estimate never ends the docking.
                let at_goal = r
                    .goal_window
                    .add(p.goal_window_s, tip_p - goal, angle, dt)
                    .is_some_and(|(e, g)| e < p.goal_tolerance_m && g < p.goal_angle_tolerance_deg.to_radians());
                let reached = if at_goal {
                    Some(None)
                } else {
                    let state = TipState {
                        tip: tip_p,
                        optical_axis,
                        force: f,
                    };
                    r.seated
                        .update(&p.seated, axis, goal_depth, &state, dt)
                        .map(|s| Some(DoneNote::Seated(s)))
                };
                self.depth_gate(reached, axis.depth_of(&tip_p), goal_depth, dt);
            }
            _ => {}
        }
        let r = &mut self.run;
        if r.supervisor.phase() != Phase::Insert {
            r.seated.reset();
        }
        if r.supervisor.phase() != phase {
            r.goal_window.reset();
            r.depth_failed = None;
        }
    }

    /// The DONE gate, in INSERT: with the goal `reached` this step (and the note DONE would
    /// carry), DONE only while the depth's figure (its uncertainty plus the tip's distance
    /// from the goal depth `goal_depth` on the estimate of this step, the tip at `depth`) is
    /// within the tolerance; otherwise judged on at the next steps for `depth.gate_wait_s`
    /// from the first failure, then HOLD `DEPTH_UNCERTAIN` (a dry run ends DONE,
    /// `DEPTH_UNVERIFIED`, at once).
    fn depth_gate(&mut self, reached: Option<Option<DoneNote>>, depth: f64, goal_depth: f64, dt: f64) {
        let d = &self.params.depth;
        let r = &mut self.run;
        if let Some(note) = reached {
            let mut report = r.depth.report(d, depth, axis_filter(&self.params));
            report.uncertainty += (depth - goal_depth).abs();
            r.depth_report = Some(report);
            if report.uncertainty <= d.tolerance_m {
                r.supervisor.goal_reached(note);
            } else if self.dry_run {
                // The ghost never meets the seal: the rehearsal ends, saying so.
                r.supervisor.goal_reached(Some(DoneNote::DepthUnverified {
                    uncertainty_m: report.uncertainty,
                    tolerance_m: d.tolerance_m,
                    basis: report.basis,
                }));
            } else {
                // Judged again at the next steps at the goal: each pose moves the goal, and
                // the tip follows it within ~0.1 s.
                let waited = r.depth_failed.map_or(0.0, |(_, w)| w);
                r.depth_failed = Some((report, waited));
            }
        }
        // The wait runs from the first failure, at the goal or not.
        if let Some((report, waited)) = r.depth_failed.filter(|_| r.supervisor.phase() == Phase::Insert) {
            if waited >= d.gate_wait_s - 1e-9 {
                // The status carries the figure the hold names.
                r.depth_report = Some(report);
                r.supervisor.depth_uncertain(HoldReason::DepthUncertain {
                    uncertainty_m: report.uncertainty,
                    tolerance_m: d.tolerance_m,
                    basis: report.basis,
                });
            } else {
                r.depth_failed = Some((report, waited + dt));
            }
        }
    }

    /// One step of the TARE phase: hold still at the start pose while the torques are
    /// averaged; then APPROACH, or IDLE with the reason.
    fn tare_step(&mut self, input: &ControlInput, arm: &MeasuredArm, guard: &CommandGuard, dt: f64) -> ControlOutput {
        let p = &self.params;
        let tau = input.tau_ext.filter(|t| {
            t.value.iter().all(|x| x.is_finite())
                && CommandGuard::fresh(input.now - t.stamp, guard.params().torque_timeout_s)
        });
        let r = &mut self.run;
        match tau {
            _ if p.tare.window_s <= 0.0 => {
                r.tare.skip();
                r.supervisor.tare_done();
            }
            None if !p.require_torques => {
                r.tare.skip();
                r.supervisor.tare_done();
            }
            None => {
                // Torques missing or stale: start the window again once they are back.
                r.tare = Tare::default();
                let age = input.tau_ext.map_or(f64::INFINITY, |t| input.now - t.stamp);
                r.supervisor.hold(HoldReason::StaleTorques { age }, false);
            }
            Some(t) => match r.tare.collect(&p.tare, &arm.q, &t.value, input.now, dt) {
                TareStep::Collecting => {}
                TareStep::Done => r.supervisor.tare_done(),
                TareStep::Refused(why) => r.supervisor.tare_refused(why),
            },
        }
        let still = (self.run.supervisor.phase() != Phase::Idle).then_some(arm.prev);
        self.run.last_command = still;
        self.output(still, Some(arm.tip), None)
    }

    /// After DONE: hold the port as the remote centre of motion while the surgeon steers,
    /// or withdraw (RETRACT); see [`super::scope::pivot`]. `None` in the other phases (and before
    /// any trocar estimate, when DONE just holds).
    fn pivot_step(
        &mut self,
        kin: &dyn Kinematics,
        input: &ControlInput,
        ctx: &StepContext<'_>,
        arm: &MeasuredArm,
    ) -> Option<ControlOutput> {
        let s = &self.run.supervisor;
        let held = s.phase() == Phase::Hold && matches!(s.resumes(), Phase::Done | Phase::Retract);
        if !held && !matches!(s.phase(), Phase::Done | Phase::Retract) {
            return None;
        }
        let sp = &self.params.scope;
        if held {
            // Standing at the last command, or walking to where the force stop found the
            // arm (the hold's reason stays: no input of this step clears a latched hold).
            if self.run.pivot.as_ref().is_none_or(|p| !p.held() || p.at_rest()) {
                let stand = self
                    .run
                    .force_stop_at
                    .map_or(arm.prev, |q| ctx.guard.walk(&arm.prev, &q, ctx.dt));
                self.run.last_command = Some(stand);
                let mut out = self.output(Some(stand), Some(arm.tip), None);
                out.pivot = self.run.pivot.as_ref().map(|p| p.report(sp, &arm.tip, &out.f_ext));
                return Some(out);
            }
        } else {
            // Every input the law needs is good: a passed hold's reason goes.
            self.run.supervisor.clear_hold();
        }
        if self.run.pivot.is_none() {
            let (t, stamp) = self.run.trocar_filtered?;
            let trocar = InsertionAxis::from_pose(&t);
            self.run.pivot = Some(Pivot::new(sp, &kin.fk(&arm.prev).ok()?, &trocar, stamp));
        }
        if std::mem::take(&mut self.run.reanchor) {
            // Resumed after a hold: from where the scope is (the measured tip).
            let pivot = self.run.pivot.as_mut()?;
            pivot.reanchor(&arm.tip);
        }
        let command = live_command(sp, input.now, input.scope);
        let pivot = self.run.pivot.as_mut()?;
        // The trocar estimate, where there is one, for the port's breathing; the law needs
        // none (the marker may leave the camera's view while the surgeon steers).
        if let Some(t) = input.trocar {
            pivot.observe_port(sp, &t.value, t.stamp, input.now);
        }
        if self.run.supervisor.phase() == Phase::Retract && !pivot.retracting() && !held {
            pivot.retract_to(-self.params.standoff_m);
        }
        // The torques less the tare's offset but not its per-joint dead-band (2 sigma of the
        // tare window's noise, 0.6 Nm in the realistic world): a few newtons across the shaft
        // load the wrist joints by tenths of Nm, which the band would zero and the wrench
        // would lose; the fulcrum low-passes its force and bands it across the shaft instead.
        let a = &self.params.admittance;
        let tau = input
            .tau_ext
            .map_or(JointVector::repeat(f64::NAN), |t| self.run.tare.remove_offset(&t.value));
        let f = pivot.sense(&arm.jac, &tau, a.pinv_damping, sp.fulcrum.filter_cutoff_hz, ctx.dt);
        // Without force feedback the law uses no force: the fulcrum stays where it began.
        let t = pivot.step(
            PivotParams::new(sp, &self.params.motion),
            command,
            &f,
            self.params.force_feedback,
            ctx.dt,
        );
        let (cmd, report) = self.solve(
            kin,
            ctx,
            arm,
            AxisTargets {
                axis: t.axis,
                point: t.point,
                reference: t.point,
            },
            &t.weights,
            Some(t.cost),
        );
        self.run.last_command = Some(cmd);
        let pivot = self.run.pivot.as_ref()?;
        let back =
            nalgebra::distance(&Point3::from(arm.tip.translation.vector), &t.point) < self.params.approach_tolerance_m;
        let status = pivot.report(&self.params.scope, &arm.tip, &f);
        if pivot.retracted() && back {
            self.run.supervisor.retract_done();
        }
        let mut out = self.output(Some(cmd), Some(arm.tip), None);
        // The shaft's force from its whole wrench: the linear rows alone read the trocar's
        // tilt spring (a couple across the bore) as a force. (The force stop still checks
        // the linear rows' estimate, which reads that couple high: the safe side.)
        out.f_ext = f;
        out.solve = Some(report);
        out.pivot = Some(status);
        Some(out)
    }

    #[allow(clippy::result_large_err)] // `Early` is a hold on its way out, not a hot path
    fn step_checked(
        &mut self,
        kin: &dyn Kinematics,
        input: &ControlInput,
        ctx: &StepContext<'_>,
    ) -> Result<ControlOutput, Early> {
        let dt = ctx.dt;
        let arm = self.measured_arm(kin, input, ctx.guard)?;
        if self.run.supervisor.phase() == Phase::Tare {
            // Tare with every input present, so that APPROACH begins with all of them.
            self.trocar_pose(input, &arm, ctx.guard)?;
            self.run.supervisor.clear_hold();
            return Ok(self.tare_step(input, &arm, ctx.guard, dt));
        }
        self.run.tare.at_pose(&self.params.tare, &arm.jac, &arm.tip.rotation);
        self.update_force(input, &arm, ctx.guard, dt)?;
        if let Some(out) = self.pivot_step(kin, input, ctx, &arm) {
            return Ok(out);
        }
        let trocar = self.trocar_pose(input, &arm, ctx.guard)?;
        let axis = InsertionAxis::from_pose(&trocar);
        let goal_depth = self.params.insertion_depth_m + self.run.depth.correction();
        let goal = axis.point_at(goal_depth);
        let tip_p = Point3::from(arm.tip.translation.vector);
        if let (Phase::Approach, Some(t)) = (self.run.supervisor.phase(), input.tau_ext) {
            let pose = (&arm.jac, &arm.tip.rotation);
            self.run
                .tare
                .track(&self.params.tare, &t.value, axis.depth_of(&tip_p), pose, dt);
        }

        // Every input is good: an unlatched hold (stale data) resumes.
        self.run.supervisor.clear_hold();
        let phase = self.run.supervisor.phase();
        let retreating = phase == Phase::Hold && self.run.retreat.active();
        if !phase.is_moving() && !retreating {
            // Idle sends nothing; DONE, HOLD and ABORTED keep commanding the last command.
            self.run.last_command = (phase != Phase::Idle).then_some(arm.prev);
            self.run.motion.rest();
            return Ok(self.output(self.run.last_command, Some(arm.tip), Some(goal)));
        }

        // Admittance reference from the force across the axis.
        let f = self.run.admittance.force();
        let x = self.run.admittance.step(&self.params.admittance, axis.across(&f), dt);
        let reference = tip_p + x;
        if phase == Phase::Insert && !retreating {
            // The seal's onset along the axis, from the force resisting the insertion.
            let p = &self.params;
            let filters = Filters {
                force_lag: force_estimate_lag(p),
                axis: axis_filter(p),
            };
            let r = &mut self.run;
            r.depth.update(&p.depth, &axis, &tip_p, &f, input.now, filters);
            r.depth_report = Some(r.depth.report(&p.depth, axis.depth_of(&tip_p), filters.axis));
        }
        let (weights, point) = self.phase_target(&axis, tip_p, f, goal_depth, dt);
        let (cmd, report) = self.solve(kin, ctx, &arm, AxisTargets { axis, point, reference }, &weights, None);
        self.run.last_command = Some(cmd);
        self.transitions(&axis, goal_depth, &arm.tip, f, dt);
        let mut out = self.output(Some(cmd), Some(arm.tip), Some(goal));
        out.solve = Some(report);
        out.reference = Some(reference);
        Ok(out)
    }
}

impl CommandSource for OptimalController {
    fn period(&self) -> f64 {
        self.params.dt_s
    }

    fn phase(&self) -> Phase {
        self.run.supervisor.phase()
    }

    fn start(&mut self) -> Result<(), String> {
        let was = self.run.supervisor.phase();
        if let (Phase::Hold, Some(HoldReason::ForceLimit { limit, .. })) = (was, self.run.supervisor.reason()) {
            let force = self.run.admittance.force().norm();
            if force.is_nan() || force > *limit {
                return Err(format!(
                    "the force estimate ({force:.1} N) is still over the {limit:.1} N stop: free the scope, then start"
                ));
            }
        }
        let resumes = self.run.supervisor.resumes();
        self.run.supervisor.start()?;
        if was == Phase::Hold && matches!(resumes, Phase::Done | Phase::Retract) {
            self.run.reanchor = true;
            self.run.force_stop_at = None;
        }
        if was == Phase::Idle {
            // A new run starts from where the arm is (it may have been moved by hand while
            // idle), not from the last command of the previous run.
            self.run = RunState {
                supervisor: self.run.supervisor.clone(),
                trocar_filtered: self.run.trocar_filtered,
                trocar_track: self.run.trocar_track,
                ..RunState::default()
            };
        }
        self.run.retreat = RetreatState::Off;
        Ok(())
    }

    fn abort(&mut self, why: &str) {
        self.run.supervisor.abort(why);
        self.run.retreat = RetreatState::Off;
    }

    fn retract(&mut self) -> Result<(), String> {
        // The law begins the withdrawal at its next step ([`Self::pivot_step`]).
        self.run.supervisor.retract()
    }

    fn reset(&mut self) {
        self.run = RunState::default();
        self.sqp.forget();
    }

    fn last_command(&self) -> Option<JointVector> {
        self.run.last_command
    }

    fn step(&mut self, kin: &dyn Kinematics, input: &ControlInput, ctx: &StepContext<'_>) -> ControlOutput {
        // Every step filters its torque samples first, whatever the step does with them.
        let input = ControlInput {
            tau_ext: self.torques.feed(input),
            ..*input
        };
        self.step_checked(kin, &input, ctx)
            .unwrap_or_else(|e| self.hold_or_idle(e))
    }

    fn hold_latched(&self) -> bool {
        self.run.supervisor.is_latched()
    }

    fn reject(&mut self, reason: HoldReason, hold_at: JointVector) {
        self.run.supervisor.hold(reason, true);
        if let Some(p) = self.run.pivot.as_mut() {
            // The guard or its wrapper decides the command: the law stops at once.
            p.stop();
        }
        self.run.motion.rest();
        self.run.goal_window.reset();
        self.run.last_command = Some(hold_at);
    }

    fn settle(&mut self, at: JointVector) {
        // A hold braked within the guard's acceleration limit: the law stands where it came
        // to rest (its next hold command, or its next step box, begins there).
        if self.run.supervisor.phase() != Phase::Idle {
            self.run.last_command = Some(at);
        }
    }
}
