//! A real robot's failure modes against the guarded controller, in closed loop with an ideal
//! plant (the measured joints are the last command) that can be blocked: the command never
//! leads the arm by more than `guard.max_command_lead_rad`; a blocked arm holds
//! (`ARM_NOT_FOLLOWING`) within 0.2 s of the lead reaching its bound, where the arm is; the
//! clock going back or jumping forward holds with its reason; an input restart
//! (`Controller::interrupt`) holds; every such hold is latched, brakes and walks to where it
//! stands within the guard's speed and acceleration limits (every command of every run
//! audited by [`CommandAudit`]), and the new start begins from the last published command.

use nalgebra::Isometry3;
use trocar_docking::control::safety::audit::CommandAudit;
use trocar_docking::control::safety::guard::LEAD_WATCH_FRACTION;
use trocar_docking::control::{ControlInput, ControlOutput, Controller, ControllerParams, HoldReason, Phase, Stamped};
use trocar_docking::kinematics::{JointVector, Kinematics, LbrKinematics};

mod common;
use common::{kin, q_start, trocar};

const DT: f64 = 0.01;

/// The controller, an ideal plant and a clock.
struct Rig {
    kin: LbrKinematics,
    trocar: Isometry3<f64>,
    c: Controller,
    q: JointVector,
    t: f64,
    blocked: bool,
    /// Every command of the run, against the guard's speed and acceleration limits.
    audit: CommandAudit,
}

impl Rig {
    fn new() -> Self {
        let kin = kin();
        let trocar = trocar(&kin);
        let p = ControllerParams::default();
        let audit = CommandAudit::new(&p.guard, kin.limits(), p.dt_s);
        let c = Controller::new(p, kin.limits().clone()).unwrap();
        Self {
            kin,
            trocar,
            c,
            q: q_start(),
            t: 0.0,
            blocked: false,
            audit,
        }
    }

    /// One step at `t` (the clock advanced by the caller, or by one period).
    fn step_at(&mut self, t: f64) -> ControlOutput {
        self.t = t;
        let s = |value| Some(Stamped { stamp: t, value });
        let input = ControlInput {
            scope: None,
            now: t,
            joints: s(self.q),
            tau_ext: s(JointVector::zeros()),
            torque_samples: Default::default(),
            trocar: Some(Stamped {
                stamp: t,
                value: self.trocar,
            }),
        };
        let out = self.c.step(&self.kin, &input);
        match out.command {
            Some(cmd) => self.audit.add(t, &cmd),
            None => self.audit.gap(),
        }
        if let (Some(cmd), false) = (out.command, self.blocked) {
            self.q = cmd;
        }
        out
    }

    /// Step while held with `code` until the command has stood still for 5 steps (at most 2 s):
    /// where it stands.
    fn settle(&mut self, code: &str) -> JointVector {
        let (mut last, mut still) = (None, 0);
        for _ in 0..200 {
            let out = self.step();
            assert_eq!((out.phase, out.reason_code()), (Phase::Hold, code), "{:?}", out.hold);
            let cmd = out.command.expect("a held command every step");
            still = if last == Some(cmd) { still + 1 } else { 0 };
            last = Some(cmd);
            if still == 5 {
                return cmd;
            }
        }
        panic!("{code}: the hold never stood still");
    }

    /// The audit's verdict: every command within the guard's limits.
    fn audited(&self) {
        if let Err(e) = self.audit.verdict() {
            panic!("{e}");
        }
    }

    fn step(&mut self) -> ControlOutput {
        self.step_at(self.t + DT)
    }

    /// Start and step until the arm moves (past the tare) for `moving_steps`.
    fn start_moving(&mut self, moving_steps: usize) {
        self.c.start().unwrap();
        let mut moving = 0;
        for _ in 0..200 {
            if self.step().phase.is_moving() {
                moving += 1;
                if moving == moving_steps {
                    return;
                }
            }
        }
        panic!("never moved (phase {:?})", self.c.phase());
    }
}

fn lead(cmd: &JointVector, q: &JointVector) -> f64 {
    (cmd - q).amax()
}

#[test]
fn a_blocked_arm_holds_without_winding_up_and_a_new_start_begins_where_it_is() {
    let mut r = Rig::new();
    let bound = r.c.params().guard.max_command_lead_rad;
    assert!((bound - 2f64.to_radians()).abs() < 1e-12, "2 deg by default");
    r.start_moving(20);
    r.blocked = true;
    let frozen = r.q;
    let (mut saturated_at, mut held_at, mut max_lead) = (None, None, 0.0f64);
    for _ in 0..300 {
        let out = r.step();
        let cmd = out.command.expect("a command every step");
        max_lead = max_lead.max(lead(&cmd, &frozen));
        if lead(&cmd, &frozen) >= LEAD_WATCH_FRACTION * bound && saturated_at.is_none() {
            saturated_at = Some(r.t);
        }
        if out.phase == Phase::Hold {
            assert_eq!(out.reason_code(), "ARM_NOT_FOLLOWING", "{:?}", out.hold);
            held_at = Some(r.t);
            break;
        }
    }
    // The hold brakes and walks the command back to where the arm is, within the limits
    // (a jump there stepped by the whole lead), and stands there.
    let stood = r.settle("ARM_NOT_FOLLOWING");
    assert!(lead(&stood, &frozen) < 1e-12, "held where the arm is, not ahead of it");
    assert!(
        max_lead <= bound + 1e-9,
        "the command led by {:.3} deg",
        max_lead.to_degrees()
    );
    let (s, h) = (
        saturated_at.expect("the lead reached its bound"),
        held_at.expect("a hold"),
    );
    assert!(
        h - s <= 0.2 + 1e-9,
        "held {:.3} s after the lead reached its bound",
        h - s
    );
    // The arm frees itself: nothing moves, the hold stays (latched), its reason too.
    r.blocked = false;
    for _ in 0..50 {
        let out = r.step();
        assert_eq!((out.phase, out.command), (Phase::Hold, Some(stood)));
        assert_eq!(out.reason_code(), "ARM_NOT_FOLLOWING");
    }
    // Moved by hand while held (2.5 deg on joint 2): the new start begins from there.
    r.blocked = true;
    r.q[1] += 2.5f64.to_radians();
    let moved = r.q;
    assert_eq!(r.step().command, Some(stood), "held");
    r.blocked = false;
    r.c.start().unwrap();
    // From the last published command (where the hold stood), within the limits.
    let mut prev = stood;
    for _ in 0..30 {
        let out = r.step();
        assert!(out.phase.is_moving(), "{:?}", out.hold);
        prev = out.command.unwrap();
    }
    assert!(lead(&prev, &moved) > 1e-4, "docking goes on after the start");
    r.audited();
}

#[test]
fn the_command_never_leads_a_lagging_arm_by_more_than_the_bound_in_any_phase() {
    // The arm follows at a fifth of the commanded speed: the command waits for it.
    let mut r = Rig::new();
    let bound = r.c.params().guard.max_command_lead_rad;
    r.c.start().unwrap();
    let mut phases = Vec::new();
    for _ in 0..600 {
        let q = r.q;
        r.blocked = true;
        let out = r.step();
        if let Some(cmd) = out.command {
            assert!(
                lead(&cmd, &q) <= bound + 1e-9,
                "{:?}: led by {:.3} deg",
                out.phase,
                lead(&cmd, &q).to_degrees()
            );
            r.q = q + (cmd - q) * 0.2;
        }
        phases.push(out.phase);
        if out.phase == Phase::Hold {
            break;
        }
    }
    assert!(phases.contains(&Phase::Approach), "it moved");
    r.audited();
}

fn jump_holds_until_a_new_start(jump: f64, code: &str) {
    let mut r = Rig::new();
    r.start_moving(30);
    let before = r.step().command.unwrap();
    let out = r.step_at(r.t + jump);
    assert_eq!(out.phase, Phase::Hold, "{code}: {:?}", out.hold);
    assert_eq!(out.reason_code(), code);
    assert!(out.reason_text().unwrap().contains("clock"), "{:?}", out.reason_text());
    // Braked to rest within the limits, near where it was (no walk elsewhere): the
    // distance a joint at the guard's speed limit brakes in, at most.
    let stood = r.settle(code);
    let p = r.c.params();
    let vmax = r.kin.limits().velocity.amax() * p.guard.velocity_scale;
    let braking = vmax * vmax / (2.0 * p.guard.max_acceleration_rad_s2) + vmax * DT;
    assert!(
        lead(&stood, &before) <= braking,
        "{code}: stood {} rad away",
        lead(&stood, &before)
    );
    // Time goes on from the new clock, every input fresh: still held, with the same reason.
    for _ in 0..100 {
        let out = r.step();
        assert_eq!((out.phase, out.command), (Phase::Hold, Some(stood)), "{code}");
        assert_eq!(out.reason_code(), code);
    }
    r.c.start().unwrap();
    let mut moved = r.step();
    for _ in 0..20 {
        moved = r.step();
    }
    assert!(moved.phase.is_moving(), "{code}: {:?}", moved.hold);
    assert!(
        lead(&moved.command.unwrap(), &stood) > 1e-4,
        "{code}: moves again after a start"
    );
    r.audited();
}

#[test]
fn the_clock_going_back_holds_with_a_reason_never_a_silent_freeze() {
    jump_holds_until_a_new_start(-5.0, "CLOCK_BACK");
}

#[test]
fn the_clock_jumping_forward_holds_with_a_reason() {
    jump_holds_until_a_new_start(5.0, "CLOCK_FORWARD");
    // A late step under the threshold (0.3 s) is no clock jump: the run goes on.
    let mut r = Rig::new();
    r.start_moving(10);
    let out = r.step_at(r.t + 0.3);
    assert!(out.phase.is_moving(), "{:?}", out.hold);
}

#[test]
fn an_input_restart_holds_until_a_new_start_in_every_phase() {
    let restart = HoldReason::DriverRestart {
        stamp_jump_s: -3.0,
        names_reordered: true,
    };
    // Moving: held, latched, walking from the last command to the newest measured joints
    // (where the restarted driver holds the arm) within the speed limits; fresh inputs do
    // not resume it.
    let mut r = Rig::new();
    r.start_moving(20);
    r.c.interrupt(restart.clone());
    let stood = r.settle("DRIVER_RESTART");
    for _ in 0..20 {
        let out = r.step();
        assert_eq!((out.phase, out.command), (Phase::Hold, Some(stood)), "standing still");
    }
    r.c.start().unwrap();
    assert!(r.step().phase.is_moving());
    r.audited();
    // Taring: back to IDLE with the reason, nothing commanded; a start tares again.
    let mut r = Rig::new();
    r.c.start().unwrap();
    assert_eq!(r.step().phase, Phase::Tare);
    r.c.interrupt(restart.clone());
    let out = r.step();
    assert_eq!((out.phase, out.command), (Phase::Idle, None));
    assert_eq!(out.reason_code(), "DRIVER_RESTART");
    r.c.start().unwrap();
    assert_eq!(r.step().phase, Phase::Tare);
    // Idle: nothing to hold.
    let mut r = Rig::new();
    r.c.interrupt(restart);
    let out = r.step();
    assert_eq!((out.phase, out.reason_code()), (Phase::Idle, ""));
}
