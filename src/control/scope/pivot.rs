//! After docking: the port held as a remote centre of motion (RCM) while the surgeon
//! steers the scope through it.
//!
//! **State** (set when DONE begins, from the last command's tip pose, so that the first
//! step's targets are where the arm already is and nothing moves): the target tip
//! orientation R (its z axis the shaft direction d, its x axis the roll), the port P (where
//! the shaft enters the trocar's face: the trocar estimate's port projected on the shaft
//! line, since the port holds the docked shaft), the target tip depth s_t past P, and the
//! fulcrum F = P + d s_f + x ([`crate::control::scope::fulcrum`]: depth s_f along the shaft from a prior,
//! displacement x across it, both adapted from the force across the shaft).
//!
//! **Per step** the surgeon's command (dead-man: older than `command_timeout_s` is none; not
//! finite, or stamped in the future, is ignored with the reason) is cut to the speed
//! limits, and its rates are shaped within the controller's `motion:` limits
//! ([`crate::control::safety::motion::RateShaper`]: a command that starts, stops or reverses at once, or
//! the dead-man, moves the target with bounded acceleration and jerk, braking ahead of the
//! cone and the depth limits); the angular velocity R (pan, tilt, roll) turns R about F (the port P turns with
//! it: P = F - d s_f), unless the new d would leave the cone about the docking axis
//! (then only the roll turns: `CONE`); the zoom moves s_t, stopped at `min_depth_m` /
//! `max_depth_m` (never pushed back into the range when it started outside it). The SQP
//! then gets: c1 tip to the line (P, d), c2 tip to P + d s_t, c3 optical axis to d, c4,
//! and the RCM term (F's distance from the shaft line) with the roll term
//! ([`crate::control::sqp::PivotCost`]). With no command the targets do not move, so the scope
//! holds still; only the fulcrum's lateral adaptation moves it, with the wall.
//!
//! **Retract** (`~retract`): the commands are ignored and s_t falls at `retract_speed_m_s` to
//! the stand-off point before the port (`-standoff_m`); then the run ends (IDLE). The port's
//! breathing is not followed meanwhile: the seal drags the trocar out with the withdrawing
//! scope, and a port followed there fed the withdrawal back into itself (the followed
//! offset caught up at its own `max_speed_m_s` on top of the withdrawal).
//!
//! **Held** ([`Pivot::stop`], the force stop while steering or withdrawing, a guard's
//! hold): the commands are ignored, the shaped rates are at rest, and nothing else moves
//! the targets: no breathing follow, no fulcrum adaptation, no axial yield (each moves the
//! scope, which a surgeon expects to stay where it stopped: neither pulled out nor pushed
//! in). The controller decides the command: the force stop walks it back to the joints
//! measured when it fired, within the guard's speed and acceleration limits, and stands
//! there (`pivot_force_stop` in `src/control/controller.rs`). A resume re-anchors the law
//! at the measured tip ([`Pivot::reanchor`]).
//!
//! Nothing here allocates.

use nalgebra::{Isometry3, Point3, Unit, UnitQuaternion, Vector3};

use crate::control::docking::geometry::{across, InsertionAxis};
use crate::control::force::wrench::{shaft_wrench, ForceFilter};
use crate::control::io::Stamped;
use crate::control::safety::motion::{MotionLimits, Rate, RateShaper};
use crate::control::scope::command::{PivotReport, ScopeCommand, ScopeLimit, ScopeParams};
use crate::control::scope::fulcrum::{Fulcrum, Motion};
use crate::control::scope::port_follow::PortFollow;
use crate::control::sqp::{CostWeights, PivotCost};
use crate::kinematics::{Jacobian, JointVector};

/// The surgeon's command for this step: `Ok(None)` when there is none or it is older than
/// the timeout (dead-man), `Err(reason)` when it must be ignored.
pub fn live_command(
    p: &ScopeParams,
    now: f64,
    cmd: Option<Stamped<ScopeCommand>>,
) -> Result<Option<ScopeCommand>, &'static str> {
    let Some(c) = cmd else { return Ok(None) };
    if !c.value.is_finite() || !c.stamp.is_finite() {
        return Err("scope command not finite: ignored, holding still");
    }
    let age = now - c.stamp;
    if age < -p.command_timeout_s {
        return Err("scope command stamped in the future: ignored, holding still");
    }
    Ok((age <= p.command_timeout_s).then_some(c.value))
}

/// The parameters of a step of [`Pivot::step`]: the scope's and the motion limits.
#[derive(Debug, Clone, Copy)]
pub struct PivotParams<'a> {
    /// The scope's parameters (`scope:`).
    pub scope: &'a ScopeParams,
    /// The tip's motion limits.
    pub motion: &'a MotionLimits,
}

impl<'a> PivotParams<'a> {
    /// The scope's parameters `scope` with the motion limits `motion`.
    pub fn new(scope: &'a ScopeParams, motion: &'a MotionLimits) -> Self {
        Self { scope, motion }
    }
}

/// What the SQP gets this step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PivotTargets {
    /// The target shaft line: through the port, along the target direction.
    pub axis: InsertionAxis,
    /// The tip's target point on it.
    pub point: Point3<f64>,
    /// The RCM and roll terms.
    pub cost: PivotCost,
    /// The weights of c1..c5.
    pub weights: CostWeights,
}

/// The RCM law's state, from DONE until the run ends.
#[derive(Debug, Clone, PartialEq)]
pub struct Pivot {
    rot: UnitQuaternion<f64>,
    /// The fulcrum without its lateral displacement.
    fulcrum_base: Point3<f64>,
    fulcrum: Fulcrum,
    tip_depth: f64,
    cone_axis: Unit<Vector3<f64>>,
    limit: Option<ScopeLimit>,
    ignored: Option<&'static str>,
    /// While retracting: the depth to withdraw to.
    retract_to: Option<f64>,
    /// The shaft's force, from its whole wrench ([`shaft_wrench`]).
    force: ForceFilter,
    /// The shaped pan, tilt and roll rates (tip frame), rad/s.
    turn_rate: RateShaper,
    /// The shaped zoom (z), m/s.
    zoom_rate: RateShaper,
    /// The port's breathing along the docking axis, from the trocar estimate.
    follow: PortFollow,
    /// Held by the force stop: braking to rest, then still (module doc).
    held: bool,
}

impl Pivot {
    /// Begin holding the port: `tip` is the commanded tip pose (its z the shaft), `trocar`
    /// the estimated docking axis (its direction the cone's axis), estimated at `stamp`.
    pub fn new(p: &ScopeParams, tip: &Isometry3<f64>, trocar: &InsertionAxis, stamp: f64) -> Self {
        let d = tip.rotation * Vector3::z();
        let e = Point3::from(tip.translation.vector);
        let tip_depth = -d.dot(&(trocar.port - e));
        let port = e - d * tip_depth;
        let mut fulcrum = Fulcrum::new(&p.fulcrum);
        fulcrum.depth = fulcrum.depth.min(tip_depth.max(0.0));
        Self {
            rot: tip.rotation,
            fulcrum_base: port + d * fulcrum.depth,
            fulcrum,
            tip_depth,
            cone_axis: trocar.direction,
            limit: None,
            ignored: None,
            retract_to: None,
            force: ForceFilter::default(),
            turn_rate: RateShaper::default(),
            zoom_rate: RateShaper::default(),
            follow: PortFollow::new(&p.breathing, trocar.direction, trocar.port, stamp),
            held: false,
        }
    }

    /// Held at once, the rates at rest (the command is decided elsewhere: a guard's hold,
    /// the force stop's walk to where the arm stopped), nothing else moving the targets
    /// (module doc), until [`Pivot::reanchor`].
    pub fn stop(&mut self) {
        self.held = true;
        self.turn_rate.stop();
        self.zoom_rate.stop();
    }

    /// Whether the law is held.
    pub fn held(&self) -> bool {
        self.held
    }

    /// Whether the shaped rates are at rest (a held law has stopped braking).
    pub fn at_rest(&self) -> bool {
        self.turn_rate.velocity() == Vector3::zeros() && self.zoom_rate.velocity() == Vector3::zeros()
    }

    /// Resume after a hold from the tip pose `tip` (the measured one: where the scope
    /// stopped): the target orientation and depth are the tip's, the port is the old port
    /// projected on the new shaft line, the fulcrum lies at its adapted depth on that line
    /// (its lateral displacement spent), the rates start from rest. A withdrawal goes on
    /// to its end depth; the breathing follow and the cone keep their state.
    pub fn reanchor(&mut self, tip: &Isometry3<f64>) {
        let d = tip.rotation * Vector3::z();
        let e = Point3::from(tip.translation.vector);
        let tip_depth = -d.dot(&(self.port() - e));
        let port = e - d * tip_depth;
        self.rot = tip.rotation;
        self.tip_depth = tip_depth;
        self.fulcrum.lateral = Vector3::zeros();
        self.fulcrum_base = port + d * self.fulcrum.depth;
        self.turn_rate.stop();
        self.zoom_rate.stop();
        self.held = false;
    }

    /// Feed a trocar estimate `trocar` (its port and axis), stamped `stamp`, at time `now`
    /// ([`PortFollow::observe`] at the fulcrum's depth: a bad or old one changes nothing).
    pub fn observe_port(&mut self, p: &ScopeParams, trocar: &Isometry3<f64>, stamp: f64, now: f64) {
        let port = Point3::from(trocar.translation.vector);
        let axis = trocar.rotation * Vector3::z();
        self.follow
            .observe(&p.breathing, (&port, &axis), self.fulcrum.depth, stamp, now);
    }

    /// Feed this step's (tared) external torques at the measured Jacobian `jac`; returns the
    /// filtered force on the shaft (base frame, N). Non-finite torques leave it unchanged.
    pub fn sense(
        &mut self,
        jac: &Jacobian,
        tau: &JointVector,
        pinv_damping: f64,
        cutoff_hz: f64,
        dt: f64,
    ) -> Vector3<f64> {
        match shaft_wrench(jac, tau, pinv_damping) {
            Some((f, _)) => self.force.update(&f, cutoff_hz, dt),
            None => self.force.force(),
        }
    }

    /// The target shaft direction.
    pub fn direction(&self) -> Unit<Vector3<f64>> {
        Unit::new_unchecked(self.rot * Vector3::z())
    }

    /// The fulcrum point.
    pub fn fulcrum(&self) -> Point3<f64> {
        self.fulcrum_base + self.fulcrum.lateral
    }

    /// The port: where the shaft line enters the trocar's face.
    pub fn port(&self) -> Point3<f64> {
        self.fulcrum() - self.direction().into_inner() * self.fulcrum.depth
    }

    /// The target tip depth past the port, m.
    pub fn target_depth(&self) -> f64 {
        self.tip_depth
    }

    /// Withdraw to `depth` past the port (negative: before it); commands are ignored from
    /// now on.
    pub fn retract_to(&mut self, depth: f64) {
        self.retract_to = Some(depth.min(self.tip_depth));
    }

    /// Whether a retract has begun.
    pub fn retracting(&self) -> bool {
        self.retract_to.is_some()
    }

    /// Whether a retract has reached its end depth.
    pub fn retracted(&self) -> bool {
        self.retract_to.is_some_and(|d| self.tip_depth <= d)
    }

    /// The speed limits: the command cut to them.
    fn capped(&mut self, p: &ScopeParams, c: ScopeCommand) -> ScopeCommand {
        let mut out = c;
        let w = c.pan.hypot(c.tilt);
        if w > p.max_angular_speed_rad_s {
            out.pan *= p.max_angular_speed_rad_s / w;
            out.tilt *= p.max_angular_speed_rad_s / w;
            self.limit = Some(ScopeLimit::Speed);
        }
        if c.roll.abs() > p.max_roll_speed_rad_s {
            out.roll = c.roll.clamp(-p.max_roll_speed_rad_s, p.max_roll_speed_rad_s);
            self.limit = Some(ScopeLimit::Speed);
        }
        if c.zoom.abs() > p.max_zoom_speed_m_s {
            out.zoom = c.zoom.clamp(-p.max_zoom_speed_m_s, p.max_zoom_speed_m_s);
            self.limit = Some(ScopeLimit::Speed);
        }
        out
    }

    /// The angle left before the cone when pan and tilt at `turn` (tip frame) head out of
    /// it; infinite when they do not.
    fn cone_room(&self, p: &ScopeParams, turn: &Vector3<f64>, dt: f64) -> f64 {
        let axis = |r: &UnitQuaternion<f64>| (r * Vector3::z()).angle(&self.cone_axis);
        let next = UnitQuaternion::from_scaled_axis(self.rot * Vector3::new(turn.x, turn.y, 0.0) * dt) * self.rot;
        if axis(&next) > axis(&self.rot) {
            p.cone_half_angle_deg.to_radians() - axis(&self.rot)
        } else {
            f64::INFINITY
        }
    }

    /// Turn the target about the fulcrum by the command's angular velocity (tip frame),
    /// within the cone; returns the pan and tilt's angular velocity taken, base frame.
    fn turn(&mut self, p: &ScopeParams, c: &ScopeCommand, dt: f64) -> Vector3<f64> {
        let pan_tilt = self.rot * Vector3::new(c.pan, c.tilt, 0.0);
        let roll = self.rot * Vector3::new(0.0, 0.0, c.roll);
        let turned = UnitQuaternion::from_scaled_axis((pan_tilt + roll) * dt) * self.rot;
        let angle = |r: &UnitQuaternion<f64>| (r * Vector3::z()).angle(&self.cone_axis);
        let cone = p.cone_half_angle_deg.to_radians();
        let taken = if angle(&turned) > cone && angle(&turned) > angle(&self.rot) {
            self.limit = Some(ScopeLimit::Cone);
            // Pan and tilt stopped here: the shaped rates start again from rest.
            self.turn_rate.cut_to(Vector3::new(0.0, 0.0, c.roll));
            self.rot = UnitQuaternion::from_scaled_axis(roll * dt) * self.rot;
            Vector3::zeros()
        } else {
            self.rot = turned;
            pan_tilt
        };
        // The fulcrum stays; the port (F - d s_f) turns about it.
        taken
    }

    /// Move the target depth by the zoom, stopped at the depth limits.
    fn zoom(&mut self, p: &ScopeParams, zoom: f64, dt: f64) {
        let s = self.tip_depth + zoom * dt;
        self.tip_depth = if zoom > 0.0 && s > p.max_depth_m {
            self.limit = Some(ScopeLimit::MaxDepth);
            self.zoom_rate.cut_to(Vector3::zeros());
            self.tip_depth.max(p.max_depth_m)
        } else if zoom < 0.0 && s < p.min_depth_m {
            self.limit = Some(ScopeLimit::MinDepth);
            self.zoom_rate.cut_to(Vector3::zeros());
            self.tip_depth.min(p.min_depth_m)
        } else {
            s
        };
    }

    /// Yield along the shaft to the force `along` it ([`FulcrumParams::axial_yield`]).
    /// Past `min_depth_m` too (the trocar that pushes the scope out moves the bore with it; a
    /// limit that stopped the yield would leave the scope pushing on it), but never out of
    /// the port nor past `max_depth_m` (a depth already beyond is not pushed further).
    fn yield_along(&mut self, p: &ScopeParams, along: f64, steering: bool, dt: f64) {
        let ds = p.fulcrum.axial_yield(along, steering, dt);
        if ds == 0.0 {
            return;
        }
        let (lo, hi) = (self.tip_depth.min(0.0), p.max_depth_m.max(self.tip_depth));
        self.tip_depth = (self.tip_depth + ds).clamp(lo, hi);
    }

    /// One step: `command` from [`live_command`], `force` the shaft's force (base frame,
    /// N; [`Pivot::sense`]); `adapt`: adapt the fulcrum from it (off: the fulcrum stays
    /// where it started, as without force feedback). Returns the SQP's targets.
    pub fn step(
        &mut self,
        params: PivotParams<'_>,
        command: Result<Option<ScopeCommand>, &'static str>,
        force: &Vector3<f64>,
        adapt: bool,
        dt: f64,
    ) -> PivotTargets {
        let (p, lim) = (params.scope, params.motion);
        self.limit = None;
        self.ignored = command.err();
        let steering = !self.held && (matches!(command, Ok(Some(_))) || self.retract_to.is_some());
        // The wanted rates (pan, tilt, roll; zoom), and how far the zoom may go.
        let (turn, zoom, zoom_room) = match (self.retract_to, command) {
            // Held: braking to rest.
            (Some(end), _) if self.held => (Vector3::zeros(), 0.0, self.tip_depth - end),
            (None, _) if self.held => (Vector3::zeros(), 0.0, f64::INFINITY),
            (Some(end), _) => (Vector3::zeros(), -p.retract_speed_m_s, self.tip_depth - end),
            (None, Ok(Some(c))) => {
                let c = self.capped(p, c);
                let room = if c.zoom > 0.0 {
                    p.max_depth_m - self.tip_depth
                } else {
                    self.tip_depth - p.min_depth_m
                };
                (Vector3::new(c.pan, c.tilt, c.roll), c.zoom, room)
            }
            (None, _) => (Vector3::zeros(), 0.0, f64::INFINITY),
        };
        let turn = self
            .turn_rate
            .step(lim, Rate::Angular, turn, self.cone_room(p, &turn, dt), dt);
        let zoom = self
            .zoom_rate
            .step(lim, Rate::Linear, Vector3::new(0.0, 0.0, zoom), zoom_room, dt)
            .z;
        let mut omega = Vector3::zeros();
        if let Some(end) = self.retract_to {
            self.tip_depth = (self.tip_depth + zoom * dt).max(end);
        } else {
            let c = ScopeCommand {
                pan: turn.x,
                tilt: turn.y,
                roll: turn.z,
                zoom,
            };
            omega = self.turn(p, &c, dt);
            self.zoom(p, c.zoom, dt);
        }
        let d = self.direction();
        // Held, nothing but the braking rates moves the targets.
        let adapt = adapt && !self.held;
        if adapt && self.retract_to.is_none() {
            self.yield_along(p, force.dot(&d), steering, dt);
        }
        if adapt {
            let m = Motion {
                omega,
                tip_depth: self.tip_depth,
                steering,
            };
            let moved = self.fulcrum.step(&p.fulcrum, force, &d, &m, dt);
            self.fulcrum_base += d.into_inner() * moved;
            // The port's breathing along the docking axis: the port, the fulcrum and the
            // tip's target move with it while the surgeon steers; not while withdrawing
            // (the seal drags the trocar out with the scope, and a port followed there fed
            // the withdrawal back into itself: the tip left at 25 mm/s for a 5 mm/s retract).
            let follow = steering && self.retract_to.is_none();
            self.fulcrum_base += self.follow.step(&p.breathing, follow, dt);
        }
        let port = self.port();
        PivotTargets {
            axis: InsertionAxis { port, direction: d },
            point: port + d.into_inner() * self.tip_depth,
            cost: PivotCost {
                fulcrum: self.fulcrum(),
                x_axis: self.rot * Vector3::x(),
                rcm_weight: p.rcm_weight,
                roll_weight: p.roll_weight,
            },
            weights: p.weights,
        }
    }

    /// The report for the status, at the measured `tip` with the force estimate `force`.
    pub fn report(&self, p: &ScopeParams, tip: &Isometry3<f64>, force: &Vector3<f64>) -> PivotReport {
        let a = tip.rotation * Vector3::z();
        let e = Point3::from(tip.translation.vector);
        let cost = PivotCost {
            fulcrum: self.fulcrum(),
            x_axis: Vector3::x(),
            rcm_weight: 0.0,
            roll_weight: 0.0,
        };
        PivotReport {
            fulcrum: self.fulcrum(),
            shaft_distance: cost.rcm_residual(tip).norm(),
            lateral_force: across(&a, force).norm(),
            depth: a.dot(&(e - self.port())),
            cone_axis: self.cone_axis.into_inner(),
            cone_half_angle: p.cone_half_angle_deg.to_radians(),
            limit: self.limit,
            ignored: self.ignored,
            fulcrum_depth: self.fulcrum.depth,
            breathing_offset: self.follow.offset(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Translation3;
    // (Stamped, JointVector: from the module's imports.)

    /// One 10 ms step of `pv` with `c`, no force, the default motion limits.
    fn go(pv: &mut Pivot, p: &ScopeParams, c: Result<Option<ScopeCommand>, &'static str>) -> PivotTargets {
        pv.step(
            PivotParams::new(p, &MotionLimits::default()),
            c,
            &Vector3::zeros(),
            true,
            0.01,
        )
    }

    fn setup() -> (ScopeParams, Pivot) {
        let p = ScopeParams::default();
        // The shaft pointing down, tip 30 mm past a port at the origin; the estimate's
        // port 2 mm beside the shaft.
        let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        let tip = Isometry3::from_parts(Translation3::new(0.0, 0.0, -0.03), down);
        let axis = InsertionAxis {
            port: Point3::new(0.002, 0.0, 0.0),
            direction: -Vector3::z_axis(),
        };
        (p.clone(), Pivot::new(&p, &tip, &axis, 0.0))
    }

    fn cmd(pan: f64, tilt: f64, roll: f64, zoom: f64) -> Result<Option<ScopeCommand>, &'static str> {
        Ok(Some(ScopeCommand { pan, tilt, roll, zoom }))
    }

    #[test]
    fn it_starts_where_the_arm_is_and_holds_still_without_a_command() {
        let (p, mut pv) = setup();
        assert!(
            (pv.port() - Point3::origin()).norm() < 1e-12,
            "the port projected on the shaft"
        );
        assert!((pv.fulcrum() - Point3::new(0.0, 0.0, -p.fulcrum.prior_depth_m)).norm() < 1e-12);
        for _ in 0..500 {
            let t = go(&mut pv, &p, Ok(None));
            assert!((t.point - Point3::new(0.0, 0.0, -0.03)).norm() < 1e-12);
            assert!((t.axis.direction.into_inner() + Vector3::z()).norm() < 1e-12);
        }
    }

    #[test]
    fn the_depth_yields_to_a_push_along_the_shaft_past_min_depth_but_not_out_of_the_port() {
        let (p, mut pv) = setup();
        let lim = MotionLimits::default();
        // The shaft points down (-z): a force +z on it pushes the scope out.
        let out = Vector3::new(0.0, 0.0, 10.0);
        // Under the still dead-band (5 N): nothing moves without a command.
        pv.step(
            PivotParams::new(&p, &lim),
            Ok(None),
            &Vector3::new(0.0, 0.0, 4.0),
            true,
            0.01,
        );
        assert_eq!(pv.target_depth(), 0.03);
        // Steering (a zero command: the dead-man held), 10 N out: (10 - 2) / 50 = 0.16 m/s,
        // cut to the rate bound (`axial_max_speed_m_s`).
        pv.step(PivotParams::new(&p, &lim), cmd(0.0, 0.0, 0.0, 0.0), &out, true, 0.01);
        assert!(
            (pv.target_depth() - (0.03 - p.fulcrum.axial_max_speed_m_s * 0.01)).abs() < 1e-12,
            "{}",
            pv.target_depth()
        );
        // Off without force feedback.
        let (_, mut off) = setup();
        off.step(PivotParams::new(&p, &lim), cmd(0.0, 0.0, 0.0, 0.0), &out, false, 0.01);
        assert_eq!(off.target_depth(), 0.03);
        // Past min_depth (30 mm), but never out of the port.
        for _ in 0..400 {
            pv.step(PivotParams::new(&p, &lim), cmd(0.0, 0.0, 0.0, 0.0), &out, true, 0.01);
        }
        assert_eq!(pv.target_depth(), 0.0);
        // Pulled in: up to max_depth, no further.
        for _ in 0..1000 {
            pv.step(PivotParams::new(&p, &lim), cmd(0.0, 0.0, 0.0, 0.0), &-out, true, 0.01);
        }
        assert_eq!(pv.target_depth(), p.max_depth_m);
    }

    #[test]
    fn pan_turns_the_shaft_about_the_fulcrum_and_zoom_moves_along_it() {
        let (p, mut pv) = setup();
        let f0 = pv.fulcrum();
        let lim = MotionLimits::default();
        let (mut angle, mut rate) = (0.0, 0.0);
        for k in 0..100 {
            let t = pv.step(
                PivotParams::new(&p, &lim),
                cmd(0.17, 0.0, 0.0, 0.0),
                &Vector3::zeros(),
                true,
                0.01,
            );
            // The target line passes through the fulcrum.
            assert!(t.axis.distance_to_axis(&f0) < 1e-12);
            assert!((t.cost.fulcrum - f0).norm() < 1e-12);
            // The rate builds up within the jerk and acceleration limits, up to the command.
            let now = pv.direction().angle(&-Vector3::z());
            let r = (now - angle) / 0.01;
            let jerk_bound = if k == 0 {
                lim.max_angular_jerk_rad_s3 * 0.01 * 0.01
            } else {
                0.17
            };
            assert!(
                r <= jerk_bound + 1e-9 && r - rate <= lim.max_angular_accel_rad_s2 * 0.01 + 1e-9,
                "step {k}: {r} rad/s"
            );
            (angle, rate) = (now, r);
        }
        assert!((rate - 0.17).abs() < 1e-9, "{rate} rad/s");
        // Released: the rate falls to 0 within the limits, in a few steps.
        for _ in 0..5 {
            pv.step(PivotParams::new(&p, &lim), Ok(None), &Vector3::zeros(), true, 0.01);
        }
        let d = pv.direction();
        let turned = d.angle(&-Vector3::z());
        assert!((turned - 0.17).abs() < 0.003, "{turned} rad for 1 s at 0.17 rad/s");
        pv.step(PivotParams::new(&p, &lim), Ok(None), &Vector3::zeros(), true, 0.01);
        assert!(
            pv.direction().angle(&d) < 1e-12,
            "still turning after 5 steps of release"
        );
        // The tip moved on a circle about the fulcrum.
        let tip = pv.port() + d.into_inner() * pv.target_depth();
        assert!(((tip - f0).norm() - (0.03 - p.fulcrum.prior_depth_m)).abs() < 1e-12);
        for _ in 0..101 {
            go(&mut pv, &p, cmd(0.0, 0.0, 0.3, 0.01));
        }
        // 10 mm in 1 s (the ramp's loss made up by the one more step).
        assert!((pv.target_depth() - 0.04).abs() < 2e-4, "{}", pv.target_depth());
        assert!(pv.direction().angle(&d) < 1e-12, "roll and zoom keep the direction");
    }

    #[test]
    fn each_limit_stops_the_command_at_it_and_says_so() {
        let (p, mut pv) = setup();
        let mut before = 0.0;
        for _ in 0..20 {
            before = pv.direction().angle(&-Vector3::z());
            go(&mut pv, &p, cmd(3.0, 0.0, 0.0, 0.0));
            assert_eq!(pv.limit, Some(ScopeLimit::Speed));
        }
        let step = pv.direction().angle(&-Vector3::z()) - before;
        assert!(
            (step - p.max_angular_speed_rad_s * 0.01).abs() < 1e-12,
            "{step} rad per step"
        );
        // Zoom out to the minimum depth and no further.
        for _ in 0..200 {
            go(&mut pv, &p, cmd(0.0, 0.0, 0.0, -0.02));
        }
        assert_eq!(pv.limit, Some(ScopeLimit::MinDepth));
        assert_eq!(pv.target_depth(), p.min_depth_m);
        for _ in 0..600 {
            go(&mut pv, &p, cmd(0.0, 0.0, 0.0, 0.02));
        }
        assert_eq!(pv.limit, Some(ScopeLimit::MaxDepth));
        assert_eq!(pv.target_depth(), p.max_depth_m);
        // Tilt into the cone's edge: stops within one step of it, roll still turns.
        for _ in 0..400 {
            go(&mut pv, &p, cmd(0.0, 0.3, 0.1, 0.0));
        }
        let r = pv.report(&p, &Isometry3::identity(), &Vector3::zeros());
        assert_eq!(r.limit, Some(ScopeLimit::Cone));
        let angle = pv.direction().angle(&-Vector3::z());
        let cone = p.cone_half_angle_deg.to_radians();
        assert!(angle <= cone && angle > cone - 0.003 - 1e-9, "{angle} vs {cone}");
        // Back out of the edge is allowed.
        go(&mut pv, &p, cmd(0.0, -0.3, 0.0, 0.0));
        assert_eq!(pv.limit, None);
        assert!(pv.direction().angle(&-Vector3::z()) < angle);
    }

    #[test]
    fn bad_or_old_commands_hold_still() {
        let (p, mut pv) = setup();
        let before = pv.clone();
        let nan = Stamped {
            stamp: 1.0,
            value: ScopeCommand {
                pan: f64::NAN,
                ..Default::default()
            },
        };
        let c = live_command(&p, 1.0, Some(nan));
        assert!(c.unwrap_err().contains("not finite"));
        go(&mut pv, &p, c);
        assert_eq!(pv.rot, before.rot);
        assert_eq!(pv.tip_depth, before.tip_depth);
        assert!(pv
            .report(&p, &Isometry3::identity(), &Vector3::zeros())
            .ignored
            .is_some());
        let inf_stamp = Stamped {
            stamp: f64::INFINITY,
            value: ScopeCommand::default(),
        };
        assert!(live_command(&p, 1.0, Some(inf_stamp)).is_err());
        let pan = ScopeCommand {
            pan: 0.1,
            ..Default::default()
        };
        let at = |stamp| Some(Stamped { stamp, value: pan });
        assert_eq!(live_command(&p, 1.0, at(0.85)), Ok(Some(pan)), "0.15 s old: live");
        assert_eq!(live_command(&p, 1.0, at(0.75)), Ok(None), "0.25 s old: dead-man");
        assert!(live_command(&p, 1.0, at(1.5)).is_err(), "from the future");
        assert_eq!(live_command(&p, 1.0, None), Ok(None));
    }

    #[test]
    fn a_step_allocates_nothing() {
        use crate::kinematics::lbr::{LbrModel, ToolParams};
        use crate::kinematics::{Kinematics, LbrKinematics};
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let (_, jac) = kin.fk_jacobian(&JointVector::repeat(0.4)).unwrap();
        let (p, mut pv) = setup();
        let c = Some(Stamped {
            stamp: 0.95,
            value: ScopeCommand {
                pan: 0.1,
                tilt: -0.05,
                roll: 0.1,
                zoom: 0.005,
            },
        });
        let before = crate::test_alloc::allocations_on_this_thread();
        for _ in 0..100 {
            let f = pv.sense(&jac, &JointVector::repeat(0.3), 0.02, 20.0, 0.01);
            let cmd = live_command(&p, 1.0, c);
            pv.step(PivotParams::new(&p, &MotionLimits::default()), cmd, &f, true, 0.01);
            let _ = pv.report(&p, &Isometry3::identity(), &f);
        }
        assert_eq!(crate::test_alloc::allocations_on_this_thread(), before);
    }

    #[test]
    fn retract_withdraws_to_the_end_and_ignores_commands() {
        let (p, mut pv) = setup();
        pv.retract_to(-0.02);
        let mut steps = 0;
        while !pv.retracted() {
            go(&mut pv, &p, cmd(0.3, 0.0, 0.0, 0.02));
            steps += 1;
            assert!(f64::from(steps) < 2.0 * 0.05 / p.retract_speed_m_s / 0.01);
        }
        assert_eq!(pv.target_depth(), -0.02);
        assert!((steps as f64 - 0.05 / p.retract_speed_m_s / 0.01).abs() <= 1.0);
        assert!(pv.direction().angle(&-Vector3::z()) < 1e-12);
    }

    #[test]
    fn a_stopped_law_stands_whatever_the_force_and_the_commands_until_reanchored() {
        let lim = MotionLimits::default();
        // Panning at full speed, then stopped with a force across the shaft and along it
        // that would move the fulcrum and the depth, and a breathing port.
        for retract in [false, true] {
            let (p, mut pv) = setup();
            if retract {
                pv.retract_to(-0.02);
            }
            let mut prev = None;
            for _ in 0..50 {
                prev = Some(go(&mut pv, &p, cmd(p.max_angular_speed_rad_s, 0.0, 0.0, 0.0)));
            }
            let prev = prev.unwrap();
            let v0 = pv.turn_rate.velocity().norm() + pv.zoom_rate.velocity().norm();
            let rate = if retract {
                p.retract_speed_m_s
            } else {
                p.max_angular_speed_rad_s
            };
            assert!(v0 > 0.5 * rate, "moving before the hold");
            pv.stop();
            assert!(pv.held() && pv.at_rest());
            let push = Vector3::new(8.0, 0.0, 9.0);
            // At rest: the targets stay, whatever the force and the commands.
            for _ in 0..200 {
                let t = pv.step(PivotParams::new(&p, &lim), cmd(0.3, 0.0, 0.0, 0.02), &push, true, 0.01);
                assert_eq!(
                    t.point, prev.point,
                    "retract {retract}: the tip's target moved while held"
                );
                assert_eq!(t.cost.fulcrum, prev.cost.fulcrum, "the fulcrum moved while held");
                assert_eq!(t.axis.direction, prev.axis.direction);
            }
            // Resumed at a tip 1 mm deeper along the shaft and turned 0.5 deg: the targets are
            // that tip, the port on its line; a withdrawal goes on.
            let d = pv.direction().into_inner();
            let turn = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.5f64.to_radians());
            let tip = Isometry3::from_parts((prev.point + d * 0.001).into(), turn * pv.rot);
            pv.reanchor(&tip);
            assert!(!pv.held());
            let t = go(&mut pv, &p, Ok(None));
            let e = Point3::from(tip.translation.vector);
            if retract {
                assert!(pv.retracting() && t.point != e, "the withdrawal goes on");
            } else {
                assert!((t.point - e).norm() < 1e-12, "re-anchored at the tip");
            }
            let shaft = tip.rotation * Vector3::z();
            assert!((t.axis.direction.into_inner() - shaft).norm() < 1e-12);
            let port = t.axis.port - e;
            assert!(
                (port - shaft * shaft.dot(&port)).norm() < 1e-12,
                "the port on the new shaft line"
            );
        }
    }
}
